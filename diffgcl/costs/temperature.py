"""The learned cost's temperature, calibrated to the demonstrations' action precision.

The maximum-entropy model ``p(τ) ∝ exp(−c(τ))`` ties the cost's scale to how precise the expert
is: under linear dynamics ``x' = A x + B u + c`` and a quadratic cost, the MaxEnt controller is
the LQR controller with covariance ``Σ_t = Q_uu,t⁻¹`` (Levine & Abbeel 2014; the MaxEnt C-step
with η = 0). Scaling the cost by ``β = e^ρ`` scales every value function and ``Q_uu`` by ``β``
and leaves the gains ``K_t, k_t`` unchanged, so ``Σ_t(β) = Σ_t(1) / β`` and the entropy of the
action noise summed over t falls by exactly ``½·T·dU·log β``.

:func:`calibrated_log_temperature` chooses ``ρ`` so that the MaxEnt controller of ``e^ρ c``,
linearised about the demonstrations, has the entropy of the demos' own fitted controller
(:func:`diffgcl.costs.demo_controller.fit_demo_controller`): a moment match of the demos'
conditional action covariance, with the cost's *shape* left to the GCL likelihood. Why not the
likelihood's own scale: where the model is right (the LQ problem of ``experiments/lq_ioc.py``,
demos from the MaxEnt controller of a quadratic cost) GCL's fit already gives the demonstrator's
covariance (within 3 %), but on the arm the cost class cannot reproduce the demos' action profile
— where the expert saturates a motor, the linearised dynamics give the action no effect, the
learned controller's mean there is set by ``w_u`` alone and differs from the demos by ~2 rad/s
RMS — and the likelihood explains that mismatch with noise: the fitted cost was ~250× too flat
for the demos' precision (docs/decisions.md has the numbers).

Written for one condition; the caller averages ``ρ`` over conditions.
"""

from __future__ import annotations

import jax.numpy as jnp

from diffgcl.control.lqr import controller_entropy, lqr_backward
from diffgcl.costs.expansion import about_origin, expand_cost_samples
from diffgcl.types import Array, LinearDynamics, LinearGaussianController


def maxent_controller(
    residual_fn, dynamics: LinearDynamics, X: Array, U: Array
) -> LinearGaussianController:
    """MaxEnt (η = 0) LQR controller of the cost ``‖r(x, u, t)‖²`` expanded by Gauss–Newton about
    trajectories ``X: [N, T+1, dX]``, ``U: [N, T, dU]`` (averaged over them, as GPS expands about
    its samples), with ``dynamics`` (fields [T, ...]) linearised about the same trajectories."""
    quad = expand_cost_samples(residual_fn, X, U, gauss_newton=True)
    quad = about_origin(quad, X.mean(axis=0), U.mean(axis=0))
    return lqr_backward(dynamics, quad).controller


def calibrated_log_temperature(
    residual_fn, dynamics: LinearDynamics, X: Array, U: Array, target_entropy: Array
) -> Array:
    """``ρ`` such that the MaxEnt controller of ``e^ρ ‖r‖²`` about the demos ``X``, ``U`` has
    action entropy ``target_entropy`` (nats, summed over t): ``ρ = 2 (H(1) − H*) / (T dU)``, with
    ``H(1)`` the entropy at ``ρ = 0`` (``residual_fn`` is the untempered residual)."""
    T, dU = U.shape[-2:]
    entropy = controller_entropy(maxent_controller(residual_fn, dynamics, X, U))
    return 2.0 * (entropy - target_entropy) / (T * dU)


def temperature_entropy_drop(log_temperature: Array, T: int, dU: int) -> Array:
    """How much the MaxEnt controller's entropy (summed over t) falls when the cost is scaled
    by ``e^ρ``: ``½ T dU ρ`` nats."""
    return 0.5 * T * dU * jnp.asarray(log_temperature)
