"""Expert demonstrations from trained GPS controllers (the seed's 10 demos from a GPS expert).

The demos are samples of the trained linear-Gaussian controllers *with their stochasticity*
(``u = Kx + k + chol(Σ)ε``, the same sampling process as GPS's own samples), spread round-robin
over the conditions, and stored as a :class:`diffgcl.data.demos.DemoSet` — the format the GCL
code reads (``demos.npz`` with X [N, T+1, dX], U [N, T, dU], O [N, T+1, dO], mask [N, T+1], and
``meta.json`` with one dict per episode; see :mod:`diffgcl.data.demos`). Each episode's metadata
records ``source="gps-expert"``, its condition, the sample index, the seed, whether it succeeds
and its true cost.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.costs.expansion import trajectory_cost
from diffgcl.data.demos import DemoSet
from diffgcl.types import Array, CostFn, Env, LinearGaussianController, PRNGKey, Trajectory


def sample_expert(
    env: Env,
    controllers: LinearGaussianController,
    x0: Array,
    key: PRNGKey,
    num_demos: int = 10,
    *,
    smooth_sigma: float | None = 2.0,
) -> tuple[Trajectory, Array]:
    """``num_demos`` stochastic rollouts of the controllers, round-robin over the C conditions.

    controllers: fields [C, T, ...]; x0: [C, dX]. Returns (Trajectory with X [num_demos, T+1, dX],
    U [num_demos, T, dU], O [num_demos, T+1, dO]; condition index [num_demos]).
    """
    from diffgcl.sim.rollout import rollout_controller, smooth_noise

    C = x0.shape[0]
    T = controllers.K.shape[-3]
    condition = jnp.arange(num_demos) % C
    keys = jax.random.split(key, num_demos)

    def one(c, k):
        ctrl = jax.tree.map(lambda a: a[c], controllers)
        noise = smooth_noise(k, T, env.dU, smooth_sigma)
        return rollout_controller(env, ctrl, x0[c], noise, with_obs=True)

    return jax.vmap(one)(condition, keys), condition


def make_demo_set(
    env: Env,
    trajectories: Trajectory,
    condition: Array,
    *,
    cost: CostFn | None = None,
    seed: int | None = None,
) -> DemoSet:
    """Host-side: a validated DemoSet from batched trajectories (see module docstring)."""
    X = np.asarray(trajectories.X)
    U = np.asarray(trajectories.U)
    O = np.asarray(trajectories.O)
    success = np.asarray(jax.vmap(env.success)(trajectories.X))
    costs = (
        np.asarray(
            jax.vmap(lambda x, u: trajectory_cost(cost, x, u))(trajectories.X, trajectories.U)
        )
        if cost is not None
        else np.full(X.shape[0], np.nan)
    )
    episodes = tuple(
        {
            "source": "gps-expert",
            "condition": int(condition[i]),
            "sample": i,
            "seed": seed,
            "success": bool(success[i]),
            "cost": float(costs[i]),
        }
        for i in range(X.shape[0])
    )
    return DemoSet(
        X=X,
        U=U,
        O=O,
        mask=np.ones(X.shape[:2], dtype=np.float32),
        dt=float(f"{float(env.dt):.7g}"),  # a float32 timestep stored as its decimal value
        env=env.name,
        episodes=episodes,
    )


def write_expert_demos(
    directory,
    env: Env,
    controllers: LinearGaussianController,
    key: PRNGKey,
    num_demos: int = 10,
    *,
    x0: Array | None = None,
    smooth_sigma: float | None = 2.0,
    cost: CostFn | None = None,
    seed: int | None = None,
) -> DemoSet:
    """Sample demos from trained controllers (fields [C, T, ...]) and save them to ``directory``."""
    x0 = jnp.asarray(env.initial_states() if x0 is None else x0)
    trajectories, condition = jax.jit(
        lambda k: sample_expert(env, controllers, x0, k, num_demos, smooth_sigma=smooth_sigma)
    )(key)
    demos = make_demo_set(env, trajectories, np.asarray(condition), cost=cost, seed=seed)
    demos.save(directory)
    return demos


EXPERT_ITERATIONS = 30
EXPERT_SEEDS = 8


def task_fingerprint(env: Env) -> dict:
    """What defines an env's task, as JSON-ready values: its name, the SHA-256 of its MJCF file,
    the start states, horizon and time step, and every task setting the env carries (the arm's
    target, torque cap, action weight, success tolerance), plus the float precision. Two envs with
    the same fingerprint pose the same control problem."""
    import hashlib
    from pathlib import Path

    spec: dict = {
        "env": env.name,
        "x0": np.asarray(env.initial_states(), dtype=float).round(12).tolist(),
        "horizon": int(env.horizon),
        "dt": float(f"{float(env.dt):.7g}"),
        "dtype": str(jnp.asarray(env.initial_states()).dtype),
    }
    path = Path(env.mjcf_path) if getattr(env, "mjcf_path", "") else None
    spec["mjcf_sha256"] = (
        hashlib.sha256(path.read_bytes()).hexdigest() if path and path.is_file() else None
    )
    for name in ("target", "torque_limit", "action_weight", "success_tolerance"):
        if hasattr(env, name):
            value = np.asarray(getattr(env, name), dtype=float).round(12)
            spec[name] = value.tolist()
    for name in ("success_hold_steps",):
        if hasattr(env, name):
            spec[name] = int(getattr(env, name))
    return spec


def best_expert(metrics, final_success) -> int | None:
    """The run (index into the leading seed axis of GPS ``metrics`` [S, iterations, C]) whose
    final controllers succeed on every condition (``final_success: [S, C]``, their noise-free
    rollouts) with the lowest final true cost; None when no run succeeds."""
    final = np.all(np.asarray(final_success), axis=-1)
    if not final.any():
        return None
    final_cost = np.asarray(metrics.cost)[:, -1].sum(axis=-1)
    return int(np.argmin(np.where(final, final_cost, np.inf)))


def builtin_demos(env=None, *, num_demos: int = 10, seed: int = 0, verbose: bool = True):
    """Expert demos for ``env``'s task (a :class:`diffgcl.data.demos.DemoSet`; default: the arm),
    generated once and cached under a key of the task and the expert settings.

    The expert is GPS on the env's expert cost (the seed's "10 demos from a GPS expert"),
    ``EXPERT_SEEDS`` seeds of ``EXPERT_ITERATIONS`` iterations; the succeeding seed with the
    lowest final true cost gives the demos (its controller sampled with its own noise). 30 rather
    than GPS's 10 iterations: at 10 the arm's expert is not converged (true cost 95.3–97.2 vs
    94.5–95.1 at 30) and its demos still drift 0.04–0.07 rad about the target over the last 10
    steps (0.01–0.04 at 30); every expert overshoots joint 1 by 0.12–0.23 rad around step 70 (the
    torque cap), and the learned cost sees that too.

    The cache folder is ``$DIFFGCL_CACHE/demos/<env>-gps-expert-<n>-it<iterations>-seed<seed>-
    <hash>``, the hash over :func:`task_fingerprint` (MJCF file, start states, target, horizon,
    ...) and the expert's settings, which ``task.json`` in the folder spells out: an arm with
    another start or target gets its own demos, never another task's."""
    import hashlib
    import json

    from diffgcl.algorithms.gps import GPSConfig
    from diffgcl.data.demos import DemoSet
    from diffgcl.envs import make_env
    from diffgcl.runtime import cache_root

    env = make_env("arm") if env is None else env
    config = GPSConfig(iterations=EXPERT_ITERATIONS)
    key = {
        "task": task_fingerprint(env),
        "expert": {
            "gps": dataclasses.asdict(config),
            "seeds": list(range(seed, seed + EXPERT_SEEDS)),
            "num_demos": num_demos,
            "demo_key": "PRNGKey(10000 + seed)",
        },
    }
    text = json.dumps(key, sort_keys=True)
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    name = f"{env.name}-gps-expert-{num_demos}-it{EXPERT_ITERATIONS}-seed{seed}-{digest}"
    folder = cache_root() / "demos" / name
    if (folder / "demos.npz").is_file():
        return DemoSet.load(folder)
    from diffgcl.algorithms.gps_runner import run_seeds

    if verbose:
        print(f"generating expert demos (GPS on the expert cost) for this task into {folder}")
    seeds = key["expert"]["seeds"]
    result = run_seeds(config, env, env.expert_cost, seeds, chunk=EXPERT_SEEDS)
    i = best_expert(result["metrics"], result["final_success"])
    if i is None:
        raise RuntimeError(
            f"builtin_demos: no GPS expert seed of {seeds} succeeded on this task "
            f"({json.dumps(key['task'])}); is it feasible?"
        )
    controllers = jax.tree.map(lambda a: jnp.asarray(a[i]), result["state"].controller)
    demos = write_expert_demos(
        folder,
        env,
        controllers,
        jax.random.PRNGKey(10_000 + seeds[i]),
        num_demos,
        cost=env.expert_cost,
        seed=seeds[i],
    )
    (folder / "task.json").write_text(json.dumps(key, indent=1, sort_keys=True))
    return demos
