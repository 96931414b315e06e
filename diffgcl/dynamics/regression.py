"""Linear-Gaussian dynamics by regression on samples, for data without a model (GPS's fit).

Per time step t a joint Gaussian over ``z = [x_t, u_t, x_{t+1}]`` is estimated from the N samples
with a normal-inverse-Wishart prior, then conditioned on ``(x_t, u_t)``:
``x_{t+1} | x_t, u_t ~ N(F [x_t; u_t] + f, Σ_dyn)``. The prior is one Gaussian fitted to the
tuples of *all* time steps pooled (GPS's dynamics prior with a single mixture component): it makes
the per-step fit well posed when N < dX + dU, which is GPS's usual regime (5 samples).

With empirical mean ``μ̂``, empirical covariance ``S`` (divided by N), prior mean ``μ₀`` and
covariance ``Φ₀``, and prior strengths ``m`` (mean) and ``n₀`` (covariance) in pseudo-samples,
the posterior covariance estimate is
``Σ = (N·S + n₀·Φ₀ + N·m/(N+m)·(μ̂ − μ₀)(μ̂ − μ₀)ᵀ) / (N + n₀)``
(the MAP of the NIW posterior up to the degrees-of-freedom offset, as in GPS's
``gauss_fit_joint_prior``), with the empirical mean kept as the mean.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffgcl.types import Array, LinearDynamics


def condition_gaussian(
    mu: Array, sigma: Array, d_in: int, reg: float
) -> tuple[Array, Array, Array]:
    """Condition N(mu, sigma) over ``[a; b]`` (a of size d_in) on a.

    Returns F [db, da], f [db], cov [db, db] with ``b | a ~ N(F a + f, cov)``; ``reg·I`` is added
    to Σ_aa before solving.
    """
    s_aa = sigma[:d_in, :d_in] + reg * jnp.eye(d_in, dtype=sigma.dtype)
    s_ab = sigma[:d_in, d_in:]
    F = jnp.linalg.solve(s_aa, s_ab).T
    f = mu[d_in:] - F @ mu[:d_in]
    cov = sigma[d_in:, d_in:] - F @ s_aa @ F.T
    return F, f, 0.5 * (cov + cov.T)


def niw_posterior_covariance(
    points: Array, prior_mean: Array, prior_cov: Array, strength: float
) -> tuple[Array, Array]:
    """Mean and NIW-regularised covariance of ``points: [N, D]`` (see module docstring)."""
    n = points.shape[0]
    mean = points.mean(axis=0)
    diff = points - mean
    emp = diff.T @ diff / n
    d0 = mean - prior_mean
    m = n0 = strength
    sigma = (n * emp + n0 * prior_cov + (n * m / (n + m)) * jnp.outer(d0, d0)) / (n + n0)
    return mean, 0.5 * (sigma + sigma.T)


def fit_dynamics_regression(
    X: Array,
    U: Array,
    *,
    prior_strength: float = 1.0,
    reg: float = 1e-6,
    cov_floor: float = 1e-6,
) -> LinearDynamics:
    """GPS-style per-step regression with a pooled NIW prior, for one condition.

    X: [N, T+1, dX], U: [N, T, dU] -> LinearDynamics (A [T, dX, dX], B [T, dX, dU], c [T, dX],
    cov [T, dX, dX]). ``prior_strength`` is the prior's weight in pseudo-samples (0 = plain least
    squares, which needs N > dX + dU).
    """
    if X.ndim != 3 or U.ndim != 3 or U.shape[:2] != (X.shape[0], X.shape[1] - 1):
        raise ValueError(
            "fit_dynamics_regression: X must be [N, T+1, dX] and U [N, T, dU]; "
            f"got {X.shape}, {U.shape}"
        )
    dX, dU = X.shape[-1], U.shape[-1]
    points = jnp.concatenate([X[:, :-1], U, X[:, 1:]], axis=-1)  # [N, T, D]
    pooled = points.reshape(-1, points.shape[-1])
    prior_mean = pooled.mean(axis=0)
    centred = pooled - prior_mean
    prior_cov = centred.T @ centred / pooled.shape[0]

    def per_step(pts):
        mean, sigma = niw_posterior_covariance(pts, prior_mean, prior_cov, prior_strength)
        F, f, cov = condition_gaussian(mean, sigma, dX + dU, reg)
        return F[:, :dX], F[:, dX:], f, cov + cov_floor * jnp.eye(dX, dtype=X.dtype)

    A, B, c, cov = jax.vmap(per_step, in_axes=1)(points)
    return LinearDynamics(A=A, B=B, c=c, cov=cov)
