"""What a synthetic bag set records: the sensors (:class:`SensorModel`), the topics of the two
layouts (:data:`LAYOUT_TOPICS`) and the set's options (:class:`SynthConfig`).

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

**Other boats** (:func:`other_boat_config`): ``layout="other"`` records the same
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
recorded: a kinematic leg, :func:`~diffgcl.data.synth.scenes.repositioning_leg`) and
``stamp_glitch`` (a topic's header stamps jump back for a span). Left at their defaults,
these options change nothing in the Odin layout's bags.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

NS = 1_000_000_000

# 4 December (the seed's collection day), 09:00 UTC, 2017.
DEFAULT_START_NS = 1_512_378_000 * NS


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


# The "other boat" (a vessel recorded unlike Odin): GNSS fix stamped 0.2 s late, radar point
# cloud every 2.5 s (0.4 Hz) from 1 m ahead of the centre, with sea clutter (about 75 % of the 16
# beams of the default layout would read a clutter return under 11 m without a filter).
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
    """What :func:`~diffgcl.data.synth.dataset.synthesize` writes.

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
    """The "other boat" bags (a vessel recorded unlike Odin): layout ``other`` (GNSS fix with
    latency, ENU IMU, NED odometry, LaserScan, radar PointCloud2 at 0.4 Hz with sea clutter and
    intensities, on-change percent/degree jet commands), one bag per set with the repositioning
    legs recorded, every pole of a set in the water at once, no markers and no obstacle topic.
    ``changes`` override any field (e.g. ``markers="id"``)."""
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
