"""The one place that resolves and loads MJCF files, with errors that name the file."""

from __future__ import annotations

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx


class MJCFError(ValueError):
    """An MJCF file is missing, malformed, or does not fit the environment that loads it."""


def models_dir() -> Path:
    """The repository's ``models/`` folder (override with ``$DIFFGCL_MODELS``)."""
    env = os.environ.get("DIFFGCL_MODELS")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "models"


def resolve_mjcf(name_or_path: str | os.PathLike) -> Path:
    """``"arm2d.xml"`` → ``models/arm2d.xml``; an existing path is returned as is."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    candidate = models_dir() / path
    if candidate.is_file():
        return candidate
    raise MJCFError(f"{name_or_path}: MJCF file not found (looked in {models_dir()})")


def load_mjcf(name_or_path: str | os.PathLike) -> mujoco.MjModel:
    """Compile an MJCF file with C MuJoCo; a parse or compile error names the file."""
    path = resolve_mjcf(name_or_path)
    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as err:
        raise MJCFError(f"{path}: cannot load MJCF: {err}") from None


def put_model(model: mujoco.MjModel) -> mjx.Model:
    """Copy a C model to an MJX model in the current default float precision, on this process's
    first device (see :func:`make_data`).

    MJX follows ``jax_enable_x64``: float64 when it is on, float32 otherwise.
    """
    mx = mjx.put_model(model, device=jax.local_devices()[0])
    dtype = jnp.zeros(()).dtype

    def cast(a):
        if isinstance(a, jax.Array | np.ndarray) and np.issubdtype(a.dtype, np.floating):
            return a.astype(dtype)
        return a

    return jax.tree.map(cast, mx)


def make_data(mx: mjx.Model) -> mjx.Data:
    """``mjx.make_data`` on this process's first device. MJX's default is ``jax.devices()[0]``,
    which in a multi-process run (:mod:`diffgcl.distributed`) belongs to process 0: the other
    processes could not even build an env (measured: "Number of addressable output shards must
    match", then "Cross-host transfers are not supported" with the model there too)."""
    return mjx.make_data(mx, device=jax.local_devices()[0])


def require(model: mujoco.MjModel, path: str | os.PathLike, **sizes: int) -> None:
    """Check model sizes (e.g. ``nq=2, nu=2``); a mismatch is an :class:`MJCFError`."""
    for field, expected in sizes.items():
        got = getattr(model, field)
        if got != expected:
            raise MJCFError(f"{path}: expected {field} = {expected}, the file has {got}")
