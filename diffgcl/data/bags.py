"""Reading, writing and inspecting ROS bags without a ROS install (``rosbags``).

Three on-disk formats are supported, named as in the CLI:

* ``ros1`` — a ROS1 bag, one ``.bag`` file (v2.0, message definitions embedded);
* ``ros2-sqlite3`` — a ROS2 bag folder (``metadata.yaml`` + ``.db3``);
* ``ros2-mcap`` — a ROS2 bag folder (``metadata.yaml`` + ``.mcap``).

All three are read through ``rosbags.highlevel.AnyReader``, which rebuilds message classes from
the definitions stored in the bag, so custom types (the Odin-like ``odin_msgs`` below) need no
registration on the reading side. Writers build messages from a typestore
(:func:`typestore_for`) holding the standard ROS1 Noetic / ROS2 Humble types plus the custom
types registered from their ``.msg`` text (:data:`CUSTOM_MSGS`).

Every failure to read is a :class:`BagError` whose message is one line naming the file, the
topic and the time (``-`` where they are not known).
"""

from __future__ import annotations

import os
from collections.abc import Collection, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

FORMATS = ("ros1", "ros2-sqlite3", "ros2-mcap")

# Custom message types of the Odin-like layout, registered from their .msg text.
CUSTOM_MSGS: dict[str, str] = {
    # Operator command, published only when the operator changes it.
    "odin_msgs/msg/JetCommand": (
        "std_msgs/Header header\n"
        "float32 thrust  # commanded total jet thrust [N], negative = reverse bucket\n"
        "float32 nozzle  # commanded nozzle angle [rad], positive turns the bow to port\n"
    ),
    # Water-jet feedback (achieved thrust and nozzle angle).
    "odin_msgs/msg/JetState": (
        "std_msgs/Header header\nfloat32 thrust  # [N]\nfloat32 nozzle  # [rad]\n"
    ),
    # The "other boat" layout's jet command (diffgcl.data.synth, layout="other"): percent and
    # degrees, positive steering to starboard, published on change.
    "jet_msgs/msg/JetCmd": (
        "std_msgs/Header header\n"
        "float64 throttle  # [%] of full thrust, negative = reverse\n"
        "float64 steering  # [deg], positive turns the bow to starboard\n"
    ),
    # One radar sweep reduced to sparse detections in the sensor frame.
    "odin_msgs/msg/RadarSector": (
        "std_msgs/Header header\n"
        "float32 range_max       # [m]\n"
        "float32[] bearings      # [rad], counter-clockwise from the bow\n"
        "float32[] ranges        # [m]\n"
        "float32[] intensities   # [0, 1]\n"
    ),
}


class IngestWarning(UserWarning):
    """A recoverable problem in a bag (dropout, missing optional sensor, masked span)."""


class BagError(Exception):
    """A bag cannot be used. ``str()`` is one line: file, topic, time, reason."""

    def __init__(
        self, path: str | os.PathLike, message: str, topic: str | None = None, time_ns=None
    ):
        self.path = str(path)
        self.topic = topic
        self.time_ns = None if time_ns is None else int(time_ns)
        self.reason = message
        super().__init__(str(self))

    def __str__(self) -> str:
        t = "-" if self.time_ns is None else f"{self.time_ns * 1e-9:.3f}s"
        return f"{self.path}: topic {self.topic or '-'}, t={t}: {self.reason}"


def bag_format(path: str | os.PathLike) -> str:
    """``ros1``, ``ros2-sqlite3`` or ``ros2-mcap`` from the path (raises :class:`BagError`)."""
    p = Path(path)
    if p.is_file() and p.suffix == ".bag":
        return "ros1"
    if p.is_dir():
        if any(p.glob("*.mcap")):
            return "ros2-mcap"
        if any(p.glob("*.db3")):
            return "ros2-sqlite3"
        raise BagError(p, "not a ROS2 bag folder (no .db3 or .mcap file)")
    if not p.exists():
        raise BagError(p, "no such file or folder")
    raise BagError(p, "not a bag (want a .bag file or a ROS2 bag folder)")


def typestore_for(fmt: str):
    """Typestore with the standard types of the format's ROS distribution + :data:`CUSTOM_MSGS`."""
    store = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    types: dict = {}
    for name, text in CUSTOM_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def stamp_ns(msg: Any) -> int | None:
    """Header stamp of a message in ns, or None when it has no header or the stamp is zero."""
    header = getattr(msg, "header", None)
    if header is None:
        return None
    ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return ns if ns > 0 else None


@dataclass(frozen=True)
class TopicMessages:
    """All messages of one topic: bag_ns: [n] int64 receive times, stamp_ns: [n] int64 header
    stamps (bag time where a message has none), msgs: the deserialised messages."""

    topic: str
    msgtype: str
    bag_ns: np.ndarray
    stamp_ns: np.ndarray
    msgs: tuple[Any, ...]


# A topic is periodic when the spread of its intervals (interquartile range) is below this fraction
# of the median interval; otherwise it is published on change (commands, markers) and has no
# "gaps". A periodic topic's gap is an interval longer than GAP_FACTOR median intervals.
PERIODIC_IQR = 0.5
GAP_FACTOR = 3.0
# Header stamps more than this behind the latest one seen go "backwards" (as in ingestion).
BACKWARDS_S = 0.5


@dataclass(frozen=True)
class TopicSummary:
    """Per-topic statistics from :func:`inspect_bag` (times in s, bag receive time unless said).

    pattern: ``periodic``, ``on change`` (irregular intervals: commands, markers) or ``sparse``
    (fewer than 3 messages); rate_hz: messages per second over the topic's span; period_s: the
    median interval; gaps: intervals longer than GAP_FACTOR periods (periodic topics only),
    largest_gap_at_s: where the longest interval starts. header: the messages carry a header
    stamp; backwards: header stamps more than BACKWARDS_S behind the latest one, first at
    backwards_at_s (bag time), by up to backwards_by_s; latency_s: median of receive time minus
    header stamp.
    """

    topic: str
    msgtype: str
    count: int
    first_s: float
    last_s: float
    rate_hz: float
    max_gap_s: float
    gaps: int = 0
    pattern: str = "sparse"
    period_s: float = float("nan")
    largest_gap_at_s: float = float("nan")
    header: bool = False
    backwards: int = 0
    backwards_at_s: float = float("nan")
    backwards_by_s: float = 0.0
    latency_s: float = float("nan")

    def problems(self) -> list[str]:
        """One line per problem found on this topic."""
        out = []
        if self.backwards:
            out.append(
                f"topic {self.topic}: header stamps go backwards {self.backwards} times (first "
                f"at t={self.backwards_at_s:.3f}s, by up to {self.backwards_by_s:.2f} s); in the "
                "topic map use time_source: receive, or bad_stamps: mask"
            )
        if self.gaps:
            hint = (
                ""
                if self.msgtype.split("/")[0] in ("sensor_msgs", "nav_msgs", "geometry_msgs")
                else " (normal if it is published on change: give the topic map to inspect)"
            )
            out.append(
                f"topic {self.topic}: {self.gaps} gaps longer than {GAP_FACTOR:g}x the "
                f"{self.period_s:.3f} s period (longest {self.max_gap_s:.2f} s from "
                f"t={self.largest_gap_at_s:.3f}s){hint}"
            )
        if self.count == 0:
            out.append(f"topic {self.topic}: no messages")
        return out


@dataclass(frozen=True)
class BagSummary:
    """What :func:`inspect_bag` found in one bag."""

    path: str
    format: str
    start_s: float
    end_s: float
    topics: tuple[TopicSummary, ...]

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s

    def problems(self) -> list[str]:
        """One line per problem found (stamps going backwards, gaps in periodic topics)."""
        return [line for t in self.topics for line in t.problems()]

    def format_text(self) -> str:
        """Human-readable table, then the problems found (or that there are none)."""
        lines = [
            f"{self.path} [{self.format}]  {self.duration_s:.1f} s  "
            f"({self.start_s:.3f} .. {self.end_s:.3f})",
            f"  {'topic':<28} {'type':<32} {'msgs':>7} {'rate':>9}  {'pattern':<9} "
            f"{'max gap':>8} {'gaps':>5} {'latency':>8}  stamps",
        ]
        for t in self.topics:
            if not t.header:
                stamps = "no header"
            elif t.backwards:
                stamps = f"{t.backwards} backwards"
            else:
                stamps = "in order"
            latency = f"{t.latency_s * 1e3:6.0f}ms" if t.header else f"{'-':>8}"
            gaps = f"{t.gaps:5d}" if t.pattern == "periodic" else f"{'-':>5}"
            lines.append(
                f"  {t.topic:<28} {t.msgtype:<32} {t.count:>7} {t.rate_hz:>6.2f} Hz  "
                f"{t.pattern:<9} {t.max_gap_s:>6.2f} s {gaps} {latency}  {stamps}"
            )
        problems = self.problems()
        lines.append("  problems:" if problems else "  no problems found")
        lines.extend(f"    {line}" for line in problems)
        return "\n".join(lines)


@contextmanager
def open_bag(path: str | os.PathLike) -> Iterator[AnyReader]:
    """Open a bag of any supported format; read errors become :class:`BagError`."""
    p = Path(path)
    bag_format(p)
    try:
        reader = AnyReader([p], default_typestore=get_typestore(Stores.ROS1_NOETIC))
        reader.open()
    except BagError:
        raise
    except Exception as err:  # rosbags raises many types on corrupt input
        raise BagError(p, f"corrupt or truncated bag ({_one_line(err)})") from None
    try:
        yield reader
    finally:
        # Closing a broken reader must not hide the real error.
        with suppress(Exception):
            reader.close()


def _one_line(err: BaseException) -> str:
    text = f"{type(err).__name__}: {err}".strip()
    return text.splitlines()[0] if text else type(err).__name__


def read_topics(path: str | os.PathLike, topics: Collection[str]) -> dict[str, TopicMessages]:
    """Deserialise every message of ``topics`` (missing topics are simply absent from the result).

    A topic carried by connections of different types is an error.
    """
    p = Path(path)
    wanted = set(topics)
    with open_bag(p) as reader:
        conns = [c for c in reader.connections if c.topic in wanted]
        types: dict[str, str] = {}
        for c in conns:
            if types.setdefault(c.topic, c.msgtype) != c.msgtype:
                raise BagError(p, f"mixed types {types[c.topic]} and {c.msgtype}", c.topic)
        bag: dict[str, list[int]] = {t: [] for t in types}
        stamps: dict[str, list[int]] = {t: [] for t in types}
        msgs: dict[str, list[Any]] = {t: [] for t in types}
        last_topic, last_ns = None, None
        try:
            if conns:
                for conn, t_ns, raw in reader.messages(connections=conns):
                    last_topic, last_ns = conn.topic, t_ns
                    msg = reader.deserialize(raw, conn.msgtype)
                    stamp = stamp_ns(msg)
                    bag[conn.topic].append(t_ns)
                    stamps[conn.topic].append(t_ns if stamp is None else stamp)
                    msgs[conn.topic].append(msg)
        except Exception as err:
            raise BagError(
                p, f"corrupt or truncated bag ({_one_line(err)})", last_topic, last_ns
            ) from None
    return {
        t: TopicMessages(
            topic=t,
            msgtype=types[t],
            bag_ns=np.asarray(bag[t], dtype=np.int64),
            stamp_ns=np.asarray(stamps[t], dtype=np.int64),
            msgs=tuple(msgs[t]),
        )
        for t in types
    }


def topic_types(path: str | os.PathLike) -> dict[str, str]:
    """Topic -> message type of every connection in the bag."""
    with open_bag(path) as reader:
        return {c.topic: c.msgtype for c in reader.connections}


def _raw_stamp(raw: bytes, fmt: str) -> int:
    """Header stamp (ns) of a serialised message whose first field is a std_msgs/Header."""
    if fmt == "ros1":  # uint32 seq, uint32 sec, uint32 nsec
        sec, nsec = np.frombuffer(raw, "<u4", count=2, offset=4)
    else:  # CDR: 4-byte encapsulation header (byte 1: 1 = little endian), int32 sec, uint32 ns
        order = "<" if raw[1] == 1 else ">"
        sec = np.frombuffer(raw, order + "i4", count=1, offset=4)[0]
        nsec = np.frombuffer(raw, order + "u4", count=1, offset=8)[0]
    return int(sec) * 1_000_000_000 + int(nsec)


def _summarise(
    topic, msgtype, bag_ns: np.ndarray, stamp_ns: np.ndarray | None, on_change: bool
) -> TopicSummary:
    """Statistics of one topic; intervals from the header stamps where there are some (free of
    transport jitter), else from the receive times."""
    t = bag_ns * 1e-9
    n = int(t.size)
    if n == 0:
        nan = float("nan")
        return TopicSummary(topic, msgtype, 0, nan, nan, 0.0, 0.0)
    clock = np.sort(stamp_ns) * 1e-9 if stamp_ns is not None and stamp_ns.size else t
    dt = np.diff(clock)
    span = t[-1] - t[0]
    kw: dict[str, Any] = {}
    if n >= 3:
        median = float(np.median(dt))
        q25, q75 = np.percentile(dt, [25, 75])
        periodic = not on_change and median > 0 and (q75 - q25) <= PERIODIC_IQR * median
        kw["pattern"] = "periodic" if periodic else "on change"
        kw["period_s"] = median
        if periodic:
            kw["gaps"] = int(np.sum(dt > GAP_FACTOR * median))
    if dt.size:
        kw["largest_gap_at_s"] = float(clock[int(np.argmax(dt))])
    if stamp_ns is not None and stamp_ns.size:
        kw["header"] = True
        latest = np.maximum.accumulate(stamp_ns)
        behind = (latest[:-1] - stamp_ns[1:]) * 1e-9
        back = np.flatnonzero(behind > BACKWARDS_S)
        if back.size:
            kw["backwards"] = int(back.size)
            kw["backwards_at_s"] = float(t[back[0] + 1])
            kw["backwards_by_s"] = float(behind[back].max())
        kw["latency_s"] = float(np.median((bag_ns - stamp_ns) * 1e-9))
    return TopicSummary(
        topic=topic,
        msgtype=msgtype,
        count=n,
        first_s=float(t[0]),
        last_s=float(t[-1]),
        rate_hz=float((n - 1) / span) if span > 0 else 0.0,
        max_gap_s=float(np.max(dt)) if dt.size else 0.0,
        **kw,
    )


def inspect_bag(path: str | os.PathLike, on_change: Collection[str] = ()) -> BagSummary:
    """Topics, types, message counts, rates, gaps, header-stamp order and latency of one bag
    (reads every record; header stamps come from the raw bytes of messages whose first field is
    a ``std_msgs/Header``, checked against the deserialised first message of each topic).

    ``on_change``: topics known to be published on change (a topic map's commands and markers),
    never called gappy; other topics are classified by the regularity of their intervals.
    """
    p = Path(path)
    fmt = bag_format(p)
    with open_bag(p) as reader:
        times: dict[str, list[int]] = {c.topic: [] for c in reader.connections}
        stamps: dict[str, list[int] | None] = {}
        types = {c.topic: c.msgtype for c in reader.connections}
        raw_fmt = "ros1" if fmt == "ros1" else "cdr"
        last_topic, last_ns = None, None
        try:
            for conn, t_ns, raw in reader.messages():
                last_topic, last_ns = conn.topic, t_ns
                times[conn.topic].append(t_ns)
                if conn.topic not in stamps:
                    msg = reader.deserialize(raw, conn.msgtype)
                    fields = list(getattr(msg, "__dataclass_fields__", ()))
                    has_header = bool(fields) and fields[0] == "header"
                    if has_header and stamp_ns(msg) != _raw_stamp(raw, raw_fmt):
                        has_header = False  # a layout this parser does not know: skip
                    stamps[conn.topic] = [] if has_header else None
                if stamps[conn.topic] is not None:
                    stamps[conn.topic].append(_raw_stamp(raw, raw_fmt))
        except Exception as err:
            raise BagError(
                p, f"corrupt or truncated bag ({_one_line(err)})", last_topic, last_ns
            ) from None
    summaries = []
    for topic in sorted(times):
        bag_ns = np.asarray(times[topic], dtype=np.int64)
        st = stamps.get(topic)
        stamps_ns = None if st is None else np.asarray(st, np.int64)
        summaries.append(_summarise(topic, types[topic], bag_ns, stamps_ns, topic in on_change))
    starts = [s.first_s for s in summaries if s.count]
    ends = [s.last_s for s in summaries if s.count]
    start = min(starts) if starts else 0.0
    end = max(ends) if ends else 0.0
    return BagSummary(path=str(p), format=fmt, start_s=start, end_s=end, topics=tuple(summaries))


class BagWriter:
    """Writes messages of any type to one bag; connections are added on first use.

    >>> with BagWriter(path, "ros1") as w:
    ...     w.write("/topic", "std_msgs/msg/String", t_ns, w.make("std_msgs/msg/String", data="x"))
    """

    def __init__(self, path: str | os.PathLike, fmt: str = "ros1"):
        if fmt not in FORMATS:
            raise ValueError(f"bag format {fmt!r}; choose one of {FORMATS}")
        self.path = Path(path)
        self.format = fmt
        self.typestore = typestore_for(fmt)
        if fmt == "ros1":
            self._writer = Writer1(self.path)
        else:
            plugin = StoragePlugin.MCAP if fmt == "ros2-mcap" else StoragePlugin.SQLITE3
            self._writer = Writer2(self.path, version=9, storage_plugin=plugin)
        self._conns: dict[str, Any] = {}
        self._seq = 0

    def __enter__(self) -> BagWriter:
        self._writer.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._writer.close()

    def make(self, msgtype: str, **fields: Any) -> Any:
        """Instantiate a message class of this writer's typestore."""
        return self.typestore.types[msgtype](**fields)

    def header(self, stamp: int, frame_id: str = "") -> Any:
        """A ``std_msgs/Header`` with the stamp in ns (ROS1 headers also get a sequence number)."""
        time = self.make("builtin_interfaces/msg/Time", sec=stamp // 10**9, nanosec=stamp % 10**9)
        if self.format == "ros1":
            self._seq += 1
            return self.make("std_msgs/msg/Header", seq=self._seq, stamp=time, frame_id=frame_id)
        return self.make("std_msgs/msg/Header", stamp=time, frame_id=frame_id)

    def write(self, topic: str, msgtype: str, t_ns: int, msg: Any) -> None:
        """Serialise ``msg`` and write it at bag time ``t_ns``."""
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
            self._conns[topic] = conn
        if self.format == "ros1":
            data = self.typestore.serialize_ros1(msg, msgtype)
        else:
            data = self.typestore.serialize_cdr(msg, msgtype)
        self._writer.write(conn, int(t_ns), data)


def bag_name(stem: str, fmt: str) -> str:
    """File (ROS1) or folder (ROS2) name of a bag."""
    return f"{stem}.bag" if fmt == "ros1" else stem
