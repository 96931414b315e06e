"""Tiny stand-in tasks the tests share: a 2-D double integrator with a known cost (plain JAX,
no MJX, so that every program compiles in seconds) and a small rGCL configuration for it."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.algorithms.gps import GPSConfig, make_gps
from diffgcl.algorithms.rgcl import RGCLConfig, demo_batch
from diffgcl.costs.gcl import GCLConfig
from diffgcl.costs.network import CostNetworkConfig


@dataclass(frozen=True)
class Slider:
    """A point in the plane pushed by a force (x = [p, v], u = force), start (1.5, −1) at rest;
    the task is to reach the origin and stay."""

    name: str = "slider"
    dX: int = 4
    dU: int = 2
    dO: int = 0
    dt: float = 0.1
    horizon: int = 15
    mjcf_path: str = ""
    success_tolerance: float = 0.15

    @property
    def target(self):
        return jnp.zeros(2)

    def step(self, x, u):
        v = x[2:] + self.dt * u
        return jnp.concatenate([x[:2] + self.dt * v, v])

    def obs(self, x, key=None):
        return jnp.zeros((0,), x.dtype)

    def initial_states(self):
        return jnp.array([[1.5, -1.0, 0.0, 0.0]])

    def expert_cost(self, x, u, t):
        return jnp.sum(x[:2] ** 2) + 0.1 * jnp.sum(x[2:] ** 2) + 1e-3 * jnp.sum(u**2)

    def success(self, X):
        return jnp.all(jnp.abs(X[-3:, :2]) < self.success_tolerance)


def tiny_config(schedule: str = "v2", **changes) -> RGCLConfig:
    config = RGCLConfig(
        schedule=schedule,
        iterations=8 if schedule == "v2" else 4,
        gps_per_update=2,
        gps=GPSConfig(num_samples=5, kl_step=1.0, init_var=1.0, gauss_newton=True),
        network=CostNetworkConfig(hidden=(16,), n_features=8, action_weight=1e-2),
        gcl=GCLConfig(
            n_steps=10, pretrain_steps=50, learning_rate=1e-2, lcr_weight=1e-3, mono_weight=1.0
        ),
        buffer_controllers=6,
        freeze_last=1,
        reopt_iterations=8,
    )
    return dataclasses.replace(config, **changes)


def slider_task():
    """The slider and 8 expert demos from GPS on its known cost: (env, DemoBatch)."""
    from diffgcl.algorithms.expert import make_demo_set, sample_expert

    env = Slider()
    gps = make_gps(GPSConfig(iterations=8, init_var=1.0, kl_step=1.0), env, env.expert_cost)
    state, metrics = jax.jit(gps.train)(jax.random.PRNGKey(0))
    assert bool(metrics.success[-1].all())
    traj, cond = sample_expert(
        env, state.controller, env.initial_states(), jax.random.PRNGKey(1), 8, smooth_sigma=None
    )
    demos = make_demo_set(env, traj, np.asarray(cond), cost=env.expert_cost)
    return env, demo_batch(demos, 1)
