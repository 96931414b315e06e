"""diffgcl: Guided Cost Learning with Guided Policy Search on differentiable MuJoCo (MJX)."""

from diffgcl.runtime import enable_compilation_cache

__all__ = ["enable_compilation_cache"]
__version__ = "0.1.0"
