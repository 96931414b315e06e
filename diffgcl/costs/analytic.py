"""Hand-written costs with the semantics of GPS's ``CostState``, ``CostAction`` and ``CostSum``.

Each cost is a frozen dataclass callable as ``c(x: [dX], u: [dU], t) -> scalar`` (the
:data:`diffgcl.types.CostFn` convention: t = 0 .. T-1 running, t = T terminal with u = 0). Being
frozen and hashable they can be closed over by jitted functions.

State cost (GPS ``evall1l2term``), with ``d = x[idx] − target`` and per-step weights
``w_t = wp · ramp(t)``::

    c = ½·l2·Σ_i w_t,i d_i² + l1·sqrt(α + Σ_i (w_t,i d_i)²)

— quadratic for l1 = 0, a smooth "l1" (linear far away, quadratic within ~sqrt(α) of the target)
for l2 = 0. Ramps over the T+1 cost entries t = 0 .. T: ``constant`` 1, ``linear`` (t+1)/(T+1),
``quadratic`` ((t+1)/(T+1))², ``final_only`` 1 at t = T and 0 before; the terminal weight is also
multiplied by ``final_multiplier`` (GPS's ``wp_final_multiplier``).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp

from diffgcl.types import Array, CostFn

RAMPS = ("constant", "linear", "quadratic", "final_only")


def ramp_multiplier(ramp: str, t: Array, T: int, final_multiplier: float = 1.0) -> Array:
    """Weight of cost entry ``t`` (0 .. T) under a GPS ramp; scalar."""
    t = jnp.asarray(t)
    frac = (t + 1.0) / (T + 1.0)
    if ramp == "constant":
        w = jnp.ones_like(frac)
    elif ramp == "linear":
        w = frac
    elif ramp == "quadratic":
        w = frac**2
    elif ramp == "final_only":
        w = jnp.where(t == T, 1.0, 0.0)
    else:
        raise ValueError(f"unknown ramp {ramp!r}; choose one of {RAMPS}")
    return jnp.where(t == T, w * final_multiplier, w)


@dataclass(frozen=True)
class StateCost:
    """Distance of selected state entries to a target, l1/l2 mix (GPS ``CostState``).

    idx: state indices compared; target, wp: per-index target and weight (same length as idx);
    horizon: T (for the ramps). Defaults give ``½Σ wp d²``.
    """

    idx: tuple[int, ...]
    target: tuple[float, ...]
    horizon: int
    wp: tuple[float, ...] | None = None
    ramp: str = "constant"
    final_multiplier: float = 1.0
    l1: float = 0.0
    l2: float = 1.0
    alpha: float = 1e-2

    def __post_init__(self):
        if len(self.target) != len(self.idx):
            raise ValueError(f"StateCost: {len(self.target)} targets for {len(self.idx)} indices")
        if self.wp is not None and len(self.wp) != len(self.idx):
            raise ValueError(f"StateCost: {len(self.wp)} weights for {len(self.idx)} indices")
        if self.ramp not in RAMPS:
            raise ValueError(f"StateCost: unknown ramp {self.ramp!r}; choose one of {RAMPS}")

    def __call__(self, x: Array, u: Array, t: Array) -> Array:
        d = x[jnp.asarray(self.idx)] - jnp.asarray(self.target, x.dtype)
        wp = jnp.ones_like(d) if self.wp is None else jnp.asarray(self.wp, x.dtype)
        w = wp * ramp_multiplier(self.ramp, t, self.horizon, self.final_multiplier)
        wd = w * d
        return 0.5 * self.l2 * jnp.sum(w * d**2) + self.l1 * jnp.sqrt(self.alpha + jnp.sum(wd**2))


@dataclass(frozen=True)
class ActionCost:
    """``½ Σ_i wu_i u_i²`` (GPS ``CostAction``); zero at the terminal step (u = 0)."""

    wu: tuple[float, ...]

    def __call__(self, x: Array, u: Array, t: Array) -> Array:
        return 0.5 * jnp.sum(jnp.asarray(self.wu, u.dtype) * u**2)


@dataclass(frozen=True)
class WeightedSum:
    """``Σ_j weights_j · costs_j(x, u, t)`` (GPS ``CostSum``)."""

    costs: tuple[CostFn, ...]
    weights: tuple[float, ...]

    def __post_init__(self):
        if len(self.costs) != len(self.weights):
            raise ValueError(
                f"WeightedSum: {len(self.weights)} weights for {len(self.costs)} costs"
            )

    def __call__(self, x: Array, u: Array, t: Array) -> Array:
        return sum(w * c(x, u, t) for c, w in zip(self.costs, self.weights, strict=True))


def arm_expert_cost(
    horizon: int, target=(0.0, 0.0), action_weight: float = 1e-5, dU: int = 2
) -> WeightedSum:
    """The box2d arm's expert cost (DESIGN §2): ``½‖q − q*‖² + w_u·½‖u‖²`` on x = [q, dq]."""
    state = StateCost(idx=(0, 1), target=tuple(float(v) for v in target), horizon=horizon)
    action = ActionCost(wu=(1.0,) * dU)
    return WeightedSum(costs=(action, state), weights=(action_weight, 1.0))
