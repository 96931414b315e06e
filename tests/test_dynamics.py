"""Dynamics fits: autodiff linearisation and GPS-style regression with a NIW prior, on systems
whose linear-Gaussian model is known."""

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.dynamics.autodiff import fit_dynamics
from diffgcl.dynamics.regression import fit_dynamics_regression


def linear_system(seed=0, dX=3, dU=2, T=5):
    rng = np.random.default_rng(seed)
    A = np.eye(dX) + 0.1 * rng.normal(size=(T, dX, dX))
    B = rng.normal(size=(T, dX, dU))
    c = rng.normal(size=(T, dX))
    return A, B, c


def simulate(A, B, c, n, noise, seed=1):
    rng = np.random.default_rng(seed)
    T, dX, dU = B.shape
    X = np.zeros((n, T + 1, dX))
    U = rng.normal(size=(n, T, dU))
    X[:, 0] = rng.normal(size=(n, dX))
    for t in range(T):
        X[:, t + 1] = X[:, t] @ A[t].T + U[:, t] @ B[t].T + c[t]
        X[:, t + 1] += noise * rng.normal(size=(n, dX))
    return X, U


def test_regression_recovers_a_known_linear_gaussian_system():
    A, B, c = linear_system()
    X, U = simulate(A, B, c, n=400, noise=0.05)
    # A weak prior: the pooled prior is wrong for a time-varying system and would inflate cov.
    dyn = fit_dynamics_regression(jnp.asarray(X), jnp.asarray(U), prior_strength=0.01)
    np.testing.assert_allclose(dyn.A, A, atol=0.02)
    np.testing.assert_allclose(dyn.B, B, atol=0.02)
    np.testing.assert_allclose(dyn.c, c, atol=0.02)
    np.testing.assert_allclose(
        dyn.cov, np.broadcast_to(0.05**2 * np.eye(3), dyn.cov.shape), atol=6e-4
    )


def test_regression_with_few_samples_is_well_posed_thanks_to_the_prior():
    # A time-invariant system: the pooled prior is right, so 3 samples per step suffice.
    A, B, c = linear_system(T=1)
    A, B, c = (np.repeat(a, 20, axis=0) for a in (A, B, c))
    X, U = simulate(A, B, c, n=3, noise=0.0)
    dyn = fit_dynamics_regression(jnp.asarray(X), jnp.asarray(U), prior_strength=10.0)
    assert np.isfinite(np.asarray(dyn.A)).all()
    pred = np.einsum("tij,ntj->nti", dyn.A, X[:, :-1]) + np.einsum("tij,ntj->nti", dyn.B, U)
    np.testing.assert_allclose(pred + np.asarray(dyn.c), X[:, 1:], atol=1e-2)


def test_autodiff_fit_is_exact_on_a_linear_step_and_measures_the_noise():
    A, B, c = linear_system(T=1)
    A0, B0, c0 = A[0], B[0], c[0]

    def step(x, u):
        return A0 @ x + B0 @ u + c0

    X, U = simulate(np.repeat(A, 4, 0), np.repeat(B, 4, 0), np.repeat(c, 4, 0), n=2000, noise=0.1)
    dyn = jax.jit(lambda X, U: fit_dynamics(step, X, U, cov_floor=1e-6))(X, U)
    np.testing.assert_allclose(dyn.A, np.repeat(A, 4, 0), atol=1e-12)
    np.testing.assert_allclose(dyn.B, np.repeat(B, 4, 0), atol=1e-12)
    # The offset puts the model's mean through the sample mean; the covariance is the noise's.
    np.testing.assert_allclose(dyn.c, np.repeat(c, 4, 0), atol=0.02)
    np.testing.assert_allclose(dyn.cov, np.broadcast_to(0.01 * np.eye(3), dyn.cov.shape), atol=2e-3)
