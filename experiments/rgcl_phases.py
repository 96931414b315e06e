"""Where an rGCL iteration spends its time, and how well each phase batches over seeds (what
the sweep speed-up is made of).

For the ``default`` v2 preset on the arm, each phase is timed as one jitted single-seed call and
as one jitted ``vmap`` over N seeds sharded over the CPU's cores as one XLA device per core
(``--devices 1``: one device) (best of 5, after compilation); the reference is the single
call looped N times, as in ``experiments/arm_rgcl.py``'s sweep speed-up. GPS phases
(:func:`diffgcl.algorithms.gps.make_gps_phases`, on the expert cost): ``outer`` (sampling and
autodiff linearisation), ``expand`` (cost expansion), ``adapt_step`` (Laplace estimates),
``inner`` (the η search: LQR backward/forward passes). Whole rGCL iterations
(``RGCL.run``) with the cost update switched off (``gcl.n_steps=0``) and on give the cost
update's share by difference.

    python experiments/rgcl_phases.py [--seeds 32] [--json PATH] [--devices N]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax

from diffgcl.runtime import add_devices_option, apply_devices_option


def best_time(fn, *args, repeats: int = 5) -> float:
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return min(times)


def compare(name: str, single, single_args, batched, batched_args, n: int, rows: list) -> None:
    t1 = best_time(single, *single_args)
    tb = best_time(batched, *batched_args)
    row = {"phase": name, "single_ms": 1e3 * t1, "loop_ms": 1e3 * n * t1, "vmapped_ms": 1e3 * tb}
    row["speedup"] = n * t1 / tb
    rows.append(row)
    print(
        f"{name:34s} single {row['single_ms']:7.2f} ms | loop of {n} {row['loop_ms']:8.1f} ms | "
        f"vmapped {row['vmapped_ms']:8.1f} ms | speed-up {row['speedup']:5.2f}x",
        flush=True,
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=32)
    parser.add_argument("--json", type=Path, default=None)
    add_devices_option(parser)
    args = parser.parse_args(argv)
    apply_devices_option(args)

    from diffgcl.algorithms.gps import make_gps_phases
    from diffgcl.algorithms.presets import default, with_overrides
    from diffgcl.algorithms.rgcl import make_train
    from diffgcl.algorithms.runner import load_demo_batch
    from diffgcl.envs import make_env
    from diffgcl.runtime import prepare_process
    from diffgcl.sim.sharding import shard_batch_if_even, vmap_over_devices

    prepare_process()
    env = make_env("arm")
    n = args.seeds
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    keys_b = shard_batch_if_even(keys)  # the batched calls' seeds, split over the devices
    rows: list = []

    # GPS phases on the expert cost (full-Hessian expansion; the learned cost uses Gauss–Newton).
    config = default("v2")
    phases = make_gps_phases(
        dataclasses.replace(config.gps, gauss_newton=False), env, true_cost=env.expert_cost
    )
    vm = lambda f: jax.jit(vmap_over_devices(f))
    state1, states = jax.jit(phases.init)(keys[0]), vm(phases.init)(keys_b)
    outer1, outerb = jax.jit(phases.outer), vm(phases.outer)
    s1, sb = outer1(state1, keys[0]), outerb(states, keys_b)
    expand = lambda s: phases.expand(env.expert_cost, s)
    q1, qb = jax.jit(expand)(s1), vm(expand)(sb)
    m1 = jax.jit(phases.adapt_step)(state1, s1, q1)
    mb = vm(phases.adapt_step)(states, sb, qb)
    outer_args = ((state1, keys[0]), (states, keys_b))
    compare("GPS outer (sample + linearise)", outer1, outer_args[0], outerb, outer_args[1], n, rows)
    compare("GPS expand (expert cost)", jax.jit(expand), (s1,), vm(expand), (sb,), n, rows)
    compare(
        "GPS adapt_step (Laplace estimates)",
        jax.jit(phases.adapt_step),
        (state1, s1, q1),
        vm(phases.adapt_step),
        (states, sb, qb),
        n,
        rows,
    )
    compare(
        "GPS inner (eta search, LQR)",
        jax.jit(phases.inner),
        (state1, s1, q1, m1),
        vm(phases.inner),
        (states, sb, qb, mb),
        n,
        rows,
    )

    # Whole rGCL v2 iterations, without and with the cost update.
    demos = load_demo_batch(None, env)
    variants = (("rGCL iteration, no cost update", ["gcl.n_steps=0"]), ("rGCL iteration", []))
    for label, overrides in variants:
        rgcl = make_train(with_overrides(config, overrides), env)
        run = lambda s, k, rgcl=rgcl: rgcl.run(s, k, demos, 1)
        init1 = jax.jit(rgcl.init)(keys[0], demos)
        initb = jax.jit(vmap_over_devices(rgcl.init, in_axes=(0, None)))(keys_b, demos)
        # A few iterations first, so that the sample buffer holds several controllers.
        warm = lambda s, k, rgcl=rgcl: rgcl.run(s, k, demos, 5)[0]
        init1 = jax.jit(warm)(init1, keys[0])
        initb = jax.jit(vmap_over_devices(warm))(initb, keys_b)
        compare(label, jax.jit(run), (init1, keys[1]), vm(run), (initb, keys_b), n, rows)
    update = {k: rows[-1][k] - rows[-2][k] for k in ("single_ms", "loop_ms", "vmapped_ms")}
    update["speedup"] = update["loop_ms"] / update["vmapped_ms"]
    print(
        f"{'cost update (difference)':34s} single {update['single_ms']:7.2f} ms | loop "
        f"{update['loop_ms']:8.1f} ms | vmapped {update['vmapped_ms']:8.1f} ms | speed-up "
        f"{update['speedup']:5.2f}x"
    )
    rows.append({"phase": "cost update (difference)", **update})
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        summary = {
            "seeds": n,
            "device": str(jax.devices()[0]),
            "devices": len(jax.devices()),
            "phases": rows,
        }
        args.json.write_text(json.dumps(summary, indent=1))
        print(f"summary in {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
