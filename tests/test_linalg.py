"""The unrolled small-matrix routines of diffgcl.linalg against NumPy's LAPACK, batched and not."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl import linalg


def spd(rng, shape, n):
    M = rng.normal(size=(*shape, n, n))
    return M @ np.swapaxes(M, -1, -2) + 0.1 * np.eye(n)


@pytest.mark.parametrize("n", [1, 2, 3, 6])
def test_cholesky_solves_and_inverse_match_numpy(n):
    rng = np.random.default_rng(n)
    A = spd(rng, (4, 3), n)
    B = rng.normal(size=(4, 3, n, 5))
    b = rng.normal(size=(4, 3, n))
    L = np.asarray(linalg.cholesky(jnp.asarray(A)))
    np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.triu(L, 1), 0.0)
    np.testing.assert_allclose(linalg.cho_solve(L, B), np.linalg.solve(A, B), rtol=1e-8)
    x = np.linalg.solve(A, b[..., None])[..., 0]
    np.testing.assert_allclose(linalg.cho_solve(L, b), x, rtol=1e-8)
    np.testing.assert_allclose(linalg.inverse_from_cholesky(L), np.linalg.inv(A), rtol=1e-8)
    np.testing.assert_allclose(linalg.solve_lower(L, B), np.linalg.solve(L, B), rtol=1e-8)
    U = np.swapaxes(L, -1, -2)
    np.testing.assert_allclose(linalg.solve_upper(U, B), np.linalg.solve(U, B), rtol=1e-8)


def test_not_positive_definite_gives_nan_and_vmap_jit_agree():
    A = jnp.array([[1.0, 2.0], [2.0, 1.0]])  # eigenvalues 3 and −1
    assert np.isnan(np.asarray(linalg.cholesky(A))).any()
    rng = np.random.default_rng(0)
    batch = jnp.asarray(spd(rng, (7,), 3))
    direct = linalg.cholesky(batch)
    mapped = jax.jit(jax.vmap(linalg.cholesky))(batch)
    np.testing.assert_allclose(direct, mapped, rtol=1e-12)
