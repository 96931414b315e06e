"""Which of trajopt_gym's double-pendulum starts a saturated LQR can balance (C MuJoCo, seconds).

A reference for ``experiments/trajopt_gym.py --models double_pendulum``: the discrete-time LQR of
gymnasium's ``inverted_double_pendulum.xml`` linearised upright (central finite differences of
one control period, frame skip 5), ``u = clip(−Kx, −1, 1)`` (the actuator's ctrlrange), from the
same 8 start states (NumPy ``default_rng(seed)``, hinge angles 3× gymnasium's), judged by the
same success test, over a grid of 108 weightings ``Q = diag(q_x, q_θ, q_θ, q_v, q_v, q_v)``,
``R = r``. A start no weighting balances is one where a linear controller within the actuator's
range does not suffice; it says nothing certain about what a nonlinear controller could do.

    python experiments/double_pendulum_lqr.py
"""

from __future__ import annotations

import argparse
import itertools

import mujoco
import numpy as np
from scipy.linalg import solve_discrete_are
from trajopt_gym import DOUBLE_WEIGHTS, TASKS, double_success, gym_asset

FRAME_SKIP = 5


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--starts", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    model = mujoco.MjModel.from_xml_path(str(gym_asset("inverted_double_pendulum.xml")))
    data = mujoco.MjData(model)
    nv = model.nv

    def step(x, u):
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:], data.ctrl[:] = x[:nv], x[nv:], u
        for _ in range(FRAME_SKIP):
            mujoco.mj_step(model, data)
        return np.concatenate([data.qpos, data.qvel])

    eps, zero_x, zero_u = 1e-6, np.zeros(2 * nv), np.zeros(1)
    A = np.stack([(step(zero_x + e, zero_u) - step(zero_x - e, zero_u)) / (2 * eps)
                  for e in eps * np.eye(2 * nv)], axis=1)  # fmt: skip
    B = ((step(zero_x, zero_u + eps) - step(zero_x, zero_u - eps)) / (2 * eps))[:, None]
    X0 = TASKS["double_pendulum"].starts(np.random.default_rng(args.seed), args.starts)
    horizon = TASKS["double_pendulum"].horizon
    ever = np.zeros(len(X0), bool)
    grid = list(
        itertools.product((0.1, 1, 10), (1, 10, 100), (0.01, 0.1, 1), (0.001, 0.01, 0.1, 1))
    )

    def balanced(Q, R):
        """Per start: whether u = clip(−Kx, −1, 1), K the discrete LQR gain, passes the test."""
        P = solve_discrete_are(A, B, Q, R)
        K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        solved = []
        for x0 in X0:
            X = [x0]
            for _ in range(horizon):
                X.append(step(X[-1], np.clip(-K @ X[-1], -1.0, 1.0)))
            solved.append(int(bool(double_success(np.asarray(X)))))
        return solved

    best = (-1, None)
    for qx, qth, qv, r in grid:
        solved = balanced(np.diag([qx, qth, qth, qv, qv, qv]), r * np.eye(1))
        ever |= np.asarray(solved, bool)
        if sum(solved) > best[0]:
            best = (sum(solved), (qx, qth, qv, r), solved)
    qx, qth, qv, r = DOUBLE_WEIGHTS
    task_solved = balanced(np.diag([qx, qth, qth, qv, qv, qv]), r * np.eye(1))
    print(f"LQR with the task cost's weights: {sum(task_solved)}/{len(X0)} {task_solved}")
    print(f"best of {len(grid)} weightings {best[1]} (q_x, q_θ, q_v, r): {best[0]}/{len(X0)} "
          f"{np.asarray(best[2]).astype(int).tolist()}")  # fmt: skip
    print(f"balanced by at least one weighting: {int(ever.sum())}/{len(X0)} "
          f"{ever.astype(int).tolist()}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
