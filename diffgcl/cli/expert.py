"""``diffgcl demos OUT.npz --mjcf MODEL.xml --cost SPEC``: expert demonstrations of your own model
from a cost, by iLQR (:func:`diffgcl.api.expert_demos`).

The cost, ``--cost``:

* ``quadratic:W`` — ``½ Σ_i W_i (x_i − g_i)² + ½ w_u ‖u‖²`` in the env's state ``x = [xq, qvel,
  act]`` (``dX = 2·nv + na``; hinge and slide joints as in ``qpos``) and its actions (each
  actuator's control divided by its largest ``|ctrlrange|``): ``W`` is ``dX`` comma-separated
  weights or one weight for all; options after ``;``: ``u=w_u`` (default 0.01) and
  ``goal=g_1,...,g_dX`` (default: the model's ``qpos0`` at rest). E.g.
  ``quadratic:1,4,0.1,0.1;u=0.01``;
* ``MODULE:FUNCTION`` or ``FILE.py:FUNCTION`` — your ``c(x, u, t) -> scalar``, a JAX function
  (t = 0 .. T−1 running, t = T terminal with u = 0).

It runs in float64: in float32 the derivatives through MuJoCo's iterative constraint solver
(joint limits, contacts) are too noisy for iLQR's line search (gymnasium's reacher: 2 of 8 starts
stuck at the elbow's limit in float32, none in float64). The model is loaded with
``lapack_free=True`` (:func:`diffgcl.envs.mjcf_env.make_mjcf_env`).

``--success`` takes a ``MODULE:FUNCTION`` / ``FILE.py:FUNCTION`` ``success(X: [T+1, dX]) ->
bool``, for the report. Start states: ``--x0 "x_1,...,x_dX;x_1,..."`` (states separated by
``;``), or ``--starts N --spread S`` about the model's keyframe / ``qpos0``.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
from pathlib import Path

import numpy as np


class SpecError(ValueError):
    """A command-line specification that cannot be used; the message is one line."""


def load_function(spec: str, what: str):
    """``MODULE:FUNCTION`` or ``FILE.py:FUNCTION`` -> the function."""
    target, sep, name = spec.rpartition(":")
    if not sep or not target or not name:
        raise SpecError(f"{what} {spec!r}: use MODULE:FUNCTION or FILE.py:FUNCTION")
    if target.endswith(".py"):
        path = Path(target)
        if not path.is_file():
            raise SpecError(f"{what} {spec!r}: no file {path}")
        module_spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(module_spec)
        try:
            module_spec.loader.exec_module(module)
        except Exception as err:  # the user's file: report, do not trace
            raise SpecError(f"{what} {spec!r}: {path} fails to import: {err}") from None
    else:
        try:
            module = importlib.import_module(target)
        except ImportError as err:
            raise SpecError(f"{what} {spec!r}: cannot import {target}: {err}") from None
    fn = getattr(module, name, None)
    if not callable(fn):
        raise SpecError(f"{what} {spec!r}: {target} has no function {name!r}")
    return fn


def _numbers(text: str, what: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise SpecError(f"{what}: {text!r} is not a comma-separated list of numbers") from None


def quadratic_cost(spec: str, env):
    """The cost of a ``quadratic:W[;u=w][;goal=g]`` spec (module docstring) for ``env``."""
    from diffgcl.costs.analytic import ActionCost, StateCost, WeightedSum

    body = spec.partition(":")[2]
    parts = [p.strip() for p in body.split(";") if p.strip()]
    if not parts:
        raise SpecError(f"--cost {spec!r}: give the state weights, e.g. quadratic:1,4,0.1,0.1")
    weights = _numbers(parts[0], f"--cost {spec!r}: state weights")
    dX = env.dX
    if len(weights) == 1:
        weights = weights * dX
    if len(weights) != dX:
        raise SpecError(f"--cost {spec!r}: {len(weights)} state weights for a state of {dX} "
                        f"(x = [{env.nv} positions, {env.nv} velocities"
                        f"{f', {env.na} activations' if env.na else ''}])")  # fmt: skip
    w_u, goal = 0.01, None
    for option in parts[1:]:
        key, eq, value = option.partition("=")
        if key.strip() == "u" and eq:
            (w_u,) = _numbers(value, f"--cost {spec!r}: u")[:1] or [0.01]
        elif key.strip() == "goal" and eq:
            goal = _numbers(value, f"--cost {spec!r}: goal")
            if len(goal) != dX:
                raise SpecError(f"--cost {spec!r}: goal has {len(goal)} numbers, the state {dX}")
        else:
            raise SpecError(f"--cost {spec!r}: unknown option {option!r}; use u=W or goal=G,...")
    if goal is None:
        qpos0 = np.asarray(env.model.qpos0)
        goal = np.asarray(env.state_from_mujoco(qpos0, np.zeros(env.nv), np.zeros(env.na)))
    if any(w < 0 for w in weights) or w_u <= 0:
        raise SpecError(f"--cost {spec!r}: weights must be >= 0 and the action weight > 0")
    state = StateCost(tuple(range(dX)), tuple(float(g) for g in goal), env.horizon,
                      wp=tuple(weights))  # fmt: skip
    action = ActionCost(tuple([float(w_u)] * env.dU))
    return WeightedSum((state, action), (1.0, 1.0))


def parse_cost(spec: str, env):
    if spec.startswith("quadratic:") or spec == "quadratic":
        return quadratic_cost(spec, env)
    return load_function(spec, "--cost")


def parse_states(text: str, dX: int) -> np.ndarray:
    rows = [r for r in text.split(";") if r.strip()]
    states = [_numbers(r, "--x0") for r in rows]
    bad = [i for i, s in enumerate(states) if len(s) != dX]
    if not states or bad:
        i = bad[0] if bad else 0
        got = len(states[i]) if states else 0
        raise SpecError(f"--x0: state {i} has {got} numbers; the model's state has {dX}")
    return np.asarray(states)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``--mjcf`` options of ``diffgcl demos``."""
    g = parser.add_argument_group("your own model (--mjcf): expert demos by iLQR on a cost")
    g.add_argument("--mjcf", default=None, help="MJCF file; OUT is then the .npz to write")
    g.add_argument("--cost", default=None, help="quadratic:W[;u=..][;goal=..] or MODULE:FUNCTION")
    g.add_argument("--success", default=None, help="MODULE:FUNCTION success(X) -> bool")
    g.add_argument("--x0", default=None, help='start states "x1,x2,...;x1,x2,..."')
    g.add_argument("--starts", type=int, default=4, help="start states about qpos0 (no --x0)")
    g.add_argument("--spread", type=float, default=0.1, help="their spread in positions")
    g.add_argument("--horizon", type=int, default=100, help="control steps per episode")
    g.add_argument("--dt", type=float, default=None, help="control period (default timestep)")
    g.add_argument("--per-start", type=int, default=5, help="demos per start state")
    g.add_argument("--noise-var", type=float, default=0.01, help="demos' mean action variance")
    g.add_argument("--temperature", type=float, default=None, help="instead: Σ = T·(Q_uu)⁻¹")
    g.add_argument("--gps-iterations", type=int, default=0, help="GPS refinement of iLQR")
    g.add_argument(
        "--initial",
        choices=("zeros", "goal_lqr", "best"),
        default=None,
        help="iLQR's initial actions: zeros, the goal's LQR (for balancing), or (the default) "
        "the better of both",
    )
    g.add_argument(
        "--shooting",
        action="store_true",
        help="also multiple shooting with the joints' ranges kept, per start the cheaper of it "
        "and iLQR (for an unstable system on a short rail; another compile)",
    )


def mjcf_demos_command(args) -> int:
    """Write the demos; exit 0 when every start's solution passes the success test (or there
    is none), 1 otherwise."""
    from diffgcl import api
    from diffgcl.sim.mjcf import MJCFError

    try:
        if args.cost is None:
            raise SpecError("demos --mjcf: give the cost with --cost (quadratic:W or MODULE:FN)")
        if args.out.suffix != ".npz":
            raise SpecError(f"demos --mjcf: OUT must be an .npz file, got {args.out}")
        if args.out.exists() and not args.out.is_file():
            raise SpecError(f"demos --mjcf: {args.out} exists and is not a file")
        success = None if args.success is None else load_function(args.success, "--success")
        env = api.load_model(
            args.mjcf,
            lapack_free=True,
            horizon=args.horizon,
            dt=args.dt,
            success=success,
            conditions=args.starts,
            spread=args.spread,
            seed=args.seed,
        )
        if args.x0 is not None:
            env = env.with_conditions(parse_states(args.x0, env.dX))
        cost = parse_cost(args.cost, env)
    except (SpecError, MJCFError) as err:
        raise SystemExit(f"diffgcl: {err}") from None
    env = env.with_task(cost=cost)
    C = int(env.initial_states().shape[0])
    print(f"iLQR expert on {env.mjcf_path}: {C} start states, T = {env.horizon}, dt {env.dt:g} s")
    demos = api.expert_demos(
        env,
        per_start=args.per_start,
        noise_var=args.noise_var,
        temperature=args.temperature,
        gps_iterations=args.gps_iterations,
        seed=args.seed,
        path=args.out,
        initial=args.initial,
        shooting=args.shooting,
    )
    first = {e["condition"]: e for e in reversed(demos.episodes)}
    for c in range(C):
        e = first[c]
        ok = "" if "solution_success" not in e else f", success {e['solution_success']}"
        print(f"  start {c}: {e['ilqr_status']}, cost {e['ilqr_cost']:.6g}{ok}")
    print(f"{demos.num_episodes} demos ({args.per_start} per start) in {args.out}")
    return 0 if all(e.get("solution_success", True) for e in demos.episodes) else 1
