"""Environment registry: ``make_env(name, **options)``; tests iterate over :data:`ENV_NAMES`."""

from __future__ import annotations

import importlib

from diffgcl.types import Env

# name -> "module:factory"; factories take keyword options and return an :class:`Env`.
_REGISTRY: dict[str, str] = {
    "arm": "diffgcl.envs.arm:make_arm_env",
    "hull": "diffgcl.envs.hull:make_hull_env",
    "usv": "diffgcl.envs.usv:make_usv_env",
    # Any MJCF file: make_env("mjcf", mjcf=PATH, ...); without a path the free-flying space robot.
    "mjcf": "diffgcl.envs.mjcf_env:make_mjcf_env",
}
ENV_NAMES: tuple[str, ...] = tuple(_REGISTRY)


def make_env(name: str, **options) -> Env:
    """Build a registered environment. The float precision follows ``jax_enable_x64``."""
    try:
        target = _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown env {name!r}; registered: {', '.join(ENV_NAMES)}") from None
    module, factory = target.split(":")
    return getattr(importlib.import_module(module), factory)(**options)
