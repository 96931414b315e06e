"""The USV pipeline (diffgcl.usv): bags' demos into the task's layout, the scores of
held-out rollouts against hand-built tracks, and (slow) the whole run on a few tiny bags."""

import dataclasses
import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl import usv as U
from diffgcl.data.demos import DemoSet
from diffgcl.envs.usv import IX_RADIUS, encode_ranges, make_usv_env
from diffgcl.sim import hull as hull_sim


def straight_track(env, cross_track: float, T: int, pole_x: float = 60.0, speed: float = 2.0):
    """[T+1, 11] a boat moving along y = cross_track at ``speed`` m per step past a pole at
    (pole_x, 0) of radius 0.5 (kinematic; only positions and heading matter to the scores)."""
    X = np.zeros((T + 1, env.dX))
    X[:, hull_sim.IX_PX] = speed * np.arange(T + 1)
    X[:, hull_sim.IX_PY] = cross_track
    X[:, hull_sim.SL_OBS] = (pole_x, 0.0)
    X[:, IX_RADIUS] = 0.5
    return X


def swerve_track(env, offset: float, T: int, back: bool, pole_x: float = 60.0):
    """[T+1, 11] on the course, out to ``offset`` around the pole, and (``back``) onto the course
    again heading along it; else it stays out."""
    X = straight_track(env, 0.0, T, pole_x)
    x = X[:, hull_sim.IX_PX]
    bump = offset * np.clip(1.0 - np.abs(x - pole_x) / 40.0, 0.0, 1.0) * 1.5
    y = np.minimum(bump, offset)
    if not back:
        y = np.where(x > pole_x, offset, y)
    X[:, hull_sim.IX_PY] = y
    X[:, hull_sim.IX_PSI] = np.arctan2(np.gradient(y), np.gradient(x))
    return X


def test_scores_of_hand_built_tracks():
    env = make_usv_env()
    T = 80
    hit = straight_track(env, 0.0, T)  # through the pole
    wide_back = swerve_track(env, 20.0, T, back=True)
    wide_out = swerve_track(env, 20.0, T, back=False)
    clearances = np.asarray(
        jax.vmap(jax.vmap(env.clearance))(jnp.asarray(np.stack([hit, wide_back])))
    )
    assert clearances[0].min() <= 0 < clearances[1].min()
    m = U.trajectory_metrics(env, np.stack([hit, wide_back, wide_out]))
    np.testing.assert_array_equal(m["collision"], [True, False, False])
    np.testing.assert_array_equal(m["returned_to_course"], [True, True, False])
    # The score against demos that swerve as wide_back: a policy flying the demos' path has path
    # distance 0 and clearance ratio 1; one through the pole collides in every episode.
    demos = np.stack([wide_back, wide_back])
    same = U.score_rollouts(env, demos, demos)
    assert same["collision_rate"] == 0.0 and same["return_to_course_rate"] == 1.0
    assert same["path_distance_to_demos_median_m"] == pytest.approx(0.0, abs=1e-9)
    assert same["clearance_ratio_vs_demos"] == pytest.approx(1.0)
    bad = U.score_rollouts(env, np.stack([hit, hit]), demos)
    assert bad["collision_rate"] == 1.0 and bad["clearance_ratio_vs_demos"] < 0
    # Per training seed: seed 0 flew through the pole, seed 1 the demos' path.
    seeds = U.per_seed_figures(
        env, np.stack([np.stack([hit, hit]), demos]), same["demo_min_clearance_median_m"]
    )
    assert seeds["collision_rate"] == [1.0, 0.0]
    assert seeds["return_to_course_rate"][1] == 1.0
    assert seeds["clearance_ratio_vs_demos"][0] < 0 < seeds["clearance_ratio_vs_demos"][1] == 1.0
    assert seeds["port_share"][1] == same["port_share"] in (0.0, 1.0)  # both demos on one side
    assert 0.0 <= seeds["straight_side_share"][1] == same["straight_side_share"] <= 1.0
    # The straight-on side: offset 1 m to port, heading 0 -> port; heading 2° to starboard over
    # the pole's 100 m -> 2.5 m to starboard.
    x0 = np.zeros((2, 2, hull_sim.DX + 1))
    x0[:, 0, hull_sim.IX_PY] = 1.0
    x0[:, 0, hull_sim.IX_OBS_X] = 100.0
    x0[1, 0, hull_sim.IX_PSI] = -np.deg2rad(2.0)
    np.testing.assert_array_equal(U.straight_side(x0), [1.0, -1.0])
    # The situations: head-on misses by 1 m and 100 tan 2° - 1 m; the collision profile counts
    # each episode in its third of every quantity.
    x0[:, 0, IX_RADIUS] = [0.4, 0.9]
    x0[:, 0, hull_sim.IX_VX] = [3.0, 4.0]
    sit = U.situations(x0)
    np.testing.assert_allclose(sit["straight_miss"], [1.0, 100 * np.tan(np.deg2rad(2.0)) - 1.0])
    np.testing.assert_allclose(sit["offset"], [1.0, 1.0])
    np.testing.assert_allclose(sit["speed"], [3.0, 4.0])
    np.testing.assert_allclose(sit["radius"], [0.4, 0.9])
    profile = U.collision_profile(x0, np.array([False, True]))
    assert profile["collisions"] == 1 and profile["colliding"][0]["episode"] == 1
    assert profile["radius"]["collisions"] == [0, 0, 1] and profile["radius"]["episodes"] == [
        1,
        0,
        1,
    ]
    assert profile["radius"]["median_colliding"] == pytest.approx(0.9)
    assert (
        bad["collision_profile"]["collisions"] == 2 and same["collision_profile"]["colliding"] == []
    )
    # A warning for a seed whose controllers hit the pole on their own starts, none otherwise.
    warn = U.controller_warnings([7, 8], seeds, 2)
    assert [seed for seed, _ in warn] == [7] and "hit the pole on 2 of their 2" in warn[0][1]
    # ... or are off course at the end on more than a tenth of them (a diverged run).
    figures = {
        "collision_rate": [0.0, 0.1, 0.0, 0.0],
        "return_to_course_rate": [1.0, 1.0, 0.8, 0.95],
        "clearance_ratio_vs_demos": [1.3, 0.7, 2.9, 1.2],
    }
    warn = dict(U.controller_warnings([20, 21, 22, 23], figures, 20))
    assert sorted(warn) == [21, 22]
    assert "hit the pole on 2 of their 20" in warn[21] and "back on course" not in warn[21]
    assert "back on course at the end on only 16 of 20" in warn[22] and "hit" not in warn[22]
    # The path distance: a track 3 m to the side of a straight demo is 3 m from it.
    d = U.path_distance_to_demos(
        straight_track(env, 3.0, T)[None], straight_track(env, 0.0, T)[None]
    )
    np.testing.assert_allclose(d, [3.0], rtol=1e-12)


def test_warned_seeds_are_trained_again():
    """A seed whose controllers or policy warn on their training starts is trained again with a
    new key, at most ``retrain`` times, until an attempt does not warn; the first such attempt is
    kept, else the best (the policy's hits, then more of it back on course, then its clearance
    short of 0.9×, then the controllers' hits, then more back on course). Others train once."""
    fine = (0.0, 1.0, 1.0)  # (hit rate, back on course, clearance ratio)
    outcomes = {  # (seed, attempt) -> (controllers', policy's) figures
        (0, 0): (fine, fine),  # no warning: trained once
        (1, 0): ((0.1, 1.0, 1.0), fine),  # controllers hit, then none: attempt 1 kept
        (1, 1): ((0.0, 0.95, 1.0), fine),
        (2, 0): ((0.1, 1.0, 1.0), (0.0, 1.0, 0.7)),  # warns every time: the policy decides
        (2, 1): ((0.0, 1.0, 1.0), (0.0, 1.0, 0.8)),  # fine controllers, a close policy
        (2, 2): ((0.2, 0.5, 1.0), (0.0, 1.0, 0.85)),  # the closest to 0.9×: kept
        (3, 0): (fine, (0.0, 1.0, 0.85)),  # only the policy warns, then not: attempt 1 kept
        (3, 1): ((0.0, 1.0, 1.1), (0.0, 1.0, 0.95)),
        (4, 0): ((0.1, 1.0, 0.8), (0.0, 1.0, 0.7)),  # a close pass that comes back: kept
        (4, 1): ((0.0, 0.0, 2.8), (0.0, 0.0, 2.9)),  # diverged: circles far off, never back
        (4, 2): ((0.0, 0.0, 3.5), (0.0, 0.0, 3.4)),
    }
    by_key = {tuple(np.asarray(U.training_key(s, a)).tolist()): (s, a) for s, a in outcomes}
    calls = []

    def train(keys):
        ids = [by_key[tuple(k)] for k in np.asarray(keys).tolist()]
        calls.append(ids)
        out = {"id": np.asarray(ids), "w": np.ones((len(ids), 2, 3))}
        Xc, Xp = (np.asarray([outcomes[i][part] for i in ids]) for part in (0, 1))
        return out, Xc, Xp

    def figures(X):
        return {
            "collision_rate": X[:, 0].tolist(),
            "return_to_course_rate": X[:, 1].tolist(),
            "clearance_ratio_vs_demos": X[:, 2].tolist(),
        }

    said = []
    out, Xc, Xp, per, _, record = U.train_retrying_warned(
        train, figures, [0, 1, 2, 3, 4], 10, retrain=2, say=said.append
    )
    assert calls == [
        [(0, 0), (1, 0), (2, 0), (3, 0), (4, 0)],
        [(1, 1), (2, 1), (3, 1), (4, 1)],
        [(2, 2), (4, 2)],
    ]
    kept = [(0, 0), (1, 1), (2, 2), (3, 1), (4, 0)]
    np.testing.assert_array_equal(out["id"], kept)
    np.testing.assert_array_equal(Xc, [outcomes[k][0] for k in kept])
    np.testing.assert_array_equal(Xp, [outcomes[k][1] for k in kept])
    assert per["controllers"]["return_to_course_rate"] == [1.0, 0.95, 0.5, 1.0, 1.0]
    assert per["policy"]["clearance_ratio_vs_demos"] == [1.0, 1.0, 0.85, 0.95, 0.7]
    assert [record[s]["kept"] for s in (0, 1, 2, 3, 4)] == [0, 1, 2, 1, 0]
    assert [len(record[s]["attempts"]) for s in (0, 1, 2, 3, 4)] == [1, 2, 3, 2, 3]
    assert record[1]["attempts"][0]["warning"] and not record[1]["attempts"][1]["warning"]
    assert record[2]["attempts"][2]["collision_rate"] == 0.2
    assert record[2]["attempts"][1]["policy"]["clearance_ratio_vs_demos"] == 0.8
    first = record[3]["attempts"][0]["warning"]
    assert "policy" in first and "0.85×" in first and "controllers" not in first
    both = record[2]["attempts"][2]["warning"]
    assert "controllers hit the pole" in both and "its policy" in both
    assert any("seed 2 (attempt 1)" in text for text in said)
    # The first attempt's key is PRNGKey(seed) (runs before retraining reproduce); retrain=0
    # only warns; without a policy (Xp None) only the controllers are judged.
    np.testing.assert_array_equal(U.training_key(5), jax.random.PRNGKey(5))
    calls.clear()
    out, *_, record = U.train_retrying_warned(train, figures, [0, 1], 10, retrain=0)
    assert calls == [[(0, 0), (1, 0)]] and record[1]["kept"] == 0
    assert record[1]["attempts"][0]["warning"]

    def train_without_policy(keys):
        out, Xc, _ = train(keys)
        return out, Xc, None

    out, Xc, Xp, per, _, record = U.train_retrying_warned(
        train_without_policy, figures, [3], 10, retrain=1
    )
    assert Xp is None and per["policy"] is None and record[3]["kept"] == 0
    assert record[3]["attempts"][0] == {
        "warning": None,
        "collision_rate": 0.0,
        "return_to_course_rate": 1.0,
        "clearance_ratio_vs_demos": 1.0,
        "policy": None,
    }


def test_policy_warnings_by_hand():
    """The policy warns on hits, on clearance below 0.9× the demos', or off course at the end on
    more than a tenth of its starts; its text joins the controllers' in one warning."""
    figures = {
        "collision_rate": [0.0, 0.05, 0.0, 0.0],
        "return_to_course_rate": [1.0, 1.0, 1.0, 0.85],
        "clearance_ratio_vs_demos": [0.9, 1.2, 0.89, 1.0],
    }
    warn = dict(U.policy_warnings([0, 1, 2, 3], figures, 20))
    assert sorted(warn) == [1, 2, 3]
    assert "hits the pole from 1 of the 20" in warn[1] and "passes" not in warn[1]
    assert "passes at 0.89×" in warn[2] and "hits" not in warn[2]
    assert "back on course from only 17" in warn[3]
    controllers = {
        "collision_rate": [0.1, 0.0, 0.0, 0.0],
        "return_to_course_rate": [1.0] * 4,
        "clearance_ratio_vs_demos": [1.0] * 4,
    }
    texts = U.training_warnings([0, 1, 2, 3], controllers, figures, 20)
    assert sorted(texts) == [0, 1, 2, 3]
    assert "controllers" in texts[0] and "policy" not in texts[0].split(";")[0][:20]
    assert U.training_warnings([0, 1, 2, 3], controllers, None, 20).keys() == {0}


@pytest.fixture(scope="module")
def tiny_bags(tmp_path_factory):
    """Two set-2 episodes (LiDAR) and one set-1 episode as ROS1 bags, ingested."""
    from diffgcl.data.ingest import ingest_bags
    from diffgcl.data.synth import SynthConfig, synthesize

    folder = tmp_path_factory.mktemp("bags") / "odin"
    config = SynthConfig(
        episodes=(1, 2), approach_m=(100.0, 110.0), end_margin_m=(110.0, 120.0), seed=3
    )
    synthesize(folder, config)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        demos = ingest_bags(U.bag_paths(folder))
    return demos, folder


def test_bag_demos_in_the_task_layout(tiny_bags):
    demos, folder = tiny_bags
    task = U.UsvTaskConfig(before=60, after=100)
    windows = U.task_windows(demos, task)
    assert windows.num_episodes == 2 and {e["set"] for e in windows.episodes} == {"2"}
    radii = U.pole_radii(windows, 0.5, folder / "manifest.json")
    truth = [
        e["profile"]["pole_radius"]
        for e in json.loads((folder / "manifest.json").read_text())["episodes"]
        if str(e["set"]) == "2"
    ]
    np.testing.assert_allclose(np.sort(radii), np.sort(truth))
    env = U.make_task_env(windows, radii, hull_sim.default_params(), task)
    task_demos = U.usv_demo_set(env, windows, radii)
    assert task_demos.X.shape == (2, task.horizon + 1, env.dX)
    assert task_demos.O.shape == (2, task.horizon + 1, env.dO)
    # Each window starts on its own condition; the pole's radius rides in the state.
    np.testing.assert_allclose(np.asarray(env.x0), task_demos.X[:, 0])
    np.testing.assert_allclose(
        task_demos.X[..., IX_RADIUS], radii[:, None] * np.ones((1, task.horizon + 1))
    )
    # Actions normalised: the physical commands come back through env.command.
    phys = np.asarray(jax.vmap(jax.vmap(env.command))(jnp.asarray(task_demos.U)))
    np.testing.assert_allclose(phys, windows.U, rtol=1e-9, atol=1e-9)
    # The recorded observations have the env's layout: everything but the ranges equals env.obs.
    n = env.layout.num_beams
    sim = np.asarray(jax.vmap(jax.vmap(env.obs))(jnp.asarray(task_demos.X)))
    np.testing.assert_allclose(task_demos.O[..., n:], sim[..., n:], atol=1e-6)
    # The recorded ranges in the env's encoding: a beam that sees nothing in the recording and
    # in the simulation reads the same in both.
    assert env.range_encoding == "saturated"
    np.testing.assert_allclose(
        task_demos.O[..., :n], np.asarray(encode_ranges(windows.O[..., :n], "saturated"))
    )
    nothing = np.asarray(encode_ranges(env.layout.max_ranges, "saturated"))
    free = (windows.O[..., :n] >= env.layout.max_ranges) & np.isclose(sim[..., :n], nothing)
    assert free.mean() > 0.5 and not np.isclose(task_demos.O[..., :n], nothing).all()
    # The pooled demo controller: one fit shared by both conditions.
    batch = U.demo_batch_pooled(task_demos)
    assert batch.X.shape == (2, 1, task.horizon + 1, env.dX)
    np.testing.assert_array_equal(
        np.asarray(batch.controller.K[0]), np.asarray(batch.controller.K[1])
    )
    assert batch.dynamics is None and batch.tail is None
    # The recordings past the windows: GCL's tails, from each window's last state on.
    tails = U.task_tails(demos, dataclasses.replace(task, tail=12))
    assert tails.shape == (2, 13, hull_sim.DX)
    np.testing.assert_array_equal(tails[:, 0], windows.X[:, -1])
    with_tail = U.demo_batch_pooled(task_demos, tail=U.window_states(tails, radii))
    assert with_tail.tail.shape == (2, 1, 13, env.dX)
    np.testing.assert_allclose(np.asarray(with_tail.tail[:, 0, 0]), task_demos.X[:, -1])
    assert U.task_tails(demos, task) is None
    # With the env: the hull linearised about each demo (the temperature calibration's input);
    # B maps a normalised action to the state as the env's own step does (finite differences).
    dyn = U.demo_batch_pooled(task_demos, env=env).dynamics
    T = task.horizon
    assert dyn.A.shape == (2, T, env.dX, env.dX) and dyn.B.shape == (2, T, env.dX, env.dU)
    x, u, h = jnp.asarray(task_demos.X[0, 5]), jnp.asarray(task_demos.U[0, 5]), 1e-4
    fd = [(env.step(x, u.at[j].add(h)) - env.step(x, u.at[j].add(-h))) / (2 * h) for j in range(2)]
    np.testing.assert_allclose(
        np.asarray(dyn.B[0, 5]), np.stack([np.asarray(c) for c in fd], 1), rtol=1e-3, atol=1e-6
    )
    # Held-out situations lie within the demos' ranges and differ from every demo start.
    ranges = U.SituationRanges.of(task_demos)
    x0 = np.asarray(U.heldout_starts(env, ranges, jax.random.PRNGKey(0), 16))
    ahead = x0[:, hull_sim.IX_OBS_X] - x0[:, hull_sim.IX_PX]
    assert np.all((ahead >= ranges.distance[0] - 1e-9) & (ahead <= ranges.distance[1] + 1e-9))
    assert not np.any(np.all(np.isclose(x0[:, None], task_demos.X[None, :, 0]), axis=-1))
    # The wider situations: radius 0.2-1.5 m, the offset range 1.5x the demos' about its centre,
    # the rest as the demos'; drawn within those ranges.
    wide = ranges.widened()
    centre = 0.5 * (ranges.offset[0] + ranges.offset[1])
    np.testing.assert_allclose(
        np.subtract(wide.offset, centre), 1.5 * np.subtract(ranges.offset, centre)
    )
    assert wide.radius == (0.2, 1.5) and wide.distance == ranges.distance
    assert wide.heading == ranges.heading and wide.speed == ranges.speed
    xw = np.asarray(U.heldout_starts(env, wide, jax.random.PRNGKey(1), 64))
    radius = xw[:, -1]
    assert np.all((radius >= 0.2 - 1e-9) & (radius <= 1.5 + 1e-9)) and radius.max() > 1.0
    offset = xw[:, hull_sim.IX_PY] - xw[:, hull_sim.IX_OBS_Y]
    assert np.all((offset >= wide.offset[0] - 1e-6) & (offset <= wide.offset[1] + 1e-6))


def test_unknown_set_is_a_one_line_error(tiny_bags):
    demos, _ = tiny_bags
    from diffgcl.data.demos import DemoError

    with pytest.raises(DemoError, match="no episode of sets"):
        U.task_windows(demos, U.UsvTaskConfig(sets=("7",)))


@pytest.mark.slow
def test_whole_run_on_tiny_bags(tiny_bags, tmp_path):
    """rGCL + MDGPS, the expert-cost reference and BC, judged on the true hull: finite figures in
    range, the plots and summary written, and a user's file in --out kept."""
    from diffgcl.algorithms.presets import usv as usv_preset
    from diffgcl.algorithms.presets import with_overrides
    from diffgcl.data.synth import true_params
    from diffgcl.viz.usv import save_usv_plots

    demos, folder = tiny_bags
    rgcl = with_overrides(
        usv_preset(),
        [
            "freeze_last=1",
            "iterations=3",
            "gcl.pretrain_steps=20",
            "gcl.n_steps=5",
            "policy.s_step.n_steps=20",
            "gcl.mono_weight=1",  # a regulariser that reads the demos' tails
        ],
    )
    config = U.UsvRunConfig(
        task=U.UsvTaskConfig(before=60, after=100, train_extra=20, tail=10),
        rgcl=rgcl,
        heldout=4,
        expert_iterations=2,
    )
    run = U.run_usv(demos, config, manifest=folder / "manifest.json", true_params=true_params())
    for name in U.METHODS:
        s = run.summary[name]
        assert s["episodes"] == 4
        for key in ("collision_rate", "return_to_course_rate", "port_share"):
            assert 0.0 <= s[key] <= 1.0
        assert np.isfinite(s["path_distance_to_demos_median_m"])
        T_eval = config.task.horizon + config.eval_extra  # judged past the window
        assert run.tracks[name].shape == (1, 4, T_eval + 1, run.env.dX)
    assert run.summary["hull_identification"]["max_relative_error"] < 0.5
    assert run.summary["demo_tail"] == 10
    c_steps = run.summary["rgcl"]["c_steps"]
    assert np.shape(c_steps["true_cost_median"]) == (1, 3)  # one seed, three iterations
    assert all(np.isfinite(v) for v in c_steps["kl_over_target"][0])
    # One training seed, trained again at most once (retrain_warned=1) if it warned;
    # the summary's warning is the kept attempt's.
    record = run.summary["rgcl"]["attempts"]["0"]
    assert len(record["attempts"]) in (1, 2) and record["kept"] < len(record["attempts"])
    kept = record["attempts"][record["kept"]]
    assert run.summary["rgcl"]["warnings"].get("0") == kept["warning"]
    per_seed = run.summary["rgcl"]["controllers_on_demo_starts"]["per_seed"]
    assert per_seed["collision_rate"] == [kept["collision_rate"]]
    # ... and the policy was judged from the same starts, its figures the kept attempt's.
    sails = run.summary["rgcl"]["policy_on_demo_starts"]
    assert sails["episodes"] == run.summary["conditions"]
    for key in U.ATTEMPT_FIGURES:
        assert sails["per_seed"][key] == [kept["policy"][key]] and np.isfinite(kept["policy"][key])
    # Trained past the window: controllers [S, C, T, ...] over 180 steps, GCL's buffer over 160.
    assert run.summary["training_horizon"] == 180 == run.train_env.horizon
    assert run.rgcl_state.gps.controller.K.shape[2] == 180
    assert run.rgcl_state.buffer.X.shape[-2] == 161
    # The cost's clearance margins come from these demos' own median clearance.
    margins = U.margins_for_clearance(run.summary["demos"]["min_clearance_median_m"])
    assert run.summary["proximity_margins"] == list(margins) == list(run.env.proximity_margins)
    assert run.train_env.proximity_margins == run.env.proximity_margins
    out = tmp_path / "run"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    from diffgcl.io import OutputError

    with pytest.raises(OutputError):
        save_usv_plots(run, out)
    save_usv_plots(run, out, overwrite=True)
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "usv_tracks.png").is_file() and (out / "usv_cost_map.png").is_file()
    assert isinstance(run.demos, DemoSet)


def test_c_step_diagnostics_by_hand():
    """Per seed and iteration, over the inner C-steps and conditions: median and largest true
    cost, mean step multiplier, median achieved KL over its target, failed C-steps."""
    from types import SimpleNamespace

    from diffgcl.usv.pipeline import c_step_diagnostics

    cost = np.ones((2, 3, 1, 4))  # [seeds, iterations, inner, conditions]
    cost[1, 2] = [1.0, 2.0, 3.0, 1e9]  # seed 1 diverges in one condition at iteration 2
    failed = np.zeros_like(cost)
    failed[0, 1, 0, :2] = 1.0
    gps = SimpleNamespace(
        cost=cost,
        step_mult=np.full_like(cost, 0.5),
        kl=np.full_like(cost, 0.3),
        epsilon=np.full_like(cost, 0.6),
        c_step_failed=failed,
    )
    d = c_step_diagnostics(SimpleNamespace(gps=gps))
    assert d["true_cost_median"] == [[1.0, 1.0, 1.0], [1.0, 1.0, 2.5]]
    assert d["true_cost_max"][1] == [1.0, 1.0, 1e9] and d["true_cost_max"][0] == [1.0] * 3
    assert d["step_mult"] == [[0.5] * 3] * 2 and d["kl_over_target"] == [[0.5] * 3] * 2
    assert d["c_step_failed"] == [[0.0, 2.0, 0.0], [0.0, 0.0, 0.0]]


def test_cli_usv_choices_are_the_envs():
    """``diffgcl usv``'s --observation and --range-encoding offer what the env knows."""
    from diffgcl.cli import build_parser
    from diffgcl.envs.usv import OBSERVATIONS, RANGE_ENCODINGS

    usv = build_parser()._subparsers._group_actions[0].choices["usv"]
    choices = {a.dest: a.choices for a in usv._actions if a.choices}
    assert set(choices["observation"]) == set(OBSERVATIONS)
    assert set(choices["range_encoding"]) == set(RANGE_ENCODINGS)
    args = build_parser().parse_args(["usv"])
    assert args.range_encoding == U.UsvTaskConfig().range_encoding


def test_cli_fast_is_the_experiments_fast_and_options_override_it():
    """``diffgcl usv --fast`` runs :func:`fast_run_config` (as ``experiments/usv_avoidance.py
    --fast`` does); an option or ``--set`` given beside it wins over the fast scale."""
    from diffgcl.algorithms.presets import usv as usv_preset
    from diffgcl.cli import build_parser
    from diffgcl.cli.usv import run_config

    parse = build_parser().parse_args
    assert run_config(parse(["usv", "--fast"])) == U.fast_run_config()
    full = run_config(parse(["usv"]))
    assert full == U.UsvRunConfig(rgcl=usv_preset())
    assert (full.heldout, full.retrain_warned, full.task.train_extra) == (256, 1, 150)
    custom = run_config(
        parse(["usv", "--fast", "--set", "iterations=3", "--heldout", "8", "--retrain", "1"])
    )
    assert custom.rgcl.iterations == 3 and custom.rgcl.freeze_last == 2
    assert (custom.heldout, custom.retrain_warned, custom.task.before) == (8, 1, 100)
    assert full.task.tail == 0 and run_config(parse(["usv", "--tail", "90"])).task.tail == 90


def test_margins_for_clearance_by_hand():
    """The tuned margins scaled by the demos' clearance over the tuned one, rounded to 1 m unless
    that merges two."""
    assert U.TUNED_CLEARANCE_M == 17.25
    for built_in in (17.248, 17.423):  # set 2, sets 1 + 2
        assert U.margins_for_clearance(built_in) == (5.0, 10.0, 15.0, 20.0)
    assert U.margins_for_clearance(30.0) == (9.0, 17.0, 26.0, 35.0)  # 8.7, 17.4, 26.1, 34.8
    assert U.margins_for_clearance(34.5, (5.0, 15.0)) == (10.0, 30.0)
    near = np.asarray(U.margins_for_clearance(2.0))  # 0.58, 1.16, 1.74, 2.32: 1, 1 merge
    np.testing.assert_allclose(near, np.asarray([5.0, 10.0, 15.0, 20.0]) * 2.0 / 17.25)
    for bad in (0.0, -3.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="median clearance"):
            U.margins_for_clearance(bad)


def test_cli_usv_margins(capsys):
    """``--margins`` gives the task's barrier clearances; a bad list is a usage error naming it."""
    from diffgcl.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["usv"]).margins is None  # the task's default
    assert parser.parse_args(["usv", "--margins", "5,12.5,25"]).margins == (5.0, 12.5, 25.0)
    for bad, why in [("5,x", "separated by commas"), ("20,10", "increasing"), ("0,5", "> 0")]:
        with pytest.raises(SystemExit):
            parser.parse_args(["usv", "--margins", bad])
        err = capsys.readouterr().err
        assert f"margins '{bad}'" in err and why in err


def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    """A folder without bags, an ``--out`` folder the program did not write, a folder that is no
    run folder, demos that are none, a preset or ``--set`` edit that makes no configuration: one
    line on stderr naming it and exit status 2, before any work; the user's folder is left as it
    was."""
    from diffgcl.cli import main

    empty = tmp_path / "no_bags"
    empty.mkdir()
    topics = tmp_path / "topics.yaml"
    topics.write_text("{}\n")
    code = main(
        ["usv", "--bags", str(empty), "--topics", str(topics), "--out", str(tmp_path / "o")]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("error: ") and str(empty) in err and "\n" not in err

    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("a user's file")
    code = main(["usv", "--fast", "--out", str(foreign)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("error: ") and str(foreign) in err and "\n" not in err
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]

    for argv, named in (
        (["eval", str(foreign)], foreign),
        (["plot", str(foreign)], foreign),
        (["train", "--demos", str(empty), "--out", str(tmp_path / "t")], empty),
        (["sweep", "--iterations", "1", "--json", str(tmp_path / "s.json")], "iterations=1"),
        (["train", "--set", "gcl.nope=2", "--out", str(tmp_path / "t")], "'nope'"),
        (["sweep", "--preset", "nope", "--json", str(tmp_path / "s.json")], "'nope'"),
    ):
        code = main(argv)
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.startswith("error: ") and str(named) in err, (argv, err)
        assert "\n" not in err
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]
    assert not (tmp_path / "t").exists()
