"""MuJoCo Warp (MJX ``impl="warp"``) as an optional, non-differentiable sampling backend.

The JAX implementation of MJX stays the default and the only differentiable path (DESIGN §9).
This module rolls out a :class:`~diffgcl.types.LinearGaussianController` for a batch of samples
with MJX's Warp implementation instead, returning the same :class:`~diffgcl.types.Trajectory`
layout as :func:`diffgcl.sim.rollout.sample_controller` (X [N, T+1, dX], U [N, T, dU],
O [N, T+1, 0]) for the same noise::

    sampler = make_warp_sampler(make_env("arm"))
    traj = sampler.sample(controller, x0, noise)      # noise: [N, T, dU], x0: [dX] or [N, dX]

How MJX 3.17 runs Warp (read from ``mujoco/mjx/_src/io.py`` and ``mujoco/mjx/warp/``):

* ``mjx.put_model(m, impl="warp")`` converts the C model with the bundled MuJoCo Warp
  (``mujoco.mjx.third_party.mujoco_warp``) and stores every float field as **float32**, whatever
  ``jax_enable_x64`` says; ``mjx.make_data(m, impl="warp")`` needs the C ``MjModel`` itself.
* ``mjx.step`` dispatches on the model's impl to a ``wp.jax_callable`` FFI call. It is a
  ``jax.custom_vmap``: a ``vmap`` over ``Data`` becomes one Warp launch over ``nworld = N``
  worlds, so the batch is stepped in one call per time step inside ``lax.scan``.
* The device is a CUDA GPU when JAX has one, otherwise the CPU: warp-lang compiles its kernels
  for the host with its bundled Clang/LLVM, and MJX then uses ``GraphMode.JAX`` (no CUDA graphs).
  It does run on this CPU-only machine. The first use compiles ~100 Warp modules (≈ 25 s on two
  cores); they are cached on disk (``wp.config.kernel_cache_dir``, by default
  ``~/.cache/warp/<version>``) and load in ≈ 2 s in a later process.
* There is no JAX derivative rule for the FFI call: do not differentiate through this backend
  (use the JAX implementation and :mod:`diffgcl.dynamics.autodiff`).
* On the CPU every ``mjx.step`` call pays ≈ 20–30 ms of Python-side FFI marshalling (warp builds
  ~170 input and ~170 output arrays and the MuJoCo Warp structs per call) before ~100 kernel
  launches, whatever N. :meth:`WarpSampler.sample_direct` skips it with a host loop of
  ``mujoco_warp.step`` on the same model (the one MJX bundles).

Measured on this 2-core CPU (arm, N = 1024, T = 100, float32, :func:`benchmark_warp` /
:func:`benchmark_jax`; three runs with other jobs sharing the cores, load 7–12, hence the
spread): ``sample`` 29–57 k steps/s, ``sample_direct`` 51–61 k steps/s, the JAX implementation
280–600 k steps/s. Warp kernels run on one CPU thread each here, so on a CPU the JAX
implementation is the faster sampler by ~10×;
this backend is meant for a CUDA GPU (DESIGN §9), where it has not been run from this repository.

Supported models: any env whose ``step`` is plain ``mjx.step`` on ``x = [qpos, qvel]`` with
``u = ctrl`` (the arm). An env that adds forces in JAX (the hull's ``qfrc_applied``) or carries
extra state is refused with :class:`WarpUnsupportedError`; so is a model that MuJoCo Warp itself
does not implement (its ``NotImplementedError`` is quoted). If warp-lang is missing or cannot
compile/launch a kernel here, :class:`WarpUnavailableError` says why (see :func:`warp_status`).

Precision: states and controls pass through Warp in float32 (the control ``K x + k + chol(Σ) ε``
is computed in the callers' precision, then rounded). Trajectories come back in the callers'
dtype, but only float32-accurate: on the arm they match float64 JAX rollouts to ≈ 3e-6 over
100 steps (tests/test_warp_backend.py allows 1e-4 and explains why).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax import lax
from mujoco import mjx

from diffgcl.checks import check_shape
from diffgcl.sim.mjcf import load_mjcf, resolve_mjcf
from diffgcl.sim.mjcf import put_model as put_model_jax
from diffgcl.types import Array, LinearGaussianController, Trajectory


class WarpUnavailableError(RuntimeError):
    """warp-lang or MuJoCo Warp cannot run in this process (the message says why)."""


class WarpUnsupportedError(ValueError):
    """The model or env cannot be simulated by this backend (the message says why)."""


# A minimal model with the pieces the arm uses (hinge, velocity actuator, Euler): the probe
# compiles the same Warp modules the arm needs, so a later arm sampler starts from a warm cache.
_PROBE_XML = """
<mujoco>
  <option timestep="0.01" gravity="0 0 0" integrator="Euler"><flag contact="disable"/></option>
  <worldbody>
    <body>
      <joint name="j" type="hinge" axis="0 0 1"/><geom type="box" size="1 .1 .1" mass="1"/>
    </body>
  </worldbody>
  <actuator><velocity joint="j" kv="10" forcelimited="true" forcerange="-5 5"/></actuator>
</mujoco>
"""


def _quiet_warp(quiet: bool) -> None:
    """Raise warp's log level to warnings: hides the start-up banner and the ~100 per-module
    "Module ... load on device 'cpu' took ..." lines it prints to stdout at INFO level."""
    if quiet:
        import warp as wp

        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)


@functools.cache
def _probe(quiet: bool = True) -> tuple[bool, str]:
    try:
        import warp as wp
    except Exception as err:  # ImportError, or RuntimeError from a broken native library
        return False, f"cannot import warp-lang: {type(err).__name__}: {err}"
    from mujoco.mjx import warp as mjxw

    if not mjxw.WARP_INSTALLED:
        return False, "mujoco.mjx.warp reports WARP_INSTALLED = False (warp-lang import failed)"
    try:
        _quiet_warp(quiet)
        wp.init()
        m = mujoco.MjModel.from_xml_string(_PROBE_XML)
        mx = mjx.put_model(m, impl="warp")
        d0 = mjx.make_data(m, impl="warp")

        def one(v, u):
            return mjx.step(mx, d0.replace(qvel=v, ctrl=u)).qvel

        v = jnp.zeros((2, 1), jnp.float32)
        u = jnp.asarray([[1.0], [-1.0]], jnp.float32)
        out = np.asarray(jax.jit(jax.vmap(one))(v, u))
        c = mujoco.MjData(m)
        c.ctrl[:] = 1.0
        mujoco.mj_step(m, c)
        if not np.allclose(out[:, 0], [c.qvel[0], -c.qvel[0]], rtol=1e-4, atol=1e-6):
            return False, f"MuJoCo Warp probe step gave {out[:, 0]}, C MuJoCo {c.qvel[0]:+.6g}"
    except Exception as err:
        return False, f"MuJoCo Warp probe step failed: {type(err).__name__}: {err}"
    devices = ", ".join(str(d) for d in wp.get_devices())
    return True, f"warp-lang {wp.__version__} on {devices}; JAX device {jax.devices()[0]}"


def warp_status(quiet: bool = True) -> tuple[bool, str]:
    """``(True, description)`` if MJX's Warp implementation steps a tiny model correctly in this
    process, else ``(False, reason)``. Decided by trying (import, Warp init, kernel compilation,
    one batched ``mjx.step`` checked against C MuJoCo); cached for the process."""
    return _probe(quiet)


def require_warp() -> str:
    """Raise :class:`WarpUnavailableError` with the reason unless Warp runs here."""
    ok, message = warp_status()
    if not ok:
        raise WarpUnavailableError(f"MJX impl='warp' is unavailable: {message}")
    return message


def _model_overrides(env) -> dict[str, np.ndarray]:
    """Fields of ``env.model`` that differ from a fresh load of ``env.mjcf_path``.

    Envs may edit the compiled model after loading it (the arm's ``torque_limit`` rewrites
    ``actuator_forcerange``); those edits have to reach the Warp model too.
    """
    fresh = put_model_jax(load_mjcf(env.mjcf_path))
    overrides = {}
    for field in dataclasses.fields(fresh):
        name = field.name
        if name.startswith("_") or name in ("opt", "stat"):
            continue
        ours, ref = getattr(env.model, name), getattr(fresh, name)
        if not isinstance(ref, np.ndarray | jax.Array):
            continue
        ours, ref = np.asarray(ours), np.asarray(ref)
        if ours.shape != ref.shape:
            raise WarpUnsupportedError(
                f"{env.name}: model field {name} has shape {ours.shape}, the MJCF gives "
                f"{ref.shape}; cannot rebuild the env's model for Warp"
            )
        if ours.dtype.kind == "f":
            same = np.allclose(ours, ref, rtol=1e-6, atol=0.0, equal_nan=True)
        else:
            same = np.array_equal(ours, ref)
        if not same:
            overrides[name] = ours
    for field in dataclasses.fields(fresh.opt):
        name = field.name
        if name.startswith("_"):
            continue
        ours, ref = getattr(env.model.opt, name), getattr(fresh.opt, name)
        try:
            same = np.allclose(np.asarray(ours, float), np.asarray(ref, float), rtol=1e-6)
        except (TypeError, ValueError):
            same = ours == ref
        if not same:
            overrides[f"opt.{name}"] = np.asarray(ours)
    return overrides


def _apply_overrides(m: mujoco.MjModel, overrides: dict[str, np.ndarray], where: str) -> None:
    for name, value in overrides.items():
        owner, attr = (m.opt, name[4:]) if name.startswith("opt.") else (m, name)
        target = getattr(owner, attr)
        if isinstance(target, np.ndarray):
            if target.size != value.size:
                raise WarpUnsupportedError(f"{where}: cannot copy model field {name} to C MuJoCo")
            target[...] = value.reshape(target.shape)
        else:
            setattr(owner, attr, type(target)(value))


def _resolve_model(env_or_model) -> tuple[mujoco.MjModel, str, object | None]:
    """(C model, description, env or None) from an env, a C model, or an MJCF name/path."""
    if isinstance(env_or_model, mujoco.MjModel):
        return env_or_model, "MjModel", None
    if isinstance(env_or_model, str | os.PathLike):
        path = resolve_mjcf(env_or_model)
        return load_mjcf(path), str(path), None
    env = env_or_model
    for attr in ("mjcf_path", "model", "dX", "dU", "step"):
        if not hasattr(env, attr):
            raise WarpUnsupportedError(
                f"make_warp_sampler: expected an env, a mujoco.MjModel or an MJCF path, got "
                f"{type(env).__name__} (no attribute {attr!r})"
            )
    if not isinstance(env.model, mjx.Model):
        raise WarpUnsupportedError(f"{env.name}: env.model is not an mjx.Model")
    m = load_mjcf(env.mjcf_path)
    _apply_overrides(m, _model_overrides(env), env.name)
    return m, f"env {env.name!r} ({env.mjcf_path})", env


@dataclasses.dataclass(frozen=True, eq=False)
class WarpSampler:
    """Batched controller rollouts through MJX's Warp implementation; build with
    :func:`make_warp_sampler`. Hashable by identity (a static argument of ``jit``)."""

    model: mjx.Model
    data0: mjx.Data
    nq: int
    nv: int
    nu: int
    description: str
    c_model: mujoco.MjModel = dataclasses.field(repr=False)
    _direct: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def dX(self) -> int:
        return self.nq + self.nv

    @property
    def dU(self) -> int:
        return self.nu

    def _step_one(self, x: Array, u: Array) -> Array:
        f32 = jnp.float32
        d = self.data0.replace(qpos=x[: self.nq].astype(f32), qvel=x[self.nq :].astype(f32))
        d = mjx.step(self.model, d.replace(ctrl=u.astype(f32)))
        return jnp.concatenate([d.qpos, d.qvel]).astype(x.dtype)

    def step(self, x: Array, u: Array) -> Array:
        """Batched step: x [N, dX], u [N, dU] -> x' [N, dX] (one Warp launch of N worlds)."""
        return jax.vmap(self._step_one)(x, u)

    def sample(self, controller: LinearGaussianController, x0: Array, noise: Array) -> Trajectory:
        """Roll out ``u_t = K_t x_t + k_t + chol(Σ_t) ε_t`` for the N noise sequences.

        ``x0``: [dX] (shared) or [N, dX]; ``noise``: [N, T, dU] (e.g. from
        :func:`diffgcl.sim.rollout.smooth_noise`). Returns X [N, T+1, dX], U [N, T, dU],
        O [N, T+1, 0], like :func:`diffgcl.sim.rollout.sample_controller` with the same noise.
        """
        T, dX, dU = controller.horizon, self.dX, self.dU
        check_shape("warp sample", "controller.K", controller.K, (T, dU, dX))
        if jnp.ndim(noise) != 3:
            raise ValueError(f"warp sample: noise must be [N, T, dU], got {jnp.shape(noise)}")
        N = jnp.shape(noise)[0]
        check_shape("warp sample", "noise", noise, (N, T, dU))
        if jnp.ndim(x0) == 1:
            check_shape("warp sample", "x0", x0, (dX,))
        else:
            check_shape("warp sample", "x0", x0, (N, dX))
        return _sample(self, controller, x0, noise)

    __call__ = sample

    def sample_direct(
        self, controller: LinearGaussianController, x0: Array, noise: Array
    ) -> Trajectory:
        """:meth:`sample` without JAX: a host loop of ``mujoco_warp.step`` on ``nworld = N``
        worlds, with the controller applied by a small Warp kernel before each step.

        Same inputs and outputs as :meth:`sample` (not jittable; returns JAX arrays). It skips
        the JAX FFI marshalling of ~170 buffers that ``mjx.step`` pays per call (≈ 25 ms on this
        CPU), so it is several times faster here. Unlike ``env.step`` the Warp data carries
        over between steps (time, solver warm start), which changes nothing on the arm and only
        solver iterates on models with constraints.
        """
        import warp as wp
        from mujoco.mjx.third_party import mujoco_warp as mjw

        T, dX, dU = controller.horizon, self.dX, self.dU
        check_shape("warp sample_direct", "controller.K", controller.K, (T, dU, dX))
        if jnp.ndim(noise) != 3:
            raise ValueError(
                f"warp sample_direct: noise must be [N, T, dU], got {jnp.shape(noise)}"
            )
        N = jnp.shape(noise)[0]
        check_shape("warp sample_direct", "noise", noise, (N, T, dU))
        if jnp.ndim(x0) != 1:
            check_shape("warp sample_direct", "x0", x0, (N, dX))
        else:
            check_shape("warp sample_direct", "x0", x0, (dX,))
        dtype = jnp.result_type(controller.K, x0, noise)
        device = "cuda:0" if jax.devices()[0].platform == "gpu" else "cpu"
        control, record = _direct_kernels()
        f32 = np.float32
        with wp.ScopedDevice(device):
            if "model" not in self._direct:
                self._direct["model"] = mjw.put_model(self.c_model)
            mw = self._direct["model"]
            key = ("data", N)
            if key not in self._direct:
                self._direct[key] = mjw.make_data(self.c_model, nworld=N)
            dw = self._direct[key]
            mjw.reset_data(mw, dw)
            x0 = np.broadcast_to(np.asarray(x0, f32), (N, dX))
            dw.qpos.assign(np.ascontiguousarray(x0[:, : self.nq]))
            dw.qvel.assign(np.ascontiguousarray(x0[:, self.nq :]))
            K, k, chol = (
                wp.array(np.asarray(a, f32))
                for a in (controller.K, controller.k, controller.chol_cov)
            )
            eps = wp.array(np.asarray(noise, f32))
            X = wp.zeros((N, T + 1, dX), dtype=wp.float32)
            U = wp.zeros((N, T, dU), dtype=wp.float32)
            for t in range(T):
                wp.launch(
                    control,
                    dim=N,
                    inputs=[t, K, k, chol, eps, dw.qpos, dw.qvel],
                    outputs=[dw.ctrl, X, U],
                )
                mjw.step(mw, dw)
            wp.launch(record, dim=N, inputs=[T, dw.qpos, dw.qvel], outputs=[X])
            X, U = X.numpy(), U.numpy()
        return Trajectory(
            X=jnp.asarray(X, dtype), U=jnp.asarray(U, dtype), O=jnp.zeros((N, T + 1, 0), dtype)
        )


@functools.partial(jax.jit, static_argnums=0)
def _sample(sampler: WarpSampler, controller, x0, noise) -> Trajectory:
    dtype = jnp.result_type(controller.K, x0, noise)
    N = noise.shape[0]
    x0 = jnp.broadcast_to(jnp.asarray(x0, dtype), (N, sampler.dX))

    def body(x, inputs):
        K, k, chol, eps = inputs  # eps: [N, dU]
        u = x @ K.T + k + eps @ chol.T
        return sampler.step(x, u), (x, u)

    time_major = (controller.K, controller.k, controller.chol_cov, jnp.swapaxes(noise, 0, 1))
    time_major = jax.tree.map(lambda a: a.astype(dtype), time_major)
    x_final, (X, U) = lax.scan(body, x0, time_major)
    X = jnp.concatenate([jnp.swapaxes(X, 0, 1), x_final[:, None]], axis=1)
    U = jnp.swapaxes(U, 0, 1)
    return Trajectory(X=X, U=U, O=jnp.zeros((N, X.shape[1], 0), dtype))


def make_warp_sampler(
    env_or_model,
    *,
    check_env_step: bool = True,
    naconmax: int | None = None,
    njmax: int | None = None,
    quiet: bool = True,
) -> WarpSampler:
    """A :class:`WarpSampler` for an env (``env.step`` = plain ``mjx.step`` on
    ``x = [qpos, qvel]``, ``u = ctrl``), a ``mujoco.MjModel``, or an MJCF name/path.

    For an env, edits it made to its model after loading the MJCF are carried over, the state and
    action sizes must be ``nq + nv`` and ``nu``, and with ``check_env_step`` one Warp step from
    the env's first initial state is compared with ``env.step`` (float32 tolerance), which
    catches envs that add forces or dynamics of their own. ``naconmax``/``njmax`` size Warp's
    contact and constraint buffers (MJX's ``make_data`` arguments; unused by the arm).

    Raises :class:`WarpUnavailableError` (with the reason) if Warp cannot run here, and
    :class:`WarpUnsupportedError` if the model or env does not fit.
    """
    require_warp()
    _quiet_warp(quiet)
    m, description, env = _resolve_model(env_or_model)
    if env is not None:
        if (env.dX, env.dU) != (m.nq + m.nv, m.nu):
            raise WarpUnsupportedError(
                f"{description}: state/action sizes (dX={env.dX}, dU={env.dU}) are not "
                f"(nq + nv, nu) = ({m.nq + m.nv}, {m.nu}); the Warp backend only steps envs whose "
                "state is [qpos, qvel] and whose action is ctrl"
            )
    if m.nq != m.nv:
        raise WarpUnsupportedError(
            f"{description}: nq = {m.nq} != nv = {m.nv} (free or ball joints); the Warp backend "
            "steps states [qpos, qvel] of hinge/slide joints only"
        )
    try:
        mx = mjx.put_model(m, impl="warp")
        d0 = mjx.make_data(m, impl="warp", naconmax=naconmax, njmax=njmax)
    except NotImplementedError as err:
        reason = f"MuJoCo Warp does not support it: {err}"
        raise WarpUnsupportedError(f"{description}: {reason}") from err
    sampler = WarpSampler(
        model=mx, data0=d0, nq=m.nq, nv=m.nv, nu=m.nu, description=description, c_model=m
    )
    if env is not None and check_env_step:
        _check_against_env(sampler, env)
    return sampler


def _check_against_env(sampler: WarpSampler, env) -> None:
    x0 = jnp.asarray(env.initial_states()[0])
    u = jnp.linspace(-1.0, 1.0, env.dU, dtype=x0.dtype)
    ref = np.asarray(jax.jit(env.step)(x0, u), float)
    got = np.asarray(jax.jit(sampler.step)(x0[None], u[None])[0], float)
    tol = 1e-3 * (1.0 + np.max(np.abs(ref)))
    err = np.max(np.abs(got - ref))
    if not np.all(np.isfinite(got)) or err > tol:
        raise WarpUnsupportedError(
            f"{sampler.description}: one Warp step differs from env.step by {err:.3g} "
            f"(tolerance {tol:.3g}); the env's step is not plain mjx.step on [qpos, qvel] "
            f"(Warp gave {got}, env.step {ref})"
        )


@functools.cache
def _direct_kernels():
    """Warp kernels of :meth:`WarpSampler.sample_direct` (defined on first use: importing this
    module must not need warp-lang)."""
    import warp as wp

    @wp.kernel(enable_backward=False)
    def control(
        t: int,
        K: wp.array3d(dtype=wp.float32),
        k: wp.array2d(dtype=wp.float32),
        chol: wp.array3d(dtype=wp.float32),
        eps: wp.array3d(dtype=wp.float32),
        qpos: wp.array2d(dtype=wp.float32),
        qvel: wp.array2d(dtype=wp.float32),
        ctrl: wp.array2d(dtype=wp.float32),
        X: wp.array3d(dtype=wp.float32),
        U: wp.array3d(dtype=wp.float32),
    ):
        n = wp.tid()
        nq = qpos.shape[1]
        nv = qvel.shape[1]
        for i in range(nq):
            X[n, t, i] = qpos[n, i]
        for i in range(nv):
            X[n, t, nq + i] = qvel[n, i]
        for j in range(ctrl.shape[1]):
            u = k[t, j]
            for i in range(nq):
                u += K[t, j, i] * qpos[n, i]
            for i in range(nv):
                u += K[t, j, nq + i] * qvel[n, i]
            for i in range(ctrl.shape[1]):
                u += chol[t, j, i] * eps[n, t, i]
            ctrl[n, j] = u
            U[n, t, j] = u

    @wp.kernel(enable_backward=False)
    def record(
        t: int,
        qpos: wp.array2d(dtype=wp.float32),
        qvel: wp.array2d(dtype=wp.float32),
        X: wp.array3d(dtype=wp.float32),
    ):
        n = wp.tid()
        nq = qpos.shape[1]
        for i in range(nq):
            X[n, t, i] = qpos[n, i]
        for i in range(qvel.shape[1]):
            X[n, t, nq + i] = qvel[n, i]

    return control, record


def _benchmark_controller(T: int, dX: int, dU: int, dtype) -> LinearGaussianController:
    from diffgcl.types import make_controller

    return make_controller(
        jnp.zeros((T, dU, dX), dtype) - 0.5 * jnp.eye(dU, dX, dtype=dtype),
        jnp.zeros((T, dU), dtype),
        jnp.broadcast_to(0.1 * jnp.eye(dU, dtype=dtype), (T, dU, dU)),
    )


def benchmark_warp(
    n_samples: int = 1024,
    T: int = 100,
    *,
    env=None,
    repeats: int = 3,
    seed: int = 0,
    engine: str = "mjx",
) -> float:
    """Steps per second (``n_samples * T / seconds``, best of ``repeats`` after a warm-up call)
    of :meth:`WarpSampler.sample` (``engine="mjx"``: ``mjx.step`` with ``impl="warp"`` under
    ``jit``) or :meth:`WarpSampler.sample_direct` (``engine="direct"``: a host loop of
    ``mujoco_warp.step``) on the arm (or ``env``) with the controller
    ``u = -0.5 [I 0] x + chol(0.1 I) ε``, in the current default float precision.

    Compare with :func:`benchmark_jax` (same controller, noise and timing) or
    ``experiments/bench_sim.py``'s MJX figure. Raises :class:`WarpUnavailableError` if Warp cannot
    run here.
    """
    if env is None:
        from diffgcl.envs import make_env

        env = make_env("arm")
    if engine not in ("mjx", "direct"):
        raise ValueError(f"benchmark_warp: engine must be 'mjx' or 'direct', got {engine!r}")
    sampler = make_warp_sampler(env)
    run = sampler.sample if engine == "mjx" else sampler.sample_direct
    dtype = jnp.zeros(()).dtype
    ctrl = _benchmark_controller(T, env.dX, env.dU, dtype)
    x0 = env.initial_states()[0]
    noise = jax.random.normal(jax.random.key(seed), (n_samples, T, env.dU), dtype)
    return n_samples * T / _best_time(lambda: run(ctrl, x0, noise).X, repeats)


def benchmark_jax(
    n_samples: int = 1024, T: int = 100, *, env=None, repeats: int = 3, seed: int = 0
) -> float:
    """The JAX-implementation counterpart of :func:`benchmark_warp` (same workload), steps/s."""
    from diffgcl.sim.rollout import rollout_controller

    if env is None:
        from diffgcl.envs import make_env

        env = make_env("arm")
    dtype = jnp.zeros(()).dtype
    ctrl = _benchmark_controller(T, env.dX, env.dU, dtype)
    x0 = env.initial_states()[0]
    noise = jax.random.normal(jax.random.key(seed), (n_samples, T, env.dU), dtype)
    run = jax.jit(jax.vmap(lambda eps: rollout_controller(env, ctrl, x0, eps).X))
    return n_samples * T / _best_time(lambda: run(noise), repeats)


def _best_time(fn, repeats: int) -> float:
    jax.block_until_ready(fn())
    best = float("inf")
    for _ in range(max(1, repeats)):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best
