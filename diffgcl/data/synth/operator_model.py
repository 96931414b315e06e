"""The simulated operator of the synthetic bags and the hull it sails.

**Operator** (one per episode, parameters drawn per episode, :class:`OperatorProfile`): heads
for the pole (pure pursuit) at a cruise thrust set in two steps; at a varying distance swerves
left or right by a fixed course change until a lateral clearance is reached; holds that offset
past the pole; turns back and follows the original course line. It acts on what it saw
``reaction_delay`` seconds ago, decides every ``decision_s`` seconds, adds noise to the nozzle,
and quantises its commands (nozzle in 2° detents, thrust in 250 N steps); commands are
published only when they change.

**Truth model**: :func:`true_params` — the default :class:`~diffgcl.sim.hull.HullParams` with the
parameters that system identification fits (:data:`diffgcl.data.sysid.SYSID_FIELDS`) changed by
the documented factors :data:`TRUE_FACTORS`, so identification has something to find.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from diffgcl.data.synth.config import SynthConfig

# The generator's hull differs from the default model in exactly these parameters (factor on the
# default value). Other parameters are the defaults. sysid.SYSID_FIELDS lists the same names.
TRUE_FACTORS: dict[str, float] = {
    "inertia_scale": 1.10,
    "damping_uu": 1.15,
    "damping_v": 1.25,
    "damping_r": 0.85,
    "jet_arm": 0.92,
    "tau_thrust": 1.30,
    "tau_nozzle": 0.80,
}


def true_params(dtype=None):
    """The generator's "true" :class:`~diffgcl.sim.hull.HullParams` (defaults × TRUE_FACTORS)."""
    from diffgcl.sim import hull

    base = hull.default_params(dtype)
    return base.replace(**{k: getattr(base, k) * f for k, f in TRUE_FACTORS.items()})


@dataclass(frozen=True)
class OperatorProfile:
    """One episode's scenario and operator (distances m, angles rad, times s, thrust N)."""

    pole_xy: tuple[float, float]
    pole_radius: float
    pole_colour: str
    course: float
    approach: float
    heading_error: float
    speed0: float
    side: int  # +1 swerve left (to port), -1 right
    swerve_distance: float
    swerve_angle: float
    clearance: float
    pass_margin: float
    return_angle: float
    end_margin: float
    cruise_thrust: float
    reaction_delay: float
    decision_s: float
    kp: float
    kd: float
    nozzle_noise: float
    nozzle_quantum: float = float(np.deg2rad(2.0))
    thrust_quantum: float = 250.0


def draw_profiles(rng: np.random.Generator, n: int, config: SynthConfig) -> list[OperatorProfile]:
    """``n`` scenarios/operators; poles half green, half grey; swerves alternate sides randomly."""
    colours = np.array(["green"] * ((n + 1) // 2) + ["grey"] * (n // 2))
    rng.shuffle(colours)
    sides = np.array([1] * ((n + 1) // 2) + [-1] * (n // 2))
    rng.shuffle(sides)
    out = []
    for i in range(n):
        approach = rng.uniform(*config.approach_m)
        out.append(
            OperatorProfile(
                pole_xy=(float(rng.uniform(-150, 150)), float(rng.uniform(-150, 150))),
                pole_radius=float(rng.uniform(0.3, 1.0)),
                pole_colour=str(colours[i]),
                course=float(rng.uniform(-np.pi, np.pi)),
                approach=float(approach),
                heading_error=float(rng.normal(0.0, np.deg2rad(4.0))),
                speed0=float(rng.uniform(3.0, 6.0)),
                side=int(sides[i]),
                swerve_distance=float(rng.uniform(0.25, 0.45) * approach),
                swerve_angle=float(np.deg2rad(rng.uniform(25.0, 40.0))),
                clearance=float(rng.uniform(12.0, 25.0)),
                pass_margin=float(rng.uniform(5.0, 20.0)),
                return_angle=float(np.deg2rad(rng.uniform(20.0, 35.0))),
                end_margin=float(rng.uniform(*config.end_margin_m)),
                cruise_thrust=float(rng.uniform(5500.0, 9000.0)),
                reaction_delay=float(rng.uniform(0.3, 0.7)),
                decision_s=float(rng.choice([0.2, 0.3])),
                kp=float(rng.uniform(1.2, 2.0)),
                kd=float(rng.uniform(1.0, 2.5)),
                nozzle_noise=float(np.deg2rad(rng.uniform(0.5, 1.5))),
            )
        )
    return out


def wrap_angle(a):
    """Angles (rad) wrapped into [−π, π)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def simulate(
    profiles: Sequence[OperatorProfile], params, rng: np.random.Generator, max_steps: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Run the operators on the hull, all episodes at once -> [(X: [K+1, dX], U: [K, dU])].

    The operator is NumPy (vectorised over episodes); the hull step is the jitted, vmapped
    :func:`diffgcl.sim.hull.hull_step` with ``params``.
    """
    import jax
    import jax.numpy as jnp

    from diffgcl.sim import hull

    dt = hull_dt()
    E = len(profiles)
    P = {
        k: np.array([getattr(p, k) for p in profiles], float)
        for k, v in asdict(profiles[0]).items()
        if isinstance(v, int | float)
    }
    pole = np.array([p.pole_xy for p in profiles], float)
    e = np.stack([np.cos(P["course"]), np.sin(P["course"])], axis=1)
    n = np.stack([-e[:, 1], e[:, 0]], axis=1)
    start = pole - P["approach"][:, None] * e
    psi0 = P["course"] + P["heading_error"]
    x = np.zeros((E, hull.DX))
    x[:, hull.IX_PX : hull.IX_PY + 1] = start
    x[:, hull.IX_PSI] = psi0
    x[:, hull.IX_VX] = P["speed0"] * np.cos(psi0)
    x[:, hull.IX_VY] = P["speed0"] * np.sin(psi0)
    x[:, hull.IX_THRUST] = 0.5 * P["cruise_thrust"]
    x[:, hull.SL_OBS] = pole

    dtype = jnp.zeros(()).dtype
    step = _batched_step()
    params = jax.tree.map(lambda v: jnp.asarray(v, dtype), params)

    delay = np.maximum(np.round(P["reaction_delay"] / dt).astype(int), 0)
    every = np.maximum(np.round(P["decision_s"] / dt).astype(int), 1)
    ramp_until = rng.uniform(2.0, 6.0, E)
    phase = np.zeros(E, int)  # 0 approach, 1 swerve, 2 pass, 3 return, 4 track
    done_at = np.full(E, -1)
    cmd = np.stack([np.round(0.5 * P["cruise_thrust"] / 250.0) * 250.0, np.zeros(E)], axis=1)
    history = [x.copy()]
    commands = []
    wander = np.zeros(E)
    for k in range(max_steps):
        seen = np.stack([history[max(k - int(d), 0)][i] for i, d in enumerate(delay)])
        rel = seen[:, hull.IX_PX : hull.IX_PY + 1] - start
        along = np.sum(rel * e, axis=1)
        cross = np.sum(rel * n, axis=1)
        to_pole = pole - seen[:, hull.IX_PX : hull.IX_PY + 1]
        side = P["side"]
        phase = np.where((phase == 0) & (P["approach"] - along < P["swerve_distance"]), 1, phase)
        phase = np.where((phase == 1) & (side * cross >= P["clearance"]), 2, phase)
        phase = np.where((phase == 2) & (along > P["approach"] + P["pass_margin"]), 3, phase)
        phase = np.where((phase == 3) & (side * cross <= 1.0), 4, phase)
        target = np.select(
            [phase == 0, phase == 1, phase == 2, phase == 3],
            [
                np.arctan2(to_pole[:, 1], to_pole[:, 0]),
                P["course"] + side * P["swerve_angle"],
                P["course"],
                P["course"] - side * P["return_angle"],
            ],
            P["course"] - np.clip(0.04 * cross, -0.35, 0.35),
        )
        wander = 0.95 * wander + rng.normal(0.0, 1.0, E) * P["nozzle_noise"] * 0.3
        nozzle = (
            P["kp"] * wrap_angle(target - seen[:, hull.IX_PSI])
            - P["kd"] * seen[:, hull.IX_R]
            + wander
            + rng.normal(0.0, 1.0, E) * P["nozzle_noise"]
        )
        nozzle = np.clip(nozzle, -np.deg2rad(30.0), np.deg2rad(30.0))
        nozzle = np.round(nozzle / P["nozzle_quantum"]) * P["nozzle_quantum"]
        level = np.where(k * dt < ramp_until, 0.5, np.where(phase == 1, 0.85, 1.0))
        thrust = np.round(level * P["cruise_thrust"] / P["thrust_quantum"]) * P["thrust_quantum"]
        decide = (k % every) == 0
        cmd = np.where(decide[:, None], np.stack([thrust, nozzle], axis=1), cmd)
        commands.append(cmd.copy())
        # Pad the batch to a multiple of 8 so that small runs share one trace of the step.
        pad = (-E) % 8
        xb = np.concatenate([x, np.repeat(x[:1], pad, 0)]) if pad else x
        ub = np.concatenate([cmd, np.repeat(cmd[:1], pad, 0)]) if pad else cmd
        x = np.asarray(step(params, jnp.asarray(xb, dtype), jnp.asarray(ub, dtype)))[:E]
        history.append(x.copy())
        finished = (phase == 4) & (along > P["approach"] + P["end_margin"]) & (done_at < 0)
        done_at = np.where(finished, k + 1, done_at)
        if (done_at >= 0).all():
            break
    X = np.stack(history, axis=1)
    U = np.stack(commands, axis=1)
    out = []
    for i in range(E):
        K = done_at[i] if done_at[i] >= 0 else U.shape[1]
        out.append((X[i, : K + 1], U[i, :K]))
    return out


@functools.lru_cache(maxsize=1)
def _batched_step():
    import jax

    from diffgcl.sim import hull

    return jax.jit(jax.vmap(hull.hull_step, in_axes=(None, 0, 0)))


def hull_dt() -> float:
    """Control step of the hull model (s)."""
    from diffgcl.sim import hull

    return float(hull.hull_model()[0].opt.timestep) * hull.SUBSTEPS
