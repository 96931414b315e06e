"""A grid of traced hyperparameters × seeds: independent rGCL runs in batches over every device.

The runs (point-major: every seed of the first grid point, then the next) go through
``jit(vmap_over_devices(train))`` in chunks of equal size, a multiple of the number of devices,
so one compiled program serves every chunk and each device runs the same share; the last chunk is
padded with copies of its last run, whose results are dropped. The batch mesh spans the devices
of every process of a multi-process run (:mod:`diffgcl.distributed`): each process computes its
slice of each chunk and the per-run outcome is all-gathered after it, so every process ends with
the whole :class:`SweepResult` (process 0 prints and writes it).

Each run's outcome is scored inside the sharded program: success (DESIGN §2, the noise-free
rollout of the final controller on every condition), final distance (largest error of the
target coordinates at the last state, worst condition), final true cost (mean over conditions of
the last GPS iteration's sample cost).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from diffgcl.algorithms.rgcl import (
    DemoBatch,
    RGCLConfig,
    RGCLHyperparams,
    RGCLMetrics,
    RGCLState,
    final_rollouts,
    make_train,
)
from diffgcl.distributed import barrier, check_same_everywhere, compile_program, to_host
from diffgcl.sim.sharding import batch_mesh, shard_batch, vmap_over_devices
from diffgcl.types import Array

SWEEPABLE = ("kl_step", "init_var", "cost_lr")


def parse_grid(items) -> dict[str, tuple[float, ...]]:
    """``["cost_lr=1e-4,1e-3", "kl_step=0.2"]`` -> ``{"cost_lr": (1e-4, 1e-3), "kl_step":
    (0.2,)}``; a ValueError names the item that is not ``NAME=V1,V2,...`` with NAME one of
    :data:`SWEEPABLE`."""
    grid: dict[str, tuple[float, ...]] = {}
    for item in items:
        name, sep, values = item.partition("=")
        if not sep or name not in SWEEPABLE:
            raise ValueError(f"--param {item!r}: expected NAME=V1,V2,... with NAME in {SWEEPABLE}")
        try:
            grid[name] = tuple(float(v) for v in values.split(","))
        except ValueError:
            raise ValueError(f"--param {item!r}: the values must be numbers") from None
    return grid


@struct.dataclass
class Outcome:
    """Per-run result of a sweep (a batch stacks a leading [runs] axis): success (bool),
    final_distance, final_true_cost."""

    success: Array
    final_distance: Array
    final_true_cost: Array


def run_outcome(env, state: RGCLState, metrics: RGCLMetrics) -> Outcome:
    """Score one finished run (see the module docstring)."""
    X = final_rollouts(env, state.gps.controller)  # [C, T+1, dX]
    target = jnp.asarray(env.target)
    return Outcome(
        success=jnp.all(jax.vmap(env.success)(X)),
        final_distance=jnp.max(jnp.abs(X[:, -1, : target.shape[0]] - target)),
        final_true_cost=jnp.mean(metrics.gps.cost[-1, -1]),
    )


@dataclass
class SweepResult:
    """What :func:`run_sweep` returns (NumPy; runs point-major, ``len(points) × len(seeds)``).

    outcome: :class:`Outcome` [runs]; state / metrics: every run's final RGCLState and
    RGCLMetrics [runs, ...] when asked for (``keep_states``), else None; compile_seconds:
    lowering + compilation of the chunk program (this process's); run_seconds: the chunks after
    every process has compiled, gathers included; processes, devices: the layout it ran on;
    chunk: runs per chunk.
    """

    grid: dict[str, tuple[float, ...]]
    points: list[tuple[float, ...]]
    seeds: list[int]
    outcome: Outcome
    state: RGCLState | None
    metrics: RGCLMetrics | None
    compile_seconds: float
    run_seconds: float
    processes: int
    devices: int
    chunk: int

    def table(self) -> list[dict]:
        """One row per grid point: its values and the success rate over the seeds."""
        S = len(self.seeds)
        success = np.asarray(self.outcome.success).reshape(len(self.points), S)
        return [
            {**dict(zip(SWEEPABLE, p, strict=True)), "success_rate": float(success[j].mean())}
            for j, p in enumerate(self.points)
        ]

    def to_dict(self) -> dict:
        """The JSON summary (no states)."""
        return {
            "seeds": self.seeds,
            "grid": self.table(),
            "runs": [
                {
                    **dict(zip(SWEEPABLE, p, strict=True)),
                    "seed": s,
                    "success": bool(self.outcome.success[i]),
                    "final_distance": float(self.outcome.final_distance[i]),
                    "final_true_cost": float(self.outcome.final_true_cost[i]),
                }
                for i, (p, s) in enumerate(itertools.product(self.points, self.seeds))
            ],
            "compile_seconds": self.compile_seconds,
            "run_seconds": self.run_seconds,
            "processes": self.processes,
            "devices": self.devices,
            "chunk": self.chunk,
        }


def run_sweep(
    config: RGCLConfig,
    env,
    demos: DemoBatch,
    seeds,
    grid: dict[str, tuple[float, ...]] | None = None,
    *,
    chunk: int = 32,
    keep_states: bool = False,
) -> SweepResult:
    """Every point of ``grid`` (names of :data:`SWEEPABLE`; the config's value for the others)
    × every seed, in chunks of about ``chunk`` runs over all devices of all processes.

    In a multi-process run every process must call this with the same arguments (checked).
    """
    seeds = [int(s) for s in seeds]
    rgcl = make_train(config, env)
    base = rgcl.default_hparams()
    grid = grid or {}
    full = {n: tuple(grid.get(n, (float(getattr(base, n)),))) for n in SWEEPABLE}
    points = list(itertools.product(*(full[name] for name in SWEEPABLE)))
    runs = list(itertools.product(points, seeds))
    mesh = batch_mesh()
    n = mesh.devices.size
    size = -(-min(chunk, len(runs)) // n) * n  # rounded up to a multiple of the devices
    dtype = jnp.asarray(env.initial_states()).dtype
    keys = np.stack([np.asarray(jax.random.PRNGKey(s)) for _, s in runs])
    hp = np.asarray([p for p, _ in runs], dtype)  # [runs, 3]
    check_same_everywhere("sweep settings", {"config": config.to_dict(), "runs": runs})
    check_same_everywhere("demos", demos)

    def one(key, demos, hp_row):
        hparams = RGCLHyperparams(*(hp_row[i] for i in range(len(SWEEPABLE))))
        state, metrics = rgcl.train(key, demos, hparams)
        outcome = run_outcome(env, state, metrics)
        return (outcome, state, metrics) if keep_states else outcome

    program = jax.jit(vmap_over_devices(one, in_axes=(0, None, 0), mesh=mesh))

    def batch(i: int):
        take = np.minimum(np.arange(i, i + size), len(runs) - 1)  # pad with the last run
        return shard_batch((keys[take], hp[take]), mesh)

    t0 = time.perf_counter()
    k0, h0 = batch(0)
    compiled = compile_program(program.lower(k0, demos, h0))
    compile_seconds = time.perf_counter() - t0
    barrier("sweep compiled")  # time the runs, not another process's compilation
    parts = []
    t0 = time.perf_counter()
    for i in range(0, len(runs), size):
        k, h = batch(i)
        out = to_host(compiled(k, demos, h))
        parts.append(jax.tree.map(lambda a, i=i: a[: len(runs) - i], out))
    run_seconds = time.perf_counter() - t0
    gathered = jax.tree.map(lambda *a: np.concatenate(a), *parts)
    outcome, state, metrics = gathered if keep_states else (gathered, None, None)
    return SweepResult(
        grid=full,
        points=points,
        seeds=seeds,
        outcome=outcome,
        state=state,
        metrics=metrics,
        compile_seconds=compile_seconds,
        run_seconds=run_seconds,
        processes=jax.process_count(),
        devices=n,
        chunk=size,
    )
