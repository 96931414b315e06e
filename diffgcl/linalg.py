"""Linear algebra on small matrices (the action and state dimensions: 2–10) as unrolled jnp code.

Why not ``jnp.linalg.cholesky`` / ``jax.scipy.linalg.cho_solve``: on the CPU each of those is a
LAPACK call per matrix. Inside the LQR's time scan that is several calls per step on 2×2 matrices,
and under ``vmap`` over seeds the batch is handed to LAPACK one matrix at a time, so the per-call
overhead, not the arithmetic, sets the cost (measured: a 32-seed vmapped C-step only 2.5× faster
than 32 single ones). jaxlib 0.10.2's batched CPU LAPACK kernels can also deadlock the 2-thread
pool when several run concurrently inside a wide vmapped program (seen once in a vmapped rGCL run,
stuck in ``lapack_strsm_ffi``). The functions below are the textbook recursions unrolled over the
static matrix size: plain elementwise XLA ops that fuse and vectorise over any leading batch axes.

All take matrices ``[..., n, n]`` with the batch in the leading axes. A matrix that is not positive
definite gives NaN in the Cholesky factor (``sqrt`` of a negative pivot); callers test for it.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array


def symmetrise(A: Array) -> Array:
    """``(A + Aᵀ) / 2`` over the last two axes."""
    return 0.5 * (A + jnp.swapaxes(A, -1, -2))


def cholesky(A: Array) -> Array:
    """Lower Cholesky factor ``L`` (``A = L Lᵀ``) of symmetric ``A: [..., n, n]`` by the column
    recursion; the strict upper triangle of the result is zero."""
    n = A.shape[-1]
    cols: list[list[Array]] = []  # cols[j][i] = L[i, j] for i >= j
    for j in range(n):
        zero = jnp.zeros_like(A[..., 0, 0])
        pivot = A[..., j, j] - sum((cols[k][j] ** 2 for k in range(j)), zero)
        d = jnp.sqrt(pivot)
        col = [jnp.zeros_like(d)] * j + [d]
        for i in range(j + 1, n):
            s = A[..., i, j] - sum((cols[k][i] * cols[k][j] for k in range(j)), jnp.zeros_like(d))
            col.append(s / d)
        cols.append(col)
    return jnp.stack([jnp.stack(c, axis=-1) for c in cols], axis=-1)


def solve_lower(L: Array, B: Array) -> Array:
    """``L⁻¹ B`` for lower-triangular ``L: [..., n, n]`` and ``B: [..., n, m]`` (forward
    substitution, row by row)."""
    n = L.shape[-1]
    rows: list[Array] = []
    for i in range(n):
        s = B[..., i, :] - sum((L[..., i, j, None] * rows[j] for j in range(i)), 0.0)
        rows.append(s / L[..., i, i, None])
    return jnp.stack(rows, axis=-2)


def solve_upper(U: Array, B: Array) -> Array:
    """``U⁻¹ B`` for upper-triangular ``U: [..., n, n]`` and ``B: [..., n, m]`` (back
    substitution)."""
    n = U.shape[-1]
    rows: list[Array | None] = [None] * n
    for i in reversed(range(n)):
        s = B[..., i, :] - sum((U[..., i, j, None] * rows[j] for j in range(i + 1, n)), 0.0)
        rows[i] = s / U[..., i, i, None]
    return jnp.stack(rows, axis=-2)


def cho_solve(L: Array, B: Array) -> Array:
    """``A⁻¹ B`` from the lower Cholesky factor ``L`` of ``A``; ``B``: [..., n, m] or [..., n]."""
    vector = B.ndim == L.ndim - 1
    B = B[..., None] if vector else B
    X = solve_upper(jnp.swapaxes(L, -1, -2), solve_lower(L, B))
    return X[..., 0] if vector else X


def inverse_from_cholesky(L: Array) -> Array:
    """``A⁻¹ = L⁻ᵀ L⁻¹`` (symmetric) from the lower Cholesky factor ``L`` of ``A``."""
    eye = jnp.broadcast_to(jnp.eye(L.shape[-1], dtype=L.dtype), L.shape)
    L_inv = solve_lower(L, eye)
    return jnp.swapaxes(L_inv, -1, -2) @ L_inv
