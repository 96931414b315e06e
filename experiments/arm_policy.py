"""A global policy on the arm from 4 training starts, judged from starts it never saw.

GPS's point: the local controllers need the simulator's state and one start each; the global
policy acts on observations (joint angles and speeds, end-effector position) and should work from
any start in the range it was trained on. Training starts: GPS's BADMM/MDGPS arm example,
``q = [0.5π, 0], [0.75π, 0.5π], [π, −0.5π], [1.25π, 0]`` at rest. Held-out starts: drawn once
uniformly from ``q1 ∈ [0.5π, 1.25π]``, ``q2 ∈ [−0.5π, 0.5π]`` at rest, in two sets — 8 that were
looked at while the settings were chosen (``--split tune``) and 12 that were not (``--split
report``, the default and what the README reports). Seeds split the same way: 0.. for tuning,
1000.. for the report.

Methods, each over the same seeds, each policy judged by DESIGN §2's strict success test on its
noise-free rollout (and on rollouts with its own noise):

* ``mdgps`` — MDGPS with the expert cost (:mod:`diffgcl.algorithms.mdgps`);
* ``rgcl`` — rGCL v2 (``default`` preset) with MDGPS, learning the cost from the demos;
* ``bc`` — behaviour cloning of the same demos, same network and observations;
* ``expert`` — the reference: the GPS expert's local controllers trained *on* each held-out start
  with the expert cost (whether the start is feasible at all within T = 100).

Demos: 5 per training start (20) from a GPS expert on the expert cost (30 iterations; the
succeeding seed with the lowest final cost), cached under ``runtime.cache_root() / "demos"``.

    python experiments/arm_policy.py --seeds 16 --json runs/arm_policy.json [--fast] [--out DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

TRAIN_STARTS = ((0.5, 0.0), (0.75, 0.5), (1.0, -0.5), (1.25, 0.0))  # × π, GPS's arm example
HELDOUT_TUNE = (
    (0.99, -0.44), (0.74, 0.35), (0.86, 0.07), (0.50, -0.26),
    (0.83, -0.42), (0.85, -0.34), (0.88, -0.11), (1.01, 0.21),
)  # fmt: skip
HELDOUT_REPORT = (
    (1.10, 0.35), (1.18, 0.03), (1.18, 0.31), (0.95, 0.34),
    (1.05, -0.13), (0.79, 0.40), (1.01, 0.42), (1.05, -0.23),
    (0.77, -0.31), (1.03, 0.12), (0.58, -0.30), (0.81, 0.43),
)  # fmt: skip
SEED_BASE = {"tune": 0, "report": 1000}
DEMOS_PER_START = 5


def starts(table) -> np.ndarray:
    """[(q1/π, q2/π)] -> x0 [C, 4] at rest."""
    q = np.asarray(table, dtype=float) * math.pi
    return np.concatenate([q, np.zeros_like(q)], axis=1)


def policy_settings(fast: bool, s_steps: int = 300):
    from diffgcl.algorithms.mdgps import PolicySettings
    from diffgcl.policies.mdgps import SStepConfig
    from diffgcl.policies.network import PolicyConfig

    return PolicySettings(
        network=PolicyConfig(hidden=(64, 64), init_var=0.1),
        s_step=SStepConfig(n_steps=100 if fast else s_steps, batch_size=128, learning_rate=1e-3),
    )


def expert_demos(env, seeds=range(8), iterations: int = 30):
    """The demos (a DemoSet, 5 per training start), generated once and cached."""
    from diffgcl.algorithms.expert import make_demo_set, sample_expert
    from diffgcl.algorithms.gps import GPSConfig
    from diffgcl.algorithms.gps_runner import run_seeds
    from diffgcl.data.demos import DemoSet
    from diffgcl.runtime import cache_root

    folder = cache_root() / "demos" / f"arm-4starts-gps{iterations}-{DEMOS_PER_START}perstart"
    if (folder / "demos.npz").is_file():
        return DemoSet.load(folder)
    seeds = list(seeds)
    result = run_seeds(GPSConfig(iterations=iterations), env, env.expert_cost, seeds, chunk=8)
    final = np.all(result["final_success"], axis=-1)
    if not final.any():
        raise RuntimeError("no GPS expert seed succeeded on all four training starts")
    cost = np.asarray(result["metrics"].cost[:, -1]).sum(-1)
    i = int(np.argmin(np.where(final, cost, np.inf)))
    controllers = jax.tree.map(lambda a: jnp.asarray(a[i]), result["state"].controller)
    n = DEMOS_PER_START * env.initial_states().shape[0]
    traj, cond = jax.jit(lambda k: sample_expert(env, controllers, env.initial_states(), k, n))(
        jax.random.PRNGKey(10_000 + seeds[i])
    )
    demos = make_demo_set(env, traj, np.asarray(cond), cost=env.expert_cost, seed=seeds[i])
    demos.save(folder)
    return demos


def evaluate(env, policy, params, x0_sets: dict, key, noisy_samples: int) -> dict:
    """Success of a batch of policies (params with a leading seed axis) from each start set:
    ``{name: {"success": [S, B], "sample_success": [S, B]}}``."""
    from diffgcl.eval.policy import policy_rollouts, policy_success

    out = {}
    for name, x0 in x0_sets.items():
        x0 = jnp.asarray(x0)
        reps = jnp.repeat(x0, noisy_samples, axis=0)

        def one(p, k, x0=x0, reps=reps):
            mean = policy_success(env, policy_rollouts(env, policy, p, x0))
            noisy = policy_rollouts(env, policy, p, reps, k, noisy=True, smooth_sigma=2.0)
            return mean, policy_success(env, noisy).reshape(x0.shape[0], noisy_samples)

        S = jax.tree.leaves(params)[0].shape[0]
        mean, noisy = jax.jit(jax.vmap(one))(params, jax.random.split(key, S))
        out[name] = {"success": np.asarray(mean), "sample_success": np.asarray(noisy).mean(-1)}
    return out


def run_batch(train, keys, *args):
    """Compile ``jit(vmap(train))`` over ``keys`` (sharded over the devices), run it; returns
    (result as NumPy, compile seconds, run seconds)."""
    from diffgcl.sim.sharding import shard_batch_if_even, vmap_over_devices

    in_axes = (0,) + (None,) * len(args)
    batch = jax.jit(vmap_over_devices(train, in_axes=in_axes))
    keys = shard_batch_if_even(keys)
    t0 = time.perf_counter()
    compiled = batch.lower(keys, *args).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(keys, *args))
    return jax.tree.map(np.asarray, out), compile_s, time.perf_counter() - t0


def time_single(train, key, *args) -> float:
    """Seconds of one run of ``jit(train)`` after compilation (best of 2)."""
    compiled = jax.jit(train).lower(key, *args).compile()
    best = float("inf")
    for _ in range(2):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(key, *args))
        best = min(best, time.perf_counter() - t0)
    return best


def summarise(name: str, result: dict, summary: dict) -> None:
    for split in ("train", "heldout"):
        r = result[split]
        summary[f"{name}_success_{split}"] = float(r["success"].mean())
        summary[f"{name}_sample_success_{split}"] = float(r["sample_success"].mean())
        summary[f"{name}_success_{split}_per_start"] = r["success"].mean(0).tolist()
    print(
        f"  {name:6s} noise-free success: train {summary[f'{name}_success_train']:.3f}, "
        f"held-out {summary[f'{name}_success_heldout']:.3f} | with the policy's noise: train "
        f"{summary[f'{name}_sample_success_train']:.3f}, held-out "
        f"{summary[f'{name}_sample_success_heldout']:.3f}"
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--split", choices=tuple(SEED_BASE), default="report")
    parser.add_argument("--fast", action="store_true", help="2 seeds, fewer iterations")
    parser.add_argument("--methods", default="expert,mdgps,rgcl,bc")
    parser.add_argument("--noisy-samples", type=int, default=5, help="noisy rollouts per start")
    parser.add_argument("--mdgps-iterations", type=int, default=30)
    parser.add_argument("--kl-step", type=float, default=0.2)
    parser.add_argument("--s-steps", type=int, default=300, help="Adam steps per S-step")
    parser.add_argument("--no-timing", action="store_true")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=None, help="plots of the policies' rollouts")
    from diffgcl.runtime import add_devices_option, apply_devices_option

    add_devices_option(parser)
    args = parser.parse_args(argv)
    apply_devices_option(args)
    from diffgcl.algorithms.bc import BCConfig, demo_arrays, make_bc
    from diffgcl.algorithms.gps import GPSConfig
    from diffgcl.algorithms.mdgps import MDGPSConfig, make_mdgps
    from diffgcl.algorithms.presets import default
    from diffgcl.algorithms.rgcl import demo_batch, make_train
    from diffgcl.envs import make_env
    from diffgcl.runtime import prepare_process

    prepare_process()
    t_start = time.perf_counter()
    methods = args.methods.split(",")
    n_seeds = 2 if args.fast and args.seeds == 16 else args.seeds
    seeds = [SEED_BASE[args.split] + s for s in range(n_seeds)]
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    heldout = starts(HELDOUT_TUNE if args.split == "tune" else HELDOUT_REPORT)
    env = make_env("arm", x0=starts(TRAIN_STARTS))
    x0_sets = {"train": starts(TRAIN_STARTS), "heldout": heldout}
    settings = policy_settings(args.fast, args.s_steps)
    summary: dict = {
        "split": args.split,
        "seeds": seeds,
        "fast": args.fast,
        "train_starts_over_pi": TRAIN_STARTS,
        "heldout_starts_over_pi": HELDOUT_TUNE if args.split == "tune" else HELDOUT_REPORT,
        "policy_settings": dataclasses.asdict(settings),
        "devices": len(jax.devices()),
    }
    eval_key = jax.random.PRNGKey(77)
    policies = {}
    demos = expert_demos(env)
    summary["demos"] = demos.num_episodes
    summary["demo_success"] = float(np.mean([e["success"] for e in demos.episodes]))

    if "expert" in methods:
        from diffgcl.algorithms.gps_runner import run_seeds

        env_h = make_env("arm", x0=heldout)
        res = run_seeds(GPSConfig(iterations=30), env_h, env_h.expert_cost, seeds[:4], chunk=4)
        ok = np.asarray(res["final_success"])  # [seeds, B]
        summary["expert_success_heldout"] = float(ok.mean())
        summary["expert_heldout_feasible"] = ok.any(axis=0).tolist()
        print(f"  expert (GPS trained on each held-out start): success {ok.mean():.3f}")

    if "mdgps" in methods:
        iters = 8 if args.fast else args.mdgps_iterations
        config = MDGPSConfig(gps=GPSConfig(iterations=iters, kl_step=args.kl_step), policy=settings)
        md = make_mdgps(config, env, env.expert_cost)
        (state, m), c_s, r_s = run_batch(md.train, keys)
        policy = md.policy_phases.policy
        params = jax.tree.map(jnp.asarray, state.policy.params)
        result = evaluate(env, policy, params, x0_sets, eval_key, args.noisy_samples)
        summary["mdgps_iterations"] = iters
        summary["mdgps_compile_seconds"] = c_s
        summary["mdgps_batch_seconds"] = r_s
        summary["mdgps_policy_success_per_iteration"] = m.policy.success.mean((0, 2)).tolist()
        summary["mdgps_policy_entropy"] = float(m.policy.s_step.entropy[:, -1].mean())
        summarise("mdgps", result, summary)
        summary["policy_success_train"] = summary["mdgps_success_train"]
        summary["policy_success_heldout"] = summary["mdgps_success_heldout"]
        policies["mdgps"] = (policy, params)
        if not args.no_timing:
            summary["mdgps_seconds_per_run_after_compile"] = time_single(md.train, keys[0])

    batch = demo_batch(demos, len(TRAIN_STARTS), env=env)
    if "rgcl" in methods:
        config = dataclasses.replace(default("v2"), policy=settings)
        if args.fast:
            config = dataclasses.replace(config, iterations=10, freeze_last=2)
        rgcl = make_train(config, env)
        (state, m), c_s, r_s = run_batch(rgcl.train, keys, batch)
        policy = rgcl.policy_phases.policy
        params = jax.tree.map(jnp.asarray, state.policy.params)
        result = evaluate(env, policy, params, x0_sets, eval_key, args.noisy_samples)
        from diffgcl.algorithms.staged import noise_free_rollouts

        X, _ = noise_free_rollouts(env, state.gps.controller, jnp.asarray(state.gps.x0))
        ctrl_success = np.asarray(jax.vmap(jax.vmap(env.success))(jnp.asarray(X))).mean()
        summary["rgcl_compile_seconds"] = c_s
        summary["rgcl_batch_seconds"] = r_s
        summary["rgcl_controller_success_train"] = float(ctrl_success)
        summary["rgcl_policy_entropy"] = float(m.policy.s_step.entropy[:, -1, -1].mean())
        summarise("rgcl", result, summary)
        summary["rgcl_policy_success_train"] = summary["rgcl_success_train"]
        summary["rgcl_policy_success_heldout"] = summary["rgcl_success_heldout"]
        policies["rgcl"] = (policy, params)
        if not args.no_timing:
            t = time_single(rgcl.train, keys[0], batch)
            summary["rgcl_seconds_per_run_after_compile"] = t
            summary["seconds_per_run_after_compile"] = t

    if "bc" in methods:
        bc_config = BCConfig(network=settings.network)
        policy, fit = make_bc(bc_config, env.dO, env.dU, jnp.zeros(()).dtype)
        O, U, mask = demo_arrays(demos, env)
        (state, _), c_s, r_s = run_batch(lambda k: fit(k, O, U, mask), keys)
        params = jax.tree.map(jnp.asarray, state.params)
        result = evaluate(env, policy, params, x0_sets, eval_key, args.noisy_samples)
        summarise("bc", result, summary)
        policies["bc"] = (policy, params)

    if args.out is not None:
        from diffgcl.viz.plots import policy_paths

        for name, (policy, params) in policies.items():
            p0 = jax.tree.map(lambda a: a[0], params)
            policy_paths(env, policy, p0, x0_sets, args.out / f"arm_policy_{name}.png", title=name)
        print(f"plots in {args.out}")
    summary["wall_seconds"] = time.perf_counter() - t_start
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1, default=str))
        print(f"summary in {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
