"""Mirror-descent Guided Policy Search with a known cost (MDGPS; Montgomery & Levine 2016, GPS's
``AlgorithmMDGPS``), and the policy phases rGCL shares with it.

One iteration, for every condition at once:

1. sample N trajectories per condition — from the local controllers (off-policy, GPS's default) or
   from the global policy itself (``sample_on_policy``) — and fit linear-Gaussian dynamics; roll
   the policy out noise-free from each condition's start (its success metric);
2. record what the policy would observe at the sample states (``env.obs``, with sensor noise
   when ``obs_noise``), and the noise-free observations with their Jacobians ``∂o/∂x``;
3. linearise the global policy around the samples: ``∂μ_θ(o(x))/∂x = ∂μ_θ/∂o · ∂o/∂x``
   (:func:`diffgcl.policies.mdgps.linearise_policy_at`);
4. expand the cost, adapt the step size — *one* step for all conditions, from the Laplace cost of
   the previous policy linearisation, of the controllers the last C-step predicted, and of the
   current policy linearisation (GPS's MDGPS ``_stepadjust``);
5. C-step: the KL-constrained LQR of each condition with the policy linearisation as its KL anchor;
6. S-step: regress the policy onto the new controllers at the sample states, weighted by their
   precision (:mod:`diffgcl.policies.mdgps`).

Steps 1–2 are the simulator's (:class:`diffgcl.sim.simulator.Simulator`, all of an iteration's
rollouts in one batched call), the rest is pure maths on what it returned. The policy's metrics
describe the policy that was in effect during the iteration (before its S-step), as GPS's
metrics describe the controller that drew the samples.

:func:`make_policy_phases` builds steps 1–3, 6 and the policy evaluation for an env; the rGCL
schedules (:mod:`diffgcl.algorithms.rgcl`) compose them with the cost updates the same way this
module composes them with a fixed cost. :func:`make_mdgps` returns pure ``init``, ``iteration``
and ``train(key, hparams=None)`` (and the iteration's ``draw`` / ``simulate`` / ``update``
parts for a host loop, :mod:`diffgcl.algorithms.staged`); ``jax.jit(jax.vmap(train))`` runs a
seed sweep.

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
    GPSState,
    SampleRequest,
    make_gps_phases,
)
from diffgcl.control.step import STEP_RULES
from diffgcl.costs.expansion import trajectory_cost
from diffgcl.policies.mdgps import (
    PolicyState,
    SStepConfig,
    SStepMetrics,
    controller_targets,
    linearise_policy_at,
    make_policy_learner,
)
from diffgcl.policies.network import GaussianPolicy, PolicyConfig, fit_obs_normaliser
from diffgcl.sim.rollout import smooth_noise
from diffgcl.sim.simulator import Simulator
from diffgcl.types import Array, CostFn, Env, LinearGaussianController, PRNGKey, Trajectory


@dataclass(frozen=True)
class PolicySettings:
    """The global policy's static settings (shared by MDGPS and rGCL).

    network: :class:`~diffgcl.policies.network.PolicyConfig`; s_step:
    :class:`~diffgcl.policies.mdgps.SStepConfig`; sample_on_policy: draw the GPS samples from the
    global policy instead of the local controllers (GPS's ``sample_on_policy``); obs_noise: the
    policy sees noisy sensors in the samples and the S-step (noise-free in its linearisation and
    evaluation); outlier_cost_ratio: a condition whose samples cost more than this multiple of
    the median condition's is left out of the S-step (:func:`condition_weights`; None: none is);
    step_rule: how the C-step's KL step adapts — ``"global"``: one multiplier for all conditions
    from their averaged cost estimates; ``"classic"``: each condition its own, from its own
    estimates (GPS's two MDGPS rules; under ``"global"`` one runaway condition's estimates,
    orders of magnitude above the rest, set every condition's step); ``"geometric"``: one
    multiplier for all, the geometric mean of the conditions' own (each condition's vote
    bounded by the rule's clip, so no one condition decides).
    """

    network: PolicyConfig = field(default_factory=PolicyConfig)
    s_step: SStepConfig = field(default_factory=SStepConfig)
    sample_on_policy: bool = False
    obs_noise: bool = False
    outlier_cost_ratio: float | None = None
    step_rule: str = "global"

    def __post_init__(self):
        if self.step_rule not in STEP_RULES:
            raise ValueError(
                f"PolicySettings: step_rule {self.step_rule!r}; choose one of {STEP_RULES}"
            )


@struct.dataclass
class PolicyMetrics:
    """Per iteration: success / cost: [C] success and true cost of the noise-free rollout, from
    each training condition, of the policy in effect during the iteration (before its S-step);
    s_step: :class:`SStepMetrics` of the iteration's S-step."""

    success: Array
    cost: Array
    s_step: SStepMetrics


@struct.dataclass
class PolicyRequest:
    """What the global policy asks the simulator for, C conditions: its params, rolled out from
    x0: [C, dX] — ``n`` times with its action noise ``noise: [C, n, T, dU]`` (sensor noise from
    ``obs_key: [C, n, 2]`` when the settings say so, else None) and once noise-free."""

    params: object
    x0: Array
    noise: Array
    obs_key: Array | None = None


@struct.dataclass
class SimulatedPolicy:
    """The simulator's answer to a :class:`PolicyRequest`: samples [C, n] (None when n = 0) and
    mean [C] (the noise-free rollouts) as :class:`~diffgcl.types.Trajectory`."""

    samples: Trajectory | None
    mean: Trajectory


class InitialSamples(NamedTuple):
    """The initial controllers' samples whose observations fit the policy's normaliser:
    controller [C, N, T, ...], x0 [C, N, dX], noise [C, N, T, dU], obs_keys [C, N, T+1, 2]
    (None without ``obs_noise``)."""

    controller: LinearGaussianController
    x0: Array
    noise: Array
    obs_keys: Array | None


class PolicyPhases(NamedTuple):
    """The policy's part of an iteration on an env (pure; C conditions at once).

    init(key, O=None) -> PolicyState (normaliser from observations ``O: [..., dO]``, else from
    the initial controllers' samples); draw(state, key, n) -> PolicyRequest (n noisy rollouts per
    condition and the noise-free one); simulate(sim, request) -> SimulatedPolicy;
    observation_keys(key, shape) -> one sensor-noise key per state (None without ``obs_noise``);
    observe(sim, X, keys) -> O [C, N, T+1, dO] (sensor noise with the keys); observe_at(sim,
    X) -> (O [C, N, T, dO], J [C, N, T, dO, dX]) noise-free observations and their Jacobians at
    the states 0 .. T−1; linearise(state, O, J, X) -> LinearGaussianController [C];
    s_step(state, key, X, O, controllers) -> (PolicyState, SStepMetrics); rollouts(state, x0) ->
    Trajectory [B] noise-free from starts ``x0: [B, dX]``; metrics(mean, s_step_metrics) ->
    PolicyMetrics from the noise-free rollouts ``mean`` [C]; policy: the :class:`GaussianPolicy`;
    act(params, o, eps): its action; name: what tells its simulator programs apart;
    initial_samples(key) -> :class:`InitialSamples` and observe_initial(sim, samples) -> O: what
    ``init(key)`` without observations draws and observes, for a host loop that simulates them
    with a staged simulator and passes the observations in (``init(key, O)``, the same state).
    """

    init: Callable[..., PolicyState]
    draw: Callable[..., PolicyRequest]
    simulate: Callable[..., SimulatedPolicy]
    observation_keys: Callable[..., Array | None]
    observe: Callable[..., Array]
    observe_at: Callable[..., tuple[Array, Array]]
    linearise: Callable[..., LinearGaussianController]
    s_step: Callable[..., tuple[PolicyState, SStepMetrics]]
    rollouts: Callable[[PolicyState, Array], Trajectory]
    metrics: Callable[[Trajectory, SStepMetrics], PolicyMetrics]
    policy: GaussianPolicy
    act: Callable
    name: tuple
    initial_samples: Callable[[PRNGKey], InitialSamples]
    observe_initial: Callable[..., Array]


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


def policy_actor(settings: PolicySettings, env: Env) -> tuple[Callable, tuple]:
    """``(act, name)``: the policy's action ``act(params, o, eps)`` and the name its simulator
    programs go by (the same for every policy of these settings on this env)."""
    policy = make_policy(settings, env)
    return policy.sample_action, ("policy", policy)


def policy_noise_free_rollouts(settings: PolicySettings, env: Env, params, x0: Array):
    """Host side: every seed's policy (``params`` with a leading [S] axis) noise-free from the
    starts ``x0: [B, dX]``, with the env's staged simulator: a Trajectory [S, B]."""
    from diffgcl.algorithms.staged import policy_rollouts

    return policy_rollouts(env, make_policy(settings, env), params, x0)


def make_policy_phases(
    settings: PolicySettings,
    gps_config: GPSConfig,
    env: Env,
    *,
    true_cost: CostFn | None = None,
    x0: Array | None = None,
    sim: Simulator | None = None,
) -> PolicyPhases:
    """The policy phases of ``env`` (see :class:`PolicyPhases`); ``gps_config`` gives the number
    of samples, the noise smoothing and the initial controllers' variance; ``true_cost`` (default
    ``env.expert_cost``) is reported for the policy's rollouts; ``x0``: training conditions [C, dX]
    (default ``env.initial_states()``); sim: the simulator ``init`` and ``rollouts`` trace in."""
    from diffgcl.control.init import init_controller

    sim = Simulator(env) if sim is None else sim
    policy = make_policy(settings, env)
    learner = make_policy_learner(policy, settings.s_step)
    true_cost = env.expert_cost if true_cost is None else true_cost
    X0 = jnp.asarray(env.initial_states() if x0 is None else x0)
    C, T, dU = X0.shape[0], env.horizon, env.dU
    N = gps_config.num_samples
    smooth = gps_config.smooth_sigma
    act, name = policy_actor(settings, env)

    def observation_keys(key: PRNGKey, shape: tuple[int, ...]) -> Array | None:
        """One sensor-noise key per state of a batch of states of ``shape`` (None without
        ``obs_noise``)."""
        if not settings.obs_noise:
            return None
        return jax.random.split(key, shape).reshape(*shape, -1)

    def observe(sim: Simulator, X: Array, keys: Array | None) -> Array:
        """What the policy sees at states X [..., dX] (``keys`` [..., 2] from
        ``observation_keys``; None: exact sensors)."""
        return sim.observations(X) if keys is None else sim.observations(X, keys)

    def observe_at(sim: Simulator, X: Array) -> tuple[Array, Array]:
        return sim.observation_jacobians(X[..., :-1, :])

    def initial_samples(key: PRNGKey) -> InitialSamples:
        """The initial controllers' N noisy samples per condition that ``init(key)`` observes
        (what they are, not yet simulated: ``observe_initial`` runs them)."""
        _, key_samples, key_obs = jax.random.split(key, 3)
        ctrl = init_controller(T, env.dX, dU, gps_config.init_var, dtype=X0.dtype)
        ctrl = jax.tree.map(lambda a: jnp.broadcast_to(a, (C, N, *a.shape)), ctrl)
        noise = jax.vmap(lambda k: noise_of(k, N))(jax.random.split(key_samples, C))
        x0 = jnp.broadcast_to(X0[:, None], (C, N, env.dX))
        return InitialSamples(ctrl, x0, noise, observation_keys(key_obs, (C, N, T + 1)))

    def observe_initial(sim: Simulator, samples: InitialSamples) -> Array:
        """O [..., C, N, T+1, dO]: what the policy sees along ``samples`` (any leading axes)."""
        X = sim.controller_rollouts(samples.controller, samples.x0, samples.noise).X
        return observe(sim, X, samples.obs_keys)

    def init(key: PRNGKey, O: Array | None = None) -> PolicyState:
        key_net = jax.random.split(key, 3)[0]
        if O is None:
            O = observe_initial(sim, initial_samples(key))
        net = settings.network
        norm = fit_obs_normaliser(O, net.obs_std_floor, rel_floor=net.obs_std_rel_floor)
        return learner.init(policy.init(key_net, norm))

    def noise_of(key: PRNGKey, n: int) -> Array:
        """[n, T, dU]: GPS's exploration noise of one condition."""
        return jax.vmap(lambda k: smooth_noise(k, T, dU, smooth))(jax.random.split(key, n))

    def draw(state: PolicyState, key: PRNGKey, n: int, x0: Array | None = None) -> PolicyRequest:
        x0 = X0 if x0 is None else x0

        def one(key_c):
            key_noise, key_obs = jax.random.split(key_c)
            return noise_of(key_noise, n), jax.random.split(key_obs, n)

        noise, obs_key = jax.vmap(one)(jax.random.split(key, C))
        if not (settings.obs_noise and n > 0):
            obs_key = None
        return PolicyRequest(params=state.params, x0=x0, noise=noise, obs_key=obs_key)

    def simulate(sim: Simulator, request: PolicyRequest) -> SimulatedPolicy:
        """Any leading batch axes before [C, ...]; the params carry them too."""
        x0, noise = request.x0, request.noise
        n = noise.shape[-3]
        zero = jnp.zeros((*noise.shape[:-3], 1, *noise.shape[-2:]), noise.dtype)
        rollouts = lambda x, e, k: sim.policy_rollouts(
            act, request.params, x, e, k, shared=2, name=name
        )
        x0_n = lambda m: jnp.broadcast_to(x0[..., None, :], (*x0.shape[:-1], m, x0.shape[-1]))
        if n == 0:
            mean = rollouts(x0_n(1), zero, None)
            return SimulatedPolicy(samples=None, mean=jax.tree.map(lambda a: a[..., 0, :, :], mean))
        if request.obs_key is None:  # one batch: the noisy samples and the noise-free rollout
            both = rollouts(x0_n(n + 1), jnp.concatenate([noise, zero], axis=-3), None)
            samples = jax.tree.map(lambda a: a[..., :n, :, :], both)
            return SimulatedPolicy(
                samples=samples, mean=jax.tree.map(lambda a: a[..., n, :, :], both)
            )
        samples = rollouts(x0_n(n), noise, request.obs_key)
        mean = rollouts(x0_n(1), zero, None)
        return SimulatedPolicy(samples=samples, mean=jax.tree.map(lambda a: a[..., 0, :, :], mean))

    def linearise(state: PolicyState, O: Array, J: Array, X: Array) -> LinearGaussianController:
        return jax.vmap(lambda o, j, x: linearise_policy_at(policy, state.params, o, j, x))(O, J, X)

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
        zero = jnp.zeros((x0.shape[0], T, dU), x0.dtype)
        return sim.policy_rollouts(act, state.params, x0, zero, shared=1, name=name)

    def metrics(mean: Trajectory, s_metrics: SStepMetrics) -> PolicyMetrics:
        cost = jax.vmap(lambda x, u: trajectory_cost(true_cost, x, u))(mean.X, mean.U)
        return PolicyMetrics(success=jax.vmap(env.success)(mean.X), cost=cost, s_step=s_metrics)

    return PolicyPhases(
        init=init,
        draw=draw,
        simulate=simulate,
        observation_keys=observation_keys,
        observe=observe,
        observe_at=observe_at,
        linearise=linearise,
        s_step=s_step,
        rollouts=rollouts,
        metrics=metrics,
        policy=policy,
        act=act,
        name=name,
        initial_samples=initial_samples,
        observe_initial=observe_initial,
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
    """The pure functions of :func:`make_mdgps`: init(key, hparams=None, O=None) -> MDGPSState
    (``O``: the observations of ``initial_samples(key)``, else simulated inside);
    iteration(state, key) -> (state, metrics), which is ``update(state, key, simulate(sim,
    draw(state, key)))``; train(key, hparams=None) -> (state, metrics [iterations]);
    policy_phases: the :class:`PolicyPhases` (policy, rollouts)."""

    init: Callable[..., MDGPSState]
    iteration: Callable[[MDGPSState, PRNGKey], tuple[MDGPSState, MDGPSMetrics]]
    train: Callable[..., tuple[MDGPSState, MDGPSMetrics]]
    policy_phases: PolicyPhases
    draw: Callable[[MDGPSState, PRNGKey], MDGPSRequest]
    simulate: Callable[..., MDGPSSimulated]
    update: Callable[..., tuple[MDGPSState, MDGPSMetrics]]
    keyed: bool = True  # update(state, key, sims): the S-step draws from the iteration's key
    # What init(key) simulates to fit the policy's normaliser; a host loop simulates it staged
    # and calls init(key, hparams, O) (diffgcl.algorithms.staged.run_gps_seeds).
    initial_samples: Callable[[PRNGKey], InitialSamples] | None = None


@struct.dataclass
class MDGPSRequest:
    """One MDGPS iteration's requests: gps (the local controllers': N noisy samples and the
    noise-free rollout, or only the latter when sampling on policy) and policy (its noise-free
    rollout, and N noisy samples when sampling on policy); obs_keys: [C, N, T+1, 2] the sensor
    noise of the samples' observations (None without ``obs_noise``)."""

    gps: SampleRequest
    policy: PolicyRequest
    obs_keys: Array | None


@struct.dataclass
class MDGPSSimulated:
    """The simulator's answer to an :class:`MDGPSRequest`: X [C, N, T+1, dX], U [C, N, T, dU]
    the iteration's samples; mean_X [C, T+1, dX] the local controllers' noise-free rollouts;
    A, B the step's Jacobians at the samples' mean (None with regression dynamics); policy_mean:
    the policy's noise-free rollouts [C]; O: [C, N, T+1, dO] what the policy observed at the
    samples (sensor noise with ``obs_noise``); O_clean [C, N, T, dO], J_obs [C, N, T, dO, dX]:
    noise-free observations and their Jacobians at the sample states."""

    X: Array
    U: Array
    mean_X: Array
    A: Array | None
    B: Array | None
    policy_mean: Trajectory
    O: Array
    O_clean: Array
    J_obs: Array


def make_policy_sampling(phases, policy_phases: PolicyPhases, settings: PolicySettings, N: int):
    """``(draw, simulate)`` of one MDGPS iteration's samples (step 1–2 of the module docstring):
    draw(gps, policy, key_sample, key_obs) -> MDGPSRequest (``key_obs``: the sensor noise of the
    samples' observations), simulate(sim, request) -> MDGPSSimulated. Shared by MDGPS and rGCL
    with a policy."""

    def draw(gps: GPSState, policy: PolicyState, key_sample: PRNGKey, key_obs) -> MDGPSRequest:
        on = settings.sample_on_policy
        gps_request = phases.draw(gps, key_sample, 0 if on else N)
        C, _, T, _ = gps_request.noise.shape
        return MDGPSRequest(
            gps=gps_request,
            policy=policy_phases.draw(policy, key_sample, N if on else 0),
            obs_keys=policy_phases.observation_keys(key_obs, (C, N, T + 1)),
        )

    def simulate(sim: Simulator, request: MDGPSRequest) -> MDGPSSimulated:
        if settings.sample_on_policy:
            local = phases.simulate(sim, request.gps, jacobians=False)
            pol = policy_phases.simulate(sim, request.policy)
            X, U = pol.samples.X, pol.samples.U
            A, B = (None, None)
            if phases.autodiff:
                A, B = sim.jacobians(X.mean(axis=-3), U.mean(axis=-3))
        else:
            local = phases.simulate(sim, request.gps)
            pol = policy_phases.simulate(sim, request.policy)
            X, U, A, B = local.X[..., :-1, :, :], local.U[..., :-1, :, :], local.A, local.B
        O = policy_phases.observe(sim, X, request.obs_keys)
        O_clean, J = policy_phases.observe_at(sim, X)
        return MDGPSSimulated(
            X=X,
            U=U,
            mean_X=local.X[..., -1, :, :],
            A=A,
            B=B,
            policy_mean=pol.mean,
            O=O,
            O_clean=O_clean,
            J_obs=J,
        )

    return draw, simulate


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
    sim = Simulator(env)
    phases = make_gps_phases(config.gps, env, true_cost=true_cost, x0=x0, sim=sim)
    policy_phases = make_policy_phases(
        config.policy, config.gps, env, true_cost=true_cost, x0=x0, sim=sim
    )
    draw_samples, simulate = make_policy_sampling(
        phases, policy_phases, config.policy, config.gps.num_samples
    )

    def init(
        key: PRNGKey, hparams: GPSHyperparams | None = None, O: Array | None = None
    ) -> MDGPSState:
        key_gps, key_policy = jax.random.split(key)
        policy = policy_phases.init(key_policy, O)
        return MDGPSState(gps=phases.init(key_gps, hparams), policy=policy)

    def initial_samples(key: PRNGKey) -> InitialSamples:
        return policy_phases.initial_samples(jax.random.split(key)[1])

    def draw(state: MDGPSState, key: PRNGKey) -> MDGPSRequest:
        key_sample, key_obs, _ = jax.random.split(key, 3)
        return draw_samples(state.gps, state.policy, key_sample, key_obs)

    def update(state: MDGPSState, key: PRNGKey, sims: MDGPSSimulated):
        _, _, key_s = jax.random.split(key, 3)
        samples = phases.fit_samples(sims.X, sims.U, sims.mean_X, sims.A, sims.B)
        anchor = policy_phases.linearise(state.policy, sims.O_clean, sims.J_obs, sims.X)
        quad = phases.expand(cost, samples)
        step_mult = phases.adapt_step(
            state.gps, samples, quad, current=anchor, rule=config.policy.step_rule
        )
        gps, gps_metrics = phases.inner(state.gps, samples, quad, step_mult, anchor=anchor)
        policy, s_metrics = policy_phases.s_step(
            state.policy, key_s, sims.X, sims.O, gps.controller, cost=gps_metrics.cost
        )
        metrics = MDGPSMetrics(
            gps=gps_metrics, policy=policy_phases.metrics(sims.policy_mean, s_metrics)
        )
        return MDGPSState(gps=gps, policy=policy), metrics

    def iteration(state: MDGPSState, key: PRNGKey) -> tuple[MDGPSState, MDGPSMetrics]:
        return update(state, key, simulate(sim, draw(state, key)))

    def train(key: PRNGKey, hparams: GPSHyperparams | None = None):
        key_init, key_iter = jax.random.split(key)
        state = init(key_init, hparams)
        return lax.scan(iteration, state, jax.random.split(key_iter, config.gps.iterations))

    return MDGPS(
        init=init,
        iteration=iteration,
        train=train,
        policy_phases=policy_phases,
        draw=draw,
        simulate=simulate,
        update=update,
        initial_samples=initial_samples,
    )
