"""Test-wide settings: float64 (references are compared in double precision), the persistent
compilation cache (each program with Jacobians through ``mjx.step`` costs seconds to compile) and
XLA's quick-compile level (the tests' programs run for well under a second; the variable reaches
every process a test starts: ``diffgcl.runtime.QUICK_COMPILE_ENV``)."""

import os

import jax

jax.config.update("jax_enable_x64", True)

from diffgcl.runtime import QUICK_COMPILE_ENV, prepare_process  # noqa: E402

os.environ.setdefault(QUICK_COMPILE_ENV, "1")
prepare_process()


import pytest  # noqa: E402


def pytest_collection_modifyitems(config, items):
    """Tests marked ``long`` run first: started last, a test of minutes would leave the other
    worker idle at the end of ``pytest -n 2``."""
    items.sort(key=lambda item: item.get_closest_marker("long") is None)


@pytest.fixture(scope="session")
def slider():
    """The tiny slider task and its expert demos (``tiny_tasks.slider_task``), made once."""
    from tiny_tasks import slider_task

    return slider_task()
