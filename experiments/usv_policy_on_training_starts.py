"""Does a training seed's *policy*, rolled out from its own training starts, show a close run?

The retraining of warned seeds (``UsvRunConfig.retrain_warned``) judges a seed by its local
controllers and by its policy on the demos' starts (the policy is what sails, and it can pass
closer than they do). This trains the default rGCL + MDGPS (main run only) and prints, per
training seed, the controllers' figures on the training starts, the policy's on the same starts
(identified hull, sensor noise on: training data only) and the policy's on the held-out
situations (true hull), to compare what the retraining sees with what is judged::

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
    from diffgcl.data.synth import true_params
    from diffgcl.usv import UsvRunConfig, builtin_demos, run_usv

    demos, folder = builtin_demos()
    seeds = tuple(range(args.first_seed, args.first_seed + args.seeds))
    config = UsvRunConfig(
        seeds=seeds, methods=("rgcl",), heldout=args.heldout, heldout_seed=args.heldout_seed
    )
    run = run_usv(demos, config, manifest=folder / "manifest.json", true_params=true_params())
    rgcl = run.summary["rgcl"]
    out = {
        "seeds": list(seeds),
        "controllers_on_training_starts": rgcl["controllers_on_demo_starts"]["per_seed"],
        "policy_on_training_starts": rgcl["policy_on_demo_starts"]["per_seed"],
        "policy_heldout": rgcl["per_seed"],
        "kept_attempts": {k: r["kept"] for k, r in rgcl["attempts"].items()},
    }
    print(json.dumps(out, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
