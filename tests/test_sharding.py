"""Batch axes sharded over several (forced host) CPU devices give the single-device result."""

import os
import subprocess
import sys
import textwrap

import pytest

from diffgcl.runtime import (
    COMPILE_LEVEL_FLAGS,
    CRASH_WORKAROUND_FLAGS,
    FAST_COMPILE_FLAGS,
    QUICK_COMPILE_ENV,
    QUICK_COMPILE_FLAGS,
    SERIAL_CODEGEN_FLAGS,
)

SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import prepare_process
    prepare_process()
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
        assert "a batch of 3 does not divide over the 2 devices" in str(err), err
    else:
        raise AssertionError("odd batch accepted")
    from diffgcl.sim.sharding import shard_batch_if_even
    odd = jnp.zeros(3)
    assert shard_batch_if_even(odd) is odd
    even = shard_batch_if_even((jnp.zeros(4), jnp.zeros((4, 2)), jnp.float32(1.0)))
    assert all(len(a.sharding.device_set) == 2 for a in even), [a.sharding for a in even]
    # shard_map over the devices: the plain vmap's result, each device holding its half.
    from diffgcl.sim.sharding import vmap_over_devices
    g = lambda k, c: sample_controller(env, ctrl, x0 + c, k, 2, smooth_sigma=2.0).X
    shift = jnp.ones(4)
    out = jax.jit(vmap_over_devices(g, in_axes=(0, None)))(keys, shift)
    assert len(out.sharding.device_set) == 2, out.sharding
    np.testing.assert_allclose(np.asarray(out), np.asarray(jax.vmap(g, (0, None))(keys, shift)))
    odd = jax.jit(vmap_over_devices(g, in_axes=(0, None)))(keys[:3], shift)  # falls back
    np.testing.assert_allclose(np.asarray(odd), np.asarray(out[:3]), atol=1e-12)
    try:
        vmap_over_devices(g, in_axes=(1, None))(keys, shift)
    except ValueError as err:
        assert "in_axes must be 0 or None" in str(err)
    else:
        raise AssertionError("in_axes=1 accepted")
    print("OK")
    """
)

CORES_SCRIPT = textwrap.dedent(
    """
    import os
    from diffgcl.runtime import set_cpu_devices
    assert set_cpu_devices(3)
    assert not set_cpu_devices(5)  # already set
    import jax
    assert len(jax.devices()) == 3, jax.devices()
    print("OK", os.environ["XLA_FLAGS"])
    """
)


def test_one_device_per_core_before_jax_starts():
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run(
        [sys.executable, "-c", CORES_SCRIPT], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-3000:]
    flags = out.stdout.split("OK", 1)[1].split()  # importing diffgcl added the workaround
    assert flags == [*CRASH_WORKAROUND_FLAGS, "--xla_force_host_platform_device_count=3"]


PREPARE_SCRIPT = textwrap.dedent(
    """
    import os
    from diffgcl.runtime import prepare_process
    prepare_process()
    import jax
    jax.devices()
    print("FLAGS", os.environ["XLA_FLAGS"])
    """
)


@pytest.mark.parametrize("quick", ["0", "1"])
def test_prepare_process_adds_compile_flags_to_what_xla_flags_sets(quick):
    """The crash workaround and the emitter flag always, then the optimisation level (0 with
    ``DIFFGCL_QUICK_COMPILE=1``, else 1), after the flags the caller set (a child given its own
    ``XLA_FLAGS`` keeps them)."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    env[QUICK_COMPILE_ENV] = quick
    out = subprocess.run(
        [sys.executable, "-c", PREPARE_SCRIPT], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-3000:]
    flags = out.stdout.split("FLAGS", 1)[1].split()
    fixed = ["--xla_force_host_platform_device_count=2", *CRASH_WORKAROUND_FLAGS]
    fixed += FAST_COMPILE_FLAGS
    assert flags[: len(fixed)] == fixed
    assert flags[len(fixed) :] == list(QUICK_COMPILE_FLAGS if quick == "1" else COMPILE_LEVEL_FLAGS)


@pytest.mark.parametrize("side_by_side", [False, True])
def test_prepare_process_codegens_serially_where_processes_fill_the_cores(side_by_side):
    """With as many processes compiling as the machine has cores, XLA's codegen is not split
    (a user's own split count wins); with fewer, XLA's default stays."""
    cores = os.cpu_count() or 1
    processes = cores if side_by_side else 1
    script = PREPARE_SCRIPT.replace("prepare_process()", f"prepare_process(processes={processes})")
    for given in ("", "--xla_cpu_parallel_codegen_split_count=4"):
        env = dict(os.environ, XLA_FLAGS=given)
        env.pop(QUICK_COMPILE_ENV, None)
        out = subprocess.run(
            [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300
        )
        assert out.returncode == 0, out.stderr[-3000:]
        flags = out.stdout.split("FLAGS", 1)[1].split()
        split = [f for f in flags if f.startswith("--xla_cpu_parallel_codegen_split_count")]
        if given:
            assert split == [given]
        elif processes >= cores:
            assert split == list(SERIAL_CODEGEN_FLAGS)
        else:
            assert split == []


def test_importing_diffgcl_turns_off_the_crashing_fusions():
    """A user's script that imports diffgcl (no entry point's prepare_process) gets the
    workaround before JAX starts."""
    script = "import os, diffgcl, jax; jax.devices(); print('FLAGS', os.environ['XLA_FLAGS'])"
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split("FLAGS", 1)[1].split() == list(CRASH_WORKAROUND_FLAGS)


def test_sharded_sampling_equals_single_device():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "OK" in out.stdout


RUNNER_SCRIPT = textwrap.dedent(
    """
    import sys, tempfile
    from pathlib import Path
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import prepare_process
    prepare_process()
    sys.path.insert(0, "tests")
    from test_rgcl import Slider, tiny_config
    from diffgcl.algorithms.expert import make_demo_set, sample_expert
    from diffgcl.algorithms.gps import GPSConfig, make_gps
    from diffgcl.algorithms.rgcl import demo_batch, make_train
    from diffgcl.algorithms import runner
    from diffgcl.algorithms.runner import SimulatedCrash, train_seeds
    assert len(jax.devices()) == 2, jax.devices()
    placed = []  # device counts of what the runner shards
    def spy(tree, place=runner.shard_batch_if_even):
        out = place(tree)
        placed.append(min(len(a.sharding.device_set) for a in jax.tree.leaves(out)))
        return out
    runner.shard_batch_if_even = spy
    env = Slider()
    gps = make_gps(GPSConfig(iterations=8, init_var=1.0, kl_step=1.0), env, env.expert_cost)
    state, _ = jax.jit(gps.train)(jax.random.PRNGKey(0))
    traj, cond = sample_expert(
        env, state.controller, env.initial_states(), jax.random.PRNGKey(1), 8, smooth_sigma=None
    )
    demos = demo_batch(make_demo_set(env, traj, np.asarray(cond), cost=env.expert_cost), 1)
    config = tiny_config("v2", iterations=3)
    seeds = [0, 1]
    out = Path(tempfile.mkdtemp()) / "run"
    try:
        train_seeds(config, env, demos, seeds, out=out, chunk=1, checkpoint_every=1, crash_after=2)
    except SimulatedCrash:
        pass
    else:
        raise AssertionError("no crash")
    resumed = train_seeds(config, env, demos, seeds, out=out, chunk=1, resume=True, progress=False)
    assert resumed.resumed_from == 2
    assert placed and min(placed) == 2, placed
    # Reference: the same seeds as one unsharded jit(vmap(train)) on the default device.
    rgcl = make_train(config, env)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    hps = jax.tree.map(lambda a: jnp.stack([a, a]), rgcl.default_hparams())
    ref, _ = jax.jit(jax.vmap(rgcl.train, in_axes=(0, None, 0)))(keys, demos, hps)
    assert len(ref.gps.controller.K.sharding.device_set) == 1
    for a, b in zip(jax.tree.leaves(resumed.state), jax.tree.leaves(ref), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-9)
    print("OK")
    """
)


def test_runner_shards_seeds_over_devices_and_resumes():
    """train_seeds splits the seed batch over 2 CPU devices; a crash and resume on that layout
    gives the unsharded single-device result (float64)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    out = subprocess.run(
        [sys.executable, "-c", RUNNER_SCRIPT],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
        cwd=root,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "OK" in out.stdout


def test_vmap_over_devices_programs_carry_the_functions_name():
    """Compile logs and experiments/bench_compile.py name a program by its function: the
    wrapper takes the mapped function's name."""

    def rollout_costs(x):
        return x * 2.0

    import jax
    import jax.numpy as jnp

    from diffgcl.sim.sharding import vmap_over_devices

    lowered = jax.jit(vmap_over_devices(rollout_costs)).lower(jnp.zeros((4, 3)))
    assert "jit_rollout_costs" in lowered.as_text()
