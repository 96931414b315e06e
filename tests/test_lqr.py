"""KL-constrained LQR (diffgcl.control.lqr, diffgcl.control.dual) against closed-form references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lqr_problems import random_problem

from diffgcl.control import dual
from diffgcl.control.dual import c_step
from diffgcl.control.lqr import (
    backward_pass,
    controller_entropy,
    forward_pass,
    kl_divergence,
    lqr_backward,
)
from diffgcl.types import QuadraticCost


def riccati_numpy(A, B, c, Qxx, Quu, Qux, qx, qu, Qf, qf):
    """Finite-horizon LQR for x' = A x + B u + c and stage cost
    ½xᵀQxx x + ½uᵀQuu u + uᵀQux x + qxᵀx + quᵀu, terminal ½xᵀQf x + qfᵀx.

    Value function V_t(x) = ½xᵀP x + pᵀx + const; the optimal action minimises
    stage + V_{t+1}(A x + B u + c). Written with plain solves (no Cholesky, no blocks).
    """
    T = A.shape[0]
    P, p = Qf.copy(), qf.copy()
    Ks, ks, Ps = [None] * T, [None] * T, [None] * (T + 1)
    Ps[T] = P
    for t in reversed(range(T)):
        At, Bt, ct = A[t], B[t], c[t]
        R = Quu[t] + Bt.T @ P @ Bt
        N = Qux[t] + Bt.T @ P @ At
        r = qu[t] + Bt.T @ (P @ ct + p)
        K = -np.linalg.solve(R, N)
        k = -np.linalg.solve(R, r)
        # Substitute u = Kx + k into stage + V_{t+1}.
        Acl = At + Bt @ K
        P_new = Qxx[t] + K.T @ Quu[t] @ K + K.T @ Qux[t] + Qux[t].T @ K + Acl.T @ P @ Acl
        p_new = (
            qx[t] + K.T @ Quu[t] @ k + Qux[t].T @ k + K.T @ qu[t] + Acl.T @ (P @ (Bt @ k + ct) + p)
        )
        P, p = 0.5 * (P_new + P_new.T), p_new
        Ks[t], ks[t], Ps[t] = K, k, P
    return np.stack(Ks), np.stack(ks), np.stack(Ps)


def _reference(dynamics, cost: QuadraticCost):
    n = lambda a: np.asarray(a)
    return riccati_numpy(
        n(dynamics.A),
        n(dynamics.B),
        n(dynamics.c),
        n(cost.l_xx[:-1]),
        n(cost.l_uu[:-1]),
        n(cost.l_ux[:-1]),
        n(cost.l_x[:-1]),
        n(cost.l_u[:-1]),
        n(cost.l_xx[-1]),
        n(cost.l_x[-1]),
    )


def test_backward_equals_riccati():
    dynamics, cost, prev, _ = random_problem(seed=1)
    K_ref, k_ref, P_ref = _reference(dynamics, cost)
    result = jax.jit(lqr_backward)(dynamics, cost)
    assert bool(result.pd_ok)
    np.testing.assert_allclose(result.controller.K, K_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(result.controller.k, k_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(result.V, P_ref, rtol=0, atol=1e-8)


def test_kl_term_vanishes_as_eta_goes_to_zero():
    """ω = 0, η → 0: C/η dominates the KL term; gains equal the Riccati solution and Σ = η·Q_uu⁻¹.
    ω = 1, η = 0: exactly the LQR of the cost with Σ = Q_uu⁻¹ (MaxEnt)."""
    dynamics, cost, prev, _ = random_problem(seed=2)
    K_ref, k_ref, _ = _reference(dynamics, cost)
    small = backward_pass(dynamics, cost, prev, 1e-12, 0.0)
    assert bool(small.pd_ok)
    np.testing.assert_allclose(small.controller.K, K_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(small.controller.k, k_ref, rtol=0, atol=1e-8)
    maxent = backward_pass(dynamics, cost, prev, 0.0, 1.0)
    plain = lqr_backward(dynamics, cost)
    np.testing.assert_allclose(maxent.controller.K, K_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(maxent.controller.cov, plain.controller.cov, rtol=0, atol=1e-12)
    np.testing.assert_allclose(small.controller.cov, 1e-12 * plain.controller.cov, rtol=1e-6)


def test_large_eta_returns_previous_controller():
    dynamics, cost, prev, _ = random_problem(seed=3)
    result = backward_pass(dynamics, cost, prev, 1e12, 0.0)
    np.testing.assert_allclose(result.controller.K, prev.K, atol=1e-8)
    np.testing.assert_allclose(result.controller.k, prev.k, atol=1e-8)
    np.testing.assert_allclose(result.controller.cov, prev.cov, atol=1e-8)


def _simulate(dynamics, controller, x0, key, n):
    """Sample n trajectories of a linear-Gaussian controller in linear-Gaussian dynamics."""
    kx, ku, kw = jax.random.split(key, 3)
    dX, dU = x0.mean.shape[0], controller.k.shape[-1]
    T = dynamics.A.shape[0]
    x = x0.mean + jax.random.normal(kx, (n, dX)) @ jnp.linalg.cholesky(x0.cov).T

    def step(x, inputs):
        A, B, c, cov, K, k, chol, eps_u, eps_x = inputs
        u = x @ K.T + k + eps_u @ chol.T
        x_next = x @ A.T + u @ B.T + c + eps_x @ jnp.linalg.cholesky(cov).T
        return x_next, (x, u)

    xs = (
        dynamics.A,
        dynamics.B,
        dynamics.c,
        dynamics.cov,
        controller.K,
        controller.k,
        controller.chol_cov,
        jax.random.normal(ku, (T, n, dU)),
        jax.random.normal(kw, (T, n, dX)),
    )
    xT, (X, U) = jax.lax.scan(step, x, xs)
    return jnp.swapaxes(X, 0, 1), jnp.swapaxes(U, 0, 1), xT


def _log_prob(controller, X, U):
    """Σ_t log N(u_t; K_t x_t + k_t, Σ_t) per sample, X: [n, T, dX], U: [n, T, dU]."""
    mean = jnp.einsum("tij,ntj->nti", controller.K, X) + controller.k
    diff = U - mean
    maha = jnp.einsum("nti,tij,ntj->nt", diff, controller.inv_cov, diff)
    logdet = 2 * jnp.sum(jnp.log(jnp.diagonal(controller.chol_cov, axis1=-2, axis2=-1)), -1)
    dU = U.shape[-1]
    return jnp.sum(-0.5 * (maha + logdet + dU * jnp.log(2 * jnp.pi)), axis=-1)


def test_forward_pass_and_kl_match_monte_carlo():
    dynamics, cost, prev, x0 = random_problem(seed=4, T=6)
    new = backward_pass(dynamics, cost, prev, 2.0, 0.0).controller
    traj = forward_pass(dynamics, new, x0)
    X, U, xT = jax.jit(_simulate, static_argnums=4)(
        dynamics, new, x0, jax.random.PRNGKey(0), 40_000
    )
    dX = X.shape[-1]
    np.testing.assert_allclose(X.mean(0), traj.mu[:, :dX], atol=0.03)
    np.testing.assert_allclose(U.mean(0), traj.mu[:, dX:], atol=0.03)
    np.testing.assert_allclose(jnp.cov(xT.T), traj.sigma_final, atol=0.03)

    kl = kl_divergence(traj, new, prev)
    log_ratio = _log_prob(new, X, U) - _log_prob(prev, X, U)
    mc, stderr = log_ratio.mean(), log_ratio.std() / np.sqrt(log_ratio.shape[0])
    assert kl > 0.1
    assert abs(float(kl - mc)) < 4 * float(stderr) + 1e-3, (kl, mc, stderr)
    assert float(kl_divergence(traj, new, new)) == pytest.approx(0.0, abs=1e-10)


@pytest.mark.parametrize("maxent", [False, True])
def test_c_step_meets_epsilon_under_vmap(maxent):
    dynamics, cost, prev, x0 = random_problem(seed=5)
    epsilons = jnp.array([0.02, 0.2, 1.0, 5.0, 20.0])
    run = jax.jit(jax.vmap(lambda e: c_step(dynamics, cost, prev, x0, e, 1.0, maxent=maxent)))
    controller, info = run(epsilons)
    assert controller.K.shape == (5, *prev.K.shape)
    omega = 1.0 if maxent else 0.0
    for i, eps in enumerate(np.asarray(epsilons)):
        status = int(info.status[i])
        assert bool(info.ok[i]), dual.describe(info)
        if status == dual.CONVERGED:
            assert abs(float(info.kl[i]) - eps) <= 0.1 * eps
        else:  # the MaxEnt KL saturates: only a large budget may leave the constraint inactive
            assert maxent and status == dual.INACTIVE and float(info.kl[i]) < eps
        # The reported KL is that of the returned controller.
        one = jax.tree.map(lambda a, i=i: a[i], controller)
        traj = forward_pass(dynamics, one, x0)
        assert float(kl_divergence(traj, one, prev)) == pytest.approx(float(info.kl[i]), 1e-8)
        rerun = backward_pass(dynamics, cost, prev, info.eta[i], omega).controller
        np.testing.assert_allclose(rerun.K, one.K, atol=1e-10)
    # Tighter budgets give larger η.
    converged = np.asarray(info.status) == dual.CONVERGED
    assert np.all(np.diff(np.asarray(info.eta)[converged]) < 0)


def _non_pd_cost(cost: QuadraticCost, scale: float) -> QuadraticCost:
    dU = cost.l_u.shape[-1]
    bad = cost.l_uu.at[:-1].set(-scale * jnp.eye(dU))
    return cost.replace(l_uu=bad)


def test_non_pd_cost_raises_eta_and_stays_finite():
    dynamics, cost, prev, x0 = random_problem(seed=6)
    bad = _non_pd_cost(cost, 50.0)
    assert not bool(backward_pass(dynamics, bad, prev, 1e-3, 0.0).pd_ok)
    controller, info = jax.jit(lambda c: c_step(dynamics, c, prev, x0, 0.5, 1e-3))(bad)
    assert int(info.not_pd) > 0
    assert bool(info.ok), dual.describe(info)
    assert float(info.eta) > 1e-3
    for leaf in jax.tree.leaves(controller):
        assert np.all(np.isfinite(leaf))
    assert np.all(np.linalg.eigvalsh(np.asarray(controller.cov)) > 0)
    assert float(info.kl) <= 0.55


def test_hopeless_cost_reports_failure_and_returns_previous():
    dynamics, cost, prev, x0 = random_problem(seed=7)
    bad = _non_pd_cost(cost, 1e22)  # needs η > 1e21 > max_eta
    controller, info = c_step(dynamics, bad, prev, x0, 0.5, 1.0)
    assert int(info.status) == dual.FAILED_NOT_PD, dual.describe(info)
    assert not bool(info.ok)
    assert int(info.iterations) < 100
    np.testing.assert_array_equal(controller.K, prev.K)
    np.testing.assert_array_equal(controller.cov, prev.cov)
    assert "failed" in dual.describe(info)[0]
    # The same in float32: the search still stops at max_eta with the right code.
    f32 = lambda tree: jax.tree.map(lambda a: a.astype(jnp.float32), tree)
    ctrl32, info32 = c_step(f32(dynamics), f32(bad), f32(prev), f32(x0), 0.5, 1.0)
    assert int(info32.status) == dual.FAILED_NOT_PD and ctrl32.K.dtype == jnp.float32
    nan_dyn = dynamics.replace(A=dynamics.A.at[3, 0, 0].set(jnp.nan))
    controller, info = c_step(nan_dyn, cost, prev, x0, 0.5, 1.0)
    assert not bool(info.ok)
    assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(controller))


def test_c_step_vmaps_over_conditions_without_recompiling():
    problems = [random_problem(seed=s) for s in (10, 11, 12)]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *problems)
    dynamics, cost, prev, x0 = stacked
    run = jax.jit(jax.vmap(lambda d, c, p, x, e, eta: c_step(d, c, p, x, e, eta)))
    eps = jnp.array([0.3, 1.0, 3.0])
    controller, info = run(dynamics, cost, prev, x0, eps, jnp.ones(3))
    assert bool(jnp.all(info.ok))
    for i in range(3):
        one_ctrl, one_info = c_step(*problems[i], eps[i], 1.0)
        np.testing.assert_allclose(controller.K[i], one_ctrl.K, atol=1e-10)
        assert float(info.eta[i]) == pytest.approx(float(one_info.eta))
    # Same shapes, new values: the cached program is reused.
    run(dynamics, cost, prev, x0, 2 * eps, info.eta)
    assert run._cache_size() == 1


def test_entropy_of_isotropic_controller():
    from diffgcl.control.init import init_controller

    ctrl = init_controller(5, 3, 2, 0.1)
    expected = 5 * 0.5 * np.log(np.linalg.det(2 * np.pi * np.e * 0.1 * np.eye(2)))
    assert float(controller_entropy(ctrl)) == pytest.approx(expected)
    assert ctrl.K.shape == (5, 2, 3) and np.all(np.asarray(ctrl.K) == 0)
    np.testing.assert_allclose(ctrl.inv_cov, 10 * np.broadcast_to(np.eye(2), (5, 2, 2)))


def test_passes_under_jit_and_vmap_match_single_instances():
    problems = [random_problem(seed=s, T=5) for s in (20, 21, 22)]
    dynamics, cost, prev, x0 = jax.tree.map(lambda *a: jnp.stack(a), *problems)
    eta = jnp.array([0.5, 1.0, 2.0])

    def kernel(d, c, p, x, e):
        result = backward_pass(d, c, p, e, 0.0)
        traj = forward_pass(d, result.controller, x)
        return result.controller, traj, kl_divergence(traj, result.controller, p)

    batched = jax.jit(jax.vmap(kernel))
    ctrl, traj, kl = batched(dynamics, cost, prev, x0, eta)
    single = jax.jit(kernel)
    for i, problem in enumerate(problems):
        one_ctrl, one_traj, one_kl = single(*problem, eta[i])
        np.testing.assert_allclose(ctrl.K[i], one_ctrl.K, atol=1e-10)
        np.testing.assert_allclose(traj.sigma[i], one_traj.sigma, atol=1e-10)
        assert float(kl[i]) == pytest.approx(float(one_kl), rel=1e-10)
    batched(dynamics, cost, prev, x0, 2 * eta)
    assert batched._cache_size() == 1
