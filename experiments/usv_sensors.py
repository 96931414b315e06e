"""The USV task's simulated observations against what ingestion makes of the bags.

The global policy trains on :meth:`diffgcl.envs.usv.UsvEnv.obs` and its cloned baseline on the
ingested observations, so the two must agree. This script writes set-2 synthetic bags (LiDAR and
radar, :mod:`diffgcl.data.synth`), ingests them, moves each episode into the task frame, and
evaluates the simulated beams at the ingested states with the episode's true pole radius
(from the generator's truth), step by step:

* noise-free (``obs(x)``) and one noisy draw per step (``obs(x, key)``), and for comparison the
  exact pole geometry (:func:`diffgcl.envs.usv.pole_ranges`, equal to ``mjx.ray``) that the
  observation used before;
* LiDAR per band of distance from the mast to the pole's centre (:func:`diffgcl.eval.sensors.
  lidar_agreement`), radar per band (:func:`diffgcl.eval.sensors.radar_agreement`) after the
  radar's first reading of the pole in the episode (before it, the clutter filter has not yet
  confirmed the pole: counted separately), and the lag-1 autocorrelation of the radar error
  (the ingested radar holds one return per 2 s sweep);
* states where the hull touches the pole are left out (the synthetic operator sometimes does).

    python experiments/usv_sensors.py --json runs/usv_sensors.json     # 8 episodes
    python experiments/usv_sensors.py --fast                           # 2 short episodes
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from diffgcl.data.ingest import IngestWarning, ingest_bags  # noqa: E402
from diffgcl.data.synth import SynthConfig, synthesize  # noqa: E402
from diffgcl.data.task_frame import to_task_frame  # noqa: E402
from diffgcl.envs.usv import make_usv_env  # noqa: E402
from diffgcl.eval.sensors import demo_beams, lidar_agreement, radar_agreement  # noqa: E402
from diffgcl.runtime import prepare_process  # noqa: E402

LIDAR_BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 40.0), (40.0, 50.0), (50.0, 60.0))
RADAR_BANDS = ((0.0, 15.0), (15.0, 40.0), (40.0, 80.0), (80.0, 300.0))


def lag1_autocorrelation(err: np.ndarray, episode: np.ndarray) -> float:
    """Lag-1 autocorrelation of a per-step error series (pairs within one episode only)."""
    same = episode[1:] == episode[:-1]
    ok = same & np.isfinite(err[1:]) & np.isfinite(err[:-1])
    a, b = err[:-1][ok], err[1:][ok]
    return float(np.corrcoef(a, b)[0, 1]) if ok.sum() > 2 else float("nan")


def report(beams: dict[str, np.ndarray], layout) -> dict:
    """Per-band agreement of simulated, noisy and exact beams with the ingested ones."""
    nL, nB = layout.lidar_beams, layout.num_beams
    ing, dist = beams["ingested"], beams["distance"]
    result: dict = {"lidar": [], "radar": []}
    for lo, hi in (*LIDAR_BANDS, (0.0, 60.0)):
        sel = (dist >= lo) & (dist < hi)
        row = {"band_m": [lo, hi], "steps": int(sel.sum())}
        for name in ("simulated", "noisy", "exact"):
            row[name] = lidar_agreement(beams[name][sel, :nL], ing[sel, :nL], layout.lidar_range)
        row["noisy_vs_simulated"] = lidar_agreement(
            beams["simulated"][sel, :nL], beams["noisy"][sel, :nL], layout.lidar_range
        )
        result["lidar"].append(row)
    confirmed = beams["confirmed"]
    for lo, hi in (*RADAR_BANDS, (0.0, 300.0)):
        sel = (dist >= lo) & (dist < hi) & confirmed
        row = {"band_m": [lo, hi], "steps": int(sel.sum())}
        row["simulated"] = radar_agreement(
            beams["simulated"][sel, nL:nB], ing[sel, nL:nB], layout.radar_range
        )
        # How much of what ingestion reads the exact rays (no point target) also read.
        row["exact"] = radar_agreement(
            ing[sel, nL:nB], beams["exact"][sel, nL:nB], layout.radar_range
        )
        row["noisy_vs_simulated"] = radar_agreement(
            beams["simulated"][sel, nL:nB], beams["noisy"][sel, nL:nB], layout.radar_range
        )
        result["radar"].append(row)
    sim_r, ing_r = beams["simulated"][:, nL:nB], ing[:, nL:nB]
    beam = np.argmin(sim_r, axis=1)
    rows = np.arange(len(beam))
    both = (sim_r[rows, beam] < layout.radar_range) & (ing_r[rows, beam] < layout.radar_range)
    err = np.where(both & confirmed, ing_r[rows, beam] - sim_r[rows, beam], np.nan)
    noisy_r = beams["noisy"][:, nL:nB]
    both_n = both & (noisy_r[rows, beam] < layout.radar_range)
    err_n = np.where(both_n & confirmed, noisy_r[rows, beam] - sim_r[rows, beam], np.nan)
    result["radar_error_lag1_autocorrelation"] = {
        "ingested": lag1_autocorrelation(err, beams["episode"]),
        "noisy": lag1_autocorrelation(err_n, beams["episode"]),
    }
    result["radar_unconfirmed_steps"] = int((~confirmed).sum())
    result["steps"] = int(len(dist))
    return result


def print_report(r: dict) -> None:
    print(f"{r['steps']} steps; radar not yet confirmed at {r['radar_unconfirmed_steps']} steps")
    print("LiDAR (error = ingested or noisy - simulated noise-free, beams both see):")
    for row in r["lidar"]:
        s, n, e, v = row["simulated"], row["noisy_vs_simulated"], row["exact"], row["band_m"]
        print(
            f"  {v[0]:3.0f}-{v[1]:3.0f} m  ingested: median {s['median_m']:+.3f} std "
            f"{s['std_m']:.3f} q95 {s['q95_abs_m']:.3f} seen/step {s['seen_per_step'][1]:.2f} "
            f"missed {s['missed']:.3f} extra {s['extra']:.3f} | noisy: std {n['std_m']:.3f} "
            f"q95 {n['q95_abs_m']:.3f} seen/step {n['seen_per_step'][1]:.2f} missed "
            f"{n['missed']:.3f} | exact surface: median {e['median_m']:+.3f}"
        )
    print("Radar (the simulated pole beam; error = ingested or noisy - simulated):")
    for row in r["radar"]:
        s, n, v = row["simulated"], row["noisy_vs_simulated"], row["band_m"]
        print(
            f"  {v[0]:3.0f}-{v[1]:3.0f} m  ingested: same beam {s['same_beam']:.3f} any "
            f"{s['any_beam']:.3f} median {s['median_m']:+.2f} std {s['std_m']:.2f} others free "
            f"{s['other_beams_free']:.4f} | noisy: same beam {n['same_beam']:.3f} any "
            f"{n['any_beam']:.3f} std {n['std_m']:.2f} others free {n['other_beams_free']:.4f} "
            f"| exact rays read it: {row['exact']['same_beam']:.3f}"
        )
    ac = r["radar_error_lag1_autocorrelation"]
    print(
        f"radar error lag-1 autocorrelation: ingested {ac['ingested']:.2f}, noisy {ac['noisy']:.2f}"
    )


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fast", action="store_true", help="2 short episodes")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    prepare_process()
    t0 = time.perf_counter()
    n = 2 if args.fast else args.episodes
    approach = (60.0, 80.0) if args.fast else (140.0, 220.0)
    config = SynthConfig(
        episodes=(0, n),
        lidar=(False, True),
        approach_m=approach,
        end_margin_m=(30.0, 40.0) if args.fast else (60.0, 100.0),
        seed=args.seed,
    )
    with tempfile.TemporaryDirectory() as tmp:
        synth = synthesize(Path(tmp) / "bags", config)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IngestWarning)
            demos = to_task_frame(ingest_bags(list(synth.bags)))
    radii = np.array([e.profile.pole_radius for e in synth.episodes])
    beams = demo_beams(demos, radii, jax.random.PRNGKey(args.seed))
    result = report(beams, make_usv_env().layout)
    result.update(episodes=n, seed=args.seed, wall_seconds=time.perf_counter() - t0)
    print_report(result)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
