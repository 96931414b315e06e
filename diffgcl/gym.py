"""A learned diffgcl cost as a reward for gymnasium and RL libraries (optional extra ``gym``).

A cost learned by :func:`diffgcl.api.learn` is a JAX function ``c(x, u, t)`` of the MJX state
``x`` and the normalised action ``u = ctrl / ctrl_scale``. An RL library sees neither: it sees
gymnasium's observation and gymnasium's action (MuJoCo's ``ctrl``). This module bridges the two:

* :data:`OBS_TO_STATE`: the map from gymnasium's observation to the state, per MuJoCo task
  (:func:`reacher_state`, :func:`inverted_pendulum_state`, :func:`inverted_double_pendulum_state`;
  your own task: any function ``obs [..., dO] -> x [..., dX]``);
* :class:`LearnedCostReward`: ``r = −c(x(obs), act / ctrl_scale, t)``, a callable with the
  signature of imitation's ``RewardFn``: ``(obs [B, dO], acts [B, dU], next_obs, dones) ->
  rewards [B]`` (NumPy in, NumPy out);
* :func:`learned_cost_env`: a ``gymnasium.Wrapper`` whose reward is that function on the step's
  observation and action (gymnasium's own reward kept in ``info["true_reward"]``), so that
  stable-baselines3's PPO can train on the learned cost;
* :class:`PlainTrajectory` with :func:`save_trajectories` / :func:`load_trajectories`: episodes
  with the fields of imitation's ``Trajectory`` (``obs [T+1, dO]``, ``acts [T, dU]``, ``infos``,
  ``terminal``) in an npz file, readable without imitation; :func:`to_imitation` and
  :func:`from_imitation` convert where imitation is installed.

gymnasium is imported only when a wrapper is built, torch and imitation only by
:func:`to_imitation` / :func:`from_imitation`.

The observation-to-state maps (gymnasium's v5 MuJoCo envs; v4's extra entries are ignored):

=========================  ==============================================  ======================
task                       gymnasium's observation                         state ``x``
=========================  ==============================================  ======================
Reacher                    ``cos q₁, cos q₂, sin q₁, sin q₂, target x, y,  ``q₁, q₂, target x, y,
                           q̇₁, q̇₂, fingertip − target (x, y[, z])``         q̇₁, q̇₂, 0, 0``
InvertedPendulum           ``qpos (cart, hinge), qvel``                    the observation
InvertedDoublePendulum     ``cart, sin θ₁, sin θ₂, cos θ₁, cos θ₂, clip(   ``cart, θ₁, θ₂, clip(q̇,
                           q̇, ±10), constraint forces``                    ±10)``
=========================  ==============================================  ======================

Angles come back through ``atan2`` in ``(−π, π]``: a reacher joint that wound past ±π (joint 1
has no limit) is seen at its principal angle. The reacher's target does not move (its velocity
is 0), the double pendulum's velocities are clipped at ±10 as gymnasium reports them.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

TRAJECTORY_FORMAT = "diffgcl-trajectories/1"


# ---- gymnasium's observations -> the MJX state -----------------------------------------------


def reacher_state(obs):
    """Reacher: obs [..., 10 or 11] -> x [..., 8] (``q₁, q₂, target, q̇₁, q̇₂, target velocity
    0``)."""
    obs = np.asarray(obs)
    q = np.arctan2(obs[..., 2:4], obs[..., 0:2])
    zeros = np.zeros((*obs.shape[:-1], 2), obs.dtype)
    return np.concatenate([q, obs[..., 4:6], obs[..., 6:8], zeros], axis=-1)


def inverted_pendulum_state(obs):
    """InvertedPendulum: obs [..., 4] = ``[qpos, qvel]`` is the state."""
    return np.asarray(obs)[..., :4]


def inverted_double_pendulum_state(obs):
    """InvertedDoublePendulum: obs [..., 9 or 11] -> x [..., 6] (``cart, θ₁, θ₂`` and the
    velocities as gymnasium clips them)."""
    obs = np.asarray(obs)
    theta = np.arctan2(obs[..., 1:3], obs[..., 3:5])
    return np.concatenate([obs[..., 0:1], theta, obs[..., 5:8]], axis=-1)


OBS_TO_STATE: dict[str, Callable] = {
    "Reacher": reacher_state,
    "InvertedPendulum": inverted_pendulum_state,
    "InvertedDoublePendulum": inverted_double_pendulum_state,
}


def state_map(env_id: str) -> Callable:
    """The observation-to-state map of a gymnasium id such as ``"Reacher-v5"``."""
    name = env_id.split("/")[-1].split("-")[0]
    if name not in OBS_TO_STATE:
        raise KeyError(f"no observation-to-state map for {env_id!r}; known: {sorted(OBS_TO_STATE)}")
    return OBS_TO_STATE[name]


# ---- the learned cost as a reward -------------------------------------------------------------


class LearnedCostReward:
    """``r = −scale · c(x(obs), act / ctrl_scale, t)`` for batches, imitation's ``RewardFn``.

    cost: ``c(x, u, t)`` (a JAX function, e.g. ``LearnedRun.learned_cost()``); state_from_obs:
    ``obs [B, dO] -> x [B, dX]`` (:data:`OBS_TO_STATE`); ctrl_scale: [dU] (the env's
    ``ctrl_scale``: gymnasium's action is MuJoCo's ``ctrl``; None: the action is ``u``);
    time: the ``t`` handed to the cost when the caller gives none (a learned cost without a time
    input ignores it); scale: a positive factor on the reward.
    """

    def __init__(
        self,
        cost: Callable,
        state_from_obs: Callable,
        ctrl_scale=None,
        *,
        time: int = 0,
        scale: float = 1.0,
    ):
        import jax
        import jax.numpy as jnp

        self.cost = cost
        self.state_from_obs = state_from_obs
        self.ctrl_scale = None if ctrl_scale is None else np.asarray(ctrl_scale, np.float64)
        self.time = int(time)
        self.scale = float(scale)
        self._batched = jax.jit(jax.vmap(lambda x, u, t: cost(x, u, t)))
        self._dtype = jnp.zeros(()).dtype

    def state(self, obs) -> np.ndarray:
        """x [B, dX] of obs [B, dO]."""
        return np.asarray(self.state_from_obs(np.atleast_2d(np.asarray(obs))), np.float64)

    def __call__(self, obs, acts, next_obs=None, dones=None, *, t=None) -> np.ndarray:
        """rewards [B] (float32) of obs [B, dO], acts [B, dU]; ``t`` [B] or a scalar."""
        x = self.state(obs)
        u = np.atleast_2d(np.asarray(acts, np.float64))
        if self.ctrl_scale is not None:
            u = u / self.ctrl_scale
        B = x.shape[0]
        t = np.full((B,), self.time) if t is None else np.broadcast_to(np.asarray(t), (B,))
        c = self._batched(x.astype(self._dtype), u.astype(self._dtype), t.astype(np.int32))
        return (-self.scale * np.asarray(c, np.float64)).astype(np.float32)


def reward_from_run(run, env_id: str, *, seed_index: int = 0, scale: float = 1.0):
    """The :class:`LearnedCostReward` of a :class:`~diffgcl.api.LearnedRun` on gymnasium's
    ``env_id`` (its observation map and the run's env's ``ctrl_scale``)."""
    return LearnedCostReward(
        run.learned_cost(seed_index), state_map(env_id), run.env.ctrl_scale, scale=scale
    )


def learned_cost_env(env, reward: Callable):
    """``env`` (a gymnasium env) with its reward replaced by ``reward(obs, act, next_obs, done,
    t=step)`` on each step's observation before the action (one-element batches); gymnasium's
    own reward is kept in ``info["true_reward"]``, the step's index within the episode is
    passed as ``t``."""
    return _wrapper_class()(env, reward)


_WRAPPER = None


def _wrapper_class():
    global _WRAPPER
    if _WRAPPER is None:
        import gymnasium

        class LearnedCostWrapper(gymnasium.Wrapper):
            """gymnasium env whose reward is a learned diffgcl cost, negated."""

            def __init__(self, env, reward):
                super().__init__(env)
                self.reward_fn = reward
                self._obs = None
                self._t = 0

            def reset(self, **kwargs):
                obs, info = self.env.reset(**kwargs)
                self._obs, self._t = obs, 0
                return obs, info

            def step(self, action):
                obs, true_reward, terminated, truncated, info = self.env.step(action)
                done = np.asarray([terminated or truncated])
                r = self.reward_fn(
                    np.asarray(self._obs)[None],
                    np.asarray(action)[None],
                    np.asarray(obs)[None],
                    done,
                    t=np.asarray([self._t]),
                )
                info = dict(info, true_reward=true_reward)
                self._obs, self._t = obs, self._t + 1
                return obs, float(r[0]), terminated, truncated, info

        _WRAPPER = LearnedCostWrapper
    return _WRAPPER


# ---- trajectories with imitation's fields ----------------------------------------------------


@dataclasses.dataclass(frozen=True)
class PlainTrajectory:
    """One episode with the fields of imitation's ``Trajectory``: obs [T+1, dO], acts [T, dU],
    infos (None or T dicts), terminal (the episode ended in a terminal state)."""

    obs: np.ndarray
    acts: np.ndarray
    infos: Sequence[dict] | None = None
    terminal: bool = True

    def __post_init__(self):
        obs, acts = np.asarray(self.obs), np.asarray(self.acts)
        if obs.ndim != 2 or acts.ndim != 2 or obs.shape[0] != acts.shape[0] + 1:
            raise ValueError(
                f"trajectory: obs must be [T+1, dO] and acts [T, dU]; got {obs.shape}, {acts.shape}"
            )
        if self.infos is not None and len(self.infos) != acts.shape[0]:
            raise ValueError(f"trajectory: {len(self.infos)} infos for {acts.shape[0]} actions")
        object.__setattr__(self, "obs", obs)
        object.__setattr__(self, "acts", acts)


def save_trajectories(path: str | os.PathLike, trajectories: Sequence[Any]) -> Path:
    """Write trajectories (:class:`PlainTrajectory`, imitation's ``Trajectory`` or anything with
    ``obs``, ``acts``, ``infos``, ``terminal``) to an npz file; infos must hold JSON values."""
    import json

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {"format": np.asarray(TRAJECTORY_FORMAT)}
    for i, tr in enumerate(trajectories):
        arrays[f"obs_{i}"] = np.asarray(tr.obs)
        arrays[f"acts_{i}"] = np.asarray(tr.acts)
        arrays[f"terminal_{i}"] = np.asarray(bool(tr.terminal))
        infos = None if tr.infos is None else [dict(d) for d in tr.infos]
        arrays[f"infos_{i}"] = np.asarray(json.dumps(infos))
    arrays["count"] = np.asarray(len(trajectories))
    np.savez_compressed(path, **arrays)
    return path


def load_trajectories(path: str | os.PathLike) -> list[PlainTrajectory]:
    """The trajectories of :func:`save_trajectories`."""
    import json

    with np.load(path, allow_pickle=False) as f:
        if str(f.get("format", "")) != TRAJECTORY_FORMAT:
            raise ValueError(f"{path}: not a {TRAJECTORY_FORMAT} file")
        return [
            PlainTrajectory(
                obs=f[f"obs_{i}"],
                acts=f[f"acts_{i}"],
                infos=json.loads(str(f[f"infos_{i}"])),
                terminal=bool(f[f"terminal_{i}"]),
            )
            for i in range(int(f["count"]))
        ]


def to_imitation(trajectories: Sequence[Any]) -> list:
    """imitation's ``Trajectory`` objects (imitation must be installed)."""
    from imitation.data.types import Trajectory

    return [
        Trajectory(
            obs=np.asarray(tr.obs),
            acts=np.asarray(tr.acts),
            infos=None if tr.infos is None else np.asarray(list(tr.infos), dtype=object),
            terminal=bool(tr.terminal),
        )
        for tr in trajectories
    ]


def from_imitation(trajectories: Sequence[Any]) -> list[PlainTrajectory]:
    """:class:`PlainTrajectory` copies of imitation's (or any) trajectories."""
    return [
        PlainTrajectory(
            obs=np.asarray(tr.obs),
            acts=np.asarray(tr.acts),
            infos=None if tr.infos is None else [dict(d) for d in tr.infos],
            terminal=bool(tr.terminal),
        )
        for tr in trajectories
    ]
