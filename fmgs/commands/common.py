"""What several ``fmgs`` commands share: reading a scene file, settings from a config dataclass, the
device, and the flags more than one command takes."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

AUTO_DEVICE = {"device": "auto"}
"""The commands pick the GPU when there is one (the library's configs default to the CPU)."""


def load_scene(path: Path):
    """The Gaussians of a scene file (.ply, compressed .ply, .splat or fmgs .safetensors); a folder gets a
    ValidationError naming the scene files it holds."""
    from fmgs.errors import ValidationError
    from fmgs.io.ply import read_ply
    from fmgs.io.tensors import load_gaussians

    if path.is_dir():
        found = sorted(
            str(p.relative_to(path))
            for p in path.glob("**/*")
            if p.suffix in (".ply", ".splat", ".safetensors")
        )
        hint = f"; it holds {', '.join(found[:3])}" if found else ""
        raise ValidationError(
            str(path), f"is a folder: pass a scene file (.ply, .splat or .safetensors){hint}"
        )
    return load_gaussians(path) if path.suffix == ".safetensors" else read_ply(path)


def out_folder(path, what: str, flag: str = "--out") -> None:
    """ValidationError naming ``flag`` when ``path`` (the folder for ``what``) is a file."""
    from fmgs.errors import ValidationError

    if path and Path(path).exists() and not Path(path).is_dir():
        raise ValidationError(flag, f"{path} is a file, not a folder for {what}")


def positive_scale(flag: str, value: float) -> None:
    """ValidationError naming ``flag`` unless ``value`` is a finite number above 0 (an image scale)."""
    import math

    from fmgs.errors import ValidationError

    if not math.isfinite(value) or value <= 0:
        raise ValidationError(flag, f"must be a positive number, got {value}")


def numbers(flag: str, text: str, count: int, expected: str) -> tuple[float, ...]:
    """``count`` comma-separated numbers from a flag's text; ValidationError naming the flag otherwise."""
    from fmgs.errors import ValidationError

    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != count:
        raise ValidationError(flag, f"expected {expected}, got {text!r}")
    return values


def settings(args, cls, defaults=None, base=None):
    """A ``cls`` config from the command's flags and its --config TOML file (fmgs/flags.py), validated;
    ``base(cfg)``: a base derived from those settings, which the same settings are then applied over;
    ``device`` "auto" resolved."""
    from fmgs import flags
    from fmgs.errors import ValidationError

    try:
        values = flags.values_from(cls, args, args.config, defaults)
        where = str(args.config or "flags")
        cfg = flags.build(cls, values, where)  # validates every value
        if base is not None:  # then the same settings over a base derived from them
            cfg = flags.build(cls, values, where, base(cfg))
    except ValueError as e:
        raise ValidationError("settings", str(e)) from e
    if getattr(cfg, "device", None) == "auto":
        cfg = replace(cfg, device=auto_device())
    return cfg


def auto_device() -> str:
    """``--device auto``: the first CUDA device when torch sees one, else the CPU."""
    import importlib.util

    if importlib.util.find_spec("torch") is None:
        return "cpu"
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def config_flag(p: argparse.ArgumentParser, what: str) -> None:
    """``--config TOML``: ``what`` settings from a file, under the flags."""
    p.add_argument(
        "--config",
        metavar="TOML",
        help=f"{what} settings from a TOML file (keys: the long flag names with _ for -, tables for the "
        "nested groups); flags given on the command line win",
    )


def undistort_flag(p: argparse.ArgumentParser) -> None:
    """``--undistort-dir``: where a distorted dataset's undistorted copy goes."""
    p.add_argument(
        "--undistort-dir",
        help="where the undistorted copy of a dataset with lens distortion goes (default: "
        "fmgs_undistorted/ beside the dataset; made once, reused while the dataset is unchanged)",
    )


def no_dotsim_flag(p) -> None:
    """``--no-dotsim``: the ablation without the dot-product-similarity loss."""
    p.add_argument("--no-dotsim", action="store_true", help="ablation: no dot-product-similarity loss")
