"""Range scans (diffgcl.data.scans): sector beams, frames, persistence, coasting, objects and the
obstacle search, each against a hand computation."""

from __future__ import annotations

import numpy as np
import pytest

from diffgcl.data.scans import (
    aim_window,
    coast,
    estimate_obstacle,
    find_objects,
    persistent,
    radar_pole_beam_hit_rate,
    radar_sector_ranges,
    to_hull,
    to_world,
)
from diffgcl.data.topics import ObstacleSearch, Persistence
from diffgcl.sim import hull
from diffgcl.sim.sensors import SensorLayout

NS = 1_000_000_000


def test_radar_sector_ranges_by_hand():
    layout = SensorLayout()  # 16 radar sectors of 22.5°, the first centred on the bow
    ox = layout.origin[0]  # 2 m ahead of the centre
    pts = np.array(
        [
            [ox + 50.0, 0.0],  # dead ahead: sector 0 at 50 m
            [ox + 80.0, 1.0],  # also sector 0, farther: the nearest counts
            [ox, 30.0],  # 90° to port: sector 4
            [ox + 10 * np.cos(np.deg2rad(-11.0)), 10 * np.sin(np.deg2rad(-11.0))],  # sector 0
            [ox + 40 * np.cos(np.deg2rad(-12.0)), 40 * np.sin(np.deg2rad(-12.0))],  # sector 15
            [ox - 500.0, 0.0],  # astern, beyond the range: no reading
        ]
    )
    r = radar_sector_ranges(pts, layout)
    want = np.full(16, layout.radar_range)
    want[0], want[4], want[15] = 10.0, 30.0, 40.0
    np.testing.assert_allclose(r, want, atol=1e-9)
    np.testing.assert_array_equal(radar_sector_ranges(np.zeros((0, 2)), layout), want * 0 + 300)


def test_world_and_hull_frames_round_trip():
    pts = np.array([[10.0, 0.0], [0.0, -5.0]])
    xy, psi = np.array([100.0, -20.0]), np.pi / 2  # heading north
    world = to_world(pts, xy, psi)
    # 10 m ahead of a boat heading north is 10 m north; 5 m to starboard is 5 m east.
    np.testing.assert_allclose(world, [[100.0, -10.0], [105.0, -20.0]], atol=1e-12)
    np.testing.assert_allclose(to_hull(world, xy, psi), pts, atol=1e-12)


def test_persistence_keeps_what_repeats_with_a_growing_radius():
    spec = Persistence(scans=2, hits=1, radius=2.0, radius_growth=0.1)
    origins = np.zeros((4, 2))
    world = [
        np.array([[10.0, 0.0], [50.0, 0.0]]),
        np.array([[13.5, 0.0], [56.0, 0.0]]),  # 3.5 m from 10 (radius 3.35: no); 6 m (7.6: yes)
        None,  # no pose: nothing kept, counts as an empty scan
        np.array([[13.0, 0.0], [40.0, 40.0]]),  # 13 is within 3.3 of 13.5 two scans back
    ]
    keep = persistent(world, origins, spec)
    assert keep[0].tolist() == [False, False]  # nothing before it
    assert keep[1].tolist() == [False, True]
    assert keep[2].tolist() == []
    assert keep[3].tolist() == [True, False]
    strict = persistent(world, origins, Persistence(scans=2, hits=2, radius=2.0, radius_growth=0.1))
    assert not strict[3].any()  # only one of the two previous scans had a return near 13


def test_coast_carries_a_kept_return_through_one_missed_scan():
    spec = Persistence(scans=2, hits=1, radius=3.0, coast=1)
    origins = np.zeros((5, 2))
    pole = np.array([[100.0, 0.0]])
    kept = [pole, pole, np.zeros((0, 2)), np.zeros((0, 2)), pole]
    gated = [pole, pole, np.zeros((0, 2)), np.zeros((0, 2)), pole]
    out = coast(kept, gated, origins, spec)
    assert [len(o) for o in out] == [1, 1, 1, 0, 1]  # one missed scan bridged, not two
    np.testing.assert_array_equal(out[2], pole)
    # A return seen again is not doubled; with coast 0 nothing is carried.
    assert [len(o) for o in coast(kept, gated, origins, Persistence(coast=0))] == [1, 1, 0, 0, 1]


def test_find_objects_separates_static_objects_from_clutter():
    rng = np.random.default_rng(0)
    scans = 20
    pts, ids = [], []
    for j in range(scans):
        for centre in ([0.0, 0.0], [60.0, 30.0]):
            pts.append(np.asarray(centre) + rng.normal(0.0, 1.0, (3, 2)))
            ids += [j] * 3
        pts.append(rng.uniform(-200, 200, (10, 2)))  # clutter: nowhere twice
        ids += [j] * 10
    found = find_objects(np.concatenate(pts), np.array(ids), cluster=5.0, min_scans=5)
    assert len(found) == 2
    centres = sorted((o.xy for o in found), key=lambda c: c[0])
    np.testing.assert_allclose(centres[0], [0, 0], atol=0.6)
    np.testing.assert_allclose(centres[1], [60, 30], atol=0.6)
    assert all(o.scans == scans for o in found)
    assert all(0.8 < o.spread < 2.0 for o in found)  # RMS radius of N(0, 1) in 2-D is √2


def _track(course_deg: float, pole_xy, passing: float, n: int = 401):
    """A boat heading for ``pole_xy`` from 200 m along ``course_deg``, swerving to pass it
    ``passing`` m to port, then back on the course: t [n] ns, xy [n, 2], ψ [n]."""
    e = np.array([np.cos(np.deg2rad(course_deg)), np.sin(np.deg2rad(course_deg))])
    left = np.array([-e[1], e[0]])
    s = np.linspace(-200.0, 100.0, n)  # along-track position relative to the pole
    offset = passing * np.exp(-0.5 * (s / 30.0) ** 2)
    xy = np.asarray(pole_xy) + s[:, None] * e + offset[:, None] * left
    d = np.gradient(xy, axis=0)
    psi = np.arctan2(d[:, 1], d[:, 0])
    t = (np.arange(n) * 0.15 * NS).astype(np.int64)  # 0.75 m per sample at 5 m/s
    return t, xy, psi


def test_estimate_obstacle_picks_the_pole_the_boat_headed_for():
    t, xy, psi = _track(30.0, [0.0, 0.0], passing=15.0)
    rng = np.random.default_rng(1)
    # The episode's pole and another pole 159 m away, both seen in every scan.
    far = np.array([120.0, -104.0])
    world = [np.stack([rng.normal(0, 1.5, 2), far + rng.normal(0, 1.5, 2)]) for _ in range(30)]
    est = estimate_obstacle(world, t, xy, psi, ObstacleSearch(), "radar")
    assert est.xy is not None and not est.ambiguous
    assert np.hypot(*est.xy) < 1.0
    assert est.chosen.closest == pytest.approx(15.0, abs=1.5)
    assert est.chosen.aim_deg < 3.0
    assert len(est.candidates) == 2 and est.candidates[1].closest > 100.0


def test_estimate_obstacle_refuses_or_flags_two_poles_in_line():
    t, xy, psi = _track(0.0, [0.0, 0.0], passing=15.0)
    # A second pole on the course line beyond the first: the boat heads for both.
    world = [np.array([[0.0, 0.0], [80.0, 0.0]]) for _ in range(10)]
    est = estimate_obstacle(world, t, xy, psi, ObstacleSearch(), "lidar")
    assert est.ambiguous and est.qualified == 2
    # Without an object passed within the gate there is no estimate at all.
    far = [np.array([[0.0, 300.0]]) for _ in range(10)]
    assert estimate_obstacle(far, t, xy, psi, ObstacleSearch(), "lidar").xy is None


def test_aim_window_by_hand():
    t = np.arange(30, dtype=np.int64) * NS  # 1 Hz
    bearing = np.deg2rad(np.r_[np.full(10, 40.0), np.full(15, 2.0), np.full(5, 50.0)])
    # Windows hold 11 samples (both ends included); from sample 5 on, six or more are at 2°.
    aim, start = aim_window(t, bearing, 26, window_s=10.0)
    assert np.rad2deg(aim) == pytest.approx(2.0) and start == 5
    aim, _ = aim_window(t, bearing, 12, window_s=10.0)  # only windows 0 and 1 end before 12
    assert np.rad2deg(aim) == pytest.approx(40.0)
    # A track shorter than the window before the pass is one window; too short, no aim.
    aim, start = aim_window(t, bearing, 5, window_s=10.0)
    assert np.rad2deg(aim) == pytest.approx(40.0) and start == 0
    assert aim_window(t, bearing, 2, window_s=10.0) == (np.inf, -1)


def test_radar_pole_beam_hit_rate_by_hand():
    layout = SensorLayout()
    X = np.zeros((3, hull.DX))
    X[:, hull.IX_PX] = [0.0, 0.0, 0.0]
    pole = np.array([102.0, 0.0])  # 100 m from the sensor origin (2 m ahead), dead ahead
    O = np.full((3, layout.num_beams + 5), 300.0)
    O[0, layout.lidar_beams] = 99.5  # pole surface at 100 - 0.5 = 99.5: a hit
    O[1, layout.lidar_beams] = 90.0  # 9.5 m short: a miss
    O[2, layout.lidar_beams + 1] = 99.5  # the wrong beam: a miss
    hits, steps = radar_pole_beam_hit_rate(O, X, np.ones(3), pole, 0.5, layout, tolerance=5.0)
    assert (hits, steps) == (1, 3)
    # Steps inside the filter's minimum range do not count.
    assert radar_pole_beam_hit_rate(O, X, np.ones(3), pole, 0.5, layout, min_range=150.0)[1] == 0
