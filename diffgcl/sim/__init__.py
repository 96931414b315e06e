"""Simulation: MJCF loading, MJX stepping, batched rollouts, sensors and hull forces."""
