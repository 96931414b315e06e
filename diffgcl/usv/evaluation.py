"""Held-out situations for the USV task and the policies' rollouts from them.

:class:`SituationRanges` takes the ranges of the demos' window starts (pole distance, the boat's
lateral offset and heading, speed, pole radius); :func:`heldout_starts` draws situations none of
the demos had from them, each quantity independently; :func:`policy_tracks` rolls global policies
out from such starts with the env's sensor noise. Scoring the tracks is
:mod:`diffgcl.usv.scores`.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.data.demos import DemoSet
from diffgcl.envs.usv import UsvEnv
from diffgcl.sim import hull as hull_sim
from diffgcl.types import Array, PRNGKey


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

    def widened(self, radius=(0.2, 1.5), offset_scale: float = 1.5) -> SituationRanges:
        """Situations the pipeline never tuned on: the pole's radius from ``radius`` and the
        boat's lateral offset over ``offset_scale`` × the demos' range (about its centre); the
        pole distance, heading and speed as the demos'."""
        centre = 0.5 * (self.offset[0] + self.offset[1])
        half = 0.5 * (self.offset[1] - self.offset[0]) * offset_scale
        return SituationRanges(
            distance=self.distance,
            offset=(centre - half, centre + half),
            heading=self.heading,
            speed=self.speed,
            radius=(float(radius[0]), float(radius[1])),
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


def policy_tracks(env: UsvEnv, policy, params, x0, keys: Array) -> np.ndarray:
    """Noise-free-action rollouts [S, B, T+1, 11] of global policies (``params`` with a leading
    seed axis S, one key each in ``keys: [S, 2]``) from ``x0: [B, 11]``, with the env's sensor
    noise in their observations (the boat's sensors are never noise-free); the env's staged
    simulator runs them (one compiled program for every policy of these settings)."""
    from diffgcl.algorithms.staged import policy_rollouts

    traj = policy_rollouts(env, policy, params, x0, keys, obs_noise=True)
    return np.asarray(traj.X)
