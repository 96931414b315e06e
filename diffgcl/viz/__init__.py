"""Plots and animations (matplotlib, Agg backend)."""
