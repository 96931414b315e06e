"""Odin-like water-jet boat: Fossen (2011) 3-DOF manoeuvring model applied inside MJX.

Problem. MuJoCo has no body-frame added mass and MJX ignores its ellipsoid fluid model, so the
hydrodynamics of a planing boat cannot come from MuJoCo itself. This module computes the body-
frame acceleration of Fossen's 3-DOF manoeuvring model (Fossen 2011, Ch. 6 and 7; chapter-level
citations throughout, the equation numbers differ between editions)

    M ν̇ + C(ν) ν + D(ν) ν = τ,          ν = [u, v, r]   (surge, sway, yaw rate; body frame)

in JAX and hands MuJoCo the *computed acceleration*: on planar joints (slide x, slide y, hinge z,
centre of mass on the hinge axis) the joint mass matrix is diag(m, m, I_z), and the world-frame
acceleration of [x, y, ψ] is (the 3-DOF kinematics η̇ = R(ψ) ν of Fossen 2011 Ch. 2, differentiated)

    η̈ = R(ψ) (ν̇ + S(r) ν),   S(r) ν = [−r v, r u, 0],

so ``qfrc_applied = diag(m, m, I_z) R(ψ) (ν̇ + [−r v, r u, 0])`` makes ``mjx.step`` integrate the
Fossen ODE (semi-implicit Euler, ``SUBSTEPS`` substeps per control step).

Frames and signs. World: x, y horizontal, z up, heading ψ counter-clockwise about +z (MuJoCo's
convention). Body: x forward, y to port. Fossen's equations are written in NED/FRD; the 3-DOF
equations below are invariant under the mirror y → −y (v, r, τ_v, τ_r all change sign), so they
hold unchanged in this right-handed z-up frame.

Propulsion. Two water jets at the transom, lumped into one jet on the centreline at
x = −``jet_arm`` (−5 m). Thrust T > 0 pushes the boat forward; the nozzle angle δ > 0 turns the
jet so that its reaction force on the stern points to starboard (−y):

    τ = [T cos δ, −T sin δ, jet_arm · T sin δ]     (moment of F_y = −T sin δ applied at x = −5 m)

so δ > 0 swings the stern to starboard and turns the bow to port (ψ increases, r > 0). Reverse
thrust (reversing buckets) uses the same formula with T < 0. Thrust and nozzle follow their
commands with first-order lags (``tau_thrust``, ``tau_nozzle``); the lagged values are state.

State and action (fixed layout; see the ``IX_*`` constants):

    x = [p_x, p_y, ψ, ẋ, ẏ, ψ̇, thrust, nozzle, obs_x, obs_y]   (dX = 10, world frame, SI units)
    u = [thrust_cmd (N), nozzle_cmd (rad)]                      (dU = 2)

``obs_x, obs_y`` is the pole position; it is constant in time and carried through the step.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from diffgcl.checks import check_shape
from diffgcl.sim.mjcf import MJCFError, load_mjcf, make_data, put_model, require

Array = jax.Array

# ---- State / action layout (the single source of truth; ROS-bag ingestion depends on it). ----
IX_PX, IX_PY, IX_PSI = 0, 1, 2  # world position (m), heading (rad, CCW from world x)
IX_VX, IX_VY, IX_R = 3, 4, 5  # world velocity (m/s), yaw rate (rad/s)
IX_THRUST, IX_NOZZLE = 6, 7  # lagged thrust (N) and nozzle angle (rad)
IX_OBS_X, IX_OBS_Y = 8, 9  # pole position (m), constant
IU_THRUST, IU_NOZZLE = 0, 1  # commands: thrust (N), nozzle angle (rad)
SL_QPOS = slice(0, 3)
SL_QVEL = slice(3, 6)
SL_ACT = slice(6, 8)
SL_OBS = slice(8, 10)
DX = 10
DU = 2
STATE_NAMES = ("p_x", "p_y", "psi", "vx", "vy", "psi_dot", "thrust", "nozzle", "obs_x", "obs_y")
ACTION_NAMES = ("thrust_cmd", "nozzle_cmd")

MJCF_NAME = "odin_hull.xml"
SUBSTEPS = 4  # MuJoCo steps per control step (timestep 0.025 s in the MJCF -> dt = 0.1 s)
KNOT = 1852.0 / 3600.0  # m/s


@struct.dataclass
class HullParams:
    """All parameters of the hull model, one scalar leaf each (a differentiable pytree).

    Odin's particulars are not public. The set below is a documented ~10.5 m, ~7.5 t planing
    water-jet boat (DESIGN.md §2). Hydrodynamic derivatives are given as positive magnitudes
    (Fossen writes them as negative derivatives, X_u̇ = −``added_mass_u`` etc.).

    For system identification, differentiate through :func:`hull_step` with respect to the
    leaves listed in :data:`IDENTIFIABLE` (the mass scale, added masses, damping, thrust gain,
    jet lever arm and lags); the limits are physical bounds and are not meant to be fitted.
    """

    # Rigid body. L = 10.5 m, B = 3.4 m, m = 7.5 t (boat of Odin's class, fully equipped);
    # I_z = m (0.25 L)^2, the usual radius of gyration of a ship in yaw.
    length: float = 10.5
    beam: float = 3.4
    mass: float = 7500.0
    inertia_z: float = 7500.0 * (0.25 * 10.5) ** 2
    # One multiplier on the whole inertia matrix M = M_RB + M_A (1 = nominal): the single
    # "how heavy does it feel" knob that system identification fits first.
    inertia_scale: float = 1.0

    # Added mass (Fossen 2011 Ch. 6). Surge: ~5 % of m, typical of slender planing hulls.
    # Sway: strip theory with flat-plate sections of draft T ≈ 0.5 m, ½ π ρ T² per metre over
    # L -> A22 ≈ 4.2 t (0.55 m). Yaw: the same uniform sections, A66 ≈ A22 L²/12 ≈ 38 t m²
    # (0.73 I_z).
    added_mass_u: float = 375.0
    added_mass_v: float = 4140.0
    added_mass_r: float = 38000.0

    # Damping (Fossen 2011 Ch. 6): linear + quadratic, D(ν)ν below. Surge is sized from the
    # resistance; sway and yaw were tuned (a grid search over Y_v, N_r, N_v, N_|r|r) so that the
    # manoeuvring figures come out like those of a ~30 kn water-jet boat. Measured with
    # experiments/hull_report.py: top speed 29.9 kn; turning diameter 4.45 L at full nozzle and
    # thrust (22 kn in the turn, 28°/s, drift 3°); 10/10 zig-zag overshoots 8.4° and 12.4°;
    # crash-stop distance 116 m (11 L) -- long for a water-jet boat, because quadratic resistance
    # has no planing hump and the brief's reverse thrust is only 40 % after a 1.5 s lag.
    # Surge: resistance ≈ 12 kN at 30 kn (15.43 m/s), i.e. resistance/weight ≈ 0.16, typical of a
    # planing hull near top speed; 20 % of it linear (X_u), 80 % quadratic (X_|u|u).
    damping_u: float = 160.0  # X_u     [N s/m]
    damping_uu: float = 40.3  # X_|u|u  [N s²/m²]
    # Sway: a planing hull with chines, keel and jet intakes resists side-slip strongly; a weaker
    # Y_v lets the boat skid (drift angles > 15° in the turn) and makes it spiral-unstable.
    damping_v: float = 80000.0  # Y_v     [N s/m]
    # Cross-flow drag ½ ρ C_d T L (C_d ≈ 0.7, T ≈ 0.5 m, L = 10.5 m; Fossen 2011 Ch. 6).
    damping_vv: float = 1880.0  # Y_|v|v  [N s²/m²]
    # Yaw: linear N_r and quadratic N_|r|r. The cross-flow integral ½ ρ C_d T ∫|x|³dx = ½ ρ C_d T
    # L⁴/32 ≈ 68 kN m s² overdamps turning (a planing hull's aft sections are partly dry); a third
    # of it keeps the turning diameter in the 2-6 L band.
    damping_r: float = 30000.0  # N_r     [N m s]
    damping_rr: float = 20000.0  # N_|r|r  [N m s²]
    # Sway-yaw coupling: the lateral resistance Y_v v acts 0.75 m behind the CG (aft body, jet
    # intakes), giving the weather-vane moment N = +0.75 Y_v v = +damping_rv·v that opposes the
    # destabilising Munk moment −(m22 − m11) u v (≈ −58 kN m s/m · v at 30 kn). With it the hull is
    # straight-line stable up to top speed.
    damping_rv: float = 60000.0  # N_v magnitude [N s]

    # Propulsion (lumped twin water jets). ~12 kN total static thrust; reverse buckets give
    # ≤ 40 % of it; nozzles steer ±30°; the jets sit at the transom, 5 m behind the CG.
    thrust_gain: float = 1.0  # multiplies the lagged thrust state
    jet_arm: float = 5.0  # m
    max_thrust: float = 12000.0  # N
    reverse_fraction: float = 0.4
    max_nozzle: float = float(np.deg2rad(30.0))  # rad
    # Actuator lags: engine spool-up ~1.5 s, hydraulic nozzle ~0.3 s (first order).
    tau_thrust: float = 1.5  # s
    tau_nozzle: float = 0.3  # s


IDENTIFIABLE = (
    "inertia_scale",
    "added_mass_u",
    "added_mass_v",
    "added_mass_r",
    "damping_u",
    "damping_v",
    "damping_r",
    "damping_rv",
    "damping_uu",
    "damping_vv",
    "damping_rr",
    "thrust_gain",
    "jet_arm",
    "tau_thrust",
    "tau_nozzle",
)


def default_params(dtype=None) -> HullParams:
    """The nominal :class:`HullParams` as arrays of ``dtype`` (default: JAX's float type)."""
    dtype = jnp.zeros(()).dtype if dtype is None else dtype
    return jax.tree.map(lambda v: jnp.asarray(v, dtype=dtype), HullParams())


def clip_command(params: HullParams, u: Array) -> Array:
    """Saturate u = [thrust_cmd, nozzle_cmd]: [2] to the actuator limits."""
    thrust = jnp.clip(u[IU_THRUST], -params.reverse_fraction * params.max_thrust, params.max_thrust)
    nozzle = jnp.clip(u[IU_NOZZLE], -params.max_nozzle, params.max_nozzle)
    return jnp.stack([thrust, nozzle])


def jet_force(params: HullParams, thrust: Array, nozzle: Array) -> Array:
    """Body-frame generalised force τ = [X, Y, N]: [3] of the lumped jet (sign convention above)."""
    t = params.thrust_gain * thrust
    return jnp.stack(
        [t * jnp.cos(nozzle), -t * jnp.sin(nozzle), params.jet_arm * t * jnp.sin(nozzle)]
    )


def body_acceleration(params: HullParams, nu: Array, tau: Array) -> Array:
    """ν̇ = M⁻¹ (τ − C(ν) ν − D(ν) ν) for ν = [u, v, r]: [3], τ: [3] (Fossen 2011 Ch. 6-7).

    M = diag(m11, m22, m33) (CG at the origin, port-starboard symmetric, off-diagonal added mass
    neglected); C = C_RB + C_A (rigid-body and added-mass Coriolis matrices for a diagonal M) gives
    C(ν)ν = [−m22 v r, m11 u r, (m22 − m11) u v], whose last entry is the Munk moment.
    D(ν)ν = [(X_u + X_|u|u |u|) u, (Y_v + Y_|v|v |v|) v, (N_r + N_|r|r |r|) r − N_v v]: linear +
    quadratic cross-flow damping with the weather-vane coupling N_v of the aft lateral resistance.
    """
    u, v, r = nu[0], nu[1], nu[2]
    s = params.inertia_scale
    m11 = s * (params.mass + params.added_mass_u)
    m22 = s * (params.mass + params.added_mass_v)
    m33 = s * (params.inertia_z + params.added_mass_r)
    coriolis = jnp.stack([-m22 * v * r, m11 * u * r, (m22 - m11) * u * v])
    damping = jnp.stack(
        [
            (params.damping_u + params.damping_uu * jnp.abs(u)) * u,
            (params.damping_v + params.damping_vv * jnp.abs(v)) * v,
            (params.damping_r + params.damping_rr * jnp.abs(r)) * r - params.damping_rv * v,
        ]
    )
    return (tau - coriolis - damping) / jnp.stack([m11, m22, m33])


def body_velocity(x: Array) -> Array:
    """ν = [u, v, r]: [3] from the world-frame state x: [dX] (ν = R(ψ)ᵀ η̇, Fossen 2011 Ch. 2)."""
    c, s = jnp.cos(x[IX_PSI]), jnp.sin(x[IX_PSI])
    vx, vy = x[IX_VX], x[IX_VY]
    return jnp.stack([c * vx + s * vy, -s * vx + c * vy, x[IX_R]])


def world_acceleration(params: HullParams, x: Array) -> Array:
    """η̈ = [ẍ, ÿ, ψ̈]: [3] for state x: [dX] with the lagged actuators as they are in x.

    η̈ = R(ψ) (ν̇ + [−r v, r u, 0]): the derivative of η̇ = R(ψ) ν with Ṙ = R S(r).
    """
    nu = body_velocity(x)
    tau = jet_force(params, x[IX_THRUST], x[IX_NOZZLE])
    nu_dot = body_acceleration(params, nu, tau)
    u, v, r = nu[0], nu[1], nu[2]
    ax_b = nu_dot[0] - r * v
    ay_b = nu_dot[1] + r * u
    c, s = jnp.cos(x[IX_PSI]), jnp.sin(x[IX_PSI])
    return jnp.stack([c * ax_b - s * ay_b, s * ax_b + c * ay_b, nu_dot[2]])


def state_derivative(params: HullParams, x: Array, u: Array) -> Array:
    """Continuous-time ẋ = f(x, u): [dX] of the full state (for reference integrators).

    The command u: [dU] is saturated and drives the first-order actuator lags.
    """
    cmd = clip_command(params, u)
    act_dot = (cmd - x[SL_ACT]) / jnp.stack([params.tau_thrust, params.tau_nozzle])
    return jnp.concatenate(
        [x[SL_QVEL], world_acceleration(params, x), act_dot, jnp.zeros_like(x[SL_OBS])]
    )


@functools.lru_cache(maxsize=8)
def _cached_model(dtype_name: str, path: str) -> tuple[mujoco.MjModel, mjx.Model]:
    model = load_mjcf(path)
    check_hull_model(model, path)
    # The cache may first be filled while tracing; the arrays must be concrete, not tracers.
    with jax.ensure_compile_time_eval():
        return model, cast_model(put_model(model), dtype_name)


def cast_model(mx: mjx.Model, dtype) -> mjx.Model:
    """``mx`` with every floating-point array cast to ``dtype``."""

    def cast(a):
        if isinstance(a, jax.Array | np.ndarray) and np.issubdtype(a.dtype, np.floating):
            return jnp.asarray(a, dtype=dtype)
        return a

    return jax.tree.map(cast, mx)


def check_hull_model(model: mujoco.MjModel, path: str = MJCF_NAME) -> None:
    """Raise :class:`MJCFError` unless ``model`` has the layout :func:`hull_step` relies on."""
    require(model, path, nq=3, nv=3, nu=0, nmocap=1)
    types = list(model.jnt_type)
    want = [mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE]
    if types != want:
        raise MJCFError(f"{path}: the hull needs joints slide x, slide y, hinge z; got {types}")
    if model.nbody < 2 or model.body(1).name != "hull" or set(model.jnt_bodyid) != {1}:
        raise MJCFError(f"{path}: body 1 must be the 'hull' and carry all three joints")
    axes = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    if not np.allclose(model.jnt_axis, axes):
        raise MJCFError(f"{path}: the hull joints must be along world x, y and z")
    # The computed-acceleration trick needs the joint mass matrix to be diag(m, m, I_z).
    # body_inertia[1, 2] is I_z only if the inertia frame is the body frame.
    if (
        not np.allclose(model.body_ipos[1], 0.0)
        or not np.allclose(np.abs(model.body_iquat[1]), [1, 0, 0, 0])
        or np.any(model.dof_armature != 0)
    ):
        raise MJCFError(
            f"{path}: the hull's inertial frame must be its body frame (centre of mass on the "
            "joint axes, principal axes aligned) and the joints must have no armature"
        )
    if model.nmat < 1:
        raise MJCFError(f"{path}: mjx.ray needs at least one <material> in the model")
    if model.opt.integrator != mujoco.mjtIntegrator.mjINT_EULER:
        raise MJCFError(f"{path}: the hull expects integrator='Euler'")


def hull_model(dtype=None, path: str = MJCF_NAME) -> tuple[mujoco.MjModel, mjx.Model]:
    """The C model and the MJX model (in ``dtype``, default JAX's float type), cached."""
    dtype = jnp.dtype(jnp.zeros(()).dtype if dtype is None else dtype)
    return _cached_model(dtype.name, str(path))


@functools.partial(jax.jit, static_argnames=("substeps",))
def hull_step(
    params: HullParams,
    x: Array,
    u: Array,
    model: mjx.Model | None = None,
    substeps: int = SUBSTEPS,
) -> Array:
    """One control step x: [dX], u: [dU] -> x': [dX] (dt = substeps × model timestep = 0.1 s).

    Each substep computes η̈ from the Fossen model in JAX, applies it as ``qfrc_applied =
    diag(m, m, I_z) η̈`` (the model's own rigid-body mass, so that MuJoCo's qacc equals η̈ for
    any ``params``), and calls ``mjx.step`` (semi-implicit Euler). The actuator lags are advanced
    exactly for the held command: s' = c + (s − c) exp(−h/τ). Pure and differentiable in
    ``params``, ``x`` and ``u``; forward mode is the safe mode through ``mjx.step``.
    ``model`` defaults to ``models/odin_hull.xml`` in the dtype of ``x``.

    Jitted, so that a program calling it many times (rollouts, Jacobians, vmapped seeds) traces
    it once per shape and reuses its batched and differentiated forms: tracing the USV ``--fast``
    run's programs took 12.1 s instead of 19.2 s, same figures (``experiments/bench_tracing.py``).
    """
    check_shape("hull_step", "x", x, (DX,))
    check_shape("hull_step", "u", u, (DU,))
    if model is None:
        model = hull_model(x.dtype)[1]
    hull_body = 1
    mass_diag = jnp.stack(
        [model.body_mass[hull_body], model.body_mass[hull_body], model.body_inertia[hull_body, 2]]
    )
    h = model.opt.timestep
    cmd = clip_command(params, u)
    decay = jnp.exp(-h / jnp.stack([params.tau_thrust, params.tau_nozzle]))
    data0 = make_data(model)
    data0 = data0.replace(mocap_pos=data0.mocap_pos.at[0, :2].set(x[SL_OBS]))

    def substep(x, _):
        data = data0.replace(
            qpos=x[SL_QPOS], qvel=x[SL_QVEL], qfrc_applied=mass_diag * world_acceleration(params, x)
        )
        data = mjx.step(model, data)
        act = cmd + (x[SL_ACT] - cmd) * decay
        return jnp.concatenate([data.qpos, data.qvel, act, x[SL_OBS]]), None

    # A scan (not an unrolled loop) keeps one mjx.step in the program: compiles several times
    # faster, also under jacfwd.
    return jax.lax.scan(substep, x, None, length=substeps)[0]
