"""The shared vocabulary of diffgcl: pytrees and protocols.

Every numerical function in the package is written for *one* instance (one trajectory, one time
step, one condition) and batched with ``jax.vmap`` at the call site. The shapes below are those of
one instance; a batch adds leading axes (samples ``N``, conditions ``C``, seeds ``S``).

Notation (GPS / the design brief): ``T`` time steps, states ``x_0 .. x_T`` (``T+1`` of them),
actions ``u_0 .. u_{T-1}``; ``dX`` state size, ``dU`` action size, ``dO`` observation size.

Costs are evaluated as ``c(x_t, u_t, t)`` for ``t = 0 .. T-1`` plus a terminal ``c(x_T, 0, T)``:
a trajectory's cost is ``sum_t c(x_t, u_t, t) + c(x_T, 0, T)``. Quadratic expansions therefore
have ``T+1`` entries; the action parts of the terminal entry are zero.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import jax
from flax import struct

from diffgcl import linalg

Array = jax.Array
PRNGKey = jax.Array


@struct.dataclass
class Trajectory:
    """One rolled-out trajectory.

    X: [T+1, dX] states, U: [T, dU] actions, O: [T+1, dO] observations (``dO = 0`` when the env
    has no sensors or they were not requested).
    """

    X: Array
    U: Array
    O: Array

    @property
    def horizon(self) -> int:
        return self.U.shape[-2]


@struct.dataclass
class LinearGaussianController:
    """Time-varying linear-Gaussian controller ``u_t ~ N(K_t x_t + k_t, cov_t)``.

    K: [T, dU, dX], k: [T, dU], cov: [T, dU, dU], chol_cov: [T, dU, dU] (lower Cholesky factor of
    cov), inv_cov: [T, dU, dU] (precision). Build with :func:`make_controller` so that the three
    covariance fields agree.
    """

    K: Array
    k: Array
    cov: Array
    chol_cov: Array
    inv_cov: Array

    @property
    def horizon(self) -> int:
        return self.K.shape[-3]

    def mean_action(self, x: Array, t: Array | int) -> Array:
        """Mean action ``K_t x + k_t`` for one state ``x: [dX]``."""
        return self.K[t] @ x + self.k[t]


def make_controller(K: Array, k: Array, cov: Array) -> LinearGaussianController:
    """A controller whose Cholesky factor and precision are computed from ``cov: [T, dU, dU]``."""
    cov = linalg.symmetrise(cov)
    chol = linalg.cholesky(cov)
    inv_cov = linalg.inverse_from_cholesky(chol)
    return LinearGaussianController(K=K, k=k, cov=cov, chol_cov=chol, inv_cov=inv_cov)


@struct.dataclass
class LinearDynamics:
    """Time-varying linear-Gaussian dynamics ``x_{t+1} ~ N(A_t x_t + B_t u_t + c_t, cov_t)``.

    A: [T, dX, dX], B: [T, dX, dU], c: [T, dX], cov: [T, dX, dX].
    """

    A: Array
    B: Array
    c: Array
    cov: Array

    @property
    def horizon(self) -> int:
        return self.A.shape[-3]


@struct.dataclass
class TrajectoryDistribution:
    """Gaussian marginals of a linear-Gaussian trajectory distribution over ``z_t = [x_t; u_t]``.

    mu: [T, dX+dU], sigma: [T, dX+dU, dX+dU] for t = 0 .. T-1; mu_final: [dX], sigma_final:
    [dX, dX] for the state x_T.
    """

    mu: Array
    sigma: Array
    mu_final: Array
    sigma_final: Array


@struct.dataclass
class QuadraticCost:
    """Second-order expansion of a cost along a trajectory, t = 0 .. T (T+1 entries).

    ``c(x_t + dx, u_t + du) ≈ l + l_x·dx + l_u·du + ½ dxᵀ l_xx dx + ½ duᵀ l_uu du + duᵀ l_ux dx``.
    l: [T+1], l_x: [T+1, dX], l_u: [T+1, dU], l_xx: [T+1, dX, dX], l_uu: [T+1, dU, dU],
    l_ux: [T+1, dU, dX]. The terminal entry's action parts are zero.
    """

    l: Array
    l_x: Array
    l_u: Array
    l_xx: Array
    l_uu: Array
    l_ux: Array


@struct.dataclass
class InitialStateDistribution:
    """Gaussian over x_0 per condition: mean: [dX], cov: [dX, dX]."""

    mean: Array
    cov: Array


# A cost on one step: c(x: [dX], u: [dU], t: int scalar) -> scalar.
CostFn = Callable[[Array, Array, Array], Array]
# A policy on one step: pi(x: [dX], o: [dO], t, key) -> u: [dU].
PolicyFn = Callable[[Array, Array, Array, PRNGKey], Array]


@runtime_checkable
class Env(Protocol):
    """What every environment provides (see :mod:`diffgcl.envs`).

    ``step`` and ``obs`` are written for one instance; batch them with ``vmap``.
    """

    name: str
    dX: int
    dU: int
    dO: int
    dt: float
    horizon: int
    mjcf_path: str

    def step(self, x: Array, u: Array) -> Array:
        """x: [dX], u: [dU] -> x': [dX]."""
        ...

    def obs(self, x: Array, key: PRNGKey | None = None) -> Array:
        """x: [dX] -> o: [dO]; ``key`` adds sensor noise where the sensor model has any."""
        ...

    def initial_states(self) -> Array:
        """Default conditions x_0: [C, dX]."""
        ...

    def expert_cost(self, x: Array, u: Array, t: Array) -> Array:
        """Hand-written cost c(x, u, t) -> scalar (terminal step: t = T, u = 0)."""
        ...

    def success(self, X: Array) -> Array:
        """X: [T+1, dX] -> bool scalar."""
        ...
