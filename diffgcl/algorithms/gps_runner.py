"""Host side of arm-scale GPS runs: many seeds as vmapped batches, summaries, failure reports.

The pure core is :mod:`diffgcl.algorithms.gps`; these functions compile it ahead of time (to time
compilation separately from execution), run seeds in chunks, and turn the metrics into
JSON-ready summaries. Used by the ``diffgcl gps`` / ``diffgcl demos`` commands, the built-in
expert demos and ``experiments/arm_gps.py``.

Definitions used in the summaries: a seed *succeeds* when the noise-free rollout of its final
controllers (after the last iteration's C-step) succeeds on every condition; its *first success*
is the 1-based iteration after whose C-step that first happened.
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
