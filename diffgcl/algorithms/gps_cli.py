"""Host shell of arm GPS: run seeds, time them, plot, write demos; ``gps`` and ``demos`` commands.

The pure core is :mod:`diffgcl.algorithms.gps`; this module owns everything outside jit:
compiling ahead of time (to time compilation separately), reporting C-step failures
(:func:`diffgcl.control.dual.describe`), the learning-curve and arm-motion plots (matplotlib,
Agg), the JSON summary and the expert demo dataset. ``experiments/arm_gps.py`` and the
``diffgcl gps`` / ``diffgcl demos`` subcommands share it.

Definitions used in the summaries: a seed *succeeds* when the noise-free rollout of its final
controllers (after the last iteration's C-step) succeeds on every condition; its *first success*
is the 1-based iteration after whose C-step that first happened.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.algorithms.gps import GPSConfig, first_success, make_gps
from diffgcl.control.dual import CStepInfo, describe


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


def make_arm(torque_limit: float | None = None):
    from diffgcl.envs import make_env

    return make_env("arm") if torque_limit is None else make_env("arm", torque_limit=torque_limit)


def run_seeds(config: GPSConfig, env, cost, seeds, *, chunk: int = 32) -> dict:
    """Train one GPS run per seed (vmapped in chunks of ``chunk``).

    Returns a dict with ``state`` and ``metrics`` (NumPy pytrees, leading axis seeds; metrics
    [seeds, iterations, C]), ``compile_seconds`` (lower + compile of one chunk) and
    ``run_seconds`` (execution of all chunks after compilation).
    """
    gps = make_gps(config, env, cost)
    keys = jnp.stack([jax.random.PRNGKey(int(s)) for s in seeds])
    size = min(chunk, len(seeds))
    pad = (-len(seeds)) % size
    keys_padded = jnp.concatenate([keys, keys[:pad]]) if pad else keys
    t0 = time.perf_counter()
    compiled = jax.jit(jax.vmap(gps.train)).lower(keys_padded[:size]).compile()
    compile_seconds = time.perf_counter() - t0
    states, metrics = [], []
    t0 = time.perf_counter()
    for i in range(0, keys_padded.shape[0], size):
        state, m = compiled(keys_padded[i : i + size])
        jax.block_until_ready(m)
        states.append(state)
        metrics.append(m)
    run_seconds = time.perf_counter() - t0
    cat = lambda *a: np.concatenate([np.asarray(x) for x in a])[: len(seeds)]
    return {
        "state": jax.tree.map(cat, *states),
        "metrics": jax.tree.map(cat, *metrics),
        "compile_seconds": compile_seconds,
        "run_seconds": run_seconds,
    }


def summarise(result: dict, seeds, config: GPSConfig) -> dict:
    """JSON-ready summary of :func:`run_seeds` (see the module docstring for definitions)."""
    m = result["metrics"]
    final = np.all(m.success[:, -1], axis=-1)
    first = np.asarray(first_success(jnp.asarray(m.success)))
    reached = first >= 0
    n = len(seeds)
    return {
        "dynamics": config.dynamics,
        "seeds": [int(s) for s in seeds],
        "iterations": config.iterations,
        "success_rate": float(final.mean()),
        "successes": int(final.sum()),
        "first_success_iteration": [int(f) + 1 if f >= 0 else None for f in first],
        "mean_first_success_iteration": float((first[reached] + 1).mean())
        if reached.any()
        else None,
        "final_mean_cost": float(m.cost[:, -1].mean()),
        "mean_cost_per_iteration": m.cost.mean(axis=(0, 2)).tolist(),
        "c_step_failures": int(m.c_step_failed.sum()),
        "compile_seconds": result["compile_seconds"],
        "batch_seconds_after_compile": result["run_seconds"],
        "seconds_per_run_after_compile": result["run_seconds"] / n,
        "seconds_per_iteration_after_compile": result["run_seconds"] / (n * config.iterations),
    }


def report_failures(metrics, seeds) -> list[str]:
    """Lines describing every failed C-step (seed, iteration, condition); also printed."""
    lines = []
    failed = np.argwhere(np.asarray(metrics.c_step_failed))
    for s, it, c in failed:
        info = CStepInfo(
            eta=metrics.eta[s, it, c],
            kl=metrics.kl[s, it, c],
            epsilon=metrics.epsilon[s, it, c],
            status=metrics.c_step_status[s, it, c],
            ok=~metrics.c_step_failed[s, it, c],
            iterations=metrics.c_step_iterations[s, it, c],
            not_pd=0,
        )
        lines.append(f"seed {seeds[s]} iteration {it + 1}: " + describe(info)[0].split(": ", 1)[1])
    for line in lines:
        print("C-step failure:", line)
    return lines


def mean_rollout(env, controllers, x0):
    """Noise-free rollouts of controllers [C, T, ...] from x0 [C, dX] -> X [C, T+1, dX]."""
    from diffgcl.sim.rollout import rollout_controller

    T = controllers.K.shape[-3]

    def one(ctrl, x):
        return rollout_controller(env, ctrl, x, jnp.zeros((T, env.dU), x.dtype)).X

    return jax.jit(jax.vmap(one))(controllers, x0)


def plot_learning_curves(metrics, path: Path, label: str = "") -> None:
    """Mean true cost, step_mult and controller entropy per iteration (mean ± std over seeds and
    conditions; what GPS's GUI showed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    its = np.arange(1, metrics.cost.shape[1] + 1)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, name, values, log in (
        (axes[0], "mean sample cost", metrics.cost, True),
        (axes[1], "step_mult", metrics.step_mult, True),
        (axes[2], "controller entropy (nats)", metrics.entropy, False),
    ):
        v = np.asarray(values).reshape(values.shape[0], values.shape[1], -1)
        mean, std = v.mean(axis=(0, 2)), v.std(axis=(0, 2))
        ax.plot(its, mean, marker="o")
        ax.fill_between(its, mean - std, mean + std, alpha=0.25)
        ax.set_xlabel("iteration")
        ax.set_title(name)
        if log:
            ax.set_yscale("log")
    success = np.all(np.asarray(metrics.success), axis=-1).mean(axis=0)
    twin = axes[0].twinx()
    twin.plot(its, success, color="tab:green", ls="--", label="success rate")
    twin.set_ylim(-0.05, 1.05)
    twin.legend(loc="upper right")
    fig.suptitle(f"GPS on the arm {label}".strip())
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def arm_points(env, X) -> np.ndarray:
    """Planar positions of the arm's bodies and sites along X: [T+1, dX] -> [T+1, P, 2]."""
    from mujoco import mjx

    def points(x):
        d = mjx.kinematics(env.model, env.data0.replace(qpos=x[:2]))
        return jnp.concatenate([d.xpos[1:, :2], d.site_xpos[:, :2]], axis=0)

    return np.asarray(jax.jit(jax.vmap(points))(jnp.asarray(X)))


def plot_arm_motion(env, X, path: Path, every: int = 5) -> None:
    """Joint angles over time and a stroboscopic drawing of the arm (X: [T+1, dX], one run)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = arm_points(env, X)
    X = np.asarray(X)
    t = np.arange(X.shape[0]) * env.dt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for j in range(2):
        axes[0].plot(t, X[:, j], label=f"q{j + 1}")
    axes[0].axhspan(-env.success_tolerance, env.success_tolerance, color="g", alpha=0.15)
    axes[0].set_xlabel("time (s)")
    axes[0].set_ylabel("joint angle (rad)")
    axes[0].legend()
    cmap = plt.get_cmap("viridis")
    idx = list(range(0, X.shape[0], every)) + [X.shape[0] - 1]
    for n, i in enumerate(idx):
        colour = cmap(n / max(len(idx) - 1, 1))
        axes[1].plot(P[i, :, 0], P[i, :, 1], "-o", color=colour, ms=3, lw=1.5)
    axes[1].set_aspect("equal")
    axes[1].set_title(f"arm every {every} steps (dark: start, yellow: end)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def animate_arm(env, X, path: Path, every: int = 2) -> None:
    """GIF of the arm along X: [T+1, dX] (every ``every``-th state, real time)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    P = arm_points(env, X)
    reach = float(np.abs(P).max()) * 1.1
    fig, ax = plt.subplots(figsize=(4, 4))
    ax.set_xlim(-reach, reach)
    ax.set_ylim(-reach, reach)
    ax.set_aspect("equal")
    target = arm_points(env, jnp.zeros((1, env.dX), jnp.asarray(X).dtype))[0]
    ax.plot(target[:, 0], target[:, 1], "--", color="g", lw=1, label="target")
    (line,) = ax.plot([], [], "-o", lw=3, ms=5)
    title = ax.set_title("")
    ax.legend(loc="lower left")
    frames = list(range(0, P.shape[0], every))

    def draw(i):
        line.set_data(P[i, :, 0], P[i, :, 1])
        title.set_text(f"t = {i * env.dt:.2f} s")
        return line, title

    anim = FuncAnimation(fig, draw, frames=frames, blit=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    anim.save(path, writer=PillowWriter(fps=max(1, round(1 / (every * env.dt)))))
    plt.close(fig)


def run_arm_gps(args) -> dict:
    """Everything ``experiments/arm_gps.py`` and ``diffgcl gps`` do; returns the summary."""
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import enable_compilation_cache

    enable_compilation_cache()
    n_seeds = 4 if args.fast and args.seeds == 32 else args.seeds
    seeds = list(range(args.first_seed, args.first_seed + n_seeds))
    compare = (not args.fast) if args.compare is None else args.compare
    env = make_arm(args.torque_limit)
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
        args.out.mkdir(parents=True, exist_ok=True)
        plot_learning_curves(result["metrics"], args.out / "arm_gps_learning.png", config.dynamics)
        final = jax.tree.map(lambda a: jnp.asarray(a[0]), result["state"].controller)
        X = mean_rollout(env, final, jnp.asarray(env.initial_states()))
        plot_arm_motion(env, X[0], args.out / "arm_gps_motion.png")
        animate_arm(env, X[0], args.out / "arm_gps_motion.gif")
        if compare:
            plot_learning_curves(res2["metrics"], args.out / f"arm_gps_learning_{other}.png", other)
        print(f"plots in {args.out}")

    if args.write_demos is not None:
        summary["demos"] = _write_demos(env, result, seeds, args)

    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1))
        print(f"summary in {args.json}")
    return summary


def _write_demos(env, result, seeds, args) -> str:
    from diffgcl.algorithms.expert import write_expert_demos

    m = result["metrics"]
    final = np.all(m.success[:, -1], axis=-1)
    if not final.any():
        raise RuntimeError("no seed succeeded; refusing to write expert demos from a failed expert")
    i = int(np.argmax(final))
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

    demos = subparsers.add_parser("demos", help="train a GPS expert on the arm, write demos")
    demos.add_argument("out", type=Path, help="dataset folder (demos.npz + meta.json)")
    demos.add_argument("--seed", type=int, default=0)
    demos.add_argument("--num-demos", type=int, default=10)
    demos.add_argument("--iterations", type=int, default=10)
    demos.add_argument("--samples", type=int, default=5)
    demos.add_argument("--kl-step", type=float, default=0.2)
    demos.add_argument("--init-var", type=float, default=0.1)
    demos.add_argument("--smooth-sigma", type=float, default=2.0)
    demos.add_argument("--dynamics", choices=("autodiff", "regression"), default="autodiff")
    demos.add_argument("--torque-limit", type=float, default=None)
    demos.add_argument("--x64", action="store_true")
    demos.set_defaults(func=_demos_command)


def _gps_command(args) -> int:
    """Exit code 0 when at least one seed succeeded, 1 otherwise."""
    return 0 if run_arm_gps(args)["success_rate"] > 0 else 1


def _demos_command(args) -> int:
    """Train on seeds seed, seed+1, ... (up to 8) until one succeeds; write its demos."""
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import enable_compilation_cache

    enable_compilation_cache()
    env = make_arm(args.torque_limit)
    config = config_from_args(args)
    seeds = list(range(args.seed, args.seed + 8))
    result = run_seeds(config, env, env.expert_cost, seeds, chunk=8)
    report_failures(result["metrics"], seeds)
    args.write_demos = args.out
    _write_demos(env, result, seeds, args)
    return 0
