"""Trajectory optimisation where the cost is known: iLQR on an env, GPS started from iLQR.

GPS (:mod:`diffgcl.algorithms.gps`) from a zero controller with ``Σ = init_var·I`` has to find
the task with KL-bounded steps from noisy samples; iLQR (:mod:`diffgcl.control.ilqr`) solves the
same problem deterministically with Newton steps through the simulator's autodiff Jacobians.
Where a cost is known — the expert that makes demonstrations, GPS's initial controllers, the
re-optimisation of a frozen learned cost — this module runs iLQR first:

* :func:`solve` — iLQR from every start state ``x0: [C, dX]`` of an env (vmapped: one compiled
  program for all start states; start states and the initial actions are traced arguments);
* :func:`ilqr_controllers` — the solutions as linear-Gaussian controllers [C, T, ...]
  (:func:`diffgcl.control.ilqr.ilqr_controller`: covariance shaped like ``(Q_uu + μI)⁻¹``);
* :func:`make_gps_from` — GPS whose ``train(key, controller, hparams=None)`` starts from given
  controllers (traced, so a zero controller and an iLQR one share one program);
  :func:`make_gps_from_ilqr` composes the two: iLQR, then GPS's KL-constrained steps refining
  the iLQR controllers, with ``init_var`` the mean variance of their (Q_uu-shaped) noise.

GPS stays what the learned-cost paths (rGCL's C-step, MDGPS) use: they need the KL bound and the
samples; this module is for a cost that is known and fixed.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from diffgcl.algorithms.gps import GPSConfig, GPSHyperparams, GPSMetrics, GPSState, make_gps
from diffgcl.control.ilqr import (
    ILQRConfig,
    ILQRResult,
    cheapest_run,
    cost_minimiser,
    goal_lqr_actions,
    ilqr,
    ilqr_best_of,
    ilqr_controller,
    squared_residual,
)
from diffgcl.control.shooting import ShootingConfig, multiple_shooting, straight_line
from diffgcl.types import Array, CostFn, Env, LinearGaussianController, PRNGKey


def _env_box(env: Env, method_name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """``env.<method_name>()``'s ``(lower, upper)`` where the env has the method and a finite
    side; None otherwise."""
    method = getattr(env, method_name, None)
    if method is None:
        return None
    lo, hi = method()
    if not (np.isfinite(lo).any() or np.isfinite(hi).any()):
        return None
    return lo, hi


def action_bounds(env: Env) -> tuple[np.ndarray, np.ndarray] | None:
    """The env's action box ``(u_min, u_max)`` where it has one with a finite side (an env with
    an ``action_bounds()`` method, such as :class:`~diffgcl.envs.mjcf_env.MJCFEnv` from the
    actuators' ``ctrlrange``); None: unlimited."""
    return _env_box(env, "action_bounds")


def state_bounds(env: Env) -> tuple[np.ndarray, np.ndarray] | None:
    """The env's state limits ``(x_min, x_max)`` where it has a finite one (an env with a
    ``state_bounds()`` method, such as :class:`~diffgcl.envs.mjcf_env.MJCFEnv` from its limited
    joints' ranges); None: unlimited."""
    return _env_box(env, "state_bounds")


def solve_shooting(
    env: Env,
    cost: CostFn,
    x0: Array,
    config: ShootingConfig | None = None,
    *,
    limits: bool = True,
    goal: Array | None = None,
    U_init: Array | None = None,
    batch_size: int | None = None,
) -> ILQRResult:
    """Multiple shooting (:func:`~diffgcl.control.shooting.multiple_shooting`) on
    ``env.step`` with ``cost`` from each start state ``x0: [C, dX]``, from the straight line of
    states to ``goal`` ([dX] or [C, dX]; default where the terminal cost is lowest,
    :func:`~diffgcl.control.ilqr.cost_minimiser` from each start) and ``U_init`` ([T, dU] or
    [C, T, dU], default zeros). limits: the env's :func:`action_bounds` and :func:`state_bounds`
    (its joints' ranges, kept by the barrier); False: none. ``cost`` is a cost, not a residual.

    batch_size: None solves all C starts in one vmap; an integer solves them in groups of that
    many (``lax.map``; the same result). A vmapped while loop runs every start as long as the
    slowest and every line-search trial for all of them, so where the starts' solves differ
    widely — on a CPU, and where some iterates press a joint's end stop, whose contact makes
    MJX's step several times dearer — small groups finish far sooner (gymnasium's double
    pendulum, 7 hard starts: one at a time 299 s, all in one vmap not done after 18 min).
    Returns an ILQRResult with leading axis C (pure; jit it)."""
    x0 = jnp.atleast_2d(x0)
    T, dU = env.horizon, env.dU
    C = x0.shape[0]
    if x0.shape[-1] != env.dX:
        raise ValueError(f"trajopt.solve_shooting: x0 must be [C, {env.dX}], got "
                         f"{tuple(x0.shape)}")  # fmt: skip
    config = ShootingConfig() if config is None else config
    box = action_bounds(env) if limits else None
    u_min, u_max = (None, None) if box is None else box
    sbox = state_bounds(env) if limits else None
    x_min, x_max = (None, None) if sbox is None else sbox
    goals = _goals(cost, x0, goal, T, dU)
    U = jnp.zeros((T, dU), x0.dtype) if U_init is None else jnp.asarray(U_init, x0.dtype)
    if U.shape[-2:] != (T, dU):
        raise ValueError(f"trajopt.solve_shooting: U_init must be [T={T}, {dU}] or [C, T, {dU}], "
                         f"got {tuple(U.shape)}")  # fmt: skip
    U = jnp.broadcast_to(U, (C, T, dU))

    def one(x, g, u):
        return multiple_shooting(env.step, cost, x, straight_line(x, g, T), u, config, u_min=u_min,
                                 u_max=u_max, x_min=x_min, x_max=x_max)  # fmt: skip

    return map_starts(one, (x0, goals, U), batch_size)


def expert_batch_size() -> int | None:
    """The expert's ``batch_size`` with ``shooting=True`` (:func:`ilqr_controllers`), for
    :func:`solve_shooting` and :func:`solve` alike: one start at a time on a CPU, where a
    vmapped while loop would run every start as long as the slowest; all at once on an
    accelerator. A function, not a constant: asking for the backend at import would start JAX's
    backends before a multi-process run's ``jax.distributed.initialize``."""
    return 1 if jax.default_backend() == "cpu" else None


INITIAL_ACTIONS = ("zeros", "goal_lqr", "best")
# Where the expert's iLQR starts unless told otherwise (``api.expert_demos``, ``diffgcl demos
# --mjcf``, :func:`make_gps_from_ilqr`): the better of zero actions and the goal's LQR. From zero
# actions an unstable system falls at once and iLQR settles on a swinging local optimum
# (gymnasium's double pendulum: 0 of 8 starts balanced); the goal's LQR means little where the
# goal is no equilibrium at zero action (a fingertip on a target). Both run side by side in one
# program, and the dearer run stops once the other has finished cheaper after as many
# iterations (:func:`~diffgcl.control.ilqr.ilqr_best_of`), so a balance found at once is not
# held up by the fall from zero actions. :func:`solve` itself keeps zero actions by default: it
# is the algorithm, this is the expert's choice.
EXPERT_INITIAL = "best"


def solve(
    env: Env,
    cost: CostFn,
    x0: Array,
    U_init: Array | None = None,
    config: ILQRConfig | None = None,
    *,
    limits: bool = True,
    initial: str = "zeros",
    goal: Array | None = None,
    batch_size: int | None = None,
) -> ILQRResult:
    """iLQR on ``env.step`` with ``cost`` from each start state ``x0: [C, dX]`` (pure; jit it).

    U_init: [T, dU] or [C, T, dU] initial actions (default zeros, ``T = env.horizon``).
    limits: control-limited iLQR on the env's :func:`action_bounds` where it has any (the
    simulator clamps actions beyond them, so an unconstrained solution would push where it has
    no authority); False: unconstrained.
    initial: where iLQR starts when ``U_init`` is None — ``"zeros"``; ``"goal_lqr"``, the
    rollout of the LQR of the dynamics linearised at the goal
    (:func:`~diffgcl.control.ilqr.goal_lqr_actions`: for balancing an unstable system, which
    falls under zero actions); ``"best"``, both side by side, keeping per start the cheaper
    (:func:`~diffgcl.control.ilqr.ilqr_best_of`: a run dearer than the other's finished one
    after as many trips stops there).
    goal: [dX] or [C, dX], the state the LQR stabilises (default: where the terminal cost is
    lowest, :func:`~diffgcl.control.ilqr.cost_minimiser` from each start).
    batch_size: as in :func:`solve_shooting` (None: all starts in one vmap; an integer: groups
    of that many, ``lax.map``).
    Returns an :class:`~diffgcl.control.ilqr.ILQRResult` with leading axis C.
    """
    x0 = jnp.atleast_2d(x0)
    T, dU = env.horizon, env.dU
    C = x0.shape[0]
    if x0.shape[-1] != env.dX:
        raise ValueError(f"trajopt.solve: x0 must be [C, {env.dX}], got {tuple(x0.shape)}")
    if initial not in INITIAL_ACTIONS:
        raise ValueError(f"trajopt.solve: initial must be one of {INITIAL_ACTIONS}, got "
                         f"{initial!r}")  # fmt: skip
    config = ILQRConfig() if config is None else config
    box = action_bounds(env) if limits else None
    u_min, u_max = (None, None) if box is None else box
    one = lambda x, u: ilqr(env.step, cost, x, u, config, u_min=u_min, u_max=u_max)
    if U_init is not None or initial == "zeros":
        U = jnp.zeros((T, dU), x0.dtype) if U_init is None else jnp.asarray(U_init, x0.dtype)
        if U.shape[-2:] != (T, dU):
            raise ValueError(f"trajopt.solve: U_init must be [T={T}, {dU}] or [C, T, {dU}], got "
                             f"{tuple(U.shape)}")  # fmt: skip
        return map_starts(one, (x0, jnp.broadcast_to(U, (C, T, dU))), batch_size)
    true_cost = squared_residual(cost) if config.gauss_newton else cost
    U_lqr = goal_lqr_starts(env, true_cost, x0, goal, limits=limits)
    if initial == "goal_lqr":
        return map_starts(one, (x0, U_lqr), batch_size)
    U = jnp.stack([jnp.zeros_like(U_lqr), U_lqr], axis=1)  # [C, 2, T, dU]
    race = lambda x, u: ilqr_best_of(env.step, cost, x, u, config, u_min=u_min, u_max=u_max)[0]
    return map_starts(race, (x0, U), batch_size)


def map_starts(solve_one: Callable, args: tuple, batch_size: int | None):
    """``solve_one(*a)`` for each start (the leading axis of every array in ``args``): all in
    one vmap (``batch_size=None``) or in groups of ``batch_size`` (``lax.map``; the same
    result). Why groups: :func:`solve_shooting`'s docstring."""
    if batch_size is None:
        return jax.vmap(solve_one)(*args)
    if batch_size < 1:
        raise ValueError(f"trajopt: batch_size must be >= 1 or None, got {batch_size}")
    C = args[0].shape[0]
    return lax.map(lambda a: solve_one(*a), args, batch_size=min(batch_size, C))


def goal_lqr_starts(
    env: Env, cost: CostFn, x0: Array, goal: Array | None = None, *, limits: bool = True
) -> Array:
    """The initial actions [C, T, dU] of ``solve(..., initial="goal_lqr")`` from each start
    ``x0: [C, dX]`` (:func:`~diffgcl.control.ilqr.goal_lqr_actions`; ``goal`` [dX] or [C, dX],
    default the terminal cost's minimiser from each start; clipped to the env's
    :func:`action_bounds` with ``limits``). ``cost`` is a cost, not a residual."""
    x0 = jnp.atleast_2d(x0)
    T, dU = env.horizon, env.dU
    box = action_bounds(env) if limits else None
    u_min, u_max = (None, None) if box is None else box
    goals = _goals(cost, x0, goal, T, dU)
    lqr = lambda x, g: goal_lqr_actions(env.step, cost, x, g, T, dU, u_min=u_min, u_max=u_max)
    return jax.vmap(lqr)(x0, goals)


def _goals(cost: CostFn, x0: Array, goal: Array | None, T: int, dU: int) -> Array:
    """[C, dX]: ``goal`` per start, or where the terminal cost is lowest from each start."""
    if goal is None:
        return jax.vmap(lambda x: cost_minimiser(cost, x, dU, T))(x0)
    return jnp.broadcast_to(jnp.asarray(goal, x0.dtype), x0.shape)


def lowest_cost(results: ILQRResult) -> tuple[ILQRResult, Array]:
    """Per start, the run of ``results`` (fields [R, C, ...]) with the lowest finite final cost
    -> (ILQRResult [C], the index of that run [C])."""
    return jax.vmap(cheapest_run, in_axes=1)(results)


def cheaper_per_start(a: ILQRResult, b: ILQRResult) -> ILQRResult:
    """Per start the cheaper of two solvers' results (fields [C, ...]; both rollouts of the
    same cost, so their costs compare; a non-finite cost loses). Their ``cost_history`` may
    differ in length (iLQR's iterations, multiple shooting's trips): the shorter is padded with
    NaN."""
    n = max(a.cost_history.shape[-1], b.cost_history.shape[-1])

    def padded(r):
        extra = n - r.cost_history.shape[-1]
        pad = [(0, 0)] * (r.cost_history.ndim - 1) + [(0, extra)]
        return r.replace(cost_history=jnp.pad(r.cost_history, pad, constant_values=jnp.nan))

    both = jax.tree_util.tree_map(lambda u, v: jnp.stack([u, v]), padded(a), padded(b))
    return lowest_cost(both)[0]


def restart_actions(T: int, dU: int, scale: float, dtype=None) -> Array:
    """Initial action sequences of :func:`solve_restarts`: zeros, and ``±scale`` held constant on
    one actuator at a time -> [1 + 2·dU, T, dU]."""
    dtype = dtype or jnp.zeros(()).dtype
    eye = jnp.eye(dU, dtype=dtype)
    consts = jnp.concatenate([jnp.zeros((1, dU), dtype), scale * eye, -scale * eye])
    return jnp.broadcast_to(consts[:, None, :], (1 + 2 * dU, T, dU))


def solve_restarts(
    env: Env,
    cost: CostFn,
    x0: Array,
    config: ILQRConfig | None = None,
    *,
    scale: float = 0.1,
) -> tuple[ILQRResult, Array, Array]:
    """iLQR from each start state and each of :func:`restart_actions`' initial action sequences
    (one program: vmapped over both), keeping per start the lowest final cost. Every run goes to
    its own end (unlike ``solve(..., initial="best")``, no run is stopped early): a user asking
    for restarts asks for the wider search.

    Why: a cost that is not convex in the actions has stationary points that zero actions sit on
    by symmetry — gymnasium's reacher with the target behind the arm: the fingertip distance's
    gradient along the shoulder vanishes at zero torque, and iLQR folds the elbow instead and
    stops short. A small constant torque either way breaks the symmetry. Returns (the kept
    ILQRResult [C], the index of its initial sequence [C], every run's ILQRResult [R, C]; run 0
    is iLQR from zero actions).
    """
    x0 = jnp.atleast_2d(x0)
    U = restart_actions(env.horizon, env.dU, scale, x0.dtype)
    results = jax.vmap(lambda u: solve(env, cost, x0, u, config))(U)  # fields [R, C, ...]
    kept, best = lowest_cost(results)
    return kept, best, results


def ilqr_controllers(
    env: Env,
    cost: CostFn,
    x0: Array,
    *,
    config: ILQRConfig | None = None,
    init_var: float | Array | None = None,
    temperature: float | Array = 1.0,
    U_init: Array | None = None,
    restarts: bool = False,
    initial: str = "zeros",
    shooting: bool = False,
) -> tuple[LinearGaussianController, ILQRResult]:
    """iLQR from every start state (``restarts``: the best of :func:`solve_restarts`; else
    :func:`solve` from ``U_init`` or ``initial``) and the solutions as controllers (fields [C,
    T, ...]); see :func:`diffgcl.control.ilqr.ilqr_controller` for ``init_var`` and
    ``temperature``. shooting: also :func:`solve_shooting` from each start, keeping per start
    the cheaper of it and iLQR (:func:`cheaper_per_start`), both solving the starts in groups
    of :func:`expert_batch_size` (one at a time on a CPU: on gymnasium's tilted double pendulum
    iLQR took 172.6 s instead of 548.8 s in one vmap). Without ``shooting`` iLQR keeps the one
    vmap: where the starts solve alike the time saved is small (gymnasium's reacher 10.4 s to
    6.5 s, ``experiments/any_mjcf.py``'s models under 0.1 s), and in groups the solutions
    differ by rounding, which rGCL learning from their demos turned into other results on
    any_mjcf's cart-pole (``docs/trajopt.md``)."""
    batch = expert_batch_size() if shooting else None
    if restarts:
        result = solve_restarts(env, cost, x0, config)[0]
    else:
        result = solve(env, cost, x0, U_init, config, initial=initial, batch_size=batch)
    if shooting:
        gauss_newton = config is not None and config.gauss_newton
        plain = squared_residual(cost) if gauss_newton else cost
        shot = solve_shooting(env, plain, x0, batch_size=batch)
        result = cheaper_per_start(result, shot)
    ctrl = jax.vmap(lambda r: ilqr_controller(r, init_var=init_var, temperature=temperature))(
        result
    )
    return ctrl, result


def make_gps_from(
    config: GPSConfig,
    env: Env,
    cost: CostFn,
    *,
    true_cost: CostFn | None = None,
    x0: Array | None = None,
) -> Callable[..., tuple[GPSState, GPSMetrics]]:
    """``train(key, controller, hparams=None) -> (state, metrics [iterations, C])``: GPS
    (:func:`~diffgcl.algorithms.gps.make_gps`, same arguments) from the initial controllers
    ``controller`` (fields [C, T, ...]) instead of the zero controller. With the zero controller
    of ``init_var`` it is ``make_gps(...).train`` (the same keys)."""
    gps = make_gps(config, env, cost, true_cost=true_cost, x0=x0)

    def train(key: PRNGKey, controller: LinearGaussianController, hparams=None):
        key_init, key_iter = jax.random.split(key)
        state = gps.init(key_init, hparams, controller=controller)
        return lax.scan(gps.iteration, state, jax.random.split(key_iter, config.iterations))

    return train


def make_gps_from_ilqr(
    config: GPSConfig,
    env: Env,
    cost: CostFn,
    *,
    ilqr_config: ILQRConfig | None = None,
    true_cost: CostFn | None = None,
    x0: Array | None = None,
    initial: str = EXPERT_INITIAL,
) -> Callable[..., tuple[GPSState, GPSMetrics, ILQRResult]]:
    """``train(key, hparams=None) -> (state, metrics, ilqr_result)``: iLQR on ``cost`` from each
    condition (from ``initial``, see :func:`solve`), then GPS's KL-constrained iterations
    starting from the iLQR controllers, whose noise has the shape of ``(Q_uu + μI)⁻¹`` and mean
    variance ``init_var`` (from ``hparams`` or ``config``). ``cost`` is a residual with
    ``config.gauss_newton`` (for both)."""
    import dataclasses

    X0 = jnp.asarray(env.initial_states() if x0 is None else x0)
    train_from = make_gps_from(config, env, cost, true_cost=true_cost, x0=X0)
    ilqr_config = dataclasses.replace(
        ILQRConfig() if ilqr_config is None else ilqr_config, gauss_newton=config.gauss_newton
    )

    def train(key: PRNGKey, hparams: GPSHyperparams | None = None):
        init_var = config.init_var if hparams is None else hparams.init_var
        ctrl, result = ilqr_controllers(
            env, cost, X0, config=ilqr_config, init_var=init_var, initial=initial
        )
        state, metrics = train_from(key, ctrl, hparams)
        return state, metrics, result

    return train


def expert_rollouts(
    env: Env,
    controllers: LinearGaussianController,
    x0: Array,
    key: PRNGKey,
    per_start: int,
    *,
    smooth_sigma: float | None = None,
):
    """``per_start`` noisy rollouts of each start's controller (fields [C, T, ...]) from its
    start ``x0: [C, dX]``, episode ``i`` from start ``i mod C``: (X [C·per_start, T+1, dX],
    U [C·per_start, T, dU], condition [C·per_start]). White noise by default (the MaxEnt
    demonstrator of :func:`~diffgcl.control.ilqr.ilqr_controller`); ``smooth_sigma`` smooths it
    in time as GPS's samples are."""
    from diffgcl.sim.rollout import rollout_controller, smooth_noise

    C = x0.shape[0]
    n = C * per_start
    condition = jnp.arange(n) % C

    def one(c, k):
        ctrl = jax.tree.map(lambda a: a[c], controllers)
        noise = smooth_noise(k, env.horizon, env.dU, smooth_sigma)
        traj = rollout_controller(env, ctrl, x0[c], noise)
        return traj.X, traj.U

    X, U = jax.vmap(one)(condition, jax.random.split(key, n))
    return X, U, condition
