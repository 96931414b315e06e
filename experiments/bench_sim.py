"""Simulation benchmark on the arm: MJX rollouts vs C MuJoCo, autodiff vs finite differences.

Measured in one run, side by side:

* rollout throughput (steps/s) of a linear-Gaussian controller on MJX (one device, and the batch
  sharded over all devices) against C ``mujoco.rollout`` with one thread per core (open-loop
  controls: C MuJoCo has no batched feedback controller, and the feedback costs ~nothing);
* the same rollouts with MJX ``impl="warp"`` (MuJoCo Warp on warp-lang; non-differentiable, for
  GPUs; here on Warp's CPU device);
* linearisation of T = 100 steps by ``jax.jacfwd`` through ``mjx.step`` against centred
  ``mujoco.mjd_transitionFD``, and their largest difference (float64).

    python experiments/bench_sim.py [--fast] [--json PATH]

The process forces one XLA host device per core (before JAX starts) so that "sharded" means
split over the cores; float32 for throughput, float64 for the Jacobian comparison.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

CORES = os.cpu_count() or 1
os.environ.setdefault("XLA_FLAGS", f"--xla_force_host_platform_device_count={CORES}")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import rollout as c_rollout  # noqa: E402

from diffgcl.dynamics.autodiff import linearize_trajectory  # noqa: E402
from diffgcl.envs import make_env  # noqa: E402
from diffgcl.runtime import prepare_process  # noqa: E402
from diffgcl.sim.rollout import sample_controller  # noqa: E402
from diffgcl.sim.sharding import batch_mesh, shard_batch  # noqa: E402
from diffgcl.sim.warp_backend import WarpUnavailableError, benchmark_warp  # noqa: E402
from diffgcl.types import make_controller  # noqa: E402


def best_time(fn, repeats: int) -> float:
    """Fastest of ``repeats`` calls (seconds); the first call is a warm-up."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def mjx_throughput(env, n: int, T: int, sharded: bool, repeats: int) -> float:
    dtype = jnp.zeros(()).dtype
    ctrl = make_controller(
        jnp.zeros((T, 2, 4), dtype) - 0.5 * jnp.eye(2, 4, dtype=dtype),
        jnp.zeros((T, 2), dtype),
        jnp.broadcast_to(0.1 * jnp.eye(2, dtype=dtype), (T, 2, 2)),
    )
    x0 = env.initial_states()[0]
    chunks = len(jax.devices()) if sharded else 1
    per = n // chunks

    @jax.jit
    def run(keys):
        traj = jax.vmap(lambda k: sample_controller(env, ctrl, x0, k, per))(keys)
        return traj.X[..., -1, :]

    keys = jax.random.split(jax.random.key(0), chunks)
    if sharded:
        keys = shard_batch(keys, batch_mesh())
    seconds = best_time(lambda: run(keys).block_until_ready(), repeats)
    return n * T / seconds


def c_throughput(env, n: int, T: int, repeats: int) -> float:
    model = mujoco.MjModel.from_xml_path(env.mjcf_path)
    model.actuator_forcerange[:] = [[-env.torque_limit, env.torque_limit]] * env.dU
    datas = [mujoco.MjData(model) for _ in range(CORES)]
    data = mujoco.MjData(model)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.zeros(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    initial = np.tile(state, (n, 1))
    controls = np.random.default_rng(0).normal(size=(n, T, model.nu))

    def run():
        c_rollout.rollout(model, datas, initial, controls, persistent_pool=True)

    return n * T / best_time(run, repeats)


def linearization_comparison(T: int, batch: int, repeats: int) -> dict:
    """Autodiff vs centred FD Jacobians along arm trajectories, float64: one trajectory of T
    steps, and ``batch`` of them at once (how a sweep over seeds linearises)."""
    with jax.enable_x64(True):
        env = make_env("arm")
        rng = np.random.default_rng(1)
        U = 0.3 * rng.normal(size=(batch, T, 2))
        X = [np.tile(np.asarray(env.initial_states()[0]), (batch, 1))]
        step = jax.jit(jax.vmap(env.step))
        for t in range(T):
            X.append(np.asarray(step(jnp.asarray(X[-1]), jnp.asarray(U[:, t]))))
        X = np.stack(X, axis=1)  # [batch, T+1, 4]
        lin = jax.jit(lambda X, U: linearize_trajectory(env.step, X, U))
        lin_batch = jax.jit(jax.vmap(lambda X, U: linearize_trajectory(env.step, X, U)))
        Xj, Uj = jnp.asarray(X), jnp.asarray(U)
        A, B = lin(Xj[0], Uj[0])
        t_ad = best_time(lambda: jax.block_until_ready(lin(Xj[0], Uj[0])), repeats)
        t_ad_batch = best_time(lambda: jax.block_until_ready(lin_batch(Xj, Uj)), repeats)

        model = mujoco.MjModel.from_xml_path(env.mjcf_path)
        data = mujoco.MjData(model)
        A_fd = np.zeros((batch, T, 4, 4))
        B_fd = np.zeros((batch, T, 4, 2))

        def fd(trajectories):
            for i in range(trajectories):
                for t in range(T):
                    data.qpos[:], data.qvel[:], data.ctrl[:] = X[i, t, :2], X[i, t, 2:], U[i, t]
                    mujoco.mjd_transitionFD(
                        model, data, 1e-6, True, A_fd[i, t], B_fd[i, t], None, None
                    )

        t_fd = best_time(lambda: fd(1), repeats)
        t_fd_batch = best_time(lambda: fd(batch), repeats)
        diff = max(np.abs(np.asarray(A) - A_fd[0]).max(), np.abs(np.asarray(B) - B_fd[0]).max())
    return {
        "linearize_autodiff_ms": 1e3 * t_ad,
        "linearize_fd_ms": 1e3 * t_fd,
        "linearize_max_abs_diff": float(diff),
        "linearize_batch": batch,
        "linearize_batch_autodiff_ms": 1e3 * t_ad_batch,
        "linearize_batch_fd_ms": 1e3 * t_fd_batch,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--fast", action="store_true", help="small sizes, one repeat")
    parser.add_argument("--json", help="write the figures to this JSON file")
    args = parser.parse_args(argv)
    prepare_process()
    T = 100
    sizes = (64, 256) if args.fast else (64, 1024, 8192)
    repeats = 1 if args.fast else 3
    env = make_env("arm")  # float32: the precision of throughput runs

    rows = []
    for n in sizes:
        row = {"n": n, "c_rollout": c_throughput(env, n, T, repeats)}
        row["mjx_1_device"] = mjx_throughput(env, n, T, sharded=False, repeats=repeats)
        if len(jax.devices()) > 1 and n % len(jax.devices()) == 0:
            row["mjx_sharded"] = mjx_throughput(env, n, T, sharded=True, repeats=repeats)
        rows.append(row)
        print(
            f"N={n:5d} T={T}: MJX 1 device {row['mjx_1_device']:12.0f} steps/s | "
            f"MJX sharded over {len(jax.devices())} {row.get('mjx_sharded', float('nan')):12.0f}"
            f" | C rollout ({CORES} threads) {row['c_rollout']:12.0f}"
        )
    warp_n = 1024 if not args.fast else sizes[-1]
    try:
        warp = benchmark_warp(warp_n, T, env=env, repeats=repeats)
        print(f"N={warp_n:5d} T={T}: MJX impl='warp' (CPU) {warp:12.0f} steps/s")
    except WarpUnavailableError as err:
        warp = None
        print(f"MJX impl='warp' unavailable here: {err}")
    ref = next(r for r in rows if r["n"] == (1024 if not args.fast else sizes[-1]))
    best_mjx = max(ref["mjx_1_device"], ref.get("mjx_sharded", 0.0))
    results = {
        "mjx_steps_per_s": best_mjx,
        "c_rollout_steps_per_s": ref["c_rollout"],
        "mjx_over_c": best_mjx / ref["c_rollout"],
        "throughput": rows,
        "warp_steps_per_s": warp,
        "devices": len(jax.devices()),
        "cores": CORES,
        "fast": args.fast,
    }
    results.update(linearization_comparison(T, 8 if args.fast else 32, repeats))
    print(
        f"linearise T={T}: autodiff {results['linearize_autodiff_ms']:.2f} ms | centred FD "
        f"{results['linearize_fd_ms']:.2f} ms | speed-up "
        f"{results['linearize_fd_ms'] / results['linearize_autodiff_ms']:.1f}x | max |diff| "
        f"{results['linearize_max_abs_diff']:.2e}"
    )
    print(
        f"linearise {results['linearize_batch']} x T={T}: autodiff "
        f"{results['linearize_batch_autodiff_ms']:.2f} ms | centred FD "
        f"{results['linearize_batch_fd_ms']:.2f} ms | speed-up "
        f"{results['linearize_batch_fd_ms'] / results['linearize_batch_autodiff_ms']:.1f}x"
    )
    print(f"MJX / C rollout at N={ref['n']}: {results['mjx_over_c']:.2f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
