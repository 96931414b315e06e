"""The network cost: identity features, normaliser, residual form, Gauss–Newton expansion."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from diffgcl.costs.expansion import expand_residual_cost
from diffgcl.costs.network import (
    CostNetwork,
    CostNetworkConfig,
    init_normaliser,
    update_normaliser,
)

dX, dU, T = 3, 2, 6


def make_network(**kw) -> CostNetwork:
    config = CostNetworkConfig(hidden=(8, 8), n_features=5, **kw)
    return CostNetwork(config, dX, dU, jnp.float64)


def test_identity_features_start_as_normalised_state():
    net = make_network()
    params = net.init(jax.random.key(0))
    norm = update_normaliser(params.norm, jax.random.normal(jax.random.key(1), (50, dX)) * 2 + 1)
    params = params.replace(norm=norm)
    x = jnp.array([0.3, -1.2, 2.5])
    z = (x - norm.mean) / jnp.sqrt(norm.var)
    np.testing.assert_allclose(net.features(params, x)[:dX], z, rtol=1e-12)


def test_identity_features_without_hidden_layers():
    net = CostNetwork(CostNetworkConfig(hidden=(), n_features=4), dX, dU, jnp.float64)
    params = net.init(jax.random.key(0))
    x = jnp.array([0.3, -1.2, 2.5])
    np.testing.assert_allclose(net.features(params, x)[:dX], x, rtol=1e-12)


@pytest.mark.parametrize(
    "config",
    [
        CostNetworkConfig(hidden=(), n_features=6),
        CostNetworkConfig(hidden=(), n_features=6, time_input=True, horizon=T),
        CostNetworkConfig(hidden=(), n_features=6, linear_skip=True, identity_init=False),
    ],
    ids=["plain", "time", "linear_skip"],
)
def test_affine_network_residual_is_one_matrix(config):
    """Without hidden layers the residual ``A y(z) + b`` is computed as ``M z + m`` and the state
    cost in Gram form; both must equal the layer-by-layer products, values and gradients."""
    net = CostNetwork(config, dX, dU, jnp.float64)
    params = net.init(jax.random.key(0))
    params = params.replace(net=jax.tree.map(lambda a: a + 0.1, params.net))  # b, biases ≠ 0
    norm = update_normaliser(params.norm, jax.random.normal(jax.random.key(1), (40, dX)) * 2 + 1)
    params = params.replace(norm=norm)
    xs = jax.random.normal(jax.random.key(2), (7, dX))
    ts = jnp.arange(7)

    def layered(net_params, x, t):
        p = params.replace(net=net_params)
        return p.net["A"] @ net.features(p, x, t) + p.net["b"]

    def collapsed(net_params, x, t):
        return net.state_residual(params.replace(net=net_params), x, t)

    for f in (layered, collapsed):
        assert jax.vmap(f, in_axes=(None, 0, 0))(params.net, xs, ts).shape == (7, 6)
    ref = jax.vmap(layered, in_axes=(None, 0, 0))(params.net, xs, ts)
    out = jax.vmap(collapsed, in_axes=(None, 0, 0))(params.net, xs, ts)
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-12)

    def total(f):
        return lambda p: jnp.sum(jax.vmap(f, in_axes=(None, 0, 0))(p, xs, ts) ** 2)

    g_ref = jax.grad(total(layered))(params.net)
    g_out = jax.grad(total(collapsed))(params.net)
    for a, b in zip(jax.tree.leaves(g_out), jax.tree.leaves(g_ref), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)

    # The state cost in Gram form is the squared layer-by-layer residual, gradients included.
    def gram(net_params):
        p = params.replace(net=net_params)
        return jnp.sum(jax.vmap(net.state_cost, in_axes=(None, 0, 0))(p, xs, ts))

    np.testing.assert_allclose(gram(params.net), total(layered)(params.net), rtol=1e-12)
    g_gram = jax.grad(gram)(params.net)
    for a, b in zip(jax.tree.leaves(g_gram), jax.tree.leaves(g_ref), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    # ... and its state gradient (the goal regulariser's) that of the residual form.
    s_ref = jax.grad(lambda x: jnp.sum(layered(params.net, x, 3) ** 2))(xs[0])
    np.testing.assert_allclose(jax.grad(net.state_cost, 1)(params, xs[0], 3), s_ref, rtol=1e-10)


def test_affine_residual_map_needs_an_affine_network():
    net = make_network()
    with pytest.raises(ValueError, match="hidden layers"):
        net.affine_residual_map(net.init(jax.random.key(0)))


def test_identity_init_rejects_narrow_layers():
    net = CostNetwork(CostNetworkConfig(hidden=(4,), n_features=5), dX, dU, jnp.float64)
    with pytest.raises(ValueError, match="identity_init"):
        net.init(jax.random.key(0))


def test_cost_is_squared_residual_and_nonnegative():
    net = make_network(time_input=True, horizon=T)
    params = net.init(jax.random.key(0))
    keys = jax.random.split(jax.random.key(1), 2)
    xs = jax.random.normal(keys[0], (20, dX))
    us = jax.random.normal(keys[1], (20, dU))
    ts = jnp.arange(20) % (T + 1)
    c = jax.vmap(net.cost, in_axes=(None, 0, 0, 0))(params, xs, us, ts)
    r = jax.vmap(net.residual, in_axes=(None, 0, 0, 0))(params, xs, us, ts)
    np.testing.assert_allclose(c, jnp.sum(r**2, axis=-1), rtol=1e-12)
    assert jnp.all(c >= 0)
    # The time input matters.
    assert not jnp.allclose(net.cost(params, xs[0], us[0], 0), net.cost(params, xs[0], us[0], T))


def test_time_input_needs_a_horizon():
    with pytest.raises(ValueError, match="horizon"):
        CostNetworkConfig(time_input=True)


def test_trajectory_cost_uses_terminal_step_without_action():
    net = make_network()
    params = net.init(jax.random.key(0))
    X = jax.random.normal(jax.random.key(1), (T + 1, dX))
    U = jax.random.normal(jax.random.key(2), (T, dU))
    by_hand = sum(net.cost(params, X[t], U[t], t) for t in range(T))
    by_hand += net.cost(params, X[T], jnp.zeros(dU), T)
    np.testing.assert_allclose(net.trajectory_cost(params, X, U), by_hand, rtol=1e-12)


def test_normaliser_merges_to_full_batch_moments_and_respects_mask():
    data = jax.random.normal(jax.random.key(0), (100, dX)) * jnp.array([1.0, 3.0, 0.1]) + 2.0
    norm = init_normaliser(dX, jnp.float64)
    for chunk in jnp.split(data, [10, 45, 80]):
        norm = update_normaliser(norm, chunk)
    np.testing.assert_allclose(norm.mean, data.mean(0), rtol=1e-12)
    np.testing.assert_allclose(norm.var, data.var(0), rtol=1e-10)
    assert norm.count == 100
    mask = jnp.arange(100) < 30
    masked = update_normaliser(init_normaliser(dX, jnp.float64), data, mask)
    np.testing.assert_allclose(masked.mean, data[:30].mean(0), rtol=1e-12)


def test_std_floor_and_no_gradient_into_normaliser():
    net = make_network(std_floor=0.5)
    params = net.init(jax.random.key(0))
    constant = jnp.ones((10, dX)) * jnp.array([1.0, 2.0, 3.0])
    params = params.replace(norm=update_normaliser(params.norm, constant))
    z = net.normalise(params, jnp.array([2.0, 2.0, 2.0]))
    np.testing.assert_allclose(z, jnp.array([2.0, 0.0, -2.0]))
    grads = jax.grad(lambda p: net.cost(p, jnp.ones(dX), jnp.ones(dU), 0))(params)
    assert all(jnp.all(g == 0) for g in jax.tree.leaves(grads.norm))
    assert any(jnp.any(g != 0) for g in jax.tree.leaves(grads.net))


def test_fixed_action_weight_gets_no_gradient():
    net = make_network(learn_action_weight=False, action_weight=0.3)
    params = net.init(jax.random.key(0))
    grads = jax.grad(lambda p: net.cost(p, jnp.ones(dX), jnp.ones(dU), 0))(params)
    assert grads.net["log_w_u"] == 0
    np.testing.assert_allclose(net.action_weight(params), 0.3)


def test_gauss_newton_expansion_of_the_network():
    net = make_network()
    params = net.init(jax.random.key(0))
    X = jax.random.normal(jax.random.key(1), (T + 1, dX))
    U = jax.random.normal(jax.random.key(2), (T, dU))
    quad = net.expand(params, X, U)
    direct = expand_residual_cost(net.bind_residual(params), X, U)
    np.testing.assert_allclose(quad.l_xx, direct.l_xx)
    full = net.expand(params, X, U, gauss_newton=False)
    np.testing.assert_allclose(full.l_x, quad.l_x, rtol=1e-10)  # same gradient, other Hessian
    U_all = jnp.concatenate([U, jnp.zeros((1, dU))])
    np.testing.assert_allclose(quad.l, jax.vmap(net.bind(params))(X, U_all, jnp.arange(T + 1)))
    assert jnp.all(jnp.linalg.eigvalsh(quad.l_xx) >= -1e-10)
    w_u = net.action_weight(params)
    np.testing.assert_allclose(quad.l_uu[:T], jnp.broadcast_to(2 * w_u * jnp.eye(dU), (T, dU, dU)))
    # l_xx = 2 JᵀAᵀAJ with J = ∂y/∂x.
    J = jax.jacfwd(net.features, argnums=1)(params, X[0], 0)
    A = params.net["A"]
    np.testing.assert_allclose(quad.l_xx[0], 2 * J.T @ A.T @ A @ J, rtol=1e-10, atol=1e-12)
    # Exact gradient.
    grad_x = jax.grad(net.cost, argnums=1)(params, X[0], U[0], 0)
    np.testing.assert_allclose(quad.l_x[0], grad_x, rtol=1e-10)


def test_jit_vmap_no_recompile():
    net = make_network()
    params = net.init(jax.random.key(0))
    batch_cost = jax.jit(jax.vmap(net.trajectory_cost, in_axes=(None, 0, 0)))
    X = jax.random.normal(jax.random.key(1), (4, T + 1, dX))
    U = jax.random.normal(jax.random.key(2), (4, T, dU))
    first = batch_cost(params, X, U)
    second = batch_cost(params, X + 1.0, U)
    assert first.shape == (4,) and jnp.all(jnp.isfinite(second))
    assert batch_cost._cache_size() == 1


def test_linear_skip_features_and_weight_decay_mask():
    from diffgcl.costs.gcl import GCLConfig, make_cost_learner

    net = make_network(linear_skip=True)
    params = net.init(jax.random.key(0))
    x = jnp.array([0.3, -1.2, 2.5])
    np.testing.assert_allclose(net.features(params, x)[:dX], x, rtol=1e-12)
    assert net.features(params, x).shape == (5,)
    # Decoupled decay shrinks the MLP and A but leaves the linear branch alone when grads vanish.
    learner = make_cost_learner(net, GCLConfig(weight_decay=0.5, learning_rate=0.1))
    state = learner.init(jax.random.key(0), params)
    zero = jax.tree.map(jnp.zeros_like, params.net)
    updates, _ = jax.jit(learner.optimiser.update)(zero, state.opt_state, params.net)
    new_net = optax.apply_updates(params.net, updates)
    features = new_net["features"]
    np.testing.assert_allclose(
        features["linear"]["kernel"], params.net["features"]["linear"]["kernel"]
    )
    old_mlp = params.net["features"]["mlp"]["Dense_0"]["kernel"]
    np.testing.assert_allclose(features["mlp"]["Dense_0"]["kernel"], old_mlp * (1 - 0.05))


def test_weighted_form_is_a_positive_weighting_of_squared_residuals():
    """form='weighted': s(x) = Σ_k e^(θ_k − mean θ) (x_k / rms_k)², rms from the data's moments; the
    Gauss–Newton expansion is exact for it (the residual is linear in x here) and GCL's
    optimiser decays none of its parameters."""
    from diffgcl.costs.gcl import GCLConfig, make_cost_learner

    config = CostNetworkConfig(form="weighted", action_weight=0.2)
    net = CostNetwork(config, dX, dU, jnp.float64)
    data = jax.random.normal(jax.random.key(1), (50, dX)) * jnp.array([1.0, 3.0, 0.5]) + 0.4
    params = net.init(jax.random.key(0)).replace(norm=net.fit_normaliser(data))
    params = params.replace(net={**params.net, "log_w": jnp.array([0.3, -1.0, 2.0])})
    rms = np.sqrt(np.mean(np.asarray(data) ** 2, axis=0))
    x, u = jnp.array([0.7, -2.0, 0.1]), jnp.array([0.5, -0.25])
    theta = np.array([0.3, -1.0, 2.0])
    w = np.exp(theta - theta.mean())  # only the ratios are learned
    expected = np.sum(w * (np.asarray(x) / rms) ** 2) + 0.2 * float(u @ u)
    np.testing.assert_allclose(float(net.cost(params, x, u)), expected, rtol=1e-12)
    np.testing.assert_allclose(net.feature_weights(params), w / rms**2, rtol=1e-12)
    # Every weight positive whatever θ: the cost's minimum is at x = 0.
    assert float(net.state_cost(params, jnp.zeros(dX))) == 0.0
    X = jax.random.normal(jax.random.key(2), (T + 1, dX))
    U = jax.random.normal(jax.random.key(3), (T, dU))
    gn, full = net.expand(params, X, U), net.expand(params, X, U, gauss_newton=False)
    np.testing.assert_allclose(gn.l_xx, full.l_xx, rtol=1e-10)
    np.testing.assert_allclose(gn.l_xx[0], 2 * np.diag(w / rms**2), rtol=1e-10)
    learner = make_cost_learner(net, GCLConfig(weight_decay=0.5, learning_rate=0.1))
    state = learner.init(jax.random.key(0), params)
    zero = jax.tree.map(jnp.zeros_like, params.net)
    updates, _ = learner.optimiser.update(zero, state.opt_state, params.net)
    new = optax.apply_updates(params.net, updates)
    np.testing.assert_allclose(new["log_w"], params.net["log_w"])
    with pytest.raises(ValueError, match="form"):
        CostNetworkConfig(form="sum")


def test_limit_weight_scales_the_actuator_limit_term_only():
    """``limit_weight`` λ multiplies the fixed limit term: c_λ − c_1 = e^ρ (λ − 1) ‖r_lim(u)‖²
    by hand, the state and action terms untouched; a non-positive λ is refused."""

    def limits(u):  # how far each action is past ±1
        return jnp.concatenate([jax.nn.relu(u - 1.0), jax.nn.relu(-u - 1.0)])

    x = jnp.array([0.3, -1.2, 2.5])
    u = jnp.array([1.7, -0.4])
    costs = {}
    for lam in (1.0, 25.0):
        net = CostNetwork(
            CostNetworkConfig(hidden=(8, 8), n_features=5, limit_weight=lam),
            dX,
            dU,
            jnp.float64,
            action_limits=limits,
        )
        params = net.init(jax.random.key(0))
        costs[lam] = float(net.cost(params, x, u, 0))
    over = 0.7**2  # only the first action is past its limit, by 0.7
    rho_scale = float(net.temperature(params))
    np.testing.assert_allclose(costs[25.0] - costs[1.0], rho_scale * 24.0 * over, rtol=1e-12)
    with pytest.raises(ValueError, match="limit_weight"):
        CostNetworkConfig(limit_weight=0.0)
