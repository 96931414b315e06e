"""Where a user's first minutes go: tracing and XLA compiling of every user entry point, each in a
fresh process with an empty persistent compilation cache, beside the run time after compiling.

Entry points (``--entries``, default all):

* ``arm_v2``, ``arm_v1`` — rGCL on the arm, ``default`` preset, the 32-seed batch of
  ``experiments/arm_rgcl.py`` (compiled and run once);
* ``arm_v2_train``, ``arm_v1_train`` — the same 32 seeds through
  :func:`diffgcl.algorithms.runner.train_seeds`, the runner behind ``diffgcl train`` and the API
  (staged: the simulator's programs shared, small programs without physics for the rest of
  an iteration), run to the end;
* ``arm_mdgps`` — rGCL v2 with a global policy (MDGPS) on the arm's four training starts of
  ``experiments/arm_policy.py`` (2 seeds, 10 iterations);
* ``reacher_learn``, ``cartpole_learn`` — the ten lines of :mod:`diffgcl.api` on
  ``models/reacher.xml`` / ``models/cartpole.xml`` with ``policy=True`` (learn, report with the
  re-optimisation check, save, the policy from held-out starts: ``experiments/any_mjcf.py``'s
  ``learn_from_demos``, 1 seed, 10 iterations); their demos are made once beforehand, outside
  the timings;
* ``usv_fast`` — the whole ``experiments/usv_avoidance.py --fast`` (its bags are written once
  beforehand, outside the timings).

Per entry point, from JAX's monitoring events: seconds tracing (Python → jaxpr), lowering
(jaxpr → StableHLO) and XLA compiling, summed over every program; the number of programs XLA
compiled, and for each program that took more than 0.5 s its name, compile seconds and size
(StableHLO operations, counted in the lowered module); ``run_s`` = wall − (trace + lower +
compile), the time spent running.

``--baseline REV`` runs every entry point a second time with the library as it was at git
revision ``REV`` (extracted to a temporary folder and imported from there), alternating
baseline and current, each in its own fresh process and empty cache: the figures before and after
a change, measured in one run on the same machine. A version whose process fails (a crash) is
reported in the table and the JSON (``runs.failed``), and the other runs go on::

    python experiments/bench_compile.py --json runs/bench_compile.json [--baseline REV]
        [--entries arm_v2,reacher_learn] [--repeats 1]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENTRIES = (
    "arm_v2",
    "arm_v1",
    "arm_v2_train",
    "arm_v1_train",
    "arm_mdgps",
    "reacher_learn",
    "cartpole_learn",
    "usv_fast",
)
EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
    "/jax/core/compile/backend_compile_duration": "compile_s",
}
BIG_PROGRAM_S = 0.5  # programs compiling longer than this are listed with their size


# ---- the worker: one entry point in this process ------------------------------------------------


def _count_ops(module) -> int:
    """StableHLO operations in a lowered MLIR module (every nested operation)."""
    count = 0

    def visit(op):
        nonlocal count
        count += 1
        return 0  # mlir.ir.WalkResult.ADVANCE

    try:
        module.operation.walk(visit)
    except (AttributeError, TypeError):  # older MLIR bindings: count lines of the text form
        count = str(module).count("\n")
    return count


def _instrument(record: dict) -> None:
    """Listen to JAX's compile events and measure the size of each program XLA compiles."""
    import jax
    from jax._src import compiler

    traces = record.setdefault("traces", {})

    def listen(event: str, duration: float, **kwargs) -> None:
        key = EVENTS.get(event)
        if key is not None:
            record[key] += duration
            if key == "compile_s":
                record["programs"] += 1
            if key == "trace_s":
                name = str(kwargs.get("fun_name", "?"))
                traces[name] = traces.get(name, 0.0) + duration

    jax.monitoring.register_event_duration_secs_listener(listen)
    original = compiler.compile_or_get_cached

    def compile_or_get_cached(backend, computation, *args, **kwargs):
        t0 = time.perf_counter()
        out = original(backend, computation, *args, **kwargs)
        seconds = time.perf_counter() - t0
        if seconds > BIG_PROGRAM_S:
            name = "?"
            try:
                name = str(computation.operation.attributes["sym_name"]).strip('"')
            except (KeyError, AttributeError):
                pass
            record["big_programs"].append(
                {"name": name, "compile_s": round(seconds, 2), "ops": _count_ops(computation)}
            )
        return out

    compiler.compile_or_get_cached = compile_or_get_cached


def _arm_rgcl(schedule: str) -> dict:
    import jax
    import jax.numpy as jnp

    sys.path.insert(0, str(Path.cwd() / "experiments"))
    from arm_rgcl import CHUNK, compile_batch, make_config  # noqa: E402

    from diffgcl.algorithms.runner import load_demo_batch
    from diffgcl.envs import make_env

    env = make_env("arm")
    demos = load_demo_batch(None, env)
    args = argparse.Namespace(preset="default", set=[], fast=False)
    program = compile_batch(make_config(args, schedule), env, demos, CHUNK)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in range(CHUNK)])
    state, _ = jax.block_until_ready(program.compiled(keys, demos))
    return {"seeds": CHUNK}


def _arm_train(schedule: str) -> dict:
    import numpy as np

    sys.path.insert(0, str(Path.cwd() / "experiments"))
    from arm_rgcl import CHUNK, make_config  # noqa: E402

    from diffgcl.algorithms.runner import load_demo_batch, train_seeds
    from diffgcl.envs import make_env

    env = make_env("arm")
    demos = load_demo_batch(None, env)
    args = argparse.Namespace(preset="default", set=[], fast=False)
    config = make_config(args, schedule)
    result = train_seeds(config, env, demos, range(CHUNK), progress=False)
    success = float(np.mean(np.asarray(result.metrics.gps.success)[:, -1]))
    return {"seeds": CHUNK, "iterations": config.iterations, "final_success_rate": success}


def _arm_mdgps() -> dict:
    import dataclasses

    import jax
    import jax.numpy as jnp

    sys.path.insert(0, str(Path.cwd() / "experiments"))
    from arm_policy import TRAIN_STARTS, expert_demos, policy_settings, starts  # noqa: E402

    from diffgcl.algorithms.presets import default
    from diffgcl.algorithms.rgcl import demo_batch, make_train
    from diffgcl.envs import make_env

    env = make_env("arm", x0=starts(TRAIN_STARTS))
    batch = demo_batch(expert_demos(env), len(TRAIN_STARTS), env=env)
    config = dataclasses.replace(
        default("v2"), policy=policy_settings(True), iterations=10, freeze_last=2
    )
    rgcl = make_train(config, env)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in range(2)])
    jax.block_until_ready(jax.jit(jax.vmap(rgcl.train, in_axes=(0, None)))(keys, batch))
    return {"seeds": 2}


def _mjcf_learn(model: str, demos_dir: Path) -> dict:
    sys.path.insert(0, str(Path.cwd() / "experiments"))
    from any_mjcf import learn_from_demos, tasks  # noqa: E402

    with tempfile.TemporaryDirectory(prefix="diffgcl-bench-run-") as out:
        report = learn_from_demos(
            tasks()[model], demos_dir / model / "demos.npz", Path(out), seeds=[0], iterations=10
        )
    return {
        "success_rate": report.get("success_rate"),
        "policy_held_out_success_rate": report["policy"]["held_out_success_rate"],
    }


def _usv_fast() -> dict:
    sys.path.insert(0, str(Path.cwd() / "experiments"))
    import usv_avoidance  # noqa: E402

    with tempfile.TemporaryDirectory(prefix="diffgcl-bench-usv-") as out:
        path = Path(out) / "usv.json"
        usv_avoidance.main(["--fast", "--json", str(path), "--out", str(Path(out) / "run")])
        summary = json.loads(path.read_text())
    keys = ("collision_rate", "return_to_course_rate", "clearance_ratio_vs_demos")
    return {k: summary.get(k) for k in (*keys, "bc_collision_rate", "radar_only_collision_rate")}


def worker(entry: str, jax_cache: str, demos_dir: Path) -> dict:
    t0 = time.perf_counter()

    from diffgcl.runtime import prepare_process

    # ``$DIFFGCL_CACHE`` is this worker's own (fresh_cache_root): the persistent compilation
    # cache starts empty, in this process and in any it starts.
    directory = prepare_process()
    assert str(directory) == jax_cache, (directory, jax_cache)
    record = {"trace_s": 0.0, "lower_s": 0.0, "compile_s": 0.0, "programs": 0, "big_programs": []}
    _instrument(record)
    if entry in ("arm_v2", "arm_v1"):
        figures = _arm_rgcl(entry[-2:])
    elif entry in ("arm_v2_train", "arm_v1_train"):
        figures = _arm_train(entry[4:6])
    elif entry == "arm_mdgps":
        figures = _arm_mdgps()
    elif entry in ("reacher_learn", "cartpole_learn"):
        figures = _mjcf_learn(entry.split("_")[0], demos_dir)
    elif entry == "usv_fast":
        figures = _usv_fast()
    else:
        raise SystemExit(f"unknown entry point {entry!r}; choose from {ENTRIES}")
    wall = time.perf_counter() - t0
    record["big_programs"].sort(key=lambda p: -p["compile_s"])
    top = sorted(record.pop("traces").items(), key=lambda kv: -kv[1])[:15]
    record["slowest_traces"] = [{"name": n, "trace_s": round(t, 2)} for n, t in top]
    busy = record["trace_s"] + record["lower_s"] + record["compile_s"]
    return {**record, "wall_s": wall, "run_s": max(0.0, wall - busy), "figures": figures}


# ---- the driver ---------------------------------------------------------------------------------


def prepare_inputs(code: Path, demos_dir: Path, entries) -> None:
    """What the entry points read but must not time: the arm's and the models' expert demos and
    the USV's built-in bags (cached under ``$DIFFGCL_CACHE``; made with ``code``)."""
    script = f"""
import sys; sys.path.insert(0, 'experiments')
from pathlib import Path
from diffgcl.runtime import prepare_process
prepare_process()
entries = {list(entries)!r}
if any(e.startswith('arm') for e in entries):
    from diffgcl.algorithms.runner import load_demo_batch
    from diffgcl.envs import make_env
    load_demo_batch(None, make_env('arm'))
if 'arm_mdgps' in entries:
    from arm_policy import TRAIN_STARTS, expert_demos, starts
    expert_demos(make_env('arm', x0=starts(TRAIN_STARTS)))
for model in ('reacher', 'cartpole'):
    path = Path({str(demos_dir)!r}) / model / 'demos.npz'
    if model + '_learn' in entries and not path.is_file():
        from any_mjcf import expert_demos, tasks
        expert_demos(tasks()[model], path, seeds=[0, 1], demos_per_condition=3)
if 'usv_fast' in entries:
    try:
        from diffgcl.usv import builtin_bags
    except ImportError:  # a revision before the USV pipeline had a package of its own
        from diffgcl.algorithms.usv import builtin_bags
    builtin_bags(fast=True, verbose=False)
"""
    subprocess.run([sys.executable, "-c", script], check=True, cwd=code, env=_env(code))


def _env(code: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(code) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def cache_root() -> Path:
    return Path(os.environ.get("DIFFGCL_CACHE", Path.home() / ".cache" / "diffgcl"))


def fresh_cache_root(into: Path) -> Path:
    """A ``$DIFFGCL_CACHE`` for one worker: links to everything in the usual one (bags, demos)
    but its ``jax`` folder, the persistent compilation cache, which starts empty. Every process
    the worker starts (the USV script's radar variant) inherits it."""
    root = into / "cache"
    root.mkdir()
    source = cache_root()
    if source.is_dir():
        for item in source.iterdir():
            if item.name != "jax":
                (root / item.name).symlink_to(item.resolve())
    return root


class WorkerFailed(RuntimeError):
    """An entry point's process failed (a crash of a library version, say): reported, and the
    other entry points and versions still run."""


def run_worker(code: Path, entry: str, demos_dir: Path) -> dict:
    with tempfile.TemporaryDirectory(prefix="diffgcl-bench-worker-") as tmp:
        env = _env(code)
        env["DIFFGCL_CACHE"] = str(fresh_cache_root(Path(tmp)))
        cache = str(Path(env["DIFFGCL_CACHE"]) / "jax")
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", entry]
        cmd += ["--jax-cache", cache, "--demos-dir", str(demos_dir)]
        out = subprocess.run(cmd, cwd=code, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        how = (
            f"killed by signal {-out.returncode}"
            if out.returncode < 0
            else f"exit {out.returncode}"
        )
        tail = "\n".join(out.stderr.strip().splitlines()[-15:])
        raise WorkerFailed(f"{entry} ({code}) failed, {how}:\n{tail}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def extract_revision(rev: str, into: Path) -> Path:
    """The tree of git revision ``rev`` (library, models, experiments) in ``into``."""
    archive = into / "tree.tar"
    subprocess.run(
        ["git", "archive", "--format=tar", "-o", str(archive), rev], cwd=ROOT, check=True
    )
    with tarfile.open(archive) as tar:
        tar.extractall(into / "tree", filter="data")
    return into / "tree"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--entries", default=",".join(ENTRIES), help="comma-separated")
    parser.add_argument("--baseline", default=None, help="git revision to measure beside")
    parser.add_argument("--repeats", type=int, default=1, help="fresh processes per entry")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--jax-cache", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--demos-dir", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        print(json.dumps(worker(args.worker, args.jax_cache, args.demos_dir)))
        return 0

    entries = [e for e in args.entries.split(",") if e]
    unknown = sorted(set(entries) - set(ENTRIES))
    if unknown:
        raise SystemExit(f"--entries: unknown {unknown}; choose from {ENTRIES}")
    with tempfile.TemporaryDirectory(prefix="diffgcl-bench-compile-") as tmp:
        tmp = Path(tmp)
        codes = {"current": ROOT}
        if args.baseline:
            codes = {"baseline": extract_revision(args.baseline, tmp), **codes}
        demos_dir = tmp / "demos"
        for code in codes.values():  # each version makes (and caches) what its entries read
            prepare_inputs(code, demos_dir, entries)
        results: dict = {name: {} for name in codes}
        head = f"{'entry':16s} {'code':9s} {'trace':>7s} {'lower':>7s} {'compile':>8s} "
        print(head + f"{'programs':>8s} {'run':>7s} {'wall':>7s}", flush=True)
        for entry in entries:
            for _ in range(args.repeats):
                for name, code in codes.items():
                    try:
                        r = run_worker(code, entry, demos_dir)
                    except WorkerFailed as err:
                        print(f"{entry:16s} {name:9s} {str(err).splitlines()[0]}", flush=True)
                        failures = results.setdefault("failed", {}).setdefault(name, {})
                        failures[entry] = str(err)
                        continue
                    results[name].setdefault(entry, []).append(r)
                    print(
                        f"{entry:16s} {name:9s} {r['trace_s']:6.1f}s {r['lower_s']:6.1f}s "
                        f"{r['compile_s']:7.1f}s {r['programs']:8d} {r['run_s']:6.1f}s "
                        f"{r['wall_s']:6.1f}s",
                        flush=True,
                    )
    summary = summarise(results)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1))
        print(f"wrote {args.json}")
    return 0


def summarise(results: dict) -> dict:
    """The headline keys (the best of the repeats, current code), the baseline's beside them with
    the suffix ``_baseline``, and every run."""

    def best(runs, key):
        return min(r[key] for r in runs)

    out: dict = {"runs": results}
    for name, suffix in (("current", ""), ("baseline", "_baseline")):
        by_entry = {e: runs for e, runs in results.get(name, {}).items() if runs}
        if not by_entry:
            continue
        headline = {
            "reacher_learn_compile_s": ("reacher_learn", "compile_s"),
            "cartpole_learn_compile_s": ("cartpole_learn", "compile_s"),
            "arm_v2_compile_s": ("arm_v2", "compile_s"),
            "arm_v1_compile_s": ("arm_v1", "compile_s"),
            "arm_v2_train_compile_s": ("arm_v2_train", "compile_s"),
            "arm_v1_train_compile_s": ("arm_v1_train", "compile_s"),
            "arm_mdgps_compile_s": ("arm_mdgps", "compile_s"),
            "usv_fast_wall_s": ("usv_fast", "wall_s"),
        }
        for key, (entry, field) in headline.items():
            if entry in by_entry:
                out[key + suffix] = best(by_entry[entry], field)
        out["programs_per_entry_point" + suffix] = {
            e: runs[0]["programs"] for e, runs in by_entry.items()
        }
        out["trace_s" + suffix] = {e: best(runs, "trace_s") for e, runs in by_entry.items()}
        out["run_s" + suffix] = {e: best(runs, "run_s") for e, runs in by_entry.items()}
    return out


if __name__ == "__main__":
    sys.exit(main())
