"""Does a training seed's *policy*, rolled out from its own training starts, show a close run?

The retraining of warned seeds (``UsvRunConfig.retrain_warned``) judges a seed by its local
controllers on the demos' starts. The policy is what sails, and it can pass closer than they do.
This trains the default rGCL + MDGPS (main run only) and prints, per training seed, the
controllers' figures on the training starts, the policy's on the same starts (identified hull,
sensor noise on: training data only) and the policy's on the held-out situations (true hull)::

    python experiments/usv_policy_on_training_starts.py [--seeds 2] [--first-seed 0]
"""

from __future__ import annotations

import argparse
import json
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--heldout", type=int, default=256)
    parser.add_argument("--heldout-seed", type=int, default=1000)
    args = parser.parse_args(argv)

    from diffgcl.runtime import prepare_process

    prepare_process()
    import jax
    import jax.numpy as jnp

    from diffgcl.algorithms.usv import (
        UsvRunConfig,
        builtin_demos,
        per_seed_figures,
        policy_tracks,
        run_usv,
    )
    from diffgcl.data.synth import true_params

    demos, folder = builtin_demos()
    seeds = tuple(range(args.first_seed, args.first_seed + args.seeds))
    config = UsvRunConfig(
        seeds=seeds, methods=("rgcl",), heldout=args.heldout, heldout_seed=args.heldout_seed
    )
    run = run_usv(demos, config, manifest=folder / "manifest.json", true_params=true_params())
    policy, params = run.policies["rgcl"]
    env = run.train_env
    keys = jnp.stack([jax.random.fold_in(jax.random.PRNGKey(7), s) for s in seeds])
    tracks = policy_tracks(env, policy, params, env.initial_states(), keys)
    demo_m = run.summary["rgcl"]["demo_min_clearance_median_m"]
    out = {
        "seeds": list(seeds),
        "controllers_on_training_starts": run.summary["rgcl"]["controllers_on_demo_starts"][
            "per_seed"
        ],
        "policy_on_training_starts": per_seed_figures(run.env, tracks, demo_m),
        "policy_heldout": run.summary["rgcl"]["per_seed"],
        "kept_attempts": {k: r["kept"] for k, r in run.summary["rgcl"]["attempts"].items()},
    }
    print(json.dumps(out, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
