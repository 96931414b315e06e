"""EPIC-style distance between two costs (Gleave et al. 2021, "Quantifying differences in reward
functions").

EPIC compares rewards up to the transformations that never change the optimal policy: positive
rescaling, constant shifts and potential shaping ``R'(s, a, s') = R(s, a, s') + γΦ(s') − Φ(s)``.
It *canonicalises* each reward with independent state and action distributions ``D_S``, ``D_A``

    C(s, a, s') = R(s, a, s') + E[γ R(s', A, S') − R(s, A, S') − γ R(S, A, S')],

then takes the Pearson distance ``sqrt((1 − ρ) / 2)`` of the canonical rewards over a coverage
distribution of transitions (s, a, s'). It lies in [0, 1]; 0 iff the two are equivalent.

What is implemented here, for per-step costs ``c(x, u)`` that do not look at the next state: the
expectations over ``S'`` drop out and the canonical cost is

    C(x, u, x') = c(x, u) + γ E_A c(x', A) − E_A c(x, A) − γ E_{S,A} c(S, A),

estimated by Monte Carlo with the samples of ``D_A`` and of ``D_S × D_A`` the caller passes
(:func:`canonical_costs`). Transitions come from the caller's coverage set, e.g. the visited
``(x_t, u_t, x_{t+1})`` of a varied set of trajectories. ``γ = 1`` is the undiscounted
finite-horizon case that GCL's trajectory costs live in. The shaping invariance is the reason to
canonicalise rather than correlate raw costs: a learned cost that differs from the truth by
``Φ(x') − Φ(x)`` ranks trajectories that share a start and end alike.

:func:`pearson_distance` alone on raw ``c(x, u)`` is the simpler state-action comparison (invariant
to scale and shift only); it is exported for reporting next to EPIC.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from diffgcl.types import Array

StepCost = Callable[[Array, Array], Array]  # c(x: [dX], u: [dU]) -> scalar


def pearson_distance(a: Array, b: Array) -> Array:
    """``sqrt((1 − ρ) / 2)`` of two samples ``a, b: [n]`` (ρ the Pearson correlation)."""
    a = a - a.mean()
    b = b - b.mean()
    rho = (a @ b) / jnp.sqrt(jnp.maximum((a @ a) * (b @ b), jnp.finfo(a.dtype).tiny))
    return jnp.sqrt(jnp.clip(0.5 * (1.0 - rho), 0.0, 1.0))


def canonical_costs(
    cost_fn: StepCost,
    X: Array,
    U: Array,
    X_next: Array,
    S: Array,
    A: Array,
    gamma: float = 1.0,
) -> Array:
    """Canonicalised costs of transitions ``X, X_next: [n, dX]``, ``U: [n, dU]`` -> [n].

    cost_fn(x: [dX], u: [dU]) -> scalar. ``S: [m, dX]`` and ``A: [m, dU]`` are independent draws
    from ``D_S`` and ``D_A``; ``E_A c(x, A)`` averages over all of ``A`` and ``E_{S,A}`` over the
    pairs ``(S_i, A_i)`` (so pass them shuffled independently).
    """
    on_actions = jax.vmap(cost_fn, in_axes=(None, 0))

    def mean_over_actions(x: Array) -> Array:
        return on_actions(x, A).mean()

    c = jax.vmap(cost_fn)(X, U)
    next_term = jax.vmap(mean_over_actions)(X_next)
    here_term = jax.vmap(mean_over_actions)(X)
    offset = jax.vmap(cost_fn)(S, A).mean()
    return c + gamma * next_term - here_term - gamma * offset


def epic_distance(
    cost_a: StepCost,
    cost_b: StepCost,
    X: Array,
    U: Array,
    X_next: Array,
    S: Array,
    A: Array,
    gamma: float = 1.0,
) -> Array:
    """EPIC distance between costs ``cost_a`` and ``cost_b`` (``c(x, u) -> scalar``) on the
    coverage transitions ``X, X_next: [n, dX]``, ``U: [n, dU]``; see :func:`canonical_costs`."""
    ca = canonical_costs(cost_a, X, U, X_next, S, A, gamma)
    cb = canonical_costs(cost_b, X, U, X_next, S, A, gamma)
    return pearson_distance(ca, cb)
