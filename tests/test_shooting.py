"""Multiple shooting (diffgcl.control.shooting) against independent references, float64."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_ilqr import _lq_problem, _numpy_cost_and_gradient, _pendulum, _riccati_rollout

from diffgcl.control.ilqr import CONVERGED, STUCK, backward_pass, ilqr
from diffgcl.control.shooting import (
    MERIT_RULES,
    ShootingConfig,
    costates,
    multiple_shooting,
    relaxed_log_barrier,
    state_barrier,
    straight_line,
)
from diffgcl.costs.expansion import expand_cost, trajectory_cost
from diffgcl.dynamics.autodiff import linearize_trajectory


def test_relaxed_barrier_is_log_inside_and_c2_at_the_switch():
    d = 1e-2
    s = jnp.array([0.5, 2.0, 1e-1])
    np.testing.assert_allclose(relaxed_log_barrier(s, d), -np.log(np.asarray(s)), rtol=1e-14)
    f = lambda s: relaxed_log_barrier(s, d)
    for g in (f, jax.grad(f), jax.grad(jax.grad(f))):  # value, slope, curvature meet at δ
        assert float(g(d * (1 - 1e-9))) == pytest.approx(float(g(d * (1 + 1e-9))), rel=1e-6)
    assert np.isfinite(float(f(-3.0))) and float(jax.grad(f)(-3.0)) < 0
    # Only the finite sides count.
    x = jnp.array([0.2, 5.0])
    lo, hi = jnp.array([-1.0, -jnp.inf]), jnp.array([1.0, jnp.inf])
    want = -np.log(1.2) - np.log(0.8)
    assert float(state_barrier(x, lo, hi, d)) == pytest.approx(want, rel=1e-14)
    assert np.all(np.isfinite(jax.grad(state_barrier)(x, lo, hi, d)))


def test_backward_pass_with_gaps_solves_the_lq_problem_with_defects():
    """The gains of the backward pass with gaps, applied to the linear model with those gaps,
    give the minimiser of the quadratic cost subject to ``x' = A x + B u + c`` from a state guess
    that is not a rollout: the Riccati solution."""
    T = 6
    A, B, c, quad, x0, step, cost = _lq_problem(T=T)
    U_ref, _ = _riccati_rollout(A, B, c, quad, x0)
    rng = np.random.default_rng(0)
    X = jnp.asarray(rng.normal(size=(T + 1, A.shape[0]))).at[0].set(x0)
    U = jnp.asarray(rng.normal(size=(T, B.shape[1])))
    gaps = jax.vmap(step)(X[:-1], U) - X[1:]
    As, Bs = jnp.broadcast_to(A, (T, *A.shape)), jnp.broadcast_to(B, (T, *B.shape))
    back = backward_pass(As, Bs, expand_cost(cost, X, U), jnp.zeros(()), gaps=gaps)
    dx, U_new = jnp.zeros(A.shape[0]), []
    for t in range(T):
        du = back.k[t] + back.K[t] @ dx
        U_new.append(U[t] + du)
        dx = A @ dx + B @ du + gaps[t]
    np.testing.assert_allclose(np.stack(U_new), U_ref, rtol=0, atol=1e-9)


def test_lq_problem_from_a_random_state_guess_equals_riccati():
    """Linear dynamics: the first full step closes every gap and lands on the optimum; the
    result is the closed-loop rollout, equal to the Riccati controller's."""
    T = 8
    A, B, c, quad, x0, step, cost = _lq_problem(T=T)
    U_ref, _ = _riccati_rollout(A, B, c, quad, x0)
    X_init = jnp.asarray(np.random.default_rng(1).normal(size=(T + 1, A.shape[0])))
    solve = jax.jit(lambda x0, X: multiple_shooting(step, cost, x0, X, jnp.zeros((T, 2))))
    result = solve(jnp.asarray(x0), X_init)
    assert int(result.status) == CONVERGED
    np.testing.assert_allclose(result.U, U_ref, rtol=0, atol=1e-9)
    x = x0.copy()
    for t in range(T):
        x = A @ x + B @ U_ref[t] + c
    np.testing.assert_allclose(result.X[-1], x, atol=1e-9)
    # One Newton step; each barrier stage then finds the point stationary (no bounds here).
    assert int(result.accepted) == 1


def test_state_limits_meet_the_constrained_optimum():
    """A linear-quadratic problem whose optimum breaks a bound on one state coordinate: with the
    barrier weight driven to 10⁻⁸ the solution keeps the bound and its cost and actions approach
    scipy's SLSQP on the condensed problem with the bound as a linear inequality."""
    from scipy.optimize import minimize

    T = 8
    A, B, c, quad, x0, step, cost = _lq_problem(T=T)
    free = ilqr(step, cost, jnp.asarray(x0), jnp.zeros((T, 2)))
    i = 0
    bound = 0.5 * float(jnp.abs(free.X[1:, i]).max())  # the optimum breaks it
    x_min = jnp.full(A.shape[0], -jnp.inf).at[i].set(-bound)
    x_max = jnp.full(A.shape[0], jnp.inf).at[i].set(bound)
    config = ShootingConfig(barrier_weights=(1.0, 1e-2, 1e-4, 1e-6, 1e-8), barrier_delta=1e-6)
    result = multiple_shooting(step, cost, jnp.asarray(x0), straight_line(jnp.asarray(x0),
                               jnp.zeros_like(jnp.asarray(x0)), T), jnp.zeros((T, 2)), config,
                               x_min=x_min, x_max=x_max)  # fmt: skip
    assert int(result.status) == CONVERGED
    # The relaxed barrier's quadratic side (curvature w/δ² = 10⁴ at the end) lets the state
    # press about 10⁻⁴ past the bound.
    assert float(jnp.abs(result.X[1:, i]).max()) <= bound + 1e-3

    def states(U):
        x, out = x0.copy(), []
        for t in range(T):
            x = A @ x + B @ U[2 * t : 2 * t + 2] + c
            out.append(x[i])
        return np.array(out)

    J_and_grad = _numpy_cost_and_gradient(A, B, c, quad, x0)
    ref = minimize(J_and_grad, np.zeros(2 * T), jac=True, method="SLSQP",
                   constraints=[{"type": "ineq", "fun": lambda U: bound - states(U)},
                                {"type": "ineq", "fun": lambda U: bound + states(U)}],
                   options={"ftol": 1e-14, "maxiter": 1000})  # fmt: skip
    assert ref.success
    assert float(result.cost) == pytest.approx(ref.fun, rel=1e-4)
    np.testing.assert_allclose(np.asarray(result.U).ravel(), ref.x, atol=1e-2)
    assert float(result.cost) > float(free.cost)


def test_costates_are_the_cost_gradient_with_respect_to_each_gap():
    """The multipliers of the dynamics: λ_{t+1} is the derivative of the total cost of the
    linearised rollout (the actions held) with respect to a push on x_{t+1}, computed here by
    reverse-mode autodiff of that rollout, independent of the adjoint recursion."""
    T = 12
    step, cost = _pendulum(T=T)
    rng = np.random.default_rng(3)
    U = jnp.asarray(rng.normal(size=(T, 1)))
    X = [jnp.array([0.4, -0.2])]
    for t in range(T):
        X.append(step(X[-1], U[t]))
    X = jnp.stack(X)
    A, B = linearize_trajectory(step, X, U)
    quad = expand_cost(cost, X, U)

    def pushed_cost(pushes):  # pushes [T, dX]: added to x_1 .. x_T of the linearised rollout
        dx, xs = jnp.zeros(2), [X[0]]
        for t in range(T):
            dx = A[t] @ dx + pushes[t]
            xs.append(X[t + 1] + dx)
        return trajectory_cost(cost, jnp.stack(xs), U)

    reference = jax.grad(pushed_cost)(jnp.zeros((T, 2)))
    np.testing.assert_allclose(costates(A, quad), reference, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("merit_rule", MERIT_RULES)
def test_unstable_system_with_a_binding_box_from_a_far_state_guess(merit_rule):
    """An unstable linear system (eigenvalues 1 ± 0.45 per step), the action box at 60 % of the
    free optimum's largest action, and a state guess far from any rollout: the problem is
    convex, so the solution must be the boxed iLQR's from zero actions. The linear model's
    step has to keep its feedback unclipped; clipped, the propagated gaps grew without bound
    and no step was ever accepted."""
    T = 60
    A = jnp.array([[1.0, 0.1], [2.0, 1.0]])
    B = jnp.array([[0.0], [0.1]])
    Q, QT, r = jnp.diag(jnp.array([1.0, 0.1])), jnp.diag(jnp.array([10.0, 1.0])), 0.01

    def step(x, u):
        return A @ x + B @ u

    def cost(x, u, t):
        return jnp.where(t < T, 0.5 * x @ Q @ x + 0.5 * r * u @ u, 0.5 * x @ QT @ x)

    x0 = jnp.array([1.0, 0.0])
    free = ilqr(step, cost, x0, jnp.zeros((T, 1)))
    u_max = 0.6 * float(jnp.abs(free.U).max())
    ref = ilqr(step, cost, x0, jnp.zeros((T, 1)), u_min=-u_max, u_max=u_max)
    assert float(ref.cost) > float(free.cost)  # the box binds
    noise = jnp.asarray(np.random.default_rng(0).normal(size=(T + 1, 2)))
    X_init = straight_line(x0, jnp.zeros(2), T) + noise
    config = ShootingConfig(barrier_weights=(0.0,), stage_iterations=100, merit_rule=merit_rule)
    result = jax.jit(lambda X: multiple_shooting(step, cost, x0, X, jnp.zeros((T, 1)), config,
                                                 u_min=-u_max, u_max=u_max))(X_init)  # fmt: skip
    assert int(result.status) == CONVERGED
    assert float(jnp.abs(result.U).max()) <= u_max + 1e-12
    assert float(result.cost) == pytest.approx(float(ref.cost), rel=1e-8)
    np.testing.assert_allclose(result.U, ref.U, atol=1e-5)


def test_pendulum_swing_up_closes_the_gaps_and_respects_the_box():
    """Swinging the pendulum up from the straight line of states (not a rollout): the result is
    a rollout of its actions that reaches the top, the actions within the torque box; from rest
    it converges to iLQR's optimum; vmapped equals unbatched."""
    T = 40
    step, cost = _pendulum(T=T)
    goal = jnp.array([jnp.pi, 0.0])
    config = ShootingConfig(barrier_weights=(0.0,), stage_iterations=200)

    def solve(x0):
        X = straight_line(x0, goal, T)
        return multiple_shooting(step, cost, x0, X, jnp.zeros((T, 1)), config, u_min=-4.0,
                                 u_max=4.0)  # fmt: skip

    X0 = jnp.array([[0.0, 0.0], [0.3, -0.5]])
    batched = jax.jit(jax.vmap(solve))(X0)
    for j in range(2):
        one = jax.jit(solve)(X0[j])
        np.testing.assert_allclose(batched.U[j], one.U, rtol=0, atol=1e-10)
        assert float(jnp.abs(batched.U[j]).max()) <= 4.0
        x = X0[j]
        for t in range(T):  # an independent rollout of the returned actions
            x = step(x, batched.U[j, t])
        np.testing.assert_allclose(batched.X[j, -1], x, atol=1e-9)
        assert abs(float(x[0]) - np.pi) < 0.1
    assert int(batched.status[0]) == CONVERGED
    ref = ilqr(step, cost, X0[0], jnp.zeros((T, 1)), u_min=-4.0, u_max=4.0)
    assert float(batched.cost[0]) == pytest.approx(float(ref.cost), rel=1e-5)


def test_fallback_attempt_restarts_from_the_guess_and_keeps_the_cheaper():
    """With a fallback rule, an attempt that ends stuck is followed by one under the other rule
    from the same initial guess: its iterations must be those of that rule run alone (the
    restart leaves nothing of the first attempt behind), and the result the cheaper of the two
    runs alone. A tiny ``mu_max`` makes the pendulum's swing-up end stuck under both rules."""
    T = 40
    step, cost = _pendulum(T=T)
    x0 = jnp.array([0.3, -0.5])
    X = straight_line(x0, jnp.array([jnp.pi, 0.0]), T)
    base = dict(barrier_weights=(0.0,), stage_iterations=200, line_search_steps=2, mu_max=1.0)

    def run(**rules):
        config = ShootingConfig(**base, **rules)
        return jax.jit(lambda X: multiple_shooting(step, cost, x0, X, jnp.zeros((T, 1)), config,
                                                   u_min=-4.0, u_max=4.0))(X)  # fmt: skip

    slope = run(merit_rule="slope", fallback_rule=None)
    filt = run(merit_rule="filter", fallback_rule=None)
    both = run(merit_rule="slope", fallback_rule="filter")
    assert int(slope.status) == STUCK and int(filt.status) == STUCK
    n1, n2 = int(slope.iterations) + 1, int(filt.iterations) + 1  # trips, the guess's included
    assert int(both.iterations) == n1 + n2 - 2
    np.testing.assert_allclose(both.cost_history[:n1], slope.cost_history[:n1], rtol=1e-12)
    np.testing.assert_allclose(both.cost_history[n1 : n1 + n2], filt.cost_history[:n2], rtol=1e-12)
    assert float(both.cost) == min(float(slope.cost), float(filt.cost))
    # Without a stuck end there is no second attempt.
    free = dict(base, line_search_steps=20, mu_max=1e10)
    config = ShootingConfig(**free, merit_rule="filter", fallback_rule="slope")
    one = jax.jit(lambda X: multiple_shooting(step, cost, x0, X, jnp.zeros((T, 1)), config,
                                              u_min=-4.0, u_max=4.0))(X)  # fmt: skip
    assert int(one.status) == CONVERGED
    assert np.isnan(np.asarray(one.cost_history)[int(one.iterations) + 1 :]).all()


def test_config_rejects_bad_settings_and_shapes():
    with pytest.raises(ValueError, match="barrier_weights"):
        ShootingConfig(barrier_weights=())
    with pytest.raises(ValueError, match="backtrack"):
        ShootingConfig(backtrack=1.5)
    with pytest.raises(ValueError, match="merit_rule"):
        ShootingConfig(merit_rule="penalty")
    with pytest.raises(ValueError, match="fallback_rule"):
        ShootingConfig(fallback_rule="penalty")
    step, cost = _pendulum(T=4)
    with pytest.raises(ValueError, match="X_init must be"):
        multiple_shooting(step, cost, jnp.zeros(2), jnp.zeros((4, 2)), jnp.zeros((4, 1)))
