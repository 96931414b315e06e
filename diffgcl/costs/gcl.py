"""Guided Cost Learning's cost update: sample-based MaxEnt IOC with fusion importance weights.

Objective for one condition (Finn et al. 2016a, eq. 3–4; the seed's eq. 2.12), in the log domain::

    L(φ) = 1/N Σ_demo c_φ(τ_i) + log( 1/M Σ_j z_j exp(−c_φ(τ_j)) ) + λ_lcr g_lcr + λ_mono g_mono

with ``c_φ(τ) = Σ_t c(x_t, u_t, t) + c(x_T, 0, T)`` and ``log z_j = −log q(τ_j)``. The partition
sum runs over a minibatch of stored samples and — GCL's fix for an objective that is otherwise
unbounded in practice — the demo minibatch appended to it. Its gradient is
``mean_demo ∂c/∂φ − Σ_j (w_j / Σ_k w_k) ∂c/∂φ(τ_j)``, ``w_j = z_j exp(−c_φ(τ_j))`` (the seed's
eq. 2.13), so the value of ``log Z`` only needs to be right up to a constant.

Fusion weights: the batch is a draw from the mixture of every proposal that produced it, so
``q(τ) = Σ_κ π_κ q_κ(τ)`` with ``log q_κ(τ) = Σ_t log N(u_t; K^κ_t x_t + k^κ_t, Σ^κ_t)`` (dynamics
and initial-state terms are common to every proposal and to the target, and cancel). Mixture
weights ``π`` (``GCLConfig.mixture``):

* ``"counts"`` (default, the deterministic-mixture / balance-heuristic weights): a sample minibatch
  of size ``M_s`` drawn uniformly from the buffer is a draw from ``Σ_κ (n_κ/n) q_κ``; with ``M_d``
  demos appended, ``π_demo = M_d / M`` and ``π_κ = (M_s / M) · n_κ / n``. With equal samples per
  controller this is GCL's uniform average over controllers, with the demo controller weighted by
  its share of the batch.
* ``"uniform"``: ``log q = logmeanexp_κ log q_κ`` over the stored controllers and the demo
  controller, as written in GCL.

Without fusion (ablation) each trajectory is weighted by the density of the proposal that drew it
alone (its own controller; the demo controller for demos).

Regularisers (Finn et al. 2016a, §4.3), on the sequence of *state* costs
``s_t = ‖A y(x_t) + b‖²``, t = 0..T (the action term is left out: i.i.d. exploration noise would
make every sequence jagged and the penalty would fight ``w_u`` rather than shape the state cost):

* local constant rate on demos and samples: ``g_lcr(τ) = Σ_t [(s_{t+1} − s_t) − (s_t − s_{t−1})]²``;
* monotonic on demos: ``g_mono(τ) = Σ_t max(0, s_t − s_{t−1} − m)²``. Sign: demonstrations make
  progress, so their cost should *decrease* along the trajectory; the penalty applies when the
  cost increases by more than the slack ``m`` (GCL's form, m = 1; m < 0 demands strict decrease).
  The GPS port's opposite sign penalised decreases, which contradicts the demos reaching a goal.

* goal (ours, off by default) on demos: ``g_goal(τ) = ‖∂s/∂z (x_T)‖²``, the squared gradient of
  the state cost at the demo's final state with respect to the *normalised* state ``z`` (so the
  weight is unit-free). It says that the demonstrator ends where it wants to stay: the final state
  is a stationary point of the state cost. Sample-based MaxEnt IOC does not pin the cost's
  minimum by itself — once the samples overlap the demos near the goal the objective has no
  gradient there, and a demonstrator that overshoots (the arm's GPS expert does, by 0.14 rad)
  drags the minimum into the overshoot.

Demo tails (``WeightedSamples.tail``, off when None): where a demo was recorded past the window
that GCL compares with the samples, the monotonic regulariser runs on over those states and the
goal term sits at the last recorded one. The likelihood still sees the window alone (the samples
have no tail to compare with); the tail only says where the demonstrator went next. A window cut
mid-manoeuvre (the USV's end mid-return to the course line) thus still gets a cost that falls
towards where the recording ends, and a stationary point there rather than mid-manoeuvre.

Without importance weights (``GCLConfig.importance_weights = False``) the samples are taken as
draws from the current cost's own MaxEnt distribution ``p_φ(τ) ∝ exp(−c_φ(τ))`` — the LQR
controllers optimised for the cost are its Laplace approximation — so every sample weighs the
same: ``log q_j := −c_φ(τ_j)`` (held constant), the log partition term is 0 and its gradient is the
samples' mean ``∂c/∂φ``. The update is then MaxEnt IRL's feature-expectation matching
(``mean_demo ∂c/∂φ − mean_sample ∂c/∂φ``; for a cost linear in its parameters, demos' minus
samples' feature sums), with no importance weights to degenerate: over T = 300 steps of a 2-D
action the proposal densities of a sample batch spread over tens of nats, and the
self-normalised weights can rest on one sample. The estimate is biased by the controllers'
KL step (they lag the cost) and is only as good as the Laplace approximation; the demos are not
draws from ``p_φ`` and stay out of the partition.

Tempered importance weights (``GCLConfig.min_ess``, off by default): over hundreds of steps the
log weights ``a_j = −c_φ(τ_j) − log q(τ_j)`` of a batch spread over hundreds of nats and the
self-normalised weights rest on one trajectory (effective sample size 1), so the update compares
the demos with that one sample alone. The tempered partition term ``(1/α) log(1/M Σ_j e^{α a_j})``,
``0 < α ≤ 1``, has the gradient ``−Σ_j softmax(α a)_j ∂c/∂φ(τ_j)``: the weights ``(p/q)^α`` of
tempered importance sampling. ``α = 1`` is GCL's estimate, ``α → 0`` feature matching
(every sample alike). Per condition and update step, ``α`` is the largest value in
``[10⁻⁴, 1]`` whose weights keep an effective sample size of at least ``min_ess`` times the
batch (bisection on ``log α``, held constant under the gradient), as adaptive tempering does in
sequential Monte Carlo: where the weights are healthy the update is GCL's own. Unlike feature
matching the objective stays bounded below when the demos are in the partition: as the cost's
scale ``s → ∞`` the term tends to ``−s min_j c(τ_j)``, which the demos' own cost bounds.

All are averaged over the trajectories they apply to. The update is optax Adam on ``params.net``
(the input normaliser is data, not a parameter) with ``n_steps`` minibatch steps in ``lax.scan``.

Pre-training: :meth:`CostLearner.pretrain` runs the same objective for ``pretrain_steps`` steps
before the outer loop, with whatever samples the caller has at that point — in rGCL, the initial
controller's samples (its buffer holds one controller) plus the demos in the partition. It thus
fits the cost that best separates the demos from the initial controller's behaviour; the seed did
one such pass before its loop.

The objective fits the cost at temperature ``ρ = 0`` (``e^ρ`` scales the cost, see
:mod:`diffgcl.costs.network`): the likelihood and the regularisers shape the cost and give it a
scale; a temperature set from the demos' precision (:mod:`diffgcl.costs.temperature`) rescales it
for the controllers without feeding back into this fit.

Everything is written for one condition and averaged over a leading condition axis ``C`` in the
update (each condition has its own partition function).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from diffgcl.costs.buffer import (
    SampleBuffer,
    action_log_densities,
    controller_log_densities,
    samples_per_controller,
    stored_log_densities,
)
from diffgcl.costs.network import CostNetwork, CostParams, untempered
from diffgcl.types import Array, LinearGaussianController, PRNGKey


@dataclass(frozen=True)
class GCLConfig:
    """Cost-update settings (shape-changing ones are static; all are hashable).

    n_steps: Adam steps per update; pretrain_steps: steps of :meth:`CostLearner.pretrain`;
    demo_batch / sample_batch: minibatch sizes per condition (capped at what is available);
    learning_rate, max_grad_norm: Adam and global-norm clipping; weight_decay: decoupled (AdamW)
    decay of the network's weight matrices (``features`` kernels other than the ``linear_skip``
    branch, and ``A``), pulling unused
    nonlinear features towards zero; fusion: mixture proposal (else
    each sample's own proposal); demos_in_partition: append the demo batch to the partition term;
    mixture: ``"counts"`` or ``"uniform"`` (see the module docstring); lcr_weight, mono_weight,
    mono_slack: regularisers; goal_weight: the goal regulariser (see the module docstring);
    importance_weights: weigh the partition's samples by ``exp(−c)/q`` (GCL); ``False`` treats
    them as draws from the current cost's own MaxEnt distribution (the LQR controllers
    optimised for it stand in for it), so each weighs the same (module docstring);
    min_ess: temper the importance weights so that their effective sample size stays at least
    this fraction of the partition's batch (0: GCL's untempered weights; module docstring).
    """

    n_steps: int = 20
    pretrain_steps: int = 200
    demo_batch: int = 5
    sample_batch: int = 10
    learning_rate: float = 1e-3
    max_grad_norm: float = 1e3
    weight_decay: float = 0.0
    fusion: bool = True
    demos_in_partition: bool = True
    mixture: str = "counts"
    lcr_weight: float = 0.0
    mono_weight: float = 0.0
    mono_slack: float = 1.0
    goal_weight: float = 0.0
    importance_weights: bool = True
    min_ess: float = 0.0

    def __post_init__(self):
        if not 0.0 <= self.min_ess <= 1.0:
            raise ValueError(
                f"GCLConfig: min_ess={self.min_ess} is a fraction of the batch, in [0, 1]"
            )
        if not self.importance_weights and self.demos_in_partition:
            raise ValueError(
                "GCLConfig: importance_weights=False treats the samples as draws from the cost's "
                "own MaxEnt distribution; the demos are not, so set demos_in_partition=False"
            )

    @property
    def reads_tails(self) -> bool:
        """Whether a demo's tail (``WeightedSamples.tail``) changes the objective: only the
        monotonic and goal regularisers read it."""
        return self.mono_weight != 0.0 or self.goal_weight != 0.0


@struct.dataclass
class WeightedSamples:
    """Trajectories with their log proposal densities (one condition).

    X: [S, T+1, dX], U: [S, T, dU], log_q: [S] (``log q(τ)``, so ``log z = −log_q``), valid: [S];
    tail: demos only, None or [S, L+1, dX]: each demo's recorded states from its last one in
    ``X`` on (``tail[:, 0] == X[:, -1]``), padded with its last recorded state; the monotonic
    and goal regularisers run over ``X`` and the tail (module docstring).
    """

    X: Array
    U: Array
    log_q: Array
    valid: Array
    tail: Array | None = None


@struct.dataclass
class GCLState:
    """params: the cost's :class:`CostParams`; opt_state: Adam's state for ``params.net``;
    step: int32 scalar, gradient steps taken."""

    params: CostParams
    opt_state: optax.OptState
    step: Array


@struct.dataclass
class GCLMetrics:
    """Per gradient step (stacked to [n_steps] by the update): loss, demo_cost (mean demo
    trajectory cost), log_partition, lcr, mono, goal (the regularisers' unweighted values), ess
    (effective sample size of the normalised partition weights, tempered where they are,
    averaged over conditions), tempering (the weights' exponent ``α``, 1 when untempered),
    grad_norm."""

    loss: Array
    demo_cost: Array
    log_partition: Array
    lcr: Array
    mono: Array
    goal: Array
    ess: Array
    tempering: Array
    grad_norm: Array


def lcr_penalty(s: Array) -> Array:
    """Local constant rate ``Σ_t [(s_{t+1} − s_t) − (s_t − s_{t−1})]²`` of ``s: [T+1]``."""
    return jnp.sum((s[2:] - 2.0 * s[1:-1] + s[:-2]) ** 2)


def mono_penalty(s: Array, slack: float) -> Array:
    """Monotonic decrease ``Σ_t max(0, s_t − s_{t−1} − slack)²`` of ``s: [T+1]``."""
    return jnp.sum(jnp.maximum(0.0, s[1:] - s[:-1] - slack) ** 2)


def goal_penalty(network: CostNetwork, params: CostParams, x: Array, t: Array | int) -> Array:
    """``‖∂s/∂z‖²`` at a demo's final state ``x: [dX]`` (step ``t``), with ``s`` the state cost
    and ``z`` the normalised state (or the normalised features with a feature map): the chain
    rule through the normaliser's scale, ``∂s/∂z = ∂s/∂φ · std``."""
    norm = jax.lax.stop_gradient(params.norm)
    std = jnp.maximum(jnp.sqrt(norm.var), network.config.std_floor)
    f = network.state_input(x)
    grad = jax.grad(lambda f: network.state_cost_of_input(params, f, t))(f)
    return jnp.sum((grad * std) ** 2)


def _mixture_log_weights(
    counts: Array, n_demo_in_batch: Array, n_sample_in_batch: Array, config: GCLConfig
) -> tuple[Array, Array]:
    """Log mixture weights ``(log π_κ: [Kc], log π_demo: [])`` of the fusion proposal."""
    present = counts > 0
    if config.mixture == "uniform":
        n_comp = present.sum() + 1.0
        log_pi = jnp.where(present, -jnp.log(n_comp), -jnp.inf)
        return log_pi, -jnp.log(n_comp)
    if config.mixture != "counts":
        raise ValueError(f"unknown mixture {config.mixture!r}; use 'counts' or 'uniform'")
    total = n_demo_in_batch + n_sample_in_batch
    share = counts / jnp.maximum(counts.sum(), 1) * n_sample_in_batch / total
    log_pi = jnp.where(present, jnp.log(jnp.where(present, share, 1.0)), -jnp.inf)
    log_pi_demo = jnp.where(n_demo_in_batch > 0, jnp.log(n_demo_in_batch / total), -jnp.inf)
    return log_pi, log_pi_demo


def fusion_weighted_samples(
    buffer: SampleBuffer,
    demo_controller: LinearGaussianController,
    demo_X: Array,
    demo_U: Array,
    config: GCLConfig,
) -> tuple[WeightedSamples, WeightedSamples]:
    """Stored samples and demos (one condition) with their fusion log proposal densities.

    demo_X: [N, T+1, dX], demo_U: [N, T, dU]. Returns ``(samples: [S], demos: [N])``. With
    ``config.fusion`` off, each trajectory gets the density of its own proposal only.
    """
    N = demo_X.shape[0]
    counts = samples_per_controller(buffer)
    n_samples = jnp.minimum(config.sample_batch, buffer.valid.sum()).astype(demo_X.dtype)
    n_demos = float(min(config.demo_batch, N)) if config.demos_in_partition else 0.0
    log_pi, log_pi_demo = _mixture_log_weights(counts, jnp.asarray(n_demos), n_samples, config)

    def log_proposal(X: Array, U: Array, log_q_ctrl: Array, own: Array | None) -> Array:
        """Log proposal densities of trajectories [M] given their densities under the stored
        controllers ``log_q_ctrl: [M, Kc]`` (``own``: each one's controller slot)."""
        demo_ctrl = jax.tree.map(lambda a: a[None], demo_controller)
        log_q_demo = action_log_densities(demo_ctrl, X, U)[:, 0]  # [M]
        if not config.fusion:
            if own is None:
                return log_q_demo
            return jnp.take_along_axis(log_q_ctrl, own[:, None], axis=1)[:, 0]
        terms = jnp.concatenate([log_pi + log_q_ctrl, (log_pi_demo + log_q_demo)[:, None]], 1)
        return jax.nn.logsumexp(terms, axis=1)

    log_q_samples = log_proposal(buffer.X, buffer.U, stored_log_densities(buffer), buffer.source)
    log_q_demos = log_proposal(
        demo_X, demo_U, controller_log_densities(buffer, demo_X, demo_U), None
    )
    samples = WeightedSamples(X=buffer.X, U=buffer.U, log_q=log_q_samples, valid=buffer.valid)
    demos = WeightedSamples(X=demo_X, U=demo_U, log_q=log_q_demos, valid=jnp.ones(N, bool))
    return samples, demos


def _state_and_action_costs(
    network: CostNetwork, params: CostParams, X: Array, U: Array
) -> tuple[Array, Array]:
    """State costs ``s: [T+1]`` and the trajectory cost (scalar) of one trajectory."""
    T = U.shape[0]
    s = jax.vmap(network.state_cost, in_axes=(None, 0, 0))(params, X, jnp.arange(T + 1))
    action = jax.vmap(network.action_cost, in_axes=(None, 0))(params, U)
    return s, s.sum() + action.sum()


def _masked_mean(v: Array, mask: Array) -> Array:
    return jnp.sum(jnp.where(mask, v, 0.0)) / jnp.maximum(mask.sum(), 1)


def gcl_objective(
    network: CostNetwork,
    params: CostParams,
    demos: WeightedSamples,
    samples: WeightedSamples,
    config: GCLConfig,
) -> tuple[Array, GCLMetrics]:
    """The regularised GCL objective for one condition's minibatches ``demos: [M_d]``,
    ``samples: [M_s]``; returns ``(loss, metrics)`` (``grad_norm`` left at 0). The cost is taken
    at ``ρ = 0`` (:func:`diffgcl.costs.network.untempered`)."""
    params = untempered(params)
    costs_of = jax.vmap(_state_and_action_costs, in_axes=(None, None, 0, 0))
    s_demo, c_demo = costs_of(network, params, demos.X, demos.U)
    s_samp, c_samp = costs_of(network, params, samples.X, samples.U)

    demo_cost = _masked_mean(c_demo, demos.valid)
    log_q = samples.log_q if config.importance_weights else -jax.lax.stop_gradient(c_samp)
    a_samp = jnp.where(samples.valid, -c_samp - log_q, -jnp.inf)
    mask = samples.valid
    if config.demos_in_partition:
        a_demo = jnp.where(demos.valid, -c_demo - demos.log_q, -jnp.inf)
        a_samp = jnp.concatenate([a_samp, a_demo])
        mask = jnp.concatenate([mask, demos.valid])
    count = mask.sum()
    # Safe logsumexp: an all-masked batch contributes 0 and no NaN gradient.
    a_safe = jnp.where(mask, a_samp, jnp.finfo(c_demo.dtype).min)
    if config.min_ess > 0.0:
        alpha = tempering_exponent(a_safe, mask, config.min_ess)
    else:
        alpha = jnp.ones((), c_demo.dtype)
    log_partition = jnp.where(
        count > 0,
        (jax.nn.logsumexp(alpha * a_safe, where=mask) - jnp.log(jnp.maximum(count, 1))) / alpha,
        0.0,
    )
    ess = effective_sample_size(alpha * a_safe, mask)

    lcr_all = jnp.concatenate([jax.vmap(lcr_penalty)(s_samp), jax.vmap(lcr_penalty)(s_demo)])
    lcr = _masked_mean(lcr_all, jnp.concatenate([samples.valid, demos.valid]))
    T = demos.U.shape[-2]
    if demos.tail is None:
        s_mono, x_end, t_end = s_demo, demos.X[:, -1], T
    else:
        L = demos.tail.shape[-2] - 1
        state_costs = jax.vmap(network.state_cost, in_axes=(None, 0, 0))
        s_tail = jax.vmap(state_costs, in_axes=(None, 0, None))(
            params, demos.tail[:, 1:], T + 1 + jnp.arange(L)
        )
        s_mono, x_end, t_end = jnp.concatenate([s_demo, s_tail], 1), demos.tail[:, -1], T + L
    mono_all = jax.vmap(mono_penalty, in_axes=(0, None))(s_mono, config.mono_slack)
    mono = _masked_mean(mono_all, demos.valid)
    goal_all = jax.vmap(goal_penalty, in_axes=(None, None, 0, None))(network, params, x_end, t_end)
    goal = _masked_mean(goal_all, demos.valid)

    loss = (
        demo_cost
        + log_partition
        + config.lcr_weight * lcr
        + config.mono_weight * mono
        + config.goal_weight * goal
    )
    metrics = GCLMetrics(
        loss=loss,
        demo_cost=demo_cost,
        log_partition=log_partition,
        lcr=lcr,
        mono=mono,
        goal=goal,
        ess=ess,
        tempering=alpha,
        grad_norm=jnp.zeros_like(loss),
    )
    return loss, metrics


def effective_sample_size(log_w: Array, mask: Array) -> Array:
    """``1 / Σ w̃²`` of the self-normalised weights ``w̃ = softmax(log_w)`` over ``mask``."""
    w = jnp.where(mask, jax.nn.softmax(log_w, where=mask), 0.0)
    return 1.0 / jnp.maximum(jnp.sum(w**2), 1e-30)


def tempering_exponent(log_w: Array, mask: Array, min_ess: float, iterations: int = 40) -> Array:
    """The largest ``α ∈ [10⁻⁴, 1]`` with ``effective_sample_size(α log_w) ≥ min_ess · count``
    (1 when ``α = 1`` already has it), by bisection on ``log α``. No gradient flows through it."""
    log_w = jax.lax.stop_gradient(log_w)
    target = min_ess * mask.sum()
    lo, hi = jnp.log(1e-4), jnp.zeros((), log_w.dtype)

    def ess_at(log_alpha):
        return effective_sample_size(jnp.exp(log_alpha) * log_w, mask)

    def bisect(_, bounds):
        lo, hi = bounds
        mid = 0.5 * (lo + hi)
        ok = ess_at(mid) >= target
        return jnp.where(ok, mid, lo), jnp.where(ok, hi, mid)

    lo, hi = jax.lax.fori_loop(0, iterations, bisect, (jnp.asarray(lo, log_w.dtype), hi))
    return jnp.where(ess_at(jnp.zeros_like(hi)) >= target, 1.0, jnp.exp(lo))


def _select(key: PRNGKey, valid: Array, n: int) -> tuple[Array, Array]:
    """``n`` distinct slots drawn uniformly among ``valid: [S]`` (Gumbel top-k); returns
    ``(idx: [n], mask: [n])`` — mask is False where fewer than n slots were valid."""
    score = jax.random.gumbel(key, valid.shape) + jnp.where(valid, 0.0, -jnp.inf)
    _, idx = jax.lax.top_k(score, n)
    return idx, valid[idx]


def minibatch(key: PRNGKey, data: WeightedSamples, n: int) -> WeightedSamples:
    """``n`` distinct valid entries of ``data: [S]`` drawn uniformly; entries past the number of
    valid ones come back with ``valid=False``."""
    idx, mask = _select(key, data.valid, min(n, data.valid.shape[-1]))
    taken = jax.tree.map(lambda a: a[idx], data)
    return taken.replace(valid=mask)


class CostLearner(NamedTuple):
    """``init(key) -> GCLState``, ``update(state, key, demos, samples) -> (state, metrics)`` (
    ``config.n_steps`` steps; metrics stacked [n_steps]) and ``pretrain`` (same, with
    ``config.pretrain_steps``), ``loss(params, demos, samples)`` on whole sets, and the optax
    ``optimiser`` acting on ``params.net``. ``demos: WeightedSamples [C, N]``,
    ``samples: WeightedSamples [C, S]`` with a leading condition axis. Pure; jit at the call
    site."""

    init: Callable[..., GCLState]
    update: Callable[..., tuple[GCLState, GCLMetrics]]
    pretrain: Callable[..., tuple[GCLState, GCLMetrics]]
    loss: Callable[..., tuple[Array, GCLMetrics]]
    optimiser: optax.GradientTransformation


def weight_decay_mask(net: dict) -> dict:
    """Weight decay on the output map ``A`` and every kernel under ``features`` except the
    linear branch (``linear_skip``); never on biases or the action weight."""
    mask = jax.tree.map(lambda _: False, net)
    if "A" in net:
        mask["A"] = True
    if "features" in net:
        mask["features"] = jax.tree_util.tree_map_with_path(
            lambda path, _: path[-1].key == "kernel" and path[0].key != "linear",
            net["features"],
        )
    return mask


def cost_optimiser(config: GCLConfig, learning_rate) -> optax.GradientTransformation:
    """Clipped AdamW on ``params.net`` (the learning rate may be a traced value)."""
    return optax.chain(
        optax.clip_by_global_norm(config.max_grad_norm),
        optax.adamw(learning_rate, weight_decay=config.weight_decay, mask=weight_decay_mask),
    )


def make_cost_learner(network: CostNetwork, config: GCLConfig) -> CostLearner:
    """Build the (init, update) pair of the GCL cost update for ``network``."""
    optimiser = cost_optimiser(config, config.learning_rate)

    def init(key: PRNGKey, params: CostParams | None = None) -> GCLState:
        params = network.init(key) if params is None else params
        return GCLState(
            params=params, opt_state=optimiser.init(params.net), step=jnp.zeros((), jnp.int32)
        )

    def batch_loss(net: dict, norm, demos, samples) -> tuple[Array, GCLMetrics]:
        params = CostParams(net=net, norm=norm, log_temperature=jnp.zeros((), norm.mean.dtype))
        per_condition = jax.vmap(gcl_objective, in_axes=(None, None, 0, 0, None))
        loss, metrics = per_condition(network, params, demos, samples, config)
        return loss.mean(), jax.tree.map(jnp.mean, metrics)

    def run(state, key, demos, samples, n_steps: int):
        C = demos.X.shape[0]

        def step(state: GCLState, key: PRNGKey):
            key_demo, key_samp = jax.random.split(key)
            demo_batch = jax.vmap(minibatch, in_axes=(0, 0, None))(
                jax.random.split(key_demo, C), demos, config.demo_batch
            )
            samp_batch = jax.vmap(minibatch, in_axes=(0, 0, None))(
                jax.random.split(key_samp, C), samples, config.sample_batch
            )
            grads, metrics = jax.grad(batch_loss, has_aux=True)(
                state.params.net, state.params.norm, demo_batch, samp_batch
            )
            updates, opt_state = optimiser.update(grads, state.opt_state, state.params.net)
            net = optax.apply_updates(state.params.net, updates)
            state = GCLState(
                params=state.params.replace(net=net), opt_state=opt_state, step=state.step + 1
            )
            return state, metrics.replace(grad_norm=optax.tree.norm(grads))

        return jax.lax.scan(step, state, jax.random.split(key, n_steps))

    def update(state, key, demos, samples):
        return run(state, key, demos, samples, config.n_steps)

    def pretrain(state, key, demos, samples):
        return run(state, key, demos, samples, config.pretrain_steps)

    def loss(params: CostParams, demos, samples):
        return batch_loss(params.net, params.norm, demos, samples)

    return CostLearner(init=init, update=update, pretrain=pretrain, loss=loss, optimiser=optimiser)
