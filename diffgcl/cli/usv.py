"""``diffgcl usv``: USV obstacle avoidance learned from bags, end to end (argument parsing and
printing; the pipeline is :func:`diffgcl.usv.run_usv`, the pictures
:func:`diffgcl.viz.usv.save_usv_plots`).

    diffgcl usv [--bags DIR --topics MAP] [--sets 2] [--observation full|radar|ranges]
                [--range-encoding saturated|metres] [--train-extra 150] [--tail 0]
                [--margins 5,10,15,20] [--seeds 1] [--retrain 1]
                [--heldout 256] [--fast]
                [--set a.b=value] [--out runs/usv]

Without ``--bags`` it runs on the built-in synthetic Odin-like bags (written once into the
cache) and judges the policies on the generator's true hull; with them, on the identified hull.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path


def parse_margins(text: str) -> tuple[float, ...]:
    """``"5,10,20,30"`` -> (5.0, 10.0, 20.0, 30.0), for ``--margins`` (``UsvTaskConfig.
    proximity_margins``); an argparse type, so a bad list is a usage error that names it."""
    try:
        margins = tuple(float(d) for d in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"margins {text!r}: give clearances in m separated by commas, e.g. 5,10,20,30"
        ) from None
    if min(margins) <= 0 or list(margins) != sorted(set(margins)):
        raise argparse.ArgumentTypeError(
            f"margins {text!r}: the clearances must be > 0 and increasing, e.g. 5,10,20,30"
        )
    return margins


def run_config(args):
    """The :class:`~diffgcl.usv.UsvRunConfig` that ``diffgcl usv`` runs for ``args``:
    the default scale, or :func:`~diffgcl.usv.fast_run_config` with ``--fast``; the
    options given on the command line (``--set`` included) override either."""
    from diffgcl.usv import METHODS, UsvRunConfig, UsvTaskConfig, fast_run_config, usv_rgcl

    task = UsvTaskConfig(
        sets=tuple(args.sets.split(",")),
        observation=args.observation,
        range_encoding=args.range_encoding,
    )
    base = fast_run_config(task) if args.fast else UsvRunConfig(task=task)
    task = base.task
    if args.train_extra is not None:
        task = dataclasses.replace(task, train_extra=args.train_extra)
    if args.tail is not None:
        task = dataclasses.replace(task, tail=args.tail)
    if args.margins is not None:
        task = dataclasses.replace(task, proximity_margins=args.margins)
    methods = tuple(m for m in args.methods.split(",") if m)
    return dataclasses.replace(
        base,
        task=task,
        rgcl=usv_rgcl(args.set, fast=args.fast),
        methods=methods or METHODS,
        seeds=tuple(range(args.seed, args.seed + args.seeds)),
        heldout=args.heldout if args.heldout is not None else base.heldout,
        retrain_warned=args.retrain if args.retrain is not None else base.retrain_warned,
    )


def usv_command(args) -> int:
    from diffgcl.io import check_output_folder
    from diffgcl.usv import builtin_demos, load_bag_demos, run_usv
    from diffgcl.viz.usv import USV_FOLDER, save_usv_plots

    check_output_folder(args.out, USV_FOLDER, args.overwrite)
    if args.topics is not None and args.bags is None:
        raise SystemExit("diffgcl usv: --topics needs --bags")
    config = run_config(args)
    if args.bags is not None:
        demos, manifest, truth = load_bag_demos(args.bags, args.topics), None, None
    else:
        from diffgcl.data.synth import true_params

        demos, folder = builtin_demos(fast=args.fast)
        manifest, truth = folder / "manifest.json", true_params()
    run = run_usv(demos, config, manifest=manifest, true_params=truth)
    paths = save_usv_plots(run, args.out, args.overwrite)
    brief = {k: v for k, v in run.summary.items() if not isinstance(v, (dict, list))}
    print(json.dumps(brief, indent=1, default=float))
    print("written: " + ", ".join(str(p) for p in paths))
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("usv", help="USV obstacle avoidance from bags (rGCL + MDGPS)")
    p.add_argument("--bags", type=Path, default=None, help="folder of your bags")
    p.add_argument("--topics", type=Path, default=None, help="topic map YAML (docs/bags.md)")
    p.add_argument("--sets", default="2", help="bag sets to use, comma-separated (default 2)")
    p.add_argument("--observation", choices=("full", "radar", "ranges"), default="full")
    p.add_argument(
        "--range-encoding",
        choices=("saturated", "metres"),  # diffgcl.envs.usv.RANGE_ENCODINGS
        default="saturated",
        help="how the policy reads its range beams (default saturated: metres near, alike far)",
    )
    p.add_argument(
        "--train-extra",
        type=int,
        default=None,
        help="steps trained past the demos' window (default 150, with --fast 40)",
    )
    p.add_argument(
        "--tail",
        type=int,
        default=None,
        help="steps recorded past each demo's window that GCL's monotonic and goal "
        "regularisers see, when GCL has them (default 0: none)",
    )
    p.add_argument(
        "--margins",
        type=parse_margins,
        default=None,
        help="clearance margins (m) of the learned cost's barriers (default: from the demos' "
        "median clearance, 5,10,15,20 on the built-in bags)",
    )
    p.add_argument(
        "--retrain",
        type=int,
        default=None,
        help="train a seed again with a new key, at most N more times, while its local "
        "controllers or its policy hit the pole, pass too close (the policy) or end off course "
        "from their own training starts (default 1, with --fast 0)",
    )
    p.add_argument("--methods", default="rgcl,expert,bc", help="of rgcl, expert, bc")
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--seed", type=int, default=0, help="first seed")
    p.add_argument(
        "--heldout", type=int, default=None, help="held-out situations to judge (256, --fast 32)"
    )
    p.add_argument("--fast", action="store_true", help="few short episodes, few iterations")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        help="rGCL override a.b=value; cost=neural (or weighted, the default) picks the cost",
    )
    p.add_argument("--out", type=Path, default=Path("runs/usv"))
    p.add_argument("--overwrite", action="store_true", help="write into a foreign folder")
    p.set_defaults(func=usv_command)
