"""A starting topic map for a new bag layout (``diffgcl bags template BAG``), written from what
:func:`~diffgcl.data.bags.inspect_bag` found.

Roles are given topics by message type (and name where types do not decide: a LiDAR scans at
several Hz, a radar every few seconds; the obstacle topic's name mentions an obstacle or pole);
``max_gap`` from each topic's period; ``time_source: receive`` where header stamps go backwards;
the heading and odometry ``frame`` (ENU or NED) from the heading that matches the direction of
motion; the command fields from the names of the custom message's numeric fields, with their
observed ranges next to the unit keys to check. Everything the bag cannot tell is a ``TODO``
comment. The text parses with :func:`~diffgcl.data.topics.parse_topic_map` as written.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from diffgcl.data.bags import BagSummary, TopicSummary, inspect_bag, read_topics
from diffgcl.data.scans import message_fields
from diffgcl.data.signals import latlon_to_local, ned_yaw_to_enu, quaternion_yaw

_SENSOR_NAMESPACES = ("sensor_msgs", "nav_msgs", "geometry_msgs", "std_msgs")
_THRUST_NAMES = re.compile(r"thrust|throttle|rpm|power|speed|engine", re.I)
_NOZZLE_NAMES = re.compile(r"nozzle|steer|rudder|helm|angle|azimuth", re.I)
_OBSTACLE_NAMES = re.compile(r"obstacle|pole|buoy|target|mark", re.I)


def _of_type(summary: BagSummary, *types: str) -> list[TopicSummary]:
    return [t for t in summary.topics if t.msgtype in types and t.count]


def _max_gap(t: TopicSummary, minimum: float = 0.5) -> float:
    """2.5 periods, at least ``minimum`` s, rounded up to 0.1 s."""
    period = t.period_s if np.isfinite(t.period_s) else 0.0
    return float(np.ceil(max(minimum, 2.5 * period) * 10) / 10)


def _timing(t: TopicSummary) -> dict[str, Any]:
    return {"time_source": "receive"} if t.backwards else {}


def _numeric_fields(msg: Any) -> dict[str, float]:
    out = {}
    for name in message_fields(msg):
        if name == "header":
            continue
        value = getattr(msg, name)
        if isinstance(value, int | float | np.number) and not isinstance(value, bool):
            out[name] = float(value)
    return out


def _command_topic(path, summary: BagSummary, used: set[str]):
    """(topic summary, thrust field, nozzle field, {field: (min, max)}) of the best-looking
    command topic: a custom message type with two numeric fields named like thrust and nozzle,
    the least regular such topic first (commands are published on change)."""
    custom = [
        t
        for t in summary.topics
        if t.count and t.topic not in used and t.msgtype.split("/")[0] not in _SENSOR_NAMESPACES
    ]
    if not custom:
        return None
    data = read_topics(path, [t.topic for t in custom])
    best = None
    for t in custom:
        msgs = data[t.topic].msgs
        fields = _numeric_fields(msgs[0]) if msgs else {}
        thrust = next((f for f in fields if _THRUST_NAMES.search(f)), None)
        nozzle = next((f for f in fields if _NOZZLE_NAMES.search(f) and f != thrust), None)
        if thrust is None or nozzle is None:
            continue
        values = np.array(
            [[_numeric_fields(m).get(f, np.nan) for f in (thrust, nozzle)] for m in msgs]
        )
        ranges = {
            thrust: (float(np.nanmin(values[:, 0])), float(np.nanmax(values[:, 0]))),
            nozzle: (float(np.nanmin(values[:, 1])), float(np.nanmax(values[:, 1]))),
        }
        score = (t.pattern != "periodic", -t.rate_hz)
        if best is None or score > best[0]:
            best = (score, t, thrust, nozzle, ranges)
    return None if best is None else best[1:]


def _frame_of(path, position: TopicSummary | None, heading: TopicSummary) -> str | None:
    """``enu``/``ned``: the heading convention under which the IMU/odometry yaw follows the
    direction of motion of the position topic while underway; None if it cannot be told."""
    if position is None:
        return None
    data = read_topics(path, [position.topic, heading.topic])
    pos, head = data[position.topic], data[heading.topic]
    if position.msgtype == "sensor_msgs/msg/NavSatFix":
        ll = np.array([[m.latitude, m.longitude] for m in pos.msgs])
        xy = latlon_to_local(ll[:, 0], ll[:, 1], tuple(ll[0]))
    else:
        xy = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for m in pos.msgs])
    if len(xy) < 3:
        return None
    step = np.diff(xy, axis=0)
    moving = np.hypot(*step.T) > 0.2
    if moving.sum() < 10:
        return None
    t_mid = (pos.stamp_ns[1:] + pos.stamp_ns[:-1])[moving] // 2
    if heading.msgtype == "sensor_msgs/msg/Imu":
        q = np.array(
            [
                [m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w]
                for m in head.msgs
            ]
        )
    else:
        q = np.array(
            [
                [
                    m.pose.pose.orientation.x,
                    m.pose.pose.orientation.y,
                    m.pose.pose.orientation.z,
                    m.pose.pose.orientation.w,
                ]
                for m in head.msgs
            ]
        )
    order = np.argsort(head.stamp_ns)
    yaw = np.unwrap(quaternion_yaw(*q[order].T))
    yaw = np.interp(t_mid, head.stamp_ns[order], yaw)
    course = np.arctan2(step[moving, 1], step[moving, 0])  # ENU course over ground
    if position.msgtype != "sensor_msgs/msg/NavSatFix":
        # The position's own frame is unknown too; only a NavSatFix track fixes East/North.
        return None
    errors = {
        frame: float(np.median(np.abs(np.angle(np.exp(1j * (course - y))))))
        for frame, y in (("enu", yaw), ("ned", ned_yaw_to_enu(yaw)))
    }
    best = min(errors, key=errors.get)
    return best if errors[best] < np.deg2rad(30.0) else None


def _yaml_value(value: Any) -> str:
    if isinstance(value, str):
        return value
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_yaml_value(v) for v in value) + "]"
    return str(value)


def _flow(mapping: dict[str, Any]) -> str:
    return "{" + ", ".join(f"{k}: {_yaml_value(v)}" for k, v in mapping.items()) + "}"


def template_from_bag(path: str | os.PathLike) -> str:
    """YAML text of a starting topic map for the bag at ``path`` (see the module docstring)."""
    path = Path(path)
    summary = inspect_bag(path)
    lines = [
        f"# Topic map drafted by `diffgcl bags template` from {path.name}.",
        "# Check every TODO, then: diffgcl bags convert BAGS --topics THIS_FILE --out DEMOS",
        "# Keys, units and frames: docs/bags.md.",
        "",
    ]
    used: set[str] = set()
    fixes = _of_type(summary, "sensor_msgs/msg/NavSatFix")
    odoms = _of_type(summary, "nav_msgs/msg/Odometry")
    imus = _of_type(summary, "sensor_msgs/msg/Imu")
    obstacles = [
        t
        for t in fixes + _of_type(summary, "geometry_msgs/msg/PointStamped")
        if _OBSTACLE_NAMES.search(t.topic)
    ]
    fixes = [t for t in fixes if t not in obstacles]
    own_fix = max(fixes, key=lambda t: t.rate_hz, default=None)
    odom = max(odoms, key=lambda t: t.rate_hz, default=None)

    if own_fix is not None:
        ll = read_topics(path, [own_fix.topic])[own_fix.topic].msgs[0]
        lines += [
            "# Local frame origin (else the first fix of each bag; one datum keeps bags alike).",
            f"datum: {{lat: {ll.latitude:.6f}, lon: {ll.longitude:.6f}}}",
            "",
        ]
    position = own_fix or odom
    if position is None:
        lines += [
            "# TODO: no NavSatFix or Odometry topic found; position is required.",
            "position: /TODO",
            "",
        ]
    else:
        spec = {"topic": position.topic, "max_gap": _max_gap(position), **_timing(position)}
        if position is own_fix:
            spec["latency"] = 0.0
            lines.append(
                f"# GNSS fixes ({position.rate_hz:.1f} Hz). TODO: latency (s) if the receiver "
                "stamps a fix after taking it."
            )
        else:
            spec["frame"] = "enu"
            lines.append(f"# Odometry pose ({position.rate_hz:.1f} Hz). TODO: frame enu or ned.")
        lines += [f"position: {_flow(spec)}", ""]
        used.add(position.topic)
    heading = max(imus, key=lambda t: t.rate_hz, default=None) or odom
    if heading is None:
        lines += [
            "# TODO: no Imu or Odometry topic found; heading is required.",
            "heading: /TODO",
            "",
        ]
    else:
        frame = _frame_of(path, own_fix, heading)
        note = (
            f"frame {frame} (its yaw follows the GNSS track as {frame.upper()})"
            if frame
            else "TODO: frame enu or ned"
        )
        spec = {
            "topic": heading.topic,
            "max_gap": _max_gap(heading),
            "frame": frame or "enu",
            **_timing(heading),
        }
        lines += [
            f"# Heading and yaw rate ({heading.msgtype}, {heading.rate_hz:.1f} Hz): {note}.",
            f"heading: {_flow(spec)}",
            "",
        ]
        used.add(heading.topic)
    if odom is not None:
        frame = _frame_of(path, own_fix, odom)
        spec = {
            "topic": odom.topic,
            "max_gap": _max_gap(odom),
            "frame": frame or "enu",
            **_timing(odom),
        }
        note = (
            f"frame {frame} from its yaw against the GNSS track"
            if frame
            else "TODO: frame enu or ned"
        )
        lines += [
            f"# Velocity from the odometry twist (body frame): {note}.",
            f"velocity: {_flow(spec)}",
            "",
        ]

    cmd = _command_topic(path, summary, used)
    if cmd is None:
        lines += [
            "# TODO: no custom message with thrust- and nozzle-like fields; commands are required.",
            "commands: {topic: /TODO, thrust_field: thrust, nozzle_field: nozzle}",
            "",
        ]
    else:
        t, thrust, nozzle, ranges = cmd
        used.add(t.topic)
        (t0, t1), (n0, n1) = ranges[thrust], ranges[nozzle]
        lines += [
            f"# Operator commands ({t.msgtype}, {t.pattern}). TODO: units and sign.",
            "commands:",
            f"  topic: {t.topic}",
            f"  thrust_field: {thrust}",
            f"  thrust_unit: N  # observed {t0:g} .. {t1:g}; N, kN, percent or fraction"
            " (+ thrust_max)",
            f"  nozzle_field: {nozzle}",
            f"  nozzle_unit: rad  # observed {n0:g} .. {n1:g}; rad, deg, percent or fraction"
            " (+ nozzle_max_deg)",
            "  nozzle_positive: port  # the side a positive value turns the bow to",
            *(["  time_source: receive"] if t.backwards else []),
            "",
            "# Without actuator feedback the jets' states are the commands through these lags (s).",
            "# TODO: your boat's lags (empty: the hull model's defaults).",
            "actuator_lags: {thrust: null, nozzle: null}",
            "",
        ]
    scans = _of_type(
        summary,
        "sensor_msgs/msg/LaserScan",
        "sensor_msgs/msg/PointCloud2",
        "odin_msgs/msg/RadarSector",
    )
    radar = [
        t
        for t in scans
        if "radar" in t.topic.lower() or t.msgtype == "odin_msgs/msg/RadarSector" or t.rate_hz < 2.0
    ]
    lidar = [t for t in scans if t not in radar]
    if lidar:
        t = max(lidar, key=lambda t: t.rate_hz)
        spec = {"topic": t.topic, "max_gap": _max_gap(t), "mount": [0.0, 0.0, 0.0], **_timing(t)}
        lines += [
            f"# LiDAR ({t.msgtype}, {t.rate_hz:.1f} Hz). TODO: mount [x, y, yaw], hull frame.",
            f"lidar: {_flow(spec)}",
            "",
        ]
    if radar:
        t = min(radar, key=lambda t: t.rate_hz)
        lines += [
            f"# Radar ({t.msgtype}, every {1 / max(t.rate_hz, 1e-9):.1f} s). TODO: mount; tune",
            "# the clutter filter on your data (min_intensity needs intensities in the message).",
            "radar:",
            f"  topic: {t.topic}",
            f"  max_gap: {_max_gap(t, 2.0):g}",
            "  mount: [0.0, 0.0, 0.0]",
            *(["  time_source: receive"] if t.backwards else []),
            "  filter:",
            "    min_range: 15.0",
            "    persistence: {scans: 2, hits: 1, radius: 4.0, radius_growth: 0.03, coast: 1}",
            "",
        ]
    if obstacles:
        t = obstacles[0]
        lines += [
            f"# Surveyed obstacle position ({t.msgtype}).",
            f"obstacle: {_flow({'topic': t.topic, **_timing(t)})}",
            "",
        ]
    else:
        lines += [
            "# No obstacle topic: the pole is estimated from the range sensors (obstacle_search).",
            "",
        ]
    strings = _of_type(summary, "std_msgs/msg/String")
    if strings:
        t = strings[0]
        lines += [
            "# Episode markers ('start ...' / 'end ...').",
            f"markers: {_flow({'topic': t.topic})}",
            "",
        ]
    else:
        lines += ["# No marker topic: episodes are found by rules (segmentation).", ""]
    return "\n".join(lines)
