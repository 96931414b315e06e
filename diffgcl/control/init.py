"""Initial controllers (GPS ``init_lqr`` in its simplest form): zero or given gains, ``Σ = v·I``."""

from __future__ import annotations

import jax.numpy as jnp

from diffgcl.types import Array, LinearGaussianController, make_controller


def init_controller(
    T: int,
    dX: int,
    dU: int,
    init_var: float | Array = 0.1,
    *,
    K: Array | None = None,
    k: Array | None = None,
    dtype=None,
) -> LinearGaussianController:
    """Controller ``u_t ~ N(K_t x + k_t, init_var·I)`` for t = 0 .. T-1.

    K: [dU, dX] or [T, dU, dX] (default zeros); k: [dU] or [T, dU] (default zeros; e.g. a
    constant action that holds the system); init_var: scalar or [dU] per-action variance.
    Returns fields K [T, dU, dX], k [T, dU], cov [T, dU, dU] (GPS box2d arm: init_var = 0.1).
    """
    dtype = dtype or jnp.zeros(()).dtype
    K = jnp.zeros((dU, dX), dtype) if K is None else jnp.asarray(K, dtype)
    k = jnp.zeros((dU,), dtype) if k is None else jnp.asarray(k, dtype)
    K = jnp.broadcast_to(K, (T, dU, dX))
    k = jnp.broadcast_to(k, (T, dU))
    var = jnp.broadcast_to(jnp.asarray(init_var, dtype), (dU,))
    cov = jnp.broadcast_to(jnp.diag(var), (T, dU, dU))
    return make_controller(K, k, cov)


def with_mean_variance(
    controller: LinearGaussianController, init_var: float | Array
) -> LinearGaussianController:
    """The same gains, the covariance rescaled so that the mean over time and actions of its
    diagonal is ``init_var`` (its shape kept): GPS's exploration budget ``init_var`` spent in
    the directions the given covariance leaves free. ``init_var`` may be traced."""
    cov = controller.cov
    mean_var = jnp.mean(jnp.diagonal(cov, axis1=-2, axis2=-1))
    return make_controller(
        controller.K, controller.k, cov * (jnp.asarray(init_var, cov.dtype) / mean_var)
    )
