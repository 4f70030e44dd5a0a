"""``fmgs-client`` (``fmgs_client.cli``) against a small in-process fake of the service: every command,
its output files, and errors as one line on stderr with status 1."""

from __future__ import annotations

import pytest

from fmgs_client import cli
from fmgs_client.ply import read_ply
from fmgs_wire.images import decode_png
from tests.helpers.client_fakes import serve_fake


@pytest.fixture(scope="module")
def fake():
    with serve_fake() as served:
        yield served


def test_cli_against_fake(fake, tmp_path, capsys):
    _, address = fake
    base = ["--address", address, "--timeout", "10"]
    assert cli.main([*base, "list"]) == 0
    out = capsys.readouterr().out
    assert "demo" in out and "ready" in out and "bad file" in out
    assert cli.main([*base, "info", "demo"]) == 0
    assert "object, stuff" in capsys.readouterr().out
    ply = tmp_path / "q.ply"
    assert (
        cli.main([*base, "query", "demo", "red cup", "--top-k", "5", "--instances", "--ply", str(ply)]) == 0
    )
    out = capsys.readouterr().out
    assert "'red cup': 5 Gaussians" in out and "1 instances" in out and "relevancy" in out
    back = read_ply(ply)
    assert back.points.shape == (5, 3) and "relevancy" in back.scalars and back.colors is not None
    png, rgb = tmp_path / "r.png", tmp_path / "rgb.png"
    assert (
        cli.main([*base, "render", "demo", "cup", "--size", "12x9", "--out", str(png), "--rgb", str(rgb)])
        == 0
    )
    out = capsys.readouterr().out
    assert "argmax pixel x=11 y=8" in out
    assert decode_png(png.read_bytes()).shape == (9, 12, 3) and decode_png(rgb.read_bytes()).shape == (
        9,
        12,
        3,
    )
    eye = ["--eye", "0", "-3", "1", "--target", "0", "0", "0"]
    assert cli.main([*base, "render", "demo", "cup", *eye, "--size", "4x4", "--out", str(png)]) == 0
    capsys.readouterr()
    assert cli.main([*base, "stream", "demo", "cup", "--frames", "6", "--size", "8x6"]) == 0
    assert "6 of 6 poses" in capsys.readouterr().out
    assert cli.main([*base, "segment", "demo", "x", "y", "--out", str(tmp_path / "seg.png")]) == 0
    assert "gaussians" in capsys.readouterr().out and (tmp_path / "seg.png").is_file()
    # Errors: one line on stderr, status 1.
    assert cli.main([*base, "info", "nope"]) == 1
    err = capsys.readouterr().err
    assert err.strip() == "error: NOT_FOUND: no scene 'nope'"
    assert cli.main([*base, "render", "demo", "", "--out", str(png)]) == 1
    assert capsys.readouterr().err.startswith("error: INVALID_ARGUMENT: ")
    assert cli.main(["--address", "127.0.0.1:1", "--timeout", "2", "list"]) == 1
    assert capsys.readouterr().err.startswith("error: ")


def test_cli_health(fake, capsys):
    _, address = fake
    assert cli.main(["--address", address, "health"]) == 0
    assert capsys.readouterr().out.strip() == "SERVING"
    assert cli.main(["--address", address, "health", "fmgs.v1.Fmgs"]) == 1
    assert capsys.readouterr().out.strip() == "NOT_SERVING"


def test_cli_token_file(fake, tmp_path, capsys):
    svc, address = fake
    tok = tmp_path / "token"
    tok.write_text("abc\n")
    assert cli.main(["--address", address, "--token-file", str(tok), "list"]) == 0
    assert svc.auth[-1] == "Bearer abc"
    capsys.readouterr()


@pytest.mark.parametrize(
    "flags, word",
    [
        (["--fov", "0"], "--fov"),
        (["--fov", "nan"], "--fov"),
        (["--fov", "180"], "--fov"),
        (["--up", "0", "0", "0"], "--up"),
        (["--up", "nan", "0", "1"], "--up"),
    ],
)
def test_default_camera_with_a_bad_fov_or_up_is_one_error_line(fake, tmp_path, capsys, flags, word):
    """The orbit cameras of render, segment and stream: no traceback, an error naming the flag."""
    _, address = fake
    base = ["--address", address, "--timeout", "10"]
    png = str(tmp_path / "r.png")
    for cmd in (["render", "demo", "cup", "--out", png], ["stream", "demo", "cup", "--frames", "2"]):
        assert cli.main([*base, *cmd, "--size", "8x6", *flags]) == 1
        err = capsys.readouterr().err
        assert err.startswith("error: ") and word in err and err.count("\n") == 1, err


@pytest.mark.parametrize("rows", ["-1", "x"])
def test_a_negative_or_non_numeric_rows_is_a_usage_error(fake, capsys, rows):
    """--rows -1 printed a wrong "... N more" line; now argparse refuses it, naming the flag."""
    _, address = fake
    with pytest.raises(SystemExit) as e:
        cli.main(["--address", address, "query", "demo", "red cup", "--rows", rows])
    assert e.value.code == 2
    assert "--rows" in capsys.readouterr().err
