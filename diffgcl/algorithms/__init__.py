"""Algorithms composed from the leaf modules: GPS, rGCL (v1, v2), behaviour cloning."""
