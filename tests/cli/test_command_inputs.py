"""The fmgs commands on bad input: exit 2 naming what is wrong, nothing written; strict JSON outputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from fmgs.cli import main
from fmgs.gaussians import GaussianSet
from fmgs.io.ply import write_ply

DEMO = Path(__file__).resolve().parents[2] / "models" / "demo"


def _strict_json(text: str):
    """``text`` parsed as strict JSON (NaN, Infinity and -Infinity refused)."""

    def refuse(name):
        raise ValueError(f"{name} is not JSON")

    return json.loads(text, parse_constant=refuse)


def _black_dataset(folder: Path, views: int = 2) -> Path:
    """Black 24x16 photos, cameras on +z looking down -z (OpenGL), declared black background."""
    (folder / "images").mkdir(parents=True)
    frames = []
    for k in range(views):
        Image.new("RGB", (24, 16)).save(folder / "images" / f"v{k}.png")
        c2w = np.eye(4)
        c2w[2, 3] = 4.0 + k
        frames.append({"file_path": f"images/v{k}.png", "transform_matrix": c2w.tolist()})
    tj = {"w": 24, "h": 16, "fl_x": 20.0, "fl_y": 20.0, "cx": 12.0, "cy": 8.0, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(tj))
    return folder


def _scene_behind(path: Path) -> Path:
    """A few Gaussians behind every camera of _black_dataset: each render is the black background."""
    n = 8
    gs = GaussianSet.from_activated(
        torch.tensor([[0.0, 0.0, 50.0]]).repeat(n, 1),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        torch.full((n, 3), 0.05),
        torch.full((n,), 0.8),
        colors=torch.ones(n, 3),
    )
    write_ply(gs, path)
    return path


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--size", "128"], "--size: expected WxH"),
        (["--size", "axb"], "--size: expected WxH"),
        (["--size", "0x0"], "--size: expected WxH"),
        (["--views", "0"], "views must be at least 1, got 0"),
        (["--views", "-3"], "views must be at least 1, got -3"),
        (["--points", "-4"], "points must be at least 0"),
        (["--objects", "-1"], "objects must be in 1..8"),
        (["--preset", "world", "--objects", "3", "--novel", "5"], "novel must be in 0..3"),
    ],
)
def test_synth_refuses_bad_settings_before_writing(tmp_path, capsys, argv, message):
    out = tmp_path / "d"
    assert main(["synth", "--out", str(out), "--size", "16x12", "--views", "2", *argv]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_synth_refuses_a_file_as_its_folder(tmp_path, capsys):
    (tmp_path / "f").write_text("keep")
    assert main(["synth", "--out", str(tmp_path / "f"), "--size", "16x12", "--views", "2"]) == 2
    assert "is a file" in capsys.readouterr().err
    assert (tmp_path / "f").read_text() == "keep"


def test_render_refuses_bad_out_and_scale_before_rendering(tmp_path, capsys):
    data = _black_dataset(tmp_path / "data")
    scene = _scene_behind(tmp_path / "s.ply")
    base = ["render", str(scene), "--data", str(data)]
    for argv, message in (
        (["--out", str(tmp_path)], "is a folder: name the image file"),
        (["--out", str(tmp_path / "r.xyz")], "not an image file name"),
        (["--out", str(tmp_path / "r")], "not an image file name"),
        (["--scale", "0", "--out", str(tmp_path / "r.png")], "--scale: must be a positive number"),
        (["--scale", "nan", "--out", str(tmp_path / "r.png")], "--scale: must be a positive number"),
    ):
        assert main([*base, *argv]) == 2, argv
        assert message in capsys.readouterr().err
    assert not (tmp_path / "r.png").exists() and not (tmp_path / "r.xyz").exists()
    out = tmp_path / "new dir é" / "r.JPG"  # a new folder, a space, non-ASCII, an upper-case extension
    assert main([*base, "--out", str(out)]) == 0
    assert Image.open(out).format == "JPEG" and [p.name for p in out.parent.iterdir()] == ["r.JPG"]


def test_eval_gs_of_an_exact_render_writes_strict_json(tmp_path, capsys):
    data = _black_dataset(tmp_path / "data")
    scene = _scene_behind(tmp_path / "s.ply")
    out = tmp_path / "eval é x"
    assert main(["eval-gs", str(data), str(scene), "--background", "0,0,0", "--out", str(out)]) == 0
    doc = _strict_json((out / "eval.json").read_text())
    assert doc["psnr"] == "inf" and doc["views"][0]["psnr"] == "inf" and doc["ssim"] == 1.0
    assert float(doc["worst"]["psnr"]) == float("inf")
    capsys.readouterr()


def test_eval_gs_refuses_bad_flags_before_any_work(tmp_path, capsys):
    data = _black_dataset(tmp_path / "data")
    scene = _scene_behind(tmp_path / "s.ply")
    (tmp_path / "f").write_text("keep")
    base = ["eval-gs", str(data), str(scene)]
    for argv, message in (
        (["--scale", "0"], "--scale: must be a positive number"),
        (["--scale", "nan"], "--scale: must be a positive number"),
        (["--background", "nan,0,0"], "--background: expected auto or R,G,B in [0,1]"),
        (["--background", "5,0,0"], "--background: expected auto or R,G,B in [0,1]"),
        (["--out", str(tmp_path / "f")], "is a file, not a folder"),
    ):
        assert main([*base, *argv]) == 2, argv
        assert message in capsys.readouterr().err
    assert (tmp_path / "f").read_text() == "keep"


def test_info_describes_a_sharded_scene(tmp_path, capsys):
    out = tmp_path / "sharded é"
    assert main(["shard", str(DEMO), "--shards", "2", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    info = _strict_json(capsys.readouterr().out)
    assert info["name"] == "demo" and len(info["shards"]) == 2
    assert sum(s["gaussians"] for s in info["shards"]) == info["gaussians"]
    assert "-inf" in info["shards"][0]["cell"]  # an open side of a k-d cell
    (out / "shards.json").write_text('{"format": "fmgs.shards"}')
    assert main(["info", str(out)]) == 2
    assert "malformed shard manifest" in capsys.readouterr().err


def test_commands_refuse_a_file_as_their_out_folder(tmp_path, capsys):
    data = _black_dataset(tmp_path / "data")
    scene = _scene_behind(tmp_path / "s.ply")
    f = tmp_path / "f"
    f.write_text("keep")
    for argv, what in (
        (["train-gs", str(data), "--steps", "2", "--device", "cpu"], "the checkpoint and point_cloud.ply"),
        (["features", str(data), "--targets", "labels", "--device", "cpu"], "the feature cache"),
        (
            ["train-field", str(data), "--gaussians", str(scene), "--features", str(tmp_path / "c")],
            "the checkpoint and field_train.json",
        ),
        (["sfm", str(data / "images")], "the reconstruction"),
    ):
        assert main([*argv, "--out", str(f)]) == 2, argv
        assert f"--out: {f} is a file, not a folder for {what}" in capsys.readouterr().err
    assert f.read_text() == "keep"


_RAISING = """
import argparse, sys
from fmgs import cli
def stop(args):
    raise {error}
class Parser:
    def parse_args(self, argv):
        return argparse.Namespace(command="synth", func=stop)
cli.build_parser = Parser
sys.exit(cli.main(["synth"]))
"""


@pytest.mark.parametrize(
    "error, code, said",
    [("KeyboardInterrupt", 130, "fmgs: synth: interrupted"), ("BrokenPipeError", 141, "")],
    ids=["ctrl-c", "closed pipe"],
)
def test_ctrl_c_and_a_closed_pipe_end_quietly(error, code, said):
    """Ctrl-C printed a KeyboardInterrupt traceback and `fmgs info ... | head` a BrokenPipeError one: now
    one line and 130 (the shell's code for SIGINT), and 141 (SIGPIPE's) with nothing said."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", _RAISING.format(error=error)], capture_output=True, text=True)
    assert r.returncode == code and r.stderr.strip() == said, r.stderr
