"""The USV task's simulated sensors (diffgcl.sim.sensors.PoleSensorModel and the pole beams,
diffgcl.envs.usv.UsvEnv.obs) against independent references: the ray-circle entry by brute
force, the radar sectors by hand and against ingestion's own reduction, the LiDAR model against
the synthetic generator's scans reduced by ingestion, the noise by Monte Carlo against the
model's stated parameters, and one synthetic episode, simulated vs ingested."""

import dataclasses
import tempfile
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import norm

from diffgcl.data.scans import radar_sector_ranges
from diffgcl.data.synth import SensorModel
from diffgcl.data.synth.recording import _lidar_ranges
from diffgcl.envs.usv import IX_RADIUS, make_usv_env
from diffgcl.sim import hull as hull_sim
from diffgcl.sim.sensors import (
    PoleSensorModel,
    SensorLayout,
    circle_entry,
    lidar_pole_ranges,
    noisy_pole_beams,
    pole_beams,
    radar_pole_ranges,
    ranges_from_points,
)

LAYOUT = SensorLayout()
MODEL = PoleSensorModel()
QUIET = dataclasses.replace(MODEL, pose_position_std=0.0, pose_heading_std=0.0)


def brute_entry(origin, d, centre, radius, t_max=120.0, step=2e-4):
    """First point along the ray inside the circle, by marching (inf: none within t_max)."""
    t = np.arange(0.0, t_max, step)
    inside = np.hypot(*(origin + t[:, None] * d - centre).T) <= radius
    return t[np.argmax(inside)] if inside.any() else np.inf


def test_circle_entry_against_brute_force():
    rng = np.random.default_rng(0)
    origin, rays, centres, radii = [], [], [], []
    for _ in range(60):
        o = rng.uniform(-5, 5, 2)
        c = o + rng.uniform(-60, 60, 2)
        r = rng.uniform(0.3, 3.0)
        if rng.uniform() < 0.1:  # origin inside the circle: 0
            c = o + rng.uniform(-0.2, 0.2, 2)
        aim = np.arctan2(*(c - o)[::-1]) + rng.normal(0.0, 0.1)  # most rays near the circle
        if rng.uniform() < 0.15:  # the circle behind the ray: inf
            aim += np.pi
        origin.append(o), rays.append([np.cos(aim), np.sin(aim)]), centres.append(c)
        radii.append(r)
    got = [
        float(circle_entry(jnp.asarray(o), jnp.asarray([d]), jnp.asarray(c), r)[0])
        for o, d, c, r in zip(origin, rays, centres, radii, strict=True)
    ]
    want = [brute_entry(*a) for a in zip(origin, np.asarray(rays), centres, radii, strict=True)]
    hits = np.isfinite(want)
    assert 10 < hits.sum() < len(want)  # both cases exercised
    np.testing.assert_array_equal(np.isfinite(got), hits)
    np.testing.assert_allclose(np.asarray(got)[hits], np.asarray(want)[hits], atol=3e-4)


def test_circle_entry_window_by_hand():
    # A ray along +x from the origin passes a circle at (10, -0.3), R = 1, 0.3 m to the left
    # of its centre: the offset is +0.3; entry at 10 - sqrt(1 - 0.09).
    o, d, c = jnp.zeros(2), jnp.asarray([[1.0, 0.0]]), jnp.asarray([10.0, -0.3])
    entry = 10.0 - np.sqrt(1.0 - 0.09)
    np.testing.assert_allclose(circle_entry(o, d, c, 1.0)[0], entry)
    np.testing.assert_allclose(circle_entry(o, d, c, 1.0, (0.2, 0.4))[0], entry)
    assert np.isinf(circle_entry(o, d, c, 1.0, (-0.4, 0.2))[0])
    assert np.isinf(circle_entry(o, d, c, 0.25)[0])  # the ray misses a thinner circle


def test_radar_sectors_by_hand_and_as_ingestion_reads_them():
    w = 2 * np.pi / 16  # 22.5° sectors, the first centred on the bow
    origin = np.asarray(LAYOUT.origin[:2])
    for bearing_deg, beam in ((0.0, 0), (11.0, 0), (12.0, 1), (-12.0, 15), (180.0, 8), (-95, 12)):
        a = np.deg2rad(bearing_deg)
        pole = origin + 80.0 * np.array([np.cos(a), np.sin(a)])
        r = np.asarray(radar_pole_ranges(LAYOUT, jnp.asarray(pole)))
        assert np.argmin(r) == beam and r[beam] == pytest.approx(80.0)
        assert (np.delete(r, beam) == LAYOUT.radar_range).all()
    assert np.isclose(w, LAYOUT.radar_width)
    # Any point target, near or far, in the same beam as ingestion's sector reduction.
    rng = np.random.default_rng(1)
    points = rng.uniform(-320.0, 320.0, (300, 2))
    for p in points:
        want = radar_sector_ranges(p[None, :], LAYOUT)
        np.testing.assert_allclose(radar_pole_ranges(LAYOUT, jnp.asarray(p)), want, rtol=1e-12)


def generator_scan_beams(pole_hull, radius, psi, rng):
    """LiDAR beams ingestion makes of the synthetic generator's noise-free scan of one pole at
    ``pole_hull`` (hull frame) from a boat at the origin heading ``psi``."""
    c, s = np.cos(psi), np.sin(psi)
    pole_world = np.array(
        [c * pole_hull[0] - s * pole_hull[1], s * pole_hull[0] + c * pole_hull[1]]
    )
    x = np.zeros(hull_sim.DX)
    x[hull_sim.IX_PSI] = psi
    quiet = SensorModel(lidar_noise=0.0, lidar_dropout=0.0)
    r = _lidar_ranges(rng, x, [(pole_world, radius)], quiet).astype(float)
    a = -np.pi + np.arange(r.size) * (2 * np.pi / r.size)  # the LaserScan's angles
    ok = np.isfinite(r)
    mount = np.asarray(quiet.lidar_mount[:2])
    pts = mount + np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=1)
    return ranges_from_points(pts, dataclasses.replace(LAYOUT, radar_beams=0))


@pytest.mark.parametrize("distance", [8.0, 30.0, 55.0])
def test_lidar_model_is_ingestion_of_the_generators_scan(distance):
    """Noise-free LiDAR beams against the generator's scan reduced by ingestion (the same rays
    and point discs), over random pole radii, bearings and scan phases (the heading).

    Tolerances: the model replaces the returns' discrete spacing b = d · 0.5° by its mean
    (a circle of radius R + ρ − b²/24ρ, the window of the mean outermost return); per draw the
    reading then differs by the spacing part of the model's noise, about k b (the returns'
    phase across the beam's rays, steepest on the flanks), the median by far less; a flank beam
    flips seen/unseen only where the phase puts the outermost return at the beam's edge.
    """
    rng = np.random.default_rng(int(distance))
    f = jax.jit(lambda p, r: lidar_pole_ranges(MODEL, LAYOUT, p, r))
    n_rays = LAYOUT.lidar_beams * LAYOUT.lidar_rays_per_beam
    dirs = jnp.asarray(LAYOUT.ray_directions[:n_rays, :2])
    bare = jax.jit(  # the layout's rays on the bare pole
        lambda p, r: (
            circle_entry(jnp.asarray(LAYOUT.origin[:2]), dirs, p, r)
            .reshape(LAYOUT.lidar_beams, -1)
            .min(axis=1)
        )
    )
    err, agree, err_bare = [], [], []
    for _ in range(150):
        radius, bearing = rng.uniform(0.3, 1.0), rng.uniform(-0.9, 0.9)
        pole = np.asarray(LAYOUT.origin[:2]) + distance * np.array(
            [np.cos(bearing), np.sin(bearing)]
        )
        ingested = generator_scan_beams(pole, radius, rng.uniform(-np.pi, np.pi), rng)
        sim = np.asarray(f(jnp.asarray(pole), radius))
        both = (ingested < LAYOUT.lidar_range) & (sim < LAYOUT.lidar_range)
        err.append((ingested - sim)[both])
        err_bare.append((ingested - np.asarray(bare(jnp.asarray(pole), radius)))[both])
        agree.append(np.mean((ingested < LAYOUT.lidar_range) == (sim < LAYOUT.lidar_range)))
    err = np.concatenate(err)
    assert abs(np.median(err)) < 0.01
    # The spread is what the model states as the spacing part of its noise, k b.
    spread = MODEL.lidar_spacing_noise * distance * MODEL.lidar_scan_step
    assert 0.6 < np.std(err) / spread < 1.35
    assert np.quantile(np.abs(err), 0.95) < 0.01 + 3.5 * spread
    assert np.mean(agree) > 0.99
    # The bare pole's surface reads about the point discs' radius ρ too far: it would fail.
    assert np.median(np.concatenate(err_bare)) < -0.8 * LAYOUT.point_radius


def test_noise_statistics_by_monte_carlo():
    """noisy_pole_beams against its stated parameters (no pose error), 20000 draws."""
    n = 20000
    keys = jax.random.split(jax.random.PRNGKey(3), n)
    nL = LAYOUT.lidar_beams
    # LiDAR: a pole of 1 m at 30 m on the centre of beam 16 (1.875° to port): that beam's
    # centre ray passes the pole's centre, so it reads the model's surface in every draw, with
    # the stated range noise sqrt(σ² + (k b)²).
    a = LAYOUT.lidar_angles[16]
    pole = jnp.asarray(LAYOUT.origin[:2]) + 30.0 * jnp.array([np.cos(a), np.sin(a)])
    draws = np.asarray(
        jax.jit(jax.vmap(lambda k: noisy_pole_beams(QUIET, LAYOUT, pole, 1.0, k)))(keys)
    )
    clean = np.asarray(pole_beams(QUIET, LAYOUT, pole, 1.0))
    b = 30.0 * MODEL.lidar_scan_step
    std = np.hypot(MODEL.lidar_noise_std, MODEL.lidar_spacing_noise * b)
    e = draws[:, 16] - clean[16]
    assert abs(e.mean()) < 4 * std / np.sqrt(n)
    assert e.std() == pytest.approx(std, rel=0.03)  # 3 % ~ 6 σ of a sample std of 20000
    # Radar: the detection rate and the range noise of a pole 150 m ahead, mounted at the
    # layout's origin so that the bearing noise alone moves the return across a sector edge:
    # bearing 1° inside beam 0's edge at 11.25° reads beam 0 w.p. Pd Φ(1°/σ), beam 1 w.p.
    # Pd (1 − Φ(1°/σ)).
    at_origin = dataclasses.replace(QUIET, radar_mount=LAYOUT.origin[:2])
    edge = 0.5 * LAYOUT.radar_width - np.deg2rad(1.0)
    pole = jnp.asarray(LAYOUT.origin[:2]) + 150.0 * jnp.array([np.cos(edge), np.sin(edge)])
    radar = np.asarray(
        jax.jit(jax.vmap(lambda k: noisy_pole_beams(at_origin, LAYOUT, pole, 0.5, k)))(keys)
    )[:, nL:]
    seen = (radar < LAYOUT.radar_range).any(axis=1)
    pd = MODEL.radar_detection
    assert seen.mean() == pytest.approx(pd, abs=4 * np.sqrt(pd * (1 - pd) / n))
    assert ((radar < LAYOUT.radar_range).sum(axis=1) <= 1).all()  # one point target
    p0 = pd * norm.cdf(np.deg2rad(1.0) / MODEL.radar_bearing_std)
    for beam, p in ((0, p0), (1, pd - p0)):
        rate = np.mean(radar[:, beam] < LAYOUT.radar_range)
        assert rate == pytest.approx(p, abs=4 * np.sqrt(p * (1 - p) / n))
    r = radar.min(axis=1)[seen]
    assert abs(r.mean() - 150.0) < 4 * MODEL.radar_range_std / np.sqrt(seen.sum())
    assert r.std() == pytest.approx(MODEL.radar_range_std, rel=0.03)


def test_observation_is_differentiable_where_the_policy_is_linearised():
    """jacfwd of the noise-free obs (MDGPS linearises π(obs(x))) is finite and equals central
    finite differences in float64, with a LiDAR beam that sees the pole moving with it."""
    env = make_usv_env(horizon=20)
    x = env.initial_states()[0].at[hull_sim.IX_PY].set(0.4).at[hull_sim.IX_PSI].set(0.05)
    x = x.at[hull_sim.IX_PX].set(x[hull_sim.IX_OBS_X] - 25.0).at[IX_RADIUS].set(0.8)
    J = np.asarray(jax.jacfwd(env.obs)(x))
    assert J.shape == (env.dO, env.dX) and np.isfinite(J).all()
    h = 1e-6
    fd = np.stack(
        [(env.obs(x.at[i].add(h)) - env.obs(x.at[i].add(-h))) / (2 * h) for i in range(env.dX)],
        axis=1,
    )
    np.testing.assert_allclose(J, np.asarray(fd), atol=1e-5)
    seen = np.asarray(env.obs(x)[: LAYOUT.lidar_beams]) < LAYOUT.lidar_range
    assert seen.any() and (np.abs(J[: LAYOUT.lidar_beams][seen, hull_sim.IX_OBS_X]) > 0.5).all()
    # Also under jit and vmap, with and without noise.
    X = jnp.stack([x, x.at[hull_sim.IX_PY].set(-0.4)])
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    assert np.isfinite(np.asarray(jax.jit(jax.vmap(env.obs))(X, keys))).all()
    assert np.isfinite(np.asarray(jax.jit(jax.vmap(jax.jacfwd(env.obs)))(X))).all()


@pytest.fixture(scope="module")
def one_episode():
    """One short synthetic set-2 episode (LiDAR and radar), ingested and in the task frame, with
    the simulated beams at its states."""
    from diffgcl.data.ingest import IngestWarning, ingest_bags
    from diffgcl.data.synth import SynthConfig, synthesize
    from diffgcl.data.task_frame import to_task_frame
    from diffgcl.eval.sensors import demo_beams

    config = SynthConfig(
        episodes=(0, 1), lidar=(False, True), approach_m=(70.0, 80.0), end_margin_m=(30.0, 40.0)
    )
    with tempfile.TemporaryDirectory() as tmp:
        synth = synthesize(Path(tmp) / "bags", config)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IngestWarning)
            demos = to_task_frame(ingest_bags(list(synth.bags)))
    radii = np.array([e.profile.pole_radius for e in synth.episodes])
    return demo_beams(demos, radii, jax.random.PRNGKey(0))


def test_simulated_beams_match_the_ingested_episode(one_episode):
    """Simulated (noise-free and noisy) against ingested beams at the ingested states."""
    from diffgcl.eval.sensors import lidar_agreement, radar_agreement

    b, nL, nB = one_episode, LAYOUT.lidar_beams, LAYOUT.num_beams
    ing = b["ingested"]
    lidar = lidar_agreement(b["simulated"][:, :nL], ing[:, :nL], LAYOUT.lidar_range)
    noisy = lidar_agreement(b["simulated"][:, :nL], b["noisy"][:, :nL], LAYOUT.lidar_range)
    exact = lidar_agreement(b["exact"][:, :nL], ing[:, :nL], LAYOUT.lidar_range)
    assert lidar["beams_both"] > 100
    # LiDAR. The median error: the model's mean surface (measured to ≤ 1 cm against the
    # generator's scans) plus the state estimate's pose error that ingestion moves each scan
    # with (5 cm); the exact pole geometry reads ~ρ = 0.25 m long and fails this.
    assert abs(lidar["median_m"]) < 0.06 and exact["median_m"] < -0.15
    # Which beams see the pole: the flank beams flip with the returns' phase, dropouts and the
    # pose error (8 episodes: 5 % missed, 3 % extra).
    assert lidar["missed"] < 0.12 and lidar["extra"] < 0.12 and lidar["seen_agreement"] > 0.98
    # The noise: the noisy draw's spread about the noise-free beam within a factor 1.6 of the
    # ingested one's (8 episodes: 0.086 m vs 0.090 m).
    assert 1 / 1.6 < noisy["std_m"] / lidar["std_m"] < 1.6
    # Radar, after the clutter filter first confirmed the pole. Same beam: the filter holds the
    # pole in 98 % of the sweeps, the bearing noise (1°) moves it across a sector edge now and
    # then. The range error: 1.5 m noise, but one sweep is held for 2 s (~20 steps), so a short
    # episode has only ~20 independent sweeps: the median within 1.2 m (~ 3 standard errors).
    c = b["confirmed"]
    radar = radar_agreement(b["simulated"][c, nL:nB], ing[c, nL:nB], LAYOUT.radar_range)
    noisy_radar = radar_agreement(
        b["simulated"][c, nL:nB], b["noisy"][c, nL:nB], LAYOUT.radar_range
    )
    assert radar["steps"] > 100
    assert radar["same_beam"] > 0.9 and radar["any_beam"] > 0.95
    assert abs(radar["median_m"]) < 1.2 and radar["other_beams_free"] > 0.99
    assert abs(noisy_radar["same_beam"] - radar["same_beam"]) < 0.08
    assert 0.5 < noisy_radar["std_m"] / radar["std_m"] < 2.0
