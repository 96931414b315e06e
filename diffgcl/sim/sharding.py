"""Sharding of batch axes (samples, conditions, seeds, hyperparameters) over all devices.

Batched functions are plain ``jit(vmap(f))``; placing their inputs with a leading axis split
over a one-dimensional device mesh lets XLA partition the whole program (GSPMD), so the same
code runs on one CPU, on ``--xla_force_host_platform_device_count=N`` CPU devices (how the tests
exercise it), on several GPUs, and across processes after :func:`diffgcl.distributed.join`.

Several processes: the mesh spans the devices of all of them and each process holds only its own
slice of a batch. Every process builds the same whole batch on the host; :func:`shard_batch`
keeps each process's slice. A batch that does not divide over the devices cannot fall back to
one device there (each process would run the whole batch on its own), so it is an error.
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


def spans_processes(mesh: Mesh) -> bool:
    """Whether the mesh holds devices of more than one process."""
    return len({d.process_index for d in mesh.devices.flat}) > 1


def _indivisible(size: int, n: int, mesh: Mesh) -> str:
    processes = len({d.process_index for d in mesh.devices.flat})
    where = f"{n} devices" + (f" of {processes} processes" if processes > 1 else "")
    return f"a batch of {size} does not divide over the {where}"


def shard_batch(tree, mesh: Mesh | None = None):
    """Place every array of ``tree`` with its leading axis split over the mesh.

    The leading axis must be divisible by the number of devices; arrays with no leading axis
    (scalars) are replicated. On a mesh over several processes every process passes the same
    whole (host) batch and keeps its own slice; an array already laid out on the mesh is left
    as it is.
    """
    mesh = batch_mesh() if mesh is None else mesh
    n = mesh.devices.size
    several = spans_processes(mesh)

    def place(a):
        spec = PartitionSpec() if np.ndim(a) == 0 else PartitionSpec(BATCH_AXIS)
        if np.ndim(a) and a.shape[0] % n:
            raise ValueError(f"shard_batch: {_indivisible(a.shape[0], n, mesh)}")
        sharding = NamedSharding(mesh, spec)
        if not several or (isinstance(a, jax.Array) and a.sharding == sharding):
            return jax.device_put(a, sharding)
        host = np.asarray(a)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(place, tree)


def shard_batch_if_even(tree, mesh: Mesh | None = None):
    """:func:`shard_batch` when every leading axis divides evenly over the devices (and there is
    more than one), else ``tree`` unchanged (it then runs on the default device). On a mesh over
    several processes an uneven batch is a ValueError (see the module docstring)."""
    mesh = batch_mesh() if mesh is None else mesh
    n = mesh.devices.size
    sizes = {np.shape(a)[0] for a in jax.tree.leaves(tree) if np.ndim(a) > 0}
    uneven = [size for size in sizes if size % n]
    if uneven and spans_processes(mesh):
        raise ValueError(_indivisible(uneven[0], n, mesh))
    if n == 1 or not sizes or uneven:
        return tree
    return shard_batch(tree, mesh)


def vmap_over_devices(fn, in_axes=0, mesh: Mesh | None = None):
    """``jax.vmap(fn, in_axes)`` with the batch split over the devices by ``shard_map``.

    Each device runs the vmapped program on its own slice of the batch with no communication —
    right for batches of independent runs (seeds, hyperparameters). Plain GSPMD partitioning of
    ``jit(vmap(f))`` is not: it all-gathered the batch inside ``lax.top_k`` (the GCL minibatch
    draw) at every Adam step, with a rendezvous of the devices each time. ``in_axes``: 0 (batched)
    or None (replicated) per positional argument; outputs are batched along axis 0. Falls back to
    the plain ``vmap`` on one device or when a batch does not divide evenly (an error on a mesh
    over several processes). Jit the result.
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
        uneven = [size for size in sizes if size % n]
        if uneven and spans_processes(m):
            raise ValueError(f"vmap_over_devices: {_indivisible(uneven[0], n, m)}")
        if n == 1 or uneven:
            return vmapped(*args)
        specs = tuple(PartitionSpec(BATCH_AXIS) if a == 0 else PartitionSpec() for a in axes)
        return jax.shard_map(
            vmapped, mesh=m, in_specs=specs, out_specs=PartitionSpec(BATCH_AXIS), check_vma=False
        )(*args)

    # Named after ``fn``, so that compile logs and experiments/bench_compile.py tell the
    # programs apart.
    batched.__name__ = batched.__qualname__ = getattr(fn, "__name__", "batched")
    return batched


def replicate(tree, mesh: Mesh | None = None):
    """Place every array of ``tree`` whole on every device of the mesh."""
    mesh = batch_mesh() if mesh is None else mesh
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))
