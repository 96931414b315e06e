"""``diffgcl gps`` and ``diffgcl demos``: GPS on the arm with the expert cost over seeds, and
expert demonstrations from it (``demos --mjcf``: your own model's, by iLQR on a cost,
:mod:`diffgcl.cli.expert`). Argument parsing and printing; the runs, summaries and plots come
from :mod:`diffgcl.algorithms.gps_runner` and :mod:`diffgcl.viz.plots`.
``experiments/arm_gps.py`` runs :func:`run_arm_gps` with a JSON summary.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp

from diffgcl.algorithms.gps import GPSConfig
from diffgcl.algorithms.gps_runner import mean_rollout, report_failures, run_seeds, summarise
from diffgcl.envs.options import add_env_options, env_from_args


def add_gps_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of arm GPS, shared by ``experiments/arm_gps.py`` and ``diffgcl gps``."""
    parser.add_argument("--seeds", type=int, default=32, help="training runs (vmapped)")
    parser.add_argument("--fast", action="store_true", help="4 seeds, no regression comparison")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--samples", type=int, default=5, help="samples per iteration")
    parser.add_argument("--kl-step", type=float, default=0.2)
    parser.add_argument("--init-var", type=float, default=0.1)
    parser.add_argument("--smooth-sigma", type=float, default=2.0, help="noise smoothing, steps")
    parser.add_argument("--dynamics", choices=("autodiff", "regression"), default="autodiff")
    parser.add_argument(
        "--compare",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="also run dynamics='regression' on the same seeds (default: on unless --fast)",
    )
    parser.add_argument("--torque-limit", type=float, default=None, help="arm torque cap")
    add_env_options(parser, ("arm",))
    parser.add_argument("--chunk", type=int, default=32, help="seeds per vmapped batch")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--x64", action="store_true", help="float64 (default float32)")
    parser.add_argument("--json", type=Path, default=None, help="write the summary here")
    parser.add_argument("--out", type=Path, default=None, help="folder for plots")
    parser.add_argument("--write-demos", type=Path, default=None, help="folder for expert demos")
    parser.add_argument("--num-demos", type=int, default=10)


def config_from_args(args, dynamics: str | None = None) -> GPSConfig:
    return GPSConfig(
        iterations=args.iterations,
        num_samples=args.samples,
        kl_step=args.kl_step,
        init_var=args.init_var,
        smooth_sigma=args.smooth_sigma or None,
        dynamics=dynamics or args.dynamics,
    )


def make_arm(args):
    """The arm of ``--env-set`` (and ``--torque-limit``, the same as ``--env-set
    torque_limit=...``)."""
    if getattr(args, "torque_limit", None) is not None:
        args.env_set = [*args.env_set, f"torque_limit={args.torque_limit}"]
    return env_from_args(args)[0]


def run_arm_gps(args) -> dict:
    """Everything ``experiments/arm_gps.py`` and ``diffgcl gps`` do; returns the summary."""
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import prepare_process

    prepare_process()
    n_seeds = 4 if args.fast and args.seeds == 32 else args.seeds
    seeds = list(range(args.first_seed, args.first_seed + n_seeds))
    compare = (not args.fast) if args.compare is None else args.compare
    if args.write_demos is not None:
        _check_demo_folder(args.write_demos)
    env = make_arm(args)
    cost = env.expert_cost
    config = config_from_args(args)

    print(f"GPS on the arm: {n_seeds} seeds, {config.iterations} iterations, {config.dynamics}")
    result = run_seeds(config, env, cost, seeds, chunk=args.chunk)
    summary = summarise(result, seeds, config)
    summary["failures"] = report_failures(result["metrics"], seeds)
    summary["dtype"] = str(jnp.zeros(()).dtype)
    summary["device"] = str(jax.devices()[0])
    _print_summary(summary)

    if compare:
        other = "regression" if config.dynamics == "autodiff" else "autodiff"
        cfg2 = config_from_args(args, other)
        print(f"comparison: dynamics={other}, same seeds")
        res2 = run_seeds(cfg2, env, cost, seeds, chunk=args.chunk)
        summary[other] = summarise(res2, seeds, cfg2)
        summary[other]["failures"] = report_failures(res2["metrics"], seeds)
        _print_summary(summary[other])

    if args.out is not None:
        from diffgcl.viz import plots

        args.out.mkdir(parents=True, exist_ok=True)
        plots.gps_learning_curves(
            result["metrics"], args.out / "arm_gps_learning.png", config.dynamics
        )
        final = jax.tree.map(lambda a: jnp.asarray(a[0]), result["state"].controller)
        X = mean_rollout(env, final, jnp.asarray(env.initial_states()))
        plots.arm_rollout(env, X[0], args.out / "arm_gps_motion.png")
        plots.arm_animation(env, X[0], args.out / "arm_gps_motion.gif")
        if compare:
            plots.gps_learning_curves(
                res2["metrics"], args.out / f"arm_gps_learning_{other}.png", other
            )
        print(f"plots in {args.out}")

    if args.write_demos is not None:
        summary["demos"] = _write_demos(env, result, seeds, args)

    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1))
        print(f"summary in {args.json}")
    return summary


DEMO_FILES = {"demos.npz", "meta.json"}


def _check_demo_folder(out: Path) -> None:
    """A demo folder may be new, empty or a dataset written before (``DemoSet.save`` replaces
    the whole folder): anything else is refused rather than deleted."""
    if out.exists() and (not out.is_dir() or set(p.name for p in out.iterdir()) - DEMO_FILES):
        raise SystemExit(
            f"diffgcl: {out} exists and is not a demo dataset; the demos would replace it — "
            "choose a new folder"
        )


def _write_demos(env, result, seeds, args) -> str:
    from diffgcl.algorithms.expert import best_expert, write_expert_demos

    i = best_expert(result["metrics"], result["final_success"])
    if i is None:
        raise SystemExit("diffgcl: no seed succeeded; no expert demos from a failed expert")
    controllers = jax.tree.map(lambda a: jnp.asarray(a[i]), result["state"].controller)
    demos = write_expert_demos(
        args.write_demos,
        env,
        controllers,
        jax.random.PRNGKey(10_000 + seeds[i]),
        args.num_demos,
        smooth_sigma=args.smooth_sigma or None,
        cost=env.expert_cost,
        seed=seeds[i],
    )
    ok = sum(e["success"] for e in demos.episodes)
    print(
        f"{demos.num_episodes} expert demos (seed {seeds[i]}, {ok} succeed) in {args.write_demos}"
    )
    return str(args.write_demos)


def _print_summary(s: dict) -> None:
    print(
        f"  [{s['dynamics']}] success {s['successes']}/{len(s['seeds'])}, "
        f"first success (mean iteration) {s['mean_first_success_iteration']}, "
        f"final cost {s['final_mean_cost']:.2f}, C-step failures {s['c_step_failures']}, "
        f"compile {s['compile_seconds']:.1f} s, "
        f"{1e3 * s['seconds_per_iteration_after_compile']:.2f} ms per iteration per seed"
    )


def register(subparsers) -> None:
    """Add the ``gps`` and ``demos`` subcommands to an argparse ``subparsers`` object."""
    gps = subparsers.add_parser("gps", help="GPS on the arm with the expert cost over seeds")
    add_gps_arguments(gps)
    gps.set_defaults(func=_gps_command)

    demos = subparsers.add_parser(
        "demos", help="expert demos: GPS on the arm, or iLQR on your model's cost (--mjcf)"
    )
    demos.add_argument(
        "out", type=Path, help="dataset folder (demos.npz + meta.json); with --mjcf an .npz file"
    )
    demos.add_argument("--seed", type=int, default=0)
    demos.add_argument("--num-demos", type=int, default=10)
    demos.add_argument(
        "--iterations", type=int, default=30, help="GPS iterations (the built-in demos' 30)"
    )
    demos.add_argument("--samples", type=int, default=5)
    demos.add_argument("--kl-step", type=float, default=0.2)
    demos.add_argument("--init-var", type=float, default=0.1)
    demos.add_argument("--smooth-sigma", type=float, default=2.0)
    demos.add_argument("--dynamics", choices=("autodiff", "regression"), default="autodiff")
    demos.add_argument("--torque-limit", type=float, default=None)
    add_env_options(demos, ("arm",))
    demos.add_argument("--x64", action="store_true")
    from diffgcl.cli import expert

    expert.add_arguments(demos)
    demos.set_defaults(func=_demos_command)


def _gps_command(args) -> int:
    """Exit code 0 when at least one seed succeeded, 1 otherwise."""
    return 0 if run_arm_gps(args)["success_rate"] > 0 else 1


def _demos_command(args) -> int:
    """Train GPS on seeds seed, ..., seed+7; write the demos of the succeeding seed with the
    lowest final cost (as the built-in demos are chosen)."""
    if args.x64 or args.mjcf is not None:  # iLQR on an MJCF model runs in float64 (cli.expert)
        jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import prepare_process

    prepare_process()
    if args.mjcf is not None:
        from diffgcl.cli.expert import mjcf_demos_command

        return mjcf_demos_command(args)
    _check_demo_folder(args.out)
    env = make_arm(args)
    config = config_from_args(args)
    seeds = list(range(args.seed, args.seed + 8))
    result = run_seeds(config, env, env.expert_cost, seeds, chunk=8)
    report_failures(result["metrics"], seeds)
    args.write_demos = args.out
    _write_demos(env, result, seeds, args)
    return 0
