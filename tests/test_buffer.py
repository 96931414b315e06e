"""The sample ring buffer: wrap-around, eviction of a controller's samples, masks, densities."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from diffgcl.costs.buffer import (
    action_log_densities,
    action_log_density,
    buffer_add,
    controller_log_densities,
    init_buffer,
    samples_per_controller,
    stored_log_densities,
)
from diffgcl.types import make_controller

T, dX, dU = 3, 2, 2
add = jax.jit(buffer_add)


def controller(k: float):
    K = jnp.broadcast_to(jnp.array([[0.5, 0.0], [0.1, -0.2]]), (T, dU, dX))
    cov = jnp.broadcast_to(jnp.array([[0.5, 0.1], [0.1, 0.3]]), (T, dU, dU))
    return make_controller(K, jnp.full((T, dU), k), cov)


def batch(value: float, n: int):
    return jnp.full((n, T + 1, dX), value), jnp.full((n, T, dU), value)


def test_empty_buffer_masks_everything():
    buffer = init_buffer(6, 3, T, dX, dU, jnp.float64)
    assert not buffer.valid.any() and not buffer.controller_valid.any()
    log_q = controller_log_densities(buffer, jnp.zeros((2, T + 1, dX)), jnp.zeros((2, T, dU)))
    assert log_q.shape == (2, 3)
    assert jnp.all(log_q == -jnp.inf)


def test_ring_wraps_and_evicts_the_overwritten_controllers_samples():
    buffer = init_buffer(6, 3, T, dX, dU, jnp.float64)
    for i in range(3):  # fills exactly: 3 controllers × 2 samples
        buffer = add(buffer, controller(float(i)), *batch(float(i), 2))
    assert buffer.valid.all() and buffer.controller_valid.all()
    np.testing.assert_array_equal(samples_per_controller(buffer), [2, 2, 2])
    # A 4th controller reuses slot 0; its 2 samples overwrite sample slots 0 and 1.
    buffer = add(buffer, controller(3.0), *batch(3.0, 2))
    np.testing.assert_array_equal(buffer.source, [0, 0, 1, 1, 2, 2])
    np.testing.assert_array_equal(buffer.X[:2, 0, 0], [3.0, 3.0])
    np.testing.assert_allclose(buffer.controllers.k[0, 0, 0], 3.0)
    # Uneven batch: 3 samples from controller slot 1 wrap around; slot 1's old samples go away.
    buffer = add(buffer, controller(4.0), *batch(4.0, 3))
    np.testing.assert_array_equal(buffer.X[:, 0, 0], [3.0, 3.0, 4.0, 4.0, 4.0, 2.0])
    np.testing.assert_array_equal(buffer.source, [0, 0, 1, 1, 1, 2])
    np.testing.assert_array_equal(samples_per_controller(buffer), [2, 3, 1])
    assert int(buffer.next_sample) == 5 and int(buffer.next_controller) == 2
    assert add._cache_size() <= 3  # one per batch size (and mask) seen in this module


def test_density_table_equals_recomputation_through_wraps_and_evictions():
    """buffer_add fills only the new column and rows of the [S, Kc] density table; after wraps,
    uneven batches, masks and evictions it must equal recomputing every pair."""
    buffer = init_buffer(7, 3, T, dX, dU, jnp.float64)
    keys = jax.random.split(jax.random.key(3), 12)
    for i, n in enumerate([2, 3, 1, 3, 2, 2, 3, 1, 2, 3, 2, 1]):
        kx, ku, kc = jax.random.split(keys[i], 3)
        X = jax.random.normal(kx, (n, T + 1, dX))
        U = jax.random.normal(ku, (n, T, dU))
        mask = jax.random.bernoulli(kc, 0.8, (n,))
        ctrl = controller(0.3 * i - 1.0)
        ctrl = ctrl.replace(K=ctrl.K * (1.0 + 0.2 * i))
        buffer = add(buffer, make_controller(ctrl.K, ctrl.k, ctrl.cov), X, U, mask=mask)
        ref = controller_log_densities(buffer, buffer.X, buffer.U)
        table = stored_log_densities(buffer)
        rows = np.asarray(buffer.valid)
        assert rows.any()
        np.testing.assert_allclose(table[rows], ref[rows], rtol=1e-12)
        assert np.all(np.isneginf(table[:, ~np.asarray(buffer.controller_valid)]))


def test_eviction_without_overwriting_invalidates():
    """Samples of an evicted controller that were not overwritten are masked out."""
    buffer = init_buffer(8, 2, T, dX, dU, jnp.float64)
    buffer = add(buffer, controller(0.0), *batch(0.0, 3))
    buffer = add(buffer, controller(1.0), *batch(1.0, 1))
    buffer = add(buffer, controller(2.0), *batch(2.0, 1))  # reuses slot 0
    np.testing.assert_array_equal(buffer.valid, [False, False, False, True, True, 0, 0, 0])
    np.testing.assert_array_equal(samples_per_controller(buffer), [1, 1])


def test_mask_on_add():
    buffer = init_buffer(4, 2, T, dX, dU, jnp.float64)
    buffer = add(buffer, controller(0.0), *batch(0.0, 3), mask=jnp.array([1, 0, 1]))
    np.testing.assert_array_equal(buffer.valid, [True, False, True, False])


def test_action_log_density_matches_scipy():
    ctrl = controller(0.4)
    X = jax.random.normal(jax.random.key(0), (T + 1, dX))
    U = jax.random.normal(jax.random.key(1), (T, dU))
    ref = sum(
        stats.multivariate_normal(
            np.asarray(ctrl.K[t] @ X[t] + ctrl.k[t]), np.asarray(ctrl.cov[t])
        ).logpdf(np.asarray(U[t]))
        for t in range(T)
    )
    np.testing.assert_allclose(action_log_density(ctrl, X, U), ref, rtol=1e-12)
    buffer = add(init_buffer(2, 2, T, dX, dU, jnp.float64), ctrl, X[None], U[None])
    log_q = controller_log_densities(buffer, X[None], U[None])[0]
    np.testing.assert_allclose(log_q[0], ref, rtol=1e-12)
    assert log_q[1] == -jnp.inf


def test_densities_of_every_trajectory_under_every_controller_match_scipy():
    """[S, Kc] densities with dX = 3 ≠ dU = 2 and time-varying gains (catches transposed
    indices in the written-out residual and quadratic form)."""
    Kc, S, T_, dX_, dU_ = 3, 4, 5, 3, 2
    keys = jax.random.split(jax.random.key(2), 5)
    K = jax.random.normal(keys[0], (Kc, T_, dU_, dX_))
    k = jax.random.normal(keys[1], (Kc, T_, dU_))
    M = jax.random.normal(keys[2], (Kc, T_, dU_, dU_))
    ctrls = make_controller(K, k, M @ jnp.swapaxes(M, -1, -2) + 0.2 * jnp.eye(dU_))
    X = jax.random.normal(keys[3], (S, T_ + 1, dX_))
    U = jax.random.normal(keys[4], (S, T_, dU_))
    got = jax.jit(action_log_densities)(ctrls, X, U)
    for s in range(S):
        for c in range(Kc):
            ref = sum(
                stats.multivariate_normal(
                    np.asarray(K[c, t] @ X[s, t] + k[c, t]), np.asarray(ctrls.cov[c, t])
                ).logpdf(np.asarray(U[s, t]))
                for t in range(T_)
            )
            np.testing.assert_allclose(got[s, c], ref, rtol=1e-10)


def test_vmap_over_conditions():
    buffers = jax.vmap(lambda _: init_buffer(4, 2, T, dX, dU, jnp.float64))(jnp.arange(3))
    ctrls = jax.vmap(controller)(jnp.arange(3.0))
    X = jnp.zeros((3, 2, T + 1, dX))
    U = jnp.zeros((3, 2, T, dU))
    buffers = jax.jit(jax.vmap(buffer_add))(buffers, ctrls, X, U)
    assert buffers.valid.shape == (3, 4) and buffers.valid[:, :2].all()
    np.testing.assert_allclose(buffers.controllers.k[:, 0, 0, 0], [0.0, 1.0, 2.0])


def test_empty_buffer_placeholders_equal_make_controller():
    """init_buffer writes the identity placeholders out (no LAPACK call); they must be exactly
    what make_controller builds from Σ = I."""
    buf = init_buffer(6, 3, 5, 4, 2, jnp.float64)
    ref = make_controller(
        jnp.zeros((3, 5, 2, 4)), jnp.zeros((3, 5, 2)), jnp.broadcast_to(jnp.eye(2), (3, 5, 2, 2))
    )
    for a, b in zip(jax.tree.leaves(buf.controllers), jax.tree.leaves(ref), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
