"""diffgcl: Guided Cost Learning with Guided Policy Search on differentiable MuJoCo (MJX)."""

from diffgcl.runtime import CRASH_WORKAROUND_FLAGS, add_xla_flags, enable_compilation_cache

# Before JAX's first computation: XLA:CPU's YNNPACK fusions crash some of the simulator's programs
# (diffgcl.runtime). Once JAX has started this does nothing; entry points import diffgcl first.
add_xla_flags(CRASH_WORKAROUND_FLAGS)

__all__ = ["enable_compilation_cache"]
__version__ = "0.1.0"
