"""The global policy (diffgcl.policies) and MDGPS (diffgcl.algorithms.mdgps): the S-step loss and
variance by hand, the autodiff linearisation against finite differences, recovery of a known
linear controller, jit(vmap) against unbatched runs, and MDGPS learning a policy on a stand-in."""

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl.algorithms.gps import GPSConfig
from diffgcl.algorithms.mdgps import (
    MDGPSConfig,
    PolicySettings,
    condition_weights,
    make_mdgps,
    make_policy_phases,
)
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

    success_tolerance: float = 0.15

    @property
    def target(self):
        return jnp.zeros(2)

    def initial_states(self):
        return jnp.array([[1.0, -1.0, 0.0, 0.0], [-1.5, 0.5, 0.0, 0.0]])

    def expert_cost(self, x, u, t):
        return 0.5 * jnp.sum(x[:2] ** 2) + 0.05 * jnp.sum(x[2:] ** 2) + 1e-3 * jnp.sum(u**2)

    def success(self, X):
        return jnp.all(jnp.abs(X[-3:, :2]) < self.success_tolerance)


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


def test_condition_weights_by_hand():
    cost = jnp.array([1.0, 3.0, 2.0, 25.0, 19.0])  # median 3: 10 × 3 = 30 keeps all, 5 × 3 not
    np.testing.assert_array_equal(condition_weights(cost, 10.0, 5, jnp.float64), np.ones(5))
    np.testing.assert_array_equal(condition_weights(cost, 5.0, 5, jnp.float64), [1, 1, 1, 0, 0])
    np.testing.assert_array_equal(condition_weights(cost, None, 5, jnp.float64), np.ones(5))
    np.testing.assert_array_equal(condition_weights(None, 5.0, 3, jnp.float64), np.ones(3))
    # A non-positive median judges nothing (a cost is not known to be positive).
    zero = jnp.array([0.0, 0.0, 7.0])
    np.testing.assert_array_equal(condition_weights(zero, 2.0, 3, jnp.float64), np.ones(3))


def test_s_step_leaves_out_a_diverged_condition():
    """Three conditions, two of them with targets from one linear controller and one diverged
    (its samples far out, its controller's gains wild, its cost 100× the others'): with
    ``outlier_cost_ratio`` the linear policy recovers the sane controller and reports one
    condition left out; without it, the diverged condition drags the fit away."""
    env = dataclasses.replace(ObservedPointMass(), horizon=10)
    rng = np.random.default_rng(2)
    T, N, dX, dU = 10, 6, 4, 2
    K = rng.normal(size=(dU, dX))
    k = rng.normal(size=dU)

    def ctrl(K, k):
        return make_controller(
            jnp.broadcast_to(K, (T, dU, dX)),
            jnp.broadcast_to(k, (T, dU)),
            jnp.broadcast_to(0.1 * jnp.eye(dU), (T, dU, dU)),
        )

    sane = ctrl(K, k)
    wild = ctrl(50.0 * rng.normal(size=(dU, dX)), 30.0 * rng.normal(size=dU))
    controllers = jax.tree.map(lambda a, b: jnp.stack([a, a, b]), sane, wild)
    X = jnp.asarray(
        rng.normal(size=(3, N, T + 1, dX)) * np.array([1.0, 1.0, 30.0])[:, None, None, None]
    )
    O = X  # the policy reads the state itself (a linear policy on [p, v] recovers K exactly)
    cost = jnp.array([10.0, 12.0, 1000.0])
    x_new = jnp.asarray(rng.normal(size=(20, dX)))
    errors = {}
    for ratio in (10.0, None):
        settings = PolicySettings(
            network=PolicyConfig(hidden=()),
            s_step=SStepConfig(n_steps=2000, batch_size=64, learning_rate=1e-2),
            outlier_cost_ratio=ratio,
        )
        point = dataclasses.replace(env, dO=dX)
        phases = make_policy_phases(settings, GPSConfig(num_samples=N), point, x0=X[:, 0, 0])
        state = phases.init(jax.random.PRNGKey(0), O[:2])
        state, metrics = jax.jit(phases.s_step)(
            state, jax.random.PRNGKey(1), X, O, controllers, cost
        )
        got = jax.vmap(phases.policy.mean_action, in_axes=(None, 0))(state.params, x_new)
        errors[ratio] = float(np.abs(np.asarray(got) - (np.asarray(x_new) @ K.T + k)).max())
        assert int(metrics.left_out) == (1 if ratio else 0)
    assert errors[10.0] < 1e-3, errors
    assert errors[None] > 0.1, errors


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


def small_mdgps(env, iterations: int, s_steps: int, **policy):
    """MDGPS on ``env`` with 3 samples per condition and an 8-unit policy (``policy``: more
    :class:`PolicySettings`), small enough to compare programs on."""
    config = MDGPSConfig(
        gps=GPSConfig(iterations=iterations, num_samples=3, kl_step=1.0, init_var=1.0),
        policy=PolicySettings(
            network=PolicyConfig(hidden=(8,), init_var=1.0),
            s_step=SStepConfig(n_steps=s_steps),
            **policy,
        ),
    )
    return make_mdgps(config, env, env.expert_cost)


def test_mdgps_step_rules():
    """``"global"`` and ``"geometric"``: one KL step multiplier for both conditions at every
    iteration; ``"classic"``: each condition adapts its own, so from two different starts they
    part after the first adaptation (the same first iteration, which keeps the initial
    multiplier). The two shared rules agree until the conditions' estimates differ, then part."""
    env = ObservedPointMass()
    steps = {}
    for rule in ("global", "geometric", "classic"):
        md = small_mdgps(env, 4, 20, step_rule=rule)
        _, m = jax.jit(md.train)(jax.random.PRNGKey(2))
        steps[rule] = np.asarray(m.gps.step_mult)  # [iterations, C]
    for rule in ("global", "geometric"):
        np.testing.assert_array_equal(steps[rule][:, 0], steps[rule][:, 1])
        np.testing.assert_array_equal(steps[rule][0], steps["classic"][0])
    assert np.any(np.abs(steps["classic"][1:, 0] - steps["classic"][1:, 1]) > 1e-6), steps
    assert np.any(np.abs(steps["geometric"][1:, 0] - steps["global"][1:, 0]) > 1e-6), steps
    with pytest.raises(ValueError, match="step_rule 'shared'"):
        PolicySettings(step_rule="shared")


@pytest.mark.parametrize("on_policy", [False, True])
def test_mdgps_vmapped_equals_unbatched(on_policy):
    env = ObservedPointMass()
    md = small_mdgps(env, 3, 20, sample_on_policy=on_policy, obs_noise=True)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (3, 4)])
    batched = jax.jit(jax.vmap(md.train))(keys)
    single = jax.jit(md.train)
    for i in range(2):
        one = single(keys[i])
        for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(batched), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b[i]), rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("obs_noise", [False, True])
def test_mdgps_staged_runner_equals_the_traced_training_program(obs_noise):
    """The host loop (:func:`run_gps_seeds`: the policy's first observations and every rollout
    through the staged simulator) gives the state and metrics of ``jax.vmap(train)``."""
    from diffgcl.algorithms.staged import run_gps_seeds

    env = ObservedPointMass()
    md = small_mdgps(env, 2, 10, obs_noise=obs_noise)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (5, 6)])
    state, metrics = jax.jit(jax.vmap(md.train))(keys)
    state_s, metrics_s, _ = run_gps_seeds(md, keys, 2, env)
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(state_s), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-8, atol=1e-9)
    for a, b in zip(jax.tree.leaves(metrics), jax.tree.leaves(metrics_s), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-8, atol=1e-9)


def test_bc_recovers_the_linear_controller_of_its_demos():
    """Demos of u = Kx + k + ε (ε ~ N(0, 0.1²) per dimension) on the stand-in: a linear policy
    cloned from their (o, u) pairs has the demonstrator's gains and noise."""
    from diffgcl.algorithms.bc import BCConfig, make_bc

    env = ObservedPointMass()
    rng = np.random.default_rng(7)
    K = np.array([[-2.0, 0.0, -1.5, 0.0], [0.0, -1.0, 0.0, -2.0]])
    k = np.array([0.3, -0.2])
    N, T = 40, env.horizon
    X = np.zeros((N, T + 1, env.dX))
    U = np.zeros((N, T, env.dU))
    X[:, 0, :2] = rng.uniform(-2, 2, size=(N, 2))
    for t in range(T):
        U[:, t] = X[:, t] @ K.T + k + 0.1 * rng.normal(size=(N, env.dU))
        X[:, t + 1] = np.asarray(jax.vmap(env.step)(jnp.asarray(X[:, t]), jnp.asarray(U[:, t])))
    O = jax.vmap(jax.vmap(env.obs))(jnp.asarray(X))
    mask = np.ones((N, T + 1))
    mask[0, 5:] = 0.0  # a truncated demo: its padding must not pull the fit
    U[0, 5:] = 100.0
    config = BCConfig(
        network=PolicyConfig(hidden=()),
        fit=SStepConfig(n_steps=4000, batch_size=128, learning_rate=1e-2),
    )
    policy, fit = make_bc(config, env.dO, env.dU, jnp.float64)
    state, _ = jax.jit(fit)(jax.random.PRNGKey(0), O, jnp.asarray(U), jnp.asarray(mask))
    x_new = jnp.asarray(X[1:, ::4].reshape(-1, env.dX))  # states the demos visited
    got = np.asarray(jax.vmap(lambda x: policy.mean_action(state.params, env.obs(x)))(x_new))
    # The reference: ordinary least squares of u on [o, 1] over the valid steps.
    valid = mask[:, :T].reshape(-1) > 0
    A = np.concatenate([np.asarray(O[:, :T]).reshape(-1, env.dO), np.ones((N * T, 1))], 1)
    coef, *_ = np.linalg.lstsq(A[valid], U.reshape(-1, env.dU)[valid], rcond=None)
    O_new = np.asarray(jax.vmap(env.obs)(x_new))
    ols = np.concatenate([O_new, np.ones((len(O_new), 1))], 1) @ coef
    np.testing.assert_allclose(got, ols, atol=1e-2)
    np.testing.assert_allclose(got, np.asarray(x_new) @ K.T + k, atol=0.1)  # the demonstrator
    resid = U.reshape(-1, env.dU)[valid] - A[valid] @ coef
    np.testing.assert_allclose(np.asarray(state.params.var), resid.var(0), rtol=1e-2)
    np.testing.assert_allclose(np.asarray(state.params.var), [0.01, 0.01], rtol=0.2)


@pytest.fixture(scope="module")
def observed_demos():
    """GPS expert demos (4 per condition) on the observed stand-in."""
    from diffgcl.algorithms.expert import make_demo_set, sample_expert
    from diffgcl.algorithms.gps import make_gps
    from diffgcl.algorithms.rgcl import demo_batch

    env = ObservedPointMass()
    gps = make_gps(GPSConfig(iterations=8, init_var=1.0, kl_step=1.0), env, env.expert_cost)
    state, metrics = jax.jit(gps.train)(jax.random.PRNGKey(0))
    assert bool(metrics.success[-1].all())
    traj, cond = sample_expert(
        env, state.controller, env.initial_states(), jax.random.PRNGKey(1), 8, smooth_sigma=None
    )
    demos = make_demo_set(env, traj, np.asarray(cond), cost=env.expert_cost)
    return env, demo_batch(demos, 2)


def rgcl_policy_config(schedule: str, **changes):
    from diffgcl.algorithms.rgcl import RGCLConfig
    from diffgcl.costs.gcl import GCLConfig
    from diffgcl.costs.network import CostNetworkConfig

    return RGCLConfig(
        schedule=schedule,
        iterations=changes.pop("iterations", 8 if schedule == "v2" else 4),
        gps_per_update=2,
        gps=GPSConfig(num_samples=5, kl_step=1.0, init_var=1.0, gauss_newton=True, maxent=True),
        network=CostNetworkConfig(hidden=(), n_features=8, action_weight=1e-2),
        gcl=GCLConfig(n_steps=10, pretrain_steps=50, learning_rate=1e-2, goal_weight=1.0),
        buffer_controllers=6,
        freeze_last=1,
        policy=PolicySettings(
            network=PolicyConfig(hidden=(32, 32), init_var=1.0),
            s_step=SStepConfig(n_steps=300, learning_rate=3e-3),
            **changes,
        ),
    )


def test_rgcl_v2_with_a_policy_learns_from_demos(observed_demos):
    """rGCL v2 with MDGPS on the stand-in: the global policy trained on the learned cost reaches
    the target from both training starts, noise-free."""
    from diffgcl.algorithms.rgcl import make_train

    env, demos = observed_demos
    rgcl = make_train(rgcl_policy_config("v2"), env)
    state, m = jax.jit(rgcl.train)(jax.random.PRNGKey(2), demos)
    assert m.policy.success.shape == (8, 1, 2)
    assert bool(m.policy.success[-1, -1].all()), np.asarray(m.policy.success[:, -1])
    assert not bool(m.rolled_back.any())
    assert int(state.policy.step) == 8 * 300
    assert state.policy.params.var.shape == (env.dU,)
    # Every iteration's policy is kept, the last one is the state's; its learned cost from the
    # training starts is the cost network's on its own rollouts.
    from diffgcl.algorithms.rgcl import policy_learned_costs
    from diffgcl.eval.policy import policy_rollouts

    for a, b in zip(
        jax.tree.leaves(state.policy.params), jax.tree.leaves(m.policy_params), strict=True
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b[-1]))
    costs = jax.jit(lambda c, p: policy_learned_costs(rgcl, env, c, p))(
        state.cost.params, m.policy_params
    )
    assert costs.shape == (8, 2) and bool(jnp.isfinite(costs).all())
    traj = policy_rollouts(
        env, rgcl.policy_phases.policy, state.policy.params, env.initial_states()
    )
    trajectory_cost = jax.vmap(rgcl.network.trajectory_cost, (None, 0, 0))
    want = trajectory_cost(state.cost.params, traj.X, traj.U)
    np.testing.assert_allclose(np.asarray(costs[-1]), np.asarray(want), rtol=1e-10)
    # The first policy (fitted to the initial controllers) does worse by the learned cost.
    assert float(costs[0].mean()) > float(costs[-1].mean())


@pytest.mark.parametrize("on_policy", [pytest.param(False, marks=pytest.mark.slow), True])
def test_rgcl_v1_with_a_policy_vmapped_equals_unbatched(observed_demos, on_policy):
    from diffgcl.algorithms.rgcl import make_train

    env, demos = observed_demos
    config = rgcl_policy_config("v1", iterations=2, sample_on_policy=on_policy)
    config = dataclasses.replace(
        config,
        policy=dataclasses.replace(config.policy, s_step=SStepConfig(n_steps=10)),
        gcl=dataclasses.replace(config.gcl, pretrain_steps=5, n_steps=3),
    )
    rgcl = make_train(config, env)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (5, 6)])
    batched = jax.jit(jax.vmap(rgcl.train, in_axes=(0, None)))(keys, demos)
    for i in range(2):
        one = jax.jit(rgcl.train)(keys[i], demos)
        for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(batched), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b[i]), rtol=1e-8, atol=1e-9)


def test_cli_train_with_a_policy_and_bc(observed_demos, tmp_path, monkeypatch):
    """``diffgcl train --policy mdgps`` writes each seed's policy (loadable, same actions) and its
    success; ``diffgcl bc DEMOS`` clones a demo folder into policies of the same format."""
    import argparse
    import json

    import diffgcl.envs
    from diffgcl.algorithms import presets
    from diffgcl.algorithms.expert import make_demo_set, sample_expert
    from diffgcl.cli import policy as policy_cli
    from diffgcl.cli import rgcl as rgcl_cli
    from diffgcl.policies.io import load_policy

    env, demos = observed_demos
    monkeypatch.setattr(diffgcl.envs, "make_env", lambda name, **kw: env)
    monkeypatch.setattr(rgcl_cli, "env_from_args", lambda args, recorded=None: (env, {}))
    from diffgcl.algorithms import runner

    for module in (rgcl_cli, runner):
        monkeypatch.setattr(module, "load_demo_batch", lambda path, env: demos)
    monkeypatch.setitem(presets.PRESETS, "tiny", lambda: rgcl_policy_config("v2", iterations=3))
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    rgcl_cli.register(sub)
    policy_cli.register(sub)
    out = tmp_path / "run"
    argv = ["train", "--preset", "tiny", "--seeds", "2", "--out", str(out), "--no-progress"]
    args = parser.parse_args(argv + ["--policy", "mdgps", "--set", "policy.s_step.n_steps=20"])
    args.func(args)
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["policy_success"]) == 2 and 0.0 <= summary["policy_success_rate"] <= 1.0
    assert json.loads((out / "config.json").read_text())["policy"]["s_step"]["n_steps"] == 20
    assert (out / "policy_rollouts.png").stat().st_size > 1000
    policy, params, info = load_policy(out / "policies" / "seed_1")
    assert info["seed"] == 1 and policy.dO == env.dO
    config, result, _ = runner.load_run(out, env)
    saved = jax.tree.map(lambda a: jnp.asarray(a[1]), result.state.policy.params)
    o = env.obs(env.initial_states()[0])
    np.testing.assert_allclose(
        np.asarray(policy.mean_action(params, o)), np.asarray(policy.mean_action(saved, o))
    )
    assert config.policy is not None and config.policy.s_step.n_steps == 20

    traj, cond = sample_expert(
        env, demos.controller, env.initial_states(), jax.random.PRNGKey(3), 6, smooth_sigma=None
    )
    make_demo_set(env, traj, np.asarray(cond)).save(tmp_path / "demos")
    bc_out = tmp_path / "bc"
    args = parser.parse_args(
        ["bc", str(tmp_path / "demos"), "--seeds", "2", "--steps", "50", "--out", str(bc_out)]
    )
    assert args.func(args) == 0
    assert len(json.loads((bc_out / "summary.json").read_text())["success"]) == 2
    load_policy(bc_out / "seed_0")


def test_obs_normaliser_floors_a_constant_dimension_relative_to_its_size():
    """A range beam that read its maximum (60 m) in every fitting sample has no spread: the
    relative floor gives it 10 % of its size, so a first sighting is a few σ, not 10⁴."""
    rng = np.random.default_rng(0)
    O = np.stack([np.full(200, 60.0), rng.normal(2.0, 0.5, 200), np.zeros(200)], axis=1)
    norm = fit_obs_normaliser(jnp.asarray(O), 1e-3, rel_floor=0.1)
    np.testing.assert_allclose(np.asarray(norm.std)[0], 6.0, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(norm.std)[1], O[:, 1].std(), rtol=1e-6)  # spread wins
    np.testing.assert_allclose(np.asarray(norm.std)[2], 1e-3)  # all zero: the absolute floor
    plain = fit_obs_normaliser(jnp.asarray(O), 1e-3)
    np.testing.assert_allclose(np.asarray(plain.std)[0], 1e-3)


def test_evaluate_policy_compiles_once_for_new_starts_keys_and_parameters():
    """Another seed's parameters, starts and key reuse the compiled program (the CLI evaluates
    every seed in a loop), and the figures are those of a plain rollout."""
    from diffgcl.eval import policy as evaluation

    env = ObservedPointMass()
    policy, params = random_policy(jax.random.PRNGKey(3), hidden=(8,))
    _, other = random_policy(jax.random.PRNGKey(4), hidden=(8,))
    evaluation._rollouts_and_success.clear_cache()
    x0 = env.initial_states()
    first = evaluation.evaluate_policy(env, policy, params, x0, jax.random.PRNGKey(0))
    second = evaluation.evaluate_policy(env, policy, other, x0 + 0.1, jax.random.PRNGKey(1))
    assert evaluation._rollouts_and_success._cache_size() == 1
    for got, p, x in ((first, params, x0), (second, other, x0 + 0.1)):
        traj = evaluation.policy_rollouts(env, policy, p, x)
        np.testing.assert_allclose(got["X"], np.asarray(traj.X), rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(got["success"], np.asarray(jax.vmap(env.success)(traj.X)))
    sampled = evaluation.evaluate_policy(
        env, policy, params, x0, jax.random.PRNGKey(2), noisy_samples=3
    )
    assert sampled["sample_success"].shape == (2,)
    assert evaluation._rollouts_and_success._cache_size() == 2  # the noisy batch: one more
