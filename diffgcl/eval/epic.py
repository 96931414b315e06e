"""EPIC-style distance between two costs (Gleave et al. 2021, "Quantifying differences in reward
functions").

EPIC compares rewards up to the transformations that never change the optimal policy: positive
rescaling, constant shifts and potential shaping ``R'(s, a, s') = R(s, a, s') + γΦ(s') − Φ(s)``.
It *canonicalises* each reward with independent state and action distributions ``D_S``, ``D_A``

    C(s, a, s') = R(s, a, s') + E[γ R(s', A, S') − R(s, A, S') − γ R(S, A, S')],

then takes the Pearson distance ``sqrt((1 − ρ) / 2)`` of the canonical rewards over a coverage
distribution of transitions (s, a, s'). It lies in [0, 1]; 0 iff the two are equivalent.

What is implemented here: exactly that canonicalisation for a cost ``R(x, u, x')`` of a transition,
with the expectations estimated by Monte Carlo over the samples the caller passes (``S`` and
``S_next`` for ``D_S``, ``A`` for ``D_A``; :func:`canonical_costs`). diffgcl's per-step costs
``c(x, u)`` enter as ``R(x, u, x') = c(x, u)`` (see :func:`step_cost_as_transition_cost`), so the
canonical cost is ``c(x, u) + γ E_A c(x', A) − E_A c(x, A) − γ E c(S, A)`` and two step costs are
at distance 0 when one equals the other, rescaled and shifted, plus a shaping term
``γΦ(x') − Φ(x)`` in transition form. ``γ = 1`` is the undiscounted finite-horizon setting of
GCL's trajectory costs. The transitions to correlate over come from the caller's coverage set,
e.g. the visited ``(x_t, u_t, x_{t+1})`` of a varied set of trajectories.

:func:`pearson_distance` alone on raw ``c(x, u)`` is the simpler state-action comparison (invariant
to scale and shift only); it is exported for reporting next to EPIC.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from diffgcl.types import Array

StepCost = Callable[[Array, Array], Array]  # c(x: [dX], u: [dU]) -> scalar
TransitionCost = Callable[[Array, Array, Array], Array]  # R(x, u, x_next) -> scalar


def pearson_distance(a: Array, b: Array) -> Array:
    """``sqrt((1 − ρ) / 2)`` of two samples ``a, b: [n]`` (ρ the Pearson correlation)."""
    a = a - a.mean()
    b = b - b.mean()
    rho = (a @ b) / jnp.sqrt(jnp.maximum((a @ a) * (b @ b), jnp.finfo(a.dtype).tiny))
    return jnp.sqrt(jnp.clip(0.5 * (1.0 - rho), 0.0, 1.0))


def step_cost_as_transition_cost(cost_fn: StepCost) -> TransitionCost:
    """``c(x, u)`` as ``R(x, u, x') = c(x, u)``."""
    return lambda x, u, x_next: cost_fn(x, u)


def canonical_costs(
    cost_fn: TransitionCost,
    X: Array,
    U: Array,
    X_next: Array,
    S: Array,
    A: Array,
    S_next: Array,
    gamma: float = 1.0,
) -> Array:
    """EPIC-canonicalised costs of transitions ``X, X_next: [n, dX]``, ``U: [n, dU]`` -> [n].

    cost_fn(x: [dX], u: [dU], x_next: [dX]) -> scalar. ``S, S_next: [m, dX]`` and ``A: [m, dU]``
    are independent draws from ``D_S``, ``D_S`` and ``D_A``; expectations average over the ``m``
    pairs ``(A_i, S_next_i)`` and triples ``(S_i, A_i, S_next_i)``.
    """
    on_samples = jax.vmap(cost_fn, in_axes=(None, 0, 0))

    def mean_from(x: Array) -> Array:
        return on_samples(x, A, S_next).mean()

    c = jax.vmap(cost_fn)(X, U, X_next)
    next_term = jax.vmap(mean_from)(X_next)
    here_term = jax.vmap(mean_from)(X)
    offset = jax.vmap(cost_fn)(S, A, S_next).mean()
    return c + gamma * next_term - here_term - gamma * offset


def epic_distance(
    cost_a: TransitionCost,
    cost_b: TransitionCost,
    X: Array,
    U: Array,
    X_next: Array,
    S: Array,
    A: Array,
    S_next: Array,
    gamma: float = 1.0,
) -> Array:
    """EPIC distance of two transition costs on the coverage transitions ``X, X_next: [n, dX]``,
    ``U: [n, dU]``, canonicalised with the samples ``S, A, S_next`` (:func:`canonical_costs`)."""
    ca = canonical_costs(cost_a, X, U, X_next, S, A, S_next, gamma)
    cb = canonical_costs(cost_b, X, U, X_next, S, A, S_next, gamma)
    return pearson_distance(ca, cb)
