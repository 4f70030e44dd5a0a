"""A stand-in for DINO's dense features: a small fully convolutional network trained without labels
(``standin-dino:FOLDER``).

No pretrained DINO can be had on the development machines, so the parts of FMGS that use DINO (its MSE
head, the dot-product similarity loss, and target schemes that group pixels by DINO similarity) would
only ever see random weights. This encoder is trained by ``scripts/train_standin_dino.py`` on renders of
generated scenes with a self-supervised objective (dense clustering consistent across augmented views:
no label, depth or pose is used), and loads through the dense regulariser's interface (``dense(image
[H,W,3], (h, w)) -> [h,w,D]``, ``id``, ``dim``), as ``DinoEncoder`` does.

What it can show: whether a regulariser or a grouping that needs "pixels of one thing look alike to
DINO" does its job when features have that property. What it cannot: DINO's own semantics (parts of one
object that look different, objects of one kind across scenes), which only pretrained weights show.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from fmgs.errors import ValidationError
from fmgs.features.models import ModelFiles
from fmgs.features.net_folder import build_net, read_net_folder, save_net_folder

CONFIG = "standin_dino.json"
WEIGHTS = "standin_dino.safetensors"
PREFIX = "standin-dino:"


class DenseStandinNet(nn.Module):
    """Images [B,3,H,W] (normalised) -> features [B,dim,ceil(H/2),ceil(W/2)] (not normalised): five 3x3
    convolutions, one halving the side and two dilated (a receptive field of about 27 input pixels),
    then a 1x1 projection."""

    def __init__(self, dim: int = 64, width: int = 32) -> None:
        super().__init__()
        w = width
        self.body = nn.Sequential(
            nn.Conv2d(3, w, 3, padding=1), nn.ReLU(),
            nn.Conv2d(w, 2 * w, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(2 * w, 2 * w, 3, padding=1), nn.ReLU(),
            nn.Conv2d(2 * w, 2 * w, 3, padding=2, dilation=2), nn.ReLU(),
            nn.Conv2d(2 * w, 2 * w, 3, padding=4, dilation=4), nn.ReLU(),
            nn.Conv2d(2 * w, dim, 1),
        )  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x)


def layer_norm(features: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Each feature vector centred and scaled to unit variance along ``dim`` (a ViT's final LayerNorm
    without its affine part), so its scale is that of DINO's tokens."""
    return F.layer_norm(features.movedim(dim, -1), (features.shape[dim],)).movedim(-1, dim)


class DenseStandinEncoder:
    """``DenseStandinNet`` behind the dense regulariser's interface: the image resized so its short side
    is the training renders' (``short_side``), normalised, run once, LayerNorm-ed per pixel and resized
    bilinearly to the requested map."""

    def __init__(self, net: DenseStandinNet, config: dict, model_id: str, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.config = config
        self.id = model_id
        self.dim = int(config["dim"])
        self.short_side = int(config["short_side"])
        self.mean = torch.tensor(config["mean"], dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(config["std"], dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.files: ModelFiles | None = None

    def input_size(self, H: int, W: int) -> tuple[int, int]:
        """(h, w) the network sees for an H x W image: short side ``short_side``, aspect kept."""
        f = self.short_side / min(H, W)
        return max(1, round(H * f)), max(1, round(W * f))

    @torch.inference_mode()
    def dense(self, image: torch.Tensor, out_hw: tuple[int, int]) -> torch.Tensor:
        """image [H,W,3] float RGB in [0,1] -> [h,w,D] float32 at out_hw = (h, w), on image's device."""
        if image.ndim != 3 or image.shape[-1] != 3:
            raise ValidationError("image", f"expected [H,W,3], got {tuple(image.shape)}")
        x = image.permute(2, 0, 1).unsqueeze(0).to(self.device, torch.float32)
        size = self.input_size(*image.shape[:2])
        if tuple(x.shape[-2:]) != size:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)
        f = layer_norm(self.net((x - self.mean) / self.std), dim=1)
        out = F.interpolate(f, size=tuple(out_hw), mode="bilinear", align_corners=False)
        return out[0].permute(1, 2, 0).contiguous().to(image.device)


def save_standin_dino(folder: str | os.PathLike, net: DenseStandinNet, config: dict) -> Path:
    """Write FOLDER/standin_dino.json and FOLDER/standin_dino.safetensors (fmgs.features.net_folder)."""
    return save_net_folder(folder, net, config, CONFIG, WEIGHTS)


def load_standin_dino(model_id: str, device: str | torch.device = "cpu") -> DenseStandinEncoder:
    """The encoder of a ``standin-dino:FOLDER`` id."""
    config, state, files = read_net_folder(model_id, PREFIX, CONFIG, WEIGHTS)

    def make() -> DenseStandinEncoder:
        net = DenseStandinNet(int(config["dim"]), int(config["width"]))
        net.load_state_dict(state)
        return DenseStandinEncoder(net, config, model_id, device)

    enc = build_net(model_id, make)
    enc.files = files
    return enc
