"""iLQR (diffgcl.control.ilqr) against independent references, float64, tiny horizons."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lqr_problems import random_problem
from test_lqr import riccati_numpy

from diffgcl.control.ilqr import (
    BEATEN,
    CONVERGED,
    ILQRConfig,
    backward_pass,
    cost_minimiser,
    goal_lqr_actions,
    ilqr,
    ilqr_best_of,
    ilqr_controller,
)
from diffgcl.sim.rollout import rollout_controller


class _LinearEnv:
    """x' = A x + B u + c for rollout_controller (the Env protocol's step only)."""

    def __init__(self, A, B, c):
        self.A, self.B, self.c = A, B, c
        self.dX, self.dU = B.shape

    def step(self, x, u):
        return self.A @ x + self.B @ u + self.c


def _lq_problem(seed=1, T=8):
    """Time-invariant linear dynamics, a time-varying convex quadratic cost with cross terms."""
    dynamics, quad, _, x0 = random_problem(seed=seed, T=T)
    A, B, c = (np.asarray(a[0]) for a in (dynamics.A, dynamics.B, dynamics.c))
    step = lambda x, u: jnp.asarray(A) @ x + jnp.asarray(B) @ u + jnp.asarray(c)

    def cost(x, u, t):
        return (
            quad.l[t]
            + quad.l_x[t] @ x
            + quad.l_u[t] @ u
            + 0.5 * x @ quad.l_xx[t] @ x
            + 0.5 * u @ quad.l_uu[t] @ u
            + u @ quad.l_ux[t] @ x
        )

    return A, B, c, quad, np.asarray(x0.mean), step, cost


def _riccati_rollout(A, B, c, quad, x0):
    """The optimal actions of the LQ problem by the NumPy Riccati recursion -> (U [T, dU], K)."""
    n = np.asarray
    T = n(quad.l_u).shape[0] - 1
    tile = lambda a: np.broadcast_to(a, (T, *a.shape)).copy()
    K_ref, k_ref, _ = riccati_numpy(
        tile(A), tile(B), tile(c), n(quad.l_xx[:-1]), n(quad.l_uu[:-1]), n(quad.l_ux[:-1]),
        n(quad.l_x[:-1]), n(quad.l_u[:-1]), n(quad.l_xx[-1]), n(quad.l_x[-1]),
    )  # fmt: skip
    x, U_ref = x0.copy(), []
    for t in range(T):
        U_ref.append(K_ref[t] @ x + k_ref[t])
        x = A @ x + B @ U_ref[-1] + c
    return np.stack(U_ref), K_ref


def test_lq_problem_equals_riccati_solution():
    """On a linear-quadratic problem iLQR's solution is the Riccati controller's rollout, its
    final gains are the Riccati gains, and it gets there in one accepted Newton step."""
    T = 8
    A, B, c, quad, x0, step, cost = _lq_problem(T=T)
    n = np.asarray
    U_ref, K_ref = _riccati_rollout(A, B, c, quad, x0)
    result = jax.jit(lambda x0: ilqr(step, cost, x0, jnp.zeros((T, 2))))(jnp.asarray(x0))
    assert int(result.status) == CONVERGED
    np.testing.assert_allclose(result.U, U_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(result.K, K_ref, rtol=0, atol=1e-9)
    assert int(result.accepted) == 1
    # The Gauss–Newton mode on the residual form of the same cost (c = ‖r‖² + const) agrees.
    H = np.block([[n(quad.l_xx), np.swapaxes(n(quad.l_ux), -1, -2)], [n(quad.l_ux), n(quad.l_uu)]])
    dX = A.shape[0]
    H[-1, dX:, :] = 0.0
    H[-1, :, dX:] = 0.0
    H[-1, dX:, dX:] = np.eye(2)  # the terminal action is 0 and unused
    L = jnp.asarray(np.linalg.cholesky(H / 2.0))
    g = np.concatenate([n(quad.l_x), n(quad.l_u)], -1)
    shift = jnp.asarray(np.linalg.solve(H, g[..., None])[..., 0])  # ½zᵀHz + gᵀz = ‖Lᵀ(z + s)‖²

    def residual(x, u, t):
        return L[t].T @ (jnp.concatenate([x, u]) + shift[t])

    gn = ilqr(step, residual, jnp.asarray(x0), jnp.zeros((T, 2)), ILQRConfig(gauss_newton=True))
    np.testing.assert_allclose(gn.U, U_ref, rtol=0, atol=1e-9)


def test_goal_lqr_actions_of_an_lq_problem_are_its_optimum():
    """Linear dynamics and a quadratic cost are their own expansion about any point, so the LQR
    at the goal is the problem's Riccati solution, whatever the goal; the terminal cost's
    minimiser is ``−l_xx⁻¹ l_x``."""
    T = 8
    A, B, c, quad, x0, step, cost = _lq_problem(T=T)
    U_ref, _ = _riccati_rollout(A, B, c, quad, x0)
    x_goal = cost_minimiser(cost, jnp.asarray(x0), 2, T)
    l_xx, l_x = np.asarray(quad.l_xx[T]), np.asarray(quad.l_x[T])
    np.testing.assert_allclose(x_goal, np.linalg.solve(l_xx, -l_x), rtol=1e-9, atol=1e-12)
    for goal in (x_goal, jnp.asarray(x0) + 1.0):
        U = goal_lqr_actions(step, cost, jnp.asarray(x0), goal, T, 2)
        np.testing.assert_allclose(U, U_ref, rtol=0, atol=1e-9)
    # With a box the rollout clips the LQR's actions.
    limit = 0.4 * np.abs(U_ref).max()
    U = goal_lqr_actions(step, cost, jnp.asarray(x0), x_goal, T, 2, u_min=-limit, u_max=limit)
    assert float(jnp.abs(U).max()) == pytest.approx(limit)


def _pendulum(dt=0.1, T=40):
    """A damped pendulum, θ = 0 hanging, swung up towards θ = π by a torque too weak to lift it
    directly (it has to pump)."""

    def step(x, u):
        th, om = x
        om = om + dt * (-9.81 * jnp.sin(th) - 0.1 * om + 1.0 * u[0])
        return jnp.stack([th + dt * om, om])

    def cost(x, u, t):
        terminal = t == T
        w = jnp.where(terminal, 100.0, 1.0)
        return w * ((x[0] - jnp.pi) ** 2 + 0.1 * x[1] ** 2) + 0.05 * u @ u

    return step, cost


def test_line_search_never_accepts_a_cost_increase():
    """Swinging a pendulum up from rest: full Newton steps overshoot (the line search backtracks),
    yet every trip's cost is at most the previous one, and the optimum is stationary: central
    finite differences of J(U) in float64 are ~0."""
    T = 40
    step, cost = _pendulum(T=T)
    tight = ILQRConfig(tol=1e-12)  # run to the stationary point for the finite differences
    solve = jax.jit(lambda x0: ilqr(step, cost, x0, jnp.zeros((T, 1)), tight))
    result = solve(jnp.array([0.0, 0.0]))
    history = np.asarray(result.cost_history)
    history = history[np.isfinite(history)]
    assert len(history) == int(result.iterations) + 1
    assert np.all(np.diff(history) <= 0.0), history
    # Some step lengths were tried and refused (more rollouts than trips with a step).
    assert int(result.rollouts) > int(result.iterations) + 1
    assert int(result.status) == CONVERGED
    assert history[0] > 3 * history[-1]

    @jax.jit
    def J(U):  # an independent rollout, a Python loop
        x, total = jnp.array([0.0, 0.0]), 0.0
        for t in range(T):
            total = total + cost(x, U[t], t)
            x = step(x, U[t])
        return total + cost(x, jnp.zeros(1), T)

    U = np.asarray(result.U)
    eps = 1e-6
    fd = np.zeros_like(U)
    for t in range(T):
        e = np.zeros_like(U)
        e[t, 0] = eps
        fd[t, 0] = (float(J(U + e)) - float(J(U - e))) / (2 * eps)
    scale = np.abs(history[0]) / T
    assert np.abs(fd).max() < 1e-6 * scale, np.abs(fd).max()


def test_backward_pass_raises_no_nan_on_indefinite_cost():
    """A concave action cost: Q_uu is not positive definite at μ = 0 (ok False, finite output)
    and is at μ large enough."""
    T, dX, dU = 4, 2, 1
    A = jnp.broadcast_to(jnp.eye(dX), (T, dX, dX))
    B = jnp.broadcast_to(jnp.ones((dX, dU)), (T, dX, dU))
    _, quad, _, _ = random_problem(seed=3, T=T, dX=dX, dU=dU)
    bad = quad.replace(l_uu=quad.l_uu.at[:-1].set(-50.0 * jnp.eye(dU)))
    low = backward_pass(A, B, bad, jnp.asarray(0.0))
    assert not bool(low.ok)
    assert all(np.all(np.isfinite(a)) for a in jax.tree.leaves(low))
    assert bool(backward_pass(A, B, bad, jnp.asarray(1e4)).ok)


def test_vmapped_equals_unbatched_and_one_program_serves_all_starts():
    T = 20
    step, cost = _pendulum(T=T)
    solve = jax.jit(jax.vmap(lambda x0: ilqr(step, cost, x0, jnp.zeros((T, 1)))))
    X0 = jnp.array([[0.0, 0.0], [0.5, -1.0], [-0.3, 2.0]])
    batched = solve(X0)
    single = jax.jit(lambda x0: ilqr(step, cost, x0, jnp.zeros((T, 1))))
    for i in range(3):
        one = single(X0[i])
        np.testing.assert_allclose(batched.U[i], one.U, rtol=0, atol=1e-10)
        assert float(batched.cost[i]) == pytest.approx(float(one.cost), rel=1e-12)
        assert int(batched.iterations[i]) == int(one.iterations)
    solve(X0 + 0.1)  # new start states, same program
    assert solve._cache_size() == 1


def test_best_of_stops_a_run_only_once_a_finished_run_is_cheaper_after_as_many_trips():
    """ilqr_best_of on the pendulum swing-up from four initial sequences: zeros, the solution
    from zeros (finishes at once), ±0.3 held. The kept run is the cheapest finished one; every
    run not stopped is exactly ilqr from its sequence alone; every stopped run is dearer than a
    run that finished in no more trips, and stopped after far fewer trips than it needs alone
    (alone, +0.3 and −0.3 end 1.5e-6 and 1.2e-6 cheaper than the solution from zeros: the
    chance the rule gives up). Identical sequences are never stopped (a tie). Vmapped over
    starts equals one start."""
    T = 40
    step, cost = _pendulum(T=T)
    alone = jax.jit(lambda x0, U: ilqr(step, cost, x0, U))
    best_of = jax.jit(lambda x0, Us: ilqr_best_of(step, cost, x0, Us))
    x0 = jnp.array([0.0, 0.0])
    solution = alone(x0, jnp.zeros((T, 1))).U
    Us = jnp.stack([jnp.zeros((T, 1)), solution, jnp.full((T, 1), 0.3), jnp.full((T, 1), -0.3)])
    kept, index, runs = best_of(x0, Us)
    status = np.asarray(runs.status)
    cost_, trips = np.asarray(runs.cost), np.asarray(runs.iterations) + 1
    assert int(index) == int(np.argmin(cost_)) and float(kept.cost) == cost_.min()
    finished = status != BEATEN
    assert finished[1] and (~finished).sum() >= 2, status  # zeros and at least one other stop
    for r in range(4):
        single = alone(x0, Us[r])
        if finished[r]:
            np.testing.assert_allclose(runs.U[r], single.U, rtol=0, atol=1e-10)
            assert int(runs.iterations[r]) == int(single.iterations)
        else:
            beaten_by = finished & (cost_ < cost_[r]) & (trips <= trips[r])
            assert beaten_by.any(), (r, cost_, trips, status)
            assert trips[r] < (int(single.iterations) + 1) / 2, (r, trips[r], single.iterations)
    np.testing.assert_allclose(kept.U, runs.U[index], rtol=0, atol=0)

    twins = best_of(x0, jnp.stack([jnp.zeros((T, 1))] * 2))[2]
    assert np.all(np.asarray(twins.status) == CONVERGED)
    np.testing.assert_array_equal(twins.U[0], twins.U[1])

    X0 = jnp.array([[0.0, 0.0], [0.5, -1.0]])
    batched = jax.jit(jax.vmap(lambda x, Us: ilqr_best_of(step, cost, x, Us)[0]))(
        X0, jnp.stack([Us, Us])
    )
    for i in range(2):
        one = best_of(X0[i], Us)[0]
        np.testing.assert_allclose(batched.U[i], one.U, rtol=0, atol=1e-10)
        assert int(batched.iterations[i]) == int(one.iterations)


def test_controller_reproduces_the_solution():
    """The iLQR controller's noise-free rollout is the optimised trajectory; with ``init_var``
    the covariance has the shape of (Q_uu + μI)⁻¹ and mean variance init_var."""
    T = 8
    A, B, c, _, x0, step, cost = _lq_problem(seed=2, T=T)
    result = ilqr(step, cost, jnp.asarray(x0), jnp.zeros((T, 2)))
    env = _LinearEnv(jnp.asarray(A), jnp.asarray(B), jnp.asarray(c))
    ctrl = ilqr_controller(result)
    traj = rollout_controller(env, ctrl, jnp.asarray(x0), jnp.zeros((T, 2)))
    np.testing.assert_allclose(traj.X, result.X, rtol=0, atol=1e-10)
    np.testing.assert_allclose(ctrl.inv_cov, result.Q_uu, rtol=1e-10, atol=1e-10)
    scaled = ilqr_controller(result, init_var=0.05)
    diag = np.diagonal(np.asarray(scaled.cov), axis1=-2, axis2=-1)
    assert diag.mean() == pytest.approx(0.05)
    ratio = np.asarray(scaled.cov) / np.asarray(ctrl.cov)
    np.testing.assert_allclose(ratio, ratio.flat[0], rtol=1e-10)


def _numpy_cost_and_gradient(A, B, c, quad, x0):
    """J(U) of the LQ problem and its gradient by the adjoint recursion, in NumPy (the
    reference for the control-limited tests)."""
    n = np.asarray
    l_x, l_u, l_xx = n(quad.l_x), n(quad.l_u), n(quad.l_xx)
    l_uu, l_ux = n(quad.l_uu), n(quad.l_ux)
    l0 = n(quad.l)
    T = l_u.shape[0] - 1

    def J_and_grad(U_flat):
        U = U_flat.reshape(T, -1)
        X = [x0]
        for t in range(T):
            X.append(A @ X[-1] + B @ U[t] + c)
        J = sum(
            l0[t] + l_x[t] @ X[t] + l_u[t] @ U[t] + 0.5 * X[t] @ l_xx[t] @ X[t]
            + 0.5 * U[t] @ l_uu[t] @ U[t] + U[t] @ l_ux[t] @ X[t]
            for t in range(T)
        ) + l0[T] + l_x[T] @ X[T] + 0.5 * X[T] @ l_xx[T] @ X[T]  # fmt: skip
        lam = l_x[T] + l_xx[T] @ X[T]  # ∂J/∂x_T
        grad = np.zeros_like(U)
        for t in reversed(range(T)):
            grad[t] = l_u[t] + l_uu[t] @ U[t] + l_ux[t] @ X[t] + B.T @ lam
            lam = l_x[t] + l_xx[t] @ X[t] + l_ux[t].T @ U[t] + A.T @ lam
        return J, grad.ravel()

    return J_and_grad


def test_control_limited_lq_problem_meets_kkt_and_matches_scipy():
    """A linear-quadratic problem whose unconstrained optimum breaks the action box: control-
    limited iLQR ends at the box QP's optimum — its projected gradient (NumPy adjoint) vanishes,
    and its cost and actions equal scipy's L-BFGS-B on the condensed problem."""
    from scipy.optimize import minimize

    T = 8
    A, B, c, quad, x0, step, cost = _lq_problem(T=T)
    free = ilqr(step, cost, jnp.asarray(x0), jnp.zeros((T, 2)))
    limit = 0.4 * np.abs(np.asarray(free.U)).max(axis=0)  # per action: the optimum saturates
    config = ILQRConfig(tol=1e-13)
    lo, hi = -jnp.asarray(limit), jnp.asarray(limit)
    solve = jax.jit(lambda x0: ilqr(step, cost, x0, jnp.zeros((T, 2)), config, u_min=lo, u_max=hi))
    result = solve(jnp.asarray(x0))
    U = np.asarray(result.U)
    assert int(result.status) == CONVERGED
    assert np.all(np.abs(U) <= limit + 1e-12)
    at_limit = np.isclose(np.abs(U), limit, rtol=0, atol=1e-9)
    assert at_limit.sum() >= 2
    J_and_grad = _numpy_cost_and_gradient(A, B, c, quad, x0)
    J, grad = J_and_grad(U.ravel())
    grad = grad.reshape(T, 2)
    assert J == pytest.approx(float(result.cost), rel=1e-12)
    # KKT: zero gradient on free actions; at a limit it points outwards (−∂J/∂u towards the bound).
    scale = np.abs(grad).max()
    assert np.abs(grad[~at_limit]).max() < 1e-6 * scale
    assert np.all(grad[at_limit] * np.sign(U[at_limit]) <= 1e-9 * scale)
    ref = minimize(J_and_grad, np.zeros(2 * T), jac=True, method="L-BFGS-B",
                   bounds=[(-limit[i % 2], limit[i % 2]) for i in range(2 * T)],
                   options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10_000})  # fmt: skip
    assert float(result.cost) <= ref.fun + 1e-9 * abs(ref.fun)
    np.testing.assert_allclose(U.ravel(), ref.x, atol=1e-5)
    # The gains on a saturated action are zero (it cannot respond to a deviation).
    K = np.asarray(result.K)
    assert np.abs(K[at_limit]).max() == 0.0


def test_control_limited_line_search_never_increases_the_cost():
    """The pendulum swing-up with its torque limited to ±2: every rollout respects the box, the
    cost never rises, and the solution uses the limit (where an unconstrained iLQR would not
    stay inside it)."""
    T = 40
    step, cost = _pendulum(T=T)
    U0 = jnp.zeros((T, 1))
    solve = jax.jit(lambda x0, lo, hi: ilqr(step, cost, x0, U0, u_min=lo, u_max=hi))
    unlimited = jax.jit(lambda x0: ilqr(step, cost, x0, jnp.zeros((T, 1))))(jnp.zeros(2))
    assert float(jnp.abs(unlimited.U).max()) > 2.0
    result = solve(jnp.zeros(2), -2.0, 2.0)
    history = np.asarray(result.cost_history)
    history = history[np.isfinite(history)]
    assert np.all(np.diff(history) <= 0.0), history
    assert float(jnp.abs(result.U).max()) <= 2.0 + 1e-12
    assert float(jnp.abs(result.U).max()) == pytest.approx(2.0)
    assert float(result.cost) >= float(unlimited.cost)  # a tighter box cannot do better
    assert int(result.status) == CONVERGED


def test_infinite_limits_equal_the_unconstrained_solver():
    T = 20
    step, cost = _pendulum(T=T)
    x0 = jnp.array([0.3, -0.5])
    free = ilqr(step, cost, x0, jnp.zeros((T, 1)))
    boxed = ilqr(step, cost, x0, jnp.zeros((T, 1)), u_min=-jnp.inf, u_max=jnp.inf)
    np.testing.assert_allclose(boxed.U, free.U, rtol=0, atol=1e-10)
    np.testing.assert_allclose(boxed.K, free.K, rtol=0, atol=1e-9)


def test_actions_resting_at_a_limit_of_a_clipping_simulator():
    """A simulator that clips its actions to the box (as MuJoCo clamps ``ctrl`` to
    ``ctrlrange``), started from actions all at one limit or the other: the derivative of the
    clip at the limit itself is not the simulator's (JAX gives half of it), so iLQR must
    linearise just inside the box. It converges (not a stall) from every start, to the optimum
    of the box-constrained problem (scipy's L-BFGS-B on the NumPy adjoint gradient)."""
    from scipy.optimize import minimize

    T = 8
    A, B, c, quad, x0, _, cost = _lq_problem(T=T)
    free = ilqr(lambda x, u: jnp.asarray(A) @ x + jnp.asarray(B) @ u + jnp.asarray(c), cost,
                jnp.asarray(x0), jnp.zeros((T, 2)))  # fmt: skip
    limit = 0.4 * np.abs(np.asarray(free.U)).max(axis=0)
    lo, hi = -jnp.asarray(limit), jnp.asarray(limit)
    step = lambda x, u: jnp.asarray(A) @ x + jnp.asarray(B) @ jnp.clip(u, lo, hi) + jnp.asarray(c)
    signs = np.random.default_rng(3).choice([-1.0, 1.0], size=(6, T, 2))
    U_init = jnp.asarray(signs * limit)
    starts = jnp.asarray(x0) * jnp.linspace(0.5, 2.0, 6)[:, None]
    config = ILQRConfig(tol=1e-12)
    solve = jax.jit(jax.vmap(lambda x, U: ilqr(step, cost, x, U, config, u_min=lo, u_max=hi)))
    result = solve(starts, U_init)
    np.testing.assert_array_equal(np.asarray(result.status), CONVERGED)
    bounds = [(-limit[i % 2], limit[i % 2]) for i in range(2 * T)]
    for i in range(6):
        J_and_grad = _numpy_cost_and_gradient(A, B, c, quad, np.asarray(starts[i]))
        ref = minimize(J_and_grad, np.zeros(2 * T), jac=True, method="L-BFGS-B", bounds=bounds,
                       options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10_000})  # fmt: skip
        assert float(result.cost[i]) <= ref.fun + 1e-8 * abs(ref.fun), i
