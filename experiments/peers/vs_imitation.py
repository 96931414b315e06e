"""diffgcl beside the imitation library: AIRL, GAIL and BC on the same gymnasium tasks and demos.

Runs in ``experiments/peers/.venv`` (``make peers``: diffgcl, gymnasium 1.4.0, stable-baselines3,
torch CPU and imitation in one environment; docs/peers.md says why and what was checked). For each
task — gymnasium's ``InvertedPendulum-v5`` and ``Reacher-v5`` with a fixed target (and
``InvertedDoublePendulum-v5`` with ``--tasks``) — in one process:

1. **the demos**, once: diffgcl's expert (``api.expert_demos``: iLQR on the hand-written cost of
   ``experiments/trajopt_gym.py``, noisy rollouts about each solution) from the training starts,
   on gymnasium's own XML read from the installed package at gymnasium's frame skip, saved as our
   npz; then **replayed in gymnasium** (``set_state`` to the demo's start, the demo's ctrl
   stepped by gymnasium's env) to give imitation's ``Trajectory`` objects with gymnasium's own
   observations (also saved, :func:`diffgcl.gym.save_trajectories`). The largest gap between
   gymnasium's replayed states and ours is reported. Both sides learn from these same episodes.
2. **diffgcl**: rGCL + MDGPS (``api.learn(..., policy=True)``), the policy then run in
   gymnasium on gymnasium's observations mapped to the state (:data:`diffgcl.gym.OBS_TO_STATE`);
   diffgcl's BC (``diffgcl.algorithms.bc``) on the same demos.
3. **imitation**: AIRL and GAIL with stable-baselines3's PPO as generator, with imitation's
   tuned MuJoCo (seals Hopper) hyperparameters (:data:`AIRL_SETTINGS`, :data:`GAIL_SETTINGS`),
   a fixed budget of environment steps; imitation's BC.
4. **the export**: PPO on diffgcl's learned cost (:func:`diffgcl.gym.learned_cost_env`) beside
   PPO on gymnasium's true reward, the same budget and settings (stable-baselines3's defaults,
   rewards normalised by ``VecNormalize`` as rl-zoo does for MuJoCo: a learned cost's scale is
   GCL's, not the task's).

Every policy is judged in gymnasium itself, noise-free, from the training starts and from
held-out starts: the task's success test on the states gymnasium visits, gymnasium's own episode
return (episode of ``T`` steps, gymnasium's termination kept). Environment steps: for diffgcl
every simulated transition counts (each iteration's samples, the mean-trajectory rollout its
Jacobians are taken about, and the noise-free rollouts of controllers and policy), with the
Jacobians' tangent directions counted as step-equivalents besides; for AIRL, GAIL and PPO
stable-baselines3's own count. Wall times are one run on the same 2 cores, compiles included.

    make peers
    PY=experiments/peers/.venv/bin/python
    $PY experiments/peers/vs_imitation.py --fast --json runs/peers_fast.json  # ~30 min, 2 cores
    $PY experiments/peers/vs_imitation.py --json runs/peers.json  # 1M steps per peer: hours
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # experiments/: the tasks' costs
import trajopt_gym as tg  # noqa: E402

REACHER_TARGET = (0.1, 0.1)  # fixed target (inside the arm's 0.21 m reach)


def reacher_fixed_starts(rng, n):
    """The reacher's v5 reset distribution for the arm (angles U(−0.1, 0.1), velocities
    U(−0.005, 0.005)) with the target fixed at :data:`REACHER_TARGET`."""
    X = np.zeros((n, 8))
    X[:, :2] = rng.uniform(-0.1, 0.1, (n, 2))
    X[:, 2:4] = REACHER_TARGET
    X[:, 4:6] = rng.uniform(-0.005, 0.005, (n, 2))
    return X


@dataclass(frozen=True)
class PeerTask:
    env_id: str
    gym: tg.GymTask  # XML, frame skip, horizon, cost, success (experiments/trajopt_gym.py)
    starts: object  # (rng, n) -> [n, dX]
    obs: tuple  # diffgcl's observation and extra cost features


TASKS = {
    "pendulum": PeerTask(
        "InvertedPendulum-v5", tg.TASKS["pendulum"], tg.pendulum_starts, ("state",)
    ),
    "reacher": PeerTask(
        "Reacher-v5", tg.TASKS["reacher"], reacher_fixed_starts, ("state", "body:fingertip")
    ),
    "double_pendulum": PeerTask(
        "InvertedDoublePendulum-v5", tg.TASKS["double_pendulum"], tg.double_starts, ("state",)
    ),
}

# diffgcl's settings on these tasks (edits of the arm's `default` preset, which the figures in
# docs/peers.md were measured with, rather than api.learn's own `mjcf`; before --diffgcl-set):
# GPS starts from the demos' fitted controllers, since a zero controller lets a pendulum fall
# before GPS's KL-bounded steps can catch it; and the zero controller's samples join the fusion
# buffer, so that GCL's partition function sees trajectories that fail, not only samples near
# the demos (without them the learned cost did not keep the pendulum up: docs/peers.md).
DIFFGCL_PRESET = "default"
DIFFGCL_SETTINGS = ("initial_controller=demos", "zero_controller_samples=True")

# imitation's tuned hyperparameters for MuJoCo (benchmarking/example_{airl,gail}_seals_hopper_
# best_hp_eval.json of the imitation repository): PPO generator, reward nets with RunningNorm.
AIRL_SETTINGS = {
    "demo_batch_size": 2048,
    "gen_replay_buffer_capacity": 8192,
    "n_disc_updates_per_round": 16,
    "rl_batch": 8192,
    "ppo": dict(
        batch_size=512,
        clip_range=0.1,
        ent_coef=0.009709494745755033,
        gae_lambda=0.98,
        gamma=0.995,
        learning_rate=0.0005807211840258373,
        max_grad_norm=0.9,
        n_epochs=20,
        vf_coef=0.20315938606555833,
    ),
}
GAIL_SETTINGS = {
    "demo_batch_size": 128,
    "gen_replay_buffer_capacity": 4096,
    "n_disc_updates_per_round": 8,
    "rl_batch": 4096,
    "ppo": dict(
        batch_size=512,
        clip_range=0.1,
        ent_coef=0.001255299425412744,
        gae_lambda=0.98,
        gamma=0.995,
        learning_rate=4.3984856156897565e-5,
        max_grad_norm=0.9,
        n_epochs=20,
        vf_coef=0.20315938606555833,
    ),
}


# ---- gymnasium: the tasks' envs ------------------------------------------------------------------


def split_state(x, nq):
    x = np.asarray(x, np.float64)
    return x[:nq], x[nq:]


def make_gym_env(task: PeerTask, seed: int, *, terminate: bool = True):
    """gymnasium's env with ``T``-step episodes, reset to a start drawn from the task's start
    distribution (``options={"x0": x}`` for a given one); without ``terminate`` gymnasium's
    termination is switched off (fixed-horizon episodes, as imitation's adversarial trainers
    expect)."""
    import gymnasium

    class Starts(gymnasium.Wrapper):
        def __init__(self, env):
            super().__init__(env)
            self.rng = np.random.default_rng(seed)

        def reset(self, *, seed=None, options=None):
            self.env.reset(seed=seed)
            x = (options or {}).get("x0")
            x = task.starts(self.rng, 1)[0] if x is None else x
            u = self.env.unwrapped
            u.set_state(*split_state(x, u.model.nq))
            return u._get_obs(), {}

        def step(self, action):
            obs, r, terminated, truncated, info = self.env.step(action)
            return obs, r, terminated and terminate, truncated, info

    env = gymnasium.make(task.env_id, max_episode_steps=task.gym.horizon)
    return Starts(env)


def judge(task: PeerTask, act, starts) -> dict:
    """Noise-free episodes of ``act(obs) -> action`` in gymnasium from each start: success (the
    task's test on the visited states; an episode gymnasium terminates fails), returns."""
    env = make_gym_env(task, 0)
    u = env.unwrapped
    T = task.gym.horizon
    success, returns = [], []
    for x0 in starts:
        obs, _ = env.reset(options={"x0": x0})
        states = [np.concatenate([u.data.qpos, u.data.qvel])]
        total, ended = 0.0, False
        for _ in range(T):
            a = np.clip(np.asarray(act(obs), np.float64).reshape(-1), -1e9, 1e9)
            a = np.clip(a, env.action_space.low, env.action_space.high)
            obs, r, terminated, truncated, _ = env.step(a)
            total += float(r)
            states.append(np.concatenate([u.data.qpos, u.data.qvel]))
            if terminated:
                ended = True
                break
        ok = (not ended) and bool(task.gym.success(np.asarray(states)))
        success.append(ok)
        returns.append(total)
    return {
        "success": success,
        "success_rate": float(np.mean(success)),
        "returns": returns,
        "mean_return": float(np.mean(returns)),
    }


# ---- 1. the demos --------------------------------------------------------------------------------


def make_demos(task: PeerTask, starts, out: Path, per_start: int) -> dict:
    """diffgcl's expert demos (npz) and their gymnasium replay (imitation's fields)."""
    import mujoco

    from diffgcl import api
    from diffgcl import gym as dgym

    path = tg.gym_asset(task.gym.xml)
    timestep = mujoco.MjModel.from_xml_path(str(path)).opt.timestep
    env = api.load_model(
        path,
        lapack_free=True,
        dt=task.gym.frame_skip * timestep,
        horizon=task.gym.horizon,
        x0=starts,
        cost=task.gym.cost,
        success=task.gym.success,
    )
    t0 = time.perf_counter()
    demo_file = out / f"{task.env_id}_demos.npz"
    demos = api.expert_demos(env, per_start=per_start, path=demo_file, verbose=False)
    seconds = time.perf_counter() - t0
    with np.load(demo_file) as f:
        qpos, qvel, ctrl = f["qpos"], f["qvel"], f["ctrl"]
    gym_env = make_gym_env(task, 0)
    u = gym_env.unwrapped
    trajectories, gaps, map_gaps = [], [], []
    to_state = dgym.state_map(task.env_id)
    for i in range(qpos.shape[0]):
        gym_env.reset()
        u.set_state(qpos[i, 0], qvel[i, 0])
        obs = [u._get_obs()]
        gq, gv = [u.data.qpos.copy()], [u.data.qvel.copy()]
        for t in range(ctrl.shape[1]):
            o, *_ = u.step(ctrl[i, t])
            obs.append(o)
            gq.append(u.data.qpos.copy())
            gv.append(u.data.qvel.copy())
        gaps.append(
            max(np.abs(np.asarray(gq) - qpos[i]).max(), np.abs(np.asarray(gv) - qvel[i]).max())
        )
        x_map = to_state(np.asarray(obs))
        x_gym = np.concatenate([np.asarray(gq), np.asarray(gv)], -1)
        if task.env_id.startswith("Reacher"):
            x_gym[:, 6:] = 0.0
        if task.env_id.startswith("InvertedDoublePendulum"):
            x_gym[:, 3:] = np.clip(x_gym[:, 3:], -10, 10)
        map_gaps.append(float(np.abs(x_map - x_gym).max()))
        trajectories.append(
            dgym.PlainTrajectory(
                obs=np.asarray(obs, np.float32), acts=ctrl[i].astype(np.float32), terminal=True
            )
        )
    traj_file = dgym.save_trajectories(out / f"{task.env_id}_trajectories.npz", trajectories)
    gym_success = [bool(task.gym.success(np.concatenate([q, v], -1))) for q, v in zip(
        qpos, qvel, strict=True)]  # fmt: skip
    return {
        "demo_file": str(demo_file),
        "trajectory_file": str(traj_file),
        "episodes": int(qpos.shape[0]),
        "per_start": per_start,
        "transitions": int(ctrl.shape[0] * ctrl.shape[1]),
        "expert_seconds": seconds,
        "demo_success_rate": float(np.mean(gym_success)),
        "solution_success": [bool(e.get("solution_success", True)) for e in demos.episodes],
        "replay_max_state_gap": float(max(gaps)),
        "obs_map_max_gap": float(max(map_gaps)),
        "trajectories": trajectories,
        "env": env,
    }


# ---- 2. diffgcl ----------------------------------------------------------------------------------


def diffgcl_env_steps(run) -> dict:
    """Simulated transitions of a run (see the module docstring)."""
    cfg, env = run.config, run.env
    C, T = int(run.env.initial_states().shape[0]), int(env.horizon)
    N, it = int(cfg.gps.num_samples), int(cfg.iterations)
    per_iteration = C * T * (N + 1 + 2)  # samples, the Jacobians' mean rollout, 2 noise-free
    tangents = C * T * (env.dX + env.dU)
    return {
        "env_steps": it * per_iteration,
        "jacobian_tangent_equivalents": it * tangents,
        "iterations": it,
        "samples_per_condition": N,
    }


def run_diffgcl(task: PeerTask, demo_file: Path, train, held_out, args) -> dict:
    import jax
    import jax.numpy as jnp
    import mujoco

    from diffgcl import api
    from diffgcl import gym as dgym
    from diffgcl.algorithms.bc import BCConfig, clone_demos

    path = tg.gym_asset(task.gym.xml)
    timestep = mujoco.MjModel.from_xml_path(str(path)).opt.timestep
    t0 = time.perf_counter()
    env = api.load_model(
        path,
        lapack_free=True,
        dt=task.gym.frame_skip * timestep,
        obs=task.obs,
        cost=task.gym.cost,
        success=task.gym.success,
    )
    demos = api.load_demos(demo_file, env)
    run = api.learn(
        env,
        demos,
        preset=DIFFGCL_PRESET,
        policy=True,
        seeds=(0,),
        iterations=args.diffgcl_iterations,
        overrides=DIFFGCL_SETTINGS + tuple(args.diffgcl_set),
        progress=False,
    )
    jax.block_until_ready(run.cost_params)
    wall = time.perf_counter() - t0
    to_state = dgym.state_map(task.env_id)
    scale = np.asarray(run.env.ctrl_scale)
    policy = run.policy()
    params = jax.tree.map(lambda a: jnp.asarray(a[0]), run.result.state.policy.params)
    mean = jax.jit(lambda x: policy.mean_action(params, run.env.obs(x)))
    act = lambda obs: np.asarray(mean(jnp.asarray(to_state(obs)))) * scale
    out = {"wall_s": wall, **diffgcl_env_steps(run)}
    out["settings"] = list(DIFFGCL_SETTINGS) + list(args.diffgcl_set)
    out["preset"] = DIFFGCL_PRESET
    out["compile_s"] = run.result.compile_seconds  # the runner's own split of the wall time
    out["run_s"] = run.result.run_seconds
    out["train"] = judge(task, act, train)
    out["held_out"] = judge(task, act, held_out)
    rep = run.report(reoptimise=False)
    out["controllers_success_mjx"] = rep.get("success_rate")
    out["policy_success_mjx"] = rep["policy"].get("success_rate")
    # diffgcl's BC on the same demos and observations
    t0 = time.perf_counter()
    bc_policy, bc_params = clone_demos(
        run.demos, run.env, BCConfig(network=run.config.policy.network), [0]
    )
    bc_params = jax.tree.map(lambda a: jnp.asarray(a[0]), bc_params)
    bc_mean = jax.jit(lambda x: bc_policy.mean_action(bc_params, run.env.obs(x)))
    bc_act = lambda obs: np.asarray(bc_mean(jnp.asarray(to_state(obs)))) * scale
    bc = {"wall_s": time.perf_counter() - t0, "env_steps": 0}
    bc["train"] = judge(task, bc_act, train)
    bc["held_out"] = judge(task, bc_act, held_out)
    reward = dgym.reward_from_run(run, task.env_id)
    return {"rgcl": out, "bc": bc, "reward": reward}


# ---- 3. imitation, 4. PPO ------------------------------------------------------------------------


def vec_env(task, seed, reward=None, *, normalize_reward: bool = False):
    """PPO's training env; ``normalize_reward``: stable-baselines3's ``VecNormalize`` on the
    rewards only (a running estimate of the discounted return's scale, as rl-zoo's MuJoCo
    settings use; the observations stay raw, so the judged policy sees what gymnasium gives)."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from diffgcl import gym as dgym

    def make():
        env = make_gym_env(task, seed, terminate=False)
        return env if reward is None else dgym.learned_cost_env(env, reward)

    venv = DummyVecEnv([make])
    return VecNormalize(venv, norm_obs=False, norm_reward=True) if normalize_reward else venv


def policy_kwargs():
    import torch
    from imitation.policies.base import NormalizeFeaturesExtractor
    from imitation.util.networks import RunningNorm

    return dict(
        activation_fn=torch.nn.ReLU,
        features_extractor_class=NormalizeFeaturesExtractor,
        features_extractor_kwargs=dict(normalize_class=RunningNorm),
        net_arch=dict(pi=[64, 64], vf=[64, 64]),
    )


def sb3_act(model):
    return lambda obs: model.predict(np.asarray(obs, np.float32), deterministic=True)[0]


def run_adversarial(kind, task, trajectories, train, held_out, args) -> dict:
    from imitation.algorithms.adversarial.airl import AIRL
    from imitation.algorithms.adversarial.gail import GAIL
    from imitation.rewards.reward_nets import (
        BasicRewardNet,
        BasicShapedRewardNet,
        NormalizedRewardNet,
    )
    from imitation.util.networks import RunningNorm
    from stable_baselines3 import PPO

    from diffgcl import gym as dgym

    s = AIRL_SETTINGS if kind == "airl" else GAIL_SETTINGS
    venv = vec_env(task, args.seed)
    rl_batch = args.rl_batch or s["rl_batch"]
    transitions = sum(len(t.acts) for t in trajectories)
    demo_batch = min(s["demo_batch_size"], transitions)
    t0 = time.perf_counter()
    learner = PPO(
        "MlpPolicy",
        venv,
        n_steps=rl_batch,
        policy_kwargs=policy_kwargs(),
        seed=args.seed,
        device="cpu",
        verbose=0,
        **{**s["ppo"], "batch_size": min(s["ppo"]["batch_size"], rl_batch)},
    )
    net_cls = BasicShapedRewardNet if kind == "airl" else BasicRewardNet
    net = net_cls(venv.observation_space, venv.action_space, normalize_input_layer=RunningNorm)
    net = NormalizedRewardNet(net, normalize_output_layer=RunningNorm)
    trainer_cls = AIRL if kind == "airl" else GAIL
    trainer = trainer_cls(
        demonstrations=dgym.to_imitation(trajectories),
        demo_batch_size=demo_batch,
        gen_replay_buffer_capacity=s["gen_replay_buffer_capacity"],
        n_disc_updates_per_round=s["n_disc_updates_per_round"],
        venv=venv,
        gen_algo=learner,
        reward_net=net,
        allow_variable_horizon=False,
    )
    trainer.train(args.steps)
    wall = time.perf_counter() - t0
    out = {
        "wall_s": wall,
        "env_steps": int(learner.num_timesteps),
        "rl_batch": rl_batch,
        "demo_batch_size": demo_batch,
    }
    out["train"] = judge(task, sb3_act(learner), train)
    out["held_out"] = judge(task, sb3_act(learner), held_out)
    return out


def run_bc(task, trajectories, train, held_out, args) -> dict:
    from imitation.algorithms import bc

    from diffgcl import gym as dgym

    env = make_gym_env(task, args.seed)
    t0 = time.perf_counter()
    trainer = bc.BC(
        observation_space=env.observation_space,
        action_space=env.action_space,
        demonstrations=dgym.to_imitation(trajectories),
        rng=np.random.default_rng(args.seed),
        device="cpu",
    )
    trainer.train(n_epochs=args.bc_epochs, progress_bar=False, log_interval=10**9)
    out = {"wall_s": time.perf_counter() - t0, "env_steps": 0, "epochs": args.bc_epochs}
    out["train"] = judge(task, sb3_act(trainer.policy), train)
    out["held_out"] = judge(task, sb3_act(trainer.policy), held_out)
    return out


def run_ppo(task, train, held_out, args, reward=None) -> dict:
    from stable_baselines3 import PPO

    venv = vec_env(task, args.seed, reward, normalize_reward=args.ppo_normalize_reward)
    t0 = time.perf_counter()
    model = PPO("MlpPolicy", venv, seed=args.seed, device="cpu", verbose=0)
    model.learn(args.steps)
    out = {"wall_s": time.perf_counter() - t0, "env_steps": int(model.num_timesteps)}
    out["train"] = judge(task, sb3_act(model), train)
    out["held_out"] = judge(task, sb3_act(model), held_out)
    return out


# ---- the table -----------------------------------------------------------------------------------


def summary(name: str, r: dict) -> dict:
    """The flat keys of the JSON for one task, and the targets."""
    flat = {}
    for key, m in r["methods"].items():
        flat[f"{key}_success"] = m["held_out"]["success_rate"]
        flat[f"{key}_train_success"] = m["train"]["success_rate"]
        flat[f"{key}_return"] = m["held_out"]["mean_return"]
        flat[f"{key}_train_return"] = m["train"]["mean_return"]
        flat[f"{key}_env_steps"] = m["env_steps"]
        flat[f"{key}_wall_s"] = m["wall_s"]
    targets = {}
    peers = [k for k in ("airl", "gail") if k in r["methods"]]
    if "diffgcl" in r["methods"] and peers:
        best = max(flat[f"{k}_success"] for k in peers)
        steps = min(flat[f"{k}_env_steps"] for k in peers)
        wall = min(flat[f"{k}_wall_s"] for k in peers)
        targets["success_at_least_best_adversarial"] = flat["diffgcl_success"] >= best
        targets["env_steps_fraction"] = flat["diffgcl_env_steps"] / steps
        targets["env_steps_at_most_1_percent"] = flat["diffgcl_env_steps"] <= 0.01 * steps
        targets["wall_fraction"] = flat["diffgcl_wall_s"] / wall
        targets["wall_at_most_10_percent"] = flat["diffgcl_wall_s"] <= 0.1 * wall
    if "ppo_true" in r["methods"] and "ppo_on_learned_cost" in r["methods"]:
        true = flat["ppo_true_success"]
        ratio = flat["ppo_on_learned_cost_success"] / true if true > 0 else None
        targets["ppo_learned_over_true"] = ratio
        targets["ppo_learned_at_least_80_percent"] = None if ratio is None else ratio >= 0.8
    flat["targets"] = targets
    return flat


def print_table(results: dict) -> None:
    for name, r in results.items():
        print(f"== {name} ({r['env_id']}): held-out success / train success / held-out return / "
              "env steps / wall s")  # fmt: skip
        for key, m in r["methods"].items():
            print(f"   {key:20s} {m['held_out']['success_rate']:5.2f} "
                  f"{m['train']['success_rate']:5.2f} {m['held_out']['mean_return']:9.2f} "
                  f"{m['env_steps']:9d} {m['wall_s']:8.1f}")  # fmt: skip
        print(f"   targets: {r['summary']['targets']}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--fast", action="store_true", help="small budgets (docs/peers.md)")
    parser.add_argument("--tasks", default="pendulum,reacher", help=f"of {','.join(TASKS)}")
    parser.add_argument(
        "--methods", default="diffgcl,airl,gail,bc,ppo", help="comma-separated; or ppo_learned"
    )
    parser.add_argument("--train-starts", type=int, default=None, help="default 8; fast 4")
    parser.add_argument("--held-out-starts", type=int, default=None, help="default 16; fast 4")
    parser.add_argument("--per-start", type=int, default=5, help="demos per training start")
    parser.add_argument("--steps", type=int, default=None, help="AIRL/GAIL/PPO env steps")
    parser.add_argument("--rl-batch", type=int, default=None, help="PPO rollout per update")
    parser.add_argument("--bc-epochs", type=int, default=100)
    parser.add_argument("--diffgcl-iterations", type=int, default=None, help="rGCL iterations")
    parser.add_argument(
        "--diffgcl-set",
        action="append",
        default=[],
        help="config edit after DIFFGCL_SETTINGS, e.g. gps.init_var=0.01",
    )
    parser.add_argument(
        "--ppo-normalize-reward",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="PPO (both rows) on VecNormalize'd rewards (rl-zoo's MuJoCo setting)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs/peers"))
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    fast = args.fast
    args.train_starts = args.train_starts or (4 if fast else 8)
    args.held_out_starts = args.held_out_starts or (4 if fast else 16)
    args.steps = args.steps or (100_000 if fast else 1_000_000)
    if fast and args.rl_batch is None:
        args.rl_batch = 2048  # the documented 8192 / 4096 leave a 100k budget a dozen updates
    methods = args.methods.split(",")

    import jax

    if set(methods) - {"diffgcl"}:  # diffgcl alone runs without the peer stack
        import torch

        torch.set_num_threads(1)
    jax.config.update("jax_enable_x64", True)  # iLQR through joint limits (docs/trajopt.md)
    from diffgcl.runtime import prepare_process

    prepare_process()
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    t_start = time.perf_counter()
    for name in args.tasks.split(","):
        task = TASKS[name]
        train = task.starts(np.random.default_rng(args.seed), args.train_starts)
        held_out = task.starts(np.random.default_rng(args.seed + 1000), args.held_out_starts)
        print(f"== {name}: demos from {len(train)} starts", flush=True)
        demos = make_demos(task, train, args.out, args.per_start)
        trajectories = demos.pop("trajectories")
        demos.pop("env")
        print(f"   demos: {demos['episodes']} episodes, success {demos['demo_success_rate']:.2f}"
              f", replay gap {demos['replay_max_state_gap']:.2e}", flush=True)  # fmt: skip
        r = {
            "env_id": task.env_id,
            "xml": str(tg.gym_asset(task.gym.xml)),
            "train_starts": train.tolist(),
            "held_out_starts": held_out.tolist(),
            "demos": demos,
            "methods": {},
        }
        results[name] = r
        reward = None

        def done(key, m, r=r, name=name):
            r["methods"][key] = m
            print(f"   {key}: held-out {m['held_out']['success_rate']:.2f}, train "
                  f"{m['train']['success_rate']:.2f}, {m['env_steps']} steps, "
                  f"{m['wall_s']:.0f} s", flush=True)  # fmt: skip
            r["summary"] = summary(name, r)
            if args.json:
                args.json.parent.mkdir(parents=True, exist_ok=True)
                meta = {"fast": fast, "args": {k: str(v) for k, v in vars(args).items()}}
                args.json.write_text(json.dumps({**meta, "tasks": results}, indent=1))

        if "diffgcl" in methods:
            d = run_diffgcl(task, Path(demos["demo_file"]), train, held_out, args)
            reward = d.pop("reward")
            done("diffgcl", d["rgcl"])
            done("bc_diffgcl", d["bc"])
        if "bc" in methods:
            done("bc", run_bc(task, trajectories, train, held_out, args))
        for kind in ("airl", "gail"):
            if kind in methods:
                done(kind, run_adversarial(kind, task, trajectories, train, held_out, args))
        if "ppo" in methods:  # both; "ppo_learned": the learned cost's alone
            done("ppo_true", run_ppo(task, train, held_out, args))
        if reward is not None and ("ppo" in methods or "ppo_learned" in methods):
            done("ppo_on_learned_cost", run_ppo(task, train, held_out, args, reward))
    print_table(results)
    print(f"total {time.perf_counter() - t_start:.0f} s")
    if args.json:
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
