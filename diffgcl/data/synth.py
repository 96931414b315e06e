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
``manifest.json`` lists the episodes with their true metadata (pole position and radius, swerve
side, times) and the true hull parameters. The output folder follows
:func:`diffgcl.io.write_folder` (kind :data:`SYNTH_FOLDER`).

**Other boats** (issue 15; :func:`other_boat_config`): ``layout="other"`` records the same
simulated runs the way another vessel does —

=========================  ===========================  ========  =============================
topic                      type                         rate      what differs
=========================  ===========================  ========  =============================
/gnss/fix                  sensor_msgs/NavSatFix        5 Hz      stamped 0.2 s after the fix
/odom                      nav_msgs/Odometry            20 Hz     NED pose, FRD twist
/imu/data                  sensor_msgs/Imu              50 Hz     ENU, as Odin's
/jet/cmd                   jet_msgs/JetCmd              on change % of 12 kN, deg to starboard
/scan                      sensor_msgs/LaserScan        10 Hz     set 2 only
/radar/points              sensor_msgs/PointCloud2      0.4 Hz    x, y, z, intensity; sea clutter
/events                    std_msgs/String              markers   "start 1" / "end 1" (optional)
=========================  ===========================  ========  =============================

(no jet feedback, no obstacle topic) — and, as options of any layout: ``markers`` (key=value,
id or none), ``obstacle_topic``, ``visible_poles="set"`` (every pole of a set stands in the
water, the range sensors see all of them; poles kept apart and off the other episodes' courses),
``repositioning`` (with one bag per set, the drive from each run's end to the next start is
recorded: a kinematic leg, :func:`repositioning_leg`) and ``stamp_glitch`` (a topic's header
stamps jump back for a span). The Odin layout with the default options is unchanged, byte for
byte.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from diffgcl.data.bags import FORMATS, BagWriter, bag_name
from diffgcl.data.signals import local_to_latlon
from diffgcl.data.topics import default_topic_map
from diffgcl.io import FolderKind, check_output_folder, write_folder

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
    # Header stamps of the GNSS fix this much after the fix was taken (a receiver that stamps on
    # output); the topic map's position.latency undoes it.
    gps_latency_s: float = 0.0
    # Radar: position on the hull [x, y, yaw]; sea clutter near the boat: Poisson(sea_clutter)
    # returns per sweep at 2 m + Exponential(sea_clutter_range) m, uniform bearing, intensity
    # uniform in sea_clutter_intensity (the pole's returns: radar_pole_intensity).
    radar_mount: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sea_clutter: float = 0.0
    sea_clutter_range: float = 6.0
    sea_clutter_intensity: tuple[float, float] = (0.02, 0.6)
    radar_pole_intensity: tuple[float, float] = (0.6, 1.0)


# The "other boat" of issue 15: GNSS fix stamped 0.2 s late, radar point cloud every 2.5 s
# (0.4 Hz) from 1 m ahead of the centre, with sea clutter (about 75 % of the 16 beams of the
# default layout would read a clutter return under 11 m without a filter).
OTHER_BOAT_SENSORS = SensorModel(
    radar_period_s=2.5,
    gps_latency_s=0.2,
    radar_mount=(1.0, 0.0, 0.0),
    sea_clutter=60.0,
    radar_pole_intensity=(0.5, 1.0),
)

# Full thrust (N) that the "other" layout's throttle percentages refer to (HullParams.max_thrust).
OTHER_BOAT_FULL_THRUST = 12000.0

# Topics (and message types) of the two layouts; see the module docstring.
LAYOUT_TOPICS: dict[str, dict[str, str]] = {
    "odin": {
        "odom": "/odin/nav/odom",
        "imu": "/odin/imu",
        "gps": "/odin/gps/fix",
        "jets": "/odin/jets/state",
        "cmd": "/odin/operator/cmd",
        "lidar": "/odin/lidar/scan",
        "radar": "/odin/radar/sector",
        "obstacle": "/odin/obstacle/fix",
        "markers": "/odin/episode",
    },
    "other": {
        "odom": "/odom",
        "imu": "/imu/data",
        "gps": "/gnss/fix",
        "cmd": "/jet/cmd",
        "lidar": "/scan",
        "radar": "/radar/points",
        "obstacle": "/pole/fix",
        "markers": "/events",
    },
}


@dataclass(frozen=True)
class StampGlitch:
    """Header stamps of ``topic`` jump back by ``jump_s`` for messages sampled in
    [at_s, at_s + duration_s) after the start of each bag's first episode (a clock glitch)."""

    topic: str
    at_s: float = 20.0
    duration_s: float = 10.0
    jump_s: float = 3.0


@dataclass(frozen=True)
class SynthConfig:
    """What :func:`synthesize` writes.

    episodes: per set (the seed: 19 and 47); lidar: per set; fmt: ``ros1`` | ``ros2-sqlite3`` |
    ``ros2-mcap``; bag_per: ``episode`` | ``set``; approach_m: range of start distances to the
    pole (m); max_duration_s: cap on an episode's length.

    Other boats (see the module docstring): layout: ``odin`` | ``other`` (topics, types, frames,
    units); markers: ``keyvalue`` ("start set=1 episode=0 pole=green" / "end"), ``id``
    ("start 1" / "end 1") or ``none``; obstacle_topic: publish the surveyed pole; visible_poles:
    ``episode`` (the range sensors see only the episode's pole) or ``set`` (every pole of the set
    stands in the water at once, at least ``min_pole_separation`` m apart); repositioning (with
    ``bag_per="set"``): the boat drives from each episode's end to the next start, recorded,
    instead of a 20 s silence; stamp_glitch: a span of backwards header stamps.
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
    layout: str = "odin"
    markers: str = "keyvalue"
    obstacle_topic: bool = True
    visible_poles: str = "episode"
    min_pole_separation: float = 100.0
    repositioning: bool = False
    stamp_glitch: StampGlitch | None = None


def other_boat_config(**changes: Any) -> SynthConfig:
    """The "other boat" bags of issue 15: layout ``other`` (GNSS fix with latency, ENU IMU, NED
    odometry, LaserScan, radar PointCloud2 at 0.4 Hz with sea clutter and intensities, on-change
    percent/degree jet commands), one bag per set with the repositioning legs recorded, every
    pole of a set in the water at once, no markers and no obstacle topic. ``changes`` override
    any field (e.g. ``markers="id"``)."""
    base = {
        "episodes": (3, 3),
        "lidar": (False, True),
        "bag_per": "set",
        "layout": "other",
        "markers": "none",
        "obstacle_topic": False,
        "visible_poles": "set",
        "repositioning": True,
        "sensors": OTHER_BOAT_SENSORS,
    }
    return SynthConfig(**{**base, **changes})


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
        brg_true = float(_wrap(np.arctan2(rel[1], rel[0]) - psi - myaw))
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


# --------------------------------------------------------------------------------------------
# The data set
# --------------------------------------------------------------------------------------------


def _owned_bags(folder: Path) -> frozenset[str] | None:
    """What an earlier :func:`synthesize` wrote into ``folder`` (None: not a synthetic set)."""
    try:
        manifest = json.loads((folder / "manifest.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(manifest, dict) or manifest.get("format") != "diffgcl-synth/1":
        return None
    return frozenset(["manifest.json", *(e["bag"] for e in manifest.get("episodes", ()))])


SYNTH_FOLDER = FolderKind("synthetic bag set", _owned_bags, marker="manifest.json")


def _hermite(p0, p1, d0, d1, n: int = 4001) -> np.ndarray:
    """[n, 2] points of the cubic Hermite curve from p0 to p1 with end tangents d0, d1."""
    u = np.linspace(0.0, 1.0, n)[:, None]
    return (
        (2 * u**3 - 3 * u**2 + 1) * p0
        + (u**3 - 2 * u**2 + u) * d0
        + (-2 * u**3 + 3 * u**2) * p1
        + (u**3 - u**2) * d1
    )


# Tangent lengths tried for a leg (times the chord, at least LEG_MIN_TANGENT m; start and end
# tangents in every combination, shortest first): the boat turns soon after a run, as a crew
# would, and keeps LEG_CLEARANCE m from every pole.
_LEG_FACTORS = (0.2, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 3.0)
LEG_TANGENTS = tuple(
    sorted(
        ((a, b) for a in _LEG_FACTORS for b in _LEG_FACTORS),
        key=lambda ab: (ab[0] + ab[1], ab),
    )
)
LEG_MIN_TANGENT = 40.0
LEG_CLEARANCE = 100.0


def repositioning_leg(x_from: np.ndarray, x_to: np.ndarray, dt: float, poles=()):
    """The drive from one episode's last state to the next one's first: a cubic Hermite curve
    between the two poses, its tangents the shortest of :data:`LEG_TANGENTS` that keeps
    :data:`LEG_CLEARANCE` m from the ``poles`` ((x, y), radius) (else the one that keeps the
    most), the speed going linearly from one speed to the other; heading along the curve, yaw
    rate by differences, jets at a cruise setting. Kinematic, not the hull model (it is not a
    demo). Returns (X: [K+1, dX], U: [K, dU])."""
    from diffgcl.sim import hull

    p0, p1 = x_from[hull.IX_PX : hull.IX_PY + 1], x_to[hull.IX_PX : hull.IX_PY + 1]
    h0, h1 = x_from[hull.IX_PSI], x_to[hull.IX_PSI]
    v0 = float(np.hypot(x_from[hull.IX_VX], x_from[hull.IX_VY]))
    v1 = float(np.hypot(x_to[hull.IX_VX], x_to[hull.IX_VY]))
    chord = float(np.hypot(*(p1 - p0)))
    best, best_clearance = None, -np.inf
    for f0, f1 in LEG_TANGENTS:
        curve = _hermite(
            p0,
            p1,
            max(f0 * chord, LEG_MIN_TANGENT) * np.array([np.cos(h0), np.sin(h0)]),
            max(f1 * chord, LEG_MIN_TANGENT) * np.array([np.cos(h1), np.sin(h1)]),
        )
        clearance = min(
            (float(np.min(np.hypot(*(curve - xy).T))) - r for xy, r in poles), default=np.inf
        )
        if clearance > best_clearance:
            best, best_clearance = curve, clearance
        if clearance >= LEG_CLEARANCE:
            break
    curve = best
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(curve, axis=0).T))])
    duration = 2.0 * arc[-1] / max(v0 + v1, 1.0)
    K = max(int(round(duration / dt)), 2)
    tau = np.arange(K + 1) / K
    travelled = arc[-1] * (v0 * tau + 0.5 * (v1 - v0) * tau**2) / (0.5 * (v0 + v1))
    xy = np.stack([np.interp(travelled, arc, curve[:, j]) for j in range(2)], axis=1)
    heading = np.unwrap(np.arctan2(*np.gradient(xy, axis=0)[:, ::-1].T))
    heading += h0 - heading[0]
    speed = v0 + (v1 - v0) * tau
    X = np.zeros((K + 1, hull.DX))
    X[:, hull.IX_PX : hull.IX_PY + 1] = xy
    X[:, hull.IX_PSI] = heading
    X[:, hull.IX_VX] = speed * np.cos(heading)
    X[:, hull.IX_VY] = speed * np.sin(heading)
    X[:, hull.IX_R] = np.gradient(heading, dt)
    X[:, hull.IX_THRUST] = np.linspace(x_from[hull.IX_THRUST], x_to[hull.IX_THRUST], K + 1)
    X[:, hull.IX_NOZZLE] = np.clip(2.0 * X[:, hull.IX_R], -0.5, 0.5)
    X[:, hull.SL_OBS] = x_to[hull.SL_OBS]
    U = X[1:, hull.SL_ACT].copy()
    U[:, 0] = np.round(U[:, 0] / 250.0) * 250.0
    U[:, 1] = np.round(U[:, 1] / np.deg2rad(2.0)) * np.deg2rad(2.0)
    return X, U


def _course_segment(p: OperatorProfile) -> tuple[np.ndarray, np.ndarray]:
    """(start, end) of an episode's nominal course line: approach before the pole to
    end_margin past it."""
    e = np.array([np.cos(p.course), np.sin(p.course)])
    return np.asarray(p.pole_xy) - p.approach * e, np.asarray(p.pole_xy) + p.end_margin * e


def _segment_distance(xy: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    d = b - a
    h = np.clip(np.dot(xy - a, d) / max(np.dot(d, d), 1e-9), 0.0, 1.0)
    return float(np.hypot(*(xy - (a + h * d))))


def _separate_poles(rng, profiles: list[OperatorProfile], min_distance: float):
    """Profiles whose scenes are moved (pole redrawn in a box that grows with their number,
    course and approach kept) until every two poles are at least ``min_distance`` apart and no
    pole lies within ``0.8 min_distance`` of another episode's course line (at most 500 tries
    each; the last try is kept)."""
    half = max(150.0, 0.6 * min_distance * np.sqrt(len(profiles)))
    out: list[OperatorProfile] = []
    for p in profiles:
        for _ in range(500):
            lines = [_course_segment(q) for q in out]
            if all(
                np.hypot(*np.subtract(p.pole_xy, q.pole_xy)) >= min_distance for q in out
            ) and all(
                _segment_distance(np.asarray(q.pole_xy), *_course_segment(p)) >= 0.8 * min_distance
                and _segment_distance(np.asarray(p.pole_xy), a, b) >= 0.8 * min_distance
                for q, (a, b) in zip(out, lines, strict=True)
            ):
                break
            xy = rng.uniform(-half, half, 2)
            p = dataclasses.replace(p, pole_xy=(float(xy[0]), float(xy[1])))
        out.append(p)
    return out


def _marker_texts(cfg: SynthConfig, set_index: int, i: int, colour: str) -> tuple[str, str]:
    if cfg.markers == "id":
        return f"start {i + 1}", f"end {i + 1}"
    return f"start set={set_index} episode={i} pole={colour}", "end"


def synthesize(
    out: str | os.PathLike,
    config: SynthConfig | None = None,
    progress: Callable[[Sequence], Any] | None = None,
    overwrite: bool = False,
) -> SynthResult:
    """Simulate every episode and write the bags into ``out`` (output folder rules of
    :func:`diffgcl.io.write_folder`, kind :data:`SYNTH_FOLDER`: an earlier synthetic set there is
    replaced atomically, a non-empty folder of anything else is refused unless ``overwrite``).

    Returns the written bags and the simulated truth (states on the model grid) per episode.
    """
    cfg = config or SynthConfig()
    if cfg.fmt not in FORMATS:
        raise ValueError(f"bag format {cfg.fmt!r}; choose one of {FORMATS}")
    if cfg.bag_per not in ("episode", "set"):
        raise ValueError(f"bag_per must be 'episode' or 'set', got {cfg.bag_per!r}")
    if len(cfg.lidar) != len(cfg.episodes):
        raise ValueError("config.lidar needs one flag per set")
    for name, value, allowed in (
        ("layout", cfg.layout, tuple(LAYOUT_TOPICS)),
        ("markers", cfg.markers, ("keyvalue", "id", "none")),
        ("visible_poles", cfg.visible_poles, ("episode", "set")),
    ):
        if value not in allowed:
            raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
    check_output_folder(out, SYNTH_FOLDER, overwrite)
    datum = cfg.datum or default_topic_map().datum
    params = true_params()
    taus = (float(params.tau_thrust), float(params.tau_nozzle))
    dt = hull_dt()
    step_ns = round(dt * NS)
    rng = np.random.default_rng(cfg.seed)
    out = Path(out)
    truths: list[EpisodeTruth] = []
    legs: list[dict] = []
    bags: list[Path] = []
    clock = cfg.start_ns
    sets = []
    for s, (n_ep, lidar) in enumerate(zip(cfg.episodes, cfg.lidar, strict=True), start=1):
        if n_ep > 0:
            profiles = draw_profiles(rng, n_ep, cfg)
            if cfg.visible_poles == "set":
                profiles = _separate_poles(rng, profiles, cfg.min_pole_separation)
            sets.append((s, n_ep, lidar, profiles))
    # One simulation batch for all sets (one trace of the jitted step per process).
    all_runs = simulate(
        [p for *_, ps in sets for p in ps], params, rng, int(cfg.max_duration_s / dt)
    )
    jobs: list[tuple[str, bool, Recording, np.random.Generator]] = []
    glitches: dict[str, tuple[str, int, int, int]] = {}
    for s, n_ep, lidar, profiles in sets:
        runs, all_runs = all_runs[:n_ep], all_runs[n_ep:]
        set_poles = tuple((p.pole_xy, p.pole_radius) for p in profiles)
        previous = None
        for i, (prof, (X, U)) in enumerate(zip(profiles, runs, strict=True)):
            stem = f"set{s}_ep{i:03d}" if cfg.bag_per == "episode" else f"set{s}"
            bag = f"set{s}/{bag_name(stem, cfg.fmt)}"
            poles = set_poles if cfg.visible_poles == "set" else ((prof.pole_xy, prof.pole_radius),)
            if previous is not None and cfg.repositioning and cfg.bag_per == "set":
                leg_X, leg_U = repositioning_leg(previous[1][-1], X[0], dt, set_poles)
                t_leg = int(previous[0][-1]) + step_ns * np.arange(leg_X.shape[0], dtype=np.int64)
                leg = Recording(t_leg, leg_X, leg_U, poles, None, ())
                jobs.append((bag, lidar, leg, np.random.default_rng([cfg.seed, s, 1000 + i])))
                clearance = min(
                    float(np.min(np.hypot(*(leg_X[:, :2] - xy).T))) - r for xy, r in set_poles
                )
                legs.append(
                    {
                        "set": s,
                        "bag": bag,
                        "t_start": t_leg[0] * 1e-9,
                        "t_end": t_leg[-1] * 1e-9,
                        "pole_clearance_m": clearance,
                    }
                )
                clock = int(t_leg[-1])
            else:
                clock = -(-clock // step_ns) * step_ns
            t = clock + step_ns * np.arange(X.shape[0], dtype=np.int64)
            marker_ns = (int(t[0] + MARKER_LEAD_NS), int(t[-1] - NS))
            start_text, end_text = _marker_texts(cfg, s, i, prof.pole_colour)
            markers = (
                ()
                if cfg.markers == "none"
                else ((marker_ns[0], start_text), (marker_ns[1], end_text))
            )
            obstacle = prof.pole_xy if cfg.obstacle_topic else None
            rec = Recording(t, X, U, poles, obstacle, markers)
            jobs.append((bag, lidar, rec, np.random.default_rng([cfg.seed, s, i])))
            truths.append(EpisodeTruth(s, i, prof, t, X, U, bag, marker_ns))
            if cfg.stamp_glitch is not None and bag not in glitches:
                g = cfg.stamp_glitch
                first = int(t[0] + round(g.at_s * NS))
                glitches[bag] = (
                    g.topic,
                    first,
                    first + round(g.duration_s * NS),
                    round(g.jump_s * NS),
                )
            previous = (t, X)
            clock = int(t[-1]) + 20 * NS
    with write_folder(out, SYNTH_FOLDER, overwrite) as stage:
        iterable = progress(jobs) if progress is not None else jobs
        batches: dict[str, list] = {}
        builder = _NullWriter(cfg.fmt)
        for bag, lidar, rec, job_rng in iterable:
            msgs = episode_messages(
                builder,
                rec,
                lidar,
                cfg.sensors,
                datum,
                job_rng,
                taus,
                cfg.layout,
                glitches.get(bag),
            )
            batches.setdefault(bag, []).append(msgs)
        for rel, msg_batches in batches.items():
            (stage / rel).parent.mkdir(parents=True, exist_ok=True)
            write_messages(stage / rel, cfg.fmt, msg_batches)
            bags.append(out / rel)
        manifest = {
            "format": "diffgcl-synth/1",
            "bag_format": cfg.fmt,
            "bag_per": cfg.bag_per,
            "layout": cfg.layout,
            "markers": cfg.markers,
            "obstacle_topic": cfg.obstacle_topic,
            "visible_poles": cfg.visible_poles,
            "repositioning": cfg.repositioning,
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
                    "pole_xy": list(tr.profile.pole_xy),
                    "pole_radius": tr.profile.pole_radius,
                    "swerve_side": "left" if tr.profile.side > 0 else "right",
                    "t_start": tr.marker_ns[0] * 1e-9,
                    "t_end": tr.marker_ns[1] * 1e-9,
                    "t_first": tr.t[0] * 1e-9,
                    "t_last": tr.t[-1] * 1e-9,
                    "profile": asdict(tr.profile),
                }
                for tr in truths
            ],
            "legs": legs,
        }
        (stage / "manifest.json").write_text(json.dumps(manifest, indent=1))
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
