"""Demonstration datasets: validated once on the host, then used as pytrees.

On disk a dataset is a folder with two files:

* ``demos.npz`` — arrays ``X: [N, T+1, dX]`` states, ``U: [N, T, dU]`` actions,
  ``O: [N, T+1, dO]`` observations (``dO`` may be 0), ``mask: [N, T+1]`` validity (1 = the step
  was observed; a masked step must not enter a loss);
* ``meta.json`` — ``{"format": "diffgcl-demos/1", "env": str, "dt": float, "episodes": [dict]}``,
  one metadata dict per episode (source file, time span, obstacle, swerve side, set, seed, ...).

Files are written through :func:`diffgcl.io.write_folder` (kind :data:`DEMO_FOLDER`): a crash
never leaves half a dataset, an earlier dataset in the folder is replaced atomically, and a folder
holding anything else is refused (or, with ``overwrite``, only ``demos.npz`` and ``meta.json``
are replaced in it).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from diffgcl.io import FolderKind, write_folder

FORMAT = "diffgcl-demos/1"
FILES = ("demos.npz", "meta.json")


def _owned_files(folder: Path) -> frozenset[str] | None:
    """The files a dataset folder got from :meth:`DemoSet.save`, None if it is not a dataset."""
    try:
        meta = json.loads((folder / "meta.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        return None
    return frozenset(FILES)


DEMO_FOLDER = FolderKind("demo dataset", _owned_files, marker="meta.json")


class DemoError(ValueError):
    """A demonstration dataset is inconsistent (shape, NaN, missing file)."""


@dataclass(frozen=True)
class DemoSet:
    """A frozen, validated set of demonstrations (NumPy arrays; see module docstring)."""

    X: np.ndarray
    U: np.ndarray
    O: np.ndarray
    mask: np.ndarray
    dt: float
    env: str
    episodes: tuple[dict[str, Any], ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        X, U, O, mask = self.X, self.U, self.O, self.mask
        if X.ndim != 3 or U.ndim != 3 or O.ndim != 3:
            raise DemoError(
                f"demos: X, U, O must be [N, T(+1), d]; got X{X.shape}, U{U.shape}, O{O.shape}"
            )
        n, t1, _ = X.shape
        if U.shape[:2] != (n, t1 - 1):
            raise DemoError(
                f"demos: U must be [{n}, {t1 - 1}, dU] to match X{X.shape}; got {U.shape}"
            )
        if O.shape[:2] != (n, t1):
            raise DemoError(f"demos: O must be [{n}, {t1}, dO] to match X{X.shape}; got {O.shape}")
        if mask.shape != (n, t1):
            raise DemoError(f"demos: mask must be [{n}, {t1}]; got {mask.shape}")
        if not self.dt > 0:
            raise DemoError(f"demos: dt must be positive; got {self.dt}")
        if len(self.episodes) not in (0, n):
            raise DemoError(f"demos: {len(self.episodes)} metadata entries for {n} episodes")
        valid = mask.astype(bool)
        for name, arr, m in (("X", X, valid), ("U", U, valid[:, :-1]), ("O", O, valid)):
            bad = ~np.isfinite(arr) & m[..., None]
            if bad.any():
                i, t, j = np.argwhere(bad)[0]
                raise DemoError(f"demos: non-finite {name}[{i}, {t}, {j}] at a valid step")
        for name in ("X", "U", "O", "mask"):
            getattr(self, name).setflags(write=False)

    @property
    def num_episodes(self) -> int:
        return self.X.shape[0]

    @property
    def horizon(self) -> int:
        return self.U.shape[1]

    def save(self, directory: str | os.PathLike, overwrite: bool = False) -> Path:
        """Write ``demos.npz`` and ``meta.json`` into ``directory`` (rules of
        :func:`diffgcl.io.write_folder`: a non-empty folder that is not a dataset raises
        :class:`diffgcl.io.OutputError` unless ``overwrite``)."""
        meta = {"format": FORMAT, "env": self.env, "dt": self.dt, "episodes": self.episodes}
        text = json.dumps(meta, indent=1, default=_json_default)
        with write_folder(directory, DEMO_FOLDER, overwrite) as tmp:
            np.savez_compressed(tmp / "demos.npz", X=self.X, U=self.U, O=self.O, mask=self.mask)
            (tmp / "meta.json").write_text(text)
        return Path(directory)

    @classmethod
    def load(cls, directory: str | os.PathLike) -> DemoSet:
        """Read a dataset written by :meth:`save`; errors name the file."""
        folder = Path(directory)
        for name in ("demos.npz", "meta.json"):
            if not (folder / name).is_file():
                raise DemoError(f"{folder}: not a demo dataset (missing {name})")
        meta = json.loads((folder / "meta.json").read_text())
        if meta.get("format") != FORMAT:
            raise DemoError(f"{folder / 'meta.json'}: format {meta.get('format')!r}, want {FORMAT}")
        with np.load(folder / "demos.npz") as arrays:
            data = {k: arrays[k] for k in ("X", "U", "O", "mask")}
        return cls(dt=float(meta["dt"]), env=meta["env"], episodes=tuple(meta["episodes"]), **data)

    def subset(self, index) -> DemoSet:
        """Episodes selected by an index array or slice."""
        idx = np.arange(self.num_episodes)[index]
        return DemoSet(
            X=self.X[idx],
            U=self.U[idx],
            O=self.O[idx],
            mask=self.mask[idx],
            dt=self.dt,
            env=self.env,
            episodes=tuple(self.episodes[i] for i in idx) if self.episodes else (),
        )


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot store {type(value).__name__} in demo metadata")
