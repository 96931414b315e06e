"""Topic maps: which ROS topics carry which signal of a demonstration.

A real bag names its topics after the vessel's drivers (``/odin/nav/odom``, ``/radar/sector``,
...); ingestion needs to know which of them gives the position, the heading, the operator's
commands and the range sensors. A topic map is a small YAML file, parsed once into the frozen
:class:`TopicMap` below. The documented default for the Odin-like layout written by
:mod:`diffgcl.data.synth` is ``diffgcl/data/odin_topics.yaml`` (:func:`default_topic_map`).

YAML layout (every key but ``position``, ``heading`` and ``commands`` is optional)::

    datum: {lat: 59.41, lon: 10.48}     # local ENU frame origin for NavSatFix (else first fix)
    min_episode_s: 10.0                 # shorter episodes are an error
    position: {topic: /odin/nav/odom, max_gap: 0.5}
    heading:  {topic: /odin/imu, max_gap: 0.5}
    velocity: {topic: /odin/nav/odom, max_gap: 0.5}
    commands: {topic: /odin/operator/cmd, thrust_field: thrust, nozzle_field: nozzle,
               thrust_scale: 1.0, nozzle_scale: 1.0}
    actuators: {topic: /odin/jets/state, thrust_field: thrust, nozzle_field: nozzle}
    lidar: {topic: /odin/lidar/scan, max_gap: 0.5, mount: [2.0, 0.0, 0.0]}
    radar: {topic: /odin/radar/sector, max_gap: 2.0, mount: [0.0, 0.0, 0.0]}
    obstacle: {topic: /odin/obstacle/fix}
    markers: {topic: /odin/episode}

``max_gap`` (seconds) is the longest interval between two messages across which a continuous
signal is still interpolated (and, for a scan, how long a scan stays valid); grid points inside a
longer gap are masked. ``mount`` is a sensor's pose ``[x, y, yaw]`` in the hull frame (m, m, rad;
x forward, y to port). ``*_scale`` converts a command field to SI units (N, rad).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import yaml

DEFAULT_TOPIC_MAP = Path(__file__).with_name("odin_topics.yaml")


class TopicMapError(ValueError):
    """A topic map file is malformed (unknown key, missing topic, wrong value)."""


@dataclass(frozen=True)
class SignalSpec:
    """A continuous signal: its topic and the longest gap (s) interpolated across."""

    topic: str
    max_gap: float = 0.5


@dataclass(frozen=True)
class CommandSpec:
    """Operator commands (thrust, nozzle), usually published only on change (zero-order hold).

    ``thrust_field``/``nozzle_field`` name the message fields (dotted paths allowed);
    ``thrust_scale``/``nozzle_scale`` convert them to N and rad. ``max_gap`` is the longest
    silence after which a held command is no longer trusted (0 = hold forever).
    """

    topic: str
    thrust_field: str = "thrust"
    nozzle_field: str = "nozzle"
    thrust_scale: float = 1.0
    nozzle_scale: float = 1.0
    max_gap: float = 0.0


@dataclass(frozen=True)
class RangeSensorSpec:
    """A range sensor (LaserScan, PointCloud2 or a radar-sector message) and its mounting."""

    topic: str
    max_gap: float = 0.5
    mount: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class TopicSpec:
    """A topic without further options (obstacle position, episode markers)."""

    topic: str


@dataclass(frozen=True)
class TopicMap:
    """Which topics give which signal (see the module docstring for the YAML form).

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
    min_episode_s: float = 10.0
    source: str = ""

    def topics(self) -> dict[str, str]:
        """Role -> topic for every role that is set."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if hasattr(value, "topic"):
                out[f.name] = value.topic
        return out

    def replace(self, **changes: Any) -> TopicMap:
        """A copy with some roles changed (``None`` drops an optional role)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(changes)
        return TopicMap(**values)


_ROLE_TYPES = {
    "position": SignalSpec,
    "heading": SignalSpec,
    "velocity": SignalSpec,
    "commands": CommandSpec,
    "actuators": CommandSpec,
    "lidar": RangeSensorSpec,
    "radar": RangeSensorSpec,
    "obstacle": TopicSpec,
    "markers": TopicSpec,
}
_REQUIRED = ("position", "heading", "commands")


def _parse_role(where: str, role: str, value: Any):
    cls = _ROLE_TYPES[role]
    if isinstance(value, str):
        value = {"topic": value}
    if not isinstance(value, dict):
        raise TopicMapError(f"{where}: {role}: expected a mapping with 'topic', got {value!r}")
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(value) - known)
    if unknown:
        raise TopicMapError(f"{where}: {role}: unknown key(s) {unknown}; known: {sorted(known)}")
    if not isinstance(value.get("topic"), str) or not value["topic"].startswith("/"):
        raise TopicMapError(f"{where}: {role}: 'topic' must be an absolute topic name")
    kwargs = dict(value)
    try:
        for f in fields(cls):
            if f.name in kwargs and f.name not in ("topic", "thrust_field", "nozzle_field"):
                if f.name == "mount":
                    mount = tuple(float(v) for v in kwargs["mount"])
                    if len(mount) != 3:
                        raise ValueError("mount must be [x, y, yaw]")
                    kwargs["mount"] = mount
                else:
                    kwargs[f.name] = float(kwargs[f.name])
    except (TypeError, ValueError) as err:
        raise TopicMapError(f"{where}: {role}: {err}") from None
    return cls(**kwargs)


def parse_topic_map(data: Any, where: str = "<topic map>") -> TopicMap:
    """Build a :class:`TopicMap` from the parsed YAML mapping ``data``."""
    if not isinstance(data, dict):
        raise TopicMapError(f"{where}: expected a mapping at the top level")
    known = set(_ROLE_TYPES) | {"datum", "min_episode_s"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise TopicMapError(f"{where}: unknown key(s) {unknown}; known: {sorted(known)}")
    missing = [r for r in _REQUIRED if data.get(r) is None]
    if missing:
        raise TopicMapError(f"{where}: missing required role(s) {missing}")
    kwargs: dict[str, Any] = {
        role: _parse_role(where, role, data[role])
        for role in _ROLE_TYPES
        if data.get(role) is not None
    }
    datum = data.get("datum")
    if datum is not None:
        try:
            kwargs["datum"] = (float(datum["lat"]), float(datum["lon"]))
        except (KeyError, TypeError, ValueError):
            raise TopicMapError(f"{where}: datum must be {{lat: deg, lon: deg}}") from None
    if "min_episode_s" in data:
        kwargs["min_episode_s"] = float(data["min_episode_s"])
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
