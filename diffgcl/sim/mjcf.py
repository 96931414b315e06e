"""The one place that resolves and loads MJCF files, with errors that name the file."""

from __future__ import annotations

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx


class MJCFError(ValueError):
    """An MJCF file is missing, malformed, or does not fit the environment that loads it."""


def models_dir() -> Path:
    """The repository's ``models/`` folder (override with ``$DIFFGCL_MODELS``)."""
    env = os.environ.get("DIFFGCL_MODELS")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "models"


def resolve_mjcf(name_or_path: str | os.PathLike) -> Path:
    """``"arm2d.xml"`` → ``models/arm2d.xml``; an existing path is returned as is."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    candidate = models_dir() / path
    if candidate.is_file():
        return candidate
    raise MJCFError(f"{name_or_path}: MJCF file not found (looked in {models_dir()})")


def load_mjcf(name_or_path: str | os.PathLike) -> mujoco.MjModel:
    """Compile an MJCF file with C MuJoCo; a parse or compile error names the file."""
    path = resolve_mjcf(name_or_path)
    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as err:
        raise MJCFError(f"{path}: cannot load MJCF: {err}") from None


def put_model(model: mujoco.MjModel) -> mjx.Model:
    """Copy a C model to an MJX model in the current default float precision, on this process's
    first device (see :func:`make_data`).

    MJX follows ``jax_enable_x64``: float64 when it is on, float32 otherwise.
    """
    mx = mjx.put_model(model, device=jax.local_devices()[0])
    dtype = jnp.zeros(()).dtype

    def cast(a):
        if isinstance(a, jax.Array | np.ndarray) and np.issubdtype(a.dtype, np.floating):
            return a.astype(dtype)
        return a

    return jax.tree.map(cast, mx)


# MJX's stages as jitted functions of (model, data), for every env's ``step`` and ``obs``. Inside
# a traced program JAX then traces ``mjx.step`` once per model layout and reuses that jaxpr (and
# its batched and forward-mode transforms) at every call site, instead of running MJX's Python
# again at each: tracing the arm's rGCL v1 batch took 11.6 s instead of 21.4 s, with the same
# compiled program and results (XLA inlines the nested call). The model is an argument, not a
# closed-over constant, so envs that differ only in their start states or targets share it.
step = jax.jit(mjx.step)
forward = jax.jit(mjx.forward)
kinematics = jax.jit(mjx.kinematics)


def make_data(mx: mjx.Model) -> mjx.Data:
    """``mjx.make_data`` on this process's first device. MJX's default is ``jax.devices()[0]``,
    which in a multi-process run (:mod:`diffgcl.distributed`) belongs to process 0: the other
    processes could not even build an env (measured: "Number of addressable output shards must
    match", then "Cross-host transfers are not supported" with the model there too)."""
    return mjx.make_data(mx, device=jax.local_devices()[0])


def require(model: mujoco.MjModel, path: str | os.PathLike, **sizes: int) -> None:
    """Check model sizes (e.g. ``nq=2, nu=2``); a mismatch is an :class:`MJCFError`."""
    for field, expected in sizes.items():
        got = getattr(model, field)
        if got != expected:
            raise MJCFError(f"{path}: expected {field} = {expected}, the file has {got}")


def _name(model: mujoco.MjModel, objtype, index: int, kind: str) -> str:
    name = mujoco.mj_id2name(model, objtype, int(index))
    return f"{kind} {name!r}" if name else f"{kind} #{int(index)}"


def mjx_unsupported(model: mujoco.MjModel) -> str | None:
    """The first feature of ``model`` that MJX's JAX backend cannot run, named with its element
    (``"actuator 'lift': transmission mjTRN_TENDON"``), or None.

    Checked element by element against the feature sets MJX declares (its ``types`` enums and the
    collision table), so that the message can say where the feature is; MJX's own
    ``put_model`` names only the feature. Should MJX's private modules move, only the option and
    flex checks remain and :func:`put_model_checked` still reports MJX's own message.
    """
    o = model.opt
    try:
        from mujoco.mjx._src import collision_driver
        from mujoco.mjx._src import types as mjx_types
    except ImportError:  # pragma: no cover - depends on the installed MJX
        mjx_types = collision_driver = None
    if model.nflex:
        return f"{_name(model, mujoco.mjtObj.mjOBJ_FLEX, 0, 'flex')}: flexes (deformables)"
    if mjx_types is None:
        return None
    options = (
        ("integrator", o.integrator, mjx_types.IntegratorType, mujoco.mjtIntegrator),
        ("solver", o.solver, mjx_types.SolverType, mujoco.mjtSolver),
        ("cone", o.cone, mjx_types.ConeType, mujoco.mjtCone),
        ("jacobian", o.jacobian, mjx_types.JacobianType, mujoco.mjtJacobian),
    )
    for field, value, supported, enum in options:
        if value not in set(supported):
            return f"<option {field}>: {enum(value).name}"
    for i in range(mujoco.mjtEnableBit.mjNENABLE):
        if o.enableflags & 2**i and 2**i not in set(mjx_types.EnableBit):
            return f"<option><flag>: {mujoco.mjtEnableBit(2**i).name}"
    fluid = o.density > 0 or o.viscosity > 0 or np.any(o.wind)
    if fluid and o.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        return "<option integrator>: implicitfast with fluid drag (density/viscosity/wind)"
    per_element = (
        ("actuator", mujoco.mjtObj.mjOBJ_ACTUATOR, model.actuator_trntype, mjx_types.TrnType,
         mujoco.mjtTrn, "transmission"),
        ("actuator", mujoco.mjtObj.mjOBJ_ACTUATOR, model.actuator_dyntype, mjx_types.DynType,
         mujoco.mjtDyn, "dynamics"),
        ("actuator", mujoco.mjtObj.mjOBJ_ACTUATOR, model.actuator_gaintype, mjx_types.GainType,
         mujoco.mjtGain, "gain"),
        ("actuator", mujoco.mjtObj.mjOBJ_ACTUATOR, model.actuator_biastype, mjx_types.BiasType,
         mujoco.mjtBias, "bias"),
        ("equality", mujoco.mjtObj.mjOBJ_EQUALITY, model.eq_type, mjx_types.EqType,
         mujoco.mjtEq, "type"),
        ("sensor", mujoco.mjtObj.mjOBJ_SENSOR, model.sensor_type, mjx_types.SensorType,
         mujoco.mjtSensor, "type"),
    )  # fmt: skip
    for kind, objtype, values, supported, enum, what in per_element:
        allowed = {int(v) for v in supported}
        for i, v in enumerate(values):
            if int(v) not in allowed:
                return f"{_name(model, objtype, i, kind)}: {what} {enum(int(v)).name}"
    allowed_wraps = {int(v) for v in mjx_types.WrapType}
    for t in range(model.ntendon):
        start, num = model.tendon_adr[t], model.tendon_num[t]
        for w in model.wrap_type[start : start + num]:
            if int(w) not in allowed_wraps:
                wrap = mujoco.mjtWrap(int(w)).name
                return f"{_name(model, mujoco.mjtObj.mjOBJ_TENDON, t, 'tendon')}: wrap {wrap}"
    if collision_driver is not None:
        for g1, g2, _ in collision_driver.geom_pairs(model):
            t1, t2 = model.geom_type[[g1, g2]]
            if not collision_driver.has_collision_fn(t1, t2):
                a = _name(model, mujoco.mjtObj.mjOBJ_GEOM, g1, "geom")
                b = _name(model, mujoco.mjtObj.mjOBJ_GEOM, g2, "geom")
                kinds = f"{mujoco.mjtGeom(int(t1)).name}-{mujoco.mjtGeom(int(t2)).name}"
                return f"{a} and {b}: collisions {kinds}"
    return None


def put_model_checked(model: mujoco.MjModel, path: str | os.PathLike) -> mjx.Model:
    """:func:`put_model` after :func:`mjx_unsupported`; what MJX cannot run is an
    :class:`MJCFError` naming the file, the element and the feature."""
    problem = mjx_unsupported(model)
    if problem is not None:
        raise MJCFError(f"{path}: MJX cannot run {problem}")
    try:
        return put_model(model)
    except NotImplementedError as err:
        raise MJCFError(f"{path}: MJX cannot run this model: {err}") from None
