"""Range sensors of the Odin-like hull: one beam layout shared by the simulator and the bags.

Problem. The policy acts on what the boat can sense, not on the full state. Odin carries a LiDAR
(dense, short range) and a marine radar (sparse, long range, noisy). Both are reduced here to a
fixed set of horizontal beams from one origin on the mast; a reading is the distance along the
beam to the first obstacle surface, or the beam's maximum range when nothing is hit.

Each beam covers an angular sector and is sampled by a few evenly spread rays (a single ray of a
32-beam fan over 120° passes a 1 m pole at 60 m four times out of five); the beam reads the
shortest of its rays, as a real sensor's sector minimum would.

* :class:`SensorLayout` is the single definition of the beams (sectors, rays, ranges, noise,
  rates).
* :func:`range_readings` casts the rays with ``mjx.ray`` in a simulated scene (JAX, jit-able).
* :func:`ranges_from_points` reduces a recorded point cloud or scan, given in the hull frame, to
  the same beams (NumPy, for ROS-bag ingestion): each point is a small disc of radius
  ``point_radius``, and a ray reads the nearest disc it passes through -- the discrete analogue
  of a ray hitting a surface sampled by the points.

Frames: the hull frame has x forward (bow), y to port, z up; a beam angle is measured from the
bow, counter-clockwise (to port) positive, like the heading ψ in :mod:`diffgcl.sim.hull`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

Array = jax.Array

# Geom groups the beams see. Obstacles live in groups 0-1; the hull is group 2 (and its body is
# excluded anyway), the visual water plane group 3.
SENSED_GROUPS = (1, 1, 0, 0, 0, 0)


@dataclasses.dataclass(frozen=True)
class SensorLayout:
    """Beam layout of the LiDAR and radar fans (hull frame, SI units, angles in rad).

    LiDAR: ``lidar_beams`` equal sectors tiling ``[-lidar_fov/2, +lidar_fov/2]`` around the bow,
    ``lidar_range`` metres, each sampled by ``lidar_rays_per_beam`` rays at its sub-sector
    centres. Radar: ``radar_beams`` equal sectors tiling 360°, the first centred on the bow,
    ``radar_range`` metres, ``radar_rays_per_beam`` rays each. Readings are ordered LiDAR first
    (starboard to port), then radar (counter-clockwise from the bow), see :attr:`angles`.
    The noise standard deviations are additive Gaussian range noise; the rates are the nominal
    update rates of the real sensors (for bag ingestion and synthetic bags).
    """

    origin: tuple[float, float, float] = (2.0, 0.0, 2.5)  # on the mast (the MJCF "lidar" site)
    lidar_beams: int = 32
    lidar_fov: float = float(np.deg2rad(120.0))
    lidar_rays_per_beam: int = 5  # 0.75° apart: a 1 m pole is never missed within 60 m
    lidar_range: float = 60.0
    lidar_noise_std: float = 0.05
    lidar_rate_hz: float = 10.0
    radar_beams: int = 16
    radar_rays_per_beam: int = 15  # 1.5° apart; odd counts keep a ray on the sector centre
    radar_range: float = 300.0
    radar_noise_std: float = 2.0
    radar_rate_hz: float = 1.0
    # Disc radius given to each point in ranges_from_points: about the spacing of LiDAR returns
    # on a pole a few tens of metres away.
    point_radius: float = 0.25

    def __post_init__(self):
        if self.lidar_beams < 1 or self.radar_beams < 0:
            raise ValueError("SensorLayout needs lidar_beams >= 1 and radar_beams >= 0")
        if self.lidar_rays_per_beam < 1 or self.radar_rays_per_beam < 1:
            raise ValueError("SensorLayout needs at least one ray per beam")
        if not (0.0 < self.lidar_fov <= 2 * np.pi):
            raise ValueError(f"lidar_fov must be in (0, 2π], got {self.lidar_fov}")

    @property
    def num_beams(self) -> int:
        return self.lidar_beams + self.radar_beams

    @property
    def lidar_width(self) -> float:
        """Angular width (rad) of one LiDAR sector."""
        return self.lidar_fov / self.lidar_beams

    @property
    def radar_width(self) -> float:
        """Angular width (rad) of one radar sector."""
        return 2 * np.pi / max(self.radar_beams, 1)

    @property
    def lidar_angles(self) -> np.ndarray:
        """[lidar_beams] sector-centre angles (rad), from starboard to port."""
        k = np.arange(self.lidar_beams)
        return -0.5 * self.lidar_fov + (k + 0.5) * self.lidar_width

    @property
    def radar_angles(self) -> np.ndarray:
        """[radar_beams] sector-centre angles (rad) in [−π, π), the first one on the bow."""
        a = np.arange(self.radar_beams) * self.radar_width
        return (a + np.pi) % (2 * np.pi) - np.pi

    @property
    def angles(self) -> np.ndarray:
        """[num_beams] all sector-centre angles: LiDAR then radar."""
        return np.concatenate([self.lidar_angles, self.radar_angles])

    @property
    def lidar_ray_angles(self) -> np.ndarray:
        """[lidar_beams, lidar_rays_per_beam] ray angles (rad) at the sub-sector centres."""
        n = self.lidar_rays_per_beam
        sub = ((np.arange(n) + 0.5) / n - 0.5) * self.lidar_width
        return self.lidar_angles[:, None] + sub[None, :]

    @property
    def radar_ray_angles(self) -> np.ndarray:
        """[radar_beams, radar_rays_per_beam] ray angles (rad) at the sub-sector centres."""
        n = self.radar_rays_per_beam
        sub = ((np.arange(n) + 0.5) / n - 0.5) * self.radar_width
        return self.radar_angles[:, None] + sub[None, :]

    @property
    def max_ranges(self) -> np.ndarray:
        """[num_beams] maximum range of each beam (m)."""
        lidar = np.full(self.lidar_beams, self.lidar_range)
        return np.concatenate([lidar, np.full(self.radar_beams, self.radar_range)])

    @property
    def noise_stds(self) -> np.ndarray:
        """[num_beams] range-noise standard deviation of each beam (m)."""
        return np.concatenate(
            [
                np.full(self.lidar_beams, self.lidar_noise_std),
                np.full(self.radar_beams, self.radar_noise_std),
            ]
        )

    def beams_from_rays(self, ray_ranges):
        """Per-ray ranges [num_rays] (LiDAR rays then radar rays, beam-major) -> [num_beams]:
        each beam reads its shortest ray. Works on NumPy and JAX arrays."""
        xp = jnp if isinstance(ray_ranges, jax.Array) else np
        n_lidar = self.lidar_beams * self.lidar_rays_per_beam
        lidar = ray_ranges[:n_lidar].reshape(self.lidar_beams, self.lidar_rays_per_beam)
        radar = ray_ranges[n_lidar:].reshape(self.radar_beams, self.radar_rays_per_beam)
        return xp.concatenate([lidar.min(axis=1), radar.min(axis=1)])

    @property
    def ray_angles(self) -> np.ndarray:
        """[num_rays] every ray's angle, LiDAR then radar, beam-major."""
        return np.concatenate([self.lidar_ray_angles.ravel(), self.radar_ray_angles.ravel()])

    @property
    def ray_directions(self) -> np.ndarray:
        """[num_rays, 3] unit ray directions in the hull frame (horizontal)."""
        a = self.ray_angles
        return np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=-1)


def range_readings(model: mjx.Model, data: mjx.Data, layout: SensorLayout, body: int = 1) -> Array:
    """Cast the layout's rays with ``mjx.ray`` from ``body``'s sensor origin -> [num_beams].

    ``data`` must hold the kinematics of the scene (``mjx.kinematics`` or a step). The carrying
    body is excluded from the hits; only geoms in groups 0-1 are sensed. Each beam reads its
    shortest ray, capped at the beam's maximum range (no hit reads the maximum range).
    One scene; vmap over scenes.
    """
    dist = ray_distances(model, data, layout, body)
    ranges = layout.beams_from_rays(jnp.where(dist < 0, jnp.inf, dist))
    return jnp.minimum(ranges, jnp.asarray(layout.max_ranges, dtype=dist.dtype))


def ray_distances(model: mjx.Model, data: mjx.Data, layout: SensorLayout, body: int = 1) -> Array:
    """Raw ``mjx.ray`` distances of every ray, [num_rays] (−1 where a ray hits nothing)."""
    rot = data.xmat[body]
    origin = data.xpos[body] + rot @ jnp.asarray(layout.origin, dtype=data.xpos.dtype)
    dirs = jnp.asarray(layout.ray_directions, dtype=data.xpos.dtype) @ rot.T
    dist, _ = jax.vmap(
        lambda v: mjx.ray(model, data, origin, v, geomgroup=SENSED_GROUPS, bodyexclude=body)
    )(dirs)
    return dist


def add_range_noise(ranges: Array, layout: SensorLayout, key: jax.Array) -> Array:
    """ranges: [num_beams] plus Gaussian noise of the layout's std on the beams that see
    something, clipped to [0, max range]; a beam without a return stays at its maximum range."""
    std = jnp.asarray(layout.noise_stds, dtype=ranges.dtype)
    max_range = jnp.asarray(layout.max_ranges, dtype=ranges.dtype)
    noisy = ranges + std * jax.random.normal(key, ranges.shape, dtype=ranges.dtype)
    return jnp.where(ranges < max_range, jnp.clip(noisy, 0.0, max_range), max_range)


def ranges_from_points(
    points_xy: np.ndarray,
    layout: SensorLayout,
    point_radius: float | None = None,
    chunk: int = 4096,
) -> np.ndarray:
    """Reduce points in the hull frame, points_xy: [N, 2] (m), to beam readings [num_beams].

    Each finite point is a disc of radius ``point_radius`` (default ``layout.point_radius``)
    in the horizontal plane. Every ray of the layout, from the sensor origin, reads the distance
    to the first disc boundary it crosses (0 if the origin is inside a disc); a beam reads its
    shortest ray, capped at the beam's maximum range (no disc crossed: the maximum range) --
    the same rays and reduction as :func:`range_readings`, with discs in place of geoms. NaN/inf
    points (invalid returns) are ignored. Pure NumPy, one scan; memory is bounded by processing
    ``chunk`` points at a time.
    """
    pts = np.asarray(points_xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points_xy must have shape [N, 2] (hull-frame x, y), got {pts.shape}")
    rho = layout.point_radius if point_radius is None else float(point_radius)
    if rho <= 0:
        raise ValueError(f"point_radius must be > 0, got {rho}")
    max_range = layout.max_ranges
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.shape[0] == 0:
        return max_range.copy()
    rel = pts - np.asarray(layout.origin[:2])  # [N, 2]
    rel = rel[np.hypot(rel[:, 0], rel[:, 1]) <= max_range.max() + rho]  # nothing beyond reach
    dirs = layout.ray_directions[:, :2]  # [R, 2]
    ray = np.full(dirs.shape[0], np.inf)
    for start in range(0, rel.shape[0], chunk):
        block = rel[start : start + chunk]
        along = dirs @ block.T  # [R, n]
        lateral2 = np.sum(block**2, axis=1)[None, :] - along**2
        half_chord = np.sqrt(np.maximum(rho**2 - lateral2, 0.0))
        hit = (lateral2 <= rho**2) & (along + half_chord >= 0)
        entry = np.maximum(along - half_chord, 0.0)
        ray = np.minimum(ray, np.where(hit, entry, np.inf).min(axis=1))
    return np.minimum(layout.beams_from_rays(ray), max_range)


# --------------------------------------------------------------------------------------------
# A pole as ingestion's beams see it (the simulated observation of the USV task)
# --------------------------------------------------------------------------------------------


def circle_entry(origin: Array, dirs: Array, centre: Array, radius: Array, window=None) -> Array:
    """Distance along each ray to a circle: [R] for rays from ``origin: [2]`` along unit
    ``dirs: [R, 2]`` into the circle (``centre: [2]``, ``radius``); 0 from inside, inf where the
    ray misses it or the circle lies behind.

    ``window = (lo, hi)`` (default ``(−radius, radius)``) narrows the silhouette: a ray hits only
    if it passes the centre at a signed offset s (m, positive: the ray passes to the left of the
    centre, looking along it) with lo ≤ s ≤ hi; where it hits, it still reads the circle.
    Differentiable where the rays hit.
    """
    rel = centre - origin
    along = dirs @ rel
    offset = dirs[:, 1] * rel[0] - dirs[:, 0] * rel[1]
    lo, hi = (-radius, radius) if window is None else window
    slack = radius**2 - offset**2
    hit = (offset >= lo) & (offset <= hi) & (slack >= 0.0)
    half_chord = jnp.sqrt(jnp.where(hit, jnp.maximum(slack, 1e-12), 1.0))
    hit = hit & (along + half_chord >= 0.0)
    return jnp.where(hit, jnp.maximum(along - half_chord, 0.0), jnp.inf)


@dataclasses.dataclass(frozen=True)
class PoleSensorModel:
    """The recorded sensors behind ingestion's beams of a pole (see :func:`pole_beams`).

    LiDAR: ``lidar_scan_step`` (rad) between returns; ``lidar_noise_std`` (m), the range noise
    of a beam that sees the pole, grows with the spacing b of the returns on the pole as
    sqrt(lidar_noise_std² + (lidar_spacing_noise · b)²); ``lidar_dropout``, the probability
    that one return is missing. Radar: ``radar_range_std`` (m) and ``radar_bearing_std`` (rad),
    the noise of its return from the pole; ``radar_detection``, the probability that the
    filtered radar holds the pole at a step.

    The defaults are the synthetic Odin-like sensors (:class:`diffgcl.data.synth.SensorModel`:
    720 returns per turn, 3 cm, 2 % dropouts; radar 1.5 m, 1°, Pd 0.9) read through the default
    topic map's clutter filter (a return kept from its second sighting in 1 of 2 sweeps,
    coasted through one miss: held in Pd (1 − (1 − Pd)²)(2 − Pd) = 98 % of the sweeps), with
    ``lidar_spacing_noise`` measured against ingestion (``tests/test_usv_sensors.py``).
    """

    lidar_scan_step: float = float(2 * np.pi / 720)
    lidar_noise_std: float = 0.03
    lidar_spacing_noise: float = 0.14
    lidar_dropout: float = 0.02
    radar_range_std: float = 1.5
    radar_bearing_std: float = float(np.deg2rad(1.0))
    radar_detection: float = 0.98
    radar_mount: tuple[float, float] = (0.0, 0.0)
    pose_position_std: float = 0.05
    pose_heading_std: float = 0.0035


def _from_origin(layout: SensorLayout, pole: Array) -> tuple[Array, Array]:
    """(pole − origin [2], its length) in the hull frame."""
    rel = pole - jnp.asarray(layout.origin[:2], pole.dtype)
    return rel, jnp.sqrt(jnp.maximum(rel @ rel, 1e-12))


def lidar_pole_ranges(
    model: PoleSensorModel, layout: SensorLayout, pole: Array, radius: Array, returns=None
) -> Array:
    """[lidar_beams] LiDAR beams of a pole of ``radius`` (``pole: [2]``, its centre in the hull
    frame, m) as ingestion reads them from the scan's returns (:func:`ranges_from_points`).

    The returns sample the pole's near surface every b = d · ``lidar_scan_step`` across the line
    of sight (d: distance from the sensor), each a disc of ρ = ``layout.point_radius``. A ray
    meets the disc of a return δ to its side sqrt(ρ² − δ²) before the surface; δ uniform on
    [0, b/2] gives ρ̄ = ρ − b²/(24ρ) (first order in δ²/ρ²): where a ray hits, it reads a circle
    of radius R + ρ̄. A ray hits when it passes within ρ of the outermost returns,
    ``returns = (first, last)``: their offsets (m) to the left of the centre across the line of
    sight. Default: the mean, ±(R − b/2), each flank's outermost return half a spacing inside
    the silhouette (:func:`noisy_pole_beams` draws them). Noise-free, differentiable in
    ``pole`` and ``radius`` where the beams see the pole.
    """
    rel, dist = _from_origin(layout, pole)
    rho = layout.point_radius
    spacing = dist * model.lidar_scan_step
    surface = radius + jnp.maximum(rho - spacing**2 / (24.0 * rho), 0.0)
    if returns is None:
        half = jnp.maximum(radius - 0.5 * spacing, -rho) + rho
        window = (-half, half)
    else:
        first, last = returns
        empty = first > last  # every return on the pole dropped
        window = (jnp.where(empty, jnp.inf, first - rho), jnp.where(empty, -jnp.inf, last + rho))
    dirs = jnp.asarray(layout.ray_directions[: layout.lidar_beams * layout.lidar_rays_per_beam, :2])
    origin = jnp.asarray(layout.origin[:2], pole.dtype)
    rays = circle_entry(origin, dirs.astype(pole.dtype), pole, surface, window)
    beams = rays.reshape(layout.lidar_beams, layout.lidar_rays_per_beam).min(axis=1)
    return jnp.minimum(beams, layout.lidar_range)


def radar_pole_ranges(layout: SensorLayout, pole: Array) -> Array:
    """[radar_beams] radar beams of a pole (``pole: [2]``, its centre in the hull frame, m) as
    ingestion reads them (:func:`diffgcl.data.scans.radar_sector_ranges`): the radar returns
    the pole's centre (a point target, not its surface); the beam whose sector holds its
    bearing from the layout's origin reads its distance, capped at the radar range, the others
    the radar range. Noise-free; differentiable in ``pole`` (the sector is piecewise constant).
    """
    rel, dist = _from_origin(layout, pole)
    w = layout.radar_width
    sector = jnp.mod(jnp.floor((jnp.arctan2(rel[1], rel[0]) + 0.5 * w) / w), layout.radar_beams)
    beams = jnp.where(jnp.arange(layout.radar_beams) == sector, dist, jnp.inf)
    return jnp.minimum(beams, layout.radar_range)


def pole_beams(model: PoleSensorModel, layout: SensorLayout, pole: Array, radius: Array) -> Array:
    """[num_beams] noise-free beams (LiDAR then radar) of a pole of ``radius`` at ``pole: [2]``
    (its centre in the hull frame): :func:`lidar_pole_ranges`, :func:`radar_pole_ranges`."""
    return jnp.concatenate(
        [lidar_pole_ranges(model, layout, pole, radius), radar_pole_ranges(layout, pole)]
    )


def noisy_pole_beams(
    model: PoleSensorModel, layout: SensorLayout, pole: Array, radius: Array, key: jax.Array
) -> Array:
    """[num_beams] one draw of :func:`pole_beams` with the noise of ingestion's beams.

    LiDAR: the returns' phase along the pole (uniform: the first return within one spacing b of
    the right flank, then one every b), each outermost return dropped with probability
    ``lidar_dropout`` (the flank one spacing narrower; no return left: the pole is not seen),
    and Gaussian range noise (see :class:`PoleSensorModel`) on the beams that see it; dropouts
    inside the silhouette are left out (another return of the beam still reads the pole). Radar:
    range (at least 1 m, as the generator's) and bearing noise of the return (near a sector edge
    the neighbouring beam reads it), and with probability 1 − ``radar_detection`` no return
    (every beam reads the radar range). Before both, the pose error of the state estimate that
    ingestion moves each scan with (``pose_position_std``, ``pose_heading_std``). Each call is
    one independent draw: the ingested radar holds one sweep for 2 s, so its error is
    correlated from step to step where this one is not.
    """
    k_pose, k_phase, k_drop, k_lidar, k_radar, k_seen = jax.random.split(key, 6)
    dtype = pole.dtype
    e = jax.random.normal(k_pose, (3,), dtype)
    c, s = jnp.cos(model.pose_heading_std * e[2]), jnp.sin(model.pose_heading_std * e[2])
    pole = jnp.stack([c * pole[0] - s * pole[1], s * pole[0] + c * pole[1]])
    pole = pole + model.pose_position_std * e[:2]
    _, dist = _from_origin(layout, pole)
    spacing = dist * model.lidar_scan_step
    phase = jax.random.uniform(k_phase, (), dtype)
    first = -radius + phase * spacing
    last = first + spacing * jnp.floor((radius - first) / spacing)
    dropped = jax.random.bernoulli(k_drop, model.lidar_dropout, (2,)).astype(dtype)
    single = last - first < 0.5 * spacing  # one return on the pole: one draw drops it
    dropped_last = jnp.where(single, dropped[0], dropped[1])
    returns = (first + dropped[0] * spacing, last - dropped_last * spacing)
    lidar = lidar_pole_ranges(model, layout, pole, radius, returns)
    std = jnp.sqrt(model.lidar_noise_std**2 + (model.lidar_spacing_noise * spacing) ** 2)
    noisy = lidar + std * jax.random.normal(k_lidar, lidar.shape, dtype)
    lidar = jnp.where(lidar < layout.lidar_range, jnp.clip(noisy, 0.0, layout.lidar_range), lidar)
    z = jax.random.normal(k_radar, (2,), dtype)
    mount = jnp.asarray(model.radar_mount, dtype)
    rel = pole - mount
    r = jnp.sqrt(jnp.maximum(rel @ rel, 1e-12)) + model.radar_range_std * z[0]
    bearing = jnp.arctan2(rel[1], rel[0]) + model.radar_bearing_std * z[1]
    echo = mount + jnp.maximum(r, 1.0) * jnp.stack([jnp.cos(bearing), jnp.sin(bearing)])
    radar = radar_pole_ranges(layout, echo)
    seen = jax.random.uniform(k_seen, (), dtype) < model.radar_detection
    return jnp.concatenate([lidar, jnp.where(seen, radar, layout.radar_range)])
