"""Driver for tests/test_distributed.py: host-side staged simulation of an MJX model (the
slider of tests/test_trajopt.py) in whatever process layout the environment describes. Each
process writes the Jacobians and observations it computed for the same batch to OUT_<i>.npz.

    python tests/multiprocess_staged.py MODEL.xml OUT
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

from diffgcl import distributed  # noqa: E402


def staged_outputs(model: Path):
    """The staged simulator's Jacobians and observations of ``model`` at fixed random states
    and actions (3 trajectories: not a multiple of the devices, so the chunk is padded)."""
    import numpy as np

    from diffgcl import api
    from diffgcl.algorithms.staged import staged_simulator

    env = api.load_model(model, x0=np.array([[0.3, 0.0]]), horizon=5)
    rng = np.random.default_rng(0)
    X = rng.normal(size=(3, env.horizon + 1, env.dX))
    U = rng.normal(size=(3, env.horizon, env.dU))
    sim = staged_simulator(env)
    A, B = sim.jacobians(X, U)
    return {"A": np.asarray(A), "B": np.asarray(B), "O": np.asarray(sim.observations(X))}


def main() -> int:
    import numpy as np

    model, out = Path(sys.argv[1]), sys.argv[2]
    distributed.join(distributed.process_settings(), heartbeat_timeout_s=20)
    from diffgcl.runtime import prepare_process

    prepare_process()
    np.savez(f"{out}_{jax.process_index()}.npz", **staged_outputs(model))
    distributed.barrier("written")
    return 0


if __name__ == "__main__":
    sys.exit(main())
