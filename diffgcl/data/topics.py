"""Topic maps: which ROS topics carry which signal of a demonstration, and how to read them.

A real bag names its topics after the vessel's drivers (``/odin/nav/odom``, ``/radar/points``,
...), stamps them with its own clocks, uses its own frames (ENU or NED) and command units.
Ingestion needs to know all of that. A topic map is a small YAML file, parsed once into the
frozen :class:`TopicMap` below; every key is validated here and a bad one is a one-line
:class:`TopicMapError` naming the file and the key (``map.yaml: radar.filter.min_range: ...``).

The reference of every key (units, frames, defaults) with an annotated example is
``docs/bags.md``; the documented default for the Odin-like layout written by
:mod:`diffgcl.data.synth` is ``diffgcl/data/odin_topics.yaml`` (:func:`default_topic_map`), and
``diffgcl/data/other_boat_topics.yaml`` is the map of the synthetic "other boat" layout (GNSS
fix, NED odometry, radar point cloud, percent/degree commands). In short::

    position: {topic: /gnss/fix, latency: 0.2}            # Odometry or NavSatFix
    heading:  {topic: /imu/data, frame: enu}              # Imu or Odometry
    commands: {topic: /jet/cmd, thrust_field: throttle, thrust_unit: percent,
               thrust_max: 12000, nozzle_field: steering, nozzle_unit: deg,
               nozzle_positive: starboard}
    radar: {topic: /radar/points, max_gap: 6.0, filter: {min_range: 15, min_intensity: 0.45,
            persistence: {scans: 2, hits: 1, radius: 10}}}

Every role takes ``topic`` and the timing keys ``time_source`` (``header``: the message's header
stamp, ``receive``: the bag's receive time), ``latency`` (s, subtracted from that time: the
measurement happened this long before it) and ``bad_stamps`` (``error``: a stamp going backwards
rejects the bag; ``mask``: such messages are dropped and the steps they would cover masked).
"""

from __future__ import annotations

import math
import os
import typing
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

DEFAULT_TOPIC_MAP = Path(__file__).with_name("odin_topics.yaml")
OTHER_BOAT_TOPIC_MAP = Path(__file__).with_name("other_boat_topics.yaml")


class TopicMapError(ValueError):
    """A topic map file is malformed (unknown key, missing topic, wrong value)."""


def _key(default=MISSING, *, choices=None, minimum=None, maximum=None, unit=""):
    """A topic-map key: its default and what the parser accepts."""
    meta = {"choices": choices, "minimum": minimum, "maximum": maximum, "unit": unit}
    if default is MISSING:
        return field(metadata=meta)
    return field(default=default, metadata=meta)


TIME_SOURCES = ("header", "receive")
BAD_STAMPS = ("error", "mask")
FRAMES = ("enu", "ned")
THRUST_UNITS = ("N", "kN", "percent", "fraction")
NOZZLE_UNITS = ("rad", "deg", "percent", "fraction")
NOZZLE_SIDES = ("port", "starboard")
AMBIGUOUS = ("skip", "keep")


@dataclass(frozen=True)
class TopicSpec:
    """A topic and how its messages are timed (obstacle position, episode markers; the base of
    every other role). ``latency`` (s) is subtracted from the chosen time source."""

    topic: str
    time_source: str = _key("header", choices=TIME_SOURCES)
    latency: float = _key(0.0, minimum=0.0, unit="s")
    bad_stamps: str = _key("error", choices=BAD_STAMPS)


@dataclass(frozen=True)
class SignalSpec(TopicSpec):
    """A continuous signal: the longest gap (s) interpolated across, and the frame of an
    Odometry/Imu message (``enu``: x east, y north, z up, body x forward y port; ``ned``: x north,
    y east, z down, body x forward y starboard)."""

    max_gap: float = _key(0.5, minimum=0.0, unit="s")
    frame: str = _key("enu", choices=FRAMES)


@dataclass(frozen=True)
class CommandSpec(TopicSpec):
    """Operator commands (thrust, nozzle), usually published only on change (zero-order hold).

    ``thrust_field``/``nozzle_field`` name the message fields (dotted paths allowed).
    Units: thrust in ``N``, ``kN``, ``percent`` or ``fraction`` of ``thrust_max`` (N); nozzle in
    ``rad``, ``deg``, ``percent`` or ``fraction`` of ``nozzle_max_deg``; ``nozzle_positive`` is
    the side a positive nozzle turns the bow to (the model's convention is ``port``).
    ``thrust_scale``/``nozzle_scale`` multiply after the unit conversion. ``max_gap`` is the
    longest silence after which a held command is no longer trusted (0 = hold forever).
    """

    thrust_field: str = "thrust"
    nozzle_field: str = "nozzle"
    thrust_unit: str = _key("N", choices=THRUST_UNITS)
    thrust_max: float | None = _key(None, minimum=0.0, unit="N")
    nozzle_unit: str = _key("rad", choices=NOZZLE_UNITS)
    nozzle_max_deg: float | None = _key(None, minimum=0.0, maximum=180.0, unit="deg")
    nozzle_positive: str = _key("port", choices=NOZZLE_SIDES)
    thrust_scale: float = 1.0
    nozzle_scale: float = 1.0
    max_gap: float = _key(0.0, minimum=0.0, unit="s")

    def __post_init__(self):
        if self.thrust_unit in ("percent", "fraction") and not self.thrust_max:
            raise ValueError(f"thrust_unit: {self.thrust_unit!r} needs thrust_max (N)")
        if self.nozzle_unit in ("percent", "fraction") and not self.nozzle_max_deg:
            raise ValueError(f"nozzle_unit: {self.nozzle_unit!r} needs nozzle_max_deg (deg)")

    def to_si(self, thrust, nozzle) -> tuple[np.ndarray, np.ndarray]:
        """Raw field values ([n] each) -> (thrust N, nozzle rad positive to port)."""
        thrust = (
            np.asarray(thrust, float)
            * {
                "N": 1.0,
                "kN": 1000.0,
                "percent": (self.thrust_max or 0.0) / 100.0,
                "fraction": self.thrust_max or 0.0,
            }[self.thrust_unit]
        )
        full = np.deg2rad(self.nozzle_max_deg or 0.0)
        nozzle = (
            np.asarray(nozzle, float)
            * {
                "rad": 1.0,
                "deg": np.pi / 180.0,
                "percent": full / 100.0,
                "fraction": full,
            }[self.nozzle_unit]
        )
        sign = 1.0 if self.nozzle_positive == "port" else -1.0
        return thrust * self.thrust_scale, sign * nozzle * self.nozzle_scale


@dataclass(frozen=True)
class Persistence:
    """Keep a return only if, in at least ``hits`` of the ``scans`` previous scans, there was a
    return within ``radius + radius_growth * range`` (m; range from the boat) of it in the local
    (world) frame: static objects persist, sea clutter does not. The radius grows with range as
    a return's position error does (bearing error times range). ``coast``: a kept return that
    finds no return within that radius in the next scan is carried into it (in the local frame),
    for at most this many scans, as a radar tracker coasts a confirmed target through a missed
    detection. Needs the boat's pose at each scan."""

    scans: int = _key(2, minimum=1)
    hits: int = _key(1, minimum=1)
    radius: float = _key(5.0, minimum=0.0, unit="m")
    radius_growth: float = _key(0.0, minimum=0.0, unit="m/m")
    coast: int = _key(0, minimum=0)

    def __post_init__(self):
        if self.hits > self.scans:
            raise ValueError(f"hits: {self.hits} > scans: {self.scans}")


@dataclass(frozen=True)
class ClutterFilter:
    """Which returns of a range sensor count, as a radar operator would set it: ranges (from
    the sensor) in [``min_range``, ``max_range``] m, intensity at least ``min_intensity`` (only
    where the message has intensities: the ``intensity_field`` of a PointCloud2, the
    ``intensities`` of a RadarSector), and, optionally, :class:`Persistence` over scans."""

    min_range: float = _key(0.0, minimum=0.0, unit="m")
    max_range: float | None = _key(None, minimum=0.0, unit="m")
    min_intensity: float | None = None
    intensity_field: str = "intensity"
    persistence: Persistence | None = None

    def __post_init__(self):
        if self.max_range is not None and self.max_range <= self.min_range:
            raise ValueError(f"max_range: {self.max_range} must exceed min_range {self.min_range}")


@dataclass(frozen=True)
class RangeSensorSpec(TopicSpec):
    """A range sensor (LaserScan, PointCloud2 or a radar-sector message): the longest time (s)
    a scan stays valid, its mounting ``[x, y, yaw]`` in the hull frame (m, m, rad; x forward,
    y to port) and an optional :class:`ClutterFilter`."""

    max_gap: float = _key(0.5, minimum=0.0, unit="s")
    mount: tuple[float, float, float] = (0.0, 0.0, 0.0)
    filter: ClutterFilter | None = None


@dataclass(frozen=True)
class ActuatorLags:
    """First-order lags (s) of the jets, used to reconstruct the actuator states from the
    commands when the bag has no actuator feedback. None: the hull model's default."""

    thrust: float | None = _key(None, minimum=0.0, unit="s")
    nozzle: float | None = _key(None, minimum=0.0, unit="s")


@dataclass(frozen=True)
class SegmentRules:
    """Episode segmentation when a bag has no markers.

    An episode is a stretch where the speed over ground is at least ``min_speed`` (m/s; dips
    shorter than ``bridge_s`` are bridged), the position stream has no gap longer than
    ``split_gap_s`` and the heading stays within ``max_course_change_deg`` of its value at the
    start of the stretch (a U-turn onto a repositioning leg ends the episode; the next one starts
    when the heading has settled for ``settle_s``). With ``require_obstacle`` (and an obstacle
    topic or range sensors) a stretch is an episode only if the boat heads for an obstacle and
    passes it within ``obstacle_search.gate``; other stretches are transits and skipped with a
    warning. An episode ends ``tail_s`` after the boat, past the obstacle, is back within
    ``return_m`` of its approach course (the line from its start through the obstacle), so a
    repositioning leg that carries on straight is not glued to it.
    """

    min_speed: float = _key(1.0, minimum=0.0, unit="m/s")
    bridge_s: float = _key(3.0, minimum=0.0, unit="s")
    split_gap_s: float = _key(5.0, minimum=0.0, unit="s")
    max_course_change_deg: float = _key(75.0, minimum=0.0, maximum=360.0, unit="deg")
    settle_s: float = _key(5.0, minimum=0.0, unit="s")
    require_obstacle: bool = True
    return_m: float = _key(5.0, minimum=0.0, unit="m")
    tail_s: float = _key(10.0, minimum=0.0, unit="s")


@dataclass(frozen=True)
class ObstacleSearch:
    """The pole's position from range scans, when the bag has no obstacle topic.

    Returns of every scan in the episode are put in the local frame; clusters of radius
    ``cluster`` (m) seen in at least ``min_scans`` scans are static objects. The episode's
    obstacle is the object the boat heads for (for ``aim_window_s`` seconds before the closest
    approach, the median bearing off the bow at most ``aim_deg``) and passes within ``gate``
    (m). Several such objects make the episode ambiguous: ``skip`` leaves it out (with a
    warning), ``keep`` keeps it flagged.
    """

    gate: float = _key(60.0, minimum=0.0, unit="m")
    aim_deg: float = _key(10.0, minimum=0.0, maximum=180.0, unit="deg")
    aim_window_s: float = _key(10.0, minimum=0.0, unit="s")
    cluster: float = _key(5.0, minimum=0.0, unit="m")
    min_scans: int = _key(3, minimum=1)
    ambiguous: str = _key("skip", choices=AMBIGUOUS)


@dataclass(frozen=True)
class TopicMap:
    """Which topics give which signal (see the module docstring and ``docs/bags.md``).

    ``datum`` is ``(lat, lon)`` in degrees, or None to use the first fix of each bag.
    """

    position: SignalSpec
    heading: SignalSpec
    commands: CommandSpec
    velocity: SignalSpec | None = None
    actuators: CommandSpec | None = None
    lidar: RangeSensorSpec | None = None
    radar: RangeSensorSpec | None = None
    obstacle: TopicSpec | None = None
    markers: TopicSpec | None = None
    datum: tuple[float, float] | None = None
    min_episode_s: float = _key(10.0, minimum=0.0, unit="s")
    actuator_lags: ActuatorLags = field(default_factory=ActuatorLags)
    segmentation: SegmentRules = field(default_factory=SegmentRules)
    obstacle_search: ObstacleSearch = field(default_factory=ObstacleSearch)
    source: str = ""

    def roles(self) -> dict[str, TopicSpec]:
        """Role -> spec for every role that is set."""
        return {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if isinstance(getattr(self, f.name), TopicSpec)
        }

    def topics(self) -> dict[str, str]:
        """Role -> topic for every role that is set."""
        return {role: spec.topic for role, spec in self.roles().items()}

    def replace(self, **changes: Any) -> TopicMap:
        """A copy with some roles changed (``None`` drops an optional role)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(changes)
        return TopicMap(**values)


ROLES = ("position", "heading", "velocity", "commands", "actuators", "lidar", "radar")
ROLES += ("obstacle", "markers")
REQUIRED = ("position", "heading", "commands")
_SECTIONS = ("actuator_lags", "segmentation", "obstacle_search")


def _optional_inner(hint) -> tuple[Any, bool]:
    """(T, True) for ``T | None``, (hint, False) otherwise."""
    args = typing.get_args(hint)
    if type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return rest[0], True
    return hint, False


def _convert(key: str, hint, value: Any, meta: dict) -> Any:
    inner, optional = _optional_inner(hint)
    if value is None:
        if optional:
            return None
        raise ValueError(f"{key}: a value is required")
    if is_dataclass(inner):
        return _parse_dataclass(key, inner, value)
    if inner is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{key}: expected true or false, got {value!r}")
        return value
    if inner is str:
        if not isinstance(value, str):
            raise ValueError(f"{key}: expected a string, got {value!r}")
        if meta.get("choices") and value not in meta["choices"]:
            raise ValueError(f"{key}: {value!r} is not one of {', '.join(meta['choices'])}")
        return value
    if inner is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{key}: expected an integer, got {value!r}")
        number = value
    elif inner is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{key}: expected a number, got {value!r}")
        number = float(value)
        if not math.isfinite(number):
            raise ValueError(f"{key}: expected a finite number, got {value!r}")
    elif typing.get_origin(inner) is tuple:
        n = len(typing.get_args(inner))
        if not isinstance(value, list | tuple) or len(value) != n:
            raise ValueError(f"{key}: expected a list of {n} numbers, got {value!r}")
        return tuple(_convert(key, float, v, {}) for v in value)
    else:  # pragma: no cover - a new field type without a parser
        raise TypeError(f"{key}: no parser for {inner}")
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    if meta.get("minimum") is not None and number < meta["minimum"]:
        raise ValueError(f"{key}: {value!r} is below the minimum {meta['minimum']}{unit}")
    if meta.get("maximum") is not None and number > meta["maximum"]:
        raise ValueError(f"{key}: {value!r} is above the maximum {meta['maximum']}{unit}")
    return number


def _parse_dataclass(key: str, cls, value: Any):
    if not isinstance(value, dict):
        raise ValueError(f"{key}: expected a mapping, got {value!r}")
    hints = typing.get_type_hints(cls)
    known = [f.name for f in fields(cls) if f.name != "source"]
    unknown = sorted(set(value) - set(known))
    if unknown:
        raise ValueError(f"{key}: unknown key(s) {unknown}; known: {known}")
    missing = [
        f.name
        for f in fields(cls)
        if f.default is MISSING and f.default_factory is MISSING and f.name not in value
    ]
    if missing:
        raise ValueError(f"{key}: missing key(s) {missing}")
    kwargs = {
        f.name: _convert(f"{key}.{f.name}", hints[f.name], value[f.name], dict(f.metadata))
        for f in fields(cls)
        if f.name in value
    }
    try:
        return cls(**kwargs)
    except ValueError as err:
        raise ValueError(f"{key}.{err}") from None


def _field_of(cls, name: str):
    return next(f for f in fields(cls) if f.name == name)


def _parse_role(role: str, value: Any) -> TopicSpec:
    cls = typing.get_type_hints(TopicMap)[role]
    cls, _ = _optional_inner(cls)
    if isinstance(value, str):
        value = {"topic": value}
    if not isinstance(value, dict):
        raise ValueError(f"{role}: expected a topic name or a mapping with 'topic', got {value!r}")
    if not isinstance(value.get("topic"), str) or not value["topic"].startswith("/"):
        raise ValueError(f"{role}.topic: must be an absolute topic name like /odom")
    return _parse_dataclass(role, cls, value)


def parse_topic_map(data: Any, where: str = "<topic map>") -> TopicMap:
    """Build a :class:`TopicMap` from the parsed YAML mapping ``data``; errors name ``where``
    and the key."""
    if not isinstance(data, dict):
        raise TopicMapError(f"{where}: expected a mapping at the top level")
    known = list(ROLES) + ["datum", "min_episode_s", *_SECTIONS]
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise TopicMapError(f"{where}: unknown key(s) {unknown}; known: {known}")
    missing = [r for r in REQUIRED if data.get(r) is None]
    if missing:
        raise TopicMapError(f"{where}: missing required role(s) {missing}")
    hints = typing.get_type_hints(TopicMap)
    kwargs: dict[str, Any] = {}
    try:
        for role in ROLES:
            if data.get(role) is not None:
                kwargs[role] = _parse_role(role, data[role])
        for section in _SECTIONS:
            if data.get(section) is not None:
                kwargs[section] = _parse_dataclass(section, hints[section], data[section])
        if "min_episode_s" in data:
            meta = dict(_field_of(TopicMap, "min_episode_s").metadata)
            kwargs["min_episode_s"] = _convert("min_episode_s", float, data["min_episode_s"], meta)
        datum = data.get("datum")
        if datum is not None:
            if not isinstance(datum, dict) or set(datum) != {"lat", "lon"}:
                raise ValueError(f"datum: expected {{lat: deg, lon: deg}}, got {datum!r}")
            lat = _convert("datum.lat", float, datum["lat"], {"minimum": -90, "maximum": 90})
            lon = _convert("datum.lon", float, datum["lon"], {"minimum": -180, "maximum": 180})
            kwargs["datum"] = (lat, lon)
    except ValueError as err:
        raise TopicMapError(f"{where}: {err}") from None
    return TopicMap(source=where, **kwargs)


def load_topic_map(path: str | os.PathLike | None = None) -> TopicMap:
    """Read a topic map YAML file (``None``: the default Odin-like map)."""
    path = Path(path) if path is not None else DEFAULT_TOPIC_MAP
    try:
        text = path.read_text()
    except OSError as err:
        raise TopicMapError(f"{path}: cannot read topic map ({err.strerror})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise TopicMapError(f"{path}: invalid YAML: {str(err).splitlines()[0]}") from None
    return parse_topic_map(data, str(path))


def default_topic_map() -> TopicMap:
    """The documented map for the Odin-like layout (``odin_topics.yaml``)."""
    return load_topic_map(DEFAULT_TOPIC_MAP)


def other_boat_topic_map() -> TopicMap:
    """The map of the synthetic "other boat" layout (``other_boat_topics.yaml``)."""
    return load_topic_map(OTHER_BOAT_TOPIC_MAP)


def key_reference() -> list[tuple[str, str, Any, str]]:
    """(key path, type, default, unit) of every topic-map key, for the documentation."""
    rows: list[tuple[str, str, Any, str]] = []

    def walk(prefix: str, cls) -> None:
        hints = typing.get_type_hints(cls)
        for f in fields(cls):
            if f.name == "source":
                continue
            inner, _ = _optional_inner(hints[f.name])
            if is_dataclass(inner):
                walk(f"{prefix}{f.name}.", inner)
                continue
            default = f.default if f.default is not MISSING else "(required)"
            rows.append((prefix + f.name, str(hints[f.name]), default, f.metadata.get("unit", "")))

    walk("", TopicMap)
    return rows
