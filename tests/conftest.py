"""Test-wide settings: float64 (references are compared in double precision) and the persistent
compilation cache (each program with Jacobians through ``mjx.step`` costs seconds to compile)."""

import jax

jax.config.update("jax_enable_x64", True)

from diffgcl.runtime import prepare_process  # noqa: E402

prepare_process()


import pytest  # noqa: E402


@pytest.fixture(scope="session")
def slider():
    """The tiny slider task and its expert demos (``tiny_tasks.slider_task``), made once."""
    from tiny_tasks import slider_task

    return slider_task()
