"""From ROS bags to a validated demonstration dataset (host side, NumPy, outside jit).

Problem: a bag holds asynchronous streams — an INS pose at 20 Hz, an IMU at 50 Hz, radar
sweeps every 2.5 s, operator commands only when the operator moves the stick — each with its own
latency, dropouts, clock, frame and units. GCL needs, per episode, states ``X: [T+1, dX]`` and
actions ``U: [T, dU]`` on the hull model's time grid, plus observations ``O: [T+1, dO]``
comparable to the simulator's range sensors. The steps, all in integer nanoseconds to keep ROS1
and ROS2 bit for bit alike:

1. *Signals* (:mod:`diffgcl.data.signals`): each role of the
   :class:`~diffgcl.data.topics.TopicMap` is timed (header stamp or receive time, minus latency;
   broken stamps an error or dropped) and decoded into ``(t: [n], v: [n, k])`` in the local
   East-North-Up frame and SI units.
2. *Scans* (:mod:`diffgcl.data.scans`): LiDAR and radar returns in the hull frame, through the
   topic map's clutter filter (range and intensity gates, persistence over scans in the local
   frame).
3. *Segmentation* (:mod:`diffgcl.data.segment`): ``start``/``end`` markers when the bag has
   them, otherwise rules: underway stretches cut at U-turns.
4. *Time grid.* Per episode, the grid ``t_k`` is every whole multiple of ``dt`` (in bag time)
   inside the episode. Continuous signals are interpolated linearly, never across a gap longer
   than the role's ``max_gap``; commands are held (zero-order hold) from each change; the
   per-step validity mask is the conjunction of the required signals' validity. Masked spans are
   reported per topic ("topic /x: 20.1 s without messages from t=... — 203 of 661 steps masked").
5. *Obstacle.* The surveyed position (mean of the obstacle topic in the episode) or, without an
   obstacle topic, the static object the boat headed for and passed within the gate
   (:func:`diffgcl.data.scans.estimate_obstacle`, LiDAR first, radar otherwise). Without markers,
   a piece that passes no obstacle is a transit and skipped; an ambiguous episode is skipped or
   kept flagged (``obstacle_search.ambiguous``); every skip is a warning naming the span.
6. *Observations.* At each grid step the latest scan (at most ``max_gap`` old) is re-expressed
   from the boat's pose at that step (motion compensation; the scan's own hull-frame points where
   a pose is missing) and reduced to the simulator's beams: LiDAR by
   :func:`diffgcl.sim.sensors.ranges_from_points`, radar by
   :func:`diffgcl.data.scans.radar_sector_ranges` (nearest return per sector).
7. *Output.* Episodes are padded to a common horizon (last value held, mask 0) into a
   :class:`~diffgcl.data.demos.DemoSet` (``env="hull"``; X, U in the layout of
   :mod:`diffgcl.sim.hull`, O in that of :func:`diffgcl.envs.hull.observation`), with metadata
   per episode: ``source`` (bag), ``episode_in_bag``, ``t_start``/``t_end`` (s) and
   ``t_start_ns``, ``steps`` (T of this episode before padding), ``cropped``, ``segmentation``
   (``markers``/``rules``), ``marker_id`` (a bare token of the start marker), ``datum``, ``set``,
   ``obstacle`` (pole colour from the marker, else ``unknown``), ``obstacle_xy``,
   ``obstacle_source`` (``topic``/``lidar``/``radar``), ``obstacle_spread_m`` (RMS scatter of the
   fixes or returns about it), ``obstacle_scans``, ``obstacle_ambiguous``,
   ``obstacle_candidates`` (scans only), ``swerve_side`` (``left``/``right``, from the track at
   the closest approach), ``valid_fraction``, ``actuators`` (``feedback``/``reconstructed``),
   ``lidar``/``radar`` (present) and ``*_valid_fraction``, ``warnings``, plus any other
   ``key=value`` of the start marker.

Bad input raises :class:`~diffgcl.data.bags.BagError` (one line naming file, topic and time);
recoverable problems (short dropouts, a missing optional LiDAR, NavSatFix without a fix) become
masks and :class:`IngestWarning` warnings, recorded in the episode metadata as well.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from diffgcl.data.bags import BagError, IngestWarning, open_bag, read_topics
from diffgcl.data.demos import DEMO_FOLDER, DemoSet
from diffgcl.data.scans import (
    Scans,
    coast,
    decode_scans,
    estimate_obstacle,
    find_objects,
    persistent,
    radar_sector_ranges,
    to_hull,
    to_world,
)
from diffgcl.data.segment import segments_from_markers, segments_from_rules
from diffgcl.data.signals import (
    Signal,
    decode_commands,
    decode_heading,
    decode_obstacle,
    decode_position,
    decode_velocity,
    first_order_lag,
    gap_spans,
    hold,
    interpolate,
    message_times,
    time_grid,
)
from diffgcl.data.topics import TopicMap, default_topic_map
from diffgcl.io import check_output_folder

__all__ = [
    "Episode",
    "IngestConfig",
    "IngestWarning",
    "convert",
    "episodes_to_demos",
    "ingest_bag",
    "ingest_bags",
    "swerve_side",
]


@dataclass(frozen=True)
class IngestConfig:
    """How bags become demonstrations (what the boat recorded is in the topic map).

    dt: model time step (s); horizon: T of the output (episodes are padded with mask 0, longer
    ones cropped; None = the longest episode); env: name stored in the dataset;
    sensors: the simulator's range sensor layout used for observations (None: the default
    :class:`diffgcl.sim.sensors.SensorLayout`); observations: reduce scans to beams (False:
    ``dO = 0``).
    """

    dt: float = 0.1
    horizon: int | None = None
    env: str = "hull"
    sensors: Any = None
    observations: bool = True


@dataclass(frozen=True)
class Episode:
    """One ingested episode on the grid: t: [T+1] int64 ns, X: [T+1, dX], U: [T, dU],
    O: [T+1, dO], mask: [T+1] bool, meta: metadata dict."""

    t: np.ndarray
    X: np.ndarray
    U: np.ndarray
    O: np.ndarray
    mask: np.ndarray
    meta: dict


@dataclass(frozen=True)
class SensorReturns:
    """One range sensor of a bag: the gated scans, their returns in the local frame (None
    where the pose at the scan is unknown) and what the clutter filter keeps (hull and local
    frame)."""

    scans: Scans
    world: tuple[np.ndarray | None, ...]
    kept: tuple[np.ndarray, ...]
    kept_world: tuple[np.ndarray | None, ...]


# --------------------------------------------------------------------------------------------
# One bag
# --------------------------------------------------------------------------------------------


def swerve_side(X: np.ndarray, mask: np.ndarray) -> str:
    """``"left"``/``"right"``: the side the boat swerved to when passing the pole.

    At the closest valid approach, a pole on the boat's starboard (right) side means the boat
    passed it to port, i.e. swerved left. X: [T+1, dX] hull states, mask: [T+1].
    """
    from diffgcl.sim import hull

    rel = X[:, hull.SL_OBS] - X[:, hull.SL_QPOS][:, :2]
    dist = np.where(mask, np.linalg.norm(rel, axis=1), np.inf)
    k = int(np.argmin(dist))
    psi = X[k, hull.IX_PSI]
    left_component = -np.sin(psi) * rel[k, 0] + np.cos(psi) * rel[k, 1]
    return "left" if left_component < 0 else "right"


def _warn(meta_warnings: list[str], message: str) -> None:
    meta_warnings.append(message)
    warnings.warn(message, IngestWarning, stacklevel=3)


def _sensor_returns(
    path, data, spec, role: str, position: Signal, heading: Signal
) -> SensorReturns:
    scans = decode_scans(path, data, spec, role)
    xy, ok_p = interpolate(position, scans.t)
    psi, ok_h = interpolate(heading, scans.t)
    world = tuple(
        to_world(p, xy[i], psi[i, 0]) if ok_p[i] and ok_h[i] else None
        for i, p in enumerate(scans.points)
    )
    persistence = spec.filter.persistence if spec.filter is not None else None
    if persistence is None:
        return SensorReturns(scans, world, scans.points, world)
    keep = persistent(world, xy, persistence)
    kept_world = [w[k] if w is not None else None for w, k in zip(world, keep, strict=True)]
    kept_world = coast(kept_world, world, xy, persistence)
    kept = tuple(
        to_hull(w, xy[i], psi[i, 0]) if w is not None else scans.points[i][:0]
        for i, w in enumerate(kept_world)
    )
    kept_world = tuple(kept_world)
    return SensorReturns(scans, world, kept, kept_world)


def _span_warnings(path, grid: np.ndarray, checks, what: str) -> list[str]:
    """One warning per topic with invalid steps: its longest span, and how many more."""
    out = []
    for sig, ok in checks:
        spans = gap_spans(sig, grid, ok)
        if not spans:
            continue
        a, b, reason = spans[0]
        text = f"{path}: topic {sig.topic}: {reason} — {b - a + 1} of {grid.size} steps {what}"
        if len(spans) > 1:
            rest = sum(q - p + 1 for p, q, _ in spans[1:])
            text += f" (and {len(spans) - 1} shorter spans, {rest} steps)"
        out.append(text)
    return out


def ingest_bag(
    path: str | os.PathLike, topic_map: TopicMap | None = None, config: IngestConfig | None = None
) -> list[Episode]:
    """All episodes of one bag, on the grid (see the module docstring)."""
    from diffgcl.sim import hull

    path = Path(path)
    tm = topic_map or default_topic_map()
    cfg = config or IngestConfig()
    with open_bag(path) as reader:
        present = sorted({c.topic for c in reader.connections})
        bag_start = reader.start_time if reader.connections else None
    roles = tm.roles()
    for role in ("position", "heading", "commands"):
        if roles[role].topic not in present:
            raise BagError(
                path,
                f"missing required topic for {role} (topics in the bag: {', '.join(present)})",
                roles[role].topic,
                bag_start,
            )
    raw = read_topics(path, {spec.topic for spec in roles.values()})
    bag_warnings: list[str] = []
    timed = {}
    for role, spec in roles.items():
        if spec.topic in raw:
            timed[role], note = message_times(path, raw[spec.topic], spec, role)
            if note is not None:
                _warn(bag_warnings, note)
    for role in ("position", "heading", "commands"):
        if not timed[role].msgs:
            raise BagError(path, f"required topic for {role} has no messages", roles[role].topic)

    position, datum = decode_position(path, timed["position"], tm.position, tm.datum)
    heading, yaw_rate = decode_heading(path, timed["heading"], tm.heading)
    commands = decode_commands(path, timed["commands"], tm.commands, "commands")
    velocity = None
    if "velocity" in timed and timed["velocity"].msgs:
        velocity = decode_velocity(path, timed["velocity"], tm.velocity)
    actuators = None
    if "actuators" in timed and timed["actuators"].msgs:
        actuators = decode_commands(path, timed["actuators"], tm.actuators, "actuators")
    obstacle_sig = None
    if "obstacle" in timed and timed["obstacle"].msgs:
        obstacle_sig = decode_obstacle(path, timed["obstacle"], datum)

    sensors: dict[str, SensorReturns | None] = {}
    for role in ("lidar", "radar"):
        spec = roles.get(role)
        if spec is None:
            sensors[role] = None
        elif role not in timed or not timed[role].msgs:
            _warn(
                bag_warnings,
                f"{path}: topic {spec.topic}: optional {role} missing; its beams read no return",
            )
            sensors[role] = None
        elif cfg.observations or obstacle_sig is None:
            sensors[role] = _sensor_returns(path, timed[role], spec, role, position, heading)
        else:
            sensors[role] = None

    if "markers" in timed and timed["markers"].msgs:
        segments = segments_from_markers(path, timed["markers"])
        segmentation = "markers"
    else:
        objects = _known_objects(obstacle_sig, sensors, tm)
        segments, left_out = segments_from_rules(
            position, heading, velocity, tm.segmentation, tm.obstacle_search, objects
        )
        segmentation = "rules"
        if left_out:
            spans = ", ".join(f"{a * 1e-9:.1f}..{b * 1e-9:.1f}" for a, b in left_out[:6])
            more = f" and {len(left_out) - 6} more" if len(left_out) > 6 else ""
            what = (
                "no run at an obstacle (headed for and passed within "
                f"{tm.obstacle_search.gate:g} m)"
                if objects is not None and tm.segmentation.require_obstacle
                else "cut at turns"
            )
            _warn(
                bag_warnings,
                f"{path}: topic {tm.position.topic}: underway but not in an episode ({what}), "
                f"left out: t={spans} s{more}",
            )
    if not segments:
        raise BagError(
            path,
            "no episode found (no markers; the boat never ran at an obstacle or was never "
            "underway)",
            tm.position.topic,
        )
    lags = (
        tm.actuator_lags.thrust or hull.HullParams().tau_thrust,
        tm.actuator_lags.nozzle or hull.HullParams().tau_nozzle,
    )

    signals = _Signals(position, heading, yaw_rate, velocity, commands, actuators)
    episodes: list[Episode] = []
    skipped: list[BagError] = []
    for index, (t_a, t_b, info) in enumerate(segments):
        grid = time_grid(t_a, t_b, cfg.dt)
        ep_warnings = list(bag_warnings)
        g = _on_grid(signals, grid, cfg.dt, lags)
        valid = g.valid
        valid_s = valid.sum() * cfg.dt
        if valid_s < tm.min_episode_s:
            short = BagError(
                path,
                f"episode too short: {valid_s:.1f} s of valid data < {tm.min_episode_s:.1f} s",
                tm.position.topic,
                t_a,
            )
            if segmentation == "markers":
                raise short
            # Rule-based segments include brief manoeuvres in harbour: skip them.
            _warn(bag_warnings, f"{short} (segment skipped)")
            skipped.append(short)
            continue

        # The obstacle: surveyed, or estimated from the scans of this episode.
        track = (grid[valid], g.pos[valid], g.psi[valid, 0])
        obstacle = _episode_obstacle(path, obstacle_sig, sensors, t_a, t_b, track, tm)
        if isinstance(obstacle, BagError):
            _warn(bag_warnings, str(obstacle))
            skipped.append(obstacle)
            continue
        obstacle_xy, obstacle_meta, estimate = obstacle
        if estimate is not None and estimate.ambiguous:
            _warn(
                ep_warnings,
                f"{path}: episode {index}: ambiguous obstacle from {estimate.sensor} scans "
                f"({estimate.describe()}); kept, flagged obstacle_ambiguous",
            )
        obs_xy = np.broadcast_to(obstacle_xy, (grid.size, 2))

        for text in _span_warnings(path, grid, _topic_checks(g.checks), "masked"):
            _warn(ep_warnings, text)
        X = np.zeros((grid.size, hull.DX))
        X[:, hull.IX_PX : hull.IX_PY + 1] = g.pos
        X[:, hull.IX_PSI] = g.psi[:, 0]
        X[:, hull.IX_VX : hull.IX_VY + 1] = g.vel
        X[:, hull.IX_R] = g.rate[:, 0]
        X[:, hull.SL_ACT] = g.act
        X[:, hull.SL_OBS] = obs_xy
        U = g.cmd[:-1]
        O, obs_meta = _observations(path, grid, X, valid, sensors, cfg, ep_warnings)
        meta = {
            "source": str(path),
            "episode_in_bag": index,
            "t_start": grid[0] * 1e-9,
            "t_end": grid[-1] * 1e-9,
            "t_start_ns": int(grid[0]),
            "segmentation": segmentation,
            "datum": list(datum) if datum is not None else None,
            "set": info.get("set"),
            "obstacle": info.get("pole", "unknown"),
            "obstacle_xy": obs_xy[0].tolist(),
            **obstacle_meta,
            "swerve_side": swerve_side(X, valid),
            "valid_fraction": float(valid.mean()),
            "actuators": "feedback" if actuators is not None else "reconstructed",
            **obs_meta,
            "warnings": ep_warnings,
        }
        meta.update({k: v for k, v in info.items() if k not in ("set", "pole")})
        # Steps that are not valid keep finite placeholder values (a DemoSet forbids NaN only
        # at valid steps, but downstream arithmetic is safer without NaN anywhere).
        X = _fill_invalid(X, valid)
        episodes.append(Episode(t=grid, X=X, U=U, O=O, mask=valid, meta=meta))
    if not episodes:
        raise skipped[0]
    return episodes


@dataclass(frozen=True)
class _Signals:
    """The decoded signals of one bag (velocity and actuators may be absent)."""

    position: Signal
    heading: Signal
    yaw_rate: Signal
    velocity: Signal | None
    commands: Signal
    actuators: Signal | None


@dataclass(frozen=True)
class _OnGrid:
    """The signals on one episode's grid (K steps): values, the validity of each, and (signal,
    validity) pairs for the span warnings."""

    pos: np.ndarray
    psi: np.ndarray
    vel: np.ndarray
    rate: np.ndarray
    cmd: np.ndarray
    act: np.ndarray
    valid: np.ndarray
    checks: tuple


def _on_grid(sig: _Signals, grid: np.ndarray, dt: float, lags) -> _OnGrid:
    pos, ok_p = interpolate(sig.position, grid)
    psi, ok_h = interpolate(sig.heading, grid)
    if sig.velocity is not None:
        vel, ok_v = interpolate(sig.velocity, grid)
    else:
        vel = np.gradient(pos, dt, axis=0) if grid.size > 1 else np.zeros_like(pos)
        # np.gradient: central differences inside, one-sided at the ends.
        before = np.concatenate([ok_p[:1], ok_p[:-1]])
        after = np.concatenate([ok_p[1:], ok_p[-1:]])
        ok_v = ok_p & before & after
    rate, ok_r = interpolate(sig.yaw_rate, grid)
    cmd, ok_c = hold(sig.commands, grid)
    if sig.actuators is not None:
        act, ok_a = interpolate(sig.actuators, grid)
    else:
        act = first_order_lag(cmd, cmd[0], dt, lags)
        ok_a = ok_c
    checks = (
        (sig.position, ok_p & ok_v if sig.velocity is None else ok_p),
        (sig.heading, ok_h & ok_r),
        (sig.velocity, ok_v),
        (sig.commands, ok_c),
        (sig.actuators, ok_a),
    )
    valid = ok_p & ok_h & ok_v & ok_r & ok_c & ok_a
    return _OnGrid(pos, psi, vel, rate, cmd, act, valid, checks)


def _topic_checks(pairs) -> list[tuple[Signal, np.ndarray]]:
    """(signal, ok) per topic, signals of the same topic merged (their validity and-ed)."""
    merged: dict[str, tuple[Signal, np.ndarray]] = {}
    for sig, ok in pairs:
        if sig is None:
            continue
        if sig.topic in merged:
            first, prev = merged[sig.topic]
            merged[sig.topic] = (first, prev & ok)
        else:
            merged[sig.topic] = (sig, ok)
    return list(merged.values())


def _episode_obstacle(path, obstacle_sig, sensors, t_a, t_b, track, tm: TopicMap):
    """(obstacle xy [2], metadata, estimate or None) of the episode [t_a, t_b] with the valid
    track (t, xy, ψ); a :class:`BagError` to skip the episode with (no object qualifies, or an
    ambiguous one with ``obstacle_search.ambiguous: skip``)."""
    if obstacle_sig is not None:
        sel = (obstacle_sig.t >= t_a) & (obstacle_sig.t <= t_b)
        vals = obstacle_sig.v[sel] if sel.any() else obstacle_sig.v
        xy = vals.mean(axis=0)
        meta = {
            "obstacle_source": "topic",
            "obstacle_spread_m": float(np.sqrt(np.mean(np.sum((vals - xy) ** 2, axis=1)))),
            "obstacle_scans": len(vals),
            "obstacle_ambiguous": False,
        }
        return xy, meta, None
    estimate = _estimate_obstacle(sensors, t_a, t_b, *track, tm)
    if estimate is None:
        raise BagError(
            path,
            "no obstacle position (no obstacle topic and no range-sensor returns)",
            tm.obstacle.topic if tm.obstacle is not None else None,
            t_a,
        )
    search = tm.obstacle_search
    problem = None
    if estimate.xy is None:
        problem = (
            f"episode: no object seen in {search.min_scans}+ {estimate.sensor} scans that the "
            f"boat headed for (aim <= {search.aim_deg:g} deg) and passed within {search.gate:g} "
            f"m; candidates: {estimate.describe()}"
        )
    elif estimate.ambiguous and search.ambiguous == "skip":
        problem = (
            f"episode: ambiguous obstacle, {estimate.qualified} objects qualify "
            f"({estimate.describe()}); set obstacle_search.ambiguous: keep to keep such "
            "episodes flagged"
        )
    if problem is not None:
        return BagError(
            path,
            f"t={t_a * 1e-9:.3f}s..{t_b * 1e-9:.3f}s: {problem} (segment skipped)",
            tm.roles()[estimate.sensor].topic,
            t_a,
        )
    best = estimate.chosen
    meta = {
        "obstacle_source": estimate.sensor,
        "obstacle_spread_m": best.object.spread,
        "obstacle_scans": best.object.scans,
        "obstacle_ambiguous": estimate.ambiguous,
        "obstacle_candidates": [
            {
                "xy": c.object.xy.tolist(),
                "scans": c.object.scans,
                "spread_m": c.object.spread,
                "closest_m": c.closest,
                "aim_deg": c.aim_deg if np.isfinite(c.aim_deg) else None,
            }
            for c in estimate.candidates[:4]
        ],
    }
    return estimate.xy, meta, estimate


def _known_objects(obstacle_sig, sensors, tm: TopicMap) -> np.ndarray | None:
    """[M, 2] positions of the obstacles of a whole bag for rule-based segmentation: the obstacle
    topic's (clustered), else the static objects in the LiDAR's returns, else the radar's; None
    when there is nothing to find them from."""
    search = tm.obstacle_search
    if obstacle_sig is not None:
        ids = np.arange(len(obstacle_sig.v))
        found = find_objects(obstacle_sig.v, ids, search.cluster, 1)
        return np.array([o.xy for o in found]).reshape(-1, 2)
    result = None
    for role in ("lidar", "radar"):
        entry = sensors.get(role)
        if entry is None:
            continue
        pts = [(i, w) for i, w in enumerate(entry.world) if w is not None and len(w)]
        if not pts:
            result = np.zeros((0, 2)) if result is None else result
            continue
        ids = np.concatenate([np.full(len(w), i) for i, w in pts])
        found = find_objects(
            np.concatenate([w for _, w in pts]), ids, search.cluster, search.min_scans
        )
        if found:
            return np.array([o.xy for o in found])
        result = np.zeros((0, 2))
    return result


def _estimate_obstacle(sensors, t_a, t_b, track_t, track, track_psi, tm: TopicMap):
    """The obstacle from the LiDAR when it finds one, else the radar; None without returns."""
    result = None
    for role in ("lidar", "radar"):
        entry = sensors.get(role)
        if entry is None:
            continue
        sel = np.flatnonzero((entry.scans.t >= t_a) & (entry.scans.t <= t_b))
        world = [entry.world[i] for i in sel]
        est = estimate_obstacle(world, track_t, track, track_psi, tm.obstacle_search, role)
        if est.xy is not None:
            return est
        result = result or est
    return result


def _fill_invalid(X: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace rows of invalid steps by the nearest valid row (finite placeholders)."""
    if valid.all() or not valid.any():
        return np.nan_to_num(X)
    idx = np.arange(valid.size)
    src = np.where(valid, idx, -1)
    src = np.maximum.accumulate(src)
    first = int(np.argmax(valid))
    src[src < 0] = first
    return np.nan_to_num(X[src])


def _observations(
    path, grid, X, valid, sensors, cfg: IngestConfig, ep_warnings
) -> tuple[np.ndarray, dict]:
    """O: [K, dO] in the hull env's layout (:func:`diffgcl.envs.hull.observation`):
    LiDAR beams, radar beams, sin ψ, cos ψ, u, v, r.

    At step k the latest scan (at most ``max_gap`` old) is taken from the local frame into the
    hull frame of step k (its own hull-frame points where a pose is missing) and reduced to the
    beams: LiDAR points fill the LiDAR beams only (:func:`~diffgcl.sim.sensors.ranges_from_points`),
    radar returns the radar beams only (:func:`~diffgcl.data.scans.radar_sector_ranges`). A step
    without a recent scan (or a bag without the sensor) reads the beams' maximum range, i.e.
    "no return", and is reported as a warning naming the topic and the span.
    """
    from diffgcl.sim import hull
    from diffgcl.sim import sensors as sim_sensors

    layout = cfg.sensors if cfg.sensors is not None else sim_sensors.SensorLayout()
    if not cfg.observations:
        return np.zeros((grid.size, 0)), {"lidar": sensors.get("lidar") is not None}
    lidar_only = dataclasses.replace(layout, radar_beams=0)
    ranges = np.broadcast_to(layout.max_ranges, (grid.size, layout.num_beams)).copy()
    fans = {
        "lidar": slice(0, layout.lidar_beams),
        "radar": slice(layout.lidar_beams, layout.num_beams),
    }
    pose = X[:, hull.IX_PX : hull.IX_PY + 1]
    meta: dict[str, Any] = {}
    for role, fan in fans.items():
        entry = sensors.get(role)
        meta[role] = entry is not None
        if entry is None:
            meta[f"{role}_valid_fraction"] = 0.0
            continue
        scans = entry.scans
        index = Signal(
            scans.topic, scans.t, np.arange(scans.t.size, dtype=float)[:, None], scans.max_gap
        )
        idx, ok = hold(index, grid)
        for k in np.flatnonzero(ok):
            i = int(idx[k, 0])
            world = entry.kept_world[i]
            if world is not None and valid[k]:
                pts = to_hull(world, pose[k], X[k, hull.IX_PSI])
            else:
                pts = entry.kept[i]
            if role == "lidar":
                ranges[k, fan] = sim_sensors.ranges_from_points(pts, lidar_only)
            else:
                ranges[k, fan] = radar_sector_ranges(pts, layout)
        meta[f"{role}_valid_fraction"] = float(ok.mean())
        for text in _span_warnings(path, grid, [(index, ok)], "read no return"):
            _warn(ep_warnings, text)
    psi = X[:, hull.IX_PSI]
    c, s = np.cos(psi), np.sin(psi)
    u = c * X[:, hull.IX_VX] + s * X[:, hull.IX_VY]
    v = -s * X[:, hull.IX_VX] + c * X[:, hull.IX_VY]
    O = np.concatenate([ranges, np.stack([s, c, u, v, X[:, hull.IX_R]], axis=1)], axis=1)
    return O, meta


# --------------------------------------------------------------------------------------------
# Many bags -> DemoSet
# --------------------------------------------------------------------------------------------


def episodes_to_demos(episodes: Sequence[Episode], config: IngestConfig) -> DemoSet:
    """Stack episodes into a :class:`DemoSet`, padding to ``config.horizon`` (mask 0 on pads)."""
    if not episodes:
        raise ValueError("no episodes to stack")
    T = config.horizon if config.horizon is not None else max(e.U.shape[0] for e in episodes)
    N = len(episodes)
    dX, dU, dO = episodes[0].X.shape[1], episodes[0].U.shape[1], episodes[0].O.shape[1]
    X = np.zeros((N, T + 1, dX))
    U = np.zeros((N, T, dU))
    O = np.zeros((N, T + 1, dO))
    mask = np.zeros((N, T + 1), np.float64)
    metas = []
    for i, e in enumerate(episodes):
        n = min(e.X.shape[0], T + 1)
        X[i, :n], X[i, n:] = e.X[:n], e.X[n - 1]
        O[i, :n], O[i, n:] = e.O[:n], e.O[n - 1]
        m = min(e.U.shape[0], T)
        U[i, :m], U[i, m:] = e.U[:m], e.U[m - 1] if m else 0.0
        mask[i, :n] = e.mask[:n]
        metas.append({**e.meta, "steps": int(n - 1), "cropped": bool(e.X.shape[0] > T + 1)})
    return DemoSet(X=X, U=U, O=O, mask=mask, dt=config.dt, env=config.env, episodes=tuple(metas))


def ingest_bags(
    paths: Sequence[str | os.PathLike],
    topic_map: TopicMap | None = None,
    config: IngestConfig | None = None,
    progress: Callable[[Sequence], Any] | None = None,
) -> DemoSet:
    """Ingest every bag in ``paths`` (in order) into one :class:`DemoSet`.

    ``progress`` wraps the iterable of paths (e.g. ``tqdm``). Raises :class:`BagError` on the
    first bad bag; nothing is written here (see :func:`convert`).
    """
    cfg = config or IngestConfig()
    episodes: list[Episode] = []
    iterable = progress(list(paths)) if progress is not None else paths
    for p in iterable:
        episodes.extend(ingest_bag(p, topic_map, cfg))
    return episodes_to_demos(episodes, cfg)


def convert(
    paths: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    topic_map: TopicMap | None = None,
    config: IngestConfig | None = None,
    progress: Callable[[Sequence], Any] | None = None,
    overwrite: bool = False,
) -> DemoSet:
    """Ingest ``paths`` and save the dataset to ``out`` (all or nothing; the output folder
    rules of :func:`diffgcl.io.write_folder` are checked before any bag is read)."""
    check_output_folder(out, DEMO_FOLDER, overwrite)
    demos = ingest_bags(paths, topic_map, config, progress)
    demos.save(out, overwrite)
    return demos
