"""Quadratic expansion of a cost ``c(x, u, t)`` along a trajectory by autodiff (DESIGN §4).

The LQR needs, per step, ``l, l_x, l_u, l_xx, l_uu, l_ux``. Three ways to get them:

* :func:`expand_cost` — full Hessian of ``c`` at a trajectory (X̄, Ū);
* :func:`expand_residual_cost` — Gauss–Newton for ``c = ‖r(x, u, t)‖²``: gradient ``2Jᵀr``,
  Hessian ``2JᵀJ`` (always PSD; the choice for a learned network cost ``‖Ay(x) + b‖²``);
* :func:`expand_cost_samples` — GPS's estimate: expand around every sample, move each expansion
  to the sample mean and average (a better estimate of the expected cost than one expansion).

An expansion is *about* its trajectory: ``c(x̄_t + dx, ū_t + du) ≈ l + l_x·dx + ...``
(see :class:`diffgcl.types.QuadraticCost`). The LQR works in absolute coordinates: move an
expansion with :func:`about_origin` (or :func:`shift_expansion`) before the C-step.

Costs follow the convention of :mod:`diffgcl.types`: ``c(x_t, u_t, t)`` for t < T and the
terminal ``c(x_T, 0, T)``; the terminal entry's action parts are zero. Per-step expansions are
independent, so they are vmapped over t rather than scanned.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffgcl.tracing import value_and_jacfwd
from diffgcl.types import Array, CostFn, QuadraticCost

ResidualFn = CostFn  # r(x: [dX], u: [dU], t) -> [dR]


def _expand_step(cost_fn: CostFn, x: Array, u: Array, t: Array):
    dX = x.shape[-1]

    def f(z):
        return cost_fn(z[:dX], z[dX:], t)

    z = jnp.concatenate([x, u])
    (val, grad), (_, hess) = value_and_jacfwd(jax.value_and_grad(f))(z)
    return val, grad, 0.5 * (hess + hess.T)


def _expand_residual_step(residual_fn: ResidualFn, x: Array, u: Array, t: Array):
    dX = x.shape[-1]

    def r(z):
        return residual_fn(z[:dX], z[dX:], t)

    z = jnp.concatenate([x, u])
    res, J = value_and_jacfwd(r)(z)  # [dR], [dR, dZ]
    return res @ res, 2.0 * J.T @ res, 2.0 * J.T @ J


def _assemble(step_fn, fn, X: Array, U: Array) -> QuadraticCost:
    T, dU = U.shape
    dX = X.shape[-1]
    ts = jnp.arange(T + 1)
    U_all = jnp.concatenate([U, jnp.zeros((1, dU), U.dtype)], axis=0)
    l, g, H = jax.vmap(lambda x, u, t: step_fn(fn, x, u, t))(X, U_all, ts)
    mask_u = jnp.concatenate([jnp.ones(T, X.dtype), jnp.zeros(1, X.dtype)])  # no terminal action
    return QuadraticCost(
        l=l,
        l_x=g[:, :dX],
        l_u=g[:, dX:] * mask_u[:, None],
        l_xx=H[:, :dX, :dX],
        l_uu=H[:, dX:, dX:] * mask_u[:, None, None],
        l_ux=H[:, dX:, :dX] * mask_u[:, None, None],
    )


def expand_cost(cost_fn: CostFn, X: Array, U: Array) -> QuadraticCost:
    """Second-order expansion (full Hessian) of ``cost_fn`` about (X, U).

    X: [T+1, dX], U: [T, dU]. Returns QuadraticCost with T+1 entries about the trajectory.
    """
    return _assemble(_expand_step, cost_fn, X, U)


def expand_residual_cost(residual_fn: ResidualFn, X: Array, U: Array) -> QuadraticCost:
    """Gauss–Newton expansion of ``c = ‖r(x, u, t)‖²`` about (X, U).

    residual_fn(x: [dX], u: [dU], t) -> [dR]. X: [T+1, dX], U: [T, dU]. Hessian ``2JᵀJ`` (PSD).
    """
    return _assemble(_expand_residual_step, residual_fn, X, U)


def _pack(cost: QuadraticCost):
    H = jnp.block([[cost.l_xx, jnp.swapaxes(cost.l_ux, -1, -2)], [cost.l_ux, cost.l_uu]])
    g = jnp.concatenate([cost.l_x, cost.l_u], axis=-1)
    return cost.l, g, H


def _unpack(l: Array, g: Array, H: Array, dX: int) -> QuadraticCost:
    return QuadraticCost(
        l=l,
        l_x=g[..., :dX],
        l_u=g[..., dX:],
        l_xx=H[..., :dX, :dX],
        l_uu=H[..., dX:, dX:],
        l_ux=H[..., dX:, :dX],
    )


def shift_expansion(
    cost: QuadraticCost, X_from: Array, U_from: Array, X_to: Array, U_to: Array
) -> QuadraticCost:
    """The same quadratic, re-expressed about another trajectory (exact for a quadratic).

    With ``d = z_from − z_to`` per step: ``l' = l − gᵀd + ½dᵀHd``, ``g' = g − Hd``, ``H' = H``.
    X_*: [T+1, dX], U_*: [T, dU] (the terminal action is 0 in both).
    """
    dX = X_from.shape[-1]
    dU = U_from.shape[-1]
    pad = jnp.zeros((1, dU), U_from.dtype)
    Z_from = jnp.concatenate([X_from, jnp.concatenate([U_from, pad])], axis=-1)
    Z_to = jnp.concatenate([X_to, jnp.concatenate([U_to, pad])], axis=-1)
    d = Z_from - Z_to  # [T+1, dZ]
    l, g, H = _pack(cost)
    Hd = jnp.einsum("tij,tj->ti", H, d)
    l_new = l - jnp.einsum("ti,ti->t", g, d) + 0.5 * jnp.einsum("ti,ti->t", d, Hd)
    return _unpack(l_new, g - Hd, H, dX)


def about_origin(cost: QuadraticCost, X: Array, U: Array) -> QuadraticCost:
    """Expansion about (X, U) -> the same quadratic about x = 0, u = 0 (absolute coordinates, as
    the LQR of :mod:`diffgcl.control.lqr` wants). X: [T+1, dX], U: [T, dU]."""
    return shift_expansion(cost, X, U, jnp.zeros_like(X), jnp.zeros_like(U))


def expand_cost_samples(
    cost_fn: CostFn, X: Array, U: Array, *, gauss_newton: bool = False
) -> QuadraticCost:
    """GPS's sample-averaged expansion, about the sample mean trajectory.

    X: [N, T+1, dX], U: [N, T, dU]. Each sample's expansion is shifted to the mean (X̄, Ū) and the
    N quadratics are averaged; ``gauss_newton=True`` treats ``cost_fn`` as a residual function
    (see :func:`expand_residual_cost`). Returns QuadraticCost with T+1 entries about (X̄, Ū).
    """
    expand = expand_residual_cost if gauss_newton else expand_cost
    X_mean, U_mean = jnp.mean(X, axis=0), jnp.mean(U, axis=0)

    def one(x, u):
        return shift_expansion(expand(cost_fn, x, u), x, u, X_mean, U_mean)

    per_sample = jax.vmap(one)(X, U)
    return jax.tree.map(lambda a: jnp.mean(a, axis=0), per_sample)


def trajectory_cost(cost_fn: CostFn, X: Array, U: Array) -> Array:
    """Total cost ``Σ_t c(x_t, u_t, t) + c(x_T, 0, T)`` of one trajectory (scalar).

    X: [T+1, dX], U: [T, dU].
    """
    T, dU = U.shape
    U_all = jnp.concatenate([U, jnp.zeros((1, dU), U.dtype)], axis=0)
    return jnp.sum(jax.vmap(cost_fn)(X, U_all, jnp.arange(T + 1)))
