"""Manoeuvring report of the Odin-like hull (MJX, nominal HullParams).

Standard trials (ITTC/IMO manoeuvring-trial style, adapted to a water-jet boat whose "rudder" is
the nozzle), all simulated with ``diffgcl.sim.hull.hull_step`` at dt = 0.1 s:

* top speed: full thrust, nozzle centred, from rest, until steady;
* turning circle: from top speed, full thrust and full nozzle (30°); the steady turning diameter
  is a least-squares circle fitted to the last 20 s of the track, in boat lengths;
* 10/10 zig-zag: from top speed, nozzle +10° until the heading has changed by +10°, then −10°
  until −10°, and so on; overshoot angles are the heading excursions beyond ±10°;
* crash stop: from top speed, full reverse thrust commanded; distance along the track until the
  surge speed reaches zero;
* RK4 agreement: 30 s of manoeuvring, MJX against an RK4 integration (10 substeps per step) of
  the same ODE (:func:`diffgcl.sim.hull.state_derivative`); largest position error divided by
  the distance travelled.

Usage: ``python experiments/hull_report.py [--fast] [--json PATH]``.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from diffgcl.runtime import prepare_process  # noqa: E402
from diffgcl.sim import hull as H  # noqa: E402

DT = 0.1


def default_config(fast: bool = False) -> dict:
    """Trial lengths in control steps of 0.1 s."""
    return {
        "steps": 700 if fast else 1200,  # top speed / turning / stop trials
        "zigzag_steps": 300 if fast else 600,
        "rk4_steps": 300,
        "zigzag_deg": 10.0,
    }


def make_rollout(params):
    @jax.jit
    def rollout(x0, U):
        """X: [T+1, 10] under open-loop commands U: [T, 2]."""
        xT, X = jax.lax.scan(lambda x, u: (H.hull_step(params, x, u), x), x0, U)
        return jnp.concatenate([X, xT[None]])

    return rollout


def make_zigzag(params, angle_deg: float, steps: int):
    angle = np.deg2rad(angle_deg)

    @jax.jit
    def zigzag(x0):
        """Heading change and nozzle sign, [steps] each, of the angle/angle zig-zag from x0."""
        psi0 = x0[H.IX_PSI]

        def step(carry, _):
            x, sign = carry
            x = H.hull_step(params, x, jnp.stack([params.max_thrust, sign * angle]))
            dpsi = x[H.IX_PSI] - psi0
            sign = jnp.where((sign > 0) & (dpsi >= angle), -1.0, sign)
            sign = jnp.where((sign < 0) & (dpsi <= -angle), 1.0, sign)
            return (x, sign), (dpsi, sign)

        return jax.lax.scan(step, (x0, jnp.asarray(1.0, x0.dtype)), None, length=steps)[1]

    return zigzag


def make_rk4(params, substeps: int = 10):
    @jax.jit
    def rk4(x0, U):
        h = DT / substeps

        def step(x, u):
            for _ in range(substeps):
                k1 = H.state_derivative(params, x, u)
                k2 = H.state_derivative(params, x + 0.5 * h * k1, u)
                k3 = H.state_derivative(params, x + 0.5 * h * k2, u)
                k4 = H.state_derivative(params, x + h * k3, u)
                x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            return x, x

        xT, X = jax.lax.scan(step, x0, U)
        return jnp.concatenate([x0[None], X])

    return rk4


def fit_circle(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares (Kåsa) circle through points xy: [N, 2] -> centre [2], radius."""
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    b = np.sum(xy**2, axis=1)
    (cx, cy, c), *_ = np.linalg.lstsq(A, b, rcond=None)
    return np.array([cx, cy]), float(np.sqrt(c + cx**2 + cy**2))


def overshoots(dpsi: np.ndarray, sign: np.ndarray, angle: float) -> list[float]:
    """Overshoot angles (deg) of a zig-zag: heading change dpsi: [T] (rad) and the nozzle sign
    in force after each step, sign: [T]. Between reversal k and k+1 the heading keeps turning
    past ±angle; the overshoot is that excursion beyond ±angle."""
    flips = np.flatnonzero(np.diff(sign) != 0) + 1
    out = []
    for a, b in zip(flips[:-1], flips[1:], strict=True):
        seg = dpsi[a:b]
        out.append(float(np.rad2deg(seg.max() - angle if sign[a] < 0 else -seg.min() - angle)))
    return out


def run(fast: bool = False) -> dict:
    cfg = default_config(fast)
    params = H.default_params(jnp.float64)
    L = float(params.length)
    rollout = make_rollout(params)
    n = cfg["steps"]
    full = jnp.broadcast_to(jnp.array([float(params.max_thrust), 0.0]), (n, 2))
    t0 = time.perf_counter()

    # Top speed from rest.
    X = np.asarray(rollout(jnp.zeros(H.DX), full))
    x_top = X[-1]
    nu_top = np.asarray(H.body_velocity(jnp.asarray(x_top)))
    top_speed = float(np.hypot(nu_top[0], nu_top[1]))
    settle = float(np.abs(X[-1, H.IX_VX] - X[-100, H.IX_VX]))  # change over the last 10 s

    # Turning circle at full nozzle.
    turn = jnp.broadcast_to(jnp.array([float(params.max_thrust), float(params.max_nozzle)]), (n, 2))
    Xt = np.asarray(rollout(jnp.asarray(x_top), turn))
    _, radius = fit_circle(Xt[-200:, :2])
    nu_turn = np.asarray(H.body_velocity(jnp.asarray(Xt[-1])))
    advance_psi = np.unwrap(Xt[:, H.IX_PSI]) - Xt[0, H.IX_PSI]
    i90 = int(np.argmax(advance_psi >= np.pi / 2))
    i180 = int(np.argmax(advance_psi >= np.pi))
    advance = float(Xt[i90, 0] - Xt[0, 0])
    tactical = float(Xt[i180, 1] - Xt[0, 1])

    # 10/10 zig-zag.
    angle = np.deg2rad(cfg["zigzag_deg"])
    zigzag = make_zigzag(params, cfg["zigzag_deg"], cfg["zigzag_steps"])
    dpsi, sign = (np.asarray(a) for a in zigzag(jnp.asarray(x_top)))
    shoots = overshoots(dpsi, sign, angle)

    # Crash stop: full reverse thrust commanded (clipped to 40 %).
    reverse = jnp.broadcast_to(jnp.array([-float(params.max_thrust), 0.0]), (n, 2))
    Xs = np.asarray(rollout(jnp.asarray(x_top), reverse))
    surge = np.asarray(jax.vmap(H.body_velocity)(jnp.asarray(Xs)))[:, 0]
    i_stop = int(np.argmax(surge <= 0.0))
    track = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(Xs[:, :2], axis=0), axis=1))])
    stopping_distance = float(track[i_stop])

    # RK4 agreement over 30 s of manoeuvring.
    T = cfg["rk4_steps"]
    t = np.arange(n) * DT
    U = np.stack([9000 + 4000 * np.sin(t / 4.0), 0.45 * np.sin(t / 2.5)], axis=1)
    U[100:140, 1] = 0.8
    U[200:240, 0] = -6000.0
    x0 = jnp.array([0.0, 0.0, 0.0, 8.0, 0.0, 0.0, 4000.0, 0.0, 0.0, 0.0])
    Xm = np.asarray(rollout(x0, jnp.asarray(U[:n])))[: T + 1]
    Xr = np.asarray(make_rk4(params)(x0, jnp.asarray(U[:T])))
    travelled = float(np.sum(np.linalg.norm(np.diff(Xr[:, :2], axis=0), axis=1)))
    rk4_err = float(np.max(np.linalg.norm(Xm[:, :2] - Xr[:, :2], axis=1)) / travelled)
    elapsed = time.perf_counter() - t0

    return {
        "top_speed_kn": top_speed / H.KNOT,
        "top_speed_ms": top_speed,
        "top_speed_settle_ms_per_10s": settle,
        "turning_diameter_L": 2 * radius / L,
        "turning_diameter_m": 2 * radius,
        "turning_speed_kn": float(np.hypot(nu_turn[0], nu_turn[1])) / H.KNOT,
        "turning_yaw_rate_deg_s": float(np.rad2deg(nu_turn[2])),
        "turning_drift_deg": float(np.rad2deg(np.arctan2(-nu_turn[1], nu_turn[0]))),
        "advance_L": advance / L,
        "tactical_diameter_L": tactical / L,
        "zigzag_overshoot_deg": shoots[0] if shoots else float("nan"),
        "zigzag_second_overshoot_deg": shoots[1] if len(shoots) > 1 else float("nan"),
        "stopping_distance_m": stopping_distance,
        "stopping_distance_L": stopping_distance / L,
        "stopping_time_s": i_stop * DT,
        "rk4_rel_error": rk4_err,
        "rk4_distance_m": travelled,
        "seconds": elapsed,
        "fast": fast,
        "dtype": "float64",
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fast", action="store_true", help="shorter trials")
    parser.add_argument("--json", metavar="PATH", help="write the figures as JSON")
    args = parser.parse_args(argv)
    prepare_process()
    out = run(args.fast)
    rows = [
        ("top speed", f"{out['top_speed_kn']:.1f} kn ({out['top_speed_ms']:.2f} m/s)"),
        (
            "turning diameter (30° nozzle)",
            f"{out['turning_diameter_L']:.2f} L ({out['turning_diameter_m']:.1f} m) at "
            f"{out['turning_speed_kn']:.1f} kn, {out['turning_yaw_rate_deg_s']:.1f}°/s, "
            f"drift {out['turning_drift_deg']:.1f}°",
        ),
        (
            "advance / tactical diameter",
            f"{out['advance_L']:.2f} L / {out['tactical_diameter_L']:.2f} L",
        ),
        (
            "10/10 zig-zag overshoot",
            f"{out['zigzag_overshoot_deg']:.1f}° "
            f"(second {out['zigzag_second_overshoot_deg']:.1f}°)",
        ),
        (
            "crash stop",
            f"{out['stopping_distance_m']:.1f} m ({out['stopping_distance_L']:.1f} L) "
            f"in {out['stopping_time_s']:.1f} s",
        ),
        (
            "MJX vs RK4 (30 s)",
            f"{100 * out['rk4_rel_error']:.3f} % of {out['rk4_distance_m']:.0f} m",
        ),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")
    print(f"({out['seconds']:.1f} s incl. compilation)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return out


if __name__ == "__main__":
    main()
