"""Behaviour cloning: the baseline every learned cost is compared with.

The same Gaussian policy and observations as MDGPS (:mod:`diffgcl.policies`), fitted directly to
the demonstrations' ``(o_t, u_t)`` pairs by least squares — the S-step's regression with unit
precision and the demos' validity mask as weights — and its variance set to the residual
variance per action dimension (the maximum-likelihood Gaussian). No cost, no dynamics, no
environment interaction: what a learned cost must beat from starts the demos never visited.

DAgger-style relabelling is left out: it needs an expert that can label the states the cloned
policy visits, and the demonstrators here (GPS's time-varying local controllers, or the recorded
boat crews) only know the states near their own trajectories.

:func:`make_bc` returns a pure ``fit(key, O, U, mask=None) -> (PolicyState, SStepMetrics)``;
``jax.jit(jax.vmap(fit, in_axes=(0, None, None, None)))`` fits several seeds at once.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import optax

from diffgcl.policies.mdgps import PolicyState, SStepConfig, make_policy_learner
from diffgcl.policies.network import GaussianPolicy, PolicyConfig, fit_obs_normaliser
from diffgcl.types import Array, PRNGKey


@dataclass(frozen=True)
class BCConfig:
    """network: the policy's shape (use the MDGPS run's to compare like with like); fit: the
    regression's Adam settings (``ent_reg`` and ``weight_clip`` unused); var_floor: lower bound
    of the fitted action variance."""

    network: PolicyConfig = field(default_factory=PolicyConfig)
    fit: SStepConfig = field(default_factory=lambda: SStepConfig(n_steps=3000, batch_size=128))
    var_floor: float = 1e-6


def make_bc(
    config: BCConfig, dO: int, dU: int, dtype=jnp.float32
) -> tuple[GaussianPolicy, Callable]:
    """``(policy, fit)`` for observations of size ``dO`` and actions of size ``dU``.

    ``fit(key, O, U, mask=None)``: O: [N, T+1, dO] or [N, T, dO] (the demos' observations; a last
    observation without an action is dropped), U: [N, T, dU], mask: [N, T+1] or [N, T] validity
    (default all valid). Returns (PolicyState, SStepMetrics).
    """
    policy = GaussianPolicy(config.network, dO, dU, param_dtype=dtype)
    # One fit: the step size decays to zero over it (cosine), so the result is the optimum rather
    # than a point of the minibatch noise around it.
    schedule = optax.cosine_decay_schedule(config.fit.learning_rate, max(config.fit.n_steps, 1))
    learner = make_policy_learner(policy, config.fit, learning_rate=schedule)

    def fit(key: PRNGKey, O: Array, U: Array, mask: Array | None = None):
        T = U.shape[1]
        O = O[:, :T]
        mask = jnp.ones(U.shape[:2], U.dtype) if mask is None else mask[:, :T].astype(U.dtype)
        O_flat = O.reshape(-1, dO)
        U_flat = U.reshape(-1, dU)
        w = mask.reshape(-1)
        net = config.network
        norm = fit_obs_normaliser(O_flat, net.obs_std_floor, w, rel_floor=net.obs_std_rel_floor)
        key_init, key_fit = jax.random.split(key)
        state: PolicyState = learner.init(policy.init(key_init, norm))
        prec = jnp.broadcast_to(jnp.eye(dU, dtype=U.dtype), (U_flat.shape[0], dU, dU))
        # Invalid steps: zero precision (no pull), so the weights need no renormalisation.
        state, metrics = learner.s_step(state, key_fit, O_flat, U_flat, prec * w[:, None, None])
        pred = jax.vmap(policy.mean_action, in_axes=(None, 0))(state.params, O_flat)
        resid = (U_flat - pred) ** 2
        var = (w[:, None] * resid).sum(0) / jnp.maximum(w.sum(), 1.0)
        params = state.params.replace(var=jnp.maximum(var, config.var_floor).astype(dtype))
        state = state.replace(params=params)
        return state, metrics.replace(entropy=policy.entropy(params))

    return policy, fit


def demo_arrays(demos, env=None):
    """Host-side: ``(O, U, mask)`` arrays of a :class:`~diffgcl.data.demos.DemoSet` for
    :func:`make_bc`; with ``env`` the observations are recomputed by ``env.obs`` from the states
    (the simulator's sensor model), else the recorded ``O`` are used."""
    U = jnp.asarray(demos.U)
    mask = jnp.asarray(demos.mask)
    if env is None:
        if demos.O.shape[-1] == 0:
            raise ValueError(
                "demos: no recorded observations (dO = 0); pass the env to compute them"
            )
        return jnp.asarray(demos.O, U.dtype), U, mask
    X = jnp.asarray(demos.X, U.dtype)
    O = jax.jit(jax.vmap(jax.vmap(env.obs)))(X)
    return O, U, mask


def clone_demos(demos, env, config: BCConfig, seeds) -> tuple[GaussianPolicy, object]:
    """Host-side: behaviour cloning of a :class:`~diffgcl.data.demos.DemoSet` for every seed
    (one vmapped fit); observations recomputed by ``env.obs`` from the demos' states so that the
    policy sees what the simulator's sensors give. Returns ``(policy, params [S, ...])``."""
    O, U, mask = demo_arrays(demos, env)
    dtype = jnp.asarray(env.initial_states()).dtype
    policy, fit = make_bc(config, env.dO, env.dU, dtype)
    keys = jnp.stack([jax.random.PRNGKey(int(s)) for s in seeds])
    state, _ = jax.jit(jax.vmap(lambda k: fit(k, O.astype(dtype), U.astype(dtype), mask)))(keys)
    return policy, state.params
