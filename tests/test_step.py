"""Step-size adaptation (diffgcl.control.step) on hand-computed numbers and a Monte-Carlo check of
the Laplace cost estimate."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lqr_problems import random_problem

from diffgcl.control.lqr import backward_pass, forward_pass
from diffgcl.control.step import (
    adapt_step_mult,
    geometric_step_multiplier,
    laplace_cost,
    step_multiplier,
)

# (J_prev, J_pred, J_act, expected multiplier), worked by hand:
# pred = J_prev − J_pred, act = J_prev − J_act, mult = pred / (2·max(1e-4, pred − act)).
CASES = [
    (10.0, 6.0, 8.0, 1.0),  # pred 4, act 2: 4 / (2·2) = 1
    (10.0, 6.0, 7.0, 2.0),  # pred 4, act 3: 4 / (2·1) = 2
    (10.0, 6.0, 12.0, 1 / 3),  # pred 4, act −2: 4 / (2·6) = 0.333
    (10.0, 6.0, 6.0, 5.0),  # act = pred: 4 / 2e-4 = 2e4, clipped to 5
    (10.0, 6.0, 5.0, 5.0),  # better than predicted: pred − act < 0 -> 1e-4, clipped to 5
    (10.0, 11.0, 12.0, 0.1),  # predicted worsening: −1 / (2·1) < 0, clipped to 0.1
    (10.0, 9.0, 20.0, 0.1),  # pred 1, act −10: 1/22 = 0.045, clipped to 0.1
]


@pytest.mark.parametrize(("J_prev", "J_pred", "J_act", "expected"), CASES)
def test_step_multiplier_hand_numbers(J_prev, J_pred, J_act, expected):
    assert float(step_multiplier(J_prev, J_pred, J_act)) == pytest.approx(expected)


def test_adapt_step_mult_clips_and_vmaps():
    J_prev, J_pred, J_act, _ = map(jnp.array, zip(*CASES, strict=True))
    step = jnp.array([1.0, 3.0, 0.02, 4.0, 1.0, 0.05, 0.5])
    new = jax.jit(jax.vmap(adapt_step_mult))(step, J_prev, J_pred, J_act)
    # 1·1, 3·2, 0.02/3 -> 0.01 (floor), 4·5 -> 10 (cap), 1·5, 0.05·0.1 -> 0.01, 0.5·0.1
    np.testing.assert_allclose(new, [1.0, 6.0, 0.01, 10.0, 5.0, 0.01, 0.05])


def test_geometric_step_multiplier_weighs_every_condition_alike():
    """Two conditions, multipliers 5 (pred 4, act 4) and 0.2 (pred 400, act −600: 400/2000),
    the second's estimates 10⁵ times the first's. Averaging the estimates (GPS's global rule)
    gives pred 202, act −298: 202/1000 = 0.202, the second condition's; the geometric mean of
    the two multipliers is √(5·0.2) = 1. A condition whose estimates are not finite is left
    out; none finite: NaN (the caller keeps its step)."""
    J_prev = jnp.array([10.0, 1e6])
    J_pred = jnp.array([6.0, 1e6 - 400.0])
    J_act = jnp.array([6.0, 1e6 + 600.0])
    np.testing.assert_allclose(step_multiplier(J_prev, J_pred, J_act), [5.0, 0.2])
    averaged = step_multiplier(J_prev.mean(), J_pred.mean(), J_act.mean())
    assert float(averaged) == pytest.approx(0.202)
    assert float(jax.jit(geometric_step_multiplier)(J_prev, J_pred, J_act)) == pytest.approx(1.0)
    with_nan = [jnp.append(J, jnp.nan) for J in (J_prev, J_pred, J_act)]
    assert float(geometric_step_multiplier(*with_nan)) == pytest.approx(1.0)
    assert np.isnan(float(geometric_step_multiplier(*(jnp.full(2, jnp.nan),) * 3)))
    # The shared rules through adapt_step_mult: one multiplier and one step for both.
    for rule, mult in (("global", 0.202), ("geometric", 1.0), ("classic", None)):
        new = adapt_step_mult(jnp.array([1.0, 1.0]), J_prev, J_pred, J_act, rule=rule)
        np.testing.assert_allclose(new, [5.0, 0.2] if mult is None else [mult, mult], rtol=1e-6)
    with pytest.raises(ValueError, match="rule 'shared'"):
        adapt_step_mult(jnp.ones(2), J_prev, J_pred, J_act, rule="shared")


def test_laplace_cost_matches_monte_carlo():
    dynamics, cost, prev, x0 = random_problem(seed=3, T=5)
    ctrl = backward_pass(dynamics, cost, prev, 1.0).controller
    traj = forward_pass(dynamics, ctrl, x0)
    key = jax.random.PRNGKey(0)
    n = 100_000
    dX = traj.mu_final.shape[0]

    def quad(t, z):
        H = jnp.block([[cost.l_xx[t], cost.l_ux[t].T], [cost.l_ux[t], cost.l_uu[t]]])
        g = jnp.concatenate([cost.l_x[t], cost.l_u[t]])
        return cost.l[t] + z @ g + 0.5 * z @ H @ z

    total = 0.0
    for t in range(traj.mu.shape[0]):
        key, sub = jax.random.split(key)
        z = jax.random.multivariate_normal(sub, traj.mu[t], traj.sigma[t], (n,))
        total += jax.vmap(lambda z, t=t: quad(t, z))(z).mean()
    key, sub = jax.random.split(key)
    xT = jax.random.multivariate_normal(sub, traj.mu_final, traj.sigma_final, (n,))
    T = traj.mu.shape[0]
    zT = jnp.concatenate([xT, jnp.zeros((n, cost.l_u.shape[-1]))], axis=1)
    total += jax.vmap(lambda z: quad(T, z))(zT).mean()
    assert dX == 3
    assert float(laplace_cost(traj, cost)) == pytest.approx(float(total), rel=2e-3)
