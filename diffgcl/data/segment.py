"""Episode segmentation: where in a bag each demonstration starts and ends.

*Markers.* A ``std_msgs/String`` topic with ``start ...`` / ``end ...`` messages. Tokens after
the keyword are kept: ``key=value`` pairs as metadata (``start set=2 pole=green``), a bare token
as the episode's id (``start 1`` -> ``marker_id: "1"``; its ``end 1`` must match).

*Rules* (:class:`~diffgcl.data.topics.SegmentRules`), when a bag has no markers, within the
stretches where the boat is underway (split at long position gaps):

* with obstacles known (the obstacle topic, or static objects found in the scans), one episode per
  *run* (:func:`runs_at_objects`): a place where the boat headed for an object (aim, see
  :class:`~diffgcl.data.topics.ObstacleSearch`) and passed it within the gate. The run starts
  where the boat turned onto that approach and ends ``tail_s`` after it is back on its approach
  course past the object, or where it turns away by more than ``max_course_change_deg``, or
  where the next run starts. Everything else (repositioning legs, transits) is left out.
* without (or with ``require_obstacle: false``), the stretches cut at turns of more than
  ``max_course_change_deg`` (:func:`split_at_turns`).
"""

from __future__ import annotations

import numpy as np

from diffgcl.data.bags import BagError, TopicMessages
from diffgcl.data.scans import aim_window, wrap_angle
from diffgcl.data.signals import NS, Signal, interpolate, require_type
from diffgcl.data.topics import ObstacleSearch, SegmentRules

MARKER_TYPES = ("std_msgs/msg/String",)

# A heading is "settled" when it stays within this of its value for rules.settle_s; a piece ends
# where the turn that took it past max_course_change_deg began (heading rate above TURN_RATE_DEG
# deg/s towards the turn). A run's approach starts where the heading last was more than
# APPROACH_TURN_DEG off its heading while aiming at the object.
SETTLE_DEG = 10.0
TURN_RATE_DEG = 3.0
APPROACH_TURN_DEG = 30.0


def parse_marker(text: str) -> tuple[str, dict[str, str]]:
    """``"start set=2 pole=green"`` -> ("start", {"set": "2", "pole": "green"});
    ``"start 1"`` -> ("start", {"marker_id": "1"})."""
    parts = text.split()
    kind = parts[0].lower() if parts else ""
    info = dict(p.split("=", 1) for p in parts[1:] if "=" in p)
    ids = [p for p in parts[1:] if "=" not in p]
    if ids:
        info["marker_id"] = " ".join(ids)
    return kind, info


def segments_from_markers(path, data: TopicMessages) -> list[tuple[int, int, dict]]:
    """(start ns, end ns, info) per ``start``/``end`` pair; unmatched markers are errors."""
    require_type(path, data, MARKER_TYPES, "markers")
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
            if "marker_id" in kv and "marker_id" in info and kv["marker_id"] != info["marker_id"]:
                raise BagError(
                    path,
                    f"end marker {m.data!r} does not match start marker id {info['marker_id']!r}",
                    data.topic,
                    t,
                )
            out.append((open_at, int(t), info))
            open_at = None
    if open_at is not None:
        raise BagError(path, "episode start marker without an end", data.topic, open_at)
    return out


def underway_stretches(
    position: Signal, velocity: Signal | None, rules: SegmentRules
) -> list[tuple[int, int]]:
    """(start ns, end ns) of the maximal stretches with speed >= ``rules.min_speed`` (dips
    shorter than ``bridge_s`` bridged), split at position gaps longer than ``split_gap_s``."""
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
    return [(int(a), int(b)) for a, b in segs]


def split_at_turns(t: np.ndarray, psi: np.ndarray, rules: SegmentRules) -> list[tuple[int, int]]:
    """Pieces (start ns, end ns) of one underway stretch, t: [n] ns, psi: [n] unwrapped heading
    (rad): each piece starts where the heading has settled (within SETTLE_DEG for ``settle_s``)
    and ends where the turn began that takes the heading more than ``max_course_change_deg``
    away from its value at the start."""
    settle = np.deg2rad(SETTLE_DEG)
    limit = np.deg2rad(rules.max_course_change_deg)
    window = int(rules.settle_s * NS)
    rate = np.gradient(psi, t * 1e-9) if t.size > 1 else np.zeros_like(psi)
    window_end = np.searchsorted(t, t + window, side="right")

    def settled(j: int) -> bool:
        if t[-1] - t[j] < window:
            return False  # too little left to tell
        return bool(np.max(np.abs(psi[j : window_end[j]] - psi[j])) <= settle)

    out = []
    i, n = 0, t.size
    while i < n:
        j = i
        while j < n and not settled(j):
            j += 1
        if j >= n:
            break
        dev = np.abs(psi[j:] - psi[j])
        over = np.flatnonzero(dev > limit)
        if not over.size:
            out.append((int(t[j]), int(t[-1])))
            break
        k = j + int(over[0])
        end = _turn_start(psi, rate, j, k)
        if end > j:
            out.append((int(t[j]), int(t[end])))
        i = k
    return out


def _turn_start(psi: np.ndarray, rate: np.ndarray, ref: int, k: int) -> int:
    """The index before ``k`` where the turn that took the heading from ``psi[ref]`` to
    ``psi[k]`` began (heading rate last below TURN_RATE_DEG/s towards it)."""
    turning = np.sign(psi[k] - psi[ref]) * rate > np.deg2rad(TURN_RATE_DEG)
    end = k - 1
    while end > ref and turning[end]:
        end -= 1
    return end


def _last_aimed(t, bearing, k: int, search: ObstacleSearch) -> tuple[int, int]:
    """(first, end) sample indices of the last ``aim_window_s`` window (the whole track before
    ``k`` if shorter) before ``k`` whose median |bearing| is within ``aim_deg`` (the best window
    if none is)."""
    window = min(int(round(search.aim_window_s * NS)), int(t[k - 1] - t[0]))
    limit = np.deg2rad(search.aim_deg)
    starts = np.flatnonzero(t[:k] <= t[k - 1] - window)
    for i in starts[::-1][:: max(1, len(starts) // 200)]:
        end = int(np.searchsorted(t, t[i] + window, side="right"))
        if np.median(np.abs(bearing[i:end])) <= limit:
            return int(i), end
    _, i = aim_window(t, bearing, k, search.aim_window_s)
    return int(i), int(np.searchsorted(t, t[i] + window, side="right"))


def _track(position: Signal, heading: Signal, a: int, b: int):
    sel = (position.t >= a) & (position.t <= b)
    t, xy = position.t[sel], position.v[sel]
    psi, ok = interpolate(Signal(heading.topic, heading.t, heading.v, np.inf), t)
    return t[ok], xy[ok], psi[ok, 0]


def runs_at_objects(
    t: np.ndarray,
    xy: np.ndarray,
    psi: np.ndarray,
    objects: np.ndarray,
    rules: SegmentRules,
    search: ObstacleSearch,
) -> list[tuple[int, int, int]]:
    """(start ns, end ns, object index) of the runs of one underway stretch (t: [n] ns, xy:
    [n, 2], psi: [n] unwrapped heading) at ``objects`` [M, 2] (see the module docstring).

    Passes whose approach overlaps an earlier run's end belong to that run (two objects side by
    side: the episode's obstacle is then ambiguous, decided by the obstacle search).
    """
    if t.size < 2:
        return []
    rate = np.gradient(psi, t * 1e-9)
    objects = np.asarray(objects, float).reshape(-1, 2)
    passes = []
    for j, obj in enumerate(objects):
        rel = obj - xy
        dist = np.hypot(rel[:, 0], rel[:, 1])
        bearing = wrap_angle(np.arctan2(rel[:, 1], rel[:, 0]) - psi)
        inside = np.concatenate([[0], (dist <= search.gate).astype(int), [0]])
        edges = np.flatnonzero(np.diff(inside))
        for lo, hi in zip(edges[::2], edges[1::2], strict=True):
            k = lo + int(np.argmin(dist[lo:hi]))
            aim, _ = aim_window(t, bearing, k, search.aim_window_s)
            if aim <= np.deg2rad(search.aim_deg):
                # The final approach: the last aimed window before the pass.
                first, last = _last_aimed(t, bearing, k, search)
                passes.append((k, first, float(np.median(psi[first:last])), j))
    passes.sort()
    runs: list[tuple[int, int, int]] = []
    last_end = -1
    limit, turn = np.deg2rad(rules.max_course_change_deg), np.deg2rad(APPROACH_TURN_DEG)
    for n, (k, first, heading, j) in enumerate(passes):
        if first <= last_end:
            continue
        # Start: back along the approach while the heading stays near the final approach's.
        i = first
        while i - 1 > last_end and abs(psi[i - 1] - heading) <= turn:
            i -= 1
        # End: where a turn away from the approach course begins, ...
        end = t.size - 1
        over = np.flatnonzero(np.abs(psi[k:] - heading) > limit)
        if over.size:
            end = _turn_start(psi, rate, first, k + int(over[0]))
        # ... tail_s after the boat is back within return_m of the course line (through the
        # object along the final approach's heading), ...
        normal = np.array([-np.sin(heading), np.cos(heading)])
        back = np.flatnonzero(np.abs((xy[k:] - objects[j]) @ normal) <= rules.return_m)
        if back.size:
            tail = t[k + back[0]] + round(rules.tail_s * NS)
            end = min(end, int(np.searchsorted(t, tail, side="right")) - 1)
        # ... or where the approach of a later pass starts.
        later = [p[1] for p in passes[n + 1 :] if p[1] > k]
        if later:
            end = min(end, min(later) - 1)
        if end > i:
            runs.append((int(t[i]), int(t[end]), j))
            last_end = end
    return runs


def segments_from_rules(
    position: Signal,
    heading: Signal,
    velocity: Signal | None,
    rules: SegmentRules,
    search: ObstacleSearch,
    objects: np.ndarray | None = None,
) -> tuple[list[tuple[int, int, dict]], list[tuple[int, int]]]:
    """Episodes (start ns, end ns, {}) by rules and the underway spans left out (transits), see
    the module docstring; ``objects`` [M, 2]: obstacle positions known from the obstacle topic or
    the scans (None: cut at turns)."""
    out: list[tuple[int, int, dict]] = []
    left_out: list[tuple[int, int]] = []
    for a, b in underway_stretches(position, velocity, rules):
        t, xy, psi = _track(position, heading, a, b)
        if t.size < 2:
            continue
        if objects is not None and rules.require_obstacle:
            pieces = [(p, q) for p, q, _ in runs_at_objects(t, xy, psi, objects, rules, search)]
        else:
            pieces = split_at_turns(t, psi, rules)
        out.extend((p, q, {}) for p, q in pieces)
        cursor = int(t[0])
        for p, q in [*pieces, (int(t[-1]) + 1, int(t[-1]) + 1)]:
            if p - cursor > rules.settle_s * NS:
                left_out.append((cursor, min(p, int(t[-1]))))
            cursor = max(cursor, q)
    return out, left_out
