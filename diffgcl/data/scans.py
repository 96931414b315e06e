"""Range scans from bags: decoding, clutter filtering, and where the pole is.

Problem: a bag's LiDAR and radar messages are returns in the sensor frame, each scan stamped at
its own time. Ingestion needs (a) the returns that are real objects — a marine radar sees sea
clutter all around the boat and anything within hundreds of metres — reduced to the simulator's
beams, and (b) when no surveyed obstacle position was recorded, the position of the one pole the
operator avoided in an episode. All functions here are host-side NumPy.

* :func:`decode_scans`: LaserScan / PointCloud2 / RadarSector messages -> hull-frame points per
  scan, after the per-return gates of the topic map's :class:`~diffgcl.data.topics.ClutterFilter`
  (range from the sensor, intensity).
* :func:`persistent`: the filter's persistence test (M of N previous scans, local frame).
* :func:`to_world` / :func:`to_hull`: a scan taken at one pose, seen from another (the held scan
  at each grid step is re-expressed from the boat's pose at that step: motion compensation).
* :func:`radar_sector_ranges`: radar returns -> the layout's radar beams (a beam reads the nearest
  return whose bearing lies in its sector).
* :func:`find_objects` and :func:`estimate_obstacle`: static objects (clusters seen in several
  scans) and the one the boat headed for and passed within a gate; several candidates make the
  episode ambiguous.
* :func:`radar_pole_beam_hit_rate`: how often the radar beam towards the pole reads it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from diffgcl.data.bags import BagError, TopicMessages
from diffgcl.data.topics import ClutterFilter, ObstacleSearch, Persistence, RangeSensorSpec

SCAN_TYPES = (
    "sensor_msgs/msg/LaserScan",
    "sensor_msgs/msg/PointCloud2",
    "odin_msgs/msg/RadarSector",
)

# sensor_msgs/PointField datatypes.
_POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


@dataclass(frozen=True)
class Scans:
    """The scans of one range sensor: t: [n] int64 ns (scan times), points: n arrays [m_i, 2]
    of returns in the hull frame (mount applied) that passed the range/intensity gates,
    returns: [n] number of returns before the gates."""

    role: str
    topic: str
    t: np.ndarray
    points: tuple[np.ndarray, ...]
    returns: np.ndarray
    max_gap: float


def message_fields(msg: Any) -> list[str]:
    """Field names of a deserialised message (for error messages)."""
    names = getattr(msg, "__dataclass_fields__", None)
    if names is None:
        return []
    return [n for n in names if not n.startswith("__")]


def _scan_returns(path, topic: str, msgtype: str, t: int, m: Any, filt: ClutterFilter | None):
    """(xy [m, 2] sensor frame, intensity [m] or None) of one message."""
    if msgtype == "sensor_msgs/msg/LaserScan":
        r = np.asarray(m.ranges, float)
        a = m.angle_min + m.angle_increment * np.arange(r.size)
        ok = np.isfinite(r) & (r >= m.range_min) & (r <= m.range_max)
        inten = np.asarray(m.intensities, float)
        inten = inten[ok] if inten.size == r.size else None
        return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=-1), inten
    if msgtype == "odin_msgs/msg/RadarSector":
        r = np.asarray(m.ranges, float)
        a = np.asarray(m.bearings, float)
        if r.shape != a.shape:
            raise BagError(path, "radar bearings and ranges differ in length", topic, t)
        if not (np.isfinite(r).all() and np.isfinite(a).all()):
            raise BagError(path, "non-finite radar detection (NaN or inf)", topic, t)
        inten = np.asarray(m.intensities, float)
        inten = inten if inten.size == r.size else None
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=-1), inten
    want = filt.intensity_field if filt is not None and filt.min_intensity is not None else None
    return _pointcloud2(path, topic, t, m, want)


def _pointcloud2(path, topic: str, t: int, msg: Any, intensity_field: str | None):
    names = {f.name: f for f in msg.fields}
    if "x" not in names or "y" not in names:
        raise BagError(
            path, f"PointCloud2 without x/y fields (fields: {', '.join(names) or 'none'})", topic, t
        )
    wanted = ["x", "y"] + ([intensity_field] if intensity_field else [])
    if intensity_field and intensity_field not in names:
        raise BagError(
            path,
            f"filter.min_intensity needs the PointCloud2 field {intensity_field!r} "
            f"(fields: {', '.join(names)}; set filter.intensity_field)",
            topic,
            t,
        )
    order = ">" if msg.is_bigendian else "<"
    formats = []
    for n in wanted:
        code = _POINTFIELD_DTYPES.get(int(names[n].datatype))
        if code is None or (n in ("x", "y") and code not in ("f4", "f8")):
            raise BagError(
                path, f"PointCloud2 field {n} has datatype {names[n].datatype}", topic, t
            )
        formats.append(order + code)
    count = int(msg.width) * int(msg.height)
    dtype = np.dtype(
        {
            "names": wanted,
            "formats": formats,
            "offsets": [int(names[n].offset) for n in wanted],
            "itemsize": int(msg.point_step),
        }
    )
    raw = np.asarray(msg.data, np.uint8).tobytes()
    if len(raw) < count * int(msg.point_step):
        raise BagError(path, "PointCloud2 data shorter than width x height x point_step", topic, t)
    pts = np.frombuffer(raw, dtype=dtype, count=count)
    xy = np.stack([pts["x"], pts["y"]], axis=-1).astype(np.float64)
    inten = pts[intensity_field].astype(np.float64) if intensity_field else None
    ok = np.isfinite(xy).all(axis=1)
    return xy[ok], (inten[ok] if inten is not None else None)


def decode_scans(path, data: TopicMessages, spec: RangeSensorSpec, role: str) -> Scans:
    """Every scan of ``data`` as hull-frame points that pass the filter's range and intensity
    gates (persistence needs poses: see :func:`persistent`)."""
    if data.msgtype not in SCAN_TYPES:
        t0 = data.bag_ns[0] if data.bag_ns.size else None
        raise BagError(
            path,
            f"unknown message type {data.msgtype} for {role} (supported: {', '.join(SCAN_TYPES)})",
            data.topic,
            t0,
        )
    filt = spec.filter
    mx, my, myaw = spec.mount
    c, s = np.cos(myaw), np.sin(myaw)
    points, returns = [], []
    for m, t in zip(data.msgs, data.stamp_ns, strict=True):
        xy, inten = _scan_returns(path, data.topic, data.msgtype, int(t), m, filt)
        returns.append(len(xy))
        if filt is not None:
            r = np.hypot(xy[:, 0], xy[:, 1])
            keep = r >= filt.min_range
            if filt.max_range is not None:
                keep &= r <= filt.max_range
            if filt.min_intensity is not None:
                if inten is None:
                    raise BagError(
                        path,
                        f"{role}.filter.min_intensity is set but {data.msgtype} messages here "
                        "carry no intensities",
                        data.topic,
                        t,
                    )
                keep &= inten >= filt.min_intensity
            xy = xy[keep]
        hull = np.stack([mx + c * xy[:, 0] - s * xy[:, 1], my + s * xy[:, 0] + c * xy[:, 1]], 1)
        points.append(hull.reshape(-1, 2))
    return Scans(
        role=role,
        topic=data.topic,
        t=data.stamp_ns,
        points=tuple(points),
        returns=np.asarray(returns, np.int64),
        max_gap=spec.max_gap,
    )


def to_world(points: np.ndarray, xy: np.ndarray, psi: float) -> np.ndarray:
    """Hull-frame points [m, 2] seen from pose (xy [2], ψ) -> local-frame points [m, 2]."""
    c, s = np.cos(psi), np.sin(psi)
    return xy + np.stack(
        [c * points[:, 0] - s * points[:, 1], s * points[:, 0] + c * points[:, 1]], 1
    )


def to_hull(points: np.ndarray, xy: np.ndarray, psi: float) -> np.ndarray:
    """Inverse of :func:`to_world`: local-frame points [m, 2] -> hull frame at pose (xy, ψ)."""
    c, s = np.cos(psi), np.sin(psi)
    d = points - xy
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1)


def persistent(
    world: Sequence[np.ndarray | None], origins: np.ndarray, spec: Persistence
) -> list[np.ndarray]:
    """Per scan, a bool mask of the returns kept by the persistence test.

    world: n arrays [m_i, 2] of returns in the local frame (None: the boat's pose at that scan is
    unknown; its returns are dropped and it counts as a scan without returns); origins: [n, 2]
    the boat's position at each scan. A return of scan j at range r from the boat is kept when
    at least ``spec.hits`` of scans j-1 .. j-``spec.scans`` have a return within
    ``spec.radius + spec.radius_growth * r`` m of it. Causal: a new object shows from its second
    sighting on.
    """
    out = []
    for j, pts in enumerate(world):
        if pts is None:
            out.append(np.zeros(0, bool))
            continue
        radius = spec.radius + spec.radius_growth * np.hypot(*(pts - origins[j]).T)
        hits = np.zeros(len(pts), int)
        for k in range(max(j - spec.scans, 0), j):
            prev = world[k]
            if prev is None or len(prev) == 0 or len(pts) == 0:
                continue
            d2 = np.sum((pts[:, None, :] - prev[None, :, :]) ** 2, axis=-1)
            hits += (d2 <= radius[:, None] ** 2).any(axis=1)
        out.append(hits >= spec.hits)
    return out


def coast(
    kept: Sequence[np.ndarray | None],
    world: Sequence[np.ndarray | None],
    origins: np.ndarray,
    spec: Persistence,
) -> list[np.ndarray | None]:
    """``kept`` (local-frame returns kept by :func:`persistent`, per scan) with confirmed returns
    carried through missed detections: a return kept in scan j-1 (itself or carried, at most
    ``spec.coast`` scans in a row) that has no return of scan j (``world``, all gated returns)
    within the persistence radius is added to scan j. Scans without a pose (None) stay None and
    end every coast."""
    out: list[np.ndarray | None] = []
    carried_prev = np.zeros((0, 2))
    age_prev = np.zeros(0, int)
    for j, pts in enumerate(kept):
        if pts is None:
            out.append(None)
            carried_prev, age_prev = np.zeros((0, 2)), np.zeros(0, int)
            continue
        if j == 0 or spec.coast == 0 or out[j - 1] is None:
            out.append(pts)
            carried_prev, age_prev = pts, np.zeros(len(pts), int)
            continue
        candidates, age = carried_prev, age_prev + 1
        now = world[j] if world[j] is not None else np.zeros((0, 2))
        radius = spec.radius + spec.radius_growth * np.hypot(*(candidates - origins[j]).T)
        if len(now) and len(candidates):
            d2 = np.sum((candidates[:, None, :] - now[None, :, :]) ** 2, axis=-1)
            seen = (d2 <= radius[:, None] ** 2).any(axis=1)
        else:
            seen = np.zeros(len(candidates), bool)
        carry = ~seen & (age <= spec.coast)
        out.append(np.concatenate([pts, candidates[carry]]))
        carried_prev = out[-1]
        age_prev = np.concatenate([np.zeros(len(pts), int), age[carry]])
    return out


def radar_sector_ranges(points: np.ndarray, layout) -> np.ndarray:
    """Radar returns in the hull frame [m, 2] -> [radar_beams] readings of the layout's radar
    fan: each beam reads the nearest return (from the layout's sensor origin) whose bearing lies
    in its sector, or the radar range when there is none (a return is a point target, found by
    the sector it lies in rather than by a ray passing within a disc of it)."""
    n = layout.radar_beams
    out = np.full(n, float(layout.radar_range))
    if n == 0 or len(points) == 0:
        return out
    rel = np.asarray(points, float) - np.asarray(layout.origin[:2])
    r = np.hypot(rel[:, 0], rel[:, 1])
    a = np.arctan2(rel[:, 1], rel[:, 0])
    w = layout.radar_width
    k = np.floor((a + 0.5 * w) / w).astype(int) % n
    np.minimum.at(out, k, r)
    return np.minimum(out, layout.radar_range)


@dataclass(frozen=True)
class SceneObject:
    """A static object found in the scans: xy [2] local frame (m), the number of scans and
    returns it was seen in, spread: RMS distance (m) of its returns to xy."""

    xy: np.ndarray
    scans: int
    returns: int
    spread: float


def find_objects(
    points: np.ndarray, scan_id: np.ndarray, cluster: float, min_scans: int, max_objects: int = 20
) -> list[SceneObject]:
    """Static objects among returns points: [N, 2] (local frame) from scans scan_id: [N].

    Repeatedly: seed at the cell (side ``cluster``) hit by the most scans, move the centre to
    the mean of the returns within ``cluster`` m until it settles. Seen in at least
    ``min_scans`` scans, it is an object: the returns within ``2 cluster`` m are taken out (the
    wider scatter of the same object, e.g. radar returns at long range; two objects closer than
    that are one). Otherwise the seed cell's returns are dropped (sea clutter and passing
    returns do not repeat at one place). Stops when no cell was hit by two scans.
    """
    pts = np.asarray(points, float).reshape(-1, 2)
    ids = np.asarray(scan_id).reshape(-1)
    found: list[SceneObject] = []
    while len(pts) and len(found) < max_objects:
        cells = np.floor(pts / cluster).astype(np.int64)
        pairs = np.unique(np.concatenate([cells, ids[:, None]], axis=1), axis=0)
        cell_keys, per_cell = np.unique(pairs[:, :2], axis=0, return_counts=True)
        if per_cell.max() < 2:
            break
        seed = (cells == cell_keys[int(np.argmax(per_cell))]).all(axis=1)
        centre = pts[seed].mean(axis=0)
        for _ in range(50):
            members = np.sum((pts - centre) ** 2, axis=1) <= cluster**2
            new = pts[members].mean(axis=0)
            moved = float(np.hypot(*(new - centre)))
            centre = new
            if moved < 1e-3:
                break
        members = np.sum((pts - centre) ** 2, axis=1) <= cluster**2
        n_scans = int(np.unique(ids[members]).size)
        if n_scans < min_scans:
            pts, ids = pts[~seed], ids[~seed]
            continue
        spread = float(np.sqrt(np.mean(np.sum((pts[members] - centre) ** 2, axis=1))))
        found.append(SceneObject(centre, n_scans, int(members.sum()), spread))
        taken = np.sum((pts - centre) ** 2, axis=1) <= (2 * cluster) ** 2
        pts, ids = pts[~taken], ids[~taken]
    return found


@dataclass(frozen=True)
class Candidate:
    """An object near the track: closest approach (m) and median bearing off the bow (deg)
    on the way to it (inf when the boat never closed in on it)."""

    object: SceneObject
    closest: float
    aim_deg: float


@dataclass(frozen=True)
class ObstacleEstimate:
    """The episode's obstacle from scans.

    chosen: the object the boat headed for and passed within the gate (None when none did);
    ambiguous: several objects qualify (chosen is then the best aimed-at one, flagged);
    candidates: every object seen in several scans with its closest approach and aim, nearest
    first; sensor: the role (``lidar``/``radar``) the returns come from; qualified: how many
    candidates passed the gate and the aim test."""

    chosen: Candidate | None
    ambiguous: bool
    candidates: tuple[Candidate, ...]
    sensor: str
    qualified: int = 0

    @property
    def xy(self) -> np.ndarray | None:
        """[2] local-frame position of the chosen object, or None."""
        return None if self.chosen is None else self.chosen.object.xy

    def describe(self, limit: int = 4) -> str:
        """One line on the nearest candidates (position, scans, closest approach, aim)."""
        parts = [
            f"({c.object.xy[0]:.1f}, {c.object.xy[1]:.1f}) m seen in {c.object.scans} scans, "
            f"passed at {c.closest:.1f} m, aim {c.aim_deg:.0f} deg"
            for c in self.candidates[:limit]
        ]
        return "; ".join(parts) if parts else "no object seen in several scans"


def wrap_angle(a):
    """Angles (rad) wrapped to [-π, π)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def aim_window(t: np.ndarray, bearing: np.ndarray, k: int, window_s: float) -> tuple[float, int]:
    """(aim in rad, start index of its window): the smallest median |bearing off the bow| over
    any ``window_s`` window of samples before index ``k`` (t: [n] ns, bearing: [n] rad). A track
    before ``k`` shorter than the window is one window; (inf, -1) with fewer than 3 samples."""
    if k < 3:
        return np.inf, -1
    window = min(int(round(window_s * 1e9)), int(t[k - 1] - t[0]))
    ends = np.searchsorted(t[:k], t[:k] + window, side="right")
    best, where = np.inf, -1
    for i in range(0, k, max(1, k // 200)):
        if ends[i] >= k and t[k - 1] - t[i] < window:
            break
        value = float(np.median(np.abs(bearing[i : ends[i]])))
        if value < best:
            best, where = value, i
    return best, where


def candidates_on_track(
    objects: Sequence[SceneObject],
    track_t: np.ndarray,
    track_xy: np.ndarray,
    track_psi: np.ndarray,
    aim_window_s: float,
) -> list[Candidate]:
    """Closest approach and aim of the track (t [K] ns, xy [K, 2], ψ [K]; valid samples only)
    to each object, nearest first. The aim (:func:`aim_window`) is the smallest median
    |bearing off the bow| over any ``aim_window_s`` window before the closest approach: a boat
    that headed for the object for that long, whatever it did before."""
    out = []
    for obj in objects:
        rel = obj.xy - track_xy
        dist = np.hypot(rel[:, 0], rel[:, 1])
        k = int(np.argmin(dist))
        bearing = wrap_angle(np.arctan2(rel[:, 1], rel[:, 0]) - track_psi)
        aim, _ = aim_window(track_t, bearing, k, aim_window_s)
        out.append(Candidate(obj, float(dist[k]), float(np.rad2deg(aim))))
    return sorted(out, key=lambda c: c.closest)


def estimate_obstacle(
    world: Sequence[np.ndarray | None],
    track_t: np.ndarray,
    track_xy: np.ndarray,
    track_psi: np.ndarray,
    search: ObstacleSearch,
    sensor: str,
) -> ObstacleEstimate:
    """The pole of one episode from the returns of its scans (local frame, None = no pose) and
    the boat's track (t [K] ns, xy [K, 2], ψ [K], valid samples only).

    Objects: :func:`find_objects` with ``search.cluster`` and ``search.min_scans``. The pole is
    the object the boat heads for (aim, see :func:`candidates_on_track`, <= ``search.aim_deg``)
    and passes within ``search.gate`` m. Exactly one: the estimate; more: ambiguous (the best
    aimed-at one is given, flagged); none: xy None.
    """
    pts = [p for p in world if p is not None and len(p)]
    if pts:
        ids = np.concatenate([np.full(len(p), j) for j, p in enumerate(pts)])
        objects = find_objects(np.concatenate(pts), ids, search.cluster, search.min_scans)
    else:
        objects = []
    cands = candidates_on_track(objects, track_t, track_xy, track_psi, search.aim_window_s)
    ok = [c for c in cands if c.closest <= search.gate and c.aim_deg <= search.aim_deg]
    best = min(ok, key=lambda c: c.aim_deg) if ok else None
    return ObstacleEstimate(best, len(ok) > 1, tuple(cands), sensor, len(ok))


def radar_pole_beam_hit_rate(
    O: np.ndarray,
    X: np.ndarray,
    mask: np.ndarray,
    pole_xy: np.ndarray,
    pole_radius: float,
    layout,
    tolerance: float = 5.0,
    min_range: float = 0.0,
    sensor_xy: Sequence[float] = (0.0, 0.0),
) -> tuple[int, int]:
    """(hits, steps): over the valid steps where the pole lies between ``min_range`` and the
    layout's radar range from the radar (at ``sensor_xy`` in the hull frame), how often the
    radar beam whose sector holds the pole reads the distance from the layout's origin to the
    pole's surface within ``tolerance`` m. O: [K, dO] (hull observation layout), X: [K, dX]
    hull states, mask: [K], pole_xy: [2] true local position."""
    from diffgcl.sim import hull

    valid = np.asarray(mask, bool)
    p = X[:, hull.IX_PX : hull.IX_PY + 1]
    psi = X[:, hull.IX_PSI]
    rel = np.asarray(pole_xy, float) - p
    c, s = np.cos(psi), np.sin(psi)
    hx, hy = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]
    from_sensor = np.hypot(hx - sensor_xy[0], hy - sensor_xy[1])
    ox, oy = hx - layout.origin[0], hy - layout.origin[1]
    dist = np.hypot(ox, oy)
    w = layout.radar_width
    beam = np.floor((np.arctan2(oy, ox) + 0.5 * w) / w).astype(int) % layout.radar_beams
    counted = valid & (from_sensor >= min_range) & (dist - pole_radius <= layout.radar_range)
    reading = O[np.arange(len(O)), layout.lidar_beams + beam]
    hit = counted & (np.abs(reading - (dist - pole_radius)) <= tolerance)
    return int(hit.sum()), int(counted.sum())
