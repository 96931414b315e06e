"""Costs: analytic expert costs, the flax cost network, quadratic expansions, the GCL objective."""
