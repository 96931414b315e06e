"""iLQR on an MJCF env, GPS started from given controllers, and the expert-demo path (api and
``diffgcl demos --mjcf``), on a one-joint model that compiles in seconds."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_lqr import riccati_numpy

from diffgcl import api
from diffgcl.algorithms import trajopt
from diffgcl.algorithms.gps import GPSConfig, make_gps
from diffgcl.control.ilqr import (
    CONVERGED,
    ILQRConfig,
    ILQRResult,
    cost_minimiser,
    goal_lqr_actions,
)
from diffgcl.control.init import init_controller
from diffgcl.dynamics.autodiff import linearize

SLIDER = """<mujoco model="slider">
  <option timestep="0.05" integrator="Euler"/>
  <worldbody>
    <body name="cart">
      <joint name="x" type="slide" axis="1 0 0" damping="0.5"/>
      <geom type="sphere" size="0.1" mass="1"/>
    </body>
  </worldbody>
  <actuator><motor joint="x" gear="2" ctrlrange="-5 5" ctrllimited="true"/></actuator>
</mujoco>
"""

T = 12


def cost(x, u, t):
    w = jnp.where(t == T, 10.0, 1.0)
    return 0.5 * w * (x[0] ** 2 + 0.1 * x[1] ** 2) + 0.5 * 0.05 * u @ u


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    path = tmp_path_factory.mktemp("slider") / "slider.xml"
    path.write_text(SLIDER)
    x0 = np.array([[0.3, 0.0], [-0.2, 0.1]])
    return api.load_model(path, x0=x0, horizon=T, cost=cost,
                          success=lambda X: jnp.all(jnp.abs(X[-3:, 0]) < 0.1))  # fmt: skip


def test_ilqr_through_mjx_equals_riccati(env):
    """The slider under Euler is linear in (x, u) (actions well inside the control range): iLQR
    through mjx.step gives the Riccati solution of its autodiff linearisation, from zero actions
    and from the goal's LQR (``initial="best"`` runs both), and the goal's LQR is that solution
    already."""
    result = jax.jit(lambda x: trajopt.solve(env, cost, x, initial="best"))(env.initial_states())
    assert np.all(np.asarray(result.status) == CONVERGED)
    x0 = np.asarray(env.initial_states()[0])
    A, B = (np.asarray(a) for a in linearize(env.step, jnp.asarray(x0), jnp.zeros(1)))
    tile = lambda a: np.broadcast_to(a, (T, *a.shape)).copy()
    dX, dU = 2, 1
    Qxx = np.diag([1.0, 0.1])
    K, k, _ = riccati_numpy(
        tile(A), tile(B), np.zeros((T, dX)), tile(Qxx), tile(0.05 * np.eye(dU)),
        np.zeros((T, dU, dX)), np.zeros((T, dX)), np.zeros((T, dU)), 10 * Qxx, np.zeros(dX),
    )  # fmt: skip
    x, U = x0, []
    for t in range(T):
        U.append(K[t] @ x + k[t])
        x = A @ x + B @ U[-1]
    assert np.abs(np.asarray(U)).max() < 5.0  # the clamp is inactive: the dynamics are linear
    np.testing.assert_allclose(result.U[0], np.asarray(U), rtol=0, atol=1e-7)
    np.testing.assert_allclose(result.K[0], K, rtol=0, atol=1e-7)
    goal = cost_minimiser(cost, jnp.asarray(x0), 1, T)
    np.testing.assert_allclose(goal, [0.0, 0.0], atol=1e-12)
    U_lqr = jax.jit(lambda x, g: goal_lqr_actions(env.step, cost, x, g, T, 1))(x0, goal)
    np.testing.assert_allclose(U_lqr, np.asarray(U), rtol=0, atol=1e-7)


def test_control_limits_come_from_ctrlrange(env):
    """The slider's ±5 ctrlrange is ±1 in its normalised actions. From 3 m away the
    unconstrained iLQR asks for more than the actuator gives (MuJoCo clamps it: no effect, only
    action cost); the control-limited solution stays in the box, costs less, and is the
    box-constrained optimum of the linear model (scipy's L-BFGS-B on the condensed problem,
    NumPy rollout)."""
    from scipy.optimize import minimize

    lo, hi = env.action_bounds()
    np.testing.assert_allclose(lo, [-1.0])
    np.testing.assert_allclose(hi, [1.0])
    x0 = jnp.asarray([[3.0, 0.0]])
    config = ILQRConfig(tol=1e-12)
    solve = jax.jit(lambda x, limits: trajopt.solve(env, cost, x, config=config, limits=limits),
                    static_argnums=1)  # fmt: skip
    free, boxed = solve(x0, False), solve(x0, True)
    assert float(jnp.abs(free.U).max()) > 1.0 + 1e-3
    assert float(boxed.cost[0]) < float(free.cost[0])
    U = np.asarray(boxed.U[0, :, 0])
    assert np.abs(U).max() <= 1.0 + 1e-12 and np.isclose(np.abs(U).max(), 1.0)
    A, B = (np.asarray(a) for a in linearize(env.step, x0[0], jnp.zeros(1)))

    def J(U_flat):
        x, total = np.asarray(x0[0]), 0.0
        for t in range(T):
            total += float(cost(jnp.asarray(x), jnp.asarray(U_flat[t : t + 1]), t))
            x = A @ x + B[:, 0] * U_flat[t]
        return total + float(cost(jnp.asarray(x), jnp.zeros(1), T))

    ref = minimize(J, np.zeros(T), method="L-BFGS-B", bounds=[(-1.0, 1.0)] * T,
                   options={"ftol": 1e-15, "gtol": 1e-10})  # fmt: skip
    assert float(boxed.cost[0]) <= ref.fun * (1 + 1e-7)
    np.testing.assert_allclose(U, ref.x, atol=1e-4)


def test_restarts_keep_the_lowest_cost(env):
    """solve_restarts: zeros and ±scale per actuator; per start the kept solution is the
    lowest-cost one, and it is that start's run from that initial sequence."""
    U = trajopt.restart_actions(T, 1, 0.1)
    assert U.shape == (3, T, 1)
    np.testing.assert_array_equal(U[:, 0, 0], [0.0, 0.1, -0.1])
    X0 = env.initial_states()
    kept, best, runs = jax.jit(lambda x: trajopt.solve_restarts(env, cost, x))(X0)
    costs = runs.cost
    np.testing.assert_array_equal(np.asarray(best), np.argmin(np.asarray(costs), axis=0))
    np.testing.assert_allclose(kept.cost, np.min(np.asarray(costs), axis=0))
    one = jax.jit(lambda x, u: trajopt.solve(env, cost, x, u))(X0, U[int(best[1])])
    np.testing.assert_allclose(kept.U[1], one.U[1], rtol=0, atol=1e-12)


def test_solving_starts_in_groups_equals_one_vmap(env):
    """``batch_size``: the starts solved one at a time (``lax.map``) give the vmap's solutions,
    for the expert's race of two initial sequences as for a single one."""
    X0 = jnp.concatenate([env.initial_states(), jnp.array([[0.1, -0.2]])])  # 3, groups of 2
    solve = jax.jit(trajopt.solve, static_argnums=(0, 1), static_argnames=("initial", "batch_size"))
    for initial in ("zeros", "best"):
        vmapped = solve(env, cost, X0, initial=initial)
        grouped = solve(env, cost, X0, initial=initial, batch_size=2)
        np.testing.assert_allclose(grouped.U, vmapped.U, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(grouped.iterations, vmapped.iterations)
    with pytest.raises(ValueError, match="batch_size must be >= 1"):
        trajopt.solve(env, cost, X0, batch_size=0)


def test_gps_from_controllers(env):
    """make_gps_from with the zero controller is make_gps's train (the same keys and numbers);
    started from the iLQR controllers GPS keeps iLQR's success from its first iteration on and
    samples at a lower cost than from zero."""
    config = GPSConfig(iterations=3, num_samples=3, init_var=0.01)
    train = trajopt.make_gps_from(config, env, cost)
    C = env.initial_states().shape[0]
    zero = init_controller(T, env.dX, env.dU, config.init_var)
    zero = jax.tree.map(lambda a: jnp.broadcast_to(a, (C, *a.shape)), zero)
    key = jax.random.PRNGKey(3)
    run = jax.jit(train)
    state, metrics = run(key, zero)
    ref_state, ref_metrics = jax.jit(make_gps(config, env, cost).train)(key)
    np.testing.assert_array_equal(state.controller.K, ref_state.controller.K)
    np.testing.assert_array_equal(metrics.cost, ref_metrics.cost)
    ctrl, result = jax.jit(lambda x: trajopt.ilqr_controllers(env, cost, x, init_var=0.01))(
        env.initial_states()
    )
    _, metrics = run(key, ctrl)
    solved = jax.vmap(env.success)(result.X)
    assert bool(jnp.any(solved))
    assert bool(jnp.all(metrics.success == solved[None]))  # GPS keeps what iLQR reached
    assert float(metrics.cost[0].mean()) < float(ref_metrics.cost[0].mean())


def test_expert_demos_api_and_cli(env, tmp_path, capsys):
    from diffgcl.cli import main

    path = tmp_path / "demos.npz"
    demos = api.expert_demos(env, per_start=3, path=path, ilqr=ILQRConfig(tol=1e-9))
    assert demos.X.shape == (6, T + 1, 2) and demos.U.shape == (6, T, 1)
    conditions = [e["condition"] for e in demos.episodes]
    assert conditions == [0, 1, 0, 1, 0, 1]
    assert all(e["source"] == "ilqr-expert" and e["solution_success"] for e in demos.episodes)
    np.testing.assert_allclose(demos.X[:, 0], np.asarray(env.initial_states())[conditions])
    loaded = api.load_demos(path, env)
    np.testing.assert_allclose(loaded.U, demos.U, atol=1e-6)
    # The demos scatter about the solution with the MaxEnt spread: not all identical.
    assert np.std(demos.U[[0, 2, 4], 0, 0]) > 0

    xml = tmp_path / "slider.xml"
    xml.write_text(SLIDER)
    out = tmp_path / "cli.npz"
    argv = ["demos", str(out), "--mjcf", str(xml), "--cost", "quadratic:1,0.1;u=0.05",
            "--x0", "0.3,0;-0.2,0.1", "--horizon", str(T), "--per-start", "2"]  # fmt: skip
    assert main(argv) == 0
    assert "4 demos (2 per start)" in capsys.readouterr().out
    assert np.load(out)["qpos"].shape == (4, T + 1, 1)
    bad = {
        "quadratic:1,0.1,3": "3 state weights for a state of 2",
        "quadratic:1;goal=1": "goal has 1 numbers, the state 2",
        "no_such_module_xyz:cost": "cannot import no_such_module_xyz",
        "quadratic:1;speed=2": "unknown option",
    }
    for spec, message in bad.items():
        with pytest.raises(SystemExit, match=message):
            main(["demos", str(out), "--mjcf", str(xml), "--cost", spec, "--horizon", str(T)])
    with pytest.raises(SystemExit, match="--x0: state 0 has 3 numbers"):
        main(["demos", str(out), "--mjcf", str(xml), "--cost", "quadratic:1", "--x0", "1,2,3"])
    with pytest.raises(SystemExit, match="must be an .npz file"):
        main(["demos", str(tmp_path / "d"), "--mjcf", str(xml), "--cost", "quadratic:1"])


RAIL = """<mujoco model="rail">
  <option timestep="0.05" integrator="Euler"/>
  <worldbody>
    <body name="cart">
      <joint name="x" type="slide" axis="1 0 0" damping="0.5" limited="true" range="-0.5 0.5"
             margin="0.02"/>
      <geom type="sphere" size="0.1" mass="1"/>
    </body>
    <body name="wheel" pos="0 1 0">
      <joint name="free_spin" type="hinge" axis="0 0 1"/>
      <geom type="sphere" size="0.1" mass="1"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="x" gear="2" ctrlrange="-5 5" ctrllimited="true"/>
    <motor joint="free_spin" gear="1" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""


def test_cheaper_per_start_picks_by_finite_cost_and_pads_the_history():
    def result(cost, trips, tag):
        C = len(cost)
        z = lambda *shape: jnp.full((C, *shape), float(tag))
        return ILQRResult(X=z(3, 2), U=z(2, 1), cost=jnp.asarray(cost), K=z(2, 1, 2),
                          Q_uu=z(2, 1, 1), backward_ok=jnp.ones(C, bool), mu=z(),
                          iterations=jnp.full(C, tag), accepted=jnp.full(C, tag),
                          rollouts=jnp.full(C, tag), status=jnp.zeros(C, jnp.int32),
                          cost_history=z(trips))  # fmt: skip

    a = result([1.0, 5.0, jnp.nan], 4, 1)
    b = result([2.0, 3.0, 9.0], 6, 2)
    kept = trajopt.cheaper_per_start(a, b)
    np.testing.assert_array_equal(kept.cost, [1.0, 3.0, 9.0])
    np.testing.assert_array_equal(kept.iterations, [1, 2, 2])
    np.testing.assert_array_equal(kept.X[:, 0, 0], [1.0, 2.0, 2.0])
    assert kept.cost_history.shape == (3, 6)
    assert np.all(np.isnan(kept.cost_history[0, 4:])) and np.all(kept.cost_history[0, :4] == 1)
    np.testing.assert_array_equal(kept.cost_history[1], np.full(6, 2.0))


def test_state_limits_from_joint_ranges_keep_a_plan_off_the_stop(tmp_path):
    """A cart whose cost pulls it past its rail's end: the env's state bounds are the limited
    joint's range less its margin and 0.5 % of the range (the unlimited hinge and the velocities
    free); multiple shooting keeps the plan inside them, and its result is the env's own rollout
    of its actions."""
    path = tmp_path / "rail.xml"
    path.write_text(RAIL)
    target = 0.8

    def pull(x, u, t):
        return 0.5 * ((x[0] - target) ** 2 + 0.1 * x[2] ** 2) + 0.5 * 0.01 * u @ u

    env = api.load_model(path, x0=np.array([[0.0, 0.0, 0.0, 0.0], [0.2, 0.0, 0.0, 0.5]]),
                         horizon=T)  # fmt: skip
    lo, hi = env.state_bounds()
    np.testing.assert_allclose(hi, [0.5 - 0.02 - 0.005, np.inf, np.inf, np.inf])
    np.testing.assert_allclose(lo, -hi)
    result = jax.jit(lambda x: trajopt.solve_shooting(env, pull, x))(env.initial_states())
    X = np.asarray(result.X)
    assert np.all(X[:, :, 0] <= hi[0] + 1e-3)
    assert np.all(X[:, -1, 0] > hi[0] - 0.05)  # it does go to the limit
    for c in range(2):
        x = env.initial_states()[c]
        for t in range(T):
            x = env.step(x, result.U[c, t])
        np.testing.assert_allclose(X[c, -1], x, atol=1e-9)
    # One start at a time (lax.map) is the same solve as the vmap.
    one_by_one = jax.jit(lambda x: trajopt.solve_shooting(env, pull, x, batch_size=1))(
        env.initial_states()
    )
    np.testing.assert_allclose(one_by_one.X, result.X, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(one_by_one.iterations, result.iterations)
    # The expert's option: per start the cheaper of iLQR and multiple shooting.
    ilqr_only = jax.jit(lambda x: trajopt.solve(env, pull, x))(env.initial_states())
    _, both = jax.jit(lambda x: trajopt.ilqr_controllers(env, pull, x, shooting=True))(
        env.initial_states()
    )
    np.testing.assert_allclose(both.cost, np.minimum(ilqr_only.cost, result.cost), rtol=1e-9)
    # Without the limits the same solver drives the cart into the end stop.
    free = jax.jit(lambda x: trajopt.solve_shooting(env, pull, x, limits=False))(
        env.initial_states()
    )
    assert float(jnp.max(free.X[:, :, 0])) > hi[0] + 0.01
