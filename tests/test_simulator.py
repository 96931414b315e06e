"""The simulator stage: fused (traced in) and staged (programs of their own, chunked) give the
same numbers; staged programs are shared across batch shapes; a staged host loop equals the
traced training program."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tiny_tasks import Slider, tiny_config

from diffgcl.algorithms.gps import GPSConfig, make_gps
from diffgcl.algorithms.staged import run_gps_seeds, staged_simulator
from diffgcl.control.init import init_controller
from diffgcl.envs import make_env
from diffgcl.sim.rollout import rollout_controller
from diffgcl.sim.simulator import Simulator


def random_controllers(key, lead, T, dX, dU):
    key_K, key_k = jax.random.split(key)
    ctrl = init_controller(T, dX, dU, 0.3)
    K = 0.1 * jax.random.normal(key_K, (*lead, T, dU, dX))
    k = jax.random.normal(key_k, (*lead, T, dU))
    bcast = lambda a: jnp.broadcast_to(a, (*lead, *a.shape))
    return ctrl.replace(
        K=K, k=k, cov=bcast(ctrl.cov), chol_cov=bcast(ctrl.chol_cov), inv_cov=bcast(ctrl.inv_cov)
    )


@pytest.fixture(scope="module")
def arm():
    return make_env("arm", horizon=6)


def test_staged_rollouts_and_jacobians_equal_fused_and_a_plain_loop(arm):
    env, T = arm, arm.horizon
    lead = (3, 5)  # 15 rollouts: four chunks of 4, the last padded
    ctrl = random_controllers(jax.random.PRNGKey(0), lead, T, env.dX, env.dU)
    x0 = jnp.broadcast_to(jnp.asarray(env.initial_states())[0], (*lead, env.dX))
    noise = jax.random.normal(jax.random.PRNGKey(1), (*lead, T, env.dU))
    fused = Simulator(env)
    staged = Simulator(env, staged=True, chunks={"controller_rollouts": 4, "jacobians": 4})
    a = jax.jit(fused.controller_rollouts)(ctrl, x0, noise)
    b = staged.controller_rollouts(ctrl, x0, noise)
    ref = rollout_controller(
        env, jax.tree.map(lambda v: v[2, 3], ctrl), x0[2, 3], noise[2, 3]
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(a.X), np.asarray(b.X), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(a.U), np.asarray(b.U), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(b.X[2, 3]), np.asarray(ref.X), rtol=1e-12, atol=1e-12)
    A1, B1 = jax.jit(fused.jacobians)(a.X, a.U)
    A2, B2 = staged.jacobians(b.X, b.U)
    assert A2.shape == (*lead, T, env.dX, env.dX) and B2.shape == (*lead, T, env.dX, env.dU)
    np.testing.assert_allclose(np.asarray(A1), np.asarray(A2), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(B1), np.asarray(B2), rtol=1e-10, atol=1e-12)
    # Another batch shape reuses the staged programs: one per kind.
    staged.controller_rollouts(
        jax.tree.map(lambda v: v[0, :2], ctrl), x0[0, :2], noise[0, :2]
    )  # fmt: skip
    kinds = [key[0] for key in staged._programs]
    assert kinds.count("controller_rollouts") == 1 and kinds.count("jacobians") == 1


def test_policy_rollouts_share_one_parameter_set_per_leading_entry():
    env = Slider()
    T = env.horizon

    def act(params, o, eps):  # a policy on the state through a toy "observation"
        return params["gain"] * jnp.ones(env.dU) + 0.0 * eps

    # Observations of the slider are empty; act ignores them.
    params = {"gain": jnp.array([0.5, -1.0])}  # one gain per seed: S = 2
    x0 = jnp.broadcast_to(jnp.asarray(env.initial_states())[0], (2, 3, env.dX))
    noise = jnp.zeros((2, 3, T, env.dU))
    for sim in (Simulator(env), Simulator(env, staged=True)):
        traj = sim.policy_rollouts(act, params, x0, noise, shared=1, name=("toy",))
        U = np.asarray(traj.U)
        assert U.shape == (2, 3, T, env.dU)
        np.testing.assert_allclose(U[0], 0.5)
        np.testing.assert_allclose(U[1], -1.0)


def test_staged_gps_loop_equals_the_traced_training_program():
    env = Slider()
    gps = make_gps(GPSConfig(iterations=4, init_var=1.0, kl_step=1.0), env, env.expert_cost)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in range(3)])
    state, metrics = jax.jit(jax.vmap(gps.train))(keys)
    state_s, metrics_s, X = run_gps_seeds(gps, keys, 4, env)
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(state_s), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(metrics.cost), np.asarray(metrics_s.cost), rtol=1e-9)
    # The final controllers' noise-free rollouts: those the metrics' next entry would describe.
    assert X.shape == (3, 1, env.horizon + 1, env.dX)
    assert staged_simulator(env) is staged_simulator(Slider())


@pytest.mark.parametrize("schedule", ["v2", "v1"])
def test_staged_rgcl_runner_equals_the_traced_chunks(slider, schedule):
    from diffgcl.algorithms.runner import train_seeds

    env, demos = slider
    config = dataclasses.replace(tiny_config(schedule), iterations=4)
    traced = train_seeds(config, env, demos, [0, 1], chunk=3, progress=False, staged=False)
    staged = train_seeds(config, env, demos, [0, 1], chunk=3, progress=False, staged=True)
    for a, b in zip(jax.tree.leaves(traced.state), jax.tree.leaves(staged.state), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-8, atol=1e-8)
    for a, b in zip(jax.tree.leaves(traced.metrics), jax.tree.leaves(staged.metrics), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-8, atol=1e-8)
    assert np.asarray(traced.metrics.gps.cost).shape[:3] == (2, 4, config.gps_per_iteration)
