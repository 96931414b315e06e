"""A small box-constrained quadratic programme, solved by projected Newton.

Problem: ``min_x ½ xᵀHx + gᵀx`` subject to ``lower ≤ x ≤ upper`` (elementwise; ±inf allowed),
``H`` symmetric positive definite, ``x: [n]`` with ``n`` small (the actions of one time step).
This is the subproblem of control-limited iLQR (Tassa, Mansard & Todorov 2014, "Control-limited
differential dynamic programming"), where ``H = Q_uu + μI``, ``g = Q_u`` and the box is the
actuators' range around the current actions.

Method (Bertsekas 1982's projected Newton, as in that paper): from the projection of ``x_init``
onto the box, repeat

1. the clamped set: coordinates at a bound whose gradient ``Hx + g`` pushes further out
   (``x = lower`` and ``∂ > 0``, or ``x = upper`` and ``∂ < 0``); the others are free;
2. Newton's step on the free coordinates with the clamped ones fixed, ``d_f = −H_ff⁻¹ ∂_f``,
   ``d_c = 0``;
3. a projected backtracking line search, ``x' = clip(x + α d)``, ``α = 1, ½, ¼, ...``, accepting
   the first ``α`` whose decrease is at least ``armijo · α · |dᵀ∂|``;

until the free gradient's norm falls below ``tol``, no step length decreases the objective, or
``max_iterations``. With every coordinate free it is one Newton step: the unconstrained minimiser.

The result carries the Cholesky factor of ``H`` restricted to the final free set (identity rows
and columns on the clamped ones) so that iLQR's feedback gains can be solved on the free
subspace, ``K_f = −H_ff⁻¹ Q_ux,f`` and ``K_c = 0``: a clamped action does not respond to a state
deviation to first order. Fixed shapes throughout (masks, not index sets), so it vmaps and runs
inside ``lax.scan``.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct
from jax import lax

from diffgcl import linalg
from diffgcl.types import Array


@struct.dataclass
class BoxQPResult:
    """x: [n] the solution; free: [n] bool, the coordinates not held at a bound; L_free: [n, n]
    the Cholesky factor of ``H`` on the free coordinates (identity on the clamped ones);
    iterations: Newton steps taken; ok: ``H`` was positive definite and everything finite."""

    x: Array
    free: Array
    L_free: Array
    iterations: Array
    ok: Array


def _clamped(x: Array, grad: Array, lower: Array, upper: Array) -> Array:
    return ((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0))


def _free_factor(H: Array, free: Array) -> Array:
    """Cholesky factor of H on the free coordinates, identity elsewhere."""
    eye = jnp.eye(H.shape[-1], dtype=H.dtype)
    both = free[:, None] & free[None, :]
    return linalg.cholesky(jnp.where(both, H, eye))


def box_qp(
    H: Array,
    g: Array,
    lower: Array,
    upper: Array,
    x_init: Array | None = None,
    *,
    max_iterations: int = 30,
    tol: float = 1e-10,
    armijo: float = 0.1,
    line_search_steps: int = 30,
) -> BoxQPResult:
    """Solve ``min ½ xᵀHx + gᵀx`` on ``lower ≤ x ≤ upper`` (module docstring). ``H: [n, n]``,
    ``g, lower, upper, x_init: [n]`` (``x_init`` default zeros; it is projected onto the box).
    Not positive definite or not finite: ``ok = False`` and ``x`` the projected start."""
    n = g.shape[-1]
    dtype = g.dtype
    lower = jnp.broadcast_to(jnp.asarray(lower, dtype), (n,))
    upper = jnp.broadcast_to(jnp.asarray(upper, dtype), (n,))
    x0 = jnp.zeros((n,), dtype) if x_init is None else jnp.asarray(x_init, dtype)
    x0 = jnp.clip(x0, lower, upper)
    value = lambda x: 0.5 * x @ (H @ x) + g @ x
    L_full = linalg.cholesky(H)
    pd = jnp.all(jnp.isfinite(L_full)) & jnp.all(jnp.diagonal(L_full) > 0)
    pd = pd & jnp.all(jnp.isfinite(g))

    def newton_step(x):
        grad = g + H @ x
        free = ~_clamped(x, grad, lower, upper)
        L = _free_factor(H, free)
        d = -linalg.cho_solve(L, jnp.where(free, grad, 0.0))
        return grad, free, d

    def cond(c):
        i, _, done = c
        return (i < max_iterations) & ~done

    def body(c):
        i, x, _ = c
        grad, free, d = newton_step(x)
        free_grad_small = jnp.linalg.norm(jnp.where(free, grad, 0.0)) < tol
        slope = d @ grad  # < 0 for a descent direction
        f0 = value(x)

        def ls_cond(s):
            j, accepted, _ = s
            return (j < line_search_steps) & ~accepted

        def ls_body(s):
            j, _, _ = s
            alpha = jnp.asarray(0.5, dtype) ** j
            x_new = jnp.clip(x + alpha * d, lower, upper)
            accepted = f0 - value(x_new) >= armijo * alpha * (-slope)
            return j + 1, accepted, x_new

        _, accepted, x_new = lax.while_loop(
            ls_cond, ls_body, (jnp.zeros((), jnp.int32), jnp.zeros((), bool), x)
        )
        moved = accepted & ~free_grad_small & (slope < 0)
        x = jnp.where(moved, x_new, x)
        return i + 1, x, ~moved

    start = (jnp.zeros((), jnp.int32), x0, ~pd)
    iterations, x, _ = lax.while_loop(cond, body, start)
    grad = g + H @ x
    free = ~_clamped(x, grad, lower, upper)
    L_free = _free_factor(H, free)
    ok = pd & jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(L_free))
    return BoxQPResult(x=x, free=free, L_free=L_free, iterations=iterations, ok=ok)
