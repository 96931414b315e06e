"""USV obstacle avoidance learned from bags, end to end (issue 13; DESIGN §7b).

The pieces, each a function the experiment (``experiments/usv_avoidance.py``) and the CLI
(``diffgcl usv``) chain:

1. :func:`builtin_bags` — the Odin-like synthetic bags (:mod:`diffgcl.data.synth`), written once
   into the cache; a user brings their own bags and topic map instead;
2. ingestion (:func:`diffgcl.data.ingest.ingest_bags`), then hull identification
   (:func:`diffgcl.data.sysid.identify`) on the demonstrations;
3. :func:`task_windows` — every demo in its task frame (:mod:`diffgcl.data.task_frame`) and cropped
   to a window of fixed horizon around its closest approach to the pole;
4. :func:`make_task_env` and :func:`usv_demo_set` — the USV task env
   (:class:`diffgcl.envs.usv.UsvEnv`) on the identified hull with one condition per demo (its
   start state and pole), and the demos in that env's layout (state with the pole's radius,
   normalised actions, the policy's observations built from the *recorded* ranges);
5. rGCL (:mod:`diffgcl.algorithms.rgcl`, :func:`diffgcl.algorithms.presets.usv`) learns the cost
   on task features and the MDGPS policy on the observations; references: MDGPS with the
   hand-written cost (:func:`train_expert`) and behaviour cloning (:mod:`diffgcl.algorithms.bc`);
6. :func:`heldout_starts` and :func:`evaluate_policy_batch` — situations none of the demos had
   (pole distance, the boat's lateral offset and heading, pole radius and speed drawn from the
   demos' ranges), rolled out on the *true* hull with sensor noise; per episode: collision, minimum
   clearance, back on course, side passed, path distance to the nearest demo.

The demonstrators' own controller for GCL's fusion weights is fitted once on all windows pooled
(one human policy, time-aligned by the closest approach), not per condition: with one demo per
condition a per-condition fit would have no residual to give it a covariance.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.algorithms.rgcl import DemoBatch
from diffgcl.data.demos import DemoError, DemoSet
from diffgcl.envs.usv import UsvEnv, make_usv_env
from diffgcl.sim import hull as hull_sim
from diffgcl.types import Array, PRNGKey

DEFAULT_POLE_RADIUS = 0.5  # m, used when neither the episode nor a manifest gives one


@dataclass(frozen=True)
class UsvTaskConfig:
    """How demos become the USV task.

    before / after: steps kept before and after the closest approach (T = before + after);
    sets: the bag sets whose episodes are used (set 1 of the seed has no LiDAR, set 2 has it);
    observation: the policy's observation set (:data:`diffgcl.envs.usv.OBSERVATIONS`);
    max_conditions: use at most this many demos (None: all); default_pole_radius: m.
    """

    before: int = 150
    after: int = 90
    sets: tuple[str, ...] = ("2",)
    observation: str = "full"
    max_conditions: int | None = None
    default_pole_radius: float = DEFAULT_POLE_RADIUS

    @property
    def horizon(self) -> int:
        return self.before + self.after


# ---- bags and demos -----------------------------------------------------------------------------


def builtin_bags(*, fast: bool = False, verbose: bool = True) -> Path:
    """The synthetic Odin-like bag set (the seed's layout: set 1, 19 episodes without LiDAR; set 2,
    47 with it; ``fast``: 3 + 5 short episodes), generated once into the cache."""
    from diffgcl.data.synth import SynthConfig, synthesize
    from diffgcl.runtime import cache_root

    config = (
        SynthConfig(episodes=(3, 5), approach_m=(110.0, 130.0), end_margin_m=(40.0, 50.0))
        if fast
        else SynthConfig()
    )
    name = "odin-synth-fast" if fast else "odin-synth"
    folder = cache_root() / "bags" / name
    if not (folder / "manifest.json").is_file():
        if verbose:
            print(f"writing the synthetic Odin-like bags into {folder}")
        synthesize(folder, config, overwrite=True)
    return folder


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


def task_windows(demos: DemoSet, config: UsvTaskConfig) -> DemoSet:
    """The chosen sets' episodes in the task frame, cropped around the pole pass (module
    docstring); episodes without a full window are left out with a warning."""
    from diffgcl.data.task_frame import pass_windows, to_task_frame

    sets = {str(e.get("set")) for e in demos.episodes}
    keep = [i for i, e in enumerate(demos.episodes) if str(e.get("set")) in config.sets]
    if not keep:
        raise DemoError(f"demos: no episode of sets {config.sets} (the data have sets {sets})")
    chosen = to_task_frame(demos.subset(np.asarray(keep)))
    windows = pass_windows(chosen, config.before, config.after)
    if config.max_conditions is not None:
        windows = windows.subset(slice(0, config.max_conditions))
    return windows


def cruise_speed_of(windows: DemoSet) -> float:
    """The demos' typical speed over ground (median over all valid steps), m/s."""
    speed = np.hypot(windows.X[..., hull_sim.IX_VX], windows.X[..., hull_sim.IX_VY])
    return float(np.median(speed[windows.mask > 0]))


def make_task_env(
    windows: DemoSet,
    radii: np.ndarray,
    params,
    config: UsvTaskConfig,
    *,
    cruise_speed: float | None = None,
    horizon: int | None = None,
) -> UsvEnv:
    """The USV env on hull ``params`` with one condition per window (its first state and pole)."""
    x0 = np.concatenate([windows.X[:, 0, : hull_sim.DX], radii[:, None]], axis=1)
    speed = cruise_speed_of(windows) if cruise_speed is None else cruise_speed
    return make_usv_env(
        x0,
        params=params,
        cruise_speed=speed,
        horizon=config.horizon if horizon is None else horizon,
        observation=config.observation,
    )


def usv_observations(env: UsvEnv, X: np.ndarray, O_hull: np.ndarray) -> np.ndarray:
    """The policy's observations [..., dO] in ``env``'s layout from states ``X: [..., 11]`` and
    the *recorded* observations in the hull layout ``O_hull: [..., 53]`` (ranges, sin ψ, cos ψ,
    ν): the ranges are what the bag's sensors read, the rest comes from the state."""
    n_beams = env.layout.num_beams
    ranges = O_hull[..., :n_beams]
    psi = X[..., hull_sim.IX_PSI]
    heading = np.stack([np.sin(psi), np.cos(psi)], axis=-1)
    nu = O_hull[..., n_beams + 2 : n_beams + 5]
    cross = X[..., hull_sim.IX_PY : hull_sim.IX_PY + 1]
    if env.observation == "ranges":
        return np.concatenate([ranges, nu], axis=-1)
    if env.observation == "radar":
        ranges = ranges[..., env.layout.lidar_beams :]
    return np.concatenate([ranges, heading, nu, cross], axis=-1)


def usv_demo_set(env: UsvEnv, windows: DemoSet, radii: np.ndarray) -> DemoSet:
    """The windows in ``env``'s layout: states with the pole radius [N, T+1, 11], normalised
    actions [N, T, 2], the policy's observations [N, T+1, dO] from the recorded ranges, and each
    episode its own condition (``condition = i``)."""
    N, T1, _ = windows.X.shape
    X = np.concatenate(
        [windows.X[..., : hull_sim.DX], np.broadcast_to(radii[:, None, None], (N, T1, 1))], -1
    )
    offset, scale = np.asarray(env.action_offset), np.asarray(env.action_scale)
    U = (windows.U - offset) / scale
    O = usv_observations(env, X, windows.O)
    episodes = tuple(
        {**e, "condition": i, "pole_radius": float(radii[i])}
        for i, e in enumerate(windows.episodes)
    )
    return DemoSet(X=X, U=U, O=O, mask=windows.mask, dt=windows.dt, env="usv", episodes=episodes)


def demo_batch_pooled(demos: DemoSet, dtype=None) -> DemoBatch:
    """A :class:`~diffgcl.algorithms.rgcl.DemoBatch` with one demo per condition [C, 1, ...] and
    the demonstrators' controller fitted on all demos pooled, shared by every condition."""
    from diffgcl.costs.demo_controller import fit_demo_controller

    dtype = dtype or jnp.zeros(()).dtype
    X = jnp.asarray(demos.X, dtype)
    U = jnp.asarray(demos.U, dtype)
    pooled = jax.jit(fit_demo_controller)(X, U)
    C = X.shape[0]
    controller = jax.tree.map(lambda a: jnp.broadcast_to(a, (C, *a.shape)), pooled)
    return DemoBatch(X=X[:, None], U=U[:, None], controller=controller)


# ---- held-out situations and evaluation ---------------------------------------------------------


@dataclass(frozen=True)
class SituationRanges:
    """Ranges of the held-out situations, from the demos' window starts (task frame): pole
    distance ahead (m), the boat's lateral offset from the pole's line (m), heading (rad), speed
    (m/s); pole radius (m)."""

    distance: tuple[float, float]
    offset: tuple[float, float]
    heading: tuple[float, float]
    speed: tuple[float, float]
    radius: tuple[float, float] = (0.3, 1.0)

    @classmethod
    def of(cls, demos: DemoSet, radius=(0.3, 1.0)) -> SituationRanges:
        x0 = demos.X[:, 0]
        rel = x0[:, hull_sim.SL_OBS] - x0[:, :2]
        speed = np.hypot(x0[:, hull_sim.IX_VX], x0[:, hull_sim.IX_VY])

        def span(v):
            return float(np.min(v)), float(np.max(v))

        return cls(
            distance=span(rel[:, 0]),
            offset=span(-rel[:, 1]),
            heading=span(x0[:, hull_sim.IX_PSI]),
            speed=span(speed),
            radius=radius,
        )


def heldout_starts(env: UsvEnv, ranges: SituationRanges, key: PRNGKey, n: int) -> Array:
    """``n`` start states [n, 11]: each quantity drawn uniformly from its range independently
    (so no start equals a demo's), the boat at (0, offset) heading ``heading``, the pole on the
    course line ahead at ``distance``."""
    keys = jax.random.split(key, 5)
    dtype = env.x0.dtype

    def draw(k, lo_hi):
        return jax.random.uniform(k, (n,), dtype, *lo_hi)

    names = ("distance", "offset", "heading", "speed", "radius")
    d, off, psi, v, r = (draw(k, getattr(ranges, f)) for k, f in zip(keys, names, strict=True))
    poles = jnp.stack([d, jnp.zeros_like(d)], axis=-1)
    return jax.vmap(env.start_state)(poles, r, v, psi, off)
