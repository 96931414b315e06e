"""The expert's iLQR over its start states: all in one vmap, or a few at a time.

``trajopt.solve(..., batch_size=None)`` solves every start state in one vmapped while loop, which
runs each start — and each of its line-search trials — as long as the slowest start needs;
``batch_size=N`` solves them N at a time (``lax.map`` over groups; the same solutions up to
rounding). Which is faster depends on how alike the starts' solves are and on the device. This
script measures both on the models a user of the expert meets, in one process, per model and
per batching: seconds to trace and compile the program, seconds of the run after compile, and
the largest relative difference of the final costs from the one vmap's (with the task's success
test, how many starts each solved).

Models: ``experiments/any_mjcf.py``'s reacher and cart-pole (the project's own MJCF files, 4
start states each), and gymnasium's reacher, inverted pendulum and inverted double pendulum
(``experiments/trajopt_gym.py``: 8 start states from the envs' reset distributions, NumPy seed
``--seed``, the pendulums tilted 3×). The expert's default initial actions (``initial="best"``),
float64 (as ``diffgcl demos --mjcf``).

``--cold`` compiles into a fresh, empty persistent compilation cache (the first run of a new
model); without it the project's cache is used, so a second run of the script measures the
programs loaded from it.

    python experiments/expert_batching.py --cold --json runs/expert_batching.json
    python experiments/expert_batching.py --models gym_double_pendulum --seed 4 --batches vmap,1
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

MODELS = (
    "mjcf_reacher",
    "mjcf_cartpole",
    "gym_reacher",
    "gym_pendulum",
    "gym_double_pendulum",
)


def model_env(name: str, seed: int):
    """(env, cost) of a model named in :data:`MODELS`."""
    if name.startswith("mjcf_"):
        import any_mjcf

        task = any_mjcf.tasks()[name.removeprefix("mjcf_")]
        return any_mjcf.expert_env(task), task.cost
    import trajopt_gym

    env, task, _ = trajopt_gym.gym_env(name.removeprefix("gym_"), seed=seed)
    return env, task.cost


def parse_batches(text: str) -> list[int | None]:
    out = []
    for word in text.split(","):
        if word == "vmap":
            out.append(None)
        elif word.isdigit() and int(word) >= 1:
            out.append(int(word))
        else:
            raise SystemExit(
                f"expert_batching: --batches takes 'vmap' or integers >= 1, got {word!r}"
            )
    return out


def measure(env, cost, batch_size):
    """(result, compile seconds, run seconds) of the expert's iLQR in groups of ``batch_size``."""
    from diffgcl.algorithms import trajopt

    X0 = env.initial_states()
    program = jax.jit(
        lambda x0: trajopt.solve(env, cost, x0, initial="best", batch_size=batch_size)
    )
    t0 = time.perf_counter()
    compiled = program.lower(X0).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = jax.block_until_ready(compiled(X0))
    return result, compile_s, time.perf_counter() - t0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    default_models = ",".join(m for m in MODELS if "double" not in m)
    parser.add_argument("--models", default=default_models,
                        help=f"comma-separated, of {', '.join(MODELS)} (default: all but "
                             "the double pendulum, 10 min in one vmap here)")  # fmt: skip
    parser.add_argument("--batches", default="vmap,1,2",
                        help="comma-separated: 'vmap' (one vmap) or a group size")  # fmt: skip
    parser.add_argument("--seed", type=int, default=7, help="NumPy seed of gymnasium's starts")
    parser.add_argument("--cold", action="store_true",
                        help="compile into a fresh, empty compilation cache")  # fmt: skip
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import prepare_process

    batches = parse_batches(args.batches)
    cold = tempfile.TemporaryDirectory(prefix="expert_batching_cache_") if args.cold else None
    prepare_process(cold.name if cold else None)
    rows = {}
    for name in args.models.split(","):
        if name not in MODELS:
            raise SystemExit(f"expert_batching: unknown model {name!r}; choose from {MODELS}")
        env, cost = model_env(name, args.seed)
        print(f"== {name}: {env.initial_states().shape[0]} starts, T = {env.horizon}", flush=True)
        rows[name] = []
        reference = None
        for b in batches:
            result, compile_s, run_s = measure(env, cost, b)
            costs = np.asarray(result.cost)
            if reference is None:
                reference = costs
            rel = float(np.max(np.abs(costs - reference) / np.maximum(np.abs(reference), 1e-12)))
            solved = None
            if env.has_success:
                solved = int(np.sum(np.asarray(jax.vmap(env.success)(result.X))))
            row = {
                "batch_size": b,
                "compile_seconds": compile_s,
                "seconds": run_s,
                "cost": costs.tolist(),
                "max_relative_cost_difference": rel,
                "solved": solved,
                "iterations": np.asarray(result.iterations).tolist(),
            }
            rows[name].append(row)
            label = "one vmap" if b is None else f"{b} at a time"
            print(f"   {label:>12}: {run_s:8.2f} s after compile, {compile_s:6.1f} s compile, "
                  f"solved {solved}, costs vs the first row {rel:.1e}", flush=True)  # fmt: skip
        if args.json:  # after each model, so a long run keeps what it finished
            args.json.parent.mkdir(parents=True, exist_ok=True)
            summary = {"seed": args.seed, "cold": args.cold, "cpu_count": jax.local_device_count(),
                       "device": str(jax.devices()[0]), "models": rows}  # fmt: skip
            args.json.write_text(json.dumps(summary, indent=1))
    if cold:
        cold.cleanup()
    if args.json:
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
