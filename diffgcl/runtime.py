"""Process-wide JAX settings shared by the CLI, the experiments and the tests.

Each distinct jitted program that differentiates through ``mjx.step`` costs 13–24 s to compile on
a 2-core CPU; JAX's persistent compilation cache brings a later process down to well under a
second, so every entry point turns it on.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax


def cache_root() -> Path:
    """Root of diffgcl's on-disk caches: ``$DIFFGCL_CACHE`` or ``~/.cache/diffgcl``."""
    return Path(os.environ.get("DIFFGCL_CACHE", Path.home() / ".cache" / "diffgcl"))


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Turn on JAX's persistent compilation cache (idempotent); returns its directory."""
    directory = Path(path) if path is not None else cache_root() / "jax"
    directory.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return directory
