"""Output folders: never delete or overwrite what the program did not write itself.

Every command that writes a folder (``bags convert``, ``bags synth``, ``demos``, ``train``, ...)
names what it writes with a :class:`FolderKind` and writes through :func:`write_folder`:

* ``out`` does not exist, or is an empty folder: the new contents appear at once (written into a
  temporary sibling folder, then renamed).
* ``out`` is a folder this kind wrote before and holds nothing else: it is replaced atomically
  (the old folder is renamed aside, the new one renamed into place, then the old one removed).
* ``out`` is a folder of this kind that also holds other files (a user's notes): only the entries
  this kind wrote are replaced or removed; everything else stays.
* ``out`` is a non-empty folder that is not of this kind (a home folder, ``--out .``): refused
  with :class:`OutputError` unless ``overwrite=True``; then the new entries replace entries of
  the same name and every other entry stays. Nothing else is ever deleted.
* ``out`` is a file: always an error.

:func:`check_output_folder` runs the same checks without writing, so that a command can refuse
before it spends minutes computing. :func:`check_output_file` is the rule for a single file.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path


class OutputError(ValueError):
    """Writing an output would lose data the program did not write. ``str()`` is one line."""


@dataclass(frozen=True)
class FolderKind:
    """What a command writes into its output folder.

    description: for messages ("demo dataset"); owned(folder): the paths (relative to the folder,
    files or folders) that an earlier run of this kind wrote into ``folder``, or None when the
    folder is not an output of this kind; marker: the file that makes a folder one of ours
    (written last and removed first when entries are replaced one by one).
    """

    description: str
    owned: Callable[[Path], Collection[str] | None]
    marker: str


# Working folders of write_folder itself (staging, replaced entries): never counted as content.
_WORK_PREFIXES = (".diffgcl-new-", ".diffgcl-old-")


def _entries(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if not p.name.startswith(_WORK_PREFIXES))


def _files_below(folder: Path) -> Iterator[str]:
    """Relative paths of every file (and symbolic link) below ``folder``, work folders aside."""
    for root, dirs, files in os.walk(folder):
        rel = Path(root).relative_to(folder)
        if rel == Path("."):
            dirs[:] = [d for d in dirs if not d.startswith(_WORK_PREFIXES)]
        for name in files + [d for d in dirs if Path(root, d).is_symlink()]:
            yield (rel / name).as_posix()


def _is_owned(rel: str, owned: Collection[str]) -> bool:
    parts = Path(rel).parts
    return any(Path(*parts[: i + 1]).as_posix() in owned for i in range(len(parts)))


@dataclass(frozen=True)
class _Plan:
    """How :func:`write_folder` will put the new contents in place."""

    mode: str  # "create" | "swap" | "merge"
    owned: frozenset[str]  # entries of an earlier run that may be replaced or removed


def _plan(out: Path, kind: FolderKind, overwrite: bool) -> _Plan:
    if out.is_symlink() and not out.exists():
        raise OutputError(f"{out}: a broken symbolic link; choose another output folder")
    if out.exists() and not out.is_dir():
        raise OutputError(
            f"{out}: is a file, not a folder; choose a folder for the {kind.description}"
        )
    if not out.exists():
        return _Plan("create", frozenset())
    entries = _entries(out)
    in_use = Path.cwd().resolve().is_relative_to(out.resolve())
    if not entries:
        return _Plan("merge" if in_use or out.is_symlink() else "swap", frozenset())
    owned = kind.owned(out)
    if owned is None:
        if not overwrite:
            names = ", ".join(p.name for p in entries[:4]) + (", ..." if len(entries) > 4 else "")
            raise OutputError(
                f"{out}: folder is not empty and not a {kind.description} (holds {names}); "
                "choose another output folder or pass --overwrite (replaces only the entries "
                "of the same name)"
            )
        return _Plan("merge", frozenset())
    owned = frozenset(Path(p).as_posix() for p in owned)
    only_ours = all(_is_owned(rel, owned) for rel in _files_below(out))
    mode = "swap" if only_ours and not in_use and not out.is_symlink() else "merge"
    return _Plan(mode, owned)


def check_output_folder(out: str | os.PathLike, kind: FolderKind, overwrite: bool = False) -> None:
    """Raise :class:`OutputError` when :func:`write_folder` would refuse ``out``."""
    _plan(Path(out), kind, overwrite)


@contextmanager
def write_folder(
    out: str | os.PathLike, kind: FolderKind, overwrite: bool = False
) -> Iterator[Path]:
    """Yield an empty staging folder; when the block succeeds its contents become ``out``.

    See the module docstring for the rules. On an exception inside the block the staging folder is
    removed and ``out`` is left as it was. The check is made on entry (before any work) and again
    before anything is moved.
    """
    out = Path(out)
    _plan(out, kind, overwrite)
    if out.exists():
        # Staged inside the folder itself: the same file system, and writable if out is.
        stage = Path(tempfile.mkdtemp(prefix=".diffgcl-new-", dir=out))
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.new-", dir=out.parent))
    try:
        yield stage
        plan = _plan(out, kind, overwrite)
        if plan.mode == "create":
            stage.rename(out)
        elif plan.mode == "swap" and os.access(out.parent, os.W_OK):
            _swap(stage, out)
        else:
            _merge(stage, out, plan.owned, kind.marker)
    finally:
        if stage.exists():
            shutil.rmtree(stage, ignore_errors=True)


def _swap(stage: Path, out: Path) -> None:
    """Replace ``out`` (only our files, or empty) by ``stage``: two renames, then cleanup."""
    moved = Path(tempfile.mkdtemp(prefix=f".{out.name}.new-", dir=out.parent))
    stage.rename(moved / "new")
    old = moved / "old"
    out.rename(old)
    try:
        (moved / "new").rename(out)
    except BaseException:
        old.rename(out)
        raise
    finally:
        shutil.rmtree(moved, ignore_errors=True)


def _merge(stage: Path, out: Path, owned: frozenset[str], marker: str) -> None:
    """Move the staged entries into ``out`` one by one; remove entries of an earlier run of
    ours that were not written again; keep everything else. The marker goes last."""
    trash = Path(tempfile.mkdtemp(prefix=".diffgcl-old-", dir=out))
    try:
        if (out / marker).exists():
            (out / marker).rename(trash / marker)
        written: set[str] = set()
        staged = sorted(_files_below(stage), key=lambda rel: rel == marker)
        for rel in staged:
            target = out / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            if target.exists() or target.is_symlink():
                target.rename(trash / f"{len(written)}-{target.name}")
            (stage / rel).rename(target)
            written.add(rel)
        for rel in sorted(owned):
            target = out / rel
            if rel not in written and not any(w.startswith(rel + "/") for w in written):
                if target.exists() or target.is_symlink():
                    target.rename(trash / f"old-{len(written)}-{target.name}")
                    written.add(rel)
    finally:
        shutil.rmtree(trash, ignore_errors=True)


def check_output_file(path: str | os.PathLike, overwrite: bool = False) -> Path:
    """An output file path that may be written: a folder is an error, an existing file needs
    ``overwrite``. Returns the path."""
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{p}: is a folder; give a file name")
    if p.exists() and not overwrite:
        raise OutputError(f"{p}: file exists; choose another name or pass --overwrite")
    return p


def write_file_atomically(path: str | os.PathLike, text: str, overwrite: bool = False) -> Path:
    """Write ``text`` to ``path`` through a temporary file in the same folder (see
    :func:`check_output_file`)."""
    p = check_output_file(path, overwrite)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", dir=p.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p
