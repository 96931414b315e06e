"""Scenes beyond one pole and one run: every pole of a set in the water at once, kept apart and
off the other episodes' courses (:func:`separate_poles`), and the recorded drive from one run's
end to the next run's start when a set is one bag (:func:`repositioning_leg`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from diffgcl.data.synth.operator_model import OperatorProfile


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


def separate_poles(rng, profiles: list[OperatorProfile], min_distance: float):
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
