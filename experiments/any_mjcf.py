"""Your own robot, end to end, on models the project does not tune for.

For each model — a planar reacher and a cart-pole written from their usual published
descriptions (``models/reacher.xml``, ``models/cartpole.xml``) — this script plays two parts:

1. **the user's expert**: a hand-written cost and success test (below, user code: nothing in the
   library knows these tasks) and demos of it, written as an npz of MuJoCo arrays (qpos, qvel,
   ctrl per episode, the documented format of :mod:`diffgcl.data.mujoco_demos`): by default
   ``api.expert_demos`` (iLQR from the task's start states, demos sampled about each solution);
   ``--expert gps``: GPS on that cost and demos from the best expert seed's controllers;
2. **the user of diffgcl**: the ≤ 10-line path of :mod:`diffgcl.api` — load the model, load the
   demos, learn the cost with the API's rGCL preset (``mjcf``; ``--preset``) and a global policy
   (MDGPS), roll the policy out, save the run — with the success test and the true cost handed
   in for the report only.

Reported per model: the expert's and the demos' success, rGCL's success (the user's test, noise-
free rollouts of the final controllers from every start state), re-optimisation (GPS from scratch
on the frozen learned cost: success and distance to the demos), the global policy's success from
the demos' start states and from held-out ones, distances to the demos, learned and true costs,
and times (compile and run, on a shared 2-core machine: indicative only).

    python experiments/any_mjcf.py --json runs/any_mjcf.json            # full: 4 seeds
    python experiments/any_mjcf.py --fast --json runs/any_mjcf_fast.json  # 1 seed, short runs
    python experiments/any_mjcf.py --fast --expert-only --json runs/any_mjcf_expert.json  # demos
    python experiments/any_mjcf.py --expert gps ...                     # the GPS expert
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl import api
from diffgcl.algorithms.gps import GPSConfig
from diffgcl.algorithms.gps_runner import run_seeds
from diffgcl.costs.expansion import trajectory_cost
from diffgcl.data.mujoco_demos import save_npz
from diffgcl.runtime import prepare_process, set_cpu_devices
from diffgcl.sim.rollout import rollout_controller, smooth_noise

# ---- the user's tasks (hand-written costs and success tests) ------------------------------------

REACHER_TARGET = (0.1, 0.12)  # the target site of models/reacher.xml
REACHER_LINKS = (0.12, 0.12)  # shoulder to wrist, wrist to fingertip


def reacher_tip(x):
    """Fingertip position of the reacher from its joint angles (forward kinematics by hand)."""
    q1, q12 = x[0], x[0] + x[1]
    l1, l2 = REACHER_LINKS
    return jnp.stack([l1 * jnp.cos(q1) + l2 * jnp.cos(q12), l1 * jnp.sin(q1) + l2 * jnp.sin(q12)])


def reacher_cost(x, u, t):
    """½‖(tip − target)/2 cm‖² + 0.05·½‖dq‖² + 1e-2·½‖u‖²."""
    d = (reacher_tip(x) - jnp.asarray(REACHER_TARGET, x.dtype)) / 0.02
    return 0.5 * d @ d + 0.05 * 0.5 * x[2:] @ x[2:] + 1e-2 * 0.5 * u @ u


def reacher_success(X):
    """The fingertip within 2 cm of the target over the last 10 states."""
    target = jnp.asarray(REACHER_TARGET, X.dtype)
    dist = jax.vmap(lambda x: jnp.linalg.norm(reacher_tip(x) - target))(X[-10:])
    return jnp.all(dist < 0.02)


CARTPOLE_WEIGHTS = (1.0, 4.0, 0.1, 0.1)  # cart position, pole angle, their rates


def cartpole_cost(x, u, t):
    """½ Σ w_i x_i² + 1e-2·½‖u‖² (pole upright at angle 0, cart at the origin)."""
    w = jnp.asarray(CARTPOLE_WEIGHTS, x.dtype)
    return 0.5 * jnp.sum(w * x * x) + 1e-2 * 0.5 * u @ u


def cartpole_success(X):
    """Cart within 10 cm of the origin and pole within 0.05 rad of upright, last 10 states."""
    return jnp.all((jnp.abs(X[-10:, 0]) < 0.1) & (jnp.abs(X[-10:, 1]) < 0.05))


@dataclass(frozen=True)
class Task:
    """One model and the user's task on it."""

    mjcf: str
    starts: tuple  # start states, the env's state coordinates
    held_out: tuple  # start states the demos never saw, for the global policy
    obs: tuple  # what the policy sees (and the cost reads besides the state)
    horizon: int
    dt: float | None
    cost: object
    success: object
    expert: GPSConfig


def tasks() -> dict[str, Task]:
    reacher_q = ((0.0, 0.0), (-1.0, 1.5), (2.5, -1.0), (1.0, 2.0))
    reacher_held_out = ((0.5, 0.5), (-0.5, 1.0), (1.5, 1.5), (2.0, -0.5))
    cart_q = ((0.3, 0.05), (-0.3, -0.05), (0.2, -0.05), (-0.2, 0.05))
    cart_held_out = ((0.1, 0.03), (-0.1, -0.03), (0.25, 0.0), (-0.25, 0.0))
    at_rest = lambda qs: tuple((*q, 0.0, 0.0) for q in qs)
    return {
        "reacher": Task(
            mjcf="reacher.xml",
            starts=at_rest(reacher_q),
            held_out=at_rest(reacher_held_out),
            # The fingertip: demos from different starts end in different arm configurations
            # (elbow up or down) with the fingertip on the target.
            obs=("state", "site:fingertip"),
            horizon=50,
            dt=None,
            cost=reacher_cost,
            success=reacher_success,
            expert=GPSConfig(iterations=20, num_samples=5, kl_step=0.2, init_var=0.1),
        ),
        "cartpole": Task(
            mjcf="cartpole.xml",
            starts=at_rest(cart_q),
            held_out=at_rest(cart_held_out),
            obs=("state",),
            horizon=100,
            dt=0.02,
            cost=cartpole_cost,
            success=cartpole_success,
            expert=GPSConfig(iterations=20, num_samples=5, kl_step=0.2, init_var=0.01),
        ),
    }


# ---- part 1: the user's expert demos ------------------------------------------------------------


def expert_env(task: Task):
    """The task's model with its start states, horizon, hand-written cost and success test: what
    either expert solves."""
    return api.load_model(
        task.mjcf,
        x0=np.asarray(task.starts),
        horizon=task.horizon,
        dt=task.dt,
        cost=task.cost,
        success=task.success,
    )


def expert_demos(task: Task, path: Path, *, seeds, demos_per_condition: int) -> dict:
    """GPS on the hand-written cost; demos sampled from the best seed's controllers, saved as
    an npz of MuJoCo arrays. Returns the expert's summary."""
    env = expert_env(task)
    t0 = time.perf_counter()
    result = run_seeds(task.expert, env, task.cost, seeds, chunk=len(seeds))
    m = result["metrics"]
    final = np.asarray(result["final_success"]).all(-1)
    if not final.any():
        raise RuntimeError(f"{task.mjcf}: no expert seed succeeded")
    final_cost = np.asarray(m.cost[:, -1]).sum(-1)
    best = int(np.argmin(np.where(final, final_cost, np.inf)))
    ctrl = jax.tree.map(lambda a: jnp.asarray(a[best]), result["state"].controller)
    X0 = env.initial_states()
    C = X0.shape[0]
    n = C * demos_per_condition
    condition = jnp.arange(n) % C

    def sample(c, key):
        one = jax.tree.map(lambda a: a[c], ctrl)
        noise = smooth_noise(key, task.horizon, env.dU, task.expert.smooth_sigma)
        traj = rollout_controller(env, one, X0[c], noise)
        return traj.X, traj.U

    key = jax.random.PRNGKey(10_000 + int(seeds[best]))
    X, U = jax.jit(jax.vmap(sample))(condition, jax.random.split(key, n))
    demos = api.rollout_arrays(env, X, U)
    # What the actuators applied: MuJoCo clamps ctrl to ctrlrange, so the clamped values give the
    # same motion, and a log of them is inside the ranges (the loader checks it).
    applied = np.clip(demos.ctrl, env.ctrl_range[:, 0], env.ctrl_range[:, 1])
    save_npz(path, demos.qpos, demos.qvel, applied, condition=np.asarray(condition), dt=env.dt)
    success = np.asarray(jax.vmap(env.success)(X))
    return {
        "gps_seeds": [int(s) for s in seeds],
        "gps_iterations": task.expert.iterations,
        "gps_success": final.tolist(),
        "best_seed": int(seeds[best]),
        "demos": n,
        "demos_per_condition": demos_per_condition,
        "demo_success_rate": float(success.mean()),
        "demo_file": str(path),
        "seconds": time.perf_counter() - t0,
    }


def ilqr_expert_demos(
    task: Task, path: Path, *, demos_per_condition: int, noise_var: float = 0.01
) -> dict:
    """The expert path of a user with a cost and no demos: ``api.expert_demos`` (iLQR from each
    start state, demos sampled about each solution) with its defaults, saved as the npz."""
    env = expert_env(task)
    t0 = time.perf_counter()
    demos = api.expert_demos(env, per_start=demos_per_condition, noise_var=noise_var, path=path)
    X = jnp.asarray(demos.X)
    success = np.asarray(jax.vmap(env.success)(X))
    true = jax.vmap(lambda x, u: trajectory_cost(task.cost, x, u))(X, jnp.asarray(demos.U))
    first = {e["condition"]: e for e in reversed(demos.episodes)}
    return {
        "expert": "ilqr",
        "noise_var": noise_var,
        "solution_success": [bool(first[c]["solution_success"]) for c in sorted(first)],
        "solution_cost": [float(first[c]["ilqr_cost"]) for c in sorted(first)],
        "ilqr_status": [first[c]["ilqr_status"] for c in sorted(first)],
        "demos": int(demos.num_episodes),
        "demos_per_condition": demos_per_condition,
        "demo_success_rate": float(success.mean()),
        "demo_true_cost": float(np.mean(np.asarray(true))),
        "demo_file": str(path),
        "seconds": time.perf_counter() - t0,
    }


# ---- part 2: the user of diffgcl (the ten lines of the API) -------------------------------------


def learn_from_demos(
    task: Task, demo_file: Path, out: Path, *, seeds, iterations, preset="mjcf", overrides=()
) -> dict:
    env = api.load_model(task.mjcf, dt=task.dt, obs=task.obs, success=task.success, cost=task.cost)
    demos = api.load_demos(demo_file, env)
    run = api.learn(
        env,
        demos,
        preset=preset,
        seeds=seeds,
        iterations=iterations,
        overrides=overrides,
        policy=True,
        progress=False,
    )
    report = run.report()
    run.save(out)
    # The user's own check of the global policy on start states the demos never saw.
    X, _ = run.policy_rollouts(np.asarray(task.held_out))
    success = np.asarray(jax.vmap(jax.vmap(run.env.success))(X))
    report["policy"]["held_out_starts"] = np.asarray(task.held_out).tolist()
    report["policy"]["held_out_success"] = success.tolist()
    report["policy"]["held_out_success_rate"] = float(success.mean())
    return report


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--fast", action="store_true", help="1 rGCL seed, short runs")
    parser.add_argument("--models", default="reacher,cartpole", help="comma-separated")
    parser.add_argument("--seeds", type=int, default=None, help="rGCL seeds (default 4; fast 1)")
    parser.add_argument(
        "--first-seed", type=int, default=0, help="rGCL seeds start here (held-out seeds: 4)"
    )
    parser.add_argument("--iterations", type=int, default=None, help="rGCL iterations")
    parser.add_argument("--out", type=Path, default=Path("runs/any_mjcf"))
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--x64", action="store_true")
    parser.add_argument(
        "--expert",
        choices=("ilqr", "gps"),
        default="ilqr",
        help="the user's expert: api.expert_demos (iLQR, default) or GPS on the cost",
    )
    parser.add_argument("--expert-only", action="store_true", help="stop after the demos")
    parser.add_argument("--preset", default="mjcf", help="rGCL preset (api.learn's default)")
    parser.add_argument(
        "--set", action="append", default=[], help="rGCL config edit, e.g. gcl.n_steps=20"
    )
    parser.add_argument(
        "--demo-noise-var", type=float, default=0.01, help="iLQR expert: demos' action variance"
    )
    args = parser.parse_args(argv)
    set_cpu_devices()
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    prepare_process()
    n_seeds = args.seeds or (1 if args.fast else 4)
    iterations = args.iterations or (10 if args.fast else None)
    expert_seeds = list(range(2 if args.fast else 4))
    results = {}
    for name in args.models.split(","):
        task = tasks()[name]
        print(f"== {name}: expert {args.expert} on the hand-written cost ({task.mjcf})")
        per_condition = 3 if args.fast else 5
        if args.expert == "ilqr":
            expert = ilqr_expert_demos(
                task,
                args.out / name / "demos.npz",
                demos_per_condition=per_condition,
                noise_var=args.demo_noise_var,
            )
            solved = expert["solution_success"]
        else:
            expert = expert_demos(
                task,
                args.out / name / "demos.npz",
                seeds=expert_seeds,
                demos_per_condition=per_condition,
            )
            solved = expert["gps_success"]
        print(
            f"   expert success {solved}, demos {expert['demos']} "
            f"(success {expert['demo_success_rate']:.2f}), {expert['seconds']:.0f} s"
        )
        if args.expert_only:
            results[name] = {"expert": expert}
            continue
        seeds = list(range(args.first_seed, args.first_seed + n_seeds))
        print(f"== {name}: rGCL from the demos, seeds {seeds[0]}..{seeds[-1]}")
        t0 = time.perf_counter()
        report = learn_from_demos(
            task,
            args.out / name / "demos.npz",
            args.out / name / "run",
            seeds=seeds,
            iterations=iterations,
            preset=args.preset,
            overrides=args.set,
        )
        seconds = time.perf_counter() - t0
        reopt, policy = report["reoptimisation"], report["policy"]
        print(
            f"   success {report['success_rate']:.2f}, re-optimisation "
            f"{reopt['success_rate']:.2f}, policy {policy['success_rate']:.2f} (held-out starts "
            f"{policy['held_out_success_rate']:.2f}), demo distance "
            f"{report['mean_demo_distance']:.2f} (re-opt {reopt['mean_demo_distance']:.2f}), "
            f"{seconds:.0f} s"
        )
        results[name] = {"expert": expert, "rgcl": report, "seconds": seconds}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        summary = {
            "fast": args.fast,
            "x64": args.x64,
            "expert": args.expert,
            "preset": args.preset,
            "seeds": list(range(args.first_seed, args.first_seed + n_seeds)),
            "overrides": args.set,
            "models": results,
        }
        args.json.write_text(json.dumps(summary, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
