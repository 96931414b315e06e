"""The demonstrations' own linear-Gaussian controller, one of the components of GCL's fusion
mixture (Finn et al. 2016a, §4.2: the demos are appended to the samples in the partition term, so
they need a density under the same proposal).

Per time step t, a ridge regression of ``u_t`` on ``[x_t, 1]`` across the ``N`` demonstrations
(the state is centred first so the ridge penalty does not shrink the offset), and the residual
covariance plus a floor ``cov_floor · I``. With fewer demos than state dimensions the ridge term
keeps the fit defined; the covariance floor keeps the density finite when demos agree exactly.

The residual covariance is divided by the residual degrees of freedom ``N − p``, not by ``N``:
``p = 1 + tr((XᵀX + λI)⁻¹ XᵀX)`` is the trace of the ridge fit's hat matrix (the offset plus the
state directions the demos actually span — at t = 0 the demos share their start, and the gains
cost no degrees of freedom). The maximum-likelihood ``÷N`` shrank the covariance by ``(N − p)/N``
(0.5 for the arm's 10 demos and ``p = 5``), which made the demos' own density, evaluated on the
same demos in GCL's partition term, tens of nats too high, and the demos' controller look more
precise than the demonstrator.
The fit uses LAPACK (``solve``, and ``make_controller``'s Cholesky): the demos do not change
during training, so fit once, outside wide vmapped programs (see :mod:`diffgcl.costs.buffer`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffgcl.types import Array, LinearGaussianController, make_controller


def _fit_step(x: Array, u: Array, ridge: float, cov_floor: float) -> tuple[Array, Array, Array]:
    """One time step: x: [N, dX], u: [N, dU] -> K: [dU, dX], k: [dU], cov: [dU, dU]."""
    N, dX = x.shape
    x_mean, u_mean = x.mean(0), u.mean(0)
    xc, uc = x - x_mean, u - u_mean
    eye = jnp.eye(dX, dtype=x.dtype)
    gram = xc.T @ xc + ridge * eye
    K = jnp.linalg.solve(gram, xc.T @ uc).T
    k = u_mean - K @ x_mean
    resid = uc - xc @ K.T
    # Degrees of freedom the fit used: tr((XᵀX + λI)⁻¹XᵀX) = dX − λ tr((XᵀX + λI)⁻¹), plus 1.
    used = 1.0 + dX - ridge * jnp.trace(jnp.linalg.solve(gram, eye))
    dof = jnp.maximum(N - used, 1.0)
    cov = resid.T @ resid / dof + cov_floor * jnp.eye(u.shape[1], dtype=u.dtype)
    return K, k, cov


def fit_demo_controller(
    X: Array, U: Array, ridge: float = 1e-3, cov_floor: float = 1e-4
) -> LinearGaussianController:
    """Fit ``u_t ~ N(K_t x_t + k_t, Σ_t)`` to demos ``X: [N, T+1, dX]``, ``U: [N, T, dU]``.

    ridge: L2 penalty on ``K_t`` (in squared state units times N); cov_floor: added to ``Σ_t``.
    """
    K, k, cov = jax.vmap(_fit_step, in_axes=(1, 1, None, None))(X[:, :-1], U, ridge, cov_floor)
    return make_controller(K, k, cov)
