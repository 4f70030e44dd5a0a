"""Scene package export and validated loading: bad packages fail with errors that name the problem."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from fmgs.errors import FmgsError, ValidationError
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


def _field_export(path, field_dtype="float32"):
    from fmgs.field.hashgrid import HashGridConfig
    from fmgs.field.model import FeatureField, FieldConfig

    g = _gaussians()
    sel = torch.arange(0, 40, 2)
    grid = HashGridConfig(levels=4, min_res=4, max_res=16, log2_table=10, features=2)
    cfg = FieldConfig(grid=grid, clip_dim=6, clip_hidden=8, clip_layers=1, dino_dim=0)
    field = FeatureField.for_points(cfg, g.means[sel])
    with torch.no_grad():
        field.grid.table.normal_(0, 0.5, generator=torch.Generator().manual_seed(1))
        emb = field(g.means[sel]).clip
    canon = safe_normalize(torch.randn(4, 6))
    p = export_scene(path, g, sel, emb, "test/enc", canon, field=field, field_dtype=field_dtype)
    return p, field, g.means[sel]


def test_field_stored_as_float16_round_trips_at_half_the_size(tmp_path):
    from safetensors.torch import load_file

    p32, field, pts = _field_export(tmp_path / "f32")
    p16, _, _ = _field_export(tmp_path / "f16", field_dtype="float16")
    assert json.loads((p16 / "manifest.json").read_text())["field"]["dtype"] == "float16"
    stored = load_file(str(p16 / "field.safetensors"))
    assert stored["grid.keys"].dtype == torch.int64
    assert all(v.dtype == torch.float16 for k, v in stored.items() if k != "grid.keys")
    s32, s16 = load_scene(p32), load_scene(p16)
    ref = field.state_dict()
    for k, v in s16.field.state_dict().items():
        assert v.dtype == ref[k].dtype  # upcast on load
        assert torch.equal(v, ref[k].half().to(ref[k].dtype) if v.is_floating_point() else ref[k]), k
    assert all(torch.equal(v, ref[k]) for k, v in s32.field.state_dict().items())  # float32 is exact
    with torch.no_grad():
        assert (s16.field(pts).clip - field(pts).clip).abs().max() < 1e-2
    size = lambda p: (p / "field.safetensors").stat().st_size  # noqa: E731
    assert size(p16) < 0.75 * size(p32)


def test_packages_without_a_field_dtype_load_as_float32(tmp_path):
    p, field, _ = _field_export(tmp_path / "old")
    m = json.loads((p / "manifest.json").read_text())
    del m["field"]["dtype"]  # as written before the option existed
    (p / "manifest.json").write_text(json.dumps(m))
    s = load_scene(p)
    assert all(torch.equal(v, field.state_dict()[k]) for k, v in s.field.state_dict().items())


@pytest.mark.parametrize(
    "dtype, message", [("float32", "is torch.float16, the manifest says float32"), ("int8", "field dtype")]
)
def test_field_dtype_that_does_not_match_the_tensors_is_rejected(tmp_path, dtype, message):
    p, *_ = _field_export(tmp_path / "s", field_dtype="float16")
    m = json.loads((p / "manifest.json").read_text())
    m["field"]["dtype"] = dtype
    (p / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ValidationError, match=message):
        load_scene(p)
    with pytest.raises(ValidationError, match="field_dtype"):
        _field_export(tmp_path / "t", field_dtype="int8")


def test_export_in_blocks_stores_what_the_whole_table_would(tmp_path, monkeypatch):
    """The embeddings are written and the query state built a block at a time (a 10M-Gaussian scene has
    no room for whole-table copies); the stored tables equal those of the whole float16 table."""
    import fmgs.io.tensor_stream as stream
    from fmgs.query.state import build_state, fingerprint, load_state

    monkeypatch.setattr(stream, "BLOCK_BYTES", 4096)
    g = torch.Generator().manual_seed(3)
    emb = safe_normalize(torch.randn(3000, 32, generator=g))
    canon = safe_normalize(torch.randn(4, 32, generator=g))
    p = export_scene(
        tmp_path / "s", _gaussians(3000), torch.arange(3000), emb, "test/enc", canon, query_rank=8
    )
    s = load_scene(p)
    assert torch.equal(s.embeddings, emb.half().float())
    assert torch.allclose(s.canonical, emb.half().float() @ canon.T, atol=1e-6, rtol=0)
    stored = load_state(p / "query_state.safetensors", 3000, 32, fingerprint(p / "embeddings.safetensors"))
    whole = build_state(emb.half(), 8)
    assert torch.equal(stored.codes, whole.codes) and torch.equal(stored.basis, whole.basis)
    assert torch.equal(stored.tier2.codes, whole.tier2.codes)


def test_embeddings_beyond_float16_are_rejected_before_anything_is_written(tmp_path):
    emb = safe_normalize(torch.randn(20, 6))
    emb[7, 1] = 1e5  # finite in float32, infinite once stored
    with pytest.raises(ValidationError, match=r"index 7.*float16 range"):
        _export(tmp_path / "s", emb=emb)
    assert list(tmp_path.iterdir()) == []


def test_export_never_writes_over_a_file_or_a_folder_that_holds_no_package(tmp_path):
    """A mistyped --out is refused before anything is written: a file or a folder of other things (a
    dataset, the scene repository) is left as it was; an empty folder takes the package."""
    (tmp_path / "notes").write_text("keep")
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.jpg").write_bytes(b"jpeg")
    for name, what in (("notes", "is a file"), ("photos", "holds no scene package")):
        with pytest.raises(ValidationError, match=what) as e:
            _export(tmp_path / name)
        assert str(tmp_path / name) in str(e.value)
    assert (tmp_path / "notes").read_text() == "keep"
    assert [p.name for p in (tmp_path / "photos").iterdir()] == ["a.jpg"]
    (tmp_path / "empty").mkdir()
    assert load_scene(_export(tmp_path / "empty")[0]).name == "empty"
    p, *_ = _export(tmp_path / "damaged")  # a package that lost its manifest is still a package
    (p / "manifest.json").unlink()
    assert load_scene(_export(p)[0]).name == "damaged"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["damaged", "empty", "notes", "photos"]


@pytest.mark.parametrize(
    "breakage, message",
    [
        (lambda g, sel: (g, sel.clone().fill_(50)), r"selected: indices must lie in \[0, 50\)"),
        (lambda g, sel: (g, -sel - 1), r"selected: indices must lie in \[0, 50\)"),
        (lambda g, sel: (g, sel.float()), "integer indices"),
        (lambda g, sel: (_with_nan_mean(g), sel), "means at index 4"),
    ],
)
def test_export_refuses_what_a_load_would_refuse_and_keeps_the_old_package(tmp_path, breakage, message):
    p, g, sel, emb, canon = _export(tmp_path / "s")
    before = {f.name: f.read_bytes() for f in p.iterdir()}
    g2, sel2 = breakage(g, sel)
    with pytest.raises(ValidationError, match=message):
        export_scene(p, g2, sel2, emb, "test/enc", canon)
    assert {f.name: f.read_bytes() for f in p.iterdir()} == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["s"]


def _with_nan_mean(g: GaussianSet) -> GaussianSet:
    g = g.subset(torch.arange(g.num))
    g.means[4, 1] = float("nan")
    return g


@pytest.mark.parametrize("failing", ["gaussians", "field"])
def test_a_write_that_fails_names_the_package_and_keeps_the_old_one(tmp_path, monkeypatch, failing):
    """Disk full (or no permission) mid-write: the error names the package folder, the old package is
    as it was and no temporary folder is left."""
    import errno

    import safetensors.torch
    from safetensors import SafetensorError

    import fmgs.scene.package as package

    p, *_ = _field_export(tmp_path / "s")
    before = {f.name: f.read_bytes() for f in p.iterdir()}

    def full(*a, **k):
        if failing == "field":  # safetensors reports its own I/O errors, without a path
            raise SafetensorError("Error while serializing: I/O error: No space left on device (os error 28)")
        raise OSError(errno.ENOSPC, "No space left on device")

    if failing == "field":
        monkeypatch.setattr(safetensors.torch, "save_file", full)
    else:
        monkeypatch.setattr(package, "save_gaussians", full)
    with pytest.raises(package.SceneWriteError, match="No space left on device") as e:
        _field_export(tmp_path / "s")
    assert str(e.value).startswith(f"{p}: writing the scene package failed")
    assert isinstance(e.value, FmgsError) and isinstance(e.value, OSError)  # `fmgs` prints it, exit 2
    assert {f.name: f.read_bytes() for f in p.iterdir()} == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["s"]
