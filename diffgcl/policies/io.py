"""A trained global policy on disk: what a run hands to the robot.

``policy.npz`` holds the parameters (network weights, observation normaliser, action variance) as
named arrays, ``policy.json`` the network's shape (:class:`PolicyConfig`), the observation and
action sizes and where the policy came from. Reading it needs NumPy and this module only; the
policy is then ``GaussianPolicy.mean_action(params, o)``.

Both files are written under temporary names and renamed, and :func:`save_policy` writes only
these two files into the folder it is given (it never removes anything).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.policies.network import GaussianPolicy, PolicyConfig, PolicyParams

FORMAT = "diffgcl-policy/1"
PARAMS_FILE = "policy.npz"
META_FILE = "policy.json"


def _leaf_names(params: PolicyParams) -> list[str]:
    paths = jax.tree_util.tree_flatten_with_path(params)[0]
    return ["/".join(str(getattr(k, "key", getattr(k, "name", k))) for k in p) for p, _ in paths]


def save_policy(folder, policy: GaussianPolicy, params: PolicyParams, **info) -> Path:
    """Write ``policy.npz`` and ``policy.json`` into ``folder`` (created if missing); ``info``:
    JSON-able provenance (method, seed, env, ...). Returns the folder."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{folder}: exists and is not a folder")
    folder.mkdir(parents=True, exist_ok=True)
    arrays = dict(zip(_leaf_names(params), map(np.asarray, jax.tree.leaves(params)), strict=True))
    tmp = folder / f".{PARAMS_FILE}.tmp.npz"
    np.savez(tmp, **arrays)
    os.replace(tmp, folder / PARAMS_FILE)
    meta = {
        "format": FORMAT,
        "dO": policy.dO,
        "dU": policy.dU,
        "config": dataclasses.asdict(policy.config),
        "info": info,
    }
    tmp = folder / f".{META_FILE}.tmp"
    tmp.write_text(json.dumps(meta, indent=1, default=str))
    os.replace(tmp, folder / META_FILE)
    return folder


def load_policy(folder, dtype=None) -> tuple[GaussianPolicy, PolicyParams, dict]:
    """``(policy, params, info)`` from a folder written by :func:`save_policy`; errors name the
    file and what is wrong."""
    folder = Path(folder)
    for name in (PARAMS_FILE, META_FILE):
        if not (folder / name).is_file():
            raise ValueError(f"{folder}: not a saved policy (missing {name})")
    meta = json.loads((folder / META_FILE).read_text())
    if meta.get("format") != FORMAT:
        raise ValueError(f"{folder / META_FILE}: format {meta.get('format')!r}, want {FORMAT}")
    config = dict(meta["config"])
    config["hidden"] = tuple(config["hidden"])
    dtype = dtype or jnp.zeros(()).dtype
    policy = GaussianPolicy(PolicyConfig(**config), int(meta["dO"]), int(meta["dU"]), dtype)
    like = policy.init(jax.random.PRNGKey(0))
    names = _leaf_names(like)
    with np.load(folder / PARAMS_FILE) as f:
        missing = [n for n in names if n not in f.files]
        if missing:
            raise ValueError(f"{folder / PARAMS_FILE}: missing arrays {missing}")
        leaves = []
        for n, ref in zip(names, jax.tree.leaves(like), strict=True):
            if f[n].shape != ref.shape:
                raise ValueError(
                    f"{folder / PARAMS_FILE}: {n} has shape {f[n].shape}, expected {ref.shape}"
                )
            leaves.append(jnp.asarray(f[n], dtype))
    params = jax.tree.unflatten(jax.tree.structure(like), leaves)
    return policy, params, meta.get("info", {})
