"""Test-wide settings: float64 (references are compared in double precision) and the persistent
compilation cache (each program with Jacobians through ``mjx.step`` costs seconds to compile)."""

import jax

jax.config.update("jax_enable_x64", True)

from diffgcl.runtime import prepare_process  # noqa: E402

prepare_process()
