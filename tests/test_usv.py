"""The USV task (diffgcl.envs.usv, diffgcl.data.task_frame): exact ranges against mjx.ray in the
hull's MJCF scene, the same dynamics and expert cost as the hull env, the task frame keeping the
demos' geometry, and the evaluation's collision test against the env's clearance."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl.envs.hull import make_hull_env
from diffgcl.envs.usv import IX_RADIUS, make_usv_env, pole_ranges
from diffgcl.sim import hull as hull_sim


def random_states(key, n, pole=(40.0, 3.0)):
    """Hull states around a pole: positions within 80 m, any heading, some speed."""
    k1, k2, k3 = jax.random.split(key, 3)
    p = jnp.asarray(pole) + jax.random.uniform(k1, (n, 2), minval=-80.0, maxval=80.0)
    psi = jax.random.uniform(k2, (n,), minval=-np.pi, maxval=np.pi)
    v = jax.random.normal(k3, (n, 3)) * jnp.array([4.0, 1.0, 0.1])
    x = jnp.zeros((n, hull_sim.DX))
    x = x.at[:, :2].set(p).at[:, hull_sim.IX_PSI].set(psi).at[:, hull_sim.SL_QVEL].set(v)
    x = x.at[:, hull_sim.IX_THRUST].set(6000.0).at[:, hull_sim.IX_NOZZLE].set(0.1)
    return x.at[:, hull_sim.SL_OBS].set(jnp.asarray(pole))


@pytest.mark.parametrize("radius", [0.3, 0.9])
def test_exact_ranges_equal_mjx_ray(radius):
    hull_env = make_hull_env(pole_radius=radius)
    X = random_states(jax.random.PRNGKey(0), 24)
    X = X.at[0, :2].set(jnp.array([40.0 - 30.0, 3.0])).at[0, hull_sim.IX_PSI].set(0.0)  # ahead
    ray = jax.jit(jax.vmap(hull_env.ranges))(X)
    exact = jax.vmap(lambda x: pole_ranges(hull_env.layout, x, radius))(X)
    np.testing.assert_allclose(np.asarray(exact), np.asarray(ray), atol=1e-6)
    assert float(jnp.min(ray[0])) < 40.0  # the pole straight ahead is seen


def test_step_cost_and_clearance_agree_with_the_hull_env():
    radius = 0.7
    usv = make_usv_env(cruise_speed=9.0)
    hull_env = make_hull_env(pole_radius=radius, cruise_speed=9.0, horizon=usv.horizon)
    X = random_states(jax.random.PRNGKey(1), 6)
    Xu = jnp.concatenate([X, jnp.full((6, 1), radius)], axis=1)
    u = jnp.array([0.3, -0.4])
    u_phys = usv.command(u)
    np.testing.assert_allclose(
        np.asarray(u_phys), [usv.cruise_thrust + 0.3 * 12000.0, -0.4 * np.deg2rad(30.0)]
    )
    np.testing.assert_allclose(np.asarray(usv.normalised_action(u_phys)), np.asarray(u))
    nxt = jax.vmap(lambda x: usv.step(x, u))(Xu)
    ref = jax.vmap(lambda x: hull_env.step(x, u_phys))(X)
    np.testing.assert_allclose(np.asarray(nxt[:, :IX_RADIUS]), np.asarray(ref), rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(nxt[:, IX_RADIUS]), radius)
    for t in (0, usv.horizon):
        c = jax.vmap(lambda x, t=t: usv.expert_cost(x, u, t))(Xu)
        r = jax.vmap(lambda x, t=t: hull_env.expert_cost(x, u_phys, t))(X)
        np.testing.assert_allclose(np.asarray(c), np.asarray(r), rtol=1e-12)
    np.testing.assert_allclose(
        np.asarray(jax.vmap(usv.clearance)(Xu)), np.asarray(jax.vmap(hull_env.clearance)(X))
    )


def test_observation_layouts_and_features():
    usv = make_usv_env(horizon=20)
    x = usv.initial_states()[1].at[hull_sim.IX_PY].set(1.5).at[hull_sim.IX_PSI].set(0.1)
    x = x.at[hull_sim.IX_PX].set(x[hull_sim.IX_OBS_X] - 30.0)  # the pole 30 m ahead
    o = usv.obs(x)
    assert o.shape == (usv.dO,) == (54,)
    np.testing.assert_allclose(np.asarray(o[48:50]), [np.sin(0.1), np.cos(0.1)])
    assert float(o[-1]) == 1.5
    assert float(jnp.min(o[:32])) < 30.0  # the LiDAR sees it
    noisy = usv.obs(x, jax.random.PRNGKey(0))
    assert 0.0 < float(jnp.max(jnp.abs(noisy - o)[:32])) < 0.5
    radar = make_usv_env(horizon=20, observation="radar")
    np.testing.assert_allclose(np.asarray(radar.obs(x)[:16]), np.asarray(o[32:48]))
    assert radar.dO == 22 and make_usv_env(observation="ranges").dO == 51
    f = jax.jacfwd(usv.cost_features)(x)
    assert f.shape == (16, usv.dX) and np.isfinite(np.asarray(f)).all()
    with pytest.raises(ValueError, match="observation"):
        make_usv_env(observation="sonar")
    with pytest.raises(ValueError, match="radius"):
        make_usv_env(np.zeros((1, 11)))
    for margins in [(), (10.0, 5.0), (0.0, 5.0)]:
        with pytest.raises(ValueError, match="proximity margins"):
            make_usv_env(proximity_margins=margins)


def test_range_encodings():
    """Metres as read; saturated: metres near the boat, far things alike, the same encoding in
    the env's observation."""
    from diffgcl.envs.usv import SATURATION_RANGE, encode_ranges

    r = jnp.linspace(0.0, 300.0, 301)
    np.testing.assert_array_equal(np.asarray(encode_ranges(r, "metres")), np.asarray(r))
    s = np.asarray(encode_ranges(r, "saturated"))
    assert np.all(np.diff(s) > 0) and np.all(s < SATURATION_RANGE)  # order kept, bounded
    slope = jax.grad(lambda v: encode_ranges(v, "saturated"))
    assert float(slope(jnp.asarray(0.0))) == pytest.approx(1.0)
    assert float(slope(jnp.asarray(10.0))) > 0.97  # metres within a swerve's reach
    np.testing.assert_allclose(s, SATURATION_RANGE * np.tanh(np.asarray(r) / SATURATION_RANGE))
    # A pole 230 m astern against no return (300 m): 0.1 % apart, not 23 % as in metres.
    assert (s[300] - s[230]) / s[300] < 0.002
    with pytest.raises(ValueError, match="range encoding"):
        encode_ranges(r, "inches")
    with pytest.raises(ValueError, match="range encoding"):
        make_usv_env(range_encoding="inches")
    plain = make_usv_env(horizon=20)
    sat = make_usv_env(horizon=20, range_encoding="saturated")
    x = plain.initial_states()[0]
    x = x.at[hull_sim.IX_PX].set(x[hull_sim.IX_OBS_X] - 40.0)
    n = plain.layout.num_beams
    o, o_sat = np.asarray(plain.obs(x)), np.asarray(sat.obs(x))
    np.testing.assert_allclose(o_sat[:n], np.asarray(encode_ranges(o[:n], "saturated")))
    np.testing.assert_array_equal(o_sat[n:], o[n:])


def test_success_and_metrics_follow_the_clearance():
    usv = make_usv_env(horizon=10)
    x = usv.initial_states()[0]
    X = jnp.broadcast_to(x, (11, usv.dX))
    m = usv.metrics(X)
    assert not bool(m["collision"]) and bool(m["success"])  # on course, far from the pole
    hit = X.at[5, :2].set(X[5, hull_sim.SL_OBS] + jnp.array([0.0, 1.0]))
    m = usv.metrics(hit)
    assert bool(m["collision"]) and not bool(m["success"]) and float(m["min_clearance"]) < 0
    assert float(m["side"]) == 1.0  # the boat is above (to the left of) the pole


def world_demos(n=3, T=40, seed=0):
    """Straight-ish hull tracks in world coordinates past poles, as ingestion would give them."""
    from diffgcl.data.demos import DemoSet
    from diffgcl.envs.hull import observation

    rng = np.random.default_rng(seed)
    X = np.zeros((n, T + 1, hull_sim.DX))
    for i in range(n):
        start, course = rng.uniform(-200, 200, 2), rng.uniform(-np.pi, np.pi)
        e = np.array([np.cos(course), np.sin(course)])
        pole = start + (90.0 + 10.0 * i) * e + rng.normal(0, 1, 2)
        t = np.arange(T + 1)[:, None]
        p = start + 5.0 * t * e + np.sin(t / 7.0) * 3.0 * np.array([-e[1], e[0]])
        X[i, :, :2] = p
        X[i, :, hull_sim.IX_PSI] = course + 0.1 * np.sin(t[:, 0] / 5.0) + 2 * np.pi * (i - 1)
        X[i, :, hull_sim.IX_VX : hull_sim.IX_VY + 1] = np.gradient(p, axis=0) / 0.1
        X[i, :, hull_sim.IX_R] = rng.normal(0, 0.05, T + 1)
        X[i, :, hull_sim.SL_OBS] = pole
    ranges = rng.uniform(1, 60, (n, T + 1, 48))
    O = np.asarray(
        jax.vmap(jax.vmap(lambda r, x: observation(r, x[2], hull_sim.body_velocity(x))))(
            jnp.asarray(ranges), jnp.asarray(X)
        )
    )
    U = rng.normal(size=(n, T, 2))
    return DemoSet(X=X, U=U, O=O, mask=np.ones((n, T + 1)), dt=0.1, env="hull")


def test_task_frame_keeps_the_geometry():
    from diffgcl.data.task_frame import rotate_states, to_task_frame

    demos = world_demos()
    task = to_task_frame(demos)

    def pole_distance(X):
        return np.hypot(*(X[..., :2] - X[..., hull_sim.SL_OBS]).T)

    np.testing.assert_allclose(pole_distance(task.X), pole_distance(demos.X), rtol=1e-12)
    np.testing.assert_allclose(task.X[:, 0, :2], 0.0, atol=1e-9)  # the start is the origin
    np.testing.assert_allclose(task.X[:, :, hull_sim.IX_OBS_Y], 0.0, atol=1e-9)  # pole ahead
    assert np.all(task.X[:, :, hull_sim.IX_OBS_X] > 0)
    assert np.all(np.abs(task.X[:, 0, hull_sim.IX_PSI]) < np.pi)
    nu = jax.vmap(jax.vmap(hull_sim.body_velocity))
    np.testing.assert_allclose(nu(task.X), nu(demos.X), atol=1e-9)  # body frame unchanged
    np.testing.assert_allclose(task.O[..., :48], demos.O[..., :48])  # ranges unchanged
    np.testing.assert_allclose(task.O[..., 48], np.sin(task.X[..., hull_sim.IX_PSI]), atol=1e-12)
    np.testing.assert_allclose(task.U, demos.U)
    for i in range(demos.num_episodes):  # the inverse transform gives the bag's data back
        frame = task.episodes[i]["task_frame"]
        back = rotate_states(task.X[i], np.zeros(2), -frame["course"])
        back[:, :2] += frame["origin"]
        back[:, hull_sim.SL_OBS] += frame["origin"]
        d = back[:, hull_sim.IX_PSI] - demos.X[i, :, hull_sim.IX_PSI]
        np.testing.assert_allclose(np.cos(d), 1.0, atol=1e-12)
        back[:, hull_sim.IX_PSI] = demos.X[i, :, hull_sim.IX_PSI]
        np.testing.assert_allclose(back, demos.X[i], atol=1e-9)


def test_pass_windows_centre_the_closest_approach():
    from diffgcl.data.task_frame import closest_approach, pass_windows, to_task_frame

    task = to_task_frame(world_demos(T=40))
    k = [closest_approach(task.X[i], task.mask[i]) for i in range(3)]
    before, after = min(k), 40 - max(k)
    win = pass_windows(task, before, after)
    assert win.X.shape == (3, before + after + 1, hull_sim.DX) and win.horizon == before + after
    for i in range(3):
        assert closest_approach(win.X[i], win.mask[i]) == before
        assert win.episodes[i]["window"] == [k[i] - before, k[i] + after]
    with pytest.warns(UserWarning, match="no valid window"):
        short = pass_windows(task, before + 1, after)
    assert short.num_episodes < 3


def test_pass_tails_continue_each_window_and_pad_with_the_last_recorded_state():
    import dataclasses

    from diffgcl.data.task_frame import closest_approach, pass_tails, pass_windows, to_task_frame

    task = to_task_frame(world_demos(T=40))
    k = [closest_approach(task.X[i], task.mask[i]) for i in range(3)]
    before, after = min(k), 40 - max(k) - 6  # every episode recorded 6 or more steps past
    mask = task.mask.copy()
    end = k[1] + after + 3  # episode 1 ends 3 steps past its window
    mask[1, end + 1 :] = 0.0
    task = dataclasses.replace(task, mask=mask)
    win = pass_windows(task, before, after)
    tails = pass_tails(task, before, after, 5)
    assert tails.shape == (3, 6, hull_sim.DX)
    for i in range(3):
        np.testing.assert_array_equal(tails[i, 0], win.X[i, -1])
        b = k[i] + after
        n = min(5, win.episodes[i]["recorded_after"])
        np.testing.assert_array_equal(tails[i, : n + 1], task.X[i, b : b + n + 1])
        np.testing.assert_array_equal(
            tails[i, n + 1 :], np.broadcast_to(task.X[i, b + n], (5 - n, hull_sim.DX))
        )
    assert win.episodes[1]["recorded_after"] == 3


def test_network_on_task_features_is_the_network_on_the_features():
    """A cost network with a feature map equals the plain network applied to φ(x); its goal
    regulariser differentiates through the normaliser the same way."""
    from diffgcl.costs.gcl import goal_penalty
    from diffgcl.costs.network import CostNetwork, CostNetworkConfig

    usv = make_usv_env()
    phi = usv.cost_features
    config = CostNetworkConfig(hidden=(40,), n_features=20, features="env")
    net = CostNetwork(config, usv.dX, usv.dU, jnp.float64, feature_map=phi)
    bare = CostNetwork(config, 16, usv.dU, jnp.float64)
    X = usv.initial_states()
    X = X.at[:, hull_sim.IX_PX].set(jnp.array([60.0, 90.0, 100.0, 95.0]))
    params = net.init(jax.random.PRNGKey(0)).replace(norm=net.fit_normaliser(X))
    u = jnp.array([0.2, -0.1])
    for x in X:
        np.testing.assert_allclose(
            float(net.cost(params, x, u)), float(bare.cost(params, phi(x), u)), rtol=1e-12
        )
    traj = jnp.broadcast_to(X[0], (5, usv.dX))
    norm = params.norm
    std = jnp.maximum(jnp.sqrt(norm.var), config.std_floor)
    grad = jax.grad(lambda f: bare.state_cost(params, f, 4))(phi(traj[-1]))
    np.testing.assert_allclose(
        float(goal_penalty(net, params, traj[-1], 4)),
        float(jnp.sum((grad * std) ** 2)),
        rtol=1e-12,
    )


@pytest.mark.parametrize("margins", [None, (5.0, 15.0, 25.0)])
def test_cost_residuals_square_to_the_sailors_terms(margins):
    """The weighted cost's residuals: squared heading residual = 2(1 − cos ψ) (periodic), progress
    is the speed made good along the course, the barriers are the softplus depth inside each
    margin (zero-ish well outside; the default margins or the task's own), and all are
    differentiable in the state."""
    from diffgcl.envs.usv import COST_RESIDUAL_NAMES, PROXIMITY_MARGINS, PROXIMITY_SOFTNESS

    if margins is None:
        usv, margins = make_usv_env(horizon=20), PROXIMITY_MARGINS
        assert usv.cost_residual_names == COST_RESIDUAL_NAMES
    else:
        usv = make_usv_env(horizon=20, proximity_margins=margins)
    assert usv.cost_residual_names[6:] == tuple(f"inside_{d:g}m" for d in margins)
    X = jnp.concatenate([random_states(jax.random.PRNGKey(3), 16), jnp.full((16, 1), 0.6)], 1)
    X = X.astype(usv.x0.dtype)
    R = jax.vmap(usv.cost_residuals)(X)
    assert R.shape == (16, 6 + len(margins)) == (16, len(usv.cost_residual_names))
    psi = np.asarray(X[:, hull_sim.IX_PSI])
    np.testing.assert_allclose(np.asarray(R[:, 1]) ** 2, 2 * (1 - np.cos(psi)), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(R[:, 0]), np.asarray(X[:, hull_sim.IX_PY]))
    np.testing.assert_allclose(
        np.asarray(R[:, 3]), np.asarray(X[:, hull_sim.IX_VX]) - usv.cruise_speed, rtol=1e-6
    )
    clearance = np.asarray(jax.vmap(usv.clearance)(X), dtype=np.float64)
    s = PROXIMITY_SOFTNESS
    for k, d in enumerate(margins):
        expected = s * np.logaddexp(0.0, (d - clearance) / s)
        np.testing.assert_allclose(np.asarray(R[:, 6 + k]), expected, rtol=1e-4, atol=1e-6)
    far = X[0].at[hull_sim.SL_OBS].set(X[0, :2] + jnp.array([200.0, 0.0]))
    assert float(jnp.max(usv.cost_residuals(far)[6:])) < 1e-10 + 2.0 * np.exp(-80.0)
    x_wrapped = X[0].at[hull_sim.IX_PSI].add(2 * np.pi)
    np.testing.assert_allclose(
        np.asarray(usv.cost_residuals(x_wrapped)) ** 2,
        np.asarray(usv.cost_residuals(X[0])) ** 2,
        rtol=1e-4,
        atol=1e-6,
    )
    J = jax.jacfwd(usv.cost_residuals)(X[0])
    assert J.shape == (6 + len(margins), usv.dX) and np.isfinite(np.asarray(J)).all()


def test_action_limit_residuals_are_the_expert_costs_limit_barrier():
    """‖r_lim(ũ)‖² equals the hand-written cost's limit penalty (weight × Σ (s softplus(z/s))²
    over the four limits), is ~0 inside the actuator range, and joins a learned cost's residual
    (the network's cost and Gauss–Newton residual both carry it)."""
    from diffgcl.algorithms.presets import usv as usv_preset
    from diffgcl.algorithms.rgcl import make_network

    usv = make_usv_env(horizon=20)
    p = usv.params
    U = jnp.array([[0.0, 0.0], [0.1, -0.5], [0.9, 1.3], [-1.2, -2.0], [3.0, 0.2]], usv.x0.dtype)

    def barrier(u):
        cmd = usv.command(u)
        sp = lambda z: (0.02 * jax.nn.softplus(z / 0.02)) ** 2  # noqa: E731
        return usv.weights.limits * (
            sp((cmd[0] - p.max_thrust) / p.max_thrust)
            + sp((-p.reverse_fraction * p.max_thrust - cmd[0]) / p.max_thrust)
            + sp((cmd[1] - p.max_nozzle) / p.max_nozzle)
            + sp((-p.max_nozzle - cmd[1]) / p.max_nozzle)
        )

    for u in U:
        r = usv.action_limit_residuals(u)
        np.testing.assert_allclose(float(r @ r), float(barrier(u)), rtol=1e-4, atol=1e-9)
    assert float(jnp.sum(usv.action_limit_residuals(U[1]) ** 2)) < 1e-6  # inside the range
    assert float(jnp.sum(usv.action_limit_residuals(U[2]) ** 2)) > 1.0  # nozzle hard beyond
    net = make_network(usv_preset(), usv)
    params = net.init(jax.random.PRNGKey(0))
    x = usv.initial_states()[0]
    w_u = float(net.action_weight(params))
    expected = float(net.state_cost(params, x)) + w_u * float(U[2] @ U[2]) + float(barrier(U[2]))
    np.testing.assert_allclose(float(net.cost(params, x, U[2])), expected, rtol=1e-4)
    r = net.residual(params, x, U[2])
    np.testing.assert_allclose(float(r @ r), expected, rtol=1e-4)


def _free_network_preset():
    """``usv_neural`` with the free network in the learned barrier's place (``--set
    network.barrier_margins=()``)."""
    import dataclasses

    from diffgcl.algorithms.presets import usv_neural

    base = usv_neural()
    return dataclasses.replace(base, network=dataclasses.replace(base.network, barrier_margins=()))


def test_neural_cost_is_zero_at_the_goal_and_reads_bounded_features():
    """The neural form (``‖A (y(z) − y(z*))‖²`` on the task features): zero at the env's goal
    state and at any state whose features equal the goal's (the pole further astern), positive
    elsewhere, with a PSD Gauss-Newton expansion; the features stay bounded far from the pole."""
    from diffgcl.algorithms.rgcl import make_network

    usv = make_usv_env(horizon=10)
    net = make_network(_free_network_preset(), usv)
    params = net.init(jax.random.PRNGKey(0))
    params = params.replace(norm=net.fit_normaliser(usv.initial_states()))
    goal = usv.cost_goal_state()
    assert float(net.state_cost(params, goal)) == 0.0
    further = goal.at[hull_sim.IX_OBS_X].set(-5000.0)  # saturated features: the same reading
    assert float(net.state_cost(params, further)) < 1e-6
    for x in usv.initial_states():
        assert float(net.state_cost(params, x)) > 0.0
    X = jnp.stack([usv.initial_states()[0]] * 3)
    U = jnp.zeros((2, usv.dU), X.dtype)
    quad = net.expand(params, X, U)
    assert np.all(np.linalg.eigvalsh(np.asarray(quad.l_xx)) > -1e-9)
    f_far = usv.cost_features(usv.start_state(jnp.array([1e5, 3.0]), 0.5, 10.0))
    assert float(jnp.max(jnp.abs(f_far[:7]))) <= 60.0 + 1e-9
    with pytest.raises(ValueError, match="goal_state"):
        from diffgcl.costs.network import CostNetwork

        CostNetwork(_free_network_preset().network, usv.dX, usv.dU)


def test_shape_only_neural_cost_has_a_fixed_scale():
    """``network.shape_only``: the same network's cost does not change when ``A`` is scaled, nor
    when the hidden layers' output grows (tanh-bounded features), stays zero at the goal, and
    never exceeds ``‖Â‖_F² · max‖tanh y − tanh y*‖² = (a_scale² F)(4F)`` per step."""
    import dataclasses

    from diffgcl.algorithms.rgcl import make_network

    usv = make_usv_env(horizon=10)
    config = _free_network_preset()
    config = dataclasses.replace(
        config, network=dataclasses.replace(config.network, shape_only=True, prior_residuals=False)
    )
    net = make_network(config, usv)
    params = net.init(jax.random.PRNGKey(0))
    params = params.replace(norm=net.fit_normaliser(usv.initial_states()))
    x = usv.initial_states()[0]
    c = float(net.state_cost(params, x))
    assert c > 0.0
    assert float(net.state_cost(params, usv.cost_goal_state())) == 0.0
    scaled = params.replace(net={**params.net, "A": 10.0 * params.net["A"]})
    np.testing.assert_allclose(float(net.state_cost(scaled, x)), c, rtol=1e-5)
    # Every weight matrix ×100: the features saturate, the cost stays under its bound.
    grown = params.replace(net=jax.tree.map(lambda a: 100.0 * a if a.ndim == 2 else a, params.net))
    F = params.net["A"].shape[0]
    bound = config.network.a_scale**2 * F * 4 * F
    for x in usv.initial_states():
        assert 0.0 <= float(net.state_cost(grown, x)) <= bound * float(net.temperature(grown))
    with pytest.raises(ValueError, match="shape_only"):
        dataclasses.replace(config.network, form="weighted")
    # asinh instead of tanh: the same scale invariance and zero at the goal, and the cost keeps
    # growing with the features (the ×100 network costs more, but far less than its raw ×10⁴+).
    asinh = make_network(
        dataclasses.replace(config, network=dataclasses.replace(config.network, squash="asinh")),
        usv,
    )
    c_asinh = float(asinh.state_cost(params, x))
    assert float(asinh.state_cost(params, usv.cost_goal_state())) == 0.0
    np.testing.assert_allclose(float(asinh.state_cost(scaled, x)), c_asinh, rtol=1e-5)
    c_grown = float(asinh.state_cost(grown, x))
    assert c_asinh < c_grown < 1e3 * c_asinh
    with pytest.raises(ValueError, match="squash"):
        dataclasses.replace(config.network, squash="relu")


def test_two_pole_env_sees_and_collides_with_both_poles():
    """The judging env with a second pole further down the course: the hull moves as in the
    one-pole env, the beams read the nearer pole, the clearance is to the nearer pole, and the
    observation keeps the one-pole layout."""
    from diffgcl.envs.usv import DX, two_pole_env

    usv = make_usv_env(horizon=20)
    x0 = usv.initial_states()[:2]
    two = two_pole_env(usv, x0, (100.0, 100.0), (1.0, 1.0), jax.random.PRNGKey(0))
    assert two.dX == DX + 3 and two.dO == usv.dO and two.x0.shape == (2, DX + 3)
    x = two.x0[0]
    np.testing.assert_allclose(float(x[DX]), float(x0[0, hull_sim.IX_OBS_X]) + 100.0)
    u = jnp.array([0.1, -0.2])
    np.testing.assert_array_equal(np.asarray(two.step(x, u)[:DX]), np.asarray(usv.step(x[:DX], u)))
    np.testing.assert_array_equal(np.asarray(two.step(x, u)[DX:]), np.asarray(x[DX:]))
    # Far from both: the first pole is nearer, and its reading is the one-pole env's.
    assert float(two.clearance(x)) == float(usv.clearance(x[:DX]))
    np.testing.assert_array_equal(np.asarray(two.obs(x)), np.asarray(usv.obs(x[:DX])))
    # Just short of the second pole (the first far astern): the beams and clearance see it.
    near = x.at[hull_sim.IX_PX].set(x[DX] - 12.0).at[hull_sim.IX_PY].set(x[DX + 1])
    assert float(two.clearance(near)) < 12.0 < float(usv.clearance(near[:DX]))
    assert float(jnp.min(two.ranges(near))) < float(jnp.min(usv.ranges(near[:DX])))
    inside = near.at[hull_sim.IX_PX].set(x[DX])
    assert bool(two.metrics(jnp.stack([x, inside]))["collision"])


def test_neural_cost_with_prior_residuals_weighs_the_course_beside_the_network():
    """``network.prior_residuals``: the state cost is the course residuals' weighted squares
    (each over its RMS on the fitted states, floored at ``std_floor``) plus the network's term,
    each scaled by ``e^θ̃`` with ``mean θ̃ = 0``; the network reads the task features alone; the
    cost is zero at the goal, grows without bound off the course line, and its Gauss-Newton
    expansion is PSD. A network without the option, or an env without prior residuals, is
    refused."""
    import dataclasses

    from diffgcl.algorithms.rgcl import make_network
    from diffgcl.costs.network import CostNetwork

    usv = make_usv_env(horizon=10)
    base = _free_network_preset()
    shape = dataclasses.replace(base.network, shape_only=True, prior_residuals=False)
    prior = dataclasses.replace(shape, prior_residuals=True)
    net = make_network(dataclasses.replace(base, network=prior), usv)
    alone = make_network(dataclasses.replace(base, network=shape), usv)
    assert net.network_input_dim == alone.state_input_dim == 16 and net.prior_dim == 6
    params = net.init(jax.random.PRNGKey(0))
    X = usv.initial_states()
    X = jnp.concatenate([X, X.at[:, hull_sim.IX_PY].add(7.0).at[:, hull_sim.IX_VX].add(-2.0)])
    params = params.replace(norm=net.fit_normaliser(X))
    theta = jnp.array([0.3, -0.2, 0.5, 0.0, -0.4, 0.1, 0.7], X.dtype)
    params = params.replace(net={**params.net, "log_w": theta})
    alone_params = net.init(jax.random.PRNGKey(0))
    alone_params = alone_params.replace(
        net={k: v for k, v in params.net.items() if k != "log_w"},
        norm=alone.fit_normaliser(X),
    )
    rho = jax.vmap(usv.cost_prior_residuals)(X)
    rms = np.maximum(np.sqrt(np.mean(np.asarray(rho) ** 2, axis=0)), prior.std_floor)
    w = np.exp(np.asarray(theta) - np.mean(np.asarray(theta)))
    for x in X:
        r = np.asarray(usv.cost_prior_residuals(x))
        expected = np.sum(w[:6] * (r / rms) ** 2) + w[6] * float(alone.state_cost(alone_params, x))
        np.testing.assert_allclose(float(net.state_cost(params, x)), expected, rtol=1e-9)
    assert float(net.state_cost(params, usv.cost_goal_state())) < 1e-12
    far = [float(net.state_cost(params, X[0].at[hull_sim.IX_PY].set(d))) for d in (100, 1000)]
    assert far[1] > 50.0 * far[0] > 0.0  # quadratic in the cross-track error, not bounded
    quad = net.expand(params, jnp.stack([X[0]] * 3), jnp.zeros((2, usv.dU), X.dtype))
    assert np.all(np.linalg.eigvalsh(np.asarray(quad.l_xx)) > -1e-9)
    grad = jax.grad(lambda p: net.state_cost(p, X[1]))(params)
    assert np.all(np.abs(np.asarray(grad.net["log_w"])) > 0.0)
    with pytest.raises(ValueError, match="prior_map"):
        CostNetwork(prior, usv.dX, usv.dU, goal_state=tuple(usv.cost_goal_state().tolist()))
    with pytest.raises(ValueError, match="prior_residuals"):
        dataclasses.replace(prior, form="weighted", shape_only=False)


def test_cost_features_have_bounded_derivatives_at_the_pole():
    """The learned cost's task features stay smooth where a boat sails through the pole's
    centre: over a grid of positions around it (the centre included) no feature's gradient in
    the hull's position exceeds a few per metre (by the pole's bearing over ``sqrt(d² + L²)``;
    over ``d`` it ran past 10³), and far from the pole the bearing is the bearing."""
    from diffgcl.envs.usv import BEARING_SOFTNESS

    usv = make_usv_env(horizon=10)
    x0 = usv.initial_states()[0]
    pole = x0[hull_sim.SL_OBS]
    worst = 0.0
    for dx in (-3.0, -0.5, 0.0, 1e-3, 0.5, 3.0):
        for dy in (-2.0, -1e-3, 0.0, 0.7, 4.0):
            x = x0.at[hull_sim.IX_PX].set(pole[0] + dx).at[hull_sim.IX_PY].set(pole[1] + dy)
            J = jax.jacfwd(usv.cost_features)(x)[:, jnp.array([hull_sim.IX_PX, hull_sim.IX_PY])]
            assert np.all(np.isfinite(np.asarray(J)))
            worst = max(worst, float(jnp.max(jnp.abs(J[:7]))))
    speed = float(jnp.linalg.norm(x0[hull_sim.SL_QVEL][:2]))
    assert worst < 2.0 + 2.0 * speed / BEARING_SOFTNESS
    far = x0.at[hull_sim.IX_PX].set(pole[0] - 500.0).at[hull_sim.IX_PY].set(pole[1])
    np.testing.assert_allclose(float(usv.cost_features(far)[4]), 1.0, atol=1e-3)  # dead ahead


def _usv_network_builder(usv, network_config):
    """``CostNetwork`` of ``network_config`` on the USV's task features, goal and course
    residuals, with the remaining fields (mirror, clearance features) left to the caller."""
    import functools

    from diffgcl.costs.network import CostNetwork

    return functools.partial(
        CostNetwork,
        network_config,
        usv.dX,
        usv.dU,
        goal_state=tuple(usv.cost_goal_state().tolist()),
        feature_map=usv.cost_features,
        prior_map=usv.cost_prior_residuals,
    )


def _reflect(x: jnp.ndarray) -> jnp.ndarray:
    """The situation reflected across the course line (world y = 0): y, heading, world sway
    velocity, yaw rate, nozzle angle and the pole's y change sign."""
    flip = np.ones(x.shape[-1])
    for i in (
        hull_sim.IX_PY,
        hull_sim.IX_PSI,
        hull_sim.IX_VY,
        hull_sim.IX_R,
        hull_sim.IX_NOZZLE,
        hull_sim.IX_OBS_Y,
    ):
        flip[i] = -1.0
    return x * flip


def test_cost_feature_mirror_is_the_features_under_reflection():
    """``UsvEnv.cost_feature_mirror`` is what reflecting the state does to each task feature,
    checked on the state itself over random situations (moving, turned, jets working)."""
    usv = make_usv_env(horizon=10)
    sign = np.asarray(usv.cost_feature_mirror)
    rng = np.random.default_rng(3)
    for x in usv.initial_states():
        for _ in range(4):
            x = x.at[:10].add(
                jnp.asarray(rng.normal(size=10) * [20, 15, 0.5, 2, 1, 0.2, 50, 0.2, 0, 0])
            )
            np.testing.assert_allclose(
                np.asarray(usv.cost_features(_reflect(x))),
                sign * np.asarray(usv.cost_features(x)),
                atol=1e-12,
            )
            r = np.asarray(usv.cost_prior_residuals(x))  # the course residuals only flip sign
            np.testing.assert_allclose(
                np.abs(np.asarray(usv.cost_prior_residuals(_reflect(x)))), np.abs(r), atol=1e-12
            )


def test_mirrored_neural_cost_cannot_prefer_a_side():
    """``network.mirror``: the neural cost of a situation equals its reflection's, to rounding,
    and is the mean of the unmirrored network's cost of the two; without it a random network
    tells the two apart (so the check can fail); a mirror needs the option and vice versa."""
    import dataclasses

    from diffgcl.algorithms.rgcl import make_network

    usv = make_usv_env(horizon=10)
    base = _free_network_preset()
    mirrored = dataclasses.replace(base, network=dataclasses.replace(base.network, mirror=True))
    net, plain = make_network(mirrored, usv), make_network(base, usv)
    X = usv.initial_states()
    X = jnp.concatenate([X, X.at[:, hull_sim.IX_PX].add(80.0).at[:, hull_sim.IX_PY].add(-6.0)])
    params = net.init(jax.random.PRNGKey(1))
    params = params.replace(norm=net.fit_normaliser(X))
    u = jnp.array([0.3, -0.2])
    gaps = []
    for x in X:
        mirrored_u = u * jnp.array([1.0, -1.0])  # the nozzle command flips
        c, c_ref = float(net.cost(params, x, u)), float(net.cost(params, _reflect(x), mirrored_u))
        np.testing.assert_allclose(c, c_ref, rtol=1e-10)
        a, b = float(plain.state_cost(params, x)), float(plain.state_cost(params, _reflect(x)))
        # the prior residuals are symmetric, so only the network's term is averaged
        np.testing.assert_allclose(float(net.state_cost(params, x)), 0.5 * (a + b), rtol=1e-10)
        gaps.append(abs(a - b) / max(a, b))
    assert max(gaps) > 1e-3
    quad = net.expand(params, jnp.stack([X[4]] * 3), jnp.zeros((2, usv.dU), X.dtype))
    assert np.all(np.linalg.eigvalsh(np.asarray(quad.l_xx)) > -1e-9)
    build = _usv_network_builder(usv, mirrored.network)
    with pytest.raises(ValueError, match="feature_mirror"):
        build()
    with pytest.raises(ValueError, match="16 signs"):
        build(feature_mirror=(1.0,) * 15)
    with pytest.raises(ValueError, match="mirror"):
        dataclasses.replace(
            mirrored.network, form="weighted", shape_only=False, prior_residuals=False
        )


def test_cost_clearance_features_read_the_clearance():
    """``UsvEnv.cost_clearance_features``: the first is the saturated clearance itself and every
    one is a function of the clearance alone (the learned barrier's gate must not see them)."""
    from diffgcl.envs.usv import SATURATION_RANGE

    usv = make_usv_env(horizon=10)
    first, *rest = usv.cost_clearance_features
    rng = np.random.default_rng(5)
    for x in usv.initial_states():
        x = x.at[:3].add(jnp.asarray(rng.normal(size=3) * [30, 15, 0.5]))
        f, c = np.asarray(usv.cost_features(x)), float(usv.clearance(x))
        np.testing.assert_allclose(f[first], SATURATION_RANGE * np.tanh(c / SATURATION_RANGE))
        ells = sorted(float(-max(c, 0.0) / np.log(f[i])) for i in rest)  # exp(−c/ℓ)
        np.testing.assert_allclose(ells, [5.0, 20.0], rtol=1e-9)


def _barrier_network(**network):
    import dataclasses

    from diffgcl.algorithms.presets import usv_neural
    from diffgcl.algorithms.rgcl import make_network

    usv = make_usv_env(horizon=10)
    base = usv_neural()
    margins = base.network.barrier_margins  # the preset's learned barrier
    assert margins == (2.5, 5.0, 10.0, 20.0)
    cfg = dataclasses.replace(base, network=dataclasses.replace(base.network, **network))
    net = make_network(cfg, usv)
    X = usv.initial_states()
    params = net.init(jax.random.PRNGKey(2))
    return usv, net, params.replace(norm=net.fit_normaliser(X)), np.asarray(margins)


def test_learned_barrier_is_the_soft_hinge_on_the_clearance_at_the_start():
    """``network.barrier_margins``: at initialisation (gate 1) the network's term is
    ``Σ_k (s·softplus((m_k − c)/s) / m_k)² / K`` of the clearance feature ``c``, checked
    against numpy from the feature itself, over clearances inside, near and far beyond the
    margins."""
    usv, net, params, margins = _barrier_network()
    s = net.config.barrier_softness
    x0 = usv.initial_states()[0]
    f0 = net.state_input(x0)
    for c in (-1.0, 0.0, 1.5, 4.0, 9.0, 19.0, 35.0, 59.0):
        f = f0.at[0].set(c)
        r = np.asarray(net.residual_of_input(params, f))[-len(margins) :]
        w_net = float(np.exp(0.5 * np.asarray(net.log_weights(params))[-1]))
        hinge = s * np.logaddexp(0.0, (margins - c) / s) / margins  # softplus, as a fraction
        np.testing.assert_allclose(r, w_net * hinge / np.sqrt(len(margins)), rtol=1e-10)


def test_learned_barrier_cannot_open_a_hole_at_the_pole():
    """Whatever the gate learns (random, large network weights), the network's term rises
    monotonically as the clearance falls, ignores the other clearance features, stays within a
    factor e² per margin of the gate-1 barrier, and its Gauss–Newton expansion is PSD; the
    options without their env part, or on another form, are refused by name."""
    import dataclasses

    usv, net, params, margins = _barrier_network()
    K = len(margins)
    keys = jax.random.split(jax.random.PRNGKey(7), 3)
    leaves, tree = jax.tree.flatten(params.net["features"])
    noisy = [
        3.0 * jax.random.normal(k, v.shape, v.dtype)
        for k, v in zip(jax.random.split(keys[0], len(leaves)), leaves, strict=True)
    ]
    gate_net = dict(params.net)
    gate_net["features"] = jax.tree.unflatten(tree, noisy)
    gate_net["A"] = 3.0 * jax.random.normal(keys[1], params.net["A"].shape)
    gate_net["b"] = jax.random.normal(keys[2], (K,))
    gated = params.replace(net=gate_net)

    def barrier(p, f):
        return np.asarray(net.residual_of_input(p, f))[-K:]

    rng = np.random.default_rng(11)
    X = usv.initial_states()
    ratios = []
    for x in X:
        x = x.at[:3].add(jnp.asarray(rng.normal(size=3) * [30, 15, 0.5]))
        f = net.state_input(x)
        costs = []
        for c in np.linspace(40.0, -1.0, 42):
            fc = f.at[0].set(c)
            r = barrier(gated, fc)
            costs.append(float(r @ r))
            other = fc.at[2].set(rng.uniform()).at[3].set(rng.uniform())  # proximities
            np.testing.assert_allclose(barrier(gated, other), r, rtol=1e-12)
            ratios.append(r / np.maximum(barrier(params, fc), 1e-300))
        assert np.all(np.diff(costs) >= 0.0) and costs[-1] > 10.0 * costs[0]
    ratios = np.concatenate(ratios)
    assert np.all((ratios > np.exp(-1.0) * (1 - 1e-9)) & (ratios < np.exp(1.0) * (1 + 1e-9)))
    assert ratios.max() / ratios.min() > 2.0  # the gate does vary with the situation
    quad = net.expand(gated, jnp.stack([X[3]] * 3), jnp.zeros((2, usv.dU), X.dtype))
    assert np.all(np.linalg.eigvalsh(np.asarray(quad.l_xx)) > -1e-9)

    build = _usv_network_builder(usv, net.config)
    with pytest.raises(ValueError, match="clearance_features"):
        build()
    with pytest.raises(ValueError, match=r"distinct indices in \[0, 16\)"):
        build(clearance_features=(16,))
    with pytest.raises(ValueError, match="barrier_margins is for form 'neural'"):
        dataclasses.replace(net.config, form="weighted", shape_only=False, prior_residuals=False)
    with pytest.raises(ValueError, match="must be > 0"):
        dataclasses.replace(net.config, barrier_margins=(5.0, 0.0))
    with pytest.raises(ValueError, match=r"tuple of margins in metres, \(\) for no"):
        dataclasses.replace(net.config, barrier_margins=None)


def test_learned_barrier_margins_move_only_when_learned():
    """``barrier_learn_margins``: off (the default), the cost has no gradient in the margins, so
    GCL leaves them where they start; on, it has (for a state inside the margins)."""
    for learn in (False, True):
        usv, net, params, margins = _barrier_network(barrier_learn_margins=learn)
        x = usv.initial_states()[0]
        f = net.state_input(x).at[0].set(4.0)  # inside the 5, 10 and 20 m margins

        def cost(log_margin, f=f, net=net, params=params):
            p = params.replace(net={**params.net, "log_margin": log_margin})
            r = net.residual_of_input(p, f)
            return r @ r

        g = np.asarray(jax.grad(cost)(params.net["log_margin"]))
        if learn:
            assert np.all(np.abs(g[1:]) > 1e-6)
        else:
            np.testing.assert_array_equal(g, 0.0)
