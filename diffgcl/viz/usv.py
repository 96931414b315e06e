"""Pictures of a USV run (:class:`diffgcl.algorithms.usv.UsvRun`): the held-out tracks of each
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

from diffgcl.io import FolderKind
from diffgcl.sim import hull as hull_sim

PLOTS = ("usv_tracks.png", "usv_cost_map.png")
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

    names = list(run.tracks)
    fig, axes = plt.subplots(len(names), 1, figsize=(11, 3.6 * len(names)), squeeze=False)
    demo = _pole_relative(run.demos.X)
    for ax, name in zip(axes[:, 0], names, strict=True):
        for p in demo:
            ax.plot(p[:, 0], p[:, 1], color="0.75", lw=0.8)
        tracks = run.tracks[name].reshape(-1, *run.tracks[name].shape[2:])
        score = run.summary.get(name, {})
        for X in tracks:
            p = _pole_relative(X[None])[0]
            clear = np.asarray(jax.vmap(run.env_true.clearance)(jnp.asarray(X)))
            colour = "k" if clear.min() <= 0 else COLOURS.get(name, "tab:purple")
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
    """The learned state cost (per step) of the first seed around the pole, for a boat heading
    along the course at cruise speed, with the demos' tracks over it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env, state = run.env, run.rgcl_state
    params = jax.tree.map(lambda a: jnp.asarray(a[seed]), state.cost.params)
    x0 = env.start_state(jnp.zeros(2), 0.5, env.cruise_speed)
    xs, ys = np.linspace(-120.0, 120.0, 121), np.linspace(-50.0, 50.0, 51)
    grid = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)

    def cost_at(p):
        x = x0.at[hull_sim.IX_PX].set(p[0]).at[hull_sim.IX_PY].set(p[1])
        return run.rgcl.network.state_cost(params, x)

    c = np.asarray(jax.jit(jax.vmap(cost_at))(jnp.asarray(grid, x0.dtype))).reshape(len(ys), -1)
    fig, ax = plt.subplots(figsize=(11, 4.5))
    mesh = ax.pcolormesh(xs, ys, c - c.min(), shading="auto", cmap="viridis")
    fig.colorbar(mesh, ax=ax, label="learned cost per step − min")
    for p in _pole_relative(run.demos.X):
        ax.plot(p[:, 0], p[:, 1], color="w", lw=0.6, alpha=0.7)
    ax.add_patch(plt.Circle((0, 0), 0.5, color="tab:orange"))
    ax.set_aspect("equal")
    ax.set_xlim(xs[0], xs[-1])
    ax.set_ylim(ys[0], ys[-1])
    ax.set_title("learned cost around the pole (boat heading +x at cruise speed); white: demos")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


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
        (tmp / SUMMARY).write_text(json.dumps(run.summary, indent=1, default=float))
    return [out / n for n in (*names, SUMMARY)]
