"""The USV task's figures of a set of rollouts against the demos: collision, minimum clearance
and its ratio to the demos', back on course, side passed, path distance to the nearest demo
(:func:`score_rollouts`), and the main ones per training seed (:func:`per_seed_figures`)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.envs.usv import IX_RADIUS, UsvEnv
from diffgcl.sim import hull as hull_sim


def path_distance_to_demos(X: np.ndarray, demo_X: np.ndarray) -> np.ndarray:
    """[B] mean distance (m) of each rollout's positions ``X: [B, T+1, 11]`` to the nearest point
    of the nearest demo path ``demo_X: [N, T+1, 11]``, both relative to their own pole."""
    P = X[..., :2] - X[:, :1, hull_sim.SL_OBS]
    Q = demo_X[..., :2] - demo_X[:, :1, hull_sim.SL_OBS]
    out = np.empty(P.shape[0])
    for b in range(P.shape[0]):
        d = np.linalg.norm(P[b][None, :, None, :] - Q[:, None, :, :], axis=-1)  # [N, T+1, T+1]
        out[b] = d.min(axis=2).mean(axis=1).min()
    return out


@functools.partial(jax.jit, static_argnums=0)
def _batch_metrics(env: UsvEnv, X):
    return jax.vmap(env.metrics)(X)


def trajectory_metrics(env: UsvEnv, X) -> dict[str, np.ndarray]:
    """:meth:`UsvEnv.metrics` of each rollout ``X: [B, T+1, 11]``, as NumPy arrays [B] (one
    compiled program per env and batch shape, however often it is called)."""
    return {k: np.asarray(v) for k, v in _batch_metrics(env, jnp.asarray(X)).items()}


def straight_side(X) -> np.ndarray:
    """The side (+1 port, −1 starboard, as :meth:`UsvEnv.metrics`' ``side``) on which each rollout
    ``X: [B, T+1, 11]`` would pass its pole if it sailed straight on from its start: the sign of
    the lateral offset from the pole at the pole's distance along the start heading."""
    return np.sign(_straight_on_offset(np.asarray(X)[:, 0]))


def _straight_on_offset(x0: np.ndarray) -> np.ndarray:
    """The lateral offset from the pole (m, + port) at which a boat in start states ``x0: [B, ≥11]``
    would pass it sailing straight on."""
    ahead = x0[:, hull_sim.IX_OBS_X] - x0[:, hull_sim.IX_PX]
    lateral = x0[:, hull_sim.IX_PY] + ahead * np.tan(x0[:, hull_sim.IX_PSI])
    return lateral - x0[:, hull_sim.IX_OBS_Y]


SITUATION_QUANTITIES = ("distance", "offset", "straight_miss", "heading", "speed", "radius")


def situations(X) -> dict[str, np.ndarray]:
    """The situation each rollout ``X: [B, T+1, ≥11]`` starts in (task frame, the first pole):
    the pole's distance ahead and the boat's lateral offset from its line (m), ``straight_miss``
    (how far from the pole's centre the boat would pass sailing straight on, m: small is
    head-on), heading (rad), speed (m/s), the pole's radius (m); each [B]."""
    x0 = np.asarray(X)[:, 0]
    return {
        "distance": x0[:, hull_sim.IX_OBS_X] - x0[:, hull_sim.IX_PX],
        "offset": x0[:, hull_sim.IX_PY] - x0[:, hull_sim.IX_OBS_Y],
        "straight_miss": np.abs(_straight_on_offset(x0)),
        "heading": x0[:, hull_sim.IX_PSI],
        "speed": np.hypot(x0[:, hull_sim.IX_VX], x0[:, hull_sim.IX_VY]),
        "radius": x0[:, IX_RADIUS],
    }


def collision_profile(X, collided, listed: int = 32) -> dict:
    """Where the collisions of rollouts ``X: [B, T+1, ≥11]`` (``collided: [B]`` bool) happen, by
    the situations they start in (:func:`situations`): for each quantity, its terciles over all
    episodes (``edges``), the episodes and collisions in each third, and the colliding episodes'
    median beside everyone's; and the first ``listed`` colliding episodes (index into ``X``, their
    situation)."""
    collided = np.asarray(collided, bool)
    sit = situations(X)
    out: dict = {"collisions": int(collided.sum())}
    for name in SITUATION_QUANTITIES:
        v = sit[name]
        edges = np.quantile(v, [1 / 3, 2 / 3])
        third = np.searchsorted(edges, v, side="right")
        out[name] = {
            "edges": edges.tolist(),
            "episodes": np.bincount(third, minlength=3).tolist(),
            "collisions": np.bincount(third[collided], minlength=3).tolist(),
            "median_all": float(np.median(v)),
            "median_colliding": float(np.median(v[collided])) if collided.any() else None,
        }
    out["colliding"] = [
        {"episode": int(i), **{name: float(sit[name][i]) for name in SITUATION_QUANTITIES}}
        for i in np.flatnonzero(collided)[:listed]
    ]
    return out


def score_rollouts(env: UsvEnv, X, demo_X, demo_env: UsvEnv | None = None) -> dict:
    """The USV figures of rollouts ``X: [B, T'+1, 11]`` against the demos ``demo_X: [N, T+1, 11]``
    (T' ≥ T: the evaluation may run past the demos' window).

    ``return_to_course_rate``: on course at the end (cross-track and heading within the env's
    tolerances, :meth:`UsvEnv.back_on_course`); ``returned_in_window_rate``: back at the course
    line within the demos' window (:meth:`UsvEnv.returned_to_course` on the first T+1 states, the
    figure the demos have too); collision rate; the median minimum clearance and its ratio to the
    demos' median; the median path distance to the nearest demo (first T+1 states); the share of
    port passes beside the demos'; ``straight_side_share``: the share that pass on the side they
    would have passed on sailing straight on (:func:`straight_side`; about 0.5 for a side picked
    at random), beside the demos'; ``turned_back_rate``: the heading more than 90° off the course
    at some step (turning round, circling); ``collision_profile``: the situations the collisions
    start in (:func:`collision_profile`; episode ``i`` of ``X``). ``demo_env`` judges the demos
    where their states are not ``env``'s (one pole, where ``env`` has two; default ``env``)."""
    X = np.asarray(X)
    T1 = demo_X.shape[1]
    m = trajectory_metrics(env, X)
    w = trajectory_metrics(env, X[:, :T1])
    d = trajectory_metrics(env if demo_env is None else demo_env, demo_X)
    demo_clearance = float(np.median(d["min_clearance"]))
    clearance = float(np.median(m["min_clearance"]))
    return {
        "episodes": int(m["collision"].shape[0]),
        "collision_rate": float(m["collision"].mean()),
        "return_to_course_rate": float(m["back_on_course"].mean()),
        "returned_in_window_rate": float(w["returned_to_course"].mean()),
        "demo_returned_in_window_rate": float(d["returned_to_course"].mean()),
        "success_rate": float(m["success"].mean()),
        "turned_back_rate": float(m["turned_back"].mean()),
        "min_clearance_median_m": clearance,
        "demo_min_clearance_median_m": demo_clearance,
        "clearance_ratio_vs_demos": clearance / demo_clearance,
        "final_cross_track_median_m": float(np.median(m["final_cross_track"])),
        "path_distance_to_demos_median_m": float(
            np.median(path_distance_to_demos(X[:, :T1], demo_X))
        ),
        "port_share": float(np.mean(m["side"] > 0)),
        "demo_port_share": float(np.mean(d["side"] > 0)),
        "straight_side_share": float(np.mean(m["side"] == straight_side(X))),
        "demo_straight_side_share": float(np.mean(d["side"] == straight_side(demo_X))),
        "collision_profile": collision_profile(X, m["collision"]),
    }


def per_seed_figures(env: UsvEnv, tracks, demo_clearance_m: float) -> dict:
    """Collision rate, on course at the end, clearance ratio (over the demos' median minimum
    clearance ``demo_clearance_m``), share of port passes and of passes on the straight-on side
    (:func:`straight_side`) of each training seed's tracks ``[S, B, T+1, 11]``, each a list over
    the seeds."""
    tracks = np.asarray(tracks)
    S = tracks.shape[0]
    flat = tracks.reshape(-1, *tracks.shape[2:])
    m = trajectory_metrics(env, flat)  # one call, all seeds
    per = {k: v.reshape(S, -1) for k, v in m.items()}
    return {
        "collision_rate": per["collision"].mean(axis=1).tolist(),
        "return_to_course_rate": per["back_on_course"].mean(axis=1).tolist(),
        "clearance_ratio_vs_demos": (
            np.median(per["min_clearance"], axis=1) / demo_clearance_m
        ).tolist(),
        "port_share": (per["side"] > 0).mean(axis=1).tolist(),
        "straight_side_share": (per["side"] == straight_side(flat).reshape(S, -1))
        .mean(axis=1)
        .tolist(),
    }
