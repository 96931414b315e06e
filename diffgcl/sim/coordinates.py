"""Vector-space coordinates for MuJoCo's configuration: a fixed chart of the quaternion joints.

MuJoCo stores a ball joint's orientation as a unit quaternion (4 numbers, 3 degrees of freedom)
and a free joint's as a position and a quaternion (7 numbers, 6 degrees of freedom), so
``qpos`` has ``nq`` entries while ``qvel`` has ``nv < nq``. Everything downstream of an env in
diffgcl — linear-Gaussian controllers ``u = K x + k``, the dynamics fit ``x' ≈ A x + B u + c``,
the cost network on normalised states, the fusion densities, the demos' fitted controller —
treats the state as a vector in ``R^dX``. A quaternion is not one: adding a perturbation leaves
the unit sphere, and a Jacobian taken in quaternion coordinates has a direction (the norm) the
dynamics do not have.

The generic env therefore holds the configuration in **exponential coordinates about a fixed
reference orientation**: a ball joint's quaternion ``q`` becomes the rotation vector
``r = log(q_ref⁻¹ ⊗ q) ∈ R³`` (``q = q_ref ⊗ exp(r)``, a rotation in the joint's local frame,
as MuJoCo integrates angular velocity), a free joint's position is kept as it is; hinge and slide
joints are scalars already. The configuration part of the state then has ``nv`` entries, one per
degree of freedom, and ``jax.jacfwd`` of ``chart ∘ mjx.step ∘ chart⁻¹`` is the linearisation in
the tangent space (at the reference orientation, carried to the current one by the chart's
derivative). The alternative — keep quaternions in the state and linearise through a retraction
about each nominal state — would make every controller, cost and density above work in
deviations from a per-time-step nominal, and the fusion weights compare samples of controllers
linearised about different nominals; the fixed chart leaves all of them unchanged.

Limit of the chart: a rotation of π from the reference is its boundary (``r`` jumps from ``π·n``
to ``−π·n``). Tasks whose bodies turn further than that from their reference orientation need a
reference (``q_ref``, the keyframe) chosen near the middle of the motion.

The exponential and logarithm switch to Taylor series near the identity so that their values and
derivatives are exact to rounding at ``r = 0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import mujoco
import numpy as np

from diffgcl.types import Array

# Below this squared angle the Taylor branches are used (their truncation error is ~θ⁴ relative).
_SMALL_ANGLE_SQ = 1e-8


def quat_mul(a: Array, b: Array) -> Array:
    """Hamilton product of quaternions ``[w, x, y, z]`` (MuJoCo's order): [4]."""
    aw, av = a[0], a[1:]
    bw, bv = b[0], b[1:]
    w = aw * bw - av @ bv
    v = aw * bv + bw * av + jnp.cross(av, bv)
    return jnp.concatenate([w[None], v])


def quat_conj(q: Array) -> Array:
    """Conjugate (the inverse of a unit quaternion): [4]."""
    return q * jnp.asarray([1.0, -1.0, -1.0, -1.0], q.dtype)


def quat_exp(r: Array) -> Array:
    """Unit quaternion of the rotation vector ``r: [3]`` (angle ``|r|`` about ``r/|r|``): [4]."""
    theta_sq = r @ r
    small = theta_sq < _SMALL_ANGLE_SQ
    theta = jnp.sqrt(jnp.where(small, 1.0, theta_sq))
    w = jnp.where(small, 1.0 - theta_sq / 8.0, jnp.cos(0.5 * theta))
    # sin(θ/2)/θ = 1/2 − θ²/48 + O(θ⁴)
    s = jnp.where(small, 0.5 - theta_sq / 48.0, jnp.sin(0.5 * theta) / theta)
    return jnp.concatenate([w[None], s * r])


def quat_log(q: Array) -> Array:
    """Rotation vector ``r: [3]`` of a quaternion ``q: [4]`` (normalised first; ``q`` and ``−q``
    give the same ``r``, with ``|r| ≤ π``)."""
    q = q / jnp.sqrt(q @ q)
    q = jnp.where(q[0] < 0, -q, q)
    w, v = q[0], q[1:]
    s_sq = v @ v
    small = s_sq < _SMALL_ANGLE_SQ
    s = jnp.sqrt(jnp.where(small, 1.0, s_sq))
    # 2·atan2(s, w)/s = 2/w − (2/3)·s²/w³ + O(s⁴)
    factor = jnp.where(small, 2.0 / w - (2.0 / 3.0) * s_sq / w**3, 2.0 * jnp.arctan2(s, w) / s)
    return factor * v


@dataclass(frozen=True, eq=False)
class ConfigurationChart:
    """The map between MuJoCo's ``qpos: [nq]`` and the vector ``xq: [nv]`` (module docstring).

    Built from a C model by :func:`configuration_chart`. Index arrays are host NumPy (static
    under jit): ``scalar_qpos``/``scalar_x`` copy hinge, slide and free-joint position entries;
    ``quat_qpos: [B, 4]``/``quat_x: [B, 3]`` locate each ball or free joint's quaternion and
    rotation vector; ``quat_ref: [B, 4]`` are the reference orientations; ``joint_names: [B]``
    name the quaternion joints (for error messages). ``identity`` when there is no quaternion and
    ``qpos`` is the state's configuration part as it is.
    """

    nq: int
    nv: int
    scalar_qpos: np.ndarray
    scalar_x: np.ndarray
    quat_qpos: np.ndarray
    quat_x: np.ndarray
    quat_ref: np.ndarray
    joint_names: tuple[str, ...]

    @property
    def identity(self) -> bool:
        return len(self.quat_qpos) == 0 and np.array_equal(self.scalar_qpos, np.arange(self.nq))

    def to_qpos(self, xq: Array) -> Array:
        """``xq: [nv]`` -> ``qpos: [nq]`` (unit quaternions ``q_ref ⊗ exp(r)``)."""
        if self.identity:
            return xq
        qpos = jnp.zeros(self.nq, xq.dtype).at[self.scalar_qpos].set(xq[self.scalar_x])
        for i in range(len(self.quat_qpos)):
            ref = jnp.asarray(self.quat_ref[i], xq.dtype)
            qpos = qpos.at[self.quat_qpos[i]].set(quat_mul(ref, quat_exp(xq[self.quat_x[i]])))
        return qpos

    def from_qpos(self, qpos: Array) -> Array:
        """``qpos: [nq]`` -> ``xq: [nv]`` (rotation vectors ``log(q_ref⁻¹ ⊗ q)``)."""
        if self.identity:
            return qpos
        xq = jnp.zeros(self.nv, qpos.dtype).at[self.scalar_x].set(qpos[self.scalar_qpos])
        for i in range(len(self.quat_qpos)):
            ref = jnp.asarray(self.quat_ref[i], qpos.dtype)
            r = quat_log(quat_mul(quat_conj(ref), qpos[self.quat_qpos[i]]))
            xq = xq.at[self.quat_x[i]].set(r)
        return xq


def configuration_chart(
    model: mujoco.MjModel, reference_qpos: np.ndarray | None = None
) -> ConfigurationChart:
    """The chart of ``model``'s joints; quaternion references from ``reference_qpos: [nq]``
    (default ``model.qpos0``, normalised)."""
    ref_qpos = np.asarray(model.qpos0 if reference_qpos is None else reference_qpos, float)
    scalar_qpos, scalar_x, quat_qpos, quat_x, quat_ref, names = [], [], [], [], [], []
    for j in range(model.njnt):
        kind = int(model.jnt_type[j])
        qa, da = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        if kind in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            scalar_qpos.append(qa)
            scalar_x.append(da)
            continue
        if kind == int(mujoco.mjtJoint.mjJNT_FREE):
            scalar_qpos += [qa, qa + 1, qa + 2]
            scalar_x += [da, da + 1, da + 2]
            qa, da = qa + 3, da + 3
        ref = ref_qpos[qa : qa + 4]
        quat_qpos.append(np.arange(qa, qa + 4))
        quat_x.append(np.arange(da, da + 3))
        quat_ref.append(ref / np.linalg.norm(ref))
        names.append(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint {j}")
    return ConfigurationChart(
        nq=model.nq,
        nv=model.nv,
        scalar_qpos=np.asarray(scalar_qpos, int),
        scalar_x=np.asarray(scalar_x, int),
        quat_qpos=np.asarray(quat_qpos, int).reshape(-1, 4),
        quat_x=np.asarray(quat_x, int).reshape(-1, 3),
        quat_ref=np.asarray(quat_ref, float).reshape(-1, 4),
        joint_names=tuple(names),
    )
