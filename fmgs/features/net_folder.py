"""The stand-ins' shipped form: a folder of one JSON config and the network's weights as float16
safetensors (half the size; integer buffers such as batch norm's counters kept as they are)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import torch

from fmgs.errors import ValidationError
from fmgs.features.models import ModelFiles, ModelNotFoundError, local_weight_hashes

T = TypeVar("T")


def save_net_folder(folder: str | os.PathLike, net: torch.nn.Module, config: dict, config_name: str,
                    weights_name: str) -> Path:  # fmt: skip
    """Write FOLDER/config_name and FOLDER/weights_name; returns the folder."""
    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    state = {k: (v.detach().half() if v.is_floating_point() else v.detach()).contiguous()
             for k, v in net.state_dict().items()}  # fmt: skip
    save_file(state, str(folder / weights_name))
    (folder / config_name).write_text(json.dumps(config, indent=1))
    return folder


def read_net_folder(model_id: str, prefix: str, config_name: str,
                    weights_name: str) -> tuple[dict, dict[str, torch.Tensor], ModelFiles]:  # fmt: skip
    """The folder a ``PREFIX:FOLDER`` id names -> (its config, its state dict in float32, its files);
    ModelNotFoundError naming both files when either is missing, ValidationError naming the file that
    cannot be read."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    rest = model_id.removeprefix(prefix)
    if not rest.strip():
        raise ValidationError("encoder id", f"{model_id!r} names no folder")
    folder = Path(rest).expanduser()
    if not (folder / config_name).is_file() or not (folder / weights_name).is_file():
        raise ModelNotFoundError(model_id, [f"{folder} (needs {config_name} and {weights_name})"])
    try:
        config = json.loads((folder / config_name).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise ValidationError(str(folder / config_name), f"cannot read the config ({e})") from e
    if not isinstance(config, dict):
        got = type(config).__name__
        raise ValidationError(str(folder / config_name), f"expected a JSON object, got {got}")
    try:
        weights = load_file(str(folder / weights_name))
    except (SafetensorError, OSError) as e:
        raise ValidationError(str(folder / weights_name), f"cannot read the weights ({e})") from e
    state = {k: v.float() if v.is_floating_point() else v for k, v in weights.items()}
    return config, state, ModelFiles(model_id, folder, "local", files=local_weight_hashes(folder))


def build_net(model_id: str, make: Callable[[], T]) -> T:
    """``make()`` (a stand-in built from its folder's config and weights), a ValidationError naming the id
    when the config lacks a setting or the weights do not fit the network it describes."""
    try:
        return make()
    except ValidationError:
        raise
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        why = f"{type(e).__name__}: {e}"
        raise ValidationError(model_id, f"its config and weights do not make the model ({why[:400]})") from e
