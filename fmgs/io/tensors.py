"""GaussianSet to and from safetensors (no pickle)."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from fmgs.errors import ValidationError
from fmgs.gaussians import GaussianSet
from fmgs.io.atomic import atomic_path

FORMAT = "fmgs.gaussians"
VERSION = "1"


def save_gaussians(gaussians: GaussianSet, path: str | os.PathLike) -> None:
    """Write the stored parameters as safetensors with a small format header, atomically."""
    from safetensors.torch import save_file

    tensors = {k: v.detach().cpu().contiguous() for k, v in gaussians.tensors().items()}
    meta = {"format": FORMAT, "version": VERSION, "sh_degree": str(gaussians.sh_degree)}
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=meta)


def load_gaussians(path: str | os.PathLike, device: str | torch.device = "cpu") -> GaussianSet:
    """Read a file written by ``save_gaussians``; ValidationError on a wrong format or bad values."""
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    try:
        with safe_open(str(path), framework="pt", device=str(device)) as f:
            meta = f.metadata() or {}
            if meta.get("format") != FORMAT:
                raise ValidationError(str(path), f"not an {FORMAT} file (format={meta.get('format')!r})")
            if meta.get("version") != VERSION:
                raise ValidationError(str(path), f"unsupported version {meta.get('version')!r}")
            data = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError) as e:
        raise ValidationError(str(path), f"cannot read safetensors file ({e})") from e
    names = ["means", "quats", "log_scales", "opacity_logits", "sh"]
    missing = [n for n in names if n not in data]
    if missing:
        raise ValidationError(str(path), f"missing tensors {missing}")
    return GaussianSet(**{n: data[n] for n in names})
