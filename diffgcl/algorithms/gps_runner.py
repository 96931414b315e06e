"""Host side of arm-scale GPS runs: many seeds as vmapped batches, summaries, failure reports.

The pure core is :mod:`diffgcl.algorithms.gps`; these functions compile it ahead of time (to time
compilation separately from execution), run seeds in chunks, and turn the metrics into
JSON-ready summaries. Used by the ``diffgcl gps`` / ``diffgcl demos`` commands, the built-in
expert demos and ``experiments/arm_gps.py``.

The iterations run as a staged loop (:func:`diffgcl.algorithms.staged.run_gps_seeds`): the
simulator's programs are compiled once per env and shared with every other run of the process.

Definitions used in the summaries: a seed *succeeds* when the noise-free rollout of its final
controllers (after the last iteration's C-step) succeeds on every condition; its *first success*
is the 1-based iteration after whose C-step that first happened (the metrics describe the
controller before each C-step, the final rollout the one after the last).
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.algorithms.gps import GPSConfig, first_success, make_gps
from diffgcl.control.dual import CStepInfo, describe


def run_seeds(config: GPSConfig, env, cost, seeds, *, chunk: int = 32) -> dict:
    """Train one GPS run per seed (vmapped in chunks of ``chunk``).

    Returns a dict with ``state`` and ``metrics`` (NumPy pytrees, leading axis seeds; metrics
    [seeds, iterations, C]), ``final_success`` [seeds, C] (the final controllers' noise-free
    rollouts), ``compile_seconds`` (tracing and compiling) and ``run_seconds`` (the rest).
    """
    from diffgcl.algorithms.staged import run_gps_seeds
    from diffgcl.runtime import CompileClock

    gps = make_gps(config, env, cost)
    keys = jnp.stack([jax.random.PRNGKey(int(s)) for s in seeds])
    size = min(chunk, len(seeds))
    pad = (-len(seeds)) % size
    keys_padded = jnp.concatenate([keys, keys[:pad]]) if pad else keys
    states, metrics, finals = [], [], []
    t0 = time.perf_counter()
    with CompileClock() as clock:
        for i in range(0, keys_padded.shape[0], size):
            state, m, X = run_gps_seeds(gps, keys_padded[i : i + size], config.iterations, env)
            states.append(state)
            metrics.append(m)
            finals.append(np.asarray(jax.vmap(jax.vmap(env.success))(jnp.asarray(X))))
    wall = time.perf_counter() - t0
    cat = lambda *a: np.concatenate([np.asarray(x) for x in a])[: len(seeds)]
    return {
        "state": jax.tree.map(cat, *states),
        "metrics": jax.tree.map(cat, *metrics),
        "final_success": cat(*finals),
        "compile_seconds": clock.seconds,
        "run_seconds": wall - clock.seconds,
    }


def success_after_c_steps(metrics_success, final_success) -> np.ndarray:
    """[..., iterations, C]: whether the controller after each iteration's C-step succeeds —
    the metrics' (which describe the controller before it) shifted by one, the final rollout's
    last."""
    m = np.asarray(metrics_success)
    return np.concatenate([m[..., 1:, :], np.asarray(final_success)[..., None, :]], axis=-2)


def summarise(result: dict, seeds, config: GPSConfig) -> dict:
    """JSON-ready summary of :func:`run_seeds` (see the module docstring for definitions)."""
    m = result["metrics"]
    final = np.all(result["final_success"], axis=-1)
    after = success_after_c_steps(m.success, result["final_success"])
    first = np.asarray(first_success(jnp.asarray(after)))
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
    from diffgcl.algorithms.staged import noise_free_rollouts

    return jnp.asarray(noise_free_rollouts(env, controllers, jnp.asarray(x0))[0])
