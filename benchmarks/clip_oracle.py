"""The CLIP path with a crop namer that makes no mistakes: the method measured apart from the stand-in.

The CLIP stand-in names an object's crop right about half the time (benchmarks/standin/standin.json:
held-out object crops 0.557), so the CLIP path's scores mix two things: the method (the crop pyramid, the
DINO-weighted blend, distillation with dotsim, the queries) and the crop namer's errors. Here every crop
of the pyramid is embedded as the stand-in is trained to embed it (fmgs.features.crop_content: each
label's share under the centre window, stuff down-weighted, spread over captions of varying detail, as
one point of MiniLM's text space), computed from the scene's label map: what a stand-in with no naming
error would answer. Everything else is the product's: the crop lattice and interpolation
(fmgs.features.pyramid), the DINO stand-in's dense map and the blend (fmgs.features.scale_blend), the
feature cache, ``fmgs train-field`` on the label build's 3DGS, packaging, and the served queries.

It does not show what CLIP would do: CLIP names crops of real photos with errors of its own. It bounds
what the method can reach on these scenes with a better crop namer, and it lets a method change be
measured without the stand-in's noise.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from fmgs.features.crop_content import caption_embeddings, caption_points, window_shares
from fmgs.features.pyramid import CropGrid, PyramidConfig, crop_grid, grid_map
from fmgs.features.scale_blend import blend_scales, scale_weights


def oracle_scale_maps(
    labels: np.ndarray, names: list[str], points: torch.Tensor, cfg: PyramidConfig, out_hw: tuple[int, int]
) -> tuple[list[torch.Tensor], list[float]]:
    """Every scale's map of one view with every crop named without error: labels [H,W] ids into ``names``
    (the scene's names, then the stand-in's WALL), ``points`` [L,D] their caption mixtures
    (caption_points), the pyramid ``cfg`` -> (one [h,w,D] map per scale, not normalised; each scale's crop
    edge in map pixels), as fmgs.features.pyramid.scale_maps gives them for an encoder."""
    H, W = labels.shape
    maps, edges = [], []
    for s in cfg.scales:
        g = crop_grid(H, W, s, cfg.overlap, cfg.max_stride)
        maps.append(grid_map(oracle_grid_embeddings(labels, names, points, g), g, (H, W), out_hw))
        edges.append(g.size * out_hw[0] / H)
    return maps, edges


def oracle_grid_embeddings(
    labels: np.ndarray, names: list[str], points: torch.Tensor, grid: CropGrid
) -> torch.Tensor:
    """[ny,nx,D] unit: each crop of ``grid`` embedded without naming error (labels, names and points as
    ``oracle_scale_maps`` takes them)."""
    ys, xs = grid.boxes[:, 0, 1].numpy(), grid.boxes[0, :, 0].numpy()
    sh = torch.from_numpy(window_shares(labels, grid.size, ys, xs, len(names)))  # [ny,nx,L]
    return caption_embeddings(sh.reshape(-1, len(names)), names, points).reshape(*sh.shape[:2], -1)


def oracle_map(
    labels: np.ndarray, names: list[str], points: torch.Tensor, cfg: PyramidConfig, out_hw: tuple[int, int],
    dense: torch.Tensor | None,
) -> torch.Tensor:  # fmt: skip
    """The hybrid target of one view with every crop named without error (``oracle_scale_maps``) blended
    as ``cfg.blend`` says (``dense`` [h,w,Dd]: the DINO map the weighted blends need) -> [h,w,D] unit."""
    maps, edges = oracle_scale_maps(labels, names, points, cfg, out_hw)
    return blend_scales(maps, scale_weights(cfg.blend, dense, edges))


def write_cache(data: Path, cache_dir: Path, clip, dense_enc, target) -> Path:
    """A feature cache of ``data`` at the build's sizes, every frame as the build extracts it: its CLIP
    target ``target(frame, image [H,W,3], hw, dense [h,w,Dd] or None) -> [h,w,D]`` and the dense encoder's
    map (``dense_enc`` None: no DINO target). Resumes: frames already in the cache are kept."""
    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCacheWriter, TargetInfo
    from fmgs.features.extract import ExtractConfig, feature_size

    ds = load_dataset(data)
    targets = {"clip": TargetInfo(clip.id, clip.dim, True)}
    if dense_enc is not None:
        targets["dino"] = TargetInfo(dense_enc.id, dense_enc.dim, False)
    with FeatureCacheWriter(cache_dir, targets) as writer, torch.inference_mode():
        for i, fr in enumerate(ds.frames):
            if writer.has(fr.name):
                continue
            hw = feature_size(fr.camera, ExtractConfig().feature_scale)
            image, _ = ds.image(i)
            dense = dense_enc.dense(image, hw) if dense_enc is not None else None
            writer.add(fr.name, target(fr, image, hw, dense), dense)
    return cache_dir


def oracle_cache(data: Path, cache_dir: Path, standin: Path, dino: Path | None, blend: str) -> Path:
    """A feature cache of ``data`` (a generated scene) with oracle CLIP targets blended by ``blend`` and the
    DINO stand-in's maps (``dino``; None: no DINO target), at the build's sizes, for every frame as the
    build extracts them (``write_cache``)."""
    from fmgs.features.dino import load_dense_encoder
    from fmgs.features.pyramid import pyramid_for
    from fmgs.features.standin import WALL, extended_labels, load_standin
    from fmgs.features.text import load_text_encoder

    clip = load_standin(f"standin:{standin}")
    dense_enc = load_dense_encoder(f"standin-dino:{dino}") if dino is not None else None
    names = [*json.loads((data / "scene.json").read_text())["label_names"], WALL]
    points = caption_points(names, load_text_encoder(clip.text_encoder_id))
    cfg = pyramid_for(clip, blend=blend)

    def target(fr, image, hw, dense):
        labels = extended_labels(data, Path(fr.name).stem, names[:-1])
        if labels.shape != tuple(image.shape[:2]):
            raise ValueError(
                f"{fr.name}: label map {labels.shape} is not the image's {tuple(image.shape[:2])}"
            )
        return oracle_map(labels, names, points, cfg, hw, dense)

    return write_cache(data, cache_dir, clip, dense_enc, target)
