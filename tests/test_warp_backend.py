"""MJX impl="warp" sampling backend: arm rollouts equal the JAX implementation's for the same noise,
env edits reach the Warp model, clear errors, and the benchmark entry point.

Skipped (with warp's own reason) only when a real Warp step cannot run in this process; the check
is :func:`diffgcl.sim.warp_backend.warp_status`, which tries one.

Tolerance: MuJoCo Warp holds model and data in float32 (eps ≈ 1.2e-7) while the reference runs in
float64 (tests/conftest.py). On the arm (|x| ≲ 3) each step rounds at ≈ 4e-7; the velocity loop
contracts (|1 − kv·dt/I| < 1, models/arm2d.xml) and positions integrate the velocity, so even a
worst case of linear accumulation over T = 100 steps stays ≈ 4e-5; measured ≈ 3e-6. 1e-4 is
above that bound and far below what a modelling difference gives (a missed torque cap is O(1)).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl.envs import make_env
from diffgcl.sim import warp_backend
from diffgcl.sim.rollout import sample_controller, smooth_noise
from diffgcl.sim.warp_backend import (
    WarpUnavailableError,
    WarpUnsupportedError,
    benchmark_warp,
    make_warp_sampler,
    warp_status,
)
from diffgcl.types import make_controller

TOL = 1e-4


@pytest.fixture(scope="module")
def warp():
    """Skip, quoting the error, unless a real Warp step runs here (tried at first use, not at
    collection: the first try in a fresh kernel cache compiles Warp modules for ~25 s)."""
    ok, why = warp_status()
    if not ok:
        pytest.skip(f"MJX impl='warp' cannot run here: {why}")


@pytest.fixture(scope="module")
def arm():
    return make_env("arm")


@pytest.fixture(scope="module")
def sampler(warp, arm):
    return make_warp_sampler(arm)  # also checks one Warp step against arm.step


def feedback_controller(T, seed=0):
    """Stabilising feedback plus random feed-forward: the motors saturate on part of the run."""
    rng = np.random.default_rng(seed)
    K = -np.eye(2, 4) + rng.normal(scale=0.1, size=(T, 2, 4))
    k = rng.normal(scale=2.0, size=(T, 2))
    L = rng.normal(scale=0.3, size=(T, 2, 2))
    cov = L @ np.swapaxes(L, 1, 2) + 0.1 * np.eye(2)
    return make_controller(jnp.asarray(K), jnp.asarray(k), jnp.asarray(cov))


def test_warp_rollout_matches_jax_rollout(arm, sampler):
    T, N, sigma = 100, 8, 2.0
    ctrl = feedback_controller(T)
    x0 = arm.initial_states()[0]
    key = jax.random.key(7)
    ref = jax.jit(lambda k: sample_controller(arm, ctrl, x0, k, N, smooth_sigma=sigma))(key)
    # The same noise sample_controller draws internally.
    noise = jax.vmap(lambda k: smooth_noise(k, T, arm.dU, sigma))(jax.random.split(key, N))
    got = sampler.sample(ctrl, x0, noise)

    for name in ("X", "U", "O"):
        a, b = getattr(got, name), getattr(ref, name)
        assert a.shape == b.shape and a.dtype == b.dtype, (name, a.shape, b.shape)
    assert got.X.shape == (N, T + 1, 4) and got.O.shape == (N, T + 1, 0)
    np.testing.assert_array_equal(got.X[:, 0], np.broadcast_to(x0, (N, 4)))
    np.testing.assert_allclose(got.X, ref.X, rtol=0, atol=TOL)
    np.testing.assert_allclose(got.U, ref.U, rtol=0, atol=TOL)
    # The host-loop engine (mujoco_warp.step without the JAX FFI) gives the same trajectories.
    direct = sampler.sample_direct(ctrl, x0, noise)
    assert direct.X.shape == ref.X.shape and direct.X.dtype == ref.X.dtype
    np.testing.assert_allclose(direct.X, ref.X, rtol=0, atol=TOL)
    np.testing.assert_allclose(direct.U, ref.U, rtol=0, atol=TOL)
    # Not a trivial agreement: the samples spread out and the arm moves.
    assert float(jnp.std(ref.X[:, -1, :2], axis=0).min()) > 1e-2
    assert float(jnp.abs(ref.X[:, -1, :2] - x0[:2]).max()) > 0.5


def test_env_model_edits_reach_warp(warp):
    """torque_limit edits actuator_forcerange after loading; the env-step check saturates the
    motors (|kv·u| = 1000 > 400), so a lost edit would fail it."""
    env = make_env("arm", torque_limit=400.0)
    s = make_warp_sampler(env)
    np.testing.assert_allclose(np.asarray(s.model.actuator_forcerange), [[-400, 400]] * 2)


def test_unsupported_env_and_model_are_refused(warp, arm, tmp_path):
    wider = dataclasses.replace(arm, dX=5)
    with pytest.raises(WarpUnsupportedError, match=r"not \(nq \+ nv, nu\)"):
        make_warp_sampler(wider)
    xml = tmp_path / "free.xml"
    xml.write_text(
        '<mujoco><worldbody><body><freejoint/><geom size=".1"/></body></worldbody></mujoco>'
    )
    with pytest.raises(WarpUnsupportedError, match="nq = 7 != nv = 6"):
        make_warp_sampler(str(xml))


def test_unavailable_warp_names_the_reason(monkeypatch, arm):
    monkeypatch.setattr(warp_backend, "_probe", lambda quiet=True: (False, "no kernels (test)"))
    with pytest.raises(WarpUnavailableError, match=r"unavailable: no kernels \(test\)"):
        make_warp_sampler(arm)


def test_wrong_shapes_are_clear(arm, sampler):
    ctrl = feedback_controller(5)
    x0 = arm.initial_states()[0]
    with pytest.raises(ValueError, match="noise must have shape"):
        sampler.sample(ctrl, x0, jnp.zeros((3, 4, 2)))
    with pytest.raises(ValueError, match="x0 must have shape"):
        sampler.sample(ctrl, x0[:3], jnp.zeros((3, 5, 2)))


def test_benchmark_reports_steps_per_second(warp, arm):
    for engine in ("mjx", "direct"):
        rate = benchmark_warp(16, 10, env=arm, repeats=1, engine=engine)
        assert np.isfinite(rate) and rate > 0, engine
