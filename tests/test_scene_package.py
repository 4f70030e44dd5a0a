"""Scene package export and validated loading: bad packages fail with errors that name the problem."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from fmgs.errors import ValidationError
from fmgs.gaussians import GaussianSet
from fmgs.scene.package import check_scene_name, export_scene, load_scene
from fmgs.vecmath import safe_normalize


def _gaussians(n: int = 50) -> GaussianSet:
    g = torch.Generator().manual_seed(0)
    return GaussianSet(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        torch.full((n, 3), -2.0),
        torch.zeros(n),
        torch.zeros(n, 1, 3),
    )


def _export(path, n=50, m=20, d=6, emb=None):
    g = _gaussians(n)
    sel = torch.arange(0, 2 * m, 2)
    emb = safe_normalize(torch.randn(m, d)) if emb is None else emb
    canon = safe_normalize(torch.randn(4, d))
    return export_scene(path, g, sel, emb, "test/enc", canon), g, sel, emb, canon


def test_round_trip(tmp_path):
    p, g, sel, emb, canon = _export(tmp_path / "s1")
    s = load_scene(p)
    assert s.name == "s1" and s.encoder_id == "test/enc" and s.dim == 6 and s.field is None
    assert torch.equal(s.selected, sel) and torch.equal(s.gaussians.means, g.means)
    assert (s.embeddings - emb).abs().max() < 1e-3  # float16 storage
    # Canonical dots are those of the stored (rounded) embeddings.
    assert torch.allclose(s.canonical, s.embeddings @ canon.T, atol=1e-6)
    assert s.canonical_phrases == ["object", "stuff", "things", "texture"]
    assert (p.stat().st_mode & 0o755) == 0o755


def test_export_replaces_atomically_and_bad_input_leaves_the_old_package(tmp_path):
    p, *_ = _export(tmp_path / "s")
    before = {f.name: f.read_bytes() for f in p.iterdir()}
    bad = safe_normalize(torch.randn(20, 6))
    bad[3, 2] = float("nan")
    with pytest.raises(ValidationError, match="embeddings"):
        _export(tmp_path / "s", emb=bad)
    assert {f.name: f.read_bytes() for f in p.iterdir()} == before
    _export(tmp_path / "s", d=5)
    assert load_scene(p).dim == 5
    assert sorted(x.name for x in tmp_path.iterdir()) == ["s"]  # no temporary folders left


@pytest.mark.parametrize(
    "breakage, message",
    [
        (lambda p: (p / "manifest.json").unlink(), "no manifest"),
        (lambda p: (p / "manifest.json").write_text("{not json"), "unreadable manifest"),
        (lambda p: _edit(p, version=99), "unsupported version"),
        (lambda p: _edit(p, format="other"), "manifest"),
        (lambda p: _edit(p, encoder={"id": "x", "dim": 7}), r"\[20,7\]"),
        (lambda p: _edit(p, encoder="x"), "encoder must be"),
        (lambda p: (p / "embeddings.safetensors").write_bytes(b"garbage"), "cannot read"),
        (lambda p: (p / "embeddings.safetensors").unlink(), "cannot read"),
        (lambda p: _tensors(p, embeddings=torch.full((20, 6), float("inf")).half()), "NaN or Inf"),
        (lambda p: _tensors(p, selected=torch.arange(20) + 45), "selected indices"),
        (lambda p: _tensors(p, canonical=torch.zeros(20, 3)), "canonical"),
        (lambda p: (p / "gaussians.safetensors").unlink(), "gaussians"),
    ],
)
def test_broken_packages_are_rejected_with_a_reason(tmp_path, breakage, message):
    p, *_ = _export(tmp_path / "s")
    breakage(p)
    with pytest.raises(ValidationError, match=message):
        load_scene(p)


def _edit(p, **kw):
    m = json.loads((p / "manifest.json").read_text())
    m.update(kw)
    (p / "manifest.json").write_text(json.dumps(m))


def _tensors(p, **kw):
    from safetensors.torch import load_file, save_file

    t = load_file(str(p / "embeddings.safetensors"))
    t.update(kw)
    save_file(t, str(p / "embeddings.safetensors"))


@pytest.mark.parametrize("name", ["", ".hidden", "a/b", "../x", "x" * 200, "sp ace"])
def test_scene_names_are_folder_names(name):
    with pytest.raises(ValidationError):
        check_scene_name(name)


def test_copy_of_a_package_loads_under_its_new_name(tmp_path):
    p, *_ = _export(tmp_path / "a")
    shutil.copytree(p, tmp_path / "b")
    assert load_scene(tmp_path / "b").name == "a"  # the manifest keeps the name it was built with
