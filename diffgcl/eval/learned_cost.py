"""How good is a learned cost? Re-optimisation on the frozen cost and the EPIC distance to the
expert cost (DESIGN §8), for costs learned by rGCL on the arm.

* :func:`evaluate_cost` — both, for a batch of learned costs (one per seed);
* :func:`arm_coverage` — the coverage transitions EPIC is measured on;
* :func:`epic_to_expert` — the EPIC distance of one learned cost to ``env.expert_cost``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.costs.network import CostNetwork, CostParams
from diffgcl.types import Array, Env, PRNGKey


def evaluate_cost(config, env, params, seeds) -> dict:
    """Re-optimisation success and EPIC distance of learned costs ``params`` [S, ...]."""
    from diffgcl.algorithms.rgcl import make_network, reoptimise_seeds

    network = make_network(config, env)
    params = jax.tree.map(jnp.asarray, params)
    keys = jnp.stack([jax.random.PRNGKey(100_000 + s) for s in seeds])
    _, _, final = reoptimise_seeds(config, env, network, params, keys)
    reopt_success = np.asarray(final).all(-1)
    coverage = arm_coverage(env, jax.random.PRNGKey(7))
    epic = jax.jit(jax.vmap(lambda p: epic_to_expert(env, network, p, coverage)))(params)
    return {
        "reopt_success": reopt_success.tolist(),
        "reopt_success_rate": float(reopt_success.mean()),
        "epic_distance": float(np.mean(epic)),
        "epic_distance_per_seed": np.asarray(epic).tolist(),
    }


def arm_coverage(env: Env, key: PRNGKey, n: int = 1024):
    """Coverage transitions for EPIC on the arm: joint angles uniform over the box spanned by the
    starts and the target with a 0.5 rad margin, velocities ~ N(0, 1), actions ~ N(0, 2²); the
    successor states come from the simulator. Returns (X, U, X_next) with [n, ·] each."""
    key_q, key_v, key_u = jax.random.split(key, 3)
    X0 = jnp.asarray(env.initial_states())
    dtype = X0.dtype
    target = jnp.asarray(env.target, dtype)
    lo = jnp.minimum(X0[:, :2].min(0), target) - 0.5
    hi = jnp.maximum(X0[:, :2].max(0), target) + 0.5
    q = lo + (hi - lo) * jax.random.uniform(key_q, (n, 2), dtype)
    v = jax.random.normal(key_v, (n, env.dX - 2), dtype)
    X = jnp.concatenate([q, v], axis=-1)
    U = 2.0 * jax.random.normal(key_u, (n, env.dU), dtype)
    X_next = jax.vmap(env.step)(X, U)
    return X, U, X_next


def epic_to_expert(
    env: Env, network: CostNetwork, params: CostParams, coverage, n_canonical: int = 256
) -> Array:
    """EPIC distance (γ = 1) between the learned per-step cost and ``env.expert_cost`` on the
    coverage transitions ``(X, U, X_next)`` (:func:`diffgcl.eval.epic.epic_distance`); the
    canonicalising distributions are the first ``n_canonical`` coverage states, successor states
    and (shifted, so independent of the states) actions."""
    from diffgcl.eval.epic import epic_distance

    X, U, X_next = coverage
    m = min(n_canonical, X.shape[0])
    A = jnp.roll(U, X.shape[0] // 3, axis=0)[:m]
    learned = lambda x, u, x_next: network.cost(params, x, u, 0)
    expert = lambda x, u, x_next: env.expert_cost(x, u, 0)
    return epic_distance(learned, expert, X, U, X_next, X[:m], A, X_next[:m])
