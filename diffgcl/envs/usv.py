"""The USV obstacle-avoidance task in the task frame: the Odin-like hull passing a pole and
returning to its course, as the demonstrations from the bags see it (DESIGN §7b).

Task frame: the course line is the x axis (y = 0, heading 0), the boat travels towards +x and a
pole of some radius stands ahead. Each demonstration is moved into this frame
(:mod:`diffgcl.data.task_frame`), so one env covers every episode; a condition is a start state.

State ``x = [p_x, p_y, ψ, ẋ, ẏ, ψ̇, thrust, nozzle, pole_x, pole_y, pole_radius]`` (dX = 11): the
hull's state of :mod:`diffgcl.sim.hull` plus the pole's radius, constant like its position, so
that poles of different sizes are conditions of one env (and batch under ``vmap``).

Action ``ũ`` (dU = 2), normalised: the physical command is ``u = offset + scale ⊙ ũ`` with
``offset = [cruise thrust, 0]`` and ``scale = [T_max, δ_max]`` by default. A unit of ũ is the
actuator's range in both dimensions, so one exploration variance and one action weight fit both
(in newtons and radians a variance of 0.1 means no thrust exploration and wild nozzle swings).

Observation (what the policy sees; the cost learns on the full state):

* ``"full"`` — LiDAR ranges (32 beams), radar ranges (16), sin ψ, cos ψ (the heading, which in
  the task frame is the heading error to the course), ν = [u, v, r], and the cross-track error y
  (from GNSS and the planned course line); dO = 54;
* ``"radar"`` — the same without the LiDAR beams (the seed's set 1 had no LiDAR); dO = 22;
* ``"ranges"`` — the ablation without course information: ranges and ν only; dO = 51.

The ranges enter in metres or, with ``range_encoding="saturated"``, through :func:`encode_ranges`
(metres near the boat, about the same for everything far away).

Ranges are what ingestion makes of the boat's recorded sensors
(:class:`~diffgcl.sim.sensors.PoleSensorModel`, :func:`~diffgcl.sim.sensors.pole_beams`), so that a
policy trained on them reads demos' observations alike: the LiDAR beams read the pole's scan returns
as discs (about 0.25 m nearer than its surface), the radar beams a point target at the pole's centre
in the one sector that holds it; ``obs(x, key)`` draws their noise, dropouts and missed detections.
The noise-free beams are differentiable in the state where they see the pole (MDGPS linearises the
policy through them). :func:`pole_ranges`, the exact intersection of the layout's rays with the pole
(the same numbers as ``mjx.ray`` in the hull's MJCF scene, tested), stays as the reference geometry.

Success (:meth:`UsvEnv.success`): the hull outline never touches the pole, and at the end the boat
is back on course (cross-track below ``course_tolerance``, heading error below
``heading_tolerance``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.checks import check_shape
from diffgcl.envs.hull import (
    HullCostWeights,
    actuator_limit_residuals,
    avoidance_cost,
    cruise_thrust,
    on_course,
    pole_clearance,
)
from diffgcl.sim import hull as hull_sim
from diffgcl.sim.hull import HullParams
from diffgcl.sim.sensors import (
    PoleSensorModel,
    SensorLayout,
    circle_entry,
    noisy_pole_beams,
    pole_beams,
)
from diffgcl.types import Array, PRNGKey

IX_RADIUS = 10
PROXIMITY_MARGINS = (5.0, 10.0, 15.0, 20.0)  # m of clearance, the weighted cost's barriers
PROXIMITY_SOFTNESS = 2.0  # m
COURSE_RESIDUAL_NAMES = (
    "cross_track",
    "heading",
    "surge_error",
    "progress_error",
    "sway",
    "yaw_rate",
)


def cost_residual_names(margins=PROXIMITY_MARGINS) -> tuple[str, ...]:
    """Names of :meth:`UsvEnv.cost_residuals` for clearance ``margins`` (m)."""
    return (*COURSE_RESIDUAL_NAMES, *(f"inside_{d:g}m" for d in margins))


COST_RESIDUAL_NAMES = cost_residual_names()
DX = 11
OBSERVATIONS = ("full", "radar", "ranges")
RANGE_ENCODINGS = ("metres", "saturated")
SATURATION_RANGE = 60.0  # m, of the saturated range encoding
#: m: the cost features' pole bearing and closing speed divide by sqrt(d² + L²), not by the
#: distance d, so that their derivatives stay bounded (about 1/L) at the pole's centre
BEARING_SOFTNESS = 5.0
STATE_NAMES = (*hull_sim.STATE_NAMES, "pole_radius")


def encode_ranges(r: Array, encoding: str) -> Array:
    """Beam ranges ``r`` (m) as the policy sees them: ``"metres"`` as read; ``"saturated"``
    ``R tanh(r / R)`` with ``R`` = :data:`SATURATION_RANGE` (the LiDAR's reach): metres near the
    boat (slope 0.97 at 10 m, 0.42 at R), and everything well beyond R — a pole far astern, a
    beam with no return — reads R. In metres a pole astern reads its growing distance, and a
    policy trained on windows that end 170 m past the pole drifts off the line once the boat
    sails on into readings it never had (docs/usv.md)."""
    if encoding == "metres":
        return r
    if encoding == "saturated":
        return SATURATION_RANGE * jnp.tanh(r / SATURATION_RANGE)
    raise ValueError(f"usv: range encoding {encoding!r}; choose one of {RANGE_ENCODINGS}")


def pole_in_hull_frame(x: Array) -> Array:
    """[2] the pole's centre in the hull frame (x forward, y to port; m) of hull state ``x``."""
    psi = x[hull_sim.IX_PSI]
    c, s = jnp.cos(psi), jnp.sin(psi)
    rel = x[hull_sim.SL_OBS] - x[:2]
    return jnp.stack([c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1]])


def pole_ranges(layout: SensorLayout, x: Array, radius: Array) -> Array:
    """Exact beam ranges [num_beams] of the layout from hull state ``x`` (its first 10 entries)
    to a pole of ``radius`` at the state's obstacle position: the reference geometry.

    Each ray leaves the mast (``layout.origin`` in the hull frame) horizontally; its distance to
    the pole is the entry point into the pole's circle (0 from inside), a beam reads its shortest
    ray, and a beam with no hit reads its maximum range (as
    :func:`~diffgcl.sim.sensors.range_readings` does with ``mjx.ray``). The observation uses
    :class:`~diffgcl.sim.sensors.PoleSensorModel` instead (what ingestion makes of the recorded
    sensors).
    """
    pole = pole_in_hull_frame(x)
    origin = jnp.asarray(layout.origin[:2], x.dtype)
    dirs = jnp.asarray(layout.ray_directions[:, :2], x.dtype)
    beams = layout.beams_from_rays(circle_entry(origin, dirs, pole, radius))
    return jnp.minimum(beams, jnp.asarray(layout.max_ranges, x.dtype))


@dataclasses.dataclass(frozen=True, eq=False)
class UsvEnv:
    """Hull passing a pole in the task frame; build with :func:`make_usv_env`. Hashable by
    identity (a jit static argument)."""

    params: HullParams
    model: object  # mjx.Model of the hull scene (for hull_step)
    layout: SensorLayout
    x0: Array  # [C, 11]
    cruise_speed: float
    cruise_thrust: float
    action_offset: Array  # [2] physical command at ũ = 0
    action_scale: Array  # [2] physical command per unit of ũ
    observation: str = "full"
    range_encoding: str = "metres"
    sensors: PoleSensorModel = PoleSensorModel()
    weights: HullCostWeights = HullCostWeights()
    proximity_margins: tuple[float, ...] = PROXIMITY_MARGINS
    horizon: int = 240
    course_tolerance: float = 5.0
    heading_tolerance: float = float(np.deg2rad(20.0))
    return_heading_tolerance: float = float(np.deg2rad(45.0))
    name: str = "usv"
    dX: int = DX
    dU: int = hull_sim.DU
    mjcf_path: str = ""
    state_names: tuple[str, ...] = STATE_NAMES

    @property
    def dO(self) -> int:
        n = {"full": self.layout.num_beams, "radar": self.layout.radar_beams}
        return {"full": n["full"] + 6, "radar": n["radar"] + 6, "ranges": n["full"] + 3}[
            self.observation
        ]

    @property
    def dt(self) -> float:
        return round(float(self.model.opt.timestep) * hull_sim.SUBSTEPS, 6)

    # ---- dynamics and sensing -----------------------------------------------------------------
    def command(self, u: Array) -> Array:
        """Physical command [thrust (N), nozzle (rad)] of a normalised action ``ũ: [2]``."""
        return self.action_offset + self.action_scale * u

    def normalised_action(self, u_phys: Array) -> Array:
        """The inverse of :meth:`command` (e.g. for recorded commands)."""
        return (u_phys - self.action_offset) / self.action_scale

    def step(self, x: Array, u: Array) -> Array:
        """x: [11], ũ: [2] -> x': [11] (:func:`diffgcl.sim.hull.hull_step` on the hull part)."""
        check_shape("usv.step", "x", x, (self.dX,))
        check_shape("usv.step", "u", u, (self.dU,))
        nxt = hull_sim.hull_step(self.params, x[:IX_RADIUS], self.command(u), self.model)
        return jnp.concatenate([nxt, x[IX_RADIUS:]])

    def ranges(self, x: Array, key: PRNGKey | None = None) -> Array:
        """Beam ranges [num_beams] (LiDAR then radar) as ingestion reads them from the recorded
        sensors (:func:`~diffgcl.sim.sensors.pole_beams`); ``key`` draws their noise."""
        pole = pole_in_hull_frame(x[:IX_RADIUS])
        if key is None:
            return pole_beams(self.sensors, self.layout, pole, x[IX_RADIUS])
        return noisy_pole_beams(self.sensors, self.layout, pole, x[IX_RADIUS], key)

    def obs(self, x: Array, key: PRNGKey | None = None) -> Array:
        """x: [11] -> o: [dO] (see the module docstring); ``key`` adds the sensors' noise."""
        check_shape("usv.obs", "x", x, (self.dX,))
        r = encode_ranges(self.ranges(x, key), self.range_encoding)
        psi = x[hull_sim.IX_PSI]
        nu = hull_sim.body_velocity(x[:IX_RADIUS])
        heading = jnp.stack([jnp.sin(psi), jnp.cos(psi)])
        cross_track = x[hull_sim.IX_PY : hull_sim.IX_PY + 1]
        if self.observation == "ranges":
            return jnp.concatenate([r, nu])
        if self.observation == "radar":
            r = r[self.layout.lidar_beams :]
        return jnp.concatenate([r, heading, nu, cross_track])

    def initial_states(self) -> Array:
        """Conditions x0: [C, 11]."""
        return self.x0

    # ---- task ---------------------------------------------------------------------------------
    def expert_cost(self, x: Array, u: Array, t: Array) -> Array:
        """The hand-written avoidance cost (:func:`diffgcl.envs.hull.avoidance_cost`) of the
        state and the normalised action (the terminal step passes ũ = 0, which it ignores)."""
        return avoidance_cost(
            self.weights,
            self.params,
            x[:IX_RADIUS],
            self.command(u),
            t >= self.horizon,
            radius=x[IX_RADIUS],
            cruise_speed=self.cruise_speed,
            cruise_thrust=self.cruise_thrust,
        )

    def clearance(self, x: Array) -> Array:
        """Distance (m) between the pole's surface and the hull outline; ≤ 0 is a collision."""
        return pole_clearance(self.params, x[:IX_RADIUS], x[IX_RADIUS])

    def back_on_course(self, x: Array) -> Array:
        """Cross-track and heading error within the tolerances (bool)."""
        return on_course(x, 0.0, self.course_tolerance, self.heading_tolerance)

    def returned_to_course(self, X: Array) -> Array:
        """X: [T+1, 11] -> bool: after the closest approach to the pole the boat comes back onto
        the course line (cross-track below ``course_tolerance``) heading along it within
        ``return_heading_tolerance`` (human demonstrators cross back at 20–40° and settle later
        than a pass window lasts)."""
        k = jnp.argmin(jax.vmap(self.clearance)(X))
        on = jax.vmap(
            lambda x: on_course(x, 0.0, self.course_tolerance, self.return_heading_tolerance)
        )(X)
        return jnp.any(on & (jnp.arange(X.shape[0]) >= k))

    def success(self, X: Array) -> Array:
        """X: [T+1, 11] -> bool: no collision at any state, back on course at the end."""
        no_collision = jnp.min(jax.vmap(self.clearance)(X)) > 0.0
        return no_collision & self.back_on_course(X[-1])

    def metrics(self, X: Array) -> dict[str, Array]:
        """X: [T+1, 11] -> min clearance (m), final cross-track (m) and heading error (rad),
        largest cross-track excursion (m), collision, back on course at the end, returned to the
        course after the pass (:meth:`returned_to_course`), the side passed at the
        closest approach (+1: the boat is to the left of the pole, y above it, i.e. it swerved to
        port; −1: to starboard), success, and ``turned_back``: the heading more than 90° off
        the course at some step (the boat turned round or circled; no demo does)."""
        clearance = jax.vmap(self.clearance)(X)
        k = jnp.argmin(clearance)
        psi = X[-1, hull_sim.IX_PSI]
        heading = X[:, hull_sim.IX_PSI]
        side = jnp.sign(X[k, hull_sim.IX_PY] - X[k, hull_sim.IX_OBS_Y])
        return {
            "min_clearance": clearance[k],
            "final_cross_track": jnp.abs(X[-1, hull_sim.IX_PY]),
            "final_heading_error": jnp.abs(jnp.arctan2(jnp.sin(psi), jnp.cos(psi))),
            "max_cross_track": jnp.max(jnp.abs(X[:, hull_sim.IX_PY])),
            "collision": clearance[k] <= 0.0,
            "back_on_course": self.back_on_course(X[-1]),
            "returned_to_course": self.returned_to_course(X),
            "side": side,
            "success": self.success(X),
            "turned_back": jnp.any(jnp.cos(heading) < 0.0),
        }

    def cost_features(self, x: Array) -> Array:
        """Task features a sailor would use, for the learned cost (Gram and neural forms): [16].

        The pole: its clearance and its distance ahead along the hull's heading (m, each read
        ``R tanh(d/R)`` with R = :data:`SATURATION_RANGE`, so that everything far reads alike), two
        soft proximity features exp(−clearance/ℓ) (ℓ = 5, 20 m), its bearing in the hull frame
        (cos, sin) and the closing speed (m/s), each over ``sqrt(d² + L²)`` instead of the
        distance ``d`` (L = :data:`BEARING_SOFTNESS`: they fade to 0 within a few metres of the
        pole's centre, where the clearance features still tell how close it is; over ``d``
        their derivatives ran to 10³–10⁴ per metre there, and the LQR expands the learned cost
        through them); the course: cross-track error (m), sin ψ and
        1 − cos ψ (heading error), the speed made good along the course minus cruise; the hull:
        surge speed minus cruise, sway speed (m/s), yaw rate (rad/s), the lagged thrust and
        nozzle as fractions of their ranges. Every feature but the cross-track error is bounded
        on any trajectory, so that a network on them reads nothing it never saw far from the
        data (a pole kilometres astern reads as one 60 m astern).
        """
        h = x[:IX_RADIUS]
        p = self.params
        psi = h[hull_sim.IX_PSI]
        c, s = jnp.cos(psi), jnp.sin(psi)
        rel = h[hull_sim.SL_OBS] - h[:2]
        along = c * rel[0] + s * rel[1]
        across = -s * rel[0] + c * rel[1]
        dist = jnp.sqrt(along**2 + across**2 + BEARING_SOFTNESS**2)
        vel = h[hull_sim.SL_QVEL][:2]
        closing = (rel @ vel) / dist
        clearance = self.clearance(x)
        nu = hull_sim.body_velocity(h)
        R = SATURATION_RANGE
        return jnp.stack(
            [
                R * jnp.tanh(clearance / R),
                R * jnp.tanh(along / R),
                jnp.exp(-jnp.maximum(clearance, 0.0) / 5.0),
                jnp.exp(-jnp.maximum(clearance, 0.0) / 20.0),
                along / dist,
                across / dist,
                closing,
                h[hull_sim.IX_PY],
                s,
                1.0 - c,
                h[hull_sim.IX_VX] - self.cruise_speed,
                nu[0] - self.cruise_speed,
                nu[1],
                nu[2],
                h[hull_sim.IX_THRUST] / p.max_thrust,
                h[hull_sim.IX_NOZZLE] / p.max_nozzle,
            ]
        )

    @property
    def cost_feature_mirror(self) -> tuple[float, ...]:
        """The sign each of :meth:`cost_features` takes when the situation is reflected across
        the course line (world y, heading, sway, yaw rate, nozzle and the pole's y negated): the
        pole's bearing across the hull, the cross-track error, sin ψ, sway, yaw rate and nozzle
        flip; the rest keep their sign. For the neural cost's ``network.mirror``."""
        flipped = (5, 7, 8, 12, 13, 15)  # across-bearing, cross-track, sin ψ, sway, yaw, nozzle
        return tuple(-1.0 if i in flipped else 1.0 for i in range(16))

    @property
    def cost_clearance_features(self) -> tuple[int, ...]:
        """The indices of :meth:`cost_features` that are functions of the pole's clearance: the
        saturated clearance (m, first: the learned barrier's input) and the two proximities.
        For the neural cost's ``network.barrier_margins``, whose gate must not read them."""
        return (0, 2, 3)

    def cost_goal_state(self) -> Array:
        """Where the task is done, for the neural cost's anchor: [11]. On the course line at
        cruise speed, heading along it, the jets at the thrust that holds that speed, the pole
        (of the first condition's radius) 1 km astern."""
        radius = self.x0[0, IX_RADIUS]
        return self.start_state(jnp.asarray([-1000.0, 0.0]), radius, self.cruise_speed)

    @property
    def cost_residual_names(self) -> tuple[str, ...]:
        """Names of :meth:`cost_residuals`, in order."""
        return cost_residual_names(self.proximity_margins)

    def cost_residuals(self, x: Array) -> Array:
        """Residuals a sailor wants at zero, for the learned cost's weighted form (the cost is
        a learned non-negative weighting of their squares; :mod:`diffgcl.costs.network`): [6 + M]
        (:attr:`cost_residual_names`).

        cross-track error (m); 2 sin(ψ/2) (heading error; its square is 2(1 − cos ψ)); surge
        speed minus cruise and progress along the course (speed made good) minus cruise, sway
        speed (m/s), yaw rate (rad/s); and how far the hull is inside each of the M clearance
        margins d (``proximity_margins``, default :data:`PROXIMITY_MARGINS`: 5, 10, 15, 20 m),
        ``s · softplus((d − clearance)/s)`` with s = 2 m. A
        positive mix of their squares is a convex barrier that rises as the clearance falls
        below the margins the weights pick, and is zero well outside the largest: passing at a
        distance costs nothing, so keeping away from the pole for the whole window (circling in
        front of it) does not pay. Proximity terms with long tails (exp(−clearance/ℓ), ℓ up to
        40 m) made exactly that pay: the controllers circled.
        """
        s = PROXIMITY_SOFTNESS
        margins = jnp.asarray(self.proximity_margins, x.dtype)
        inside = s * jax.nn.softplus((margins - self.clearance(x)) / s)
        return jnp.concatenate([self.cost_prior_residuals(x), inside])

    def cost_prior_residuals(self, x: Array) -> Array:
        """The course residuals of :meth:`cost_residuals` (its first six, names
        :data:`COURSE_RESIDUAL_NAMES`): [6]. What the neural cost with
        ``network.prior_residuals`` weighs beside its network. They say where the boat should
        go: along the course line at cruise speed. They say nothing of the pole, and there
        are no clearance margins; keeping clear is left to the network."""
        h = x[:IX_RADIUS]
        nu = hull_sim.body_velocity(h)
        return jnp.stack(
            [
                h[hull_sim.IX_PY],
                2.0 * jnp.sin(0.5 * h[hull_sim.IX_PSI]),
                nu[0] - self.cruise_speed,
                h[hull_sim.IX_VX] - self.cruise_speed,
                nu[1],
                nu[2],
            ]
        )

    def action_limit_residuals(self, u: Array) -> Array:
        """Residuals [4] of the normalised action beyond the actuators' limits (thrust above its
        maximum or below full reverse, nozzle beyond ±its maximum), in fractions of the limit:
        the hand-written cost's limit barrier (weight ``weights.limits``, softness 2 %) as
        residuals, so that a learned cost keeps the commands where the clipped actuators still
        respond (:class:`~diffgcl.costs.network.CostNetwork`'s ``action_limits``)."""
        over = actuator_limit_residuals(self.params, self.command(u))
        return jnp.sqrt(self.weights.limits) * over

    def start_state(self, pole_xy, radius, speed, heading: float = 0.0, cross_track: float = 0.0):
        """x0: [11] at (0, cross_track) heading ``heading`` at ``speed`` m/s (thrust lagged at the
        thrust that holds that speed, nozzle centred), the pole at ``pole_xy`` with ``radius``."""
        dtype = self.x0.dtype
        p = self.params
        thrust = (p.damping_u * speed + p.damping_uu * speed * jnp.abs(speed)) / p.thrust_gain
        x = jnp.zeros(self.dX, dtype)
        x = x.at[hull_sim.IX_PY].set(cross_track).at[hull_sim.IX_PSI].set(heading)
        x = x.at[hull_sim.IX_VX].set(speed * jnp.cos(heading))
        x = x.at[hull_sim.IX_VY].set(speed * jnp.sin(heading))
        x = x.at[hull_sim.IX_THRUST].set(thrust)
        x = x.at[hull_sim.SL_OBS].set(jnp.asarray(pole_xy, dtype))
        return x.at[IX_RADIUS].set(radius)


IX_POLE2 = slice(DX, DX + 2)  # the second pole's position in a TwoPoleUsvEnv state
IX_RADIUS2 = DX + 2


@dataclasses.dataclass(frozen=True, eq=False)
class TwoPoleUsvEnv(UsvEnv):
    """The task with a second pole further down the course, for judging policies trained on one
    (:func:`two_pole_env`): state ``[x (11); pole2_x, pole2_y, pole2_radius]`` (dX = 14). The
    hull moves as in :class:`UsvEnv`; the sensors see both poles (each beam reads the nearer), the
    clearance is to the nearer pole, and a collision is with either. Observations have the
    one-pole env's layout, so a policy trained there acts here unchanged."""

    dX: int = DX + 3

    def step(self, x: Array, u: Array) -> Array:
        check_shape("usv.step", "x", x, (self.dX,))
        nxt = hull_sim.hull_step(self.params, x[:IX_RADIUS], self.command(u), self.model)
        return jnp.concatenate([nxt, x[IX_RADIUS:]])

    def _second(self, x: Array) -> Array:
        """The one-pole state [11] of the same hull with the second pole in place of the first."""
        return jnp.concatenate([x[: hull_sim.SL_OBS.start], x[IX_POLE2], x[IX_RADIUS2, None]])

    def ranges(self, x: Array, key: PRNGKey | None = None) -> Array:
        keys = (None, None) if key is None else tuple(jax.random.split(key))
        one = UsvEnv.ranges(self, x[:DX], keys[0])
        two = UsvEnv.ranges(self, self._second(x), keys[1])
        return jnp.minimum(one, two)

    def clearance(self, x: Array) -> Array:
        return jnp.minimum(UsvEnv.clearance(self, x[:DX]), UsvEnv.clearance(self, self._second(x)))


def two_pole_env(env: UsvEnv, x0: Array, gap, radius, key: PRNGKey) -> TwoPoleUsvEnv:
    """``env`` (one pole) with a second pole on the course line beyond each start's first: ``gap``
    (m, a (low, high) range) further down the course, of a radius drawn from ``radius`` (a range);
    the starts ``x0: [B, 11]`` keep everything else. The env judges with ``env.horizon``."""
    k_gap, k_radius = jax.random.split(key)
    n, dtype = x0.shape[0], x0.dtype
    d = jax.random.uniform(k_gap, (n,), dtype, *gap)
    r = jax.random.uniform(k_radius, (n,), dtype, *radius)
    pole2 = jnp.stack([x0[:, hull_sim.IX_OBS_X] + d, x0[:, hull_sim.IX_OBS_Y]], axis=-1)
    x2 = jnp.concatenate([x0, pole2, r[:, None]], axis=-1)
    fields = {f.name: getattr(env, f.name) for f in dataclasses.fields(UsvEnv) if f.init}
    names = (*STATE_NAMES, "pole2_x", "pole2_y", "pole2_radius")
    changes = {"x0": x2, "dX": DX + 3, "name": env.name + "_two_poles", "state_names": names}
    return TwoPoleUsvEnv(**{**fields, **changes})


def default_conditions(radius: float = 0.5, speed: float = 10.0) -> np.ndarray:
    """x0 [4, 11]: the hull env's default poles (:data:`diffgcl.envs.hull.DEFAULT_POLES`) ahead of
    a boat at the origin on course at ``speed`` (thrust state at the thrust that holds it)."""
    from diffgcl.envs.hull import DEFAULT_POLES

    params = hull_sim.default_params()  # JAX's float type: float64 only where x64 is on
    poles = np.asarray(DEFAULT_POLES, dtype=float)
    x0 = np.zeros((poles.shape[0], DX))
    x0[:, hull_sim.IX_VX] = speed
    x0[:, hull_sim.IX_THRUST] = cruise_thrust(params, speed)
    x0[:, hull_sim.SL_OBS] = poles
    x0[:, IX_RADIUS] = radius
    return x0


def make_usv_env(
    x0=None,
    *,
    params: HullParams | None = None,
    layout: SensorLayout | None = None,
    cruise_speed: float = 10.0,
    horizon: int = 240,
    observation: str = "full",
    range_encoding: str = "metres",
    weights: HullCostWeights | None = None,
    action_scale=None,
    sensors: PoleSensorModel | None = None,
    proximity_margins=PROXIMITY_MARGINS,
) -> UsvEnv:
    """The USV task env with conditions ``x0: [C, 11]`` (task frame; see
    :func:`diffgcl.usv.task.make_task_env`; default :func:`default_conditions`), hull
    ``params`` (default nominal; e.g. identified from bags), sensor ``layout``, ``cruise_speed``
    (m/s; the thrust that holds it is the action offset), horizon T, the policy's
    ``observation`` set (``OBSERVATIONS``) and how it reads ranges (``range_encoding``, of
    ``RANGE_ENCODINGS``: :func:`encode_ranges`), the recorded ``sensors`` behind the observed beams
    (default: the synthetic Odin-like ones), the clearance margins (m) of the learned cost's
    barrier residuals (:meth:`UsvEnv.cost_residuals`). ``action_scale`` defaults to [max thrust,
    max nozzle angle]."""
    if observation not in OBSERVATIONS:
        raise ValueError(f"usv: observation {observation!r}; choose one of {OBSERVATIONS}")
    if range_encoding not in RANGE_ENCODINGS:
        raise ValueError(f"usv: range encoding {range_encoding!r}; choose one of {RANGE_ENCODINGS}")
    margins = tuple(float(d) for d in proximity_margins)
    if not margins or min(margins) <= 0 or list(margins) != sorted(set(margins)):
        raise ValueError(
            f"usv: proximity margins {proximity_margins!r}; give one or more increasing "
            "clearances in m, each > 0 (e.g. 5, 10, 15, 20)"
        )
    dtype = jnp.zeros(()).dtype
    x0 = default_conditions(speed=cruise_speed) if x0 is None else x0
    x0 = np.atleast_2d(np.asarray(x0, dtype=float))
    if x0.shape[1:] != (DX,):
        raise ValueError(f"usv: x0 must be [C, {DX}] task-frame states, got {x0.shape}")
    if not np.all(x0[:, IX_RADIUS] > 0):
        raise ValueError("usv: every condition needs a positive pole radius (x0[:, 10])")
    params = hull_sim.default_params(dtype) if params is None else params
    params = jax.tree.map(lambda v: jnp.asarray(v, dtype), params)
    thrust = cruise_thrust(params, cruise_speed)
    scale = (
        [float(params.max_thrust), float(params.max_nozzle)]
        if action_scale is None
        else action_scale
    )
    return UsvEnv(
        params=params,
        model=hull_sim.hull_model(dtype)[1],
        layout=layout or SensorLayout(),
        x0=jnp.asarray(x0, dtype),
        cruise_speed=float(cruise_speed),
        cruise_thrust=thrust,
        action_offset=jnp.asarray([thrust, 0.0], dtype),
        action_scale=jnp.asarray(scale, dtype),
        observation=observation,
        range_encoding=range_encoding,
        sensors=sensors or PoleSensorModel(),
        weights=weights or HullCostWeights(),
        proximity_margins=margins,
        horizon=horizon,
    )
