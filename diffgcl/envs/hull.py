"""Odin-like water-jet boat avoiding a pole: the USV task of the seed's demonstrations.

Task (DESIGN §2). The boat runs along a course line (the world x axis, heading 0) at cruise speed
with a pole ahead of it, at a distance and lateral offset that vary per condition. It must swerve
to either side, pass the pole without touching it and come back to the course line by the end of
the horizon (T = 300 steps of dt = 0.1 s = 30 s).

State ``x = [p_x, p_y, ψ, ẋ, ẏ, ψ̇, thrust, nozzle, obs_x, obs_y]`` (dX = 10, the layout of
:mod:`diffgcl.sim.hull`), action ``u = [thrust_cmd (N), nozzle_cmd (rad)]`` (dU = 2).
Observation (what the policy sees; GPS trains with the full state and tests on sensors):

    o = [LiDAR ranges (32), radar ranges (16), sin ψ, cos ψ, u, v, r]     (dO = 53)

ranges in metres from ``mjx.ray`` (:mod:`diffgcl.sim.sensors`), ν = [u, v, r] in the body frame.
:func:`observation` assembles the same vector from recorded ranges, heading and speed.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from diffgcl.checks import check_shape
from diffgcl.sim import hull as hull_sim
from diffgcl.sim import mjcf
from diffgcl.sim.hull import HullParams
from diffgcl.sim.mjcf import load_mjcf, make_data, put_model, resolve_mjcf
from diffgcl.sim.sensors import SensorLayout, add_range_noise, range_readings
from diffgcl.types import Array, PRNGKey

HULL_MJCF = hull_sim.MJCF_NAME
# Default conditions: pole (x, y) ahead of the boat, which starts at the origin heading +x. No
# pole sits exactly on the course line: a dead-centre pole makes the expert cost symmetric, and a
# deterministic optimiser started straight ahead (zero lateral gradient) brakes into it instead of
# choosing a side. Every offset is below pole radius + half beam (2.2 m), so holding the course
# is a collision: each condition needs a swerve.
DEFAULT_POLES = ((90.0, 1.0), (110.0, 2.0), (130.0, -2.0), (100.0, -1.0))


@dataclasses.dataclass(frozen=True)
class HullCostWeights:
    """Weights of the hand-written expert cost (per step; see :meth:`HullEnv.expert_cost`)."""

    clearance: float = 20.0  # barrier on the pole clearance of bow, centre and stern
    clearance_margin: float = 6.0  # m of extra clearance wanted beyond contact
    clearance_scale: float = 1.5  # m, softness of the barrier
    course: float = 0.02  # per m² of cross-track error
    heading: float = 2.0  # on 1 − cos(ψ − course heading)
    speed: float = 0.05  # per (m/s)² of surge error
    thrust: float = 0.5  # on ((T_cmd − T_cruise) / T_max)²
    nozzle: float = 0.5  # on (δ_cmd / δ_max)²
    limits: float = 100.0  # smooth penalty on commands beyond the actuator limits
    terminal: float = 20.0  # multiplies course, heading and speed terms at t = T


def observation(ranges: Array, psi: Array, nu: Array) -> Array:
    """o: [num_beams + 5] from ranges: [num_beams] (m), heading ψ (rad), ν = [u, v, r]: [3].

    Shared by the simulator (:meth:`HullEnv.obs`) and by ROS-bag ingestion.
    """
    return jnp.concatenate([ranges, jnp.stack([jnp.sin(psi), jnp.cos(psi)]), nu])


def _softplus_sq(z: Array, scale: Array) -> Array:
    """scale² · softplus(z / scale)²: a smooth (C∞) one-sided quadratic penalty on z > 0."""
    return (scale * jax.nn.softplus(z / scale)) ** 2


def actuator_limit_residuals(params: HullParams, u: Array, softness: float = 0.02) -> Array:
    """[4] how far the physical command ``u = [thrust (N), nozzle (rad)]`` lies beyond the
    actuators' limits (thrust above its maximum, below full reverse; nozzle beyond ±its maximum),
    in fractions of the limit and softened: ``s · softplus(z / s)``. Their squares are the
    hand-written cost's limit penalty; a learned cost carries them as fixed residuals."""
    p = params
    top = jnp.stack([p.max_thrust, p.max_nozzle]).astype(u.dtype)  # the upper limits, the units
    bottom = jnp.stack([-p.reverse_fraction * p.max_thrust, -p.max_nozzle]).astype(u.dtype)
    z = jnp.concatenate([u - top, bottom - u]) / jnp.concatenate([top, top])
    return softness * jax.nn.softplus(z / softness)


def hull_points(params: HullParams, x: Array) -> Array:
    """[3, 2] world positions of the bow, centre and stern circle centres of the hull outline
    (a stadium of width ``beam`` and length ``length``) for a hull state ``x``."""
    half = 0.5 * (params.length - params.beam)
    c, s = jnp.cos(x[hull_sim.IX_PSI]), jnp.sin(x[hull_sim.IX_PSI])
    offsets = jnp.asarray([-half, 0.0, half], x.dtype)
    return x[:2] + offsets[:, None] * jnp.stack([c, s])


def pole_clearance(params: HullParams, x: Array, radius: Array) -> Array:
    """Distance (m) between the surface of a pole of ``radius`` at ``x``'s obstacle position and
    the hull outline (a stadium of beam B around the centre line); ≤ 0 is a collision."""
    half = 0.5 * (params.length - params.beam)
    c, s = jnp.cos(x[hull_sim.IX_PSI]), jnp.sin(x[hull_sim.IX_PSI])
    rel = x[hull_sim.SL_OBS] - x[:2]
    along = c * rel[0] + s * rel[1]
    across = -s * rel[0] + c * rel[1]
    gap = jnp.hypot(along - jnp.clip(along, -half, half), across)
    return gap - radius - 0.5 * params.beam


def avoidance_cost(
    weights: HullCostWeights,
    params: HullParams,
    x: Array,
    u: Array,
    terminal: Array,
    *,
    radius: Array,
    cruise_speed: float,
    cruise_thrust: float,
    course_y: float = 0.0,
) -> Array:
    """The hand-written obstacle-avoidance cost of one step (see :meth:`HullEnv.expert_cost`):
    hull state ``x``, physical command ``u = [thrust (N), nozzle (rad)]``, ``terminal`` (bool:
    the step after the last action, where the course, heading and speed terms are weighted by
    ``weights.terminal`` and there is no effort), a pole of ``radius`` at ``x``'s obstacle."""
    w, p = weights, params
    rel = hull_points(p, x) - x[hull_sim.SL_OBS]
    dist = jnp.sqrt(jnp.sum(rel**2, axis=-1) + 1e-6)
    d_safe = radius + 0.5 * p.beam + w.clearance_margin
    clearance = w.clearance * jnp.sum(_softplus_sq(d_safe - dist, w.clearance_scale))
    course = w.course * (x[hull_sim.IX_PY] - course_y) ** 2
    heading = w.heading * (1.0 - jnp.cos(x[hull_sim.IX_PSI]))
    speed = w.speed * (hull_sim.body_velocity(x)[0] - cruise_speed) ** 2
    end_weight = jnp.where(terminal, w.terminal, 1.0)
    thrust = u[hull_sim.IU_THRUST]
    nozzle = u[hull_sim.IU_NOZZLE]
    effort = w.thrust * ((thrust - cruise_thrust) / p.max_thrust) ** 2
    effort += w.nozzle * (nozzle / p.max_nozzle) ** 2
    over = actuator_limit_residuals(p, u)
    effort = jnp.where(terminal, 0.0, effort + w.limits * (over @ over))
    return clearance + end_weight * (course + heading + speed) + effort


def on_course(x: Array, course_y: float, course_tolerance: float, heading_tolerance: float):
    """Whether hull state ``x`` is back on the course line y = course_y, heading 0: cross-track
    error below ``course_tolerance`` (m) and heading error below ``heading_tolerance`` (rad)."""
    psi = x[hull_sim.IX_PSI]
    heading_ok = jnp.abs(jnp.arctan2(jnp.sin(psi), jnp.cos(psi))) < heading_tolerance
    return (jnp.abs(x[hull_sim.IX_PY] - course_y) < course_tolerance) & heading_ok


@dataclasses.dataclass(frozen=True, eq=False)
class HullEnv:
    """Hull + pole env; build with :func:`make_hull_env`. Hashable by identity (jit static)."""

    params: HullParams
    model: mjx.Model
    data0: mjx.Data
    layout: SensorLayout
    x0: Array  # [C, dX]
    mjcf_path: str
    pole_radius: float
    cruise_speed: float
    cruise_thrust: float
    weights: HullCostWeights = HullCostWeights()
    horizon: int = 300
    substeps: int = hull_sim.SUBSTEPS
    course_y: float = 0.0  # the course line is y = course_y, heading 0
    course_tolerance: float = 5.0  # m, success: final cross-track error
    heading_tolerance: float = float(np.deg2rad(20.0))  # success: final heading error
    name: str = "hull"
    dX: int = hull_sim.DX
    dU: int = hull_sim.DU

    @property
    def dO(self) -> int:
        return self.layout.num_beams + 5

    @property
    def dt(self) -> float:
        # Rounded to microseconds: the float32 MJX copy holds 0.025 as 0.0250000004.
        return round(float(self.model.opt.timestep) * self.substeps, 6)

    # ---- dynamics and sensing -----------------------------------------------------------------
    def step(self, x: Array, u: Array) -> Array:
        """x: [10], u: [2] -> x': [10] (:func:`diffgcl.sim.hull.hull_step`)."""
        check_shape("hull.step", "x", x, (self.dX,))
        check_shape("hull.step", "u", u, (self.dU,))
        return hull_sim.hull_step(self.params, x, u, self.model, self.substeps)

    def ranges(self, x: Array) -> Array:
        """x: [10] -> noiseless beam ranges [num_beams] from mjx.ray in the scene of x."""
        check_shape("hull.ranges", "x", x, (self.dX,))
        mocap = self.data0.mocap_pos.at[0, :2].set(x[hull_sim.SL_OBS])
        d = self.data0.replace(qpos=x[hull_sim.SL_QPOS], mocap_pos=mocap)
        d = mjcf.kinematics(self.model, d)
        return range_readings(self.model, d, self.layout)

    def obs(self, x: Array, key: PRNGKey | None = None) -> Array:
        """x: [10] -> o: [dO]; with ``key`` the ranges get the layout's Gaussian noise."""
        check_shape("hull.obs", "x", x, (self.dX,))
        r = self.ranges(x)
        if key is not None:
            r = add_range_noise(r, self.layout, key)
        return observation(r, x[hull_sim.IX_PSI], hull_sim.body_velocity(x))

    def initial_states(self) -> Array:
        """Conditions x0: [C, 10]."""
        return self.x0

    def initial_state(self, pole_xy: Array) -> Array:
        """x0: [10] at the origin, heading +x at cruise speed and thrust, pole at pole_xy: [2]."""
        dtype = self.x0.dtype
        x = jnp.zeros(self.dX, dtype)
        x = x.at[hull_sim.IX_VX].set(self.cruise_speed)
        x = x.at[hull_sim.IX_THRUST].set(self.cruise_thrust)
        return x.at[hull_sim.SL_OBS].set(jnp.asarray(pole_xy, dtype))

    def random_initial_states(
        self, key: PRNGKey, n: int, distance=(80.0, 140.0), offset=(-2.0, 2.0)
    ) -> Array:
        """n held-out conditions [n, 10]: pole distance and lateral offset drawn uniformly (the
        default offsets all put the pole in the boat's path)."""
        k1, k2 = jax.random.split(key)
        dtype = self.x0.dtype
        px = jax.random.uniform(k1, (n,), dtype, *distance)
        py = self.course_y + jax.random.uniform(k2, (n,), dtype, *offset)
        return jax.vmap(self.initial_state)(jnp.stack([px, py], axis=-1))

    # ---- task ---------------------------------------------------------------------------------
    def expert_cost(self, x: Array, u: Array, t: Array) -> Array:
        """Hand-written obstacle-avoidance cost c(x: [10], u: [2], t) -> scalar (C∞ in x, u).

        * clearance: Σ over bow/centre/stern circles of w·s²·softplus((d_safe − d)/s)² with
          d the distance to the pole and d_safe = pole radius + half beam + margin;
        * course: w·(y − y_course)² + w·(1 − cos ψ) (the course heading is 0);
        * speed: w·(u_surge − cruise)²; effort on the commands around cruise;
        * a smooth penalty on commands beyond the actuator limits.
        At t = T (u = 0 passed) the course, heading and speed terms are weighted by ``terminal``.
        """
        return avoidance_cost(
            self.weights,
            self.params,
            x,
            u,
            t >= self.horizon,
            radius=self.pole_radius,
            cruise_speed=self.cruise_speed,
            cruise_thrust=self.cruise_thrust,
            course_y=self.course_y,
        )

    def clearance(self, x: Array) -> Array:
        """Distance (m) between the pole surface and the hull outline (a 10.5 × 3.4 stadium)."""
        return pole_clearance(self.params, x, self.pole_radius)

    def metrics(self, X: Array) -> dict[str, Array]:
        """X: [T+1, 10] -> scalars: minimum clearance (m), final cross-track error (m), final
        heading error (rad), largest cross-track excursion (m) and success."""
        psi = X[-1, hull_sim.IX_PSI]
        return {
            "min_clearance": jnp.min(jax.vmap(self.clearance)(X)),
            "final_cross_track": jnp.abs(X[-1, hull_sim.IX_PY] - self.course_y),
            "final_heading_error": jnp.abs(jnp.arctan2(jnp.sin(psi), jnp.cos(psi))),
            "max_cross_track": jnp.max(jnp.abs(X[:, hull_sim.IX_PY] - self.course_y)),
            "success": self.success(X),
        }

    def success(self, X: Array) -> Array:
        """X: [T+1, 10] -> bool: never touches the pole, and ends near the course line.

        No collision: the hull outline (stadium of beam B around the centre line) keeps a
        positive clearance to the pole at every state. Back on course: final cross-track error
        < ``course_tolerance`` and final heading error < ``heading_tolerance``.
        """
        no_collision = jnp.min(jax.vmap(self.clearance)(X)) > 0.0
        back = on_course(X[-1], self.course_y, self.course_tolerance, self.heading_tolerance)
        return no_collision & back


def cruise_thrust(params: HullParams, speed: float) -> float:
    """Thrust (N) that holds surge speed ``speed`` (m/s) straight ahead: X_u U + X_|u|u U²."""
    drag = float(params.damping_u) * speed + float(params.damping_uu) * speed * abs(speed)
    return drag / float(params.thrust_gain)


def make_hull_env(
    *,
    poles=DEFAULT_POLES,
    pole_radius: float = 0.5,
    cruise_speed: float = 8.0,
    horizon: int = 300,
    params: HullParams | None = None,
    layout: SensorLayout | None = None,
    weights: HullCostWeights | None = None,
    mjcf: str = HULL_MJCF,
) -> HullEnv:
    """The hull env in the current float precision (``jax_enable_x64``).

    poles: [C, 2] pole positions (one condition each; the boat starts at the origin heading +x
    at ``cruise_speed`` m/s, ≈ 15.5 kn by default). ``pole_radius`` (m, 0.3-1 in the seed's
    demonstrations) resizes the pole capsule of the MJCF. ``params`` replaces the nominal
    :class:`~diffgcl.sim.hull.HullParams` (e.g. identified from bags).
    """
    path = resolve_mjcf(mjcf)
    model = load_mjcf(path)
    hull_sim.check_hull_model(model, str(path))
    if not pole_radius > 0:
        raise ValueError(f"hull: pole_radius must be positive, got {pole_radius}")
    names = [model.geom(i).name for i in range(model.ngeom)]
    if "pole" not in names:
        raise ValueError(f"{path}: the hull scene needs a geom named 'pole'")
    pole_geom = names.index("pole")
    # Resize the pole capsule; keep its bounding sphere and box (used by C mj_ray) consistent.
    half_length = model.geom_size[pole_geom, 1]
    model.geom_size[pole_geom, 0] = pole_radius
    model.geom_rbound[pole_geom] = pole_radius + half_length
    model.geom_aabb[pole_geom, 3:] = [pole_radius, pole_radius, pole_radius + half_length]
    mx = put_model(model)
    dtype = jnp.zeros(()).dtype
    params = hull_sim.default_params(dtype) if params is None else params
    params = jax.tree.map(lambda v: jnp.asarray(v, dtype), params)
    poles = np.atleast_2d(np.asarray(poles, dtype=float))
    if poles.ndim != 2 or poles.shape[1] != 2:
        raise ValueError(f"hull: poles must be [C, 2] positions, got {poles.shape}")
    thrust = cruise_thrust(params, cruise_speed)
    x0 = np.zeros((poles.shape[0], hull_sim.DX))
    x0[:, hull_sim.IX_VX] = cruise_speed
    x0[:, hull_sim.IX_THRUST] = thrust
    x0[:, hull_sim.SL_OBS] = poles
    return HullEnv(
        params=params,
        model=mx,
        data0=make_data(mx),
        layout=layout or SensorLayout(),
        x0=jnp.asarray(x0, dtype),
        mjcf_path=str(path),
        pole_radius=float(pole_radius),
        cruise_speed=float(cruise_speed),
        cruise_thrust=thrust,
        weights=weights or HullCostWeights(),
        horizon=horizon,
    )
