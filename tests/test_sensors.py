"""Range sensors: mjx.ray readings equal C ``mj_ray`` on the same scene; ``ranges_from_points``
(the bag path) reproduces the ray readings on a synthetic scene and exact hand-made cases."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from diffgcl.sim import hull as H
from diffgcl.sim.mjcf import load_mjcf, put_model
from diffgcl.sim.sensors import (
    SENSED_GROUPS,
    SensorLayout,
    range_readings,
    ranges_from_points,
    ray_distances,
)

LAYOUT = SensorLayout()
POLE_RADIUS = 2.0  # big enough that several beams see it
# (hull x, y, ψ), pole (x, y): ahead, off the bow, abeam, behind, out of range.
SCENES = [
    ((0.0, 0.0, 0.0), (30.0, 0.0)),
    ((3.0, -2.0, 0.3), (40.0, 12.0)),
    ((-10.0, 5.0, 2.0), (-30.0, 20.0)),
    ((0.0, 0.0, -1.2), (-5.0, 15.0)),
    ((0.0, 0.0, 0.0), (1.0, 200.0)),
    ((0.0, 0.0, 0.5), (600.0, 0.0)),
]


@pytest.fixture(scope="module")
def scene():
    model = load_mjcf(H.MJCF_NAME)
    pole = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "pole")
    half = model.geom_size[pole, 1]
    model.geom_size[pole, 0] = POLE_RADIUS
    model.geom_rbound[pole] = POLE_RADIUS + half
    model.geom_aabb[pole, 3:] = [POLE_RADIUS, POLE_RADIUS, POLE_RADIUS + half]
    mx = put_model(model)
    d0 = mjx.make_data(mx)

    @jax.jit
    def sense(qpos, pole_xy):
        d = d0.replace(qpos=qpos, mocap_pos=d0.mocap_pos.at[0, :2].set(pole_xy))
        d = mjx.kinematics(mx, d)
        return ray_distances(mx, d, LAYOUT), range_readings(mx, d, LAYOUT)

    return model, sense


def c_rays(model, qpos, pole_xy):
    """C mj_ray distances of every ray of LAYOUT in the scene, [num_rays]."""
    d = mujoco.MjData(model)
    d.qpos[:] = qpos
    d.mocap_pos[0, :2] = pole_xy
    mujoco.mj_forward(model, d)
    rot = d.xmat[1].reshape(3, 3)
    origin = d.xpos[1] + rot @ np.asarray(LAYOUT.origin)
    groups = np.asarray(SENSED_GROUPS, np.uint8)
    geomid = np.zeros(1, np.int32)
    rays = [rot @ v for v in LAYOUT.ray_directions]
    return np.array([mujoco.mj_ray(model, d, origin, v, groups, 1, 1, geomid) for v in rays])


def pole_points(qpos, pole_xy, radius, spacing=0.005):
    """Points on a circle of ``radius`` around the pole, in the hull frame: [N, 2]."""
    th = np.linspace(0.0, 2 * np.pi, max(int(2 * np.pi * radius / spacing), 8), endpoint=False)
    world = np.asarray(pole_xy) + radius * np.stack([np.cos(th), np.sin(th)], axis=1)
    c, s = np.cos(qpos[2]), np.sin(qpos[2])
    rel = world - np.asarray(qpos[:2])
    return np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], axis=1)


def test_layout():
    assert LAYOUT.num_beams == 48 and LAYOUT.angles.shape == (48,)
    lidar = LAYOUT.lidar_ray_angles
    assert lidar.shape == (32, 5)
    np.testing.assert_allclose(np.diff(lidar.ravel()), LAYOUT.lidar_width / 5)  # even fan
    np.testing.assert_allclose([lidar.min(), lidar.max()], np.deg2rad([-60, 60]) * (1 - 1 / 160))
    radar = LAYOUT.radar_ray_angles
    assert radar.shape == (16, 15) and LAYOUT.radar_angles[0] == 0.0
    assert 0.0 in radar[0]  # a ray dead ahead
    steps = np.diff(np.unwrap(radar.ravel()))
    np.testing.assert_allclose(steps, 2 * np.pi / 240)  # 360° evenly, no gaps
    assert LAYOUT.max_ranges[:32].tolist() == [60.0] * 32
    assert LAYOUT.max_ranges[32:].tolist() == [300.0] * 16
    with pytest.raises(ValueError):
        SensorLayout(lidar_rays_per_beam=0)


@pytest.mark.parametrize("k", range(len(SCENES)))
def test_mjx_ray_equals_c_mj_ray(scene, k):
    model, sense = scene
    qpos, pole = SCENES[k]
    dist, ranges = sense(jnp.asarray(qpos), jnp.asarray(pole))
    ref = c_rays(model, qpos, pole)
    np.testing.assert_allclose(np.asarray(dist), ref, atol=1e-9)
    expected = np.minimum(LAYOUT.beams_from_rays(np.where(ref < 0, np.inf, ref)), LAYOUT.max_ranges)
    np.testing.assert_allclose(np.asarray(ranges), expected, atol=1e-9)
    if k < 4:
        assert (ref > 0).any(), "scene should put the pole in some beams"


@pytest.mark.parametrize("k", range(len(SCENES)))
def test_ranges_from_points_matches_rays_on_synthetic_scene(scene, k):
    """Dense points on a circle of radius R − ρ, each a disc of radius ρ, form the pole's
    cross-section at the sensor height (radius R): the bag path must read what mjx.ray reads."""
    _, sense = scene
    qpos, pole = SCENES[k]
    _, ranges = sense(jnp.asarray(qpos), jnp.asarray(pole))
    rho = 0.25
    pts = pole_points(qpos, pole, POLE_RADIUS - rho)
    from_points = ranges_from_points(pts, LAYOUT, point_radius=rho)
    np.testing.assert_allclose(from_points, np.asarray(ranges), atol=2e-3)
    chunked = ranges_from_points(pts, LAYOUT, point_radius=rho, chunk=97)
    np.testing.assert_array_equal(chunked, from_points)


def test_ranges_from_points_exact_cases():
    origin = np.asarray(LAYOUT.origin[:2])
    ahead = origin + [20.0, 0.0]
    r = ranges_from_points(ahead[None], LAYOUT, point_radius=0.5)
    front_lidar = np.argmin(np.abs(LAYOUT.lidar_angles))  # beams 15 and 16 straddle the bow
    radar_bow = LAYOUT.lidar_beams
    assert r[radar_bow] == pytest.approx(19.5)
    a = LAYOUT.lidar_width / 10  # the rays nearest the bow are ±a off it
    chord = 20 * np.cos(a) - np.sqrt(0.5**2 - (20 * np.sin(a)) ** 2)
    assert r[front_lidar] == pytest.approx(chord) and r[front_lidar + 1] == pytest.approx(chord)
    hit = np.flatnonzero(r < LAYOUT.max_ranges)
    assert set(hit) <= {front_lidar - 1, front_lidar, front_lidar + 1, radar_bow}
    # A point abeam to port at 100 m: only the radar sees it (LiDAR is ±60°, 60 m).
    port = origin + [0.0, 100.0]
    r = ranges_from_points(port[None], LAYOUT, point_radius=0.5)
    assert (r[:32] == 60.0).all() and r[32 + 4] == pytest.approx(99.5)  # radar beam at +90°
    # Out of range, NaN returns and an empty scan read the maximum range.
    far = origin + [500.0, 0.0]
    nan = np.array([np.nan, 1.0])
    np.testing.assert_array_equal(
        ranges_from_points(np.stack([far, nan]), LAYOUT), LAYOUT.max_ranges
    )
    np.testing.assert_array_equal(ranges_from_points(np.zeros((0, 2)), LAYOUT), LAYOUT.max_ranges)
    # A point on the sensor itself reads 0 on every beam.
    np.testing.assert_array_equal(ranges_from_points(origin[None], LAYOUT), 0.0)
    with pytest.raises(ValueError, match=r"\[N, 2\]"):
        ranges_from_points(np.zeros((3, 3)), LAYOUT)
