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
