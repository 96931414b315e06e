"""USV obstacle avoidance learned from bags, end to end (issue 13; DESIGN §7b).

The pieces, each a function the experiment (``experiments/usv_avoidance.py``) and the CLI
(``diffgcl usv``) chain:

1. :func:`builtin_bags` — the Odin-like synthetic bags (:mod:`diffgcl.data.synth`), written once
   into the cache; a user brings their own bags and topic map instead;
2. ingestion (:func:`diffgcl.data.ingest.ingest_bags`), then hull identification
   (:func:`diffgcl.data.sysid.identify`) on the demonstrations;
3. :func:`task_windows` — every demo in its task frame (:mod:`diffgcl.data.task_frame`) and cropped
   to a window of fixed horizon around its closest approach to the pole;
4. :func:`make_task_env` and :func:`usv_demo_set` — the USV task env
   (:class:`diffgcl.envs.usv.UsvEnv`) on the identified hull with one condition per demo (its
   start state and pole), and the demos in that env's layout (state with the pole's radius,
   normalised actions, the policy's observations built from the *recorded* ranges);
5. rGCL (:mod:`diffgcl.algorithms.rgcl`, :func:`diffgcl.algorithms.presets.usv`) learns the cost
   on task features and the MDGPS policy on the observations; references: MDGPS with the
   hand-written cost (:func:`diffgcl.algorithms.mdgps.make_mdgps` on ``env.expert_cost``) and
   behaviour cloning (:mod:`diffgcl.algorithms.bc`);
6. :func:`heldout_starts`, :func:`policy_tracks` and :func:`score_rollouts` — situations none of
   the demos had (pole distance, the boat's lateral offset and heading, pole radius and speed
   drawn from the demos' ranges), rolled out on the *true* hull with sensor noise; per episode:
   collision, minimum clearance, back on course, side passed, path distance to the nearest demo;
   :func:`per_seed_figures` splits the main ones by training seed.

The demonstrators' own controller for GCL's fusion weights is fitted once on all windows pooled
(one human policy, time-aligned by the closest approach), not per condition: with one demo per
condition a per-condition fit would have no residual to give it a covariance.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.algorithms.rgcl import DemoBatch
from diffgcl.data.demos import DemoError, DemoSet
from diffgcl.envs.usv import PROXIMITY_MARGINS, UsvEnv, encode_ranges, make_usv_env
from diffgcl.sim import hull as hull_sim
from diffgcl.types import Array, PRNGKey

DEFAULT_POLE_RADIUS = 0.5  # m, used when neither the episode nor a manifest gives one


@dataclass(frozen=True)
class UsvTaskConfig:
    """How demos become the USV task.

    before / after: steps kept before and after the closest approach (T = before + after);
    sets: the bag sets whose episodes are used (set 1 of the seed has no LiDAR, set 2 has it);
    observation: the policy's observation set (:data:`diffgcl.envs.usv.OBSERVATIONS`);
    range_encoding: how the policy reads the ranges (:func:`diffgcl.envs.usv.encode_ranges`);
    max_conditions: use at most this many demos (None: all); default_pole_radius: m;
    train_extra: steps the controllers and the policy are trained past the window (their
    horizon is ``horizon + train_extra``; GCL compares the demos with the window's steps only,
    see :mod:`diffgcl.algorithms.rgcl`), so that holding the course after the recordings end is
    trained too (trained on the window alone, policies drifted off the line after it, and runs
    diverged on some seeds: docs/usv.md); proximity_margins: the clearances (m) of the learned
    cost's barrier residuals (:meth:`diffgcl.envs.usv.UsvEnv.cost_residuals`), or None to take
    them from the demos (:func:`margins_for_clearance`: 5, 10, 15, 20 m on the built-in bags).
    Their largest bounds where the learned cost can still push the boat away: with a 30 m
    margin, boats passed at 1.25–1.35× the demos' clearance (17 m on the built-in bags), with
    20 m at about 1.1×; but with 20 m about one training seed in five passed too close and hit
    the pole, unless it was trained again (:attr:`UsvRunConfig.retrain_warned`; docs/usv.md).
    """

    before: int = 120
    after: int = 180
    sets: tuple[str, ...] = ("2",)
    observation: str = "full"
    range_encoding: str = "saturated"
    max_conditions: int | None = None
    default_pole_radius: float = DEFAULT_POLE_RADIUS
    train_extra: int = 150
    proximity_margins: tuple[float, ...] | None = None

    @property
    def horizon(self) -> int:
        return self.before + self.after

    @property
    def training_horizon(self) -> int:
        return self.horizon + self.train_extra


# ---- bags and demos -----------------------------------------------------------------------------


BUILTIN_SYNTH = {
    # The seed's Odin sets (19 episodes without LiDAR, 47 with), each recorded until the boat is
    # back on its course line and has held it a while (end margin past the pole), so that a window
    # around the pass holds the return too.
    "full": dict(end_margin_m=(170.0, 230.0), max_duration_s=160.0),
    "fast": dict(episodes=(3, 5), approach_m=(110.0, 130.0), end_margin_m=(120.0, 140.0)),
}


def builtin_bags(*, fast: bool = False, verbose: bool = True) -> Path:
    """The synthetic Odin-like bag set (the seed's layout: set 1, 19 episodes without LiDAR; set 2,
    47 with it; ``fast``: 3 + 5 short episodes), generated once into the cache."""
    from diffgcl.data.synth import SynthConfig, synthesize
    from diffgcl.runtime import cache_root

    name = "fast" if fast else "full"
    folder = cache_root() / "bags" / f"odin-usv-{name}"
    if not (folder / "manifest.json").is_file():
        if verbose:
            print(f"writing the synthetic Odin-like bags into {folder}")
        synthesize(folder, SynthConfig(**BUILTIN_SYNTH[name]), overwrite=True)
    return folder


def load_bag_demos(folder: Path, topics: Path | None = None, *, verbose: bool = True) -> DemoSet:
    """Every bag below ``folder`` ingested with the topic map ``topics`` (default: the Odin-like
    one). Nothing is written (a user's folder is never touched)."""
    from diffgcl.data.ingest import ingest_bags
    from diffgcl.data.topics import load_topic_map

    paths = bag_paths(folder)
    if verbose:
        print(f"ingesting {len(paths)} bags from {folder}")
    return ingest_bags(paths, load_topic_map(topics))


def builtin_demos(*, fast: bool = False, verbose: bool = True) -> tuple[DemoSet, Path]:
    """The built-in bags (:func:`builtin_bags`) ingested, cached beside them; returns the demos
    and the bag folder (whose ``manifest.json`` has the generator's truth)."""
    folder = builtin_bags(fast=fast, verbose=verbose)
    cached = folder.parent / f"{folder.name}-demos"
    if (cached / "demos.npz").is_file():
        return DemoSet.load(cached), folder
    demos = load_bag_demos(folder, verbose=verbose)
    demos.save(cached)
    return demos, folder


def bag_paths(folder: Path) -> list[Path]:
    """Every bag below ``folder`` (ROS1 ``.bag`` files and ROS2 bag folders), sorted."""
    folder = Path(folder)
    found = sorted(folder.rglob("*.bag")) + sorted(
        m.parent for m in folder.rglob("metadata.yaml") if m.parent != folder
    )
    if not found:
        raise DemoError(f"{folder}: no ROS bags below this folder")
    return found


def pole_radii(demos: DemoSet, default: float, manifest: Path | None = None) -> np.ndarray:
    """The pole radius of each episode [N] (m): from the episode's metadata (``pole_radius`` or
    ``radius``, e.g. a key of the start marker), else from a synthetic set's ``manifest.json``
    (matched by bag file and start time), else ``default``."""
    truth = {}
    if manifest is not None and Path(manifest).is_file():
        for e in json.loads(Path(manifest).read_text())["episodes"]:
            truth[(Path(e["bag"]).name, round(float(e["t_start"]), 1))] = e["profile"][
                "pole_radius"
            ]
    radii = []
    for meta in demos.episodes:
        value = meta.get("pole_radius", meta.get("radius"))
        if value is None:
            value = truth.get((Path(meta.get("source", "")).name, round(meta["t_start"], 1)))
        radii.append(float(default if value is None else value))
    return np.asarray(radii)


def task_windows(demos: DemoSet, config: UsvTaskConfig) -> DemoSet:
    """The chosen sets' episodes in the task frame, cropped around the pole pass (module
    docstring); episodes without a full window are left out with a warning."""
    from diffgcl.data.task_frame import pass_windows, to_task_frame

    sets = {str(e.get("set")) for e in demos.episodes}
    keep = [i for i, e in enumerate(demos.episodes) if str(e.get("set")) in config.sets]
    if not keep:
        raise DemoError(f"demos: no episode of sets {config.sets} (the data have sets {sets})")
    chosen = to_task_frame(demos.subset(np.asarray(keep)))
    windows = pass_windows(chosen, config.before, config.after)
    if config.max_conditions is not None:
        windows = windows.subset(slice(0, config.max_conditions))
    return windows


def cruise_speed_of(windows: DemoSet) -> float:
    """The demos' typical speed over ground (median over all valid steps), m/s."""
    speed = np.hypot(windows.X[..., hull_sim.IX_VX], windows.X[..., hull_sim.IX_VY])
    return float(np.median(speed[windows.mask > 0]))


TUNED_CLEARANCE_M = 17.25  # m, the built-in bags' demos' median clearance (set 2: 17.25)


def margins_for_clearance(clearance_m: float, margins=PROXIMITY_MARGINS) -> tuple[float, ...]:
    """Clearance margins (m) for demos that pass at a median minimum clearance ``clearance_m``:
    ``margins``, tuned for the built-in demos' :data:`TUNED_CLEARANCE_M`, scaled by the ratio and
    rounded to 1 m (unrounded where rounding would merge two or make one 0). The built-in bags
    (17.25 m on set 2, 17.4 m on sets 1 + 2) keep 5, 10, 15, 20 m; demos that pass at 30 m get
    9, 17, 26, 35 m."""
    if not clearance_m > 0 or not np.isfinite(clearance_m):
        raise ValueError(
            f"usv: the demos' median clearance is {clearance_m} m; margins need a positive one "
            "(set UsvTaskConfig.proximity_margins / --margins instead)"
        )
    scaled = np.asarray(margins, float) * (clearance_m / TUNED_CLEARANCE_M)
    rounded = np.round(scaled)
    if rounded[0] <= 0 or np.any(np.diff(rounded) <= 0):
        rounded = scaled
    return tuple(float(m) for m in rounded)


def demo_clearance_median(env: UsvEnv, windows: DemoSet, radii: np.ndarray) -> float:
    """The demos' median minimum clearance (m) to their poles, in ``env``'s hull outline."""
    X = window_states(windows, radii)
    return float(np.median(trajectory_metrics(env, X)["min_clearance"]))


def task_margins(windows: DemoSet, radii: np.ndarray, params, config: UsvTaskConfig):
    """The learned cost's clearance margins (m) for ``config``: its own, or taken from the
    windows' median clearance (:func:`margins_for_clearance`)."""
    if config.proximity_margins is not None:
        return config.proximity_margins
    x0 = np.concatenate([windows.X[:, 0, : hull_sim.DX], radii[:, None]], axis=1)
    probe = make_usv_env(x0, params=params, horizon=1)
    return margins_for_clearance(demo_clearance_median(probe, windows, radii))


def make_task_env(
    windows: DemoSet,
    radii: np.ndarray,
    params,
    config: UsvTaskConfig,
    *,
    cruise_speed: float | None = None,
    horizon: int | None = None,
) -> UsvEnv:
    """The USV env on hull ``params`` with one condition per window (its first state and pole);
    the cost's clearance margins are the task's, or taken from the windows
    (:func:`margins_for_clearance`)."""
    x0 = np.concatenate([windows.X[:, 0, : hull_sim.DX], radii[:, None]], axis=1)
    speed = cruise_speed_of(windows) if cruise_speed is None else cruise_speed
    return make_usv_env(
        x0,
        params=params,
        cruise_speed=speed,
        horizon=config.horizon if horizon is None else horizon,
        observation=config.observation,
        range_encoding=config.range_encoding,
        proximity_margins=task_margins(windows, radii, params, config),
    )


def usv_observations(env: UsvEnv, X: np.ndarray, O_hull: np.ndarray) -> np.ndarray:
    """The policy's observations [..., dO] in ``env``'s layout from states ``X: [..., 11]`` and
    the *recorded* observations in the hull layout ``O_hull: [..., 53]`` (ranges, sin ψ, cos ψ,
    ν): the ranges are what the bag's sensors read, the rest comes from the state."""
    n_beams = env.layout.num_beams
    ranges = np.asarray(encode_ranges(O_hull[..., :n_beams], env.range_encoding))
    psi = X[..., hull_sim.IX_PSI]
    heading = np.stack([np.sin(psi), np.cos(psi)], axis=-1)
    nu = O_hull[..., n_beams + 2 : n_beams + 5]
    cross = X[..., hull_sim.IX_PY : hull_sim.IX_PY + 1]
    if env.observation == "ranges":
        return np.concatenate([ranges, nu], axis=-1)
    if env.observation == "radar":
        ranges = ranges[..., env.layout.lidar_beams :]
    return np.concatenate([ranges, heading, nu, cross], axis=-1)


def window_states(windows: DemoSet, radii: np.ndarray) -> np.ndarray:
    """The windows' hull states with each pole's radius appended: [N, T+1, 11]."""
    N, T1, _ = windows.X.shape
    return np.concatenate(
        [windows.X[..., : hull_sim.DX], np.broadcast_to(radii[:, None, None], (N, T1, 1))], -1
    )


def usv_demo_set(env: UsvEnv, windows: DemoSet, radii: np.ndarray) -> DemoSet:
    """The windows in ``env``'s layout: states with the pole radius [N, T+1, 11], normalised
    actions [N, T, 2], the policy's observations [N, T+1, dO] from the recorded ranges, and each
    episode its own condition (``condition = i``)."""
    X = window_states(windows, radii)
    offset, scale = np.asarray(env.action_offset), np.asarray(env.action_scale)
    U = (windows.U - offset) / scale
    O = usv_observations(env, X, windows.O)
    episodes = tuple(
        {**e, "condition": i, "pole_radius": float(radii[i])}
        for i, e in enumerate(windows.episodes)
    )
    return DemoSet(X=X, U=U, O=O, mask=windows.mask, dt=windows.dt, env="usv", episodes=episodes)


def demo_batch_pooled(demos: DemoSet, dtype=None, env: UsvEnv | None = None) -> DemoBatch:
    """A :class:`~diffgcl.algorithms.rgcl.DemoBatch` with one demo per condition [C, 1, ...] and
    the demonstrators' controller fitted on all demos pooled, shared by every condition; given
    the ``env``, its dynamics linearised about each demo (for ``temperature='demos'``)."""
    from diffgcl.costs.demo_controller import fit_demo_controller

    dtype = dtype or jnp.zeros(()).dtype
    X = jnp.asarray(demos.X, dtype)
    U = jnp.asarray(demos.U, dtype)
    pooled = jax.jit(fit_demo_controller)(X, U)
    C = X.shape[0]
    controller = jax.tree.map(lambda a: jnp.broadcast_to(a, (C, *a.shape)), pooled)
    dynamics = None
    if env is not None:
        from diffgcl.algorithms.rgcl import demo_dynamics

        dynamics = demo_dynamics(env, X[:, None], U[:, None])
    return DemoBatch(X=X[:, None], U=U[:, None], controller=controller, dynamics=dynamics)


# ---- held-out situations and evaluation ---------------------------------------------------------


@dataclass(frozen=True)
class SituationRanges:
    """Ranges of the held-out situations, from the demos' window starts (task frame): pole
    distance ahead (m), the boat's lateral offset from the pole's line (m), heading (rad), speed
    (m/s); pole radius (m)."""

    distance: tuple[float, float]
    offset: tuple[float, float]
    heading: tuple[float, float]
    speed: tuple[float, float]
    radius: tuple[float, float] = (0.3, 1.0)

    @classmethod
    def of(cls, demos: DemoSet, radius=(0.3, 1.0)) -> SituationRanges:
        x0 = demos.X[:, 0]
        rel = x0[:, hull_sim.SL_OBS] - x0[:, :2]
        speed = np.hypot(x0[:, hull_sim.IX_VX], x0[:, hull_sim.IX_VY])

        def span(v):
            return float(np.min(v)), float(np.max(v))

        return cls(
            distance=span(rel[:, 0]),
            offset=span(-rel[:, 1]),
            heading=span(x0[:, hull_sim.IX_PSI]),
            speed=span(speed),
            radius=radius,
        )


def heldout_starts(env: UsvEnv, ranges: SituationRanges, key: PRNGKey, n: int) -> Array:
    """``n`` start states [n, 11]: each quantity drawn uniformly from its range independently
    (so no start equals a demo's), the boat at (0, offset) heading ``heading``, the pole on the
    course line ahead at ``distance``."""
    keys = jax.random.split(key, 5)
    dtype = env.x0.dtype

    def draw(k, lo_hi):
        return jax.random.uniform(k, (n,), dtype, *lo_hi)

    names = ("distance", "offset", "heading", "speed", "radius")
    d, off, psi, v, r = (draw(k, getattr(ranges, f)) for k, f in zip(keys, names, strict=True))
    poles = jnp.stack([d, jnp.zeros_like(d)], axis=-1)
    return jax.vmap(env.start_state)(poles, r, v, psi, off)


def path_distance_to_demos(X: np.ndarray, demo_X: np.ndarray) -> np.ndarray:
    """[B] mean distance (m) of each rollout's positions ``X: [B, T+1, 11]`` to the nearest point
    of the nearest demo path ``demo_X: [N, T+1, 11]``, both relative to their own pole."""
    P = X[..., :2] - X[:, :1, hull_sim.SL_OBS]
    Q = demo_X[..., :2] - demo_X[:, :1, hull_sim.SL_OBS]
    out = np.empty(P.shape[0])
    for b in range(P.shape[0]):
        d = np.linalg.norm(P[b][None, :, None, :] - Q[:, None, :, :], axis=-1)  # [N, T+1, T+1]
        out[b] = d.min(axis=2).mean(axis=1).min()
    return out


def trajectory_metrics(env: UsvEnv, X) -> dict[str, np.ndarray]:
    """:meth:`UsvEnv.metrics` of each rollout ``X: [B, T+1, 11]``, as NumPy arrays [B]."""
    return {k: np.asarray(v) for k, v in jax.jit(jax.vmap(env.metrics))(jnp.asarray(X)).items()}


def straight_side(X) -> np.ndarray:
    """The side (+1 port, −1 starboard, as :meth:`UsvEnv.metrics`' ``side``) on which each rollout
    ``X: [B, T+1, 11]`` would pass its pole if it sailed straight on from its start: the sign of
    the lateral offset from the pole at the pole's distance along the start heading."""
    x0 = np.asarray(X)[:, 0]
    ahead = x0[:, hull_sim.IX_OBS_X] - x0[:, hull_sim.IX_PX]
    lateral = x0[:, hull_sim.IX_PY] + ahead * np.tan(x0[:, hull_sim.IX_PSI])
    return np.sign(lateral - x0[:, hull_sim.IX_OBS_Y])


def score_rollouts(env: UsvEnv, X, demo_X) -> dict:
    """The USV figures of rollouts ``X: [B, T'+1, 11]`` against the demos ``demo_X: [N, T+1, 11]``
    (T' ≥ T: the evaluation may run past the demos' window).

    ``return_to_course_rate``: on course at the end (cross-track and heading within the env's
    tolerances, :meth:`UsvEnv.back_on_course`); ``returned_in_window_rate``: back at the course
    line within the demos' window (:meth:`UsvEnv.returned_to_course` on the first T+1 states, the
    figure the demos have too); collision rate; the median minimum clearance and its ratio to the
    demos' median; the median path distance to the nearest demo (first T+1 states); the share of
    port passes beside the demos'; ``straight_side_share``: the share that pass on the side they
    would have passed on sailing straight on (:func:`straight_side`; about 0.5 for a side picked
    at random), beside the demos'."""
    X = np.asarray(X)
    T1 = demo_X.shape[1]
    m = trajectory_metrics(env, X)
    w = trajectory_metrics(env, X[:, :T1])
    d = trajectory_metrics(env, demo_X)
    demo_clearance = float(np.median(d["min_clearance"]))
    clearance = float(np.median(m["min_clearance"]))
    return {
        "episodes": int(m["collision"].shape[0]),
        "collision_rate": float(m["collision"].mean()),
        "return_to_course_rate": float(m["back_on_course"].mean()),
        "returned_in_window_rate": float(w["returned_to_course"].mean()),
        "demo_returned_in_window_rate": float(d["returned_to_course"].mean()),
        "success_rate": float(m["success"].mean()),
        "min_clearance_median_m": clearance,
        "demo_min_clearance_median_m": demo_clearance,
        "clearance_ratio_vs_demos": clearance / demo_clearance,
        "final_cross_track_median_m": float(np.median(m["final_cross_track"])),
        "path_distance_to_demos_median_m": float(
            np.median(path_distance_to_demos(X[:, :T1], demo_X))
        ),
        "port_share": float(np.mean(m["side"] > 0)),
        "demo_port_share": float(np.mean(d["side"] > 0)),
        "straight_side_share": float(np.mean(m["side"] == straight_side(X))),
        "demo_straight_side_share": float(np.mean(d["side"] == straight_side(demo_X))),
    }


def per_seed_figures(env: UsvEnv, tracks, demo_clearance_m: float) -> dict:
    """Collision rate, on course at the end, clearance ratio (over the demos' median minimum
    clearance ``demo_clearance_m``), share of port passes and of passes on the straight-on side
    (:func:`straight_side`) of each training seed's tracks ``[S, B, T+1, 11]``, each a list over
    the seeds."""
    tracks = np.asarray(tracks)
    S = tracks.shape[0]
    flat = tracks.reshape(-1, *tracks.shape[2:])
    m = trajectory_metrics(env, flat)  # one call, all seeds
    per = {k: v.reshape(S, -1) for k, v in m.items()}
    return {
        "collision_rate": per["collision"].mean(axis=1).tolist(),
        "return_to_course_rate": per["back_on_course"].mean(axis=1).tolist(),
        "clearance_ratio_vs_demos": (
            np.median(per["min_clearance"], axis=1) / demo_clearance_m
        ).tolist(),
        "port_share": (per["side"] > 0).mean(axis=1).tolist(),
        "straight_side_share": (per["side"] == straight_side(flat).reshape(S, -1))
        .mean(axis=1)
        .tolist(),
    }


ON_COURSE_WARN = 0.9  # warn below this share of training starts back on course at the end


def _seed_rows(seeds, per_seed: dict):
    """(seed, hit rate, back on course, clearance ratio) per seed of :func:`per_seed_figures`."""
    return zip(
        seeds,
        per_seed["collision_rate"],
        per_seed["return_to_course_rate"],
        per_seed["clearance_ratio_vs_demos"],
        strict=True,
    )


def controller_warnings(seeds, per_seed: dict, conditions: int) -> list[tuple[int, str]]:
    """``(seed, text)`` for each training seed whose local controllers, on their own training
    starts (``per_seed``: :func:`per_seed_figures` of the controllers on the ``conditions`` demo
    starts), hit the pole on some, or are back on course at the end on fewer than
    :data:`ON_COURSE_WARN` of them. Warning signs, not verdicts (docs/usv.md):
    every run whose policy passed at 0.55–0.75× the demos' clearance and hit the pole had hits,
    and so did some whose policy was fine; the one diverged run of seeds 8–23 (seed 20; its
    policy circled, 0 % on course) had its controllers on course on none of their starts."""
    out = []
    for seed, hit_rate, on_course, ratio in _seed_rows(seeds, per_seed):
        hits = round(hit_rate * conditions)
        signs = []
        if hits:
            signs.append(f"hit the pole on {hits} of their {conditions} training starts")
        if on_course < ON_COURSE_WARN:
            back = round(on_course * conditions)
            signs.append(f"are back on course at the end on only {back} of {conditions}")
        if signs:
            out.append(
                (
                    int(seed),
                    f"its local controllers {' and '.join(signs)} (clearance {ratio:.2f}× the "
                    "demos'); its policy may pass too close or fail to return (a diverged run "
                    "circles): compare its per-seed figures, or train it again with another seed",
                )
            )
    return out


SENSOR_NOISE_FOLD = 7  # folded into a training key for the noise of its policy's judging rollouts
POLICY_CLEARANCE_WARN = 0.9  # warn when the policy passes closer than this × the demos' clearance


def policy_warnings(seeds, per_seed: dict, conditions: int) -> list[tuple[int, str]]:
    """``(seed, text)`` for each training seed whose global policy, sailing from the controllers'
    training starts (``per_seed``: :func:`per_seed_figures` of its tracks on the identified hull,
    sensor noise on: training data only), hits the pole on some, passes below
    :data:`POLICY_CLEARANCE_WARN` × the demos' median clearance, or is back on course at the end
    on fewer than :data:`ON_COURSE_WARN` of them. The policy is what sails, and it
    can pass closer than its controllers: on stop 27's headline, seed 0's controllers passed at
    0.99×, its policy at 0.85× from the same starts and 0.70× held out (2 % collisions); on the
    tuning seeds 0–7 (stop 28) it passed at 1.01–1.12× from the training starts, within 0.07 of
    its held-out figure, so none warned. Not complete either: tuning seed 7 hit the pole in 1 of
    64 held-out episodes with no sign on its training starts (docs/usv.md)."""
    out = []
    for seed, hit_rate, on_course, ratio in _seed_rows(seeds, per_seed):
        signs = []
        hits = round(hit_rate * conditions)
        if hits:
            signs.append(f"hits the pole from {hits} of the {conditions} training starts")
        if ratio < POLICY_CLEARANCE_WARN:
            signs.append(
                f"passes at {ratio:.2f}× the demos' clearance (below {POLICY_CLEARANCE_WARN}×)"
            )
        if on_course < ON_COURSE_WARN:
            signs.append(f"is back on course from only {round(on_course * conditions)}")
        if signs:
            out.append(
                (int(seed), f"its policy, sailing from the same starts, {' and '.join(signs)}")
            )
    return out


def training_warnings(seeds, controllers: dict, policy: dict | None, conditions: int) -> dict:
    """``{seed: text}`` for each training seed whose controllers (:func:`controller_warnings`) or
    policy (:func:`policy_warnings`; ``policy`` None: not judged) warn, both signs in one text."""
    texts: dict = {}
    signs = controller_warnings(seeds, controllers, conditions)
    if policy is not None:
        signs += policy_warnings(seeds, policy, conditions)
    for seed, text in signs:
        texts[seed] = f"{texts[seed]}; {text}" if seed in texts else text
    return texts


def training_key(seed: int, attempt: int = 0) -> Array:
    """The key of training seed ``seed``'s ``attempt``-th training: ``PRNGKey(seed)`` the first
    time (attempt 0), a key folded from it for each retraining (:func:`train_retrying_warned`)."""
    key = jax.random.PRNGKey(int(seed))
    return key if attempt == 0 else jax.random.fold_in(key, int(attempt))


def seed_name(seed: int, attempt: int) -> str:
    """How a training attempt is named in messages: ``3`` for the first, ``3 (attempt 1)``."""
    return str(seed) if attempt == 0 else f"{seed} (attempt {attempt})"


def _standing(controllers: dict, policy: dict | None, i: int, warned: bool) -> tuple:
    """Sort key of seed ``i``'s training attempt, lower is better: no warning; then, the policy
    being what sails, fewer policy hits, less clearance short of :data:`POLICY_CLEARANCE_WARN`,
    more of it back on course; then fewer controller hits, more controllers back on course."""
    sails = ()
    if policy is not None:
        short = max(0.0, POLICY_CLEARANCE_WARN - policy["clearance_ratio_vs_demos"][i])
        sails = (policy["collision_rate"][i], short, -policy["return_to_course_rate"][i])
    return (
        warned,
        *sails,
        controllers["collision_rate"][i],
        -controllers["return_to_course_rate"][i],
    )


ATTEMPT_FIGURES = ("collision_rate", "return_to_course_rate", "clearance_ratio_vs_demos")


def train_retrying_warned(train, figures, seeds, conditions: int, retrain: int, say=None):
    """Train every seed, then train again, each time with a new key (:func:`training_key`), each
    seed that warns (:func:`training_warnings`: its local controllers or its global policy on
    their own training starts), at most ``retrain`` more times; keep per seed its first attempt
    without a warning, else its best one (:func:`_standing`). Only the training starts decide:
    nothing held out is seen.

    ``train(keys [k, 2]) -> (out, Xc, Xp)``: a pytree of host arrays, the controllers' tracks on
    their ``conditions`` training starts and the policy's from the same starts (None: no policy
    judged), each with a leading axis over the keys; ``figures(X) -> per_seed``
    (:func:`per_seed_figures`). Returns ``out``, ``Xc`` and ``Xp`` of the kept attempts, their
    ``per_seed`` figures as ``{"controllers": ..., "policy": ...}``, the seconds spent in
    ``train`` and a record per seed: ``{"kept": attempt, "attempts": [{"warning": text or None,
    "collision_rate", "return_to_course_rate", "clearance_ratio_vs_demos", "policy": {the same
    three} or None}, ...]}`` (the unnamed figures are the controllers'); ``say(text)`` hears each
    warning and each retraining as it happens."""
    import time

    say = say or (lambda text: None)

    def judged(keys):
        t0 = time.perf_counter()
        out, Xc, Xp = train(keys)
        seconds = time.perf_counter() - t0
        Xc = np.array(Xc)
        Xp = None if Xp is None else np.array(Xp)
        per = {"controllers": figures(Xc), "policy": None if Xp is None else figures(Xp)}
        return out, Xc, Xp, per, seconds

    def attempt_record(per: dict, i: int, text) -> dict:
        record = {"warning": text, **{k: float(per["controllers"][k][i]) for k in ATTEMPT_FIGURES}}
        pol = per["policy"]
        record["policy"] = None if pol is None else {k: float(pol[k][i]) for k in ATTEMPT_FIGURES}
        return record

    def standing(per: dict, i: int, warned: bool) -> tuple:
        return _standing(per["controllers"], per["policy"], i, warned)

    seeds = [int(s) for s in seeds]
    out, Xc, Xp, per_seed, seconds = judged(jnp.stack([training_key(s) for s in seeds]))
    out = jax.tree.map(np.array, out)  # writable copies: retrained seeds are put in place
    warned = training_warnings(seeds, per_seed["controllers"], per_seed["policy"], conditions)
    for seed, text in warned.items():
        say(f"warning: training seed {seed}: {text}")
    record = {
        s: {"kept": 0, "attempts": [attempt_record(per_seed, i, warned.get(s))]}
        for i, s in enumerate(seeds)
    }
    for attempt in range(1, retrain + 1):
        again = [
            i for i, s in enumerate(seeds) if record[s]["attempts"][record[s]["kept"]]["warning"]
        ]
        if not again:
            break
        say(f"training seeds {[seeds[i] for i in again]} again with new keys (attempt {attempt})")
        keys = jnp.stack([training_key(seeds[i], attempt) for i in again])
        new_out, new_Xc, new_Xp, new_per, new_seconds = judged(keys)
        seconds += new_seconds
        new_warned = training_warnings(
            [seeds[i] for i in again], new_per["controllers"], new_per["policy"], conditions
        )
        for j, i in enumerate(again):
            s = seeds[i]
            text = new_warned.get(s)
            record[s]["attempts"].append(attempt_record(new_per, j, text))
            if text:
                say(f"warning: training seed {seed_name(s, attempt)}: {text}")
            if standing(new_per, j, text is not None) < standing(per_seed, i, True):
                record[s]["kept"] = attempt
                for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(new_out), strict=True):
                    a[i] = np.asarray(b)[j]
                Xc[i] = new_Xc[j]
                if Xp is not None:
                    Xp[i] = new_Xp[j]
                for part, figs in per_seed.items():
                    if figs is not None:
                        for k in figs:
                            figs[k][i] = new_per[part][k][j]
        for i in again:
            s = seeds[i]
            say(f"training seed {s}: keeps attempt {record[s]['kept']}")
    return out, Xc, Xp, per_seed, seconds, record


def policy_tracks(env: UsvEnv, policy, params, x0, keys: Array) -> np.ndarray:
    """Noise-free-action rollouts [S, B, T+1, 11] of global policies (``params`` with a leading
    seed axis S, one key each in ``keys: [S, 2]``) from ``x0: [B, 11]``, with the env's sensor
    noise in their observations (the boat's sensors are never noise-free); one compiled program
    for all seeds."""
    from diffgcl.eval.policy import policy_rollouts

    def one(p, k):
        return policy_rollouts(env, policy, p, jnp.asarray(x0), k, obs_noise=True).X

    return np.asarray(jax.jit(jax.vmap(one))(params, keys))


# ---- the whole run ------------------------------------------------------------------------------

METHODS = ("rgcl", "expert", "bc")


@dataclass(frozen=True)
class UsvRunConfig:
    """One run of the USV pipeline.

    task: :class:`UsvTaskConfig`; rgcl: the rGCL + MDGPS settings (None: :func:`~diffgcl.
    algorithms.presets.usv`); methods: of :data:`METHODS` — ``rgcl`` (learned cost + MDGPS),
    ``expert`` (MDGPS with the hand-written cost, ``expert_iterations`` iterations at its own
    KL step ``expert_kl_step`` and ``expert_max_step_mult``, with which it was measured; a fixed
    cost takes larger steps than a learned one that moves every iteration), ``bc``
    (behaviour cloning on the recorded observations); seeds: training seeds (vmapped);
    heldout: number of held-out situations (drawn with ``heldout_seed``), each rolled out for
    the window's horizon plus ``eval_extra`` steps (to judge the return); identify: fit the
    hull to the demos (else the nominal hull); sysid: its settings; retrain_warned: how many
    more times a training seed of ``rgcl`` is trained, each time with a new key, while its local
    controllers or its policy warn on their own training starts (:func:`train_retrying_warned`;
    0: warn only).
    """

    task: UsvTaskConfig = UsvTaskConfig()
    rgcl: object = None
    methods: tuple[str, ...] = METHODS
    seeds: tuple[int, ...] = (0,)
    heldout: int = 256
    heldout_seed: int = 1000
    eval_extra: int = 150
    expert_iterations: int = 15
    expert_kl_step: float = 1.0
    expert_max_step_mult: float = 10.0
    identify: bool = True
    sysid: object = None
    retrain_warned: int = 1

    def __post_init__(self):
        unknown = set(self.methods) - set(METHODS)
        if unknown:
            raise ValueError(f"usv: unknown methods {sorted(unknown)}; choose from {METHODS}")
        if self.retrain_warned < 0:
            raise ValueError(f"usv: retrain_warned must be >= 0, not {self.retrain_warned}")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"usv: training seeds repeat: {list(self.seeds)}")


FAST_RGCL_OVERRIDES = (
    "iterations=6",
    "freeze_last=2",
    "gcl.pretrain_steps=100",
    "gcl.n_steps=20",
    "policy.s_step.n_steps=100",
)


def fast_run_config(task: UsvTaskConfig | None = None) -> UsvRunConfig:
    """A run at smoke-test scale (``--fast`` of ``diffgcl usv`` and
    ``experiments/usv_avoidance.py``): ``task`` (default :class:`UsvTaskConfig`) with windows of
    240 steps (100 before the closest approach, 140 after, 40 trained past them), rGCL with
    :data:`FAST_RGCL_OVERRIDES` (6 iterations, the last 2 on a frozen cost, shorter GCL and
    S-step passes), 4 iterations of the hand-written cost's reference, 32 held-out situations
    and no retraining (6 iterations leave controllers off course: every seed would warn)."""
    import dataclasses

    from diffgcl.algorithms.presets import usv as usv_preset
    from diffgcl.algorithms.presets import with_overrides

    task = dataclasses.replace(
        task if task is not None else UsvTaskConfig(), before=100, after=140, train_extra=40
    )
    rgcl = with_overrides(usv_preset(), list(FAST_RGCL_OVERRIDES))
    return UsvRunConfig(task=task, rgcl=rgcl, heldout=32, expert_iterations=4, retrain_warned=0)


@dataclass
class UsvRun:
    """What :func:`run_usv` returns: ``summary`` (JSON-ready figures), the task env on the
    identified hull (``env``, demos' conditions; ``train_env`` the same with the training
    horizon, :attr:`UsvTaskConfig.training_horizon`) and on the true one (``env_true``, held-out
    starts ``x0_heldout``), the demos in the task layout, and per method its policy, parameters
    (leading seed axis) and held-out tracks [S, B, T+1, 11]; the rGCL state (``rgcl_state``)."""

    summary: dict
    env: UsvEnv
    env_true: UsvEnv
    demos: DemoSet
    x0_heldout: np.ndarray
    policies: dict
    tracks: dict
    rgcl_state: object = None
    rgcl: object = None
    train_env: UsvEnv | None = None


def _say(verbose: bool, text: str) -> None:
    if verbose:
        print(text, flush=True)


def _batched(fn, seeds, *args):
    """``jit(vmap(fn))`` over the seeds' keys; host arrays out and seconds (compile + run)."""
    import time

    keys = jnp.stack([training_key(s) for s in seeds])
    in_axes = (0,) + (None,) * len(args)
    t0 = time.perf_counter()
    out = jax.block_until_ready(jax.jit(jax.vmap(fn, in_axes=in_axes))(keys, *args))
    return jax.tree.map(np.asarray, out), time.perf_counter() - t0


def learned_cost_weights(network, params, names: tuple[str, ...]) -> dict:
    """The weighted-form cost per residual (``names``: :attr:`diffgcl.envs.usv.UsvEnv.
    cost_residual_names`), per
    training seed (``params`` with a leading seed axis): ``per_unit`` — its weight per squared
    unit of the residual, at the cost's temperature; ``log_w`` — the learned θ̃ (0 at the start,
    where every residual weighs 1 per squared RMS of the demos; their mean stays 0)."""
    w = np.asarray(jax.vmap(lambda p: network.feature_weights(p) * network.temperature(p))(params))
    theta = np.asarray(jax.vmap(network.log_weights)(params))
    return {
        name: {"per_unit": w[:, k].tolist(), "log_w": theta[:, k].tolist()}
        for k, name in enumerate(names)
    }


def identify_hull(demos: DemoSet, config=None, truth=None) -> tuple[object, dict]:
    """The hull identified from ``demos`` (:func:`diffgcl.data.sysid.identify`) and a summary:
    the fitted values and, given the ``truth``, the largest relative error."""
    from diffgcl.data.sysid import identify

    result = identify(demos, config)
    info = {"fitted": result.values()}
    if truth is not None:
        errors = result.relative_errors(truth)
        info["relative_errors"] = errors
        info["max_relative_error"] = max(errors.values())
    return result.params, info


def run_usv(
    demos: DemoSet,
    config: UsvRunConfig = UsvRunConfig(),
    *,
    manifest: Path | None = None,
    true_params=None,
    verbose: bool = True,
) -> UsvRun:
    """Bags' demos (ingested, world frame) → hull identification → task windows → rGCL + MDGPS on
    the identified hull, the references (:data:`METHODS`) → every policy rolled out from held-out
    situations on ``true_params`` (default: the identified hull) with sensor noise, scored by
    :func:`score_rollouts` against the demos. ``manifest``: a synthetic set's truth (pole radii).
    """
    import dataclasses
    import time

    from diffgcl.algorithms.presets import usv as usv_preset

    t_start = time.perf_counter()
    task = config.task
    rgcl_config = config.rgcl if config.rgcl is not None else usv_preset()
    summary: dict = {
        "sets": list(task.sets),
        "observation": task.observation,
        "range_encoding": task.range_encoding,
    }

    windows = task_windows(demos, task)
    radii = pole_radii(windows, task.default_pole_radius, manifest)
    summary["conditions"] = windows.num_episodes
    summary["horizon"] = task.horizon
    _say(verbose, f"{windows.num_episodes} demo windows of {task.horizon} steps (sets {task.sets})")

    if config.identify:
        chosen = [i for i, e in enumerate(demos.episodes) if str(e.get("set")) in task.sets]
        params, info = identify_hull(demos.subset(np.asarray(chosen)), config.sysid, true_params)
        summary["hull_identification"] = info
        _say(
            verbose,
            f"hull identified: {info.get('max_relative_error', float('nan')):.3f} "
            "largest relative error",
        )
    else:
        params = hull_sim.default_params()
    truth = true_params if true_params is not None else params

    # The margins once, for every env of the run (each would measure the demos' clearance again).
    task = dataclasses.replace(task, proximity_margins=task_margins(windows, radii, params, task))
    env = make_task_env(windows, radii, params, task)
    train_env = make_task_env(windows, radii, params, task, horizon=task.training_horizon)
    task_demos = usv_demo_set(env, windows, radii)
    needs_dynamics = rgcl_config.temperature != "likelihood" and "rgcl" in config.methods
    batch = demo_batch_pooled(task_demos, env=env if needs_dynamics else None)
    ranges = SituationRanges.of(task_demos, radius=(float(radii.min()), float(radii.max())))
    probe = make_task_env(windows, radii, truth, task, horizon=task.horizon + config.eval_extra)
    x0_heldout = np.asarray(
        heldout_starts(probe, ranges, jax.random.PRNGKey(config.heldout_seed), config.heldout)
    )
    env_true = dataclasses.replace(probe, x0=jnp.asarray(x0_heldout, probe.x0.dtype))
    demo_score = score_rollouts(env, task_demos.X, task_demos.X)
    summary["demos"] = {
        k: demo_score[k]
        for k in (
            "episodes",
            "collision_rate",
            "return_to_course_rate",
            "returned_in_window_rate",
            "min_clearance_median_m",
            "port_share",
        )
    }
    summary["proximity_margins"] = list(env.proximity_margins)
    summary["evaluation_horizon"] = task.horizon + config.eval_extra
    summary["training_horizon"] = task.training_horizon
    run = UsvRun(summary, env, env_true, task_demos, x0_heldout, {}, {}, train_env=train_env)
    eval_key = jax.random.PRNGKey(config.heldout_seed + 1)

    def judge(name: str, policy, params) -> None:
        keys = jnp.stack([jax.random.fold_in(eval_key, s) for s in range(len(config.seeds))])
        tracks = policy_tracks(
            env_true, policy, jax.tree.map(jnp.asarray, params), x0_heldout, keys
        )
        run.policies[name] = (policy, params)
        run.tracks[name] = tracks
        score = score_rollouts(env_true, tracks.reshape(-1, *tracks.shape[2:]), task_demos.X)
        score["per_seed"] = per_seed_figures(env_true, tracks, score["demo_min_clearance_median_m"])
        summary[name] = {**summary.get(name, {}), **score}
        _say(
            verbose,
            f"  {name}: collisions {score['collision_rate']:.2f}, back on course "
            f"{score['return_to_course_rate']:.2f}, clearance {score['min_clearance_median_m']:.1f}"
            f" m (demos {score['demo_min_clearance_median_m']:.1f} m), path to demos "
            f"{score['path_distance_to_demos_median_m']:.1f} m",
        )

    if "rgcl" in config.methods:
        from diffgcl.algorithms.rgcl import final_rollouts, make_train

        _say(verbose, f"rGCL + MDGPS on the identified hull, seeds {list(config.seeds)}")
        rgcl = make_train(rgcl_config, train_env)
        train = jax.jit(jax.vmap(rgcl.train, in_axes=(0, None)))
        controllers = jax.jit(jax.vmap(lambda c: final_rollouts(train_env, c)))

        def train_seeds(keys):
            state, metrics = jax.block_until_ready(train(keys, batch))
            Xc = controllers(state.gps.controller)
            # The policy from the same starts, its sensor noise drawn from the training key.
            sensor_keys = jax.vmap(lambda k: jax.random.fold_in(k, SENSOR_NOISE_FOLD))(keys)
            x0 = train_env.initial_states()
            Xp = policy_tracks(train_env, policy, state.policy.params, x0, sensor_keys)
            return jax.tree.map(np.asarray, (state, metrics)), Xc, Xp

        policy = rgcl.policy_phases.policy
        (state, metrics), Xc, Xp, per_seed, seconds, record = train_retrying_warned(
            train_seeds,
            lambda X: per_seed_figures(env, X, demo_score["demo_min_clearance_median_m"]),
            config.seeds,
            task_demos.num_episodes,
            config.retrain_warned,
            say=lambda text: _say(verbose, f"  {text}"),
        )
        on_starts = {}
        for name, X in (("controllers", Xc), ("policy", Xp)):
            on_starts[name] = score_rollouts(env, X.reshape(-1, *X.shape[2:]), task_demos.X)
            on_starts[name]["per_seed"] = per_seed[name]  # the kept attempts'
        kept = {seed: r["attempts"][r["kept"]] for seed, r in record.items()}
        summary["rgcl"] = {
            "seconds": seconds,
            "controllers_on_demo_starts": on_starts["controllers"],
            "policy_on_demo_starts": on_starts["policy"],
            "true_cost_per_iteration": np.asarray(metrics.gps.cost).mean((0, 2)).tolist(),
            "warnings": {str(seed): a["warning"] for seed, a in kept.items() if a["warning"]},
            "attempts": {str(seed): r for seed, r in record.items()},
        }
        if rgcl.network.config.form == "weighted" and rgcl_config.network.features == "env":
            summary["rgcl"]["cost_weights"] = learned_cost_weights(
                rgcl.network, state.cost.params, env.cost_residual_names
            )
        run.rgcl_state, run.rgcl = state, rgcl
        judge("rgcl", rgcl.policy_phases.policy, state.policy.params)

    if "expert" in config.methods:
        from diffgcl.algorithms.mdgps import MDGPSConfig, make_mdgps

        _say(verbose, "MDGPS with the hand-written cost (reference)")
        gps = dataclasses.replace(
            rgcl_config.gps,
            iterations=config.expert_iterations,
            kl_step=config.expert_kl_step,
            max_step_mult=config.expert_max_step_mult,
            maxent=False,
            gauss_newton=False,
        )
        md = make_mdgps(
            MDGPSConfig(gps=gps, policy=rgcl_config.policy), train_env, train_env.expert_cost
        )
        (state, _), seconds = _batched(md.train, config.seeds)
        summary["expert"] = {"seconds": seconds}
        judge("expert", md.policy_phases.policy, state.policy.params)

    if "bc" in config.methods:
        from diffgcl.algorithms.bc import BCConfig, make_bc

        _say(verbose, "behaviour cloning on the recorded observations (baseline)")
        dtype = env.x0.dtype
        policy, fit = make_bc(BCConfig(network=rgcl_config.policy.network), env.dO, env.dU, dtype)
        O, U, mask = (jnp.asarray(a, dtype) for a in (task_demos.O, task_demos.U, task_demos.mask))
        (state, _), seconds = _batched(lambda k: fit(k, O, U, mask), config.seeds)
        summary["bc"] = {"seconds": seconds}
        judge("bc", policy, state.params)

    summary["wall_seconds"] = time.perf_counter() - t_start
    return run
