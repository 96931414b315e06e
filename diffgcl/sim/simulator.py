"""The simulator stage: the one place where an env's ``step``, its Jacobian and ``obs`` run.

Every algorithm (GPS, MDGPS, rGCL, the re-optimisation check, the evaluations) asks a
:class:`Simulator` for what it needs from the physics — rollouts of linear-Gaussian controllers,
rollouts of a global policy, Jacobians of ``step`` along mean trajectories, observations and their
Jacobians — and does the rest (cost expansions, LQR, cost learning, S-steps) as pure maths on the
results. Why a stage of its own: XLA compiles a program's every call site of ``mjx.step`` again
(a nested ``jit`` is inlined), and one ``mjx.step`` is thousands of operations, its forward-mode
Jacobian about twice that; an rGCL iteration that rolled out at three places and linearised at a
fourth compiled the simulator four times over (``docs/compile.md``). Here all the rollouts of an
iteration go through one batched call, so a program holds each kernel once.

Two modes, the same numbers (``tests/test_simulator.py``):

* **fused** (``staged=False``, the default): the methods are plain vmapped JAX functions, traced
  into the caller's program — what a pure ``train`` and ``jax.jit(jax.vmap(train))`` use;
* **staged** (``staged=True``): every method runs a separately compiled program of the env over
  chunks of a fixed size of the flattened batch (:attr:`Simulator.CHUNKS`), so that calls of any
  batch shape share it. Host code (the runners) calls them between the algorithm's jitted update
  programs: the simulator is then compiled once per env and kind and shared by every algorithm,
  entry point and process (through the persistent compilation cache).

Batched methods take arrays with any number of leading axes, the same on every argument; the
policy's parameters may carry fewer (a prefix: one set per seed, shared by that seed's rollouts).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from diffgcl.tracing import value_and_jacfwd
from diffgcl.types import Array, Env, LinearGaussianController, Trajectory

# ---- kernels for one instance -------------------------------------------------------------------


def controller_rollout(env: Env, K, k, chol, x0: Array, noise: Array) -> tuple[Array, Array]:
    """``u_t = K_t x_t + k_t + chol_t ε_t`` from ``x0: [dX]`` with ``noise ε: [T, dU]``:
    X [T+1, dX], U [T, dU]."""

    def body(x, inputs):
        K_t, k_t, chol_t, eps = inputs
        u = K_t @ x + k_t + chol_t @ eps
        return env.step(x, u), (x, u)

    x_final, (X, U) = lax.scan(body, x0, (K, k, chol, noise))
    return jnp.concatenate([X, x_final[None]], axis=0), U


def trajectory_jacobians(env: Env, X: Array, U: Array) -> tuple[Array, Array]:
    """``A_t, B_t = ∂step/∂(x, u)`` at ``(X_t, U_t)``, t = 0 .. T−1 (forward mode): X [T+1, dX],
    U [T, dU] -> A [T, dX, dX], B [T, dX, dU]."""
    from diffgcl.dynamics.autodiff import linearize_trajectory

    return linearize_trajectory(env.step, X, U)


def observed_rollout(env: Env, act, x0: Array, noise: Array, obs_key) -> Trajectory:
    """``u_t = act(o_t, ε_t)`` on the env's observations (noisy sensors when ``obs_key`` is not
    None): X [T+1, dX], U [T, dU], O [T+1, dO] (what the actor saw; the last one noise-free)."""
    from diffgcl.sim.rollout import rollout_observed

    return rollout_observed(env, act, x0, noise, obs_key=obs_key)


# ---- batching over leading axes -----------------------------------------------------------------


def _flatten(tree, lead: tuple[int, ...]):
    n = int(np.prod(lead, dtype=int))
    return jax.tree.map(lambda a: jnp.reshape(a, (n, *a.shape[len(lead) :])), tree)


def _unflatten(tree, lead: tuple[int, ...]):
    return jax.tree.map(lambda a: jnp.reshape(a, (*lead, *a.shape[1:])), tree)


def _broadcast_shared(tree, lead: tuple[int, ...], shared: int):
    """Broadcast the leaves of ``tree``, whose leading axes are ``lead`` without its last
    ``shared`` axes, to all of ``lead``."""
    own = lead[: len(lead) - shared]

    def one(a):
        if tuple(a.shape[: len(own)]) != own:
            raise ValueError(
                f"simulator: parameters with leading axes {a.shape[: len(own)]}, expected {own} "
                f"(the batch {lead} without its last {shared})"
            )
        a = jnp.reshape(a, (*own, *(1,) * shared, *a.shape[len(own) :]))
        return jnp.broadcast_to(a, (*lead, *a.shape[len(lead) :]))

    return jax.tree.map(one, tree)


class Simulator:
    """Batched simulation of ``env`` (see the module docstring); ``staged`` runs each method as a
    separately compiled program from host code."""

    #: Staged programs run over batches of this many rollouts / trajectories / states (rounded
    #: up to a multiple of the device count): one compiled program per kind for any batch.
    CHUNKS = {
        "controller_rollouts": 32,
        "policy_rollouts": 32,
        "jacobians": 8,
        "observations": 1024,
        "observations_noisy": 1024,
        "observation_jacobians": 256,
    }

    def __init__(self, env: Env, *, staged: bool = False, chunks: dict | None = None):
        self.env = env
        self.staged = staged
        self.chunks = {**self.CHUNKS, **(chunks or {})}
        self._programs: dict = {}

    def __repr__(self) -> str:
        return f"Simulator({self.env.name!r}, staged={self.staged})"

    # ---- the batched methods ---------------------------------------------------------------

    def controller_rollouts(
        self, controller: LinearGaussianController, x0: Array, noise: Array
    ) -> Trajectory:
        """Rollouts of controllers (fields [..., T, ...]) from ``x0: [..., dX]`` with standard
        normal ``noise: [..., T, dU]`` (zeros: the noise-free rollout): X [..., T+1, dX],
        U [..., T, dU], O [..., T+1, 0]."""
        env = self.env
        lead = tuple(x0.shape[:-1])
        inputs = (controller.K, controller.k, controller.chol_cov, x0, noise)
        kernel = lambda K, k, chol, x, eps: controller_rollout(env, K, k, chol, x, eps)
        X, U = self._run("controller_rollouts", kernel, inputs, lead)
        return Trajectory(X=X, U=U, O=jnp.zeros((*X.shape[:-1], 0), X.dtype))

    def jacobians(self, X: Array, U: Array) -> tuple[Array, Array]:
        """Jacobians of ``step`` along trajectories X [..., T+1, dX], U [..., T, dU]:
        A [..., T, dX, dX], B [..., T, dX, dU]."""
        env = self.env
        kernel = lambda X, U: trajectory_jacobians(env, X, U)
        return self._run("jacobians", kernel, (X, U), tuple(X.shape[:-2]))

    def policy_rollouts(
        self,
        act: Callable,
        params,
        x0: Array,
        noise: Array,
        obs_key: Array | None = None,
        *,
        shared: int,
        name=("policy",),
    ) -> Trajectory:
        """Rollouts of ``u_t = act(params, o_t, ε_t)`` from ``x0: [..., dX]`` with ``noise:
        [..., T, dU]``; ``params`` (a pytree) with the leading axes of x0 but its last ``shared``
        (one set of parameters shared by that many trailing batch axes, e.g. a seed's
        conditions and samples); ``obs_key: [..., 2]`` noisy sensors (None: exact). ``name``
        (hashable) identifies the policy function: staged calls with the same name share one
        compiled program (:func:`diffgcl.algorithms.mdgps.policy_actor` names a policy by its
        settings and the env's sizes)."""
        env = self.env
        lead = tuple(x0.shape[:-1])
        keys = obs_key if obs_key is not None else jnp.zeros((*lead, 0), jnp.uint32)

        def kernel(p, x, eps, k):
            return observed_rollout(
                env, lambda o, e: act(p, o, e), x, eps, None if obs_key is None else k
            )

        if self.staged:
            params = _broadcast_shared(params, lead, shared)
            program = ("policy_rollouts", name, obs_key is None)
            return self._run_staged(program, kernel, (params, x0, noise, keys), lead)
        # Fused: one set of parameters per leading batch entry, vmapped over the shared axes.
        own, inner = lead[: len(lead) - shared], lead[len(lead) - shared :]
        n_own, n_inner = int(np.prod(own, dtype=int)), int(np.prod(inner, dtype=int))
        p = jax.tree.map(lambda a: jnp.reshape(a, (n_own, *a.shape[len(own) :])), params)
        x, e, k = jax.tree.map(
            lambda a: jnp.reshape(a, (n_own, n_inner, *a.shape[len(lead) :])), (x0, noise, keys)
        )
        inner_map = lambda p, x, e, k: jax.vmap(lambda x, e, k: kernel(p, x, e, k))(x, e, k)
        out = jax.vmap(inner_map)(p, x, e, k)
        return jax.tree.map(lambda a: jnp.reshape(a, (*lead, *a.shape[2:])), out)

    def observations(self, X: Array, keys: Array | None = None) -> Array:
        """``env.obs`` of states X [..., dX] (noisy sensors with ``keys: [..., 2]``): [..., dO]."""
        env = self.env
        lead = tuple(X.shape[:-1])
        if keys is None:
            return self._run("observations", lambda x: env.obs(x), (X,), lead)
        return self._run("observations_noisy", lambda x, k: env.obs(x, k), (X, keys), lead)

    def observation_jacobians(self, X: Array) -> tuple[Array, Array]:
        """Noise-free ``o(x)`` and ``∂o/∂x`` (forward mode) at states X [..., dX]: [..., dO],
        [..., dO, dX]."""
        env = self.env

        kernel = value_and_jacfwd(lambda x: env.obs(x))
        return self._run("observation_jacobians", kernel, (X,), tuple(X.shape[:-1]))

    # ---- running a kernel over a batch -------------------------------------------------------

    def _run(self, name, kernel, inputs, lead: tuple[int, ...]):
        if not self.staged:
            flat = _flatten(inputs, lead)
            out = jax.vmap(kernel)(*flat)
            return _unflatten(out, lead)
        return self._run_staged(name, kernel, inputs, lead)

    def _run_staged(self, name, kernel, inputs, lead: tuple[int, ...]):
        """``kernel`` vmapped over the flattened batch, as one compiled program over chunks of
        a fixed size (the last padded with copies of the first element: a valid state,
        controller and key), however large the batch: every call of this kind shares it.

        The chunks are split over this process's devices only: a staged result is a host array,
        and in a run of several processes each one computes the whole batch itself (the same in
        every process), where a mesh over all processes' devices would leave it slices it cannot
        read."""
        from diffgcl.sim.sharding import batch_mesh, shard_batch

        mesh = batch_mesh(jax.local_devices())
        devices = mesh.devices.size
        n = int(np.prod(lead, dtype=int))
        kind = name if isinstance(name, str) else name[0]
        chunk = int(math.ceil(self.chunks[kind] / devices) * devices)
        flat = jax.tree.map(lambda a: np.asarray(a).reshape(n, *np.shape(a)[len(lead) :]), inputs)
        total = max(chunk, int(math.ceil(n / chunk)) * chunk)
        padded = jax.tree.map(
            lambda a: np.concatenate([a, np.repeat(a[:1], total - n, axis=0)]) if total > n else a,
            flat,
        )
        key = (name, chunk, jax.tree.structure(padded))
        key += tuple((a.shape[1:], a.dtype) for a in jax.tree.leaves(padded))
        program = self._programs.get(key)
        if program is None:
            program = jax.jit(jax.vmap(kernel))
            self._programs[key] = program
        outs = []
        for start in range(0, total, chunk):
            part = jax.tree.map(lambda a, start=start: a[start : start + chunk], padded)
            if devices > 1:
                part = shard_batch(part, mesh)
            outs.append(program(*part))
        out = jax.tree.map(lambda *a: np.concatenate([np.asarray(x) for x in a])[:n], *outs)
        return jax.tree.map(lambda a: jnp.reshape(a, (*lead, *a.shape[1:])), out)
