"""Each rGCL iteration's USV policy on held-out situations, beside its learned cost.

The USV run judges the last iteration's global policy; this script judges every iteration's, per
training seed, so that one can see how a figure moves while the run trains. Per iteration and
seed it prints the policy's mean learned cost (under the seed's final cost) from the demos'
starts over the training window and over the window plus ``--extra`` steps (on the identified
hull, no true cost), then on held-out situations on the true hull with sensor noise: on course
at the end of the evaluation horizon, collisions and the clearance ratio; and for the local
controllers, their samples' median and largest true cost and how many C-steps failed.

    python experiments/usv_iterations.py --seeds 2 --heldout 64 --heldout-seed 7 \
        --json runs/usv_iterations.json

Defaults: the tuning split (held-out seed 7, 64 situations), training seeds 0 and 1, the USV
preset (``--set a.b=value`` overrides it).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--heldout", type=int, default=64)
    parser.add_argument("--heldout-seed", type=int, default=7)
    parser.add_argument("--extra", type=int, default=150, help="steps judged past the window")
    parser.add_argument(
        "--train-extra", type=int, default=None, help="steps trained past the window (150)"
    )
    parser.add_argument("--set", action="append", default=[], help="rGCL override a.b=value")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    from diffgcl.runtime import prepare_process

    prepare_process()

    import jax
    import jax.numpy as jnp
    import numpy as np

    from diffgcl import usv as U
    from diffgcl.algorithms.presets import usv as usv_preset
    from diffgcl.algorithms.presets import with_overrides
    from diffgcl.algorithms.rgcl import make_train, policy_learned_costs
    from diffgcl.data.synth import true_params

    t0 = time.perf_counter()
    rgcl_config = with_overrides(usv_preset(), args.set) if args.set else usv_preset()
    demos, folder = U.builtin_demos()
    config = U.UsvRunConfig(
        task=U.UsvTaskConfig(
            train_extra=U.UsvTaskConfig.train_extra
            if args.train_extra is None
            else args.train_extra
        ),
        methods=(),
        heldout=args.heldout,
        heldout_seed=args.heldout_seed,
        eval_extra=args.extra,
    )
    base = U.run_usv(
        demos, config, manifest=folder / "manifest.json", true_params=true_params(), verbose=False
    )
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    rgcl = make_train(rgcl_config, base.train_env)
    batch = U.demo_batch_pooled(base.demos, env=base.env)
    print(f"rGCL + MDGPS, seeds {seeds}", flush=True)
    (state, metrics), seconds = U.run_over_seeds(rgcl.train, seeds, batch)

    def learned(env):
        fn = jax.vmap(lambda c, p: policy_learned_costs(rgcl, env, c, p))
        params = jax.tree.map(jnp.asarray, (state.cost.params, metrics.policy_params))
        return np.asarray(jax.jit(fn)(*params)).mean(axis=-1)  # [S, I]

    window = learned(base.env)
    longer = learned(dataclasses.replace(base.env, horizon=base.env.horizon + args.extra))
    demo_clearance = U.score_rollouts(base.env, base.demos.X, base.demos.X)[
        "demo_min_clearance_median_m"
    ]
    eval_key = jax.random.PRNGKey(args.heldout_seed + 1)
    keys = jnp.stack([jax.random.fold_in(eval_key, s) for s in range(len(seeds))])
    rows = []
    true_cost = np.asarray(metrics.gps.cost)  # [S, I, G, C]
    failed = np.asarray(metrics.gps.c_step_failed).sum(axis=(2, 3))  # [S, I]
    print(
        "iteration  seed  learned cost (window / +extra)  on course at the end  collisions  "
        "clearance ÷ demos  samples' true cost (median / max)  failed C-steps"
    )
    for it in range(window.shape[1]):
        params = jax.tree.map(lambda a, i=it: jnp.asarray(a[:, i]), metrics.policy_params)
        tracks = U.policy_tracks(
            base.env_true, rgcl.policy_phases.policy, params, base.x0_heldout, keys
        )
        figures = U.per_seed_figures(base.env_true, tracks, demo_clearance)
        for k, seed in enumerate(seeds):
            row = {
                "iteration": it,
                "seed": seed,
                "learned_cost_window": float(window[k, it]),
                "learned_cost_longer": float(longer[k, it]),
                **{name: values[k] for name, values in figures.items()},
                "sample_true_cost_median": float(np.median(true_cost[k, it])),
                "sample_true_cost_max": float(np.max(true_cost[k, it])),
                "failed_c_steps": int(failed[k, it]),
            }
            rows.append(row)
            print(
                f"{it:9d}  {seed:4d}  {row['learned_cost_window']:12.0f} / "
                f"{row['learned_cost_longer']:<12.0f}  {row['return_to_course_rate']:20.3f}  "
                f"{row['collision_rate']:10.3f}  {row['clearance_ratio_vs_demos']:17.2f}  "
                f"{row['sample_true_cost_median']:10.3g} / {row['sample_true_cost_max']:<10.3g}"
                f"  {row['failed_c_steps']:14d}",
                flush=True,
            )
    summary = {
        "seeds": seeds,
        "heldout": args.heldout,
        "heldout_seed": args.heldout_seed,
        "training_horizon": base.train_env.horizon,
        "evaluation_horizon": base.env.horizon + args.extra,
        "rgcl_seconds": seconds,
        "wall_seconds": time.perf_counter() - t0,
        "rows": rows,
    }
    print(f"wall time {summary['wall_seconds']:.0f} s")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1))
        print(f"summary in {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
