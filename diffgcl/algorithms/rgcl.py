"""Reworked Guided Cost Learning (rGCL): GPS on a learned cost, the cost learned by GCL (DESIGN §6).

The seed's rGCL alternates trajectory-optimisation GPS (:mod:`diffgcl.algorithms.gps`) with the
sample-based MaxEnt IOC cost update of GCL (:mod:`diffgcl.costs.gcl`, Finn et al. 2016a). Two
schedules (the seed's Fig. 3.3):

* **v1** — per rGCL iteration, ``gps_per_update`` full GPS iterations with the current cost
  (sample, fit dynamics, expand, adapt the step, C-step), then one cost update; the step of the
  first GPS iteration after an update is judged with the cost before it (the one its controller
  was optimised for, ``CostState.prev_params``), so that every step is judged under one cost;
* **v2** — GPS's outer loop (sample + fit dynamics), the KL step adapted with the *previous*
  cost (Finn et al. compute it before the cost changes), the cost update, then GPS's inner loop
  (expand the *new* cost, C-step).

Before the loop the cost is pre-trained on the demos (``GCLConfig.pretrain_steps``) against the
initial controller's samples (or, as in the seed, against the demos alone); the network's input
normaliser is set from the demos once and then frozen, so that the cost GPS optimises only changes
through the GCL update.

Samples for the cost update (``RGCLConfig.sample_source``): ``"buffer"`` — every real sample of
the last ``buffer_controllers`` controllers with GCL's fusion importance weights (and the demos'
own fitted controller in the mixture); ``"model"`` — the seed's variant, ``model_samples`` fresh
trajectories of the current controller in the fitted linear-Gaussian model with their full
``log p(τ)``.

No LAPACK inside the vmapped program: jaxlib 0.10.2's CPU LAPACK kernels (triangular solve,
Cholesky, LU) split a large batch over the intra-op thread pool and block on it; when the thunk
executor runs as many of them concurrently as the pool has threads (2 here), the process
deadlocks (measured: an 8-seed vmapped arm run hung in ``lapack_strsm_ffi``). The LQR, the
controllers and the proposal densities use the unrolled small-matrix routines of
:mod:`diffgcl.linalg`; the demos' controller (a least-squares fit) is fitted once on the host
(:func:`demo_batch`).

Everything is pure: :func:`make_train` returns ``train(key, demos, hparams) -> (state, metrics)``;
``jax.jit(jax.vmap(train))`` over keys and :class:`RGCLHyperparams` (KL step, initial controller
variance, cost learning rate — all traced) is a sweep. The same iteration is exposed as
``init`` / ``run`` so that a host loop (:mod:`diffgcl.algorithms.runner`) can run it in chunks
with checkpoints; the per-iteration keys are ``fold_in(key_loop, step)``, so a chunked run equals
an uninterrupted one.

Global policy (``RGCLConfig.policy``, DESIGN §6; MDGPS, :mod:`diffgcl.algorithms.mdgps`): every
GPS iteration then linearises the policy around its samples, uses that linearisation as the
C-step's KL anchor and as the controller the (shared) step rule judges, and ends with the S-step
onto the new controllers. v2 runs the S-step after its inner loop, v1 after each of its GPS
iterations. With ``sample_on_policy`` the samples come from the policy and the fusion buffer
records the policy's linearisation at them as their proposal (an approximation of the policy's
density, exact for a policy linear in the state). The policy's observation normaliser is fitted
once from the demonstrations' observations.

Training past the demos' window: the env's horizon T may exceed the demos' T_d (their ``U``'s
time axis). The controllers, their samples and the policy then cover all T steps, while GCL compares
the demos with the samples' first T_d steps only (the fusion buffer stores those steps and the
proposals' first T_d steps; the samples' learned cost in the metrics is over the same steps). A
time-invariant cost learned on the window is so also optimised past it, where a boat must hold
its course after the demos' recordings end. A cost with a time input
(``CostNetworkConfig.time_input``) is not time-invariant: past the window it is the network at
times GCL never fitted, and nothing in the update corrects it there (docs/usv_cost_form.md).

NaN guard (pure, per run): when an iteration turns a finite value anywhere in the state into a
non-finite one, the iteration is rolled back (the previous state is kept,
``metrics.rolled_back`` is set) and the next step tries again with a fresh key.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
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
from diffgcl.algorithms.mdgps import (
    PolicyMetrics,
    PolicySettings,
    make_policy_phases,
    make_policy_sampling,
)
from diffgcl.control.init import with_mean_variance
from diffgcl.control.lqr import controller_entropy
from diffgcl.costs.buffer import SampleBuffer, buffer_add, init_buffer
from diffgcl.costs.demo_controller import fit_demo_controller
from diffgcl.costs.gcl import (
    GCLConfig,
    GCLMetrics,
    WeightedSamples,
    cost_optimiser,
    fusion_weighted_samples,
    make_cost_learner,
    minibatch,
)
from diffgcl.costs.model_samples import model_weighted_samples
from diffgcl.costs.network import (
    CostNetwork,
    CostNetworkConfig,
    CostParams,
    untempered,
)
from diffgcl.costs.temperature import calibrated_log_temperature
from diffgcl.eval.controllers import demo_log_likelihood
from diffgcl.policies.mdgps import PolicyState
from diffgcl.sim.rollout import rollout_controller
from diffgcl.sim.simulator import Simulator
from diffgcl.tracing import batched_like
from diffgcl.types import Array, Env, LinearDynamics, LinearGaussianController, PRNGKey

SCHEDULES = ("v1", "v2")
SAMPLE_SOURCES = ("buffer", "model")
TEMPERATURES = ("likelihood", "demos")
INITIAL_CONTROLLERS = ("zero", "demos")


@dataclass(frozen=True)
class RGCLConfig:
    """Static settings of an rGCL run (anything that changes shapes or the program).

    schedule: "v1" or "v2"; iterations: rGCL iterations; gps_per_update: v1's GPS iterations per
    cost update (v2: one outer/inner pair per iteration); gps: GPS settings (its ``iterations``
    is unused; ``gauss_newton`` is forced on — the network cost is expanded by Gauss–Newton);
    network, gcl: the cost and its update; sample_source: "buffer" (fusion) or "model" (the
    seed); model_samples: generated samples per update with "model"; buffer_controllers:
    controllers (and their samples) kept for fusion; pretrain: run the pre-training pass;
    pretrain_with_samples: pre-train against the initial controller's samples (else the demos
    alone form the partition, as in the seed); freeze_last: the last ``freeze_last`` iterations
    skip the cost update (GPS polishes on a fixed cost); late_max_step_mult /
    late_iterations: cap on step_mult over the last ``late_iterations`` iterations (a late KL cap;
    None: off); nan_guard: roll back iterations that produce non-finite values;
    reopt_iterations: GPS iterations of the re-optimisation check; policy: a global policy on the
    env's observations trained by MDGPS alongside (:class:`PolicySettings`; None: local
    controllers only); temperature: how the learned cost's scale ``e^ρ`` is set —
    ``"likelihood"``: ρ = 0, the scale the GCL fit gives; ``"demos"``: after pre-training and
    after every cost update, ρ makes the MaxEnt controller of the cost about the demos as precise
    as the demos' own fitted controller (equal action entropy; :mod:`diffgcl.costs.temperature`;
    needs ``DemoBatch.dynamics``); temperature_start, temperature_ramp: with ``"demos"``, ρ stays
    0 until ``temperature_start`` cost updates are done, then grows linearly to the calibrated
    value over ``temperature_ramp`` more (0: at once; both 0: calibrated from the pre-training
    on), so that GPS explores at the likelihood's scale while the cost takes shape;
    initial_controller: where GPS starts — ``"zero"``: K = 0, k = 0, Σ = init_var·I (the seed's
    rGCL); ``"demos"``: the demos' own fitted controller per condition (``DemoBatch.controller``)
    with its covariance rescaled to a mean variance of init_var
    (:func:`diffgcl.control.init.with_mean_variance`), for tasks where a zero controller fails
    at once (a pendulum falls before GPS's KL-bounded steps can catch it);
    zero_controller_samples: also put N samples of the zero controller (``init_var``) per
    condition in the fusion buffer at the start, with their proposal, so that the partition
    function sees trajectories that fail even when GPS starts from the demos and draws only
    samples near them (they leave the buffer after ``buffer_controllers`` iterations).
    """

    schedule: str = "v2"
    iterations: int = 30
    gps_per_update: int = 1
    gps: GPSConfig = field(default_factory=lambda: GPSConfig(gauss_newton=True))
    network: CostNetworkConfig = field(default_factory=CostNetworkConfig)
    gcl: GCLConfig = field(default_factory=GCLConfig)
    sample_source: str = "buffer"
    model_samples: int = 10
    buffer_controllers: int = 20
    pretrain: bool = True
    pretrain_with_samples: bool = True
    freeze_last: int = 0
    late_max_step_mult: float | None = None
    late_iterations: int = 0
    nan_guard: bool = True
    reopt_iterations: int = 30
    policy: PolicySettings | None = None
    temperature: str = "likelihood"
    temperature_start: int = 0
    temperature_ramp: int = 0
    initial_controller: str = "zero"
    zero_controller_samples: bool = False

    def __post_init__(self):
        if self.schedule not in SCHEDULES:
            raise ValueError(f"RGCLConfig: schedule {self.schedule!r}; choose one of {SCHEDULES}")
        if self.sample_source not in SAMPLE_SOURCES:
            raise ValueError(
                f"RGCLConfig: sample_source {self.sample_source!r}; choose one of {SAMPLE_SOURCES}"
            )
        if self.initial_controller not in INITIAL_CONTROLLERS:
            raise ValueError(
                f"RGCLConfig: initial_controller {self.initial_controller!r}; choose one of "
                f"{INITIAL_CONTROLLERS}"
            )
        if self.temperature not in TEMPERATURES:
            raise ValueError(
                f"RGCLConfig: temperature {self.temperature!r}; choose one of {TEMPERATURES}"
            )
        updates = self.iterations - self.freeze_last
        if not 0 <= self.temperature_start + self.temperature_ramp <= updates:
            raise ValueError(
                f"RGCLConfig: temperature_start + temperature_ramp must be within 0 and the "
                f"{updates} cost updates (iterations − freeze_last)"
            )
        if self.iterations < 1 or self.gps_per_update < 1 or self.buffer_controllers < 1:
            raise ValueError("RGCLConfig: iterations, gps_per_update, buffer_controllers >= 1")

    @property
    def gps_per_iteration(self) -> int:
        """GPS C-steps per rGCL iteration (G in the metrics' shapes)."""
        return self.gps_per_update if self.schedule == "v1" else 1

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@struct.dataclass
class RGCLHyperparams:
    """Traced (sweepable) scalars: kl_step (GPS base KL step), init_var (initial controller
    variance), cost_lr (Adam learning rate of the cost update)."""

    kl_step: Array
    init_var: Array
    cost_lr: Array


@struct.dataclass
class DemoBatch:
    """Demonstrations grouped by condition: X: [C, N, T+1, dX], U: [C, N, T, dU]; controller:
    the demos' own fitted linear-Gaussian controller per condition (fields [C, T, ...]), a
    component of the fusion mixture (:func:`diffgcl.costs.demo_controller.fit_demo_controller`);
    dynamics: the env's dynamics linearised about the demos (fields [C, T, ...]; None when built
    without the env), for the temperature calibration; tail: None or [C, N, L+1, dX], each demo's
    recorded states from the window's last on, padded with its last recorded state, which GCL's
    monotonic and goal regularisers run on over (:mod:`diffgcl.costs.gcl`)."""

    X: Array
    U: Array
    controller: LinearGaussianController
    dynamics: LinearDynamics | None = None
    tail: Array | None = None


@struct.dataclass
class CostState:
    """The learned cost and its optimiser: params (:class:`CostParams`), opt_state (optax state
    of ``params.net``, learning rate inside), step: int32 gradient steps taken; prev_params: the
    parameters before the last update — the cost that the current controllers were optimised
    for, with which v1 judges the step of its first GPS iteration after an update."""

    params: CostParams
    opt_state: optax.OptState
    step: Array
    prev_params: CostParams


@struct.dataclass
class RGCLState:
    """State of one rGCL run with C conditions.

    gps: :class:`GPSState` (fields [C, ...]); cost: :class:`CostState`; buffer: fusion
    :class:`SampleBuffer` with a leading [C] axis; iteration: int32, rGCL iterations
    accepted; step: int32, iterations attempted (keys are ``fold_in(key_loop, step)``; differs
    from ``iteration`` after a rollback); policy: the global policy's :class:`PolicyState` (None
    without ``config.policy``).
    """

    gps: GPSState
    cost: CostState
    buffer: SampleBuffer
    iteration: Array
    step: Array
    policy: PolicyState | None = None


@struct.dataclass
class RGCLMetrics:
    """Per rGCL iteration (a run stacks a leading [iterations] axis).

    gps: :class:`GPSMetrics` with fields [G, C] (G = ``config.gps_per_iteration``); learned_cost:
    [G, C] mean learned trajectory cost of the GPS samples; demo_learned_cost: [C] mean learned
    trajectory cost of the demos (both under the cost after this iteration's update);
    demo_log_likelihood: [G, C] the demos' mean action log-likelihood under the new controllers
    (:func:`diffgcl.eval.controllers.demo_log_likelihood`); log_temperature: the cost's ρ after
    the update; gcl: :class:`GCLMetrics` averaged over the update's gradient steps (scalars;
    zeros on frozen iterations); cost_updated: bool; rolled_back: bool, the NaN guard rejected
    this iteration; sample_X: [G, C, N, T+1, dX] the GPS samples (for the motion plots); policy:
    :class:`PolicyMetrics` with fields [G, ...] after each S-step (None without a policy);
    policy_params: the global policy's parameters after this iteration (None without a policy),
    to choose among the iterations' policies afterwards (:func:`policy_learned_costs`).
    """

    gps: GPSMetrics
    learned_cost: Array
    demo_learned_cost: Array
    demo_log_likelihood: Array
    log_temperature: Array
    sample_X: Array
    gcl: GCLMetrics
    cost_updated: Array
    rolled_back: Array
    policy: PolicyMetrics | None = None
    policy_params: object = None


class V1Parts(NamedTuple):
    """v1's iteration in parts, for a host loop that runs the simulator as programs of its own
    (:class:`~diffgcl.algorithms.staged.StagedV1Loop`); ``RGCL.run`` traces the same functions
    into a ``lax.scan`` over the ``gps_iterations`` GPS iterations.

    begin(state, key_loop) -> (carry, keys [G, 2], key_cost); draw(carry, key) -> request;
    simulate(sim, request) -> the simulator's results; gps(state, carry, key, first, demos,
    sims) -> (carry, outputs) — ``first``: the phase's first GPS iteration; finish(state, carry,
    outputs stacked [G], key_cost, demos) -> (state, metrics), the cost update and the guard.
    """

    begin: Callable
    draw: Callable
    simulate: Callable
    gps: Callable
    finish: Callable
    gps_iterations: int


class RGCL(NamedTuple):
    """The pure functions of :func:`make_train`.

    train(key, demos, hparams=None) -> (RGCLState, RGCLMetrics [iterations]);
    split_key(key) -> (key_init, key_loop); init(key_init, demos, hparams=None) -> RGCLState
    (with pre-training); run(state, key_loop, demos, n) -> (state, metrics [n]) (``n`` static);
    default_hparams() -> RGCLHyperparams; network: the :class:`CostNetwork`; policy_phases: the
    global policy's :class:`~diffgcl.algorithms.mdgps.PolicyPhases` (None without a policy).
    v2's iteration in parts, for a host loop that runs the simulator as programs of its own
    (:mod:`diffgcl.algorithms.staged`; None for v1, whose parts are ``v1``): draw(state,
    key_loop) -> request, simulate(sim, request) -> the simulator's results, update(state,
    key_loop, demos, sims) -> (state, metrics) — ``run`` is these three traced into a
    ``lax.scan``; iterations: the config's.
    """

    train: Callable[..., tuple[RGCLState, RGCLMetrics]]
    split_key: Callable[[PRNGKey], tuple[PRNGKey, PRNGKey]]
    init: Callable[..., RGCLState]
    run: Callable[..., tuple[RGCLState, RGCLMetrics]]
    default_hparams: Callable[[], RGCLHyperparams]
    network: CostNetwork
    policy_phases: object = None
    draw: Callable | None = None
    simulate: Callable | None = None
    update: Callable | None = None
    iterations: int = 0
    v1: V1Parts | None = None


def make_network(config: RGCLConfig, env: Env) -> CostNetwork:
    """The cost network of ``config`` for ``env`` (parameters in the run's float dtype; with
    ``network.features == "env"`` it reads ``env.cost_features``, or ``env.cost_residuals`` for
    the weighted form; the neural form is anchored at ``env.cost_goal_state()`` and with
    ``network.prior_residuals`` weighs ``env.cost_prior_residuals`` beside it, with
    ``network.barrier_margins`` reads ``env.cost_clearance_features``; an env with
    ``action_limit_residuals`` gets its actuator-limit barrier as a fixed part of the cost)."""
    dtype = jnp.asarray(env.initial_states()).dtype
    net = config.network
    features = None
    if net.features == "env":
        name = "cost_residuals" if net.form == "weighted" else "cost_features"
        features = _env_part(env, name, f"network.features='env' (form {net.form!r})")
    limits = getattr(env, "action_limit_residuals", None)
    goal = None
    if net.form == "neural":
        goal_state = _env_part(
            env, "cost_goal_state", "network.form='neural' (the state where the cost is zero)"
        )
        goal = tuple(float(v) for v in np.asarray(goal_state()))  # hashable
    prior = None
    if net.prior_residuals:
        prior = _env_part(
            env,
            "cost_prior_residuals",
            "network.prior_residuals=True (the residuals weighed beside the network)",
        )
    mirror = None
    if net.mirror:
        mirror = _env_tuple(
            env,
            "cost_feature_mirror",
            "network.mirror=True (the features' signs under the task's reflection)",
            float,
        )
    clearance = None
    if net.barrier_margins:
        clearance = _env_tuple(
            env,
            "cost_clearance_features",
            "network.barrier_margins (the features that read the clearance, the barrier's input)",
            int,
        )
    return CostNetwork(
        config.network,
        env.dX,
        env.dU,
        param_dtype=dtype,
        feature_map=features,
        action_limits=limits,
        goal_state=goal,
        prior_map=prior,
        feature_mirror=mirror,
        clearance_features=clearance,
    )


def _env_part(env: Env, name: str, needed_for: str):
    """``env.<name>``, or a ValueError naming the env, the missing part and the option that
    needs it."""
    if not hasattr(env, name):
        raise ValueError(f"env {env.name!r} has no {name} for {needed_for}")
    return getattr(env, name)


def _env_tuple(env: Env, name: str, needed_for: str, cast) -> tuple:
    """:func:`_env_part`'s sequence as a tuple of ``cast`` values (hashable, for the network's
    static fields)."""
    return tuple(cast(v) for v in _env_part(env, name, needed_for))


def became_non_finite(old, new) -> Array:
    """Whether any float value of the pytree ``new`` is non-finite where ``old``'s is finite
    (scalar bool). The leaves are compared as one concatenated vector: one check for the whole
    state rather than a few compiled kernels per leaf (hundreds of leaves)."""
    pairs = [
        (jnp.ravel(a), jnp.ravel(b))
        for a, b in zip(jax.tree.leaves(old), jax.tree.leaves(new), strict=True)
        if jnp.issubdtype(b.dtype, jnp.inexact)
    ]
    if not pairs:
        return jnp.zeros((), bool)
    dtype = jnp.result_type(*(b.dtype for _, b in pairs))
    old_v = jnp.concatenate([a.astype(dtype) for a, _ in pairs])
    new_v = jnp.concatenate([b.astype(dtype) for _, b in pairs])
    return jnp.any(jnp.isfinite(old_v) & ~jnp.isfinite(new_v))


def _make_optimiser(config: GCLConfig, learning_rate: Array) -> optax.GradientTransformation:
    """Clipped AdamW on ``params.net`` with a traced learning rate (kept in the optimiser state)."""

    chain = lambda learning_rate: cost_optimiser(config, learning_rate)
    return optax.inject_hyperparams(chain)(learning_rate=learning_rate)


def make_train(config: RGCLConfig, env: Env) -> RGCL:
    """Set up rGCL on ``env``; see the module docstring and :class:`RGCL`."""
    gps_config = dataclasses.replace(config.gps, gauss_newton=True)
    sim = Simulator(env)
    phases = make_gps_phases(gps_config, env, true_cost=env.expert_cost, sim=sim)
    network = make_network(config, env)
    learner = make_cost_learner(network, config.gcl)
    X0 = jnp.asarray(env.initial_states())
    dtype = X0.dtype
    C, T, dX, dU = X0.shape[0], env.horizon, env.dX, env.dU
    N = gps_config.num_samples
    G = config.gps_per_iteration
    gcl_cfg = config.gcl
    settings = config.policy
    policy_phases = None
    if settings is not None:
        policy_phases = make_policy_phases(
            settings, gps_config, env, true_cost=env.expert_cost, sim=sim
        )
        draw_policy_samples, simulate_policy_samples = make_policy_sampling(
            phases, policy_phases, settings, N
        )
    # v2 pre-trains the cost in its first update, on the samples of the initial controllers that
    # update stores (the same data as a separate pass before the loop, without a second copy of
    # the simulator and of the cost update in the program); v1 runs GPS on the pre-trained cost
    # before its first update, so it pre-trains in ``init``.
    pretrain = config.pretrain and gcl_cfg.pretrain_steps > 0
    pretrain_in_update = pretrain and config.pretrain_with_samples and config.schedule == "v2"

    def default_hparams() -> RGCLHyperparams:
        return RGCLHyperparams(
            kl_step=jnp.asarray(gps_config.kl_step, dtype),
            init_var=jnp.asarray(gps_config.init_var, dtype),
            cost_lr=jnp.asarray(gcl_cfg.learning_rate, dtype),
        )

    def residual(params: CostParams):
        return network.bind_residual(params)

    def expand_both(first: CostParams, second: CostParams, samples: GPSSamples):
        """The expansions [C] of two costs about the samples, as one batched expansion."""
        both = jax.tree.map(lambda a, b: jnp.stack([a, b]), first, second)
        quads = jax.vmap(lambda p: phases.expand(residual(p), samples))(both)
        return jax.tree.map(lambda q: q[0], quads), jax.tree.map(lambda q: q[1], quads)

    def window(demos: DemoBatch, per_step=None, X=None, U=None):
        """The first T_d steps (the demos' horizon) of per-step fields [C, T, ...] (controllers,
        dynamics), X [C, N, T+1, dX] and U [C, N, T, dU]; see "Training past the demos' window"
        in the module docstring."""
        Td = demos.U.shape[-2]
        if Td > T:
            raise ValueError(
                f"rGCL: the demos have {Td} steps, more than the env's horizon {T}; crop the "
                "demos or lengthen the env's horizon"
            )
        head = None if per_step is None else jax.tree.map(lambda a: a[:, :Td], per_step)
        return (
            head,
            None if X is None else X[..., : Td + 1, :],
            None if U is None else U[..., :Td, :],
        )

    def store(buffer: SampleBuffer, demos: DemoBatch, proposal, X: Array, U: Array):
        """Add each condition's samples (their window) and their proposal to the buffer."""
        return jax.vmap(buffer_add)(buffer, *window(demos, proposal, X, U))

    def learned_cost(params: CostParams, X: Array, U: Array) -> Array:
        """Mean learned trajectory cost of trajectories X: [C, N, T+1, dX] per condition: [C]."""
        per_traj = jax.vmap(jax.vmap(network.trajectory_cost, (None, 0, 0)), (None, 0, 0))
        return per_traj(params, X, U).mean(axis=-1)

    def window_cost(params: CostParams, demos: DemoBatch, samples: GPSSamples) -> Array:
        """The samples' mean learned cost over the demos' window, per condition: [C]."""
        _, X, U = window(demos, X=samples.X, U=samples.U)
        return learned_cost(params, X, U)

    def demo_likelihood(controller: LinearGaussianController, demos: DemoBatch) -> Array:
        """The demos' mean action log-likelihood under controllers [C, T, ...]: [C]."""
        controller, _, _ = window(demos, controller)
        return jax.vmap(demo_log_likelihood)(controller, demos.X, demos.U)

    def calibrate(params: CostParams, demos: DemoBatch, updates: Array | int) -> CostParams:
        """Set ρ (``config.temperature``) after ``updates`` cost updates: the demos' own action
        entropy for the MaxEnt controller of the cost about the demos, one ρ for all conditions
        (scaled by the ramp's fraction)."""
        if config.temperature == "likelihood":
            return params
        if demos.dynamics is None:
            raise ValueError(
                "temperature='demos' needs the dynamics about the demos: build the DemoBatch "
                "with demo_batch(..., env=env)"
            )
        raw = network.bind_residual(untempered(params))
        target = jax.vmap(controller_entropy)(demos.controller)
        rho = jax.vmap(lambda dyn, X, U, H: calibrated_log_temperature(raw, dyn, X, U, H))(
            demos.dynamics, demos.X, demos.U, target
        )
        done = jnp.asarray(updates, dtype) - config.temperature_start
        if config.temperature_ramp == 0:
            fraction = (done >= 0).astype(dtype)
        else:
            fraction = jnp.clip(done / config.temperature_ramp, 0.0, 1.0)
        return params.replace(log_temperature=(fraction * rho.mean()).astype(dtype))

    # ---- cost update -------------------------------------------------------------------------

    def weighted_sets(
        buffer: SampleBuffer,
        demos: DemoBatch,
        key: PRNGKey,
        samples: GPSSamples | None = None,
        sample_ctrl: LinearGaussianController | None = None,
    ) -> tuple[WeightedSamples, WeightedSamples]:
        """(samples [C, S], demos [C, N]) with their log proposal densities (and the demos'
        tails)."""
        if config.sample_source == "model" and samples is not None:
            sample_ctrl, _, _ = window(demos, sample_ctrl)
            dynamics, _, _ = window(demos, samples.dynamics)
            samples_w, demos_w = jax.vmap(model_weighted_samples, in_axes=(0, 0, 0, 0, 0, 0, None))(
                jax.random.split(key, C),
                dynamics,
                sample_ctrl,
                samples.x0,
                demos.X,
                demos.U,
                config.model_samples,
            )
        else:
            samples_w, demos_w = jax.vmap(fusion_weighted_samples, in_axes=(0, 0, 0, 0, None))(
                buffer, demos.controller, demos.X, demos.U, gcl_cfg
            )
        return samples_w, demos_w.replace(tail=demos.tail)

    def optimise(cost: CostState, key: PRNGKey, demos_w, samples_w, n_steps, max_steps=None):
        """``n_steps`` minibatch Adam steps (``n_steps`` may be traced, up to ``max_steps``);
        returns (CostState, GCLMetrics averaged over the steps). Step ``i`` draws its minibatches
        with the ``i``-th of ``split(key, max_steps)``."""
        optimiser = _make_optimiser(gcl_cfg, jnp.zeros((), dtype))  # lr read from opt_state
        max_steps = n_steps if max_steps is None else max_steps

        def step(cost: CostState, key: PRNGKey):
            key_demo, key_samp = jax.random.split(key)
            pick = jax.vmap(minibatch, in_axes=(0, 0, None))
            d = pick(jax.random.split(key_demo, C), demos_w, gcl_cfg.demo_batch)
            s = pick(jax.random.split(key_samp, C), samples_w, gcl_cfg.sample_batch)

            def loss(net):
                return learner.loss(cost.params.replace(net=net), d, s)

            grads, metrics = jax.grad(loss, has_aux=True)(cost.params.net)
            updates, opt_state = optimiser.update(grads, cost.opt_state, cost.params.net)
            net = optax.apply_updates(cost.params.net, updates)
            new = cost.replace(
                params=cost.params.replace(net=net), opt_state=opt_state, step=cost.step + 1
            )
            return new, metrics.replace(grad_norm=optax.tree.norm(grads))

        zero = jnp.zeros((), dtype)
        zeros = GCLMetrics(*(zero for _ in dataclasses.fields(GCLMetrics)))
        if max_steps == 0:
            return cost, zeros

        keys = jax.random.split(key, max_steps)

        def body(i, carry):
            cost, total = carry
            cost, metrics = step(cost, keys[i])
            return cost, jax.tree.map(jnp.add, total, metrics)

        cost, total = lax.fori_loop(0, n_steps, body, (cost, zeros))
        count = jnp.maximum(jnp.asarray(n_steps, dtype), 1.0)
        return cost, jax.tree.map(lambda m: m / count, total)

    # ---- init (with pre-training) --------------------------------------------------------------

    def split_key(key: PRNGKey) -> tuple[PRNGKey, PRNGKey]:
        key_init, key_loop = jax.random.split(key)
        return key_init, key_loop

    def init(key: PRNGKey, demos: DemoBatch, hparams: RGCLHyperparams | None = None) -> RGCLState:
        hp = default_hparams() if hparams is None else hparams
        key_gps, key_net, key_samples, key_pretrain = jax.random.split(key, 4)
        start = None
        if config.initial_controller == "demos":
            start = with_mean_variance(demos.controller, hp.init_var)
        gps_hp = GPSHyperparams(kl_step=hp.kl_step, init_var=hp.init_var)
        gps = phases.init(key_gps, gps_hp, controller=start)
        params = network.init(key_net)
        params = params.replace(norm=network.fit_normaliser(demos.X))
        optimiser = _make_optimiser(gcl_cfg, hp.cost_lr)
        cost = CostState(
            params=params,
            opt_state=optimiser.init(params.net),
            step=jnp.zeros((), jnp.int32),
            prev_params=params,
        )
        Kc = config.buffer_controllers
        empty = init_buffer(N * Kc, Kc, demos.U.shape[-2], dX, dU, dtype)
        buffer = jax.tree.map(lambda a: jnp.broadcast_to(a, (C, *a.shape)), empty)
        if config.zero_controller_samples:
            key_zero, key_samples = jax.random.split(key_samples)
            zero = phases.init(key_zero, gps_hp)
            sims = phases.simulate(sim, phases.draw(zero, key_zero), jacobians=False)
            buffer = store(buffer, demos, zero.controller, sims.X[:, :-1], sims.U[:, :-1])
        if pretrain and not pretrain_in_update:
            pre_buffer = buffer
            if config.pretrain_with_samples:
                # The initial controller's samples (no dynamics fit needed here).
                request = phases.draw(gps, key_samples)
                sims = phases.simulate(sim, request, jacobians=False)
                X, U = sims.X[:, :-1], sims.U[:, :-1]
                pre_buffer = store(buffer, demos, gps.controller, X, U)
            samples_w, demos_w = weighted_sets(pre_buffer, demos, key_samples)
            cost, _ = optimise(cost, key_pretrain, demos_w, samples_w, gcl_cfg.pretrain_steps)
        if not pretrain_in_update:
            params = calibrate(cost.params, demos, 0)
            cost = cost.replace(params=params, prev_params=params)
        policy = None
        if policy_phases is not None:
            # The observation normaliser comes from what the demonstrator's sensors would show.
            key_policy, key_obs = jax.random.split(jax.random.fold_in(key, 1))
            keys = policy_phases.observation_keys(key_obs, demos.X.shape[:-1])
            policy = policy_phases.init(key_policy, policy_phases.observe(sim, demos.X, keys))
        return RGCLState(
            gps=gps,
            cost=cost,
            buffer=buffer,
            iteration=jnp.zeros((), jnp.int32),
            step=jnp.zeros((), jnp.int32),
            policy=policy,
        )

    # ---- one rGCL iteration ------------------------------------------------------------------

    def cap_step(state: RGCLState, step_mult: Array) -> Array:
        if config.late_max_step_mult is None or config.late_iterations <= 0:
            return step_mult
        late = state.iteration >= config.iterations - config.late_iterations
        return jnp.where(late, jnp.minimum(step_mult, config.late_max_step_mult), step_mult)

    def cost_step(state: RGCLState, cost: CostState, key, demos, samples, sample_ctrl, buffer):
        """The cost update (or none on frozen iterations)."""
        key_sets, key_opt = jax.random.split(key)
        samples_w, demos_w = weighted_sets(buffer, demos, key_sets, samples, sample_ctrl)
        n_steps, most = gcl_cfg.n_steps, gcl_cfg.n_steps
        if pretrain_in_update:  # the first update pre-trains too
            most = gcl_cfg.n_steps + gcl_cfg.pretrain_steps
            n_steps = jnp.where(state.iteration == 0, most, gcl_cfg.n_steps)
        new, metrics = optimise(cost, key_opt, demos_w, samples_w, n_steps, most)
        params = calibrate(new.params, demos, state.iteration + 1)
        new = new.replace(params=params, prev_params=cost.params)
        update = state.iteration < config.iterations - config.freeze_last
        # A frozen iteration leaves the cost as it is: the controllers' cost is then the current.
        kept = cost.replace(prev_params=cost.params)
        new = jax.tree.map(lambda a, b: jnp.where(update, a, b), new, kept)
        metrics = jax.tree.map(lambda m: jnp.where(update, m, 0.0), metrics)
        return new, metrics, update

    # ---- the global policy's part of a GPS iteration (no-ops without a policy) ----------------

    def draw_samples(gps: GPSState, policy, key: PRNGKey, key_obs: PRNGKey):
        """What one GPS iteration asks the simulator for (``key_obs``: the sensor noise of the
        policy's observations at the samples)."""
        if policy_phases is None:
            return phases.draw(gps, key)
        return draw_policy_samples(gps, policy, key, key_obs)

    def simulate_samples(sim: Simulator, request):
        if policy_phases is None:
            return phases.simulate(sim, request)
        return simulate_policy_samples(sim, request)

    def fit_samples(gps: GPSState, policy, sims):
        """(samples with fitted dynamics, the KL anchor or None, the samples' proposal)."""
        if policy_phases is None:
            return phases.fit(sims), None, gps.controller
        samples = phases.fit_samples(sims.X, sims.U, sims.mean_X, sims.A, sims.B)
        anchor = policy_phases.linearise(policy, sims.O_clean, sims.J_obs, sims.X)
        return samples, anchor, anchor if settings.sample_on_policy else gps.controller

    def adapt(state: RGCLState, gps: GPSState, samples, quad, anchor) -> Array:
        rule = "classic" if anchor is None else settings.step_rule
        step = phases.adapt_step(gps, samples, quad, current=anchor, rule=rule)
        return cap_step(state, step)

    def s_step(policy, key: PRNGKey, samples: GPSSamples, gps: GPSState, params, sims):
        """The S-step on the policy's observations at the samples; a diverged condition is
        judged by its samples' learned cost (``params``, the cost the controllers were just
        optimised for) over the whole horizon. Returns the policy and its metrics (those of the
        policy in effect during the iteration, from the simulator's rollouts)."""
        if policy_phases is None:
            return None, None
        _, key_fit = jax.random.split(key)
        judged = settings.outlier_cost_ratio is not None
        cost = learned_cost(params, samples.X, samples.U) if judged else None
        policy, s_metrics = policy_phases.s_step(
            policy, key_fit, samples.X, sims.O, gps.controller, cost=cost
        )
        return policy, policy_phases.metrics(sims.policy_mean, s_metrics)

    def iteration_keys(state: RGCLState, key_loop: PRNGKey):
        """(key_outer, key_cost, key_policy, key_obs) of the iteration ``state.step``."""
        key = jax.random.fold_in(key_loop, state.step)
        key_outer, key_cost, key_policy = jax.random.split(key, 3)
        key_obs, _ = jax.random.split(key_policy)
        return key_outer, key_cost, key_policy, key_obs

    def draw_v2(state: RGCLState, key_loop: PRNGKey):
        key_outer, _, _, key_obs = iteration_keys(state, key_loop)
        return draw_samples(state.gps, state.policy, key_outer, key_obs)

    def update_v2(state: RGCLState, key_loop: PRNGKey, demos: DemoBatch, sims):
        _, key_cost, key_policy, _ = iteration_keys(state, key_loop)
        gps = state.gps
        samples, anchor, proposal = fit_samples(gps, state.policy, sims)
        buffer = store(state.buffer, demos, proposal, samples.X, samples.U)
        cost, gcl_metrics, updated = cost_step(
            state, state.cost, key_cost, demos, samples, proposal, buffer
        )
        # The step is judged with the cost the current controller was optimised for, the C-step
        # optimises the updated one: both expanded about the samples in one batched call.
        quad_prev, quad = expand_both(state.cost.params, cost.params, samples)
        step_mult = adapt(state, gps, samples, quad_prev, anchor)
        gps, gps_metrics = phases.inner(gps, samples, quad, step_mult, anchor=anchor)
        policy, policy_metrics = s_step(state.policy, key_policy, samples, gps, cost.params, sims)
        metrics = RGCLMetrics(
            gps=jax.tree.map(lambda a: a[None], gps_metrics),
            learned_cost=window_cost(cost.params, demos, samples)[None],
            demo_learned_cost=learned_cost(cost.params, demos.X, demos.U),
            demo_log_likelihood=demo_likelihood(gps.controller, demos)[None],
            log_temperature=cost.params.log_temperature,
            sample_X=samples.X[None],
            gcl=gcl_metrics,
            cost_updated=updated,
            rolled_back=jnp.zeros((), bool),
            policy=jax.tree.map(lambda a: a[None], policy_metrics),
            policy_params=None if policy is None else policy.params,
        )
        new = state.replace(gps=gps, cost=cost, buffer=buffer, policy=policy)
        return guard(state, new, metrics)

    # v1's iteration in parts, so that a host loop can run its simulator staged
    # (:class:`diffgcl.algorithms.staged.StagedV1Loop`) and ``iteration_v1`` traces the same
    # functions into one program: begin -> G x (draw_v1 -> simulate -> gps_v1) -> finish_v1.

    def begin_v1(state: RGCLState, key_loop: PRNGKey):
        """The carry of v1's GPS phase and its keys: (carry, [G, 2] GPS keys, the cost key)."""
        key = jax.random.fold_in(key_loop, state.step)
        key_gps, key_cost = jax.random.split(key)
        empty = jax.tree.map(
            lambda s: jnp.zeros(s.shape, s.dtype),
            jax.eval_shape(
                lambda: phases.fit(phases.simulate(sim, phases.draw(state.gps, key_gps)))
            ),
        )
        # Batched from the start under vmap (diffgcl.tracing): ``empty`` is not, until the body.
        carry = batched_like(
            (state.gps, state.policy, state.buffer, empty, state.gps.controller), key
        )
        return carry, jax.random.split(key_gps, G), key_cost

    def draw_v1(carry, key: PRNGKey):
        gps, policy = carry[0], carry[1]
        key_sample, key_policy = jax.random.split(key)
        key_obs, _ = jax.random.split(key_policy)
        return draw_samples(gps, policy, key_sample, key_obs)

    def gps_v1(state: RGCLState, carry, key: PRNGKey, first, demos: DemoBatch, sims):
        """One GPS iteration of v1's phase on the samples ``sims`` -> (carry, its outputs)."""
        gps, policy, buffer, _, _ = carry
        params = state.cost.params
        _, key_policy = jax.random.split(key)
        samples, anchor, proposal = fit_samples(gps, policy, sims)
        # Each step is judged under one cost: the one its controller was optimised for (J_prev
        # and J_pred were expanded with it) — on the first GPS iteration after a cost update,
        # the cost before that update. The GCL objective does not fix the cost's constant, so
        # mixing two costs here would let the cost's drift set the step.
        judged = jax.tree.map(
            lambda old, new: jnp.where(first, old, new), state.cost.prev_params, params
        )
        quad_judged, quad = expand_both(judged, params, samples)
        step_mult = adapt(state, gps, samples, quad_judged, anchor)
        buffer = store(buffer, demos, proposal, samples.X, samples.U)
        new_gps, m = phases.inner(gps, samples, quad, step_mult, anchor=anchor)
        policy, pm = s_step(policy, key_policy, samples, new_gps, params, sims)
        lc = window_cost(params, demos, samples)
        ll = demo_likelihood(new_gps.controller, demos)
        out = (m, lc, ll, samples.X, pm)
        return (new_gps, policy, buffer, samples, proposal), out

    def finish_v1(state: RGCLState, carry, outs, key_cost: PRNGKey, demos: DemoBatch):
        """The cost update after v1's GPS phase (``outs``: its outputs stacked [G]) and the
        iteration's metrics, counted and guarded."""
        gps, policy, buffer, samples, proposal = carry
        gps_metrics, lc, ll, sample_X, pm = outs
        # The model variant generates from the last fitted model and the controller it sampled.
        cost, gcl_metrics, updated = cost_step(
            state, state.cost, key_cost, demos, samples, proposal, buffer
        )
        metrics = RGCLMetrics(
            gps=gps_metrics,
            learned_cost=lc,
            demo_learned_cost=learned_cost(cost.params, demos.X, demos.U),
            demo_log_likelihood=ll,
            log_temperature=cost.params.log_temperature,
            sample_X=sample_X,
            gcl=gcl_metrics,
            cost_updated=updated,
            rolled_back=jnp.zeros((), bool),
            policy=pm,
            policy_params=None if policy is None else policy.params,
        )
        new = state.replace(gps=gps, cost=cost, buffer=buffer, policy=policy)
        return guard(state, new, metrics)

    def iteration_v1(state: RGCLState, key_loop: PRNGKey, demos: DemoBatch):
        carry, keys, key_cost = begin_v1(state, key_loop)

        def gps_iteration(carry, inputs):
            key, first = inputs
            sims = simulate_samples(sim, draw_v1(carry, key))
            return gps_v1(state, carry, key, first, demos, sims)

        carry, outs = lax.scan(gps_iteration, carry, (keys, jnp.arange(G) == 0))
        return finish_v1(state, carry, outs, key_cost, demos)

    def guard(state: RGCLState, new: RGCLState, metrics: RGCLMetrics):
        """Count the iteration; with the NaN guard, keep ``state`` when the iteration made a
        finite value non-finite (a swept hyperparameter that is itself not finite does not
        count)."""
        new = new.replace(iteration=state.iteration + 1, step=state.step + 1)
        if not config.nan_guard:
            return new, metrics
        finite = ~jnp.any(became_non_finite(state, new))
        kept = jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, state)
        kept = kept.replace(step=state.step + 1)
        return kept, metrics.replace(rolled_back=~finite)

    def guarded(state: RGCLState, key_loop: PRNGKey, demos: DemoBatch):
        if config.schedule == "v2":
            return update_v2(
                state, key_loop, demos, simulate_samples(sim, draw_v2(state, key_loop))
            )
        return iteration_v1(state, key_loop, demos)

    def run(state: RGCLState, key_loop: PRNGKey, demos: DemoBatch, n: int):
        return lax.scan(lambda s, _: guarded(s, key_loop, demos), state, None, length=n)

    def train(key: PRNGKey, demos: DemoBatch, hparams: RGCLHyperparams | None = None):
        key_init, key_loop = split_key(key)
        state = batched_like(init(key_init, demos, hparams), key)  # diffgcl.tracing
        return run(state, key_loop, demos, config.iterations)

    v2 = config.schedule == "v2"
    return RGCL(
        train=train,
        split_key=split_key,
        init=init,
        run=run,
        default_hparams=default_hparams,
        network=network,
        policy_phases=policy_phases,
        draw=draw_v2 if v2 else None,
        simulate=simulate_samples if v2 else None,
        update=update_v2 if v2 else None,
        iterations=config.iterations,
        v1=None if v2 else V1Parts(begin_v1, draw_v1, simulate_samples, gps_v1, finish_v1, G),
    )


# ---- evaluation (pure, one run) -----------------------------------------------------------------


def policy_learned_costs(rgcl: RGCL, env: Env, cost_params: CostParams, policy_params) -> Array:
    """[I, C]: the learned trajectory cost, under ``cost_params``, of the noise-free rollout of
    each iteration's global policy (``policy_params`` with a leading [I] axis, e.g.
    ``RGCLMetrics.policy_params``) from the env's conditions. Lowest = the policy that does best
    by the cost the run learned, judged without the true cost (``experiments/usv_iterations.py``
    sets it beside each iteration's held-out figures)."""
    from diffgcl.eval.policy import policy_rollouts

    if rgcl.policy_phases is None:
        raise ValueError("policy_learned_costs: this rGCL run has no global policy")
    policy = rgcl.policy_phases.policy
    x0 = jnp.asarray(env.initial_states())
    per_traj = jax.vmap(rgcl.network.trajectory_cost, (None, 0, 0))

    def one(params):
        traj = policy_rollouts(env, policy, params, x0)
        return per_traj(cost_params, traj.X, traj.U)

    return jax.lax.map(one, policy_params)


def final_rollouts(env: Env, controller: LinearGaussianController) -> Array:
    """Noise-free rollouts of controllers (fields [C, T, ...]) from the env's conditions:
    X [C, T+1, dX]."""
    X0 = jnp.asarray(env.initial_states())
    T = controller.K.shape[-3]

    def one(ctrl, x0):
        return rollout_controller(env, ctrl, x0, jnp.zeros((T, env.dU), x0.dtype)).X

    return jax.vmap(one)(controller, X0)


@dataclass(frozen=True, eq=False)
class Reoptimise:
    """The re-optimisation check of :func:`make_reoptimise`. Called as ``reopt(key, params,
    hparams=None) -> (GPSState, GPSMetrics [iterations, C])`` (one traced program; jit it as any
    function); its parts for a staged loop (:func:`reoptimise_seeds`): init(key, hparams=None),
    draw(state, key), simulate(sim, request), update(state, params, sims)."""

    train: Callable[..., tuple[GPSState, GPSMetrics]]
    init: Callable[..., GPSState]
    draw: Callable
    simulate: Callable
    update: Callable
    iterations: int

    def __call__(self, key: PRNGKey, params: CostParams, hparams=None):
        return self.train(key, params, hparams)


def make_reoptimise(config: RGCLConfig, env: Env, network: CostNetwork) -> Reoptimise:
    """A fresh initial controller optimised by GPS on the frozen learned cost ``params``
    (Gauss–Newton), the metrics reporting the true cost and success (of the controller before
    each C-step; the final controllers are judged by their rollouts, :func:`reoptimise_seeds`).
    ``config.reopt_iterations`` iterations."""
    gps_config = dataclasses.replace(config.gps, gauss_newton=True)
    sim = Simulator(env)
    phases = make_gps_phases(gps_config, env, true_cost=env.expert_cost, sim=sim)

    def init(key: PRNGKey, hparams: RGCLHyperparams | None = None) -> GPSState:
        gps_hp = None if hparams is None else GPSHyperparams(hparams.kl_step, hparams.init_var)
        return phases.init(key, gps_hp)

    def update(state: GPSState, params: CostParams, sims) -> tuple[GPSState, GPSMetrics]:
        samples = phases.fit(sims)
        quad = phases.expand(network.bind_residual(params), samples)
        return phases.inner(state, samples, quad, phases.adapt_step(state, samples, quad))

    def train(key: PRNGKey, params: CostParams, hparams: RGCLHyperparams | None = None):
        key_init, key_iter = jax.random.split(key)

        def iteration(state: GPSState, key: PRNGKey):
            return update(state, params, phases.simulate(sim, phases.draw(state, key)))

        state = init(key_init, hparams)
        return lax.scan(iteration, state, jax.random.split(key_iter, config.reopt_iterations))

    return Reoptimise(
        train=train,
        init=init,
        draw=phases.draw,
        simulate=phases.simulate,
        update=update,
        iterations=config.reopt_iterations,
    )


def reoptimise_seeds(config: RGCLConfig, env: Env, network: CostNetwork, params, keys):
    """Host side: the re-optimisation check for learned costs ``params`` (leading [S] axis) with
    ``keys: [S, 2]``, as a staged loop (:mod:`diffgcl.algorithms.staged`). Returns (GPSState,
    GPSMetrics [S, iterations, C], final_success [S, C]: the final controllers' noise-free
    rollouts succeed)."""
    from diffgcl.algorithms.staged import run_gps_seeds

    reopt = make_reoptimise(config, env, network)
    params = jax.tree.map(jnp.asarray, params)
    state, metrics, X = run_gps_seeds(
        reopt, keys, reopt.iterations, env, update_args=(params,), update_axes=(0,)
    )
    success = np.asarray(jax.vmap(jax.vmap(env.success))(jnp.asarray(X)))
    return state, metrics, success


def demo_batch(demos, conditions: int, dtype=None, env: Env | None = None) -> DemoBatch:
    """Host-side: a :class:`DemoBatch` [C, N, ...] from a :class:`diffgcl.data.demos.DemoSet`,
    grouping episodes by their ``condition`` metadata (all in condition 0 when absent), with the
    demos' fitted controller and, given the ``env``, its dynamics linearised about the demos (by
    autodiff, :func:`diffgcl.dynamics.autodiff.fit_dynamics`); every condition must have the same
    number of demos."""
    cond = np.array(
        [int(e.get("condition", 0)) for e in demos.episodes]
        if demos.episodes
        else [0] * demos.num_episodes
    )
    groups = [np.flatnonzero(cond == c) for c in range(conditions)]
    sizes = {len(g) for g in groups}
    if len(sizes) != 1 or 0 in sizes:
        raise ValueError(
            f"demos: need the same positive number of demos per condition; got "
            f"{[len(g) for g in groups]} for {conditions} conditions"
        )
    dtype = dtype or jnp.zeros(()).dtype
    X = jnp.asarray(np.stack([demos.X[g] for g in groups]), dtype)
    U = jnp.asarray(np.stack([demos.U[g] for g in groups]), dtype)
    controller = jax.jit(jax.vmap(fit_demo_controller))(X, U)
    dynamics = None if env is None else demo_dynamics(env, X, U)
    return DemoBatch(X=X, U=U, controller=controller, dynamics=dynamics)


def demo_dynamics(env: Env, X: Array, U: Array) -> LinearDynamics:
    """Host side: the env's dynamics linearised about the demos of each condition, X: [C, N,
    T+1, dX], U: [C, N, T, dU] -> LinearDynamics [C, T, ...] (the Jacobians by the env's staged
    simulator, shared with the training's programs)."""
    from diffgcl.algorithms.staged import staged_simulator
    from diffgcl.dynamics.autodiff import dynamics_from_jacobians

    A, B = staged_simulator(env).jacobians(X.mean(axis=1), U.mean(axis=1))
    return jax.jit(jax.vmap(dynamics_from_jacobians))(A, B, X, U)
