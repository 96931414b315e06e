"""Host loops that run an algorithm's iterations in stages: the simulator as programs of its own.

Every algorithm splits an iteration into ``draw`` (pure: what to simulate), ``simulate`` (the
only part that runs the env, :class:`~diffgcl.sim.simulator.Simulator`) and ``update`` (pure:
everything else). Traced together into one program (``train``, ``run``), the simulator is
compiled into that program — and again into every other program that simulates: the expert's
GPS, rGCL's chunks, the re-optimisation check, the evaluations. Here ``draw`` and ``update``
are jitted (vmapped over seeds, split over the devices), and ``simulate`` runs on the host
with the env's staged simulator (:func:`staged_simulator`): its rollout and Jacobian programs
are compiled once per env and kind and shared by every algorithm and call in the
process, and through the persistent compilation cache by every later process.

The results equal the traced programs' (``tests/test_simulator.py``); the cost is a few
program dispatches per iteration (under a millisecond each) and the simulator's inputs and
outputs passing through host memory.
"""

from __future__ import annotations

import functools
import weakref

import jax
import numpy as np

from diffgcl.eval.policy import rollout_sensor_keys
from diffgcl.sim.sharding import vmap_over_devices
from diffgcl.sim.simulator import Simulator

_SIMULATORS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def staged_simulator(env) -> Simulator:
    """The process-wide staged :class:`Simulator` of ``env`` (one per env object, so that every
    caller shares its compiled programs)."""
    sim = _SIMULATORS.get(env)
    if sim is None:
        sim = Simulator(env, staged=True)
        _SIMULATORS[env] = sim
    return sim


def can_stage() -> bool:
    """Staged loops run in one process (several processes run the traced programs, whose
    batches XLA lays out over all their devices)."""
    return jax.process_count() == 1


def stack_metrics(metrics: list):
    """Per-iteration metrics [S, ...] -> [S, n, ...] (NumPy)."""
    return jax.tree.map(lambda *a: np.stack([np.asarray(x) for x in a], axis=1), *metrics)


class StagedLoop:
    """``n`` iterations of ``update(state, *args, simulate(sim, draw(state, *draw_args)))`` for
    a batch of seeds (every state leaf with a leading seed axis).

    draw(state, *draw_args) -> request and update(state, *args, sims) -> (state, metrics) are
    written for one seed; ``draw_axes`` / ``update_axes`` give the ``in_axes`` (0: per seed,
    None: shared) of their extra arguments. simulate(sim, request) takes the seed-batched
    request.
    """

    def __init__(self, draw, simulate, update, sim: Simulator, draw_axes=(), update_axes=()):
        self.simulate = simulate
        self.sim = sim
        self.draw = jax.jit(vmap_over_devices(draw, in_axes=(0, *draw_axes)))
        self.update = jax.jit(vmap_over_devices(update, in_axes=(0, *update_axes, 0)))

    def step(self, state, draw_args=(), update_args=()):
        request = self.draw(state, *draw_args)
        sims = self.simulate(self.sim, request)
        return self.update(state, *update_args, sims)

    def run(self, state, n: int, draw_args=(), update_args=()):
        """(state, metrics [S, n, ...] as NumPy) after ``n`` iterations."""
        metrics = []
        for _ in range(n):
            state, m = self.step(state, draw_args, update_args)
            metrics.append(m)
        return state, stack_metrics(metrics)


def noise_free_rollouts(env, controller, x0):
    """Noise-free rollouts of controllers (fields [..., C, T, ...]) from ``x0: [..., C, dX]``
    with the env's staged simulator: X [..., C, T+1, dX], U [..., C, T, dU] (NumPy)."""
    import jax.numpy as jnp

    T = controller.K.shape[-3]
    zeros = jnp.zeros((*x0.shape[:-1], T, env.dU), jnp.asarray(x0).dtype)
    traj = staged_simulator(env).controller_rollouts(controller, jnp.asarray(x0), zeros)
    return np.asarray(traj.X), np.asarray(traj.U)


def run_gps_seeds(gps, keys, iterations: int, env, update_args=(), update_axes=(), hparams=None):
    """GPS-like iterations for a batch of seeds as a staged loop (the same results as
    ``jax.vmap(gps.train)``): ``gps`` has ``init(key[, hparams])``, ``draw(state, key)``,
    ``simulate(sim, request)`` and ``update(state, *update_args, sims)`` (or, with a ``keyed``
    attribute that is true, ``update(state, key, *update_args, sims)`` with the iteration's
    key); with an ``initial_samples`` attribute (MDGPS), the samples ``init`` would simulate
    run on the staged simulator and their observations go to ``init(key, hparams, O)``;
    ``keys: [S, 2]`` (split into the init key and one key per iteration as ``train`` does).
    Returns (state, metrics [S, iterations, ...], X_final [S, C, T+1, dX]: the final
    controllers' noise-free rollouts)."""
    import jax.numpy as jnp

    def split(key):
        key_init, key_iter = jax.random.split(key)
        return key_init, jax.random.split(key_iter, iterations)

    key_init, key_iter = jax.jit(jax.vmap(split))(keys)
    sim = staged_simulator(env)
    args, axes = (key_init, hparams), (0, None if hparams is None else 0)
    initial_samples = getattr(gps, "initial_samples", None)
    if initial_samples is not None:  # MDGPS: the policy's first observations, staged
        samples = jax.jit(jax.vmap(initial_samples))(key_init)
        args, axes = (*args, gps.policy_phases.observe_initial(sim, samples)), (*axes, 0)
    state = jax.jit(jax.vmap(gps.init, in_axes=axes))(*args)
    keyed = getattr(gps, "keyed", False)
    axes = ((0,) if keyed else ()) + tuple(update_axes)
    loop = StagedLoop(gps.draw, gps.simulate, gps.update, sim, (0,), axes)
    metrics = []
    for i in range(iterations):
        args = ((key_iter[:, i],) if keyed else ()) + tuple(update_args)
        state, m = loop.step(state, (key_iter[:, i],), args)
        metrics.append(m)
    gps_state = state.gps if hasattr(state, "gps") else state
    X, _ = noise_free_rollouts(env, gps_state.controller, jnp.asarray(gps_state.x0))
    return state, stack_metrics(metrics), X


class StagedV1Loop(StagedLoop):
    """rGCL v1's iterations for a batch of seeds as a host loop (:class:`StagedLoop`'s ``run``,
    with ``draw_args=(key_loop,)`` and ``update_args=(key_loop, demos)``); one iteration (its
    ``step``) is ``begin``, then ``G`` times ``draw`` -> the staged simulator -> ``gps``, then
    ``finish`` (the cost update), each jitted over the seeds
    (:class:`~diffgcl.algorithms.rgcl.V1Parts`)."""

    def __init__(self, parts, sim: Simulator):  # the parts replace StagedLoop's draw and update
        self.parts, self.sim = parts, sim
        self.begin = jax.jit(vmap_over_devices(parts.begin, in_axes=(0, 0)))
        self.draw = jax.jit(vmap_over_devices(parts.draw, in_axes=(0, 0)))
        self.gps = jax.jit(vmap_over_devices(parts.gps, in_axes=(0, 0, 0, None, None, 0)))
        self.finish = jax.jit(vmap_over_devices(parts.finish, in_axes=(0, 0, 0, 0, None)))

    def step(self, state, draw_args=(), update_args=()):
        import jax.numpy as jnp

        (key_loop,), (_, demos) = draw_args, update_args
        carry, keys, key_cost = self.begin(state, key_loop)
        outs = []
        for g in range(self.parts.gps_iterations):
            key = keys[:, g]
            sims = self.parts.simulate(self.sim, self.draw(carry, key))
            carry, out = self.gps(state, carry, key, np.bool_(g == 0), demos, sims)
            outs.append(out)
        outs = jax.tree.map(lambda *a: jnp.stack(a, axis=1), *outs)
        return self.finish(state, carry, outs, key_cost, demos)


def rgcl_loop(rgcl, env) -> StagedLoop:
    """The staged host loop of an rGCL run (``rgcl`` from
    :func:`~diffgcl.algorithms.rgcl.make_train`), v1's or v2's, on ``env``'s staged simulator:
    ``run(state, n, draw_args=(key_loop,), update_args=(key_loop, demos))``."""
    sim = staged_simulator(env)
    if rgcl.v1 is not None:
        return StagedV1Loop(rgcl.v1, sim)
    return StagedLoop(rgcl.draw, rgcl.simulate, rgcl.update, sim, (0,), (0, None))


def run_rgcl(rgcl, keys, demos, env, hparams=None):
    """rGCL for a batch of seeds (``keys: [S, 2]``, ``rgcl`` from
    :func:`~diffgcl.algorithms.rgcl.make_train`) as a staged loop (:func:`rgcl_loop`). The same
    results as ``jax.vmap(rgcl.train, in_axes=(0, None))``: (state, metrics [S, iterations,
    ...])."""
    key_init, key_loop = jax.jit(jax.vmap(rgcl.split_key))(keys)
    if hparams is None:
        hp = rgcl.default_hparams()
        hparams = jax.tree.map(lambda a: np.broadcast_to(a, (keys.shape[0],)), hp)
    state = jax.jit(vmap_over_devices(rgcl.init, in_axes=(0, None, 0)))(key_init, demos, hparams)
    loop = rgcl_loop(rgcl, env)
    return loop.run(state, rgcl.iterations, draw_args=(key_loop,), update_args=(key_loop, demos))


@functools.partial(jax.jit, static_argnums=1)
def _rollout_obs_keys(keys, n: int):
    """[S, n, 2]: the sensor-noise keys of ``n`` rollouts per seed key (``keys: [S, 2]``)."""
    return jax.vmap(lambda key: rollout_sensor_keys(key, n))(keys)


def policy_rollouts(env, policy, params, x0, keys=None, *, obs_noise: bool = False):
    """Host side: noise-free-action rollouts [S, B] of global policies (``params`` with a
    leading seed axis S) from ``x0: [B, dX]`` with the env's staged simulator; with
    ``obs_noise``, sensor noise from one key per seed (``keys: [S, 2]``, drawn as
    :func:`diffgcl.eval.policy.policy_rollouts` draws it, so the rollouts are the same)."""
    import jax.numpy as jnp

    S = jax.tree.leaves(params)[0].shape[0]
    x0 = jnp.asarray(x0)
    B = x0.shape[0]
    x0 = jnp.broadcast_to(x0[None], (S, *x0.shape))
    zeros = jnp.zeros((S, B, env.horizon, env.dU), x0.dtype)
    obs_key = None
    if obs_noise:
        if keys is None:
            raise ValueError("policy_rollouts: sensor noise needs one key per seed")

        obs_key = _rollout_obs_keys(keys, B)
    sim = staged_simulator(env)
    return sim.policy_rollouts(
        policy.sample_action, params, x0, zeros, obs_key, shared=1, name=("policy", policy)
    )
