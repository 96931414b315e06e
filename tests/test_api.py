"""The ten-line path of diffgcl.api on a model the project does not tune for (the reacher).

Default suite: conditions from the demos' start states, a user's folder left alone, demos that do
not fit the model. Slow (``make test-slow``; rGCL with a policy compiled for a new model takes
minutes on 2 cores): the whole path with a tiny rGCL configuration — conditions and horizon from
the demos, the cost on the state and the fingertip, the report with and without the user's test
and cost, the global policy, the run folder."""

import dataclasses
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


@pytest.fixture(scope="module")
def run(demo_file):  # used by slow tests only
    """The ten lines' learning step on the reacher, tiny: one seed, two iterations, a policy."""
    env = api.load_model("reacher.xml", obs=("state", "site:fingertip"))
    demos = api.load_demos(demo_file, env)
    return api.learn(env, demos, iterations=2, overrides=TINY, policy=True, progress=False)


@pytest.mark.slow
def test_learn_takes_conditions_and_horizon_from_the_demos_and_reports(run, tmp_path):
    # Conditions: the two distinct start states (no labels in the file), horizon: the demos'.
    np.testing.assert_allclose(np.asarray(run.env.initial_states()), STARTS, atol=1e-12)
    assert run.env.horizon == 8 and run.env.dO == 7
    assert [e["condition"] for e in run.demos.episodes] == [0, 1, 0, 1, 0, 1]
    # The cost reads the state and the fingertip, normalised by the demos.
    network = run.network()
    assert run.config.network.features == "env" and network.state_input_dim == 7
    norm = jax.tree.map(lambda a: np.asarray(a[0]), run.cost_params.norm)
    S = np.asarray(jax.vmap(jax.vmap(run.env.cost_features))(jnp.asarray(run.demos.X)))
    np.testing.assert_allclose(norm.mean, S.reshape(-1, 7).mean(0), rtol=1e-10, atol=1e-12)

    rollout, policy = run.rollout(), run.policy_rollout()
    assert rollout.X.shape == (2, 9, 4) and rollout.ctrl.shape == (2, 8, 2)
    assert policy.X.shape == (2, 9, 4) and np.all(np.isfinite(policy.X))
    np.testing.assert_array_equal(rollout.qpos, rollout.X[..., :2])
    held_out = run.policy_rollout(np.array([[0.5, 0.5, 0.0, 0.0]]))
    assert held_out.X.shape == (1, 9, 4)

    report = run.report(reoptimise=False)
    assert report["conditions"] == 2 and report["demos"] == 6
    for key in ("learned_cost", "demo_learned_cost", "demo_distance", "entropy", "demo_entropy"):
        assert np.all(np.isfinite(report[key])), key
    assert np.asarray(report["demo_distance"]).shape == (1, 2)
    assert np.asarray(report["policy"]["demo_distance"]).shape == (1, 2)
    # Without the user's test and cost there are no success or true-cost entries.
    assert "success" not in report and "true_cost" not in report
    assert "success" not in report["policy"] and "reoptimisation" not in report

    out = run.save(tmp_path / "run")
    assert {p.name for p in out.iterdir()} == set(api.RUN_FILES)
    assert json.loads((out / "report.json").read_text())["demos"] == 6
    with np.load(out / "learned.npz") as f:
        np.testing.assert_allclose(f["rollout_ctrl"], rollout.ctrl)
        np.testing.assert_allclose(f["policy_rollout_X"], policy.X)
        assert f["K"].shape == (1, 2, 8, 2, 4)
    run.save(out)  # an earlier run of the API may be replaced
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match=r"mine: folder not empty and not a run"):
        run.save(mine)
    assert (mine / "notes.txt").read_text() == "keep me" and len(list(mine.iterdir())) == 1


@pytest.mark.slow
def test_the_users_test_and_cost_enter_the_report(run):
    env = run.env.with_task(success=near_start, cost=joint_cost)
    report = dataclasses.replace(run, env=env, _report=None).report()
    rollout = run.rollout()
    expected = np.asarray(jax.vmap(near_start)(jnp.asarray(rollout.X)))
    assert report["success"] == [expected.tolist()]
    assert report["success_rate"] == float(expected.all())
    true = [sum(joint_cost(x, u, 0) for x, u in zip(X, U, strict=False)) + X[-1] @ X[-1]
            for X, U in zip(rollout.X, rollout.U, strict=True)]  # fmt: skip
    np.testing.assert_allclose(report["true_cost"][0], true, rtol=1e-5)
    assert set(report["reoptimisation"]) >= {"demo_distance", "distance_to_rgcl", "success"}
    assert "success" in report["policy"] and "true_cost" in report["policy"]


def test_demos_that_do_not_fit_the_model(demo_file):
    other = api.load_model("cartpole.xml")
    with pytest.raises(DemoError, match=r"qpos must be \[steps, 2\]|ctrl must be \[steps, 1\]"):
        api.load_demos(demo_file, other)
    env = api.load_model("reacher.xml", dt=0.04)
    with pytest.raises(DemoError, match=r"demos: dt = 0\.02 s, the env steps 0\.04 s"):
        api.learn(env, api.load_demos(demo_file, api.load_model("reacher.xml")), iterations=1)


def test_conditions_from_labels_or_equal_start_states():
    from diffgcl.data.demos import DemoSet

    X = np.zeros((5, 3, 2))
    X[:, 0] = [[0, 0], [1, 0], [0, 0], [1, 0], [2, 0]]
    X[:, 1:] = np.arange(5)[:, None, None]
    U = np.zeros((5, 2, 1))

    def demos(episodes=()):
        return DemoSet(X=X, U=U, O=X, mask=np.ones((5, 3)), dt=0.1, env="e", episodes=episodes)

    x0, labelled = api.demo_conditions(demos())
    np.testing.assert_array_equal(x0, [[0, 0], [1, 0], [2, 0]])
    assert [e["condition"] for e in labelled.episodes] == [0, 1, 0, 1, 2]
    x0, labelled = api.demo_conditions(demos(tuple({"condition": c} for c in [1, 0, 1, 0, 0])))
    np.testing.assert_allclose(x0, [[4 / 3, 0], [0, 0]])
    with pytest.raises(DemoError, match=r"condition labels must be 0\.\.C-1, got \[0, 2\]"):
        api.demo_conditions(demos(tuple({"condition": c} for c in [0, 2, 0, 2, 0])))


def test_a_users_folder_is_never_written_into(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match=r"mine: folder not empty and not a run"):
        api._run_folder(mine)
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(FileExistsError, match=r"file: exists and is not a folder"):
        api._run_folder(tmp_path / "file")
    ours = api._run_folder(tmp_path / "new")
    (ours / "run.json").write_text(json.dumps({"format": api.RUN_FORMAT}))
    assert api._run_folder(ours) == ours


def test_cli_train_mjcf_needs_demos(capsys):
    from diffgcl.cli import main

    with pytest.raises(SystemExit, match=r"train --mjcf: give the demonstrations with --demos"):
        main(["train", "--mjcf", "reacher.xml", "--x64"])


@pytest.mark.slow
def test_cli_train_mjcf_writes_the_run_folder(demo_file, tmp_path, capsys):
    from diffgcl.cli import main

    out = tmp_path / "cli_run"
    args = ["train", "--mjcf", "reacher.xml", "--demos", str(demo_file), "--out", str(out)]
    args += ["--seeds", "1", "--iterations", "1", "--no-progress", "--x64", "--policy", "mdgps"]
    args += [a for item in TINY for a in ("--set", item)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "conditions 2, horizon 8" in printed and "global policy" in printed
    assert json.loads((out / "run.json").read_text())["format"] == api.RUN_FORMAT
