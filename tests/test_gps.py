"""Trajectory-optimisation GPS (diffgcl.algorithms.gps): a linear stand-in env with two
conditions, the MJX arm with its expert cost, expert demos, and compilation counts."""

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl.algorithms.expert import write_expert_demos
from diffgcl.algorithms.gps import GPSConfig, GPSHyperparams, first_success, make_gps
from diffgcl.data.demos import DemoSet


@dataclass(frozen=True)
class PointMass:
    """2-D double integrator (a stand-in env for the GPS wiring): x = [p, v], u = force."""

    name: str = "point"
    dX: int = 4
    dU: int = 2
    dO: int = 0
    dt: float = 0.1
    horizon: int = 20
    mjcf_path: str = ""

    def step(self, x, u):
        p, v = x[:2], x[2:]
        v = v + self.dt * u
        return jnp.concatenate([p + self.dt * v, v])

    def obs(self, x, key=None):
        return jnp.zeros((0,), x.dtype)

    def initial_states(self):
        return jnp.array([[1.0, -1.0, 0.0, 0.0], [-2.0, 0.5, 0.0, 0.0]])

    def expert_cost(self, x, u, t):
        return 0.5 * jnp.sum(x[:2] ** 2) + 0.05 * jnp.sum(x[2:] ** 2) + 1e-3 * jnp.sum(u**2)

    def success(self, X):
        return jnp.all(jnp.abs(X[-3:, :2]) < 0.1)


@pytest.mark.parametrize("dynamics", ["autodiff", "regression"])
def test_gps_on_point_mass_two_conditions(dynamics):
    env = PointMass()
    config = GPSConfig(iterations=6, num_samples=5, dynamics=dynamics, init_var=1.0)
    gps = make_gps(config, env, env.expert_cost)
    # A sweep over a traced hyperparameter: two KL steps in one vmapped program.
    hparams = GPSHyperparams(kl_step=jnp.array([0.2, 0.4]), init_var=jnp.array([1.0, 1.0]))
    sweep = jax.jit(jax.vmap(gps.train, in_axes=(None, 0)))
    states, sweep_metrics = sweep(jax.random.PRNGKey(0), hparams)
    np.testing.assert_allclose(sweep_metrics.epsilon[:, 0], [[4.0, 4.0], [8.0, 8.0]])
    state, metrics = jax.tree.map(lambda a: a[0], (states, sweep_metrics))
    assert metrics.cost.shape == (6, 2)
    assert state.controller.K.shape == (2, env.horizon, env.dU, env.dX)
    assert not bool(metrics.c_step_failed.any())
    for leaf in jax.tree.leaves(state):
        assert np.all(np.isfinite(leaf))
    cost = np.asarray(metrics.cost)
    assert np.all(cost[-1] < 0.5 * cost[0])
    assert bool(metrics.success[-1].all())
    assert np.all(np.asarray(metrics.entropy[-1]) < np.asarray(metrics.entropy[0]))
    # The C-step met its KL budget whenever it converged.
    done = np.asarray(metrics.c_step_status) == 0
    kl, eps = np.asarray(metrics.kl), np.asarray(metrics.epsilon)
    assert np.all(np.abs(kl - eps)[done] <= 0.1 * eps[done])


@pytest.fixture(scope="module")
def arm_run():
    from diffgcl.envs import make_env

    env = make_env("arm")
    gps = make_gps(GPSConfig(), env, env.expert_cost)
    train = jax.jit(jax.vmap(gps.train))
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    state, metrics = train(keys)
    return env, train, state, metrics


def test_arm_gps_reaches_upright(arm_run):
    env, train, state, metrics = arm_run
    assert metrics.success.shape == (2, 10, 1)
    assert bool(metrics.success[:, -1].all()), np.asarray(metrics.success)
    first = np.asarray(first_success(metrics.success))
    assert np.all((first >= 1) & (first < 10))
    assert not bool(metrics.c_step_failed.any())
    cost = np.asarray(metrics.cost)
    assert np.all(cost[:, -1] < 0.5 * cost[:, 0])
    # A second sweep with other seeds reuses the compiled program.
    train(jax.random.split(jax.random.PRNGKey(1), 2))
    assert train._cache_size() == 1


def test_expert_demos_round_trip(arm_run, tmp_path):
    env, _, state, _ = arm_run
    controllers = jax.tree.map(lambda a: a[0], state.controller)
    demos = write_expert_demos(
        tmp_path / "demos", env, controllers, jax.random.PRNGKey(3), 4, cost=env.expert_cost
    )
    loaded = DemoSet.load(tmp_path / "demos")
    assert loaded.X.shape == (4, env.horizon + 1, env.dX)
    assert loaded.U.shape == (4, env.horizon, env.dU)
    assert loaded.O.shape == (4, env.horizon + 1, env.dO)
    assert loaded.env == "arm" and loaded.dt == pytest.approx(env.dt)
    assert all(e["source"] == "gps-expert" for e in loaded.episodes)
    assert sum(e["success"] for e in loaded.episodes) >= 3
    np.testing.assert_array_equal(loaded.X, demos.X)
    # The demos carry the controller's stochasticity: they differ from each other.
    assert np.std(loaded.U[:, 10], axis=0).min() > 1e-3


@pytest.mark.slow
def test_arm_gps_32_seeds():
    from diffgcl.envs import make_env

    env = make_env("arm")
    gps = make_gps(GPSConfig(), env, env.expert_cost)
    _, metrics = jax.jit(jax.vmap(gps.train))(jax.random.split(jax.random.PRNGKey(42), 32))
    assert int(metrics.success[:, -1].all(axis=-1).sum()) >= 31
    assert not bool(metrics.c_step_failed.any())


def test_cli_registers_gps_and_demos_subcommands(tmp_path, monkeypatch):
    import argparse

    from diffgcl.cli import gps as gps_cli

    parser = argparse.ArgumentParser()
    gps_cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["gps", "--fast", "--seeds", "3", "--json", str(tmp_path / "s.json")])
    assert args.command == "gps" and args.seeds == 3 and args.fast and callable(args.func)
    config = gps_cli.config_from_args(args)
    assert config.num_samples == 5 and config.kl_step == 0.2 and config.init_var == 0.1
    assert config.smooth_sigma == 2.0 and config.iterations == 10
    args = parser.parse_args(["demos", str(tmp_path / "demos"), "--num-demos", "7"])
    assert args.command == "demos" and args.num_demos == 7 and callable(args.func)
    with pytest.raises(ValueError, match="dynamics"):
        GPSConfig(dynamics="magic")
    # The commands return exit codes (diffgcl.cli.main passes them to sys.exit).
    monkeypatch.setattr(gps_cli, "run_arm_gps", lambda a: {"success_rate": 0.0})
    args = parser.parse_args(["gps"])
    assert args.func(args) == 1


def test_gps_reports_c_step_failures_without_nan(capsys):
    from diffgcl.algorithms.gps_runner import report_failures

    env = PointMass()

    def hopeless(x, u, t):  # concave in u beyond any eta the search may try
        return env.expert_cost(x, u, t) - 1e22 * jnp.sum(u**2)

    config = GPSConfig(iterations=2, num_samples=3, init_var=1.0)
    gps = make_gps(config, env, hopeless, true_cost=env.expert_cost)
    state, metrics = jax.jit(gps.train)(jax.random.PRNGKey(0))
    assert bool(metrics.c_step_failed.all())
    for leaf in jax.tree.leaves((state, metrics)):
        assert np.all(np.isfinite(leaf))
    # The controller is kept (the initial one) and the host loop names every failure.
    np.testing.assert_array_equal(state.controller.K, np.zeros_like(state.controller.K))
    batched = jax.tree.map(lambda a: np.asarray(a)[None], metrics)
    lines = report_failures(batched, [7])
    assert len(lines) == 4 and "not positive definite" in lines[0] and "seed 7" in lines[0]
    assert "C-step failure" in capsys.readouterr().out
