"""EPIC distance: zero on equivalent costs (scale, shift, potential shaping), one on negation."""

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.eval.epic import (
    canonical_costs,
    epic_distance,
    pearson_distance,
    step_cost_as_transition_cost,
)

dX, dU, n, m = 3, 2, 300, 200


def quadratic(key):
    key_q, key_r = jax.random.split(key)
    M = jax.random.normal(key_q, (dX, dX))
    R = jax.random.normal(key_r, (dU, dU))
    return lambda x, u: x @ M.T @ M @ x + u @ R.T @ R @ u + 0.3 * x[0] * u[1]


def coverage(key):
    keys = jax.random.split(key, 6)
    X = jax.random.normal(keys[0], (n, dX))
    U = jax.random.normal(keys[1], (n, dU))
    X_next = X + 0.1 * jnp.concatenate([U, U[:, :1]], axis=1)
    S = jax.random.normal(keys[2], (m, dX))
    A = jax.random.normal(keys[3], (m, dU))
    S_next = jax.random.normal(keys[4], (m, dX))
    return X, U, X_next, S, A, S_next


def test_pearson_distance_range():
    a = jax.random.normal(jax.random.key(0), (100,))
    np.testing.assert_allclose(pearson_distance(a, 3 * a + 2), 0.0, atol=1e-7)
    np.testing.assert_allclose(pearson_distance(a, -a), 1.0, atol=1e-7)
    b = jax.random.normal(jax.random.key(1), (100,))
    assert 0.5 < pearson_distance(a, b) < 0.9


def test_epic_zero_for_equivalent_costs_and_positive_otherwise():
    data = coverage(jax.random.key(0))
    c = quadratic(jax.random.key(1))
    R = step_cost_as_transition_cost(c)
    phi = lambda x: jnp.sin(x).sum() + x @ x
    gamma = 0.9

    def shaped(x, u, x_next):
        return 2.5 * c(x, u) + 4.0 + gamma * phi(x_next) - phi(x)

    epic = jax.jit(epic_distance, static_argnums=(0, 1, 8))
    np.testing.assert_allclose(epic(R, shaped, *data, gamma), 0.0, atol=1e-6)
    other = step_cost_as_transition_cost(quadratic(jax.random.key(2)))
    assert epic(R, other, *data, gamma) > 0.1
    negated = lambda x, u, x_next: -c(x, u)
    np.testing.assert_allclose(epic(R, negated, *data, gamma), 1.0, atol=1e-6)


def test_canonical_cost_of_state_action_cost_by_hand():
    """For R(x, u, x') = c(x, u): C = c(x, u) + γ E_A c(x', A) − E_A c(x, A) − γ E c(S, A)."""
    X, U, X_next, S, A, S_next = coverage(jax.random.key(3))
    c = quadratic(jax.random.key(4))
    gamma = 1.0
    got = canonical_costs(step_cost_as_transition_cost(c), X[:5], U[:5], X_next[:5], S, A, S_next)
    on_pairs = jax.jit(jax.vmap(c))
    offset = on_pairs(S, A).mean()
    for i in range(5):
        here = on_pairs(jnp.broadcast_to(X[i], S.shape), A).mean()
        there = on_pairs(jnp.broadcast_to(X_next[i], S.shape), A).mean()
        want = c(X[i], U[i]) + gamma * there - here - gamma * offset
        np.testing.assert_allclose(got[i], want, rtol=1e-9)
