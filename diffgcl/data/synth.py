"""Odin-like synthetic ROS bags: a simulated operator avoiding a pole, recorded like the real boat.

The seed's 66 demonstrations of manual obstacle avoidance on the USV Odin (two sets on one day:
set 1 with 19 episodes and no LiDAR, set 2 with 47 episodes with LiDAR; green or grey poles, half
each; varied start and swerve point) are not public. This module writes bags with the same
layout from runs of a simulated human operator on the hull model, so that the whole path bag ->
ingestion -> system identification -> GCL is exercised.

**Operator** (one per episode, parameters drawn per episode, :class:`OperatorProfile`): heads
for the pole (pure pursuit) at a cruise thrust set in two steps; at a varying distance swerves
left or right by a fixed course change until a lateral clearance is reached; holds that offset
past the pole; turns back and follows the original course line. It acts on what it saw
``reaction_delay`` seconds ago, decides every ``decision_s`` seconds, adds noise to the nozzle,
and quantises its commands (nozzle in 2° detents, thrust in 250 N steps); commands are
published only when they change.

**Truth model**: :func:`true_params` — the default :class:`~diffgcl.sim.hull.HullParams` with the
parameters that system identification fits (:data:`diffgcl.data.sysid.SYSID_FIELDS`) changed by
the documented factors :data:`TRUE_FACTORS`, so identification has something to find.

**Sensors** (:class:`SensorModel`; header stamp = sampling time, bag time = stamp + latency +
jitter):

=========================  ===========================  ========  =============================
topic                      type                         rate      noise (1 σ)
=========================  ===========================  ========  =============================
/odin/nav/odom             nav_msgs/Odometry            20 Hz     0.05 m, 0.002 rad, 0.02 m/s
/odin/imu                  sensor_msgs/Imu              50 Hz     0.0035 rad, 0.005 rad/s
/odin/gps/fix              sensor_msgs/NavSatFix        5 Hz      0.3 m
/odin/jets/state           odin_msgs/JetState           10 Hz     30 N, 0.003 rad
/odin/operator/cmd         odin_msgs/JetCommand         on change exact (quantised)
/odin/lidar/scan           sensor_msgs/LaserScan        10 Hz     0.03 m, 2 % dropouts (set 2)
/odin/radar/sector         odin_msgs/RadarSector        0.5 Hz    1.5 m, 1°, Pd 0.9, clutter
/odin/obstacle/fix         sensor_msgs/NavSatFix        1 Hz      0.2 m (surveyed pole)
/odin/episode              std_msgs/String              markers   "start set=.. pole=.." / "end"
=========================  ===========================  ========  =============================

**Files**: one bag per episode (``set1/ep000.bag`` ...), the way a boat crew records one run at a
time; each bag has episode markers 2.5 s after its first and 1 s before its last message, so the
bags also work with ``bag_per="set"`` (one bag per set, episodes one after another, 20 s apart).
``manifest.json`` lists the episodes with their true metadata and the true hull parameters.
The output folder is written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from diffgcl.data.bags import FORMATS, BagWriter, bag_name
from diffgcl.data.ingest import local_to_latlon
from diffgcl.data.topics import default_topic_map

NS = 1_000_000_000

# The generator's hull differs from the default model in exactly these parameters (factor on the
# default value). Other parameters are the defaults. sysid.SYSID_FIELDS lists the same names.
TRUE_FACTORS: dict[str, float] = {
    "inertia_scale": 1.10,
    "damping_uu": 1.15,
    "damping_v": 1.25,
    "damping_r": 0.85,
    "jet_arm": 0.92,
    "tau_thrust": 1.30,
    "tau_nozzle": 0.80,
}

# Episode start marker this long after the first message (so every sensor, the 0.5 Hz radar
# included, has reported once inside the episode); end marker 1 s before the last message.
MARKER_LEAD_NS = 2_500_000_000

# 4 December (the seed's collection day), 09:00 UTC, 2017.
DEFAULT_START_NS = 1_512_378_000 * NS


def true_params(dtype=None):
    """The generator's "true" :class:`~diffgcl.sim.hull.HullParams` (defaults × TRUE_FACTORS)."""
    from diffgcl.sim import hull

    base = hull.default_params(dtype)
    return base.replace(**{k: getattr(base, k) * f for k, f in TRUE_FACTORS.items()})


@dataclass(frozen=True)
class SensorModel:
    """Rates (Hz), noise (1 σ) and latency (s) of the synthetic sensors (see module table)."""

    odom_hz: float = 20.0
    odom_pos: float = 0.05
    odom_yaw: float = 0.002
    odom_vel: float = 0.02
    imu_hz: float = 50.0
    imu_yaw: float = 0.0035
    imu_rate: float = 0.005
    gps_hz: float = 5.0
    gps_pos: float = 0.3
    jets_hz: float = 10.0
    jets_thrust: float = 30.0
    jets_nozzle: float = 0.003
    lidar_hz: float = 10.0
    lidar_beams: int = 720
    lidar_range: float = 120.0
    lidar_noise: float = 0.03
    lidar_dropout: float = 0.02
    radar_period_s: float = 2.0
    radar_range: float = 1500.0
    radar_range_noise: float = 1.5
    radar_bearing_noise: float = float(np.deg2rad(1.0))
    radar_pd: float = 0.9
    radar_clutter: float = 3.0
    obstacle_hz: float = 1.0
    obstacle_pos: float = 0.2
    latency_s: float = 0.02
    jitter_s: float = 0.01
    lidar_mount: tuple[float, float, float] = (2.0, 0.0, 0.0)


@dataclass(frozen=True)
class SynthConfig:
    """What :func:`synthesize` writes.

    episodes: per set (the seed: 19 and 47); lidar: per set; fmt: ``ros1`` | ``ros2-sqlite3`` |
    ``ros2-mcap``; bag_per: ``episode`` | ``set``; approach_m: range of start distances to the
    pole (m); max_duration_s: cap on an episode's length.
    """

    episodes: tuple[int, ...] = (19, 47)
    lidar: tuple[bool, ...] = (False, True)
    fmt: str = "ros1"
    bag_per: str = "episode"
    seed: int = 0
    approach_m: tuple[float, float] = (140.0, 220.0)
    end_margin_m: tuple[float, float] = (60.0, 100.0)
    max_duration_s: float = 120.0
    start_ns: int = DEFAULT_START_NS
    sensors: SensorModel = field(default_factory=SensorModel)
    datum: tuple[float, float] | None = None


@dataclass(frozen=True)
class OperatorProfile:
    """One episode's scenario and operator (distances m, angles rad, times s, thrust N)."""

    pole_xy: tuple[float, float]
    pole_radius: float
    pole_colour: str
    course: float
    approach: float
    heading_error: float
    speed0: float
    side: int  # +1 swerve left (to port), -1 right
    swerve_distance: float
    swerve_angle: float
    clearance: float
    pass_margin: float
    return_angle: float
    end_margin: float
    cruise_thrust: float
    reaction_delay: float
    decision_s: float
    kp: float
    kd: float
    nozzle_noise: float
    nozzle_quantum: float = float(np.deg2rad(2.0))
    thrust_quantum: float = 250.0


@dataclass(frozen=True)
class EpisodeTruth:
    """A simulated episode: t: [K+1] int64 ns, X: [K+1, dX], U: [K, dU] (hull layout)."""

    set: int
    index: int
    profile: OperatorProfile
    t: np.ndarray
    X: np.ndarray
    U: np.ndarray
    bag: str = ""
    marker_ns: tuple[int, int] = (0, 0)


@dataclass(frozen=True)
class SynthResult:
    """Bags written by :func:`synthesize` and the simulated truth of every episode."""

    out: Path
    bags: tuple[Path, ...]
    episodes: tuple[EpisodeTruth, ...]


def draw_profiles(rng: np.random.Generator, n: int, config: SynthConfig) -> list[OperatorProfile]:
    """``n`` scenarios/operators; poles half green, half grey; swerves alternate sides randomly."""
    colours = np.array(["green"] * ((n + 1) // 2) + ["grey"] * (n // 2))
    rng.shuffle(colours)
    sides = np.array([1] * ((n + 1) // 2) + [-1] * (n // 2))
    rng.shuffle(sides)
    out = []
    for i in range(n):
        approach = rng.uniform(*config.approach_m)
        out.append(
            OperatorProfile(
                pole_xy=(float(rng.uniform(-150, 150)), float(rng.uniform(-150, 150))),
                pole_radius=float(rng.uniform(0.3, 1.0)),
                pole_colour=str(colours[i]),
                course=float(rng.uniform(-np.pi, np.pi)),
                approach=float(approach),
                heading_error=float(rng.normal(0.0, np.deg2rad(4.0))),
                speed0=float(rng.uniform(3.0, 6.0)),
                side=int(sides[i]),
                swerve_distance=float(rng.uniform(0.25, 0.45) * approach),
                swerve_angle=float(np.deg2rad(rng.uniform(25.0, 40.0))),
                clearance=float(rng.uniform(12.0, 25.0)),
                pass_margin=float(rng.uniform(5.0, 20.0)),
                return_angle=float(np.deg2rad(rng.uniform(20.0, 35.0))),
                end_margin=float(rng.uniform(*config.end_margin_m)),
                cruise_thrust=float(rng.uniform(5500.0, 9000.0)),
                reaction_delay=float(rng.uniform(0.3, 0.7)),
                decision_s=float(rng.choice([0.2, 0.3])),
                kp=float(rng.uniform(1.2, 2.0)),
                kd=float(rng.uniform(1.0, 2.5)),
                nozzle_noise=float(np.deg2rad(rng.uniform(0.5, 1.5))),
            )
        )
    return out


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def simulate(
    profiles: Sequence[OperatorProfile], params, rng: np.random.Generator, max_steps: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Run the operators on the hull, all episodes at once -> [(X: [K+1, dX], U: [K, dU])].

    The operator is NumPy (vectorised over episodes); the hull step is the jitted, vmapped
    :func:`diffgcl.sim.hull.hull_step` with ``params``.
    """
    import jax
    import jax.numpy as jnp

    from diffgcl.sim import hull

    dt = hull_dt()
    E = len(profiles)
    P = {
        k: np.array([getattr(p, k) for p in profiles], float)
        for k, v in asdict(profiles[0]).items()
        if isinstance(v, int | float)
    }
    pole = np.array([p.pole_xy for p in profiles], float)
    e = np.stack([np.cos(P["course"]), np.sin(P["course"])], axis=1)
    n = np.stack([-e[:, 1], e[:, 0]], axis=1)
    start = pole - P["approach"][:, None] * e
    psi0 = P["course"] + P["heading_error"]
    x = np.zeros((E, hull.DX))
    x[:, hull.IX_PX : hull.IX_PY + 1] = start
    x[:, hull.IX_PSI] = psi0
    x[:, hull.IX_VX] = P["speed0"] * np.cos(psi0)
    x[:, hull.IX_VY] = P["speed0"] * np.sin(psi0)
    x[:, hull.IX_THRUST] = 0.5 * P["cruise_thrust"]
    x[:, hull.SL_OBS] = pole

    dtype = jnp.zeros(()).dtype
    step = _batched_step()
    params = jax.tree.map(lambda v: jnp.asarray(v, dtype), params)

    delay = np.maximum(np.round(P["reaction_delay"] / dt).astype(int), 0)
    every = np.maximum(np.round(P["decision_s"] / dt).astype(int), 1)
    ramp_until = rng.uniform(2.0, 6.0, E)
    phase = np.zeros(E, int)  # 0 approach, 1 swerve, 2 pass, 3 return, 4 track
    done_at = np.full(E, -1)
    cmd = np.stack([np.round(0.5 * P["cruise_thrust"] / 250.0) * 250.0, np.zeros(E)], axis=1)
    history = [x.copy()]
    commands = []
    wander = np.zeros(E)
    for k in range(max_steps):
        seen = np.stack([history[max(k - int(d), 0)][i] for i, d in enumerate(delay)])
        rel = seen[:, hull.IX_PX : hull.IX_PY + 1] - start
        along = np.sum(rel * e, axis=1)
        cross = np.sum(rel * n, axis=1)
        to_pole = pole - seen[:, hull.IX_PX : hull.IX_PY + 1]
        side = P["side"]
        phase = np.where((phase == 0) & (P["approach"] - along < P["swerve_distance"]), 1, phase)
        phase = np.where((phase == 1) & (side * cross >= P["clearance"]), 2, phase)
        phase = np.where((phase == 2) & (along > P["approach"] + P["pass_margin"]), 3, phase)
        phase = np.where((phase == 3) & (side * cross <= 1.0), 4, phase)
        target = np.select(
            [phase == 0, phase == 1, phase == 2, phase == 3],
            [
                np.arctan2(to_pole[:, 1], to_pole[:, 0]),
                P["course"] + side * P["swerve_angle"],
                P["course"],
                P["course"] - side * P["return_angle"],
            ],
            P["course"] - np.clip(0.04 * cross, -0.35, 0.35),
        )
        wander = 0.95 * wander + rng.normal(0.0, 1.0, E) * P["nozzle_noise"] * 0.3
        nozzle = (
            P["kp"] * _wrap(target - seen[:, hull.IX_PSI])
            - P["kd"] * seen[:, hull.IX_R]
            + wander
            + rng.normal(0.0, 1.0, E) * P["nozzle_noise"]
        )
        nozzle = np.clip(nozzle, -np.deg2rad(30.0), np.deg2rad(30.0))
        nozzle = np.round(nozzle / P["nozzle_quantum"]) * P["nozzle_quantum"]
        level = np.where(k * dt < ramp_until, 0.5, np.where(phase == 1, 0.85, 1.0))
        thrust = np.round(level * P["cruise_thrust"] / P["thrust_quantum"]) * P["thrust_quantum"]
        decide = (k % every) == 0
        cmd = np.where(decide[:, None], np.stack([thrust, nozzle], axis=1), cmd)
        commands.append(cmd.copy())
        # Pad the batch to a multiple of 8 so that small runs share one trace of the step.
        pad = (-E) % 8
        xb = np.concatenate([x, np.repeat(x[:1], pad, 0)]) if pad else x
        ub = np.concatenate([cmd, np.repeat(cmd[:1], pad, 0)]) if pad else cmd
        x = np.asarray(step(params, jnp.asarray(xb, dtype), jnp.asarray(ub, dtype)))[:E]
        history.append(x.copy())
        finished = (phase == 4) & (along > P["approach"] + P["end_margin"]) & (done_at < 0)
        done_at = np.where(finished, k + 1, done_at)
        if (done_at >= 0).all():
            break
    X = np.stack(history, axis=1)
    U = np.stack(commands, axis=1)
    out = []
    for i in range(E):
        K = done_at[i] if done_at[i] >= 0 else U.shape[1]
        out.append((X[i, : K + 1], U[i, :K]))
    return out


@functools.lru_cache(maxsize=1)
def _batched_step():
    import jax

    from diffgcl.sim import hull

    return jax.jit(jax.vmap(hull.hull_step, in_axes=(None, 0, 0)))


def hull_dt() -> float:
    """Control step of the hull model (s)."""
    from diffgcl.sim import hull

    return float(hull.hull_model()[0].opt.timestep) * hull.SUBSTEPS


# --------------------------------------------------------------------------------------------
# Sensors
# --------------------------------------------------------------------------------------------


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


def _lidar_ranges(rng, state, pole, radius, sm: SensorModel) -> np.ndarray:
    """LaserScan ranges [beams] (inf = no return) of a 360° scan from the mast."""
    from diffgcl.sim import hull

    psi = state[hull.IX_PSI]
    c, s = np.cos(psi), np.sin(psi)
    mx, my, myaw = sm.lidar_mount
    origin = state[hull.IX_PX : hull.IX_PY + 1] + np.array([c * mx - s * my, s * mx + c * my])
    angles = -np.pi + np.arange(sm.lidar_beams) * (2 * np.pi / sm.lidar_beams)
    world = psi + myaw + angles
    d = np.stack([np.cos(world), np.sin(world)], axis=1)
    rel = np.asarray(pole) - origin
    proj = d @ rel
    disc = proj**2 - (rel @ rel - radius**2)
    hit = (disc >= 0) & (proj > 0)
    r = np.where(hit, proj - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    r = r + rng.normal(0.0, sm.lidar_noise, r.shape)
    r[(r > sm.lidar_range) | (rng.uniform(size=r.shape) < sm.lidar_dropout)] = np.inf
    return r.astype(np.float32)


def _radar_detections(rng, state, pole, sm: SensorModel):
    """(bearings, ranges, intensities) of one sweep: the pole (prob. Pd) plus clutter."""
    from diffgcl.sim import hull

    rel = np.asarray(pole) - state[hull.IX_PX : hull.IX_PY + 1]
    rng_true = float(np.hypot(*rel))
    brg_true = float(_wrap(np.arctan2(rel[1], rel[0]) - state[hull.IX_PSI]))
    bearings, ranges, power = [], [], []
    if rng_true < sm.radar_range and rng.uniform() < sm.radar_pd:
        bearings.append(brg_true + rng.normal(0.0, sm.radar_bearing_noise))
        ranges.append(max(rng_true + rng.normal(0.0, sm.radar_range_noise), 1.0))
        power.append(rng.uniform(0.6, 1.0))
    for _ in range(rng.poisson(sm.radar_clutter)):
        bearings.append(rng.uniform(-np.pi, np.pi))
        ranges.append(rng.uniform(20.0, 0.6 * sm.radar_range))
        power.append(rng.uniform(0.05, 0.5))
    f32 = lambda v: np.asarray(v, np.float32)
    return f32(bearings), f32(ranges), f32(power)


def episode_messages(
    w: BagWriter,
    truth: EpisodeTruth,
    lidar: bool,
    sm: SensorModel,
    datum: tuple[float, float],
    rng: np.random.Generator,
    taus: tuple[float, float],
    set_index: int,
) -> list[tuple[int, str, str, Any]]:
    """All messages of one episode as (bag ns, topic, type, message), unsorted."""
    from diffgcl.sim import hull

    dt = hull_dt()
    X, U, t_ns = truth.X, truth.U, truth.t
    p = truth.profile
    t0_ns = int(t_ns[0])
    dur = U.shape[0] * dt
    msgs: list[tuple[int, str, str, Any]] = []

    def emit(topic, msgtype, stamp_s, build):
        stamp = t0_ns + int(round(stamp_s * NS))
        lag = sm.latency_s + abs(rng.normal(0.0, sm.jitter_s))
        msgs.append((stamp + int(lag * NS), topic, msgtype, build(w.header(stamp, "odin"))))

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
            pose = w.make(
                "geometry_msgs/msg/Pose",
                position=w.make(
                    "geometry_msgs/msg/Point",
                    x=float(x[hull.IX_PX] + sm.odom_pos * noise[0]),
                    y=float(x[hull.IX_PY] + sm.odom_pos * noise[1]),
                    z=0.0,
                ),
                orientation=w.make("geometry_msgs/msg/Quaternion", **_quat(yaw)),
            )
            twist = w.make(
                "geometry_msgs/msg/Twist",
                linear=w.make(
                    "geometry_msgs/msg/Vector3",
                    x=float(u_b + sm.odom_vel * noise[3]),
                    y=float(v_b + sm.odom_vel * noise[4]),
                    z=0.0,
                ),
                angular=w.make("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=float(x[hull.IX_R])),
            )
            h.frame_id = "odin_local"
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

        emit("/odin/nav/odom", "nav_msgs/msg/Odometry", si, odom)

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

        emit("/odin/imu", "sensor_msgs/msg/Imu", si, imu)

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
        emit("/odin/gps/fix", "sensor_msgs/msg/NavSatFix", si, lambda h, v=lat_lon: fix_msg(h, v))

    s = _sample_times(rng, 0.0, dur, sm.obstacle_hz)
    ll = local_to_latlon(
        np.asarray(p.pole_xy) + rng.normal(0.0, sm.obstacle_pos, (len(s), 2)), datum
    )
    for si, lat_lon in zip(s, ll, strict=True):
        emit(
            "/odin/obstacle/fix",
            "sensor_msgs/msg/NavSatFix",
            si,
            lambda h, v=lat_lon: fix_msg(h, v),
        )

    s, st = states(sm.jets_hz)
    for si, x in zip(s, st, strict=True):
        thrust = float(x[hull.IX_THRUST] + rng.normal(0.0, sm.jets_thrust))
        nozzle = float(x[hull.IX_NOZZLE] + rng.normal(0.0, sm.jets_nozzle))
        emit(
            "/odin/jets/state",
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
        emit(
            "/odin/operator/cmd",
            "odin_msgs/msg/JetCommand",
            k * dt,
            lambda h, c=U[k]: w.make(
                "odin_msgs/msg/JetCommand", header=h, thrust=float(c[0]), nozzle=float(c[1])
            ),
        )

    if lidar:
        s, st = states(sm.lidar_hz)
        for si, x in zip(s, st, strict=True):
            ranges = _lidar_ranges(rng, x, p.pole_xy, p.pole_radius, sm)

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

            emit("/odin/lidar/scan", "sensor_msgs/msg/LaserScan", si, scan)

    s, st = states(1.0 / sm.radar_period_s)
    for si, x in zip(s, st, strict=True):
        b, r, pw = _radar_detections(rng, x, p.pole_xy, sm)
        emit(
            "/odin/radar/sector",
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

    start_ns, end_ns = truth.marker_ns
    text = f"start set={set_index} episode={truth.index} pole={p.pole_colour}"
    for stamp, body in ((start_ns, text), (end_ns, "end")):
        msgs.append((stamp, "/odin/episode", "std_msgs/msg/String", _string(w, body)))
    return msgs


def _string(w: BagWriter, text: str):
    return w.make("std_msgs/msg/String", data=text)


def write_messages(path: Path, fmt: str, batches: Sequence[list]) -> None:
    """Write (bag ns, topic, type, message) tuples into one bag, in bag-time order."""
    rows = sorted((m for batch in batches for m in batch), key=lambda r: r[0])
    with BagWriter(path, fmt) as w:
        for t, topic, msgtype, msg in rows:
            w.write(topic, msgtype, t, msg)


# --------------------------------------------------------------------------------------------
# The data set
# --------------------------------------------------------------------------------------------


def synthesize(
    out: str | os.PathLike,
    config: SynthConfig | None = None,
    progress: Callable[[Sequence], Any] | None = None,
) -> SynthResult:
    """Simulate every episode and write the bags into ``out`` (replaced atomically).

    Returns the written bags and the simulated truth (states on the model grid) per episode.
    """
    cfg = config or SynthConfig()
    if cfg.fmt not in FORMATS:
        raise ValueError(f"bag format {cfg.fmt!r}; choose one of {FORMATS}")
    if cfg.bag_per not in ("episode", "set"):
        raise ValueError(f"bag_per must be 'episode' or 'set', got {cfg.bag_per!r}")
    if len(cfg.lidar) != len(cfg.episodes):
        raise ValueError("config.lidar needs one flag per set")
    datum = cfg.datum or default_topic_map().datum
    params = true_params()
    taus = (float(params.tau_thrust), float(params.tau_nozzle))
    dt = hull_dt()
    step_ns = round(dt * NS)
    rng = np.random.default_rng(cfg.seed)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        truths: list[EpisodeTruth] = []
        bags: list[Path] = []
        clock = cfg.start_ns
        jobs = []
        sets = [
            (s, n_ep, lidar, draw_profiles(rng, n_ep, cfg))
            for s, (n_ep, lidar) in enumerate(zip(cfg.episodes, cfg.lidar, strict=True), start=1)
            if n_ep > 0
        ]
        # One simulation batch for all sets (one trace of the jitted step per process).
        all_runs = simulate(
            [p for *_, ps in sets for p in ps], params, rng, int(cfg.max_duration_s / dt)
        )
        for s, n_ep, lidar, profiles in sets:
            runs, all_runs = all_runs[:n_ep], all_runs[n_ep:]
            set_dir = tmp / f"set{s}"
            set_dir.mkdir()
            set_truths = []
            for i, (prof, (X, U)) in enumerate(zip(profiles, runs, strict=True)):
                clock = -(-clock // step_ns) * step_ns
                t = clock + step_ns * np.arange(X.shape[0], dtype=np.int64)
                markers = (int(t[0] + MARKER_LEAD_NS), int(t[-1] - NS))
                stem = f"set{s}_ep{i:03d}" if cfg.bag_per == "episode" else f"set{s}"
                bag = set_dir / bag_name(stem, cfg.fmt)
                truth = EpisodeTruth(s, i, prof, t, X, U, str(bag.relative_to(tmp)), markers)
                set_truths.append(truth)
                clock = int(t[-1]) + 20 * NS
            jobs.append((set_dir, lidar, s, set_truths))
            truths.extend(set_truths)
        total = [(d, lid, s, [tr]) for d, lid, s, trs in jobs for tr in trs]
        iterable = progress(total) if progress is not None else total
        batches: dict[str, list] = {}
        builder = _NullWriter(cfg.fmt)
        for _, lidar, s, (truth,) in iterable:
            ep_rng = np.random.default_rng([cfg.seed, s, truth.index])
            msgs = episode_messages(builder, truth, lidar, cfg.sensors, datum, ep_rng, taus, s)
            batches.setdefault(truth.bag, []).append(msgs)
        for rel, msg_batches in batches.items():
            write_messages(tmp / rel, cfg.fmt, msg_batches)
            bags.append(out / rel)
        manifest = {
            "format": "diffgcl-synth/1",
            "bag_format": cfg.fmt,
            "bag_per": cfg.bag_per,
            "seed": cfg.seed,
            "dt": dt,
            "datum": list(datum),
            "true_factors": TRUE_FACTORS,
            "true_params": {k: float(getattr(params, k)) for k in TRUE_FACTORS},
            "sets": {
                str(s): {"episodes": n, "lidar": lid}
                for s, (n, lid) in enumerate(zip(cfg.episodes, cfg.lidar, strict=True), start=1)
            },
            "episodes": [
                {
                    "set": tr.set,
                    "index": tr.index,
                    "bag": tr.bag,
                    "pole": tr.profile.pole_colour,
                    "swerve_side": "left" if tr.profile.side > 0 else "right",
                    "t_start": tr.marker_ns[0] * 1e-9,
                    "t_end": tr.marker_ns[1] * 1e-9,
                    "profile": asdict(tr.profile),
                }
                for tr in truths
            ],
        }
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1))
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return SynthResult(out=out, bags=tuple(dict.fromkeys(bags)), episodes=tuple(truths))


class _NullWriter(BagWriter):
    """A writer used only to build messages (typestore, headers); it writes no file."""

    def __init__(self, fmt: str):
        from diffgcl.data.bags import typestore_for

        self.path = Path(os.devnull)
        self.format = fmt
        self.typestore = typestore_for(fmt)
        self._seq = 0

    def __enter__(self) -> _NullWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        return None
