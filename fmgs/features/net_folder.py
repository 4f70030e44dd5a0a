"""The stand-ins' shipped form: a folder of one JSON config and the network's weights as float16
safetensors (half the size; integer buffers such as batch norm's counters kept as they are)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch

from fmgs.features.models import ModelFiles, ModelNotFoundError, local_weight_hashes


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
    ModelNotFoundError naming both files when either is missing."""
    from safetensors.torch import load_file

    folder = Path(model_id.removeprefix(prefix)).expanduser()
    if not (folder / config_name).is_file() or not (folder / weights_name).is_file():
        raise ModelNotFoundError(model_id, [f"{folder} (needs {config_name} and {weights_name})"])
    config = json.loads((folder / config_name).read_text())
    state = {
        k: v.float() if v.is_floating_point() else v for k, v in load_file(str(folder / weights_name)).items()
    }
    return config, state, ModelFiles(model_id, folder, "local", files=local_weight_hashes(folder))
