"""Demos in MuJoCo's terms (npz of qpos/qvel/ctrl, imitation-style (obs, acts) pairs): converted
to the env's states exactly, and every bad input a one-line error naming file, episode, array and
step."""

import re
from dataclasses import dataclass

import jax
import numpy as np
import pytest

from diffgcl.data.demos import DemoError
from diffgcl.data.mujoco_demos import (
    demos_from_npz,
    demos_from_trajectories,
    load_demos,
    save_npz,
)
from diffgcl.envs.mjcf_env import make_mjcf_env


@pytest.fixture(scope="module")
def reacher():
    return make_mjcf_env("reacher.xml", action_scale=[0.5, 1.0])


@pytest.fixture(scope="module")
def robot():
    return make_mjcf_env("space_robot.xml")


def episodes(n=3, T=6, seed=0):
    rng = np.random.default_rng(seed)
    qpos = rng.uniform(-1, 1, size=(n, T + 1, 2))
    qvel = rng.normal(size=(n, T + 1, 2))
    ctrl = rng.uniform(-0.9, 0.9, size=(n, T, 2))
    return qpos, qvel, ctrl


def test_npz_stacked_and_per_episode_give_the_env_states(reacher, tmp_path):
    qpos, qvel, ctrl = episodes()
    path = save_npz(tmp_path / "d.npz", qpos, qvel, ctrl, condition=[0, 1, 0], dt=0.02)
    demos = demos_from_npz(path, reacher)
    np.testing.assert_array_equal(demos.X, np.concatenate([qpos, qvel], -1))
    np.testing.assert_allclose(demos.U, ctrl / [0.5, 1.0])  # actions: ctrl / ctrl_scale
    np.testing.assert_array_equal(demos.O, demos.X)  # the default observation is the state
    assert [e["condition"] for e in demos.episodes] == [0, 1, 0]
    assert demos.dt == 0.02 and demos.env == "reacher"
    # Per-episode arrays of different lengths, cut to a common horizon.
    long = episodes(1, T=9, seed=1)
    per_episode = [list(a) + list(b) for a, b in zip(episodes(), long, strict=True)]
    path = save_npz(tmp_path / "e.npz", *per_episode)
    with pytest.raises(DemoError, match=r"episodes differ in length \(episode 0: 6 control steps, "
                       r"episode 3: 9\); pass horizon="):  # fmt: skip
        load_demos(path, reacher)
    demos = load_demos(path, reacher, horizon=5)
    assert demos.X.shape == (4, 6, 4) and demos.U.shape == (4, 5, 2)
    np.testing.assert_array_equal(demos.X[3, :, :2], long[0][0, :6])


def test_quaternions_become_rotation_vectors_and_back(robot, tmp_path):
    rng = np.random.default_rng(2)
    x = rng.normal(scale=0.5, size=(2, 5, robot.dX))
    qpos, qvel, _ = jax.vmap(jax.vmap(robot.mujoco_from_state))(x)
    ctrl = rng.uniform(-1, 1, size=(2, 4, robot.dU))
    path = save_npz(tmp_path / "r.npz", np.asarray(qpos), np.asarray(qvel), ctrl)
    demos = load_demos(path, robot)
    np.testing.assert_allclose(demos.X, x, atol=1e-12)
    # A quaternion scaled by 1.0005 is renormalised; by 1.01 it is an error.
    q = np.array(qpos)
    q[:, :, 3:7] *= 1.0005
    np.testing.assert_allclose(load_demos(save_npz(path, q, qvel, ctrl), robot).X, x, atol=1e-12)
    q[1, 2, 7:11] *= 1.01
    with pytest.raises(DemoError, match=r"episode 1: qpos\[2, 7:11\] \(joint 'shoulder'\) is a "
                       r"quaternion of norm 1\.01"):  # fmt: skip
        load_demos(save_npz(path, q, qvel, ctrl), robot)


@dataclass
class ImitationTrajectory:
    """The fields of imitation's ``Trajectory`` this format reads."""

    obs: np.ndarray
    acts: np.ndarray


def test_obs_acts_pairs_and_imitation_trajectories(reacher):
    qpos, qvel, ctrl = episodes(2)
    obs = np.concatenate([qpos, qvel], -1)
    from_pairs = demos_from_trajectories([(o, a) for o, a in zip(obs, ctrl, strict=True)], reacher)
    from_objects = demos_from_trajectories(
        [ImitationTrajectory(o, a) for o, a in zip(obs, ctrl, strict=True)], reacher
    )
    np.testing.assert_array_equal(from_pairs.X, obs)
    np.testing.assert_array_equal(from_objects.X, obs)
    # The user's observations mapped to (qpos, qvel).
    gym_obs = np.concatenate([np.cos(qpos), np.sin(qpos), qvel], -1)
    unmap = lambda o: (np.arctan2(o[:, 2:4], o[:, :2]), o[:, 4:])
    mapped = demos_from_trajectories(list(zip(gym_obs, ctrl, strict=True)), reacher,
                                     state_from_obs=unmap)  # fmt: skip
    np.testing.assert_allclose(mapped.X, obs, atol=1e-12)
    with pytest.raises(DemoError, match=r"episode 0: obs must be MuJoCo's state \[steps, nq \+ "
                       r"nv \+ na = 4\], got shape \(7, 6\); pass state_from_obs="):  # fmt: skip
        demos_from_trajectories(list(zip(gym_obs, ctrl, strict=True)), reacher)
    with pytest.raises(DemoError, match=r"episode 1: expected an \(obs, acts\) pair"):
        demos_from_trajectories([(obs[0], ctrl[0]), obs[1]], reacher)


def _bad_inputs():
    """(name, edit of (qpos, qvel, ctrl, extra npz arrays), expected message)."""

    def edit(fn):
        def apply(qpos, qvel, ctrl):
            qpos, qvel, ctrl = qpos.copy(), qvel.copy(), ctrl.copy()
            extra = fn(qpos, qvel, ctrl) or {}
            return qpos, qvel, ctrl, extra

        return apply

    def nan(q, v, c):
        v[1, 3, 0] = np.nan

    def out_of_range(q, v, c):
        c[2, 4, 1] = 1.25

    return [
        ("short ctrl", lambda q, v, c: (q, v, c[:, :-1], {}),
         r"episode 0: ctrl has 5 steps for 7 states; need 6 \(one fewer\)$"),
        ("qvel length", lambda q, v, c: (q, v[:, :-1], c, {}),
         r"episode 0: qvel has 6 steps, qpos 7; they must match$"),
        ("qpos width", lambda q, v, c: (q[..., :1], v, c, {}),
         r"episode 0: qpos must be \[steps, 2\], got shape \(7, 1\)$"),
        ("nan", edit(nan), r"episode 1: non-finite qvel\[3, 0\] = nan$"),
        ("ctrl range", edit(out_of_range),
         r"episode 2: ctrl\[4, 1\] = 1\.25 outside the ctrlrange \[-1, 1\] of actuator 'wrist'$"),
        ("dt", lambda q, v, c: (q, v, c, {"dt": np.asarray(0.01)}),
         r"dt = 0\.01 s per control step, the env steps 0\.02 s"),
        ("missing", lambda q, v, c: (q, v, None, {}),
         r"no 'ctrl' array \(has qpos, qvel\)$"),
        ("one state", lambda q, v, c: (q[:, :1], v[:, :1], c[:, :0], {}),
         r"episode 0: 1 state\(s\); need at least 2"),
        ("condition", lambda q, v, c: (q, v, c, {"condition": np.asarray([0.5, 1, 2])}),
         r"condition must be 3 integers"),
    ]  # fmt: skip


@pytest.mark.parametrize("name, edit, message", _bad_inputs(), ids=[b[0] for b in _bad_inputs()])
def test_bad_demos_give_one_line_errors_naming_file_episode_and_array(
    reacher, tmp_path, name, edit, message
):
    qpos, qvel, ctrl, extra = edit(*episodes())
    path = tmp_path / "bad.npz"
    arrays = {"qpos": qpos, "qvel": qvel, **extra}
    if ctrl is not None:
        arrays["ctrl"] = ctrl
    np.savez(path, **arrays)
    with pytest.raises(DemoError) as err:
        demos_from_npz(path, reacher)
    text = str(err.value)
    assert "\n" not in text and text.startswith(str(path)), text
    assert re.search(message, text), text


def test_unreadable_or_missing_files(reacher, tmp_path):
    with pytest.raises(DemoError, match=r"nope\.npz: demo file not found$"):
        demos_from_npz(tmp_path / "nope.npz", reacher)
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip")
    with pytest.raises(DemoError, match=r"junk\.npz: not a readable npz file"):
        demos_from_npz(junk, reacher)
    empty = tmp_path / "empty.npz"
    np.savez(empty, something=np.zeros(3))
    with pytest.raises(DemoError, match=r"no 'qpos' \(stacked\) or 'qpos_0' \(per episode\)"):
        demos_from_npz(empty, reacher)
