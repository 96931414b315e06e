"""rGCL on the two-joint arm: the seed's chapter 4 experiment, v1 and v2, over seeds and tasks.

For each schedule of the preset (``default``: v1 and v2 of ours; ``paper``: the seed's paper_v1
and paper_v2; ``paper_v1`` / ``paper_v2`` alone), every seed set runs as ``jit(vmap(train))``
batches (chunks of 32, sharded over the CPU's cores) on the task's expert demos
(:func:`diffgcl.algorithms.expert.builtin_demos`, generated and cached per task).

Seeds. *Tuning* seeds (``--first-seed``, default 0–31) are the ones the ``default`` preset was
tuned on (0–95); *held-out* seeds (``--heldout-first``, default 1000–1031) were never used for
tuning, and every figure is reported for both, the held-out ones with the suffix
``_heldout_seeds``. The two other arm tasks (:data:`OTHER_TASKS`: another start and target each,
expert demos generated for them) run on the held-out seeds with the preset unchanged.

Figures per schedule and seed set: ``success_rate`` (DESIGN §2: the final controllers'
noise-free rollout within 0.1 rad of the target on both joints over the last 10 steps),
``mean_final_distance`` (largest joint error at the last step), ``reopt_success_rate`` (a fresh
controller optimised by GPS on the frozen learned cost, same test), ``epic_distance`` (the
learned per-step cost against the expert cost on a coverage set of arm transitions), and the fit
of the final controllers as a distribution (:mod:`diffgcl.eval.controllers`, 20 samples per
seed): ``sample_success_rate`` (noisy samples with their own Σ, time-smoothed noise as in GPS's
samples) and ``sample_success_rate_white`` (white noise), ``entropy_gap_nats`` (controller
minus the demos' controller action entropy, nats), ``demo_log_likelihood`` (the demos' mean
action log-likelihood under the final controllers, beside ``demo_self_log_likelihood`` under
their own) and ``log_temperature`` (the cost's ρ, :mod:`diffgcl.costs.temperature`).

Timing (v2, or the preset's only schedule; tuning seeds): ``seconds_per_run_after_compile`` is
one unbatched run of ``jit(train)`` after compilation (best of 2); ``sweep_speedup`` divides the
time of the seeds run one by one through that single-run program on one device by the time of
the batch sharded over all devices (one XLA CPU device per core); ``sweep_speedup_fair`` divides
instead the time of the same loop run as concurrent streams, one per device (so one per core),
the runs dispatched alternately to each. All best of 2, after compilation. ``compile_seconds``
is the lowering + compilation of the batch program in this process (the persistent compilation
cache on, so usually warm); ``compile_seconds_empty_cache`` the same in a fresh process with an
empty temporary cache (``--no-empty-cache-compile`` skips it).

    python experiments/arm_rgcl.py --preset default --seeds 32 --json out.json [--fast]
        [--heldout-seeds 32] [--no-tasks] [--no-timing] [--set temperature=likelihood ...]
        [--out DIR] [--devices N]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.algorithms.presets import default, paper_v1, paper_v2, with_overrides
from diffgcl.algorithms.rgcl import final_rollouts, make_train
from diffgcl.algorithms.runner import load_demo_batch
from diffgcl.eval.controllers import distribution_fit
from diffgcl.eval.learned_cost import evaluate_cost
from diffgcl.runtime import add_devices_option, apply_devices_option
from diffgcl.sim.sharding import shard_batch_if_even, vmap_over_devices

TIMING_REPEATS = 2  # the sweep speed-ups compare best-of-2 times of the batch and the loops
CHUNK = 32  # seeds per batch
FAST_SEEDS = 8  # --fast: seeds per set (with 4 the batch and the loop took the same time)

SCHEDULES = {
    "default": {"v1": lambda: default("v1"), "v2": lambda: default("v2")},
    "paper": {"v1": paper_v1, "v2": paper_v2},
    "paper_v1": {"v1": paper_v1},
    "paper_v2": {"v2": paper_v2},
}

# Two other arm tasks (start, target), reported on the held-out seeds without retuning.
OTHER_TASKS = {
    "start_half_pi": {
        "x0": [0.5 * math.pi, 0.5 * math.pi, 0.0, 0.0],
        "target": [-0.25 * math.pi, 0.25 * math.pi],
    },
    "fold_back": {
        "x0": [-0.25 * math.pi, -0.75 * math.pi, 0.0, 0.0],
        "target": [0.25 * math.pi, 0.25 * math.pi],
    },
}


@dataclasses.dataclass
class BatchProgram:
    """One schedule's batch program on one task, compiled once and run on every seed set of
    that task (chunks of ``size`` seeds)."""

    rgcl: object
    batch: object
    compiled: object
    size: int
    compile_seconds: float


def compile_batch(config, env, demos, size: int) -> BatchProgram:
    """``jit(vmap(train))`` sharded over the devices, lowered and compiled for ``size`` seeds."""
    rgcl = make_train(config, env)
    keys = shard_batch_if_even(jnp.stack([jax.random.PRNGKey(s) for s in range(size)]))
    batch = jax.jit(vmap_over_devices(rgcl.train, in_axes=(0, None)))
    t0 = time.perf_counter()
    compiled = batch.lower(keys, demos).compile()
    return BatchProgram(rgcl, batch, compiled, size, time.perf_counter() - t0)


def run_schedule(program: BatchProgram, env, demos, seeds, *, timing_repeats: int = 1) -> dict:
    """All seeds of one schedule as vmapped batches of the compiled program; returns the states,
    metrics, outcome per seed and the batch's run time."""
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    size, compiled, batch = program.size, program.compiled, program.batch
    states, metrics = [], []
    t0 = time.perf_counter()
    for i in range(0, len(seeds), size):
        k = shard_batch_if_even(keys[i : i + size])
        fn = compiled if k.shape[0] == size else batch
        state, m = jax.block_until_ready(fn(k, demos))
        states.append(jax.tree.map(np.asarray, state))
        metrics.append(jax.tree.map(np.asarray, m))
    batch_seconds = time.perf_counter() - t0
    if timing_repeats > 1 and len(seeds) <= size:  # best of N, as the loops are timed
        k = shard_batch_if_even(keys)
        for _ in range(timing_repeats - 1):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(k, demos))
            batch_seconds = min(batch_seconds, time.perf_counter() - t0)
    state = jax.tree.map(lambda *a: np.concatenate(a), *states)
    m = jax.tree.map(lambda *a: np.concatenate(a), *metrics)
    controller = jax.tree.map(jnp.asarray, state.gps.controller)
    X = np.asarray(jax.jit(jax.vmap(lambda c: final_rollouts(env, c)))(controller))
    success = np.asarray(jax.vmap(jax.vmap(env.success))(jnp.asarray(X))).all(-1)
    dist = np.abs(X[:, :, -1, :2] - np.asarray(env.target)).max(axis=(1, 2))
    fit_keys = jnp.stack([jax.random.PRNGKey(200_000 + s) for s in seeds])
    fit = jax.jit(
        jax.vmap(
            lambda c, k: distribution_fit(env, c, demos.controller, demos.X, demos.U, k),
        )
    )(controller, fit_keys)
    return {
        "rgcl": program.rgcl,
        "state": state,
        "metrics": m,
        "success": success,
        "final_distance": dist,
        "fit": jax.tree.map(np.asarray, fit),
        "batch_seconds": batch_seconds,
        "keys": keys,
    }


def figures(res: dict, config, env, seeds, suffix: str) -> dict:
    """The per-split figures of the module docstring, keys ``<name><suffix>``."""
    cost_eval = evaluate_cost(config, env, res["state"].cost.params, seeds)
    fit, m = res["fit"], res["metrics"]
    c_iters = m.gps.c_step_iterations
    out = {
        "seeds": [int(s) for s in seeds],
        "success_rate": float(res["success"].mean()),
        "successes": int(res["success"].sum()),
        "mean_final_distance": float(res["final_distance"].mean()),
        "reopt_success_rate": cost_eval["reopt_success_rate"],
        "epic_distance": cost_eval["epic_distance"],
        "sample_success_rate": float(fit.sample_success.mean()),
        "sample_success_rate_white": float(fit.sample_success_white.mean()),
        "entropy_gap_nats": float(fit.entropy_gap.mean()),
        "entropy_nats": float(fit.entropy.mean()),
        "demo_entropy_nats": float(fit.demo_entropy.mean()),
        "demo_log_likelihood": float(fit.demo_log_likelihood.mean()),
        "demo_self_log_likelihood": float(fit.demo_self_log_likelihood.mean()),
        "log_temperature": float(np.mean(res["state"].cost.params.log_temperature)),
        "final_true_cost": float(m.gps.cost[:, -1, -1].mean()),
        "rollbacks": int(m.rolled_back.sum()),
        "c_step_failures": int(m.gps.c_step_failed.sum()),
        "c_step_iterations_mean": float(c_iters.mean()),
        "c_step_iterations_max": int(c_iters.max()),
        "per_seed": {
            "success": res["success"].tolist(),
            "final_distance": res["final_distance"].round(4).tolist(),
            "reopt_success": cost_eval["reopt_success"],
            "sample_success": fit.sample_success.mean(-1).round(3).tolist(),
            "entropy_gap_nats": fit.entropy_gap.mean(-1).round(1).tolist(),
        },
        "batch_seconds": res["batch_seconds"],
    }
    return {f"{k}{suffix}": v for k, v in out.items()}


def time_single_runs(rgcl, demos, keys, repeats: int = 2) -> dict:
    """The single-run program ``jit(train)``: one run (best of 2), the loop over every key on one
    device and the same loop as concurrent streams, one per device (runs dispatched alternately,
    then awaited together), each best of ``repeats``."""
    single = jax.jit(rgcl.train)
    devices = jax.devices()
    demos_on = [jax.device_put(demos, d) for d in devices]
    keys_on = [jax.device_put(keys, d) for d in devices]
    # Compiled for device 0's arrays, the program the runs below call there (an executable is
    # bound to its device: every other device compiles its own, in the warm-up).
    t0 = time.perf_counter()
    single.lower(keys_on[0][0], demos_on[0]).compile()
    compile_seconds = time.perf_counter() - t0
    for d in range(len(devices)):  # warm up (and load) the program on every device
        jax.block_until_ready(single(keys_on[d][0], demos_on[d]))
    one = []
    for _ in range(2):
        t0 = time.perf_counter()
        jax.block_until_ready(single(keys_on[0][0], demos_on[0]))
        one.append(time.perf_counter() - t0)
    loop = fair = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(keys.shape[0]):
            jax.block_until_ready(single(keys_on[0][i], demos_on[0]))
        loop = min(loop, time.perf_counter() - t0)
        t0 = time.perf_counter()
        n = len(devices)
        outs = [single(keys_on[i % n][i], demos_on[i % n]) for i in range(keys.shape[0])]
        jax.block_until_ready(outs)
        fair = min(fair, time.perf_counter() - t0)
    return {
        "single_compile_seconds": compile_seconds,
        "one_run": min(one),
        "loop": loop,
        "loop_streams": fair,
        "streams": len(devices),
    }


def compile_in_fresh_process(args, schedule: str, n_seeds: int) -> float:
    """Compile seconds of the batch program of ``schedule`` in a new process whose persistent
    compilation cache is a new empty folder (the demos come from the usual cache)."""
    with tempfile.TemporaryDirectory(prefix="diffgcl-jax-cache-") as cache:
        cmd = [sys.executable, __file__, "--compile-only", schedule, "--jax-cache", cache]
        cmd += ["--preset", args.preset, "--seeds", str(n_seeds)]
        cmd += sum((["--set", s] for s in args.set), [])
        if args.fast:
            cmd.append("--fast")
        if args.devices is not None:
            cmd += ["--devices", str(args.devices)]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=os.environ)
        return float(json.loads(out.stdout.strip().splitlines()[-1])["compile_seconds"])


def make_config(args, schedule: str):
    config = with_overrides(SCHEDULES[args.preset][schedule](), args.set)
    if args.fast:
        config = dataclasses.replace(config, iterations=min(config.iterations, 10))
    return config


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", choices=tuple(SCHEDULES), default="default")
    parser.add_argument("--schedule", choices=("v1", "v2"), default=None, help="only this one")
    parser.add_argument("--seeds", type=int, default=32, help="tuning seeds")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--heldout-seeds", type=int, default=32, help="0: none")
    parser.add_argument("--heldout-first", type=int, default=1000)
    parser.add_argument(
        "--fast", action="store_true", help="8 seeds per set, 10 iterations, no other tasks"
    )
    parser.add_argument("--no-tasks", action="store_true", help="skip the two other tasks")
    parser.add_argument("--no-timing", action="store_true", help="skip the single-run loops")
    parser.add_argument("--no-empty-cache-compile", action="store_true")
    parser.add_argument(
        "--set", action="append", default=[], metavar="FIELD=VALUE", help="config override"
    )
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=None, help="run folders with plots")
    parser.add_argument("--x64", action="store_true")
    parser.add_argument("--compile-only", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--jax-cache", default=None, help=argparse.SUPPRESS)
    add_devices_option(parser)
    args = parser.parse_args(argv)
    apply_devices_option(args)
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    from diffgcl.envs import make_env
    from diffgcl.runtime import prepare_process

    prepare_process(args.jax_cache)
    env = make_env("arm")
    demos = load_demo_batch(None, env)
    n = FAST_SEEDS if args.fast and args.seeds == 32 else args.seeds
    n_heldout = FAST_SEEDS if args.fast and args.heldout_seeds == 32 else args.heldout_seeds
    seeds = list(range(args.first_seed, args.first_seed + n))
    heldout = list(range(args.heldout_first, args.heldout_first + n_heldout))

    if args.compile_only is not None:
        program = compile_batch(make_config(args, args.compile_only), env, demos, min(CHUNK, n))
        print(json.dumps({"compile_seconds": program.compile_seconds}))
        return 0

    schedules = SCHEDULES[args.preset]
    if args.schedule is not None:
        if args.schedule not in schedules:
            raise SystemExit(f"--schedule {args.schedule}: preset {args.preset} has {schedules}")
        schedules = {args.schedule: schedules[args.schedule]}
    timed = "v2" if "v2" in schedules else "v1"
    summary: dict = {"preset": args.preset, "overrides": args.set, "fast": args.fast}
    summary.update(seeds=seeds, heldout_seeds=heldout, dtype=str(jnp.zeros(()).dtype))
    summary.update(device=str(jax.devices()[0]), devices=len(jax.devices()))
    summary["load_average_at_start"] = os.getloadavg()
    for schedule in schedules:
        config = make_config(args, schedule)
        summary[f"config_{schedule}"] = config.to_dict()
        repeats = 1 if args.no_timing or schedule != timed else TIMING_REPEATS
        programs: dict[int, BatchProgram] = {}  # by batch size: both splits share one program
        for split, split_seeds, suffix in (
            ("tuning", seeds, ""),
            ("held-out", heldout, "_heldout_seeds"),
        ):
            if not split_seeds:
                continue
            print(f"[{schedule}] {args.preset}, {split} seeds {split_seeds[0]}–{split_seeds[-1]}")
            size = min(CHUNK, len(split_seeds))
            compiled_here = size not in programs
            if compiled_here:
                programs[size] = compile_batch(config, env, demos, size)
            program = programs[size]
            res = run_schedule(
                program, env, demos, split_seeds, timing_repeats=repeats if not suffix else 1
            )
            figs = figures(res, config, env, split_seeds, suffix)
            summary.update({f"{k}_{schedule}": v for k, v in figs.items()})
            compile_seconds = program.compile_seconds if compiled_here else 0.0
            summary[f"compile_seconds_batch_{schedule}{suffix}"] = compile_seconds
            print(
                f"  success {figs['successes' + suffix]}/{len(split_seeds)}, re-optimisation "
                f"{figs['reopt_success_rate' + suffix]:.2f}, EPIC "
                f"{figs['epic_distance' + suffix]:.3f}, noisy samples "
                f"{figs['sample_success_rate' + suffix]:.2f}, entropy gap "
                f"{figs['entropy_gap_nats' + suffix]:.0f} nats, compile "
                f"{compile_seconds:.1f} s, batch {res['batch_seconds']:.1f} s"
            )
            if schedule == timed and not suffix:
                summary["compile_seconds"] = program.compile_seconds
                if not args.no_timing:
                    t = time_single_runs(res["rgcl"], demos, res["keys"], TIMING_REPEATS)
                    summary["seconds_per_run_after_compile"] = t["one_run"]
                    summary["compile_seconds_single"] = t["single_compile_seconds"]
                    summary["loop_seconds"] = t["loop"]
                    summary["loop_streams_seconds"] = t["loop_streams"]
                    summary["streams"] = t["streams"]
                    summary["sweep_speedup"] = t["loop"] / res["batch_seconds"]
                    summary["sweep_speedup_fair"] = t["loop_streams"] / res["batch_seconds"]
                    print(
                        f"  one run {t['one_run']:.2f} s; {n} runs looped {t['loop']:.1f} s, as "
                        f"{t['streams']} streams {t['loop_streams']:.1f} s, vmapped "
                        f"{res['batch_seconds']:.1f} s -> speed-up {summary['sweep_speedup']:.2f}x"
                        f", fair {summary['sweep_speedup_fair']:.2f}x"
                    )
            if args.out is not None:
                from diffgcl.algorithms.runner import RunResult, write_run_folder

                result = RunResult(
                    state=res["state"], metrics=res["metrics"], seeds=split_seeds, config=config
                )
                folder = args.out / f"{args.preset}_{schedule}{suffix}"
                write_run_folder(folder, result, env, demos)
    if not args.no_timing and not args.no_empty_cache_compile:
        print(f"compiling the {timed} batch program in a new process with an empty cache")
        summary["compile_seconds_empty_cache"] = compile_in_fresh_process(args, timed, n)
        print(
            f"  {summary['compile_seconds_empty_cache']:.1f} s (this process: "
            f"{summary['compile_seconds']:.1f} s)"
        )

    if not (args.fast or args.no_tasks) and heldout:
        summary["tasks"] = {}
        for name, options in OTHER_TASKS.items():
            task_env = make_env("arm", **options)
            task_demos = load_demo_batch(None, task_env)
            task = {"options": options}
            for schedule in schedules:
                config = make_config(args, schedule)
                print(f"[{schedule}] task {name} {options}, held-out seeds")
                program = compile_batch(config, task_env, task_demos, min(CHUNK, len(heldout)))
                res = run_schedule(program, task_env, task_demos, heldout)
                figs = figures(res, config, task_env, heldout, "")
                task.update({f"{k}_{schedule}": v for k, v in figs.items()})
                print(
                    f"  success {figs['successes']}/{len(heldout)}, re-optimisation "
                    f"{figs['reopt_success_rate']:.2f}, noisy samples "
                    f"{figs['sample_success_rate']:.2f}, entropy gap "
                    f"{figs['entropy_gap_nats']:.0f} nats"
                )
            summary["tasks"][name] = task
    summary["load_average_at_end"] = os.getloadavg()
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1, default=str))
        print(f"summary in {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
