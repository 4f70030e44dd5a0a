"""End to end: a synthetic labelled scene -> fmgs build -> a package that answers text queries."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from fmgs.cli import main
from tests.helpers.scenes import surface_ply


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    from fmgs.synth import SynthConfig, generate

    tmp = tmp_path_factory.mktemp("build")
    generate(tmp / "scene", SynthConfig(views=16, width=48, height=36, points=4000, supersample=1))
    surface_ply(tmp / "scene", tmp / "surface.ply")
    (tmp / "extra.json").write_text(json.dumps({"description": "toy scene", "source": "test"}))
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
        "--field-dtype",
        "float16",
        "--extra",
        str(tmp / "extra.json"),
        "--device",
        "cpu",
    ]
    assert main(args) == 0
    return tmp, args


@pytest.mark.slow
def test_build_writes_a_package_that_answers_queries(built):
    from fmgs.data.dataset import load_dataset
    from fmgs.features.text import load_text_encoder
    from fmgs.query.engine import SceneEngine
    from fmgs.scene.package import load_scene
    from fmgs.train.evaluate_field import evaluate_field

    tmp, _ = built
    scene = load_scene(tmp / "models" / "toy")
    engine = SceneEngine.open(tmp / "models" / "toy")  # as the server opens it
    assert scene.encoder_id == "sentence-transformers/all-MiniLM-L6-v2" and scene.dim == 384
    enc = load_text_encoder(scene.encoder_id)
    r = engine.text_query(enc.encode_text(["blue ball"])[0], top_k=10)
    assert len(r.index) == 10 and float(r.relevancy[0]) > 0.5
    extra = scene.manifest.extra
    assert extra["label_names"][:4] == ["background", "floor", "red cube", "blue ball"]
    assert extra["description"] == "toy scene" and extra["source"] == "test"  # --extra wins
    assert scene.manifest.field.dtype == "float16" and scene.field.grid.table.dtype == torch.float32
    ds = load_dataset(tmp / "scene")
    q = evaluate_field(engine, ds, enc, ds.split(8)[1], tmp / "scene" / "scene.json")
    # A tiny, briefly trained scene: far from the benchmark's thresholds, far above chance (1/6).
    assert q.localisation_3d >= 0.5 and q.localisation_2d >= 0.5 and q.miou > 0.3, q


@pytest.mark.slow
def test_rebuild_skips_complete_stages(built, capsys):
    tmp, args = built
    stamp = (tmp / "models" / ".work" / "toy" / "field" / "field_train.json").stat().st_mtime_ns
    manifest = json.loads((tmp / "models" / ".work" / "toy" / "features" / "manifest.json").read_text())
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "[2/5] geometry: given" in out and "[4/5] field: complete" in out
    assert "held-out PSNR" in out and " dB, SSIM " in out  # the geometry is scored, given or trained
    scores = json.loads((tmp / "models" / ".work" / "toy" / "geometry.json").read_text())
    assert (
        f"held-out PSNR {scores['psnr']:.2f} dB" in out and scores["views"] >= 1 and 0 < scores["ssim"] <= 1
    )
    # Every held-out view's scores, the worst named on the terminal, and the views under the threshold.
    per_view = scores["per_view"]
    mean = sum(v["psnr"] for v in per_view) / len(per_view)
    assert len(per_view) == scores["views"] and abs(mean - scores["psnr"]) < 1e-9
    worst = min(per_view, key=lambda v: v["psnr"])
    assert scores["worst"] == worst and f"worst {worst['name']} {worst['psnr']:.2f} dB" in out
    low = [v["name"] for v in sorted(per_view, key=lambda v: v["psnr"]) if v["psnr"] < scores["threshold_db"]]
    assert scores["below"] == low
    # What the fit left in front of the training cameras, counted against the scene's sparse points.
    fl = scores["floaters"]
    assert fl["total"] == scores["gaussians"] and fl["cameras_checked"] >= 1
    assert 0 <= fl["count"] <= fl["total"] and 0 <= fl["beyond"] <= fl["total"]
    assert f"floaters: {fl['count']:,} of {fl['total']:,} Gaussians" in out
    assert (tmp / "models" / ".work" / "toy" / "field" / "field_train.json").stat().st_mtime_ns == stamp
    again = json.loads((tmp / "models" / ".work" / "toy" / "features" / "manifest.json").read_text())
    assert again == manifest


def test_build_rejects_bad_names_and_sources(tmp_path, capsys):
    assert main(["build", str(tmp_path), "--name", "../evil", "--models", str(tmp_path / "m")]) == 2
    assert "scene name" in capsys.readouterr().err
    assert main(["build", str(tmp_path / "missing"), "--name", "ok", "--models", str(tmp_path / "m")]) == 2
    assert "not a folder" in capsys.readouterr().err
    # A folder of other things where the package goes is refused before any stage, not at the export.
    (tmp_path / "m" / "ok").mkdir(parents=True)
    (tmp_path / "m" / "ok" / "notes.txt").write_text("mine")
    assert main(["build", str(tmp_path), "--name", "ok", "--models", str(tmp_path / "m")]) == 2
    assert "holds no scene package" in capsys.readouterr().err
    assert not (tmp_path / "m" / ".work").exists() and (tmp_path / "m" / "ok" / "notes.txt").is_file()


@pytest.mark.slow
def test_geometry_settings_reach_3dgs_and_a_change_retrains(tmp_path, monkeypatch, capsys):
    from fmgs.build import pipeline
    from fmgs.synth import SynthConfig, generate
    from fmgs.train import gaussians as gs_mod

    generate(tmp_path / "scene", SynthConfig(views=9, width=32, height=24, points=800, supersample=1))
    calls = []

    def fake_train(ds, out, cfg, progress=True, resume=True):  # a stand-in fit: the surface samples
        calls.append((cfg, resume))
        surface_ply(tmp_path / "scene", out / "point_cloud.ply")
        (out / "train.json").write_text(json.dumps({"steps": cfg.steps, "config": gs_mod.config_record(cfg)}))

    monkeypatch.setattr(pipeline, "train_gaussians", fake_train)  # the name the build calls
    args = ["build", str(tmp_path / "scene"), "--name", "g", "--models", str(tmp_path / "m")]
    args += ["--targets", "labels", "--gs-steps", "12", "--field-steps", "3", "--device", "cpu"]
    assert main([*args, "--sh-degree", "0", "--grad-threshold", "0.5"]) == 0
    cfg, resume = calls[-1]
    assert (cfg.steps, cfg.sh_degree, cfg.densify.grad_threshold, resume) == (12, 0, 0.5, True)
    capsys.readouterr()
    # another thread count changes speed, not the result: the finished geometry is kept
    assert main([*args, "--sh-degree", "0", "--grad-threshold", "0.5", "--gs-threads", "1"]) == 0
    assert "[2/5] geometry: complete" in capsys.readouterr().out and len(calls) == 1
    assert main([*args, "--sh-degree", "1", "--grad-threshold", "0.5"]) == 0
    assert "[2/5] geometry: 3DGS, 12 steps" in capsys.readouterr().out
    cfg, resume = calls[-1]
    assert cfg.sh_degree == 1 and not resume  # a finished run with other settings starts over


def test_a_dataset_without_points_stops_unless_random_gaussians_are_allowed(tmp_path, monkeypatch, capsys):
    from fmgs.build import pipeline
    from fmgs.synth import SynthConfig, generate
    from fmgs.train import gaussians as gs_mod

    generate(tmp_path / "scene", SynthConfig(views=9, width=32, height=24, points=800, supersample=1))
    surface_ply(tmp_path / "scene", tmp_path / "fit.ply")  # made while the dataset still lists points
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    del meta["ply_file_path"]
    (tmp_path / "scene" / "transforms.json").write_text(json.dumps(meta))
    calls = []

    def fake_train(ds, out, cfg, progress=True, resume=True):
        calls.append(ds.points)
        out.mkdir(parents=True, exist_ok=True)
        shutil.copy(tmp_path / "fit.ply", out / "point_cloud.ply")
        (out / "train.json").write_text(json.dumps({"steps": cfg.steps, "config": gs_mod.config_record(cfg)}))

    monkeypatch.setattr(pipeline, "train_gaussians", fake_train)  # the name the build calls
    args = ["build", str(tmp_path / "scene"), "--name", "g", "--models", str(tmp_path / "m")]
    args += ["--targets", "labels", "--gs-steps", "12", "--field-steps", "3", "--device", "cpu"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "has no sparse points" in err and "--allow-random-init" in err and "ply_file_path" in err
    assert not calls and not (tmp_path / "m" / "g").exists()  # stopped before any work
    assert main([*args, "--allow-random-init"]) == 0
    assert calls == [None]  # the geometry stage ran on the points-free dataset


def test_build_rejects_a_bad_extra_file(tmp_path, capsys):
    (tmp_path / "extra.json").write_text("[1, 2]")
    args = ["build", str(tmp_path), "--name", "x", "--models", str(tmp_path / "m")]
    assert main([*args, "--extra", str(tmp_path / "extra.json")]) == 2
    assert "must hold a JSON object" in capsys.readouterr().err
    assert main([*args, "--extra", str(tmp_path / "missing.json")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_a_ply_without_gaussians_or_an_unwritable_repository_stops_before_any_stage(tmp_path, capsys):
    """A .ply with no Gaussians ran to an IndexError in the field stage; a file where the model
    repository goes was a NotADirectoryError traceback."""
    from fmgs.gaussians import GaussianSet
    from fmgs.io.ply import write_ply
    from fmgs.synth import SynthConfig, generate

    generate(tmp_path / "scene", SynthConfig(views=9, width=32, height=24, points=800, supersample=1))
    empty = GaussianSet(
        torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 1, 3)
    )
    write_ply(empty, tmp_path / "empty.ply")
    args = ["build", str(tmp_path / "scene"), "--name", "e", "--targets", "labels", "--device", "cpu"]
    assert main([*args, "--models", str(tmp_path / "m"), "--ply", str(tmp_path / "empty.ply")]) == 2
    assert "empty.ply: holds no Gaussians" in capsys.readouterr().err
    assert not (tmp_path / "m" / "e").exists() and not (tmp_path / "m" / ".work" / "e" / "features").exists()
    (tmp_path / "file").write_text("")
    assert main([*args, "--models", str(tmp_path / "file")]) == 2
    assert "model repository: cannot create" in capsys.readouterr().err
    assert main([*args, "--models", str(tmp_path / "m"), "--work", str(tmp_path / "file")]) == 2
    assert "work folder: cannot create" in capsys.readouterr().err


def test_photos_are_posed_again_when_they_or_the_sfm_settings_change(tmp_path, monkeypatch, capsys):
    """A finished SfM was reused whatever the --sfm-* settings or the photos were, and so were the
    geometry, features and field made from its poses."""
    import os
    from dataclasses import asdict

    from PIL import Image

    from fmgs.build import pipeline
    from fmgs.errors import FmgsError
    from fmgs.sfm.config import SfMConfig
    from fmgs.sfm.pipeline import SFM_RECORD, photo_names, photos_fingerprint

    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        Image.new("RGB", (8, 6), (i, i, i)).save(photos / f"{i}.png")
    work = tmp_path / "m" / ".work" / "p"
    (work / "sfm" / "undistorted").mkdir(parents=True)
    (work / "sfm" / "undistorted" / "transforms.json").write_text("{}")  # a dataset, as far as stage 1 sees
    record = {
        "config": asdict(SfMConfig()),
        "photos": photos_fingerprint(photos, photo_names(photos), SfMConfig()),
    }
    (work / "sfm" / SFM_RECORD).write_text(json.dumps(record))
    (work / "gs").mkdir()
    ran = []

    def fake_sfm(images, out, cfg):
        ran.append(cfg)
        raise FmgsError("SfM ran")

    def loaded(path, *a, **k):  # stop once stage 1 has chosen its dataset
        raise FmgsError(f"loaded {path}")

    monkeypatch.setattr(pipeline, "run_sfm", fake_sfm)
    monkeypatch.setattr(pipeline, "load_dataset", loaded)
    args = ["build", str(photos), "--name", "p", "--models", str(tmp_path / "m"), "--targets", "labels"]
    args += ["--device", "cpu"]
    assert main(args) == 2
    out = capsys.readouterr()
    assert "[1/5] poses: complete" in out.out and "loaded" in out.err and not ran and (work / "gs").is_dir()
    assert main([*args, "--sfm-camera-model", "PINHOLE"]) == 2
    assert "SfM ran" in capsys.readouterr().err and ran[-1].camera_model == "PINHOLE"
    assert not (work / "gs").exists()  # the old poses' geometry starts over
    st = (photos / "1.png").stat()
    os.utime(photos / "1.png", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # a photo replaced
    assert main(args) == 2 and len(ran) == 2
