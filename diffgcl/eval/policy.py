"""Evaluating a global policy from any start states: batched rollouts and the env's own success
test (DESIGN §8: held-out starts are the point of a policy).

:func:`policy_rollouts` rolls a :class:`~diffgcl.policies.network.GaussianPolicy` out from a batch
of starts ``x0: [B, dX]`` — noise-free (its mean action) or with its own noise, on exact or noisy
sensors — as one vmapped ``lax.scan``; :func:`policy_success` applies ``env.success`` to them.
Pure; jit at the call site (or use :func:`evaluate_policy`, which does).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.policies.network import GaussianPolicy, PolicyParams
from diffgcl.sim.rollout import rollout_observed, smooth_noise
from diffgcl.types import Array, Env, PRNGKey, Trajectory


def policy_rollouts(
    env: Env,
    policy: GaussianPolicy,
    params: PolicyParams,
    x0: Array,
    key: PRNGKey | None = None,
    *,
    noisy: bool = False,
    obs_noise: bool = False,
    smooth_sigma: float | None = None,
    horizon: int | None = None,
) -> Trajectory:
    """Rollouts [B] from ``x0: [B, dX]`` of ``u_t = μ_θ(o_t) (+ sqrt(var)·ε_t when noisy)``.

    ``key`` is needed for ``noisy`` (action noise, optionally time-smoothed by ``smooth_sigma``
    steps as GPS's exploration noise) and ``obs_noise`` (the env's sensor noise)."""
    T = env.horizon if horizon is None else horizon
    B = x0.shape[0]
    if (noisy or obs_noise) and key is None:
        raise ValueError("policy_rollouts: noisy actions or sensors need a key")
    key = jax.random.PRNGKey(0) if key is None else key
    key_act, _ = jax.random.split(key)
    if noisy:
        noise = jax.vmap(lambda k: smooth_noise(k, T, env.dU, smooth_sigma))(
            jax.random.split(key_act, B)
        )
    else:
        noise = jnp.zeros((B, T, env.dU), x0.dtype)

    def act(o, eps):
        return policy.sample_action(params, o, eps)

    def one(x, eps, k):
        return rollout_observed(env, act, x, eps, obs_key=k if obs_noise else None)

    return jax.vmap(one)(x0, noise, rollout_sensor_keys(key, B))


def rollout_sensor_keys(key: PRNGKey, n: int) -> Array:
    """[n, 2]: the sensor-noise keys of :func:`policy_rollouts`' ``n`` rollouts from ``key``
    (the staged rollouts draw theirs the same way)."""
    _, key_obs = jax.random.split(key)
    return jax.random.split(key_obs, n)


def policy_success(env: Env, trajectories: Trajectory) -> Array:
    """``env.success`` of each rollout: [B] bool."""
    return jax.vmap(env.success)(trajectories.X)


@functools.partial(jax.jit, static_argnames=("env", "policy", "noisy", "obs_noise", "smooth_sigma"))
def _rollouts_and_success(env, policy, params, x0, key, *, noisy, obs_noise, smooth_sigma):
    """One compiled program per env, policy, flags and batch shape: the starts, the key and the
    parameters are arguments, so evaluating another seed or start set reuses it."""
    traj = policy_rollouts(
        env, policy, params, x0, key, noisy=noisy, obs_noise=obs_noise, smooth_sigma=smooth_sigma
    )
    return traj.X, policy_success(env, traj)


def evaluate_policy(
    env: Env,
    policy: GaussianPolicy,
    params: PolicyParams,
    x0,
    key: PRNGKey,
    *,
    noisy_samples: int = 0,
    obs_noise: bool = False,
    smooth_sigma: float | None = None,
) -> dict:
    """Host-side summary on starts ``x0: [B, dX]``: the noise-free rollouts' success per start
    and, with ``noisy_samples`` > 0, the success rate of that many noisy rollouts per start.
    Returns a dict of NumPy values (``success: [B]``, ``success_rate``, and
    ``sample_success_rate`` / ``sample_success: [B]`` when sampled) plus ``X: [B, T+1, dX]``.
    Compiled once per env, policy and batch shape, not per call."""
    x0 = jnp.asarray(x0)
    X, success = _rollouts_and_success(
        env, policy, params, x0, key, noisy=False, obs_noise=obs_noise, smooth_sigma=None
    )
    success = np.asarray(success)
    out = {"success": success, "success_rate": float(success.mean()), "X": np.asarray(X)}
    if noisy_samples > 0:
        reps = jnp.repeat(x0, noisy_samples, axis=0)
        _, sampled = _rollouts_and_success(
            env,
            policy,
            params,
            reps,
            key,
            noisy=True,
            obs_noise=obs_noise,
            smooth_sigma=smooth_sigma,
        )
        s = np.asarray(sampled).reshape(x0.shape[0], noisy_samples)
        out["sample_success"] = s.mean(axis=1)
        out["sample_success_rate"] = float(s.mean())
    return out
