"""From ROS bags to a validated demonstration dataset (host side, NumPy, outside jit).

Problem: a bag holds asynchronous streams — an INS pose at 20 Hz, an IMU at 50 Hz, radar
sweeps every 2 s, operator commands only when the operator moves the stick — each with its own
latency, dropouts and clock. GCL needs, per episode, states ``X: [T+1, dX]`` and actions
``U: [T, dU]`` on the hull model's time grid, plus observations ``O: [T+1, dO]`` comparable to
the simulator's range sensors. The steps, all in integer nanoseconds to keep ROS1 and ROS2 bit
for bit alike:

1. *Time stamps.* A message's time is its header stamp where it has one (non-zero), its bag
   (receive) time otherwise. Stamps of one topic must not decrease (error otherwise).
2. *Signals.* Each role of the :class:`~diffgcl.data.topics.TopicMap` is decoded into
   ``(t: [n], v: [n, k])``: positions in a local East-North-Up frame (NavSatFix latitude /
   longitude through a local tangent plane at the datum), unwrapped heading, body-frame
   velocities rotated to the world frame, commands in SI units.
3. *Segmentation.* Episodes come from ``start``/``end`` marker messages when the bag has them,
   otherwise from rules (:class:`SegmentRules`): maximal stretches where the boat is underway,
   split at long position gaps.
4. *Time grid.* Per episode, the grid ``t_k`` is every whole multiple of ``dt`` (in bag time)
   inside the episode. Continuous signals are interpolated linearly, never across a gap longer
   than the role's ``max_gap``; commands are held (zero-order hold) from each change; the
   per-step validity mask is the conjunction of the required signals' validity.
5. *Observations.* Each LiDAR scan / radar sweep is turned into points in the hull frame and
   reduced by :func:`diffgcl.sim.sensors.ranges_from_points` to the simulator's beams, held until
   the next scan (at most ``max_gap``).
6. *Output.* Episodes are padded to a common horizon (last value held, mask 0) into a
   :class:`~diffgcl.data.demos.DemoSet` (``env="hull"``; X, U in the layout of
   :mod:`diffgcl.sim.hull`, O in that of :func:`diffgcl.envs.hull.observation`), with metadata
   per episode: ``source`` (bag), ``episode_in_bag``, ``t_start``/``t_end`` (s) and
   ``t_start_ns``, ``steps`` (T of this episode before padding), ``cropped``, ``segmentation``
   (``markers``/``rules``), ``datum``, ``set``, ``obstacle`` (pole colour from the marker, else
   ``unknown``), ``obstacle_xy``, ``swerve_side`` (``left``/``right``, from the track at the
   closest approach), ``valid_fraction``, ``actuators`` (``feedback``/``reconstructed``),
   ``lidar``/``radar`` (present) and ``*_valid_fraction``, ``warnings``, plus any other
   ``key=value`` of the start marker.

Bad input raises :class:`~diffgcl.data.bags.BagError` (one line naming file, topic and time);
recoverable problems (short dropouts, a missing optional LiDAR, NavSatFix without a fix) become
masks and :class:`IngestWarning` warnings, recorded in the episode metadata as well.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from diffgcl.data.bags import BagError, TopicMessages, open_bag, read_topics
from diffgcl.data.demos import DemoSet
from diffgcl.data.topics import CommandSpec, RangeSensorSpec, TopicMap, default_topic_map

NS = 1_000_000_000

# WGS-84 ellipsoid, for the local tangent plane of lat/lon positions.
_WGS84_A = 6378137.0
_WGS84_F = 1.0 / 298.257223563
_WGS84_E2 = _WGS84_F * (2.0 - _WGS84_F)

# Message types each role accepts.
POSITION_TYPES = ("nav_msgs/msg/Odometry", "sensor_msgs/msg/NavSatFix")
HEADING_TYPES = ("sensor_msgs/msg/Imu", "nav_msgs/msg/Odometry")
VELOCITY_TYPES = ("nav_msgs/msg/Odometry",)
SCAN_TYPES = (
    "sensor_msgs/msg/LaserScan",
    "sensor_msgs/msg/PointCloud2",
    "odin_msgs/msg/RadarSector",
)
OBSTACLE_TYPES = ("sensor_msgs/msg/NavSatFix", "geometry_msgs/msg/PointStamped")
MARKER_TYPES = ("std_msgs/msg/String",)


class IngestWarning(UserWarning):
    """A recoverable problem in a bag (dropout, missing optional sensor)."""


@dataclass(frozen=True)
class SegmentRules:
    """Episode segmentation when a bag has no markers.

    An episode is a maximal stretch where the speed over ground is at least ``min_speed`` (m/s;
    dips shorter than ``bridge_s`` are bridged) and the position stream has no gap longer than
    ``split_gap_s``. ``min_obstacle_distance`` (m), when set, also requires that the boat comes
    that close to the pole (only with an obstacle topic), which discards transits.
    """

    min_speed: float = 1.0
    bridge_s: float = 3.0
    split_gap_s: float = 5.0
    min_obstacle_distance: float | None = None


@dataclass(frozen=True)
class IngestConfig:
    """How bags become demonstrations.

    dt: model time step (s); horizon: T of the output (episodes are padded with mask 0, longer
    ones cropped; None = the longest episode); env: name stored in the dataset;
    sensors: the simulator's range sensor layout used for observations (None: the default
    :class:`diffgcl.sim.sensors.SensorLayout`); tau_thrust / tau_nozzle: actuator lags used to
    reconstruct the actuator states from commands when the bag has no jet feedback.
    """

    dt: float = 0.1
    horizon: int | None = None
    env: str = "hull"
    sensors: Any = None
    tau_thrust: float = 1.5
    tau_nozzle: float = 0.3
    segment: SegmentRules = field(default_factory=SegmentRules)
    observations: bool = True


@dataclass(frozen=True)
class Signal:
    """A decoded signal: t: [n] int64 ns (sorted), v: [n, k] float64, max_gap: s."""

    topic: str
    t: np.ndarray
    v: np.ndarray
    max_gap: float


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


# --------------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------------


def latlon_to_local(lat, lon, datum: tuple[float, float]) -> np.ndarray:
    """Local East-North (m) of WGS-84 ``lat, lon`` (deg, [n]) around ``datum`` -> [n, 2].

    Local tangent plane with the ellipsoid's meridional and prime-vertical radii at the datum;
    exact to a few mm within a few km, plenty for one harbour.
    """
    lat0 = np.deg2rad(datum[0])
    s2 = np.sin(lat0) ** 2
    rn = _WGS84_A / np.sqrt(1.0 - _WGS84_E2 * s2)
    rm = rn * (1.0 - _WGS84_E2) / (1.0 - _WGS84_E2 * s2)
    east = np.deg2rad(np.asarray(lon, float) - datum[1]) * rn * np.cos(lat0)
    north = np.deg2rad(np.asarray(lat, float) - datum[0]) * rm
    return np.stack([east, north], axis=-1)


def local_to_latlon(xy, datum: tuple[float, float]) -> np.ndarray:
    """Inverse of :func:`latlon_to_local`: xy: [n, 2] (m) -> [n, 2] (lat, lon deg)."""
    xy = np.asarray(xy, float)
    lat0 = np.deg2rad(datum[0])
    s2 = np.sin(lat0) ** 2
    rn = _WGS84_A / np.sqrt(1.0 - _WGS84_E2 * s2)
    rm = rn * (1.0 - _WGS84_E2) / (1.0 - _WGS84_E2 * s2)
    lat = datum[0] + np.rad2deg(xy[..., 1] / rm)
    lon = datum[1] + np.rad2deg(xy[..., 0] / (rn * np.cos(lat0)))
    return np.stack([lat, lon], axis=-1)


def quaternion_yaw(x, y, z, w) -> np.ndarray:
    """Yaw (rad, about +z) of quaternions given component-wise ([n] each)."""
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


# --------------------------------------------------------------------------------------------
# Decoding messages into signals
# --------------------------------------------------------------------------------------------


def _field(msg: Any, path: str) -> Any:
    for part in path.split("."):
        msg = getattr(msg, part)
    return msg


# Header stamps may arrive slightly out of order (transport jitter); a step back larger than this
# is a clock jump or a corrupt stamp, i.e. "time going backwards".
MAX_REORDER_S = 0.5


def order_by_stamp(path, data: TopicMessages) -> TopicMessages:
    """``data`` sorted by header stamp; raises :class:`BagError` if a stamp jumps backwards by
    more than :data:`MAX_REORDER_S` relative to the latest stamp seen so far."""
    t = data.stamp_ns
    if t.size < 2:
        return data
    latest = np.maximum.accumulate(t)
    back = np.flatnonzero(latest[:-1] - t[1:] > MAX_REORDER_S * NS)
    if back.size:
        i = back[0] + 1
        raise BagError(
            path,
            f"time goes backwards (stamp {t[i] * 1e-9:.3f}s after {latest[i - 1] * 1e-9:.3f}s)",
            data.topic,
            data.bag_ns[i],
        )
    if np.all(np.diff(t) >= 0):
        return data
    order = np.argsort(t, kind="stable")
    return TopicMessages(
        data.topic,
        data.msgtype,
        data.bag_ns[order],
        t[order],
        tuple(data.msgs[i] for i in order),
    )


def _check_finite(path, topic: str, t: np.ndarray, v: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(v.reshape(len(t), -1)).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise BagError(path, f"non-finite {what} (NaN or inf)", topic, t[i])


def _require_type(path, topic: str, data: TopicMessages, allowed: Sequence[str], role: str):
    if data.msgtype not in allowed:
        t0 = data.bag_ns[0] if data.bag_ns.size else None
        raise BagError(
            path,
            f"unknown message type {data.msgtype} for {role} (supported: {', '.join(allowed)})",
            topic,
            t0,
        )


def _signal(path, data: TopicMessages, values: np.ndarray, max_gap: float, what: str) -> Signal:
    t = data.stamp_ns
    _check_finite(path, data.topic, t, values, what)
    return Signal(data.topic, t, values.reshape(len(t), -1).astype(np.float64), max_gap)


def decode_position(path, data: TopicMessages, max_gap: float, datum) -> tuple[Signal, tuple]:
    """Position [n, 2] in the local frame; returns (signal, datum used)."""
    _require_type(path, data.topic, data, POSITION_TYPES, "position")
    if data.msgtype == "nav_msgs/msg/Odometry":
        xy = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for m in data.msgs])
        return _signal(path, data, xy.reshape(-1, 2), max_gap, "position"), datum
    fix = np.array([m.status.status >= 0 for m in data.msgs], bool)
    if (~fix).any():
        warnings.warn(
            f"{path}: topic {data.topic}: {int((~fix).sum())} NavSatFix messages without a fix "
            "dropped",
            IngestWarning,
            stacklevel=2,
        )
    ll = np.array([[m.latitude, m.longitude] for m in data.msgs]).reshape(-1, 2)
    _check_finite(path, data.topic, data.stamp_ns, ll, "latitude/longitude")
    if datum is None:
        if not fix.any():
            raise BagError(path, "no GNSS fix in the whole bag", data.topic)
        datum = (float(ll[fix][0, 0]), float(ll[fix][0, 1]))
    xy = latlon_to_local(ll[:, 0], ll[:, 1], datum)
    kept = TopicMessages(
        data.topic,
        data.msgtype,
        data.bag_ns[fix],
        data.stamp_ns[fix],
        tuple(m for m, f in zip(data.msgs, fix, strict=True) if f),
    )
    return _signal(path, kept, xy[fix], max_gap, "position"), datum


def decode_heading(path, data: TopicMessages, max_gap: float) -> tuple[Signal, Signal | None]:
    """Unwrapped heading [n, 1] and, from an Imu, yaw rate [n, 1]."""
    _require_type(path, data.topic, data, HEADING_TYPES, "heading")
    if data.msgtype == "sensor_msgs/msg/Imu":
        q = np.array([[o.x, o.y, o.z, o.w] for o in (m.orientation for m in data.msgs)]).reshape(
            -1, 4
        )
        rate = np.array([m.angular_velocity.z for m in data.msgs], float)
    else:
        q = np.array(
            [
                [
                    m.pose.pose.orientation.x,
                    m.pose.pose.orientation.y,
                    m.pose.pose.orientation.z,
                    m.pose.pose.orientation.w,
                ]
                for m in data.msgs
            ]
        ).reshape(-1, 4)
        rate = np.array([m.twist.twist.angular.z for m in data.msgs], float)
    _check_finite(path, data.topic, data.stamp_ns, q, "orientation")
    yaw = np.unwrap(quaternion_yaw(q[:, 0], q[:, 1], q[:, 2], q[:, 3]))
    heading = _signal(path, data, yaw, max_gap, "heading")
    return heading, _signal(path, data, rate, max_gap, "yaw rate")


def decode_velocity(path, data: TopicMessages, max_gap: float) -> Signal:
    """World-frame velocity [n, 2] from an Odometry twist (body frame, rotated by its own yaw)."""
    _require_type(path, data.topic, data, VELOCITY_TYPES, "velocity")
    rows = [
        [
            m.twist.twist.linear.x,
            m.twist.twist.linear.y,
            quaternion_yaw(
                m.pose.pose.orientation.x,
                m.pose.pose.orientation.y,
                m.pose.pose.orientation.z,
                m.pose.pose.orientation.w,
            ),
        ]
        for m in data.msgs
    ]
    a = np.array(rows, float).reshape(-1, 3)
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    world = np.stack([c * a[:, 0] - s * a[:, 1], s * a[:, 0] + c * a[:, 1]], axis=-1)
    return _signal(path, data, world, max_gap, "velocity")


def decode_commands(path, data: TopicMessages, spec: CommandSpec, role: str) -> Signal:
    """[thrust (N), nozzle (rad)]: [n, 2] from any message with the two configured fields."""
    try:
        v = np.array(
            [
                [
                    float(_field(m, spec.thrust_field)) * spec.thrust_scale,
                    float(_field(m, spec.nozzle_field)) * spec.nozzle_scale,
                ]
                for m in data.msgs
            ]
        ).reshape(-1, 2)
    except (AttributeError, TypeError, ValueError):
        raise BagError(
            path,
            f"unknown message type {data.msgtype} for {role} (needs fields "
            f"{spec.thrust_field!r} and {spec.nozzle_field!r})",
            data.topic,
            data.bag_ns[0] if data.bag_ns.size else None,
        ) from None
    return _signal(path, data, v, spec.max_gap, role)


def scan_points(path, data: TopicMessages, spec: RangeSensorSpec) -> list[np.ndarray]:
    """Each scan as points [m, 2] in the hull frame (sensor mount applied); returns a list."""
    _require_type(path, data.topic, data, SCAN_TYPES, "range sensor")
    mx, my, myaw = spec.mount
    c, s = np.cos(myaw), np.sin(myaw)
    out = []
    for m, t in zip(data.msgs, data.stamp_ns, strict=True):
        if data.msgtype == "sensor_msgs/msg/LaserScan":
            r = np.asarray(m.ranges, float)
            a = m.angle_min + m.angle_increment * np.arange(r.size)
            ok = np.isfinite(r) & (r >= m.range_min) & (r <= m.range_max)
            pts = np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=-1)
        elif data.msgtype == "odin_msgs/msg/RadarSector":
            r = np.asarray(m.ranges, float)
            a = np.asarray(m.bearings, float)
            if r.shape != a.shape:
                raise BagError(path, "radar bearings and ranges differ in length", data.topic, t)
            if not (np.isfinite(r).all() and np.isfinite(a).all()):
                raise BagError(path, "non-finite radar detection (NaN or inf)", data.topic, t)
            pts = np.stack([r * np.cos(a), r * np.sin(a)], axis=-1)
        else:
            pts = _pointcloud2_xy(path, data.topic, t, m)
        hull = np.stack([mx + c * pts[:, 0] - s * pts[:, 1], my + s * pts[:, 0] + c * pts[:, 1]])
        out.append(hull.T.reshape(-1, 2))
    return out


def _pointcloud2_xy(path, topic: str, t: int, msg: Any) -> np.ndarray:
    names = {f.name: f for f in msg.fields}
    if "x" not in names or "y" not in names:
        raise BagError(path, "PointCloud2 without x/y fields", topic, t)
    for n in ("x", "y"):
        if names[n].datatype != 7:  # FLOAT32
            raise BagError(path, f"PointCloud2 field {n} is not float32", topic, t)
    order = ">" if msg.is_bigendian else "<"
    n = int(msg.width) * int(msg.height)
    raw = np.asarray(msg.data, np.uint8).tobytes()
    dtype = np.dtype(
        {
            "names": ["x", "y"],
            "formats": [order + "f4", order + "f4"],
            "offsets": [names["x"].offset, names["y"].offset],
            "itemsize": int(msg.point_step),
        }
    )
    pts = np.frombuffer(raw, dtype=dtype, count=n)
    xy = np.stack([pts["x"], pts["y"]], axis=-1).astype(np.float64)
    return xy[np.isfinite(xy).all(axis=1)]


# --------------------------------------------------------------------------------------------
# Resampling on the grid
# --------------------------------------------------------------------------------------------


def interpolate(sig: Signal, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of ``sig`` at ``grid: [K]`` ns -> (values [K, k], valid [K]).

    A grid point is valid when it lies between two samples at most ``max_gap`` apart (or on a
    sample); nothing is extrapolated.
    """
    t, v = sig.t, sig.v
    K = grid.size
    out = np.zeros((K, v.shape[1]))
    valid = np.zeros(K, bool)
    if t.size == 0:
        return out, valid
    hi = np.searchsorted(t, grid, side="left")
    exact = (hi < t.size) & (t[np.minimum(hi, t.size - 1)] == grid)
    lo = np.clip(hi - 1, 0, t.size - 1)
    hi_c = np.clip(hi, 0, t.size - 1)
    inside = (hi > 0) & (hi < t.size)
    gap = (t[hi_c] - t[lo]) * 1e-9
    valid = exact | (inside & (gap <= sig.max_gap + 1e-9))
    span = np.maximum(t[hi_c] - t[lo], 1)
    w = np.where(inside, (grid - t[lo]) / span, 0.0)[:, None]
    out = np.where(exact[:, None], v[hi_c], (1.0 - w) * v[lo] + w * v[hi_c])
    return out, valid


def hold(sig: Signal, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order hold of ``sig`` at ``grid: [K]`` -> (values [K, k], valid [K]).

    Valid from the first sample on; with ``max_gap > 0`` a value older than that is invalid.
    """
    idx = np.searchsorted(sig.t, grid, side="right") - 1
    valid = idx >= 0
    values = (
        sig.v[np.clip(idx, 0, max(sig.t.size - 1, 0))]
        if sig.t.size
        else np.zeros((grid.size, sig.v.shape[1]))
    )
    if sig.max_gap > 0 and sig.t.size:
        age = (grid - sig.t[np.clip(idx, 0, sig.t.size - 1)]) * 1e-9
        valid &= age <= sig.max_gap + 1e-9
    return values, valid


def time_grid(t_start: int, t_end: int, dt: float) -> np.ndarray:
    """Every whole multiple of ``dt`` (in bag time, ns) within [t_start, t_end]: [K] int64."""
    step = round(dt * NS)
    first = -(-t_start // step) * step
    return np.arange(first, t_end + 1, step, dtype=np.int64)


def first_order_lag(cmd: np.ndarray, x0: np.ndarray, dt: float, tau: np.ndarray) -> np.ndarray:
    """Actuator states [K, k] of the lag s' = c + (s - c) exp(-dt/tau) driven by cmd: [K, k]."""
    decay = np.exp(-dt / np.asarray(tau, float))
    out = np.empty_like(cmd)
    s = np.asarray(x0, float)
    for k in range(cmd.shape[0]):
        out[k] = s
        s = cmd[k] + (s - cmd[k]) * decay
    return out


# --------------------------------------------------------------------------------------------
# Segmentation
# --------------------------------------------------------------------------------------------


def parse_marker(text: str) -> tuple[str, dict[str, str]]:
    """``"start set=2 pole=green"`` -> ("start", {"set": "2", "pole": "green"})."""
    parts = text.split()
    kind = parts[0].lower() if parts else ""
    info = dict(p.split("=", 1) for p in parts[1:] if "=" in p)
    return kind, info


def segments_from_markers(path, data: TopicMessages) -> list[tuple[int, int, dict]]:
    """(start ns, end ns, info) per ``start``/``end`` pair; unmatched markers are errors."""
    _require_type(path, data.topic, data, MARKER_TYPES, "markers")
    out, open_at, info = [], None, {}
    for m, t in zip(data.msgs, data.stamp_ns, strict=True):
        kind, kv = parse_marker(m.data)
        if kind == "start":
            if open_at is not None:
                raise BagError(path, "episode start marker inside an open episode", data.topic, t)
            open_at, info = int(t), kv
        elif kind == "end":
            if open_at is None:
                raise BagError(path, "episode end marker without a start", data.topic, t)
            out.append((open_at, int(t), info))
            open_at = None
    if open_at is not None:
        raise BagError(path, "episode start marker without an end", data.topic, open_at)
    return out


def segments_from_rules(
    position: Signal, velocity: Signal | None, rules: SegmentRules, obstacle_xy=None
) -> list[tuple[int, int, dict]]:
    """(start ns, end ns, {}) of the stretches where the boat is underway (see SegmentRules)."""
    t, p = position.t, position.v
    if t.size < 2:
        return []
    if velocity is not None and velocity.t.size:
        vel, _ = interpolate(Signal("", velocity.t, velocity.v, np.inf), t)
        speed = np.linalg.norm(vel, axis=1)
    else:
        dtp = np.maximum(np.diff(t) * 1e-9, 1e-9)
        v = np.linalg.norm(np.diff(p, axis=0), axis=1) / dtp
        speed = np.concatenate([v[:1], v])
    moving = speed >= rules.min_speed
    gaps = np.diff(t) * 1e-9 > rules.split_gap_s
    segs = []
    start = None
    last_moving = None
    for i in range(t.size):
        if i > 0 and gaps[i - 1] and start is not None:
            segs.append((start, last_moving))
            start = None
        if moving[i]:
            if start is None:
                start = t[i]
            elif (t[i] - last_moving) * 1e-9 > rules.bridge_s:
                segs.append((start, last_moving))
                start = t[i]
            last_moving = t[i]
    if start is not None:
        segs.append((start, last_moving))
    out = []
    for a, b in segs:
        if rules.min_obstacle_distance is not None and obstacle_xy is not None:
            sel = (t >= a) & (t <= b)
            if np.min(np.linalg.norm(p[sel] - obstacle_xy, axis=1)) > rules.min_obstacle_distance:
                continue
        out.append((int(a), int(b), {}))
    return out


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


def ingest_bag(
    path: str | os.PathLike, topic_map: TopicMap | None = None, config: IngestConfig | None = None
) -> list[Episode]:
    """All episodes of one bag, on the grid (see the module docstring)."""
    from diffgcl.sim import hull

    path = Path(path)
    tm = topic_map or default_topic_map()
    cfg = config or IngestConfig()
    with open_bag(path) as reader:
        present = {c.topic for c in reader.connections}
        bag_start = reader.start_time if reader.connections else None
    roles = tm.topics()
    for role in ("position", "heading", "commands"):
        if roles[role] not in present:
            raise BagError(path, f"missing required topic for {role}", roles[role], bag_start)
    data = {
        topic: order_by_stamp(path, msgs)
        for topic, msgs in read_topics(path, set(roles.values())).items()
    }
    for role in ("position", "heading", "commands"):
        if not data[roles[role]].msgs:
            raise BagError(path, f"required topic for {role} has no messages", roles[role])

    position, datum = decode_position(path, data[tm.position.topic], tm.position.max_gap, tm.datum)
    heading, yaw_rate = decode_heading(path, data[tm.heading.topic], tm.heading.max_gap)
    commands = decode_commands(path, data[tm.commands.topic], tm.commands, "commands")
    velocity = None
    if tm.velocity is not None and tm.velocity.topic in data:
        velocity = decode_velocity(path, data[tm.velocity.topic], tm.velocity.max_gap)
    actuators = None
    if tm.actuators is not None and tm.actuators.topic in data:
        actuators = decode_commands(path, data[tm.actuators.topic], tm.actuators, "actuators")
    obstacle_sig = None
    if tm.obstacle is not None and tm.obstacle.topic in data:
        obstacle_sig = _decode_obstacle(path, data[tm.obstacle.topic], datum)

    bag_warnings: list[str] = []
    scans: dict[str, tuple[Signal, list[np.ndarray]] | None] = {}
    for role, spec in (("lidar", tm.lidar), ("radar", tm.radar)):
        if spec is None:
            scans[role] = None
            continue
        if spec.topic not in data or not data[spec.topic].msgs:
            _warn(
                bag_warnings,
                f"{path}: topic {spec.topic}: optional {role} missing; its beams read no return",
            )
            scans[role] = None
            continue
        d = data[spec.topic]
        pts = scan_points(path, d, spec) if cfg.observations else []
        index = np.arange(d.stamp_ns.size, dtype=float)[:, None]
        scans[role] = (Signal(spec.topic, d.stamp_ns, index, spec.max_gap), pts)

    if tm.markers is not None and tm.markers.topic in data and data[tm.markers.topic].msgs:
        segments = segments_from_markers(path, data[tm.markers.topic])
        segmentation = "markers"
    else:
        obstacle_xy = None if obstacle_sig is None else obstacle_sig.v.mean(axis=0)
        segments = segments_from_rules(position, velocity, cfg.segment, obstacle_xy)
        segmentation = "rules"
    if not segments:
        raise BagError(
            path, "no episode found (no markers, boat never underway)", tm.position.topic
        )

    episodes: list[Episode] = []
    too_short: list[BagError] = []
    for index, (t_a, t_b, info) in enumerate(segments):
        grid = time_grid(t_a, t_b, cfg.dt)
        ep_warnings = list(bag_warnings)
        pos, ok_p = interpolate(position, grid)
        psi, ok_h = interpolate(heading, grid)
        if velocity is not None:
            vel, ok_v = interpolate(velocity, grid)
        else:
            vel = np.gradient(pos, cfg.dt, axis=0) if grid.size > 1 else np.zeros_like(pos)
            # np.gradient: central differences inside, one-sided at the ends.
            before = np.concatenate([ok_p[:1], ok_p[:-1]])
            after = np.concatenate([ok_p[1:], ok_p[-1:]])
            ok_v = ok_p & before & after
        if yaw_rate is not None:
            rate, ok_r = interpolate(yaw_rate, grid)
        else:
            rate = np.gradient(psi[:, 0], cfg.dt)[:, None]
            ok_r = ok_h
        cmd, ok_c = hold(commands, grid)
        if actuators is not None:
            act, ok_a = interpolate(actuators, grid)
        else:
            act = first_order_lag(cmd, cmd[0], cfg.dt, (cfg.tau_thrust, cfg.tau_nozzle))
            ok_a = ok_c
        if obstacle_sig is not None:
            sel = (obstacle_sig.t >= t_a) & (obstacle_sig.t <= t_b)
            vals = obstacle_sig.v[sel] if sel.any() else obstacle_sig.v
            obs_xy = np.broadcast_to(vals.mean(axis=0), (grid.size, 2))
        else:
            est = _obstacle_from_scans(scans, position, heading, t_a, t_b)
            if est is None:
                raise BagError(
                    path,
                    "no obstacle position (no obstacle topic and no range-sensor detections)",
                    tm.obstacle.topic if tm.obstacle is not None else None,
                    t_a,
                )
            _warn(ep_warnings, f"{path}: episode {index}: obstacle position estimated from scans")
            obs_xy = np.broadcast_to(est, (grid.size, 2))
        valid = ok_p & ok_h & ok_v & ok_r & ok_c & ok_a
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
            too_short.append(short)
            continue
        if not valid.all():
            _warn(
                ep_warnings,
                f"{path}: episode {index}: {int((~valid).sum())} of {valid.size} steps masked "
                f"(dropouts) from t={grid[np.argmin(valid)] * 1e-9:.3f}s",
            )
        X = np.zeros((grid.size, hull.DX))
        X[:, hull.IX_PX : hull.IX_PY + 1] = pos
        X[:, hull.IX_PSI] = psi[:, 0]
        X[:, hull.IX_VX : hull.IX_VY + 1] = vel
        X[:, hull.IX_R] = rate[:, 0]
        X[:, hull.SL_ACT] = act
        X[:, hull.SL_OBS] = obs_xy
        U = cmd[:-1]
        O, obs_meta = _observations(path, grid, X, scans, cfg, ep_warnings)
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
            "swerve_side": swerve_side(X, valid) if obstacle_sig is not None else "unknown",
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
        raise too_short[0]
    return episodes


def _decode_obstacle(path, data: TopicMessages, datum) -> Signal:
    _require_type(path, data.topic, data, OBSTACLE_TYPES, "obstacle")
    if data.msgtype == "sensor_msgs/msg/NavSatFix":
        ll = np.array([[m.latitude, m.longitude] for m in data.msgs]).reshape(-1, 2)
        _check_finite(path, data.topic, data.stamp_ns, ll, "obstacle latitude/longitude")
        if datum is None:
            raise BagError(path, "obstacle given as NavSatFix but no datum", data.topic)
        xy = latlon_to_local(ll[:, 0], ll[:, 1], datum)
    else:
        xy = np.array([[m.point.x, m.point.y] for m in data.msgs]).reshape(-1, 2)
    return _signal(path, data, xy, np.inf, "obstacle position")


def _obstacle_from_scans(scans, position: Signal, heading: Signal, t_a: int, t_b: int):
    """World position [2] of the pole from the scans in [t_a, t_b]: the densest 5 m cell of all
    returns (LiDAR preferred, radar otherwise), averaged over the returns within 5 m of it."""
    for role in ("lidar", "radar"):
        entry = scans.get(role)
        if entry is None:
            continue
        sig, pts = entry
        sel = np.flatnonzero((sig.t >= t_a) & (sig.t <= t_b))
        if sel.size == 0:
            continue
        pose, ok_p = interpolate(position, sig.t[sel])
        psi, ok_h = interpolate(heading, sig.t[sel])
        world = []
        for j, i in enumerate(sel):
            if not (ok_p[j] and ok_h[j]) or len(pts[i]) == 0:
                continue
            c, s = np.cos(psi[j, 0]), np.sin(psi[j, 0])
            p = pts[i]
            world.append(
                pose[j] + np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], 1)
            )
        if not world:
            continue
        w = np.concatenate(world)
        cells, counts = np.unique(np.floor(w / 5.0).astype(np.int64), axis=0, return_counts=True)
        centre = (cells[np.argmax(counts)] + 0.5) * 5.0
        near = np.linalg.norm(w - centre, axis=1) < 5.0
        return w[near].mean(axis=0)
    return None


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


def _observations(path, grid, X, scans, cfg: IngestConfig, ep_warnings) -> tuple[np.ndarray, dict]:
    """O: [K, dO] in the hull env's layout (:func:`diffgcl.envs.hull.observation`):
    LiDAR beams, radar beams, sin ψ, cos ψ, u, v, r.

    Each scan's points (hull frame) are reduced with
    :func:`~diffgcl.sim.sensors.ranges_from_points`; LiDAR points fill the LiDAR beams only and
    radar detections the radar beams only. A step without a recent scan (or a bag without the
    sensor) reads the beams' maximum range, i.e. "no return", and is reported as a warning.
    """
    from diffgcl.sim import hull, sensors

    layout = cfg.sensors if cfg.sensors is not None else sensors.SensorLayout()
    if not cfg.observations:
        return np.zeros((grid.size, 0)), {"lidar": scans.get("lidar") is not None}
    ranges = np.broadcast_to(layout.max_ranges, (grid.size, layout.num_beams)).copy()
    fans = {
        "lidar": slice(0, layout.lidar_beams),
        "radar": slice(layout.lidar_beams, layout.num_beams),
    }
    meta: dict[str, Any] = {}
    for role, fan in fans.items():
        entry = scans.get(role)
        meta[role] = entry is not None
        if entry is None:
            meta[f"{role}_valid_fraction"] = 0.0
            continue
        sig, pts = entry
        idx, ok = hold(sig, grid)
        cache: dict[int, np.ndarray] = {}
        for k in np.flatnonzero(ok):
            i = int(idx[k, 0])
            if i not in cache:
                cache[i] = sensors.ranges_from_points(pts[i], layout)[fan]
            ranges[k, fan] = cache[i]
        meta[f"{role}_valid_fraction"] = float(ok.mean())
        if not ok.all():
            _warn(
                ep_warnings,
                f"{path}: topic {sig.topic}: {int((~ok).sum())} steps without a recent "
                f"{role} scan (no-return ranges used)",
            )
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
) -> DemoSet:
    """Ingest ``paths`` and save the dataset to ``out`` (atomically: all or nothing)."""
    demos = ingest_bags(paths, topic_map, config, progress)
    demos.save(out)
    return demos
