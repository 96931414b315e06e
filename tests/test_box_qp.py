"""The box QP of control-limited iLQR (diffgcl.control.box_qp) against enumerated active sets."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl.control.box_qp import box_qp


def _enumerated_minimum(H, g, lower, upper):
    """The box QP's minimiser by brute force: every assignment of each coordinate to free, lower
    or upper; solve the free block; keep the feasible candidate of lowest objective (a strictly
    convex QP's minimiser is one of them)."""
    n = g.shape[0]
    best, best_value = None, np.inf
    for assignment in itertools.product((0, 1, 2), repeat=n):
        fixed = np.array([a != 0 for a in assignment])
        x = np.where(np.array(assignment) == 1, lower, upper).astype(float)
        x[~fixed] = 0.0
        if np.any(~np.isfinite(x[fixed])):
            continue
        f = ~fixed
        if f.any():
            rhs = -(g[f] + H[np.ix_(f, fixed)] @ x[fixed])
            x[f] = np.linalg.solve(H[np.ix_(f, f)], rhs)
        if np.all(x >= lower - 1e-12) and np.all(x <= upper + 1e-12):
            value = 0.5 * x @ H @ x + g @ x
            if value < best_value:
                best, best_value = x, value
    return best, best_value


def _random_qp(rng, n):
    M = rng.standard_normal((n, n))
    H = M @ M.T + 0.1 * np.eye(n)
    g = 3.0 * rng.standard_normal(n)
    lower = -rng.uniform(0.05, 1.0, n)
    upper = rng.uniform(0.05, 1.0, n)
    return H, g, lower, upper


@pytest.mark.parametrize("n", [1, 2, 4])
def test_box_qp_equals_enumerated_minimum(n):
    rng = np.random.default_rng(n)
    solve = jax.jit(lambda H, g, lo, hi, x: box_qp(H, g, lo, hi, x))
    clamped_somewhere = 0
    for _ in range(20):
        H, g, lower, upper = _random_qp(rng, n)
        x_ref, v_ref = _enumerated_minimum(H, g, lower, upper)
        x_init = rng.uniform(-2, 2, n)  # infeasible starts are projected
        r = solve(*(jnp.asarray(a) for a in (H, g, lower, upper, x_init)))
        assert bool(r.ok)
        np.testing.assert_allclose(np.asarray(r.x), x_ref, atol=1e-9)
        at_bound = np.isclose(x_ref, lower) | np.isclose(x_ref, upper)
        # The free set is the coordinates off their bounds (no degenerate ties in these draws).
        np.testing.assert_array_equal(np.asarray(r.free), ~at_bound)
        clamped_somewhere += int(at_bound.any())
    assert clamped_somewhere >= 5  # the draws exercise the constraints


def test_box_qp_without_active_bounds_is_the_newton_step():
    rng = np.random.default_rng(7)
    H, g, _, _ = _random_qp(rng, 3)
    r = box_qp(jnp.asarray(H), jnp.asarray(g), -jnp.inf, jnp.inf)
    np.testing.assert_allclose(np.asarray(r.x), -np.linalg.solve(H, g), atol=1e-10)
    assert bool(jnp.all(r.free)) and int(r.iterations) <= 2
    np.testing.assert_allclose(np.asarray(r.L_free @ r.L_free.T), H, atol=1e-10)


def test_box_qp_factor_is_the_free_block():
    """L_free factors H on the free coordinates and is the identity on the clamped ones."""
    H = np.array([[2.0, 0.5, 0.1], [0.5, 1.0, 0.2], [0.1, 0.2, 3.0]])
    g = np.array([-10.0, 0.1, 0.2])  # pushes x_0 past its upper bound
    r = box_qp(jnp.asarray(H), jnp.asarray(g), -jnp.ones(3), jnp.ones(3))
    assert np.asarray(r.free).tolist() == [False, True, True]
    LLt = np.asarray(r.L_free @ r.L_free.T)
    np.testing.assert_allclose(LLt[1:, 1:], H[1:, 1:], atol=1e-12)
    np.testing.assert_allclose(LLt[0], [1.0, 0.0, 0.0], atol=1e-12)


def test_box_qp_refuses_indefinite_hessian():
    H = jnp.asarray([[1.0, 0.0], [0.0, -1.0]])
    r = box_qp(H, jnp.ones(2), -jnp.ones(2), jnp.ones(2))
    assert not bool(r.ok)
    assert bool(jnp.all(jnp.isfinite(r.x)))
