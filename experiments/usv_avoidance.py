"""USV obstacle avoidance learned from bags, end to end.

The built-in synthetic Odin-like bags (or ``--bags DIR --topics MAP``) → demonstrations
(ingestion) → hull identification → the demos in the task frame (approach course = +x, pole
kept) → rGCL on the identified hull with a learned cost on task features and an MDGPS policy on
the boat's observations → every policy rolled out from held-out situations (pole distance, the
boat's offset, heading, speed and the pole's radius drawn from the demos' ranges) on the
generator's **true** hull with sensor noise. References in the same run: MDGPS with the
hand-written cost (``expert``) and behaviour cloning of the recorded observations (``bc``).
Main run: set 2 (47 episodes, LiDAR); variant: radar-only observations on all 66, trained in a
process of its own beside the main run (one run alone keeps about one of the two cores busy;
``--serial`` runs them one after the other).

    python experiments/usv_avoidance.py --json runs/usv_avoidance.json [--out runs/usv]
    python experiments/usv_avoidance.py --fast          # a few short episodes, minutes

Figures (JSON): ``episodes`` (held-out rollouts judged), ``collision_rate``,
``return_to_course_rate``, ``clearance_ratio_vs_demos`` (median minimum clearance over the
demos'), ``expert_cost_collision_rate``, ``bc_collision_rate``, ``bc_return_to_course_rate``,
``radar_only_collision_rate``, ``wall_seconds``, and each method's full score; from situations of
wider ranges than the demos' (pole radius 0.2–1.5 m, the boat's offset 1.5× the demos' range),
``wider_collision_rate``, ``wider_return_to_course_rate``, ``wider_clearance_ratio_vs_demos``;
from the held-out situations with a second pole 120-180 m beyond the first, the same with
``two_poles_``; each also with ``expert_cost_`` and ``bc_`` in front.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import multiprocessing
import sys
import time
import traceback
from pathlib import Path

from diffgcl.cli.errors import guarded
from diffgcl.cli.usv import parse_margins


def fast_configs():
    from diffgcl.usv import fast_run_config

    main = fast_run_config()
    radar = dataclasses.replace(
        main,
        task=dataclasses.replace(main.task, sets=("1", "2"), observation="radar"),
        methods=("rgcl",),
    )
    return main, radar


def full_configs(seeds, heldout: int, heldout_seed: int = 1000):
    from diffgcl.usv import UsvRunConfig, UsvTaskConfig

    task = UsvTaskConfig()
    main = UsvRunConfig(task=task, seeds=tuple(seeds), heldout=heldout, heldout_seed=heldout_seed)
    radar = dataclasses.replace(
        main,
        task=dataclasses.replace(task, sets=("1", "2"), observation="radar"),
        methods=("rgcl",),
    )
    return main, radar


class _Labelled(io.TextIOBase):
    """A text stream that writes each line to ``stream`` behind ``label`` (the variant's process
    shares the terminal with the main run's)."""

    def __init__(self, stream, label: str):
        self.stream, self.label, self.pending = stream, label, ""

    def write(self, text: str) -> int:
        lines = (self.pending + text).split("\n")
        self.pending = lines.pop()
        for line in lines:
            self.stream.write(f"{self.label}{line}\n")
        self.stream.flush()
        return len(text)

    def flush(self) -> None:
        self.stream.flush()


def variant_summary(demos, config, manifest, truth, label: str) -> dict:
    """One variant's :func:`run_usv` summary, in a process of its own (spawned, so its JAX is its
    own); its printed lines carry ``label``."""
    sys.stdout = _Labelled(sys.__stdout__, label)
    from diffgcl.runtime import prepare_process

    prepare_process()
    from diffgcl.usv import run_usv

    return run_usv(demos, config, manifest=manifest, true_params=truth).summary


def warm_worker() -> None:
    """First thing in the variant's process, which starts before the main process reads the
    demos: it imports JAX, MJX and the pipeline meanwhile (seconds), so that the variant computes
    as soon as its demos arrive. Its ``XLA_FLAGS`` are the main process's (inherited)."""
    from diffgcl.runtime import prepare_process

    prepare_process()
    import diffgcl.usv  # noqa: F401


def variant_result(pending, name: str) -> dict:
    """The variant's summary (``pending``: its ``AsyncResult``), or ``{"error": ...}`` when its
    process failed (the main run's figures are written all the same)."""
    try:
        return pending.get()
    except Exception as error:  # the child's exception, re-raised here
        detail = "".join(traceback.format_exception_only(type(error), error)).strip()
        print(f"== {name} variant failed: {detail}", file=sys.stderr)
        return {"error": detail}


def headline(main: dict, radar: dict | None) -> dict:
    """The headline figures (the top-level JSON keys) from the runs' summaries."""
    rgcl = main.get("rgcl", {})
    out = {
        "episodes": rgcl.get("episodes"),
        "collision_rate": rgcl.get("collision_rate"),
        "return_to_course_rate": rgcl.get("return_to_course_rate"),
        "clearance_ratio_vs_demos": rgcl.get("clearance_ratio_vs_demos"),
        "expert_cost_collision_rate": main.get("expert", {}).get("collision_rate"),
        "expert_cost_return_to_course_rate": main.get("expert", {}).get("return_to_course_rate"),
        "bc_collision_rate": main.get("bc", {}).get("collision_rate"),
        "bc_return_to_course_rate": main.get("bc", {}).get("return_to_course_rate"),
    }
    for prefix, name in (("", "rgcl"), ("expert_cost_", "expert"), ("bc_", "bc")):
        for row in ("wider", "two_poles"):
            score = main.get(name, {}).get(row)
            if score is not None:
                for key in ("collision_rate", "return_to_course_rate", "clearance_ratio_vs_demos"):
                    out[f"{prefix}{row}_{key}"] = score.get(key)
    if radar is not None:
        out["radar_only_collision_rate"] = radar.get("rgcl", {}).get("collision_rate")
        out["radar_only_return_to_course_rate"] = radar.get("rgcl", {}).get("return_to_course_rate")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--fast", action="store_true", help="a few short episodes, few iterations")
    parser.add_argument("--bags", type=Path, default=None, help="your bags (default: built-in)")
    parser.add_argument("--topics", type=Path, default=None, help="topic map YAML for --bags")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--first-seed", type=int, default=0, help="training seeds start here")
    parser.add_argument(
        "--heldout-seed",
        type=int,
        default=1000,
        help="draws the held-out situations (1000: the report set; tune on another)",
    )
    parser.add_argument("--heldout", type=int, default=256, help="held-out situations")
    parser.add_argument("--no-radar", action="store_true", help="skip the radar-only variant")
    parser.add_argument(
        "--serial",
        action="store_true",
        help="run the radar-only variant after the main run, in this process (default: beside "
        "it, in a process of its own; twice the memory)",
    )
    parser.add_argument("--methods", default=None, help="of rgcl, expert, bc (default: all)")
    parser.add_argument("--conditions", type=int, default=None, help="use the first N demos")
    parser.add_argument(
        "--range-encoding",
        choices=("saturated", "metres"),
        default=None,
        help="how the policies read their range beams (default: the task's, saturated)",
    )
    parser.add_argument(
        "--train-extra",
        type=int,
        default=None,
        help="steps trained past the demos' window (UsvTaskConfig.train_extra)",
    )
    parser.add_argument(
        "--tail",
        type=int,
        default=None,
        help="steps recorded past each demo's window that GCL's monotonic and goal "
        "regularisers see, when GCL has them (UsvTaskConfig.tail; default 0: none)",
    )
    parser.add_argument(
        "--margins",
        type=parse_margins,
        default=None,
        help="clearance margins (m) of the learned cost's barriers, e.g. 5,10,15,20 "
        "(default: from the demos, UsvTaskConfig.proximity_margins)",
    )
    parser.add_argument(
        "--retrain",
        type=int,
        default=None,
        help="train a seed again with a new key, at most N more times, while its local "
        "controllers or its policy warn on their own training starts "
        "(UsvRunConfig.retrain_warned; default 1, with --fast 0)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        help="rGCL override a.b=value; cost=neural (or weighted, the default) picks the cost",
    )
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=None, help="plots (a new or own folder)")
    args = parser.parse_args(argv)

    from diffgcl.runtime import prepare_process

    side_by_side = not args.no_radar and not args.serial
    # The radar-only variant compiles in a process of its own beside this one.
    prepare_process(processes=2 if side_by_side else 1)
    pool = None
    if side_by_side:  # started first: its imports overlap this process's imports and ingestion
        pool = multiprocessing.get_context("spawn").Pool(1, initializer=warm_worker)
    try:
        return guarded(run_variants)(args, pool)
    finally:
        if pool is not None:
            pool.terminate()  # not left training on after a failed or interrupted main run


def run_variants(args, pool) -> int:
    """The main run here and the radar-only variant in ``pool`` (None: after the main run, in
    this process, or not at all with ``--no-radar``); the summary, plots and JSON."""
    from diffgcl.data.synth import true_params
    from diffgcl.usv import builtin_demos, load_bag_demos, run_usv, usv_rgcl

    t0 = time.perf_counter()
    if args.bags is not None:
        demos, manifest, truth = load_bag_demos(args.bags, args.topics), None, None
    else:
        demos, folder = builtin_demos(fast=args.fast)
        manifest, truth = folder / "manifest.json", true_params()
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    main_cfg, radar_cfg = (
        fast_configs() if args.fast else full_configs(seeds, args.heldout, args.heldout_seed)
    )
    if args.methods is not None:
        main_cfg = dataclasses.replace(main_cfg, methods=tuple(args.methods.split(",")))
    if args.conditions is not None:
        main_cfg = dataclasses.replace(
            main_cfg, task=dataclasses.replace(main_cfg.task, max_conditions=args.conditions)
        )
    task_changes = {
        "range_encoding": args.range_encoding,
        "train_extra": args.train_extra,
        "tail": args.tail,
        "proximity_margins": args.margins,
    }
    task_changes = {k: v for k, v in task_changes.items() if v is not None}
    main_cfg, radar_cfg = (
        dataclasses.replace(c, task=dataclasses.replace(c.task, **task_changes))
        for c in (main_cfg, radar_cfg)
    )
    if args.retrain is not None:
        main_cfg, radar_cfg = (
            dataclasses.replace(c, retrain_warned=args.retrain) for c in (main_cfg, radar_cfg)
        )
    if args.set:  # cost=neural|weighted picks the learned cost's form (diffgcl.usv.usv_rgcl)
        rgcl = usv_rgcl(args.set, fast=args.fast)
        main_cfg = dataclasses.replace(main_cfg, rgcl=rgcl)
        radar_cfg = dataclasses.replace(radar_cfg, rgcl=rgcl)
    radar_label = "== radar-only variant: sets " + ", ".join(radar_cfg.task.sets)
    if pool is not None:
        print(radar_label + ", in a process of its own (lines marked [radar])")
        beside = pool.apply_async(variant_summary, (demos, radar_cfg, manifest, truth, "[radar] "))
    print("== main run: " + ", ".join(main_cfg.task.sets) + f" ({main_cfg.task.observation})")
    run = run_usv(demos, main_cfg, manifest=manifest, true_params=truth)
    radar = None
    if pool is not None:
        radar = variant_result(beside, "radar-only")
        pool.close()
        pool.join()
    elif not args.no_radar:
        print(radar_label)
        radar = run_usv(demos, radar_cfg, manifest=manifest, true_params=truth).summary
    summary = {
        **headline(run.summary, radar),
        "wall_seconds": time.perf_counter() - t0,
        "fast": args.fast,
        "bags": str(args.bags) if args.bags else "built-in synthetic Odin-like",
        "main": run.summary,
        "radar_only": radar,
        "radar_beside_main": pool is not None,
    }
    print(json.dumps({k: v for k, v in summary.items() if not isinstance(v, dict)}, indent=1))
    if args.out is not None:
        from diffgcl.viz.usv import save_usv_plots

        print("plots:", ", ".join(str(p) for p in save_usv_plots(run, args.out)))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1, default=float))
        print(f"summary in {args.json}")
    return 1 if radar is not None and "error" in radar else 0


if __name__ == "__main__":
    sys.exit(main())
