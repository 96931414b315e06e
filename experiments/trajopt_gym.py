"""Trajectory optimisation on gymnasium's MuJoCo tasks with hand-written quadratic costs.

For gymnasium's ``reacher.xml``, ``inverted_pendulum.xml`` and ``inverted_double_pendulum.xml``
(read from the installed gymnasium package, loaded with ``api.load_model`` at gymnasium's control
period: frame skip 2, 2 and 5), from start states drawn from the v5 envs' own reset
distributions (NumPy ``default_rng(seed)``, default seed 0; the pendulums' hinge angles scaled
3×, ``--tilt-scale 1`` for gymnasium's own), each task with a plain quadratic cost written by
hand (below), this script runs and reports per start state:

* **iLQR** (:mod:`diffgcl.control.ilqr`) from the expert's default initial actions (the better
  of zero actions and the goal's LQR, ``--initial best``; ``--initial zeros`` for the plain
  solver): success, iterations, final cost, seconds after compile (one program, vmapped over the
  start states); with ``--to-the-end-row`` also both initial sequences each run to its own end
  (``best`` stops the dearer run once the other has finished cheaper after as many iterations:
  this row is that rule's reference, for time and for what it gives up); with ``--restarts`` also
  the best of iLQR from zero and from ±0.1 constant actions on each actuator
  (:func:`diffgcl.algorithms.trajopt.solve_restarts`); with ``--shooting`` also multiple shooting
  from the straight line of states to the goal with the joints' ranges as state limits
  (:func:`diffgcl.algorithms.trajopt.solve_shooting`; one start at a time, ``--shooting-batch``)
  and, per start, the cheaper of it and iLQR; ``--shooting-only``: that row alone; with
  ``--ilqr-batch N`` also iLQR's row solved N starts at a time (``lax.map``) beside the vmap
  (``--no-ilqr-vmap``: only in the groups, the row the shooting's per-start choice then uses);
  ``--shooting-merit RULE``, ``--shooting-fallback RULE|none``: multiple shooting with that
  ``ShootingConfig.merit_rule`` and ``fallback_rule``;
* **GPS from iLQR**: trajectory-optimisation GPS (``GPSConfig`` of the project's reacher: 5
  samples, KL step 0.2, init_var 0.1, 20 iterations) started from the iLQR controllers;
* **GPS from zero** (K = 0, k = 0, Σ = init_var·I; the same compiled program, another initial
  controller), the baseline; both also with KL step 1.0 (``--gps-settings KL:VAR,...``: the
  (KL step, init_var) pairs, traced hyperparameters of one program; ``--gps-iterations``: the
  success after 20 iterations and at the end; ``--gps-cost-scale``: GPS sees the cost times
  that);
* **trajax** (``trajax.optimizers.ilqr``, google/trajax) on the same model, cost, horizon and
  start states, from the same initial actions (zeros, or the goal's LQR with ``--initial
  goal_lqr``), if it is importable: iterations, final cost, seconds after compile. trajax
  differentiates the dynamics in reverse mode, which ``mjx.step`` does not support once its
  constraint solver iterates (these models' joint limits are constraints), so it gets the same
  step function with a custom VJP that multiplies by the forward-mode Jacobian
  (:func:`reverse_mode_step`); both then compute the same Jacobians. trajax is not on PyPI (the
  PyPI package of that name is another project): ``pip install git+https://github.com/google/trajax``
  into a virtual environment of its own that also sees this project's (``docs/trajopt.md``
  gives the three commands), then run this script with that environment's python.

    python experiments/trajopt_gym.py --x64 --json runs/trajopt_gym.json
    python experiments/trajopt_gym.py --x64 --models pendulum --hard --json runs/trajopt_hard.json
    python experiments/trajopt_gym.py --models reacher --no-gps --no-trajax  # iLQR only
    python experiments/trajopt_gym.py --x64 --models double_pendulum --shooting-only --seed 5

The tasks (user code: nothing in the library knows them):

* reacher, T = 50 (gymnasium's episode, 1 s): ``½‖(tip − target)/2 cm‖² + 0.05·½‖q̇_arm‖² +
  0.01·½‖u‖²`` with the fingertip from the joint angles by hand (links 0.1 and 0.11 m) and the
  target read from the state (its two slide joints); success: the fingertip within 2 cm of the
  target over the last 10 states. Starts: arm angles U(−0.1, 0.1), target uniform in the disk of
  radius 0.2 (rejection sampling), arm velocities U(−0.005, 0.005).
* inverted pendulum, T = 100 (4 s): ``½(x² + 4θ² + 0.1ẋ² + 0.1θ̇²) + 0.01·½u²``; success: gymnasium's
  healthy test |θ| ≤ 0.2 throughout, and |x| < 0.1 m, |θ| < 0.05 rad over the last 10 states.
  Starts: qpos, qvel U(−0.01, 0.01), θ scaled 3×.
* inverted double pendulum, T = 100 (5 s): ``½(0.1x² + θ₁² + θ₂² + 0.1‖q̇‖²) + 0.001·½u²``,
  the weights chosen on the starts of seed 0 with ``experiments/double_pendulum_lqr.py``
  (``--double-weights 1,4,0.1,0.01`` for the first guess, the pendulum's weights);
  success: gymnasium's healthy test (tip height > 1 m) throughout, and |x| < 0.1 m, |θ₁|, |θ₂| <
  0.05 rad over the last 10 states. Starts: qpos U(−0.1, 0.1), qvel 0.1·N(0, 1), θ₁, θ₂ scaled
  3×.

A start counts as solved when the method's noise-free rollout passes the task's success test.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

# ---- the user's tasks --------------------------------------------------------------------------


def gym_asset(name: str) -> Path:
    """The MJCF file of the installed gymnasium package (dev extra)."""
    try:
        import gymnasium
    except ImportError:
        raise SystemExit(
            "trajopt_gym: gymnasium is not installed (pip install -e '.[dev]')"
        ) from None
    path = Path(gymnasium.__file__).parent / "envs" / "mujoco" / "assets" / name
    if not path.is_file():
        raise SystemExit(f"trajopt_gym: {path} not found in gymnasium {gymnasium.__version__}")
    return path


REACHER_LINKS = (0.1, 0.11)  # shoulder to elbow, elbow to fingertip (reacher.xml)


def reacher_tip(x):
    q1, q12 = x[0], x[0] + x[1]
    l1, l2 = REACHER_LINKS
    return jnp.stack([l1 * jnp.cos(q1) + l2 * jnp.cos(q12), l1 * jnp.sin(q1) + l2 * jnp.sin(q12)])


def reacher_cost(x, u, t):
    d = (reacher_tip(x) - x[2:4]) / 0.02
    return 0.5 * d @ d + 0.05 * 0.5 * x[4:6] @ x[4:6] + 0.01 * 0.5 * u @ u


def reacher_success(X):
    dist = jax.vmap(lambda x: jnp.linalg.norm(reacher_tip(x) - x[2:4]))(X[-10:])
    return jnp.all(dist < 0.02)


def pendulum_cost(x, u, t):
    w = jnp.asarray([1.0, 4.0, 0.1, 0.1], x.dtype)
    return 0.5 * jnp.sum(w * x * x) + 0.01 * 0.5 * u @ u


def pendulum_success(X):
    healthy = jnp.all(jnp.abs(X[:, 1]) <= 0.2)
    return healthy & jnp.all((jnp.abs(X[-10:, 0]) < 0.1) & (jnp.abs(X[-10:, 1]) < 0.05))


# The cart, each hinge angle, every velocity, the action: the best of 108 weightings for the
# clipped LQR on seed 0's starts (experiments/double_pendulum_lqr.py); seeds 1-4 never tuned on.
DOUBLE_WEIGHTS = (0.1, 1.0, 0.1, 0.001)


def double_pendulum_cost(weights=DOUBLE_WEIGHTS):
    """``½(q_x x² + q_θ(θ₁² + θ₂²) + q_v‖q̇‖²) + r·½u²`` with ``weights = (q_x, q_θ, q_v, r)``."""
    q_x, q_th, q_v, r = weights

    def cost(x, u, t):
        w = jnp.asarray([q_x, q_th, q_th, q_v, q_v, q_v], x.dtype)
        return 0.5 * jnp.sum(w * x * x) + r * 0.5 * u @ u

    return cost


double_cost = double_pendulum_cost()


def double_tip_height(x):
    return 0.6 * jnp.cos(x[1]) + 0.6 * jnp.cos(x[1] + x[2])


def double_success(X):
    healthy = jnp.all(jax.vmap(double_tip_height)(X) > 1.0)
    end = X[-10:]
    still = (jnp.abs(end[:, 0]) < 0.1) & (jnp.abs(end[:, 1]) < 0.05) & (jnp.abs(end[:, 2]) < 0.05)
    return healthy & jnp.all(still)


def reacher_starts(rng, n):
    X = np.zeros((n, 8))
    X[:, :2] = rng.uniform(-0.1, 0.1, (n, 2))
    for i in range(n):
        while True:
            goal = rng.uniform(-0.2, 0.2, 2)
            if np.linalg.norm(goal) < 0.2:
                break
        X[i, 2:4] = goal
    X[:, 4:6] = rng.uniform(-0.005, 0.005, (n, 2))
    return X


# The pendulums' hinge angles: gymnasium's reset distribution scaled up this much (--tilt-scale).
TILT_SCALE = 3.0


def pendulum_starts(rng, n, tilt=TILT_SCALE):
    X = rng.uniform(-0.01, 0.01, (n, 4))
    X[:, 1] *= tilt
    return X


def double_starts(rng, n, tilt=TILT_SCALE):
    X = np.concatenate([rng.uniform(-0.1, 0.1, (n, 3)), 0.1 * rng.standard_normal((n, 3))], 1)
    X[:, 1:3] *= tilt
    return X


def pendulum_hard_starts(rng, n):
    """The starts where GPS failed before iLQR: tilts of ±0.15 rad, the cart 0.1–0.2 m off
    centre either side, at rest (``--hard``; ``n`` of them, cycling through the 8 sign and offset
    combinations)."""
    combos = [(c * s, t) for c in (0.1, 0.2) for s in (1, -1) for t in (0.15, -0.15)]
    return np.asarray([[*combos[i % 8], 0.0, 0.0] for i in range(n)])


@dataclass(frozen=True)
class GymTask:
    xml: str
    frame_skip: int  # gymnasium's default for the v5 env
    horizon: int
    cost: object
    success: object
    starts: object  # (rng, n) -> [n, dX]


TASKS = {
    "reacher": GymTask("reacher.xml", 2, 50, reacher_cost, reacher_success, reacher_starts),
    "pendulum": GymTask(
        "inverted_pendulum.xml", 2, 100, pendulum_cost, pendulum_success, pendulum_starts
    ),
    "double_pendulum": GymTask(
        "inverted_double_pendulum.xml", 5, 100, double_cost, double_success, double_starts
    ),
}


# ---- trajax on the same problem ----------------------------------------------------------------


def reverse_mode_step(step):
    """``step(x, u)`` with a custom VJP ``g ↦ (Jₓᵀg, J_uᵀg)`` from the forward-mode Jacobian, so
    that reverse-mode autodiff (trajax's ``jax.jacobian``) works through ``mjx.step``."""
    from diffgcl.dynamics.autodiff import linearize

    @jax.custom_vjp
    def f(x, u):
        return step(x, u)

    def fwd(x, u):
        A, B = linearize(step, x, u)
        return step(x, u), (A, B)

    def bwd(res, g):
        A, B = res
        return A.T @ g, B.T @ g

    f.defvjp(fwd, bwd)
    return f


def run_trajax(env, cost, X0, *, maxiter, tol, U_init=None):
    """trajax's iLQR from each start (vmapped, jitted; from ``U_init: [C, T, dU]``, default
    zeros), or None when trajax is missing. trajax's ``ilqr`` has no control limits."""
    try:
        from trajax import optimizers
    except ImportError:
        return None
    step = reverse_mode_step(env.step)
    dynamics = lambda x, u, t: step(x, u)
    if U_init is None:
        U_init = jnp.zeros((X0.shape[0], env.horizon, env.dU), X0.dtype)

    def one(x0, U0):
        X, U, obj, _, _, _, it = optimizers.ilqr(
            cost, dynamics, x0, U0, maxiter=maxiter, obj_step_threshold=tol
        )
        return X, U, obj, it

    (X, U, obj, it), seconds, compile_s = timed(jax.jit(jax.vmap(one)), X0, U_init)
    return {
        "success": np.asarray(jax.vmap(env.success)(X)).tolist(),
        "cost": np.asarray(obj).tolist(),
        "iterations": np.asarray(it).tolist(),
        "seconds": seconds,
        "compile_seconds": compile_s,
    }


def cheaper_records(a: dict, b: dict) -> dict:
    """Two runs' records combined: per start the one with the lower final cost (both are
    rollouts of the simulator, so their costs compare); their seconds added."""
    pick = np.asarray(b["cost"]) < np.asarray(a["cost"])
    out = {k: np.where(pick, b[k], a[k]).tolist() for k in ("success", "cost", "iterations")}
    out["seconds"] = a["seconds"] + b["seconds"]
    out["compile_seconds"] = a["compile_seconds"] + b["compile_seconds"]
    return out


# ---- the runs ----------------------------------------------------------------------------------


def timed(program, *args):
    """(result, seconds of the run, seconds of tracing and compiling) of a jitted program."""
    t0 = time.perf_counter()
    compiled = program.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    return out, time.perf_counter() - t0, compile_s


def gym_env(name, *, seed=0, starts=8, tilt_scale=TILT_SCALE, hard=False, double_weights=None):
    """(env, task, tilt) of the named task: its model at gymnasium's control period with
    ``starts`` start states drawn with NumPy seed ``seed`` (``hard``: the pendulum's harder
    starts; ``tilt``: the hinge angles' scale, None for the reacher), the task's cost (the double
    pendulum's with ``double_weights`` where given) and success test."""
    import mujoco

    from diffgcl import api

    task = TASKS[name]
    path = gym_asset(task.xml)
    timestep = mujoco.MjModel.from_xml_path(str(path)).opt.timestep
    draw = task.starts
    if hard:
        if name != "pendulum":
            raise SystemExit("trajopt_gym: --hard is for the pendulum only")
        draw = pendulum_hard_starts
    rng = np.random.default_rng(seed)
    tilt = tilt_scale if draw in (pendulum_starts, double_starts) else None
    X0 = draw(rng, starts) if tilt is None else draw(rng, starts, tilt=tilt)
    if name == "double_pendulum" and double_weights is not None:
        task = dataclasses.replace(task, cost=double_pendulum_cost(double_weights))
    env = api.load_model(
        path,
        lapack_free=True,  # see make_mjcf_env: without it the vmapped programs can hang here
        dt=task.frame_skip * timestep,
        horizon=task.horizon,
        x0=X0,
        cost=task.cost,
        success=task.success,
    )
    return env, task, tilt


# GPS's (kl_step, init_var) settings: the project's reacher step, and a five times larger one.
GPS_SETTINGS = ((0.2, 0.1), (1.0, 0.1))


def gps_settings(text: str) -> tuple[tuple[float, float], ...]:
    """``--gps-settings``: ``KL:VAR,...`` -> ((kl_step, init_var), ...), each positive."""
    try:
        pairs = tuple(tuple(float(v) for v in item.split(":")) for item in text.split(","))
    except ValueError:
        pairs = ()
    if not pairs or any(len(p) != 2 or min(p) <= 0 for p in pairs):
        raise argparse.ArgumentTypeError(
            f"expected KL:VAR,... with positive numbers (e.g. 0.2:0.1,1.0:0.1), got {text!r}"
        )
    return pairs


def run_task(name, args) -> dict:
    from diffgcl.algorithms import trajopt
    from diffgcl.algorithms.gps import GPSConfig, GPSHyperparams
    from diffgcl.control.ilqr import STATUS_NAMES, ILQRConfig, ilqr_controller
    from diffgcl.control.init import init_controller
    from diffgcl.control.shooting import ShootingConfig
    from diffgcl.costs.expansion import trajectory_cost
    from diffgcl.sim.rollout import rollout_controller

    env, task, tilt = gym_env(
        name,
        seed=args.seed,
        starts=args.starts,
        tilt_scale=args.tilt_scale,
        hard=args.hard,
        double_weights=args.double_weights,
    )
    path = gym_asset(task.xml)
    X0 = env.initial_states()
    C, T = X0.shape[0], env.horizon
    out = {
        "mjcf": str(path),
        "dt": env.dt,
        "frame_skip": env.frame_skip,
        "horizon": T,
        "ctrl_scale": np.asarray(env.ctrl_scale).tolist(),
        "starts": np.asarray(X0).tolist(),
        "seed": args.seed,
        "tilt_scale": tilt,
    }
    if name == "double_pendulum":
        out["weights"] = list(args.double_weights or DOUBLE_WEIGHTS)
    print(f"== {name}: {path.name}, dt {env.dt:g} s (frame skip {env.frame_skip}), T = {T}, "
          f"{C} starts")  # fmt: skip

    config = ILQRConfig(max_iterations=args.max_iterations, tol=args.tol)

    def record(result, seconds, compile_s):
        success = np.asarray(jax.vmap(env.success)(result.X))
        return {
            "success": success.tolist(),
            "cost": np.asarray(result.cost).tolist(),
            "iterations": np.asarray(result.iterations).tolist(),
            "rollouts": np.asarray(result.rollouts).tolist(),
            "status": [STATUS_NAMES[int(s)] for s in np.asarray(result.status)],
            "seconds": seconds,
            "compile_seconds": compile_s,
        }

    def show(label, r):
        print(f"   {label}: {int(np.sum(r['success']))}/{C} solved, iterations "
              f"{min(r['iterations'])}–{max(r['iterations'])}, cost {np.mean(r['cost']):.4g} "
              f"(mean), {r['seconds']:.2f} s after compile ({r['compile_seconds']:.0f} s "
              "compile)")  # fmt: skip

    out["action_bounds"] = [np.asarray(b).tolist() for b in env.action_bounds()]

    def solve(x0, limits, initial, batch_size=None):
        return trajopt.solve(env, task.cost, x0, config=config, limits=limits, initial=initial,
                             batch_size=batch_size)  # fmt: skip

    def shooting_row():  # multiple shooting from the straight line to the goal, joints' ranges kept
        batch = args.shooting_batch or None
        rules = {}  # ShootingConfig's defaults unless asked otherwise
        if args.shooting_merit is not None:
            rules["merit_rule"] = args.shooting_merit
        if args.shooting_fallback is not None:
            fallback = args.shooting_fallback
            rules["fallback_rule"] = None if fallback == "none" else fallback
        shooting_config = ShootingConfig(**rules)
        shoot = jax.jit(lambda x0: trajopt.solve_shooting(env, task.cost, x0, shooting_config,
                                                          limits=args.limits,
                                                          batch_size=batch))  # fmt: skip
        result, seconds, compile_s = timed(shoot, X0)
        out["shooting"] = record(result, seconds, compile_s)
        out["shooting"]["rules"] = list(shooting_config.rules)
        show("multiple shooting from the straight line", out["shooting"])

    if args.shooting_only:
        shooting_row()
        return out

    # iLQR's row in one vmap, or with --ilqr-batch N --no-ilqr-vmap in groups of N starts
    row_batch = args.ilqr_batch if args.ilqr_batch and not args.ilqr_vmap else None
    program = jax.jit(lambda x0: solve(x0, args.limits, args.initial, row_batch))
    result, seconds, compile_s = timed(program, X0)
    out["ilqr"] = record(result, seconds, compile_s)
    out["ilqr"]["control_limited"] = args.limits
    out["ilqr"]["initial"] = args.initial
    out["ilqr"]["batch_size"] = row_batch
    start = {"zeros": "zero actions", "goal_lqr": "the goal's LQR", "best": "the better of both"}
    label = f"iLQR from {start[args.initial]}{'' if args.limits else ', no control limits'}"
    if row_batch:
        label += f", {row_batch} start(s) at a time"
    show(label, out["ilqr"])
    if args.ilqr_batch and args.ilqr_vmap:  # the same solve in groups (lax.map) beside the vmap
        grouped = jax.jit(lambda x0: solve(x0, args.limits, args.initial, args.ilqr_batch))
        result, seconds, compile_s = timed(grouped, X0)
        out["ilqr_grouped"] = record(result, seconds, compile_s) | {"batch_size": args.ilqr_batch}
        show(f"the same, {args.ilqr_batch} start(s) at a time", out["ilqr_grouped"])
    if args.shooting:
        shooting_row()
        out["ilqr_or_shooting"] = cheaper_records(out["ilqr"], out["shooting"])
        show("per start the cheaper of iLQR and multiple shooting", out["ilqr_or_shooting"])
    if args.initial != "zeros" and args.zeros_row:  # the same solver from zero actions
        zeros, seconds, compile_s = timed(jax.jit(lambda x0: solve(x0, args.limits, "zeros")), X0)
        out["ilqr_zeros"] = record(zeros, seconds, compile_s)
        show("iLQR from zero actions", out["ilqr_zeros"])
    if args.initial == "best" and args.to_the_end_row:
        # The reference for best's early stop: from zero actions and from the goal's LQR, each
        # run to its own end in one vmapped loop, the cheaper kept per start.
        def both_to_the_end(x0):
            U_lqr = trajopt.goal_lqr_starts(env, task.cost, x0, limits=args.limits)
            U = jnp.stack([jnp.zeros_like(U_lqr), U_lqr])
            one = lambda U: trajopt.solve(env, task.cost, x0, U, config, limits=args.limits)
            return trajopt.lowest_cost(jax.vmap(one)(U))[0]

        full, seconds, compile_s = timed(jax.jit(both_to_the_end), X0)
        out["ilqr_to_the_end"] = record(full, seconds, compile_s)
        show("iLQR from both, each to its end", out["ilqr_to_the_end"])
    if args.limits and args.unlimited_row:  # the same problem without the box, for comparison
        unlimited, seconds, compile_s = timed(
            jax.jit(lambda x0: solve(x0, False, args.initial)), X0
        )
        out["ilqr_unlimited"] = record(unlimited, seconds, compile_s)
        out["ilqr_unlimited"]["max_abs_action"] = float(jnp.abs(unlimited.U).max())
        show("iLQR without control limits", out["ilqr_unlimited"])
    if args.restarts:  # the best of zero and ±0.1 constant actions per actuator
        program = jax.jit(lambda x0: trajopt.solve_restarts(env, task.cost, x0, config))
        (kept, best, runs), seconds, compile_s = timed(program, X0)
        out["ilqr_restarts"] = record(kept, seconds, compile_s)
        out["ilqr_restarts"]["restart"] = np.asarray(best).tolist()
        out["ilqr_restarts"]["restart_costs"] = np.asarray(runs.cost).tolist()
        show(f"iLQR, best of {int(runs.cost.shape[0])} initial actions", out["ilqr_restarts"])
    if args.trajax:
        # trajax from iLQR's initial actions: zeros, the goal's LQR, or with best both, keeping
        # per start the cheaper result as trajopt.solve does
        inits = {"zeros": [None], "goal_lqr": ["lqr"], "best": [None, "lqr"]}[args.initial]
        U_lqr = None
        if "lqr" in inits:
            U_lqr = jax.jit(lambda x: trajopt.goal_lqr_starts(env, task.cost, x))(X0)
        tj = None
        for init in inits:
            one = run_trajax(
                env,
                task.cost,
                X0,
                maxiter=args.max_iterations,
                tol=args.tol,
                U_init=U_lqr if init == "lqr" else None,
            )
            tj = one if tj is None or one is None else cheaper_records(tj, one)
        if tj is None:
            print("   trajax: not importable, skipped (see the module docstring to install it)")
            out["trajax"] = None
        else:
            ratio = np.asarray(out["ilqr"]["cost"]) / np.asarray(tj["cost"])
            tj["cost_ratio"] = ratio.tolist()  # ours / trajax's, per start
            out["trajax"] = tj
            print(f"   trajax: {int(np.sum(tj['success']))}/{C} solved, iterations "
                  f"{min(tj['iterations'])}–{max(tj['iterations'])}, our cost / trajax's "
                  f"{ratio.min():.4f}–{ratio.max():.4f}, {tj['seconds']:.2f} s after compile "
                  f"({tj['compile_seconds']:.0f} s compile)")  # fmt: skip

    if args.gps:
        gps_config = GPSConfig(
            iterations=args.gps_iterations, num_samples=5, kl_step=0.2, init_var=0.1
        )
        scale = args.gps_cost_scale  # GPS sees the cost times this; the figures are unscaled

        def gps_cost(x, u, t):
            return scale * task.cost(x, u, t)

        train = trajopt.make_gps_from(gps_config, env, gps_cost, x0=X0)
        settings = args.gps_settings  # (kl_step, init_var) pairs
        dtype = X0.dtype
        hps = GPSHyperparams(
            kl_step=jnp.asarray([s[0] for s in settings], dtype),
            init_var=jnp.asarray([s[1] for s in settings], dtype),
        )

        def zero_ctrl(init_var):
            c = init_controller(T, env.dX, env.dU, init_var, dtype=dtype)
            return jax.tree.map(lambda a: jnp.broadcast_to(a, (C, *a.shape)), c)

        def ilqr_ctrl(init_var):
            return jax.vmap(lambda res: ilqr_controller(res, init_var=init_var))(result)

        def final_rollouts(ctrl):
            def one(c, x0):
                traj = rollout_controller(env, c, x0, jnp.zeros((T, env.dU), dtype))
                return traj.X, trajectory_cost(task.cost, traj.X, traj.U)

            return jax.vmap(one)(ctrl, X0)

        def run(key, ctrl0, hp):
            state, metrics = train(key, ctrl0, hp)
            X, cost = final_rollouts(state.controller)
            return metrics.success, jax.vmap(env.success)(X), cost

        keys = jnp.stack([jax.random.PRNGKey(s) for s in range(args.gps_seeds)])
        inits = ("zero", "ilqr")
        ctrls = jax.tree.map(
            lambda a, b: jnp.stack([a, b]),
            jax.vmap(zero_ctrl)(hps.init_var),
            jax.vmap(ilqr_ctrl)(hps.init_var),
        )  # [init, setting, C, ...]
        over_settings = jax.vmap(run, (None, 0, 0))
        over_inits = jax.vmap(over_settings, (None, 0, None))
        batched = jax.jit(jax.vmap(over_inits, (0, None, None)))  # seeds, inits, settings
        (it_success, final, cost), seconds, compile_s = timed(batched, keys, ctrls, hps)
        it_success = np.asarray(it_success)  # [S, init, H, iterations, C]
        final, cost = np.asarray(final), np.asarray(cost)  # [S, init, H, C]
        at = min(19, args.gps_iterations - 1)
        out["gps"] = {
            "config": {
                "samples": 5,
                "iterations": args.gps_iterations,
                "seeds": args.gps_seeds,
                "cost_scale": scale,
            },
            "settings": [{"kl_step": k, "init_var": v} for k, v in settings],
            "seconds": seconds,
            "compile_seconds": compile_s,
        }
        for i, init in enumerate(inits):
            out["gps"][init] = {
                "success_at_20": it_success[:, i, :, at].tolist(),
                "success_final": final[:, i].tolist(),
                "cost_final": cost[:, i].tolist(),
            }
            for h, (kl, var) in enumerate(settings):
                at20, fin = it_success[:, i, h, at], final[:, i, h]
                print(f"   GPS from {init:4s} (kl_step {kl}, init_var {var}): solved "
                      f"{int(at20.sum())}/{at20.size} after {at + 1} iterations, "
                      f"{int(fin.sum())}/{fin.size} after {args.gps_iterations}, final cost "
                      f"{cost[:, i, h].mean():.4g} (mean)")  # fmt: skip
        print(f"   ({seconds:.1f} s after compile for {args.gps_seeds} seeds × 2 initial "
              f"controllers × {len(settings)} settings, {compile_s:.0f} s compile)")  # fmt: skip
    return out


def main(argv=None) -> int:
    from diffgcl.control.shooting import MERIT_RULES

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--models", default=",".join(TASKS), help="comma-separated")
    parser.add_argument("--starts", type=int, default=8, help="start states per model")
    parser.add_argument("--seed", type=int, default=0, help="NumPy seed of the start states")
    parser.add_argument("--max-iterations", type=int, default=100)
    parser.add_argument("--tol", type=float, default=1e-6, help="relative cost improvement")
    parser.add_argument("--gps", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--gps-iterations", type=int, default=20)
    parser.add_argument("--gps-seeds", type=int, default=1)
    parser.add_argument("--gps-cost-scale", type=float, default=1.0,
                        help="GPS minimises the task's cost times this (a check that the KL "
                             "step, not the cost's units, sets its pace)")  # fmt: skip
    parser.add_argument("--gps-settings", type=gps_settings, default=GPS_SETTINGS,
                        metavar="KL:VAR,...",
                        help="GPS's (kl_step, init_var) pairs, each run from both initial "
                             "controllers (default 0.2:0.1,1.0:0.1)")  # fmt: skip
    parser.add_argument("--trajax", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--restarts", action="store_true", help="also iLQR's best of 1 + 2·dU")
    parser.add_argument("--shooting", action="store_true",
                        help="also multiple shooting (trajopt.solve_shooting)")  # fmt: skip
    parser.add_argument("--ilqr-batch", type=int, default=0,
                        help="also iLQR's row solved N starts at a time (lax.map) beside the "
                             "one vmap")  # fmt: skip
    parser.add_argument("--shooting-merit", choices=MERIT_RULES, default=None,
                        help="multiple shooting's ShootingConfig.merit_rule (default: its "
                             "default)")  # fmt: skip
    parser.add_argument("--shooting-fallback", choices=MERIT_RULES + ("none",), default=None,
                        help="multiple shooting's ShootingConfig.fallback_rule (default: its "
                             "default)")  # fmt: skip
    parser.add_argument("--ilqr-vmap", action=argparse.BooleanOptionalAction, default=True,
                        help="with --ilqr-batch: --no-ilqr-vmap solves iLQR's row only in the "
                             "groups, without the one-vmap row")  # fmt: skip
    parser.add_argument("--shooting-only", action="store_true",
                        help="multiple shooting's row alone: no iLQR, GPS or trajax")  # fmt: skip
    parser.add_argument("--shooting-batch", type=int, default=1,
                        help="multiple shooting's starts solved together (default 1: one at a "
                             "time, faster on a CPU where the starts' solves differ; 0: all in "
                             "one vmap)")  # fmt: skip
    parser.add_argument(
        "--limits",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="control-limited iLQR on the actuators' ctrlrange (the library's default)",
    )
    parser.add_argument(
        "--unlimited-row", action="store_true", help="also iLQR without control limits"
    )
    parser.add_argument(
        "--initial",
        choices=("zeros", "goal_lqr", "best"),
        default="best",
        help="iLQR's initial actions (trajopt.solve's initial; best: the expert's default)",
    )
    parser.add_argument(
        "--to-the-end-row",
        action="store_true",
        help="with --initial best: also both initial sequences each run to its end (no early "
        "stop of the dearer run), the cheaper kept",
    )
    parser.add_argument(
        "--zeros-row", action="store_true", help="with --initial: also iLQR from zero actions"
    )
    parser.add_argument(
        "--hard", action="store_true", help="pendulum: tilts ±0.15 rad, cart 0.1–0.2 m off"
    )
    parser.add_argument(
        "--tilt-scale",
        type=float,
        default=TILT_SCALE,
        help="the pendulums' hinge angles: gymnasium's reset distribution times this (1: its own)",
    )
    parser.add_argument(
        "--double-weights",
        type=lambda v: tuple(float(w) for w in v.split(",")),
        default=None,
        help="the double pendulum's cost weights q_x,q_theta,q_v,r (default 0.1,1,0.1,0.001)",
    )
    parser.add_argument("--x64", action="store_true", help="float64 (default float32)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import prepare_process

    prepare_process()
    results = {}
    for name in args.models.split(","):
        if name not in TASKS:
            raise SystemExit(f"trajopt_gym: unknown model {name!r}; choose from {list(TASKS)}")
        results[name] = run_task(name, args)
        if args.json:  # written after each model, so a long run keeps what it finished
            args.json.parent.mkdir(parents=True, exist_ok=True)
            summary = {"x64": args.x64, "device": str(jax.devices()[0]), "models": results}
            args.json.write_text(json.dumps(summary, indent=1))
    if args.json:
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
