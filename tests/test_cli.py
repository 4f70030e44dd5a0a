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
    g = torch.Generator().manual_seed(0)
    gs = GaussianSet.from_activated(
        torch.randn(n, 3, generator=g) * 0.5,
        torch.randn(n, 4, generator=g),
        torch.full((n, 3), 0.05),
        torch.full((n,), 0.8),
        colors=torch.rand(n, 3, generator=g),
    )
    write_ply(gs, tmp_path / "s.ply")
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
    assert "mean" in capsys.readouterr().out and (tmp_path / "ev" / "eval.json").is_file()
