"""Training-free lifting of 2D targets onto the Gaussians: the baseline the feature field is measured against.

    python -m benchmarks.lift DATA --source PACKAGE --features CACHE --out PACKAGE

Each embedded Gaussian's embedding is the blending-weighted mean of the language targets of every training
pixel it reaches: sum over views and pixels of w_k(p) t(p), over the sum of w_k(p) (the renderer's adjoint
applied to the targets, as learning-free uplifting does, e.g. LUDVIG, Marrie et al. 2024). No field, no
DINO head, no optimisation: each Gaussian carries its targets' average and nothing of what DINO groups.
The Gaussians and their selection are those of ``--source`` (the package distilled from the same cache on
the same 3DGS), so the two differ only in how the targets reach the Gaussians; the stored embeddings get
the same neighbour mean (fmgs.field.neighbours) the source's manifest records.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import NamedTuple

import torch

from fmgs.gaussians import GaussianSet


class Lifted(NamedTuple):
    """Targets lifted onto M Gaussians."""

    embeddings: torch.Tensor
    """[M,D] float32 unit weighted means (a Gaussian no pixel reaches: zeros)."""
    weight: torch.Tensor
    """[M] float64 sum of each Gaussian's blending weights over the supervised pixels (0: unseen)."""


def _view_terms(g: GaussianSet, ds, cache, i: int):
    """(columns [m], weights [h*w,m] as a SparseMatrix, targets [h*w,D] float64, mask [h*w,1] float64) of
    frame i at the cache's map size, as field training sees it (fmgs.train.field.prepare_views)."""
    from fmgs.train.field import prepare_views

    (v,) = prepare_views(g, ds, cache, [i], torch.device("cpu"))
    n = v.clip.shape[0]
    mask = torch.ones(n, 1, dtype=torch.float64) if v.mask is None else v.mask.reshape(n, 1).double()
    return v.weights.gaussians, v.weights.matrix, v.clip.double(), mask


def lift(g: GaussianSet, ds, cache, frames: list[int]) -> Lifted:
    """The language targets of ``frames`` (cache: a FeatureCache) lifted onto the Gaussians ``g``."""
    acc = weight = None
    for i in frames:
        cols, W, t, mask = _view_terms(g, ds, cache, i)
        wt = W.csr_t.to(torch.float64)  # [m, h*w]: the transpose of the view's blend
        if acc is None:
            acc = torch.zeros(g.num, t.shape[1], dtype=torch.float64)
            weight = torch.zeros(g.num, dtype=torch.float64)
        acc.index_add_(0, cols, wt @ (t * mask))
        weight.index_add_(0, cols, (wt @ mask)[:, 0])
    if acc is None:
        raise ValueError("no frames to lift from")
    # The mean's direction is the sum's; an unreached Gaussian's zero sum stays zero.
    return Lifted(torch.nn.functional.normalize(acc, dim=1).float(), weight)


def lift_reference(g: GaussianSet, ds, cache, frames: list[int]) -> Lifted:
    """Twin of ``lift``: every view's weights as a dense matrix, every Gaussian's weighted mean by a loop
    over its pixels (small scenes only)."""
    D = cache.targets["clip"].dim
    acc = torch.zeros(g.num, D, dtype=torch.float64)
    weight = torch.zeros(g.num, dtype=torch.float64)
    for i in frames:
        cols, W, t, mask = _view_terms(g, ds, cache, i)
        dense = W.dense().double()  # [h*w, m]
        for j, k in enumerate(cols.tolist()):
            for p in torch.nonzero(dense[:, j] * mask[:, 0]).flatten().tolist():
                acc[k] += dense[p, j] * t[p]
                weight[k] += dense[p, j]
    emb = torch.zeros(g.num, D)
    for k in range(g.num):
        if weight[k] > 0:
            emb[k] = (acc[k] / acc[k].norm()).float()
    return Lifted(emb, weight)


def lift_package(data: Path, source: Path, features: Path, out: Path) -> Path:
    """Write package ``out``: ``source``'s Gaussians and selection with the lifted embeddings of the cache
    ``features`` (training frames of ``data``); a selected Gaussian no training pixel reaches keeps
    ``source``'s embedding."""
    from fmgs.data import HOLDOUT_EVERY
    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCache
    from fmgs.features.text import load_text_encoder
    from fmgs.field.neighbours import neighbour_mean, reach_of, stored_neighbours
    from fmgs.scene.manifest import CANONICAL_PHRASES
    from fmgs.scene.package import export_scene, load_scene

    ds = load_dataset(data)
    cache = FeatureCache.open(features)
    sc = load_scene(source)
    if cache.targets["clip"].dim != sc.manifest.dim:
        raise ValueError(f"{features} holds {cache.targets['clip'].dim}-D targets, {source} serves "
                         f"{sc.manifest.dim}-D embeddings")  # fmt: skip
    g = sc.gaussians.subset(sc.selected)
    train, _ = ds.split(HOLDOUT_EVERY)
    t0 = time.perf_counter()
    got = lift(g, ds, cache, train)
    emb = torch.where(got.weight[:, None] > 0, got.embeddings, sc.embeddings.float())
    k = stored_neighbours(sc.manifest.extra)
    emb = neighbour_mean(g.means, reach_of(g.scales), emb, k, workers=torch.get_num_threads())
    canon = load_text_encoder(sc.manifest.encoder_id).encode_text(list(CANONICAL_PHRASES)).float()
    extra = {**sc.manifest.extra, "lifted": {"seconds": time.perf_counter() - t0, "features": str(features),
                                             "unseen": int((got.weight <= 0).sum())}}  # fmt: skip
    return export_scene(out, sc.gaussians, sc.selected, emb, sc.manifest.encoder_id, canon, extra=extra)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="posed dataset folder (its training frames are lifted)")
    ap.add_argument("--source", required=True, help="package whose Gaussians and selection are embedded")
    ap.add_argument("--features", required=True, help="feature cache the targets come from")
    ap.add_argument("--out", required=True, help="package folder to write")
    a = ap.parse_args()
    print(lift_package(Path(a.data), Path(a.source), Path(a.features), Path(a.out)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
