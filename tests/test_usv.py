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
