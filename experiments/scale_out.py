"""The same rGCL sweep in 1 process × 2 devices and in 2 processes × 1 device.

Each layout is one ``diffgcl sweep`` command in a fresh process (the device count is fixed when
JAX starts), the ``default`` preset, 32 seeds as one chunk of 32 runs (16 per device):

    python -m diffgcl.cli sweep --preset default --schedule v2 --seeds 32 --devices 2 --json A
    python -m diffgcl.cli sweep --preset default --schedule v2 --seeds 32 \\
        --local-processes 2 --devices 1 --json B

Reported per layout: ``wall_seconds`` (the whole command: start-up, imports, demos,
compilation, runs, gathers), and the sweep's own ``compile_seconds`` and ``run_seconds`` (process
0's; the runs are timed once every process has compiled, the all-gather of the outcomes
included). ``run_ratio`` = run seconds of 2 processes / run seconds of 1 process (> 1: the
processes are slower); ``wall_ratio`` likewise. ``identical_outcomes``: every run's success,
final distance and final true cost are bitwise equal in the two layouts (each device runs the
same program on the same runs). With ``--repeats N`` the layouts alternate N times and each
figure is the best of N. On CPU, process 1 compiles afresh in every run (JAX's persistent
cache is written by process 0 only and its keys differ per process), which the wall time shows
and the run time does not; ``*_each`` lists every repeat. ``load_average`` (1 min, before and
after) says how busy the machine was: the figures are only comparable on a quiet one.

    python experiments/scale_out.py --json PATH [--seeds 32] [--repeats 1] [--fast] [--x64]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LAYOUTS = {
    "1_process_x_2_devices": ["--devices", "2"],
    "2_processes_x_1_device": ["--local-processes", "2", "--devices", "1"],
}


def run_layout(name: str, sweep_args: list[str], folder: Path) -> dict:
    """One ``diffgcl sweep`` command in a fresh process; its JSON summary and wall time."""
    out = folder / f"{name}.json"
    command = [sys.executable, "-m", "diffgcl.cli", "sweep", *sweep_args, *LAYOUTS[name]]
    command += ["--json", str(out)]
    t0 = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"scale_out: {name} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    summary = json.loads(out.read_text())
    return {"wall_seconds": wall, "summary": summary, "command": " ".join(command[1:])}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--seeds", type=int, default=32)
    parser.add_argument("--preset", default="default")
    parser.add_argument("--schedule", default="v2")
    parser.add_argument("--repeats", type=int, default=1, help="best of N per layout")
    parser.add_argument("--fast", action="store_true", help="4 seeds, 3 iterations")
    parser.add_argument("--x64", action="store_true")
    args = parser.parse_args(argv)
    seeds = 4 if args.fast else args.seeds
    sweep_args = ["--preset", args.preset, "--schedule", args.schedule, "--seeds", str(seeds)]
    sweep_args += ["--chunk", str(seeds)]
    if args.fast:
        sweep_args += ["--iterations", "3"]
    if args.x64:
        sweep_args.append("--x64")
    load_before = os.getloadavg()[0]
    best: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):
            for name in LAYOUTS:
                r = run_layout(name, sweep_args, Path(tmp))
                s = r["summary"]
                print(
                    f"[{repeat + 1}/{args.repeats}] {name}: wall {r['wall_seconds']:.1f} s, "
                    f"compile {s['compile_seconds']:.1f} s, run {s['run_seconds']:.2f} s "
                    f"({s['processes']} process(es), {s['devices']} devices)"
                )
                b = best.setdefault(name, {"command": r["command"], "runs": s["runs"]})
                for key, value in (
                    ("wall_seconds", r["wall_seconds"]),
                    ("compile_seconds", s["compile_seconds"]),
                    ("run_seconds", s["run_seconds"]),
                ):
                    b[key] = min(b.get(key, float("inf")), value)
                    b.setdefault(f"{key}_each", []).append(value)
                b.update(processes=s["processes"], devices=s["devices"], chunk=s["chunk"])
                if b["runs"] != s["runs"]:
                    raise SystemExit(f"scale_out: {name} gave different outcomes on repeat")
    one, two = best["1_process_x_2_devices"], best["2_processes_x_1_device"]
    result = {
        "preset": args.preset,
        "schedule": args.schedule,
        "seeds": seeds,
        "fast": args.fast,
        "repeats": args.repeats,
        "cpu_count": os.cpu_count(),
        "load_average": [load_before, os.getloadavg()[0]],
        "success_rate": sum(r["success"] for r in one["runs"]) / len(one["runs"]),
        "identical_outcomes": one["runs"] == two["runs"],
        "run_ratio": two["run_seconds"] / one["run_seconds"],
        "wall_ratio": two["wall_seconds"] / one["wall_seconds"],
        "layouts": {name: {k: v for k, v in b.items() if k != "runs"} for name, b in best.items()},
    }
    print(
        f"run time 2 processes / 1 process: {result['run_ratio']:.2f} "
        f"({two['run_seconds']:.2f} / {one['run_seconds']:.2f} s); wall "
        f"{result['wall_ratio']:.2f}; identical outcomes: {result['identical_outcomes']}; "
        f"success {result['success_rate']:.2f}; load average {load_before:.1f} -> "
        f"{result['load_average'][1]:.1f} on {os.cpu_count()} cores"
    )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1))
    print(f"summary in {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
