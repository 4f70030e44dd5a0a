"""Drivers that fill a feature cache from a posed dataset (resumable: done images are skipped).

Map sizes follow ``Frame.camera.scaled(scale)`` (``feature_size``), so a trainer rendering with the same
scaled camera gets pixel-aligned targets.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fmgs.cameras import Camera
from fmgs.data.dataset import Frame, PosedDataset
from fmgs.errors import ValidationError
from fmgs.features.cache import FeatureCache, FeatureCacheWriter, TargetInfo
from fmgs.features.clip import ImageEncoder
from fmgs.features.dino import DinoEncoder
from fmgs.features.labels import label_embedding_map
from fmgs.features.pyramid import PyramidConfig, hybrid_map
from fmgs.features.segment_pool import pool_segments, resize_segments
from fmgs.features.sizes import FEATURE_SIDE, check_feature_scale, feature_scale_for
from fmgs.features.text import TextEncoder


@dataclass(frozen=True)
class ExtractConfig:
    """How target maps are extracted."""

    feature_scale: float | None = None
    """Stored maps are this fraction of the full image size per axis (rounded like Camera.scaled);
    None: the fraction that makes the map's longer side ``feature_side`` pixels (1 for smaller images)."""
    feature_side: int = FEATURE_SIDE
    """Longer side of the stored maps in pixels when ``feature_scale`` is None."""
    image_scale: float = 1.0
    """Fraction of the full resolution the CLIP crops and the DINO input are taken from."""
    device: str = "cpu"
    """Where images and the pyramid arithmetic live (encoders keep their own device)."""
    progress: bool = True
    """Show a progress bar over images."""

    def __post_init__(self) -> None:
        check_feature_scale(self.feature_scale, self.feature_side)
        if not 0.0 < self.image_scale <= 1.0:
            raise ValidationError("image_scale", f"must lie in (0, 1], got {self.image_scale}")


def feature_size(
    camera: Camera, feature_scale: float | None, feature_side: int = FEATURE_SIDE
) -> tuple[int, int]:
    """(h, w) of the stored maps for a full-resolution ``camera``."""
    c = camera.scaled(feature_scale_for(camera.width, camera.height, feature_scale, feature_side))
    return c.height, c.width


def clip_settings(pyramid: PyramidConfig, cfg: ExtractConfig, segmenter_id: str | None) -> dict:
    """What besides the encoders decides an image's CLIP (and DINO) maps, as the cache records it
    (FeatureCacheWriter's ``settings``): a resumed run with others is refused."""
    return {
        "kind": "clip",
        "crop_scales": list(pyramid.scales),
        "overlap": pyramid.overlap,
        "crop_stride": pyramid.max_stride,
        "scale_blend": pyramid.blend,
        "segmenter": segmenter_id,
        "feature_scale": cfg.feature_scale,
        "feature_side": cfg.feature_side,
        "image_scale": cfg.image_scale,
    }


def label_settings(names: Sequence[str], ignore: frozenset[int] | set[int], cfg: ExtractConfig) -> dict:
    """What besides the text encoder decides an image's label targets (``clip_settings``' twin)."""
    return {
        "kind": "labels",
        "names": list(names),
        "ignore": sorted(int(v) for v in ignore),
        "feature_scale": cfg.feature_scale,
        "feature_side": cfg.feature_side,
    }


def _todo(ds: PosedDataset, writer: FeatureCacheWriter, indices: Sequence[int] | None) -> list[int]:
    idx = list(range(len(ds))) if indices is None else list(indices)
    return [i for i in idx if not writer.has(ds.frames[i].name)]


def extract_targets(
    ds: PosedDataset,
    cache_dir: str | os.PathLike,
    clip_encoder: ImageEncoder,
    dino_encoder: DinoEncoder | None = None,
    pyramid: PyramidConfig | None = None,
    cfg: ExtractConfig = ExtractConfig(),
    indices: Sequence[int] | None = None,
    segmenter=None,
) -> FeatureCache:
    """Hybrid CLIP maps (and DINO maps when ``dino_encoder`` is given) for the frames ``indices`` (all by
    default) into ``cache_dir``; both maps of an image go into one file. Returns the opened cache.
    ``pyramid`` defaults to ``PyramidConfig()``; ``segmenter`` (``segments(image) -> [H,W] ids``, e.g.
    fmgs.features.standin_seg): each CLIP map pooled within the image's segments (``image_targets``).
    """
    pyramid = PyramidConfig() if pyramid is None else pyramid
    targets = {"clip": TargetInfo(clip_encoder.id, clip_encoder.dim, True)}
    if dino_encoder is not None:
        targets["dino"] = TargetInfo(dino_encoder.id, dino_encoder.dim, False)
    from tqdm.auto import tqdm

    seg_id = None if segmenter is None else str(getattr(segmenter, "id", type(segmenter).__name__))
    settings = clip_settings(pyramid, cfg, seg_id)
    with FeatureCacheWriter(cache_dir, targets, settings) as writer:
        for i in tqdm(_todo(ds, writer, indices), desc="features", unit="image", disable=not cfg.progress):
            writer.add(**image_targets(ds, i, clip_encoder, dino_encoder, pyramid, cfg, segmenter))
    return FeatureCache.open(cache_dir)


def image_targets(
    ds: PosedDataset,
    i: int,
    clip_encoder: ImageEncoder,
    dino_encoder: DinoEncoder | None,
    pyramid: PyramidConfig,
    cfg: ExtractConfig,
    segmenter=None,
) -> dict:
    """One frame's maps, as FeatureCacheWriter.add's keyword arguments (image_name, clip, dino). With a
    ``segmenter`` the CLIP map is pooled within its segments of the image (mask pooling,
    fmgs.features.segment_pool; the segments cut at the image's size, taken to the map's by nearest
    neighbour)."""
    frame = ds.frames[i]
    image, _ = ds.image(i, cfg.image_scale)
    image = image.to(cfg.device)
    hw = feature_size(frame.camera, cfg.feature_scale, cfg.feature_side)
    dino = dino_encoder.dense(image, hw) if dino_encoder is not None else None
    clip = hybrid_map(clip_encoder, image, pyramid, hw, dense=dino)
    if segmenter is not None:
        seg = torch.from_numpy(segmenter.segments(image)).to(clip.device)
        clip = pool_segments(clip, resize_segments(seg, hw))
    return {"image_name": frame.name, "clip": clip, "dino": dino}


def read_label_names(path: str | os.PathLike) -> list[str]:
    """``label_names`` from a ``scene.json`` (``fmgs.synth``), given the file or its folder."""
    p = Path(path)
    if p.is_dir():
        p = p / "scene.json"
    try:
        names = json.loads(p.read_text()).get("label_names")
    except (OSError, json.JSONDecodeError, AttributeError) as e:
        raise ValidationError(str(p), f"cannot read label_names ({e})") from e
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise ValidationError(str(p), f"label_names must be a non-empty list of strings, got {names!r}")
    return names


def read_label_map(path: str | os.PathLike, width: int, height: int) -> torch.Tensor:
    """[H,W] int64 labels from a single-channel image (PNG), checked against the frame's size."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            if im.mode not in ("L", "P", "I", "I;16"):
                raise ValidationError(str(path), f"label image has mode {im.mode}, expected single channel")
            a = np.asarray(im).astype(np.int64)
    except OSError as e:
        raise ValidationError(str(path), f"cannot read label image ({e})") from e
    if a.shape != (height, width):
        raise ValidationError(str(path), f"label map is {a.shape[1]}x{a.shape[0]}, frame is {width}x{height}")
    return torch.from_numpy(a)


def extract_labels(
    ds: PosedDataset,
    cache_dir: str | os.PathLike,
    labels: str | os.PathLike | Callable[[Frame], Path],
    names: list[str],
    text_encoder: TextEncoder,
    ignore: frozenset[int] | set[int] = frozenset({0}),
    cfg: ExtractConfig = ExtractConfig(),
    indices: Sequence[int] | None = None,
) -> FeatureCache:
    """Label-name text embeddings as the language target, with a supervision mask, into ``cache_dir``.

    ``labels`` is a folder holding one label image per frame under the frame image's file name
    (``fmgs.synth``: ``labels/<name>.png``), or a function from a frame to its label image path.
    Label ``l`` means ``names[l]``; labels in ``ignore`` (default: 0, the synthetic background) are not
    supervised. Each name is embedded once.
    """
    emb = label_embeddings(names, text_encoder, cfg.device)
    targets = {"clip": TargetInfo(text_encoder.id, text_encoder.dim, True)}
    from tqdm.auto import tqdm

    with FeatureCacheWriter(cache_dir, targets, label_settings(names, ignore, cfg)) as writer:
        for i in tqdm(
            _todo(ds, writer, indices), desc="label targets", unit="image", disable=not cfg.progress
        ):
            writer.add(**image_label_targets(ds, i, labels, emb, ignore, cfg))
    return FeatureCache.open(cache_dir)


def label_embeddings(names: list[str], text_encoder: TextEncoder, device: str = "cpu") -> torch.Tensor:
    """[L,D] float32 embeddings of the label names (checked)."""
    emb = text_encoder.encode_text(list(names)).to(device, torch.float32)
    if emb.shape != (len(names), text_encoder.dim):
        raise ValidationError("text_encoder", f"returned {tuple(emb.shape)} for {len(names)} names")
    return emb


def image_label_targets(
    ds: PosedDataset,
    i: int,
    labels: str | os.PathLike | Callable[[Frame], Path],
    emb: torch.Tensor,
    ignore: frozenset[int] | set[int],
    cfg: ExtractConfig,
) -> dict:
    """One frame's label targets, as FeatureCacheWriter.add's keyword arguments (image_name, clip, mask)."""
    label_path = labels if callable(labels) else (lambda f, d=Path(labels): d / Path(f.name).name)
    frame = ds.frames[i]
    path = label_path(frame)
    lab = read_label_map(path, frame.camera.width, frame.camera.height).to(cfg.device)
    hw = feature_size(frame.camera, cfg.feature_scale, cfg.feature_side)
    try:
        t = label_embedding_map(lab, emb, hw, ignore)
    except ValidationError as e:  # name the label image, not just the value
        raise ValidationError(str(path), f"{e.reason} ({len(emb)} label names)") from e
    return {"image_name": frame.name, "clip": t.clip, "mask": t.mask}
