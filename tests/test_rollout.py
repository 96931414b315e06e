"""Rollouts: exploration noise statistics, controller rollouts against a plain Python loop,
batching, and no recompilation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage

from diffgcl.costs.expansion import trajectory_cost
from diffgcl.envs import make_env
from diffgcl.sim.rollout import (
    rollout_controller,
    rollout_policy,
    sample_controller,
    smooth_noise,
)
from diffgcl.types import make_controller


@pytest.fixture(scope="module")
def arm():
    return make_env("arm")


def random_controller(T, dU, dX, seed=0):
    rng = np.random.default_rng(seed)
    K = rng.normal(scale=0.3, size=(T, dU, dX))
    k = rng.normal(size=(T, dU))
    L = rng.normal(scale=0.2, size=(T, dU, dU))
    cov = L @ np.swapaxes(L, 1, 2) + 0.05 * np.eye(dU)
    return make_controller(jnp.asarray(K), jnp.asarray(k), jnp.asarray(cov))


def test_smoothed_noise_matches_scipy_gaussian_filter():
    key = jax.random.key(3)
    raw = np.asarray(smooth_noise(key, 50, 2, None))
    smoothed = np.asarray(smooth_noise(key, 50, 2, 2.0))
    ref = np.stack([scipy.ndimage.gaussian_filter1d(raw[:, i], 2.0) for i in range(2)], 1)
    ref /= ref.std(axis=0, keepdims=True)
    np.testing.assert_allclose(smoothed, ref, atol=1e-10)
    np.testing.assert_allclose(smoothed.std(axis=0), 1.0, atol=1e-12)
    # Smoothing correlates neighbouring steps.
    lag1 = np.corrcoef(smoothed[:-1, 0], smoothed[1:, 0])[0, 1]
    assert lag1 > 0.7


def test_controller_rollout_matches_python_loop(arm):
    T = 12
    ctrl = random_controller(T, 2, 4)
    x0 = arm.initial_states()[0]
    noise = jax.random.normal(jax.random.key(1), (T, 2), jnp.float64)
    traj = jax.jit(lambda x0, e: rollout_controller(arm, ctrl, x0, e))(x0, noise)
    x = x0
    for t in range(T):
        u = ctrl.K[t] @ x + ctrl.k[t] + ctrl.chol_cov[t] @ noise[t]
        np.testing.assert_allclose(traj.U[t], u, atol=1e-12)
        np.testing.assert_allclose(traj.X[t], x, atol=1e-12)
        x = arm.step(x, u)
    np.testing.assert_allclose(traj.X[T], x, atol=1e-12)
    assert traj.O.shape == (T + 1, 0)


def test_sampled_actions_have_the_controller_covariance(arm):
    T = 3
    cov = jnp.broadcast_to(jnp.array([[0.5, 0.2], [0.2, 0.3]]), (T, 2, 2))
    ctrl = make_controller(jnp.zeros((T, 2, 4)), jnp.ones((T, 2)), cov)
    traj = jax.jit(lambda k: sample_controller(arm, ctrl, arm.initial_states()[0], k, 4000))(
        jax.random.key(0)
    )
    emp = np.cov(np.asarray(traj.U[:, 0]).T)
    np.testing.assert_allclose(emp, cov[0], atol=0.03)
    np.testing.assert_allclose(np.asarray(traj.U[:, 0]).mean(0), 1.0, atol=0.03)


def test_batched_sampling_equals_unbatched_and_does_not_recompile(arm):
    T = 10
    ctrl = random_controller(T, 2, 4, seed=2)
    x0s = jnp.stack([arm.initial_states()[0], jnp.array([0.5, -0.5, 0.0, 0.1])])
    keys = jax.random.split(jax.random.key(5), 2)

    @jax.jit
    def batched(x0s, keys):
        return jax.vmap(lambda x0, k: sample_controller(arm, ctrl, x0, k, 3, smooth_sigma=2.0))(
            x0s, keys
        )

    out = batched(x0s, keys)
    single = sample_controller(arm, ctrl, x0s[1], keys[1], 3, smooth_sigma=2.0)
    np.testing.assert_allclose(out.X[1], single.X, atol=1e-10)
    batched(x0s + 0.01, jax.random.split(jax.random.key(6), 2))
    assert batched._cache_size() == 1


def test_policy_rollout_and_trajectory_cost(arm):
    T = 6

    def policy(x, o, t, key):
        return -0.5 * o[:2] + 0.0 * t

    traj = rollout_policy(arm, policy, arm.initial_states()[0], jax.random.key(0), T)
    assert traj.X.shape == (T + 1, 4) and traj.O.shape == (T + 1, arm.dO)
    np.testing.assert_allclose(traj.U[2], -0.5 * traj.X[2, :2], atol=1e-12)
    total = trajectory_cost(arm.expert_cost, traj.X, traj.U)
    by_hand = sum(float(arm.expert_cost(traj.X[t], traj.U[t], t)) for t in range(T))
    by_hand += float(arm.expert_cost(traj.X[T], jnp.zeros(2), T))
    np.testing.assert_allclose(total, by_hand, rtol=1e-12)
