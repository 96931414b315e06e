"""Sharding of batch axes (samples, conditions, seeds, hyperparameters) over all devices.

Batched functions are plain ``jit(vmap(f))``; placing their inputs with a leading axis split
over a one-dimensional device mesh lets XLA partition the whole program (GSPMD), so the same
code runs on one CPU, on ``--xla_force_host_platform_device_count=N`` CPU devices (how the tests
exercise it), on several GPUs, and across hosts after ``jax.distributed.initialize()``.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

BATCH_AXIS = "batch"


def batch_mesh(devices=None) -> Mesh:
    """A 1-D mesh named ``"batch"`` over ``devices`` (default: every device of every host)."""
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devices), (BATCH_AXIS,))


def shard_batch(tree, mesh: Mesh | None = None):
    """Place every array of ``tree`` with its leading axis split over the mesh.

    The leading axis must be divisible by the number of devices; arrays with no leading axis
    (scalars) are replicated.
    """
    mesh = batch_mesh() if mesh is None else mesh
    n = mesh.devices.size

    def place(a):
        if np.ndim(a) == 0:
            return jax.device_put(a, NamedSharding(mesh, PartitionSpec()))
        if a.shape[0] % n:
            raise ValueError(
                f"shard_batch: leading axis {a.shape[0]} is not divisible by {n} devices"
            )
        return jax.device_put(a, NamedSharding(mesh, PartitionSpec(BATCH_AXIS)))

    return jax.tree.map(place, tree)


def shard_batch_if_even(tree, mesh: Mesh | None = None):
    """:func:`shard_batch` when every leading axis divides evenly over the devices (and there is
    more than one), else ``tree`` unchanged (it then runs on the default device)."""
    mesh = batch_mesh() if mesh is None else mesh
    n = mesh.devices.size
    sizes = {np.shape(a)[0] for a in jax.tree.leaves(tree) if np.ndim(a) > 0}
    if n == 1 or not sizes or any(size % n for size in sizes):
        return tree
    return shard_batch(tree, mesh)


def vmap_over_devices(fn, in_axes=0, mesh: Mesh | None = None):
    """``jax.vmap(fn, in_axes)`` with the batch split over the devices by ``shard_map``.

    Each device runs the vmapped program on its own slice of the batch with no communication —
    right for batches of independent runs (seeds, hyperparameters). Plain GSPMD partitioning of
    ``jit(vmap(f))`` is not: it all-gathered the batch inside ``lax.top_k`` (the GCL minibatch
    draw) at every Adam step, with a rendezvous of the devices each time. ``in_axes``: 0 (batched)
    or None (replicated) per positional argument; outputs are batched along axis 0. Falls back to
    the plain ``vmap`` on one device or when a batch does not divide evenly. Jit the result.
    """

    def batched(*args):
        m = batch_mesh() if mesh is None else mesh
        axes = in_axes if isinstance(in_axes, tuple) else (in_axes,) * len(args)
        if any(a not in (0, None) for a in axes):
            raise ValueError(f"vmap_over_devices: in_axes must be 0 or None, got {in_axes}")
        vmapped = jax.vmap(fn, in_axes=axes)
        n = m.devices.size
        sizes = {
            np.shape(leaf)[0]
            for arg, a in zip(args, axes, strict=True)
            if a == 0
            for leaf in jax.tree.leaves(arg)
        }
        if n == 1 or any(size % n for size in sizes):
            return vmapped(*args)
        specs = tuple(PartitionSpec(BATCH_AXIS) if a == 0 else PartitionSpec() for a in axes)
        return jax.shard_map(
            vmapped, mesh=m, in_specs=specs, out_specs=PartitionSpec(BATCH_AXIS), check_vma=False
        )(*args)

    return batched


def replicate(tree, mesh: Mesh | None = None):
    """Place every array of ``tree`` whole on every device of the mesh."""
    mesh = batch_mesh() if mesh is None else mesh
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))
