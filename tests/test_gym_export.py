"""diffgcl.gym: a learned cost as gymnasium's reward, and trajectories with imitation's fields.

Nothing is learned here: the cost is a cost network with random parameters, so the check is
that the wrapper's reward is minus that cost at the recorded step's state and action."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl import gym as dgym
from diffgcl.costs.network import CostNetwork, CostNetworkConfig

gymnasium = pytest.importorskip("gymnasium")


def random_cost(dX, dU, seed=0):
    net = CostNetwork(CostNetworkConfig(hidden=(), n_features=2 * dX), dX, dU, jnp.float32)
    params = net.init(jax.random.PRNGKey(seed))
    return net.bind(params)


@pytest.mark.parametrize(
    "env_id, dX", [("InvertedPendulum-v5", 4), ("Reacher-v5", 8)], ids=["pendulum", "reacher"]
)
def test_wrapper_reward_is_minus_the_learned_cost(env_id, dX):
    env = gymnasium.make(env_id)
    dU = env.action_space.shape[0]
    cost = random_cost(dX, dU)
    scale = np.full(dU, 3.0 if dU == 1 else 1.0)  # inverted_pendulum.xml: ctrlrange ±3
    reward = dgym.LearnedCostReward(cost, dgym.state_map(env_id), scale)
    wrapped = dgym.learned_cost_env(env, reward)
    obs, _ = wrapped.reset(seed=3)
    data = env.unwrapped.data
    qpos, qvel = data.qpos.copy(), data.qvel.copy()  # the state the step starts from
    action = np.asarray(env.action_space.sample(), np.float32)
    _, r, _, _, info = wrapped.step(action)
    x = np.concatenate([qpos, qvel])
    if env_id.startswith("Reacher"):
        x[6:] = 0.0  # the target's velocity: 0 in MuJoCo, 0 by the map
    expected = -float(cost(jnp.asarray(x, jnp.float32), jnp.asarray(action / scale), 0))
    assert r == pytest.approx(expected, rel=1e-4, abs=1e-4)
    assert "true_reward" in info
    # The observation-to-state map recovers MuJoCo's state.
    np.testing.assert_allclose(dgym.state_map(env_id)(obs), x, atol=1e-6)
    # The imitation-style call on a batch: (obs, acts, next_obs, dones) -> rewards [B].
    batch = reward(np.stack([obs, obs]), np.stack([action, action]), None, np.zeros(2, bool))
    assert batch.shape == (2,) and batch.dtype == np.float32
    np.testing.assert_allclose(batch, expected, rtol=1e-4, atol=1e-4)


def test_double_pendulum_state_map():
    env = gymnasium.make("InvertedDoublePendulum-v5")
    obs, _ = env.reset(seed=1)
    d = env.unwrapped.data
    x = np.concatenate([d.qpos, np.clip(d.qvel, -10, 10)])
    np.testing.assert_allclose(dgym.state_map("InvertedDoublePendulum-v5")(obs), x, atol=1e-6)


def test_trajectories_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    trajs = [
        dgym.PlainTrajectory(
            obs=rng.normal(size=(6, 4)).astype(np.float32),
            acts=rng.normal(size=(5, 1)).astype(np.float32),
            infos=[{"t": i} for i in range(5)] if k == 0 else None,
            terminal=bool(k),
        )
        for k in range(2)
    ]
    path = dgym.save_trajectories(tmp_path / "demos_traj.npz", trajs)
    back = dgym.load_trajectories(path)
    assert len(back) == 2
    for a, b in zip(trajs, back, strict=True):
        np.testing.assert_array_equal(a.obs, b.obs)
        assert a.obs.dtype == b.obs.dtype
        np.testing.assert_array_equal(a.acts, b.acts)
        assert a.infos == b.infos and a.terminal == b.terminal
    again = dgym.from_imitation(back)
    assert [t.terminal for t in again] == [False, True]
    with pytest.raises(ValueError, match="obs must be"):
        dgym.PlainTrajectory(obs=np.zeros((5, 4)), acts=np.zeros((5, 1)))
