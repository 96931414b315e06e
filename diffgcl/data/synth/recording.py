"""What the synthetic sensors publish: every message of a stretch of a bag's timeline (an
episode or a repositioning leg, :class:`Recording`) from the simulated states, with the
rates, noise and latencies of :class:`~diffgcl.data.synth.config.SensorModel` (the topics and
their noise: :mod:`diffgcl.data.synth.config`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from diffgcl.data.bags import BagWriter
from diffgcl.data.signals import local_to_latlon
from diffgcl.data.synth.config import LAYOUT_TOPICS, NS, OTHER_BOAT_FULL_THRUST, SensorModel
from diffgcl.data.synth.operator_model import hull_dt, wrap_angle


def _sample_times(rng, t0: float, t1: float, hz: float) -> np.ndarray:
    """Sample times (s, relative) at ``hz`` with a random phase in [t0, t1]."""
    period = 1.0 / hz
    first = t0 + rng.uniform(0.0, period)
    return np.arange(first, t1, period)


def _state_at(X: np.ndarray, U: np.ndarray, dt: float, s: np.ndarray, taus) -> np.ndarray:
    """True state at times ``s`` (s from the first step): [m, dX].

    Position and heading by cubic Hermite interpolation with the velocities, velocities linearly,
    actuator states by the exact first-order response to the held command.
    """
    from diffgcl.sim import hull

    K = U.shape[0]
    k = np.clip(np.floor(s / dt).astype(int), 0, K - 1)
    h = np.clip(s / dt - k, 0.0, 1.0)
    a, b = X[k], X[k + 1]
    out = a + h[:, None] * (b - a)
    for ip, iv in ((hull.IX_PX, hull.IX_VX), (hull.IX_PY, hull.IX_VY), (hull.IX_PSI, hull.IX_R)):
        h2, h3 = h * h, h * h * h
        out[:, ip] = (
            (2 * h3 - 3 * h2 + 1) * a[:, ip]
            + (h3 - 2 * h2 + h) * dt * a[:, iv]
            + (-2 * h3 + 3 * h2) * b[:, ip]
            + (h3 - h2) * dt * b[:, iv]
        )
    c = U[k]
    decay = np.exp(-(h * dt)[:, None] / np.asarray(taus)[None, :])
    out[:, hull.SL_ACT] = c + (a[:, hull.SL_ACT] - c) * decay
    return out


def _quat(yaw) -> dict[str, float]:
    return {"x": 0.0, "y": 0.0, "z": float(np.sin(yaw / 2)), "w": float(np.cos(yaw / 2))}


def _lidar_ranges(rng, state, poles, sm: SensorModel) -> np.ndarray:
    """LaserScan ranges [beams] (inf = no return) of a 360° scan from the mast; poles: visible
    ((x, y), radius) pairs."""
    from diffgcl.sim import hull

    psi = state[hull.IX_PSI]
    c, s = np.cos(psi), np.sin(psi)
    mx, my, myaw = sm.lidar_mount
    origin = state[hull.IX_PX : hull.IX_PY + 1] + np.array([c * mx - s * my, s * mx + c * my])
    angles = -np.pi + np.arange(sm.lidar_beams) * (2 * np.pi / sm.lidar_beams)
    world = psi + myaw + angles
    d = np.stack([np.cos(world), np.sin(world)], axis=1)
    r = np.full(sm.lidar_beams, np.inf)
    for pole, radius in poles:
        rel = np.asarray(pole) - origin
        proj = d @ rel
        disc = proj**2 - (rel @ rel - radius**2)
        hit = (disc >= 0) & (proj > 0)
        r = np.minimum(r, np.where(hit, proj - np.sqrt(np.maximum(disc, 0.0)), np.inf))
    r = r + rng.normal(0.0, sm.lidar_noise, r.shape)
    r[(r > sm.lidar_range) | (rng.uniform(size=r.shape) < sm.lidar_dropout)] = np.inf
    return r.astype(np.float32)


def _radar_detections(rng, state, poles, sm: SensorModel):
    """(bearings, ranges, intensities) of one sweep in the radar frame: each visible pole
    (prob. Pd each), far clutter, and sea clutter near the boat."""
    from diffgcl.sim import hull

    psi = state[hull.IX_PSI]
    c, s = np.cos(psi), np.sin(psi)
    mx, my, myaw = sm.radar_mount
    origin = state[hull.IX_PX : hull.IX_PY + 1] + np.array([c * mx - s * my, s * mx + c * my])
    bearings, ranges, power = [], [], []
    for pole, _ in poles:
        rel = np.asarray(pole) - origin
        rng_true = float(np.hypot(*rel))
        brg_true = float(wrap_angle(np.arctan2(rel[1], rel[0]) - psi - myaw))
        if rng_true < sm.radar_range and rng.uniform() < sm.radar_pd:
            bearings.append(brg_true + rng.normal(0.0, sm.radar_bearing_noise))
            ranges.append(max(rng_true + rng.normal(0.0, sm.radar_range_noise), 1.0))
            power.append(rng.uniform(*sm.radar_pole_intensity))
    for _ in range(rng.poisson(sm.radar_clutter)):
        bearings.append(rng.uniform(-np.pi, np.pi))
        ranges.append(rng.uniform(20.0, 0.6 * sm.radar_range))
        power.append(rng.uniform(0.05, 0.5))
    if sm.sea_clutter > 0:
        n = rng.poisson(sm.sea_clutter)
        bearings.extend(rng.uniform(-np.pi, np.pi, n))
        ranges.extend(2.0 + rng.exponential(sm.sea_clutter_range, n))
        power.extend(rng.uniform(*sm.sea_clutter_intensity, n))
    f32 = lambda v: np.asarray(v, np.float32)
    return f32(bearings), f32(ranges), f32(power)


def _pointcloud2(w: BagWriter, h, bearings, ranges, intensities):
    """A sensor_msgs/PointCloud2 with float32 x, y, z, intensity (16-byte points)."""
    n = len(ranges)
    pts = np.zeros((n, 4), np.float32)
    pts[:, 0] = ranges * np.cos(bearings)
    pts[:, 1] = ranges * np.sin(bearings)
    pts[:, 3] = intensities
    fields = [
        w.make("sensor_msgs/msg/PointField", name=name, offset=4 * k, datatype=7, count=1)
        for k, name in enumerate(("x", "y", "z", "intensity"))
    ]
    return w.make(
        "sensor_msgs/msg/PointCloud2",
        header=h,
        height=1,
        width=n,
        fields=fields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * n,
        data=np.frombuffer(pts.astype("<f4").tobytes(), np.uint8),
        is_dense=True,
    )


@dataclass(frozen=True)
class Recording:
    """One stretch of a bag's timeline as the sensors record it (an episode or a repositioning
    leg): t: [K+1] int64 ns, X: [K+1, dX], U: [K, dU]; poles: the visible ((x, y), radius);
    obstacle: the surveyed pole published on the obstacle topic (None: none); markers: (ns,
    text) episode markers."""

    t: np.ndarray
    X: np.ndarray
    U: np.ndarray
    poles: tuple[tuple[tuple[float, float], float], ...]
    obstacle: tuple[float, float] | None
    markers: tuple[tuple[int, str], ...]


def episode_messages(
    w: BagWriter,
    rec: Recording,
    lidar: bool,
    sm: SensorModel,
    datum: tuple[float, float],
    rng: np.random.Generator,
    taus: tuple[float, float],
    layout: str = "odin",
    glitch: tuple[str, int, int, int] | None = None,
) -> list[tuple[int, str, str, Any]]:
    """All messages of one recording as (bag ns, topic, type, message), unsorted.

    glitch: (topic, first ns, end ns, jump ns): header stamps of ``topic`` sampled in
    [first, end) are ``jump`` ns early.
    """
    from diffgcl.sim import hull

    topics = LAYOUT_TOPICS[layout]
    ned_odom = layout == "other"
    dt = hull_dt()
    X, U, t_ns = rec.X, rec.U, rec.t
    t0_ns = int(t_ns[0])
    dur = U.shape[0] * dt
    msgs: list[tuple[int, str, str, Any]] = []

    def emit(role, msgtype, stamp_s, build, lag_s: float = 0.0):
        topic = topics[role]
        stamp = t0_ns + int(round(stamp_s * NS))
        lag = sm.latency_s + abs(rng.normal(0.0, sm.jitter_s))
        published = stamp + int(round(lag_s * NS))
        header_stamp = published
        if glitch is not None and topic == glitch[0] and glitch[1] <= stamp < glitch[2]:
            header_stamp -= glitch[3]
        msgs.append(
            (published + int(lag * NS), topic, msgtype, build(w.header(header_stamp, "odin")))
        )

    def states(hz):
        s = _sample_times(rng, 0.0, dur, hz)
        return s, _state_at(X, U, dt, s, taus)

    s, st = states(sm.odom_hz)
    for si, x in zip(s, st, strict=True):
        c, sn = np.cos(x[hull.IX_PSI]), np.sin(x[hull.IX_PSI])
        u_b = c * x[hull.IX_VX] + sn * x[hull.IX_VY]
        v_b = -sn * x[hull.IX_VX] + c * x[hull.IX_VY]
        noise = rng.normal(0.0, 1.0, 5)

        def odom(h, x=x, u_b=u_b, v_b=v_b, noise=noise):
            yaw = x[hull.IX_PSI] + sm.odom_yaw * noise[2]
            px = float(x[hull.IX_PX] + sm.odom_pos * noise[0])
            py = float(x[hull.IX_PY] + sm.odom_pos * noise[1])
            vx, vy = float(u_b + sm.odom_vel * noise[3]), float(v_b + sm.odom_vel * noise[4])
            r = float(x[hull.IX_R])
            if ned_odom:  # x north, y east, z down; body x forward, y starboard
                px, py, yaw, vy, r = py, px, np.pi / 2 - yaw, -vy, -r
            pose = w.make(
                "geometry_msgs/msg/Pose",
                position=w.make("geometry_msgs/msg/Point", x=px, y=py, z=0.0),
                orientation=w.make("geometry_msgs/msg/Quaternion", **_quat(yaw)),
            )
            twist = w.make(
                "geometry_msgs/msg/Twist",
                linear=w.make("geometry_msgs/msg/Vector3", x=vx, y=vy, z=0.0),
                angular=w.make("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=r),
            )
            h.frame_id = "odin_local" if not ned_odom else "ned"
            return w.make(
                "nav_msgs/msg/Odometry",
                header=h,
                child_frame_id="base_link",
                pose=w.make(
                    "geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=np.zeros(36)
                ),
                twist=w.make(
                    "geometry_msgs/msg/TwistWithCovariance", twist=twist, covariance=np.zeros(36)
                ),
            )

        emit("odom", "nav_msgs/msg/Odometry", si, odom)

    s, st = states(sm.imu_hz)
    for si, x in zip(s, st, strict=True):
        noise = rng.normal(0.0, 1.0, 2)

        def imu(h, x=x, noise=noise):
            zero3 = w.make("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
            return w.make(
                "sensor_msgs/msg/Imu",
                header=h,
                orientation=w.make(
                    "geometry_msgs/msg/Quaternion", **_quat(x[hull.IX_PSI] + sm.imu_yaw * noise[0])
                ),
                orientation_covariance=np.zeros(9),
                angular_velocity=w.make(
                    "geometry_msgs/msg/Vector3",
                    x=0.0,
                    y=0.0,
                    z=float(x[hull.IX_R] + sm.imu_rate * noise[1]),
                ),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=zero3,
                linear_acceleration_covariance=np.zeros(9),
            )

        emit("imu", "sensor_msgs/msg/Imu", si, imu)

    def fix_msg(h, latlon):
        return w.make(
            "sensor_msgs/msg/NavSatFix",
            header=h,
            status=w.make("sensor_msgs/msg/NavSatStatus", status=0, service=1),
            latitude=float(latlon[0]),
            longitude=float(latlon[1]),
            altitude=0.0,
            position_covariance=np.zeros(9),
            position_covariance_type=0,
        )

    s, st = states(sm.gps_hz)
    ll = local_to_latlon(
        st[:, hull.IX_PX : hull.IX_PY + 1] + rng.normal(0.0, sm.gps_pos, (len(s), 2)), datum
    )
    for si, lat_lon in zip(s, ll, strict=True):
        emit(
            "gps",
            "sensor_msgs/msg/NavSatFix",
            si,
            lambda h, v=lat_lon: fix_msg(h, v),
            lag_s=sm.gps_latency_s,
        )

    if rec.obstacle is not None:
        s = _sample_times(rng, 0.0, dur, sm.obstacle_hz)
        ll = local_to_latlon(
            np.asarray(rec.obstacle) + rng.normal(0.0, sm.obstacle_pos, (len(s), 2)), datum
        )
        for si, lat_lon in zip(s, ll, strict=True):
            emit("obstacle", "sensor_msgs/msg/NavSatFix", si, lambda h, v=lat_lon: fix_msg(h, v))

    if "jets" in topics:
        s, st = states(sm.jets_hz)
        for si, x in zip(s, st, strict=True):
            thrust = float(x[hull.IX_THRUST] + rng.normal(0.0, sm.jets_thrust))
            nozzle = float(x[hull.IX_NOZZLE] + rng.normal(0.0, sm.jets_nozzle))
            emit(
                "jets",
                "odin_msgs/msg/JetState",
                si,
                lambda h, a=thrust, b=nozzle: w.make(
                    "odin_msgs/msg/JetState", header=h, thrust=a, nozzle=b
                ),
            )

    # Commands: published when they change (and once at the start).
    changed = np.ones(U.shape[0], bool)
    changed[1:] = np.any(U[1:] != U[:-1], axis=1)
    for k in np.flatnonzero(changed):
        if layout == "odin":
            emit(
                "cmd",
                "odin_msgs/msg/JetCommand",
                k * dt,
                lambda h, c=U[k]: w.make(
                    "odin_msgs/msg/JetCommand", header=h, thrust=float(c[0]), nozzle=float(c[1])
                ),
            )
        else:  # percent of full thrust; degrees, positive to starboard
            emit(
                "cmd",
                "jet_msgs/msg/JetCmd",
                k * dt,
                lambda h, c=U[k]: w.make(
                    "jet_msgs/msg/JetCmd",
                    header=h,
                    throttle=float(c[0]) / OTHER_BOAT_FULL_THRUST * 100.0,
                    steering=-float(np.rad2deg(c[1])),
                ),
            )

    if lidar:
        s, st = states(sm.lidar_hz)
        for si, x in zip(s, st, strict=True):
            ranges = _lidar_ranges(rng, x, rec.poles, sm)

            def scan(h, r=ranges):
                h.frame_id = "lidar"
                return w.make(
                    "sensor_msgs/msg/LaserScan",
                    header=h,
                    angle_min=float(-np.pi),
                    angle_max=float(np.pi - 2 * np.pi / sm.lidar_beams),
                    angle_increment=float(2 * np.pi / sm.lidar_beams),
                    time_increment=0.0,
                    scan_time=float(1.0 / sm.lidar_hz),
                    range_min=0.5,
                    range_max=float(sm.lidar_range),
                    ranges=r,
                    intensities=np.zeros(0, np.float32),
                )

            emit("lidar", "sensor_msgs/msg/LaserScan", si, scan)

    s, st = states(1.0 / sm.radar_period_s)
    for si, x in zip(s, st, strict=True):
        b, r, pw = _radar_detections(rng, x, rec.poles, sm)
        if layout == "odin":
            emit(
                "radar",
                "odin_msgs/msg/RadarSector",
                si,
                lambda h, b=b, r=r, pw=pw: w.make(
                    "odin_msgs/msg/RadarSector",
                    header=h,
                    range_max=float(sm.radar_range),
                    bearings=b,
                    ranges=r,
                    intensities=pw,
                ),
            )
        else:
            emit(
                "radar",
                "sensor_msgs/msg/PointCloud2",
                si,
                lambda h, b=b, r=r, pw=pw: _pointcloud2(w, h, b, r, pw),
            )

    for stamp, body in rec.markers:
        msgs.append((stamp, topics["markers"], "std_msgs/msg/String", _string(w, body)))
    return msgs


def _string(w: BagWriter, text: str):
    return w.make("std_msgs/msg/String", data=text)


def write_messages(path: Path, fmt: str, batches: Sequence[list]) -> None:
    """Write (bag ns, topic, type, message) tuples into one bag, in bag-time order."""
    rows = sorted((m for batch in batches for m in batch), key=lambda r: r[0])
    with BagWriter(path, fmt) as w:
        for t, topic, msgtype, msg in rows:
            w.write(topic, msgtype, t, msg)
