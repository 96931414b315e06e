"""Hand-built linear-quadratic problems shared by the control tests (float64, NumPy inputs)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from diffgcl.types import (
    InitialStateDistribution,
    LinearDynamics,
    QuadraticCost,
    make_controller,
)


def random_problem(seed: int = 0, T: int = 8, dX: int = 3, dU: int = 2):
    """Random stable dynamics, a convex cost about the origin with cross terms, a random
    previous controller and an initial state distribution."""
    rng = np.random.default_rng(seed)
    A = np.eye(dX) + 0.1 * rng.standard_normal((T, dX, dX))
    B = 0.3 * rng.standard_normal((T, dX, dU))
    c = 0.05 * rng.standard_normal((T, dX))
    G = 0.05 * rng.standard_normal((T, dX, dX))
    dyn_cov = G @ np.swapaxes(G, -1, -2) + 1e-4 * np.eye(dX)

    H = np.empty((T + 1, dX + dU, dX + dU))
    for t in range(T + 1):
        M = rng.standard_normal((dX + dU, dX + dU))
        H[t] = M @ M.T / (dX + dU) + 0.5 * np.eye(dX + dU)
    g = rng.standard_normal((T + 1, dX + dU))
    H[T, dX:, :] = 0.0
    H[T, :, dX:] = 0.0
    g[T, dX:] = 0.0
    cost = QuadraticCost(
        l=jnp.asarray(rng.standard_normal(T + 1)),
        l_x=jnp.asarray(g[:, :dX]),
        l_u=jnp.asarray(g[:, dX:]),
        l_xx=jnp.asarray(H[:, :dX, :dX]),
        l_uu=jnp.asarray(H[:, dX:, dX:]),
        l_ux=jnp.asarray(H[:, dX:, :dX]),
    )
    dynamics = LinearDynamics(
        A=jnp.asarray(A), B=jnp.asarray(B), c=jnp.asarray(c), cov=jnp.asarray(dyn_cov)
    )
    S = 0.3 * rng.standard_normal((T, dU, dU))
    prev = make_controller(
        jnp.asarray(0.2 * rng.standard_normal((T, dU, dX))),
        jnp.asarray(0.2 * rng.standard_normal((T, dU))),
        jnp.asarray(S @ np.swapaxes(S, -1, -2) + 0.2 * np.eye(dU)),
    )
    x0 = InitialStateDistribution(
        mean=jnp.asarray(rng.standard_normal(dX)), cov=jnp.asarray(0.01 * np.eye(dX))
    )
    return dynamics, cost, prev, x0
