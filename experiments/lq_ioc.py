"""Inverse optimal control on a linear-quadratic problem with a known cost.

A planar point mass (x = [p_x, p_y, v_x, v_y], u = acceleration, dt = 0.1, deterministic linear
dynamics) with the true cost ``c(x, u) = (x − x*)ᵀQ(x − x*) + r‖u‖²`` at every step and at the end.
Demonstrations come from the MaxEnt-optimal controller of the true cost (the plain LQR backward
pass, ``Σ = Q_uu⁻¹``), from several start states (conditions). GCL then learns the network cost:

    pre-train on the demos against the initial controller's samples, then per iteration
    C-step (MaxEnt KL-constrained LQR on the Gauss–Newton expansion of the learned cost) →
    sample the new controller → store in the fusion buffer → cost update (Adam steps).

Evaluation on held-out trajectories that the learner never saw: controllers interpolated between
the initial and the true optimal one (plus wider noise), pooled over conditions. Reported:
Spearman rank correlation of learned vs true trajectory costs, and the EPIC distance of the
learned per-step cost to the true one on the held-out transitions (:mod:`diffgcl.eval.epic`).
An ablation (same seeds) switches off fusion weights, demos in the partition, and lcr.

    python experiments/lq_ioc.py --json out.json [--fast] [--no-ablation]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.control.dual import c_step
from diffgcl.control.init import init_controller
from diffgcl.control.lqr import controller_entropy, lqr_backward
from diffgcl.costs.buffer import buffer_add, init_buffer
from diffgcl.costs.demo_controller import fit_demo_controller
from diffgcl.costs.expansion import about_origin, expand_cost, expand_cost_samples
from diffgcl.costs.gcl import GCLConfig, GCLState, fusion_weighted_samples, make_cost_learner
from diffgcl.costs.model_samples import model_weighted_samples
from diffgcl.costs.network import CostNetwork, CostNetworkConfig, untempered, update_normaliser
from diffgcl.costs.temperature import calibrated_log_temperature
from diffgcl.eval.epic import epic_distance, pearson_distance, step_cost_as_transition_cost
from diffgcl.types import (
    InitialStateDistribution,
    LinearDynamics,
    LinearGaussianController,
    make_controller,
)

maxent_c_step = functools.partial(c_step, maxent=True)


@dataclass(frozen=True)
class LQIOCConfig:
    """The problem and the learner (demos / samples per condition; the conditions are the start
    states). sample_source: ``"buffer"`` (GCL: every past sample, fusion weights) or ``"model"``
    (the seed's variant: fresh samples of the current controller in the linear-Gaussian model,
    full ``log p``). temperature: ``"likelihood"`` (the cost's scale as GCL fits it) or
    ``"demos"`` (rescaled after pre-training and every update so that its MaxEnt controller is as
    precise as the demos' fitted one, :mod:`diffgcl.costs.temperature`). The default network has
    no hidden layers — affine features, so the learned
    cost is a PSD quadratic in x plus ``w_u‖u‖²``, the true model class; the ``mlp`` row of the
    ablation uses a ReLU network."""

    horizon: int = 20
    dt: float = 0.1
    n_demos: int = 20
    n_samples: int = 10
    n_iterations: int = 10
    kl_step: float = 2.0
    init_var: float = 1.0
    action_weight: float = 0.5
    n_heldout: int = 10
    sample_source: str = "buffer"
    temperature: str = "likelihood"
    network: CostNetworkConfig = field(
        default_factory=lambda: CostNetworkConfig(
            hidden=(), n_features=8, action_weight=0.1, std_floor=1e-2
        )
    )
    gcl: GCLConfig = field(
        default_factory=lambda: GCLConfig(
            n_steps=100,
            pretrain_steps=300,
            demo_batch=10,
            sample_batch=20,
            learning_rate=3e-3,
            lcr_weight=1.0,
        )
    )


def default_config() -> LQIOCConfig:
    return LQIOCConfig()


def fast_config() -> LQIOCConfig:
    return dataclasses.replace(LQIOCConfig(), n_iterations=4)


START_STATES = np.array(
    [[0.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 1.0], [0.0, 2.0, 1.0, 0.0], [2.0, 2.0, -1.0, -1.0]]
)
TARGET = np.array([1.0, 1.0, 0.0, 0.0])
STATE_WEIGHT = np.array(
    [[2.0, 0.5, 0.0, 0.0], [0.5, 1.0, 0.0, 0.0], [0.0, 0.0, 0.2, 0.0], [0.0, 0.0, 0.0, 0.2]]
)


def point_mass(config: LQIOCConfig) -> LinearDynamics:
    """Double integrator in 2-D, fields [T, ...] (deterministic: cov = 0)."""
    dt, T = config.dt, config.horizon
    eye = np.eye(2)
    A = np.block([[eye, dt * eye], [np.zeros((2, 2)), eye]])
    B = np.concatenate([0.5 * dt**2 * eye, dt * eye])
    return LinearDynamics(
        A=jnp.broadcast_to(jnp.asarray(A), (T, 4, 4)),
        B=jnp.broadcast_to(jnp.asarray(B), (T, 4, 2)),
        c=jnp.zeros((T, 4)),
        cov=jnp.zeros((T, 4, 4)),
    )


def true_cost(config: LQIOCConfig):
    """c(x, u, t) = (x − x*)ᵀQ(x − x*) + r‖u‖²."""
    Q, target, r = jnp.asarray(STATE_WEIGHT), jnp.asarray(TARGET), config.action_weight

    def cost(x, u, t):
        d = x - target
        return d @ Q @ d + r * (u @ u)

    return cost


def rollout(key, dynamics: LinearDynamics, controller: LinearGaussianController, x0):
    """One trajectory from a fixed start ``x0: [dX]`` -> (X: [T+1, dX], U: [T, dU])."""
    T, dU, _ = controller.K.shape
    noise = jax.random.normal(key, (T, dU), x0.dtype)

    def step(x, inputs):
        A, B, c, K, k, L, v = inputs
        u = K @ x + k + L @ v
        return A @ x + B @ u + c, (x, u)

    xs = (
        dynamics.A,
        dynamics.B,
        dynamics.c,
        controller.K,
        controller.k,
        controller.chol_cov,
        noise,
    )
    x_T, (X, U) = jax.lax.scan(step, x0, xs)
    return jnp.concatenate([X, x_T[None]]), U


def rollouts(key, dynamics, controllers, x0s, n):
    """n trajectories per condition: controllers [C, ...], x0s [C, dX] -> X [C, n, T+1, dX], U."""
    C = x0s.shape[0]
    keys = jax.random.split(key, (C, n))
    per_condition = jax.vmap(rollout, in_axes=(0, None, None, None))
    return jax.vmap(per_condition, in_axes=(0, None, 0, 0))(keys, dynamics, controllers, x0s)


def maxent_optimal_controller(dynamics: LinearDynamics, cost_fn) -> LinearGaussianController:
    """MaxEnt-optimal controller of a quadratic cost: LQR backward pass with ``Σ = Q_uu⁻¹``."""
    T, dX, dU = dynamics.B.shape
    quad = expand_cost(cost_fn, jnp.zeros((T + 1, dX)), jnp.zeros((T, dU)))  # about the origin
    return lqr_backward(dynamics, quad).controller


def heldout_controllers(optimal: LinearGaussianController, initial: LinearGaussianController):
    """Controllers between the initial and the optimal one: blend α ∈ {0, ¼, ½, ¾, 1} of the gains,
    and the optimal gains with 3× the noise. Fields [6, T, ...]."""
    alphas = jnp.array([0.0, 0.25, 0.5, 0.75, 1.0])

    def blend(a):
        return make_controller(
            a * optimal.K + (1 - a) * initial.K,
            a * optimal.k + (1 - a) * initial.k,
            a * optimal.cov + (1 - a) * initial.cov,
        )

    blended = jax.vmap(blend)(alphas)
    wide = make_controller(optimal.K, optimal.k, 3.0 * optimal.cov)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]]), blended, wide)


def spearman(a, b) -> float:
    """Spearman rank correlation of two samples (no ties expected in continuous data)."""
    ra = np.argsort(np.argsort(np.asarray(a)))
    rb = np.argsort(np.argsort(np.asarray(b)))
    return float(np.corrcoef(ra, rb)[0, 1])


@jax.tree_util.register_dataclass
@dataclass
class TrainResult:
    """GCL state after training, the last controllers [C, ...] and per-iteration metrics."""

    gcl: GCLState
    controllers: LinearGaussianController
    loss: jax.Array
    kl: jax.Array
    true_cost: jax.Array


def make_train(config: LQIOCConfig):
    """Python-side setup; returns the pure ``train(key) -> TrainResult`` and the problem."""
    dynamics = point_mass(config)
    cost_true = true_cost(config)
    T, dX, dU = config.horizon, 4, 2
    x0s = jnp.asarray(START_STATES)
    C = x0s.shape[0]
    x0_dists = InitialStateDistribution(
        mean=x0s, cov=jnp.broadcast_to(1e-6 * jnp.eye(dX), (C, dX, dX))
    )
    network = CostNetwork(config.network, dX, dU, x0s.dtype)
    learner = make_cost_learner(network, config.gcl)
    optimal = maxent_optimal_controller(dynamics, cost_true)
    initial = init_controller(T, dX, dU, config.init_var, dtype=x0s.dtype)
    stack = lambda c: jax.tree.map(lambda a: jnp.broadcast_to(a, (C, *a.shape)), c)
    capacity = config.n_samples * (config.n_iterations + 1)
    epsilon = config.kl_step * T

    def true_traj_cost(X, U):
        U_all = jnp.concatenate([U, jnp.zeros((1, dU))])
        return jax.vmap(cost_true)(X, U_all, jnp.arange(T + 1)).sum()

    def train(key):
        key_demo, key_init, key_net, key_pre, key_loop = jax.random.split(key, 5)
        DX, DU = rollouts(key_demo, dynamics, stack(optimal), x0s, config.n_demos)
        demo_ctrl = jax.vmap(fit_demo_controller)(DX, DU)

        controllers = stack(initial)
        X, U = rollouts(key_init, dynamics, controllers, x0s, config.n_samples)
        buffer = jax.vmap(
            lambda c: init_buffer(capacity, config.n_iterations + 1, T, dX, dU, x0s.dtype)
        )(jnp.arange(C))
        buffer = jax.vmap(buffer_add)(buffer, controllers, X, U)

        state = learner.init(key_net)
        norm = update_normaliser(state.params.norm, jnp.concatenate([DX, X], axis=1))
        state = state.replace(params=state.params.replace(norm=norm))
        fuse = jax.vmap(fusion_weighted_samples, in_axes=(0, 0, 0, 0, None))

        def model_sets(key, controllers, DX, DU):
            keys = jax.random.split(key, C)
            one = lambda k, c, x0, dx, du: model_weighted_samples(
                k, dynamics, c, x0, dx, du, config.n_samples
            )
            return jax.vmap(one)(keys, controllers, x0_dists, DX, DU)

        demo_entropy = jax.vmap(controller_entropy)(demo_ctrl)

        def calibrate(state: GCLState) -> GCLState:
            if config.temperature == "likelihood":
                return state
            raw = network.bind_residual(untempered(state.params))
            rho = jax.vmap(lambda X, U, H: calibrated_log_temperature(raw, dynamics, X, U, H))(
                DX, DU, demo_entropy
            )
            return state.replace(params=state.params.replace(log_temperature=rho.mean()))

        samples, demos = fuse(buffer, demo_ctrl, DX, DU, config.gcl)
        state, _ = learner.pretrain(state, key_pre, demos, samples)
        state = calibrate(state)

        def iteration(carry, key):
            state, buffer, controllers, eta, X, U = carry
            key_sample, key_cost, key_model = jax.random.split(key, 3)
            residual = network.bind_residual(state.params)

            def expand(X_c, U_c):
                quad = expand_cost_samples(residual, X_c, U_c, gauss_newton=True)
                return about_origin(quad, X_c.mean(0), U_c.mean(0))

            quads = jax.vmap(expand)(X, U)
            new, info = jax.vmap(maxent_c_step, in_axes=(None, 0, 0, 0, None, 0))(
                dynamics, quads, controllers, x0_dists, epsilon, eta
            )
            X, U = rollouts(key_sample, dynamics, new, x0s, config.n_samples)
            buffer = jax.vmap(buffer_add)(buffer, new, X, U)
            if config.sample_source == "model":
                samples, demos = model_sets(key_model, new, DX, DU)
            else:
                samples, demos = fuse(buffer, demo_ctrl, DX, DU, config.gcl)
            state, metrics = learner.update(state, key_cost, demos, samples)
            state = calibrate(state)
            true = jax.vmap(jax.vmap(true_traj_cost))(X, U).mean()
            out = (metrics.loss[-1], info.kl.mean(), true)
            return (state, buffer, new, info.eta, X, U), out

        eta0 = jnp.ones(C)
        carry = (state, buffer, controllers, eta0, X, U)
        keys = jax.random.split(key_loop, config.n_iterations)
        (state, _, controllers, _, _, _), (loss, kl, true) = jax.lax.scan(iteration, carry, keys)
        return TrainResult(gcl=state, controllers=controllers, loss=loss, kl=kl, true_cost=true)

    problem = dict(
        dynamics=dynamics,
        cost_true=cost_true,
        network=network,
        optimal=optimal,
        initial=initial,
        x0s=x0s,
        true_traj_cost=true_traj_cost,
    )
    return train, problem


def covariance_ratio(problem: dict, params) -> tuple[float, float]:
    """How the MaxEnt controller of the learned cost compares with the demonstrator's: the
    smallest and largest eigenvalue over t of ``Σ*^{-1/2} Σ Σ*^{-1/2}`` (1 and 1 when the action
    covariances agree). The learned cost is quadratic, so its expansion about 0 is exact."""
    dynamics, network = problem["dynamics"], problem["network"]
    T, dX, dU = dynamics.B.shape
    quad = expand_cost(network.bind(params), jnp.zeros((T + 1, dX)), jnp.zeros((T, dU)))
    learned = lqr_backward(dynamics, quad).controller.cov
    L = np.linalg.cholesky(np.asarray(problem["optimal"].cov))
    Linv = np.linalg.inv(L)
    eig = np.linalg.eigvalsh(Linv @ np.asarray(learned) @ np.swapaxes(Linv, -1, -2))
    return float(eig.min()), float(eig.max())


def evaluate(config: LQIOCConfig, problem: dict, result: TrainResult, key) -> dict:
    """Spearman and EPIC of the learned cost against the truth on held-out trajectories."""
    network = problem["network"]
    params = result.gcl.params
    C = problem["x0s"].shape[0]
    ctrls = heldout_controllers(problem["optimal"], problem["initial"])
    n_ctrl = ctrls.K.shape[0]
    key_roll, key_s, key_sn, key_a = jax.random.split(key, 4)

    def per_controller(key, ctrl):
        stacked = jax.tree.map(lambda a: jnp.broadcast_to(a, (C, *a.shape)), ctrl)
        return rollouts(key, problem["dynamics"], stacked, problem["x0s"], config.n_heldout)

    X, U = jax.vmap(per_controller)(jax.random.split(key_roll, n_ctrl), ctrls)
    dX, dU = X.shape[-1], U.shape[-1]
    X, U = X.reshape(-1, *X.shape[-2:]), U.reshape(-1, *U.shape[-2:])
    true = jax.vmap(problem["true_traj_cost"])(X, U)
    learned = jax.vmap(network.trajectory_cost, in_axes=(None, 0, 0))(params, X, U)

    Xs, Us, Xn = X[:, :-1].reshape(-1, dX), U.reshape(-1, dU), X[:, 1:].reshape(-1, dX)
    m = min(512, Xs.shape[0])
    S = jax.random.permutation(key_s, Xs)[:m]
    S_next = jax.random.permutation(key_sn, Xs)[:m]
    A = jax.random.permutation(key_a, Us)[:m]
    cost_true = problem["cost_true"]
    c_true = lambda x, u: cost_true(x, u, 0)
    c_learned = lambda x, u: network.cost(params, x, u, 0)
    epic = epic_distance(
        step_cost_as_transition_cost(c_true),
        step_cost_as_transition_cost(c_learned),
        Xs,
        Us,
        Xn,
        S,
        A,
        S_next,
        gamma=1.0,
    )
    pearson = pearson_distance(jax.vmap(c_true)(Xs, Us), jax.vmap(c_learned)(Xs, Us))
    ratio_min, ratio_max = covariance_ratio(problem, params)
    return dict(
        covariance_ratio_min=ratio_min,
        covariance_ratio_max=ratio_max,
        log_temperature=float(params.log_temperature),
        spearman=spearman(true, learned),
        epic_distance=float(epic),
        pearson_distance=float(pearson),
        action_weight=float(network.action_weight(params)),
        final_true_cost=float(result.true_cost[-1]),
        demo_true_cost=None,
    )


def _gcl(**change):
    return lambda c: dataclasses.replace(c, gcl=dataclasses.replace(c.gcl, **change))


def _mlp(c: LQIOCConfig) -> LQIOCConfig:
    """A GCL-sized ReLU network (2 × 32 units, 16 features) next to linear features, with
    decoupled weight decay on the MLP and ``A`` (Adam settings as tuned for it on seed 0)."""
    network = dataclasses.replace(
        c.network, hidden=(32, 32), n_features=16, a_scale=0.3, linear_skip=True
    )
    gcl = dataclasses.replace(c.gcl, weight_decay=1.0, learning_rate=1e-2, n_steps=50)
    return dataclasses.replace(c, network=network, gcl=gcl)


VARIANTS = {
    "full": lambda c: c,
    "no_fusion": _gcl(fusion=False),
    "no_demos_in_partition": _gcl(demos_in_partition=False),
    "no_lcr": _gcl(lcr_weight=0.0),
    "seed_model_samples": lambda c: dataclasses.replace(c, sample_source="model"),
    "mlp_32x32_skip_wd1": _mlp,
}


def run(config: LQIOCConfig, seeds: list[int]) -> dict:
    """Train and evaluate on each seed (vmapped); returns per-seed and mean figures."""
    train, problem = make_train(config)
    keys = jax.vmap(jax.random.key)(jnp.asarray(seeds))
    start = time.perf_counter()
    results = jax.jit(jax.vmap(train))(keys)
    jax.block_until_ready(results)
    seconds = time.perf_counter() - start
    per_seed = []
    for i, seed in enumerate(seeds):
        one = jax.tree.map(lambda a, i=i: a[i], results)
        figures = evaluate(config, problem, one, jax.random.key(10_000 + seed))
        optimal = problem["optimal"]
        stacked = jax.tree.map(lambda a: jnp.broadcast_to(a, (4, *a.shape)), optimal)
        Xd, Ud = rollouts(
            jax.random.key(20_000 + seed), problem["dynamics"], stacked, problem["x0s"], 50
        )
        figures["demo_true_cost"] = float(
            jax.vmap(jax.vmap(problem["true_traj_cost"]))(Xd, Ud).mean()
        )
        figures["true_cost_per_iteration"] = np.asarray(one.true_cost).round(3).tolist()
        per_seed.append(figures)
    keys = ("spearman", "epic_distance", "final_true_cost", "demo_true_cost")
    mean = {k: float(np.mean([f[k] for f in per_seed])) for k in keys}
    worst = {
        "spearman_min": min(f["spearman"] for f in per_seed),
        "epic_distance_max": max(f["epic_distance"] for f in per_seed),
        "covariance_ratio_min": min(f["covariance_ratio_min"] for f in per_seed),
        "covariance_ratio_max": max(f["covariance_ratio_max"] for f in per_seed),
    }
    return dict(**mean, **worst, seeds=seeds, per_seed=per_seed, train_seconds=seconds)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the figures to this path")
    parser.add_argument("--fast", action="store_true", help="small setting (used by the tests)")
    parser.add_argument("--seeds", type=int, default=None, help="number of seeds")
    parser.add_argument("--no-ablation", action="store_true")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    from diffgcl.runtime import prepare_process

    prepare_process()
    config = fast_config() if args.fast else default_config()
    seeds = list(range(args.seeds or (2 if args.fast else 4)))
    out = run(config, seeds)
    print(
        f"full: spearman {out['spearman']:.3f}  EPIC {out['epic_distance']:.3f}  "
        f"({out['train_seconds']:.1f} s incl. compile)"
    )
    if not args.no_ablation:
        table = {"full": out}
        for name, change in list(VARIANTS.items())[1:]:
            table[name] = run(change(config), seeds)
        print(f"\nablation over seeds {seeds}: mean (worst seed); true cost of the last controller")
        print(f"{'variant':<24}{'spearman':>15}{'EPIC':>15}{'true cost':>11}{'demos':>8}")
        for name, r in table.items():
            print(
                f"{name:<24}{r['spearman']:>8.3f} ({r['spearman_min']:.3f})"
                f"{r['epic_distance']:>8.3f} ({r['epic_distance_max']:.3f})"
                f"{r['final_true_cost']:>11.2f}{r['demo_true_cost']:>8.2f}"
            )
        fields = ("spearman", "spearman_min", "epic_distance", "epic_distance_max")
        fields += ("final_true_cost", "demo_true_cost")
        out["ablation"] = {name: {k: r[k] for k in fields} for name, r in table.items()}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return out


if __name__ == "__main__":
    main()
