"""Messages -> time-stamped signals, and signals on a time grid (host side, NumPy).

Each role of a :class:`~diffgcl.data.topics.TopicMap` is decoded into a :class:`Signal`
``(t: [n] ns, v: [n, k])`` in the project's frames and SI units:

* *Time.* A message's time is its header stamp (``time_source: header``; the bag time where a
  message has no header) or the bag's receive time (``time_source: receive``), minus the role's
  ``latency``. Times of one topic must not go backwards by more than :data:`MAX_REORDER_S`: an
  error, or with ``bad_stamps: mask`` the messages whose time is off the topic's usual
  stamp-to-receive offset are dropped (the grid steps they would cover are masked later).
* *Frames.* Positions in a local East-North-Up frame (NavSatFix through a local tangent plane at
  the datum; Odometry in ``enu`` or ``ned``), heading ψ about Up from East (unwrapped), yaw rate
  about Up, velocities in the local frame; body frame x forward, y to port.
* *Units.* Commands and actuator feedback in N and rad (positive nozzle turns the bow to port),
  converted by :meth:`~diffgcl.data.topics.CommandSpec.to_si`.

On the grid: :func:`interpolate` (linear, never across a gap longer than ``max_gap``),
:func:`hold` (zero-order hold of on-change commands) and :func:`first_order_lag`.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from diffgcl.data.bags import BagError, IngestWarning, TopicMessages
from diffgcl.data.scans import message_fields
from diffgcl.data.topics import CommandSpec, SignalSpec, TopicSpec

NS = 1_000_000_000

# WGS-84 ellipsoid, for the local tangent plane of lat/lon positions.
_WGS84_A = 6378137.0
_WGS84_F = 1.0 / 298.257223563
_WGS84_E2 = _WGS84_F * (2.0 - _WGS84_F)

# Message types each role accepts.
POSITION_TYPES = ("nav_msgs/msg/Odometry", "sensor_msgs/msg/NavSatFix")
HEADING_TYPES = ("sensor_msgs/msg/Imu", "nav_msgs/msg/Odometry")
VELOCITY_TYPES = ("nav_msgs/msg/Odometry",)
OBSTACLE_TYPES = ("sensor_msgs/msg/NavSatFix", "geometry_msgs/msg/PointStamped")

# Header stamps may arrive slightly out of order (transport jitter); a step back larger than this
# is a clock jump or a corrupt stamp, i.e. "time going backwards".
MAX_REORDER_S = 0.5


@dataclass(frozen=True)
class Signal:
    """A decoded signal: t: [n] int64 ns (sorted), v: [n, k] float64, max_gap: s."""

    topic: str
    t: np.ndarray
    v: np.ndarray
    max_gap: float


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


def _radii(lat0_deg: float) -> tuple[float, float]:
    lat0 = np.deg2rad(lat0_deg)
    s2 = np.sin(lat0) ** 2
    rn = _WGS84_A / np.sqrt(1.0 - _WGS84_E2 * s2)
    rm = rn * (1.0 - _WGS84_E2) / (1.0 - _WGS84_E2 * s2)
    return rn * np.cos(lat0), rm


def latlon_to_local(lat, lon, datum: tuple[float, float]) -> np.ndarray:
    """Local East-North (m) of WGS-84 ``lat, lon`` (deg, [n]) around ``datum`` -> [n, 2].

    Local tangent plane with the ellipsoid's meridional and prime-vertical radii at the datum;
    exact to a few mm within a few km, plenty for one harbour.
    """
    re, rm = _radii(datum[0])
    east = np.deg2rad(np.asarray(lon, float) - datum[1]) * re
    north = np.deg2rad(np.asarray(lat, float) - datum[0]) * rm
    return np.stack([east, north], axis=-1)


def local_to_latlon(xy, datum: tuple[float, float]) -> np.ndarray:
    """Inverse of :func:`latlon_to_local`: xy: [n, 2] (m) -> [n, 2] (lat, lon deg)."""
    xy = np.asarray(xy, float)
    re, rm = _radii(datum[0])
    lat = datum[0] + np.rad2deg(xy[..., 1] / rm)
    lon = datum[1] + np.rad2deg(xy[..., 0] / re)
    return np.stack([lat, lon], axis=-1)


def quaternion_yaw(x, y, z, w) -> np.ndarray:
    """Yaw (rad, about +z) of quaternions given component-wise ([n] each)."""
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def ned_yaw_to_enu(yaw_ned):
    """Heading clockwise from North (NED/FRD) -> counter-clockwise from East (ENU/FLU)."""
    return np.pi / 2 - np.asarray(yaw_ned, float)


# --------------------------------------------------------------------------------------------
# Message times
# --------------------------------------------------------------------------------------------


def message_times(
    path, data: TopicMessages, spec: TopicSpec, role: str
) -> tuple[TopicMessages, str | None]:
    """(``data`` with ``stamp_ns`` replaced by the times ingestion uses for ``role`` (time source
    minus latency), sorted; a warning when messages with broken times were dropped, else None).
    See the module docstring for bad stamps."""
    t = (data.stamp_ns if spec.time_source == "header" else data.bag_ns).copy()
    t -= int(round(spec.latency * NS))
    keep = np.ones(t.size, bool)
    note = None
    back = _backwards(t)
    if back is not None and spec.bad_stamps == "mask":
        offset = t - data.bag_ns
        keep = np.abs(offset - np.median(offset)) <= MAX_REORDER_S * NS
        dropped = np.flatnonzero(~keep)
        if dropped.size:
            note = (
                f"{path}: topic {data.topic}: {dropped.size} messages with broken "
                f"{spec.time_source} times dropped ({role}.bad_stamps: mask), received between "
                f"t={data.bag_ns[dropped[0]] * 1e-9:.3f}s and "
                f"t={data.bag_ns[dropped[-1]] * 1e-9:.3f}s"
            )
        back = _backwards(t[keep])
    if back is not None:
        i, latest = back
        bag_ns = data.bag_ns[keep]
        raise BagError(
            path,
            f"time goes backwards ({spec.time_source} time {t[keep][i] * 1e-9:.3f}s after "
            f"{latest * 1e-9:.3f}s); set {role}.time_source: receive, or {role}.bad_stamps: mask "
            "in the topic map",
            data.topic,
            bag_ns[i],
        )
    idx = np.flatnonzero(keep)
    idx = idx[np.argsort(t[idx], kind="stable")]
    timed = TopicMessages(
        data.topic, data.msgtype, data.bag_ns[idx], t[idx], tuple(data.msgs[i] for i in idx)
    )
    return timed, note


def _backwards(t: np.ndarray) -> tuple[int, int] | None:
    """(index, latest time before it) of the first time more than MAX_REORDER_S behind the
    latest one seen so far, or None."""
    if t.size < 2:
        return None
    latest = np.maximum.accumulate(t)
    back = np.flatnonzero(latest[:-1] - t[1:] > MAX_REORDER_S * NS)
    if not back.size:
        return None
    return int(back[0] + 1), int(latest[back[0]])


# --------------------------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------------------------


def field_value(path, data: TopicMessages, msg: Any, dotted: str, key: str) -> Any:
    """``msg.a.b`` for ``dotted = "a.b"``; a missing field is a :class:`BagError` that lists the
    fields there and names the topic-map ``key`` to fix."""
    value = msg
    parts = dotted.split(".")
    for depth, part in enumerate(parts):
        if not hasattr(value, part) or part.startswith("_"):
            where = data.msgtype if depth == 0 else f"{'.'.join(parts[:depth])} of {data.msgtype}"
            have = ", ".join(message_fields(value)) or "none"
            raise BagError(
                path,
                f"no field {dotted!r}: {where} has fields {have}; set {key} in the topic map",
                data.topic,
                data.bag_ns[0] if data.bag_ns.size else None,
            )
        value = getattr(value, part)
    return value


def _check_finite(path, topic: str, t: np.ndarray, v: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(v.reshape(len(t), -1)).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise BagError(path, f"non-finite {what} (NaN or inf)", topic, t[i])


def require_type(path, data: TopicMessages, allowed: Sequence[str], role: str) -> None:
    """A :class:`BagError` unless the topic's type is one ``role`` can decode."""
    if data.msgtype not in allowed:
        t0 = data.bag_ns[0] if data.bag_ns.size else None
        raise BagError(
            path,
            f"unknown message type {data.msgtype} for {role} (supported: {', '.join(allowed)})",
            data.topic,
            t0,
        )


def _signal(path, data: TopicMessages, values: np.ndarray, max_gap: float, what: str) -> Signal:
    t = data.stamp_ns
    _check_finite(path, data.topic, t, values, what)
    return Signal(data.topic, t, values.reshape(len(t), -1).astype(np.float64), max_gap)


def _subset(data: TopicMessages, keep: np.ndarray) -> TopicMessages:
    return TopicMessages(
        data.topic,
        data.msgtype,
        data.bag_ns[keep],
        data.stamp_ns[keep],
        tuple(m for m, k in zip(data.msgs, keep, strict=True) if k),
    )


def decode_position(path, data: TopicMessages, spec: SignalSpec, datum) -> tuple[Signal, tuple]:
    """Position [n, 2] in the local ENU frame; returns (signal, datum used)."""
    require_type(path, data, POSITION_TYPES, "position")
    if data.msgtype == "nav_msgs/msg/Odometry":
        xy = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for m in data.msgs])
        xy = xy.reshape(-1, 2)
        if spec.frame == "ned":
            xy = xy[:, ::-1]  # (north, east) -> (east, north)
        return _signal(path, data, xy, spec.max_gap, "position"), datum
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
    return _signal(path, _subset(data, fix), xy[fix], spec.max_gap, "position"), datum


def _orientation(m: Any) -> list[float]:
    o = m.orientation
    return [o.x, o.y, o.z, o.w]


def decode_heading(path, data: TopicMessages, spec: SignalSpec) -> tuple[Signal, Signal]:
    """Unwrapped heading [n, 1] (about Up from East) and yaw rate [n, 1] (about Up)."""
    require_type(path, data, HEADING_TYPES, "heading")
    if data.msgtype == "sensor_msgs/msg/Imu":
        q = np.array([_orientation(m) for m in data.msgs]).reshape(-1, 4)
        rate = np.array([m.angular_velocity.z for m in data.msgs], float)
    else:
        q = np.array([_orientation(m.pose.pose) for m in data.msgs]).reshape(-1, 4)
        rate = np.array([m.twist.twist.angular.z for m in data.msgs], float)
    _check_finite(path, data.topic, data.stamp_ns, q, "orientation")
    yaw = quaternion_yaw(q[:, 0], q[:, 1], q[:, 2], q[:, 3])
    if spec.frame == "ned":
        yaw, rate = ned_yaw_to_enu(yaw), -rate
    heading = _signal(path, data, np.unwrap(yaw), spec.max_gap, "heading")
    return heading, _signal(path, data, rate, spec.max_gap, "yaw rate")


def decode_velocity(path, data: TopicMessages, spec: SignalSpec) -> Signal:
    """Local-frame velocity [n, 2] from an Odometry twist (body frame, rotated by its own
    orientation)."""
    require_type(path, data, VELOCITY_TYPES, "velocity")
    a = np.array(
        [
            [m.twist.twist.linear.x, m.twist.twist.linear.y, *_orientation(m.pose.pose)]
            for m in data.msgs
        ],
        float,
    ).reshape(-1, 6)
    yaw = quaternion_yaw(a[:, 2], a[:, 3], a[:, 4], a[:, 5])
    u, v = a[:, 0], a[:, 1]
    if spec.frame == "ned":
        yaw, v = ned_yaw_to_enu(yaw), -v  # body y to starboard -> to port
    c, s = np.cos(yaw), np.sin(yaw)
    world = np.stack([c * u - s * v, s * u + c * v], axis=-1)
    return _signal(path, data, world, spec.max_gap, "velocity")


def decode_commands(path, data: TopicMessages, spec: CommandSpec, role: str) -> Signal:
    """[thrust (N), nozzle (rad, positive to port)]: [n, 2] from the two configured fields."""
    raw = np.zeros((len(data.msgs), 2))
    for i, m in enumerate(data.msgs):
        for j, (name, key) in enumerate(
            ((spec.thrust_field, "thrust_field"), (spec.nozzle_field, "nozzle_field"))
        ):
            value = field_value(path, data, m, name, f"{role}.{key}")
            try:
                raw[i, j] = float(value)
            except (TypeError, ValueError):
                raise BagError(
                    path,
                    f"field {name!r} of {data.msgtype} is not a number ({type(value).__name__}); "
                    f"set {role}.{key} in the topic map",
                    data.topic,
                    data.bag_ns[i],
                ) from None
    thrust, nozzle = spec.to_si(raw[:, 0], raw[:, 1])
    return _signal(path, data, np.stack([thrust, nozzle], axis=1), spec.max_gap, role)


def decode_obstacle(path, data: TopicMessages, datum) -> Signal:
    """Surveyed obstacle position [n, 2] in the local frame (NavSatFix or PointStamped)."""
    require_type(path, data, OBSTACLE_TYPES, "obstacle")
    if data.msgtype == "sensor_msgs/msg/NavSatFix":
        ll = np.array([[m.latitude, m.longitude] for m in data.msgs]).reshape(-1, 2)
        _check_finite(path, data.topic, data.stamp_ns, ll, "obstacle latitude/longitude")
        if datum is None:
            raise BagError(path, "obstacle given as NavSatFix but no datum", data.topic)
        xy = latlon_to_local(ll[:, 0], ll[:, 1], datum)
    else:
        xy = np.array([[m.point.x, m.point.y] for m in data.msgs]).reshape(-1, 2)
    return _signal(path, data, xy, np.inf, "obstacle position")


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


def gap_spans(sig: Signal, grid: np.ndarray, ok: np.ndarray) -> list[tuple[int, int, str]]:
    """Runs of invalid grid steps of one signal: (first step, last step, what the messages did
    there), longest first. ``ok``: [K] validity of ``sig`` on ``grid``."""
    bad = ~np.asarray(ok, bool)
    if not bad.any():
        return []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], bad.astype(int), [0]])))
    spans = []
    for a, b in zip(edges[::2], edges[1::2] - 1, strict=True):
        i = np.searchsorted(sig.t, grid[a], side="right") - 1
        j = np.searchsorted(sig.t, grid[b], side="left")
        if i < 0:
            what = f"no messages before t={sig.t[0] * 1e-9:.3f}s" if sig.t.size else "no messages"
        elif j >= sig.t.size:
            what = f"no messages after t={sig.t[-1] * 1e-9:.3f}s"
        else:
            gap = (sig.t[j] - sig.t[i]) * 1e-9
            what = f"{gap:.1f} s without messages from t={sig.t[i] * 1e-9:.3f}s"
        spans.append((int(a), int(b), what))
    return sorted(spans, key=lambda s: s[0] - s[1])
