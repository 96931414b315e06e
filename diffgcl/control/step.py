"""Step-size adaptation of the KL bound from Laplace cost estimates (DESIGN §4; GPS
``_stepadjust`` / ``_set_new_mult``, Levine et al. 2016 appendix).

The Laplace estimate of a controller's expected cost is the expectation of a quadratic cost
expansion under the Gaussian trajectory marginals of the forward pass. Three estimates decide the
next step:

* ``J_prev``: previous controller, previous dynamics and cost expansion (what we had);
* ``J_pred``: current controller, previous dynamics and cost (what the C-step predicted);
* ``J_act``: current controller, current dynamics and cost (what the new samples say).

Predicted improvement ``pred = J_prev − J_pred``, actual ``act = J_prev − J_act``;
``mult = pred / (2·max(1e-4, pred − act))`` clipped to [0.1, 5]; ``step_mult ← clip(step_mult·mult,
0.01, 10)``: a model that predicted well (act ≈ pred) gets a larger step, a poor one a smaller one.

One multiplier for several conditions comes either from their averaged estimates (GPS's global
MDGPS rule: a condition whose estimates are orders of magnitude above the rest decides alone) or
as the geometric mean of the conditions' own multipliers (:func:`geometric_step_multiplier`: each
condition's vote is bounded by the clip, so one runaway condition moves the shared step by at
most a factor 50^(1/C)).
"""

from __future__ import annotations

import jax.numpy as jnp

from diffgcl.types import Array, QuadraticCost, TrajectoryDistribution

# How several conditions' steps adapt: each its own ("classic"), or one for all from their
# averaged estimates ("global") or the geometric mean of their multipliers ("geometric").
STEP_RULES = ("global", "geometric", "classic")


def laplace_cost_per_step(traj_dist: TrajectoryDistribution, cost: QuadraticCost) -> Array:
    """``E[l_t(z_t)]`` of a quadratic expansion *about the origin* under Gaussian marginals.

    traj_dist: mu [T, dX+dU], sigma [T, dX+dU, dX+dU], mu_final [dX], sigma_final [dX, dX];
    cost: T+1 entries. For z ~ N(μ, Σ): ``E = l + gᵀμ + ½μᵀHμ + ½tr(HΣ)``. Returns [T+1]
    (entry T: terminal state cost).
    """
    H = jnp.block(
        [
            [cost.l_xx[:-1], jnp.swapaxes(cost.l_ux[:-1], -1, -2)],
            [cost.l_ux[:-1], cost.l_uu[:-1]],
        ]
    )  # [T, dZ, dZ]
    g = jnp.concatenate([cost.l_x[:-1], cost.l_u[:-1]], axis=-1)  # [T, dZ]
    mu, sigma = traj_dist.mu, traj_dist.sigma
    running = (
        cost.l[:-1]
        + jnp.einsum("ti,ti->t", g, mu)
        + 0.5 * jnp.einsum("ti,tij,tj->t", mu, H, mu)
        + 0.5 * jnp.einsum("tij,tji->t", H, sigma)
    )
    mT, sT, HT = traj_dist.mu_final, traj_dist.sigma_final, cost.l_xx[-1]
    terminal = cost.l[-1] + cost.l_x[-1] @ mT + 0.5 * mT @ HT @ mT + 0.5 * jnp.trace(HT @ sT)
    return jnp.concatenate([running, terminal[None]])


def laplace_cost(traj_dist: TrajectoryDistribution, cost: QuadraticCost) -> Array:
    """Total Laplace expected cost (scalar); see :func:`laplace_cost_per_step`."""
    return jnp.sum(laplace_cost_per_step(traj_dist, cost))


def step_multiplier(
    J_prev: Array, J_pred: Array, J_act: Array, *, min_mult: float = 0.1, max_mult: float = 5.0
) -> Array:
    """``pred / (2·max(1e-4, pred − act))`` clipped to [min_mult, max_mult] (scalars)."""
    predicted = J_prev - J_pred
    actual = J_prev - J_act
    mult = predicted / (2.0 * jnp.maximum(1e-4, predicted - actual))
    return jnp.clip(mult, min_mult, max_mult)


def geometric_step_multiplier(J_prev: Array, J_pred: Array, J_act: Array) -> Array:
    """The geometric mean over conditions [C] of their clipped :func:`step_multiplier`; a
    condition whose multiplier is not finite is left out (all of them: NaN). Returns a scalar."""
    log_mult = jnp.log(step_multiplier(J_prev, J_pred, J_act))
    finite = jnp.isfinite(log_mult)
    total = jnp.sum(jnp.where(finite, log_mult, 0.0))
    return jnp.exp(total / jnp.where(finite.any(), finite.sum(), jnp.nan))


def adapt_step_mult(
    step_mult: Array,
    J_prev: Array,
    J_pred: Array,
    J_act: Array,
    *,
    rule: str = "classic",
    min_step_mult: float = 0.01,
    max_step_mult: float = 10.0,
) -> Array:
    """New ``step_mult = clip(step_mult · mult, min_step_mult, max_step_mult)``.

    ``rule`` (:data:`STEP_RULES`): ``"classic"``, each entry's own :func:`step_multiplier`; the
    shared rules read the last axis as the conditions [C] and give them one multiplier, from
    their averaged estimates (``"global"``) or :func:`geometric_step_multiplier`
    (``"geometric"``), and one step (the mean of the conditions' adapted steps)."""
    if rule not in STEP_RULES:
        raise ValueError(f"adapt_step_mult: rule {rule!r}; choose one of {STEP_RULES}")
    if rule == "global":
        mult = step_multiplier(J_prev.mean(-1), J_pred.mean(-1), J_act.mean(-1))[..., None]
    elif rule == "geometric":
        mult = geometric_step_multiplier(J_prev, J_pred, J_act)[..., None]
    else:
        mult = step_multiplier(J_prev, J_pred, J_act)
    adapted = jnp.clip(step_mult * mult, min_step_mult, max_step_mult)
    if rule == "classic":
        return adapted
    return jnp.broadcast_to(adapted.mean(-1, keepdims=True), adapted.shape)
