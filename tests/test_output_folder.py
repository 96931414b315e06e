"""Output folders (diffgcl.io): a user's files survive every write; our own output is replaced."""

from __future__ import annotations

import os

import numpy as np
import pytest

from diffgcl.data.demos import DemoSet
from diffgcl.io import OutputError, check_output_file, write_file_atomically


def _demos(value: float = 0.0, n: int = 2) -> DemoSet:
    X = np.full((n, 4, 3), value)
    return DemoSet(
        X=X,
        U=np.zeros((n, 3, 1)),
        O=np.zeros((n, 4, 0)),
        mask=np.ones((n, 4)),
        dt=0.1,
        env="test",
        episodes=tuple({"i": i} for i in range(n)),
    )


def _tree(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


def test_new_and_empty_folders_are_written(tmp_path):
    _demos(1.0).save(tmp_path / "a" / "b")
    assert DemoSet.load(tmp_path / "a" / "b").X[0, 0, 0] == 1.0
    (tmp_path / "empty").mkdir()
    _demos(2.0).save(tmp_path / "empty")
    assert _tree(tmp_path / "empty") == ["demos.npz", "meta.json"]


def test_own_dataset_is_replaced_atomically(tmp_path):
    out = tmp_path / "demos"
    _demos(1.0).save(out)
    inode = (out / "meta.json").stat().st_ino
    _demos(2.0, n=3).save(out)
    new = DemoSet.load(out)
    assert new.num_episodes == 3 and new.X[0, 0, 0] == 2.0
    assert (out / "meta.json").stat().st_ino != inode
    assert _tree(out) == ["demos.npz", "meta.json"]
    assert [p.name for p in tmp_path.iterdir()] == ["demos"]  # no work folders left


def test_folder_with_a_users_file_survives(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("my notes")
    (out / "sub").mkdir()
    (out / "sub" / "data.csv").write_text("1,2")
    with pytest.raises(OutputError, match=r"mine: folder is not empty and not a demo dataset"):
        _demos().save(out)
    assert _tree(out) == ["notes.txt", "sub", "sub/data.csv"]
    # --overwrite writes the dataset next to the user's files and deletes nothing.
    _demos(3.0).save(out, overwrite=True)
    assert (out / "notes.txt").read_text() == "my notes"
    assert (out / "sub" / "data.csv").read_text() == "1,2"
    assert DemoSet.load(out).X[0, 0, 0] == 3.0
    # Now it is a dataset with a user's files in it: replacing it keeps them, no flag needed.
    _demos(4.0).save(out)
    assert _tree(out) == ["demos.npz", "meta.json", "notes.txt", "sub", "sub/data.csv"]
    assert DemoSet.load(out).X[0, 0, 0] == 4.0


def test_out_is_a_file_is_an_error(tmp_path):
    f = tmp_path / "report.txt"
    f.write_text("keep me")
    for overwrite in (False, True):
        with pytest.raises(OutputError, match="report.txt: is a file"):
            _demos().save(f, overwrite=overwrite)
    assert f.read_text() == "keep me"


def test_out_dot_never_empties_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "thesis.tex").write_text("x")
    with pytest.raises(OutputError, match="not empty"):
        _demos().save(".")
    assert _tree(tmp_path) == ["thesis.tex"]
    _demos(5.0).save(".", overwrite=True)
    assert _tree(tmp_path) == ["demos.npz", "meta.json", "thesis.tex"]
    # A dataset in the working directory itself is replaced entry by entry (cwd stays).
    _demos(6.0).save(".")
    assert os.getcwd() == str(tmp_path)
    assert DemoSet.load(".").X[0, 0, 0] == 6.0


def test_a_crash_while_writing_leaves_the_old_dataset(tmp_path, monkeypatch):
    out = tmp_path / "demos"
    _demos(1.0).save(out)

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(np, "savez_compressed", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        _demos(2.0).save(out)
    monkeypatch.undo()
    assert DemoSet.load(out).X[0, 0, 0] == 1.0
    assert _tree(out) == ["demos.npz", "meta.json"]
    assert [p.name for p in tmp_path.iterdir()] == ["demos"]


def test_output_file_rule(tmp_path):
    f = tmp_path / "map.yaml"
    write_file_atomically(f, "a: 1\n")
    with pytest.raises(OutputError, match="map.yaml: file exists"):
        write_file_atomically(f, "a: 2\n")
    write_file_atomically(f, "a: 2\n", overwrite=True)
    assert f.read_text() == "a: 2\n"
    with pytest.raises(OutputError, match="is a folder"):
        check_output_file(tmp_path)
