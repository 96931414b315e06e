"""Mirror-descent GPS's policy half: the S-step and the policy's linearisation (Montgomery & Levine
2016; DESIGN §6).

**S-step.** After the C-step, the global policy is regressed onto the *new* local controllers at
the states the samples visited, each action weighted by the controller's precision there:

    L(θ) = (1/M) Σ_i ½ (μ*_i − μ_θ(o_i))ᵀ w_i P_i (μ*_i − μ_θ(o_i)),
    μ*_i = K_t x_i + k_t,  P_i = Σ_t⁻¹ of the new controller of x_i's condition at x_i's step t,

over the ``M = C·N·T`` (condition, sample, step) triples, by minibatch Adam (optax) in a
``lax.scan``. The per-sample weights ``w_i`` are normalised as in GPS's policy optimiser (mean
1, clipped at twice the robust median, divided by that median) and folded into the precision.
Where the controller is certain (large precision) the policy must follow it closely; where it
explores, loosely. This is the KL projection of the controllers onto the policy class for a
Gaussian policy with fixed covariance (the covariance terms separate, below).

**Variance.** The policy's diagonal, state-independent covariance minimises the same KL in
closed form: ``A = Σ_i w_i P_i / Σ_i w_i + 2·ent_reg·I``, ``var = 1 / diag(A)`` (GPS: the
precision averaged over the samples, plus an entropy regulariser).

**Linearisation.** The C-step's KL anchor is the policy as a linear-Gaussian controller around the
samples. GPS fits it by regressing ``π(o(x))`` on ``x`` with a GMM prior; here it is exact: the
Jacobian ``∂μ_θ(o(x))/∂x`` by forward-mode autodiff through the observation function (the
simulator's kinematics and sensors) at every sample state, averaged over the samples of each step
(the first-order least-squares fit), ``k_t`` so that the linear map reproduces the samples' mean
action, and the policy's own covariance ``diag(var)``.

Everything is written for one instance or one flat batch; vmap over conditions and seeds at the
call site.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from diffgcl.policies.network import GaussianPolicy, PolicyParams
from diffgcl.tracing import value_and_jacfwd
from diffgcl.types import Array, LinearGaussianController, PRNGKey, make_controller


@dataclass(frozen=True)
class SStepConfig:
    """Settings of the S-step regression.

    n_steps: Adam steps per S-step (warm-started from the previous policy); batch_size: triples
    per step, drawn with replacement; learning_rate, max_grad_norm: Adam and global-norm clipping;
    ent_reg: GPS's entropy regulariser on the variance; weight_clip: weights are clipped at this
    multiple of their robust median (GPS: 2).
    """

    n_steps: int = 300
    batch_size: int = 128
    learning_rate: float = 1e-3
    max_grad_norm: float = 1e2
    ent_reg: float = 0.0
    weight_clip: float = 2.0

    def __post_init__(self):
        if self.n_steps < 0 or self.batch_size < 1:
            raise ValueError("SStepConfig: n_steps >= 0 and batch_size >= 1")


@struct.dataclass
class PolicyState:
    """The global policy and its optimiser: params (:class:`PolicyParams`), opt_state (optax state
    of ``params.net``), step: int32 Adam steps taken."""

    params: PolicyParams
    opt_state: optax.OptState
    step: Array


@struct.dataclass
class SStepMetrics:
    """loss: mean S-step loss over the update's steps; final_loss: the last step's; entropy:
    the policy's action entropy per step after the update (nats); left_out: conditions whose
    samples were left out (:func:`diffgcl.algorithms.mdgps.condition_weights`; 0 here)."""

    loss: Array
    final_loss: Array
    entropy: Array
    left_out: Array


def controller_targets(controller: LinearGaussianController, X: Array) -> tuple[Array, Array]:
    """Targets of the S-step from one condition's controller (fields [T, ...]) at its samples
    ``X: [N, T+1, dX]``: ``μ* = K_t x + k_t`` [N, T, dU] and the precision [N, T, dU, dU]."""
    mu = jnp.einsum("tij,ntj->nti", controller.K, X[:, :-1]) + controller.k
    prec = jnp.broadcast_to(controller.inv_cov, (X.shape[0], *controller.inv_cov.shape))
    return mu, prec


def normalise_weights(w: Array, clip: float = 2.0) -> Array:
    """GPS's per-sample weight normalisation: scale to mean 1, clip at ``clip`` × the median of
    the weights above 1e-2, divide by that median. w: [M] -> [M]."""
    w = w * (w.shape[0] / jnp.maximum(w.sum(), 1e-30))
    big = w > 1e-2
    median = jnp.nanmedian(jnp.where(big, w, jnp.nan))
    median = jnp.where(jnp.isfinite(median) & (median > 0), median, 1.0)
    return jnp.minimum(w, clip * median) / median


def s_step_loss(policy: GaussianPolicy, params: PolicyParams, O: Array, mu: Array, prec: Array):
    """``(1/M) Σ_i ½ rᵢᵀ Pᵢ rᵢ``, ``rᵢ = μ*ᵢ − μ_θ(oᵢ)``, for O: [M, dO], mu: [M, dU] and the
    (weighted) precisions prec: [M, dU, dU]."""
    r = mu - jax.vmap(policy.mean_action, in_axes=(None, 0))(params, O)
    return 0.5 * jnp.mean(jnp.einsum("mi,mij,mj->m", r, prec, r))


def policy_variance(prec: Array, w: Array, ent_reg: float = 0.0) -> Array:
    """``1 / diag(Σ wᵢPᵢ / Σ wᵢ + 2·ent_reg·I)``: the diagonal variance [dU] from precisions
    prec: [M, dU, dU] and weights w: [M]."""
    A = jnp.einsum("m,mij->ij", w, prec) / jnp.maximum(w.sum(), 1e-30)
    return 1.0 / (jnp.diagonal(A) + 2.0 * ent_reg)


def linearise_policy(
    policy: GaussianPolicy,
    params: PolicyParams,
    obs_fn: Callable[[Array], Array],
    X: Array,
) -> LinearGaussianController:
    """The policy as a linear-Gaussian controller around one condition's samples
    ``X: [N, T+1, dX]`` (states 0 .. T−1): ``K_t = mean_n ∂μ_θ(o(x))/∂x`` at the samples (forward
    mode), ``k_t = mean_n μ_θ(o(x_n,t)) − K_t · mean_n x_n,t``, covariance ``diag(var)``.
    ``obs_fn(x: [dX]) -> o: [dO]`` (noise-free). Returns fields [T, ...].

    :func:`linearise_policy_at` is the same from the observations and their Jacobians, which the
    simulator computes (the algorithms use that one)."""
    states = X[:, :-1]
    O, J = jax.vmap(jax.vmap(value_and_jacfwd(obs_fn)))(states)
    return linearise_policy_at(policy, params, O, J, X)


def linearise_policy_at(
    policy: GaussianPolicy, params: PolicyParams, O: Array, J: Array, X: Array
) -> LinearGaussianController:
    """:func:`linearise_policy` by the chain rule ``∂μ_θ(o(x))/∂x = ∂μ_θ/∂o · ∂o/∂x`` from the
    noise-free observations ``O: [N, T, dO]`` and their Jacobians ``J: [N, T, dO, dX]`` at one
    condition's sample states ``X: [N, T+1, dX]`` (states 0 .. T−1). Returns fields [T, ...]."""

    def at_obs(o, J_o):
        u, du_do = value_and_jacfwd(lambda o: policy.mean_action(params, o))(o)
        return u, du_do @ J_o

    u, K_all = jax.vmap(jax.vmap(at_obs))(O, J)  # [N, T, dU], [N, T, dU, dX]
    K = K_all.mean(axis=0)
    k = u.mean(axis=0) - jnp.einsum("tij,tj->ti", K, X[:, :-1].mean(axis=0))
    T, dU = k.shape
    cov = jnp.broadcast_to(jnp.diag(params.var), (T, dU, dU))
    return make_controller(K, k, cov)


class PolicyLearner(NamedTuple):
    """``init(params) -> PolicyState`` and ``s_step(state, key, O, mu, prec, w=None) ->
    (PolicyState, SStepMetrics)`` on one flat batch (O: [M, dO], mu: [M, dU], prec:
    [M, dU, dU], w: [M], default ones); the optax ``optimiser`` acting on ``params.net``. Pure;
    jit at the call site."""

    init: Callable[[PolicyParams], PolicyState]
    s_step: Callable[..., tuple[PolicyState, SStepMetrics]]
    optimiser: optax.GradientTransformation


def make_policy_learner(
    policy: GaussianPolicy, config: SStepConfig, learning_rate=None
) -> PolicyLearner:
    """Build the S-step of ``policy`` (see the module docstring). ``learning_rate``: an optax
    schedule in place of the constant ``config.learning_rate`` (counted in Adam steps over the
    learner's whole life, so meant for a one-shot fit such as behaviour cloning)."""
    lr = config.learning_rate if learning_rate is None else learning_rate
    optimiser = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(lr))

    def init(params: PolicyParams) -> PolicyState:
        return PolicyState(
            params=params, opt_state=optimiser.init(params.net), step=jnp.zeros((), jnp.int32)
        )

    def s_step(state: PolicyState, key: PRNGKey, O, mu, prec, w=None):
        M = O.shape[0]
        w = jnp.ones(M, O.dtype) if w is None else w
        w = normalise_weights(w, config.weight_clip)
        prec_w = w[:, None, None] * prec

        def step(state: PolicyState, key: PRNGKey):
            idx = jax.random.randint(key, (config.batch_size,), 0, M)

            def loss(net):
                return s_step_loss(
                    policy, state.params.replace(net=net), O[idx], mu[idx], prec_w[idx]
                )

            value, grads = jax.value_and_grad(loss)(state.params.net)
            updates, opt_state = optimiser.update(grads, state.opt_state, state.params.net)
            net = optax.apply_updates(state.params.net, updates)
            new = PolicyState(
                params=state.params.replace(net=net), opt_state=opt_state, step=state.step + 1
            )
            return new, value

        if config.n_steps > 0:
            state, losses = jax.lax.scan(step, state, jax.random.split(key, config.n_steps))
        else:
            losses = jnp.zeros((1,), O.dtype)
        var = policy_variance(prec, w, config.ent_reg)
        state = state.replace(params=state.params.replace(var=var.astype(state.params.var.dtype)))
        metrics = SStepMetrics(
            loss=losses.mean(),
            final_loss=losses[-1],
            entropy=policy.entropy(state.params),
            left_out=jnp.zeros((), jnp.int32),
        )
        return state, metrics

    return PolicyLearner(init=init, s_step=s_step, optimiser=optimiser)
