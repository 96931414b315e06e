"""Trajectory-optimisation GPS with a known cost (GPS ``AlgorithmTrajOpt``; Levine et al. 2016).

One iteration, for every condition at once:

1. sample N trajectories with the current linear-Gaussian controller (time-smoothed noise), and
   its noise-free rollout (the success metric), in one batched call of the simulator;
2. fit linear-Gaussian dynamics at the samples (autodiff through the simulator, DESIGN §3, or
   GPS's regression with a prior);
3. expand the cost around the samples (averaged, GPS-style) and move it to absolute coordinates;
4. adapt the KL step from the three Laplace estimates (:mod:`diffgcl.control.step`; from the
   second iteration on);
5. C-step: the KL-constrained LQR with ``ε = kl_step · step_mult · T`` anchored at the controller
   that produced the samples (:func:`diffgcl.control.dual.c_step`).

:func:`make_gps` does the Python-side setup and returns pure ``init(key) -> state``,
``iteration(state, key) -> (state, metrics)`` and ``train(key, hparams=None) -> (state,
metrics)``, the last a ``lax.scan`` over iterations. An iteration is ``update(state,
simulate(sim, draw(state, key)))``: ``draw`` says what to simulate (controllers, starts, noise),
``simulate`` is the only part that runs the env (:class:`diffgcl.sim.simulator.Simulator`) and
``update`` is pure maths on its results — so that a host loop can run the simulator as programs
compiled once per env and shared by every algorithm (:mod:`diffgcl.algorithms.staged`), while
``train`` traces all three into one program that holds the simulator once.
``jax.jit(jax.vmap(train))`` runs a sweep over seeds, and vmapping over a
:class:`GPSHyperparams` too sweeps kl_step / init_var. The cost is a
:data:`diffgcl.types.CostFn` closed over by these functions (or a residual function with
``gauss_newton=True``); the reported "true cost" may be a different function.

:func:`make_gps_phases` exposes the same iteration split in two, for algorithms whose cost changes
between them (rGCL, :mod:`diffgcl.algorithms.rgcl`): the *outer* part (steps 1–2: sample and fit
dynamics: ``draw → simulate → fit``, or ``outer`` for all three traced in place) and the *inner*
part (steps 3–5), whose cost expansion and step adaptation take the cost as an argument.
``make_gps``'s iteration is ``outer → expand → adapt_step → inner``.

Metrics describe the controller that drew the iteration's samples: its samples' mean true cost,
the fraction of them that succeed, and whether its noise-free rollout succeeds (``success``) —
the controller *before* the iteration's C-step, simulated with its samples. The controller a run
ends with is judged by its own rollout afterwards (``final_success`` of
:func:`diffgcl.algorithms.gps_runner.run_seeds`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax import lax

from diffgcl.control.dual import c_step
from diffgcl.control.ilqr import zero_expansion
from diffgcl.control.init import init_controller
from diffgcl.control.lqr import controller_entropy, forward_pass
from diffgcl.control.step import adapt_step_mult, laplace_cost
from diffgcl.costs.expansion import about_origin, expand_cost_samples, trajectory_cost
from diffgcl.sim.simulator import Simulator
from diffgcl.types import (
    Array,
    CostFn,
    Env,
    InitialStateDistribution,
    LinearDynamics,
    LinearGaussianController,
    PRNGKey,
    QuadraticCost,
)

DYNAMICS_FITS = ("autodiff", "regression")


@dataclass(frozen=True)
class GPSConfig:
    """Static settings of trajectory-optimisation GPS (defaults: GPS's box2d arm example).

    iterations: GPS iterations in ``train``; num_samples: samples per condition and iteration;
    kl_step: base KL step per time step (ε = kl_step·step_mult·T); step_mult bounds and start;
    init_var: initial controller variance (K = 0, k = 0); init_eta: first η guess;
    smooth_sigma: exploration-noise smoothing in steps (None: white noise); dynamics: "autodiff"
    or "regression"; dyn_cov_floor: floor on Σ_dyn; regression_prior_strength: NIW prior weight
    in pseudo-samples; x0_var: floor on the variance of the initial-state Gaussian; maxent: ω = 1
    in the C-step; gauss_newton: the cost is a residual function r with c = ‖r‖²;
    dual_max_iter: trip bound of the η search.
    """

    iterations: int = 10
    num_samples: int = 5
    kl_step: float = 0.2
    min_step_mult: float = 0.01
    max_step_mult: float = 10.0
    init_step_mult: float = 1.0
    init_var: float = 0.1
    init_eta: float = 1.0
    smooth_sigma: float | None = 2.0
    dynamics: str = "autodiff"
    dyn_cov_floor: float = 1e-6
    regression_prior_strength: float = 1.0
    x0_var: float = 1e-6
    maxent: bool = False
    gauss_newton: bool = False
    dual_max_iter: int = 100

    def __post_init__(self):
        if self.dynamics not in DYNAMICS_FITS:
            raise ValueError(
                f"GPSConfig: dynamics {self.dynamics!r}; choose one of {DYNAMICS_FITS}"
            )
        if self.num_samples < 1 or self.iterations < 1:
            raise ValueError("GPSConfig: num_samples and iterations must be positive")


@struct.dataclass
class GPSHyperparams:
    """Continuous hyperparameters that may be traced (swept with vmap): scalars.

    kl_step: base KL step per time step; init_var: initial controller variance. Defaults come
    from :class:`GPSConfig`.
    """

    kl_step: Array
    init_var: Array


@struct.dataclass
class GPSState:
    """GPS state for C conditions (leading axis C on every field but ``iteration``).

    controller: the controller to sample next, fields [C, T, ...]. prev_controller,
    prev_dynamics, prev_cost (about the origin, T+1 entries), prev_x0: what the last iteration
    sampled with and fitted (placeholders before the first iteration). step_mult, eta: [C].
    kl_step: scalar base KL step (from GPSHyperparams). iteration: int32 scalar, iterations done.
    x0: [C, dX] the conditions' start states (an argument of the programs, not a constant in
    them: another task's starts reuse the compiled programs).
    """

    controller: LinearGaussianController
    prev_controller: LinearGaussianController
    prev_dynamics: LinearDynamics
    prev_cost: QuadraticCost
    prev_x0: InitialStateDistribution
    step_mult: Array
    eta: Array
    kl_step: Array
    iteration: Array
    x0: Array


@struct.dataclass
class GPSMetrics:
    """Per-iteration metrics, each [C] (a scan over iterations adds a leading axis).

    cost: mean true cost of this iteration's samples; step_mult: the multiplier used for this
    C-step; epsilon, eta, kl: the η search's target, result and achieved KL; entropy: action
    entropy of the new controller (nats, summed over t); success: the noise-free rollout of the
    controller that drew this iteration's samples succeeds (the controller before this C-step);
    sample_success: fraction of this iteration's samples that succeed;
    c_step_failed / c_step_status / c_step_iterations: the η search's report (dual.STATUS_NAMES).
    """

    cost: Array
    step_mult: Array
    epsilon: Array
    eta: Array
    kl: Array
    entropy: Array
    success: Array
    sample_success: Array
    c_step_failed: Array
    c_step_status: Array
    c_step_iterations: Array


class GPS(NamedTuple):
    """The pure functions returned by :func:`make_gps`: init(key, hparams=None); iteration(state,
    key) -> (state, metrics), which is ``update(state, simulate(sim, draw(state, key)))``;
    train(key, hparams=None) -> (state, metrics [iterations]); phases: the
    :class:`GPSPhases`."""

    init: Callable[..., GPSState]  # (key, hparams=None, controller=None)
    iteration: Callable[[GPSState, PRNGKey], tuple[GPSState, GPSMetrics]]
    train: Callable[..., tuple[GPSState, GPSMetrics]]
    draw: Callable[[GPSState, PRNGKey], SampleRequest]
    simulate: Callable[..., SimulatedSamples]
    update: Callable[[GPSState, SimulatedSamples], tuple[GPSState, GPSMetrics]]
    phases: GPSPhases


@struct.dataclass
class GPSSamples:
    """What GPS's outer loop collected for C conditions (leading axis C on every field).

    X: [C, N, T+1, dX], U: [C, N, T, dU] samples of ``state.controller``; dynamics: fitted
    linear-Gaussian dynamics, fields [C, T, ...]; x0: empirical initial-state Gaussian, mean
    [C, dX], cov [C, dX, dX]; mean_X: [C, T+1, dX] the sampling controller's noise-free rollout.
    """

    X: Array
    U: Array
    dynamics: LinearDynamics
    x0: InitialStateDistribution
    mean_X: Array


@struct.dataclass
class SampleRequest:
    """What GPS asks the simulator for, C conditions: controller (fields [C, T, ...]) rolled out
    from x0: [C, dX] with noise: [C, M, T, dU] (standard normal, time-smoothed; the last of each
    condition's M = N + 1 is zero: the noise-free rollout)."""

    controller: LinearGaussianController
    x0: Array
    noise: Array


@struct.dataclass
class SimulatedSamples:
    """What the simulator returns for a :class:`SampleRequest`: X [C, M, T+1, dX], U [C, M, T,
    dU] (the last of each condition noise-free); A [C, T, dX, dX], B [C, T, dX, dU] the step's
    Jacobians along the mean of the M − 1 noisy samples (None with regression dynamics)."""

    X: Array
    U: Array
    A: Array | None = None
    B: Array | None = None


class GPSPhases(NamedTuple):
    """One GPS iteration in parts (pure; every function handles all C conditions at once).

    init(key, hparams=None, controller=None) -> GPSState (``controller``: initial controllers
    [C, ...], default zero gains); draw(state, key) -> SampleRequest (the current
    controllers, N noisy samples and the noise-free rollout each); simulate(sim, request) ->
    SimulatedSamples (the only part that runs the env: rollouts and, with autodiff dynamics, the
    Jacobians at the samples' mean); fit(simulated) -> GPSSamples (dynamics, start Gaussian);
    outer(state, key) -> GPSSamples (the three in place, the simulator traced in);
    fit_samples(X, U, mean_X, A=None, B=None) -> GPSSamples (the same from given samples
    [C, N, ...], e.g. drawn from a global policy); expand(cost, samples) -> QuadraticCost [C]
    about the origin (the GPS sample-averaged expansion of ``cost``, a residual function when
    ``config.gauss_newton``); adapt_step(state, samples, quad, current=None, rule="classic") ->
    step_mult [C] (from the second iteration on; ``quad`` is the expansion of the cost the step is
    judged with); inner(state, samples, quad, step_mult, anchor=None) -> (GPSState, GPSMetrics)
    (C-step with ε = kl_step·step_mult·T and the metrics); autodiff: the dynamics come from the
    step's Jacobians (else by regression on the samples).

    The KL anchor and the step rule default to trajectory-optimisation GPS: the C-step is bounded
    against the controller that drew the samples, and each condition adapts its own step from
    ``J_prev`` (that controller), ``J_pred`` (the controller the last C-step produced, both under
    the previous dynamics and cost) and ``J_act`` (the current controller under the new ones).
    MDGPS (Montgomery & Levine 2016; :mod:`diffgcl.algorithms.mdgps`) passes the global policy
    linearised at the samples as ``anchor`` and as ``current``, and a shared ``rule``: one step
    size serves all conditions, from their averaged estimates (``"global"``, GPS's) or the
    geometric mean of their own multipliers (``"geometric"``). The state keeps
    the last anchor as ``prev_controller``, so ``J_prev`` is the previous policy linearisation
    there, as in GPS's ``AlgorithmMDGPS``.
    """

    init: Callable[..., GPSState]
    draw: Callable[..., SampleRequest]
    simulate: Callable[..., SimulatedSamples]
    fit: Callable[[SimulatedSamples], GPSSamples]
    outer: Callable[[GPSState, PRNGKey], GPSSamples]
    fit_samples: Callable[..., GPSSamples]
    expand: Callable[[Callable, GPSSamples], QuadraticCost]
    adapt_step: Callable[..., Array]
    inner: Callable[..., tuple[GPSState, GPSMetrics]]
    autodiff: bool


def empirical_x0(X0: Array, var_floor: float) -> InitialStateDistribution:
    """Gaussian over x0 from samples X0: [N, dX]: mean, and the per-dimension variance floored
    (GPS's ``x0sigma`` with ``initial_state_var``)."""
    mean = X0.mean(axis=0)
    var = jnp.maximum(X0.var(axis=0), var_floor)
    return InitialStateDistribution(mean=mean, cov=jnp.diag(var))


def make_gps_phases(
    config: GPSConfig,
    env: Env,
    *,
    true_cost: CostFn | None = None,
    x0: Array | None = None,
    sim: Simulator | None = None,
) -> GPSPhases:
    """Set up the parts of a GPS iteration on ``env`` (see :class:`GPSPhases`).

    x0: conditions [C, dX] (default ``env.initial_states()``; the state carries them, see
    :class:`GPSState`); true_cost: the cost reported in the metrics (default ``env.expert_cost``);
    sim: the simulator ``outer`` traces in (default: the env's fused one).
    """
    from diffgcl.dynamics.autodiff import dynamics_from_jacobians
    from diffgcl.sim.rollout import smooth_noise

    if config.dynamics == "regression":
        from diffgcl.dynamics.regression import fit_dynamics_regression

    sim = Simulator(env) if sim is None else sim
    true_cost = env.expert_cost if true_cost is None else true_cost
    X0 = jnp.asarray(env.initial_states() if x0 is None else x0)
    if X0.ndim != 2 or X0.shape[1] != env.dX:
        raise ValueError(f"make_gps: x0 must be [C, {env.dX}], got {X0.shape}")
    C, T, dX, dU = X0.shape[0], env.horizon, env.dX, env.dU
    N = config.num_samples
    dtype = X0.dtype
    x0_host = np.asarray(X0)

    def default_hparams() -> GPSHyperparams:
        return GPSHyperparams(
            kl_step=jnp.asarray(config.kl_step, dtype), init_var=jnp.asarray(config.init_var, dtype)
        )

    def init(
        key: PRNGKey,
        hparams: GPSHyperparams | None = None,
        controller: LinearGaussianController | None = None,
    ) -> GPSState:
        """``controller``: initial controllers [C, T, ...] (e.g. from iLQR,
        :mod:`diffgcl.algorithms.trajopt`); default K = 0, k = 0, Σ = init_var·I."""
        del key  # the initial controller is deterministic
        hp = default_hparams() if hparams is None else hparams
        if controller is None:
            ctrl = init_controller(T, dX, dU, hp.init_var, dtype=dtype)
            ctrl = jax.tree.map(lambda a: jnp.broadcast_to(a, (C, *a.shape)), ctrl)
        else:
            ctrl = jax.tree.map(lambda a: jnp.asarray(a, dtype), controller)
        zeros = lambda *shape: jnp.zeros((C, *shape), dtype)
        x0_state = jnp.asarray(x0_host, dtype)
        return GPSState(
            controller=ctrl,
            prev_controller=ctrl,
            prev_dynamics=LinearDynamics(
                A=zeros(T, dX, dX), B=zeros(T, dX, dU), c=zeros(T, dX), cov=zeros(T, dX, dX)
            ),
            prev_cost=jax.tree.map(
                lambda a: jnp.broadcast_to(a, (C, *a.shape)), zero_expansion(T, dX, dU, dtype)
            ),
            prev_x0=InitialStateDistribution(mean=x0_state, cov=zeros(dX, dX)),
            step_mult=jnp.full((C,), config.init_step_mult, dtype),
            eta=jnp.full((C,), config.init_eta, dtype),
            kl_step=jnp.asarray(hp.kl_step, dtype),
            iteration=jnp.zeros((), jnp.int32),
            x0=x0_state,
        )

    def sample_noise(key: PRNGKey, n: int) -> Array:
        """[C, n + 1, T, dU]: n smoothed noise sequences per condition and a zero one."""

        def one(key_c):
            keys = jax.random.split(key_c, n)
            return jax.vmap(lambda k: smooth_noise(k, T, dU, config.smooth_sigma))(keys)

        noise = jax.vmap(one)(jax.random.split(key, C))
        return jnp.concatenate([noise, jnp.zeros((C, 1, T, dU), noise.dtype)], axis=1)

    def draw(state: GPSState, key: PRNGKey, n: int | None = None) -> SampleRequest:
        """The controllers' ``n`` (default: N) noisy samples and noise-free rollouts."""
        n = N if n is None else n
        return SampleRequest(controller=state.controller, x0=state.x0, noise=sample_noise(key, n))

    def simulate(
        sim: Simulator, request: SampleRequest, jacobians: bool = True
    ) -> SimulatedSamples:
        """Runs the env: the requested rollouts (any leading batch axes before [C, M]) and, with
        autodiff dynamics and ``jacobians``, the Jacobians at the mean of the noisy ones."""
        M = request.noise.shape[-3]

        def per_rollout(a, trailing: int):
            lead = a.shape[: a.ndim - trailing]
            return jnp.broadcast_to(
                a.reshape(*lead, 1, *a.shape[len(lead) :]), (*lead, M, *a.shape[len(lead) :])
            )

        c = request.controller
        ctrl = c.replace(
            K=per_rollout(c.K, 3),
            k=per_rollout(c.k, 2),
            cov=per_rollout(c.cov, 3),
            chol_cov=per_rollout(c.chol_cov, 3),
            inv_cov=per_rollout(c.inv_cov, 3),
        )
        x0 = jnp.broadcast_to(request.x0[..., None, :], (*request.noise.shape[:-2], dX))
        traj = sim.controller_rollouts(ctrl, x0, request.noise)
        if config.dynamics != "autodiff" or not jacobians:
            return SimulatedSamples(X=traj.X, U=traj.U)
        A, B = sim.jacobians(traj.X[..., :-1, :, :].mean(axis=-3), traj.U[..., :-1, :, :].mean(-3))
        return SimulatedSamples(X=traj.X, U=traj.U, A=A, B=B)

    # The per-condition parts below see ``state`` without the condition axis.
    def fit_one(X: Array, U: Array, mean_X: Array, A, B) -> GPSSamples:
        if config.dynamics == "autodiff":
            if A is None:
                raise ValueError("GPS: autodiff dynamics need the Jacobians at the samples")
            dynamics = dynamics_from_jacobians(A, B, X, U, cov_floor=config.dyn_cov_floor)
        else:
            dynamics = fit_dynamics_regression(
                X,
                U,
                prior_strength=config.regression_prior_strength,
                cov_floor=config.dyn_cov_floor,
            )
        x0 = empirical_x0(X[:, 0], config.x0_var)
        return GPSSamples(X=X, U=U, dynamics=dynamics, x0=x0, mean_X=mean_X)

    def fit_samples(X: Array, U: Array, mean_X: Array, A=None, B=None) -> GPSSamples:
        if A is None:
            return jax.vmap(lambda X, U, m: fit_one(X, U, m, None, None))(X, U, mean_X)
        return jax.vmap(fit_one)(X, U, mean_X, A, B)

    def fit(sims: SimulatedSamples) -> GPSSamples:
        return fit_samples(sims.X[:, :-1], sims.U[:, :-1], sims.X[:, -1], sims.A, sims.B)

    def outer(state: GPSState, key: PRNGKey) -> GPSSamples:
        return fit(simulate(sim, draw(state, key)))

    def expand_one(cost: Callable, samples: GPSSamples) -> QuadraticCost:
        X, U = samples.X, samples.U
        quad = expand_cost_samples(cost, X, U, gauss_newton=config.gauss_newton)
        return about_origin(quad, X.mean(axis=0), U.mean(axis=0))

    def laplace_estimates(
        state: GPSState, samples: GPSSamples, quad: QuadraticCost, current
    ) -> Array:
        """[J_prev, J_pred, J_act] of one condition (GPS ``_stepadjust``)."""
        prev_dyn, prev_cost, prev_x0 = state.prev_dynamics, state.prev_cost, state.prev_x0
        J_prev = laplace_cost(forward_pass(prev_dyn, state.prev_controller, prev_x0), prev_cost)
        J_pred = laplace_cost(forward_pass(prev_dyn, state.controller, prev_x0), prev_cost)
        J_act = laplace_cost(forward_pass(samples.dynamics, current, samples.x0), quad)
        return jnp.stack([J_prev, J_pred, J_act])

    def inner_one(
        state: GPSState,
        samples: GPSSamples,
        quad: QuadraticCost,
        step_mult: Array,
        anchor: LinearGaussianController,
    ) -> tuple[GPSState, GPSMetrics]:
        X, U = samples.X, samples.U
        epsilon = state.kl_step * step_mult * T
        new_ctrl, info = c_step(
            samples.dynamics,
            quad,
            anchor,
            samples.x0,
            epsilon,
            state.eta,
            maxent=config.maxent,
            max_iter=config.dual_max_iter,
        )
        sample_costs = jax.vmap(lambda x, u: trajectory_cost(true_cost, x, u))(X, U)
        metrics = GPSMetrics(
            cost=sample_costs.mean(),
            step_mult=step_mult,
            epsilon=info.epsilon,
            eta=info.eta,
            kl=info.kl,
            entropy=controller_entropy(new_ctrl),
            success=env.success(samples.mean_X),
            sample_success=jax.vmap(env.success)(X).mean(),
            c_step_failed=~info.ok,
            c_step_status=info.status,
            c_step_iterations=info.iterations,
        )
        new_state = state.replace(
            controller=new_ctrl,
            prev_controller=anchor,
            prev_dynamics=samples.dynamics,
            prev_cost=quad,
            prev_x0=samples.x0,
            step_mult=step_mult,
            eta=info.eta,
            iteration=state.iteration + 1,
        )
        return new_state, metrics

    # Every state field has a leading condition axis except the shared iteration counter.
    state_axes = GPSState(
        controller=0,
        prev_controller=0,
        prev_dynamics=0,
        prev_cost=0,
        prev_x0=0,
        step_mult=0,
        eta=0,
        kl_step=None,
        iteration=None,
        x0=0,
    )

    def expand(cost: Callable, samples: GPSSamples) -> QuadraticCost:
        return jax.vmap(expand_one, in_axes=(None, 0))(cost, samples)

    def adapt_step(
        state: GPSState,
        samples: GPSSamples,
        quad: QuadraticCost,
        current: LinearGaussianController | None = None,
        rule: str = "classic",
    ) -> Array:
        """New step_mult [C]; skipped (kept) on the first iteration and where not finite.
        ``current``: the controllers [C] judged by ``J_act`` (default ``state.controller``);
        ``rule``: ``"classic"`` each condition from its own estimates; one step for all
        (MDGPS) from the estimates averaged over the conditions (``"global"``) or from the
        geometric mean of the conditions' multipliers (``"geometric"``;
        :func:`diffgcl.control.step.geometric_step_multiplier`)."""
        current = state.controller if current is None else current
        J = jax.vmap(laplace_estimates, in_axes=(state_axes, 0, 0, 0))(
            state, samples, quad, current
        )  # [C, 3]
        adapted = adapt_step_mult(
            state.step_mult,
            J[:, 0],
            J[:, 1],
            J[:, 2],
            rule=rule,
            min_step_mult=config.min_step_mult,
            max_step_mult=config.max_step_mult,
        )
        keep = (state.iteration == 0) | ~jnp.isfinite(adapted)
        return jnp.where(keep, state.step_mult, adapted)

    def inner(
        state: GPSState,
        samples: GPSSamples,
        quad: QuadraticCost,
        step_mult: Array,
        anchor: LinearGaussianController | None = None,
    ) -> tuple[GPSState, GPSMetrics]:
        """C-step of every condition; ``anchor``: the KL anchor [C] (default: the controllers
        that drew the samples, ``state.controller``)."""
        anchor = state.controller if anchor is None else anchor
        return jax.vmap(inner_one, in_axes=(state_axes, 0, 0, 0, 0), out_axes=(state_axes, 0))(
            state, samples, quad, step_mult, anchor
        )

    return GPSPhases(
        init=init,
        draw=draw,
        simulate=simulate,
        fit=fit,
        outer=outer,
        fit_samples=fit_samples,
        expand=expand,
        adapt_step=adapt_step,
        inner=inner,
        autodiff=config.dynamics == "autodiff",
    )


def make_gps(
    config: GPSConfig,
    env: Env,
    cost: CostFn,
    *,
    true_cost: CostFn | None = None,
    x0: Array | None = None,
) -> GPS:
    """Set up GPS on ``env`` with ``cost``; see the module docstring.

    x0: conditions [C, dX] (default ``env.initial_states()``); true_cost: the cost reported in the
    metrics (default ``cost``; with ``gauss_newton`` a residual ``cost`` needs a ``true_cost``).
    """
    if true_cost is None:
        if config.gauss_newton:
            raise ValueError("make_gps: gauss_newton=True needs the true_cost to report")
        true_cost = cost
    phases = make_gps_phases(config, env, true_cost=true_cost, x0=x0)
    sim = Simulator(env)

    def update(state: GPSState, sims: SimulatedSamples) -> tuple[GPSState, GPSMetrics]:
        samples = phases.fit(sims)
        quad = phases.expand(cost, samples)
        step_mult = phases.adapt_step(state, samples, quad)
        return phases.inner(state, samples, quad, step_mult)

    def iteration(state: GPSState, key: PRNGKey) -> tuple[GPSState, GPSMetrics]:
        return update(state, phases.simulate(sim, phases.draw(state, key)))

    def train(key: PRNGKey, hparams: GPSHyperparams | None = None) -> tuple[GPSState, GPSMetrics]:
        key_init, key_iter = jax.random.split(key)
        state = phases.init(key_init, hparams)
        return lax.scan(iteration, state, jax.random.split(key_iter, config.iterations))

    return GPS(
        init=phases.init,
        iteration=iteration,
        train=train,
        draw=phases.draw,
        simulate=phases.simulate,
        update=update,
        phases=phases,
    )


def first_success(success: Array) -> Array:
    """Index of the first iteration whose sampling controller succeeds on every condition, or
    −1: the number of C-steps it took (metrics describe the controller before each C-step).

    success: [..., iterations, C] bool (metrics.success of ``train``) -> [...] int.
    """
    all_c = jnp.all(success, axis=-1)
    found = jnp.any(all_c, axis=-1)
    return jnp.where(found, jnp.argmax(all_c, axis=-1), -1)
