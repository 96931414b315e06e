"""Your own robot in ten lines: learn a cost and a controller from demonstrations of any MJCF model.

    from diffgcl import api

    env = api.load_model("my_robot.xml", success=reached)  # your test is optional
    demos = api.load_demos("demos.npz", env)  # qpos, qvel, ctrl per episode
    run = api.learn(env, demos, policy=True)  # rGCL (`default`) + MDGPS
    rollout = run.policy_rollout(new_starts)  # the global policy from any states
    print(run.report()["policy"]["success_rate"], rollout.ctrl.shape)
    run.save("runs/my_robot")  # report, controllers, cost, policy, plot

What :func:`learn` decides for a model it has never seen (``docs/your_robot.md``):

* conditions: the demos' start states (episodes grouped by their ``condition`` label, or by equal
  start states when they carry none), the horizon: the demos' length;
* actions scaled by the control range (:func:`load_model` builds the env with
  ``action_scale="range"``), so GPS's exploration variance ``init_var`` and the cost's action
  weight are fractions of each actuator's range, whatever its units;
* the cost: the ``default`` preset's quadratic in the state and the observation's site, body and
  sensor parts (:meth:`~diffgcl.envs.mjcf_env.MJCFEnv.cost_features`; ``network.features="env"``
  when there are any), each normalised by the demos' mean and standard deviation
  (:class:`~diffgcl.costs.network.CostNetwork`).

With ``policy=True`` rGCL trains a global policy on the env's observations alongside (MDGPS,
:mod:`diffgcl.algorithms.mdgps`; ``RGCLConfig.policy``): it acts from any start state, where the
local controllers only serve the demos' own.

What :meth:`LearnedRun.report` gives without a user's cost or test: the learned cost of the
controllers' rollouts and of the demos, the distance of the rollouts to the demos (root mean
square over time and state dimensions, in units of the demos' standard deviation per dimension),
the controllers' action entropy beside the demos' own, and the re-optimisation check — a fresh
GPS run on the frozen learned cost, its distance to the demos and to the rGCL controllers'
rollouts. With a success test and a true cost (``success=``, ``cost=`` of :func:`load_model`)
it adds success rates and true costs for both.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.data.demos import DemoError, DemoSet
from diffgcl.envs.mjcf_env import MJCFEnv, make_mjcf_env
from diffgcl.types import Array, CostFn

RUN_FORMAT = "diffgcl-mjcf-run/1"
RUN_FILES = ("run.json", "config.json", "report.json", "learned.npz", "learning_curves.png")


def load_model(
    mjcf: str | os.PathLike,
    *,
    success: Callable[[Array], Array] | None = None,
    cost: CostFn | None = None,
    **options,
) -> MJCFEnv:
    """The generic env of an MJCF file with actions scaled by the control range (see
    :func:`~diffgcl.envs.mjcf_env.make_mjcf_env` for ``options``: ``obs``, ``dt``, ``keyframe``,
    ...). ``success(X: [T+1, dX]) -> bool`` and ``cost(x, u, t)`` are optional, for reports."""
    options.setdefault("action_scale", "range")
    return make_mjcf_env(mjcf, success=success, cost=cost, **options)


def load_demos(source, env: MJCFEnv, **options) -> DemoSet:
    """Demos for ``env``: an npz file or dataset folder (a path), or a list of ``(obs, acts)``
    pairs / imitation trajectories (:mod:`diffgcl.data.mujoco_demos`)."""
    from diffgcl.data.mujoco_demos import demos_from_trajectories, load_demos

    if isinstance(source, str | os.PathLike):
        return load_demos(source, env, **options)
    return demos_from_trajectories(source, env, **options)


def expert_demos(
    env: MJCFEnv,
    cost: CostFn | None = None,
    x0=None,
    *,
    per_start: int = 5,
    noise_var: float | None = 0.01,
    temperature: float | None = None,
    gps_iterations: int = 0,
    seed: int = 0,
    path: str | os.PathLike | None = None,
    ilqr=None,
    restarts: bool = False,
    initial: str | None = None,
    shooting: bool = False,
    verbose: bool = True,
) -> DemoSet:
    """Demonstrations for a user with a cost and no demos (:mod:`diffgcl.algorithms.trajopt`).

    iLQR on ``cost`` (default: the env's ``cost=``) from each start state ``x0: [C, dX]``
    (default: the env's conditions; with ``restarts`` the best of iLQR from zero actions and
    from a small constant action either way on each actuator,
    :func:`diffgcl.algorithms.trajopt.solve_restarts`; else from ``initial``, by default
    ``"best"``: iLQR from zero actions and from the goal's LQR, keeping per start the cheaper
    solution, so that an unstable system is balanced rather than left to fall (the dearer run
    stops once the other has finished cheaper after as many iterations);
    ``"zeros"`` or ``"goal_lqr"`` runs one of them, see
    :func:`diffgcl.algorithms.trajopt.solve`; with ``shooting`` also multiple shooting from
    the straight line of states to the goal, the joints' ranges kept by a barrier, and per start
    the cheaper of it and iLQR, :func:`diffgcl.algorithms.trajopt.solve_shooting`: for an
    unstable system on a short rail, where every rollout iLQR starts from falls — of the
    tilted double pendulum's starts iLQR drops it catches 3 of 7 on the seeds it was tuned on
    and 3 of 7 on seeds never looked at; it costs another compile, and both solvers then go one
    start at a time on a CPU), then ``per_start`` noisy rollouts of
    each solution's closed-loop controller ``u ~ N(K x + k, Σ_t)``, white noise. ``Σ_t`` has the
    shape of ``(Q_uu,t + μI)⁻¹`` — the demonstrator varies most where the cost-to-go is flattest
    — and a mean variance of ``noise_var`` in the normalised actions (0.01: a standard deviation
    of a tenth of each actuator's range), whatever the cost's scale. With ``temperature``
    instead, ``Σ_t = temperature · (Q_uu,t + μI)⁻¹``: the maximum-entropy demonstrator of the
    cost linearised about the solution (GCL's model of an expert; at temperature 1 it is as
    broad as the cost's own scale makes it, which for a cost of a few units over the horizon is
    far broader than the task allows). With ``gps_iterations`` GPS refines the iLQR controllers
    first (its samples' noise then comes from GPS). ``path``: also write the npz format of
    :mod:`diffgcl.data.mujoco_demos` (ctrl clamped to the control ranges, as MuJoCo applies it).
    ``ilqr``: an :class:`~diffgcl.control.ilqr.ILQRConfig`. Episodes' metadata:
    ``source="ilqr-expert"``, the condition, and the noise-free solution's ``ilqr_status``,
    ``ilqr_cost`` and (with the env's success test) ``solution_success``. A start whose solution
    fails the test is reported.

    Precision: run it with ``jax_enable_x64`` for a model with joint limits or contacts; in
    float32 the derivatives through MuJoCo's iterative constraint solver are too noisy for the
    line search (gymnasium's reacher: 2 of 8 starts stuck at the elbow's limit in float32, none
    in float64). For a model whose vmapped programs hang in LAPACK, load it with
    ``lapack_free=True``.
    """
    from diffgcl.algorithms import trajopt
    from diffgcl.control.ilqr import STATUS_NAMES, ILQRConfig
    from diffgcl.data.mujoco_demos import demos_from_arrays, save_npz

    if cost is None:
        if not env.has_cost:
            raise ValueError("expert_demos: give a cost (or load_model(..., cost=...))")
        cost = env.expert_cost
    if int(per_start) < 1:
        raise ValueError(f"expert_demos: per_start must be >= 1, got {per_start}")
    if temperature is None and (noise_var is None or noise_var <= 0):
        raise ValueError("expert_demos: give a positive noise_var or a temperature")
    if temperature is not None and temperature <= 0:
        raise ValueError(f"expert_demos: temperature must be > 0, got {temperature}")
    init_var = None if temperature is not None else float(noise_var)
    temp = 1.0 if temperature is None else float(temperature)
    if x0 is not None:
        env = env.with_conditions(x0)
    X0 = env.initial_states()
    config = ILQRConfig() if ilqr is None else ilqr
    initial = trajopt.EXPERT_INITIAL if initial is None else initial
    solve = jax.jit(
        lambda x: trajopt.ilqr_controllers(
            env,
            cost,
            x,
            config=config,
            init_var=init_var,
            temperature=temp,
            restarts=restarts,
            initial=initial,
            shooting=shooting,
        )
    )
    ctrl, result = solve(X0)
    if gps_iterations:
        from diffgcl.algorithms.gps import GPSConfig
        from diffgcl.control.ilqr import ilqr_controller

        gps_config = GPSConfig(iterations=int(gps_iterations))
        train = trajopt.make_gps_from(gps_config, env, cost, x0=X0)
        start = jax.vmap(lambda r: ilqr_controller(r, init_var=gps_config.init_var))(result)
        ctrl = jax.jit(train)(jax.random.PRNGKey(seed), start)[0].controller
    key = jax.random.PRNGKey(10_000 + seed)
    X, U, condition = jax.jit(
        lambda c, x, k: trajopt.expert_rollouts(env, c, x, k, int(per_start))
    )(ctrl, X0, key)
    r = rollout_arrays(env, X, U)
    applied = np.clip(r.ctrl, env.ctrl_range[:, 0], env.ctrl_range[:, 1])
    condition = np.asarray(condition)
    demos = demos_from_arrays(env, r.qpos, r.qvel, applied, condition=condition,
                              source="ilqr-expert")  # fmt: skip
    status = [STATUS_NAMES[int(s)] for s in np.asarray(result.status)]
    solved = np.asarray(jax.vmap(env.success)(result.X)) if env.has_success else None
    episodes = tuple(
        dict(e)
        | {"seed": int(seed), "ilqr_status": status[c], "ilqr_cost": float(result.cost[c])}
        | ({} if solved is None else {"solution_success": bool(solved[c])})
        for e, c in zip(demos.episodes, condition, strict=True)
    )
    demos = dataclasses.replace(demos, episodes=episodes)
    if verbose:
        for c in range(X0.shape[0]):
            if solved is not None and not solved[c]:
                print(f"expert_demos: start {c}: the iLQR solution fails the success test "
                      f"({status[c]}, cost {float(result.cost[c]):.6g})")  # fmt: skip
    if path is not None:
        save_npz(path, r.qpos, r.qvel, applied, condition=condition, dt=env.dt)
    return demos


def demo_conditions(demos: DemoSet, atol: float = 1e-6) -> tuple[np.ndarray, DemoSet]:
    """Start states ``x0: [C, dX]`` and the demos labelled with their condition.

    Episodes with a ``condition`` label keep it (x0: the mean start state of each); without
    labels, episodes whose start states agree within ``atol`` (relative to the largest start
    state entry) share a condition, numbered in order of first appearance.
    """
    X0 = np.asarray(demos.X[:, 0], float)
    labels = [e.get("condition") for e in demos.episodes] if demos.episodes else []
    if labels and all(c is not None for c in labels):
        cond = np.asarray(labels, int)
        if set(cond.tolist()) != set(range(cond.max() + 1)):
            raise DemoError(
                f"demos: condition labels must be 0..C-1, got {sorted(set(cond.tolist()))}"
            )
    else:
        tol = atol * max(1.0, float(np.abs(X0).max()))
        starts: list[np.ndarray] = []
        cond = np.empty(len(X0), int)
        for i, x in enumerate(X0):
            match = [j for j, s in enumerate(starts) if np.abs(x - s).max() <= tol]
            if match:
                cond[i] = match[0]
            else:
                cond[i] = len(starts)
                starts.append(x)
    x0 = np.stack([X0[cond == c].mean(0) for c in range(cond.max() + 1)])
    old = demos.episodes or tuple({} for _ in range(demos.num_episodes))
    episodes = tuple(dict(e) | {"condition": int(c)} for e, c in zip(old, cond, strict=True))
    return x0, dataclasses.replace(demos, episodes=episodes)


@dataclasses.dataclass(frozen=True)
class Rollout:
    """Noise-free rollouts from each condition: X [C, T+1, dX], U [C, T, dU] (the env's states
    and actions) and MuJoCo's qpos [C, T+1, nq], qvel [C, T+1, nv], ctrl [C, T, nu]."""

    X: np.ndarray
    U: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    ctrl: np.ndarray


def rollout_arrays(env: MJCFEnv, X, U) -> Rollout:
    """:class:`Rollout` of states ``X: [..., T+1, dX]`` and actions ``U: [..., T, dU]``."""
    to_mj = jnp.vectorize(lambda x: env.mujoco_from_state(x)[:2], signature="(x)->(q),(v)")
    qpos, qvel = jax.jit(to_mj)(jnp.asarray(X))
    return Rollout(
        X=np.asarray(X),
        U=np.asarray(U),
        qpos=np.asarray(qpos),
        qvel=np.asarray(qvel),
        ctrl=np.asarray(env.ctrl_from_action(jnp.asarray(U))),
    )


def demo_distance(X: Array, demo_X: Array, scale: Array) -> Array:
    """Root mean square of ``(X − mean demo) / scale`` over time and state: X [T+1, dX], demo_X
    [N, T+1, dX], scale [dX] -> scalar (in demo standard deviations)."""
    return jnp.sqrt(jnp.mean(((X - demo_X.mean(0)) / scale) ** 2))


def state_scale(demo_X: np.ndarray) -> np.ndarray:
    """Per-dimension standard deviation of the demos' states [dX], floored at 1e-3 of the
    largest (a coordinate the demos never move does not blow up distances)."""
    std = np.asarray(demo_X, float).reshape(-1, demo_X.shape[-1]).std(0)
    return np.maximum(std, 1e-3 * max(float(std.max()), 1e-12))


@dataclasses.dataclass
class LearnedRun:
    """What :func:`learn` returns: the env with the demos' conditions and horizon, the rGCL
    config, the demos (labelled with conditions), the runner's result (leading axis seeds)."""

    env: MJCFEnv
    config: object
    demos: DemoSet
    result: object
    _report: dict | None = None

    @property
    def seeds(self) -> list[int]:
        return list(self.result.seeds)

    @property
    def cost_params(self):
        """Learned cost parameters (leading axis seeds)."""
        return self.result.state.cost.params

    @property
    def controllers(self):
        """Final local controllers, fields [S, C, T, ...]."""
        return self.result.state.gps.controller

    def network(self):
        from diffgcl.algorithms.rgcl import make_network

        return make_network(self.config, self.env)

    def learned_cost(self, seed_index: int = 0) -> CostFn:
        """The learned cost ``c(x, u, t)`` of one seed (a pure JAX function)."""
        params = jax.tree.map(lambda a: jnp.asarray(a[seed_index]), self.cost_params)
        return self.network().bind(params)

    @property
    def has_policy(self) -> bool:
        return self.result.state.policy is not None

    def policy_rollout(self, x0=None, seed_index: int = 0) -> Rollout:
        """Noise-free rollouts of one seed's global policy from ``x0: [B, dX]`` (default: the
        training conditions), ``env.horizon`` steps."""
        X, U = self.policy_rollouts(x0)
        return rollout_arrays(self.env, X[seed_index], U[seed_index])

    def policy_rollouts(self, x0=None) -> tuple[Array, Array]:
        """Every seed's global policy from ``x0: [B, dX]`` (default: the training conditions):
        X [S, B, T+1, dX], U [S, B, T, dU] (one compiled program per run)."""
        if not self.has_policy:
            raise ValueError("this run has no global policy; learn(..., policy=True) trains one")
        x0 = self.env.initial_states() if x0 is None else jnp.atleast_2d(jnp.asarray(x0))
        if x0.ndim != 2 or x0.shape[1] != self.env.dX:
            raise ValueError(f"policy_rollout: x0 must be [B, {self.env.dX}], got {x0.shape}")
        from diffgcl.algorithms.mdgps import policy_noise_free_rollouts

        params = jax.tree.map(jnp.asarray, self.result.state.policy.params)
        x0 = x0.astype(self.env.x0.dtype)
        traj = policy_noise_free_rollouts(self.config.policy, self.env, params, x0)
        return traj.X, traj.U

    def policy(self):
        """The :class:`~diffgcl.policies.network.GaussianPolicy` (parameters: the run's
        ``result.state.policy.params``, leading axis seeds)."""
        from diffgcl.algorithms.mdgps import make_policy

        return make_policy(self.config.policy, self.env)

    def rollout(self, seed_index: int = 0) -> Rollout:
        """Noise-free rollouts of one seed's final controllers from every condition."""
        X, U = self.controller_rollouts()
        return rollout_arrays(self.env, X[seed_index], U[seed_index])

    def controller_rollouts(self) -> tuple[Array, Array]:
        """Every seed's final local controllers from their conditions, noise-free: X [S, C, T+1,
        dX], U [S, C, T, dU] (the env's staged simulator, shared with the training's programs)."""
        return _noise_free(self.env, self.controllers)

    def report(self, *, reoptimise: bool = True) -> dict:
        """The run's report (module docstring), computed once."""
        if self._report is None or ("reoptimisation" not in self._report and reoptimise):
            self._report = _report(self, reoptimise)
        return self._report

    def save(self, folder: str | os.PathLike) -> Path:
        """Write the run into ``folder`` (created; an existing folder must be empty or an
        earlier run of this API, whose files alone are replaced): run.json, config.json,
        report.json, learned.npz (controllers, cost parameters, rollouts), learning_curves.png."""
        from diffgcl.viz import plots

        out = _run_folder(folder)
        report = self.report()
        r = self.rollout()
        leaves = jax.tree.leaves(self.cost_params)
        ctrl = self.controllers
        arrays = {
            "K": ctrl.K,
            "k": ctrl.k,
            "cov": ctrl.cov,
            "rollout_X": r.X,
            "rollout_U": r.U,
            "rollout_qpos": r.qpos,
            "rollout_qvel": r.qvel,
            "rollout_ctrl": r.ctrl,
            "x0": self.env.initial_states(),
            **{f"cost_param_{i}": a for i, a in enumerate(leaves)},
        }
        if self.has_policy:
            p = self.policy_rollout()
            arrays.update(
                {
                    f"policy_param_{i}": a
                    for i, a in enumerate(jax.tree.leaves(self.result.state.policy.params))
                }
            )
            arrays.update(policy_rollout_X=p.X, policy_rollout_ctrl=p.ctrl)  # fmt: skip
        np.savez_compressed(out / "learned.npz", **{k: np.asarray(v) for k, v in arrays.items()})
        (out / "config.json").write_text(json.dumps(self.config.to_dict(), indent=1, default=str))
        (out / "report.json").write_text(json.dumps(report, indent=1))
        env = self.env
        meta = {
            "format": RUN_FORMAT,
            "mjcf": env.mjcf_path,
            "env": env.name,
            "dt": env.dt,
            "horizon": env.horizon,
            "frame_skip": env.frame_skip,
            "ctrl_scale": None if env.ctrl_scale is None else np.asarray(env.ctrl_scale).tolist(),
            "conditions": int(env.initial_states().shape[0]),
            "demos": int(self.demos.num_episodes),
            "seeds": self.seeds,
        }
        (out / "run.json").write_text(json.dumps(meta, indent=1))
        plots.learning_curves(self.result.metrics, out / "learning_curves.png", title=env.name)
        return out


def _noise_free(env, controllers):
    """Noise-free rollouts of controllers [S, C, ...] from the env's conditions."""
    from diffgcl.algorithms.staged import noise_free_rollouts

    ctrl = jax.tree.map(jnp.asarray, controllers)
    S = ctrl.K.shape[0]
    x0 = jnp.broadcast_to(jnp.asarray(env.initial_states()), (S, *env.initial_states().shape))
    X, U = noise_free_rollouts(env, ctrl, x0)
    return jnp.asarray(X), jnp.asarray(U)


def _controller_actions(ctrl, X):
    """Mean actions ``K_t x_t + k_t`` along noise-free rollouts X [C, T+1, dX] -> [C, T, dU]."""
    return jnp.einsum("ctij,ctj->cti", ctrl.K, X[:, :-1]) + ctrl.k


def _run_folder(folder) -> Path:
    out = Path(folder)
    if out.exists():
        if not out.is_dir():
            raise FileExistsError(f"{out}: exists and is not a folder")
        contents = {p.name for p in out.iterdir()}
        ours = (out / "run.json").is_file() and _is_run(out / "run.json")
        if contents and not ours:
            raise FileExistsError(
                f"{out}: folder not empty and not a run of diffgcl.api; choose another --out"
            )
    out.mkdir(parents=True, exist_ok=True)
    return out


def _is_run(path: Path) -> bool:
    try:
        return json.loads(path.read_text()).get("format") == RUN_FORMAT
    except (OSError, ValueError, AttributeError):
        return False


def learn(
    env: MJCFEnv,
    demos: DemoSet,
    *,
    preset: str = "mjcf",
    schedule: str | None = None,
    seeds: Sequence[int] = (0,),
    iterations: int | None = None,
    overrides: Sequence[str] = (),
    policy=False,
    progress: bool = True,
    out: str | os.PathLike | None = None,
) -> LearnedRun:
    """Learn a cost (rGCL, ``preset``: by default ``"mjcf"``,
    :func:`diffgcl.algorithms.presets.mjcf`) and local controllers from ``demos`` on ``env``,
    and with ``policy`` (True, or :class:`~diffgcl.algorithms.mdgps.PolicySettings`) a global
    policy on the env's observations (MDGPS inside rGCL).

    The env gets the demos' start states as conditions and their length as horizon
    (:func:`demo_conditions`); seeds run as one vmapped batch; ``overrides`` are
    ``"gcl.n_steps=20"``-style config edits; ``out``: a checkpoint folder for the runner.
    """
    from diffgcl.algorithms.mdgps import PolicySettings
    from diffgcl.algorithms.presets import get_preset, with_overrides
    from diffgcl.algorithms.rgcl import demo_batch
    from diffgcl.algorithms.runner import train_seeds

    if demos.X.shape[-1] != env.dX or demos.U.shape[-1] != env.dU:
        raise DemoError(
            f"demos: states [{demos.X.shape[-1]}] and actions [{demos.U.shape[-1]}] do not fit "
            f"the env {env.name} (dX = {env.dX}, dU = {env.dU})"
        )
    if not np.isclose(demos.dt, env.dt, rtol=1e-6):
        raise DemoError(f"demos: dt = {demos.dt:g} s, the env steps {env.dt:g} s")
    x0, demos = demo_conditions(demos)
    env = env.with_conditions(x0, horizon=demos.horizon)
    config = get_preset(preset, schedule)
    edits = list(overrides) + ([f"iterations={int(iterations)}"] if iterations else [])
    if isinstance(policy, PolicySettings):
        config = dataclasses.replace(config, policy=policy)
    elif policy and config.policy is None:
        config = dataclasses.replace(config, policy=PolicySettings())
    if env.n_cost_features > env.dX:  # sites, bodies or sensors besides the state
        config = dataclasses.replace(
            config, network=dataclasses.replace(config.network, features="env")
        )
    config = with_overrides(config, edits)
    batch = demo_batch(demos, x0.shape[0], env=env)
    result = train_seeds(
        config, env, batch, list(seeds), out=None if out is None else Path(out), progress=progress
    )
    return LearnedRun(env=env, config=config, demos=demos, result=result)


def _report(run: LearnedRun, reoptimise: bool) -> dict:
    """See :meth:`LearnedRun.report`."""
    from diffgcl.algorithms.rgcl import reoptimise_seeds
    from diffgcl.control.lqr import controller_entropy
    from diffgcl.costs.demo_controller import fit_demo_controller
    from diffgcl.costs.expansion import trajectory_cost

    env, config = run.env, run.config
    network = run.network()
    params = jax.tree.map(jnp.asarray, run.cost_params)
    ctrl = jax.tree.map(jnp.asarray, run.controllers)
    C = int(env.initial_states().shape[0])
    cond = np.asarray([e["condition"] for e in run.demos.episodes])
    demo_X = [jnp.asarray(run.demos.X[cond == c]) for c in range(C)]
    demo_U = [jnp.asarray(run.demos.U[cond == c]) for c in range(C)]
    scale = jnp.asarray(state_scale(run.demos.X), demo_X[0].dtype)

    rollouts, actions = run.controller_rollouts()  # [S, C, T+1, dX], [S, C, T, dU]
    traj_cost = jax.vmap(network.trajectory_cost, (None, 0, 0))

    def per_seed(X, U, p):
        """Learned cost, distance to the demos and success of X [C, T+1, dX] under params p."""
        learned = traj_cost(p, X, U)
        dist = jnp.stack([demo_distance(X[c], demo_X[c], scale) for c in range(C)])
        return learned, dist

    learned, dist = jax.jit(jax.vmap(per_seed))(rollouts, actions, params)
    demo_learned = jax.jit(jax.vmap(
        lambda p: jnp.stack([traj_cost(p, demo_X[c], demo_U[c]).mean() for c in range(C)])
    ))(params)  # fmt: skip
    demo_spread = [
        float(jnp.mean(jax.vmap(lambda x, c=c: demo_distance(x, demo_X[c], scale))(demo_X[c])))
        for c in range(C)
    ]
    demo_entropy = [
        float(controller_entropy(fit_demo_controller(demo_X[c], demo_U[c]))) for c in range(C)
    ]
    report = {
        "env": env.name,
        "mjcf": env.mjcf_path,
        "seeds": run.seeds,
        "conditions": C,
        "demos": int(run.demos.num_episodes),
        "horizon": int(env.horizon),
        "learned_cost": np.asarray(learned).tolist(),
        "demo_learned_cost": np.asarray(demo_learned).tolist(),
        "demo_distance": np.asarray(dist).tolist(),
        "mean_demo_distance": float(jnp.mean(dist)),
        "demo_spread": demo_spread,
        "entropy": np.asarray(jax.vmap(jax.vmap(controller_entropy))(ctrl)).tolist(),
        "demo_entropy": demo_entropy,
        "rollbacks": list(run.result.rollbacks),
        "compile_seconds": run.result.compile_seconds,
        "run_seconds": run.result.run_seconds,
    }
    if env.has_success:
        success = np.asarray(jax.vmap(jax.vmap(env.success))(rollouts))
        report["success"] = success.tolist()
        report["success_rate"] = float(success.all(-1).mean())
        report["demo_success_rate"] = float(
            np.mean([np.asarray(jax.vmap(env.success)(x)).mean() for x in demo_X])
        )
    if env.has_cost:
        true = jax.vmap(jax.vmap(lambda X, U: trajectory_cost(env.expert_cost, X, U)))
        report["true_cost"] = np.asarray(true(rollouts, actions)).tolist()
        report["demo_true_cost"] = [
            float(jnp.mean(jax.vmap(lambda X, U: trajectory_cost(env.expert_cost, X, U))(x, u)))
            for x, u in zip(demo_X, demo_U, strict=True)
        ]
    if run.has_policy:
        report["policy"] = _policy_report(run, demo_X, scale)
    if reoptimise:
        keys = jnp.stack([jax.random.PRNGKey(100_000 + s) for s in run.seeds])
        state, _, _ = reoptimise_seeds(config, env, network, params, keys)
        re_X, re_U = _noise_free(env, state.controller)
        re_dist = jax.vmap(
            lambda X: jnp.stack([demo_distance(X[c], demo_X[c], scale) for c in range(C)])
        )(re_X)
        agreement = jnp.sqrt(jnp.mean(((re_X - rollouts) / scale) ** 2, axis=(-2, -1)))
        block = {
            "iterations": config.reopt_iterations,
            "demo_distance": np.asarray(re_dist).tolist(),
            "mean_demo_distance": float(jnp.mean(re_dist)),
            "distance_to_rgcl": np.asarray(agreement).tolist(),
        }
        if env.has_success:
            success = np.asarray(jax.vmap(jax.vmap(env.success))(re_X))
            block["success"] = success.tolist()
            block["success_rate"] = float(success.all(-1).mean())
        if env.has_cost:
            true = jax.vmap(jax.vmap(lambda X, U: trajectory_cost(env.expert_cost, X, U)))
            block["true_cost"] = np.asarray(true(re_X, re_U)).tolist()
        report["reoptimisation"] = block
    return report


def _policy_report(run: LearnedRun, demo_X, scale) -> dict:
    """The global policy's noise-free rollouts from the training conditions, per seed."""
    env = run.env
    C = len(demo_X)
    X, U = run.policy_rollouts()  # [S, C, T+1, dX]
    dist = jax.vmap(lambda X: jnp.stack([demo_distance(X[c], demo_X[c], scale) for c in range(C)]))(
        X
    )
    block = {"demo_distance": np.asarray(dist).tolist(), "mean_demo_distance": float(dist.mean())}
    if env.has_success:
        success = np.asarray(jax.vmap(jax.vmap(env.success))(X))
        block["success"] = success.tolist()
        block["success_rate"] = float(success.all(-1).mean())
    if env.has_cost:
        from diffgcl.costs.expansion import trajectory_cost

        true = jax.vmap(jax.vmap(lambda X, U: trajectory_cost(env.expert_cost, X, U)))
        block["true_cost"] = np.asarray(true(X, U)).tolist()
    return block
