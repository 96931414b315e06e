"""Speed of USV rollouts with every range beam computed at every step, beside the same rollouts
without sensors.

B rollouts of T steps of the USV task env under ``jit(vmap)``: (a) the hull alone, with open-loop
commands; (b) the same with the policy's whole observation (32 LiDAR + 16 radar beams as
ingestion reads them, heading, ν, cross-track) computed at every step, noise-free; (c) the same
with the sensors' noise drawn at every step; (d) a global policy (64×64 MLP) closing the loop on
the noisy observation, as the evaluation does. Median of 3 timed runs after a warm-up; steps/s
counts hull steps (B·T per run).

    python experiments/usv_speed.py [--batch 256] [--horizon 300] [--json runs/usv_speed.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np


def timed(fn, *args, repeats: int = 3) -> float:
    """Median seconds of ``fn(*args)`` after one warm-up call (which compiles)."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--horizon", type=int, default=300)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    from diffgcl.envs.usv import default_conditions, make_usv_env
    from diffgcl.policies.network import GaussianPolicy, PolicyConfig
    from diffgcl.runtime import prepare_process

    prepare_process()
    B, T = args.batch, args.horizon
    env = make_usv_env(default_conditions(), horizon=T)
    x0 = jnp.tile(env.initial_states(), (B // env.initial_states().shape[0] + 1, 1))[:B]
    x0 = x0.at[:, 1].add(jnp.linspace(-20.0, 20.0, B))
    U = 0.3 * jnp.sin(jnp.linspace(0.0, 6.0, T))[:, None] * jnp.array([0.2, 1.0])
    policy = GaussianPolicy(PolicyConfig(hidden=(64, 64)), env.dO, env.dU)
    params = policy.init(jax.random.PRNGKey(0))

    def hull_only(x):
        def step(x, u):
            return env.step(x, u), x[0]

        return jax.lax.scan(step, x, U)[1]

    def with_obs(x):
        def step(x, u):
            return env.step(x, u), env.obs(x)[0]

        return jax.lax.scan(step, x, U)[1]

    def with_noisy_obs(x, key):
        def step(x, inp):
            u, k = inp
            return env.step(x, u), env.obs(x, k)[0]

        return jax.lax.scan(step, x, (U, jax.random.split(key, T)))[1]

    def closed_loop(x, key):
        def step(x, k):
            u = policy.mean_action(params, env.obs(x, k))
            return env.step(x, u), x[1]

        return jax.lax.scan(step, x, jax.random.split(key, T))[1]

    keys = jax.random.split(jax.random.PRNGKey(1), B)
    cases = {
        "hull only": (jax.jit(jax.vmap(hull_only)), (x0,)),
        "hull + observation (48 beams)": (jax.jit(jax.vmap(with_obs)), (x0,)),
        "hull + noisy observation": (jax.jit(jax.vmap(with_noisy_obs)), (x0, keys)),
        "policy on noisy observation": (jax.jit(jax.vmap(closed_loop)), (x0, keys)),
    }
    out = {"batch": B, "horizon": T, "devices": [str(d) for d in jax.devices()]}
    base = None
    for name, (fn, a) in cases.items():
        s = timed(fn, *a)
        rate = B * T / s
        base = base or rate
        out[name] = {"seconds": s, "steps_per_second": rate, "relative_to_hull_only": rate / base}
        print(f"{name:32s} {rate / 1e6:6.2f} M steps/s  ({rate / base:.2f}× the hull alone)")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
