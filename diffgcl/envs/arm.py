"""The planar two-joint arm of the seed's experiment (GPS's box2d arm), on MJX.

State ``x = [q1, q2, dq1, dq2]`` (dX = 4), action ``u`` = target joint speeds (dU = 2), observation
``o = [q1, q2, dq1, dq2, ee_x, ee_y]`` (dO = 6; the end effector comes from MJX kinematics).
Task (DESIGN §2): from ``x0 = [0.75π, 0.5π, 0, 0]`` reach ``q* = [0, 0]`` within T = 100 steps of
dt = 0.05 and hold it; expert cost ``½‖q − q*‖² + 1e-5·½‖u‖²``; success when both joints are
within 0.1 rad of the target over the last 10 states.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from diffgcl.checks import check_shape
from diffgcl.sim import mjcf
from diffgcl.sim.mjcf import load_mjcf, make_data, put_model, require, resolve_mjcf
from diffgcl.types import Array, PRNGKey

ARM_MJCF = "arm2d.xml"
DEFAULT_X0 = (0.75 * math.pi, 0.5 * math.pi, 0.0, 0.0)
DEFAULT_TARGET = (0.0, 0.0)


@dataclasses.dataclass(frozen=True, eq=False)
class ArmEnv:
    """Two-joint arm; build with :func:`make_arm_env`. Hashable by identity (a jit static arg)."""

    model: mjx.Model
    data0: mjx.Data
    x0: Array  # [C, dX]
    target: Array  # [2]
    mjcf_path: str
    torque_limit: float
    dt: float  # from the C model: the MJX copy may hold it in float32
    horizon: int = 100
    action_weight: float = 1e-5
    success_tolerance: float = 0.1
    success_hold_steps: int = 10
    name: str = "arm"
    dX: int = 4
    dU: int = 2
    dO: int = 6

    def step(self, x: Array, u: Array) -> Array:
        """One MJX step. x: [4], u: [2] -> x': [4]."""
        check_shape("arm.step", "x", x, (self.dX,))
        check_shape("arm.step", "u", u, (self.dU,))
        d = self.data0.replace(qpos=x[:2], qvel=x[2:], ctrl=u)
        d = mjcf.step(self.model, d)
        return jnp.concatenate([d.qpos, d.qvel])

    def end_effector(self, x: Array) -> Array:
        """End-effector position [2] in the plane, from MJX forward kinematics."""
        d = mjcf.kinematics(self.model, self.data0.replace(qpos=x[:2]))
        return d.site_xpos[0, :2]

    def obs(self, x: Array, key: PRNGKey | None = None) -> Array:
        """x: [4] -> o: [6]. The arm's sensors are exact; ``key`` is accepted and unused."""
        check_shape("arm.obs", "x", x, (self.dX,))
        return jnp.concatenate([x, self.end_effector(x)])

    def initial_states(self) -> Array:
        """Conditions x0: [C, 4]."""
        return self.x0

    def expert_cost(self, x: Array, u: Array, t: Array) -> Array:
        """½‖q − q*‖² + w_u·½‖u‖² (the terminal step passes u = 0)."""
        dq = x[:2] - self.target
        return 0.5 * jnp.dot(dq, dq) + self.action_weight * 0.5 * jnp.dot(u, u)

    def success(self, X: Array) -> Array:
        """X: [T+1, 4] -> bool: |q − q*| < tol on both joints over the last states."""
        err = jnp.abs(X[-self.success_hold_steps :, :2] - self.target)
        return jnp.all(err < self.success_tolerance)

    def final_distance(self, X: Array) -> Array:
        """Largest joint error at the final state, radians."""
        return jnp.max(jnp.abs(X[-1, :2] - self.target))


def make_arm_env(
    *,
    torque_limit: float = 1000.0,
    x0=DEFAULT_X0,
    target=DEFAULT_TARGET,
    horizon: int = 100,
    mjcf: str = ARM_MJCF,
) -> ArmEnv:
    """The arm env. ``x0`` may be one state [4] or conditions [C, 4]; ``target``: the joint angles
    to reach [2]; ``torque_limit=400`` reproduces box2d's cap (infeasible within T = 100, see
    models/arm2d.xml). On the command line: ``--env-set x0=...,target=...``
    (:mod:`diffgcl.envs.options`)."""
    path = resolve_mjcf(mjcf)
    model = load_mjcf(path)
    require(model, path, nq=2, nv=2, nu=2)
    if not torque_limit > 0:
        raise ValueError(f"arm: torque_limit must be positive, got {torque_limit}")
    model.actuator_forcerange[:] = [[-torque_limit, torque_limit]] * 2
    mx = put_model(model)
    dtype = jnp.zeros(()).dtype
    x0 = np.atleast_2d(np.asarray(x0, dtype=float))
    if x0.ndim != 2 or x0.shape[1:] != (4,):
        raise ValueError(f"arm: x0 must be [4] or [C, 4], got shape {x0.shape}")
    target = np.asarray(target, dtype=float)
    if target.shape != (2,):
        raise ValueError(f"arm: target must be [2] (joint angles), got shape {target.shape}")
    if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(target))):
        raise ValueError("arm: x0 and target must be finite")
    if horizon < 1:
        raise ValueError(f"arm: horizon must be positive, got {horizon}")
    return ArmEnv(
        model=mx,
        data0=make_data(mx),
        x0=jnp.asarray(x0, dtype),
        target=jnp.asarray(target, dtype),
        mjcf_path=str(path),
        torque_limit=float(torque_limit),
        dt=float(model.opt.timestep),
        horizon=horizon,
    )
