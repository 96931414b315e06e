"""``diffgcl bags inspect|convert|synth``: the ROS-bag commands of the CLI.

:func:`register` adds the ``bags`` command to an ``argparse`` sub-parser collection; the module
also runs on its own (``python -m diffgcl.cli.bags bags inspect PATH``).

* ``bags inspect PATH...`` — topics, types, message counts, rates, largest gaps, duration.
* ``bags convert PATH... --out DIR [--topics MAP.yaml]`` — ingest into a demo dataset
  (:mod:`diffgcl.data.demos` format), with a progress bar; warnings go to stderr.
* ``bags synth --out DIR`` — write the Odin-like synthetic data set (:mod:`diffgcl.data.synth`).

Bad input prints one line ``error: FILE: topic T, t=...: reason`` to stderr and exits with
status 2; nothing is written then.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

EXIT_BAD_INPUT = 2


def register(subparsers) -> argparse.ArgumentParser:
    """Add ``bags`` (with ``inspect``, ``convert``, ``synth``) to ``subparsers``."""
    bags = subparsers.add_parser("bags", help="ROS bags: inspect, convert to demos, synthesise")
    sub = bags.add_subparsers(dest="bags_command", required=True)

    p = sub.add_parser("inspect", help="topics, types, rates, gaps and duration of bags")
    p.add_argument("paths", nargs="+", help=".bag files (ROS1) or ROS2 bag folders")
    p.set_defaults(func=_guarded(cmd_inspect))

    p = sub.add_parser("convert", help="ingest bags into a demonstration dataset")
    p.add_argument("paths", nargs="+", help=".bag files (ROS1) or ROS2 bag folders")
    p.add_argument("--out", required=True, help="output dataset folder (replaced atomically)")
    p.add_argument("--topics", default=None, help="topic map YAML (default: the Odin-like map)")
    p.add_argument("--dt", type=float, default=None, help="grid step in s (default: the hull's)")
    p.add_argument("--horizon", type=int, default=None, help="pad/crop episodes to T steps")
    p.add_argument("--no-observations", action="store_true", help="skip range-sensor reduction")
    p.add_argument("--quiet", action="store_true", help="no progress bar, no warnings")
    p.set_defaults(func=_guarded(cmd_convert))

    p = sub.add_parser("synth", help="write Odin-like synthetic bags (simulated operator)")
    p.add_argument("--out", required=True, help="output folder (replaced atomically)")
    p.add_argument(
        "--format", default="ros1", choices=("ros1", "ros2-sqlite3", "ros2-mcap"), dest="fmt"
    )
    p.add_argument("--bag-per", default="episode", choices=("episode", "set"))
    p.add_argument(
        "--episodes-per-set",
        type=int,
        nargs=2,
        default=(19, 47),
        metavar=("SET1", "SET2"),
        help="episodes in set 1 (no LiDAR) and set 2 (LiDAR); the seed had 19 and 47",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--short", action="store_true", help="short episodes (start 60-80 m from the pole)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_guarded(cmd_synth))
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

    for path in _bag_paths(args.paths):
        print(inspect_bag(path).format_text())
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
        demos = convert(paths, args.out, topic_map, config, progress)
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

    from diffgcl.data.synth import SynthConfig, synthesize

    kwargs = {}
    if args.short:
        kwargs = {"approach_m": (60.0, 80.0), "end_margin_m": (30.0, 40.0)}
    config = SynthConfig(
        episodes=tuple(args.episodes_per_set),
        fmt=args.fmt,
        bag_per=args.bag_per,
        seed=args.seed,
        **kwargs,
    )
    progress = None if args.quiet else (lambda xs: tqdm(xs, desc="episodes", unit="ep"))
    result = synthesize(args.out, config, progress)
    print(f"{result.out}: {len(result.episodes)} episodes in {len(result.bags)} bags ({args.fmt})")
    return 0


def _guarded(command):
    """``command`` with bad input turned into one line on stderr and exit status 2."""

    def guarded(args) -> int:
        from diffgcl.data.bags import BagError
        from diffgcl.data.demos import DemoError
        from diffgcl.data.topics import TopicMapError

        try:
            return command(args)
        except (BagError, TopicMapError, DemoError) as err:
            print(f"error: {err}", file=sys.stderr)
            return EXIT_BAD_INPUT

    guarded.__name__ = command.__name__
    return guarded


def run(args) -> int:
    """Run a parsed ``bags`` command (returns its exit status)."""
    return args.func(args)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="diffgcl")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    from diffgcl.runtime import enable_compilation_cache

    enable_compilation_cache()
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
