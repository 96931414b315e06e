"""The ten-line path of diffgcl.api on a model the project does not tune for (the reacher), with
a tiny rGCL configuration: conditions and horizon from the demos, the report with and without the
user's test and cost, the run folder, and a user's folder left alone."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl import api
from diffgcl.data.demos import DemoError
from diffgcl.data.mujoco_demos import save_npz
from diffgcl.sim.rollout import rollout_controller
from diffgcl.types import make_controller

TINY = (
    "gps.num_samples=2",
    "gcl.pretrain_steps=3",
    "gcl.n_steps=2",
    "gcl.demo_batch=2",
    "gcl.sample_batch=2",
    "buffer_controllers=2",
    "freeze_last=0",
    "reopt_iterations=2",
)
STARTS = np.array([[0.0, 0.0, 0.0, 0.0], [1.0, -0.5, 0.0, 0.0]])


def near_start(X):
    """A stand-in success test: the first joint ends within 1 rad of where it started."""
    return jnp.abs(X[-1, 0] - X[0, 0]) < 1.0


def joint_cost(x, u, t):
    return x @ x + 0.1 * u @ u


@pytest.fixture(scope="module")
def demo_file(tmp_path_factory):
    """Three noisy PD-like rollouts from each of two start states (8 steps), as a user's npz."""
    env = api.load_model("reacher.xml", x0=STARTS, horizon=8)
    T = 8
    K = jnp.broadcast_to(jnp.asarray([[-0.5, 0, -0.1, 0], [0, -0.5, 0, -0.1]]), (T, 2, 4))
    ctrl = make_controller(K, jnp.zeros((T, 2)), jnp.broadcast_to(0.01 * jnp.eye(2), (T, 2, 2)))
    noise = jax.random.normal(jax.random.key(0), (6, T, 2))
    starts = jnp.asarray(STARTS)[jnp.arange(6) % 2]
    traj = jax.jit(jax.vmap(lambda x0, e: rollout_controller(env, ctrl, x0, e)))(starts, noise)
    r = api.rollout_arrays(env, traj.X, traj.U)
    clipped = np.clip(r.ctrl, -1, 1)
    return save_npz(tmp_path_factory.mktemp("demos") / "demos.npz", r.qpos, r.qvel, clipped)


def test_ten_line_path_learns_reports_and_saves(demo_file, tmp_path):
    env = api.load_model("reacher.xml", success=near_start, cost=joint_cost)
    demos = api.load_demos(demo_file, env)
    run = api.learn(env, demos, iterations=2, overrides=TINY, progress=False)
    rollout = run.rollout()
    report = run.report()
    out = run.save(tmp_path / "run")

    # Conditions: the two distinct start states (no labels in the file), horizon: the demos'.
    np.testing.assert_allclose(np.asarray(run.env.initial_states()), STARTS, atol=1e-12)
    assert run.env.horizon == 8 and report["conditions"] == 2 and report["demos"] == 6
    assert [e["condition"] for e in run.demos.episodes] == [0, 1, 0, 1, 0, 1]
    assert rollout.X.shape == (2, 9, 4) and rollout.ctrl.shape == (2, 8, 2)
    np.testing.assert_array_equal(rollout.qpos, rollout.X[..., :2])
    for key in ("learned_cost", "demo_learned_cost", "demo_distance", "entropy", "demo_entropy"):
        assert np.all(np.isfinite(report[key])), key
    assert np.asarray(report["demo_distance"]).shape == (1, 2)
    assert set(report["reoptimisation"]) >= {"demo_distance", "distance_to_rgcl", "success"}
    # The user's test and cost enter the report, evaluated on the rollouts.
    expected = np.asarray(jax.vmap(near_start)(jnp.asarray(rollout.X)))
    assert report["success"] == [expected.tolist()]
    assert report["success_rate"] == float(expected.all())
    true = [sum(joint_cost(x, u, 0) for x, u in zip(X, U, strict=False)) + X[-1] @ X[-1]
            for X, U in zip(rollout.X, rollout.U, strict=True)]  # fmt: skip
    np.testing.assert_allclose(report["true_cost"][0], true, rtol=1e-5)
    # The run folder.
    assert {p.name for p in out.iterdir()} == set(api.RUN_FILES)
    saved = json.loads((out / "report.json").read_text())
    assert saved["success"] == report["success"]
    with np.load(out / "learned.npz") as f:
        np.testing.assert_allclose(f["rollout_ctrl"], rollout.ctrl)
        assert f["K"].shape == (1, 2, 8, 2, 4)
    run.save(out)  # an earlier run of the API may be replaced


def test_report_without_user_test_or_cost_and_a_users_folder_survives(demo_file, tmp_path):
    env = api.load_model("reacher.xml")
    run = api.learn(env, api.load_demos(demo_file, env), iterations=1, overrides=TINY,
                    progress=False)  # fmt: skip
    report = run.report(reoptimise=False)
    assert "success" not in report and "true_cost" not in report
    assert "reoptimisation" not in report and np.isfinite(report["mean_demo_distance"])
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match=r"mine: folder not empty and not a run"):
        run.save(mine)
    assert (mine / "notes.txt").read_text() == "keep me" and len(list(mine.iterdir())) == 1


def test_demos_that_do_not_fit_the_model(demo_file):
    other = api.load_model("cartpole.xml")
    with pytest.raises(DemoError, match=r"qpos must be \[steps, 2\]|ctrl must be \[steps, 1\]"):
        api.load_demos(demo_file, other)
    env = api.load_model("reacher.xml", dt=0.04)
    with pytest.raises(DemoError, match=r"demos: dt = 0\.02 s, the env steps 0\.04 s"):
        api.learn(env, api.load_demos(demo_file, api.load_model("reacher.xml")), iterations=1)
