"""Demonstrations of the pole task in one common frame, and windows around the pole pass.

Bags record each episode where it happened: a different start, course and pole position each
time (world East-North-Up). The task is the same in every one — approach a pole head-on, swerve,
come back to the course — so the learned cost and the policy see it in the *task frame*
(DESIGN §7b): origin at the episode's start (its first valid position), +x along its approach
course, so that the course line is y = 0 with heading 0 and the pole lies ahead. The approach
course is the line from the start to the pole, the line the crew aims along and returns to.
The transform is a rotation and a shift: distances to the pole, speeds, yaw rates, body-frame
velocities, actuator states and the hull-frame range readings are unchanged; positions, world
velocities, the heading and the pole position are rotated.

:func:`to_task_frame` applies it to a :class:`~diffgcl.data.demos.DemoSet` in the hull layout
(:mod:`diffgcl.sim.hull`; observations in that of :func:`diffgcl.envs.hull.observation`) and
records ``task_frame = {"origin": [x, y], "course": a}`` in each episode's metadata.
:func:`pass_windows` crops every episode to a fixed horizon around its closest approach to the
pole, so that one GPS horizon covers every demonstration's swerve and pass.

NumPy, host side (ingestion's side of the line).
"""

from __future__ import annotations

import warnings

import numpy as np

from diffgcl.data.demos import DemoError, DemoSet
from diffgcl.sim import hull

# In the hull observation layout [ranges..., sin ψ, cos ψ, u, v, r] the heading is at these
# offsets from the end.
_SIN_PSI, _COS_PSI = -5, -4


def episode_frame(X: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """(origin [2], course angle a) of one episode ``X: [T+1, dX]`` (hull layout), ``mask:
    [T+1]``: its first valid position and the direction from there to the pole."""
    valid = np.flatnonzero(mask > 0)
    if valid.size == 0:
        raise DemoError("task frame: an episode has no valid step")
    first = valid[0]
    origin = X[first, hull.IX_PX : hull.IX_PY + 1]
    to_pole = X[first, hull.SL_OBS] - origin
    if np.hypot(*to_pole) < 1e-6:
        raise DemoError("task frame: the episode starts on the pole")
    return origin.copy(), float(np.arctan2(to_pole[1], to_pole[0]))


def rotate_states(X: np.ndarray, origin: np.ndarray, angle: float) -> np.ndarray:
    """Hull-layout states ``X: [..., dX]`` in the frame with ``origin`` and +x along ``angle``:
    positions and the pole shifted and rotated, world velocities rotated, ``ψ − angle``."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, s], [-s, c]])  # world -> task frame
    out = np.array(X, dtype=float, copy=True)
    out[..., hull.IX_PX : hull.IX_PY + 1] = (X[..., hull.IX_PX : hull.IX_PY + 1] - origin) @ R.T
    out[..., hull.SL_OBS] = (X[..., hull.SL_OBS] - origin) @ R.T
    out[..., hull.IX_VX : hull.IX_VY + 1] = X[..., hull.IX_VX : hull.IX_VY + 1] @ R.T
    out[..., hull.IX_PSI] = X[..., hull.IX_PSI] - angle
    return out


def to_task_frame(demos: DemoSet) -> DemoSet:
    """Every episode of ``demos`` (hull layout) in its own task frame (module docstring).

    The heading is shifted by a multiple of 2π so that it starts in [−π, π) and stays continuous;
    observations keep their ranges and body velocities and get the rotated heading.
    """
    if demos.X.shape[-1] < hull.DX:
        raise DemoError(f"task frame: states must be in the hull layout (dX = {hull.DX})")
    X = np.array(demos.X, dtype=float, copy=True)
    O = np.array(demos.O, dtype=float, copy=True)
    metas = []
    for i in range(demos.num_episodes):
        origin, angle = episode_frame(demos.X[i], demos.mask[i])
        Xi = rotate_states(demos.X[i, :, : hull.DX], origin, angle)
        first = int(np.argmax(demos.mask[i] > 0))
        Xi[:, hull.IX_PSI] -= 2 * np.pi * np.floor((Xi[first, hull.IX_PSI] + np.pi) / (2 * np.pi))
        X[i, :, : hull.DX] = Xi
        if O.shape[-1] >= 5:
            O[i, :, _SIN_PSI] = np.sin(Xi[:, hull.IX_PSI])
            O[i, :, _COS_PSI] = np.cos(Xi[:, hull.IX_PSI])
        meta = dict(demos.episodes[i]) if demos.episodes else {}
        meta["task_frame"] = {"origin": origin.tolist(), "course": angle}
        metas.append(meta)
    return DemoSet(
        X=X,
        U=np.array(demos.U),
        O=O,
        mask=np.array(demos.mask),
        dt=demos.dt,
        env=demos.env,
        episodes=tuple(metas),
    )


def closest_approach(X: np.ndarray, mask: np.ndarray) -> int:
    """Index of the valid step of ``X: [T+1, dX]`` nearest to the pole."""
    d = np.hypot(*(X[:, hull.IX_PX : hull.IX_PY + 1] - X[:, hull.SL_OBS]).T)
    return int(np.argmin(np.where(mask > 0, d, np.inf)))


def _window_starts(demos: DemoSet, before: int, after: int, warn: bool) -> list[tuple[int, int]]:
    """(episode, first step) of every episode with a full valid window (see
    :func:`pass_windows`), warning about the others when ``warn``."""
    keep = []
    for i in range(demos.num_episodes):
        k = closest_approach(demos.X[i], demos.mask[i])
        a, b = k - before, k + after
        if a < 0 or b >= demos.X.shape[1] or not np.all(demos.mask[i, a : b + 1] > 0):
            if warn:
                meta = demos.episodes[i] if demos.episodes else {}
                name = meta.get("source", f"episode {i}")
                warnings.warn(
                    f"{name}: episode {meta.get('episode', i)} has no valid window of {before} "
                    f"steps before and {after} after its closest approach (step {k}); left out",
                    stacklevel=3,
                )
            continue
        keep.append((i, a))
    return keep


def pass_windows(demos: DemoSet, before: int, after: int) -> DemoSet:
    """Each episode cropped to ``before`` steps before and ``after`` steps after its closest
    approach to the pole (horizon ``before + after``), keeping only windows whose every step is
    valid. Episodes that are too short on either side are left out with a warning naming them;
    the metadata records ``window = [first, last]`` (steps of the episode) and ``recorded_after``,
    the steps recorded past the window's last before the recording ends or has a gap."""
    keep = _window_starts(demos, before, after, warn=True)
    if not keep:
        raise DemoError(f"pass windows: no episode has {before} + {after} valid steps")
    T = before + after
    metas = []
    for i, a in keep:
        meta = dict(demos.episodes[i]) if demos.episodes else {}
        meta["window"] = [int(a), int(a + T)]
        meta["recorded_after"] = _valid_steps_from(demos.mask[i], a + T) - 1
        metas.append(meta)
    X = np.stack([demos.X[i, a : a + T + 1] for i, a in keep])
    U = np.stack([demos.U[i, a : a + T] for i, a in keep])
    O = np.stack([demos.O[i, a : a + T + 1] for i, a in keep])
    mask = np.stack([demos.mask[i, a : a + T + 1] for i, a in keep])
    return DemoSet(X=X, U=U, O=O, mask=mask, dt=demos.dt, env=demos.env, episodes=tuple(metas))


def _valid_steps_from(mask: np.ndarray, step: int, at_most: int | None = None) -> int:
    """How many steps of one episode's ``mask`` are valid in a row from ``step`` on (``step``
    itself valid), up to ``at_most``."""
    valid = mask[step:] > 0 if at_most is None else mask[step : step + at_most] > 0
    return int(np.argmin(valid)) if not valid.all() else int(valid.size)


def pass_tails(demos: DemoSet, before: int, after: int, length: int) -> np.ndarray:
    """The states recorded past each of :func:`pass_windows`' windows (same episodes, same
    order): ``[N, length+1, dX]`` from the window's last state on, up to ``length`` steps,
    padded with the episode's last recorded state where it ends sooner. A gap in the recording
    ends the tail at the last valid step before it."""
    if length < 0:
        raise ValueError(f"pass tails: length {length} must be >= 0")
    T = before + after
    tails = []
    for i, a in _window_starts(demos, before, after, warn=False):
        b = a + T
        n = _valid_steps_from(demos.mask[i], b, length + 1)
        tail = demos.X[i, b : b + n]
        pad = np.broadcast_to(tail[-1], (length + 1 - n, tail.shape[-1]))
        tails.append(np.concatenate([tail, pad]))
    return np.stack(tails)
