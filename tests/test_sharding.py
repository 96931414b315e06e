"""Batch axes sharded over several (forced host) CPU devices give the single-device result."""

import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import enable_compilation_cache
    enable_compilation_cache()
    from diffgcl.envs import make_env
    from diffgcl.sim.rollout import sample_controller
    from diffgcl.sim.sharding import shard_batch, batch_mesh
    from diffgcl.types import make_controller
    assert len(jax.devices()) == 2, jax.devices()
    env = make_env("arm")
    T = 10
    ctrl = make_controller(jnp.zeros((T, 2, 4)), jnp.zeros((T, 2)),
                           jnp.broadcast_to(0.1 * jnp.eye(2), (T, 2, 2)))
    x0 = env.initial_states()[0]
    f = jax.jit(jax.vmap(lambda k: sample_controller(env, ctrl, x0, k, 2, smooth_sigma=2.0)))
    keys = jax.random.split(jax.random.key(0), 4)
    ref = f(keys)
    out = f(shard_batch(keys, batch_mesh()))
    assert len(out.X.sharding.device_set) == 2, out.X.sharding
    np.testing.assert_allclose(np.asarray(out.X), np.asarray(ref.X), atol=1e-12)
    try:
        shard_batch(jnp.zeros(3))
    except ValueError as err:
        assert "not divisible by 2 devices" in str(err)
    else:
        raise AssertionError("odd batch accepted")
    print("OK")
    """
)


def test_sharded_sampling_equals_single_device():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "OK" in out.stdout
