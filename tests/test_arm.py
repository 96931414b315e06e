"""The MJX arm against C MuJoCo: trajectories (mj_step) and Jacobians (mjd_transitionFD)."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from diffgcl.dynamics.autodiff import linearize
from diffgcl.envs import make_env


@pytest.fixture(scope="module")
def arm():
    return make_env("arm")


def c_model(env):
    model = mujoco.MjModel.from_xml_path(env.mjcf_path)
    model.actuator_forcerange[:] = [[-env.torque_limit, env.torque_limit]] * 2
    return model


def test_mjx_trajectory_matches_c_mujoco(arm):
    rng = np.random.default_rng(0)
    U = rng.normal(scale=1.5, size=(100, 2))  # saturates the motors some of the time
    x0 = np.asarray(arm.initial_states()[0])

    def scan(x0, U):
        def body(x, u):
            x = arm.step(x, u)
            return x, x

        return jax.lax.scan(body, x0, U)[1]

    X_mjx = np.asarray(jax.jit(scan)(jnp.asarray(x0), jnp.asarray(U)))

    model = c_model(arm)
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = x0[:2], x0[2:]
    X_c = []
    for u in U:
        data.ctrl[:] = u
        mujoco.mj_step(model, data)
        X_c.append(np.concatenate([data.qpos, data.qvel]))
    np.testing.assert_allclose(X_mjx, np.array(X_c), rtol=0, atol=1e-8)


def test_autodiff_jacobians_match_centred_finite_differences(arm):
    model = c_model(arm)
    data = mujoco.MjData(model)
    # Motors far from their torque cap, where the dynamics are smooth.
    for x, u in [
        (np.array([2.1, 1.2, 0.3, -0.4]), np.array([0.5, -0.2])),
        (np.array([-0.4, 0.9, -0.1, 0.2]), np.array([-0.1, 0.3])),
    ]:
        A, B = jax.jit(lambda x, u: linearize(arm.step, x, u))(jnp.asarray(x), jnp.asarray(u))
        data.qpos[:], data.qvel[:], data.ctrl[:] = x[:2], x[2:], u
        A_fd = np.zeros((4, 4))
        B_fd = np.zeros((4, 2))
        mujoco.mjd_transitionFD(model, data, 1e-6, True, A_fd, B_fd, None, None)
        np.testing.assert_allclose(np.asarray(A), A_fd, rtol=0, atol=1e-5)
        np.testing.assert_allclose(np.asarray(B), B_fd, rtol=0, atol=1e-5)


def test_cost_and_success(arm):
    T = arm.horizon
    X = jnp.zeros((T + 1, 4)).at[:, 0].set(0.05)
    assert bool(arm.success(X))
    assert not bool(arm.success(X.at[-3, 1].set(0.2)))
    x = jnp.array([1.0, -2.0, 0.0, 0.0])
    u = jnp.array([3.0, 4.0])
    np.testing.assert_allclose(arm.expert_cost(x, u, 0), 0.5 * 5.0 + 1e-5 * 0.5 * 25.0)


def test_box2d_torque_cap_is_an_option():
    env = make_env("arm", torque_limit=400.0)
    x = env.initial_states()[0]
    # A huge speed command saturates the motor: the torque on joint 1 is at most the cap.
    x1 = env.step(x, jnp.array([100.0, 0.0]))
    m1 = make_env("arm").step(x, jnp.array([100.0, 0.0]))
    assert float(x1[2]) < float(m1[2])
    with pytest.raises(ValueError, match="torque_limit"):
        make_env("arm", torque_limit=-1.0)
