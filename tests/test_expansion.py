"""Cost expansion by autodiff (diffgcl.costs.expansion) and GPS-style analytic costs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl.costs.analytic import ActionCost, StateCost, WeightedSum, arm_expert_cost
from diffgcl.costs.expansion import (
    about_origin,
    expand_cost,
    expand_cost_samples,
    expand_residual_cost,
    shift_expansion,
    trajectory_cost,
)

T, dX, dU = 6, 4, 2


def _trajectory(seed=0, n=None):
    rng = np.random.default_rng(seed)
    shape = () if n is None else (n,)
    return jnp.asarray(rng.standard_normal((*shape, T + 1, dX))), jnp.asarray(
        rng.standard_normal((*shape, T, dU))
    )


def _model_value(q, t, x, u):
    """Evaluate the quadratic model of entry t at a displacement (x, u) from its point."""
    return (
        q.l[t]
        + q.l_x[t] @ x
        + q.l_u[t] @ u
        + 0.5 * x @ q.l_xx[t] @ x
        + 0.5 * u @ q.l_uu[t] @ u
        + u @ q.l_ux[t] @ x
    )


def test_expansion_of_a_quadratic_is_exact():
    rng = np.random.default_rng(1)
    M = rng.standard_normal((dX + dU, dX + dU))
    H = jnp.asarray(M @ M.T)
    g = jnp.asarray(rng.standard_normal(dX + dU))

    def cost(x, u, t):
        z = jnp.concatenate([x, u])
        return 0.5 * z @ H @ z + g @ z + t

    X, U = _trajectory()
    q = about_origin(jax.jit(expand_cost, static_argnums=0)(cost, X, U), X, U)
    for t in range(T):
        np.testing.assert_allclose(q.l_xx[t], H[:dX, :dX], atol=1e-10)
        np.testing.assert_allclose(q.l_uu[t], H[dX:, dX:], atol=1e-10)
        np.testing.assert_allclose(q.l_ux[t], H[dX:, :dX], atol=1e-10)
        np.testing.assert_allclose(q.l_x[t], g[:dX], atol=1e-10)
        np.testing.assert_allclose(q.l_u[t], g[dX:], atol=1e-10)
        assert float(q.l[t]) == pytest.approx(t, abs=1e-10)
    # The terminal entry has no action part, and its state part is c(x, 0, T).
    assert np.all(np.asarray(q.l_u[T]) == 0) and np.all(np.asarray(q.l_uu[T]) == 0)
    np.testing.assert_allclose(q.l_xx[T], H[:dX, :dX], atol=1e-10)


def test_full_hessian_matches_finite_differences():
    cost = StateCost(idx=(0, 1, 3), target=(0.3, -0.2, 0.1), horizon=T, l1=1.0, l2=0.5)
    X, U = _trajectory(2)
    q = expand_cost(cost, X, U)
    t, h = 2, 1e-5
    f = jax.jit(lambda x: cost(x, U[t], t))
    grad_fd = np.array([(f(X[t] + h * e) - f(X[t] - h * e)) / (2 * h) for e in np.eye(dX)])
    np.testing.assert_allclose(q.l_x[t], grad_fd, atol=1e-8)
    g = jax.jit(jax.grad(f))
    hess_fd = np.array([(g(X[t] + h * e) - g(X[t] - h * e)) / (2 * h) for e in np.eye(dX)])
    np.testing.assert_allclose(q.l_xx[t], hess_fd, atol=1e-6)


def test_gauss_newton_is_psd_and_exact_for_linear_residuals():
    rng = np.random.default_rng(3)
    R = jnp.asarray(rng.standard_normal((3, dX + dU)))
    b = jnp.asarray(rng.standard_normal(3))
    residual = lambda x, u, t: R @ jnp.concatenate([x, u]) + b
    squared = lambda x, u, t: jnp.sum(residual(x, u, t) ** 2)
    X, U = _trajectory(4)
    gn = expand_residual_cost(residual, X, U)
    full = expand_cost(squared, X, U)
    for a, b_ in zip(jax.tree.leaves(gn), jax.tree.leaves(full), strict=True):
        np.testing.assert_allclose(a, b_, atol=1e-10)
    # Non-linear residual: the Gauss–Newton Hessian stays PSD.
    r2 = lambda x, u, t: jnp.tanh(R @ jnp.concatenate([x, u]) + b)
    gn2 = expand_residual_cost(r2, X, U)
    for t in range(T):
        H = np.block([[gn2.l_xx[t], gn2.l_ux[t].T], [gn2.l_ux[t], gn2.l_uu[t]]])
        assert np.linalg.eigvalsh(H).min() > -1e-10


def test_shift_expansion_keeps_the_quadratic():
    cost = StateCost(idx=(0, 1), target=(1.0, -1.0), horizon=T, l1=0.3, l2=1.0)
    X, U = _trajectory(5)
    X2, U2 = _trajectory(6)
    q = expand_cost(cost, X, U)
    shifted = shift_expansion(q, X, U, X2, U2)
    rng = np.random.default_rng(7)
    for t in (0, 3, T - 1):
        x, u = jnp.asarray(rng.standard_normal(dX)), jnp.asarray(rng.standard_normal(dU))
        a = _model_value(q, t, x - X[t], u - U[t])
        b = _model_value(shifted, t, x - X2[t], u - U2[t])
        assert float(a) == pytest.approx(float(b), rel=1e-10, abs=1e-10)


def test_sample_average_of_a_quadratic_equals_mean_expansion():
    cost = arm_expert_cost(T)
    X, U = _trajectory(8, n=5)
    avg = jax.jit(expand_cost_samples, static_argnums=0)(cost, X, U)
    at_mean = expand_cost(cost, X.mean(0), U.mean(0))
    # For a quadratic, every sample's expansion moved to the mean is the expansion at the mean.
    np.testing.assert_allclose(avg.l_x, at_mean.l_x, atol=1e-10)
    np.testing.assert_allclose(avg.l_xx, at_mean.l_xx, atol=1e-10)
    np.testing.assert_allclose(avg.l_uu, at_mean.l_uu, atol=1e-12)
    # Constants: c(z_i) − ∇c(z̄)ᵀd_i − ½d_iᵀHd_i = c(z̄) for every sample i (d_i = z_i − z̄).
    np.testing.assert_allclose(avg.l, at_mean.l, atol=1e-10)


def test_analytic_costs_follow_gps_semantics():
    x = jnp.array([0.5, -1.0, 2.0, 0.0])
    u = jnp.array([3.0, -4.0])
    quad = StateCost(idx=(0, 1), target=(0.0, 0.0), horizon=10, wp=(2.0, 1.0))
    assert float(quad(x, u, 0)) == pytest.approx(0.5 * (2 * 0.25 + 1.0))
    l1 = StateCost(idx=(0, 1), target=(0.0, 0.0), horizon=10, l1=1.0, l2=0.0, alpha=1e-2)
    assert float(l1(x, u, 0)) == pytest.approx(np.sqrt(1e-2 + 0.25 + 1.0))
    lin = StateCost(idx=(0,), target=(0.0,), horizon=9, ramp="linear")
    assert float(lin(x, u, 4)) == pytest.approx(0.5 * 0.25 * 5 / 10)
    fin = StateCost(idx=(0,), target=(0.0,), horizon=9, ramp="final_only", final_multiplier=3.0)
    assert float(fin(x, u, 8)) == 0.0
    assert float(fin(x, u, 9)) == pytest.approx(3 * 0.5 * 0.25)
    quadratic = StateCost(idx=(0,), target=(0.0,), horizon=9, ramp="quadratic")
    assert float(quadratic(x, u, 4)) == pytest.approx(0.5 * 0.25 * 0.25)
    act = ActionCost(wu=(1.0, 2.0))
    assert float(act(x, u, 0)) == pytest.approx(0.5 * (9 + 32))
    total = WeightedSum(costs=(act, quad), weights=(0.1, 2.0))
    assert float(total(x, u, 0)) == pytest.approx(0.1 * 20.5 + 2 * 0.75)
    arm = arm_expert_cost(100)
    expected = 0.5 * (0.25 + 1.0) + 1e-5 * 0.5 * 25
    assert float(arm(x, u, 0)) == pytest.approx(expected)
    with pytest.raises(ValueError, match="ramp"):
        StateCost(idx=(0,), target=(0.0,), horizon=9, ramp="cubic")
    X, U = _trajectory(9)
    assert float(trajectory_cost(arm, X, U)) == pytest.approx(
        sum(float(arm(X[t], U[t], t)) for t in range(T)) + float(arm(X[T], jnp.zeros(dU), T))
    )
