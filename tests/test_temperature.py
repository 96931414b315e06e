"""The learned cost's temperature (diffgcl.costs.temperature, network.CostParams.log_temperature)
and the distribution-fit figures (diffgcl.eval.controllers), on linear-quadratic problems where
the MaxEnt controller is known in closed form."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lqr_problems import random_problem

from diffgcl.control.lqr import controller_entropy, lqr_backward
from diffgcl.costs.expansion import expand_cost
from diffgcl.costs.network import CostNetwork, CostNetworkConfig, untempered
from diffgcl.costs.temperature import (
    calibrated_log_temperature,
    maxent_controller,
    temperature_entropy_drop,
)
from diffgcl.eval.controllers import demo_log_likelihood, distribution_fit
from diffgcl.types import make_controller

T, dX, dU = 8, 3, 2
NET = CostNetwork(
    CostNetworkConfig(hidden=(), n_features=5, action_weight=0.2), dX, dU, jnp.float64
)


def problem(seed=0):
    dynamics, _, _, _ = random_problem(seed=seed, T=T, dX=dX, dU=dU)
    params = NET.init(jax.random.key(seed))
    key_x, key_u = jax.random.split(jax.random.key(seed + 1))
    X = jax.random.normal(key_x, (6, T + 1, dX))
    U = jax.random.normal(key_u, (6, T, dU))
    return dynamics, params, X, U


def test_temperature_scales_the_whole_cost_and_its_gauss_newton_expansion():
    dynamics, params, X, U = problem()
    hot = params.replace(log_temperature=jnp.asarray(0.7))
    x, u = X[0, 3], U[0, 3]
    np.testing.assert_allclose(NET.cost(hot, x, u, 3), np.exp(0.7) * NET.cost(params, x, u, 3))
    r, r_hot = NET.residual(params, x, u, 3), NET.residual(hot, x, u, 3)
    np.testing.assert_allclose(r_hot @ r_hot, NET.cost(hot, x, u, 3), rtol=1e-12)
    np.testing.assert_allclose(r_hot, np.exp(0.35) * r, rtol=1e-12)
    # The temperature is data: no gradient flows into it, and the GCL objective fits ρ = 0.
    grad = jax.grad(lambda p: NET.cost(p, x, u, 3))(hot)
    assert float(grad.log_temperature) == 0.0
    assert float(untempered(hot).log_temperature) == 0.0


def test_maxent_controller_is_lqr_of_the_exact_expansion():
    """The network cost with affine features is a quadratic, so its Gauss–Newton expansion about
    any trajectories is exact: the MaxEnt controller equals the LQR of the full expansion."""
    dynamics, params, X, U = problem(1)
    ours = maxent_controller(NET.bind_residual(params), dynamics, X, U)
    zeros_x, zeros_u = jnp.zeros((T + 1, dX)), jnp.zeros((T, dU))
    ref = lqr_backward(dynamics, expand_cost(NET.bind(params), zeros_x, zeros_u)).controller
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(ref), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("shift", [-7.3, 0.0, 12.5])
def test_calibrated_temperature_reaches_the_target_entropy(shift):
    """Scaling the cost by e^ρ divides the MaxEnt covariance by e^ρ and keeps the gains, so the
    entropy falls by ½·T·dU·ρ; the calibrated ρ lands on the target exactly."""
    dynamics, params, X, U = problem(2)
    raw = NET.bind_residual(params)
    H1 = controller_entropy(maxent_controller(raw, dynamics, X, U))
    target = H1 - shift
    chex.clear_trace_counter()
    calibrate = jax.jit(chex.assert_max_traces(calibrated_log_temperature, n=1), static_argnums=0)
    rho = calibrate(raw, dynamics, X, U, target)
    np.testing.assert_allclose(temperature_entropy_drop(rho, T, dU), shift, atol=1e-12)
    hot = params.replace(log_temperature=rho)
    cold, warm = (maxent_controller(NET.bind_residual(p), dynamics, X, U) for p in (params, hot))
    np.testing.assert_allclose(controller_entropy(warm), target, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(warm.cov, cold.cov / np.exp(rho), rtol=1e-9)
    np.testing.assert_allclose(warm.K, cold.K, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(warm.k, cold.k, rtol=1e-8, atol=1e-10)
    calibrate(raw, dynamics, X, U + 0.1, target)  # new values, no retrace


def test_distribution_fit_on_a_known_system():
    """Entropy gap by hand; the demos' log-likelihood against a direct sum of Gaussian log
    densities; noisy samples of a nearly deterministic controller succeed as its mean does, those
    of a very broad one do not."""
    from test_rgcl import Slider

    env = Slider()
    Tn = env.horizon
    K = jnp.zeros((Tn, env.dU, env.dX)).at[:, 0, 0].set(-25.0).at[:, 1, 1].set(-25.0)
    K = K.at[:, 0, 2].set(-10.0).at[:, 1, 3].set(-10.0)
    tight = make_controller(
        K, jnp.zeros((Tn, env.dU)), jnp.broadcast_to(1e-6 * jnp.eye(2), (Tn, 2, 2))
    )
    broad = tight.replace(cov=jnp.broadcast_to(400.0 * jnp.eye(2), (Tn, 2, 2)))
    broad = make_controller(broad.K, broad.k, broad.cov)
    demo_ctrl = make_controller(
        K, jnp.zeros((Tn, 2)), jnp.broadcast_to(0.01 * jnp.eye(2), (Tn, 2, 2))
    )
    add_c = lambda c: jax.tree.map(lambda a: a[None], c)
    X = jnp.broadcast_to(jnp.array([1.5, -1.0, 0.0, 0.0]), (3, Tn + 1, 4))
    U = 0.1 * jax.random.normal(jax.random.key(0), (3, Tn, 2))
    fit = jax.jit(
        lambda c: distribution_fit(
            env, c, add_c(demo_ctrl), X[None], U[None], jax.random.key(1), n_samples=16
        )
    )
    f_tight, f_broad = fit(add_c(tight)), fit(add_c(broad))
    expected_gap = 0.5 * Tn * 2 * np.log(400.0 / 0.01)
    np.testing.assert_allclose(f_broad.entropy_gap, [expected_gap], rtol=1e-9)
    assert float(f_tight.sample_success[0]) == 1.0 and float(f_tight.sample_success_white[0]) == 1.0
    assert float(f_broad.sample_success[0]) < 0.2
    resid = U - (jnp.einsum("tij,ntj->nti", K, X[:, :-1]))
    by_hand = (
        -0.5 * jnp.sum(resid**2, axis=(1, 2)) / 400.0 - 0.5 * Tn * 2 * np.log(2 * np.pi * 400.0)
    ).mean()
    np.testing.assert_allclose(demo_log_likelihood(broad, X, U), by_hand, rtol=1e-10)
    np.testing.assert_allclose(f_broad.demo_log_likelihood, [by_hand], rtol=1e-10)
