"""Multiple-shooting trajectory optimisation of a known cost, with box limits on the actions and
on the states (a relaxed log barrier).

Problem (one start state): minimise ``J = Σ_{t<T} c(x_t, u_t, t) + c(x_T, 0, T)`` over the states
``X = x_1 .. x_T`` *and* the actions ``U`` subject to ``x_{t+1} = f(x_t, u_t)`` (``x_0`` given),
``u_min ≤ u ≤ u_max`` and ``x_min ≤ x ≤ x_max`` (elementwise, ±inf where free).

Why beside :mod:`diffgcl.control.ilqr`: iLQR shoots once — every iterate is a rollout of the
actions — so its first trajectory is the system's response to the initial actions, and for an
unstable system the Newton steps taken along a fallen or runaway trajectory settle on a local
optimum near it. Gymnasium's double pendulum tilted 3× shows it: iLQR pushes under the lean at
once and runs out of rail, where the catch that exists backs off first
(``experiments/double_pendulum_catch.py``). Multiple shooting starts from a *state* guess (by
default the straight line from the start to the goal) that need not be a rollout; the dynamics
are only met at convergence, so the iterates are not dragged along by the instability.

Each iteration (Gauss–Newton multiple shooting with a Riccati sweep, as in Bock & Plitt 1984
and the "feasibility-driven" DDP of Mastalli et al. 2020):

1. linearise the dynamics along (X, U), ``δx' = A_t δx + B_t δu + g_t`` with the gaps ``g_t =
   f(X_t, U_t) − X_{t+1}``, and expand the cost (with the barrier) to second order;
2. the backward pass of iLQR with the gaps (:func:`~diffgcl.control.ilqr.backward_pass`,
   ``gaps=``): gains ``k, K``, actions boxed by projected Newton, ``μ`` regularising ``Q_uu``;
3. the step of the linear model, ``δu_t = k_t + K_t δx_t``, ``δx_{t+1} = A_t δx_t + B_t δu_t +
   g_t`` (``δx_0 = 0``): a full step closes every gap of the linear model. ``δu`` is not
   clipped to the action box here: the feedback ``K δx`` keeps an unstable model's propagated
   gaps bounded, and clipping it lets them grow without bound;
4. a backtracking line search on ``(X + α δX, clip(U + α δU))`` with the ℓ1 merit ``φ = J +
   ν Σ|g|`` (ν raised to twice the cost's slope over the gaps whenever that is larger, so that
   the step is a descent direction of φ; or, with ``merit_rule="multipliers"``, twice the
   largest costate, below), accepting the first α with Armijo's decrease. Where
   the clip binds, the step may not descend; the search then fails, ``μ`` grows and the next
   step is shorter, until one is accepted.

State limits: each bounded coordinate adds ``w·B(x_max − x) + w·B(x − x_min)`` to every step's
cost, with ``B`` the relaxed log barrier (Hauser & Saccon 2006): ``−log s`` for ``s > δ``, its
quadratic extension below (finite and smooth everywhere, so an iterate outside the box is
pulled back rather than lost). The weight runs through ``barrier_weights`` (default 1 down to
10⁻³, the central path of an interior-point method): the first stages keep the iterates well
inside the box while the manoeuvre forms, the last let the solution use it. Why not a penalty
``ρ·max(0, x − x_max)²``: it only acts past the limit, so the iterates overrun it, and where the
limit is a joint's end stop the linearisation there holds the stop's stiff force; on the double
pendulum the penalty method parked the cart at the rail (a dearer local optimum), the barrier
caught all three starts iLQR drops (``docs/trajopt.md``).

Each stage runs to convergence (the largest gap below ``gap_tol`` and the last step below
``step_tol``) or ``stage_iterations``; then the barrier weight drops and the next stage starts
from where it ended. The returned trajectory is the closed-loop rollout of the final gains,
``u_t = U_t + K_t (x_t − X_t)`` clipped to the action box, from ``x_0``: a true trajectory of
the simulator whatever gaps were left, with its cost without the barrier.

Compile time, as in :mod:`~diffgcl.control.ilqr`: the whole solve is one ``lax.while_loop``;
its body holds one linearisation (``jacfwd``, vmapped over time) and one evaluation of the step
at all T states at once (the line search's gaps, vmapped over time, not a scan); the final
rollout is the third and last call site. Written for one start state; ``jax.vmap`` it.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
from flax import struct
from jax import lax

from diffgcl.control.ilqr import (
    CONVERGED,
    MAX_ITERATIONS,
    STUCK,
    ILQRResult,
    StepFn,
    _Backward,
    action_box,
    backward_pass,
    closed_loop_rollout,
    no_gains,
    zero_expansion,
)
from diffgcl.costs.expansion import expand_cost, trajectory_cost
from diffgcl.dynamics.autodiff import linearize_trajectory
from diffgcl.types import Array, CostFn, QuadraticCost

MERIT_RULES = ("slope", "multipliers")


@dataclass(frozen=True)
class ShootingConfig:
    """Settings of :func:`multiple_shooting` (static: each distinct config is another program).

    barrier_weights: the state barrier's weight ``w`` in each stage, in order (module docstring;
    in the cost's units); barrier_delta: where the relaxed barrier turns quadratic (in the
    state's units); stage_iterations: iterations at most per stage; gap_tol: a stage has
    converged when every gap's largest entry is below it and the last step moved no action by
    more than ``step_tol·(1 + max|U|)``, or when the gaps are below it and the cost's slope
    along the next step is below ``tol·(1 + |J|)`` (stationary: no step left to take);
    line_search_steps, backtrack, armijo: the line search ``α = backtrack^i``; merit_weight:
    the initial ν of the merit ``J + ν Σ|g|``; merit_rule: how ν follows — ``"slope"`` (the
    default): raised to twice the cost's slope along the step over the gaps whenever that is
    larger, never lowered; ``"multipliers"``: set each iteration to twice the largest costate
    ``|λ|`` of the linearised problem (``λ_T = l_x(T)``, ``λ_t = l_x(t) + A_tᵀ λ_{t+1}``, the
    multipliers of the dynamics; at least 10⁻⁶, so that the gaps still count where the cost is
    flat), the exact ℓ1 penalty's threshold (Nocedal & Wright, ch. 15 and 18). The slope rule
    can grow without bound as the gaps shrink towards ``gap_tol``, and on the double pendulum
    its later stages' line searches accept only tiny steps (docs/trajopt.md); the costates do
    not depend on the gaps. Measured there: half the iterations, dearer solutions. mu_init,
    mu_min, mu_max, mu_shrink, mu_grow: the regularisation of ``Q_uu`` (multiplied by
    ``mu_shrink`` after an accepted step, and set to 0 below ``mu_min``; by ``mu_grow`` after a
    failed one, at least to ``mu_min``; a stage ends when it passes ``mu_max``).
    """

    barrier_weights: tuple[float, ...] = (1.0, 0.1, 0.01, 0.001)
    barrier_delta: float = 1e-3
    stage_iterations: int = 60
    gap_tol: float = 1e-8
    step_tol: float = 1e-6
    tol: float = 1e-9
    line_search_steps: int = 20
    backtrack: float = 0.5
    armijo: float = 1e-4
    merit_weight: float = 100.0
    merit_rule: str = "slope"
    mu_init: float = 0.0
    mu_min: float = 1e-8
    mu_max: float = 1e10
    mu_shrink: float = 0.25
    mu_grow: float = 10.0

    def __post_init__(self):
        if not self.barrier_weights or any(w < 0 for w in self.barrier_weights):
            raise ValueError(
                f"ShootingConfig: barrier_weights must be a non-empty tuple of weights >= 0, "
                f"got {self.barrier_weights}"
            )
        if self.stage_iterations < 1 or self.line_search_steps < 1:
            raise ValueError("ShootingConfig: stage_iterations and line_search_steps must be >= 1")
        if not 0.0 < self.backtrack < 1.0:
            raise ValueError(f"ShootingConfig: backtrack must be in (0, 1), got {self.backtrack}")
        if self.merit_rule not in MERIT_RULES:
            raise ValueError(
                f"ShootingConfig: merit_rule must be one of {MERIT_RULES}, got {self.merit_rule!r}"
            )
        if self.barrier_delta <= 0:
            raise ValueError(f"ShootingConfig: barrier_delta must be > 0, got {self.barrier_delta}")

    @property
    def max_trips(self) -> int:
        return len(self.barrier_weights) * self.stage_iterations


def relaxed_log_barrier(s: Array, delta: float) -> Array:
    """``−log s`` for ``s > δ``; below, the quadratic that meets it with equal value, slope and
    curvature at ``δ``: ``½((s − 2δ)/δ)² − ½ − log δ`` (finite for every ``s``)."""
    inside = -jnp.log(jnp.maximum(s, delta))
    outside = 0.5 * ((s - 2.0 * delta) / delta) ** 2 - 0.5 - jnp.log(delta)
    return jnp.where(s > delta, inside, outside)


def state_barrier(x: Array, x_min: Array, x_max: Array, delta: float) -> Array:
    """``Σ_i B(x_max,i − x_i) + B(x_i − x_min,i)`` over the coordinates with a finite bound
    (:func:`relaxed_log_barrier`), zero for a free coordinate."""
    lo_ok, hi_ok = jnp.isfinite(x_min), jnp.isfinite(x_max)
    s_lo = jnp.where(lo_ok, x - jnp.where(lo_ok, x_min, 0.0), 1.0)
    s_hi = jnp.where(hi_ok, jnp.where(hi_ok, x_max, 0.0) - x, 1.0)
    terms = jnp.where(lo_ok, relaxed_log_barrier(s_lo, delta), 0.0)
    terms = terms + jnp.where(hi_ok, relaxed_log_barrier(s_hi, delta), 0.0)
    return jnp.sum(terms)


def costates(A: Array, quad: QuadraticCost) -> Array:
    """The multipliers ``λ_{t+1}`` [T, dX] of the dynamics ``x_{t+1} = f(x_t, u_t)`` in the
    linearised problem, by the adjoint recursion ``λ_T = l_x(T)``, ``λ_t = l_x(t) + A_tᵀ
    λ_{t+1}`` (the Lagrangian's stationarity in each state); row t belongs to the gap t."""

    def back(lam_next, inputs):
        A_t, l_x_t = inputs
        return l_x_t + A_t.T @ lam_next, lam_next

    _, lams = lax.scan(back, quad.l_x[-1], (A, quad.l_x[:-1]), reverse=True)
    return lams


def straight_line(x0: Array, x_goal: Array, T: int) -> Array:
    """States [T+1, dX] on the straight line from ``x0`` to ``x_goal``: the default state guess."""
    s = jnp.linspace(0.0, 1.0, T + 1, dtype=x0.dtype)[:, None]
    return (1.0 - s) * x0[None] + s * x_goal[None]


@struct.dataclass
class _Shoot:
    X: Array
    U: Array
    gaps: Array
    J: Array  # the cost with the current stage's barrier
    quad: QuadraticCost
    A: Array
    B: Array
    back: _Backward
    dX: Array  # the step of the linear model
    dU: Array
    slope: Array  # the cost's directional derivative along (dX, dU)
    nu: Array
    mu: Array
    stage: Array
    stage_trip: Array
    trip: Array
    accepted: Array
    rollouts: Array
    done: Array
    status: Array
    history: Array


def multiple_shooting(
    step: StepFn,
    cost: CostFn,
    x0: Array,
    X_init: Array,
    U_init: Array,
    config: ShootingConfig = ShootingConfig(),
    *,
    u_min: Array | None = None,
    u_max: Array | None = None,
    x_min: Array | None = None,
    x_max: Array | None = None,
) -> ILQRResult:
    """Minimise the cost over states and actions from ``x0: [dX]`` (module docstring), starting
    from the state guess ``X_init: [T+1, dX]`` (its first row is replaced by ``x0``; e.g.
    :func:`straight_line`) and ``U_init: [T, dU]``.

    ``step(x, u) -> x'`` and ``cost(x, u, t)`` are pure JAX functions for one instance; vmap at
    the call site. u_min, u_max: [dU] (or scalars) the action box, as in
    :func:`~diffgcl.control.ilqr.ilqr`; x_min, x_max: [dX] (or scalars, ±inf where free) the
    state limits, enforced by the barrier (approximately: the relaxed barrier lets a state sit
    within about ``barrier_delta`` of a limit, or past it where the limit cannot be kept).

    Returns an :class:`~diffgcl.control.ilqr.ILQRResult` whose ``X, U, cost`` are the
    closed-loop rollout of the final gains from ``x0`` and its cost without the barrier; ``K``,
    ``Q_uu`` the final backward pass's; ``cost_history`` the barrier-augmented cost after each
    iteration (NaN after the last); ``status`` CONVERGED when the last stage converged,
    MAX_ITERATIONS when it ran out of iterations, STUCK when its regularisation passed
    ``mu_max``.
    """
    T, dU = U_init.shape
    dX = x0.shape[-1]
    if X_init.shape != (T + 1, dX):
        raise ValueError(
            f"multiple_shooting: X_init must be [T+1={T + 1}, {dX}], got {tuple(X_init.shape)}"
        )
    dtype = x0.dtype
    X_init = X_init.astype(dtype).at[0].set(x0)
    U_init = U_init.astype(dtype)
    bounds = action_box(u_min, u_max, dU, dtype)
    if bounds is not None:
        U_init = jnp.clip(U_init, bounds[0], bounds[1])
        width = bounds[1] - bounds[0]
        margin = jnp.where(jnp.isfinite(width), 1e-5 * width, 0.0)
        inner = (bounds[0] + margin, bounds[1] - margin)
    lo_x = jnp.broadcast_to(jnp.asarray(-jnp.inf if x_min is None else x_min, dtype), (dX,))
    hi_x = jnp.broadcast_to(jnp.asarray(jnp.inf if x_max is None else x_max, dtype), (dX,))
    weights = jnp.asarray(config.barrier_weights, dtype)
    n_stages = len(config.barrier_weights)
    n_hist = config.max_trips + 1

    def barrier_cost(w):
        def c(x, u, t):
            return cost(x, u, t) + w * state_barrier(x, lo_x, hi_x, config.barrier_delta)

        return c

    def gaps_of(X, U):
        return jax.vmap(step)(X[:-1], U) - X[1:]

    def linearise(X, U, w):
        # B just inside the action limits: the one-sided derivative a step can use (ilqr.py).
        U_lin = U if bounds is None else jnp.clip(U, inner[0], inner[1])
        A, B = linearize_trajectory(step, X, U_lin)
        return A, B, expand_cost(barrier_cost(w), X, U)

    def linear_step(A, B, back, gaps):
        """(δX, δU) of the linear model under the gains, not clipped to the action box: the
        feedback ``K δx`` is what keeps an unstable model's propagated gaps bounded, and a clip
        here cuts it (on the tilted double pendulum δX reached 10¹⁶ and every line search
        failed). The line search clips ``U + α δU`` instead."""

        def body(dx, inputs):
            A_t, B_t, K_t, k_t, g_t = inputs
            du = k_t + K_t @ dx
            return A_t @ dx + B_t @ du + g_t, (dx, du)

        dx_T, (dX_, dU_) = lax.scan(body, jnp.zeros((dX,), dtype), (A, B, back.K, back.k, gaps))
        return jnp.concatenate([dX_, dx_T[None]]), dU_

    def line_search(s: _Shoot, w, stationary):
        h0 = jnp.sum(jnp.abs(s.gaps))
        first = s.trip == 0
        merit0 = s.J + s.nu * h0
        descent = s.slope - s.nu * h0  # the merit's directional derivative along the step

        def cond(c):
            go = s.back.ok & ~s.done & ~stationary
            return (~c[1]) & (c[0] < config.line_search_steps) & go

        def body(c):
            i, _, X_best, U_best, g_best, J_best, step_best = c
            alpha = jnp.asarray(config.backtrack, dtype) ** i
            X1 = s.X + alpha * s.dX
            U1 = s.U + alpha * s.dU
            if bounds is not None:
                U1 = jnp.clip(U1, bounds[0], bounds[1])
            g1 = gaps_of(X1, U1)
            J1 = trajectory_cost(barrier_cost(w), X1, U1)
            merit1 = J1 + s.nu * jnp.sum(jnp.abs(g1))
            ok = jnp.isfinite(merit1) & jnp.all(jnp.isfinite(g1))
            ok = ok & ((merit1 <= merit0 + config.armijo * alpha * descent) | first)
            pick = lambda new, old: jnp.where(ok, new, old)
            moved = jnp.max(jnp.abs(U1 - s.U))
            return (i + 1, ok, pick(X1, X_best), pick(U1, U_best), pick(g1, g_best),
                    pick(J1, J_best), pick(moved, step_best))  # fmt: skip

        zero_i = jnp.zeros((), jnp.int32)
        init = (zero_i, jnp.zeros((), bool), s.X, s.U, s.gaps, s.J, jnp.zeros((), dtype))
        i, ok, X, U, gaps, J, moved = lax.while_loop(cond, body, init)
        return ok, X, U, gaps, J, moved, i

    def trip(s: _Shoot) -> _Shoot:
        first = s.trip == 0
        w = weights[s.stage]
        stationary = (
            ~first
            & s.back.ok
            & (jnp.max(jnp.abs(s.gaps)) < config.gap_tol)
            & (-s.slope < config.tol * (1.0 + jnp.abs(s.J)))
        )
        accepted, X, U, gaps, J, moved, n = line_search(s, w, stationary)
        shrunk = s.mu * config.mu_shrink
        mu = jnp.where(
            accepted,
            jnp.where(shrunk < config.mu_min, 0.0, shrunk),
            jnp.maximum(s.mu * config.mu_grow, config.mu_min),
        )
        mu = jnp.where(first, jnp.asarray(config.mu_init, dtype), mu)
        closed = jnp.max(jnp.abs(gaps)) < config.gap_tol
        still = moved <= config.step_tol * (1.0 + jnp.max(jnp.abs(U)))
        converged = (accepted & ~first & closed & still) | stationary
        mu = jnp.where(stationary, s.mu, mu)
        stuck = (mu > config.mu_max) & ~converged
        stage_trip = s.stage_trip + 1
        stage_over = converged | stuck | (stage_trip >= config.stage_iterations)
        last_stage = s.stage + 1 >= n_stages
        done = (stage_over & last_stage) | (first & ~accepted)
        status = jnp.where(converged, CONVERGED, jnp.where(stuck, STUCK, MAX_ITERATIONS))
        status = jnp.where(first & ~accepted, STUCK, status)  # the initial guess is not finite
        stage = jnp.where(stage_over & ~last_stage, s.stage + 1, s.stage)
        w_next = weights[stage]
        new_stage = stage != s.stage
        mu = jnp.where(new_stage, jnp.asarray(config.mu_init, dtype), mu)
        stage_trip = jnp.where(new_stage, 0, stage_trip)
        J = jnp.where(new_stage, trajectory_cost(barrier_cost(w_next), X, U), J)
        A, B, quad = lax.cond(
            (accepted | new_stage) & ~done,
            lambda: linearise(X, U, w_next),
            lambda: (s.A, s.B, s.quad),
        )
        if bounds is None:
            back = backward_pass(A, B, quad, mu, gaps=gaps)
        else:
            back = backward_pass(A, B, quad, mu, bounds[0] - U, bounds[1] - U, s.back.k, gaps)
        dX_, dU_ = linear_step(A, B, back, gaps)
        dX_ = jnp.where(back.ok, dX_, 0.0)
        dU_ = jnp.where(back.ok, dU_, 0.0)
        slope = jnp.sum(quad.l_x * dX_) + jnp.sum(quad.l_u[:-1] * dU_)
        if config.merit_rule == "multipliers":
            nu = jnp.maximum(2.0 * jnp.max(jnp.abs(costates(A, quad))), 1e-6)
        else:
            # ν only grows while the gaps are real: against rounding-sized gaps it would blow up
            # and the merit would be rounding noise.
            gap_sum = jnp.sum(jnp.abs(gaps))
            real = jnp.max(jnp.abs(gaps)) >= config.gap_tol
            nu = jnp.where(
                real, jnp.maximum(s.nu, 2.0 * jnp.abs(slope) / jnp.where(real, gap_sum, 1.0)), s.nu
            )
        return _Shoot(
            X=X,
            U=U,
            gaps=gaps,
            J=J,
            quad=quad,
            A=A,
            B=B,
            back=back,
            dX=dX_,
            dU=dU_,
            slope=slope,
            nu=nu,
            mu=mu,
            stage=stage,
            stage_trip=stage_trip,
            trip=s.trip + 1,
            accepted=s.accepted + (accepted & ~first).astype(jnp.int32),
            rollouts=s.rollouts + n,
            done=done | (s.trip + 1 >= n_hist),
            status=status.astype(jnp.int32),
            history=s.history.at[s.trip].set(J),
        )

    zeros = lambda *shape: jnp.zeros(shape, dtype)
    quad0 = zero_expansion(T, dX, dU, dtype)
    back0 = no_gains(T, dX, dU, dtype)
    # Trip 0: a zero step and J = +inf, so its line search evaluates the initial guess's gaps.
    init = _Shoot(
        X=X_init,
        U=U_init,
        gaps=zeros(T, dX),
        J=jnp.asarray(jnp.inf, dtype),
        quad=quad0,
        A=zeros(T, dX, dX),
        B=zeros(T, dX, dU),
        back=back0,
        dX=zeros(T + 1, dX),
        dU=zeros(T, dU),
        slope=zeros(),
        nu=jnp.asarray(config.merit_weight, dtype),
        mu=jnp.asarray(config.mu_init, dtype),
        stage=jnp.zeros((), jnp.int32),
        stage_trip=jnp.zeros((), jnp.int32),
        trip=jnp.zeros((), jnp.int32),
        accepted=jnp.zeros((), jnp.int32),
        rollouts=jnp.zeros((), jnp.int32),
        done=jnp.zeros((), bool),
        status=jnp.asarray(MAX_ITERATIONS, jnp.int32),
        history=jnp.full((n_hist,), jnp.nan, dtype),
    )
    s = lax.while_loop(lambda s: ~s.done, trip, init)
    zero_k = jnp.zeros_like(s.back.k)
    X, U, J = closed_loop_rollout(
        step, cost, x0, s.X, s.U, s.back.K, zero_k, jnp.zeros((), dtype), bounds
    )
    return ILQRResult(
        X=X,
        U=U,
        cost=J,
        K=s.back.K,
        Q_uu=s.back.Q_uu,
        backward_ok=s.back.ok,
        mu=s.mu,
        iterations=s.trip - 1,
        accepted=s.accepted,
        rollouts=s.rollouts + 1,
        status=s.status,
        cost_history=s.history,
    )
