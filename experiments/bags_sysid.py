"""Odin-like bags -> demonstrations -> hull system identification, end to end.

1. ``synthesize``: the seed's data set layout — set 1 with 19 episodes and no LiDAR, set 2 with
   47 episodes with LiDAR — as ROS bags written from a simulated operator on the "true" hull
   (:func:`diffgcl.data.synth.true_params`, the defaults changed by documented factors).
2. ``ingest``: bags -> :class:`~diffgcl.data.demos.DemoSet` (grid dt = 0.1 s, masks, the hull
   env's observation layout).
3. ``identify``: multiple-shooting fit of :data:`diffgcl.data.sysid.SYSID_FIELDS` through
   ``hull_step`` on the even-numbered episodes, starting from the default parameters.
4. Report the relative error of each identified parameter and the one-step / 10 s open-loop
   prediction error on the odd-numbered (held-out) episodes before and after; plot the tracks of
   each set around the pole, coloured by swerve side.

    python experiments/bags_sysid.py --json runs/bags_sysid.json          # full (19 + 47)
    python experiments/bags_sysid.py --fast --json runs/bags_sysid_fast.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from diffgcl.data.demos import DemoSet  # noqa: E402
from diffgcl.data.ingest import IngestConfig, IngestWarning, ingest_bags  # noqa: E402
from diffgcl.data.synth import TRUE_FACTORS, SynthConfig, synthesize, true_params  # noqa: E402
from diffgcl.data.sysid import SysIdConfig, identify, prediction_error  # noqa: E402
from diffgcl.runtime import enable_compilation_cache  # noqa: E402
from diffgcl.sim import hull  # noqa: E402


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
    synth: SynthConfig
    sysid: SysIdConfig
    open_loop_s: float = 10.0


def default_config() -> ExperimentConfig:
    """The seed's data set size; sysid on up to 1024 windows of 1 s."""
    return ExperimentConfig(
        synth=SynthConfig(episodes=(19, 47), lidar=(False, True)),
        sysid=SysIdConfig(window=10, stride=5, max_windows=1024, iterations=8),
    )


def fast_config() -> ExperimentConfig:
    """A few short episodes per set, fewer windows."""
    return ExperimentConfig(
        synth=SynthConfig(
            episodes=(3, 5), lidar=(False, True), approach_m=(70.0, 90.0), end_margin_m=(30, 40)
        ),
        sysid=SysIdConfig(window=10, stride=5, max_windows=384, iterations=6),
    )


def course_frame(X: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Track [T+1, 2] in the pole's frame: pole at the origin, the approach course along +x
    (the direction from the first valid position to the pole)."""
    valid = mask.astype(bool)
    p = X[:, hull.IX_PX : hull.IX_PY + 1]
    pole = X[np.argmax(valid), hull.SL_OBS]
    d = pole - p[np.argmax(valid)]
    a = np.arctan2(d[1], d[0])
    c, s = np.cos(a), np.sin(a)
    rel = p - pole
    out = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], axis=1)
    out[~valid] = np.nan
    return out


def plot_set(demos: DemoSet, set_id: str, path: Path) -> None:
    """Tracks of one episode set around the pole, coloured by swerve side."""
    fig, ax = plt.subplots(figsize=(9, 4.5))
    colours = {"left": "tab:blue", "right": "tab:red", "unknown": "tab:gray"}
    seen = set()
    for i, meta in enumerate(demos.episodes):
        if str(meta.get("set")) != set_id:
            continue
        side = meta.get("swerve_side", "unknown")
        track = course_frame(demos.X[i], demos.mask[i])
        ax.plot(
            track[:, 0],
            track[:, 1],
            color=colours.get(side, "tab:gray"),
            lw=1.0,
            alpha=0.8,
            label=f"swerve {side}" if side not in seen else None,
        )
        seen.add(side)
    ax.plot([0], [0], "o", color="k", ms=6, label="pole")
    ax.set_aspect("equal")
    ax.set_xlabel("along the approach course (m)")
    ax.set_ylabel("to port (m)")
    n = sum(str(m.get("set")) == set_id for m in demos.episodes)
    lidar = any(m.get("lidar") for m in demos.episodes if str(m.get("set")) == set_id)
    ax.set_title(f"set {set_id}: {n} episodes, LiDAR {'yes' if lidar else 'no'}")
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    parser.add_argument("--fast", action="store_true", help="few short episodes")
    parser.add_argument("--out", type=Path, default=Path("runs/bags_sysid"), help="work folder")
    parser.add_argument(
        "--format", default="ros1", choices=("ros1", "ros2-sqlite3", "ros2-mcap"), dest="fmt"
    )
    parser.add_argument("--step", default="mjx", choices=("mjx", "ode"), help="sysid rollouts")
    parser.add_argument(
        "--method",
        default="gauss-newton",
        choices=("gauss-newton", "adam"),
        help="sysid optimiser (adam: 400 iterations, learning rate 0.02)",
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    enable_compilation_cache()

    base = fast_config() if args.fast else default_config()
    cfg = dataclasses.replace(
        base,
        synth=dataclasses.replace(base.synth, fmt=args.fmt, seed=args.seed),
        sysid=dataclasses.replace(
            base.sysid,
            step=args.step,
            method=args.method,
            **({"iterations": 400, "learning_rate": 0.02} if args.method == "adam" else {}),
        ),
    )
    args.out.mkdir(parents=True, exist_ok=True)
    timings = {}

    t0 = time.perf_counter()
    synth = synthesize(args.out / "bags", cfg.synth)
    timings["synth_s"] = time.perf_counter() - t0
    print(f"synth: {len(synth.episodes)} episodes, {len(synth.bags)} bags", file=sys.stderr)

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IngestWarning)
        demos = ingest_bags(list(synth.bags), config=IngestConfig())
    demos.save(args.out / "demos")
    timings["ingest_s"] = time.perf_counter() - t0
    sets = [str(m.get("set")) for m in demos.episodes]
    print(f"ingest: {demos.num_episodes} episodes, T={demos.horizon}", file=sys.stderr)

    train = demos.subset(slice(0, None, 2))
    test = demos.subset(slice(1, None, 2))
    truth = true_params()
    initial = hull.default_params()

    t0 = time.perf_counter()
    before = prediction_error(initial, test, cfg.open_loop_s, step=cfg.sysid.step)
    timings["prediction_before_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = identify(train, cfg.sysid, initial)
    timings["sysid_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    after = prediction_error(result.params, test, cfg.open_loop_s, step=cfg.sysid.step)
    truth_error = prediction_error(truth, test, cfg.open_loop_s, step=cfg.sysid.step)
    timings["prediction_after_s"] = time.perf_counter() - t0
    rel = result.relative_errors(truth)
    rel_before = {
        f: float(abs(float(getattr(initial, f)) / float(getattr(truth, f)) - 1.0))
        for f in result.fields
    }

    plots = []
    for set_id in sorted(set(sets)):
        path = args.out / f"tracks_set{set_id}.png"
        plot_set(demos, set_id, path)
        plots.append(str(path))

    def count(set_id, key, value):
        return sum(1 for m in demos.episodes if str(m.get("set")) == set_id and m.get(key) == value)

    report = {
        "fast": bool(args.fast),
        "bag_format": args.fmt,
        "episodes_set1": sets.count("1"),
        "episodes_set2": sets.count("2"),
        "lidar_set1": any(m.get("lidar") for m in demos.episodes if str(m.get("set")) == "1"),
        "lidar_set2": any(m.get("lidar") for m in demos.episodes if str(m.get("set")) == "2"),
        "poles": {s: {c: count(s, "obstacle", c) for c in ("green", "grey")} for s in ("1", "2")},
        "swerve_sides": {
            s: {c: count(s, "swerve_side", c) for c in ("left", "right")} for s in ("1", "2")
        },
        "horizon": demos.horizon,
        "dt": demos.dt,
        "valid_fraction": float(demos.mask.mean()),
        "sysid_fields": list(result.fields),
        "sysid_step": cfg.sysid.step,
        "sysid_method": cfg.sysid.method,
        "sysid_windows": cfg.sysid.max_windows,
        "sysid_window_s": cfg.sysid.window * demos.dt,
        "train_episodes": train.num_episodes,
        "test_episodes": test.num_episodes,
        "true_factors": TRUE_FACTORS,
        "params_true": {f: float(getattr(truth, f)) for f in result.fields},
        "params_initial": {f: float(getattr(initial, f)) for f in result.fields},
        "params_identified": result.values(),
        "param_rel_error_before": rel_before,
        "param_rel_error": rel,
        "max_param_rel_error": max(rel.values()),
        "sysid_loss": result.loss.tolist(),
        "prediction_error_before": before.as_dict(),
        "prediction_error_after": after.as_dict(),
        "prediction_error_true_params": truth_error.as_dict(),
        "plots": plots,
        "timings": timings,
    }
    text = json.dumps(report, indent=1)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text)
    print(
        json.dumps(
            {
                k: report[k]
                for k in (
                    "episodes_set1",
                    "episodes_set2",
                    "lidar_set1",
                    "max_param_rel_error",
                    "param_rel_error",
                )
            },
            indent=1,
        )
    )
    print(
        "open-loop 10 s position RMSE (m): before "
        f"{before.open_loop['position_rmse_m']:.2f}, after {after.open_loop['position_rmse_m']:.2f}"
        f" (true params {truth_error.open_loop['position_rmse_m']:.2f})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
