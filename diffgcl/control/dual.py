"""The C-step: search the dual variable η so that the new controller's KL meets ε (DESIGN §4).

``KL(η)`` — the KL divergence between the controller from the η-augmented LQR and the previous
one — decreases as η grows. :func:`c_step` looks for ``|KL(η) − ε| ≤ tol·ε`` (tol = 10 %) inside
one ``lax.while_loop`` with a bounded trip count:

* bracketing: from ``eta_init``, multiply η by ``bracket_factor`` (10) while KL is too large,
  divide while it is too small;
* once bracketed, interpolate in (log η, log KL) — the secant of a near power law — kept inside
  the inner 80 % of the bracket, or bisect in log η when an end has no finite KL;
* a non-positive-definite ``Q_uu`` counts as "KL too large": η ← η + δ with δ doubling, starting
  from ``max(del0, η)`` (GPS starts δ at 1e-4 and doubles it; starting at η makes the rise
  geometric from any η, so the bound is reached in a few dozen trips), and the search gives up at
  ``max_eta`` (1e16);
* KL below ε already at ``min_eta``: the constraint is inactive and that controller is returned.

The outcome is never silent: :class:`CStepInfo` carries η, the KL, a status code and the trip
count. On a failure the previous controller is returned unchanged (always valid, no NaN). Written
for one condition; vmap over conditions (the loop runs until every condition is done).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct
from jax import lax

from diffgcl.control.lqr import backward_pass, forward_pass, kl_divergence
from diffgcl.types import (
    Array,
    InitialStateDistribution,
    LinearDynamics,
    LinearGaussianController,
    QuadraticCost,
)

# Status codes of CStepInfo.status.
CONVERGED = 0  # |KL − ε| ≤ tol·ε
INACTIVE = 1  # KL < ε at min_eta: the constraint does not bind
LOOSE = 2  # trip limit reached; returned the bracket's feasible end (KL < ε, not tight)
FAILED_NOT_PD = 3  # Q_uu not PD (or non-finite) up to max_eta; returned the previous controller
FAILED_NO_FEASIBLE = 4  # trip limit reached without any controller with KL ≤ (1+tol)ε

STATUS_NAMES = {
    CONVERGED: "converged",
    INACTIVE: "constraint inactive at min_eta",
    LOOSE: "trip limit, KL below epsilon",
    FAILED_NOT_PD: "failed: Q_uu not positive definite up to max_eta",
    FAILED_NO_FEASIBLE: "failed: trip limit without a feasible eta",
}


@struct.dataclass
class CStepInfo:
    """What the η search did (one condition; leading axes when vmapped).

    eta: the returned controller's η (``eta_init`` on a failure). kl: its KL to the previous
    controller (0 on a failure). epsilon: the target. status: int32 code (module constants).
    ok: bool, status is CONVERGED, INACTIVE or LOOSE. iterations: backward passes run.
    not_pd: how many of those had a non-PD Q_uu.
    """

    eta: Array
    kl: Array
    epsilon: Array
    status: Array
    ok: Array
    iterations: Array
    not_pd: Array


@struct.dataclass
class _Search:
    it: Array
    eta: Array
    delta: Array
    log_lo: Array  # largest η known to give KL too large (or non-PD)
    log_hi: Array  # smallest η known to give KL too small
    kl_lo: Array  # KL at lo (inf when lo was not PD)
    kl_hi: Array
    has_lo: Array
    has_hi: Array
    done: Array
    status: Array
    not_pd: Array
    best: LinearGaussianController  # controller at hi, or the accepted one
    best_eta: Array
    best_kl: Array
    has_best: Array


def c_step(
    dynamics: LinearDynamics,
    cost: QuadraticCost,
    prev: LinearGaussianController,
    x0: InitialStateDistribution,
    epsilon: Array,
    eta_init: Array,
    *,
    maxent: bool = False,
    tol: float = 0.1,
    max_iter: int = 100,
    min_eta: float = 1e-8,
    max_eta: float = 1e16,
    del0: float = 1e-4,
    bracket_factor: float = 10.0,
) -> tuple[LinearGaussianController, CStepInfo]:
    """New controller with ``KL(new ‖ prev) ≈ epsilon`` (one condition).

    dynamics: fields [T, ...]; cost: QuadraticCost about the origin, T+1 entries; prev: fields
    [T, ...], the KL anchor; x0: mean [dX], cov [dX, dX]; epsilon: scalar total KL budget
    (GPS: ``kl_step · step_mult · T``); eta_init: scalar starting η (the last iteration's η).
    ``maxent``: ω = 1 (GCL's maximum-entropy objective) instead of ω = 0.
    Returns (controller with fields [T, ...], CStepInfo).
    """
    omega = 1.0 if maxent else 0.0
    dtype = cost.l.dtype
    epsilon = jnp.asarray(epsilon, dtype)
    eta0 = jnp.clip(jnp.asarray(eta_init, dtype), min_eta, max_eta)
    log_factor = jnp.log(bracket_factor)
    log_min, log_max = jnp.log(min_eta), jnp.log(max_eta)

    def evaluate(eta):
        result = backward_pass(dynamics, cost, prev, eta, omega)
        traj = forward_pass(dynamics, result.controller, x0)
        kl = kl_divergence(traj, result.controller, prev)
        usable = result.pd_ok & jnp.isfinite(kl)
        return result.controller, usable, jnp.where(usable, kl, jnp.inf)

    def cond(s: _Search):
        return ~s.done

    def body(s: _Search):
        ctrl, usable, kl = evaluate(s.eta)
        log_eta = jnp.log(s.eta)
        converged = usable & (jnp.abs(kl - epsilon) <= tol * epsilon)
        too_small = usable & ~converged & (kl < epsilon)
        too_large = ~converged & ~too_small  # includes non-PD / non-finite
        at_min = log_eta <= log_min + 1e-4  # log-space margins hold in float32 too
        inactive = too_small & at_min

        # Accepted or feasible-side controller: keep it as the best so far.
        take = converged | too_small
        best = _select(take, ctrl, s.best)
        best_eta = jnp.where(take, s.eta, s.best_eta)
        best_kl = jnp.where(take, kl, s.best_kl)
        has_best = s.has_best | take

        log_lo = jnp.where(too_large, log_eta, s.log_lo)
        kl_lo = jnp.where(too_large, kl, s.kl_lo)
        has_lo = s.has_lo | too_large
        log_hi = jnp.where(too_small, log_eta, s.log_hi)
        kl_hi = jnp.where(too_small, kl, s.kl_hi)
        has_hi = s.has_hi | too_small

        # Next η.
        bracketed = has_lo & has_hi
        mid = 0.5 * (log_lo + log_hi)
        finite_ends = jnp.isfinite(kl_lo) & jnp.isfinite(kl_hi) & (kl_lo > kl_hi)
        safe_lo = jnp.log(jnp.where(finite_ends, kl_lo, 2.0))
        safe_hi = jnp.log(jnp.where(finite_ends, kl_hi, 1.0))
        frac = (safe_lo - jnp.log(epsilon)) / (safe_lo - safe_hi)
        secant = log_lo + jnp.clip(frac, 0.1, 0.9) * (log_hi - log_lo)
        log_bracketed = jnp.where(finite_ends, secant, mid)

        not_pd = ~usable
        delta = jnp.where(not_pd, jnp.maximum(s.delta, s.eta), s.delta)
        log_up_not_pd = jnp.log(s.eta + delta)
        next_delta = jnp.where(not_pd, 2.0 * delta, s.delta)
        log_up = jnp.where(not_pd, log_up_not_pd, log_eta + log_factor)
        log_down = jnp.maximum(log_eta - log_factor, log_min)
        log_next = jnp.where(bracketed, log_bracketed, jnp.where(too_large, log_up, log_down))
        log_next = jnp.clip(log_next, log_min, log_max)

        it = s.it + 1
        gave_up_pd = not_pd & ~has_hi & (log_eta >= log_max - 1e-4)
        out_of_trips = it >= max_iter
        done = converged | inactive | gave_up_pd | out_of_trips
        status = jnp.where(
            converged,
            CONVERGED,
            jnp.where(
                inactive,
                INACTIVE,
                jnp.where(
                    gave_up_pd,
                    FAILED_NOT_PD,
                    jnp.where(has_best, LOOSE, FAILED_NO_FEASIBLE),
                ),
            ),
        ).astype(jnp.int32)
        return _Search(
            it=it,
            eta=jnp.exp(log_next),
            delta=next_delta,
            log_lo=log_lo,
            log_hi=log_hi,
            kl_lo=kl_lo,
            kl_hi=kl_hi,
            has_lo=has_lo,
            has_hi=has_hi,
            done=done,
            status=jnp.where(done, status, s.status),
            not_pd=s.not_pd + not_pd.astype(jnp.int32),
            best=best,
            best_eta=best_eta,
            best_kl=best_kl,
            has_best=has_best,
        )

    zero = jnp.zeros((), dtype)
    init = _Search(
        it=jnp.zeros((), jnp.int32),
        eta=eta0,
        delta=jnp.asarray(del0, dtype),
        log_lo=zero,
        log_hi=zero,
        kl_lo=zero,
        kl_hi=zero,
        has_lo=jnp.zeros((), bool),
        has_hi=jnp.zeros((), bool),
        done=jnp.zeros((), bool),
        status=jnp.asarray(FAILED_NO_FEASIBLE, jnp.int32),
        not_pd=jnp.zeros((), jnp.int32),
        best=prev,
        best_eta=eta0,
        best_kl=zero,
        has_best=jnp.zeros((), bool),
    )
    s = lax.while_loop(cond, body, init)
    ok = s.status <= LOOSE
    controller = _select(ok, s.best, prev)
    info = CStepInfo(
        eta=jnp.where(ok, s.best_eta, eta0),
        kl=jnp.where(ok, s.best_kl, zero),
        epsilon=epsilon,
        status=s.status,
        ok=ok,
        iterations=s.it,
        not_pd=s.not_pd,
    )
    return controller, info


def _select(pred: Array, a: LinearGaussianController, b: LinearGaussianController):
    return LinearGaussianController(
        K=jnp.where(pred, a.K, b.K),
        k=jnp.where(pred, a.k, b.k),
        cov=jnp.where(pred, a.cov, b.cov),
        chol_cov=jnp.where(pred, a.chol_cov, b.chol_cov),
        inv_cov=jnp.where(pred, a.inv_cov, b.inv_cov),
    )


def describe(info: CStepInfo) -> list[str]:
    """Host-side: one line per condition naming the outcome (for logs and error messages)."""
    status = np.atleast_1d(np.asarray(info.status))
    eta = np.atleast_1d(np.asarray(info.eta))
    kl = np.atleast_1d(np.asarray(info.kl))
    eps = np.atleast_1d(np.asarray(info.epsilon))
    its = np.atleast_1d(np.asarray(info.iterations))
    return [
        f"condition {i}: {STATUS_NAMES[int(s)]} (eta={e:.3g}, KL={k:.4g}/{p:.4g}, {n} passes)"
        for i, (s, e, k, p, n) in enumerate(
            zip(status.ravel(), eta.ravel(), kl.ravel(), eps.ravel(), its.ravel(), strict=False)
        )
    ]
