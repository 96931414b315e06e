"""KL-constrained LQR: the backward and forward passes of GPS's C-step (DESIGN §4).

Given time-varying linear-Gaussian dynamics ``x_{t+1} ~ N(A_t x_t + B_t u_t + c_t, Σ_dyn,t)``, a
quadratic cost expansion *about the origin* (absolute coordinates; see
:func:`diffgcl.costs.expansion.about_origin`) and a previous controller ``p̄(u|x) = N(K̄x + k̄, Σ̄)``,
the Lagrangian of ``min E_p[cost] s.t. KL(p‖p̄) ≤ ε`` for a fixed dual variable η is an LQR problem
with the augmented cost (Levine & Abbeel 2014, eq. 3–4; GPS code base ``compute_costs``)

    C̃_t = C_t/(η+ω) + η/(η+ω)·[[K̄ᵀP̄K̄, −K̄ᵀP̄], [−P̄K̄, P̄]],
    c̃_t = c_t/(η+ω) + η/(η+ω)·[K̄ᵀP̄k̄; −P̄k̄],          P̄ = Σ̄⁻¹,

where ω = 0 for GPS and ω = 1 for the maximum-entropy objective GCL uses. Its solution is the
linear-Gaussian controller ``K = −Q_uu⁻¹Q_ux``, ``k = −Q_uu⁻¹q_u``, ``Σ = Q_uu⁻¹``.

Every function here is written for one condition; vmap over conditions at the call site. Time is a
``lax.scan``. A non-positive-definite ``Q_uu`` is detected and reported through a flag (the
outputs stay finite); :mod:`diffgcl.control.dual` reacts by raising η.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct
from jax import lax

from diffgcl import linalg
from diffgcl.types import (
    Array,
    InitialStateDistribution,
    LinearDynamics,
    LinearGaussianController,
    QuadraticCost,
    TrajectoryDistribution,
)


@struct.dataclass
class BackwardResult:
    """Output of :func:`lqr_backward`.

    controller: the new controller (fields [T, ...]; finite even when ``pd_ok`` is False, in which
    case it must not be used). pd_ok: bool scalar, every ``Q_uu`` was positive definite and every
    output finite. V: [T+1, dX, dX], v: [T+1, dX] quadratic and linear value-function terms
    (entry T is the terminal cost).
    """

    controller: LinearGaussianController
    pd_ok: Array
    V: Array
    v: Array


def _sym(M: Array) -> Array:
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def kl_augmented_cost(
    cost: QuadraticCost, prev: LinearGaussianController, eta: Array, omega: float | Array = 0.0
) -> QuadraticCost:
    """The augmented cost C̃, c̃ of the module docstring (DESIGN §4) for one dual value η.

    cost: QuadraticCost about the origin, T+1 entries; prev: controller with fields [T, ...];
    eta: scalar with ``eta + omega > 0``. The KL term ``η·(−log p̄(u|x))`` has no action at the
    terminal step, so entry T is only rescaled. Returns a QuadraticCost with T+1 entries.
    """
    scale = 1.0 / (eta + omega)
    w = eta * scale
    P = prev.inv_cov  # [T, dU, dU]
    K, k = prev.K, prev.k
    PK = P @ K  # [T, dU, dX]
    Pk = jnp.einsum("tij,tj->ti", P, k)  # [T, dU]
    kl_xx = jnp.swapaxes(K, -1, -2) @ PK  # K̄ᵀP̄K̄
    kl_x = jnp.einsum("tji,tj->ti", K, Pk)  # K̄ᵀP̄k̄
    kl_l = 0.5 * jnp.einsum("ti,ti->t", k, Pk)  # ½k̄ᵀP̄k̄ (constant; kept for completeness)

    def pad(a: Array) -> Array:  # append a zero terminal entry
        return jnp.concatenate([a, jnp.zeros_like(a[:1])], axis=0)

    return QuadraticCost(
        l=cost.l * scale + w * pad(kl_l),
        l_x=cost.l_x * scale + w * pad(kl_x),
        l_u=cost.l_u * scale - w * pad(Pk),
        l_xx=cost.l_xx * scale + w * pad(kl_xx),
        l_uu=cost.l_uu * scale + w * pad(P),
        l_ux=cost.l_ux * scale - w * pad(PK),
    )


def lqr_backward(dynamics: LinearDynamics, cost: QuadraticCost) -> BackwardResult:
    """Finite-horizon LQR backward pass (dynamic programming, DESIGN §4).

    dynamics: A [T, dX, dX], B [T, dX, dU], c [T, dX] (cov unused); cost: QuadraticCost about the
    origin with T+1 entries, entry T giving ``V_T = l_xx[T]``, ``v_T = l_x[T]``. The controller's
    covariance is ``Q_uu⁻¹`` and its precision ``Q_uu``. Non-PD ``Q_uu`` at any step sets
    ``pd_ok = False``; that step then uses the identity in its place so that nothing becomes NaN.
    """
    dU = cost.l_u.shape[-1]
    eye_u = jnp.eye(dU, dtype=cost.l_uu.dtype)

    def step(carry, inputs):
        V, v, ok = carry
        A, B, c, l_x, l_u, l_xx, l_uu, l_ux = inputs
        Vc = v + V @ c
        Q_xx = l_xx + A.T @ V @ A
        Q_uu = _sym(l_uu + B.T @ V @ B)
        Q_ux = l_ux + B.T @ V @ A
        q_x = l_x + A.T @ Vc
        q_u = l_u + B.T @ Vc

        L = linalg.cholesky(Q_uu)
        pd = jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diagonal(L) > 0)
        L = jnp.where(pd, L, eye_u)
        Q_uu = jnp.where(pd, Q_uu, eye_u)
        cov = _sym(linalg.inverse_from_cholesky(L))
        chol_cov = linalg.cholesky(cov)
        K = -linalg.cho_solve(L, Q_ux)
        k = -linalg.cho_solve(L, q_u)
        V_new = _sym(Q_xx + Q_ux.T @ K)
        v_new = q_x + Q_ux.T @ k

        finite = (
            jnp.all(jnp.isfinite(chol_cov))
            & jnp.all(jnp.isfinite(V_new))
            & jnp.all(jnp.isfinite(v_new))
            & jnp.all(jnp.isfinite(K))
            & jnp.all(jnp.isfinite(k))
        )
        step_ok = pd & finite
        # Keep the recursion finite after a failure; the flag says the result is unusable.
        V_new = jnp.where(step_ok, V_new, jnp.zeros_like(V_new))
        v_new = jnp.where(step_ok, v_new, jnp.zeros_like(v_new))
        K = jnp.where(step_ok, K, jnp.zeros_like(K))
        k = jnp.where(step_ok, k, jnp.zeros_like(k))
        cov = jnp.where(step_ok, cov, eye_u)
        chol_cov = jnp.where(step_ok, chol_cov, eye_u)
        Q_uu = jnp.where(step_ok, Q_uu, eye_u)
        out = (K, k, cov, chol_cov, Q_uu, V_new, v_new)
        return (V_new, v_new, ok & step_ok), out

    V_T = _sym(cost.l_xx[-1])
    v_T = cost.l_x[-1]
    xs = (
        dynamics.A,
        dynamics.B,
        dynamics.c,
        cost.l_x[:-1],
        cost.l_u[:-1],
        cost.l_xx[:-1],
        cost.l_uu[:-1],
        cost.l_ux[:-1],
    )
    terminal_ok = jnp.all(jnp.isfinite(V_T)) & jnp.all(jnp.isfinite(v_T))
    (_, _, ok), (K, k, cov, chol_cov, prec, V, v) = lax.scan(
        step, (V_T, v_T, terminal_ok), xs, reverse=True
    )
    controller = LinearGaussianController(K=K, k=k, cov=cov, chol_cov=chol_cov, inv_cov=prec)
    V = jnp.concatenate([V, V_T[None]], axis=0)
    v = jnp.concatenate([v, v_T[None]], axis=0)
    return BackwardResult(controller=controller, pd_ok=ok, V=V, v=v)


def backward_pass(
    dynamics: LinearDynamics,
    cost: QuadraticCost,
    prev: LinearGaussianController,
    eta: Array,
    omega: float | Array = 0.0,
) -> BackwardResult:
    """LQR on the KL-augmented cost for dual variable ``eta`` (``omega = 1``: MaxEnt variant).

    Shapes as in :func:`lqr_backward`; ``eta + omega > 0``.
    """
    return lqr_backward(dynamics, kl_augmented_cost(cost, prev, eta, omega))


def forward_pass(
    dynamics: LinearDynamics, controller: LinearGaussianController, x0: InitialStateDistribution
) -> TrajectoryDistribution:
    """Gaussian marginals over ``z_t = [x_t; u_t]`` of a linear-Gaussian controller in linear-
    Gaussian dynamics (DESIGN §4): ``μ_u = Kμ_x + k``, ``Σ_z = [[Σ, ΣKᵀ], [KΣ, KΣKᵀ + Σ_u]]``,
    ``μ'_x = Fμ_z + f``, ``Σ'_x = FΣ_zFᵀ + Σ_dyn``.

    dynamics: fields [T, ...]; controller: fields [T, ...]; x0: mean [dX], cov [dX, dX].
    Returns TrajectoryDistribution with mu [T, dX+dU], sigma [T, dX+dU, dX+dU], mu_final [dX],
    sigma_final [dX, dX].
    """

    def step(carry, inputs):
        mu_x, sigma_x = carry
        A, B, c, dyn_cov, K, k, cov_u = inputs
        mu_u = K @ mu_x + k
        sxk = sigma_x @ K.T
        sigma_z = jnp.block([[sigma_x, sxk], [sxk.T, K @ sxk + cov_u]])
        sigma_z = _sym(sigma_z)
        mu_z = jnp.concatenate([mu_x, mu_u])
        F = jnp.concatenate([A, B], axis=1)
        mu_next = F @ mu_z + c
        sigma_next = _sym(F @ sigma_z @ F.T + dyn_cov)
        return (mu_next, sigma_next), (mu_z, sigma_z)

    xs = (
        dynamics.A,
        dynamics.B,
        dynamics.c,
        dynamics.cov,
        controller.K,
        controller.k,
        controller.cov,
    )
    (mu_T, sigma_T), (mu, sigma) = lax.scan(step, (x0.mean, _sym(x0.cov)), xs)
    return TrajectoryDistribution(mu=mu, sigma=sigma, mu_final=mu_T, sigma_final=sigma_T)


def kl_divergence_per_step(
    traj_dist: TrajectoryDistribution,
    new: LinearGaussianController,
    prev: LinearGaussianController,
) -> Array:
    """``E_{x_t ~ p}[KL(p(u|x_t) ‖ p̄(u|x_t))]`` for t = 0 .. T-1 -> [T].

    With shared dynamics, the KL between the trajectory distributions of ``new`` and ``prev`` is
    the sum of these terms. Closed form for Gaussians with means ``Kx + k`` and ``K̄x + k̄``:
    ``½[tr(P̄Σ) + (ΔKμ + Δk)ᵀP̄(ΔKμ + Δk) + tr(ΔKᵀP̄ΔK Σ_x) − dU + log|Σ̄| − log|Σ|]`` with
    ``ΔK = K − K̄``; each part is non-negative, so the result is too up to round-off (clipped at 0).
    traj_dist: the forward pass of ``new``.
    """
    dX = new.K.shape[-1]
    dU = new.K.shape[-2]
    mu_x = traj_dist.mu[:, :dX]
    sigma_x = traj_dist.sigma[:, :dX, :dX]
    dK = new.K - prev.K
    dmean = jnp.einsum("tij,tj->ti", dK, mu_x) + new.k - prev.k  # [T, dU]
    P = prev.inv_cov
    mean_term = jnp.einsum("ti,tij,tj->t", dmean, P, dmean)
    spread_term = jnp.einsum("tij,tjk,tki->t", jnp.swapaxes(dK, -1, -2) @ P, dK, sigma_x)
    trace_term = jnp.einsum("tij,tji->t", P, new.cov)
    logdet_prev = 2.0 * jnp.sum(jnp.log(jnp.diagonal(prev.chol_cov, axis1=-2, axis2=-1)), -1)
    logdet_new = 2.0 * jnp.sum(jnp.log(jnp.diagonal(new.chol_cov, axis1=-2, axis2=-1)), -1)
    kl = 0.5 * (trace_term + mean_term + spread_term - dU + logdet_prev - logdet_new)
    return jnp.maximum(kl, 0.0)


def kl_divergence(
    traj_dist: TrajectoryDistribution,
    new: LinearGaussianController,
    prev: LinearGaussianController,
) -> Array:
    """KL(p‖p̄) of the trajectory distributions, summed over t (scalar). See
    :func:`kl_divergence_per_step`."""
    return jnp.sum(kl_divergence_per_step(traj_dist, new, prev))


def controller_entropy(controller: LinearGaussianController) -> Array:
    """Sum over t of the entropy of the action noise ``N(0, Σ_t)``, nats (scalar).

    ``H_t = ½·dU·log(2πe) + Σ_i log L_ii`` with L the Cholesky factor of Σ_t.
    """
    dU = controller.cov.shape[-1]
    log_diag = jnp.log(jnp.diagonal(controller.chol_cov, axis1=-2, axis2=-1))
    per_step = 0.5 * dU * jnp.log(2.0 * jnp.pi * jnp.e) + jnp.sum(log_diag, axis=-1)
    return jnp.sum(per_step)
