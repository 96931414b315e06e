"""How well do learned controllers fit the demonstrations as a *distribution*?

GCL fits the maximum-entropy model ``p(τ) ∝ exp(−c(τ))`` to the demos, and the MaxEnt C-step
turns the learned cost into linear-Gaussian controllers whose covariance is the inverse action
curvature of that cost: a cost too flat by a factor ``κ`` gives controllers ``√κ`` times too
noisy, whatever their noise-free mean does. Three figures say whether the scale (the model's
temperature) is right, each for one condition:

* the entropy of the controller's action noise (nats, summed over t) beside that of the demos'
  own fitted controller (:func:`diffgcl.costs.demo_controller.fit_demo_controller`), and their
  difference, the *entropy gap* (≈ 200 nats per factor e² in action variance on the arm's 2 action
  dimensions over 100 steps);
* the demos' mean log-likelihood ``Σ_t log N(u_t; K_t x_t + k_t, Σ_t)`` under the controller
  (the dynamics terms are the same for every controller), beside the same under the demos' own;
* the success rate of the controller's noisy samples: rollouts with its own ``Σ_t`` and the noise
  smoothed as in GPS's samples (``smooth_sigma``), and with white noise.

Pure and written for one run (fields [C, ...]); vmap over seeds at the call site.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from diffgcl.control.lqr import controller_entropy
from diffgcl.costs.buffer import action_log_densities
from diffgcl.types import Array, Env, LinearGaussianController, PRNGKey


@struct.dataclass
class DistributionFit:
    """Per condition, [C] each: entropy and demo_entropy (nats, summed over t) of the controller
    and of the demos' own controller, entropy_gap = entropy − demo_entropy; demo_log_likelihood
    (mean over demos, nats) under the controller and demo_self_log_likelihood under the demos'
    own; sample_success (smoothed noise, as GPS samples) and sample_success_white: fraction of
    the noisy samples that succeed."""

    entropy: Array
    demo_entropy: Array
    entropy_gap: Array
    demo_log_likelihood: Array
    demo_self_log_likelihood: Array
    sample_success: Array
    sample_success_white: Array


def demo_log_likelihood(controller: LinearGaussianController, X: Array, U: Array) -> Array:
    """Mean over demos ``X: [N, T+1, dX]``, ``U: [N, T, dU]`` of their action log-likelihood under
    one controller (fields [T, ...]): scalar, nats."""
    one = jax.tree.map(lambda a: a[None], controller)
    return action_log_densities(one, X, U)[:, 0].mean()


def noisy_sample_success(
    env: Env,
    controller: LinearGaussianController,
    x0: Array,
    key: PRNGKey,
    n: int,
    smooth_sigma: float | None,
) -> Array:
    """Fraction of ``n`` rollouts of one controller (fields [T, ...]) from ``x0: [dX]`` with its
    own noise (``smooth_sigma``: time-smoothing in steps, None: white) that succeed: scalar."""
    from diffgcl.sim.rollout import sample_controller

    samples = sample_controller(env, controller, x0, key, n, smooth_sigma=smooth_sigma)
    return jax.vmap(env.success)(samples.X).mean()


def distribution_fit(
    env: Env,
    controller: LinearGaussianController,
    demo_controller: LinearGaussianController,
    demo_X: Array,
    demo_U: Array,
    key: PRNGKey,
    *,
    n_samples: int = 20,
    smooth_sigma: float | None = 2.0,
) -> DistributionFit:
    """The figures of the module docstring for one run: controller and demo_controller fields
    [C, T, ...], demos ``demo_X: [C, N, T+1, dX]``, ``demo_U: [C, N, T, dU]``."""
    X0 = jnp.asarray(env.initial_states())
    C = X0.shape[0]
    key_smooth, key_white = jax.random.split(key)
    entropy = jax.vmap(controller_entropy)(controller)
    demo_entropy = jax.vmap(controller_entropy)(demo_controller)

    def success(key, sigma):
        one = lambda c, x0, k: noisy_sample_success(env, c, x0, k, n_samples, sigma)
        return jax.vmap(one)(controller, X0, jax.random.split(key, C))

    return DistributionFit(
        entropy=entropy,
        demo_entropy=demo_entropy,
        entropy_gap=entropy - demo_entropy,
        demo_log_likelihood=jax.vmap(demo_log_likelihood)(controller, demo_X, demo_U),
        demo_self_log_likelihood=jax.vmap(demo_log_likelihood)(demo_controller, demo_X, demo_U),
        sample_success=success(key_smooth, smooth_sigma),
        sample_success_white=success(key_white, None),
    )
