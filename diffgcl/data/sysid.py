"""System identification of the hull from demonstrations, by gradient descent through MJX.

Problem: the default :class:`~diffgcl.sim.hull.HullParams` are a documented guess at Odin; the bags
show how the boat really answers its commands. We fit a subset of the parameters,
:data:`SYSID_FIELDS`, to the ingested trajectories by *multiple shooting*: the data are cut into
short windows of ``window`` steps; each window is rolled out with
:func:`~diffgcl.sim.hull.hull_step` from its measured first state under the recorded commands, and
the loss is the mean squared, noise-normalised difference to the measured states (heading,
velocities, yaw rate and actuator states; positions enter with a small weight). Short windows keep
the loss close to quadratic in the parameters and the gradients sane; windows from all episodes are
one batch (``vmap``), and the Adam iterations run inside one ``lax.scan``.

Parametrisation: ``p_i = p_i^0 · exp(θ_i)`` (log-scale, so every parameter stays positive and
all θ are O(1)); θ = 0 is the starting guess. Gradients are forward-mode (``jax.jacfwd``), the
mode the hull model recommends through ``mjx.step``; with ~8 parameters it costs ~8 tangents.

Identifiability: thrust gain, damping and the inertia scale can all be multiplied by one factor
without changing the motion (only ratios force/mass are observable). The jet thrust is taken as
calibrated (``thrust_gain`` fixed at 1, e.g. from a bollard-pull test) and the inertia scale is
fitted; likewise the added masses are fixed (they are not separable from the inertia scale from
planar motion alone) and the quadratic sway/yaw damping and the sway-yaw coupling stay at their
defaults (the swerves hardly excite them separately from the linear terms), and so does the
linear surge damping: at the demonstrations' 3-10 m/s it is < 30 % of the surge resistance and
trades off against the quadratic term (measured: ~15 % error where the others reach 1-4 %).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import optax

from diffgcl.data.demos import DemoSet
from diffgcl.sim import hull
from diffgcl.tracing import value_and_jacfwd

SYSID_FIELDS: tuple[str, ...] = (
    "inertia_scale",
    "damping_uu",
    "damping_v",
    "damping_r",
    "jet_arm",
    "tau_thrust",
    "tau_nozzle",
)

# Per-component scale of state errors in the loss (≈ the sensors' noise): p_x, p_y (m), ψ (rad),
# ẋ, ẏ (m/s), ψ̇ (rad/s), thrust (N), nozzle (rad); obs_x, obs_y do not enter (weight 0).
STATE_SCALE = (0.5, 0.5, 0.0035, 0.02, 0.02, 0.005, 30.0, 0.003, 1.0, 1.0)
STATE_WEIGHT = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0)


@dataclass(frozen=True)
class SysIdConfig:
    """fields: parameters to fit; window: steps per shooting window; stride: steps between window
    starts; max_windows: random subset of windows used (None: all); iterations, method
    (``gauss-newton`` | ``adam``), damping (Levenberg–Marquardt λ), max_step (trust region on
    θ per iteration), learning_rate (Adam): see :func:`make_identify`; step: ``"mjx"`` (rollouts
    through :func:`~diffgcl.sim.hull.hull_step`) or ``"ode"`` (:func:`ode_step`, the same
    integration in plain JAX, for quick checks); seed: window subsampling.
    """

    fields: tuple[str, ...] = SYSID_FIELDS
    window: int = 10
    stride: int = 5
    max_windows: int | None = 512
    iterations: int = 20
    method: str = "gauss-newton"
    damping: float = 1e-3
    max_step: float = 0.5
    learning_rate: float = 0.05
    step: str = "mjx"
    seed: int = 0
    state_scale: tuple[float, ...] = STATE_SCALE
    state_weight: tuple[float, ...] = STATE_WEIGHT


@dataclass(frozen=True)
class Windows:
    """Shooting windows: x0: [W, dX] first states, U: [W, L, dU] commands, target: [W, L, dX]
    measured states after each command."""

    x0: np.ndarray
    U: np.ndarray
    target: np.ndarray


@dataclass(frozen=True)
class SysIdResult:
    """Identified parameters, the starting guess, θ (log-factors over the guess) and the loss
    per Adam iteration: loss: [iterations]."""

    params: hull.HullParams
    initial: hull.HullParams
    theta: np.ndarray
    loss: np.ndarray
    fields: tuple[str, ...] = field(default_factory=tuple)

    def values(self) -> dict[str, float]:
        return {f: float(getattr(self.params, f)) for f in self.fields}

    def relative_errors(self, truth: hull.HullParams) -> dict[str, float]:
        """|p̂ / p_true − 1| per fitted parameter."""
        return {
            f: float(abs(float(getattr(self.params, f)) / float(getattr(truth, f)) - 1.0))
            for f in self.fields
        }


def make_windows(
    demos: DemoSet, window: int, stride: int, max_windows: int | None = None, seed: int = 0
) -> Windows:
    """All windows of ``window`` steps, every ``stride`` steps, whose states are all valid."""
    x0, U, target = [], [], []
    valid = demos.mask.astype(bool)
    for i in range(demos.num_episodes):
        T = demos.horizon
        for s in range(0, T - window + 1, stride):
            if valid[i, s : s + window + 1].all():
                x0.append(demos.X[i, s])
                U.append(demos.U[i, s : s + window])
                target.append(demos.X[i, s + 1 : s + window + 1])
    if not x0:
        raise ValueError(f"sysid: no fully valid window of {window} steps in the demonstrations")
    x0, U, target = np.stack(x0), np.stack(U), np.stack(target)
    if max_windows is not None and len(x0) > max_windows:
        pick = np.sort(np.random.default_rng(seed).choice(len(x0), max_windows, replace=False))
        x0, U, target = x0[pick], U[pick], target[pick]
    return Windows(x0=x0, U=U, target=target)


def with_factors(base: hull.HullParams, fields: tuple[str, ...], theta) -> hull.HullParams:
    """``base`` with ``fields[i]`` multiplied by ``exp(theta[i])`` (theta: [len(fields)])."""
    return base.replace(**{f: getattr(base, f) * jnp.exp(theta[i]) for i, f in enumerate(fields)})


def ode_step(params: hull.HullParams, x, u, model=None, substeps: int = hull.SUBSTEPS):
    """The integration :func:`~diffgcl.sim.hull.hull_step` performs, written directly in JAX.

    On the hull's planar joints (diagonal mass matrix, no contact or constraint) ``mjx.step``
    with ``qfrc_applied = M η̈`` reduces to MuJoCo's semi-implicit Euler ``v' = v + h η̈``,
    ``q' = q + h v'``; the actuator lags decay exactly. Same function of (params, x, u) to
    rounding (tested), but it compiles in seconds where the MJX graph takes a minute or more
    on a small CPU; x: [dX], u: [dU] -> x': [dX]. ``model`` gives the substep (``opt.timestep``).
    """
    h = model.opt.timestep if model is not None else _substep_seconds()
    cmd = hull.clip_command(params, u)
    decay = jnp.exp(-h / jnp.stack([params.tau_thrust, params.tau_nozzle]))
    for _ in range(substeps):
        qvel = x[hull.SL_QVEL] + h * hull.world_acceleration(params, x)
        qpos = x[hull.SL_QPOS] + h * qvel
        act = cmd + (x[hull.SL_ACT] - cmd) * decay
        x = jnp.concatenate([qpos, qvel, act, x[hull.SL_OBS]])
    return x


def _substep_seconds() -> float:
    return float(hull.hull_model()[0].opt.timestep)


STEPS = {"mjx": hull.hull_step, "ode": ode_step}


def rollout(params: hull.HullParams, x0, U, model=None, step: str = "mjx"):
    """States after each command: x0: [dX], U: [L, dU] -> [L, dX] (one window).

    ``model``: the MJX hull model (:func:`diffgcl.sim.hull.hull_model`); pass it in from outside
    ``jit`` (the default loads and caches it, which must not first happen under a trace).
    ``step``: ``"mjx"`` (:func:`~diffgcl.sim.hull.hull_step`) or ``"ode"`` (:func:`ode_step`).
    """
    step_fn = STEPS[step]

    def body(x, u):
        x = step_fn(params, x, u, model)
        return x, x

    return jax.lax.scan(body, x0, U)[1]


def shooting_residuals(
    params: hull.HullParams, win: Windows, scale, sqrt_weight, model=None, step: str = "mjx"
):
    """Normalised residuals √w_j (x̂_j − x_j) / s_j of every window, step and component,
    flattened: [W·L·dX] (scale, sqrt_weight: [dX])."""
    pred = jax.vmap(rollout, in_axes=(None, 0, 0, None, None))(params, win.x0, win.U, model, step)
    return (sqrt_weight * (pred - win.target) / scale).reshape(-1)


def shooting_loss(
    params: hull.HullParams, win: Windows, scale, weight, model=None, step: str = "mjx"
):
    """Mean over windows and steps of Σ_j w_j ((x̂_j − x_j) / s_j)² (scale, weight: [dX])."""
    r = shooting_residuals(params, win, scale, jnp.sqrt(weight), model, step)
    return jnp.mean(r**2) * scale.shape[0]


def make_identify(config: SysIdConfig):
    """Returns a pure ``identify(base, model, x0, U, target) -> (theta, losses)`` (jitted);
    ``model`` is the MJX hull model.

    ``config.method``: ``"gauss-newton"`` — Levenberg–Marquardt steps
    ``Δθ = −(JᵀJ + λ diag(JᵀJ) + εI)⁻¹ Jᵀr`` from the forward-mode Jacobian J of the normalised
    residuals r (the same cost as a forward-mode gradient, and ~20 iterations instead of
    hundreds), passed through an optax trust-region clip; ``"adam"`` — plain optax Adam on the
    loss gradient ``Jᵀr``.
    """
    fields = tuple(config.fields)
    if config.method == "adam":
        opt = optax.adam(config.learning_rate)
    elif config.method == "gauss-newton":
        # The LM step is the update; clip it to a trust region of max_step in log-factor space.
        opt = optax.clip(config.max_step)
    else:
        raise ValueError(f"sysid method {config.method!r}; choose 'gauss-newton' or 'adam'")

    def identify(base, model, x0, U, target):
        win = Windows(x0=x0, U=U, target=target)
        scale = jnp.asarray(config.state_scale, x0.dtype)
        weight = jnp.sqrt(jnp.asarray(config.state_weight, x0.dtype))

        def residuals(theta):
            params = with_factors(base, fields, theta)
            return shooting_residuals(params, win, scale, weight, model, config.step)

        def step(carry, _):
            theta, state = carry
            r, J = value_and_jacfwd(residuals)(theta)
            grad = J.T @ r / r.size
            if config.method == "adam":
                direction = grad
            else:
                H = J.T @ J / r.size
                damped = H + config.damping * jnp.diag(jnp.diag(H)) + 1e-9 * jnp.eye(len(fields))
                direction = jnp.linalg.solve(damped, grad)
            step_dir = direction if config.method == "adam" else -direction
            updates, state = opt.update(step_dir, state, theta)
            return (optax.apply_updates(theta, updates), state), jnp.mean(r**2) * weight.size

        theta0 = jnp.zeros(len(fields), x0.dtype)
        (theta, _), losses = jax.lax.scan(
            step, (theta0, opt.init(theta0)), None, length=config.iterations
        )
        return theta, losses

    return jax.jit(identify)


def identify(
    demos: DemoSet, config: SysIdConfig | None = None, initial: hull.HullParams | None = None
) -> SysIdResult:
    """Fit ``config.fields`` of ``initial`` (default: the nominal parameters) to ``demos``."""
    cfg = config or SysIdConfig()
    dtype = jnp.zeros(()).dtype
    base = initial if initial is not None else hull.default_params(dtype)
    base = jax.tree.map(lambda v: jnp.asarray(v, dtype), base)
    win = make_windows(demos, cfg.window, cfg.stride, cfg.max_windows, cfg.seed)
    model = hull.hull_model(dtype)[1]
    theta, losses = make_identify(cfg)(
        base,
        model,
        jnp.asarray(win.x0, dtype),
        jnp.asarray(win.U, dtype),
        jnp.asarray(win.target, dtype),
    )
    params = with_factors(base, tuple(cfg.fields), theta)
    return SysIdResult(
        params=params,
        initial=base,
        theta=np.asarray(theta),
        loss=np.asarray(losses),
        fields=tuple(cfg.fields),
    )


@dataclass(frozen=True)
class PredictionError:
    """How well a parameter set predicts the demonstrations under their recorded commands.

    one_step: RMS one-step (dt) error per state component; open_loop: RMS position error (m) and
    heading error (rad) over open-loop rollouts of ``horizon_s`` seconds from measured states,
    and the mean final position error (m) at ``horizon_s``.
    """

    one_step: dict[str, float]
    open_loop: dict[str, float]

    def as_dict(self) -> dict:
        return {"one_step": self.one_step, "open_loop": self.open_loop}


@functools.partial(jax.jit, static_argnames="step")
def _batched_rollout_jit(params, model, x0, U, step):
    return jax.vmap(rollout, in_axes=(None, 0, 0, None, None))(params, x0, U, model, step)


def _batched_rollout(params, x0, U, step: str = "mjx"):
    """States [W, L, dX] of windows x0: [W, dX], U: [W, L, dU]."""
    return _batched_rollout_jit(params, hull.hull_model(x0.dtype)[1], x0, U, step)


def prediction_error(
    params: hull.HullParams,
    demos: DemoSet,
    horizon_s: float = 10.0,
    stride_s: float = 5.0,
    max_windows: int = 256,
    step: str = "mjx",
) -> PredictionError:
    """One-step and ``horizon_s`` open-loop prediction errors of ``params`` on ``demos``."""
    dtype = jnp.zeros(()).dtype
    params = jax.tree.map(lambda v: jnp.asarray(v, dtype), params)
    one = make_windows(demos, 1, 1, max_windows=4096)
    pred = np.asarray(
        _batched_rollout(params, jnp.asarray(one.x0, dtype), jnp.asarray(one.U, dtype), step)
    )
    err = (pred - one.target)[:, 0]
    names = hull.STATE_NAMES[:8]
    one_step = {n: float(np.sqrt(np.mean(err[:, j] ** 2))) for j, n in enumerate(names)}
    L = int(round(horizon_s / demos.dt))
    stride = max(int(round(stride_s / demos.dt)), 1)
    win = make_windows(demos, L, stride, max_windows=max_windows)
    pred = np.asarray(
        _batched_rollout(params, jnp.asarray(win.x0, dtype), jnp.asarray(win.U, dtype), step)
    )
    dpos = np.linalg.norm(pred[..., :2] - win.target[..., :2], axis=-1)
    dpsi = pred[..., hull.IX_PSI] - win.target[..., hull.IX_PSI]
    open_loop = {
        "horizon_s": float(horizon_s),
        "windows": int(len(win.x0)),
        "position_rmse_m": float(np.sqrt(np.mean(dpos**2))),
        "final_position_error_m": float(np.mean(dpos[:, -1])),
        "heading_rmse_rad": float(np.sqrt(np.mean(dpsi**2))),
    }
    return PredictionError(one_step=one_step, open_loop=open_loop)
