"""The Odin-like hull: MJX (computed acceleration) against an independent RK4 integration of the
Fossen 3-DOF ODE written here, sign conventions, differentiability in the parameters, and the
hull env under jit/vmap in float64 and float32."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgcl.envs.hull import HullEnv, make_hull_env
from diffgcl.sim import hull as H
from diffgcl.types import Env


def fossen_rhs(p: dict, s: np.ndarray, cmd: np.ndarray) -> np.ndarray:
    """ṡ for s = [x, y, ψ, u, v, r, T, δ] (body-frame velocities), written from Fossen (2011):
    M ν̇ + C(ν)ν + D(ν)ν = τ with diagonal M = M_RB + M_A, C(ν)ν = [−m22 v r, m11 u r,
    (m22 − m11) u v], linear + quadratic damping, N_v coupling; η̇ = R(ψ) ν; first-order lags."""
    _, _, psi, u, v, r, thrust, nozzle = s
    k = p["inertia_scale"]
    m11 = k * (p["mass"] + p["added_mass_u"])
    m22 = k * (p["mass"] + p["added_mass_v"])
    m33 = k * (p["inertia_z"] + p["added_mass_r"])
    f = p["thrust_gain"] * thrust
    tau = np.array([f * np.cos(nozzle), -f * np.sin(nozzle), p["jet_arm"] * f * np.sin(nozzle)])
    rhs = tau - np.array(
        [
            -m22 * v * r + (p["damping_u"] + p["damping_uu"] * abs(u)) * u,
            m11 * u * r + (p["damping_v"] + p["damping_vv"] * abs(v)) * v,
            (m22 - m11) * u * v
            + (p["damping_r"] + p["damping_rr"] * abs(r)) * r
            - p["damping_rv"] * v,
        ]
    )
    nu_dot = rhs / np.array([m11, m22, m33])
    eta_dot = np.array([u * np.cos(psi) - v * np.sin(psi), u * np.sin(psi) + v * np.cos(psi), r])
    lim = [-p["reverse_fraction"] * p["max_thrust"], p["max_thrust"]]
    cmd = np.array([np.clip(cmd[0], *lim), np.clip(cmd[1], -p["max_nozzle"], p["max_nozzle"])])
    act_dot = (cmd - s[6:8]) / np.array([p["tau_thrust"], p["tau_nozzle"]])
    return np.concatenate([eta_dot, nu_dot, act_dot])


def rk4_trajectory(p: dict, s0: np.ndarray, U: np.ndarray, dt: float, sub: int = 10):
    """Classic RK4 with the command held over each control step; returns [T+1, 8]."""
    out, s, h = [s0], s0.copy(), dt / sub
    for cmd in U:
        for _ in range(sub):
            k1 = fossen_rhs(p, s, cmd)
            k2 = fossen_rhs(p, s + 0.5 * h * k1, cmd)
            k3 = fossen_rhs(p, s + 0.5 * h * k2, cmd)
            k4 = fossen_rhs(p, s + h * k3, cmd)
            s = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(s.copy())
    return np.array(out)


def manoeuvre(T=300, dt=0.1):
    """30 s of manoeuvring: thrust and nozzle sweeps, a hard-over and a crash-reverse phase."""
    t = np.arange(T) * dt
    thrust = 9000 + 4000 * np.sin(t / 4.0)
    thrust[200:240] = -6000.0  # beyond the reverse limit: exercises the clip
    nozzle = 0.45 * np.sin(t / 2.5)
    nozzle[100:140] = 0.8  # beyond ±30°
    return np.stack([thrust, nozzle], axis=1)


@pytest.fixture(scope="module")
def env64():
    return make_hull_env()


@jax.jit
def rollout(params, x0, U):
    """X: [T+1, 10] of hull_step from x0: [10] under U: [T, 2] (one compiled program, reused)."""
    xT, X = jax.lax.scan(lambda x, u: (H.hull_step(params, x, u), x), x0, U)
    return jnp.concatenate([X, xT[None]])


@jax.jit
def step_jvp(params, x, u, dparams):
    """Forward-mode derivative of hull_step(params, x, u) along dparams: [10]."""
    return jax.jvp(lambda q: H.hull_step(q, x, u), (params,), (dparams,))[1]


SYSID_POINT = (
    H.default_params(jnp.float64),
    jnp.array([0.0, 0.0, 0.1, 9.0, 1.0, 0.2, 9000.0, 0.25, 40.0, 3.0]),
    jnp.array([11000.0, -0.3]),
)


@functools.partial(jax.jit, static_argnums=0)
def step_and_sense(env, x, u, key):
    """Batched step + noiseless and noisy observations (one program for the env tests)."""
    x1 = jax.vmap(env.step)(x, u)
    keys = jax.random.split(key, x.shape[0])
    return x1, jax.vmap(env.obs)(x1), jax.vmap(env.obs)(x1, keys)


def test_mjx_hull_matches_independent_rk4_within_one_percent():
    params = H.default_params(jnp.float64)
    p = {k: float(v) for k, v in vars(params).items()}
    x0 = np.array([5.0, -3.0, 0.2, 8.0 * np.cos(0.2), 8.0 * np.sin(0.2), 0.0, 4000.0, 0.0, 1, 2])
    U = manoeuvre()
    X = np.asarray(rollout(params, jnp.asarray(x0), jnp.asarray(U)))

    c, s = np.cos(x0[2]), np.sin(x0[2])
    nu0 = [c * x0[3] + s * x0[4], -s * x0[3] + c * x0[4], x0[5]]
    S = rk4_trajectory(p, np.array([*x0[:3], *nu0, *x0[6:8]]), U, dt=0.1)

    travelled = np.sum(np.linalg.norm(np.diff(S[:, :2], axis=0), axis=1))
    assert travelled > 200.0  # the manoeuvre really goes somewhere
    pos_err = np.linalg.norm(X[:, :2] - S[:, :2], axis=1)
    assert pos_err.max() < 0.01 * travelled, (pos_err.max(), travelled)
    assert np.abs(X[:, 2] - S[:, 2]).max() < 0.02  # heading (rad)
    np.testing.assert_allclose(X[:, 6:8], S[:, 6:8], rtol=1e-6, atol=1e-6)  # exact lags
    np.testing.assert_array_equal(X[:, 8:], np.broadcast_to(x0[8:], (301, 2)))  # pole carried


def test_sign_convention_positive_nozzle_turns_to_port():
    params = H.default_params(jnp.float64)
    tau = H.jet_force(params, jnp.asarray(10000.0), jnp.deg2rad(20.0))
    assert tau[0] > 0 and tau[1] < 0 and tau[2] > 0  # stern pushed to starboard, bow to port
    np.testing.assert_allclose(tau[2], -params.jet_arm * tau[1])
    x = jnp.zeros(H.DX).at[H.IX_VX].set(10.0).at[H.IX_THRUST].set(8000.0)
    x = rollout(params, x, jnp.broadcast_to(jnp.array([8000.0, 0.3]), (300, 2)))[30]
    assert x[H.IX_PSI] > 0.2 and x[H.IX_PY] > 0  # heading and track turn counter-clockwise


def test_world_acceleration_is_fossen_in_world_frame():
    """η̈ = R(ψ)(ν̇ + S(r)ν) against a finite difference of η̇ = R(ψ) ν along the ODE."""
    params = H.default_params(jnp.float64)
    x = jnp.array([0.0, 0.0, 0.7, 6.0, 2.0, 0.3, 7000.0, 0.2, 50.0, 0.0])
    xdot = H.state_derivative(params, x, jnp.array([7000.0, 0.2]))
    h = 1e-6
    xp = x + h * xdot
    nu, nu_p = H.body_velocity(x), H.body_velocity(xp)
    tau = H.jet_force(params, x[H.IX_THRUST], x[H.IX_NOZZLE])
    nu_dot = H.body_acceleration(params, nu, tau)
    np.testing.assert_allclose((nu_p - nu) / h, nu_dot, rtol=1e-4, atol=1e-4)


def test_hull_step_is_differentiable_in_params():
    """Forward-mode derivatives of one step w.r.t. identifiable parameters match central
    differences (what system identification by gradient descent relies on)."""
    params, x, u = SYSID_POINT
    U = jnp.broadcast_to(u, (300, 2))
    basis = jax.tree.map(jnp.zeros_like, params)
    for name in ("inertia_scale", "damping_v", "thrust_gain", "jet_arm", "tau_nozzle"):
        base = float(getattr(params, name))
        tangent = step_jvp(params, x, u, basis.replace(**{name: jnp.float64(1.0)}))
        eps = 1e-6 * max(abs(base), 1.0)
        plus = rollout(params.replace(**{name: jnp.float64(base + eps)}), x, U)[1]
        minus = rollout(params.replace(**{name: jnp.float64(base - eps)}), x, U)[1]
        fd = (plus - minus) / (2 * eps)
        np.testing.assert_allclose(tangent, fd, rtol=1e-4, atol=1e-7, err_msg=name)
        assert np.abs(np.asarray(tangent)).max() > 0, name


@pytest.mark.slow
def test_reverse_mode_in_params_agrees_with_forward_mode():
    """Gradients w.r.t. every identifiable parameter by reverse mode equal forward mode (no
    constraint is active in the hull model, so reverse mode through mjx.step is exact)."""
    params, x, u = SYSID_POINT
    basis = jax.tree.map(jnp.zeros_like, params)
    w = jnp.linspace(1.0, 2.0, H.DX)
    grad = jax.jit(jax.grad(lambda q: w @ H.hull_step(q, x, u)))(params)
    for name in H.IDENTIFIABLE:
        tangent = step_jvp(params, x, u, basis.replace(**{name: jnp.float64(1.0)}))
        np.testing.assert_allclose(getattr(grad, name), w @ tangent, rtol=1e-9, err_msg=name)


def test_env_protocol_steps_under_jit_and_vmap_float64(env64):
    env = env64
    assert isinstance(env, Env) and isinstance(env, HullEnv)
    assert (env.name, env.dX, env.dU, env.dO) == ("hull", 10, 2, 53)
    assert env.dt == pytest.approx(0.1) and env.horizon == 300
    x0s = env.initial_states()
    u = jnp.broadcast_to(jnp.array([env.cruise_thrust, 0.1]), (x0s.shape[0], 2))
    x1, o1, _ = step_and_sense(env, x0s, u, jax.random.key(0))
    assert x1.dtype == jnp.float64 and o1.shape == (x0s.shape[0], env.dO)
    assert np.isfinite(np.asarray(x1)).all() and np.isfinite(np.asarray(o1)).all()
    step_and_sense(env, x1, u + 1.0, jax.random.key(1))
    assert step_and_sense._cache_size() == 1, "a second call with new data recompiled"
    # At cruise thrust straight ahead the speed is held (the cruise thrust is the equilibrium).
    straight = jnp.broadcast_to(jnp.array([env.cruise_thrust, 0.0]), (300, 2))
    for x0 in x0s:
        X = rollout(env.params, x0, straight)
        np.testing.assert_allclose(X[:, H.IX_VX], env.cruise_speed, rtol=1e-9)
        assert not bool(env.success(X)), "holding the course must hit the pole"


def test_env_float32():
    with jax.enable_x64(False):
        env = make_hull_env()
        x0s = env.initial_states()
        assert x0s.dtype == jnp.float32

        def run(x0):
            step = lambda x, _: (env.step(x, jnp.array([9000.0, 0.2], jnp.float32)), None)
            xT = jax.lax.scan(step, x0, None, length=20)[0]
            return xT, env.obs(xT)

        xT, o = jax.jit(jax.vmap(run))(x0s)
        assert xT.dtype == jnp.float32 and o.dtype == jnp.float32
        assert np.isfinite(np.asarray(xT)).all() and np.isfinite(np.asarray(o)).all()


def test_wrong_shapes_give_clear_errors(env64):
    x = env64.initial_states()[0]
    with pytest.raises(ValueError, match=r"hull.step: u must have shape \(2,\)"):
        env64.step(x, jnp.zeros(3))
    with pytest.raises(ValueError, match=r"hull.step: x must have shape \(10,\)"):
        jax.jit(env64.step)(x[:8], jnp.zeros(2))
    with pytest.raises(ValueError, match=r"hull.obs: x must have shape"):
        env64.obs(env64.initial_states())
    with pytest.raises(ValueError, match=r"hull_step: x must have shape"):
        H.hull_step(H.default_params(), jnp.zeros(9), jnp.zeros(2))
    with pytest.raises(ValueError, match="poles"):
        make_hull_env(poles=[1.0, 2.0, 3.0])


def test_observation_noise_only_with_key(env64):
    x0s = env64.initial_states().at[0, H.IX_OBS_Y].set(0.0)  # condition 0's pole dead ahead
    u = jnp.zeros((x0s.shape[0], 2))
    _, o, on = step_and_sense(env64, x0s, u, jax.random.key(3))
    _, o_again, _ = step_and_sense(env64, x0s, u, jax.random.key(4))
    np.testing.assert_array_equal(o, o_again)  # no key, no noise
    nb = env64.layout.num_beams
    hit = np.asarray(o[:, :nb]) < env64.layout.max_ranges
    assert hit.any() and not np.allclose(on[:, :nb][hit], o[:, :nb][hit])
    np.testing.assert_array_equal(on[:, :nb][~hit], o[:, :nb][~hit])  # no return, no noise
    np.testing.assert_array_equal(on[:, nb:], o[:, nb:])  # heading and speed are exact
    assert (np.asarray(on[:, :nb]) <= env64.layout.max_ranges + 1e-12).all()
    assert (np.asarray(on[:, :nb]) >= 0).all()
    # Condition 0 has the pole dead ahead at 90 m: the radar's bow beam sees it at
    # 90 m − boat travel in 0.1 s − mast offset (2 m) − pole radius (0.5 m).
    travel = float(o[0, nb + 2]) * 0.1  # ≈ surge speed × dt, without drift
    assert float(o[0, env64.layout.lidar_beams]) == pytest.approx(90 - travel - 2.5, abs=0.05)
    np.testing.assert_allclose(o[0, nb : nb + 2], [0.0, 1.0], atol=1e-12)  # sin ψ, cos ψ


def test_expert_cost_smooth_and_success(env64):
    env = env64
    x0 = env.initial_state(jnp.array([90.0, 0.0]))  # pole dead ahead
    u = jnp.array([env.cruise_thrust, 0.0])
    hess = jax.jit(jax.hessian(env.expert_cost, argnums=(0, 1)))(x0.at[0].set(84.0), u, 10)
    assert all(np.isfinite(np.asarray(h)).all() for h in jax.tree.leaves(hess))
    far, near = env.expert_cost(x0, u, 0), env.expert_cost(x0.at[0].set(88.0), u, 0)
    assert near > 100 * max(float(far), 1e-3)  # the barrier dominates near the pole
    assert env.expert_cost(x0.at[1].set(3.0), u, 300) > env.expert_cost(x0.at[1].set(3.0), u, 0)

    success = jax.jit(env.success)
    T = env.horizon
    t = np.linspace(0.0, 30.0, T + 1)
    X = np.tile(np.asarray(x0), (T + 1, 1))
    X[:, 0] = 8.0 * t
    assert not bool(success(jnp.asarray(X)))  # straight through the pole
    X_swerve = X.copy()
    X_swerve[:, 1] = 8.0 * np.exp(-(((X[:, 0] - 90.0) / 40.0) ** 2))  # 8 m to port and back
    assert bool(success(jnp.asarray(X_swerve)))
    X_far = X_swerve.copy()
    X_far[:, 1] += 6.0  # ends 6 m off the course line
    assert not bool(success(jnp.asarray(X_far)))
    assert env.clearance(jnp.asarray(X_swerve[135])) > 0  # abeam of the pole
    m = jax.jit(env.metrics)(jnp.asarray(X_swerve))
    assert bool(m["success"]) and float(m["max_cross_track"]) == pytest.approx(8.0, abs=0.01)
    assert float(m["min_clearance"]) == pytest.approx(8.0 - 0.5 - 1.7, abs=0.1)


def test_commands_are_saturated():
    params = H.default_params(jnp.float64)
    cmd = H.clip_command(params, jnp.array([1e6, -2.0]))
    np.testing.assert_allclose(cmd, [params.max_thrust, -params.max_nozzle])
    cmd = H.clip_command(params, jnp.array([-1e6, 0.1]))
    np.testing.assert_allclose(cmd, [-0.4 * params.max_thrust, 0.1])


def test_hull_mjcf_that_breaks_the_trick_is_rejected(tmp_path):
    from pathlib import Path

    from diffgcl.sim.mjcf import MJCFError, resolve_mjcf

    text = Path(resolve_mjcf(H.MJCF_NAME)).read_text()
    off_centre = tmp_path / "off_centre.xml"
    off_centre.write_text(text.replace('<inertial pos="0 0 0"', '<inertial pos="1 0 0"'))
    with pytest.raises(MJCFError, match="off_centre.xml.*centre of mass"):
        make_hull_env(mjcf=str(off_centre))
    no_material = tmp_path / "no_material.xml"
    body = text.split("<asset>")[0] + text.split("</asset>")[1]
    no_material.write_text(body.replace('material="water"', "").replace('material="hull"', ""))
    no_material.write_text(no_material.read_text().replace('material="pole"', ""))
    with pytest.raises(MJCFError, match="material"):
        make_hull_env(mjcf=str(no_material))


def ilqr(env, x0, iterations=60):
    """A plain iLQR (full cost Hessians, Levenberg-Marquardt on Q_uu, backtracking line search)
    on the expert cost, in scaled actions v = u / [T_max, δ_max]; returns X: [T+1, 10]."""
    scale = jnp.array([float(env.params.max_thrust), float(env.params.max_nozzle)])
    T = env.horizon
    f = lambda x, v: env.step(x, scale * v)
    c = lambda x, v, t: env.expert_cost(x, scale * v, t)
    ts = jnp.arange(T)

    @jax.jit
    def forward(Xref, V, k, K, alpha):
        def step(x, inp):
            xr, v, kt, Kt = inp
            v = v + alpha * kt + Kt @ (x - xr)
            return f(x, v), (x, v)

        xT, (X, Vn) = jax.lax.scan(step, x0, (Xref[:-1], V, k, K))
        X = jnp.concatenate([X, xT[None]])
        return X, Vn, jnp.sum(jax.vmap(c)(X[:-1], Vn, ts)) + c(xT, jnp.zeros(2), T)

    @jax.jit
    def backward(X, V, mu):
        A, B = jax.vmap(jax.jacfwd(f, (0, 1)))(X[:-1], V)
        lx, lu = jax.vmap(jax.grad(c, (0, 1)))(X[:-1], V, ts)
        (lxx, lxu), (_, luu) = jax.vmap(jax.hessian(c, (0, 1)))(X[:-1], V, ts)
        vT = jax.grad(c)(X[-1], jnp.zeros(2), T)
        VT = jax.hessian(c)(X[-1], jnp.zeros(2), T)

        def step(carry, inp):
            vx, Vxx = carry
            A, B, lx, lu, lxx, lxu, luu = inp
            Qx, Qu = lx + A.T @ vx, lu + B.T @ vx
            Qxx, Qux = lxx + A.T @ Vxx @ A, lxu.T + B.T @ Vxx @ A
            Quu = luu + B.T @ Vxx @ B + mu * jnp.eye(2)
            k, K = -jnp.linalg.solve(Quu, Qu), -jnp.linalg.solve(Quu, Qux)
            vx = Qx + K.T @ Quu @ k + K.T @ Qu + Qux.T @ k
            Vxx = Qxx + K.T @ Quu @ K + K.T @ Qux + Qux.T @ K
            return (vx, 0.5 * (Vxx + Vxx.T)), (k, K)

        return jax.lax.scan(step, (vT, VT), (A, B, lx, lu, lxx, lxu, luu), reverse=True)[1]

    V = jnp.tile(jnp.array([env.cruise_thrust / scale[0], 0.0]), (T, 1))
    zeros = (jnp.zeros((T + 1, env.dX)), jnp.zeros((T, 2)), jnp.zeros((T, 2, env.dX)))
    X, V, J = forward(zeros[0], V, zeros[1], zeros[2], 0.0)
    mu = 1.0
    for _ in range(iterations):
        k, K = backward(X, V, mu)
        for alpha in (1.0, 0.5, 0.25, 0.1, 0.03):
            Xn, Vn, Jn = forward(X, V, k, K, alpha)
            if Jn < J:
                X, V, J, mu = Xn, Vn, Jn, max(mu / 2, 1e-3)
                break
        else:
            mu *= 10.0
            if mu > 1e6:
                break
    return X


@pytest.mark.slow
def test_expert_cost_is_solvable_by_trajectory_optimisation(env64):
    """The expert cost and the success test fit together: iLQR on the expert cost swerves
    round the pole and returns to the course line on every default condition."""
    for x0 in env64.initial_states():
        X = ilqr(env64, x0)
        m = env64.metrics(X)
        assert bool(m["success"]), {k: float(v) for k, v in m.items()}
        assert float(m["max_cross_track"]) > 3.0  # it really swerved
