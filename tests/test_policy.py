"""The global policy (diffgcl.policies) and MDGPS (diffgcl.algorithms.mdgps): the S-step loss and
variance by hand, the autodiff linearisation against finite differences, recovery of a known
linear controller, jit(vmap) against unbatched runs, and MDGPS learning a policy on a stand-in."""

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl.algorithms.gps import GPSConfig
from diffgcl.algorithms.mdgps import MDGPSConfig, PolicySettings, make_mdgps
from diffgcl.policies.mdgps import (
    SStepConfig,
    controller_targets,
    linearise_policy,
    make_policy_learner,
    normalise_weights,
    policy_variance,
    s_step_loss,
)
from diffgcl.policies.network import GaussianPolicy, PolicyConfig, fit_obs_normaliser
from diffgcl.types import make_controller


@dataclass(frozen=True)
class ObservedPointMass:
    """2-D double integrator x = [p, v], u = force; the policy observes [p, v, |p|²] (a nonlinear
    sensor, so the linearisation has something to differentiate)."""

    name: str = "point"
    dX: int = 4
    dU: int = 2
    dO: int = 5
    dt: float = 0.1
    horizon: int = 20
    mjcf_path: str = ""

    def step(self, x, u):
        p, v = x[:2], x[2:]
        v = v + self.dt * u
        return jnp.concatenate([p + self.dt * v, v])

    def obs(self, x, key=None):
        o = jnp.concatenate([x, jnp.sum(x[:2] ** 2)[None]])
        if key is not None:
            o = o + 0.01 * jax.random.normal(key, o.shape, o.dtype)
        return o

    def initial_states(self):
        return jnp.array([[1.0, -1.0, 0.0, 0.0], [-1.5, 0.5, 0.0, 0.0]])

    def expert_cost(self, x, u, t):
        return 0.5 * jnp.sum(x[:2] ** 2) + 0.05 * jnp.sum(x[2:] ** 2) + 1e-3 * jnp.sum(u**2)

    def success(self, X):
        return jnp.all(jnp.abs(X[-3:, :2]) < 0.15)


def random_policy(key, dO=5, dU=2, hidden=(16, 16), activation="tanh"):
    """A policy with a random (non-zero) output layer and a non-trivial normaliser."""
    policy = GaussianPolicy(PolicyConfig(hidden=hidden, activation=activation), dO, dU, jnp.float64)
    k1, k2, k3 = jax.random.split(key, 3)
    O = jax.random.normal(k1, (50, dO)) * jnp.arange(1.0, dO + 1.0)
    params = policy.init(k2, fit_obs_normaliser(O, 1e-3))
    net = jax.tree.map(lambda a: a + 0.3 * jax.random.normal(k3, a.shape, a.dtype), params.net)
    return policy, params.replace(net=net)


def test_s_step_loss_is_the_precision_weighted_form():
    policy, params = random_policy(jax.random.PRNGKey(0))
    rng = np.random.default_rng(1)
    M = 7
    O = rng.normal(size=(M, 5))
    mu = rng.normal(size=(M, 2))
    L = rng.normal(size=(M, 2, 2))
    prec = L @ np.swapaxes(L, -1, -2) + 0.1 * np.eye(2)
    expected = 0.0
    for i in range(M):
        r = mu[i] - np.asarray(policy.mean_action(params, jnp.asarray(O[i])))
        expected += 0.5 * r @ prec[i] @ r
    got = s_step_loss(policy, params, jnp.asarray(O), jnp.asarray(mu), jnp.asarray(prec))
    np.testing.assert_allclose(float(got), expected / M, rtol=1e-12)


def test_weight_normalisation_and_variance_by_hand():
    # Mean 1: [1, 1, 4, 1e-3] * 4 / 6.001; median of those above 1e-2 is 4/6.001; clipping at
    # twice it and dividing by it gives [1, 1, 2, 1e-3].
    w = normalise_weights(jnp.array([1.0, 1.0, 4.0, 1e-3]))
    np.testing.assert_allclose(np.asarray(w), [1.0, 1.0, 2.0, 1e-3], rtol=1e-12)
    prec = jnp.array([[[4.0, 1.0], [1.0, 2.0]], [[2.0, 0.0], [0.0, 6.0]]])
    var = policy_variance(prec, jnp.array([1.0, 3.0]), ent_reg=0.5)
    # A = (1·P1 + 3·P2) / 4 = [[2.5, .25], [.25, 5]]; diag + 2·0.5 = [3.5, 6].
    np.testing.assert_allclose(np.asarray(var), [1 / 3.5, 1 / 6.0], rtol=1e-12)


def test_controller_targets():
    rng = np.random.default_rng(2)
    T, N, dX, dU = 4, 3, 3, 2
    K, k = rng.normal(size=(T, dU, dX)), rng.normal(size=(T, dU))
    cov = np.broadcast_to(np.diag([0.5, 2.0]), (T, dU, dU))
    ctrl = make_controller(jnp.asarray(K), jnp.asarray(k), jnp.asarray(cov))
    X = rng.normal(size=(N, T + 1, dX))
    mu, prec = controller_targets(ctrl, jnp.asarray(X))
    np.testing.assert_allclose(np.asarray(mu[1, 2]), K[2] @ X[1, 2] + k[2], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(prec[2, 3]), np.diag([2.0, 0.5]), rtol=1e-12)


def test_policy_linearisation_matches_finite_differences():
    env = ObservedPointMass()
    policy, params = random_policy(jax.random.PRNGKey(3))
    X = jax.random.normal(jax.random.PRNGKey(4), (4, 6, env.dX))
    lin = linearise_policy(policy, params, env.obs, X)

    def act(x):
        return np.asarray(policy.mean_action(params, env.obs(jnp.asarray(x))))

    h = 1e-6
    for t in (0, 3):
        J = np.zeros((env.dU, env.dX))
        for n in range(X.shape[0]):
            for j in range(env.dX):
                e = np.zeros(env.dX)
                e[j] = h
                x = np.asarray(X[n, t])
                J[:, j] += (act(x + e) - act(x - e)) / (2 * h) / X.shape[0]
        np.testing.assert_allclose(np.asarray(lin.K[t]), J, atol=1e-8)
        mean_u = np.mean([act(np.asarray(X[n, t])) for n in range(X.shape[0])], axis=0)
        np.testing.assert_allclose(
            np.asarray(lin.K[t] @ X[:, t].mean(0) + lin.k[t]), mean_u, atol=1e-10
        )
    np.testing.assert_allclose(np.asarray(lin.cov[2]), np.diag(np.asarray(params.var)))


def test_s_step_recovers_a_known_linear_controller():
    """Targets from one time-invariant controller u = Kx + k with precision P: a linear policy
    (no hidden layer) regressed on them recovers K and k, and its variance is 1/diag(P)."""
    rng = np.random.default_rng(5)
    T, N, dX, dU = 10, 8, 4, 2
    K = rng.normal(size=(dU, dX))
    k = rng.normal(size=dU)
    cov = np.array([[0.2, 0.05], [0.05, 0.1]])
    ctrl = make_controller(
        jnp.broadcast_to(K, (T, dU, dX)),
        jnp.broadcast_to(k, (T, dU)),
        jnp.broadcast_to(cov, (T, 2, 2)),
    )
    X = jnp.asarray(rng.normal(size=(N, T + 1, dX)) * [1.0, 2.0, 0.5, 1.0])
    mu, prec = controller_targets(ctrl, X)
    O = X[:, :-1].reshape(-1, dX)
    policy = GaussianPolicy(PolicyConfig(hidden=()), dX, dU, jnp.float64)
    learner = make_policy_learner(
        policy, SStepConfig(n_steps=3000, batch_size=64, learning_rate=1e-2)
    )
    state = learner.init(policy.init(jax.random.PRNGKey(0), fit_obs_normaliser(O, 1e-3)))
    state, metrics = jax.jit(learner.s_step)(
        state, jax.random.PRNGKey(1), O, mu.reshape(-1, dU), prec.reshape(-1, dU, dU)
    )
    x_new = jnp.asarray(rng.normal(size=(20, dX)))
    got = jax.vmap(policy.mean_action, in_axes=(None, 0))(state.params, x_new)
    np.testing.assert_allclose(np.asarray(got), np.asarray(x_new) @ K.T + k, atol=1e-3)
    np.testing.assert_allclose(np.asarray(state.params.var), 1 / np.diag(np.linalg.inv(cov)))
    assert float(metrics.final_loss) < 1e-5


def test_mdgps_learns_a_policy_that_holds_from_new_starts():
    """MDGPS with the true cost on the stand-in: after 8 iterations the global policy's
    noise-free rollout succeeds from both training starts and from starts it never saw."""
    env = ObservedPointMass()
    config = MDGPSConfig(
        gps=GPSConfig(iterations=8, num_samples=5, kl_step=1.0, init_var=1.0),
        policy=PolicySettings(
            network=PolicyConfig(hidden=(32, 32), init_var=1.0),
            s_step=SStepConfig(n_steps=400, learning_rate=3e-3),
        ),
    )
    md = make_mdgps(config, env, env.expert_cost)
    state, m = jax.jit(md.train)(jax.random.PRNGKey(0))
    assert not bool(m.gps.c_step_failed.any())
    assert bool(m.policy.success[-1].all()), np.asarray(m.policy.success)
    held_out = jnp.array([[0.5, 1.0, 0.0, 0.0], [-1.0, -1.0, 0.0, 0.0], [1.2, 0.2, 0.0, 0.0]])
    traj = jax.jit(md.policy_phases.rollouts)(state.policy, held_out)
    assert bool(jax.vmap(env.success)(traj.X).all())
    # One step size for every condition (MDGPS's shared step rule).
    np.testing.assert_array_equal(m.gps.step_mult[:, 0], m.gps.step_mult[:, 1])


@pytest.mark.parametrize("on_policy", [False, True])
def test_mdgps_vmapped_equals_unbatched(on_policy):
    env = ObservedPointMass()
    config = MDGPSConfig(
        gps=GPSConfig(iterations=3, num_samples=3, kl_step=1.0, init_var=1.0),
        policy=PolicySettings(
            network=PolicyConfig(hidden=(8,), init_var=1.0),
            s_step=SStepConfig(n_steps=20),
            sample_on_policy=on_policy,
            obs_noise=True,
        ),
    )
    md = make_mdgps(config, env, env.expert_cost)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (3, 4)])
    batched = jax.jit(jax.vmap(md.train))(keys)
    single = jax.jit(md.train)
    for i in range(2):
        one = single(keys[i])
        for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(batched), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b[i]), rtol=1e-9, atol=1e-10)
