"""Pictures of a USV run (:class:`diffgcl.usv.UsvRun`): the held-out tracks of each
policy beside the demos, relative to the pole, and the learned cost around the pole.

:func:`save_usv_plots` writes them (and the run's ``summary.json``) into a run folder through
:func:`diffgcl.io.write_folder` (a user's folder is never emptied).
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.envs.usv import IX_RADIUS
from diffgcl.io import FolderKind
from diffgcl.sim import hull as hull_sim

PLOTS = ("usv_tracks.png", "usv_cost_map.png", "usv_episode.gif")
SUMMARY = "usv_summary.json"
USV_FOLDER = FolderKind(
    "USV run",
    lambda folder: [*PLOTS, SUMMARY] if (Path(folder) / SUMMARY).is_file() else None,
    marker=SUMMARY,
)
COLOURS = {"rgcl": "tab:blue", "expert": "tab:green", "bc": "tab:red"}
LABELS = {"rgcl": "rGCL + MDGPS", "expert": "MDGPS, hand-written cost", "bc": "behaviour cloning"}


def _pole_relative(X: np.ndarray) -> np.ndarray:
    """[..., T+1, 2] positions relative to the pole of each track."""
    return X[..., :2] - X[..., :1, hull_sim.SL_OBS]


def tracks_figure(run, path: Path) -> None:
    """One panel per method: the demos' tracks (grey) and the policy's held-out tracks on the
    true hull (collisions in black), all relative to the pole, the course along +x."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffgcl.usv.scores import trajectory_metrics

    names = list(run.tracks)
    fig, axes = plt.subplots(len(names), 1, figsize=(11, 3.6 * len(names)), squeeze=False)
    demo = _pole_relative(run.demos.X)
    for ax, name in zip(axes[:, 0], names, strict=True):
        for p in demo:
            ax.plot(p[:, 0], p[:, 1], color="0.75", lw=0.8)
        tracks = run.tracks[name].reshape(-1, *run.tracks[name].shape[2:])
        # The scores' own per-episode metrics (one program per env and shape, already compiled
        # by the scoring), not a clearance dispatched per track.
        hit = trajectory_metrics(run.env_true, tracks)["collision"]
        score = run.summary.get(name, {})
        for X, collided in zip(tracks, hit, strict=True):
            p = _pole_relative(X[None])[0]
            colour = "k" if collided else COLOURS.get(name, "tab:purple")
            ax.plot(p[:, 0], p[:, 1], color=colour, lw=0.9)
        ax.add_patch(plt.Circle((0, 0), float(run.x0_heldout[:, -1].mean()), color="tab:orange"))
        ax.axhline(0.0, color="0.5", ls=":", lw=0.8)
        ax.set_aspect("equal")
        ax.set_ylabel("m (to port)")
        ax.set_title(
            f"{LABELS.get(name, name)}: collisions {score.get('collision_rate', np.nan):.0%}, "
            f"back on course {score.get('return_to_course_rate', np.nan):.0%} "
            "(held-out, true hull; grey: demos)"
        )
    axes[-1, 0].set_xlabel("m along the course, relative to the pole")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def cost_map_figure(run, path: Path, seed: int = 0) -> None:
    """The learned state cost (per step, first seed) beside the hand-written one, over the x–y
    plane around the pole for a boat heading along the course at cruise speed, with the demos'
    tracks over them. Each map is shifted to its minimum; the colour scale is each map's own.
    A cost network that reads the time is drawn at the demos' median step of closest approach
    (at step 0 the pole is still far ahead of every demo)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env, state = run.env, run.rgcl_state
    params = jax.tree.map(lambda a: jnp.asarray(a[seed]), state.cost.params)
    x0 = env.start_state(jnp.zeros(2), 0.5, env.cruise_speed)
    u0 = jnp.zeros(env.dU, x0.dtype)
    xs, ys = np.linspace(-120.0, 120.0, 121), np.linspace(-50.0, 50.0, 51)
    grid = jnp.asarray(np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2), x0.dtype)

    def at(p):
        return x0.at[hull_sim.IX_PX].set(p[0]).at[hull_sim.IX_PY].set(p[1])

    step, when = 0, ""
    if run.rgcl.network.config.time_input:
        distance = np.linalg.norm(_pole_relative(np.asarray(run.demos.X)), axis=-1)
        step = int(np.median(np.argmin(distance, axis=-1)))
        when = f" at step {step}, the closest approach"
    maps = {
        f"learned cost (rGCL){when}": jax.vmap(
            lambda p: run.rgcl.network.state_cost(params, at(p), step)
        ),
        "hand-written cost": jax.vmap(lambda p: env.expert_cost(at(p), u0, 0)),
    }
    fig, axes = plt.subplots(2, 1, figsize=(11, 8.5))
    for ax, (title, fn) in zip(axes, maps.items(), strict=True):
        c = np.asarray(jax.jit(fn)(grid)).reshape(len(ys), -1)
        c = c - c.min()
        mesh = ax.pcolormesh(xs, ys, np.log1p(c / max(np.median(c), 1e-12)), shading="auto")
        fig.colorbar(mesh, ax=ax, label="log(1 + (cost − min) / median)")
        for p in _pole_relative(run.demos.X):
            ax.plot(p[:, 0], p[:, 1], color="w", lw=0.6, alpha=0.7)
        ax.add_patch(plt.Circle((0, 0), 0.5, color="tab:orange"))
        ax.set_aspect("equal")
        ax.set_xlim(xs[0], xs[-1])
        ax.set_ylim(ys[0], ys[-1])
        ax.set_title(f"{title} per step, boat heading +x at cruise speed; white: demos")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def episode_animation(run, path: Path, method: str | None = None, index: int = 0, every: int = 5):
    """GIF of one held-out episode of ``method`` (default: the first one run) on the true hull:
    the hull outline, its wake, the pole, the course line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffgcl.envs.hull import hull_points
    from diffgcl.viz.plots import write_gif

    method = method or next(iter(run.tracks))
    X = run.tracks[method][0, index]
    env = run.env_true
    P = np.asarray(jax.vmap(lambda x: hull_points(env.params, x[:IX_RADIUS]))(jnp.asarray(X)))
    pole = X[0, hull_sim.SL_OBS]
    fig, ax = plt.subplots(figsize=(10, 4))
    ax.axhline(0.0, color="0.6", ls=":", lw=0.8)
    ax.add_patch(plt.Circle(tuple(pole), float(X[0, IX_RADIUS]), color="tab:orange"))
    ax.set_xlim(X[:, 0].min() - 10, X[:, 0].max() + 10)
    span = max(np.abs(X[:, 1]).max(), 10.0) + 10
    ax.set_ylim(-span, span)
    ax.set_aspect("equal")
    (wake,) = ax.plot([], [], color="tab:blue", lw=0.8)
    (hull,) = ax.plot([], [], color="k", lw=4, solid_capstyle="round")
    title = ax.set_title("")

    def draw(i):
        wake.set_data(X[: i + 1, 0], X[: i + 1, 1])
        hull.set_data(P[i, [0, 2], 0], P[i, [0, 2], 1])
        title.set_text(
            f"{LABELS.get(method, method)}, held-out episode {index}: t = {i * env.dt:.1f} s"
        )

    fps = max(1, round(1 / (every * env.dt)))
    write_gif(fig, (wake, hull, title), draw, range(0, X.shape[0], every), path, fps)


def save_usv_plots(run, out, overwrite: bool = False) -> list[Path]:
    """Write ``usv_summary.json`` and the pictures of ``run`` into ``out`` (a new folder, or one
    an earlier USV run wrote; see :mod:`diffgcl.io`). Returns the written paths."""
    from diffgcl.io import write_folder

    out = Path(out)
    with write_folder(out, USV_FOLDER, overwrite) as tmp:
        tracks_figure(run, tmp / PLOTS[0])
        names = [PLOTS[0]]
        if run.rgcl_state is not None:
            cost_map_figure(run, tmp / PLOTS[1])
            names.append(PLOTS[1])
        episode_animation(run, tmp / PLOTS[2])
        names.append(PLOTS[2])
        (tmp / SUMMARY).write_text(json.dumps(run.summary, indent=1, default=float))
    return [out / n for n in (*names, SUMMARY)]
