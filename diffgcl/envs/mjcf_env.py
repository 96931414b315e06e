"""A generic environment from any MJCF file that MJX can run: your own robot.

State ``x = [xq, qvel, act]`` with ``dX = 2·nv + na``: ``xq: [nv]`` is the configuration in the
vector-space chart of :mod:`diffgcl.sim.coordinates` (hinge and slide joints as they are, a ball
or free joint's quaternion as a rotation vector about a reference orientation — so that
controllers, costs and the autodiff linearisation live in the tangent space), ``qvel: [nv]``
MuJoCo's velocities, ``act: [na]`` the actuator activations where the model has any. Without
ball or free joints ``xq`` is ``qpos`` itself and the state is MuJoCo's ``[qpos, qvel, act]``.

Action ``u: [nu]``: ``ctrl = ctrl_scale · u``. With ``action_scale="ctrl"`` (the default) the
action *is* ``ctrl`` (MuJoCo clamps it to the actuators' ``ctrlrange`` where they are limited);
with ``action_scale="range"`` each actuator's action is divided by the largest magnitude of its
control range, so every action lives in about ``[-1, 1]`` — one exploration variance and one
action weight then fit all actuators, whatever their units (what the rGCL defaults for an unseen
model use, :mod:`diffgcl.api`).

Time step ``dt = frame_skip · model timestep`` (``dt`` from the user must be a whole multiple of
the model's timestep); the horizon ``T`` comes from the user (or the demos, in the API).
Conditions (start states): given as states ``x0``, or sampled around a keyframe (or the model's
``qpos0`` at rest) with ``spread`` in the configuration coordinates.

Observation, chosen with ``obs``: ``"state"`` (the default), or a tuple of parts concatenated in
order — ``"state"``, ``"qpos"`` (MuJoCo's, quaternions included), ``"qvel"``, ``"site:NAME"``
(world position [3]), ``"body:NAME"`` (world position [3]), ``"sensor:NAME"`` (the sensor's
reading, computed by ``mjx.forward`` at ``ctrl = 0``) — or a function ``o = f(x)`` of one state.
The parts that are not the state also feed a learned cost: :meth:`MJCFEnv.cost_features` is the
state followed by them, the network's input with ``network.features="env"`` (what
:func:`diffgcl.api.learn` sets when there are such parts).

Cost and success test are the user's, both optional: ``cost(x, u, t)`` (a
:data:`~diffgcl.types.CostFn`, the "true cost" reported next to the learned one) and
``success(X: [T+1, dX]) -> bool``. Without them ``expert_cost`` is 0 and ``success`` False, and
``has_cost`` / ``has_success`` say so (reports then leave them out).

What MJX cannot run is refused when the env is built, naming the element and the feature
(:func:`diffgcl.sim.mjcf.mjx_unsupported`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax import lax
from mujoco import mjx

from diffgcl.checks import check_shape
from diffgcl.sim import mjcf
from diffgcl.sim.coordinates import ConfigurationChart, configuration_chart
from diffgcl.sim.mjcf import MJCFError, load_mjcf, make_data, put_model_checked, resolve_mjcf
from diffgcl.types import Array, CostFn, PRNGKey

ACTION_SCALES = ("ctrl", "range")
OBS_KINDS = ("state", "qpos", "qvel", "site", "body", "sensor")


@dataclasses.dataclass(frozen=True, eq=False)
class MJCFEnv:
    """Generic MJCF env (module docstring); build with :func:`make_mjcf_env`. Hashable by identity
    (a jit static argument); change conditions or horizon with :meth:`with_conditions`."""

    model: mjx.Model
    data0: mjx.Data
    chart: ConfigurationChart
    x0: Array  # [C, dX]
    ctrl_scale: np.ndarray | None  # [nu]; None: the action is ctrl
    ctrl_range: np.ndarray  # [nu, 2]; ±inf where the actuator is not ctrl-limited
    joint_range: np.ndarray  # [dX, 2]; the limited hinge and slide joints' ranges (state_bounds)
    actuator_names: tuple[str, ...]
    mjcf_path: str
    dt: float
    frame_skip: int
    horizon: int
    name: str
    nq: int
    nv: int
    na: int
    dX: int
    dU: int
    dO: int
    obs_parts: tuple  # ((kind, index or None), ...) or a callable
    n_cost_features: int  # dX + the observation parts that are not the state
    true_cost: CostFn | None = None
    success_test: Callable[[Array], Array] | None = None

    # ---- MuJoCo <-> state ------------------------------------------------------------------

    def state_from_mujoco(self, qpos: Array, qvel: Array, act: Array | None = None) -> Array:
        """One state ``x: [dX]`` from MuJoCo's ``qpos: [nq]``, ``qvel: [nv]``, ``act: [na]``."""
        xq = self.chart.from_qpos(jnp.asarray(qpos))
        parts = [xq, jnp.asarray(qvel, xq.dtype)]
        if self.na:
            parts.append(jnp.asarray(act, xq.dtype))
        return jnp.concatenate(parts)

    def mujoco_from_state(self, x: Array) -> tuple[Array, Array, Array]:
        """``(qpos: [nq], qvel: [nv], act: [na])`` of one state ``x: [dX]``."""
        nv = self.nv
        return self.chart.to_qpos(x[:nv]), x[nv : 2 * nv], x[2 * nv :]

    def ctrl_from_action(self, u: Array) -> Array:
        """``ctrl = ctrl_scale · u`` ([..., nu])."""
        if self.ctrl_scale is None:
            return u
        return u * jnp.asarray(self.ctrl_scale, jnp.asarray(u).dtype)

    def action_from_ctrl(self, ctrl: Array) -> Array:
        """Inverse of :meth:`ctrl_from_action`."""
        if self.ctrl_scale is None:
            return ctrl
        return ctrl / np.asarray(self.ctrl_scale)

    def action_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(u_min, u_max)``: [nu] each, the actuators' ``ctrlrange`` in actions (±inf where an
        actuator is not ctrl-limited). MuJoCo clamps ``ctrl`` to it, so an action beyond it does
        nothing more: what control-limited trajectory optimisation needs to know."""
        lo, hi = (self.action_from_ctrl(self.ctrl_range[:, i]) for i in (0, 1))
        return np.asarray(lo, float), np.asarray(hi, float)

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(x_min, x_max)``: [dX] each, where the limited hinge and slide joints' positions may
        go without their end stop acting: the joint's ``range`` less its limit ``margin`` (where
        MuJoCo's limit constraint switches on) and a further 0.5 % of the range, ±inf for every
        other coordinate. What trajectory optimisation with state limits keeps a plan inside
        (:func:`diffgcl.control.shooting.multiple_shooting`): a stop's force is stiff and
        switches on abruptly, which a linearisation cannot follow."""
        return self.joint_range[:, 0].copy(), self.joint_range[:, 1].copy()

    def _data(self, x: Array, ctrl: Array) -> mjx.Data:
        qpos, qvel, act = self.mujoco_from_state(x)
        d = self.data0.replace(qpos=qpos, qvel=qvel, ctrl=ctrl)
        return d.replace(act=act) if self.na else d

    def _state(self, d: mjx.Data) -> Array:
        parts = [self.chart.from_qpos(d.qpos), d.qvel]
        if self.na:
            parts.append(d.act)
        return jnp.concatenate(parts)

    # ---- the Env protocol --------------------------------------------------------------------

    def step(self, x: Array, u: Array) -> Array:
        """``frame_skip`` MJX steps. x: [dX], u: [dU] -> x': [dX]."""
        check_shape(f"{self.name}.step", "x", x, (self.dX,))
        check_shape(f"{self.name}.step", "u", u, (self.dU,))
        d = self._data(x, self.ctrl_from_action(u))
        if self.frame_skip == 1:
            d = mjcf.step(self.model, d)
        else:
            d = lax.fori_loop(0, self.frame_skip, lambda _, d: mjcf.step(self.model, d), d)
        return self._state(d)

    def obs(self, x: Array, key: PRNGKey | None = None) -> Array:
        """x: [dX] -> o: [dO] (the parts chosen with ``obs``; exact, ``key`` unused)."""
        check_shape(f"{self.name}.obs", "x", x, (self.dX,))
        if callable(self.obs_parts):
            return jnp.asarray(self.obs_parts(x))
        kinds = {kind for kind, _ in self.obs_parts}
        d = None
        if "sensor" in kinds:
            d = mjcf.forward(self.model, self._data(x, jnp.zeros(self.dU, x.dtype)))
        elif kinds & {"site", "body"}:
            d = mjcf.kinematics(self.model, self._data(x, jnp.zeros(self.dU, x.dtype)))
        out = []
        for kind, index in self.obs_parts:
            if kind == "state":
                out.append(x)
            elif kind == "qpos":
                out.append(self.chart.to_qpos(x[: self.nv]))
            elif kind == "qvel":
                out.append(x[self.nv : 2 * self.nv])
            elif kind == "site":
                out.append(d.site_xpos[index])
            elif kind == "body":
                out.append(d.xpos[index])
            else:
                start, dim = index
                out.append(d.sensordata[start : start + dim])
        return jnp.concatenate(out) if out else jnp.zeros(0, x.dtype)

    def cost_features(self, x: Array) -> Array:
        """What a learned cost reads of a state: ``[x, o']`` with ``o'`` the observation parts
        that are not already the state (sites, bodies, sensors; all of a function's output):
        [n_cost_features]. With ``obs="state"`` it is ``x``."""
        if callable(self.obs_parts):
            return jnp.concatenate([x, jnp.asarray(self.obs_parts(x))])
        extra = tuple(p for p in self.obs_parts if p[0] not in ("state", "qpos", "qvel"))
        if not extra:
            return x
        return jnp.concatenate([x, dataclasses.replace(self, obs_parts=extra).obs(x)])

    def initial_states(self) -> Array:
        """Conditions x0: [C, dX]."""
        return self.x0

    def expert_cost(self, x: Array, u: Array, t: Array) -> Array:
        """The user's cost ``c(x, u, t)``; 0 when none was given (see ``has_cost``)."""
        if self.true_cost is None:
            return jnp.zeros((), x.dtype)
        return jnp.asarray(self.true_cost(x, u, t), x.dtype)

    def success(self, X: Array) -> Array:
        """The user's success test on X: [T+1, dX]; False when none was given."""
        if self.success_test is None:
            return jnp.zeros((), bool)
        return jnp.asarray(self.success_test(X), bool)

    @property
    def has_cost(self) -> bool:
        return self.true_cost is not None

    @property
    def has_success(self) -> bool:
        return self.success_test is not None

    # ---- variants ----------------------------------------------------------------------------

    def with_conditions(self, x0=None, *, horizon: int | None = None) -> MJCFEnv:
        """The same env with other start states ``x0: [C, dX]`` and/or horizon."""
        changes = {}
        if x0 is not None:
            x0 = jnp.atleast_2d(jnp.asarray(x0, self.x0.dtype))
            if x0.ndim != 2 or x0.shape[1] != self.dX:
                raise ValueError(f"{self.name}: x0 must be [{self.dX}] or [C, {self.dX}], got "
                                 f"{tuple(x0.shape)}")  # fmt: skip
            changes["x0"] = x0
        if horizon is not None:
            if int(horizon) < 1:
                raise ValueError(f"{self.name}: horizon must be >= 1, got {horizon}")
            changes["horizon"] = int(horizon)
        return dataclasses.replace(self, **changes)

    def with_task(self, *, cost: CostFn | None = None, success=None) -> MJCFEnv:
        """The same env with the user's cost and/or success test."""
        changes = {}
        if cost is not None:
            changes["true_cost"] = cost
        if success is not None:
            changes["success_test"] = success
        return dataclasses.replace(self, **changes)


def _obs_parts(model: mujoco.MjModel, obs, path) -> tuple:
    if callable(obs):
        return obs
    items = (obs,) if isinstance(obs, str) else tuple(obs)
    parts = []
    for item in items:
        kind, _, name = str(item).partition(":")
        if kind not in OBS_KINDS or (kind in ("state", "qpos", "qvel")) == bool(name):
            raise MJCFError(
                f"{path}: obs part {item!r}: use state, qpos, qvel, site:NAME, body:NAME or "
                "sensor:NAME"
            )
        if kind in ("state", "qpos", "qvel"):
            parts.append((kind, None))
            continue
        objtype = {
            "site": mujoco.mjtObj.mjOBJ_SITE,
            "body": mujoco.mjtObj.mjOBJ_BODY,
            "sensor": mujoco.mjtObj.mjOBJ_SENSOR,
        }[kind]
        index = mujoco.mj_name2id(model, objtype, name)
        if index < 0:
            raise MJCFError(f"{path}: obs part {item!r}: the model has no {kind} named {name!r}")
        if kind == "sensor":
            index = (int(model.sensor_adr[index]), int(model.sensor_dim[index]))
        parts.append((kind, index))
    return tuple(parts)


def _frame_skip(model: mujoco.MjModel, dt: float | None, path) -> int:
    if dt is None:
        return 1
    ratio = float(dt) / float(model.opt.timestep)
    skip = int(round(ratio))
    if skip < 1 or abs(ratio - skip) > 1e-6 * max(1.0, ratio):
        raise MJCFError(
            f"{path}: dt = {dt} is not a whole multiple of the model's timestep "
            f"{model.opt.timestep}"
        )
    return skip


def _ctrl_scale(model: mujoco.MjModel, action_scale, path) -> np.ndarray | None:
    if isinstance(action_scale, str):
        if action_scale not in ACTION_SCALES:
            raise MJCFError(f"{path}: action_scale {action_scale!r}; use one of {ACTION_SCALES}"
                            " or an array of per-actuator scales")  # fmt: skip
        if action_scale == "ctrl":
            return None
        limited = model.actuator_ctrllimited.astype(bool)
        magnitude = np.abs(model.actuator_ctrlrange).max(axis=1)
        return np.where(limited & (magnitude > 0), magnitude, 1.0)
    scale = np.asarray(action_scale, float).reshape(-1)
    if scale.shape != (model.nu,) or not np.all(np.isfinite(scale) & (scale > 0)):
        raise MJCFError(f"{path}: action_scale must be {model.nu} positive numbers, got {scale}")
    return scale


def _joint_state_range(model: mujoco.MjModel) -> np.ndarray:
    """[dX, 2]: :meth:`MJCFEnv.state_bounds` (a hinge or slide joint's position is the state
    entry at its dof address; ball and free joints stay unbounded)."""
    out = np.tile([-np.inf, np.inf], (2 * model.nv + model.na, 1))
    scalar = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    for j in range(model.njnt):
        if int(model.jnt_type[j]) not in scalar or not model.jnt_limited[j]:
            continue
        lo, hi = (float(v) for v in model.jnt_range[j])
        inset = float(model.jnt_margin[j]) + 0.005 * (hi - lo)
        if hi - lo > 2 * inset:
            out[int(model.jnt_dofadr[j])] = (lo + inset, hi - inset)
    return out


def _start_states(model, chart, keyframe, x0, conditions, spread, seed, path) -> np.ndarray:
    dX = 2 * model.nv + model.na
    if x0 is not None:
        if keyframe is not None or spread:
            raise MJCFError(f"{path}: give start states x0, or a keyframe (with spread), not both")
        x0 = np.atleast_2d(np.asarray(x0, float))
        if x0.ndim != 2 or x0.shape[1] != dX:
            raise MJCFError(f"{path}: x0 must be [{dX}] or [C, {dX}], got {x0.shape}")
        return x0
    qpos, qvel, act = model.qpos0.copy(), np.zeros(model.nv), np.zeros(model.na)
    if keyframe is not None:
        k = keyframe
        if isinstance(keyframe, str):
            k = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, keyframe)
        if not 0 <= int(k) < model.nkey:
            raise MJCFError(f"{path}: no keyframe {keyframe!r} (the model has {model.nkey})")
        qpos, qvel, act = model.key_qpos[k], model.key_qvel[k], model.key_act[k]
    base = np.concatenate([np.asarray(chart.from_qpos(jnp.asarray(qpos))), qvel, act])
    if int(conditions) < 1:
        raise MJCFError(f"{path}: conditions must be >= 1, got {conditions}")
    X0 = np.repeat(base[None], int(conditions), axis=0)
    if spread:
        noise = np.random.default_rng(seed).normal(size=(int(conditions), model.nv))
        X0[:, : model.nv] += float(spread) * noise
    return X0


def make_mjcf_env(
    mjcf: str | Path = "space_robot.xml",
    *,
    x0=None,
    keyframe: str | int | None = None,
    conditions: int = 1,
    spread: float = 0.0,
    seed: int = 0,
    horizon: int = 100,
    dt: float | None = None,
    obs: str | Sequence[str] | Callable = "state",
    action_scale: str | Sequence[float] = "ctrl",
    cost: CostFn | None = None,
    success: Callable[[Array], Array] | None = None,
    name: str | None = None,
    lapack_free: bool = False,
) -> MJCFEnv:
    """The generic env of the MJCF file ``mjcf`` (a path, or a file name under ``models/``; the
    default is the free-flying space robot, a model with free, ball and hinge joints).

    x0: start states [dX] or [C, dX]; or keyframe (name or index; default: ``qpos0`` at rest)
    with ``conditions`` start states sampled ``spread``·N(0, 1) about it in the configuration
    coordinates (NumPy ``seed``); horizon: T; dt: control period (a whole multiple of the model's
    timestep; default the timestep); obs, action_scale, cost, success: see the module docstring;
    name: default the file's stem. The float precision follows ``jax_enable_x64``.

    lapack_free: simulate with a sparse mass-matrix factorisation and the CG constraint solver
    (``<option jacobian="sparse" solver="CG">`` set on the loaded model, the file untouched), so
    that ``mjx.step`` makes no LAPACK call: jaxlib 0.10.2's batched CPU LAPACK kernels (MJX's
    dense Cholesky of the mass matrix and the Newton solver's Hessian) can deadlock a wide
    vmapped program on a 2-thread pool (measured: iLQR over 8 start states of gymnasium's reacher
    hung in ``lapack_strsm_ffi``). Same dynamics up to the constraint solver's tolerance.
    """
    path = resolve_mjcf(mjcf)
    model = load_mjcf(path)
    if lapack_free:
        model.opt.jacobian = mujoco.mjtJacobian.mjJAC_SPARSE
        model.opt.solver = mujoco.mjtSolver.mjSOL_CG
    if model.nu < 1:
        raise MJCFError(f"{path}: the model has no actuators (the action is MuJoCo's ctrl)")
    mx = put_model_checked(model, path)
    reference = None
    if keyframe is not None and x0 is None and model.nkey:
        k = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, keyframe) if isinstance(
            keyframe, str) else int(keyframe)  # fmt: skip
        if 0 <= k < model.nkey:
            reference = model.key_qpos[k]
    chart = configuration_chart(model, reference)
    X0 = _start_states(model, chart, keyframe, x0, conditions, spread, seed, path)
    if int(horizon) < 1:
        raise MJCFError(f"{path}: horizon must be >= 1, got {horizon}")
    dtype = jnp.zeros(()).dtype
    limited = model.actuator_ctrllimited.astype(bool)[:, None]
    ctrl_range = np.where(limited, model.actuator_ctrlrange, [[-np.inf, np.inf]])
    names = tuple(
        mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"#{i}"
        for i in range(model.nu)
    )
    skip = _frame_skip(model, dt, path)
    env = MJCFEnv(
        model=mx,
        data0=make_data(mx),
        chart=chart,
        x0=jnp.asarray(X0, dtype),
        ctrl_scale=_ctrl_scale(model, action_scale, path),
        ctrl_range=ctrl_range,
        joint_range=_joint_state_range(model),
        actuator_names=names,
        mjcf_path=str(path),
        dt=float(model.opt.timestep) * skip,
        frame_skip=skip,
        horizon=int(horizon),
        name=name or path.stem,
        nq=model.nq,
        nv=model.nv,
        na=model.na,
        dX=2 * model.nv + model.na,
        dU=model.nu,
        dO=0,
        obs_parts=_obs_parts(model, obs, path),
        n_cost_features=0,
        true_cost=cost,
        success_test=success,
    )
    # Trace one step and one observation: what MJX refuses only while tracing fails here, once.
    x = env.x0[0]
    try:
        jax.eval_shape(env.step, x, jnp.zeros(env.dU, dtype))
        o = jax.eval_shape(env.obs, x)
        s = jax.eval_shape(env.cost_features, x)
    except NotImplementedError as err:
        raise MJCFError(f"{path}: MJX cannot run this model: {err}") from None
    if len(o.shape) != 1:
        raise MJCFError(f"{path}: the observation must be a vector, got shape {o.shape}")
    return dataclasses.replace(env, dO=int(o.shape[0]), n_cost_features=int(s.shape[0]))
