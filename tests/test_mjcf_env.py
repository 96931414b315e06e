"""The generic MJCF env: equal to the hand-built arm, the quaternion chart against SciPy, a free-
joint model against C MuJoCo and its tangent-space linearisation against finite differences
(float64), observations against C MuJoCo, and one-line errors for what MJX cannot run."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from diffgcl.dynamics.autodiff import fit_dynamics, linearize
from diffgcl.envs import make_env
from diffgcl.envs.mjcf_env import make_mjcf_env
from diffgcl.sim.coordinates import configuration_chart, quat_exp, quat_log
from diffgcl.sim.mjcf import MJCFError, load_mjcf, mjx_unsupported
from diffgcl.sim.rollout import sample_controller
from diffgcl.types import make_controller

# ---- the arm, twice -----------------------------------------------------------------------------


def test_generic_env_of_arm2d_gives_exactly_the_arm_envs_rollouts_and_linearisations():
    arm = make_env("arm", horizon=20)
    generic = make_mjcf_env("arm2d.xml", x0=arm.initial_states(), horizon=20)
    assert (generic.dX, generic.dU, generic.dt) == (arm.dX, arm.dU, arm.dt)
    assert generic.chart.identity
    T = 20
    rng = np.random.default_rng(0)
    ctrl = make_controller(
        jnp.asarray(rng.normal(scale=0.3, size=(T, 2, 4))),
        jnp.asarray(rng.normal(size=(T, 2))),
        jnp.broadcast_to(0.5 * jnp.eye(2), (T, 2, 2)),
    )
    x0 = arm.initial_states()[0]

    @jax.jit
    def both(key):
        out = []
        for env in (arm, generic):
            traj = sample_controller(env, ctrl, x0, key, 4, smooth_sigma=2.0, with_obs=False)
            out.append((traj.X, traj.U, fit_dynamics(env.step, traj.X, traj.U)))
        return out

    (X_a, U_a, dyn_a), (X_g, U_g, dyn_g) = both(jax.random.key(3))
    assert X_a.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(X_g), np.asarray(X_a))
    np.testing.assert_array_equal(np.asarray(U_g), np.asarray(U_a))
    for name in ("A", "B", "c", "cov"):
        np.testing.assert_array_equal(np.asarray(getattr(dyn_g, name)), getattr(dyn_a, name))
    assert np.abs(np.asarray(X_a[:, -1] - X_a[:, 0])).max() > 0.1  # the arm moved


# ---- the chart ----------------------------------------------------------------------------------


def _scipy_quat(r):
    x, y, z, w = Rotation.from_rotvec(np.array(r, float)).as_quat()
    return np.array([w, x, y, z])


def test_quaternion_exp_and_log_against_scipy_and_at_the_identity():
    rng = np.random.default_rng(1)
    for r in [*rng.normal(size=(5, 3)), np.array([1e-5, -2e-5, 0.5e-5]), np.zeros(3)]:
        q = np.asarray(quat_exp(jnp.asarray(r)))
        np.testing.assert_allclose(q, _scipy_quat(r), atol=1e-14)
        np.testing.assert_allclose(np.asarray(quat_log(jnp.asarray(q))), r, atol=1e-13)
        np.testing.assert_allclose(np.asarray(quat_log(jnp.asarray(-q))), r, atol=1e-13)
    # Derivatives at and near the identity: exp'(0) = [0; ½I], log'(1) = [0, 2I]; the Taylor
    # branch and the closed form agree with central differences.
    J_exp = np.asarray(jax.jacfwd(quat_exp)(jnp.zeros(3)))
    np.testing.assert_allclose(J_exp, np.vstack([np.zeros(3), 0.5 * np.eye(3)]), atol=1e-15)
    J_log = np.asarray(jax.jacfwd(quat_log)(jnp.asarray([1.0, 0.0, 0.0, 0.0])))
    np.testing.assert_allclose(J_log[:, 1:], 2.0 * np.eye(3), atol=1e-15)
    for r in (np.array([3e-5, 1e-5, -2e-5]), np.array([0.3, -0.2, 0.1])):
        eps = 1e-7
        fd = np.stack(
            [(_scipy_quat(r + eps * e) - _scipy_quat(r - eps * e)) / (2 * eps) for e in np.eye(3)],
            1,
        )
        np.testing.assert_allclose(np.asarray(jax.jacfwd(quat_exp)(jnp.asarray(r))), fd, atol=1e-8)


def test_chart_round_trip_of_the_space_robot():
    model = load_mjcf("space_robot.xml")
    chart = configuration_chart(model)
    assert (chart.nq, chart.nv, chart.joint_names) == (12, 10, ("root", "shoulder"))
    xq = jnp.asarray([0.1, -0.2, 1.0, 0.4, -0.3, 0.5, 0.3, 0.2, -0.6, 0.7])
    qpos = chart.to_qpos(xq)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(qpos[3:7])), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(qpos[3:7]), _scipy_quat(np.asarray(xq[3:6])), atol=1e-15)
    np.testing.assert_allclose(np.asarray(chart.from_qpos(qpos)), np.asarray(xq), atol=1e-14)


# ---- a free joint: C MuJoCo and the tangent space -----------------------------------------------


def _c_step(model, data, x, u, ref_root, ref_shoulder):
    """C MuJoCo's step in the env's coordinates, with SciPy's rotations (independent of
    diffgcl.sim.coordinates): q = q_ref ⊗ exp(r)."""

    def to_quat(r, ref):
        rot = Rotation.from_quat(np.roll(ref, -1)) * Rotation.from_rotvec(r)
        return np.roll(rot.as_quat(), 1)

    def to_vec(q, ref):
        return (Rotation.from_quat(np.roll(ref, -1)).inv() * Rotation.from_quat(np.roll(q, -1)))\
            .as_rotvec()  # fmt: skip

    data.qpos[:3] = x[:3]
    data.qpos[3:7] = to_quat(x[3:6], ref_root)
    data.qpos[7:11] = to_quat(x[6:9], ref_shoulder)
    data.qpos[11] = x[9]
    data.qvel[:] = x[10:]
    data.ctrl[:] = u
    data.qacc_warmstart[:] = 0
    mujoco.mj_step(model, data)
    q = data.qpos
    return np.concatenate(
        [q[:3], to_vec(q[3:7], ref_root), to_vec(q[7:11], ref_shoulder), q[11:], data.qvel]
    )


def test_free_and_ball_joints_step_like_c_mujoco_and_linearise_in_the_tangent_space():
    # The keyframe's orientations (not the identity) are the chart's reference and start state.
    env = make_mjcf_env("space_robot.xml", keyframe="tumbling")
    assert (env.nq, env.nv, env.dX, env.dU) == (12, 10, 20, 10)
    model = load_mjcf(env.mjcf_path)
    key = model.key_qpos[0]
    refs = key[3:7] / np.linalg.norm(key[3:7]), key[7:11] / np.linalg.norm(key[7:11])
    np.testing.assert_allclose(np.asarray(env.initial_states()[0, :10]),
                               [0, 0, 1, 0, 0, 0, 0, 0, 0, 0.5], atol=1e-15)  # fmt: skip
    data = mujoco.MjData(model)
    f = lambda x, u: _c_step(model, data, x, u, *refs)

    rng = np.random.default_rng(0)
    x = np.concatenate([[0.1, -0.2, 1.0], [0.4, -0.3, 0.5], [0.3, 0.2, -0.6], [0.7]])
    x = np.concatenate([x, rng.normal(size=10)])
    u = rng.uniform(-1, 1, size=10)
    step = jax.jit(env.step)
    np.testing.assert_allclose(
        np.asarray(step(jnp.asarray(x), jnp.asarray(u))), f(x, u), atol=1e-12
    )

    A, B = jax.jit(lambda x, u: linearize(env.step, x, u))(jnp.asarray(x), jnp.asarray(u))
    eps = 1e-6
    A_fd = np.stack([(f(x + eps * e, u) - f(x - eps * e, u)) / (2 * eps) for e in np.eye(20)], 1)
    B_fd = np.stack([(f(x, u + eps * e) - f(x, u - eps * e)) / (2 * eps) for e in np.eye(10)], 1)
    np.testing.assert_allclose(np.asarray(A), A_fd, atol=1e-8)
    np.testing.assert_allclose(np.asarray(B), B_fd, atol=1e-8)
    # The orientation rows couple to the angular velocities (the chart's derivative is not I).
    assert np.abs(np.asarray(A)[3:6, 13:16] - env.dt * np.eye(3)).max() > 1e-3
    # A perturbation along the tangent space is predicted to second order.
    dx = 1e-4 * rng.normal(size=20)
    pred = f(x, u) + np.asarray(A) @ dx
    assert np.abs(f(x + dx, u) - pred).max() < 1e-6


# ---- options: frame skip, observations, conditions ----------------------------------------------


def test_frame_skip_observations_and_keyframe_conditions():
    env1 = make_mjcf_env("reacher.xml", obs=("state", "site:fingertip", "sensor:fingertip_pos"))
    env2 = make_mjcf_env("reacher.xml", dt=0.04, obs="qpos", conditions=3, spread=0.5, seed=2)
    assert (env1.dO, env2.dO, env2.frame_skip, env2.dt) == (10, 2, 2, 0.04)
    X0 = np.asarray(env2.initial_states())
    assert X0.shape == (3, 4) and np.all(X0[:, 2:] == 0) and np.ptp(X0[:, 0]) > 0.1
    x = jnp.asarray([0.3, -0.7, 0.5, -1.0])
    u = jnp.asarray([0.4, -0.2])
    two_steps, skipped, o = jax.jit(
        lambda x, u: (env1.step(env1.step(x, u), u), env2.step(x, u), env1.obs(x))
    )(x, u)
    np.testing.assert_allclose(np.asarray(skipped), np.asarray(two_steps), atol=1e-14)
    model = load_mjcf("reacher.xml")
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = [0.3, -0.7], [0.5, -1.0]
    mujoco.mj_forward(model, data)
    o = np.asarray(o)
    tip = data.site_xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "fingertip")]
    np.testing.assert_allclose(o[:4], np.asarray(x))
    np.testing.assert_allclose(o[4:7], tip, atol=1e-12)
    np.testing.assert_allclose(o[7:10], data.sensordata[:3], atol=1e-12)
    with pytest.raises(MJCFError, match=r"obs part 'site:nose'.*no site named 'nose'$"):
        make_mjcf_env("reacher.xml", obs=("site:nose",))
    with pytest.raises(MJCFError, match=r"dt = 0.03 is not a whole multiple"):
        make_mjcf_env("reacher.xml", dt=0.03)
    with pytest.raises(MJCFError, match=r"no keyframe 'home'"):
        make_mjcf_env("reacher.xml", keyframe="home")
    with pytest.raises(MJCFError, match=r"x0 must be \[4\] or \[C, 4\]"):
        make_mjcf_env("reacher.xml", x0=np.zeros(5))


def test_action_scale_by_control_range():
    env = make_mjcf_env("space_robot.xml", action_scale="range")
    assert np.all(env.ctrl_scale == 1.0)
    env = make_mjcf_env("cartpole.xml", action_scale=[2.0])
    np.testing.assert_allclose(np.asarray(env.ctrl_from_action(jnp.asarray([0.25]))), [0.5])
    np.testing.assert_allclose(np.asarray(env.action_from_ctrl(np.asarray([0.5]))), [0.25])
    with pytest.raises(MJCFError, match=r"action_scale must be 1 positive numbers"):
        make_mjcf_env("cartpole.xml", action_scale=[0.0])


# ---- what MJX cannot run ------------------------------------------------------------------------

_UNSUPPORTED = {
    "adhesion": (
        """<mujoco><worldbody><body name="pad"><joint name="j"/><geom size="0.1" mass="1"/>
        </body></worldbody><actuator><adhesion name="grip" body="pad" ctrlrange="0 1"/>
        </actuator></mujoco>""",
        r"MJX cannot run actuator 'grip': transmission mjTRN_BODY$",
    ),
    "solver": (
        """<mujoco><option solver="PGS"/><worldbody><body><joint name="j"/>
        <geom size="0.1"/></body></worldbody><actuator><motor joint="j"/></actuator></mujoco>""",
        r"MJX cannot run <option solver>: mjSOL_PGS$",
    ),
    "collision": (
        """<mujoco><worldbody><geom name="floor_box" type="box" size="1 1 0.1"/>
        <body name="b" pos="0 0 1"><freejoint name="b_free"/>
        <geom name="can" type="cylinder" size="0.1 0.2"/></body></worldbody>
        <actuator><motor joint="b_free" gear="1 0 0 0 0 0"/></actuator></mujoco>""",
        r"geom 'can' and geom 'floor_box': collisions mjGEOM_CYLINDER-mjGEOM_BOX$",
    ),
    "no actuators": (
        """<mujoco><worldbody><body><joint/><geom size="0.1"/></body></worldbody></mujoco>""",
        r"the model has no actuators",
    ),
}


@pytest.mark.parametrize("case", sorted(_UNSUPPORTED))
def test_what_mjx_cannot_run_is_one_line_naming_element_and_feature(case, tmp_path):
    xml, message = _UNSUPPORTED[case]
    path = tmp_path / f"{case.replace(' ', '_')}.xml"
    path.write_text(xml)
    with pytest.raises(MJCFError) as err:
        make_mjcf_env(path)
    text = str(err.value)
    assert "\n" not in text and text.startswith(str(path))
    assert len(__import__("re").findall(message, text)) == 1, text


def test_mjx_unsupported_is_none_for_every_shipped_model():
    from diffgcl.sim.mjcf import models_dir

    for path in sorted(models_dir().glob("*.xml")):
        assert mjx_unsupported(load_mjcf(path)) is None, path.name
