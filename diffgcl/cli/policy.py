"""``diffgcl bc DEMOS``: behaviour cloning of a demonstration folder, the baseline of the global
policy. Argument parsing and printing; the fit is :func:`diffgcl.algorithms.bc.clone_demos`, the
evaluation :func:`diffgcl.eval.policy.evaluate_policy`, the files
:func:`diffgcl.policies.io.save_policy`.

    diffgcl bc DEMOS [--seeds 4] [--out DIR] [--steps 3000] [--hidden 64,64]

writes ``DIR/seed_<s>/policy.{npz,json}``, ``DIR/summary.json`` (success of each seed's
noise-free rollouts from the env's conditions) and ``DIR/policy_rollouts.png``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path


def bc_command(args) -> int:
    import dataclasses

    import jax
    import jax.numpy as jnp
    import numpy as np

    from diffgcl.algorithms.bc import BCConfig, clone_demos
    from diffgcl.data.demos import DemoSet
    from diffgcl.envs import make_env
    from diffgcl.eval.policy import evaluate_policy
    from diffgcl.policies.io import save_policy
    from diffgcl.policies.network import PolicyConfig
    from diffgcl.viz import plots

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    demos = DemoSet.load(args.demos)
    env = make_env(demos.env)
    hidden = tuple(int(h) for h in args.hidden.split(",") if h)
    config = BCConfig(network=PolicyConfig(hidden=hidden))
    config = dataclasses.replace(config, fit=dataclasses.replace(config.fit, n_steps=args.steps))
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    out = args.out or Path("runs") / f"bc-{demos.env}-{time.strftime('%Y%m%d-%H%M%S')}"
    print(f"behaviour cloning of {demos.num_episodes} demos ({demos.env}), seeds {seeds} -> {out}")
    policy, params = clone_demos(demos, env, config, seeds)
    x0 = jnp.asarray(env.initial_states())
    rates = []
    for i, seed in enumerate(seeds):
        p = jax.tree.map(lambda a, i=i: a[i], params)
        result = evaluate_policy(env, policy, p, x0, jax.random.PRNGKey(seed))
        rates.append(result["success"].tolist())
        save_policy(out / f"seed_{seed}", policy, p, method="bc", seed=seed, demos=str(args.demos))
    success = np.asarray(rates)
    summary = {
        "demos": str(args.demos),
        "seeds": seeds,
        "success": success.tolist(),
        "success_rate": float(success.all(-1).mean()),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    p0 = jax.tree.map(lambda a: a[0], params)
    plots.policy_paths(env, policy, p0, {"training": x0}, out / "policy_rollouts.png", title="BC")
    rate = summary["success_rate"]
    print(f"noise-free success from the env's {x0.shape[0]} conditions: {rate:.2f}")
    return 0


def register(subparsers) -> None:
    bc = subparsers.add_parser("bc", help="behaviour cloning of a demo folder (baseline policy)")
    bc.add_argument("demos", type=Path, help="demo folder (demos.npz + meta.json)")
    bc.add_argument("--seeds", type=int, default=4)
    bc.add_argument("--first-seed", type=int, default=0)
    bc.add_argument("--steps", type=int, default=3000, help="Adam steps of the fit")
    bc.add_argument("--hidden", default="64,64", help="hidden layer widths")
    bc.add_argument("--out", type=Path, default=None)
    bc.add_argument("--x64", action="store_true")
    bc.set_defaults(func=bc_command)
