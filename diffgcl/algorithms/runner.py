"""Host loop around the pure rGCL core: chunks, progress, checkpoints, resume, NaN report, run dir.

Also the host-side readers the commands and experiments share: :func:`load_demo_batch` (a demo
folder or the built-in demos as a :class:`~diffgcl.algorithms.rgcl.DemoBatch`) and
:func:`load_run` (a run folder back into its config, state and metrics).

:func:`train_seeds` runs one rGCL configuration for several seeds as one vmapped batch. The pure
pieces come from :func:`diffgcl.algorithms.rgcl.make_train`: ``init`` (with pre-training) once,
then ``run`` over chunks of ``chunk`` iterations, each a jitted call. Because the per-iteration
keys are ``fold_in(key_loop, step)``, the chunked run gives exactly the states and metrics of
``train`` in one call, and so does a run resumed from a checkpoint.

Checkpoints are plain ``np.savez`` files of the flattened state pytree (plus the metrics so far),
written to a temporary name and renamed, every ``checkpoint_every`` iterations. Orbax would work
too, but this state is a few MB of arrays in one process: a single atomic ``.npz`` whose leaves
are restored into the tree structure of ``jax.eval_shape(init)`` needs no async machinery, no
version coupling and reads back with NumPy alone.

Several processes (:mod:`diffgcl.distributed`): the seeds are split over the devices of every
process, and after each chunk the metrics and the state are all-gathered, so every process holds
the whole run on the host; process 0 alone writes the one ``checkpoint.npz``, the same file as a
one-process run. Not per-process files: those would tie a resume to the same number of processes
and the same split, and ``eval`` / ``plot`` / :func:`load_run` would need to stitch them. Not
orbax's multi-host checkpointing: it exists for states too large for one host (each process
writes its shards, asynchronously), while a few MB per seed gathers in milliseconds; it needs a
shared filesystem just the same. A resume on several machines therefore needs the run folder on
a filesystem they share (or a copy on each): every process reads the checkpoint, and a process
that finds a different one (or none) stops the run with an error rather than diverging.

NaN guard: the core rolls back any iteration that makes a finite value of the state non-finite
(``RGCLMetrics.rolled_back``); this loop reports each one (seed, iteration). Should a chunk still
return a state with new non-finite values, the loop restores the state before the chunk, reports
it and stops.
"""

from __future__ import annotations

import csv
import json
import os
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.algorithms.rgcl import (
    DemoBatch,
    RGCLConfig,
    RGCLHyperparams,
    RGCLMetrics,
    RGCLState,
    make_train,
)
from diffgcl.algorithms.staged import can_stage, rgcl_loop
from diffgcl.distributed import check_same_everywhere, compile_program, is_leader, to_host
from diffgcl.runtime import CompileClock
from diffgcl.sim.sharding import shard_batch_if_even, vmap_over_devices

CHECKPOINT = "checkpoint.npz"


class SimulatedCrash(RuntimeError):
    """Raised by :func:`train_seeds` with ``crash_after`` (tests of resume)."""


@dataclass
class RunResult:
    """What :func:`train_seeds` returns (NumPy arrays, leading axis seeds).

    state: RGCLState [S, ...]; metrics: RGCLMetrics [S, iterations, ...]; seeds; config;
    compile_seconds: lowering + compilation of the init and chunk programs (0 when cached in this
    process); run_seconds: execution after compilation; resumed_from: the iteration a resumed run
    started at (0 otherwise); rollbacks: report lines of NaN-guard rollbacks.
    """

    state: RGCLState
    metrics: RGCLMetrics
    seeds: list[int]
    config: RGCLConfig
    compile_seconds: float = 0.0
    run_seconds: float = 0.0
    resumed_from: int = 0
    rollbacks: list[str] = field(default_factory=list)


def _save_checkpoint(path: Path, state, metrics, done: int, seeds) -> None:
    leaves = jax.tree.leaves(state)
    m_leaves = jax.tree.leaves(metrics) if metrics is not None else []
    arrays = {f"s{i}": np.asarray(a) for i, a in enumerate(leaves)}
    arrays.update({f"m{i}": np.asarray(a) for i, a in enumerate(m_leaves)})
    arrays["done"] = np.asarray(done)
    arrays["seeds"] = np.asarray(seeds)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def checkpoint_like(rgcl, key_init, key_loop, demos, hparams):
    """Shapes (``jax.eval_shape``) of a seed-vmapped run's state and of one iteration's metrics:
    the pytree structures a checkpoint is read back into."""
    state_like = jax.eval_shape(jax.vmap(rgcl.init, in_axes=(0, None, 0)), key_init, demos, hparams)
    m_like = jax.eval_shape(
        jax.vmap(lambda s, k, d: rgcl.run(s, k, d, 1), in_axes=(0, 0, None)),
        state_like,
        key_loop,
        demos,
    )[1]
    return state_like, m_like


def _load_checkpoint(path: Path, state_like, metrics_like):
    with np.load(path) as f:
        done = int(f["done"])
        seeds = [int(s) for s in f["seeds"]]
        s_def = jax.tree.structure(state_like)
        m_def = jax.tree.structure(metrics_like)
        stored = {p: sum(1 for k in f.files if k[0] == p and k[1:].isdigit()) for p in "sm"}
        expected = {"s": s_def.num_leaves, "m": m_def.num_leaves if done > 0 else 0}
        if stored != expected:
            raise ValueError(
                f"{path}: checkpoint of {stored['s']} state and {stored['m']} metric arrays, "
                f"this run's settings and version need {expected['s']} and {expected['m']}: "
                "it was written with other settings or by another version of diffgcl "
                "(resume with those, or start a new run folder)"
            )
        state = jax.tree.unflatten(s_def, [f[f"s{i}"] for i in range(s_def.num_leaves)])
        metrics = None
        if done > 0:
            metrics = jax.tree.unflatten(m_def, [f[f"m{i}"] for i in range(m_def.num_leaves)])
    return state, metrics, done, seeds


def _finite(new, old) -> bool:
    """No value that was finite in ``old`` is non-finite in ``new``."""
    return all(
        bool(np.all(np.isfinite(a) | ~np.isfinite(b)))
        for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(old), strict=True)
        if np.issubdtype(np.asarray(a).dtype, np.inexact)
    )


def _postfix(m: RGCLMetrics) -> dict:
    """Progress-bar summary of the last iteration of a chunk (means over seeds, conditions)."""
    last = jax.tree.map(lambda a: np.asarray(a)[:, -1], m)
    return {
        "true": f"{last.gps.cost[:, -1].mean():.1f}",
        "learned": f"{last.learned_cost[:, -1].mean():.1f}",
        "step": f"{last.gps.step_mult[:, -1].mean():.3g}",
        "entropy": f"{last.gps.entropy[:, -1].mean():.1f}",
        "success": f"{np.all(last.gps.success[:, -1], axis=-1).mean():.2f}",
    }


def train_seeds(
    config: RGCLConfig,
    env,
    demos: DemoBatch,
    seeds,
    *,
    hparams: RGCLHyperparams | None = None,
    out: Path | None = None,
    chunk: int = 5,
    checkpoint_every: int = 5,
    resume: bool = False,
    progress: bool = True,
    crash_after: int | None = None,
    staged: bool | None = None,
) -> RunResult:
    """Train ``config`` on ``env`` for every seed (one vmapped batch); see the module docstring.

    hparams: RGCLHyperparams with a leading [S] axis (default: the config's values for all).
    out: run folder for the checkpoint (``out/checkpoint.npz``); resume: continue from it.
    crash_after: raise :class:`SimulatedCrash` once this many iterations are done (tests).
    staged: run the iterations as a host loop over the jitted draw and update programs with the
    env's staged simulator (:mod:`diffgcl.algorithms.staged`; the same results, the simulator
    compiled once for every program of the process) — default: in one process; else each chunk
    of iterations is one traced program.
    """
    seeds = [int(s) for s in seeds]
    S = len(seeds)
    if jax.process_count() > 1 and S % jax.device_count():
        raise ValueError(
            f"{S} seeds do not divide over the {jax.device_count()} devices of "
            f"{jax.process_count()} processes"
        )
    rgcl = make_train(config, env)
    if hparams is None:
        hp = rgcl.default_hparams()
        hparams = jax.tree.map(lambda a: jnp.broadcast_to(a, (S,)), hp)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    key_init, key_loop = jax.vmap(rgcl.split_key)(keys)
    check_same_everywhere("training settings", {"config": config.to_dict(), "seeds": seeds})
    check_same_everywhere("demos and hyperparameters", (demos, hparams))
    leader = is_leader()
    # Seeds split over all devices (the CPU's cores with runtime.set_cpu_devices).
    key_init, key_loop, hparams = shard_batch_if_even((key_init, key_loop, hparams))
    total = config.iterations
    chunk = max(1, min(chunk, total))

    init_fn = jax.jit(vmap_over_devices(rgcl.init, in_axes=(0, None, 0)))
    programs: dict[int, object] = {}
    compile_seconds = 0.0
    if staged is None:
        staged = can_stage()
    loop = rgcl_loop(rgcl, env) if staged else None

    def chunk_fn(n: int):
        nonlocal compile_seconds
        if loop is not None:
            return lambda s, k, d: loop.run(s, n, draw_args=(k,), update_args=(k, d))
        if n not in programs:
            run_n = lambda s, k, d: rgcl.run(s, k, d, n)  # noqa: E731
            f = jax.jit(vmap_over_devices(run_n, in_axes=(0, 0, None)))
            t0 = time.perf_counter()
            programs[n] = compile_program(f.lower(state, key_loop, demos))
            compile_seconds += time.perf_counter() - t0
        return programs[n]

    ckpt = None if out is None else Path(out) / CHECKPOINT
    metrics_parts: list = []
    done = 0
    run_seconds = 0.0
    resuming = resume and ckpt is not None and ckpt.is_file()
    if resuming:
        state_like, m_like = checkpoint_like(rgcl, key_init, key_loop, demos, hparams)
        m_like = jax.tree.map(lambda a: jax.ShapeDtypeStruct((S, 0, *a.shape[2:]), a.dtype), m_like)
        state_host, metrics, done, saved_seeds = _load_checkpoint(ckpt, state_like, m_like)
        if saved_seeds != seeds:
            raise ValueError(f"{ckpt}: checkpoint of seeds {saved_seeds}, not {seeds}")
        state = jax.tree.map(jnp.asarray, state_host)
        if metrics is not None:
            metrics_parts.append(metrics)
    check_same_everywhere(
        f"resume points ({ckpt})",
        {"resume": resuming, "done": done},
        hint="resuming on several machines needs the run folder on a filesystem they share",
    )
    if resuming:
        if leader:
            print(f"resumed {ckpt} at iteration {done}/{total}")
    else:
        t0 = time.perf_counter()
        compiled_init = compile_program(init_fn.lower(key_init, demos, hparams))
        compile_seconds += time.perf_counter() - t0
        t0 = time.perf_counter()
        state = jax.block_until_ready(compiled_init(key_init, demos, hparams))
        run_seconds += time.perf_counter() - t0
        state_host = to_host(state)
    resumed_from = done

    bar = None
    if progress and leader:
        from tqdm.auto import tqdm

        bar = tqdm(total=total, initial=done, desc=f"rGCL {config.schedule}", unit="it")
    rollbacks: list[str] = []
    last_ckpt = done
    try:
        while done < total:
            n = min(chunk, total - done)
            # The compiled chunk takes the batch split over the devices; a state loaded from a
            # checkpoint comes back on the default device (a no-op when already in place).
            state = shard_batch_if_even(state)
            program = chunk_fn(n)
            t0 = time.perf_counter()
            with CompileClock() as clock:
                new_state, m = jax.block_until_ready(program(state, key_loop, demos))
            compile_seconds += clock.seconds
            run_seconds += time.perf_counter() - t0 - clock.seconds
            m, new_host = to_host((m, new_state))
            for s, i in np.argwhere(m.rolled_back):
                line = f"seed {seeds[s]} iteration {done + i + 1}: non-finite state, rolled back"
                rollbacks.append(line)
                if leader:
                    print("NaN guard:", line)
            if not _finite(new_host, state_host):
                line = f"iterations {done + 1}-{done + n}: non-finite state; restored, stopping"
                rollbacks.append(line)
                if leader:
                    print("NaN guard:", line)
                break
            state, state_host = new_state, new_host
            metrics_parts.append(m)
            done += n
            if bar is not None:
                bar.update(n)
                bar.set_postfix(_postfix(m))
            if ckpt is not None and (done - last_ckpt >= checkpoint_every or done == total):
                if leader:
                    _save_checkpoint(ckpt, state_host, _concat(metrics_parts), done, seeds)
                last_ckpt = done
            if crash_after is not None and done >= crash_after and done < total:
                raise SimulatedCrash(f"simulated crash after iteration {done}")
    finally:
        if bar is not None:
            bar.close()
    return RunResult(
        state=state_host,
        metrics=_concat(metrics_parts),
        seeds=seeds,
        config=config,
        compile_seconds=compile_seconds,
        run_seconds=run_seconds,
        resumed_from=resumed_from,
        rollbacks=rollbacks,
    )


def write_policies(out: Path, result: RunResult, env) -> dict:
    """The global policies of a run: each seed's in ``out/policies/seed_<s>/``
    (:func:`diffgcl.policies.io.save_policy`), a plot of seed 0's noise-free rollouts from the
    training conditions, and their success per seed (returned for the summary)."""
    from diffgcl.algorithms.mdgps import make_policy
    from diffgcl.eval.policy import policy_rollouts, policy_success
    from diffgcl.policies.io import save_policy
    from diffgcl.viz import plots

    out = Path(out)
    policy = make_policy(result.config.policy, env)
    params = jax.tree.map(jnp.asarray, result.state.policy.params)
    x0 = jnp.asarray(env.initial_states())
    rollouts = jax.vmap(lambda p: policy_success(env, policy_rollouts(env, policy, p, x0)))
    success = np.asarray(jax.jit(rollouts)(params))  # [S, C]
    for i, seed in enumerate(result.seeds):
        one = jax.tree.map(lambda a, i=i: a[i], params)
        save_policy(out / "policies" / f"seed_{seed}", policy, one, method="rgcl+mdgps", seed=seed)
    p0 = jax.tree.map(lambda a: a[0], params)
    plots.policy_paths(env, policy, p0, {"training": x0}, out / "policy_rollouts.png")
    return {
        "policy_success": success.all(-1).tolist(),
        "policy_success_rate": float(success.all(-1).mean()),
    }


def _concat(parts):
    if not parts:
        return None
    return jax.tree.map(lambda *a: np.concatenate(a, axis=1), *parts)


# ---- run folder ---------------------------------------------------------------------------------


def run_summary(result: RunResult, env, demos: DemoBatch | None = None) -> dict:
    """Per-seed outcome of a run: success (DESIGN §2, noise-free rollout of the final controller
    on every condition), final distance (largest joint error at the last state, worst condition),
    first successful iteration; with the ``demos``, the final controllers' fit as a distribution
    (:mod:`diffgcl.eval.controllers`: entropy beside the demos' controller's, the demos' mean
    log-likelihood, success of 20 noisy samples per seed and condition) and the cost's
    log-temperature."""
    from diffgcl.algorithms.gps_runner import success_after_c_steps
    from diffgcl.algorithms.staged import noise_free_rollouts

    controller = jax.tree.map(jnp.asarray, result.state.gps.controller)
    X, _ = noise_free_rollouts(env, controller, jnp.asarray(result.state.gps.x0))
    per_condition = np.asarray(jax.vmap(jax.vmap(env.success))(jnp.asarray(X)))  # [S, C]
    success = per_condition.all(axis=-1)
    dist = np.abs(X[:, :, -1, :2] - np.asarray(env.target)).max(axis=(1, 2))
    sampled = np.asarray(result.metrics.gps.success)  # [S, iterations, G, C]
    S, I, G, C = sampled.shape
    after = success_after_c_steps(sampled.reshape(S, I * G, C), per_condition)
    per_iter = np.all(after.reshape(S, I, G, C)[:, :, -1], axis=-1)  # [S, iterations]
    first = [int(np.argmax(r)) + 1 if r.any() else None for r in per_iter]
    return {
        "seeds": result.seeds,
        "success": success.tolist(),
        "success_rate": float(success.mean()),
        "final_distance": dist.tolist(),
        "mean_final_distance": float(dist.mean()),
        "first_success_iteration": first,
        "final_true_cost": result.metrics.gps.cost[:, -1, -1].mean(-1).tolist(),
        "rollbacks": result.rollbacks,
        "c_step_failures": int(np.asarray(result.metrics.gps.c_step_failed).sum()),
        "compile_seconds": result.compile_seconds,
        "run_seconds": result.run_seconds,
        "log_temperature": np.asarray(result.state.cost.params.log_temperature).tolist(),
        **(distribution_summary(env, controller, demos, result.seeds) if demos else {}),
        "final_rollouts": X,
    }


def distribution_summary(env, controller, demos: DemoBatch, seeds) -> dict:
    """Per seed (mean over conditions): the final controllers' action entropy, the demos'
    controller's, their gap, the demos' mean log-likelihood and the success of 20 noisy samples
    (time-smoothed noise as in GPS; and white). ``controller``: fields [S, C, T, ...]."""
    from diffgcl.eval.controllers import distribution_fit

    keys = jnp.stack([jax.random.PRNGKey(200_000 + int(s)) for s in seeds])
    fit = jax.jit(
        jax.vmap(lambda c, k: distribution_fit(env, c, demos.controller, demos.X, demos.U, k))
    )(controller, keys)
    per_seed = {f.name: np.asarray(getattr(fit, f.name)).mean(-1) for f in fields(fit)}
    out = {k: v.round(4).tolist() for k, v in per_seed.items()}
    out["entropy_gap_nats_mean"] = float(per_seed["entropy_gap"].mean())
    out["sample_success_rate"] = float(per_seed["sample_success"].mean())
    out["sample_success_rate_white"] = float(per_seed["sample_success_white"].mean())
    out["demo_log_likelihood_mean"] = float(per_seed["demo_log_likelihood"].mean())
    return out


def write_run_folder(out: Path, result: RunResult, env, demos: DemoBatch, extra=None) -> dict:
    """config.json, metrics.json, metrics.csv, summary.json and the plots of a run in ``out``."""
    from diffgcl.algorithms.rgcl import make_network
    from diffgcl.viz import plots

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(result.config.to_dict(), indent=1, default=str))
    m = result.metrics
    summary = run_summary(result, env, demos)
    X_final = summary.pop("final_rollouts")
    if extra:
        summary.update(extra)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    series = {
        "true_cost": m.gps.cost[:, :, :, 0],
        "learned_cost": m.learned_cost[:, :, :, 0],
        "step_mult": m.gps.step_mult[:, :, :, 0],
        "entropy": m.gps.entropy[:, :, :, 0],
        "success": m.gps.success[:, :, :, 0],
        "sample_success": m.gps.sample_success[:, :, :, 0],
        "demo_log_likelihood": m.demo_log_likelihood[:, :, :, 0],
    }
    (out / "metrics.json").write_text(
        json.dumps(
            {
                "seeds": result.seeds,
                "shape": "[seed, rGCL iteration, GPS iteration], condition 0",
                **{k: np.asarray(v).tolist() for k, v in series.items()},
                "gcl_loss": m.gcl.loss.tolist(),
                "demo_learned_cost": m.demo_learned_cost[:, :, 0].tolist(),
                "log_temperature": m.log_temperature.tolist(),
                "rolled_back": m.rolled_back.tolist(),
            }
        )
    )
    with open(out / "metrics.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["seed", "iteration", "gps_iteration", *series, "gcl_loss", "rolled_back"])
        S, I, G = series["true_cost"].shape
        for s in range(S):
            for i in range(I):
                for g in range(G):
                    row = [float(series[k][s, i, g]) for k in series]
                    w.writerow(
                        [result.seeds[s], i + 1, g + 1, *row, float(m.gcl.loss[s, i])]
                        + [bool(m.rolled_back[s, i])]
                    )
    if result.state.policy is not None:
        summary.update(write_policies(out, result, env))
        (out / "summary.json").write_text(json.dumps(summary, indent=1))
    network = make_network(result.config, env)
    params0 = jax.tree.map(lambda a: jnp.asarray(a[0]), result.state.cost.params)
    from diffgcl.control.lqr import controller_entropy

    demo_entropy = float(controller_entropy(jax.tree.map(lambda a: a[0], demos.controller)))
    plots.learning_curves(
        m, out / "learning_curves.png", f"rGCL {result.config.schedule}", demo_entropy
    )
    plots.arm_motion(env, m.sample_X[0], X_final[0, 0], out / "arm_motion.png")
    plots.cost_landscape(env, network, params0, np.asarray(demos.X[0]), out / "cost_landscape.png")
    return summary


# ---- demos and saved runs ----------------------------------------------------------------------


def load_demo_batch(path: Path | None, env):
    """The demos at ``path`` (a DemoSet folder) or the built-in ones for ``env``'s task, as a
    DemoBatch; demos of another env, horizon or state size are a one-line error."""
    from diffgcl.algorithms.expert import builtin_demos
    from diffgcl.algorithms.rgcl import demo_batch
    from diffgcl.data.demos import DemoError, DemoSet

    demos = builtin_demos(env) if path is None else DemoSet.load(path)
    where = "built-in demos" if path is None else str(path)
    expected = (env.horizon + 1, env.dX)
    if demos.env != env.name or demos.X.shape[1:] != expected or demos.U.shape[2] != env.dU:
        raise DemoError(
            f"{where}: demos of env {demos.env!r} with X{demos.X.shape}, U{demos.U.shape}; the "
            f"{env.name} env needs X[N, {expected[0]}, {expected[1]}], U[N, {env.horizon}, "
            f"{env.dU}]"
        )
    return demo_batch(demos, int(np.asarray(env.initial_states()).shape[0]), env=env)


RUN_ENV = "env.json"


def write_run_env(out: Path, env, options: dict, demos: Path | None) -> None:
    """Record in a run folder the env a run trains on (its name, the options it was made with,
    the task's fingerprint) and the demo folder (None: the built-in demos), for ``eval`` and
    ``plot``."""
    from diffgcl.algorithms.expert import task_fingerprint

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    record = {
        "name": env.name,
        "options": options,
        "demos": None if demos is None else str(demos),
        "task": task_fingerprint(env),
    }
    (out / RUN_ENV).write_text(json.dumps(record, indent=1))


def read_run_env(run_dir: Path) -> dict:
    """What :func:`write_run_env` recorded (``{}`` for a run folder without it: the default
    arm and the built-in demos)."""
    path = Path(run_dir) / RUN_ENV
    return json.loads(path.read_text()) if path.is_file() else {}


def _with_tuples(d: dict) -> dict:
    """``d`` with its lists made tuples: JSON has no tuples, and every sequence field of the
    configs is one (hashable, as a jitted program's static argument must be)."""
    return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}


def config_from_dict(d: dict):
    """Inverse of ``RGCLConfig.to_dict`` (for run folders), also after a JSON round trip."""
    from diffgcl.algorithms.gps import GPSConfig
    from diffgcl.algorithms.rgcl import RGCLConfig
    from diffgcl.costs.gcl import GCLConfig
    from diffgcl.costs.network import CostNetworkConfig

    d = dict(d)
    return RGCLConfig(
        gps=GPSConfig(**_with_tuples(d.pop("gps"))),
        network=CostNetworkConfig(**_with_tuples(d.pop("network"))),
        gcl=GCLConfig(**_with_tuples(d.pop("gcl"))),
        policy=policy_settings_from_dict(d.pop("policy", None)),
        **_with_tuples(d),
    )


def policy_settings_from_dict(d: dict | None):
    """Inverse of ``dataclasses.asdict`` of a :class:`~diffgcl.algorithms.mdgps.PolicySettings`
    (None stays None)."""
    if d is None:
        return None
    from diffgcl.algorithms.mdgps import PolicySettings
    from diffgcl.policies.mdgps import SStepConfig
    from diffgcl.policies.network import PolicyConfig

    d = dict(d)
    return PolicySettings(
        network=PolicyConfig(**_with_tuples(d.pop("network"))),
        s_step=SStepConfig(**_with_tuples(d.pop("s_step"))),
        **_with_tuples(d),
    )


class RunFolderError(ValueError):
    """A folder given as a run folder that ``train`` did not write."""


def load_run(run_dir: Path, env):
    """(config, RunResult, DemoBatch) of a run folder written by ``train``."""
    run_dir = Path(run_dir)
    missing = [name for name in ("config.json", CHECKPOINT) if not (run_dir / name).is_file()]
    if missing:
        raise RunFolderError(
            f"{run_dir}: not a run folder of `diffgcl train` (no {' or '.join(missing)})"
        )
    config = config_from_dict(json.loads((run_dir / "config.json").read_text()))
    with np.load(run_dir / CHECKPOINT) as f:
        seeds = [int(s) for s in f["seeds"]]
    demo_dir = read_run_env(run_dir).get("demos")
    demos = load_demo_batch(Path(demo_dir) if demo_dir else None, env)
    rgcl = make_train(config, env)
    S = len(seeds)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    key_init, key_loop = jax.vmap(rgcl.split_key)(keys)
    hp = jax.tree.map(lambda a: jnp.broadcast_to(a, (S,)), rgcl.default_hparams())
    state_like, m_like = checkpoint_like(rgcl, key_init, key_loop, demos, hp)
    state, metrics, done, _ = _load_checkpoint(run_dir / CHECKPOINT, state_like, m_like)
    return config, RunResult(state=state, metrics=metrics, seeds=seeds, config=config), demos
