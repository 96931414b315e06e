"""The seed's variant of the GCL sample set: trajectories drawn from the fitted linear-Gaussian
model instead of the stored real samples (design brief §5, "the seed's own variant").

``x_0 ~ N(μ_0, Σ_0)``, ``u_t = K_t x_t + k_t + chol(Σ_t) v_t``,
``x_{t+1} = A_t x_t + B_t u_t + c_t + chol(Σ_dyn,t) w_t`` with standard normal ``v, w``. The
proposal density is the full
``log p(τ) = log N(x_0) + Σ_t [log N(u_t | x_t) + log N(x_{t+1} | x_t, u_t)]``.
Only the current iteration's controller is used (no fusion), as in the seed. The demonstrations'
densities under the same model (:func:`model_log_density`) put them in the partition term.

Σ_dyn may be singular (a deterministic model): it gets a small jitter ``dyn_jitter · I`` for
sampling and density alike. The small Cholesky factorisations and triangular solves are the
unrolled ones of :mod:`diffgcl.linalg`, not LAPACK calls.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffgcl import linalg
from diffgcl.costs.buffer import action_log_density
from diffgcl.costs.gcl import WeightedSamples
from diffgcl.types import (
    Array,
    InitialStateDistribution,
    LinearDynamics,
    LinearGaussianController,
    PRNGKey,
)


def _gaussian_log_density(x: Array, mean: Array, chol: Array) -> Array:
    """``log N(x; mean, L Lᵀ)`` for ``x: [n]``, ``chol = L: [n, n]``."""
    white = linalg.solve_lower(chol, (x - mean)[:, None])[:, 0]
    log_det = 2.0 * jnp.log(jnp.diagonal(chol)).sum()
    return -0.5 * (white @ white + log_det + x.shape[-1] * jnp.log(2.0 * jnp.pi))


def _chol(cov: Array, jitter: float) -> Array:
    """Lower Cholesky factor of ``cov + jitter·I`` (symmetrised), ``cov: [n, n]``."""
    eye = jnp.eye(cov.shape[-1], dtype=cov.dtype)
    return linalg.cholesky(linalg.symmetrise(cov) + jitter * eye)


def model_log_density(
    dynamics: LinearDynamics,
    controller: LinearGaussianController,
    x0: InitialStateDistribution,
    X: Array,
    U: Array,
    dyn_jitter: float = 1e-6,
) -> Array:
    """Full ``log p(τ)`` of one trajectory ``X: [T+1, dX]``, ``U: [T, dU]`` under the model."""
    log_p0 = _gaussian_log_density(X[0], x0.mean, _chol(x0.cov, dyn_jitter))
    mean_next = (
        jnp.einsum("tij,tj->ti", dynamics.A, X[:-1])
        + jnp.einsum("tij,tj->ti", dynamics.B, U)
        + dynamics.c
    )
    chol_dyn = jax.vmap(_chol, in_axes=(0, None))(dynamics.cov, dyn_jitter)
    log_dyn = jax.vmap(_gaussian_log_density)(X[1:], mean_next, chol_dyn).sum()
    return log_p0 + action_log_density(controller, X, U) + log_dyn


def sample_from_model(
    key: PRNGKey,
    dynamics: LinearDynamics,
    controller: LinearGaussianController,
    x0: InitialStateDistribution,
    dyn_jitter: float = 1e-6,
) -> tuple[Array, Array, Array]:
    """One trajectory from the model: ``(X: [T+1, dX], U: [T, dU], log_p: scalar)``."""
    T, dU, dX = controller.K.shape
    key_x0, key_u, key_w = jax.random.split(key, 3)
    x_init = x0.mean + _chol(x0.cov, dyn_jitter) @ jax.random.normal(key_x0, (dX,), x0.mean.dtype)
    v = jax.random.normal(key_u, (T, dU), x0.mean.dtype)
    w = jax.random.normal(key_w, (T, dX), x0.mean.dtype)
    chol_dyn = jax.vmap(_chol, in_axes=(0, None))(dynamics.cov, dyn_jitter)

    def step(x, inputs):
        A, B, c, L_dyn, K, k, L_u, v_t, w_t = inputs
        u = K @ x + k + L_u @ v_t
        x_next = A @ x + B @ u + c + L_dyn @ w_t
        return x_next, (x, u)

    xs = (
        dynamics.A,
        dynamics.B,
        dynamics.c,
        chol_dyn,
        controller.K,
        controller.k,
        controller.chol_cov,
        v,
        w,
    )
    x_T, (X, U) = jax.lax.scan(step, x_init, xs)
    X = jnp.concatenate([X, x_T[None]])
    return X, U, model_log_density(dynamics, controller, x0, X, U, dyn_jitter)


def model_weighted_samples(
    key: PRNGKey,
    dynamics: LinearDynamics,
    controller: LinearGaussianController,
    x0: InitialStateDistribution,
    demo_X: Array,
    demo_U: Array,
    n_samples: int,
    dyn_jitter: float = 1e-6,
) -> tuple[WeightedSamples, WeightedSamples]:
    """The seed's GCL sample set for one condition: ``n_samples`` model rollouts and the demos
    (``demo_X: [N, T+1, dX]``, ``demo_U: [N, T, dU]``), each with its full model ``log p(τ)``.
    Returns ``(samples: [n_samples], demos: [N])`` for :class:`diffgcl.costs.gcl.CostLearner`."""
    keys = jax.random.split(key, n_samples)
    X, U, log_p = jax.vmap(sample_from_model, in_axes=(0, None, None, None, None))(
        keys, dynamics, controller, x0, dyn_jitter
    )
    log_p_demo = jax.vmap(model_log_density, in_axes=(None, None, None, 0, 0, None))(
        dynamics, controller, x0, demo_X, demo_U, dyn_jitter
    )
    samples = WeightedSamples(X=X, U=U, log_q=log_p, valid=jnp.ones(n_samples, bool))
    demos = WeightedSamples(
        X=demo_X, U=demo_U, log_q=log_p_demo, valid=jnp.ones(demo_X.shape[0], bool)
    )
    return samples, demos
