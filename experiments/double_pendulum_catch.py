"""Can any action sequence within the actuator's range catch a double-pendulum start? (IPOPT)

A reference for ``experiments/trajopt_gym.py --models double_pendulum``: for each start (the
same starts, NumPy ``default_rng(seed)``, hinge angles 3× gymnasium's), it looks for actions
within ``ctrlrange`` (±1) that pass the task's success test — the tip above 1 m at every step,
and the cart within 0.1 m, the hinges within 0.05 rad over the last 10 of 100 steps — by direct
multiple shooting: the states and actions of all 100 steps are the unknowns, the step function
an equality constraint, the success test's bounds inequality constraints, the task's cost
(``DOUBLE_WEIGHTS``) the objective, solved by IPOPT (through CasADi) from a straight line of
states from the start to upright. The cart is kept within ``--rail`` (0.98 m: inside the
slider's limit, 1 m less its 0.01 m margin, so MuJoCo's end stop never acts). A start IPOPT
cannot solve there is solved again with the rail bound loosened and then tightened step by step
(2 m down to ``--rail``, each warm-started from the last), and the smallest bound met is
reported with its cost. IPOPT is a local method: a start it does not solve may still be
catchable, and the end stop (which the model leaves out unless ``--stops``) pushes harder than
the motor.

Every solution is replayed in C MuJoCo (``mujoco.MjModel`` of the same file) with a
time-varying LQR that tracks it (an unstable system's open-loop actions diverge from any
trajectory within a second), and judged by the same success test.

The step function is the MJCF's cart and two links written out symbolically (masses, inertias,
centres of mass, joint damping, gear, gravity and timestep read from the ``MjModel``; RK4,
frame skip 5), checked against C MuJoCo's step before anything else (the largest difference
over random 10-step rollouts is printed; the script stops above 10⁻⁶).

``--stops``: for a start not solved within ``--rail``, IPOPT again on the model with MuJoCo's
end stops written in (its soft limit constraint: reference acceleration, impedance, regulariser
from the joint's solref, solimp and margin; checked against C MuJoCo on runs into the stops),
the cart within 1.1 m, warm-started from the solution at the smallest bound met. The stop's
force switches on within the margin and is clipped at zero, which IPOPT's Newton steps do not
converge on, so IPOPT solves a smoothed stop (a tanh switch, a softplus clip: ``SMOOTHING``,
tightened in five steps); each solution is replayed in C MuJoCo, whose stops are exact, and
judged by the success test.

``--reach N``: for each start also the highest its tip can be kept over the first 1.5 s with the
cart within ``--rail`` (IPOPT maximising the lowest tip height; no cost, no end box: a
relaxation of the success test), along the rail from the loosest catch and from ``N`` initial
guesses (the straight line, random full pushes). A start whose best stays below 1 m is one
IPOPT finds no catch for either way.

``--sqp`` also runs a multiple-shooting SQP written here in NumPy (Gauss-Newton, the LQ
subproblem with the shooting gaps solved by a Riccati sweep, actions clamped to the box, an ℓ1
merit on the gaps) from the same straight line, on C MuJoCo's own step (central finite
differences, end stops included; ``--sqp-on symbolic``: the symbolic model, no rail), with a
penalty ``--rail-penalty·max(0, |x| − --rail)²`` on the cart's position (0: none) and the last
state's cost weights times ``--terminal-weight``: the prototype of a solver that could replace
iLQR's single shooting where iLQR falls into local optima.

Needs CasADi, which is not a dependency of the project (``pip install casadi``); without it the
script says so and stops.

    python experiments/double_pendulum_catch.py --seeds 1,2,3,4,5,6,7 --json runs/dp_catch.json
    python experiments/double_pendulum_catch.py --keys 3:6,7:5 --stops
    python experiments/double_pendulum_catch.py --keys 4:5,5:2 --reach 12
    python experiments/double_pendulum_catch.py --keys 4:4,5:4 --sqp --rail-penalty 1e4
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import mujoco
import numpy as np
from trajopt_gym import DOUBLE_WEIGHTS, TASKS, double_success, double_tip_height, gym_asset

FRAME_SKIP = 5
T = 100
RAIL_PATH = (2.0, 1.7, 1.5, 1.4, 1.3, 1.2, 1.1, 1.05, 1.0)


class Plant:
    """gymnasium's inverted double pendulum: C MuJoCo, and the same model written for CasADi."""

    def __init__(self, ca):
        self.ca = ca
        path = gym_asset("inverted_double_pendulum.xml")
        m = self.model = mujoco.MjModel.from_xml_path(str(path))
        self.data = mujoco.MjData(m)
        slide, hinge, hinge2 = (mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE,
                                mujoco.mjtJoint.mjJNT_HINGE)  # fmt: skip
        if list(m.jnt_type) != [slide, hinge, hinge2] or m.nbody != 4 or m.nu != 1:
            raise SystemExit("expected a cart on a slider with two hinged links and one actuator")
        if m.opt.integrator != mujoco.mjtIntegrator.mjINT_RK4:
            raise SystemExit("expected the RK4 integrator")
        q = ca.SX.sym("q", 3)
        qd = ca.SX.sym("qd", 3)
        u = ca.SX.sym("u")
        g = m.opt.gravity  # world (x, y, z); the model moves in the x-z plane
        mc, m1, m2 = m.body_mass[1:4]
        c1, c2 = m.body_ipos[2, 2], m.body_ipos[3, 2]  # centres of mass along each link
        length = m.body_pos[3, 2]  # the second hinge's height on the first link
        i1, i2 = m.body_inertia[2, 1], m.body_inertia[3, 1]  # about each link's y axis
        a, phi = q[1], q[1] + q[2]
        p1 = ca.vertcat(q[0] + c1 * ca.sin(a), c1 * ca.cos(a))
        p2 = ca.vertcat(q[0] + length * ca.sin(a) + c2 * ca.sin(phi),
                        length * ca.cos(a) + c2 * ca.cos(phi))  # fmt: skip
        v1, v2 = ca.jtimes(p1, q, qd), ca.jtimes(p2, q, qd)
        kinetic = (0.5 * mc * qd[0] ** 2 + 0.5 * m1 * ca.dot(v1, v1) + 0.5 * i1 * qd[1] ** 2
                   + 0.5 * m2 * ca.dot(v2, v2) + 0.5 * i2 * (qd[1] + qd[2]) ** 2)  # fmt: skip
        potential = -(m1 * (g[0] * p1[0] + g[2] * p1[1]) + m2 * (g[0] * p2[0] + g[2] * p2[1])
                      + mc * g[0] * q[0])  # fmt: skip
        mass_inv = ca.inv(ca.hessian(kinetic, qd)[0])
        bias = (ca.jacobian(ca.gradient(kinetic, qd), q) @ qd - ca.gradient(kinetic, q)
                + ca.gradient(potential, q))  # fmt: skip
        force = ca.vertcat(m.actuator_gear[0, 0] * u, 0, 0) - m.dof_damping * qd
        qdd = mass_inv @ (force - bias)
        self._sym = (ca.vertcat(q, qd), u, qd, qdd, mass_inv)
        self.step_sx, self.jac = self._rk4(qdd)
        self.step_stops, self.jac_stops = self.with_stops()
        self.u_lo, self.u_hi = m.actuator_ctrlrange[0]

    def _rk4(self, qdd):
        """(step, its Jacobians) of the acceleration ``qdd``: RK4 over the frame skip."""
        ca, (state, u, qd, _, _) = self.ca, self._sym
        f = ca.Function("f", [state, u], [ca.vertcat(qd, qdd)])
        s = ca.SX.sym("s", 6)
        h = self.model.opt.timestep
        z = s
        for _ in range(FRAME_SKIP):
            k1 = f(z, u)
            k2 = f(z + h / 2 * k1, u)
            k3 = f(z + h / 2 * k2, u)
            k4 = f(z + h * k3, u)
            z = z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        step = ca.Function("step", [s, u], [z])
        return step, ca.Function("AB", [s, u], [ca.jacobian(z, s), ca.jacobian(z, u)])

    def with_stops(self, smoothing=None):
        """(step, Jacobians) with the slider's end stops: MuJoCo's soft limit constraint, one per
        end, active within the joint's margin of its range: aref = −b·Jv − k·d(r)·r,
        r = distance − margin, d the solimp impedance, R = (1 − d)/d · dof_invweight0, the push
        max(0, (aref − J·a₀)/(A + R)). ``smoothing = (ε, σ)``: for a Newton solver, the switch
        at r = 0 a tanh of width ε m, the max a softplus of scale σ N, d its solimp maximum."""
        ca, m = self.ca, self.model
        _, _, qd, qdd, mass_inv = self._sym
        q0 = self._sym[0][0]
        (timeconst, dampratio), (dmin, dmax, width, mid, power) = m.jnt_solref[0], m.jnt_solimp[0]
        timeconst = max(timeconst, 2 * m.opt.timestep)  # MuJoCo's own floor
        b, k = 2 / (dmax * timeconst), 1 / (dmax * timeconst * dampratio) ** 2
        lo, hi = m.jnt_range[0]
        acc = qdd
        for J, distance in ((-1.0, hi - q0), (1.0, q0 - lo)):
            r = distance - m.jnt_margin[0]
            if smoothing is None:
                x = ca.fmin(ca.fabs(r) / width, 1)
                y = ca.if_else(x <= mid, x**power / mid ** (power - 1),
                               1 - (1 - x) ** power / (1 - mid) ** (power - 1))  # fmt: skip
                d = dmin + y * (dmax - dmin)
            else:
                d = dmax
            aref = -b * J * qd[0] - k * d * r
            z = (aref - J * qdd[0]) / (mass_inv[0, 0] + (1 - d) / d * m.dof_invweight0[0])
            if smoothing is None:
                push = ca.if_else(r < 0, 1, 0) * ca.fmax(0, z)
            else:
                eps, sigma = smoothing
                softplus = ca.fmax(z, 0) + sigma * ca.log1p(ca.exp(-ca.fabs(z) / sigma))
                push = 0.5 * (1 + ca.tanh(-r / eps)) * softplus
            acc = acc + mass_inv[:, 0] * J * push
        return self._rk4(acc)

    def mj_step(self, x, u):
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:], d.ctrl[:] = x[:3], x[3:], u
        for _ in range(FRAME_SKIP):
            mujoco.mj_step(m, d)
        return np.concatenate([d.qpos, d.qvel])

    def mj_jacobians(self, x, u, eps=1e-6):
        A = np.stack([(self.mj_step(x + e, u) - self.mj_step(x - e, u)) / (2 * eps)
                      for e in eps * np.eye(6)], axis=1)  # fmt: skip
        B = (self.mj_step(x, u + eps) - self.mj_step(x, u - eps)) / (2 * eps)
        return A, B

    def model_error(self, starts, rng) -> float:
        """Largest |symbolic − C MuJoCo| over 10-step rollouts with random actions, inside the
        rail (where the end stop does not act)."""
        err = 0.0
        for x0 in starts:
            x_mj = x_sym = np.asarray(x0, float)
            for u in rng.uniform(self.u_lo, self.u_hi, 10):
                x_mj = self.mj_step(x_mj, u)
                x_sym = np.asarray(self.step_sx(x_sym, u)).ravel()
                if abs(x_mj[0]) > 0.95:
                    break
                err = max(err, float(np.abs(x_mj - x_sym).max()))
        return err

    def stops_error(self, rng) -> float:
        """Largest |symbolic with end stops − C MuJoCo| over 10-step runs into either stop."""
        err = 0.0
        for _ in range(20):
            side = rng.choice([-1.0, 1.0])
            x_mj = x_sym = np.array([side * rng.uniform(0.5, 0.95), *rng.normal(0, 0.1, 2),
                                     side * rng.uniform(0, 3), 0, 0])  # fmt: skip
            for u in side * rng.uniform(0, self.u_hi, 10):
                x_mj = self.mj_step(x_mj, u)
                x_sym = np.asarray(self.step_stops(x_sym, u)).ravel()
                err = max(err, float(np.abs(x_mj - x_sym).max()))
        return err

    def track(self, x0, X, U, jac=None):
        """C MuJoCo rollout of ``u = clip(U + K (x − X))``, K a time-varying LQR about (X, U)
        on the Jacobians ``jac`` (default: the model without stops)."""
        Q, R = np.diag([10.0, 100, 100, 1, 1, 1]), np.array([[0.01]])
        P, K = Q.copy(), np.zeros((T, 6))
        jac = self.jac if jac is None else jac
        for t in reversed(range(T)):
            A, B = (np.asarray(a) for a in jac(X[t], U[t]))
            K[t] = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)[0]
            P = Q + A.T @ P @ (A - B @ K[t][None])
        xs = [np.asarray(x0, float)]
        for t in range(T):
            u = float(np.clip(U[t] - K[t] @ (xs[-1] - X[t]), self.u_lo, self.u_hi))
            xs.append(self.mj_step(xs[-1], u))
        return np.asarray(xs)


def tip(X):
    """The tip's height of each state in ``X: [..., 6]`` (the experiment's own formula)."""
    return np.asarray(double_tip_height(np.moveaxis(np.asarray(X), -1, 0)))


def weights():
    q_x, q_th, q_v, r = DOUBLE_WEIGHTS
    return np.array([q_x, q_th, q_th, q_v, q_v, q_v]), r


class CatchNLP:
    """IPOPT on the success test's constraints with the task's cost; the rail bound a parameter."""

    def __init__(self, plant, x0, step=None, max_iter=1000):
        ca = plant.ca
        step = plant.step_sx if step is None else step
        w, r = weights()
        opti = self.opti = ca.Opti()
        X, U = self.X, self.U = opti.variable(6, T + 1), opti.variable(1, T)
        self.rail = opti.parameter()
        opti.subject_to(X[:, 0] == x0)
        J = 0
        for t in range(T):
            opti.subject_to(X[:, t + 1] == step(X[:, t], U[t]))
            J += 0.5 * ca.sumsqr(np.sqrt(w) * X[:, t]) + 0.5 * r * U[t] ** 2
        J += 0.5 * ca.sumsqr(np.sqrt(w) * X[:, T])
        self.J = J
        opti.subject_to(0.6 * ca.cos(X[1, 1:]) + 0.6 * ca.cos(X[1, 1:] + X[2, 1:]) >= 1.001)
        opti.subject_to(opti.bounded(-self.rail, X[0, :], self.rail))
        opti.subject_to(opti.bounded(plant.u_lo, U, plant.u_hi))
        for i, bound in enumerate((0.09, 0.045, 0.045)):
            opti.subject_to(opti.bounded(-bound, X[i, T - 9 :], bound))
        opti.minimize(J)
        opti.solver("ipopt", {"print_time": False},
                    {"max_iter": max_iter, "print_level": 0, "tol": 1e-7})  # fmt: skip
        self.guess = (np.linspace(1.0, 0.0, T + 1)[:, None] * np.asarray(x0)[None], np.zeros(T))

    def solve(self, rail):
        """Solve at ``rail`` from the current guess; a solution becomes the next guess."""
        o = self.opti
        o.set_value(self.rail, rail)
        o.set_initial(self.X, self.guess[0].T)
        o.set_initial(self.U, self.guess[1][None])
        try:
            sol = o.solve()
        except RuntimeError:
            return False
        self.guess = (np.asarray(sol.value(self.X)).T, np.asarray(sol.value(self.U)).ravel())
        self.cost = float(sol.value(self.J))
        return True


def catch(plant, x0, rail):
    """(solved at ``rail``, the smallest rail bound met on the path, its cost, X, U)."""
    nlp = CatchNLP(plant, x0)
    if nlp.solve(rail):
        return True, rail, nlp.cost, *nlp.guess
    met, cost = None, None
    for bound in (b for b in RAIL_PATH if b > rail):
        if not nlp.solve(bound):
            break
        met, cost = bound, nlp.cost
    if met is not None and met == min(b for b in RAIL_PATH if b > rail) and nlp.solve(rail):
        return True, rail, nlp.cost, *nlp.guess
    return (False, met, cost, *nlp.guess) if met is not None else (False, None, None, None, None)


SMOOTHING = ((5e-3, 100.0), (2e-3, 30.0), (1e-3, 10.0), (5e-4, 3.0), (2e-4, 1.0))


def catch_with_stops(plant, x0, X, U, bound=1.1):
    """IPOPT on the model with the end stops smoothed (``SMOOTHING``, each level warm-started
    from the last, the first from (X, U); the cart within ``bound``) -> a row per level, each
    solution replayed in C MuJoCo (exact stops) with a tracking LQR: any row caught is a
    controller that catches the start."""
    rows, guess = [], (X, U)
    for smoothing in SMOOTHING:
        step, jac = plant.with_stops(smoothing)
        nlp = CatchNLP(plant, x0, step=step, max_iter=1500)
        nlp.guess = guess
        if not nlp.solve(bound):
            rows.append({"smoothing": smoothing, "status": nlp.opti.stats()["return_status"]})
            break
        guess = nlp.guess
        Xm = plant.track(x0, *guess, jac=jac)
        replay = {"caught_in_mujoco": bool(double_success(Xm)),
                  "min_tip": round(float(tip(Xm).min()), 4),
                  "max_cart": round(float(np.abs(Xm[:, 0]).max()), 4)}  # fmt: skip
        cart = round(float(np.abs(guess[0][:, 0]).max()), 4)
        rows.append({"smoothing": smoothing, "status": "solved", "cost": round(nlp.cost, 3),
                     "max_cart": cart, **replay})  # fmt: skip
    return rows


REACH_STEPS = 30  # 1.5 s: a catch is won or lost early (seed 5's start 4: its lowest tip at step 3)


def bang_bang_guess(plant, x0, rng, step):
    """An initial guess for :func:`reach`: the rollout (on ``step``) of 1–4 random full pushes
    of random sign, each 1–8 control steps, one after another from the start, then zero action."""
    U = np.zeros(T)
    t = 0
    for _ in range(rng.integers(1, 5)):
        n = int(rng.integers(1, 9))
        U[t : t + n] = rng.choice([plant.u_lo, plant.u_hi])
        t += n
    X = [np.asarray(x0, float)]
    for u in U:
        X.append(step(X[-1], u))
    return np.asarray(X), U


class ReachNLP:
    """IPOPT's highest minimum tip height over the first ``horizon`` steps (:func:`reach`), the
    rail bound a parameter."""

    def __init__(self, plant, x0, horizon=REACH_STEPS):
        ca, step = plant.ca, plant.step_sx
        opti = self.opti = ca.Opti()
        self.horizon = horizon
        X, U, s = self.X, self.U, self.s = (opti.variable(6, horizon + 1),
                                            opti.variable(1, horizon), opti.variable())  # fmt: skip
        self.rail = opti.parameter()
        opti.subject_to(X[:, 0] == x0)
        for t in range(horizon):
            opti.subject_to(X[:, t + 1] == step(X[:, t], U[t]))
        opti.subject_to(0.6 * ca.cos(X[1, 1:]) + 0.6 * ca.cos(X[1, 1:] + X[2, 1:]) >= s)
        opti.subject_to(opti.bounded(-self.rail, X[0, :], self.rail))
        opti.subject_to(opti.bounded(plant.u_lo, U, plant.u_hi))
        opti.minimize(-s)
        # a small first barrier weight, so that a good guess is not pushed far into the interior
        opti.solver("ipopt", {"print_time": False},
                    {"max_iter": 300, "print_level": 0, "tol": 1e-7, "mu_init": 1e-4})  # fmt: skip

    def solve(self, rail, X, U):
        """(the highest minimum tip, X, U) at ``rail`` from the guess (X, U) (cart clipped to
        the rail), or None where IPOPT fails."""
        o, h = self.opti, self.horizon
        X = np.array(X[: h + 1], float)
        X[:, 0] = np.clip(X[:, 0], -rail, rail)
        o.set_value(self.rail, rail)
        o.set_initial(self.X, X.T)
        o.set_initial(self.U, np.asarray(U, float)[None, :h])
        o.set_initial(self.s, float(tip(X).min()))
        try:
            sol = o.solve()
        except RuntimeError:
            return None
        return (
            float(sol.value(self.s)),
            np.asarray(sol.value(self.X)).T,
            np.asarray(sol.value(self.U)).ravel(),
        )


def reach(plant, x0, rail, n, rng, loose=None):
    """The highest the tip can be kept over the first :data:`REACH_STEPS` steps with the cart
    within ``rail``: IPOPT maximises ``s`` subject to the tip at or above ``s`` at each of
    them and the actions within their range — no cost, no end box, no later step, so a
    relaxation of the success test, short because the catches are won or lost in the first
    second. Two ways in, IPOPT being local:

    - along the rail: from ``loose = (bound, X, U)``, a catch at a looser rail bound (what
      :func:`catch` met), the bound tightened through ``RAIL_PATH`` to ``rail``, each solve
      warm-started from the last: how the best height falls as the rail shortens;
    - from ``n`` initial guesses at ``rail``: the straight line to upright, then
      :func:`bang_bang_guess`'s random pushes.

    A start whose best ``s`` stays below 1 m both ways is one IPOPT found no catch for: evidence,
    not proof, that no controller within the rail catches it. -> a dict for the row."""
    nlp = ReachNLP(plant, x0)
    row, best = {}, None
    if loose is not None:
        bound, X, U = loose
        path = {}
        for b in dict.fromkeys([bound, *(b for b in RAIL_PATH if rail < b < bound), rail]):
            found = nlp.solve(b, X, U)
            if found is None:
                break
            height, X, U = found
            path[str(b)] = round(height, 4)
        row["reach_along_rail"] = path
        if str(rail) in path:
            best = path[str(rail)]
    line = np.linspace(1.0, 0.0, T + 1)[:, None] * np.asarray(x0)[None]
    step = symbolic_step(plant)
    guesses = [(line, np.zeros(T))] + [bang_bang_guess(plant, x0, rng, step) for _ in range(n - 1)]
    heights = [found[0] for found in (nlp.solve(rail, *g) for g in guesses) if found is not None]
    row.update(reach_guesses=n, reach_converged=len(heights),
               reach_at_1m=sum(h >= 1.0 for h in heights))  # fmt: skip
    candidates = heights if best is None else [best, *heights]
    row["reach_best_min_tip"] = round(max(candidates), 4) if candidates else None
    return row


def symbolic_step(plant):
    """The symbolic model's step as a NumPy function of (x, u)."""
    return lambda x, u: np.asarray(plant.step_sx(x, u)).ravel()


def sqp(plant, x0, rail, penalty, on="mujoco", terminal=1.0, iterations=200):
    """Multiple-shooting SQP from the straight line -> (X, U, iterations, largest gap left), on
    C MuJoCo's step (``on="mujoco"``: end stops included, central finite differences) or on the
    symbolic model (``"symbolic"``: no rail). ``terminal`` multiplies the last state's cost
    weights."""
    w, r = weights()
    if on == "mujoco":
        step, jacobians = plant.mj_step, plant.mj_jacobians
    else:
        step = symbolic_step(plant)
        jacobians = lambda x, u: tuple(np.asarray(a) for a in plant.jac(x, u))
    lo, hi = plant.u_lo, plant.u_hi

    def l_x(x):
        g = w * x
        g[0] += 2 * penalty * max(abs(x[0]) - rail, 0.0) * np.sign(x[0])
        return g

    def l_xx(x):
        H = np.diag(w)
        H[0, 0] += 2 * penalty * (abs(x[0]) > rail)
        return H

    def cost(X, U):
        over = np.maximum(np.abs(X[:, 0]) - rail, 0.0)
        ends = 0.5 * (terminal - 1.0) * np.sum(w * X[T] ** 2)
        return 0.5 * np.sum(w * X**2) + ends + 0.5 * r * np.sum(U**2) + penalty * np.sum(over**2)

    def gaps_of(X, U):
        return np.array([step(X[t], U[t]) for t in range(T)]) - X[1:]

    X = np.linspace(1.0, 0.0, T + 1)[:, None] * np.asarray(x0)[None]
    U, nu, mu, n = np.zeros(T), 100.0, 1e-8, 0
    while n < iterations:
        n += 1
        gaps = gaps_of(X, U)
        AB = [
            tuple(np.reshape(a, (6, -1)).squeeze() for a in jacobians(X[t], U[t])) for t in range(T)
        ]
        P, p = l_xx(X[T]) + (terminal - 1.0) * np.diag(w), l_x(X[T]) + (terminal - 1.0) * w * X[T]
        k, K = np.zeros(T), np.zeros((T, 6))
        for t in reversed(range(T)):
            A, B = AB[t]
            pg = p + P @ gaps[t]
            Qx, Qu = l_x(X[t]) + A.T @ pg, r * U[t] + B @ pg
            Qxx, Quu, Qux = l_xx(X[t]) + A.T @ P @ A, r + B @ P @ B + mu, B @ P @ A
            newton = -Qu / Quu
            if lo - U[t] < newton < hi - U[t]:
                k[t], K[t] = newton, -Qux / Quu
            else:
                k[t] = np.clip(newton, lo - U[t], hi - U[t])
            P = Qxx + Quu * np.outer(K[t], K[t]) + np.outer(K[t], Qux) + np.outer(Qux, K[t])
            P = 0.5 * (P + P.T)
            p = Qx + Quu * K[t] * k[t] + K[t] * Qu + Qux * k[t]
        dX, dU = np.zeros_like(X), np.zeros(T)
        for t in range(T):
            A, B = AB[t]
            dU[t] = k[t] + K[t] @ dX[t]
            dX[t + 1] = A @ dX[t] + B * dU[t] + gaps[t]
        gap = np.abs(gaps).sum()
        slope = sum(l_x(X[t]) @ dX[t] for t in range(T + 1)) + r * U @ dU
        slope += (terminal - 1.0) * (w * X[T]) @ dX[T]
        if gap > 1e-9:
            nu = max(nu, 2 * abs(slope) / gap)
        merit0 = cost(X, U) + nu * gap
        alpha, accepted = 1.0, False
        for _ in range(20):
            X1, U1 = X + alpha * dX, np.clip(U + alpha * dU, lo, hi)
            merit1 = cost(X1, U1) + nu * np.abs(gaps_of(X1, U1)).sum()
            if np.isfinite(merit1) and merit1 <= merit0 + 1e-4 * alpha * (slope - nu * gap):
                accepted = True
                break
            alpha /= 2
        if accepted:
            X, U, mu = X1, U1, max(mu / 4, 1e-10)
        else:
            mu *= 10
        if accepted and gap < 1e-8 and np.abs(alpha * dU).max() < 1e-7:
            break
    return X, U, n, float(np.abs(gaps_of(X, U)).max())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="1,2,3,4,5,6,7")
    parser.add_argument("--starts", type=int, default=8)
    parser.add_argument("--keys", default=None, help="SEED:START,... instead of every start")
    parser.add_argument("--rail", type=float, default=0.98)
    parser.add_argument("--stops", action="store_true",
                        help="for a start not caught within --rail: IPOPT on the model with the "
                             "end stops from the loosest solution met")  # fmt: skip
    parser.add_argument("--sqp", action="store_true")
    parser.add_argument("--sqp-on", choices=("mujoco", "symbolic"), default="mujoco")
    parser.add_argument("--rail-penalty", type=float, default=0.0)
    parser.add_argument("--terminal-weight", type=float, default=1.0, help="--sqp's last state")
    parser.add_argument("--reach", type=int, default=0, metavar="N",
                        help="for each start also the highest lowest tip height IPOPT finds "
                             "over the first 1.5 s within --rail, along the rail from the "
                             "loosest catch and from N initial guesses (reach)")  # fmt: skip
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    try:
        import casadi
    except ImportError:
        print("CasADi is not installed (pip install casadi): nothing to run.", file=sys.stderr)
        return 1
    plant = Plant(casadi)
    if args.keys:
        try:
            keys = [(int(a), int(b)) for a, b in (k.split(":") for k in args.keys.split(","))]
        except ValueError:
            raise SystemExit(
                f"--keys: expected SEED:START,... (e.g. 4:4,5:2), got {args.keys!r}"
            ) from None
        if any(not 0 <= i < args.starts for _, i in keys):
            raise SystemExit(f"--keys: each START must lie in 0..{args.starts - 1}")
    else:
        keys = [(s, i) for s in map(int, args.seeds.split(",")) for i in range(args.starts)]
    starts = {s: TASKS["double_pendulum"].starts(np.random.default_rng(s), args.starts)
              for s in {k[0] for k in keys}}  # fmt: skip
    err = plant.model_error([starts[s][i] for s, i in keys[:20]], np.random.default_rng(0))
    print(f"symbolic model vs C MuJoCo, largest state difference over 10 steps: {err:.1e}")
    stops_err = plant.stops_error(np.random.default_rng(1))
    print(f"with the end stops, over 10 steps run into them: {stops_err:.1e}")
    if max(err, stops_err) > 1e-6:
        raise SystemExit("the symbolic model does not match the MJCF")
    rows = []
    for s, i in keys:
        x0 = starts[s][i]
        t0 = time.perf_counter()
        solved, met, cost, X, U = catch(plant, x0, args.rail)
        row = {"seed": s, "start": i, "tip0": round(float(tip(x0)), 4), "ipopt_solved": solved,
               "smallest_rail_met": met, "ipopt_cost": cost}  # fmt: skip
        if solved:
            Xm = plant.track(x0, X, U)
            row.update(caught_in_mujoco=bool(double_success(Xm)),
                       min_tip=round(float(tip(Xm).min()), 4),
                       min_tip_step=int(np.argmin(tip(Xm))),
                       max_cart=round(float(np.abs(Xm[:, 0]).max()), 4))  # fmt: skip
        row["ipopt_s"] = round(time.perf_counter() - t0, 1)
        if args.stops and not solved and X is not None:
            t0 = time.perf_counter()
            levels = catch_with_stops(plant, x0, X, U)
            caught = any(level.get("caught_in_mujoco", False) for level in levels)
            row.update(stops=levels, stops_caught_in_mujoco=caught,
                       stops_s=round(time.perf_counter() - t0, 1))  # fmt: skip
        if args.reach:
            t0 = time.perf_counter()
            loose = None if solved or X is None else (met, X, U)
            rng = np.random.default_rng([s, i])
            row.update(reach(plant, x0, args.rail, args.reach, rng, loose))
            row["reach_s"] = round(time.perf_counter() - t0, 1)
        if args.sqp:
            t0 = time.perf_counter()
            Xs, Us, n, gap = sqp(
                plant, x0, args.rail, args.rail_penalty, args.sqp_on, args.terminal_weight
            )
            Xm = plant.track(x0, Xs, Us)
            row.update(sqp_on=args.sqp_on, sqp_max_cart=round(float(np.abs(Xs[:, 0]).max()), 4),
                       sqp_min_tip=round(float(tip(Xs).min()), 4),
                       sqp_iterations=n, sqp_gap=gap, sqp_caught_in_mujoco=bool(double_success(Xm)),
                       sqp_s=round(time.perf_counter() - t0, 1))  # fmt: skip
        rows.append(row)
        print(json.dumps(row), flush=True)
    caught = sum(r.get("caught_in_mujoco", False) for r in rows)
    print(f"caught (IPOPT within ±{args.rail} m, replayed in C MuJoCo): {caught}/{len(rows)}")
    if args.stops:
        more = sum(r.get("stops_caught_in_mujoco", False) for r in rows)
        print(f"caught by running into the end stops as well: {more} more")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rail": args.rail, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
