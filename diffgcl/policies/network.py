"""The global policy of Guided Policy Search: a Gaussian ``π_θ(u | o) = N(μ_θ(o), diag(var))``.

GPS's point (Levine et al. 2016, §4): the local controllers see the full state, the global policy
only what the robot senses — observations ``o`` — so that it can run from new starts without the
simulator's state. The mean ``μ_θ`` is a flax MLP on *normalised* observations; the covariance is
diagonal and state-independent, set by the S-step from the controllers' precisions
(:func:`diffgcl.policies.mdgps.policy_variance`), not learned by gradient descent.

Observation normalisation (GPS ``policy_opt``): ``(o − mean) / max(std, floor)`` with statistics
taken once from data and then frozen; the floor stops a dimension that never moved in that data
(GPS users met NaNs from it) from being blown up later. The statistics live in the parameter
pytree but are never trained (``stop_gradient``).

The last layer starts at zero, so a new policy outputs ``u = 0`` everywhere: the same mean as
GPS's initial controllers (``K = 0, k = 0``), which makes the policy's first linearisation equal to
the initial controller (GPS instead runs a first S-step to "catch the policy up").

Everything here is pure and written for one observation; vmap at the call site. The action
functions :meth:`GaussianPolicy.mean_action` / :meth:`GaussianPolicy.sample_action` take an
explicit noise or key and run inside ``lax.scan`` rollouts
(:func:`diffgcl.sim.rollout.rollout_policy`, :func:`diffgcl.sim.rollout.sample_observed`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from diffgcl.checks import check_shape
from diffgcl.types import Array, PRNGKey

ACTIVATIONS = {"relu": nn.relu, "tanh": jnp.tanh, "softplus": nn.softplus}


@dataclass(frozen=True)
class PolicyConfig:
    """Shape of the policy network and its normaliser.

    hidden: widths of the hidden layers (GPS's examples: 2 × 40–100); activation: one of
    ``ACTIVATIONS``; obs_std_floor: lower bound of the normaliser's standard deviation (GPS:
    1e-3, in the observation's own units); obs_std_rel_floor: a second lower bound, this fraction
    of each dimension's root mean square (a range beam that read its maximum in every fitting
    sample has no spread: with an absolute floor of 1e-3 m, the first time it sees something
    its input to the network is −10⁴ σ and the policy's action explodes); init_var: action
    variance of a new policy (usually the GPS ``init_var`` of the controllers it starts from).
    """

    hidden: tuple[int, ...] = (64, 64)
    activation: str = "relu"
    obs_std_floor: float = 1e-3
    obs_std_rel_floor: float = 0.0
    init_var: float = 0.1

    def __post_init__(self):
        if self.activation not in ACTIVATIONS:
            raise ValueError(
                f"PolicyConfig: activation {self.activation!r}; choose one of {tuple(ACTIVATIONS)}"
            )
        if not self.init_var > 0 or not self.obs_std_floor > 0:
            raise ValueError("PolicyConfig: init_var and obs_std_floor must be positive")
        if not self.obs_std_rel_floor >= 0:
            raise ValueError("PolicyConfig: obs_std_rel_floor must be non-negative")


@struct.dataclass
class ObsNormaliser:
    """Frozen observation statistics: mean: [dO], std: [dO] (already floored)."""

    mean: Array
    std: Array


@struct.dataclass
class PolicyParams:
    """net: flax parameters of the mean network; norm: :class:`ObsNormaliser`; var: [dU] action
    variance (diagonal, state-independent)."""

    net: dict
    norm: ObsNormaliser
    var: Array


class MeanNetwork(nn.Module):
    """``μ_θ(z)``: MLP from the normalised observation ``z: [dO]`` to the action mean ``[dU]``;
    the output layer starts at zero."""

    hidden: Sequence[int]
    dU: int
    activation: str = "relu"
    param_dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, z: Array) -> Array:
        act = ACTIVATIONS[self.activation]
        h = z
        for width in self.hidden:
            h = act(nn.Dense(width, param_dtype=self.param_dtype)(h))
        out = nn.Dense(
            self.dU,
            kernel_init=nn.initializers.zeros,
            bias_init=nn.initializers.zeros,
            param_dtype=self.param_dtype,
        )
        return out(h)


def fit_obs_normaliser(
    O: Array, std_floor: float, mask: Array | None = None, rel_floor: float = 0.0
) -> ObsNormaliser:
    """Statistics of observations ``O: [..., dO]`` (``mask: [...]``, 1 = use; default all):
    per-dimension mean and standard deviation, the latter floored at ``std_floor`` and at
    ``rel_floor`` times the dimension's root mean square."""
    O = O.reshape(-1, O.shape[-1])
    w = jnp.ones(O.shape[0], O.dtype) if mask is None else mask.reshape(-1).astype(O.dtype)
    n = jnp.maximum(w.sum(), 1.0)
    mean = (w[:, None] * O).sum(0) / n
    var = (w[:, None] * (O - mean) ** 2).sum(0) / n
    rms = jnp.sqrt((w[:, None] * O**2).sum(0) / n)
    floor = jnp.maximum(std_floor, rel_floor * rms)
    return ObsNormaliser(mean=mean, std=jnp.maximum(jnp.sqrt(var), floor))


@dataclass(frozen=True)
class GaussianPolicy:
    """``π_θ(u | o)`` for observations of size ``dO`` and actions of size ``dU``; every method is
    a pure function of explicit :class:`PolicyParams`, for one observation. ``param_dtype``:
    dtype of new parameters (float64 in the tests)."""

    config: PolicyConfig
    dO: int
    dU: int
    param_dtype: object = jnp.float32

    @property
    def _net(self) -> MeanNetwork:
        cfg = self.config
        return MeanNetwork(cfg.hidden, self.dU, cfg.activation, param_dtype=self.param_dtype)

    def init(self, key: PRNGKey, norm: ObsNormaliser | None = None) -> PolicyParams:
        """New parameters: random hidden layers, zero output layer (``μ ≡ 0``), variance
        ``config.init_var``; ``norm`` defaults to the identity normaliser."""
        dtype = self.param_dtype
        net = self._net.init(key, jnp.zeros(self.dO, dtype))["params"]
        if norm is None:
            norm = ObsNormaliser(mean=jnp.zeros(self.dO, dtype), std=jnp.ones(self.dO, dtype))
        var = jnp.full(self.dU, self.config.init_var, dtype)
        return PolicyParams(net=net, norm=norm, var=var)

    def normalise(self, params: PolicyParams, o: Array) -> Array:
        """``(o − mean) / std`` with the statistics held constant: [dO]."""
        norm = jax.lax.stop_gradient(params.norm)
        return (o - norm.mean) / norm.std

    def mean_action(self, params: PolicyParams, o: Array) -> Array:
        """``μ_θ(o)``: [dU] for one observation ``o: [dO]``."""
        check_shape("policy", "observation", o, (self.dO,))
        return self._net.apply({"params": params.net}, self.normalise(params, o))

    def sample_action(self, params: PolicyParams, o: Array, noise: Array) -> Array:
        """``μ_θ(o) + sqrt(var) ⊙ ε`` for a standard-normal ``noise ε: [dU]``."""
        return self.mean_action(params, o) + jnp.sqrt(params.var) * noise

    def log_prob(self, params: PolicyParams, o: Array, u: Array) -> Array:
        """``log π_θ(u | o)``: scalar."""
        r = u - self.mean_action(params, o)
        var = params.var
        return -0.5 * jnp.sum(r**2 / var + jnp.log(2.0 * jnp.pi * var))

    def entropy(self, params: PolicyParams) -> Array:
        """Entropy of the action noise per step, nats (scalar)."""
        return 0.5 * jnp.sum(jnp.log(2.0 * jnp.pi * jnp.e * params.var))

    def as_policy_fn(self, params: PolicyParams, *, noisy: bool = False):
        """A :data:`diffgcl.types.PolicyFn` ``(x, o, t, key) -> u`` acting on ``o`` only: the
        noise-free mean, or (``noisy``) a sample with the policy's own variance."""

        def policy(x, o, t, key):
            del x, t
            if not noisy:
                return self.mean_action(params, o)
            return self.sample_action(params, o, jax.random.normal(key, (self.dU,), o.dtype))

        return policy
