"""The scene repository (``fmgs_server.repository``) with a fake loader: listing, lazy loads, reloads on
change, failures, unloads and the memory budget, and the state changes it reports."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fmgs.errors import FmgsError
from fmgs_server.errors import FailedPrecondition, NotFound
from fmgs_server.repository import FAILED, READY, UNLOADED, SceneRepository, scene_version


class FakeEngine:
    """Stands in for a SceneEngine: remembers what it was loaded from and how big it is."""

    def __init__(self, folder: Path) -> None:
        spec = json.loads((folder / "manifest.json").read_text())
        if spec.get("fail"):
            raise FmgsError(spec["fail"])
        self.name, self.generation, self.size = folder.name, spec.get("generation", 0), spec.get("bytes", 100)

    def nbytes(self) -> int:
        return self.size


def _write(root: Path, name: str, **spec) -> Path:
    folder = root / name
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "manifest.json").write_text(json.dumps(spec))
    return folder


class Repo:
    """A repository over ``root`` that records every load and every reported state change."""

    def __init__(self, root: Path, **kw) -> None:
        self.loads: list[str] = []
        self.changes: list[tuple[str, str]] = []
        self.repo = SceneRepository(
            root, self._load, on_change=lambda n, s: self.changes.append((n, s)), **kw
        )

    def _load(self, folder: Path) -> FakeEngine:
        self.loads.append(folder.name)
        return FakeEngine(folder)


def test_scene_version(tmp_path):
    folder = tmp_path / "s"
    folder.mkdir()
    assert scene_version(folder) == ""  # no manifest: not a scene
    _write(tmp_path, "s", generation=1)
    v1 = scene_version(folder)
    assert len(v1) == 16 and v1 == scene_version(folder)
    (folder / "gaussians.safetensors").write_bytes(b"x" * 10)
    v2 = scene_version(folder)
    (folder / "notes.txt").write_text("not part of the package")
    assert v2 != v1 and scene_version(folder) == v2
    (folder / "gaussians.safetensors").write_bytes(b"x" * 11)
    assert scene_version(folder) not in (v1, v2)


def test_scan_lists_scene_folders_only(tmp_path):
    for name in ("b", "a", ".hidden", "bad name"):
        _write(tmp_path, name)
    (tmp_path / "no_manifest").mkdir()
    (tmp_path / "file.txt").write_text("x")
    r = Repo(tmp_path)
    assert [s.name for s in r.repo.scan()] == ["a", "b"]
    assert all(s.state == UNLOADED for s in r.repo.scan()) and r.loads == []  # listing loads nothing
    assert Repo(tmp_path / "missing").repo.scan() == []
    # A scene whose folder went away is dropped and reported.
    (tmp_path / "b" / "manifest.json").unlink()
    assert [s.name for s in r.repo.scan()] == ["a"] and r.changes == [("b", "removed")]


def test_bad_or_missing_names_are_not_found(tmp_path):
    _write(tmp_path, "a")
    r = Repo(tmp_path)
    for name in ("../a", "", ".a", "a/b", "x" * 200, "a\n", "x" * 10_000):
        with pytest.raises(NotFound, match="invalid name") as e:
            r.repo.get(name)
        assert len(e.value.message) < 200  # a hostile name is not echoed whole (gRPC metadata limits)
    with pytest.raises(NotFound, match=r"scene 'zz' not found in the model repository") as e:
        r.repo.get("zz")
    assert str(tmp_path) not in e.value.message  # no host paths in what clients see
    r.repo.get("a")
    (tmp_path / "a" / "manifest.json").unlink()
    with pytest.raises(NotFound):
        r.repo.slot("a")
    assert r.changes == [("a", READY), ("a", "removed")]


def test_lazy_load_and_reload_on_change(tmp_path):
    _write(tmp_path, "a", generation=1)
    r = Repo(tmp_path, reload_check_s=3600)
    e1 = r.repo.get("a")
    assert e1.generation == 1 and r.repo.get("a") is e1 and r.loads == ["a"]
    slot = r.repo.slot("a")
    assert slot.state == READY and slot.loaded_version == scene_version(tmp_path / "a")
    _write(tmp_path, "a", generation=22)
    assert r.repo.get("a") is e1  # not checked again within reload_check_s
    r.repo.reload_check_s = 0.0
    e2 = r.repo.get("a")
    assert e2.generation == 22 and r.loads == ["a", "a"]
    assert r.repo.get("a") is e2  # unchanged files: no reload
    assert r.repo.reload("a").engine is not e2 and r.loads == ["a"] * 3  # admin reload: always
    assert r.changes == [("a", READY)] * 3


def test_failed_load_is_remembered_until_the_files_change(tmp_path):
    _write(tmp_path, "a", fail="broken embeddings")
    r = Repo(tmp_path, reload_check_s=0.0)
    for _ in range(2):
        with pytest.raises(FailedPrecondition, match=r"^scene 'a' failed to load: broken embeddings$"):
            r.repo.get("a")
    assert r.loads == ["a"]  # the same files are not tried again
    slot = r.repo.slot("a")
    assert slot.state == FAILED and slot.reason == "broken embeddings" and slot.engine is None
    _write(tmp_path, "a", generation=3)
    assert r.repo.get("a").generation == 3
    assert r.changes == [("a", FAILED), ("a", READY)]


def test_failed_reload_keeps_serving_the_previous_version(tmp_path):
    _write(tmp_path, "a", generation=1)
    r = Repo(tmp_path, reload_check_s=0.0)
    e1 = r.repo.get("a")
    _write(tmp_path, "a", fail="truncated file")
    assert r.repo.get("a") is e1
    slot = r.repo.reload("a")
    assert slot.state == READY and slot.engine is e1
    assert slot.reason == "reload failed, serving the previous version: truncated file"


def test_a_broken_replacement_is_tried_once_per_version(tmp_path):
    """Regression: while the previous version served, every access past reload_check_s loaded the broken
    replacement again (holding the scene's lock, so its requests waited on each failing load)."""
    _write(tmp_path, "a", generation=1)
    r = Repo(tmp_path, reload_check_s=0.0)
    e1 = r.repo.get("a")
    _write(tmp_path, "a", fail="truncated file")
    assert r.repo.get("a") is e1 and r.repo.get("a") is e1
    assert r.loads == ["a", "a"]
    _write(tmp_path, "a", generation=2, bytes=101)  # a good replacement is loaded on the next access
    assert r.repo.get("a").generation == 2 and r.loads == ["a", "a", "a"]


def test_files_changing_during_a_load_fail_it(tmp_path):
    _write(tmp_path, "a", generation=1)
    r = Repo(tmp_path)

    def racing_load(folder: Path) -> FakeEngine:
        engine = FakeEngine(folder)
        _write(tmp_path, "a", generation=1000)  # another writer replaces the package meanwhile
        return engine

    r.repo.loader = racing_load
    with pytest.raises(FailedPrecondition, match="changed while loading; retry"):
        r.repo.get("a")


def test_files_changing_during_a_reload_keep_the_previous_version(tmp_path):
    """Regression: an admin reload accepted an engine whose files changed while it loaded (it may mix
    the old manifest with the new arrays), recorded as the version from before the load."""
    _write(tmp_path, "a", generation=1)
    r = Repo(tmp_path, reload_check_s=60.0)
    e1 = r.repo.get("a")

    def racing_load(folder: Path) -> FakeEngine:
        engine = FakeEngine(folder)
        _write(tmp_path, "a", generation=1000, bytes=101)  # another writer replaces the package meanwhile
        return engine

    r.repo.loader = racing_load
    slot = r.repo.reload("a")
    assert slot.state == READY and slot.engine is e1
    assert (
        slot.reason
        == "reload failed, serving the previous version: the scene's files changed while loading; retry"
    )
    r.repo.loader = r._load
    slot = r.repo.reload("a")
    assert slot.engine.generation == 1000 and slot.reason == ""


def test_unload_keeps_engines_in_flight(tmp_path):
    _write(tmp_path, "a")
    r = Repo(tmp_path)
    held = r.repo.get("a")
    slot = r.repo.unload("a")
    assert slot.state == UNLOADED and slot.engine is None and r.repo.resident_bytes(slot) == 0
    assert held.nbytes() == 100  # a request holding the engine keeps using it
    assert r.repo.get("a") is not held and r.loads == ["a", "a"]
    assert r.changes == [("a", READY), ("a", UNLOADED), ("a", READY)]


def test_memory_budget(tmp_path):
    for name in ("a", "b", "c"):
        _write(tmp_path, name, bytes=100)
    _write(tmp_path, "huge", bytes=1000)
    r = Repo(tmp_path, memory_budget=250)
    with pytest.raises(FailedPrecondition, match="needs 1000 bytes, more than the memory budget 250"):
        r.repo.get("huge")
    r.repo.get("a")
    r.repo.get("b")
    r.repo.get("a")  # b is now the least recently used
    r.repo.get("c")
    resident = {s.name: r.repo.resident_bytes(s) for s in r.repo.scan()}
    assert resident == {"a": 100, "b": 0, "c": 100, "huge": 0}
    assert ("b", UNLOADED) in r.changes and ("a", UNLOADED) not in r.changes
    assert r.repo.slot("huge").state == FAILED
