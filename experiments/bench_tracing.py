"""Where a training run's first minutes go, and what two settings save: tracing and compiling the
USV ``--fast`` rGCL + MDGPS run (main run only: identification, training, evaluation), each
setting in a fresh process, first with an empty compile cache (cold), then again with the cache
it filled (warm).

Settings, side by side: ``reference`` — Python's default garbage-collector thresholds and
``hull_step`` traced afresh at every call (as before); ``jitted hull_step`` — ``hull_step`` a
jitted function, so that JAX traces it once per shape and reuses its batched and differentiated
forms; ``+ relaxed GC`` — also :func:`diffgcl.runtime.relax_garbage_collection` (what every entry
point now does). Seconds are summed over all programs from JAX's monitoring events: tracing
(Python → jaxpr), lowering (jaxpr → MLIR), XLA compiling; ``wall`` is the whole run. Each
setting must reproduce the reference's figures exactly (checked)::

    python experiments/bench_tracing.py [--json runs/bench_tracing.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SETTINGS = {
    "reference": {"jit_hull_step": False, "relax_gc": False},
    "jitted hull_step": {"jit_hull_step": True, "relax_gc": False},
    "+ relaxed GC": {"jit_hull_step": True, "relax_gc": True},
}
EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
    "/jax/core/compile/backend_compile_duration": "compile_s",
}
FIGURES = ("collision_rate", "return_to_course_rate", "clearance_ratio_vs_demos")


def worker(setting: str, cache: str) -> dict:
    """One run of the fast pipeline in this process under ``setting``; its seconds and figures."""
    import gc

    t0 = time.perf_counter()
    from diffgcl.runtime import prepare_process

    prepare_process(cache)
    flags = SETTINGS[setting]
    if not flags["relax_gc"]:
        gc.set_threshold(700, 10, 10)  # Python's default
    import dataclasses

    import jax

    from diffgcl.data.synth import true_params
    from diffgcl.sim import hull
    from diffgcl.usv import builtin_demos, fast_run_config, run_usv

    if not flags["jit_hull_step"]:
        hull.hull_step = hull.hull_step.__wrapped__  # the envs look it up in the module

    seconds = dict.fromkeys(EVENTS.values(), 0.0)

    def listen(event: str, duration: float, **_) -> None:
        if event in EVENTS:
            seconds[EVENTS[event]] += duration

    jax.monitoring.register_event_duration_secs_listener(listen)
    demos, folder = builtin_demos(fast=True, verbose=False)
    config = dataclasses.replace(fast_run_config(), methods=("rgcl",))
    run = run_usv(
        demos, config, manifest=folder / "manifest.json", true_params=true_params(), verbose=False
    )
    return {
        **seconds,
        "wall_s": time.perf_counter() - t0,
        "figures": {k: run.summary["rgcl"][k] for k in FIGURES},
    }


def run_worker(setting: str, cache: str) -> dict:
    out = subprocess.run(
        [sys.executable, __file__, "--worker", setting, "--cache", cache],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--worker", choices=tuple(SETTINGS), default=None, help=argparse.SUPPRESS)
    parser.add_argument("--cache", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        print(json.dumps(worker(args.worker, args.cache)))
        return 0

    from diffgcl.usv import builtin_bags

    builtin_bags(fast=True)  # written once, outside the timings
    results: dict = {}
    print(f"{'setting':18s} {'cache':5s} {'trace':>7s} {'lower':>7s} {'compile':>8s} {'wall':>7s}")
    for setting in SETTINGS:
        with tempfile.TemporaryDirectory(prefix="diffgcl-bench-cache-") as cache:
            for phase in ("cold", "warm"):
                r = run_worker(setting, cache)
                results.setdefault(setting, {})[phase] = r
                print(
                    f"{setting:18s} {phase:5s} {r['trace_s']:6.1f}s {r['lower_s']:6.1f}s "
                    f"{r['compile_s']:7.1f}s {r['wall_s']:6.1f}s",
                    flush=True,
                )
    reference = results["reference"]["cold"]["figures"]
    same = all(r[p]["figures"] == reference for r in results.values() for p in r)
    print(f"figures identical in every setting and phase: {same} ({reference})")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"settings": results, "figures_identical": same}, indent=1))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
