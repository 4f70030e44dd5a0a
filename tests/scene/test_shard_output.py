"""``fmgs shard`` and write_shards: where the sharded scene goes. A mistyped --out never deletes what is
there (another folder, the scene repository, the source), a failed write names the folder and leaves
nothing, a damaged source is refused before anything is written, and "." names the package's folder."""

from __future__ import annotations

import errno
import json
import os

import pytest
import torch

from fmgs.cli import main
from fmgs.errors import ValidationError
from fmgs.scene.package import SceneWriteError
from fmgs.scene.shards import ShardManifest, write_shards
from tests.scene.test_package import _export


@pytest.fixture
def repo(tmp_path):
    """models/ with two packages, x and y."""
    _export(tmp_path / "models" / "x")
    _export(tmp_path / "models" / "y")
    return tmp_path / "models"


def _tree(folder) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_shards_are_never_written_over_the_repository_a_file_or_the_source(repo, capsys):
    before = _tree(repo)
    (repo.parent / "notes").write_text("keep")
    for out, message in (
        (repo, "holds no scene package"),
        (repo.parent / "notes", "is a file"),
        (repo / "x", "is the source package"),
    ):
        assert main(["shard", str(repo / "x"), "--shards", "2", "--out", str(out)]) == 2
        assert f"fmgs: error: {out}: " in (err := capsys.readouterr().err) and message in err
    assert _tree(repo) == before and (repo.parent / "notes").read_text() == "keep"
    # An earlier sharded scene at --out is replaced.
    assert main(["shard", str(repo / "x"), "--shards", "2", "--out", str(repo / "x-sh")]) == 0
    assert main(["shard", str(repo / "x"), "--shards", "3", "--out", str(repo / "x-sh")]) == 0
    assert len(ShardManifest.read(repo / "x-sh").shards) == 3


def test_the_default_out_of_a_package_given_as_dot_lies_beside_it(repo, monkeypatch, capsys):
    monkeypatch.chdir(repo / "x")
    assert main(["shard", ".", "--shards", "2"]) == 0
    assert sorted(os.listdir(repo)) == ["x", "x-2shards", "y"]
    assert sorted(os.listdir(repo / "x")) == [
        "embeddings.safetensors",
        "gaussians.safetensors",
        "manifest.json",
    ]
    assert ShardManifest.read(repo / "x-2shards").name == "x"


def test_a_failed_write_names_the_folder_and_leaves_nothing(repo, monkeypatch):
    import fmgs.scene.shards as shards

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(shards, "save_gaussians", full)
    with pytest.raises(SceneWriteError, match=r"writing the sharded scene failed.*No space left") as e:
        write_shards(repo / "x", repo / "x-sh", 2)
    assert str(repo / "x-sh") in str(e.value)
    assert sorted(os.listdir(repo)) == ["x", "y"]


@pytest.mark.parametrize(
    "breakage, message",
    [
        (lambda p: _set(p, selected=torch.arange(20) + 45), r"selected indices must lie in \[0, 50\)"),
        (lambda p: _set(p, selected=torch.arange(19)), "do not match its manifest"),
        (lambda p: _manifest(p, dim=7), "do not match its manifest"),
    ],
)
def test_a_damaged_source_is_refused_before_anything_is_written(repo, breakage, message):
    breakage(repo / "x")
    with pytest.raises(ValidationError, match=message):
        write_shards(repo / "x", repo / "x-sh", 2)
    assert sorted(os.listdir(repo)) == ["x", "y"]


def _set(p, **kw):
    from safetensors.torch import load_file, save_file

    t = load_file(str(p / "embeddings.safetensors"))
    t.update(kw)
    save_file(t, str(p / "embeddings.safetensors"))


def _manifest(p, dim):
    m = json.loads((p / "manifest.json").read_text())
    m["encoder"]["dim"] = dim
    (p / "manifest.json").write_text(json.dumps(m))
