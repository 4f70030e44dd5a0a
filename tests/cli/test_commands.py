"""The fmgs command line."""

from __future__ import annotations

import json

import numpy as np
import torch
from PIL import Image

from fmgs.cli import main
from fmgs.gaussians import GaussianSet
from fmgs.io.ply import write_ply


def test_info_and_render(tmp_path, capsys):
    n = 300
    _scene_file(tmp_path, n, seed=0, spread=0.5, scale=0.05)
    assert main(["info", str(tmp_path / "s.ply")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["gaussians"] == n and info["sh_degree"] == 0
    c2w = np.eye(4)
    c2w[2, 3] = 4.0  # OpenGL camera on +z looking down -z at the origin
    tj = {
        "w": 40,
        "h": 30,
        "fl_x": 40.0,
        "fl_y": 40.0,
        "cx": 20.0,
        "cy": 15.0,
        "frames": [{"file_path": "x.png", "transform_matrix": c2w.tolist()}],
    }
    (tmp_path / "transforms.json").write_text(json.dumps(tj))
    out = tmp_path / "r.png"
    assert (
        main(
            [
                "render",
                str(tmp_path / "s.ply"),
                "--transforms",
                str(tmp_path / "transforms.json"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    img = np.asarray(Image.open(out))
    assert img.shape == (30, 40, 3) and img.max() > 50  # the cloud is in view


def test_error_is_reported_not_raised(tmp_path, capsys):
    assert main(["info", str(tmp_path / "nope.ply")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_train_and_eval_commands_apply_their_flags(tmp_path, capsys):
    from fmgs.synth import SynthConfig, generate

    generate(tmp_path / "data", SynthConfig(views=9, width=32, height=24, objects=6, seed=0, points=800))
    out = tmp_path / "run"
    assert (
        main(
            [
                "train-gs",
                str(tmp_path / "data"),
                "--out",
                str(out),
                "--steps",
                "12",
                "--grad-threshold",
                "0.5",
                "--seed",
                "3",
            ]
        )
        == 0
    )
    cfg = json.loads((out / "train.json").read_text())["config"]
    assert cfg["densify"]["grad_threshold"] == 0.5 and cfg["steps"] == 12 and cfg["seed"] == 3
    assert (
        main(["eval-gs", str(tmp_path / "data"), str(out / "point_cloud.ply"), "--out", str(tmp_path / "ev")])
        == 0
    )
    printed = capsys.readouterr().out
    assert "mean" in printed and (tmp_path / "ev" / "eval.json").is_file()
    assert " Gaussians (" in printed and "lie beyond the sparse points" in printed  # the floaters line


def _scene_file(tmp_path, n: int = 200, seed: int = 1, spread: float = 0.4, scale: float = 0.06):
    """A random degree-0 scene written as tmp_path/s.ply; returns the path."""
    g = torch.Generator().manual_seed(seed)
    gs = GaussianSet.from_activated(
        torch.randn(n, 3, generator=g) * spread,
        torch.randn(n, 4, generator=g),
        torch.full((n, 3), scale),
        torch.full((n,), 0.8),
        colors=torch.rand(n, 3, generator=g),
    )
    write_ply(gs, tmp_path / "s.ply")
    return tmp_path / "s.ply"


def test_render_reads_datasets_like_every_command(tmp_path, capsys):
    """One reader: Blender-style files (camera_angle_x, no size, extensionless paths), frames numbered
    over the photos that exist (sorted by name), picked by index or image name; user errors exit 2."""
    scene = _scene_file(tmp_path)
    data = tmp_path / "blender"
    (data / "train").mkdir(parents=True)
    poses = []
    for k, z in enumerate((4.0, 5.0, 6.0)):
        c2w = np.eye(4)
        c2w[2, 3] = z
        poses.append(c2w)
        if k != 1:  # r_1's photo is missing
            Image.new("RGB", (36, 24)).save(data / "train" / f"r_{k}.png")
    frames = [{"file_path": f"./train/r_{k}", "transform_matrix": p.tolist()} for k, p in enumerate(poses)]
    (data / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    out = tmp_path / "r.png"
    assert main(["render", str(scene), "--data", str(data), "--frame", "1", "--out", str(out)]) == 0
    assert "train/r_2.png" in capsys.readouterr().out  # index 1 of the photos that exist
    assert np.asarray(Image.open(out)).shape == (24, 36, 3)
    assert main(["render", str(scene), "--data", str(data), "--frame", "r_0.png", "--out", str(out)]) == 0
    assert "train/r_0.png" in capsys.readouterr().out
    for argv, message in (
        (["--frame", "2"], "--frame: 2 is out of range"),
        (["--frame", "r_9.png"], "no frame named 'r_9.png'"),
    ):
        assert main(["render", str(scene), "--data", str(data), *argv, "--out", str(out)]) == 2
        assert message in capsys.readouterr().err
    assert main(["render", str(scene), "--data", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert "no such file or folder" in capsys.readouterr().err


def test_info_describes_a_scene_package_folder(tmp_path, capsys):
    import shutil
    from pathlib import Path

    demo = Path(__file__).resolve().parents[2] / "models" / "demo"
    assert main(["info", str(demo)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["name"] == "demo" and info["encoder"]["dim"] == 384
    assert info["gaussians"] > info["embedded"] > 0 and len(info["bounds_min"]) == 3
    assert "red cube" in info["label_names"] and "source" in info["build"]
    assert info["files"]["manifest.json"] > 0 and "gaussians.safetensors" in info["files"]
    broken = tmp_path / "broken"
    broken.mkdir()
    shutil.copy(demo / "manifest.json", broken)
    assert main(["info", str(broken)]) == 2
    assert "scene package without gaussians.safetensors, embeddings.safetensors" in capsys.readouterr().err


def test_folders_and_photo_folders_get_a_hint(tmp_path, capsys):
    _scene_file(tmp_path)
    assert main(["info", str(tmp_path)]) == 2
    assert (
        "is a folder: pass a scene file (.ply, .splat or .safetensors); it holds s.ply"
        in capsys.readouterr().err
    )
    photos = tmp_path / "shots"
    (photos / "images").mkdir(parents=True)
    Image.new("RGB", (8, 8)).save(photos / "images" / "a.jpg")
    assert main(["eval-gs", str(photos), str(tmp_path / "s.ply")]) == 2
    assert "photos without poses need `fmgs sfm`" in capsys.readouterr().err


def test_synth_robot_bag_and_bag_info(tmp_path, capsys):
    assert (
        main(
            ["synth", "--out", str(tmp_path / "r"), "--size", "48x36", "--objects", "2", "--robot-bag", "1.5"]
        )
        == 0
    )
    assert "1.5 s drive" in capsys.readouterr().out
    assert (tmp_path / "r" / "truth.json").is_file() and len(
        list((tmp_path / "r" / "labels").iterdir())
    ) == 22
    assert main(["bag-info", str(tmp_path / "r" / "bag")]) == 0
    out = capsys.readouterr().out
    assert "colour cameras: /camera/color/image_raw" in out and "depth: /camera/depth/image_raw" in out
    assert main(["bag-info", str(tmp_path / "r" / "bag"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert "camera_optical_frame" in info["tf_frames"] and info["colour_topics"] == [
        "/camera/color/image_raw"
    ]
    assert main(["bag-info", str(tmp_path / "nothing")]) == 2
    assert "no such recording" in capsys.readouterr().err
    assert main(["synth", "--out", str(tmp_path / "x"), "--robot-bag", "-1"]) == 2
