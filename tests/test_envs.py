"""Every registered env and every MJCF file: loads, steps without NaNs under jit and vmap, in
float64 and float32; a second call does not recompile; bad input gives a clear error."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl.envs import ENV_NAMES, make_env
from diffgcl.sim.mjcf import MJCFError, load_mjcf, models_dir
from diffgcl.sim.rollout import sample_controller
from diffgcl.types import Env, make_controller


def zero_controller(env, T):
    dtype = jnp.zeros(()).dtype
    return make_controller(
        jnp.zeros((T, env.dU, env.dX), dtype),
        jnp.zeros((T, env.dU), dtype),
        jnp.broadcast_to(0.01 * jnp.eye(env.dU, dtype=dtype), (T, env.dU, env.dU)),
    )


def batched_rollout(env, T=8, n=3):
    x0s = env.initial_states()
    ctrl = zero_controller(env, T)

    @jax.jit
    def run(key):
        keys = jax.random.split(key, x0s.shape[0])
        return jax.vmap(lambda x0, k: sample_controller(env, ctrl, x0, k, n, with_obs=True))(
            x0s, keys
        )

    return run


@pytest.mark.parametrize("name", ENV_NAMES)
def test_env_protocol_and_batched_steps_float64(name):
    env = make_env(name)
    assert isinstance(env, Env)
    run = batched_rollout(env)
    traj = run(jax.random.key(0))
    C = env.initial_states().shape[0]
    assert traj.X.shape == (C, 3, 9, env.dX) and traj.X.dtype == jnp.float64
    assert traj.O.shape == (C, 3, 9, env.dO)
    assert np.isfinite(np.asarray(traj.X)).all() and np.isfinite(np.asarray(traj.O)).all()
    run(jax.random.key(1))
    assert run._cache_size() == 1, "a second call with new data recompiled"
    cost = jax.vmap(env.expert_cost)(traj.X[0, 0, :-1], traj.U[0, 0], jnp.arange(8))
    assert np.isfinite(np.asarray(cost)).all()
    assert env.success(traj.X[0, 0]).shape == ()


@pytest.mark.parametrize("name", ENV_NAMES)
def test_env_runs_in_float32(name):
    with jax.enable_x64(False):
        env = make_env(name)
        traj = batched_rollout(env, T=5, n=2)(jax.random.key(0))
        assert traj.X.dtype == jnp.float32
        assert np.isfinite(np.asarray(traj.X)).all()


@pytest.mark.parametrize("name", ENV_NAMES)
def test_wrong_shapes_give_clear_errors(name):
    env = make_env(name)
    x = env.initial_states()[0]
    with pytest.raises(ValueError, match=r"step: u must have shape"):
        env.step(x, jnp.zeros(env.dU + 1))
    with pytest.raises(ValueError, match=r"step: x must have shape"):
        env.step(x[:-1], jnp.zeros(env.dU))


@pytest.mark.parametrize("path", sorted(models_dir().glob("*.xml")), ids=lambda p: p.name)
def test_every_mjcf_file_loads(path):
    model = load_mjcf(path)
    assert model.nq > 0


def test_malformed_mjcf_names_the_file(tmp_path: Path):
    bad = tmp_path / "broken.xml"
    bad.write_text("<mujoco><worldbody><body><geom type='box'/></body></worldbody>")
    with pytest.raises(MJCFError, match="broken.xml"):
        load_mjcf(bad)
    with pytest.raises(MJCFError, match="not found"):
        load_mjcf(tmp_path / "missing.xml")
    with pytest.raises(ValueError, match="unknown env"):
        make_env("submarine")
