"""Trajectory optimisation: KL-constrained LQR (the GPS C-step), dual search, step adaptation."""
