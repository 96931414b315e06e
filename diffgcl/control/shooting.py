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
4. a backtracking line search on ``(X + α δX, clip(U + α δU))`` that accepts the first α whose
   trial lowers the gaps ``Σ|g|`` or the cost enough against the current iterate and against
   the earlier iterates of the stage (a filter, as in IPOPT; ``ShootingConfig.merit_rule``
   names it and the ℓ1 merits it replaced). Where the clip binds, the step may not descend;
   the search then fails, ``μ`` grows and the next step is shorter, until one is accepted.

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

MERIT_RULES = ("slope", "multipliers", "filter")

# The filter line search's constants, IPOPT's defaults (Wächter & Biegler 2006, section 3.2 and
# table 1): the margins of sufficient decrease in the gaps and in the cost, the switching
# condition's exponents and factor, the filter's envelope (times the first iterate's gaps, at
# least 1). IPOPT's filter grows without limit; here it keeps the last FILTER_SIZE entries of a
# stage (the oldest overwritten first), so that the loop's state has a fixed shape.
FILTER_GAMMA_GAPS = 1e-5
FILTER_GAMMA_COST = 1e-5
FILTER_S_GAPS = 1.1
FILTER_S_COST = 2.3
FILTER_DELTA = 1.0
FILTER_GAPS_MAX = 1e4
FILTER_GAPS_MIN = 1e-4
FILTER_SIZE = 64


@dataclass(frozen=True)
class ShootingConfig:
    """Settings of :func:`multiple_shooting` (static: each distinct config is another program).

    barrier_weights: the state barrier's weight ``w`` in each stage, in order (module docstring;
    in the cost's units); barrier_delta: where the relaxed barrier turns quadratic (in the
    state's units); stage_iterations: iterations at most per stage; gap_tol: a stage has
    converged when every gap's largest entry is below it and the last step moved no action by
    more than ``step_tol·(1 + max|U|)``, or when the gaps are below it and the cost's slope
    along the next step is below ``tol·(1 + |J|)`` (stationary: no step left to take);
    line_search_steps, backtrack, armijo: the line search ``α = backtrack^i``; merit_rule: which
    trial the line search accepts — ``"filter"`` (the default): Wächter & Biegler's filter
    (2006, as in IPOPT, with IPOPT's constants: ``FILTER_*`` here), which judges the gaps
    ``h = Σ|g|`` and the cost ``J`` apart: a trial is accepted where it lowers either enough
    against the current iterate and no earlier iterate of the stage (the filter) was better in
    both; where the gaps are already small and the step promises enough decrease of the cost,
    Armijo's decrease of ``J`` alone; ``"slope"``: the ℓ1 merit ``J + ν Σ|g|`` with Armijo's
    decrease, ν (from ``merit_weight``) raised to twice the cost's slope along the step over
    the gaps whenever that is larger, never lowered; ``"multipliers"``: the same merit with ν
    set each iteration to twice the largest costate ``|λ|`` of the linearised problem (``λ_T =
    l_x(T)``, ``λ_t = l_x(t) + A_tᵀ λ_{t+1}``, the multipliers of the dynamics; at least 10⁻⁶,
    so that the gaps still count where the cost is flat), the exact ℓ1 penalty's threshold
    (Nocedal & Wright, ch. 15 and 18). Why the filter: under the slope rule ν grows without
    bound as the gaps shrink towards ``gap_tol``, and from then on only tiny steps pass (the
    second-order gaps of a full step, times ν, outweigh the cost it saves): on gymnasium's
    tilted double pendulum the later stages crawled at α = 2⁻¹⁰ to the iteration limit and
    stopped short of the optimum; the multipliers rule converged in half the iterations but at
    dearer solutions; the filter converged in about a quarter of the iterations at solutions
    18 % cheaper (median; docs/trajopt.md). fallback_rule: None, or the rule of a second attempt
    from the same initial guess where the first ends stuck (no step its rule accepts, ``μ``
    past ``mu_max`` in the last stage), keeping the cheaper of the two (default ``"slope"``:
    on that pendulum the filter ends stuck on a few hard starts the slope rule solves; the
    second attempt runs in the same loop, so the program is compiled once). mu_init, mu_min,
    mu_max, mu_shrink, mu_grow: the regularisation of ``Q_uu`` (multiplied by
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
    merit_rule: str = "filter"
    fallback_rule: str | None = "slope"
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
        if self.fallback_rule is not None and self.fallback_rule not in MERIT_RULES:
            raise ValueError(
                f"ShootingConfig: fallback_rule must be None or one of {MERIT_RULES}, got "
                f"{self.fallback_rule!r}"
            )
        if self.barrier_delta <= 0:
            raise ValueError(f"ShootingConfig: barrier_delta must be > 0, got {self.barrier_delta}")

    @property
    def rules(self) -> tuple[str, ...]:
        """The line search's rule of each attempt: ``merit_rule``, then ``fallback_rule``."""
        return (self.merit_rule,) + (() if self.fallback_rule is None else (self.fallback_rule,))

    @property
    def max_trips(self) -> int:
        """Iterations at most, over every attempt (each has one more, its initial guess's)."""
        return len(self.rules) * (len(self.barrier_weights) * self.stage_iterations + 1) - 1


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
    filter_J: Array  # [FILTER_SIZE] the filter's entries (merit_rule "filter"; +inf where empty)
    filter_h: Array
    filter_n: Array  # entries added in this stage (the next goes to filter_n mod FILTER_SIZE)
    h_min: Array  # below these gaps (ℓ1) a step may be judged on the cost alone
    h_max: Array  # no trial may open the gaps past this
    mu: Array
    stage: Array
    stage_trip: Array
    trip: Array
    attempt: Array  # which of config.rules the line search follows
    attempt_start: Array  # the trip at which this attempt began (its initial guess's)
    kept_X: Array  # the first attempt's nominal trajectory and gains, where it ended stuck
    kept_U: Array
    kept_back: _Backward
    kept_mu: Array
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
    rules = config.rules

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

    def by_attempt(s: _Shoot, values):
        """The value of the current attempt's rule (``values`` in the order of config.rules)."""
        out = values[0]
        for i, v in enumerate(values[1:], start=1):
            out = jnp.where(s.attempt == i, v, out)
        return out

    def acceptable(s: _Shoot, h0, J1, h1, alpha):
        """Whether the trial ``(J1, h1)`` at step ``alpha`` is accepted by the current attempt's
        rule, and whether it was judged on the cost alone (then it need not enter the filter)."""
        judged = [accepts(rule, s, h0, J1, h1, alpha) for rule in rules]
        return by_attempt(s, [j[0] for j in judged]), by_attempt(s, [j[1] for j in judged])

    def accepts(rule, s: _Shoot, h0, J1, h1, alpha):
        if rule != "filter":
            # The ℓ1 merit J + ν Σ|g| and Armijo's decrease along the step, whose directional
            # derivative is slope − ν Σ|g|.
            merit0 = s.J + s.nu * h0
            merit1 = J1 + s.nu * h1
            ok = merit1 <= merit0 + config.armijo * alpha * (s.slope - s.nu * h0)
            return ok, jnp.zeros((), bool)
        # Wächter & Biegler's filter: no trial the filter dominates, none past h_max; where the
        # gaps are small and the step promises enough decrease (the switching condition),
        # Armijo's decrease of the cost; else enough decrease of the gaps or of the cost.
        dominated = jnp.any((h1 >= s.filter_h) & (J1 >= s.filter_J))
        switching = (s.slope < 0) & (
            alpha * jnp.abs(s.slope) ** FILTER_S_COST > FILTER_DELTA * h0**FILTER_S_GAPS
        )
        cost_only = (h0 <= s.h_min) & switching
        armijo = J1 <= s.J + config.armijo * alpha * s.slope
        decrease = (h1 <= (1.0 - FILTER_GAMMA_GAPS) * h0) | (J1 <= s.J - FILTER_GAMMA_COST * h0)
        ok = ~dominated & (h1 <= s.h_max) & jnp.where(cost_only, armijo, decrease)
        return ok, cost_only & armijo

    def line_search(s: _Shoot, w, stationary, h0):
        first = s.trip == s.attempt_start

        def cond(c):
            go = s.back.ok & ~s.done & ~stationary
            return (~c[1]) & (c[0] < config.line_search_steps) & go

        def body(c):
            i, _, X_best, U_best, g_best, J_best, step_best, _ = c
            alpha = jnp.asarray(config.backtrack, dtype) ** i
            X1 = s.X + alpha * s.dX
            U1 = s.U + alpha * s.dU
            if bounds is not None:
                U1 = jnp.clip(U1, bounds[0], bounds[1])
            g1 = gaps_of(X1, U1)
            J1 = trajectory_cost(barrier_cost(w), X1, U1)
            h1 = jnp.sum(jnp.abs(g1))
            decreases, cost_only = acceptable(s, h0, J1, h1, alpha)
            ok = jnp.isfinite(J1) & jnp.all(jnp.isfinite(g1)) & (decreases | first)
            pick = lambda new, old: jnp.where(ok, new, old)
            moved = jnp.max(jnp.abs(U1 - s.U))
            return (i + 1, ok, pick(X1, X_best), pick(U1, U_best), pick(g1, g_best),
                    pick(J1, J_best), pick(moved, step_best), cost_only)  # fmt: skip

        zero_i = jnp.zeros((), jnp.int32)
        no = jnp.zeros((), bool)
        init = (zero_i, no, s.X, s.U, s.gaps, s.J, jnp.zeros((), dtype), no)
        i, ok, X, U, gaps, J, moved, cost_only = lax.while_loop(cond, body, init)
        return ok, X, U, gaps, J, moved, i, cost_only

    def trip(s: _Shoot) -> _Shoot:
        first = s.trip == s.attempt_start
        w = weights[s.stage]
        stationary = (
            ~first
            & s.back.ok
            & (jnp.max(jnp.abs(s.gaps)) < config.gap_tol)
            & (-s.slope < config.tol * (1.0 + jnp.abs(s.J)))
        )
        h0 = jnp.sum(jnp.abs(s.gaps))  # the current iterate's gaps (ℓ1)
        accepted, X, U, gaps, J, moved, n, cost_only = line_search(s, w, stationary, h0)
        # The filter: an accepted step not judged on the cost alone adds its start's entry (the
        # gaps and cost no later trial of the stage may come near); the first iterate's gaps set
        # the envelope.
        grow = accepted & ~first & ~cost_only
        slot = s.filter_n % FILTER_SIZE
        filter_h = jnp.where(
            grow, s.filter_h.at[slot].set((1.0 - FILTER_GAMMA_GAPS) * h0), s.filter_h
        )
        filter_J = jnp.where(
            grow, s.filter_J.at[slot].set(s.J - FILTER_GAMMA_COST * h0), s.filter_J
        )
        filter_n = s.filter_n + grow.astype(jnp.int32)
        h_first = jnp.maximum(1.0, jnp.sum(jnp.abs(gaps)))
        h_min = jnp.where(first, FILTER_GAPS_MIN * h_first, s.h_min)
        h_max = jnp.where(first, FILTER_GAPS_MAX * h_first, s.h_max)
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
        # Another stage is another cost: its filter starts empty.
        filter_h = jnp.where(new_stage, jnp.inf, filter_h)
        filter_J = jnp.where(new_stage, jnp.inf, filter_J)
        filter_n = jnp.where(new_stage, 0, filter_n)
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
        # ν only grows while the gaps are real: against rounding-sized gaps it would blow up and
        # the merit would be rounding noise. (The filter does not use ν.)
        gap_sum = jnp.sum(jnp.abs(gaps))
        real = jnp.max(jnp.abs(gaps)) >= config.gap_tol
        nu_slope = jnp.where(
            real, jnp.maximum(s.nu, 2.0 * jnp.abs(slope) / jnp.where(real, gap_sum, 1.0)), s.nu
        )
        if "multipliers" in rules:
            nu_multipliers = jnp.maximum(2.0 * jnp.max(jnp.abs(costates(A, quad))), 1e-6)
        nu = by_attempt(s, [nu_multipliers if r == "multipliers" else nu_slope for r in rules])
        s_next = s.replace(  # the attempt and what an earlier attempt kept carry over
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
            filter_J=filter_J,
            filter_h=filter_h,
            filter_n=filter_n,
            h_min=h_min,
            h_max=h_max,
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
        if len(rules) == 1:
            return s_next
        # An attempt that ended stuck (no step its rule accepts, its regularisation past mu_max)
        # is kept, and the next attempt starts again from the initial guess under the next rule.
        again = done & stuck & (s.attempt + 1 < len(rules)) & ~(first & ~accepted)
        fresh = initial(s.attempt + 1, s.trip + 1).replace(
            kept_X=X, kept_U=U, kept_back=back, kept_mu=mu, accepted=s_next.accepted,
            rollouts=s_next.rollouts, history=s_next.history, trip=s.trip + 1
        )  # fmt: skip
        return jax.tree_util.tree_map(lambda a, b: jnp.where(again, a, b), fresh, s_next)

    zeros = lambda *shape: jnp.zeros(shape, dtype)
    quad0 = zero_expansion(T, dX, dU, dtype)
    back0 = no_gains(T, dX, dU, dtype)

    def initial(attempt, start) -> _Shoot:
        """The state before an attempt's first trip: a zero step and J = +inf, so that its line
        search evaluates the initial guess's gaps."""
        return _Shoot(
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
            filter_J=jnp.full((FILTER_SIZE,), jnp.inf, dtype),
            filter_h=jnp.full((FILTER_SIZE,), jnp.inf, dtype),
            filter_n=jnp.zeros((), jnp.int32),
            h_min=zeros(),
            h_max=jnp.asarray(jnp.inf, dtype),
            mu=jnp.asarray(config.mu_init, dtype),
            stage=jnp.zeros((), jnp.int32),
            stage_trip=jnp.zeros((), jnp.int32),
            trip=jnp.asarray(start, jnp.int32),
            attempt=jnp.asarray(attempt, jnp.int32),
            attempt_start=jnp.asarray(start, jnp.int32),
            kept_X=X_init,
            kept_U=U_init,
            kept_back=back0,
            kept_mu=jnp.asarray(jnp.inf, dtype),
            accepted=jnp.zeros((), jnp.int32),
            rollouts=jnp.zeros((), jnp.int32),
            done=jnp.zeros((), bool),
            status=jnp.asarray(MAX_ITERATIONS, jnp.int32),
            history=jnp.full((n_hist,), jnp.nan, dtype),
        )

    s = lax.while_loop(lambda s: ~s.done, trip, initial(0, 0))
    zero_k = jnp.zeros_like(s.back.k)
    no_step = jnp.zeros((), dtype)  # α = 0: the feedback alone about the nominal (X, U)

    def feedback_rollout(X, U, K):
        return closed_loop_rollout(step, cost, x0, X, U, K, zero_k, no_step, bounds)

    if len(rules) == 1:
        X, U, J = feedback_rollout(s.X, s.U, s.back.K)
        back, mu, status = s.back, s.mu, s.status
    else:
        # Both attempts' rollouts (the first's only where it ended stuck), the cheaper kept.
        Xs, Us, Js = jax.vmap(feedback_rollout)(
            jnp.stack([s.X, s.kept_X]),
            jnp.stack([s.U, s.kept_U]),
            jnp.stack([s.back.K, s.kept_back.K]),
        )
        J_kept = jnp.where((s.attempt > 0) & jnp.isfinite(Js[1]), Js[1], jnp.inf)
        first_wins = J_kept < jnp.where(jnp.isfinite(Js[0]), Js[0], jnp.inf)
        pick = lambda a, b: jnp.where(first_wins, b, a)
        X, U, J = pick(Xs[0], Xs[1]), pick(Us[0], Us[1]), pick(Js[0], Js[1])
        back = jax.tree_util.tree_map(pick, s.back, s.kept_back)
        mu = pick(s.mu, s.kept_mu)
        status = jnp.where(first_wins, STUCK, s.status)
    return ILQRResult(
        X=X,
        U=U,
        cost=J,
        K=back.K,
        Q_uu=back.Q_uu,
        backward_ok=back.ok,
        mu=mu,
        iterations=s.trip - 1 - s.attempt,  # each attempt's first trip evaluates its guess
        accepted=s.accepted,
        rollouts=s.rollouts + 1 + s.attempt,
        status=status,
        cost_history=s.history,
    )
