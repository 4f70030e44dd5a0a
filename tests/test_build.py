"""End to end: a synthetic labelled scene -> fmgs build -> a package that answers text queries."""

from __future__ import annotations

import json

import pytest

from fmgs.cli import main


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    from fmgs.synth import SynthConfig, generate

    tmp = tmp_path_factory.mktemp("build")
    generate(tmp / "scene", SynthConfig(views=16, width=48, height=36, points=4000, supersample=1))
    _surface_ply(tmp / "scene", tmp / "surface.ply")
    args = [
        "build",
        str(tmp / "scene"),
        "--name",
        "toy",
        "--models",
        str(tmp / "models"),
        "--targets",
        "labels",
        "--feature-scale",
        "0.5",
        "--ply",
        str(tmp / "surface.ply"),
        "--field-steps",
        "400",
        "--device",
        "cpu",
    ]
    assert main(args) == 0
    return tmp, args


def _surface_ply(scene, out) -> None:
    """A '3DGS scene trained elsewhere': small opaque Gaussians on the generator's surface samples.
    (Geometry training is tested in test_train_gs; this keeps the end-to-end test fast.)"""
    import torch

    from fmgs.data.dataset import load_dataset
    from fmgs.gaussians import GaussianSet
    from fmgs.io.ply import write_ply

    ds = load_dataset(scene)
    pts = torch.from_numpy(ds.points).float()
    cols = torch.from_numpy(ds.colors).float() / 255
    n = len(pts)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    g = GaussianSet.from_activated(pts, quats, torch.full((n, 3), 0.04), torch.full((n,), 0.9), cols)
    write_ply(g, out)


def test_build_writes_a_package_that_answers_queries(built):
    from fmgs.data.dataset import load_dataset
    from fmgs.features.text import load_text_encoder
    from fmgs.query.text import rank_gaussians
    from fmgs.scene.package import load_scene
    from fmgs.train.evaluate_field import evaluate_field

    tmp, _ = built
    scene = load_scene(tmp / "models" / "toy")
    assert scene.encoder_id == "sentence-transformers/all-MiniLM-L6-v2" and scene.dim == 384
    enc = load_text_encoder(scene.encoder_id)
    r = rank_gaussians(scene, enc.encode_text(["blue ball"])[0], top_k=10)
    assert len(r.index) == 10 and float(r.relevancy[0]) > 0.5
    ds = load_dataset(tmp / "scene")
    q = evaluate_field(scene, ds, enc, ds.split(8)[1], tmp / "scene" / "scene.json")
    # A tiny, briefly trained scene: far from the benchmark's thresholds, far above chance (1/6).
    assert q.localisation_3d >= 0.5 and q.localisation_2d >= 0.5 and q.miou > 0.3, q


def test_rebuild_skips_complete_stages(built, capsys):
    tmp, args = built
    stamp = (tmp / "models" / ".work" / "toy" / "field" / "field_train.json").stat().st_mtime_ns
    manifest = json.loads((tmp / "models" / ".work" / "toy" / "features" / "manifest.json").read_text())
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "[2/5] geometry: given" in out and "[4/5] field: complete" in out
    assert (tmp / "models" / ".work" / "toy" / "field" / "field_train.json").stat().st_mtime_ns == stamp
    again = json.loads((tmp / "models" / ".work" / "toy" / "features" / "manifest.json").read_text())
    assert again == manifest


def test_build_rejects_bad_names_and_sources(tmp_path, capsys):
    assert main(["build", str(tmp_path), "--name", "../evil", "--models", str(tmp_path / "m")]) == 2
    assert "scene name" in capsys.readouterr().err
    assert main(["build", str(tmp_path / "missing"), "--name", "ok", "--models", str(tmp_path / "m")]) == 2
    assert "not a folder" in capsys.readouterr().err
