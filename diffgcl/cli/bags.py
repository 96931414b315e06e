"""``diffgcl bags inspect|template|convert|synth``: the ROS-bag commands of the CLI.

:func:`register` adds the ``bags`` command to an ``argparse`` sub-parser collection; the module
also runs on its own (``python -m diffgcl.cli.bags bags inspect PATH``). The user's guide is
``docs/bags.md``.

* ``bags inspect PATH... [--topics MAP.yaml]`` — topics, types, counts, rates, on-change or
  periodic, gaps, header-stamp order and latency, then the problems found.
* ``bags template BAG [--out MAP.yaml]`` — a starting topic map from what inspect found.
* ``bags convert PATH... --out DIR [--topics MAP.yaml] [--overwrite]`` — ingest into a demo
  dataset (:mod:`diffgcl.data.demos` format), with a progress bar; warnings go to stderr.
* ``bags synth --out DIR [--layout odin|other]`` — write a synthetic data set
  (:mod:`diffgcl.data.synth`).

Output folders follow :func:`diffgcl.io.write_folder`: a non-empty folder that is not this
command's output is refused unless ``--overwrite`` (which replaces only the entries of the same
name); ``--out`` naming a file is an error. Bad input prints one line
``error: FILE: topic T, t=...: reason`` to stderr and exits with status 2; nothing is written.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

from diffgcl.cli.errors import guarded


def register(subparsers) -> argparse.ArgumentParser:
    """Add ``bags`` (with ``inspect``, ``convert``, ``synth``) to ``subparsers``."""
    bags = subparsers.add_parser("bags", help="ROS bags: inspect, convert to demos, synthesise")
    sub = bags.add_subparsers(dest="bags_command", required=True)

    p = sub.add_parser("inspect", help="topics, types, rates, gaps, stamp order of bags")
    p.add_argument("paths", nargs="+", help=".bag files (ROS1) or ROS2 bag folders")
    p.add_argument(
        "--topics", default=None, help="topic map YAML: its commands and markers are on change"
    )
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("template", help="write a starting topic map for a bag")
    p.add_argument("path", help="a .bag file (ROS1) or a ROS2 bag folder")
    p.add_argument("--out", default=None, help="YAML file to write (default: print it)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=cmd_template)

    p = sub.add_parser("convert", help="ingest bags into a demonstration dataset")
    p.add_argument("paths", nargs="+", help=".bag files (ROS1) or ROS2 bag folders")
    p.add_argument("--out", required=True, help="output dataset folder (see --overwrite)")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="write into a non-empty folder that is not a dataset (same-named entries replaced)",
    )
    p.add_argument("--topics", default=None, help="topic map YAML (default: the Odin-like map)")
    p.add_argument("--dt", type=float, default=None, help="grid step in s (default: the hull's)")
    p.add_argument("--horizon", type=int, default=None, help="pad/crop episodes to T steps")
    p.add_argument("--no-observations", action="store_true", help="skip range-sensor reduction")
    p.add_argument("--quiet", action="store_true", help="no progress bar, no warnings")
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("synth", help="write synthetic bags (simulated operator)")
    p.add_argument("--out", required=True, help="output folder (see --overwrite)")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="write into a non-empty folder that is not a synthetic set",
    )
    p.add_argument(
        "--layout",
        default="odin",
        choices=("odin", "other"),
        help="odin: the Odin-like bags; other: another boat's layout (GNSS latency, NED "
        "odometry, radar point cloud with sea clutter, percent/degree commands, one bag per "
        "set with repositioning legs, no markers, no obstacle topic)",
    )
    p.add_argument(
        "--markers",
        default=None,
        choices=("keyvalue", "id", "none"),
        help="episode markers (default: keyvalue for odin, none for other)",
    )
    p.add_argument(
        "--format", default="ros1", choices=("ros1", "ros2-sqlite3", "ros2-mcap"), dest="fmt"
    )
    p.add_argument("--bag-per", default=None, choices=("episode", "set"))
    p.add_argument(
        "--episodes-per-set",
        type=int,
        nargs=2,
        default=None,
        metavar=("SET1", "SET2"),
        help="episodes in set 1 (no LiDAR) and set 2 (LiDAR); default 19 47 (the seed's) for "
        "odin, 3 3 for other",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--short", action="store_true", help="short episodes (start 60-80 m from the pole)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_synth)
    return bags


def _bag_paths(paths: list[str]) -> list[Path]:
    out = []
    for p in map(Path, paths):
        if p.is_dir() and not (p / "metadata.yaml").exists():
            # A folder of bags (e.g. the output of `bags synth`): every bag below it, sorted.
            found = sorted(p.rglob("*.bag")) + sorted(
                m.parent for m in p.rglob("metadata.yaml") if m.parent != p
            )
            out.extend(found if found else [p])
        else:
            out.append(p)
    return out


def cmd_inspect(args) -> int:
    from diffgcl.data.bags import inspect_bag
    from diffgcl.data.topics import load_topic_map

    on_change: set[str] = set()
    if args.topics is not None:
        tm = load_topic_map(args.topics)
        on_change = {spec.topic for spec in (tm.commands, tm.markers) if spec is not None}
    for path in _bag_paths(args.paths):
        print(inspect_bag(path, on_change).format_text())
    return 0


def cmd_template(args) -> int:
    from diffgcl.data.template import template_from_bag
    from diffgcl.io import check_output_file, write_file_atomically

    if args.out is not None:
        check_output_file(args.out, args.overwrite)
    text = template_from_bag(args.path)
    if args.out is None:
        print(text)
    else:
        write_file_atomically(args.out, text, args.overwrite)
        print(f"{args.out}: topic map drafted from {args.path}; check its TODOs")
    return 0


def cmd_convert(args) -> int:
    from tqdm import tqdm

    from diffgcl.data.ingest import IngestConfig, IngestWarning, convert
    from diffgcl.data.synth import hull_dt
    from diffgcl.data.topics import load_topic_map

    topic_map = load_topic_map(args.topics)
    config = IngestConfig(
        dt=args.dt if args.dt is not None else hull_dt(),
        horizon=args.horizon,
        observations=not args.no_observations,
    )
    paths = _bag_paths(args.paths)
    progress = None if args.quiet else (lambda xs: tqdm(xs, desc="bags", unit="bag"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", IngestWarning)
        demos = convert(paths, args.out, topic_map, config, progress, args.overwrite)
    if not args.quiet:
        for w in caught:
            if issubclass(w.category, IngestWarning):
                print(f"warning: {w.message}", file=sys.stderr)
    print(
        f"{args.out}: {demos.num_episodes} episodes, T={demos.horizon}, dt={demos.dt}, "
        f"valid steps {int(demos.mask.sum())}/{demos.mask.size}"
    )
    return 0


def cmd_synth(args) -> int:
    from tqdm import tqdm

    from diffgcl.data.synth import SynthConfig, other_boat_config, synthesize

    kwargs: dict = {"fmt": args.fmt, "seed": args.seed}
    if args.short:
        kwargs.update(approach_m=(60.0, 80.0), end_margin_m=(30.0, 40.0))
    if args.episodes_per_set is not None:
        kwargs["episodes"] = tuple(args.episodes_per_set)
    if args.bag_per is not None:
        kwargs["bag_per"] = args.bag_per
    if args.markers is not None:
        kwargs["markers"] = args.markers
    config = other_boat_config(**kwargs) if args.layout == "other" else SynthConfig(**kwargs)
    progress = None if args.quiet else (lambda xs: tqdm(xs, desc="pieces", unit="piece"))
    result = synthesize(args.out, config, progress, args.overwrite)
    print(f"{result.out}: {len(result.episodes)} episodes in {len(result.bags)} bags ({args.fmt})")
    return 0


def run(args) -> int:
    """Run a parsed ``bags`` command (returns its exit status)."""
    return args.func(args)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="diffgcl")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    from diffgcl.runtime import prepare_process

    prepare_process()
    return guarded(run)(args)


if __name__ == "__main__":
    sys.exit(main())
