"""Agreement of two sets of range beams, e.g. simulated observations against those ingestion made
of a bag at the same states (the USV task's policy trains on the first and its cloned baseline
on the second, so they must agree; see :class:`diffgcl.sim.sensors.PoleSensorModel`).

A beam *sees* something when it reads less than its maximum range. For the LiDAR fan the
statistics are over the beams that both sets see (the range error ``other − reference``) and
over all beams (whether both see the same ones); for the radar fan, whose pole is one point
target, over the steps where the reference sees the pole: does the other set read it in the
same sector, in any sector, and how far off. Host-side NumPy, except :func:`demo_beams`, which
evaluates the env's observation at the states of ingested demos.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.envs.usv import IX_RADIUS, make_usv_env, pole_ranges
from diffgcl.sim import hull as hull_sim


def demo_beams(demos, radii: np.ndarray, key: jax.Array) -> dict[str, np.ndarray]:
    """Ingested and simulated beams at every valid, collision-free step of ``demos`` (a hull
    :class:`~diffgcl.data.demos.DemoSet` in the task frame, observations in the default layout)
    with the episodes' pole radii ``radii: [N]`` (m; e.g. the generator's truth).

    Returns [K, num_beams] arrays ``ingested`` (the demos' beams), ``simulated`` (``env.obs(x)``,
    noise-free), ``noisy`` (``env.obs(x, key)``, one draw per step) and ``exact`` (the exact
    pole geometry, :func:`~diffgcl.envs.usv.pole_ranges`, equal to ``mjx.ray``), and [K]
    ``distance`` (m, from the sensor origin to the pole's centre), ``episode`` and ``confirmed``
    (at or after the episode's first ingested radar reading: before it the radar's clutter
    filter has not confirmed the pole). States where the hull touches the pole are left out.
    """
    env = make_usv_env(np.concatenate([demos.X[:, 0], np.asarray(radii)[:, None]], axis=1))
    layout = env.layout
    nL, nB = layout.lidar_beams, layout.num_beams
    obs = jax.jit(jax.vmap(env.obs))
    noisy = jax.jit(jax.vmap(env.obs))
    exact = jax.jit(jax.vmap(lambda x: pole_ranges(layout, x[:IX_RADIUS], x[IX_RADIUS])))
    clearance = jax.jit(jax.vmap(env.clearance))
    out: dict[str, list] = {k: [] for k in ("ingested", "simulated", "noisy", "exact")}
    out.update(distance=[], episode=[], confirmed=[])
    for i in range(demos.num_episodes):
        X = np.concatenate([demos.X[i], np.full((demos.X.shape[1], 1), radii[i])], axis=1)
        keep = (demos.mask[i] > 0) & (np.asarray(clearance(jnp.asarray(X))) > 0)
        X, O = jnp.asarray(X[keep]), demos.O[i][keep]
        key, k_obs = jax.random.split(key)
        out["ingested"].append(O[:, :nB])
        out["simulated"].append(np.asarray(obs(X))[:, :nB])
        out["noisy"].append(np.asarray(noisy(X, jax.random.split(k_obs, X.shape[0])))[:, :nB])
        out["exact"].append(np.asarray(exact(X)))
        Xn = np.asarray(X)
        rel = Xn[:, hull_sim.SL_OBS] - Xn[:, :2]
        c, s = np.cos(Xn[:, hull_sim.IX_PSI]), np.sin(Xn[:, hull_sim.IX_PSI])
        along, across = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]
        out["distance"].append(np.hypot(along - layout.origin[0], across - layout.origin[1]))
        radar_seen = (O[:, nL:nB] < layout.radar_range).any(axis=1)
        first = int(np.argmax(radar_seen)) if radar_seen.any() else len(O)
        out["confirmed"].append(np.arange(len(O)) >= first)
        out["episode"].append(np.full(len(O), i))
    return {k: np.concatenate(v) for k, v in out.items()}


def lidar_agreement(reference: np.ndarray, other: np.ndarray, max_range: float) -> dict:
    """Statistics of LiDAR beams ``other: [K, B]`` against ``reference: [K, B]`` (m).

    ``median_m``, ``mean_m``, ``std_m``, ``q95_abs_m``: the error ``other − reference`` over
    the ``beams_both`` beams that both see; ``seen_agreement``: fraction of all beams where both
    see or both do not; ``missed``: fraction of the beams the reference sees that the other does
    not; ``extra``: fraction of the beams the other sees that the reference does not;
    ``seen_per_step``: mean number of beams that see, (reference, other).
    """
    ref_seen, oth_seen = reference < max_range, other < max_range
    both = ref_seen & oth_seen
    err = (other - reference)[both]
    finite = err.size > 0
    return {
        "beams_both": int(both.sum()),
        "median_m": float(np.median(err)) if finite else float("nan"),
        "mean_m": float(np.mean(err)) if finite else float("nan"),
        "std_m": float(np.std(err)) if finite else float("nan"),
        "q95_abs_m": float(np.quantile(np.abs(err), 0.95)) if finite else float("nan"),
        "seen_agreement": float(np.mean(ref_seen == oth_seen)),
        "missed": float(np.sum(ref_seen & ~oth_seen) / max(ref_seen.sum(), 1)),
        "extra": float(np.sum(oth_seen & ~ref_seen) / max(oth_seen.sum(), 1)),
        "seen_per_step": (float(ref_seen.sum(1).mean()), float(oth_seen.sum(1).mean())),
    }


def radar_agreement(reference: np.ndarray, other: np.ndarray, max_range: float) -> dict:
    """Statistics of radar beams ``other: [K, B]`` against ``reference: [K, B]`` (m), where the
    reference sees one point target (the pole) in at most one beam per step.

    Over the ``steps`` where the reference sees it: ``same_beam``, the fraction where the other
    reads something in that beam; ``any_beam``, in any beam; ``median_m``, ``std_m``,
    ``q95_abs_m``: the error in that beam where both read; ``other_beams_free``: the fraction of
    the remaining beams the other reads as free (maximum range).
    """
    ref_seen = reference < max_range
    steps = ref_seen.any(axis=1)
    beam = np.argmin(reference, axis=1)
    k = np.flatnonzero(steps)
    ref, oth = reference[k, beam[k]], other[k, beam[k]]
    same = oth < max_range
    err = (oth - ref)[same]
    finite = err.size > 0
    rest = ~ref_seen
    return {
        "steps": int(k.size),
        "same_beam": float(same.mean()) if k.size else float("nan"),
        "any_beam": float((other[k] < max_range).any(axis=1).mean()) if k.size else float("nan"),
        "median_m": float(np.median(err)) if finite else float("nan"),
        "std_m": float(np.std(err)) if finite else float("nan"),
        "q95_abs_m": float(np.quantile(np.abs(err), 0.95)) if finite else float("nan"),
        "other_beams_free": float(np.mean(other[rest] >= max_range)) if rest.any() else 1.0,
    }
