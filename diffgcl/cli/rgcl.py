"""Command line of rGCL on the arm: ``train``, ``sweep``, ``eval``, ``plot`` and the built-in demo.

    diffgcl train [--preset default] [--schedule v2] [--seeds 4] [--demos DIR] [--out DIR]
                  [--env arm] [--env-set x0=...,target=...] [--set gcl.n_steps=50 ...]
                  [--resume] [--x64]
    diffgcl train --mjcf MODEL.xml --demos DEMOS.npz [--dt 0.02] [--obs state,site:tip]
                  [--policy mdgps]        your own model (diffgcl.api, docs/your_robot.md)
    diffgcl sweep --param cost_lr=1e-4,1e-3,1e-2 [--param kl_step=0.1,0.2] [--seeds 4] ...
    diffgcl sweep|train ... --local-processes 2 [--devices 1]      N processes on this host
    diffgcl sweep|train ... --coordinator HOST:PORT --num-processes N --process-id I
    diffgcl eval RUN_DIR [--env-set ...]   success, final distance, re-optimisation, EPIC
    diffgcl plot RUN_DIR        redraw a run folder's plots

``--env-set`` poses another task (:mod:`diffgcl.envs.options`), e.g. ``--env-set
x0=0.5pi,0.25pi,0,0,target=0.3,-0.4``; without ``--demos`` the expert demos for that task are
generated on first use and cached (:func:`diffgcl.algorithms.expert.builtin_demos`). ``train``
records the env and its options in the run folder (``env.json``), which ``eval`` and ``plot``
read back; ``eval --env-set`` changes them (e.g. re-optimise the learned cost from another start).

Argument parsing and printing only: the host loop, run folders and demo loading live in
:mod:`diffgcl.algorithms.runner`, the sweep in :mod:`diffgcl.algorithms.sweep`, the multi-process
runtime (options, launcher, gathering) in :mod:`diffgcl.distributed`, the built-in demonstrations in
:func:`diffgcl.algorithms.expert.builtin_demos`, the cost evaluation in
:mod:`diffgcl.eval.learned_cost`.

:func:`run_demo` is what ``diffgcl demo`` / ``make demo`` runs: the ``default`` preset, both
schedules, a handful of seeds, a success table and the run folders with their plots.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

from diffgcl.algorithms.runner import load_demo_batch, load_run, read_run_env, write_run_env
from diffgcl.envs.options import add_env_options, env_from_args
from diffgcl.eval.learned_cost import evaluate_cost

RGCL_ENVS = ("arm",)  # envs with rGCL presets and evaluation so far

# ---- shared helpers -----------------------------------------------------------------------------


def _setup(args):
    if getattr(args, "x64", False):
        jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import prepare_process

    prepare_process()


def _policy_settings(args):
    """The global policy's settings of ``--policy mdgps [--on-policy]``, else None."""
    if getattr(args, "policy", "none") != "mdgps":
        return None
    from diffgcl.algorithms.mdgps import PolicySettings

    return PolicySettings(sample_on_policy=bool(getattr(args, "on_policy", False)))


def config_from_args(args):
    from diffgcl.algorithms.presets import get_preset, with_overrides

    args.preset = args.preset or "default"
    config = get_preset(args.preset, getattr(args, "schedule", None))
    if (settings := _policy_settings(args)) is not None:
        import dataclasses

        config = dataclasses.replace(config, policy=settings)
    overrides = list(getattr(args, "set", None) or [])
    if getattr(args, "iterations", None):
        overrides.append(f"iterations={args.iterations}")
    return with_overrides(config, overrides)


def _launch_or_join(args) -> int | None:
    """``--local-processes``: the launched processes' exit status; else None after joining the
    multi-process run the options or the environment describe (if any)."""
    from diffgcl.distributed import launch_or_join

    def prepare():  # the built-in demos are generated (and cached) by one process, here
        _setup(args)
        load_demo_batch(args.demos, env_from_args(args)[0])

    program = [sys.executable, "-m", "diffgcl.cli"]
    return launch_or_join(args, program, getattr(args, "argv", sys.argv[1:]), prepare)


def _add_common(p: argparse.ArgumentParser, seeds: int = 4) -> None:
    p.add_argument(
        "--preset",
        default=None,
        help="default (the arm's), mjcf (--mjcf's default), paper_v1 or paper_v2",
    )
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
    p.add_argument(
        "--demos", type=Path, default=None, help="demo folder (default: built-in); --mjcf: npz"
    )
    p.add_argument("--x64", action="store_true", help="float64 (default float32)")
    add_env_options(p, RGCL_ENVS)


def _print_table(rows: list[tuple[str, dict]]) -> None:
    print(
        f"{'run':<24s} {'success':>9s} {'mean final dist':>16s} {'first success':>14s} "
        f"{'noisy samples':>14s} {'entropy gap':>12s}"
    )
    for name, s in rows:
        first = [f for f in s["first_success_iteration"] if f is not None]
        mean_first = f"{np.mean(first):.1f}" if first else "-"
        n = len(s["success"])
        noisy = f"{s['sample_success_rate']:.2f}" if "sample_success_rate" in s else "-"
        gap = f"{s['entropy_gap_nats_mean']:.0f} nats" if "entropy_gap_nats_mean" in s else "-"
        print(
            f"{name:<24s} {sum(s['success']):>4d}/{n:<4d} {s['mean_final_distance']:>16.3f} "
            f"{mean_first:>14s} {noisy:>14s} {gap:>12s}"
        )


# ---- train --------------------------------------------------------------------------------------


def train_mjcf_command(args) -> int:
    """``train --mjcf PATH --demos PATH``: your own model through :mod:`diffgcl.api`."""
    from diffgcl import api

    if args.demos is None:
        raise SystemExit("train --mjcf: give the demonstrations with --demos PATH")
    obs = tuple(args.obs.split(",")) if args.obs else "state"
    env = api.load_model(args.mjcf, dt=args.dt, obs=obs)
    demos = api.load_demos(args.demos, env)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    args.preset = args.preset or "mjcf"
    out = args.out or Path("runs") / f"{env.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    print(f"rGCL ({args.preset}) on {env.mjcf_path}: {demos.num_episodes} demos, seeds {seeds}")
    run = api.learn(
        env,
        demos,
        preset=args.preset,
        schedule=args.schedule,
        seeds=seeds,
        iterations=args.iterations,
        overrides=args.set,
        policy=_policy_settings(args) or False,
        progress=not args.no_progress,
    )
    report = run.report()
    run.save(out)
    reopt = report["reoptimisation"]
    print(
        f"conditions {report['conditions']}, horizon {report['horizon']}; distance to the demos "
        f"{report['mean_demo_distance']:.3f} (re-optimised {reopt['mean_demo_distance']:.3f}, "
        f"demos among themselves {np.mean(report['demo_spread']):.3f}) demo standard deviations"
    )
    if "policy" in report:
        print(f"global policy: distance to the demos {report['policy']['mean_demo_distance']:.3f}")
    print(f"compile {report['compile_seconds']:.1f} s, run {report['run_seconds']:.1f} s; "
          f"report and plots in {out}")  # fmt: skip
    return 0


def train_command(args) -> int:
    """Train one configuration over seeds through the host runner; write the run folder."""
    from diffgcl.algorithms.runner import train_seeds, write_run_folder
    from diffgcl.distributed import ProcessLost, abandon, barrier, is_leader

    if (status := _launch_or_join(args)) is not None:
        return status
    _setup(args)
    if args.mjcf is not None:
        return train_mjcf_command(args)
    env, env_options = env_from_args(args)
    config = config_from_args(args)
    demos = load_demo_batch(args.demos, env)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    out = (
        args.out
        or Path("runs") / f"rgcl-{args.preset}-{config.schedule}-{time.strftime('%Y%m%d-%H%M%S')}"
    )
    leader = is_leader()
    if leader:
        print(f"rGCL {config.schedule} ({args.preset}) on the {env.name}, seeds {seeds}, {out}")
        write_run_env(out, env, env_options, args.demos)
    try:
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
    except ValueError as err:  # seeds that do not divide over the processes, another checkpoint
        raise SystemExit(f"diffgcl train: {err}") from None
    except ProcessLost as err:
        abandon(f"diffgcl train: {err}")
    if not leader:  # process 0 writes the run folder; the others wait for it
        barrier("run folder written")
        return 0
    summary = write_run_folder(out, result, env, demos)
    _print_table([(f"{args.preset} {config.schedule}", summary)])
    print(f"compile {result.compile_seconds:.1f} s, run {result.run_seconds:.1f} s; plots in {out}")
    barrier("run folder written")
    return 0 if summary["success_rate"] > 0 else 1


# ---- sweep --------------------------------------------------------------------------------------


def sweep_command(args) -> int:
    """A grid over traced hyperparameters × seeds (:func:`diffgcl.algorithms.sweep.run_sweep`)."""
    from diffgcl.algorithms.sweep import SWEEPABLE, parse_grid, run_sweep
    from diffgcl.distributed import ProcessLost, abandon, barrier, is_leader

    try:
        grid = parse_grid(args.param)
    except ValueError as err:
        raise SystemExit(f"diffgcl sweep: {err}") from None
    if (status := _launch_or_join(args)) is not None:
        return status
    _setup(args)
    env, _ = env_from_args(args)
    config = config_from_args(args)
    demos = load_demo_batch(args.demos, env)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    t0 = time.perf_counter()
    try:
        result = run_sweep(config, env, demos, seeds, grid, chunk=args.chunk)
    except ValueError as err:  # processes started with different settings
        raise SystemExit(f"diffgcl sweep: {err}") from None
    except ProcessLost as err:
        abandon(f"diffgcl sweep: {err}")
    if is_leader():
        runs = len(result.points) * len(seeds)
        print(
            f"{runs} runs in {time.perf_counter() - t0:.1f} s (compile "
            f"{result.compile_seconds:.1f} s, run {result.run_seconds:.1f} s) on "
            f"{result.devices} devices of {result.processes} process(es)"
        )
        for row in result.table():
            values = ", ".join(f"{n}={row[n]:g}" for n in SWEEPABLE)
            print(f"  {values} -> {row['success_rate']:.2f}")
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            summary = {"config": config.to_dict(), **result.to_dict()}
            args.json.write_text(json.dumps(summary, indent=1, default=str))
    barrier("sweep written")
    return 0


# ---- eval / plot --------------------------------------------------------------------------------


def eval_command(args) -> int:
    """Success, final distance, re-optimisation and EPIC of a saved run (on the task it was
    trained on, or with ``--env-set`` another)."""
    from diffgcl.algorithms.runner import run_summary

    _setup(args)
    env, options = env_from_args(args, read_run_env(args.run))
    config, result, demos = load_run(args.run, env)
    summary = run_summary(result, env, demos)
    summary.pop("final_rollouts")
    summary.update(evaluate_cost(config, env, result.state.cost.params, result.seeds))
    summary["env"] = {"name": env.name, "options": options}
    print(json.dumps({k: v for k, v in summary.items() if k not in ("rollbacks",)}, indent=1))
    (Path(args.run) / "eval.json").write_text(json.dumps(summary, indent=1))
    return 0


def plot_command(args) -> int:
    """Redraw the plots of a run folder from its checkpoint."""
    from diffgcl.algorithms.runner import write_run_folder

    _setup(args)
    env, _ = env_from_args(args, read_run_env(args.run))
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
    demos = load_demo_batch(None, env)
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
    from diffgcl.algorithms.sweep import SWEEPABLE
    from diffgcl.distributed import add_process_options
    from diffgcl.runtime import add_devices_option

    train = subparsers.add_parser(
        "train", help="rGCL over seeds (run folder): the arm, or your model with --mjcf"
    )
    _add_common(train)
    train.add_argument("--mjcf", type=Path, default=None,
                       help="your MJCF model; --demos is then an npz of qpos/qvel/ctrl "
                       "(docs/your_robot.md)")  # fmt: skip
    train.add_argument("--dt", type=float, default=None, help="--mjcf: control period (s)")
    train.add_argument("--obs", default=None, help="--mjcf: e.g. state,site:fingertip")
    train.add_argument("--out", type=Path, default=None, help="run folder")
    train.add_argument("--chunk", type=int, default=5, help="iterations per jitted call")
    train.add_argument("--checkpoint-every", type=int, default=5)
    train.add_argument("--resume", action="store_true", help="continue from out/checkpoint.npz")
    train.add_argument("--no-progress", action="store_true")
    add_devices_option(train)
    add_process_options(train)
    train.add_argument(
        "--policy",
        choices=("none", "mdgps"),
        default="none",
        help="also train a global policy on the observations (MDGPS; override its settings "
        "with --set policy.s_step.n_steps=... etc.)",
    )
    train.add_argument(
        "--on-policy", action="store_true", help="with --policy: sample from the global policy"
    )
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
    add_devices_option(sweep)
    add_process_options(sweep)
    sweep.set_defaults(func=sweep_command)

    ev = subparsers.add_parser("eval", help="evaluate a run folder (re-optimisation, EPIC)")
    ev.add_argument("run", type=Path)
    ev.add_argument("--x64", action="store_true")
    ev.add_argument(
        "--env-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change the recorded env options (e.g. re-optimise from another start x0=...)",
    )
    ev.set_defaults(func=eval_command)

    plot = subparsers.add_parser("plot", help="redraw a run folder's plots")
    plot.add_argument("run", type=Path)
    plot.add_argument("--x64", action="store_true")
    plot.set_defaults(func=plot_command)
