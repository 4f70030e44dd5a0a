"""A stand-in for a class-agnostic segmenter (SAM's role): a small network that says which neighbouring
pixels belong to one thing (``standin-seg:FOLDER``).

Mask-based open-vocabulary methods (LangSplat, OpenMask3D, Gaussian Grouping) cut each image into
segments with SAM and give every pixel of a segment one CLIP embedding, so that a small object's pixels
are named by what the object's own crops say, not by crops dominated by the floor around it. No SAM can
be had on the development machines, so this network takes its role. Like SAM it is trained with masks
and knows no names: ``scripts/train_standin_seg.py`` fits it on the instance masks of generated scenes
(which pixel pairs lie on one object, one floor, one wall), seeds no benchmark scores. It predicts, per
pixel, whether the pixel belongs with its right and its lower neighbour (affinities); segments are the
connected components of the pixels joined by confident affinities (``affinity_segments``).

What it can show: how much better targets become when small objects get masks of their own, with a
segmenter that errs as learned segmenters do (parts of textured objects split, low-contrast boundaries
leak). What it cannot: SAM's masks on real photos (its granularity, its whole-object vs part choices).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from fmgs.errors import ValidationError
from fmgs.features.models import ModelFiles
from fmgs.features.net_folder import build_net, read_net_folder, save_net_folder
from fmgs.features.segment_pool import MIN_PIXELS, relabel

CONFIG = "standin_seg.json"
WEIGHTS = "standin_seg.safetensors"
PREFIX = "standin-seg:"
JOIN = 0.8
"""Default affinity above which two neighbouring pixels are joined into one segment. Conservative, as SAM's
mask generator keeps only stable masks: one leaked boundary pair merges an object with the floor and
costs it its name, while a split object's parts still pool their own pixels (chosen on the dev scenes
301 and 302 among 0.3, 0.5 and 0.8 by the mIoU of the pooled target maps)."""


class SegStandinNet(nn.Module):
    """Images [B,3,H,W] (normalised, H and W even) -> affinity logits [B,2,H,W]: channel 0 that pixel
    (y, x) and (y, x+1) are one segment, channel 1 that (y, x) and (y+1, x) are (the last column's and
    last row's are meaningless). A small U-Net: full-resolution convolutions, a half-resolution body
    with dilated convolutions (a receptive field of about 50 pixels, so that a textured object's
    stripes are seen as one surface), upsampled and joined with the full-resolution features."""

    def __init__(self, width: int = 24) -> None:
        super().__init__()
        w = width
        self.stem = nn.Sequential(
            nn.Conv2d(3, w, 3, padding=1), nn.ReLU(), nn.Conv2d(w, w, 3, padding=1), nn.ReLU()
        )  # fmt: skip
        self.body = nn.Sequential(
            nn.Conv2d(w, 2 * w, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(2 * w, 2 * w, 3, padding=2, dilation=2), nn.ReLU(),
            nn.Conv2d(2 * w, 2 * w, 3, padding=4, dilation=4), nn.ReLU(),
            nn.Conv2d(2 * w, 2 * w, 3, padding=8, dilation=8), nn.ReLU(),
            nn.Conv2d(2 * w, 2 * w, 3, padding=1), nn.ReLU(),
        )  # fmt: skip
        self.head = nn.Sequential(
            nn.Conv2d(3 * w, w, 3, padding=1), nn.ReLU(), nn.Conv2d(w, 2, 3, padding=1)
        )  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = self.stem(x)
        b = F.interpolate(self.body(s), size=s.shape[-2:], mode="bilinear", align_corners=False)
        return self.head(torch.cat([s, b], 1))


def affinity_targets(labels: torch.Tensor) -> torch.Tensor:
    """labels [B,H,W] int -> [B,2,H,W] float: 1 where a pixel and its right (channel 0) / lower (1)
    neighbour carry one label, else 0 (0 in the last column / row)."""
    out = torch.zeros(labels.shape[0], 2, *labels.shape[1:])
    out[:, 0, :, :-1] = (labels[:, :, 1:] == labels[:, :, :-1]).float()
    out[:, 1, :-1, :] = (labels[:, 1:, :] == labels[:, :-1, :]).float()
    return out


def affinity_segments(affinity: np.ndarray, join: float = JOIN, min_pixels: int = MIN_PIXELS) -> np.ndarray:
    """affinity [2,H,W] probabilities (``SegStandinNet``'s channels) -> [H,W] int64 segment ids 1..n
    (0: in a segment of fewer than ``min_pixels``): the connected components of the graph whose edges
    are the neighbour pairs with affinity above ``join``; ids in order of each segment's first pixel
    (row-major)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    _, H, W = affinity.shape
    idx = np.arange(H * W).reshape(H, W)
    right = affinity[0, :, :-1] > join
    down = affinity[1, :-1, :] > join
    a = np.concatenate([idx[:, :-1][right], idx[:-1, :][down]])
    b = np.concatenate([idx[:, 1:][right], idx[1:, :][down]])
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(H * W, H * W))
    _, comp = connected_components(graph, directed=False)
    return relabel(comp.reshape(H, W), min_pixels)


def affinity_segments_reference(affinity: np.ndarray, join: float = JOIN,
                                min_pixels: int = MIN_PIXELS) -> np.ndarray:  # fmt: skip
    """``affinity_segments`` by a breadth-first flood fill from each pixel in row-major order: the
    exact twin the tests hold the sparse-graph version to."""
    from collections import deque

    _, H, W = affinity.shape
    comp = -np.ones((H, W), np.int64)
    n = 0
    for y0 in range(H):
        for x0 in range(W):
            if comp[y0, x0] >= 0:
                continue
            comp[y0, x0] = n
            todo = deque([(y0, x0)])
            while todo:
                y, x = todo.popleft()
                for ny, nx, p in ((y, x + 1, affinity[0, y, x] if x + 1 < W else 0.0),
                                  (y + 1, x, affinity[1, y, x] if y + 1 < H else 0.0),
                                  (y, x - 1, affinity[0, y, x - 1] if x > 0 else 0.0),
                                  (y - 1, x, affinity[1, y - 1, x] if y > 0 else 0.0)):  # fmt: skip
                    if p > join and comp[ny, nx] < 0:
                        comp[ny, nx] = n
                        todo.append((ny, nx))
            n += 1
    return relabel(comp, min_pixels)


def object_segment_scores(seg: np.ndarray, labels: np.ndarray, objects) -> tuple[list[float], int, int]:
    """How a segmentation ``seg`` [H,W] (0: no segment) serves the objects ``objects`` (label ids) of
    ``labels`` [H,W]: (each present object's best IoU with one segment, object pixels whose segment is
    mostly their own object, object pixels)."""
    ious, own, total = [], 0, 0
    for c in objects:
        m = labels == c
        if not m.any():
            continue
        ids, counts = np.unique(seg[m], return_counts=True)
        sizes = {int(i): int((seg == i).sum()) for i in ids if i}
        ious.append(max((k / float((m | (seg == i)).sum()) for i, k in zip(ids, counts, strict=True) if i),
                        default=0.0))  # fmt: skip
        own += sum(int(k) for i, k in zip(ids, counts, strict=True) if i and 2 * k > sizes[int(i)])
        total += int(m.sum())
    return ious, own, total


class SegStandinEncoder:
    """``SegStandinNet`` behind a segmenter's interface: ``segments(image [H,W,3]) -> [H,W] int64``. The
    image is resized so its short side is the training renders' and padded to even sides, the
    affinities resized back to the image's size."""

    def __init__(self, net: SegStandinNet, config: dict, model_id: str, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.config = config
        self.id = model_id
        self.short_side = int(config["short_side"])
        self.join = float(config.get("join", JOIN))
        self.mean = torch.tensor(config["mean"], dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(config["std"], dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.files: ModelFiles | None = None

    @torch.inference_mode()
    def affinity(self, image: torch.Tensor) -> np.ndarray:
        """image [H,W,3] float RGB in [0,1] -> [2,H,W] float32 probabilities (see ``SegStandinNet``)."""
        if image.ndim != 3 or image.shape[-1] != 3:
            raise ValidationError("image", f"expected [H,W,3], got {tuple(image.shape)}")
        H, W = image.shape[:2]
        x = image.permute(2, 0, 1).unsqueeze(0).to(self.device, torch.float32)
        f = self.short_side / min(H, W)
        h, w = max(2, round(H * f)), max(2, round(W * f))
        if (h, w) != (H, W):
            x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        x = F.pad((x - self.mean) / self.std, (0, w % 2, 0, h % 2), mode="replicate")
        p = torch.sigmoid(self.net(x))[..., :h, :w]
        if (h, w) != (H, W):
            p = F.interpolate(p, size=(H, W), mode="bilinear", align_corners=False)
        return p[0].float().cpu().numpy()

    def segments(self, image: torch.Tensor, min_pixels: int = MIN_PIXELS) -> np.ndarray:
        """image [H,W,3] -> [H,W] int64 segment ids (``affinity_segments`` at the model's ``join``)."""
        return affinity_segments(self.affinity(image), self.join, min_pixels)


def save_standin_seg(folder: str | os.PathLike, net: SegStandinNet, config: dict) -> Path:
    """Write FOLDER/standin_seg.json and FOLDER/standin_seg.safetensors (fmgs.features.net_folder)."""
    return save_net_folder(folder, net, config, CONFIG, WEIGHTS)


def load_segmenter(model_id: str, device: str | torch.device = "cpu", *, revision: str | None = None,
                   offline: bool | str | None = None):  # fmt: skip
    """The segmenter of an id: the stand-in (``standin-seg:FOLDER``) or SAM (a transformers ``sam`` model:
    a hub id, ``hf:`` id or folder, at ``revision``, fmgs.features.sam). Both offer ``segments(image)``,
    ``id`` and ``files``."""
    from fmgs.features.registry import parse_encoder_id

    family = parse_encoder_id(model_id).family
    if family == "standin-seg":
        return load_standin_seg(model_id, device)
    if family != "hf":
        raise ValidationError(
            "segmenter", f"{model_id!r} is not a segmenter id; give standin-seg:FOLDER or a SAM model"
        )
    from fmgs.features.models import DEFAULT_REVISION
    from fmgs.features.sam import SamSegmenter

    return SamSegmenter.load(model_id, device, revision=revision or DEFAULT_REVISION, offline=offline)


def load_standin_seg(model_id: str, device: str | torch.device = "cpu") -> SegStandinEncoder:
    """The segmenter of a ``standin-seg:FOLDER`` id."""
    config, state, files = read_net_folder(model_id, PREFIX, CONFIG, WEIGHTS)

    def make() -> SegStandinEncoder:
        net = SegStandinNet(int(config["width"]))
        net.load_state_dict(state)
        return SegStandinEncoder(net, config, model_id, device)

    enc = build_net(model_id, make)
    enc.files = files
    return enc
