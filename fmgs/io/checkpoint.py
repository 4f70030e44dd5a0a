"""Training checkpoints as safetensors: module tensors, optimiser state, JSON counters. No pickle."""

from __future__ import annotations

import json
import os

import torch

from fmgs.errors import ValidationError
from fmgs.io.atomic import atomic_path


def save_training_state(
    path: str | os.PathLike,
    fmt: str,
    tensors: dict[str, torch.Tensor],
    optimizer: torch.optim.Optimizer,
    meta: dict,
) -> None:
    """Write module tensors, the optimiser's per-parameter state and ``meta`` (JSON-able) atomically."""
    from safetensors.torch import save_file

    t = {f"param/{k}": v.detach().cpu().contiguous() for k, v in tensors.items()}
    sd = optimizer.state_dict()
    scalars: dict[str, dict] = {}
    for i, st in sd["state"].items():
        for k, v in st.items():
            if torch.is_tensor(v) and v.ndim > 0:
                t[f"opt/{i}/{k}"] = v.detach().cpu().contiguous()
            else:
                scalars.setdefault(str(i), {})[k] = float(v)
    groups = [
        {k: v for k, v in g.items() if k != "params"} | {"params": g["params"]} for g in sd["param_groups"]
    ]
    header = {
        "format": fmt,
        "meta": json.dumps(meta),
        "groups": json.dumps(groups),
        "scalars": json.dumps(scalars),
    }
    with atomic_path(path) as tmp:
        save_file(t, str(tmp), metadata=header)


def load_training_state(path: str | os.PathLike, fmt: str) -> tuple[dict[str, torch.Tensor], dict, dict]:
    """(module tensors, optimiser state_dict, meta) from ``save_training_state``'s file."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
            if header.get("format") != fmt:
                raise ValidationError(str(path), f"not a {fmt} checkpoint (format={header.get('format')!r})")
            t = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError) as e:
        raise ValidationError(str(path), f"cannot read checkpoint ({e})") from e
    tensors = {k[len("param/") :]: v for k, v in t.items() if k.startswith("param/")}
    state: dict[int, dict] = {}
    for k, v in t.items():
        if k.startswith("opt/"):
            _, i, name = k.split("/", 2)
            state.setdefault(int(i), {})[name] = v
    for i, sc in json.loads(header["scalars"]).items():
        for k, v in sc.items():
            state.setdefault(int(i), {})[k] = torch.tensor(v) if k == "step" else v
    opt_sd = {"state": state, "param_groups": json.loads(header["groups"])}
    return tensors, opt_sd, json.loads(header["meta"])
