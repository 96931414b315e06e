"""Hull system identification: the shooting fit recovers the generator's parameters.

Fast checks use ``step="ode"`` (the same integration as ``hull_step`` in plain JAX, tested equal
here) so that compilation stays in seconds; the MJX path is the slow check.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl.data.demos import DemoSet
from diffgcl.data.synth import TRUE_FACTORS, SynthConfig, draw_profiles, simulate, true_params
from diffgcl.data.synth.operator_model import _batched_step
from diffgcl.data.sysid import (
    SYSID_FIELDS,
    SysIdConfig,
    identify,
    make_windows,
    ode_step,
    prediction_error,
)
from diffgcl.sim import hull

SHORT = SynthConfig(approach_m=(60.0, 80.0), end_margin_m=(25.0, 30.0))


@pytest.fixture(scope="module")
def truth_runs():
    """Eight short simulated episodes on the true hull: [(X: [K+1, dX], U: [K, dU])]."""
    rng = np.random.default_rng(7)
    profiles = draw_profiles(rng, 8, SHORT)
    return simulate(profiles, true_params(), rng, max_steps=400)


def _demos(runs) -> DemoSet:
    """Stack noiseless runs into a DemoSet (padded, mask 0 on pads)."""
    T = max(U.shape[0] for _, U in runs)
    N = len(runs)
    X = np.zeros((N, T + 1, hull.DX))
    U = np.zeros((N, T, hull.DU))
    mask = np.zeros((N, T + 1))
    for i, (x, u) in enumerate(runs):
        X[i, : len(x)], X[i, len(x) :] = x, x[-1]
        U[i, : len(u)] = u
        mask[i, : len(x)] = 1
    return DemoSet(X=X, U=U, O=np.zeros((N, T + 1, 0)), mask=mask, dt=0.1, env="hull")


def test_ode_step_equals_hull_step(truth_runs):
    params = true_params(jnp.float64)
    model = hull.hull_model(jnp.float64)[1]
    x = jnp.asarray(np.stack([X[40] for X, _ in truth_runs]))
    u = jnp.asarray(np.stack([U[40] for _, U in truth_runs]))
    mjx_next = _batched_step()(params, x, u)
    ode_next = jax.jit(jax.vmap(ode_step, in_axes=(None, 0, 0, None)))(params, x, u, model)
    np.testing.assert_allclose(ode_next, mjx_next, rtol=1e-12, atol=1e-9)


def test_windows_only_from_valid_steps(truth_runs):
    demos = _demos(truth_runs)
    win = make_windows(demos, window=10, stride=5)
    assert win.x0.shape[1:] == (hull.DX,)
    assert win.U.shape[1:] == (10, hull.DU) and win.target.shape[1:] == (10, hull.DX)
    lengths = [U.shape[0] for _, U in truth_runs]
    assert len(win.x0) == sum((n - 10) // 5 + 1 for n in lengths)


def test_sysid_recovers_true_parameters_from_clean_data(truth_runs):
    demos = _demos(truth_runs)
    cfg = SysIdConfig(step="ode", max_windows=256, iterations=8)
    result = identify(demos, cfg)
    errors = result.relative_errors(true_params())
    assert set(errors) == set(SYSID_FIELDS) == set(TRUE_FACTORS)
    assert max(errors.values()) < 1e-4, errors


@pytest.fixture(scope="module")
def ingested_demos(tmp_path_factory):
    """Eight short episodes (3 in set 1, 5 in set 2) through bags and ingestion."""
    from diffgcl.data.ingest import IngestConfig, IngestWarning, ingest_bags
    from diffgcl.data.synth import synthesize

    cfg = SynthConfig(episodes=(3, 5), approach_m=(70.0, 90.0), end_margin_m=(30.0, 40.0))
    result = synthesize(tmp_path_factory.mktemp("sysid") / "bags", cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IngestWarning)
        return ingest_bags(list(result.bags), config=IngestConfig(observations=False))


def test_sysid_within_five_percent_on_ingested_bags(ingested_demos):
    """The fast check of experiments/bags_sysid.py: fit on bag data, ≤ 5 % on each parameter,
    and the held-out 10 s open-loop prediction improves."""
    train = ingested_demos.subset(slice(0, None, 2))
    test = ingested_demos.subset(slice(1, None, 2))
    result = identify(train, SysIdConfig(step="ode", max_windows=384, iterations=6))
    errors = result.relative_errors(true_params())
    assert max(errors.values()) <= 0.05, errors
    assert result.loss[-1] < result.loss[0]
    before = prediction_error(hull.default_params(), test, 10.0, step="ode")
    after = prediction_error(result.params, test, 10.0, step="ode")
    assert after.open_loop["position_rmse_m"] < 0.5 * before.open_loop["position_rmse_m"]


@pytest.mark.slow
def test_sysid_through_mjx_on_ingested_bags(tmp_path):
    from diffgcl.data.ingest import IngestWarning, ingest_bags
    from diffgcl.data.synth import synthesize

    cfg = SynthConfig(episodes=(3, 3), approach_m=(70.0, 90.0), end_margin_m=(30.0, 40.0))
    result = synthesize(tmp_path / "bags", cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IngestWarning)
        demos = ingest_bags(list(result.bags))
    fit = identify(demos, SysIdConfig(step="mjx", max_windows=256, iterations=5))
    assert max(fit.relative_errors(true_params()).values()) <= 0.05
