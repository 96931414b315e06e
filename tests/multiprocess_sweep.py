"""Driver for tests/test_distributed.py: tiny float64 rGCL runs on the stand-in env of
tests/test_rgcl.py, in whatever process layout the environment describes (one process, or one of
the processes :func:`diffgcl.distributed.launch_local` starts).

    python tests/multiprocess_sweep.py sweep DEMOS.pkl OUT.npz [--kill-process I]
    python tests/multiprocess_sweep.py train DEMOS.pkl OUT.npz --run-dir DIR

``sweep``: 2 learning rates × 3 seeds in chunks of 4 (the last one padded); process 0 writes every
leaf of the gathered result (outcome, final states, metrics) to OUT.npz. ``--kill-process I``:
process I kills itself (SIGKILL) once the processes have agreed on the settings and demos, while
the others go on to compile and run their first chunk (it does not compile: process 1 cannot
use the persistent compilation cache, and the test stays short). ``train``: the host runner over
2 seeds, crashed after 2 of 3 iterations (checkpoint every iteration) and resumed; OUT.npz holds
the resumed state and metrics.
"""

from __future__ import annotations

import argparse
import os
import pickle
import signal
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

from diffgcl import distributed  # noqa: E402

HEARTBEAT_TIMEOUT_S = 20


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=("sweep", "train"))
    parser.add_argument("demos", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--kill-process", type=int, default=None)
    parser.add_argument("--run-dir", type=Path, default=None)
    args = parser.parse_args()
    distributed.join(distributed.process_settings(), heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S)

    import numpy as np

    from diffgcl.algorithms import sweep
    from diffgcl.runtime import prepare_process

    prepare_process()
    sys.path.insert(0, str(Path(__file__).parent))
    from test_rgcl import Slider, tiny_config

    demos = pickle.loads(args.demos.read_bytes())
    config = tiny_config("v2", iterations=3)
    if args.mode == "train":
        from diffgcl.algorithms.runner import SimulatedCrash, train_seeds

        try:
            train_seeds(
                config,
                Slider(),
                demos,
                [0, 1],
                out=args.run_dir,
                chunk=1,
                checkpoint_every=1,
                crash_after=2,
                progress=False,
            )
        except SimulatedCrash:
            pass
        result = train_seeds(
            config, Slider(), demos, [0, 1], out=args.run_dir, chunk=1, resume=True, progress=False
        )
        assert result.resumed_from == 2, result.resumed_from
        tree = (result.state, result.metrics)
    else:
        if args.kill_process == jax.process_index():
            check = sweep.check_same_everywhere

            def check_then_die(what, value):
                check(what, value)
                if what == "demos":  # the last check before the sweep compiles and runs
                    os.kill(os.getpid(), signal.SIGKILL)

            sweep.check_same_everywhere = check_then_die
        try:
            result = sweep.run_sweep(
                config,
                Slider(),
                demos,
                seeds=[0, 1, 2],
                grid={"cost_lr": (1e-2, 3e-3)},
                chunk=4,
                keep_states=True,
            )
        except distributed.ProcessLost as err:
            distributed.abandon(f"sweep: {err}")
        tree = (result.outcome, result.state, result.metrics)
        print(
            f"chunk {result.chunk} devices {result.devices} processes {result.processes} "
            f"compile {result.compile_seconds:.1f} s run {result.run_seconds:.1f} s"
        )
        # A batch that does not divide over the devices of several processes is an error.
        from diffgcl.sim.sharding import shard_batch_if_even

        try:
            shard_batch_if_even(np.zeros(3))
        except ValueError as err:
            print("uneven:", err)
    if distributed.is_leader():
        np.savez(args.out, *jax.tree.leaves(tree))
    distributed.barrier("written")
    return 0


if __name__ == "__main__":
    sys.exit(main())
