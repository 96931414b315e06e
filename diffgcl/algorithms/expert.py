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


BUILTIN_DEMOS = "arm-gps-expert-10-it30"
EXPERT_ITERATIONS = 30


def builtin_demos(env=None, *, num_demos: int = 10, seed: int = 0, verbose: bool = True):
    """The built-in arm demos (a :class:`diffgcl.data.demos.DemoSet`), generated once and cached.

    The expert is GPS on the expert cost (the seed's "10 demos from a GPS expert"), 8 seeds of
    ``EXPERT_ITERATIONS`` iterations; the succeeding seed with the lowest final true cost gives the
    demos (its controller sampled with its own noise). 30 rather than GPS's 10 iterations: at 10
    the expert is not converged (true cost 95.3–97.2 vs 94.5–95.1 at 30) and its demos still
    drift 0.04–0.07 rad about the target over the last 10 steps (0.01–0.04 at 30); every expert
    overshoots joint 1 by 0.12–0.23 rad around step 70 (the torque cap), and the learned cost
    sees that too."""
    from diffgcl.data.demos import DemoSet
    from diffgcl.runtime import cache_root

    folder = cache_root() / "demos" / f"{BUILTIN_DEMOS}-seed{seed}"
    if (folder / "demos.npz").is_file():
        return DemoSet.load(folder)
    from diffgcl.algorithms.expert import write_expert_demos
    from diffgcl.algorithms.gps import GPSConfig
    from diffgcl.algorithms.gps_runner import run_seeds
    from diffgcl.envs import make_env

    env = make_env("arm") if env is None else env
    if verbose:
        print(f"generating the built-in expert demos (GPS on the expert cost) into {folder}")
    seeds = list(range(seed, seed + 8))
    config = GPSConfig(iterations=EXPERT_ITERATIONS)
    result = run_seeds(config, env, env.expert_cost, seeds, chunk=8)
    final = np.all(result["metrics"].success[:, -1], axis=-1)
    if not final.any():
        raise RuntimeError("builtin_demos: no GPS expert seed succeeded")
    final_cost = np.asarray(result["metrics"].cost[:, -1]).sum(axis=-1)
    i = int(np.argmin(np.where(final, final_cost, np.inf)))
    controllers = jax.tree.map(lambda a: jnp.asarray(a[i]), result["state"].controller)
    return write_expert_demos(
        folder,
        env,
        controllers,
        jax.random.PRNGKey(10_000 + seeds[i]),
        num_demos,
        cost=env.expert_cost,
        seed=seeds[i],
    )
