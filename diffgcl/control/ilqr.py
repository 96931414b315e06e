"""iLQR: trajectory optimisation of a known cost through a differentiable simulator, with or
without box limits on the actions.

Problem (one start state): minimise ``J(U) = Σ_{t<T} c(x_t, u_t, t) + c(x_T, 0, T)`` over the
actions ``U = u_0 .. u_{T-1}`` subject to ``x_{t+1} = f(x_t, u_t)``, ``x_0`` given. Each
iteration (Li & Todorov 2004; the regularisation and line search of Tassa, Erez & Todorov 2012):

1. linearise the dynamics along the current trajectory, ``δx' = A_t δx + B_t δu`` (forward-mode
   autodiff, :func:`diffgcl.dynamics.autodiff.linearize_trajectory`; reverse mode through
   ``mjx.step`` fails when its constraint solver iterates), and expand the cost to second order
   (:func:`diffgcl.costs.expansion.expand_cost`, full Hessian; or Gauss–Newton for a residual cost
   ``c = ‖r‖²``);
2. backward pass: ``Q_uu = l_uu + BᵀV'B``, ``Q_ux = l_ux + BᵀV'A``, ``Q_u = l_u + BᵀV'_x``, the
   gains ``k = −(Q_uu + μI)⁻¹Q_u``, ``K = −(Q_uu + μI)⁻¹Q_ux`` and the value ``V_x = Q_x + KᵀQ_uu k
   + KᵀQ_u + Q_uxᵀk``, ``V_xx = Q_xx + KᵀQ_uu K + KᵀQ_ux + Q_uxᵀK`` (the quadratic model's value
   under those gains, right for any μ). ``μ ≥ 0`` regularises the actions: it is raised until
   every ``Q_uu + μI`` is positive definite (a non-convex cost, or ``V'`` indefinite far from the
   optimum) and lowered after each accepted step, so that near the optimum the step is Newton's;
3. backtracking line search on the closed-loop rollout ``u_t = U_t + α k_t + K_t (x_t − X_t)``,
   ``α = 1, β, β², ...``: a step is accepted only when the cost strictly decreases and by at least
   ``armijo`` times the decrease the quadratic model predicts, ``ΔJ(α) = α Σ kᵀQ_u +
   ½α² Σ kᵀQ_uu k``. With no acceptable α, μ rises and the backward pass is repeated on the same
   linearisation.

Control limits (Tassa, Mansard & Todorov 2014), given as ``u_min ≤ u ≤ u_max``: the rollouts
clip their actions, and in the backward pass ``k_t`` minimises the quadratic model ``½kᵀ(Q_uu +
μI)k + Q_uᵀk`` on the box ``u_min − U_t ≤ k ≤ u_max − U_t`` (projected Newton,
:mod:`diffgcl.control.box_qp`, warm-started at the last pass's ``k``), and ``K_t`` is solved on
the actions left free, zero on those held at a limit. Without it, where MuJoCo clamps ``ctrl``
to an actuator's ``ctrlrange`` the linearised ``B`` is zero past the limit and the Newton step
asks for ever larger actions that do nothing (gymnasium's double pendulum: actions of 50–60× the
range, the cart on its rail, both links fallen).

Stopping: the accepted step improved the cost by less than ``tol·(1 + |J|)``, or the model predicts
less than that at ``α = 1`` with μ at its floor (a stationary point), or μ exceeds ``mu_max``, or
``max_iterations``. The line search never accepts an increase, so ``J`` is non-increasing.

Compile time is the constraint this module is built around (each program with Jacobians through
``mjx.step`` takes 10–60 s to compile on a 2-core CPU): the iteration is one ``lax.while_loop``
whose body holds *one* closed-loop rollout (inside the line search's ``lax.while_loop``) and *one*
linearisation, and the first trip's line search is the rollout of the initial actions (gains zero,
cost +∞ before it), so there is no second call site of the simulator. Everything is written for
one start state; ``jax.vmap`` over start states (and anything the cost reads, passed as traced
arguments) gives one compiled program for all of them.

:func:`ilqr_best_of` runs iLQR from several initial action sequences of one start side by side
and keeps the cheapest, stopping a run once another has finished cheaper after as many trips.

:func:`ilqr_controller` turns a result into the :class:`~diffgcl.types.LinearGaussianController`
that GPS starts from, ``u = K_t x + (U_t − K_t X_t)`` with the final backward pass's gains and a
covariance of the shape of ``(Q_uu + μI)⁻¹`` (see there for the scaling).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
from flax import struct
from jax import lax

from diffgcl import linalg
from diffgcl.control.box_qp import box_qp
from diffgcl.control.init import with_mean_variance
from diffgcl.costs.expansion import (
    expand_cost,
    expand_residual_cost,
    shift_expansion,
    trajectory_cost,
)
from diffgcl.dynamics.autodiff import linearize, linearize_trajectory
from diffgcl.tracing import value_and_jacfwd
from diffgcl.types import Array, CostFn, LinearGaussianController, QuadraticCost, make_controller

StepFn = Callable[[Array, Array], Array]

# ILQRResult.status codes.
CONVERGED = 0  # the cost stopped improving (accepted step or predicted step below tol)
MAX_ITERATIONS = 1  # max_iterations reached while still improving
STUCK = 2  # μ rose past mu_max: no descent step found (or Q_uu never positive definite)
BEATEN = 3  # stopped by ilqr_best_of: dearer than a finished run after as many trips

STATUS_NAMES = {
    CONVERGED: "converged",
    MAX_ITERATIONS: "iteration limit",
    STUCK: "regularisation limit (no descent step)",
    BEATEN: "stopped: another initial sequence finished cheaper",
}


@dataclass(frozen=True)
class ILQRConfig:
    """Settings of :func:`ilqr` (static: each distinct config is another compiled program).

    max_iterations: backward passes after the initial rollout; tol: relative improvement below
    which the optimisation stops (``tol·(1 + |J|)``); line_search_steps: step lengths tried,
    ``α = backtrack^i``; armijo: least fraction of the predicted decrease an accepted step must
    reach; mu_init, mu_min, mu_max, mu_factor: the regularisation schedule (Tassa et al. 2012:
    the factor ``Δ`` grows geometrically while steps fail and shrinks while they succeed; μ below
    ``mu_min`` is set to 0); gauss_newton: the cost is a residual ``r(x, u, t)`` with
    ``c = ‖r‖²`` (Hessian ``2JᵀJ``, always PSD).
    """

    max_iterations: int = 100
    tol: float = 1e-6
    line_search_steps: int = 12
    backtrack: float = 0.5
    armijo: float = 1e-4
    mu_init: float = 0.0
    mu_min: float = 1e-6
    mu_max: float = 1e10
    mu_factor: float = 2.0
    gauss_newton: bool = False

    def __post_init__(self):
        if self.max_iterations < 1 or self.line_search_steps < 1:
            raise ValueError("ILQRConfig: max_iterations and line_search_steps must be >= 1")
        if not 0.0 < self.backtrack < 1.0:
            raise ValueError(f"ILQRConfig: backtrack must be in (0, 1), got {self.backtrack}")
        if self.mu_factor <= 1.0:
            raise ValueError(f"ILQRConfig: mu_factor must be > 1, got {self.mu_factor}")


@struct.dataclass
class ILQRResult:
    """What :func:`ilqr` returns for one start state (leading axes when vmapped).

    X: [T+1, dX], U: [T, dU] the optimised trajectory; cost: its total cost; K: [T, dU, dX] the
    feedback gains of the last backward pass at (X, U) (zero where it failed); Q_uu: [T, dU, dU]
    its regularised ``Q_uu + μI`` (identity where it failed); backward_ok: that pass was positive
    definite and finite; mu: the final regularisation; iterations: backward passes after the
    initial rollout; accepted: accepted steps (not counting the initial rollout); rollouts:
    closed-loop rollouts run (the initial one included); status: a module constant;
    cost_history: [max_iterations + 1], the cost after each trip (trip 0: the initial actions;
    NaN after the last trip).
    """

    X: Array
    U: Array
    cost: Array
    K: Array
    Q_uu: Array
    backward_ok: Array
    mu: Array
    iterations: Array
    accepted: Array
    rollouts: Array
    status: Array
    cost_history: Array


@struct.dataclass
class _Backward:
    K: Array  # [T, dU, dX]
    k: Array  # [T, dU]
    Q_uu: Array  # [T, dU, dU], regularised
    dV1: Array  # Σ kᵀQ_u
    dV2: Array  # ½ Σ kᵀQ_uu k
    ok: Array


def backward_pass(
    A: Array,
    B: Array,
    quad: QuadraticCost,
    mu: Array,
    lower: Array | None = None,
    upper: Array | None = None,
    k_init: Array | None = None,
    gaps: Array | None = None,
) -> _Backward:
    """The iLQR backward pass (module docstring, step 2) on deviations from the trajectory.

    A: [T, dX, dX], B: [T, dX, dU]; quad: the cost expanded *about the trajectory* (T+1 entries);
    mu: scalar regularisation. A step whose ``Q_uu + μI`` is not positive definite (or any
    non-finite value) sets ``ok = False``; the outputs stay finite (zero gains) either way.

    lower, upper: [T, dU] bounds on the action *deviations* (the actuators' range minus the
    current actions) for control-limited iLQR: ``k_t`` then solves the box QP ``min ½kᵀQ_uu k +
    Q_uᵀk`` on them (:func:`~diffgcl.control.box_qp.box_qp`, warm-started from ``k_init``) and
    ``K_t`` is solved on the free actions only, zero rows on the clamped ones (Tassa et al.
    2014). None: unconstrained.

    gaps: [T, dX] the defects ``f(X_t, U_t) − X_{t+1}`` of a trajectory that is not a rollout
    (multiple shooting, :mod:`diffgcl.control.shooting`): the linear model is then ``δx' = A δx
    + B δu + gap``, so the value's gradient seen from step t is ``V_x' + V_xx'·gap_t``. None: a
    rollout (no gaps).
    """
    dU = B.shape[-1]
    eye_u = jnp.eye(dU, dtype=B.dtype)
    boxed = lower is not None or upper is not None
    if boxed:
        T = B.shape[0]
        inf = jnp.full((T, dU), jnp.inf, B.dtype)
        lower = -inf if lower is None else jnp.broadcast_to(lower, (T, dU))
        upper = inf if upper is None else jnp.broadcast_to(upper, (T, dU))
        k_init = jnp.zeros((T, dU), B.dtype) if k_init is None else k_init

    def gains(Q_reg, Q_u, Q_ux, box):
        """(k, K, positive definite) of one step."""
        L = linalg.cholesky(Q_reg)
        pd = jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diagonal(L) > 0)
        L = jnp.where(pd, L, eye_u)
        if box is None:
            return -linalg.cho_solve(L, Q_u), -linalg.cho_solve(L, Q_ux), pd
        lo, hi, k0 = box
        qp = box_qp(Q_reg, Q_u, lo, hi, k0)
        K = -linalg.cho_solve(qp.L_free, jnp.where(qp.free[:, None], Q_ux, 0.0))
        return qp.x, K, pd & qp.ok

    def step(carry, inputs):
        V_x, V_xx, dV1, dV2, ok = carry
        A_t, B_t, l_x, l_u, l_xx, l_uu, l_ux, box, gap = inputs
        if gap is not None:
            V_x = V_x + V_xx @ gap
        Q_x = l_x + A_t.T @ V_x
        Q_u = l_u + B_t.T @ V_x
        Q_xx = l_xx + A_t.T @ V_xx @ A_t
        Q_uu = linalg.symmetrise(l_uu + B_t.T @ V_xx @ B_t)
        Q_ux = l_ux + B_t.T @ V_xx @ A_t
        Q_reg = Q_uu + mu * eye_u
        k, K, pd = gains(Q_reg, Q_u, Q_ux, box)
        V_x_new = Q_x + K.T @ (Q_uu @ k) + K.T @ Q_u + Q_ux.T @ k
        V_xx_new = linalg.symmetrise(Q_xx + K.T @ Q_uu @ K + K.T @ Q_ux + Q_ux.T @ K)
        good = (
            pd
            & jnp.all(jnp.isfinite(V_x_new))
            & jnp.all(jnp.isfinite(V_xx_new))
            & jnp.all(jnp.isfinite(K))
            & jnp.all(jnp.isfinite(k))
        )
        zero = lambda a: jnp.where(good, a, jnp.zeros_like(a))
        k, K, V_x_new, V_xx_new = zero(k), zero(K), zero(V_x_new), zero(V_xx_new)
        dV1 = dV1 + jnp.where(good, k @ Q_u, 0.0)
        dV2 = dV2 + jnp.where(good, 0.5 * k @ (Q_uu @ k), 0.0)
        Q_reg = jnp.where(good, Q_reg, eye_u)
        return (V_x_new, V_xx_new, dV1, dV2, ok & good), (K, k, Q_reg)

    V_x, V_xx = quad.l_x[-1], linalg.symmetrise(quad.l_xx[-1])
    zero = jnp.zeros((), B.dtype)
    init = (V_x, V_xx, zero, zero, jnp.all(jnp.isfinite(V_x)) & jnp.all(jnp.isfinite(V_xx)))
    box = (lower, upper, k_init) if boxed else None
    xs = (A, B, quad.l_x[:-1], quad.l_u[:-1], quad.l_xx[:-1], quad.l_uu[:-1], quad.l_ux[:-1], box,
          gaps)  # fmt: skip
    (_, _, dV1, dV2, ok), (K, k, Q_reg) = lax.scan(step, init, xs, reverse=True)
    return _Backward(K=K, k=k, Q_uu=Q_reg, dV1=dV1, dV2=dV2, ok=ok)


def closed_loop_rollout(
    step: StepFn,
    cost: CostFn,
    x0: Array,
    X: Array,
    U: Array,
    K: Array,
    k: Array,
    alpha: Array,
    bounds: tuple[Array, Array] | None = None,
) -> tuple[Array, Array, Array]:
    """``u_t = U_t + α k_t + K_t (x_t − X_t)`` from ``x0`` -> (X' [T+1, dX], U' [T, dU], J'),
    the actions clipped to ``bounds = (u_min, u_max)`` ([dU] each) where given."""

    def body(x, inputs):
        X_t, U_t, K_t, k_t = inputs
        u = U_t + alpha * k_t + K_t @ (x - X_t)
        if bounds is not None:
            u = jnp.clip(u, bounds[0], bounds[1])
        return step(x, u), (x, u)

    x_T, (X_new, U_new) = lax.scan(body, x0, (X[:-1], U, K, k))
    X_new = jnp.concatenate([X_new, x_T[None]], axis=0)
    return X_new, U_new, trajectory_cost(cost, X_new, U_new)


def squared_residual(residual: CostFn) -> CostFn:
    """The cost ``c = ‖r(x, u, t)‖²`` of a residual (``ILQRConfig.gauss_newton``)."""
    return lambda x, u, t: jnp.sum(residual(x, u, t) ** 2)


def action_box(u_min, u_max, dU: int, dtype) -> tuple[Array, Array] | None:
    """``(u_min, u_max)`` as [dU] arrays (a missing side ±inf), or None when both are None."""
    if u_min is None and u_max is None:
        return None
    lo = -jnp.inf if u_min is None else u_min
    hi = jnp.inf if u_max is None else u_max
    return tuple(jnp.broadcast_to(jnp.asarray(b, dtype), (dU,)) for b in (lo, hi))


@struct.dataclass
class _Loop:
    X: Array
    U: Array
    J: Array
    A: Array
    B: Array
    quad: QuadraticCost
    back: _Backward
    mu: Array
    delta: Array
    trip: Array
    accepted: Array
    rollouts: Array
    done: Array
    status: Array
    history: Array


def ilqr(
    step: StepFn,
    cost: CostFn,
    x0: Array,
    U_init: Array,
    config: ILQRConfig = ILQRConfig(),
    *,
    u_min: Array | None = None,
    u_max: Array | None = None,
) -> ILQRResult:
    """Minimise the cost of the rollout from ``x0: [dX]`` over actions, starting from
    ``U_init: [T, dU]`` (module docstring). ``step(x, u) -> x'`` and ``cost(x, u, t)`` are pure
    JAX functions for one instance (a residual ``r(x, u, t)`` with ``config.gauss_newton``);
    vmap over ``x0`` (and any traced values ``cost`` closes over) at the call site.

    u_min, u_max: [dU] (or scalars; ±inf for an unlimited action) the actions' box, for
    control-limited iLQR (module docstring): ``U_init`` is clipped to it, every rollout clips its
    actions, and the backward pass solves a box QP per step. Give them wherever the simulator
    clamps the actions (MuJoCo's ``ctrlrange``): past a limit the simulator's ``B`` is zero and
    unconstrained iLQR keeps pushing where it has no authority. None (both): unconstrained.
    """
    init, trip = _ilqr_loop(step, cost, x0, U_init, config, u_min, u_max)
    return _result(lax.while_loop(lambda s: ~s.done, trip, init))


def ilqr_best_of(
    step: StepFn,
    cost: CostFn,
    x0: Array,
    U_inits: Array,
    config: ILQRConfig = ILQRConfig(),
    *,
    u_min: Array | None = None,
    u_max: Array | None = None,
) -> tuple[ILQRResult, Array, ILQRResult]:
    """:func:`ilqr` from ``x0: [dX]`` and each of the initial sequences ``U_inits: [R, T, dU]``,
    side by side in one loop, keeping the cheapest finished run -> (that run's ILQRResult, its
    index, every run's ILQRResult [R]).

    A run stops early, with status :data:`BEATEN`, once another run has finished (any status,
    finite cost) at a lower cost and this one has had as many trips: equal effort, and the
    dearer one is dropped. Why: the runs of one vmapped loop end together, when the slowest
    ends, and the runs differ by orders of magnitude — balancing gymnasium's double pendulum,
    iLQR from the goal's LQR converges in 0–2 iterations, from zero actions (the system falls)
    in 47–100, and that run is then discarded. Its cost can only decide the choice if it falls
    below the finished run's, and after the same number of trips it had not; a run that is
    ahead, or has had fewer trips, goes on. What this gives up: a run that is dearer after equal
    effort but would end cheaper (iLQR's runs to different local optima can cross); the runs of
    :func:`ilqr` from each sequence separately keep that chance, at the slowest run's time.
    A run never stops on a tie, so identical initial sequences both run to the end.
    """
    if U_inits.ndim != 3:
        raise ValueError(f"ilqr_best_of: U_inits must be [R, T, dU], got {tuple(U_inits.shape)}")
    R = U_inits.shape[0]
    loop = lambda U: _ilqr_loop(step, cost, x0, U, config, u_min, u_max)
    init = jax.vmap(lambda U: loop(U)[0])(U_inits)
    trip = loop(U_inits[0])[1]  # a function of the state alone: the same for every run
    others = ~jnp.eye(R, dtype=bool)

    def race(S: _Loop) -> _Loop:
        new = jax.vmap(trip)(S)
        keep = lambda old, upd: jnp.where(S.done.reshape((R,) + (1,) * (upd.ndim - 1)), old, upd)
        new = jax.tree.map(keep, S, new)
        finished = new.done & jnp.isfinite(new.J)
        beats = (  # beats[r, q]: run q finished cheaper than run r, which has had as many trips
            others
            & finished[None, :]
            & (new.J[None, :] < new.J[:, None])
            & (new.trip[:, None] >= new.trip[None, :])
        )
        beaten = ~new.done & jnp.any(beats, axis=1)
        return new.replace(done=new.done | beaten, status=jnp.where(beaten, BEATEN, new.status))

    final = lax.while_loop(lambda S: ~jnp.all(S.done), race, init)
    runs = jax.vmap(_result)(final)
    kept, best = cheapest_run(runs)
    return kept, best, runs


def cheapest_run(runs: ILQRResult) -> tuple[ILQRResult, Array]:
    """Of runs from one start (fields [R, ...]), the one with the lowest finite final cost ->
    (its ILQRResult, its index); vmap over further axes."""
    costs = jnp.where(jnp.isfinite(runs.cost), runs.cost, jnp.inf)
    best = jnp.argmin(costs)
    return jax.tree.map(lambda a: a[best], runs), best


def _ilqr_loop(step, cost, x0, U_init, config, u_min, u_max) -> tuple[_Loop, Callable]:
    """:func:`ilqr`'s loop: (the state before trip 0, one trip ``_Loop -> _Loop``). A trip on a
    state that is already ``done`` runs no line search (its result is discarded: under ``vmap``
    a finished lane would otherwise hold the line search's loop for the others)."""
    T, dU = U_init.shape
    dX = x0.shape[-1]
    dtype = x0.dtype
    U_init = U_init.astype(dtype)
    bounds = action_box(u_min, u_max, dU, dtype)
    if bounds is not None:
        U_init = jnp.clip(U_init, bounds[0], bounds[1])
        # The limits moved inwards by 1e-5 of the range (unchanged where a limit is infinite).
        width = bounds[1] - bounds[0]
        margin = jnp.where(jnp.isfinite(width), 1e-5 * width, 0.0)
        inner = (bounds[0] + margin, bounds[1] - margin)
    tol, armijo = config.tol, config.armijo
    n_hist = config.max_iterations + 1
    if config.gauss_newton:
        expand = lambda X, U: expand_residual_cost(cost, X, U)
        true_cost = squared_residual(cost)
    else:
        expand = lambda X, U: expand_cost(cost, X, U)
        true_cost = cost

    def linearise(X, U):
        # An action exactly at a limit is where the simulator's clip is not differentiable, and
        # JAX's derivative there is the mean of the two sides (jnp.clip) or zero (lax.clamp):
        # B at half its value or none, so the box QP can see a descent direction into the box
        # that the simulator does not have. The limits only let an action move inwards, so B
        # is taken just inside them: the one-sided derivative the step will see.
        U_lin = U if bounds is None else jnp.clip(U, inner[0], inner[1])
        A, B = linearize_trajectory(step, X, U_lin)
        return A, B, expand(X, U)

    def line_search(s: _Loop):
        """(accepted, X', U', J', rollouts run) of the gains in ``s.back``."""
        b = s.back

        def cond(c):
            i, accepted = c[0], c[1]
            return (~accepted) & (i < config.line_search_steps) & b.ok & ~s.done

        def body(c):
            i, _, X_best, U_best, J_best = c
            alpha = jnp.asarray(config.backtrack, dtype) ** i
            X_new, U_new, J_new = closed_loop_rollout(
                step, true_cost, x0, s.X, s.U, b.K, b.k, alpha, bounds
            )
            predicted = -(alpha * b.dV1 + alpha**2 * b.dV2)
            ok = jnp.isfinite(J_new) & (J_new < s.J) & (s.J - J_new >= armijo * predicted)
            X_best = jnp.where(ok, X_new, X_best)
            U_best = jnp.where(ok, U_new, U_best)
            J_best = jnp.where(ok, J_new, J_best)
            return i + 1, ok, X_best, U_best, J_best

        i, accepted, X_new, U_new, J_new = lax.while_loop(
            cond, body, (jnp.zeros((), jnp.int32), jnp.zeros((), bool), s.X, s.U, s.J)
        )
        return accepted, X_new, U_new, J_new, i

    def trip(s: _Loop) -> _Loop:
        accepted, X, U, J, n = line_search(s)
        first = s.trip == 0
        improvement = s.J - J
        A, B, quad = lax.cond(accepted, lambda: linearise(X, U), lambda: (s.A, s.B, s.quad))
        # Regularisation schedule (Tassa et al. 2012): shrink after a success, grow after a failure.
        f = config.mu_factor
        delta_down = jnp.minimum(s.delta / f, 1.0 / f)
        mu_down = s.mu * delta_down
        mu_down = jnp.where(mu_down < config.mu_min, 0.0, mu_down)
        delta_up = jnp.maximum(s.delta * f, f)
        mu_up = jnp.maximum(config.mu_min, s.mu * delta_up)
        mu = jnp.where(accepted, mu_down, mu_up).astype(dtype)
        delta = jnp.where(accepted, delta_down, delta_up).astype(dtype)
        mu = jnp.where(first, jnp.asarray(config.mu_init, dtype), mu)
        delta = jnp.where(first, jnp.ones((), dtype), delta)
        if bounds is None:
            back = backward_pass(A, B, quad, mu)
        else:  # the box on the deviations from the current actions, warm-started at the last k
            back = backward_pass(A, B, quad, mu, bounds[0] - U, bounds[1] - U, s.back.k)
        scale = tol * (1.0 + jnp.abs(J))
        small_step = accepted & ~first & (improvement < scale)
        predicted = -(back.dV1 + back.dV2)
        stationary = back.ok & (mu <= config.mu_min) & (predicted < scale)
        converged = small_step | stationary
        stuck = mu > config.mu_max
        last = s.trip + 1 >= n_hist
        done = converged | stuck | last | (first & ~accepted)
        status = jnp.where(converged, CONVERGED, jnp.where(stuck, STUCK, MAX_ITERATIONS))
        status = jnp.where(first & ~accepted, STUCK, status)  # the initial rollout is not finite
        return _Loop(
            X=X,
            U=U,
            J=J,
            A=A,
            B=B,
            quad=quad,
            back=back,
            mu=mu,
            delta=delta,
            trip=s.trip + 1,
            accepted=s.accepted + (accepted & ~first).astype(jnp.int32),
            rollouts=s.rollouts + n,
            done=done,
            status=status.astype(jnp.int32),
            history=s.history.at[s.trip].set(J),
        )

    zeros = lambda *shape: jnp.zeros(shape, dtype)
    quad0 = zero_expansion(T, dX, dU, dtype)
    # Trip 0: zero gains and J = +inf, so its line search is the rollout of U_init.
    back0 = no_gains(T, dX, dU, dtype)
    init = _Loop(
        X=jnp.broadcast_to(x0, (T + 1, dX)),
        U=U_init,
        J=jnp.asarray(jnp.inf, dtype),
        A=zeros(T, dX, dX),
        B=zeros(T, dX, dU),
        quad=quad0,
        back=back0,
        mu=jnp.asarray(config.mu_init, dtype),
        delta=jnp.ones((), dtype),
        trip=jnp.zeros((), jnp.int32),
        accepted=jnp.zeros((), jnp.int32),
        rollouts=jnp.zeros((), jnp.int32),
        done=jnp.zeros((), bool),
        status=jnp.asarray(MAX_ITERATIONS, jnp.int32),
        history=jnp.full((n_hist,), jnp.nan, dtype),
    )
    return init, trip


def zero_expansion(T: int, dX: int, dU: int, dtype) -> QuadraticCost:
    """An all-zero cost expansion of T+1 steps: a solver loop's state before its first
    linearisation."""
    zeros = lambda *shape: jnp.zeros(shape, dtype)
    return QuadraticCost(
        l=zeros(T + 1),
        l_x=zeros(T + 1, dX),
        l_u=zeros(T + 1, dU),
        l_xx=zeros(T + 1, dX, dX),
        l_uu=zeros(T + 1, dU, dU),
        l_ux=zeros(T + 1, dU, dX),
    )


def no_gains(T: int, dX: int, dU: int, dtype) -> _Backward:
    """A backward pass with zero gains (``Q_uu`` the identity): a step of nothing."""
    zeros = lambda *shape: jnp.zeros(shape, dtype)
    return _Backward(
        K=zeros(T, dU, dX),
        k=zeros(T, dU),
        Q_uu=jnp.broadcast_to(jnp.eye(dU, dtype=dtype), (T, dU, dU)),
        dV1=zeros(),
        dV2=zeros(),
        ok=jnp.ones((), bool),
    )


def _result(s: _Loop) -> ILQRResult:
    return ILQRResult(
        X=s.X,
        U=s.U,
        cost=s.J,
        K=s.back.K,
        Q_uu=s.back.Q_uu,
        backward_ok=s.back.ok,
        mu=s.mu,
        iterations=s.trip - 1,
        accepted=s.accepted,
        rollouts=s.rollouts,
        status=s.status,
        cost_history=s.history,
    )


def cost_minimiser(
    cost: CostFn, x_init: Array, dU: int, t: int | Array, iterations: int = 20
) -> Array:
    """The state where ``c(x, 0, t)`` is lowest, by regularised Newton from ``x_init: [dX]``
    (``x ← x − (H + εI)⁻¹∇c``, ``ε = 10⁻⁶·(1 + max|diag H|)``; a step whose ``H + εI`` is not
    positive definite is not taken): for a quadratic cost its goal after one step, with the
    coordinates the cost ignores left at ``x_init``'s."""
    u = jnp.zeros((dU,), x_init.dtype)
    f = lambda x: cost(x, u, t)
    eye = jnp.eye(x_init.shape[-1], dtype=x_init.dtype)

    def newton(x, _):
        g, H = value_and_jacfwd(jax.grad(f))(x)
        H = linalg.symmetrise(H)
        H = H + 1e-6 * (1.0 + jnp.max(jnp.abs(jnp.diagonal(H)))) * eye
        L = linalg.cholesky(H)
        pd = jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diagonal(L) > 0)
        step = linalg.cho_solve(jnp.where(pd, L, eye), g)
        return jnp.where(pd & jnp.all(jnp.isfinite(step)), x - step, x), None

    return lax.scan(newton, x_init, None, length=iterations)[0]


def goal_lqr_actions(
    step: StepFn,
    cost: CostFn,
    x0: Array,
    x_goal: Array,
    T: int,
    dU: int,
    *,
    u_min: Array | None = None,
    u_max: Array | None = None,
) -> Array:
    """Initial actions [T, dU] for :func:`ilqr`: the rollout from ``x0`` of the time-varying
    LQR of the dynamics linearised at the goal ``(x_goal, u = 0)`` (an affine model where the
    goal is not an equilibrium) and the cost expanded there, its actions clipped to the box.

    Why: iLQR linearises along its current trajectory. From zero actions an unstable system
    (gymnasium's double pendulum) falls at once, and the Newton steps taken along a fallen
    trajectory find local optima that swing instead of balancing. The LQR of the upright
    linearisation is the textbook stabiliser; where it catches the system iLQR starts next to
    the answer. Only meaningful where the goal is an equilibrium at ``u ≈ 0`` (balancing,
    holding a pose); elsewhere it is one more start to try (:func:`diffgcl.algorithms.trajopt.solve`
    keeps the cheaper result).
    """
    dX = x0.shape[-1]
    dtype = x0.dtype
    U_zero = jnp.zeros((T, dU), dtype)
    A_goal, B_goal = linearize(step, x_goal, U_zero[0])
    A, B = jnp.broadcast_to(A_goal, (T, dX, dX)), jnp.broadcast_to(B_goal, (T, dX, dU))
    # The affine model x' − g = A(x − g) + B u + d, d = f(g, 0) − g (zero at an equilibrium);
    # its free response from g is the trajectory the backward pass's deviations are about.
    drift = step(x_goal, U_zero[0]) - x_goal

    def free(x, _):
        return x_goal + A_goal @ (x - x_goal) + drift, x

    x_T, X_ref = lax.scan(free, x_goal, None, length=T)
    X_ref = jnp.concatenate([X_ref, x_T[None]])
    X_goal = jnp.broadcast_to(x_goal, (T + 1, dX))
    quad = shift_expansion(expand_cost(cost, X_goal, U_zero), X_goal, U_zero, X_ref, U_zero)
    back = backward_pass(A, B, quad, jnp.zeros((), dtype))
    bounds = action_box(u_min, u_max, dU, dtype)
    one = jnp.ones((), dtype)
    _, U, _ = closed_loop_rollout(step, cost, x0, X_ref, U_zero, back.K, back.k, one, bounds)
    return jnp.where(back.ok & jnp.all(jnp.isfinite(U)), U, U_zero)


def ilqr_controller(
    result: ILQRResult, *, init_var: float | Array | None = None, temperature: float | Array = 1.0
) -> LinearGaussianController:
    """The time-varying linear-Gaussian controller of an iLQR solution (one start state).

    Mean ``u_t = K_t x + k_t`` with ``k_t = U_t − K_t X_t`` (the solution's closed loop: it
    reproduces (X, U) from the same start and corrects deviations with the last backward pass's
    gains). Covariance ``Σ_t ∝ (Q_uu,t + μI)⁻¹``: the action directions the cost-to-go is flat in
    explore most. Its scale:

    * ``init_var=None``: ``Σ_t = temperature · (Q_uu,t + μI)⁻¹`` — with temperature 1 the
      maximum-entropy controller of the cost linearised about the solution, ``p(u|x) ∝
      exp(−Q(x, u))`` (the demonstrator model GCL assumes);
    * ``init_var=v`` (what GPS starts from): that shape rescaled so that the mean over time and
      actions of its diagonal is ``v`` — GPS's exploration budget ``init_var`` in the directions
      the cost leaves free. ``v`` may be traced.
    """
    cov = linalg.inverse_from_cholesky(linalg.cholesky(result.Q_uu))
    k = result.U - jnp.einsum("tij,tj->ti", result.K, result.X[:-1])
    controller = make_controller(result.K, k, temperature * linalg.symmetrise(cov))
    return controller if init_var is None else with_mean_variance(controller, init_var)


def describe(result: ILQRResult) -> list[str]:
    """One line per start state (host-side): status, cost, iterations."""
    status = jnp.atleast_1d(result.status)
    cost = jnp.atleast_1d(result.cost)
    its = jnp.atleast_1d(result.iterations)
    return [
        f"{STATUS_NAMES[int(s)]}: cost {float(c):.6g} after {int(i)} iterations"
        for s, c, i in zip(status, cost, its, strict=True)
    ]
