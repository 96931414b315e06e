"""Rollouts of linear-Gaussian controllers and arbitrary policies through an env's ``step``.

Each function rolls out **one** trajectory from one initial state with ``lax.scan`` over time;
:func:`sample_controller` vmaps over samples, and callers vmap over conditions and seeds. The
exploration noise is drawn up front, so a rollout is a deterministic function of (x0, noise):
that is what makes batched and unbatched runs comparable and lets the caller reuse noise.

GPS's exploration noise (``generate_noise`` in the GPS code base): i.i.d. standard normal per
step and action dimension, optionally smoothed along time with a Gaussian filter of width
``sigma`` steps and renormalised to unit empirical variance per dimension.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import lax

from diffgcl.checks import check_shape
from diffgcl.types import Array, Env, LinearGaussianController, PolicyFn, PRNGKey, Trajectory


def gaussian_kernel(sigma: float, truncate: float = 4.0) -> Array:
    """Normalised 1-D Gaussian filter taps (as scipy.ndimage: radius = truncate·sigma)."""
    radius = int(truncate * float(sigma) + 0.5)
    offsets = jnp.arange(-radius, radius + 1)
    taps = jnp.exp(-0.5 * (offsets / sigma) ** 2)
    return taps / taps.sum()


def smooth_noise(key: PRNGKey, T: int, dU: int, sigma: float | None = None) -> Array:
    """Exploration noise [T, dU]: standard normal, optionally time-smoothed and renormalised.

    With ``sigma`` the noise of each action dimension is filtered by a Gaussian of ``sigma`` steps
    (edges reflected, like scipy's default) and divided by its empirical standard deviation.
    """
    dtype = jnp.zeros(()).dtype
    noise = jax.random.normal(key, (T, dU), dtype)
    if not sigma:
        return noise
    taps = gaussian_kernel(sigma).astype(dtype)
    radius = (taps.shape[0] - 1) // 2
    padded = jnp.pad(noise, ((radius, radius), (0, 0)), mode="symmetric")
    smoothed = jax.vmap(lambda col: jnp.convolve(col, taps, mode="valid"), 1, 1)(padded)
    return smoothed / jnp.std(smoothed, axis=0, keepdims=True)


def rollout_controller(
    env: Env,
    controller: LinearGaussianController,
    x0: Array,
    noise: Array,
    *,
    with_obs: bool = False,
) -> Trajectory:
    """Roll out ``u_t = K_t x_t + k_t + chol(Σ_t) ε_t`` from ``x0: [dX]``, ``noise ε: [T, dU]``."""
    T = controller.horizon
    check_shape("rollout_controller", "x0", x0, (env.dX,))
    check_shape("rollout_controller", "noise", noise, (T, env.dU))

    def body(x, inputs):
        K, k, chol, eps = inputs
        u = K @ x + k + chol @ eps
        return env.step(x, u), (x, u)

    x_final, (X, U) = lax.scan(body, x0, (controller.K, controller.k, controller.chol_cov, noise))
    X = jnp.concatenate([X, x_final[None]], axis=0)
    O = jax.vmap(env.obs)(X) if with_obs else jnp.zeros((T + 1, 0), X.dtype)
    return Trajectory(X=X, U=U, O=O)


def sample_controller(
    env: Env,
    controller: LinearGaussianController,
    x0: Array,
    key: PRNGKey,
    n_samples: int,
    *,
    smooth_sigma: float | None = None,
    with_obs: bool = False,
) -> Trajectory:
    """``n_samples`` rollouts of one controller from one ``x0``: X [N, T+1, dX], U [N, T, dU]."""
    noise = jax.vmap(lambda k: smooth_noise(k, controller.horizon, env.dU, smooth_sigma))(
        jax.random.split(key, n_samples)
    )
    return jax.vmap(lambda eps: rollout_controller(env, controller, x0, eps, with_obs=with_obs))(
        noise
    )


def rollout_policy(
    env: Env,
    policy: PolicyFn,
    x0: Array,
    key: PRNGKey,
    horizon: int,
    *,
    obs_noise: bool = False,
) -> Trajectory:
    """Roll out ``u_t = policy(x_t, o_t, t, key_t)`` (o from ``env.obs``) from ``x0: [dX]``.

    With ``obs_noise`` the policy sees noisy sensors (``env.obs(x, key)``); the trajectory's ``O``
    records what it saw, with the final observation noise-free.
    """
    check_shape("rollout_policy", "x0", x0, (env.dX,))
    keys = jax.random.split(key, horizon)

    def body(x, inputs):
        t, k = inputs
        key_obs, key_act = jax.random.split(k)
        o = env.obs(x, key_obs) if obs_noise else env.obs(x)
        u = policy(x, o, t, key_act)
        return env.step(x, u), (x, u, o)

    x_final, (X, U, O) = lax.scan(body, x0, (jnp.arange(horizon), keys))
    X = jnp.concatenate([X, x_final[None]], axis=0)
    O = jnp.concatenate([O, env.obs(x_final)[None]], axis=0)
    return Trajectory(X=X, U=U, O=O)


def rollout_observed(
    env: Env,
    act: Callable[[Array, Array], Array],
    x0: Array,
    noise: Array,
    *,
    obs_key: PRNGKey | None = None,
) -> Trajectory:
    """Roll out ``u_t = act(o_t, ε_t)`` on observations ``o_t = env.obs(x_t)`` from ``x0: [dX]``
    with pre-drawn noise ``ε: [T, dU]`` (a global policy acting on what it senses).

    With ``obs_key`` the sensors are noisy (``env.obs(x, key_t)``); the trajectory's ``O`` records
    what the policy saw, the final observation noise-free.
    """
    T = noise.shape[0]
    check_shape("rollout_observed", "x0", x0, (env.dX,))
    check_shape("rollout_observed", "noise", noise, (T, env.dU))
    keys = None if obs_key is None else jax.random.split(obs_key, T)

    def body(x, inputs):
        eps, k = inputs
        o = env.obs(x) if k is None else env.obs(x, k)
        u = act(o, eps)
        return env.step(x, u), (x, u, o)

    x_final, (X, U, O) = lax.scan(body, x0, (noise, keys))
    X = jnp.concatenate([X, x_final[None]], axis=0)
    O = jnp.concatenate([O, env.obs(x_final)[None]], axis=0)
    return Trajectory(X=X, U=U, O=O)


def sample_observed(
    env: Env,
    act: Callable[[Array, Array], Array],
    x0: Array,
    key: PRNGKey,
    n_samples: int,
    horizon: int,
    *,
    smooth_sigma: float | None = None,
    obs_noise: bool = False,
) -> Trajectory:
    """``n_samples`` rollouts of :func:`rollout_observed` from one ``x0`` with GPS's (optionally
    time-smoothed) exploration noise: X [N, T+1, dX], U [N, T, dU], O [N, T+1, dO]."""
    key_noise, key_obs = jax.random.split(key)
    noise = jax.vmap(lambda k: smooth_noise(k, horizon, env.dU, smooth_sigma))(
        jax.random.split(key_noise, n_samples)
    )
    obs_keys = jax.random.split(key_obs, n_samples)

    def one(eps, k):
        return rollout_observed(env, act, x0, eps, obs_key=k if obs_noise else None)

    return jax.vmap(one)(noise, obs_keys)
