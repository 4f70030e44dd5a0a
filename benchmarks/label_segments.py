"""Segment pooling with the label masks as segments: the bound a perfect segmenter reaches, distilled.

``--segmenter`` pools each image's target map within class-agnostic segments (fmgs.features.segment_pool;
SAM's masks, or the segmenter stand-in's). The stand-in segmenter misses objects and splits others
(CLIP_PATH.md), so what the pooled targets lose after distillation mixes its misses with the method.
Here the segments are the scene's own label masks, each connected component of one label a segment (as
SAM gives an occluded object's two visible parts two masks), so only the method and the crop namer (the
CLIP stand-in) are left: what a segmenter as good as the masks themselves would let the product reach.
Everything else is the product's: the finest scale's crops (``pyramid_for(..., finest_only=True)``) or
the blend, the pooling, the feature cache, ``fmgs train-field`` on the label build's 3DGS, the queries.

Benchmark code (the clip_path variants with "label_segments"); not a build option.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch


def label_segments(data: Path, stem: str, names: list[str]) -> np.ndarray:
    """[H,W] int64 segment ids of one view of a generated scene: every connected component of one label
    (walls and the backdrop included) of at least fmgs.features.segment_pool.MIN_PIXELS pixels; 0 for
    smaller ones, which keep their own target as a segmenter leaves them."""
    from benchmarks.region_crops import label_regions
    from fmgs.features.segment_pool import MIN_PIXELS
    from fmgs.features.standin import extended_labels

    return label_regions(torch.from_numpy(extended_labels(data, stem, names)), MIN_PIXELS)


def label_segments_cache(data: Path, cache_dir: Path, standin: Path, dino: Path, segment_map: str) -> Path:
    """A feature cache of ``data`` as ``fmgs build --segmenter S --segment-map segment_map`` writes it, with
    the label masks as S's segments (``label_segments``): the CLIP stand-in's map ("finest": the finest
    scale alone; "blend": the default blend) pooled within them, and the DINO stand-in's map, for every
    frame at the build's sizes (benchmarks.clip_oracle.write_cache)."""
    from benchmarks.clip_oracle import write_cache
    from fmgs.build.config import SEGMENT_MAPS
    from fmgs.features.dino import load_dense_encoder
    from fmgs.features.pyramid import hybrid_map, pyramid_for
    from fmgs.features.segment_pool import pool_segments, resize_segments
    from fmgs.features.sizes import SCALE_BLEND
    from fmgs.features.standin import load_standin

    if segment_map not in SEGMENT_MAPS:
        raise ValueError(f"segment_map must be one of {SEGMENT_MAPS}, got {segment_map!r}")
    clip = load_standin(f"standin:{standin}")
    finest = segment_map == "finest"
    cfg = pyramid_for(clip, blend="mean" if finest else SCALE_BLEND, finest_only=finest)
    names = json.loads((data / "scene.json").read_text())["label_names"]

    def target(fr, image, hw, dense):
        seg = torch.from_numpy(label_segments(data, Path(fr.name).stem, names))
        if tuple(seg.shape) != tuple(image.shape[:2]):
            shape = tuple(image.shape[:2])
            raise ValueError(f"{fr.name}: label map {tuple(seg.shape)} is not the image's {shape}")
        return pool_segments(hybrid_map(clip, image, cfg, hw, dense=dense), resize_segments(seg, hw))

    return write_cache(data, cache_dir, clip, load_dense_encoder(f"standin-dino:{dino}"), target)
