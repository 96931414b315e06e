"""A synthetic bag set on disk: :func:`synthesize` simulates every episode, records it into bags
and writes the set's ``manifest.json`` (the true metadata of every episode and the true hull
parameters). The output folder follows :func:`diffgcl.io.write_folder` (kind
:data:`SYNTH_FOLDER`)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from diffgcl.data.bags import FORMATS, BagWriter, bag_name
from diffgcl.data.synth.config import LAYOUT_TOPICS, NS, SynthConfig
from diffgcl.data.synth.operator_model import (
    TRUE_FACTORS,
    OperatorProfile,
    draw_profiles,
    hull_dt,
    simulate,
    true_params,
)
from diffgcl.data.synth.recording import Recording, episode_messages, write_messages
from diffgcl.data.synth.scenes import repositioning_leg, separate_poles
from diffgcl.data.topics import default_topic_map
from diffgcl.io import FolderKind, check_output_folder, write_folder

# Episode start marker this long after the first message (so every sensor, the 0.5 Hz radar
# included, has reported once inside the episode); end marker 1 s before the last message.
MARKER_LEAD_NS = 2_500_000_000


@dataclass(frozen=True)
class EpisodeTruth:
    """A simulated episode: t: [K+1] int64 ns, X: [K+1, dX], U: [K, dU] (hull layout)."""

    set: int
    index: int
    profile: OperatorProfile
    t: np.ndarray
    X: np.ndarray
    U: np.ndarray
    bag: str = ""
    marker_ns: tuple[int, int] = (0, 0)


@dataclass(frozen=True)
class SynthResult:
    """Bags written by :func:`synthesize` and the simulated truth of every episode."""

    out: Path
    bags: tuple[Path, ...]
    episodes: tuple[EpisodeTruth, ...]


def _owned_bags(folder: Path) -> frozenset[str] | None:
    """What an earlier :func:`synthesize` wrote into ``folder`` (None: not a synthetic set)."""
    try:
        manifest = json.loads((folder / "manifest.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(manifest, dict) or manifest.get("format") != "diffgcl-synth/1":
        return None
    return frozenset(["manifest.json", *(e["bag"] for e in manifest.get("episodes", ()))])


SYNTH_FOLDER = FolderKind("synthetic bag set", _owned_bags, marker="manifest.json")


def _marker_texts(cfg: SynthConfig, set_index: int, i: int, colour: str) -> tuple[str, str]:
    if cfg.markers == "id":
        return f"start {i + 1}", f"end {i + 1}"
    return f"start set={set_index} episode={i} pole={colour}", "end"


def synthesize(
    out: str | os.PathLike,
    config: SynthConfig | None = None,
    progress: Callable[[Sequence], Any] | None = None,
    overwrite: bool = False,
) -> SynthResult:
    """Simulate every episode and write the bags into ``out`` (output folder rules of
    :func:`diffgcl.io.write_folder`, kind :data:`SYNTH_FOLDER`: an earlier synthetic set there is
    replaced atomically, a non-empty folder of anything else is refused unless ``overwrite``).

    Returns the written bags and the simulated truth (states on the model grid) per episode.
    """
    cfg = config or SynthConfig()
    if cfg.fmt not in FORMATS:
        raise ValueError(f"bag format {cfg.fmt!r}; choose one of {FORMATS}")
    if cfg.bag_per not in ("episode", "set"):
        raise ValueError(f"bag_per must be 'episode' or 'set', got {cfg.bag_per!r}")
    if len(cfg.lidar) != len(cfg.episodes):
        raise ValueError("config.lidar needs one flag per set")
    for name, value, allowed in (
        ("layout", cfg.layout, tuple(LAYOUT_TOPICS)),
        ("markers", cfg.markers, ("keyvalue", "id", "none")),
        ("visible_poles", cfg.visible_poles, ("episode", "set")),
    ):
        if value not in allowed:
            raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
    check_output_folder(out, SYNTH_FOLDER, overwrite)
    datum = cfg.datum or default_topic_map().datum
    params = true_params()
    taus = (float(params.tau_thrust), float(params.tau_nozzle))
    dt = hull_dt()
    step_ns = round(dt * NS)
    rng = np.random.default_rng(cfg.seed)
    out = Path(out)
    truths: list[EpisodeTruth] = []
    legs: list[dict] = []
    bags: list[Path] = []
    clock = cfg.start_ns
    sets = []
    for s, (n_ep, lidar) in enumerate(zip(cfg.episodes, cfg.lidar, strict=True), start=1):
        if n_ep > 0:
            profiles = draw_profiles(rng, n_ep, cfg)
            if cfg.visible_poles == "set":
                profiles = separate_poles(rng, profiles, cfg.min_pole_separation)
            sets.append((s, n_ep, lidar, profiles))
    # One simulation batch for all sets (one trace of the jitted step per process).
    all_runs = simulate(
        [p for *_, ps in sets for p in ps], params, rng, int(cfg.max_duration_s / dt)
    )
    jobs: list[tuple[str, bool, Recording, np.random.Generator]] = []
    glitches: dict[str, tuple[str, int, int, int]] = {}
    for s, n_ep, lidar, profiles in sets:
        runs, all_runs = all_runs[:n_ep], all_runs[n_ep:]
        set_poles = tuple((p.pole_xy, p.pole_radius) for p in profiles)
        previous = None
        for i, (prof, (X, U)) in enumerate(zip(profiles, runs, strict=True)):
            stem = f"set{s}_ep{i:03d}" if cfg.bag_per == "episode" else f"set{s}"
            bag = f"set{s}/{bag_name(stem, cfg.fmt)}"
            poles = set_poles if cfg.visible_poles == "set" else ((prof.pole_xy, prof.pole_radius),)
            if previous is not None and cfg.repositioning and cfg.bag_per == "set":
                leg_X, leg_U = repositioning_leg(previous[1][-1], X[0], dt, set_poles)
                t_leg = int(previous[0][-1]) + step_ns * np.arange(leg_X.shape[0], dtype=np.int64)
                leg = Recording(t_leg, leg_X, leg_U, poles, None, ())
                jobs.append((bag, lidar, leg, np.random.default_rng([cfg.seed, s, 1000 + i])))
                clearance = min(
                    float(np.min(np.hypot(*(leg_X[:, :2] - xy).T))) - r for xy, r in set_poles
                )
                legs.append(
                    {
                        "set": s,
                        "bag": bag,
                        "t_start": t_leg[0] * 1e-9,
                        "t_end": t_leg[-1] * 1e-9,
                        "pole_clearance_m": clearance,
                    }
                )
                clock = int(t_leg[-1])
            else:
                clock = -(-clock // step_ns) * step_ns
            t = clock + step_ns * np.arange(X.shape[0], dtype=np.int64)
            marker_ns = (int(t[0] + MARKER_LEAD_NS), int(t[-1] - NS))
            start_text, end_text = _marker_texts(cfg, s, i, prof.pole_colour)
            markers = (
                ()
                if cfg.markers == "none"
                else ((marker_ns[0], start_text), (marker_ns[1], end_text))
            )
            obstacle = prof.pole_xy if cfg.obstacle_topic else None
            rec = Recording(t, X, U, poles, obstacle, markers)
            jobs.append((bag, lidar, rec, np.random.default_rng([cfg.seed, s, i])))
            truths.append(EpisodeTruth(s, i, prof, t, X, U, bag, marker_ns))
            if cfg.stamp_glitch is not None and bag not in glitches:
                g = cfg.stamp_glitch
                first = int(t[0] + round(g.at_s * NS))
                glitches[bag] = (
                    g.topic,
                    first,
                    first + round(g.duration_s * NS),
                    round(g.jump_s * NS),
                )
            previous = (t, X)
            clock = int(t[-1]) + 20 * NS
    with write_folder(out, SYNTH_FOLDER, overwrite) as stage:
        iterable = progress(jobs) if progress is not None else jobs
        batches: dict[str, list] = {}
        builder = _NullWriter(cfg.fmt)
        for bag, lidar, rec, job_rng in iterable:
            msgs = episode_messages(
                builder,
                rec,
                lidar,
                cfg.sensors,
                datum,
                job_rng,
                taus,
                cfg.layout,
                glitches.get(bag),
            )
            batches.setdefault(bag, []).append(msgs)
        for rel, msg_batches in batches.items():
            (stage / rel).parent.mkdir(parents=True, exist_ok=True)
            write_messages(stage / rel, cfg.fmt, msg_batches)
            bags.append(out / rel)
        manifest = {
            "format": "diffgcl-synth/1",
            "bag_format": cfg.fmt,
            "bag_per": cfg.bag_per,
            "layout": cfg.layout,
            "markers": cfg.markers,
            "obstacle_topic": cfg.obstacle_topic,
            "visible_poles": cfg.visible_poles,
            "repositioning": cfg.repositioning,
            "seed": cfg.seed,
            "dt": dt,
            "datum": list(datum),
            "true_factors": TRUE_FACTORS,
            "true_params": {k: float(getattr(params, k)) for k in TRUE_FACTORS},
            "sets": {
                str(s): {"episodes": n, "lidar": lid}
                for s, (n, lid) in enumerate(zip(cfg.episodes, cfg.lidar, strict=True), start=1)
            },
            "episodes": [
                {
                    "set": tr.set,
                    "index": tr.index,
                    "bag": tr.bag,
                    "pole": tr.profile.pole_colour,
                    "pole_xy": list(tr.profile.pole_xy),
                    "pole_radius": tr.profile.pole_radius,
                    "swerve_side": "left" if tr.profile.side > 0 else "right",
                    "t_start": tr.marker_ns[0] * 1e-9,
                    "t_end": tr.marker_ns[1] * 1e-9,
                    "t_first": tr.t[0] * 1e-9,
                    "t_last": tr.t[-1] * 1e-9,
                    "profile": asdict(tr.profile),
                }
                for tr in truths
            ],
            "legs": legs,
        }
        (stage / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return SynthResult(out=out, bags=tuple(dict.fromkeys(bags)), episodes=tuple(truths))


class _NullWriter(BagWriter):
    """A writer used only to build messages (typestore, headers); it writes no file."""

    def __init__(self, fmt: str):
        from diffgcl.data.bags import typestore_for

        self.path = Path(os.devnull)
        self.format = fmt
        self.typestore = typestore_for(fmt)
        self._seq = 0

    def __enter__(self) -> _NullWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        return None
