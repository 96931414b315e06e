"""Mirror-descent Guided Policy Search with a known cost (MDGPS; Montgomery & Levine 2016, GPS's
``AlgorithmMDGPS``), and the policy phases rGCL shares with it.

One iteration, for every condition at once:

1. sample N trajectories per condition — from the local controllers (off-policy, GPS's default) or
   from the global policy itself (``sample_on_policy``) — and fit linear-Gaussian dynamics;
2. record what the policy would observe at the sample states (``env.obs``, with sensor noise
   when ``obs_noise``);
3. linearise the global policy around the samples by autodiff of ``μ_θ(o(x))``
   (:func:`diffgcl.policies.mdgps.linearise_policy`);
4. expand the cost, adapt the step size — *one* step for all conditions, from the Laplace cost of
   the previous policy linearisation, of the controllers the last C-step predicted, and of the
   current policy linearisation (GPS's MDGPS ``_stepadjust``);
5. C-step: the KL-constrained LQR of each condition with the policy linearisation as its KL anchor;
6. S-step: regress the policy onto the new controllers at the sample states, weighted by their
   precision (:mod:`diffgcl.policies.mdgps`).

:func:`make_policy_phases` builds steps 1–3, 6 and the policy evaluation for an env; the rGCL
schedules (:mod:`diffgcl.algorithms.rgcl`) compose them with the cost updates the same way this
module composes them with a fixed cost. :func:`make_mdgps` returns pure ``init``, ``iteration``
and ``train(key, hparams=None)``; ``jax.jit(jax.vmap(train))`` runs a seed sweep.

The policy's observation normaliser is fitted once, when the state is created: from given
observations (e.g. the demonstrations') or else from the initial controllers' samples, as GPS
fits it on its first S-step batch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct
from jax import lax

from diffgcl.algorithms.gps import (
    GPSConfig,
    GPSHyperparams,
    GPSMetrics,
    GPSSamples,
    GPSState,
    make_gps_phases,
)
from diffgcl.costs.expansion import trajectory_cost
from diffgcl.policies.mdgps import (
    PolicyState,
    SStepConfig,
    SStepMetrics,
    controller_targets,
    linearise_policy,
    make_policy_learner,
)
from diffgcl.policies.network import GaussianPolicy, PolicyConfig, fit_obs_normaliser
from diffgcl.sim.rollout import sample_controller, sample_observed
from diffgcl.types import Array, CostFn, Env, LinearGaussianController, PRNGKey, Trajectory


@dataclass(frozen=True)
class PolicySettings:
    """The global policy's static settings (shared by MDGPS and rGCL).

    network: :class:`~diffgcl.policies.network.PolicyConfig`; s_step:
    :class:`~diffgcl.policies.mdgps.SStepConfig`; sample_on_policy: draw the GPS samples from the
    global policy instead of the local controllers (GPS's ``sample_on_policy``); obs_noise: the
    policy sees noisy sensors in the samples and the S-step (noise-free in its linearisation and
    evaluation); outlier_cost_ratio: a condition whose samples cost more than this multiple of
    the median condition's is left out of the S-step (:func:`condition_weights`; None: none is).
    """

    network: PolicyConfig = field(default_factory=PolicyConfig)
    s_step: SStepConfig = field(default_factory=SStepConfig)
    sample_on_policy: bool = False
    obs_noise: bool = False
    outlier_cost_ratio: float | None = None


@struct.dataclass
class PolicyMetrics:
    """Per iteration: success / cost: [C] success and true cost of the policy's noise-free
    rollout from each training condition; s_step: :class:`SStepMetrics`."""

    success: Array
    cost: Array
    s_step: SStepMetrics


class PolicyPhases(NamedTuple):
    """The policy's part of an iteration on an env (pure; C conditions at once).

    init(key, O=None) -> PolicyState (normaliser from observations ``O: [..., dO]``, else from
    the initial controllers' samples); sample(state, key) -> (X [C, N, T+1, dX], U [C, N, T, dU])
    with the policy's noise; observe(X, key) -> O [C, N, T+1, dO]; linearise(state, X) ->
    LinearGaussianController [C]; s_step(state, key, X, O, controllers) -> (PolicyState,
    SStepMetrics); rollouts(state, x0) -> Trajectory [B] noise-free from starts ``x0: [B, dX]``;
    metrics(state, s_step_metrics) -> PolicyMetrics on the training conditions; policy: the
    :class:`GaussianPolicy`.
    """

    init: Callable[..., PolicyState]
    sample: Callable[[PolicyState, PRNGKey], tuple[Array, Array]]
    observe: Callable[[Array, PRNGKey], Array]
    linearise: Callable[[PolicyState, Array], LinearGaussianController]
    s_step: Callable[..., tuple[PolicyState, SStepMetrics]]
    rollouts: Callable[[PolicyState, Array], Trajectory]
    metrics: Callable[[PolicyState, SStepMetrics], PolicyMetrics]
    policy: GaussianPolicy


def make_policy(settings: PolicySettings, env: Env) -> GaussianPolicy:
    """The Gaussian policy of ``settings`` on ``env``'s observations (the run's float dtype)."""
    if env.dO < 1:
        raise ValueError(f"env {env.name!r} has no observations (dO = 0) for a global policy")
    dtype = jnp.asarray(env.initial_states()).dtype
    return GaussianPolicy(settings.network, env.dO, env.dU, param_dtype=dtype)


def condition_weights(cost: Array | None, ratio: float | None, C: int, dtype) -> Array:
    """Each condition's weight in the S-step, [C]: 0 where its samples' mean cost ``cost: [C]``
    is more than ``ratio`` × the median condition's, else 1 (all ones without a cost or ratio).

    A condition whose samples diverged (true cost 10⁶ and more where the others have 10³) gives
    the S-step targets far outside every other condition's states; regressed on them, the
    policy is pulled away everywhere, and since each controller's C-step is held within a KL
    step of the policy's linearisation, the divergence spreads to every condition (docs/usv.md).
    """
    if cost is None or ratio is None:
        return jnp.ones((C,), dtype)
    median = jnp.median(cost)
    keep = (cost <= ratio * median) | ~(median > 0)
    return keep.astype(dtype)


def make_policy_phases(
    settings: PolicySettings,
    gps_config: GPSConfig,
    env: Env,
    *,
    true_cost: CostFn | None = None,
    x0: Array | None = None,
) -> PolicyPhases:
    """The policy phases of ``env`` (see :class:`PolicyPhases`); ``gps_config`` gives the number
    of samples, the noise smoothing and the initial controllers' variance; ``true_cost`` (default
    ``env.expert_cost``) is reported for the policy's rollouts; ``x0``: training conditions [C, dX]
    (default ``env.initial_states()``)."""
    from diffgcl.control.init import init_controller
    from diffgcl.eval.policy import policy_rollouts

    policy = make_policy(settings, env)
    learner = make_policy_learner(policy, settings.s_step)
    true_cost = env.expert_cost if true_cost is None else true_cost
    X0 = jnp.asarray(env.initial_states() if x0 is None else x0)
    C, T, dU = X0.shape[0], env.horizon, env.dU
    N = gps_config.num_samples
    smooth = gps_config.smooth_sigma

    def observe_one(x, key):
        return env.obs(x, key) if settings.obs_noise else env.obs(x)

    def observe(X: Array, key: PRNGKey) -> Array:
        keys = jax.random.split(key, X.shape[:-1]).reshape(*X.shape[:-1], -1)
        flat = jax.vmap(observe_one)(X.reshape(-1, X.shape[-1]), keys.reshape(-1, keys.shape[-1]))
        return flat.reshape(*X.shape[:-1], -1)

    def init(key: PRNGKey, O: Array | None = None) -> PolicyState:
        key_net, key_samples, key_obs = jax.random.split(key, 3)
        if O is None:
            ctrl = init_controller(T, env.dX, dU, gps_config.init_var, dtype=X0.dtype)
            sample = lambda x0, k: sample_controller(env, ctrl, x0, k, N, smooth_sigma=smooth).X
            X = jax.vmap(sample)(X0, jax.random.split(key_samples, C))
            O = observe(X, key_obs)
        net = settings.network
        norm = fit_obs_normaliser(O, net.obs_std_floor, rel_floor=net.obs_std_rel_floor)
        return learner.init(policy.init(key_net, norm))

    def act(params):
        return lambda o, eps: policy.sample_action(params, o, eps)

    def sample(state: PolicyState, key: PRNGKey) -> tuple[Array, Array]:
        def one(x0, k):
            traj = sample_observed(
                env,
                act(state.params),
                x0,
                k,
                N,
                T,
                smooth_sigma=smooth,
                obs_noise=settings.obs_noise,
            )
            return traj.X, traj.U

        return jax.vmap(one)(X0, jax.random.split(key, C))

    def linearise(state: PolicyState, X: Array) -> LinearGaussianController:
        obs = lambda x: env.obs(x)
        return jax.vmap(lambda x: linearise_policy(policy, state.params, obs, x))(X)

    def s_step(state: PolicyState, key: PRNGKey, X: Array, O: Array, controllers, cost=None):
        mu, prec = jax.vmap(controller_targets)(controllers, X)  # [C, N, T, ...]
        flat = lambda a, k: a.reshape(-1, *a.shape[k:])
        w_cond = condition_weights(cost, settings.outlier_cost_ratio, X.shape[0], X.dtype)
        w = jnp.broadcast_to(w_cond[:, None, None], mu.shape[:3])
        state, metrics = learner.s_step(
            state, key, flat(O[:, :, :-1], 3), flat(mu, 3), flat(prec, 3), flat(w, 3)
        )
        return state, metrics.replace(left_out=jnp.sum(w_cond == 0).astype(jnp.int32))

    def rollouts(state: PolicyState, x0: Array) -> Trajectory:
        return policy_rollouts(env, policy, state.params, x0)

    def metrics(state: PolicyState, s_metrics: SStepMetrics) -> PolicyMetrics:
        traj = rollouts(state, X0)
        cost = jax.vmap(lambda x, u: trajectory_cost(true_cost, x, u))(traj.X, traj.U)
        return PolicyMetrics(success=jax.vmap(env.success)(traj.X), cost=cost, s_step=s_metrics)

    return PolicyPhases(
        init=init,
        sample=sample,
        observe=observe,
        linearise=linearise,
        s_step=s_step,
        rollouts=rollouts,
        metrics=metrics,
        policy=policy,
    )


# ---- MDGPS with a known cost --------------------------------------------------------------------


@dataclass(frozen=True)
class MDGPSConfig:
    """Static settings of MDGPS: gps (GPS's; ``iterations``, samples, KL step, ...) and policy
    (:class:`PolicySettings`)."""

    gps: GPSConfig = field(default_factory=GPSConfig)
    policy: PolicySettings = field(default_factory=PolicySettings)


@struct.dataclass
class MDGPSState:
    """gps: :class:`GPSState` (local controllers, fields [C, ...]; its ``prev_controller`` is the
    last policy linearisation); policy: :class:`PolicyState`."""

    gps: GPSState
    policy: PolicyState


@struct.dataclass
class MDGPSMetrics:
    """Per iteration: gps: :class:`GPSMetrics` [C] (the local controllers); policy:
    :class:`PolicyMetrics` (the global policy after the S-step)."""

    gps: GPSMetrics
    policy: PolicyMetrics


class MDGPS(NamedTuple):
    """The pure functions of :func:`make_mdgps`: init(key, hparams=None) -> MDGPSState;
    iteration(state, key) -> (state, metrics); train(key, hparams=None) -> (state, metrics
    [iterations]); policy_phases: the :class:`PolicyPhases` (policy, rollouts)."""

    init: Callable[..., MDGPSState]
    iteration: Callable[[MDGPSState, PRNGKey], tuple[MDGPSState, MDGPSMetrics]]
    train: Callable[..., tuple[MDGPSState, MDGPSMetrics]]
    policy_phases: PolicyPhases


def policy_iteration_samples(
    phases, policy_phases: PolicyPhases, settings: PolicySettings, gps, policy, key
) -> GPSSamples:
    """Step 1: the iteration's samples with fitted dynamics, from the local controllers or (on
    policy) from the global policy."""
    if settings.sample_on_policy:
        X, U = policy_phases.sample(policy, key)
        return phases.fit(X, U)
    return phases.outer(gps, key)


def make_mdgps(
    config: MDGPSConfig,
    env: Env,
    cost: CostFn,
    *,
    true_cost: CostFn | None = None,
    x0: Array | None = None,
) -> MDGPS:
    """Set up MDGPS on ``env`` with ``cost`` (see the module docstring); x0: training conditions
    [C, dX] (default ``env.initial_states()``); true_cost: reported in the metrics (default
    ``cost``; a residual ``cost`` with ``gauss_newton`` needs one)."""
    if true_cost is None:
        if config.gps.gauss_newton:
            raise ValueError("make_mdgps: gauss_newton=True needs the true_cost to report")
        true_cost = cost
    phases = make_gps_phases(config.gps, env, true_cost=true_cost, x0=x0)
    policy_phases = make_policy_phases(config.policy, config.gps, env, true_cost=true_cost, x0=x0)

    def init(key: PRNGKey, hparams: GPSHyperparams | None = None) -> MDGPSState:
        key_gps, key_policy = jax.random.split(key)
        return MDGPSState(gps=phases.init(key_gps, hparams), policy=policy_phases.init(key_policy))

    def iteration(state: MDGPSState, key: PRNGKey) -> tuple[MDGPSState, MDGPSMetrics]:
        key_sample, key_obs, key_s = jax.random.split(key, 3)
        samples = policy_iteration_samples(
            phases, policy_phases, config.policy, state.gps, state.policy, key_sample
        )
        O = policy_phases.observe(samples.X, key_obs)
        anchor = policy_phases.linearise(state.policy, samples.X)
        quad = phases.expand(cost, samples)
        step_mult = phases.adapt_step(state.gps, samples, quad, current=anchor, shared=True)
        gps, gps_metrics = phases.inner(state.gps, samples, quad, step_mult, anchor=anchor)
        policy, s_metrics = policy_phases.s_step(
            state.policy, key_s, samples.X, O, gps.controller, cost=gps_metrics.cost
        )
        metrics = MDGPSMetrics(gps=gps_metrics, policy=policy_phases.metrics(policy, s_metrics))
        return MDGPSState(gps=gps, policy=policy), metrics

    def train(key: PRNGKey, hparams: GPSHyperparams | None = None):
        key_init, key_iter = jax.random.split(key)
        state = init(key_init, hparams)
        return lax.scan(iteration, state, jax.random.split(key_iter, config.gps.iterations))

    return MDGPS(init=init, iteration=iteration, train=train, policy_phases=policy_phases)
