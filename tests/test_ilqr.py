"""iLQR (diffgcl.control.ilqr) against independent references, float64, tiny horizons."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lqr_problems import random_problem
from test_lqr import riccati_numpy

from diffgcl.control.ilqr import CONVERGED, ILQRConfig, backward_pass, ilqr, ilqr_controller
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


def test_lq_problem_equals_riccati_solution():
    """On a linear-quadratic problem iLQR's solution is the Riccati controller's rollout, its
    final gains are the Riccati gains, and it gets there in one accepted Newton step."""
    T = 8
    A, B, c, quad, x0, step, cost = _lq_problem(T=T)
    n = np.asarray
    tile = lambda a: np.broadcast_to(a, (T, *a.shape)).copy()
    K_ref, k_ref, _ = riccati_numpy(
        tile(A), tile(B), tile(c), n(quad.l_xx[:-1]), n(quad.l_uu[:-1]), n(quad.l_ux[:-1]),
        n(quad.l_x[:-1]), n(quad.l_u[:-1]), n(quad.l_xx[-1]), n(quad.l_x[-1]),
    )  # fmt: skip
    x, U_ref = x0.copy(), []
    for t in range(T):
        U_ref.append(K_ref[t] @ x + k_ref[t])
        x = A @ x + B @ U_ref[-1] + c
    U_ref = np.stack(U_ref)

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
