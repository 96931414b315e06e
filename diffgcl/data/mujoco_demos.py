"""Demonstrations of your own robot, in MuJoCo's terms, turned into a :class:`DemoSet`.

Two simple formats beside diffgcl's own dataset folder (:mod:`diffgcl.data.demos`), both checked
once on the host against the model of a :class:`~diffgcl.envs.mjcf_env.MJCFEnv`, every problem a
one-line :class:`~diffgcl.data.demos.DemoError` that names the file, the episode, the array and
the step:

* **npz of MuJoCo arrays** (:func:`demos_from_npz`). Either stacked arrays
  ``qpos: [N, T+1, nq]``, ``qvel: [N, T+1, nv]``, ``ctrl: [N, T, nu]`` (and ``act: [N, T+1, na]``
  for a model with actuator activations), or one set per episode, ``qpos_0, qvel_0, ctrl_0,
  qpos_1, ...`` (episodes may then differ in length; ``horizon`` cuts them to a common one).
  Optional: ``condition: [N]`` integers grouping episodes that share a start state, and ``dt``
  (seconds per control step; checked against the env's). ``ctrl[t]`` is the control applied
  between ``qpos[t]`` and ``qpos[t+1]``. Write one with :func:`save_npz`.
* **(observations, actions) pairs as the imitation library keeps them**
  (:func:`demos_from_trajectories`): a list whose items are ``(obs, acts)`` tuples or objects with
  ``.obs: [T+1, d]`` and ``.acts: [T, nu]`` (imitation's ``Trajectory``). The observation must be
  MuJoCo's state ``[qpos, qvel(, act)]`` unless ``state_from_obs`` maps one episode's
  observations to ``(qpos, qvel)`` (or ``(qpos, qvel, act)``).

Checks: array present, 2-D with the model's width, ``T+1`` states for ``T`` controls, at least
one control step, finite values, unit quaternions (within 1e-3; then normalised), controls inside
the ranges of ctrl-limited actuators, a common length, the env's ``dt``. The states are converted
with the env's chart (quaternions to rotation vectors) and the controls to its actions
(``ctrl / ctrl_scale``).
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.data.demos import DemoError, DemoSet

QUATERNION_TOLERANCE = 1e-3


def _as_2d(where: str, name: str, value, width: int) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise DemoError(f"{where}: {name} is not a numeric array") from None
    if a.ndim == 1 and width == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[1] != width:
        raise DemoError(f"{where}: {name} must be [steps, {width}], got shape {a.shape}")
    return a


def _check_episode(where: str, env, qpos, qvel, ctrl, act) -> tuple[np.ndarray, ...]:
    """Validated float arrays of one episode (quaternions normalised)."""
    qpos = _as_2d(where, "qpos", qpos, env.nq)
    qvel = _as_2d(where, "qvel", qvel, env.nv)
    ctrl = _as_2d(where, "ctrl", ctrl, env.dU)
    if env.na:
        if act is None:
            raise DemoError(f"{where}: the model has {env.na} actuator activations; give act")
        act = _as_2d(where, "act", act, env.na)
    else:
        act = np.zeros((qpos.shape[0], 0))
    n = qpos.shape[0]
    if n < 2:
        raise DemoError(f"{where}: {n} state(s); need at least 2 (one control step)")
    for name, a in (("qvel", qvel), ("act", act)):
        if a.shape[0] != n:
            raise DemoError(f"{where}: {name} has {a.shape[0]} steps, qpos {n}; they must match")
    if ctrl.shape[0] != n - 1:
        raise DemoError(
            f"{where}: ctrl has {ctrl.shape[0]} steps for {n} states; need {n - 1} (one fewer)"
        )
    for name, a in (("qpos", qpos), ("qvel", qvel), ("ctrl", ctrl), ("act", act)):
        bad = ~np.isfinite(a)
        if bad.any():
            t, j = np.argwhere(bad)[0]
            raise DemoError(f"{where}: non-finite {name}[{t}, {j}] = {a[t, j]}")
    chart = env.chart
    for joint, idx in zip(chart.joint_names, chart.quat_qpos, strict=True):
        norm = np.linalg.norm(qpos[:, idx], axis=1)
        off = np.abs(norm - 1.0) > QUATERNION_TOLERANCE
        if off.any():
            t = int(np.argmax(off))
            raise DemoError(
                f"{where}: qpos[{t}, {idx[0]}:{idx[-1] + 1}] (joint {joint!r}) is a quaternion of "
                f"norm {norm[t]:.4g}, not 1"
            )
        qpos[:, idx] /= norm[:, None]
    low, high = env.ctrl_range[:, 0], env.ctrl_range[:, 1]
    slack = 1e-6 * np.maximum(1.0, np.abs(env.ctrl_range).clip(max=1e12))
    out = (ctrl < low - slack[:, 0]) | (ctrl > high + slack[:, 1])
    if out.any():
        t, j = np.argwhere(out)[0]
        raise DemoError(
            f"{where}: ctrl[{t}, {j}] = {ctrl[t, j]:.6g} outside the ctrlrange "
            f"[{low[j]:g}, {high[j]:g}] of actuator {env.actuator_names[j]!r}"
        )
    return qpos, qvel, ctrl, act


def demos_from_arrays(
    env,
    qpos: Sequence,
    qvel: Sequence,
    ctrl: Sequence,
    *,
    act: Sequence | None = None,
    condition: Sequence[int] | None = None,
    horizon: int | None = None,
    source: str = "demos",
) -> DemoSet:
    """A DemoSet from per-episode MuJoCo arrays (``qpos[i]: [T_i+1, nq]`` ...; or stacked
    ``[N, T+1, nq]``); ``source`` names the data in errors and metadata."""
    n = len(qpos)
    if n == 0:
        raise DemoError(f"{source}: no episodes")
    for name, seq in (("qvel", qvel), ("ctrl", ctrl), ("act", act), ("condition", condition)):
        if seq is not None and len(seq) != n:
            raise DemoError(f"{source}: {len(seq)} {name} entries for {n} qpos episodes")
    episodes = [
        _check_episode(
            f"{source}: episode {i}",
            env,
            qpos[i],
            qvel[i],
            ctrl[i],
            None if act is None else act[i],
        )
        for i in range(n)
    ]
    lengths = [e[2].shape[0] for e in episodes]
    if horizon is None:
        if len(set(lengths)) > 1:
            i = int(np.argmax(np.asarray(lengths) != lengths[0]))
            raise DemoError(
                f"{source}: episodes differ in length (episode 0: {lengths[0]} control steps, "
                f"episode {i}: {lengths[i]}); pass horizon= to cut them to a common length"
            )
        horizon = lengths[0]
    short = [i for i, length in enumerate(lengths) if length < horizon]
    if short:
        i = short[0]
        raise DemoError(f"{source}: episode {i} has {lengths[i]} control steps, fewer than the "
                        f"horizon {horizon}")  # fmt: skip
    T = int(horizon)
    qpos_a = np.stack([e[0][: T + 1] for e in episodes])
    qvel_a = np.stack([e[1][: T + 1] for e in episodes])
    ctrl_a = np.stack([e[2][:T] for e in episodes])
    act_a = np.stack([e[3][: T + 1] for e in episodes])
    dtype = jnp.asarray(env.initial_states()).dtype
    to_state = jax.jit(jax.vmap(jax.vmap(env.state_from_mujoco)))
    X = np.asarray(to_state(jnp.asarray(qpos_a, dtype), jnp.asarray(qvel_a, dtype),
                            jnp.asarray(act_a, dtype)))  # fmt: skip
    U = np.asarray(env.action_from_ctrl(ctrl_a), dtype=X.dtype)
    O = np.asarray(jax.jit(jax.vmap(jax.vmap(env.obs)))(jnp.asarray(X)))
    if condition is not None:
        condition = np.asarray(condition)
        if condition.shape != (n,) or not np.issubdtype(condition.dtype, np.integer):
            raise DemoError(f"{source}: condition must be {n} integers, got {condition!r}")
        if condition.min() < 0:
            raise DemoError(f"{source}: condition must be >= 0, got {condition.min()}")
    meta = tuple(
        {"source": str(source), "episode": i}
        | ({} if condition is None else {"condition": int(condition[i])})
        for i in range(n)
    )
    return DemoSet(
        X=X,
        U=U,
        O=O,
        mask=np.ones(X.shape[:2], np.float32),
        dt=float(f"{float(env.dt):.7g}"),
        env=env.name,
        episodes=meta,
    )


def _check_dt(where: str, dt, env) -> None:
    dt = float(np.asarray(dt))
    if not np.isclose(dt, env.dt, rtol=1e-6, atol=0.0):
        raise DemoError(
            f"{where}: dt = {dt:g} s per control step, the env steps {env.dt:g} s (choose the "
            "env's dt, a whole multiple of the model timestep, to match)"
        )


def demos_from_npz(path: str | os.PathLike, env, *, horizon: int | None = None) -> DemoSet:
    """Read the npz format of the module docstring; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise DemoError(f"{path}: demo file not found")
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise DemoError(f"{path}: not a readable npz file ({err})") from None
    if "dt" in arrays:
        _check_dt(str(path), arrays["dt"], env)
    keys = ("qpos", "qvel", "ctrl", "act")
    if "qpos" in arrays:
        missing = [k for k in ("qvel", "ctrl") if k not in arrays]
        if missing:
            raise DemoError(f"{path}: no {missing[0]!r} array (has {', '.join(sorted(arrays))})")
        for k in keys:
            if k in arrays and arrays[k].ndim not in (2, 3):
                raise DemoError(f"{path}: {k} must be [N, steps, d], got shape {arrays[k].shape}")
        seqs = {k: list(arrays[k]) if k in arrays else None for k in keys}
    else:
        n = 0
        while f"qpos_{n}" in arrays:
            n += 1
        if n == 0:
            raise DemoError(
                f"{path}: no 'qpos' (stacked) or 'qpos_0' (per episode) array "
                f"(has {', '.join(sorted(arrays)) or 'nothing'})"
            )
        seqs = {}
        for k in keys:
            present = [f"{k}_{i}" in arrays for i in range(n)]
            if k == "act" and not any(present):
                seqs[k] = None
                continue
            if not all(present):
                raise DemoError(f"{path}: no {k}_{present.index(False)} array for episode "
                                f"{present.index(False)}")  # fmt: skip
            seqs[k] = [arrays[f"{k}_{i}"] for i in range(n)]
    condition = arrays.get("condition")
    return demos_from_arrays(
        env,
        seqs["qpos"],
        seqs["qvel"],
        seqs["ctrl"],
        act=seqs["act"],
        condition=None if condition is None else condition.tolist(),
        horizon=horizon,
        source=str(path),
    )


def save_npz(
    path: str | os.PathLike,
    qpos,
    qvel,
    ctrl,
    *,
    act=None,
    condition=None,
    dt: float | None = None,
) -> Path:
    """Write demos in the npz format: stacked arrays ``[N, ...]`` (NumPy arrays) or lists of
    per-episode arrays (written as ``qpos_0, qvel_0, ...``)."""
    path = Path(path)
    arrays = {}
    stacked = all(isinstance(a, np.ndarray) and a.ndim == 3 for a in (qpos, qvel, ctrl))
    for name, value in (("qpos", qpos), ("qvel", qvel), ("ctrl", ctrl), ("act", act)):
        if value is None:
            continue
        if stacked:
            arrays[name] = np.asarray(value)
        else:
            arrays.update({f"{name}_{i}": np.asarray(a) for i, a in enumerate(value)})
    if condition is not None:
        arrays["condition"] = np.asarray(condition, dtype=np.int64)
    if dt is not None:
        arrays["dt"] = np.asarray(float(dt))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path


def demos_from_trajectories(
    episodes: Sequence,
    env,
    *,
    state_from_obs: Callable | None = None,
    condition: Sequence[int] | None = None,
    horizon: int | None = None,
    source: str = "trajectories",
) -> DemoSet:
    """A DemoSet from ``(obs, acts)`` pairs or imitation-style trajectories (``.obs``,
    ``.acts``); see the module docstring."""
    if len(episodes) == 0:
        raise DemoError(f"{source}: no episodes")
    width = env.nq + env.nv + env.na
    qpos, qvel, ctrl, act = [], [], [], []
    for i, item in enumerate(episodes):
        where = f"{source}: episode {i}"
        if hasattr(item, "obs") and hasattr(item, "acts"):
            obs, acts = item.obs, item.acts
        elif isinstance(item, tuple | list) and len(item) == 2:
            obs, acts = item
        else:
            raise DemoError(f"{where}: expected an (obs, acts) pair or an object with .obs and "
                            f".acts, got {type(item).__name__}")  # fmt: skip
        if state_from_obs is not None:
            parts = state_from_obs(np.asarray(obs))
            if not isinstance(parts, tuple | list) or len(parts) not in (2, 3):
                raise DemoError(f"{where}: state_from_obs must return (qpos, qvel) or (qpos, "
                                "qvel, act)")  # fmt: skip
            qpos.append(parts[0])
            qvel.append(parts[1])
            act.append(parts[2] if len(parts) == 3 else None)
        else:
            o = np.asarray(obs, dtype=float)
            if o.ndim != 2 or o.shape[1] != width:
                raise DemoError(
                    f"{where}: obs must be MuJoCo's state [steps, nq + nv + na = {width}], got "
                    f"shape {o.shape}; pass state_from_obs= to map your observations"
                )
            qpos.append(o[:, : env.nq])
            qvel.append(o[:, env.nq : env.nq + env.nv])
            act.append(o[:, env.nq + env.nv :])
        ctrl.append(acts)
    return demos_from_arrays(
        env,
        qpos,
        qvel,
        ctrl,
        act=act if env.na else None,
        condition=condition,
        horizon=horizon,
        source=source,
    )


def load_demos(path: str | os.PathLike, env, *, horizon: int | None = None) -> DemoSet:
    """Demos for ``env`` from an npz file (this module's format) or a diffgcl dataset folder
    (:meth:`DemoSet.load`, its states checked against the env's sizes)."""
    path = Path(path)
    if path.is_dir():
        demos = DemoSet.load(path)
        if demos.X.shape[-1] != env.dX or demos.U.shape[-1] != env.dU:
            raise DemoError(
                f"{path}: states [{demos.X.shape[-1]}] and actions [{demos.U.shape[-1]}] do not "
                f"fit the env {env.name} (dX = {env.dX}, dU = {env.dU})"
            )
        return demos if horizon is None else _cut(demos, int(horizon), path)
    return demos_from_npz(path, env, horizon=horizon)


def _cut(demos: DemoSet, horizon: int, where) -> DemoSet:
    if horizon > demos.horizon:
        raise DemoError(f"{where}: horizon {horizon} is longer than the demos ({demos.horizon})")
    return DemoSet(
        X=demos.X[:, : horizon + 1],
        U=demos.U[:, :horizon],
        O=demos.O[:, : horizon + 1],
        mask=demos.mask[:, : horizon + 1],
        dt=demos.dt,
        env=demos.env,
        episodes=demos.episodes,
    )
