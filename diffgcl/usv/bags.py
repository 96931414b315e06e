"""Where the USV task's demonstrations come from: the built-in synthetic Odin-like bags
(:mod:`diffgcl.data.synth`, written once into the cache) or a folder of your own bags with a topic
map (:func:`load_bag_demos`), and the pole radius of each episode (:func:`pole_radii`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from diffgcl.data.demos import DemoError, DemoSet

BUILTIN_SYNTH = {
    # The seed's Odin sets (19 episodes without LiDAR, 47 with), each recorded until the boat is
    # back on its course line and has held it a while (end margin past the pole), so that a window
    # around the pass holds the return too.
    "full": dict(end_margin_m=(170.0, 230.0), max_duration_s=160.0),
    "fast": dict(episodes=(3, 5), approach_m=(110.0, 130.0), end_margin_m=(120.0, 140.0)),
}


def builtin_bags(*, fast: bool = False, verbose: bool = True) -> Path:
    """The synthetic Odin-like bag set (the seed's layout: set 1, 19 episodes without LiDAR; set 2,
    47 with it; ``fast``: 3 + 5 short episodes), generated once into the cache."""
    from diffgcl.data.synth import SynthConfig, synthesize
    from diffgcl.runtime import cache_root

    name = "fast" if fast else "full"
    folder = cache_root() / "bags" / f"odin-usv-{name}"
    if not (folder / "manifest.json").is_file():
        if verbose:
            print(f"writing the synthetic Odin-like bags into {folder}")
        synthesize(folder, SynthConfig(**BUILTIN_SYNTH[name]), overwrite=True)
    return folder


def load_bag_demos(folder: Path, topics: Path | None = None, *, verbose: bool = True) -> DemoSet:
    """Every bag below ``folder`` ingested with the topic map ``topics`` (default: the Odin-like
    one). Nothing is written (a user's folder is never touched)."""
    from diffgcl.data.ingest import ingest_bags
    from diffgcl.data.topics import load_topic_map

    paths = bag_paths(folder)
    if verbose:
        print(f"ingesting {len(paths)} bags from {folder}")
    return ingest_bags(paths, load_topic_map(topics))


def builtin_demos(*, fast: bool = False, verbose: bool = True) -> tuple[DemoSet, Path]:
    """The built-in bags (:func:`builtin_bags`) ingested, cached beside them; returns the demos
    and the bag folder (whose ``manifest.json`` has the generator's truth)."""
    folder = builtin_bags(fast=fast, verbose=verbose)
    cached = folder.parent / f"{folder.name}-demos"
    if (cached / "demos.npz").is_file():
        return DemoSet.load(cached), folder
    demos = load_bag_demos(folder, verbose=verbose)
    demos.save(cached)
    return demos, folder


def bag_paths(folder: Path) -> list[Path]:
    """Every bag below ``folder`` (ROS1 ``.bag`` files and ROS2 bag folders), sorted."""
    folder = Path(folder)
    found = sorted(folder.rglob("*.bag")) + sorted(
        m.parent for m in folder.rglob("metadata.yaml") if m.parent != folder
    )
    if not found:
        raise DemoError(f"{folder}: no ROS bags below this folder")
    return found


def pole_radii(demos: DemoSet, default: float, manifest: Path | None = None) -> np.ndarray:
    """The pole radius of each episode [N] (m): from the episode's metadata (``pole_radius`` or
    ``radius``, e.g. a key of the start marker), else from a synthetic set's ``manifest.json``
    (matched by bag file and start time), else ``default``."""
    truth = {}
    if manifest is not None and Path(manifest).is_file():
        for e in json.loads(Path(manifest).read_text())["episodes"]:
            truth[(Path(e["bag"]).name, round(float(e["t_start"]), 1))] = e["profile"][
                "pole_radius"
            ]
    radii = []
    for meta in demos.episodes:
        value = meta.get("pole_radius", meta.get("radius"))
        if value is None:
            value = truth.get((Path(meta.get("source", "")).name, round(meta["t_start"], 1)))
        radii.append(float(default if value is None else value))
    return np.asarray(radii)
