"""Plots of rGCL runs (matplotlib, Agg backend; host side only).

* :func:`learning_curves` — true and learned cost of the GPS samples (and the learned cost of the
  demos), step_mult, controller entropy, the demos' log-likelihood under the controllers and the
  cost's temperature per GPS iteration (mean ± std over seeds; GPS's GUI showed the first four),
  with the success rate;
* :func:`arm_motion` — the arm's joint-space paths: the samples of every iteration coloured by
  iteration, the final controller's noise-free rollout, and a stroboscopic drawing of it;
* :func:`cost_landscape` — the learned cost over (q1, q2) at rest (dq = 0, u = 0) beside the
  expert cost, with the demonstrations drawn on both;
* :func:`write_gif` — the animations' writer (the arm's here, the USV's episode).
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _flat(a) -> np.ndarray:
    """[S, I, G, C] -> [S, I·G] (condition 0)."""
    a = np.asarray(a)[..., 0]
    return a.reshape(a.shape[0], -1)


def learning_curves(metrics, path: Path, title: str = "", demo_entropy: float | None = None):
    """Six panels over GPS iterations (metrics: RGCLMetrics with [S, I, G, C] GPS fields; mean ±
    std over seeds, condition 0): the true cost of the samples with the success rate; the
    learned cost of the samples and of the demos (its level: the cost's scale rises for both,
    the learned cost's minimum stays near 0); step_mult; the controllers' action entropy (and the
    demos' controller's, ``demo_entropy``); the demos' log-likelihood under the controllers; the
    cost's log-temperature ρ."""
    plt = _plt()
    S = np.asarray(metrics.gps.cost).shape[0]
    G = np.asarray(metrics.gps.cost).shape[2]
    per_update = lambda a: np.repeat(np.asarray(a)[..., None], G, axis=2).reshape(S, -1)
    panels = (
        ("true cost of samples", _flat(metrics.gps.cost), True),
        ("learned cost: samples (—), demos (--)", _flat(metrics.learned_cost), True),
        ("step_mult", _flat(metrics.gps.step_mult), True),
        ("controller entropy (nats)", _flat(metrics.gps.entropy), False),
        ("demos' log-likelihood under the controllers", _flat(metrics.demo_log_likelihood), False),
        ("cost log-temperature ρ", per_update(metrics.log_temperature), False),
    )
    its = np.arange(1, panels[0][1].shape[1] + 1)
    fig, axes = plt.subplots(2, 3, figsize=(15, 7.5))
    axes = axes.ravel()
    for ax, (name, v, log) in zip(axes, panels, strict=True):
        mean, std = v.mean(0), v.std(0)
        ax.plot(its, mean, marker=".")
        ax.fill_between(its, mean - std, mean + std, alpha=0.25)
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("GPS iteration")
        if log and np.all(v > 0):
            ax.set_yscale("log")
    demo_cost = per_update(np.asarray(metrics.demo_learned_cost)[..., 0])
    axes[1].plot(its, demo_cost.mean(0), "k--", lw=1)
    if demo_entropy is not None:
        axes[3].axhline(demo_entropy, color="k", ls="--", lw=1, label="demos' controller")
        axes[3].legend(loc="best", fontsize=8)
    success = np.asarray(metrics.gps.success).all(axis=-1).reshape(S, -1)
    twin = axes[0].twinx()
    twin.plot(its, success.mean(0), color="tab:green", ls="--", label="success rate")
    twin.set_ylim(-0.05, 1.05)
    twin.legend(loc="upper right")
    fig.suptitle(f"{title} ({S} seeds, mean ± std)".strip())
    _save(fig, path)


def arm_motion(env, sample_X, X_final, path: Path) -> None:
    """sample_X: [I, G, C, N, T+1, dX] one seed's GPS samples; X_final: [T+1, dX] the final
    controller's noise-free rollout (condition 0)."""
    plt = _plt()
    q = np.asarray(sample_X)[..., 0, :, :, :2]  # [I, G, N, T+1, 2]
    q = q.reshape(-1, *q.shape[-3:])  # [I·G, N, T+1, 2]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8))
    cmap = plt.get_cmap("viridis")
    for i in range(q.shape[0]):
        colour = cmap(i / max(q.shape[0] - 1, 1))
        for n in range(q.shape[1]):
            axes[0].plot(q[i, n, :, 0], q[i, n, :, 1], color=colour, lw=0.6, alpha=0.5)
    X_final = np.asarray(X_final)
    axes[0].plot(X_final[:, 0], X_final[:, 1], "r-", lw=2, label="final controller mean")
    axes[0].plot(*np.asarray(env.target), "g*", ms=14, label="target")
    tol = env.success_tolerance
    tx, ty = np.asarray(env.target)
    axes[0].add_patch(plt.Rectangle((tx - tol, ty - tol), 2 * tol, 2 * tol, color="g", alpha=0.2))
    axes[0].set_xlabel("q1 (rad)")
    axes[0].set_ylabel("q2 (rad)")
    axes[0].set_title("samples by iteration (dark: early, yellow: late)")
    axes[0].legend(loc="best", fontsize=8)
    if not hasattr(env, "model"):  # not an MJX arm: no drawing of the links
        axes[1].plot(np.arange(X_final.shape[0]), X_final[:, :2])
        axes[1].set_xlabel("step")
        axes[1].set_title("final controller mean, q1 and q2")
        _save(fig, path)
        return
    P = arm_points(env, jnp.asarray(X_final))
    idx = list(range(0, P.shape[0], 5)) + [P.shape[0] - 1]
    for k, t in enumerate(idx):
        axes[1].plot(P[t, :, 0], P[t, :, 1], "-o", color=cmap(k / max(len(idx) - 1, 1)), ms=3)
    axes[1].set_aspect("equal")
    axes[1].set_title("final motion, every 5 steps")
    _save(fig, path)


def cost_landscape(env, network, params, demo_X, path: Path, n: int = 81) -> None:
    """Learned vs expert per-step cost at rest over a (q1, q2) grid; demo_X: [N, T+1, dX]."""
    plt = _plt()
    demo_X = np.asarray(demo_X)
    target = np.asarray(env.target)
    lo = np.minimum(demo_X[..., :2].min(axis=(0, 1)), target) - 0.7
    hi = np.maximum(demo_X[..., :2].max(axis=(0, 1)), target) + 0.7
    q1, q2 = np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n))
    dtype = jnp.asarray(env.initial_states()).dtype
    X = jnp.asarray(
        np.stack([q1.ravel(), q2.ravel(), 0 * q1.ravel(), 0 * q1.ravel()], -1)[:, : env.dX], dtype
    )
    U = jnp.zeros((X.shape[0], env.dU), dtype)
    learned = jax.jit(jax.vmap(lambda x, u: network.cost(params, x, u, 0)))(X, U)
    expert = jax.jit(jax.vmap(lambda x, u: env.expert_cost(x, u, 0)))(X, U)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    for ax, name, v in ((axes[0], "learned cost", learned), (axes[1], "expert cost", expert)):
        v = np.asarray(v).reshape(q1.shape)
        im = ax.contourf(q1, q2, np.log10(v - v.min() + 1e-3 * (np.ptp(v) + 1e-12)), 30)
        fig.colorbar(im, ax=ax, label="log10(c − min c)")
        for d in demo_X:
            ax.plot(d[:, 0], d[:, 1], "w-", lw=0.8, alpha=0.8)
        ax.plot(*np.asarray(env.target), "r*", ms=12)
        ax.set_xlabel("q1 (rad)")
        ax.set_ylabel("q2 (rad)")
        ax.set_title(f"{name} at rest (dq = 0, u = 0); white: demos")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---- GPS runs (experiments/arm_gps.py, diffgcl gps) ----


def gps_learning_curves(metrics, path: Path, label: str = "") -> None:
    """Mean true cost, step_mult and controller entropy per iteration (mean ± std over seeds and
    conditions; what GPS's GUI showed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    its = np.arange(1, metrics.cost.shape[1] + 1)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, name, values, log in (
        (axes[0], "mean sample cost", metrics.cost, True),
        (axes[1], "step_mult", metrics.step_mult, True),
        (axes[2], "controller entropy (nats)", metrics.entropy, False),
    ):
        v = np.asarray(values).reshape(values.shape[0], values.shape[1], -1)
        mean, std = v.mean(axis=(0, 2)), v.std(axis=(0, 2))
        ax.plot(its, mean, marker="o")
        ax.fill_between(its, mean - std, mean + std, alpha=0.25)
        ax.set_xlabel("iteration")
        ax.set_title(name)
        if log:
            ax.set_yscale("log")
    success = np.all(np.asarray(metrics.success), axis=-1).mean(axis=0)
    twin = axes[0].twinx()
    twin.plot(its, success, color="tab:green", ls="--", label="success rate")
    twin.set_ylim(-0.05, 1.05)
    twin.legend(loc="upper right")
    fig.suptitle(f"GPS on the arm {label}".strip())
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def arm_points(env, X) -> np.ndarray:
    """Planar positions of the arm's bodies and sites along X: [T+1, dX] -> [T+1, P, 2]."""
    from mujoco import mjx

    def points(x):
        d = mjx.kinematics(env.model, env.data0.replace(qpos=x[:2]))
        return jnp.concatenate([d.xpos[1:, :2], d.site_xpos[:, :2]], axis=0)

    return np.asarray(jax.jit(jax.vmap(points))(jnp.asarray(X)))


def arm_rollout(env, X, path: Path, every: int = 5) -> None:
    """Joint angles over time and a stroboscopic drawing of the arm (X: [T+1, dX], one run)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = arm_points(env, X)
    X = np.asarray(X)
    t = np.arange(X.shape[0]) * env.dt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for j in range(2):
        axes[0].plot(t, X[:, j], label=f"q{j + 1}")
    axes[0].axhspan(-env.success_tolerance, env.success_tolerance, color="g", alpha=0.15)
    axes[0].set_xlabel("time (s)")
    axes[0].set_ylabel("joint angle (rad)")
    axes[0].legend()
    cmap = plt.get_cmap("viridis")
    idx = list(range(0, X.shape[0], every)) + [X.shape[0] - 1]
    for n, i in enumerate(idx):
        colour = cmap(n / max(len(idx) - 1, 1))
        axes[1].plot(P[i, :, 0], P[i, :, 1], "-o", color=colour, ms=3, lw=1.5)
    axes[1].set_aspect("equal")
    axes[1].set_title(f"arm every {every} steps (dark: start, yellow: end)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _pack(rgb: np.ndarray) -> np.ndarray:
    """RGB uint8 [..., 3] -> one uint32 per colour [N]."""
    return rgb.reshape(-1, 3).astype(np.uint32) @ np.array([1 << 16, 1 << 8, 1], np.uint32)


def _unpack(packed: np.ndarray) -> np.ndarray:
    """The inverse of :func:`_pack`: [N] -> [N, 3] (float, for distances)."""
    return np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], 1).astype(float)


def _shared_palette(samples):
    """A flat 256-colour palette for ``samples`` (RGB uint8 images): their 40 commonest colours
    exactly (the background, the axes, the lines' cores) and a 6 × 6 × 6 colour cube for every
    other hue (a patch a few pixels wide keeps its colour); and a function mapping an RGB image
    to palette indices, each colour to itself where the palette has it, else to the nearest.
    (Pillow's own RGB → P conversion looks colours up in coarse boxes, which turns matplotlib's
    white into 252; a palette of the commonest colours alone loses small patches.)"""
    colours, counts = np.unique(np.concatenate([_pack(s) for s in samples]), return_counts=True)
    levels = np.arange(6, dtype=np.uint32) * 51
    cube = _pack(np.stack(np.meshgrid(levels, levels, levels, indexing="ij"), -1))
    common = colours[np.argsort(-counts, kind="stable")[:40]]
    top = np.union1d(common, cube)
    rgb = _unpack(top)

    def index_of(image: np.ndarray) -> np.ndarray:
        packed = _pack(image)
        found, inverse = np.unique(packed, return_inverse=True)
        slot = np.clip(np.searchsorted(top, found), 0, len(top) - 1)
        exact = top[slot] == found
        if not exact.all():
            distance = ((_unpack(found[~exact])[:, None, :] - rgb[None]) ** 2).sum(-1)
            slot[~exact] = distance.argmin(1)
        return slot[inverse].astype(np.uint8).reshape(image.shape[:2])

    flat = np.pad(rgb.astype(np.uint8), ((0, 256 - len(rgb)), (0, 0))).ravel().tolist()
    return flat, index_of


def write_gif(fig, artists, update, frames, path: Path, fps: float) -> None:
    """Write an animation of ``fig`` to the GIF ``path``: ``update(i)`` for each ``i`` in
    ``frames`` changes ``artists`` (the only parts that move), ``fps`` frames per second; the
    figure is closed.

    The rest of the figure (axes, ticks, labels, static patches) is rendered once and each frame
    draws only ``artists`` over a copy of it, and every frame is mapped to one palette
    (:func:`_shared_palette`) instead of a palette of its own: matplotlib's
    ``FuncAnimation`` with its Pillow writer renders the whole figure twice per frame and
    quantises each frame afresh: 8× the time for the USV's 79-frame episode."""
    import matplotlib.pyplot as plt
    from PIL import Image

    frames = list(frames)
    if not frames:
        raise ValueError(f"write_gif: no frames for {path}")
    for artist in artists:
        artist.set_animated(True)  # left out of the full render: drawn per frame only
    canvas = fig.canvas
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)
    images = []
    for i in frames:
        canvas.restore_region(background)
        update(i)
        for artist in artists:
            fig.draw_artist(artist)
        images.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    palette, index_of = _shared_palette([images[0], images[len(images) // 2], images[-1]])
    paletted = []
    for im in images:
        indices = index_of(im)
        frame = Image.frombytes("P", (indices.shape[1], indices.shape[0]), indices.tobytes())
        frame.putpalette(palette)
        paletted.append(frame)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    paletted[0].save(
        path,
        save_all=True,
        append_images=paletted[1:],
        duration=max(1, round(1000 / fps)),
        loop=0,
    )


def arm_animation(env, X, path: Path, every: int = 2) -> None:
    """GIF of the arm along X: [T+1, dX] (every ``every``-th state, real time)."""
    plt = _plt()

    P = arm_points(env, X)
    reach = float(np.abs(P).max()) * 1.1
    fig, ax = plt.subplots(figsize=(4, 4))
    ax.set_xlim(-reach, reach)
    ax.set_ylim(-reach, reach)
    ax.set_aspect("equal")
    target = arm_points(env, jnp.zeros((1, env.dX), jnp.asarray(X).dtype))[0]
    ax.plot(target[:, 0], target[:, 1], "--", color="g", lw=1, label="target")
    (line,) = ax.plot([], [], "-o", lw=3, ms=5)
    title = ax.set_title("")
    ax.legend(loc="lower left")

    def draw(i):
        line.set_data(P[i, :, 0], P[i, :, 1])
        title.set_text(f"t = {i * env.dt:.2f} s")

    fps = max(1, round(1 / (every * env.dt)))
    write_gif(fig, (line, title), draw, range(0, P.shape[0], every), path, fps)


# ---- global policies ----


def policy_paths(env, policy, params, start_sets: dict, path: Path, title: str = "") -> None:
    """Paths of a global policy's noise-free rollouts in the plane of the first two state
    coordinates (the arm's joint angles, the hull's position) from sets of starts
    (``{name: x0 [B, dX]}``), one panel per set; green: the env's success test passes, red: it
    fails; the grey square is the success box around ``env.target`` where the env has one."""
    from diffgcl.eval.policy import policy_rollouts, policy_success

    plt = _plt()
    fig, axes = plt.subplots(1, len(start_sets), figsize=(5.2 * len(start_sets), 4.6))
    axes = np.atleast_1d(axes)
    tol = getattr(env, "success_tolerance", None)
    target = getattr(env, "target", None)
    for ax, (name, x0) in zip(axes, start_sets.items(), strict=True):
        rollouts = jax.jit(lambda p, x: policy_rollouts(env, policy, p, x))
        traj = rollouts(params, jnp.asarray(x0))
        ok = np.asarray(policy_success(env, traj))
        X = np.asarray(traj.X)
        for b in range(X.shape[0]):
            colour = "tab:green" if ok[b] else "tab:red"
            ax.plot(X[b, :, 0], X[b, :, 1], color=colour, lw=1.4)
            ax.plot(X[b, 0, 0], X[b, 0, 1], "o", color=colour, ms=4)
        if tol is not None and target is not None:
            corner = np.asarray(target)[:2] - float(tol)
            box = plt.Rectangle(corner, 2 * tol, 2 * tol, color="0.5", alpha=0.4, label="target")
            ax.add_patch(box)
            ax.legend(loc="lower right")
        names = getattr(env, "state_names", ("x[0]", "x[1]"))
        ax.set_xlabel(names[0])
        ax.set_ylabel(names[1])
        ax.set_title(f"{name} starts: {ok.sum()}/{ok.size} succeed")
    fig.suptitle(f"global policy {title}, noise-free rollouts".strip())
    _save(fig, path)
