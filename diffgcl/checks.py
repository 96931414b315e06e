"""Input checks at public entry points: clear errors instead of stack traces from inside JAX.

Shapes are static under ``jit`` and ``vmap``, so these checks cost nothing at run time.
"""

from __future__ import annotations

import jax.numpy as jnp


def check_shape(where: str, name: str, value, shape: tuple[int, ...]) -> None:
    """Raise ``ValueError("where: name must have shape (..), got (..)")`` on a mismatch."""
    got = tuple(jnp.shape(value))
    if got != tuple(shape):
        raise ValueError(f"{where}: {name} must have shape {tuple(shape)}, got {got}")
