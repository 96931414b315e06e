"""The USV pipeline end to end: :func:`run_usv` and its configuration (:class:`UsvRunConfig`).

Bags' demos (ingested, world frame) → hull identification (:func:`identify_hull`) → task windows
and the task env (:mod:`diffgcl.usv.task`) → rGCL + MDGPS on the identified hull, retraining
seeds that warn (:mod:`diffgcl.usv.retraining`), and the references (MDGPS with the hand-written
cost, behaviour cloning) → every policy rolled out from held-out situations on the true hull with
sensor noise (:mod:`diffgcl.usv.evaluation`) and scored against the demos
(:mod:`diffgcl.usv.scores`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.data.demos import DemoSet
from diffgcl.envs.usv import COURSE_RESIDUAL_NAMES, UsvEnv, two_pole_env
from diffgcl.sim import hull as hull_sim
from diffgcl.usv.bags import pole_radii
from diffgcl.usv.evaluation import SituationRanges, heldout_starts, policy_tracks
from diffgcl.usv.retraining import SENSOR_NOISE_FOLD, train_retrying_warned, training_key
from diffgcl.usv.scores import per_seed_figures, score_rollouts
from diffgcl.usv.task import (
    UsvTaskConfig,
    demo_batch_pooled,
    make_task_env,
    task_margins,
    task_tails,
    task_windows,
    usv_demo_set,
    window_states,
)

METHODS = ("rgcl", "expert", "bc")


@dataclass(frozen=True)
class UsvRunConfig:
    """One run of the USV pipeline.

    task: :class:`UsvTaskConfig`; rgcl: the rGCL + MDGPS settings (None:
    :func:`~diffgcl.algorithms.presets.usv`); methods: of :data:`METHODS` — ``rgcl`` (learned cost +
    MDGPS), ``expert`` (MDGPS with the hand-written cost, ``expert_iterations`` iterations at its
    own KL step ``expert_kl_step`` and ``expert_max_step_mult``, with which it was measured; a fixed
    cost takes larger steps than a learned one that moves every iteration), ``bc`` (behaviour
    cloning on the recorded observations); seeds: training seeds (vmapped); heldout: number of
    held-out situations (drawn with ``heldout_seed``), each rolled out for the window's horizon plus
    ``eval_extra`` steps (to judge the return); identify: fit the hull to the demos (else the
    nominal hull); sysid: its settings; retrain_warned: how many more times a training seed of
    ``rgcl`` is trained, each time with a new key, while its local controllers or its policy warn on
    their own training starts (:func:`train_retrying_warned`; 0: warn only); wider: also judge
    every policy from ``heldout`` situations of wider ranges than the demos' (pole radius
    ``wider_radius``, the boat's offset ``wider_offset_scale`` × the demos' range;
    :meth:`SituationRanges.widened`), reported apart (``<method>.wider``); two_poles: also judge
    every policy from the held-out situations with a second pole on the course line
    ``two_pole_gap`` m beyond the first (:func:`~diffgcl.envs.usv.two_pole_env`, radius from the
    demos' range), reported apart (``<method>.two_poles``).
    """

    task: UsvTaskConfig = UsvTaskConfig()
    rgcl: object = None
    methods: tuple[str, ...] = METHODS
    seeds: tuple[int, ...] = (0,)
    heldout: int = 256
    heldout_seed: int = 1000
    eval_extra: int = 150
    expert_iterations: int = 15
    expert_kl_step: float = 1.0
    expert_max_step_mult: float = 10.0
    identify: bool = True
    sysid: object = None
    retrain_warned: int = 1
    wider: bool = True
    wider_radius: tuple[float, float] = (0.2, 1.5)
    wider_offset_scale: float = 1.5
    two_poles: bool = True
    two_pole_gap: tuple[float, float] = (120.0, 180.0)

    def __post_init__(self):
        unknown = set(self.methods) - set(METHODS)
        if unknown:
            raise ValueError(f"usv: unknown methods {sorted(unknown)}; choose from {METHODS}")
        if self.retrain_warned < 0:
            raise ValueError(f"usv: retrain_warned must be >= 0, not {self.retrain_warned}")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"usv: training seeds repeat: {list(self.seeds)}")


FAST_RGCL_OVERRIDES = (
    "iterations=6",
    "freeze_last=2",
    "gcl.pretrain_steps=100",
    "gcl.n_steps=20",
    "policy.s_step.n_steps=100",
)


def usv_rgcl(overrides=(), *, fast: bool = False):
    """The USV's rGCL settings: :func:`~diffgcl.algorithms.presets.usv` with ``overrides``
    (``"a.b=value"``, :func:`~diffgcl.algorithms.presets.with_overrides`), where ``cost=weighted``
    or ``cost=neural`` picks the learned cost's form (``neural``:
    :func:`~diffgcl.algorithms.presets.usv_neural`); ``fast``: with :data:`FAST_RGCL_OVERRIDES`
    before ``overrides``."""
    from diffgcl.algorithms.presets import usv as usv_preset
    from diffgcl.algorithms.presets import with_overrides

    cost, rest = "weighted", []
    for item in overrides:
        name, _, value = item.partition("=")
        if name.strip() == "cost":
            cost = value.strip()
        else:
            rest.append(item)
    config = usv_preset(cost)
    if fast:
        config = with_overrides(config, list(FAST_RGCL_OVERRIDES))
    return with_overrides(config, rest)


def fast_run_config(task: UsvTaskConfig | None = None, overrides=()) -> UsvRunConfig:
    """A run at smoke-test scale (``--fast`` of ``diffgcl usv`` and
    ``experiments/usv_avoidance.py``): ``task`` (default :class:`UsvTaskConfig`) with windows of
    240 steps (100 before the closest approach, 140 after, 40 trained past them), rGCL with
    :data:`FAST_RGCL_OVERRIDES` (6 iterations, the last 2 on a frozen cost, shorter GCL and
    S-step passes), 4 iterations of the hand-written cost's reference, 32 held-out situations
    and no retraining (6 iterations leave controllers off course: every seed would warn);
    ``overrides`` as :func:`usv_rgcl`'s."""
    import dataclasses

    task = dataclasses.replace(
        task if task is not None else UsvTaskConfig(), before=100, after=140, train_extra=40
    )
    rgcl = usv_rgcl(overrides, fast=True)
    return UsvRunConfig(task=task, rgcl=rgcl, heldout=32, expert_iterations=4, retrain_warned=0)


@dataclass
class UsvRun:
    """What :func:`run_usv` returns: ``summary`` (JSON-ready figures), the task env on the
    identified hull (``env``, demos' conditions; ``train_env`` the same with the training
    horizon, :attr:`UsvTaskConfig.training_horizon`) and on the true one (``env_true``, held-out
    starts ``x0_heldout``), the demos in the task layout, and per method its policy, parameters
    (leading seed axis) and held-out tracks [S, B, T+1, 11]; the rGCL state (``rgcl_state``)."""

    summary: dict
    env: UsvEnv
    env_true: UsvEnv
    demos: DemoSet
    x0_heldout: np.ndarray
    policies: dict
    tracks: dict
    rgcl_state: object = None
    rgcl: object = None
    train_env: UsvEnv | None = None


def _say(verbose: bool, text: str) -> None:
    if verbose:
        print(text, flush=True)


def run_over_seeds(fn, seeds, *args):
    """``fn(key, *args)`` jit-compiled and vmapped over the first training keys of ``seeds``
    (:func:`~diffgcl.usv.retraining.training_key`); returns its output as host arrays and the
    seconds it took (compile + run)."""
    import time

    keys = jnp.stack([training_key(s) for s in seeds])
    in_axes = (0,) + (None,) * len(args)
    t0 = time.perf_counter()
    out = jax.block_until_ready(jax.jit(jax.vmap(fn, in_axes=in_axes))(keys, *args))
    return jax.tree.map(np.asarray, out), time.perf_counter() - t0


def learned_cost_weights(network, params, names: tuple[str, ...]) -> dict:
    """The weighted-form cost per residual (``names``:
    :attr:`diffgcl.envs.usv.UsvEnv.cost_residual_names`; with the neural form's
    ``prior_residuals`` the course residuals and ``"network"``, its term), per training seed
    (``params`` with a leading seed axis): ``per_unit`` — its weight per squared unit of the
    residual (the network's: of its term), at the cost's temperature; ``log_w`` — the learned
    θ̃ (0 at the start, where every residual weighs 1 per squared RMS of the demos; their mean
    stays 0)."""
    w = np.asarray(jax.vmap(lambda p: network.feature_weights(p) * network.temperature(p))(params))
    theta = np.asarray(jax.vmap(network.log_weights)(params))
    return {
        name: {"per_unit": w[:, k].tolist(), "log_w": theta[:, k].tolist()}
        for k, name in enumerate(names)
    }


WIDER_FOLD = 77  # the wider situations' draw: fold_in(PRNGKey(heldout_seed), WIDER_FOLD)
TWO_POLES_FOLD = 78  # the second poles' draw


def gcl_diagnostics(metrics) -> dict:
    """Per rGCL iteration, mean over seeds (lists [iterations]): the cost update's effective sample
    size of the partition's weights (``gcl_ess``) and their tempering exponent (``gcl_tempering``,
    1 when untempered: ``GCLConfig.min_ess``), the learned trajectory cost (over the demos'
    window) of the demos and of the iteration's GPS samples under the cost after that
    iteration's update, and how much dearer the samples are (``sample_excess``; a cost that no
    longer tells them apart has it near 0)."""
    demo = np.asarray(metrics.demo_learned_cost, np.float64)  # [S, I, C]
    samples = np.asarray(metrics.learned_cost, np.float64)  # [S, I, G, C]
    demo_mean = demo.mean(axis=(0, 2))
    sample_mean = samples.reshape(*samples.shape[:2], -1).mean(axis=(0, 2))
    ess = np.asarray(metrics.gcl.ess, np.float64).reshape(demo.shape[0], demo.shape[1], -1)
    tempering = np.asarray(metrics.gcl.tempering, np.float64).reshape(ess.shape)
    return {
        "gcl_ess": ess.mean(axis=(0, 2)).tolist(),
        "gcl_tempering": tempering.mean(axis=(0, 2)).tolist(),
        "demo_learned_cost": demo_mean.tolist(),
        "sample_learned_cost": sample_mean.tolist(),
        "sample_excess": (sample_mean - demo_mean).tolist(),
        "cost_updated": np.asarray(metrics.cost_updated).reshape(demo.shape[0], -1).any(0).tolist(),
    }


def c_step_diagnostics(metrics) -> dict:
    """Per training seed and rGCL iteration (lists [seeds][iterations]), over the conditions
    (and the iteration's inner C-steps): the median and largest true cost of the samples
    (``true_cost_median``, ``true_cost_max``; a seed whose controllers diverge shows here
    alone, where ``true_cost_per_iteration`` averages it with the others), the mean step
    multiplier, the median KL the C-step reached over its target (``kl_over_target``; near 1
    when the η search met the constraint) and how many C-steps failed (``c_step_failed``)."""
    gps = metrics.gps

    def per_seed(a, reduce):
        a = np.asarray(a, np.float64)
        return reduce(a.reshape(*a.shape[:2], -1), axis=2).tolist()

    ratio = np.asarray(gps.kl, np.float64) / np.maximum(np.asarray(gps.epsilon, np.float64), 1e-30)
    return {
        "true_cost_median": per_seed(gps.cost, np.median),
        "true_cost_max": per_seed(gps.cost, np.max),
        "step_mult": per_seed(gps.step_mult, np.mean),
        "kl_over_target": per_seed(ratio, np.median),
        "c_step_failed": per_seed(gps.c_step_failed, np.sum),
    }


def identify_hull(demos: DemoSet, config=None, truth=None) -> tuple[object, dict]:
    """The hull identified from ``demos`` (:func:`diffgcl.data.sysid.identify`) and a summary:
    the fitted values and, given the ``truth``, the largest relative error."""
    from diffgcl.data.sysid import identify

    result = identify(demos, config)
    info = {"fitted": result.values()}
    if truth is not None:
        errors = result.relative_errors(truth)
        info["relative_errors"] = errors
        info["max_relative_error"] = max(errors.values())
    return result.params, info


def run_usv(
    demos: DemoSet,
    config: UsvRunConfig = UsvRunConfig(),
    *,
    manifest: Path | None = None,
    true_params=None,
    verbose: bool = True,
) -> UsvRun:
    """Bags' demos (ingested, world frame) → hull identification → task windows → rGCL + MDGPS on
    the identified hull, the references (:data:`METHODS`) → every policy rolled out from held-out
    situations on ``true_params`` (default: the identified hull) with sensor noise, scored by
    :func:`score_rollouts` against the demos. ``manifest``: a synthetic set's truth (pole radii).
    """
    import dataclasses
    import time

    from diffgcl.algorithms.presets import usv as usv_preset

    t_start = time.perf_counter()
    task = config.task
    rgcl_config = config.rgcl if config.rgcl is not None else usv_preset()
    summary: dict = {
        "sets": list(task.sets),
        "observation": task.observation,
        "range_encoding": task.range_encoding,
    }

    windows = task_windows(demos, task)
    radii = pole_radii(windows, task.default_pole_radius, manifest)
    summary["conditions"] = windows.num_episodes
    summary["horizon"] = task.horizon
    _say(verbose, f"{windows.num_episodes} demo windows of {task.horizon} steps (sets {task.sets})")

    if config.identify:
        chosen = [i for i, e in enumerate(demos.episodes) if str(e.get("set")) in task.sets]
        params, info = identify_hull(demos.subset(np.asarray(chosen)), config.sysid, true_params)
        summary["hull_identification"] = info
        _say(
            verbose,
            f"hull identified: {info.get('max_relative_error', float('nan')):.3f} "
            "largest relative error",
        )
    else:
        params = hull_sim.default_params()
    truth = true_params if true_params is not None else params

    # The margins once, for every env of the run (each would measure the demos' clearance again).
    task = dataclasses.replace(task, proximity_margins=task_margins(windows, radii, params, task))
    env = make_task_env(windows, radii, params, task)
    train_env = make_task_env(windows, radii, params, task, horizon=task.training_horizon)
    task_demos = usv_demo_set(env, windows, radii)
    needs_dynamics = rgcl_config.temperature != "likelihood" and "rgcl" in config.methods
    tails = task_tails(demos, task) if rgcl_config.gcl.reads_tails else None
    if tails is not None:
        summary["demo_tail"] = task.tail
    batch = demo_batch_pooled(
        task_demos,
        env=env if needs_dynamics else None,
        tail=None if tails is None else window_states(tails, radii),
    )
    ranges = SituationRanges.of(task_demos, radius=(float(radii.min()), float(radii.max())))
    probe = make_task_env(windows, radii, truth, task, horizon=task.horizon + config.eval_extra)
    x0_heldout = np.asarray(
        heldout_starts(probe, ranges, jax.random.PRNGKey(config.heldout_seed), config.heldout)
    )
    env_true = dataclasses.replace(probe, x0=jnp.asarray(x0_heldout, probe.x0.dtype))
    wider = None
    if config.wider:
        wide = ranges.widened(config.wider_radius, config.wider_offset_scale)
        key_wide = jax.random.fold_in(jax.random.PRNGKey(config.heldout_seed), WIDER_FOLD)
        # Rolled out and judged by env_true (the same hull, horizon and metrics; its staged
        # simulator's programs serve both): only the starts differ.
        wider = (np.asarray(heldout_starts(probe, wide, key_wide, config.heldout)), wide)
    demo_score = score_rollouts(env, task_demos.X, task_demos.X)
    summary["demos"] = {
        k: demo_score[k]
        for k in (
            "episodes",
            "collision_rate",
            "return_to_course_rate",
            "returned_in_window_rate",
            "min_clearance_median_m",
            "port_share",
        )
    }
    summary["proximity_margins"] = list(env.proximity_margins)
    summary["evaluation_horizon"] = task.horizon + config.eval_extra
    if wider is not None:
        summary["wider_situations"] = dataclasses.asdict(wider[1])
    env_two = None
    if config.two_poles:
        key_two = jax.random.fold_in(jax.random.PRNGKey(config.heldout_seed), TWO_POLES_FOLD)
        env_two = two_pole_env(
            env_true, jnp.asarray(x0_heldout), config.two_pole_gap, ranges.radius, key_two
        )
        summary["two_pole_gap_m"] = list(config.two_pole_gap)
    summary["training_horizon"] = task.training_horizon
    run = UsvRun(summary, env, env_true, task_demos, x0_heldout, {}, {}, train_env=train_env)
    eval_key = jax.random.PRNGKey(config.heldout_seed + 1)

    def judge(name: str, policy, params) -> None:
        keys = jnp.stack([jax.random.fold_in(eval_key, s) for s in range(len(config.seeds))])
        params_j = jax.tree.map(jnp.asarray, params)

        def scored(judge_env, x0, demo_env=None):
            tracks = policy_tracks(judge_env, policy, params_j, x0, keys)
            flat = tracks.reshape(-1, *tracks.shape[2:])
            score = score_rollouts(judge_env, flat, task_demos.X, demo_env=demo_env)
            score["per_seed"] = per_seed_figures(
                judge_env, tracks, score["demo_min_clearance_median_m"]
            )
            return tracks, score

        tracks, score = scored(env_true, x0_heldout)
        run.policies[name] = (policy, params)
        run.tracks[name] = tracks
        if wider is not None:
            _, wide = scored(env_true, wider[0])
            score["wider"] = wide
        if env_two is not None:
            _, two = scored(env_two, np.asarray(env_two.x0), demo_env=env_true)
            score["two_poles"] = two
        summary[name] = {**summary.get(name, {}), **score}
        _say(
            verbose,
            f"  {name}: collisions {score['collision_rate']:.2f}, back on course "
            f"{score['return_to_course_rate']:.2f}, clearance {score['min_clearance_median_m']:.1f}"
            f" m (demos {score['demo_min_clearance_median_m']:.1f} m), path to demos "
            f"{score['path_distance_to_demos_median_m']:.1f} m",
        )
        for key, label in (("two_poles", "two poles"), ("wider", "wider situations")):
            if key in score:
                row = score[key]
                _say(
                    verbose,
                    f"  {name}, {label}: collisions {row['collision_rate']:.2f}, back on course "
                    f"{row['return_to_course_rate']:.2f}, clearance "
                    f"{row['clearance_ratio_vs_demos']:.2f}× the demos'",
                )

    if "rgcl" in config.methods:
        from diffgcl.algorithms.rgcl import make_train
        from diffgcl.algorithms.staged import noise_free_rollouts, run_rgcl

        _say(verbose, f"rGCL + MDGPS on the identified hull, seeds {list(config.seeds)}")
        rgcl = make_train(rgcl_config, train_env)

        def train_seeds(keys):
            state, metrics = jax.block_until_ready(run_rgcl(rgcl, keys, batch, train_env))
            Xc, _ = noise_free_rollouts(train_env, state.gps.controller, state.gps.x0)
            # The policy from the same starts, its sensor noise drawn from the training key.
            sensor_keys = jax.vmap(lambda k: jax.random.fold_in(k, SENSOR_NOISE_FOLD))(keys)
            x0 = train_env.initial_states()
            Xp = policy_tracks(train_env, policy, state.policy.params, x0, sensor_keys)
            return jax.tree.map(np.asarray, (state, metrics)), Xc, Xp

        policy = rgcl.policy_phases.policy
        (state, metrics), Xc, Xp, per_seed, seconds, record = train_retrying_warned(
            train_seeds,
            lambda X: per_seed_figures(env, X, demo_score["demo_min_clearance_median_m"]),
            config.seeds,
            task_demos.num_episodes,
            config.retrain_warned,
            say=lambda text: _say(verbose, f"  {text}"),
        )
        on_starts = {}
        for name, X in (("controllers", Xc), ("policy", Xp)):
            on_starts[name] = score_rollouts(env, X.reshape(-1, *X.shape[2:]), task_demos.X)
            on_starts[name]["per_seed"] = per_seed[name]  # the kept attempts'
        kept = {seed: r["attempts"][r["kept"]] for seed, r in record.items()}
        summary["rgcl"] = {
            "seconds": seconds,
            "controllers_on_demo_starts": on_starts["controllers"],
            "policy_on_demo_starts": on_starts["policy"],
            "true_cost_per_iteration": np.asarray(metrics.gps.cost).mean((0, 2)).tolist(),
            "learning": gcl_diagnostics(metrics),
            "c_steps": c_step_diagnostics(metrics),
            "warnings": {str(seed): a["warning"] for seed, a in kept.items() if a["warning"]},
            "attempts": {str(seed): r for seed, r in record.items()},
        }
        names = None
        if rgcl.network.config.form == "weighted" and rgcl_config.network.features == "env":
            names = env.cost_residual_names
        elif rgcl.network.config.prior_residuals:
            names = (*COURSE_RESIDUAL_NAMES, "network")
        if names is not None:
            summary["rgcl"]["cost_weights"] = learned_cost_weights(
                rgcl.network, state.cost.params, names
            )
        if rgcl.network.config.barrier_margins:  # per seed, m
            margins = jax.vmap(rgcl.network.barrier_margins)(state.cost.params)
            summary["rgcl"]["barrier_margins"] = np.asarray(margins).tolist()
        run.rgcl_state, run.rgcl = state, rgcl
        judge("rgcl", rgcl.policy_phases.policy, state.policy.params)

    if "expert" in config.methods:
        from diffgcl.algorithms.mdgps import MDGPSConfig, make_mdgps
        from diffgcl.algorithms.staged import run_gps_seeds

        _say(verbose, "MDGPS with the hand-written cost (reference)")
        gps = dataclasses.replace(
            rgcl_config.gps,
            iterations=config.expert_iterations,
            kl_step=config.expert_kl_step,
            max_step_mult=config.expert_max_step_mult,
            maxent=False,
            gauss_newton=False,
        )
        md = make_mdgps(
            MDGPSConfig(gps=gps, policy=rgcl_config.policy), train_env, train_env.expert_cost
        )
        t0 = time.perf_counter()
        keys = jnp.stack([training_key(s) for s in config.seeds])
        state, _, _ = run_gps_seeds(md, keys, gps.iterations, train_env)
        seconds = time.perf_counter() - t0
        summary["expert"] = {"seconds": seconds}
        judge("expert", md.policy_phases.policy, state.policy.params)

    if "bc" in config.methods:
        from diffgcl.algorithms.bc import BCConfig, make_bc

        _say(verbose, "behaviour cloning on the recorded observations (baseline)")
        dtype = env.x0.dtype
        policy, fit = make_bc(BCConfig(network=rgcl_config.policy.network), env.dO, env.dU, dtype)
        O, U, mask = (jnp.asarray(a, dtype) for a in (task_demos.O, task_demos.U, task_demos.mask))
        (state, _), seconds = run_over_seeds(lambda k: fit(k, O, U, mask), config.seeds)
        summary["bc"] = {"seconds": seconds}
        judge("bc", policy, state.params)

    summary["wall_seconds"] = time.perf_counter() - t_start
    return run
