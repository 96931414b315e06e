"""rGCL on the two-joint arm: the seed's chapter 4 experiment, v1 and v2, over seeds (issue 6).

For each schedule of the preset (``default``: v1 and v2 of ours; ``paper``: the seed's paper_v1
and paper_v2; ``paper_v1`` / ``paper_v2`` alone), all seeds run as one ``jit(vmap(train))`` batch
(chunks of 32) on the built-in 10 expert demos. Reported per schedule: success rate (DESIGN §2:
the final controller's noise-free rollout within 0.1 rad of upright on both joints over the last
10 steps), mean final distance (largest joint error at the last step), re-optimisation success
(a fresh initial controller optimised by GPS on the frozen learned cost, same success test), the
EPIC distance of the learned per-step cost to the expert cost on a coverage set of arm
transitions (:func:`diffgcl.eval.learned_cost.arm_coverage`), compile and run times.

Timing (v2, or the preset's only schedule): ``seconds_per_run_after_compile`` is one unbatched
run of ``jit(train)`` after compilation (best of 2); ``sweep_speedup`` is the time of the same
seeds run one by one through that compiled single-run function divided by the time of the
vmapped batch (also after compilation; both best of 2 when the seeds fit one batch). The batch
is sharded over the CPU's cores as one XLA device per core (``--devices 1``: one device); the
single runs take the same time with one device or two (measured), a single run cannot use the
second core. ``compile_seconds`` is the lowering + compilation of the vmapped batch program of
that schedule (the persistent compilation cache is on, so a second process reports much less;
``compile_seconds_*`` list every program).

    python experiments/arm_rgcl.py --preset default --seeds 32 --json out.json [--fast] [--out DIR]
        [--devices N]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.algorithms.presets import default, paper_v1, paper_v2
from diffgcl.algorithms.rgcl import final_rollouts, make_train
from diffgcl.algorithms.runner import load_demo_batch
from diffgcl.eval.learned_cost import evaluate_cost
from diffgcl.runtime import add_devices_option, apply_devices_option
from diffgcl.sim.sharding import shard_batch_if_even, vmap_over_devices

TIMING_REPEATS = 2  # the sweep speed-up compares best-of-2 times of the batch and the loop

SCHEDULES = {
    "default": {"v1": lambda: default("v1"), "v2": lambda: default("v2")},
    "paper": {"v1": paper_v1, "v2": paper_v2},
    "paper_v1": {"v1": paper_v1},
    "paper_v2": {"v2": paper_v2},
}


def run_schedule(config, env, demos, seeds, *, chunk: int = 32, timing_repeats: int = 1) -> dict:
    """All seeds of one schedule as vmapped batches; returns outcome, state and timings."""
    rgcl = make_train(config, env)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    size = min(chunk, len(seeds))
    batch = jax.jit(vmap_over_devices(rgcl.train, in_axes=(0, None)))
    t0 = time.perf_counter()
    compiled = batch.lower(shard_batch_if_even(keys[:size]), demos).compile()
    compile_seconds = time.perf_counter() - t0
    states, metrics = [], []
    t0 = time.perf_counter()
    for i in range(0, len(seeds), size):
        k = shard_batch_if_even(keys[i : i + size])
        fn = compiled if k.shape[0] == size else batch
        state, m = jax.block_until_ready(fn(k, demos))
        states.append(jax.tree.map(np.asarray, state))
        metrics.append(jax.tree.map(np.asarray, m))
    batch_seconds = time.perf_counter() - t0
    if timing_repeats > 1 and len(seeds) <= size:  # best of N, as the loop is timed
        k = shard_batch_if_even(keys)
        for _ in range(timing_repeats - 1):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(k, demos))
            batch_seconds = min(batch_seconds, time.perf_counter() - t0)
    state = jax.tree.map(lambda *a: np.concatenate(a), *states)
    m = jax.tree.map(lambda *a: np.concatenate(a), *metrics)
    X = np.asarray(
        jax.jit(jax.vmap(lambda c: final_rollouts(env, c)))(
            jax.tree.map(jnp.asarray, state.gps.controller)
        )
    )
    success = np.asarray(jax.vmap(jax.vmap(env.success))(jnp.asarray(X))).all(-1)
    dist = np.abs(X[:, :, -1, :2] - np.asarray(env.target)).max(axis=(1, 2))
    return {
        "rgcl": rgcl,
        "state": state,
        "metrics": m,
        "success": success,
        "final_distance": dist,
        "compile_seconds": compile_seconds,
        "batch_seconds": batch_seconds,
        "keys": keys,
    }


def time_single_runs(rgcl, demos, keys, repeats: int = 2) -> dict:
    """Compile ``jit(train)`` once; time one run (best of 2) and the loop over every key (best
    of ``repeats``)."""
    single = jax.jit(rgcl.train)
    t0 = time.perf_counter()
    compiled = single.lower(keys[0], demos).compile()
    compile_seconds = time.perf_counter() - t0
    jax.block_until_ready(compiled(keys[0], demos))  # warm-up
    one = []
    for _ in range(2):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(keys[0], demos))
        one.append(time.perf_counter() - t0)
    loop_seconds = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for k in keys:
            jax.block_until_ready(compiled(k, demos))
        loop_seconds = min(loop_seconds, time.perf_counter() - t0)
    return {"single_compile_seconds": compile_seconds, "one_run": min(one), "loop": loop_seconds}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", choices=tuple(SCHEDULES), default="default")
    parser.add_argument("--seeds", type=int, default=32)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--fast", action="store_true", help="4 seeds, 10 iterations")
    parser.add_argument("--no-timing", action="store_true", help="skip the single-run loop")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=None, help="run folders with plots")
    parser.add_argument("--x64", action="store_true")
    add_devices_option(parser)
    args = parser.parse_args(argv)
    apply_devices_option(args)
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    from diffgcl.envs import make_env
    from diffgcl.runtime import enable_compilation_cache

    enable_compilation_cache()
    env = make_env("arm")
    demos = load_demo_batch(None, env)
    n = 4 if args.fast and args.seeds == 32 else args.seeds
    seeds = list(range(args.first_seed, args.first_seed + n))
    schedules = SCHEDULES[args.preset]
    timed = "v2" if "v2" in schedules else "v1"
    summary: dict = {"preset": args.preset, "seeds": seeds, "fast": args.fast}
    summary["dtype"] = str(jnp.zeros(()).dtype)
    summary["device"] = str(jax.devices()[0])
    summary["devices"] = len(jax.devices())
    for schedule, make_config in schedules.items():
        config = make_config()
        if args.fast:
            import dataclasses

            config = dataclasses.replace(config, iterations=min(config.iterations, 10))
        print(f"[{schedule}] {args.preset}: {n} seeds, {config.iterations} iterations")
        repeats = 1 if args.no_timing or schedule != timed else TIMING_REPEATS
        res = run_schedule(config, env, demos, seeds, timing_repeats=repeats)
        cost_eval = evaluate_cost(config, env, res["state"].cost.params, seeds)
        c_iters = res["metrics"].gps.c_step_iterations
        s = {
            f"success_rate_{schedule}": float(res["success"].mean()),
            f"successes_{schedule}": int(res["success"].sum()),
            f"mean_final_distance_{schedule}": float(res["final_distance"].mean()),
            f"reopt_success_rate_{schedule}": cost_eval["reopt_success_rate"],
            f"epic_distance_{schedule}": cost_eval["epic_distance"],
            f"compile_seconds_batch_{schedule}": res["compile_seconds"],
            f"batch_seconds_{schedule}": res["batch_seconds"],
            f"final_true_cost_{schedule}": float(res["metrics"].gps.cost[:, -1, -1].mean()),
            f"rollbacks_{schedule}": int(res["metrics"].rolled_back.sum()),
            f"c_step_failures_{schedule}": int(res["metrics"].gps.c_step_failed.sum()),
            f"c_step_iterations_mean_{schedule}": float(c_iters.mean()),
            f"c_step_iterations_max_{schedule}": int(c_iters.max()),
            f"config_{schedule}": config.to_dict(),
        }
        summary.update(s)
        print(
            f"  success {s[f'successes_{schedule}']}/{n}, mean final distance "
            f"{s[f'mean_final_distance_{schedule}']:.3f} rad, re-optimisation "
            f"{cost_eval['reopt_success_rate']:.2f}, EPIC {cost_eval['epic_distance']:.3f}, "
            f"compile {res['compile_seconds']:.1f} s, batch {res['batch_seconds']:.1f} s"
        )
        if schedule == timed:
            summary["compile_seconds"] = res["compile_seconds"]
            if not args.no_timing:
                t = time_single_runs(res["rgcl"], demos, res["keys"], TIMING_REPEATS)
                summary["seconds_per_run_after_compile"] = t["one_run"]
                summary["compile_seconds_single"] = t["single_compile_seconds"]
                summary["loop_seconds"] = t["loop"]
                summary["sweep_speedup"] = t["loop"] / res["batch_seconds"]
                print(
                    f"  one {schedule} run {t['one_run']:.2f} s after compile; loop over {n} "
                    f"seeds {t['loop']:.1f} s vs vmapped {res['batch_seconds']:.1f} s "
                    f"-> speed-up {summary['sweep_speedup']:.2f}x"
                )
        if args.out is not None:
            from diffgcl.algorithms.runner import RunResult, write_run_folder

            result = RunResult(
                state=res["state"], metrics=res["metrics"], seeds=seeds, config=config
            )
            write_run_folder(args.out / f"{args.preset}_{schedule}", result, env, demos)
    for key in ("success_rate", "reopt_success_rate", "epic_distance"):
        if key == "success_rate":
            continue
        vals = [summary[f"{key}_{s}"] for s in schedules]
        summary[key] = float(np.mean(vals))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1, default=str))
        print(f"summary in {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
