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

BUILTIN_DEMOS = "arm-gps-expert-10"


def builtin_demos(env=None, *, num_demos: int = 10, seed: int = 0, verbose: bool = True):
    """The built-in arm demos (a :class:`diffgcl.data.demos.DemoSet`), generated once and cached."""
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
    result = run_seeds(GPSConfig(), env, env.expert_cost, seeds, chunk=8)
    final = np.all(result["metrics"].success[:, -1], axis=-1)
    if not final.any():
        raise RuntimeError("builtin_demos: no GPS expert seed succeeded")
    i = int(np.argmax(final))
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
