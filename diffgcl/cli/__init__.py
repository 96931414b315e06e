"""The ``diffgcl`` command line.

    diffgcl demo            the built-in default job (what ``make demo`` runs): rGCL v1 and v2
                            with the ``default`` preset on the arm, a handful of seeds
    diffgcl linearize       arm rollout + autodiff-vs-finite-difference linearisation report
    diffgcl envs            registered environments and their sizes

Subcommands of other parts of the package register themselves in :data:`SUBCOMMAND_MODULES`
(a module with ``register(subparsers)``).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time

from diffgcl.cli.errors import guarded

SUBCOMMAND_MODULES: tuple[str, ...] = (
    "diffgcl.cli.gps",
    "diffgcl.cli.rgcl",
    "diffgcl.cli.bags",
    "diffgcl.cli.policy",
    "diffgcl.cli.usv",
)


def cmd_envs(args: argparse.Namespace) -> int:
    from diffgcl.envs import ENV_NAMES, make_env

    for name in ENV_NAMES:
        env = make_env(name)
        print(
            f"{name:6s} dX={env.dX:3d} dU={env.dU} dO={env.dO:3d} dt={env.dt:g} "
            f"T={env.horizon} conditions={env.initial_states().shape[0]} mjcf={env.mjcf_path}"
        )
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from diffgcl.cli.rgcl import run_demo

    return run_demo(args)


def cmd_linearize(args: argparse.Namespace) -> int:
    """Arm rollout and linearisation report: batched MJX samples, autodiff vs C finite
    differences along their mean."""
    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np

    from diffgcl.dynamics.autodiff import fit_dynamics
    from diffgcl.envs import make_env
    from diffgcl.sim.rollout import sample_controller
    from diffgcl.types import make_controller

    jax.config.update("jax_enable_x64", True)
    env = make_env("arm")
    T, n = env.horizon, args.samples
    ctrl = make_controller(
        jnp.zeros((T, env.dU, env.dX)),
        jnp.zeros((T, env.dU)),
        jnp.broadcast_to(0.1 * jnp.eye(env.dU), (T, env.dU, env.dU)),
    )
    x0 = env.initial_states()[0]

    @jax.jit
    def iteration(key):
        traj = sample_controller(env, ctrl, x0, key, n, smooth_sigma=2.0)
        return traj, fit_dynamics(env.step, traj.X, traj.U)

    start = time.perf_counter()
    traj, dyn = jax.block_until_ready(iteration(jax.random.key(args.seed)))
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    traj, dyn = jax.block_until_ready(iteration(jax.random.key(args.seed + 1)))
    run_s = time.perf_counter() - start

    model = mujoco.MjModel.from_xml_path(env.mjcf_path)
    data = mujoco.MjData(model)
    X, U = np.asarray(traj.X.mean(0)), np.asarray(traj.U.mean(0))
    worst = 0.0
    for t in range(T):
        data.qpos[:], data.qvel[:], data.ctrl[:] = X[t, :2], X[t, 2:], U[t]
        A = np.zeros((4, 4))
        B = np.zeros((4, 2))
        mujoco.mjd_transitionFD(model, data, 1e-6, True, A, B, None, None)
        worst = max(worst, np.abs(A - dyn.A[t]).max(), np.abs(B - dyn.B[t]).max())

    final = np.asarray(traj.X[:, -1, :2])
    print(f"arm: {n} samples x T={T} of a zero-gain controller with smoothed noise (Σ = 0.1 I)")
    print(f"  first call (compile + run) {compile_s:.1f} s, next call {1e3 * run_s:.1f} ms")
    print(f"  final joint angles: mean {final.mean(0).round(3)} std {final.std(0).round(3)}")
    print(f"  autodiff A, B vs centred finite differences (C MuJoCo): max |diff| {worst:.1e}")
    noise = float(jnp.trace(dyn.cov, axis1=1, axis2=2).mean())
    print(f"  dynamics noise trace (mean over t): {noise:.2e}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="diffgcl", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="run the built-in default job (rGCL on the arm)")
    demo.add_argument("--seeds", type=int, default=4, help="number of seeds")
    demo.add_argument("--seed", type=int, default=0, help="first seed")
    demo.add_argument("--out", default="runs/demo", help="run folders go here")
    demo.set_defaults(func=cmd_demo)
    lin = sub.add_parser("linearize", help="arm rollout + linearisation report")
    lin.add_argument("--samples", type=int, default=5)
    lin.add_argument("--seed", type=int, default=0)
    lin.set_defaults(func=cmd_linearize)
    envs = sub.add_parser("envs", help="list registered environments")
    envs.set_defaults(func=cmd_envs)
    for module in SUBCOMMAND_MODULES:
        importlib.import_module(module).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from diffgcl.runtime import apply_devices_option, prepare_process, set_cpu_devices

    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # for --local-processes
    if hasattr(args, "devices"):
        apply_devices_option(args)
    else:
        set_cpu_devices()  # seed batches are sharded over the cores
    prepare_process()
    return int(guarded(args.func)(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
