"""Command line of rGCL on the arm: ``train``, ``sweep``, ``eval``, ``plot`` and the built-in demo.

    diffgcl train [--preset default] [--schedule v2] [--seeds 4] [--demos DIR] [--out DIR]
                  [--set gcl.n_steps=50 ...] [--resume] [--x64]
    diffgcl sweep --param cost_lr=1e-4,1e-3,1e-2 [--param kl_step=0.1,0.2] [--seeds 4] ...
    diffgcl eval RUN_DIR        success, final distance, re-optimisation, EPIC of a saved run
    diffgcl plot RUN_DIR        redraw a run folder's plots

The built-in demonstrations (:func:`builtin_demos`): 10 stochastic rollouts of a GPS expert
trained on the arm with the expert cost (:mod:`diffgcl.algorithms.expert`). They are generated on
first use (a GPS run over up to 8 seeds, ~1 min on 2 cores) and cached under
``diffgcl.runtime.cache_root() / "demos"``; later runs load them.

:func:`run_demo` is what ``diffgcl demo`` / ``make demo`` runs: the ``default`` preset, both
schedules, a handful of seeds, a success table and the run folders with their plots.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

BUILTIN_DEMOS = "arm-gps-expert-10-it30"
EXPERT_ITERATIONS = 30


def builtin_demos(env=None, *, num_demos: int = 10, seed: int = 0, verbose: bool = True):
    """The built-in arm demos (a :class:`diffgcl.data.demos.DemoSet`), generated once and cached.

    The expert is GPS on the expert cost (the seed's "10 demos from a GPS expert"), 8 seeds of
    ``EXPERT_ITERATIONS`` iterations; the succeeding seed with the lowest final true cost gives the
    demos (its controller sampled with its own noise). 30 rather than GPS's 10 iterations: at 10
    the expert is not converged (true cost 95.3–97.2 vs 94.5–95.1 at 30) and its demos still
    drift 0.04–0.07 rad about the target over the last 10 steps (0.01–0.04 at 30); every expert
    overshoots joint 1 by 0.12–0.23 rad around step 70 (the torque cap), and the learned cost
    sees that too."""
    from diffgcl.data.demos import DemoSet
    from diffgcl.runtime import cache_root

    folder = cache_root() / "demos" / f"{BUILTIN_DEMOS}-seed{seed}"
    if (folder / "demos.npz").is_file():
        return DemoSet.load(folder)
    from diffgcl.algorithms.expert import write_expert_demos
    from diffgcl.algorithms.gps import GPSConfig
    from diffgcl.algorithms.gps_cli import run_seeds
    from diffgcl.envs import make_env

    env = make_env("arm") if env is None else env
    if verbose:
        print(f"generating the built-in expert demos (GPS on the expert cost) into {folder}")
    seeds = list(range(seed, seed + 8))
    config = GPSConfig(iterations=EXPERT_ITERATIONS)
    result = run_seeds(config, env, env.expert_cost, seeds, chunk=8)
    final = np.all(result["metrics"].success[:, -1], axis=-1)
    if not final.any():
        raise RuntimeError("builtin_demos: no GPS expert seed succeeded")
    final_cost = np.asarray(result["metrics"].cost[:, -1]).sum(axis=-1)
    i = int(np.argmin(np.where(final, final_cost, np.inf)))
    controllers = jax.tree.map(lambda a: jnp.asarray(a[i]), result["state"].controller)
    return write_expert_demos(
        folder,
        env,
        controllers,
        jax.random.PRNGKey(10_000 + seeds[i]),
        num_demos,
        cost=env.expert_cost,
        seed=seeds[i],
    )


# ---- shared helpers -----------------------------------------------------------------------------


def _setup(args):
    if getattr(args, "x64", False):
        jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import enable_compilation_cache

    enable_compilation_cache()


def load_demos(path: Path | None, env):
    """The demos at ``path`` (a DemoSet folder) or the built-in ones, as a DemoBatch."""
    from diffgcl.algorithms.rgcl import demo_batch
    from diffgcl.data.demos import DemoSet

    demos = builtin_demos(env) if path is None else DemoSet.load(path)
    return demo_batch(demos, int(np.asarray(env.initial_states()).shape[0]))


def config_from_args(args):
    from diffgcl.algorithms.presets import get_preset, with_overrides

    config = get_preset(args.preset, getattr(args, "schedule", None))
    overrides = list(getattr(args, "set", None) or [])
    if getattr(args, "iterations", None):
        overrides.append(f"iterations={args.iterations}")
    return with_overrides(config, overrides)


def config_from_dict(d: dict):
    """Inverse of ``RGCLConfig.to_dict`` (for run folders)."""
    from diffgcl.algorithms.gps import GPSConfig
    from diffgcl.algorithms.rgcl import RGCLConfig
    from diffgcl.costs.gcl import GCLConfig
    from diffgcl.costs.network import CostNetworkConfig

    d = dict(d)
    net = dict(d.pop("network"))
    net["hidden"] = tuple(net["hidden"])
    return RGCLConfig(
        gps=GPSConfig(**d.pop("gps")),
        network=CostNetworkConfig(**net),
        gcl=GCLConfig(**d.pop("gcl")),
        **d,
    )


def _add_common(p: argparse.ArgumentParser, seeds: int = 4) -> None:
    p.add_argument("--preset", default="default", help="default, paper_v1 or paper_v2")
    p.add_argument("--schedule", choices=("v1", "v2"), default=None, help="default preset: v1/v2")
    p.add_argument("--seeds", type=int, default=seeds)
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--iterations", type=int, default=None, help="override rGCL iterations")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="config override, e.g. gcl.n_steps=50 or gps.maxent=True (repeatable)",
    )
    p.add_argument("--demos", type=Path, default=None, help="demo folder (default: built-in)")
    p.add_argument("--x64", action="store_true", help="float64 (default float32)")


def _print_table(rows: list[tuple[str, dict]]) -> None:
    print(f"{'run':<24s} {'success':>9s} {'mean final dist':>16s} {'first success':>14s}")
    for name, s in rows:
        first = [f for f in s["first_success_iteration"] if f is not None]
        mean_first = f"{np.mean(first):.1f}" if first else "-"
        n = len(s["success"])
        print(
            f"{name:<24s} {sum(s['success']):>4d}/{n:<4d} {s['mean_final_distance']:>16.3f} "
            f"{mean_first:>14s}"
        )


# ---- train --------------------------------------------------------------------------------------


def train_command(args) -> int:
    """Train one configuration over seeds through the host runner; write the run folder."""
    from diffgcl.algorithms.runner import train_seeds, write_run_folder
    from diffgcl.envs import make_env

    _setup(args)
    env = make_env("arm")
    config = config_from_args(args)
    demos = load_demos(args.demos, env)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    out = (
        args.out
        or Path("runs") / f"rgcl-{args.preset}-{config.schedule}-{time.strftime('%Y%m%d-%H%M%S')}"
    )
    print(f"rGCL {config.schedule} ({args.preset}) on the arm, seeds {seeds}, run folder {out}")
    result = train_seeds(
        config,
        env,
        demos,
        seeds,
        out=out,
        chunk=args.chunk,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume,
        progress=not args.no_progress,
    )
    summary = write_run_folder(out, result, env, demos)
    _print_table([(f"{args.preset} {config.schedule}", summary)])
    print(f"compile {result.compile_seconds:.1f} s, run {result.run_seconds:.1f} s; plots in {out}")
    return 0 if summary["success_rate"] > 0 else 1


# ---- sweep --------------------------------------------------------------------------------------

SWEEPABLE = ("kl_step", "init_var", "cost_lr")


def sweep_command(args) -> int:
    """A grid over traced hyperparameters × seeds as one jit(vmap(train)) (chunked)."""
    import itertools

    from diffgcl.algorithms.rgcl import RGCLHyperparams, final_rollouts, make_train
    from diffgcl.envs import make_env
    from diffgcl.sim.sharding import shard_batch_if_even, vmap_over_devices

    _setup(args)
    env = make_env("arm")
    config = config_from_args(args)
    demos = load_demos(args.demos, env)
    rgcl = make_train(config, env)
    base = rgcl.default_hparams()
    grid = {name: [float(getattr(base, name))] for name in SWEEPABLE}
    for item in args.param:
        name, values = item.split("=", 1)
        if name not in SWEEPABLE:
            raise SystemExit(f"sweep: {name} is not sweepable; choose from {SWEEPABLE}")
        grid[name] = [float(v) for v in values.split(",")]
    points = list(itertools.product(*(grid[n] for n in SWEEPABLE)))
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    runs = [(p, s) for p in points for s in seeds]
    dtype = jnp.asarray(env.initial_states()).dtype
    keys = jnp.stack([jax.random.PRNGKey(s) for _, s in runs])
    hp = RGCLHyperparams(*(jnp.asarray([p[i] for p, _ in runs], dtype) for i in range(3)))
    train = jax.jit(vmap_over_devices(rgcl.train, in_axes=(0, None, 0)))
    rollout = jax.jit(jax.vmap(lambda c: final_rollouts(env, c)))
    success = []
    t0 = time.perf_counter()
    for i in range(0, len(runs), args.chunk):
        sl = slice(i, i + args.chunk)
        batch = shard_batch_if_even((keys[sl], jax.tree.map(lambda a, sl=sl: a[sl], hp)))
        state, _ = train(batch[0], demos, batch[1])
        X = rollout(state.gps.controller)
        success.append(np.asarray(jax.vmap(jax.vmap(env.success))(X)).all(-1))
    success = np.concatenate(success)
    print(f"{len(runs)} runs in {time.perf_counter() - t0:.1f} s (incl. compile)")
    table = []
    for j, p in enumerate(points):
        rate = float(success[j * len(seeds) : (j + 1) * len(seeds)].mean())
        table.append({**dict(zip(SWEEPABLE, p, strict=True)), "success_rate": rate})
        print(
            "  " + ", ".join(f"{n}={v:g}" for n, v in zip(SWEEPABLE, p, strict=True)),
            f"-> {rate:.2f}",
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps(
                {"config": config.to_dict(), "seeds": seeds, "grid": table}, indent=1, default=str
            )
        )
    return 0


# ---- eval / plot --------------------------------------------------------------------------------


def load_run(run_dir: Path, env):
    """(config, RunResult, DemoBatch) of a run folder written by ``train``."""
    from diffgcl.algorithms.rgcl import make_train
    from diffgcl.algorithms.runner import CHECKPOINT, RunResult, _load_checkpoint, checkpoint_like

    run_dir = Path(run_dir)
    config = config_from_dict(json.loads((run_dir / "config.json").read_text()))
    with np.load(run_dir / CHECKPOINT) as f:
        seeds = [int(s) for s in f["seeds"]]
    summary = (
        json.loads((run_dir / "summary.json").read_text())
        if (run_dir / "summary.json").is_file()
        else {}
    )
    demo_dir = summary.get("demos")
    demos = load_demos(Path(demo_dir) if demo_dir else None, env)
    rgcl = make_train(config, env)
    S = len(seeds)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    key_init, key_loop = jax.vmap(rgcl.split_key)(keys)
    hp = jax.tree.map(lambda a: jnp.broadcast_to(a, (S,)), rgcl.default_hparams())
    state_like, m_like = checkpoint_like(rgcl, key_init, key_loop, demos, hp)
    state, metrics, done, _ = _load_checkpoint(run_dir / CHECKPOINT, state_like, m_like)
    return config, RunResult(state=state, metrics=metrics, seeds=seeds, config=config), demos


def eval_command(args) -> int:
    """Success, final distance, re-optimisation and EPIC of a saved run."""
    from diffgcl.algorithms.runner import run_summary
    from diffgcl.envs import make_env

    _setup(args)
    env = make_env("arm")
    config, result, demos = load_run(args.run, env)
    summary = run_summary(result, env)
    summary.pop("final_rollouts")
    summary.update(evaluate_cost(config, env, result.state.cost.params, result.seeds))
    print(json.dumps({k: v for k, v in summary.items() if k not in ("rollbacks",)}, indent=1))
    (Path(args.run) / "eval.json").write_text(json.dumps(summary, indent=1))
    return 0


def evaluate_cost(config, env, params, seeds) -> dict:
    """Re-optimisation success and EPIC distance of learned costs ``params`` [S, ...]."""
    from diffgcl.algorithms.rgcl import arm_coverage, epic_to_expert, make_network, make_reoptimise

    network = make_network(config, env)
    params = jax.tree.map(jnp.asarray, params)
    reopt = make_reoptimise(config, env, network)
    keys = jnp.stack([jax.random.PRNGKey(100_000 + s) for s in seeds])
    _, m = jax.jit(jax.vmap(reopt))(keys, params)
    reopt_success = np.asarray(m.success[:, -1]).all(-1)
    coverage = arm_coverage(env, jax.random.PRNGKey(7))
    epic = jax.jit(jax.vmap(lambda p: epic_to_expert(env, network, p, coverage)))(params)
    return {
        "reopt_success": reopt_success.tolist(),
        "reopt_success_rate": float(reopt_success.mean()),
        "epic_distance": float(np.mean(epic)),
        "epic_distance_per_seed": np.asarray(epic).tolist(),
    }


def plot_command(args) -> int:
    """Redraw the plots of a run folder from its checkpoint."""
    from diffgcl.algorithms.runner import write_run_folder
    from diffgcl.envs import make_env

    _setup(args)
    env = make_env("arm")
    _, result, demos = load_run(args.run, env)
    write_run_folder(args.run, result, env, demos)
    print(f"plots in {args.run}")
    return 0


# ---- the built-in demo --------------------------------------------------------------------------


def run_demo(args=None) -> int:
    """``diffgcl demo``: the ``default`` preset, v1 and v2, on the arm with the built-in 10 expert
    demos over a handful of seeds (``args.seeds``, default 4); prints the success table and the
    run folders (``args.out``, default ``runs/demo``)."""
    from diffgcl.algorithms.presets import default
    from diffgcl.algorithms.runner import train_seeds, write_run_folder
    from diffgcl.envs import make_env

    _setup(args)
    env = make_env("arm")
    demos = load_demos(None, env)
    n = int(getattr(args, "seeds", None) or 4)
    first = int(getattr(args, "seed", 0) or 0)
    seeds = list(range(first, first + n))
    root = Path(getattr(args, "out", None) or "runs/demo")
    rows = []
    for schedule in ("v1", "v2"):
        config = default(schedule)
        print(f"rGCL {schedule} (default preset), seeds {seeds}")
        result = train_seeds(config, env, demos, seeds, out=root / schedule, chunk=5)
        summary = write_run_folder(root / schedule, result, env, demos)
        rows.append((f"default {schedule}", summary))
        print(f"  compile {result.compile_seconds:.1f} s, run {result.run_seconds:.1f} s")
    print()
    _print_table(rows)
    print("\nseed's own result (chapter 4): v1 4/13, v2 10/19")
    for schedule in ("v1", "v2"):
        names = "{learning_curves,arm_motion,cost_landscape}.png"
        print(f"plots ({schedule}): {root / schedule}/{names}")
    return 0


def register(subparsers) -> None:
    """Add ``train``, ``sweep``, ``eval`` and ``plot`` to an argparse ``subparsers`` object."""
    train = subparsers.add_parser("train", help="rGCL on the arm over seeds (run folder)")
    _add_common(train)
    train.add_argument("--out", type=Path, default=None, help="run folder")
    train.add_argument("--chunk", type=int, default=5, help="iterations per jitted call")
    train.add_argument("--checkpoint-every", type=int, default=5)
    train.add_argument("--resume", action="store_true", help="continue from out/checkpoint.npz")
    train.add_argument("--no-progress", action="store_true")
    train.set_defaults(func=train_command)

    sweep = subparsers.add_parser("sweep", help="rGCL over a grid of traced hyperparameters")
    _add_common(sweep)
    sweep.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=V1,V2,...",
        help=f"one of {', '.join(SWEEPABLE)} (repeatable; grid product)",
    )
    sweep.add_argument("--chunk", type=int, default=32, help="runs per vmapped batch")
    sweep.add_argument("--json", type=Path, default=None)
    sweep.set_defaults(func=sweep_command)

    ev = subparsers.add_parser("eval", help="evaluate a run folder (re-optimisation, EPIC)")
    ev.add_argument("run", type=Path)
    ev.add_argument("--x64", action="store_true")
    ev.set_defaults(func=eval_command)

    plot = subparsers.add_parser("plot", help="redraw a run folder's plots")
    plot.add_argument("run", type=Path)
    plot.add_argument("--x64", action="store_true")
    plot.set_defaults(func=plot_command)
