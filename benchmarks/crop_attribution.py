"""Where the crop pyramid's CLIP targets lose small objects, on dev scenes: naming, attribution or pixels.

    python -m benchmarks.crop_attribution --out OUT [--seeds 301,302] [--sizes 128x96,256x192] [--views 6]
                                          [--report]

The CLIP path's targets place names worse than the label path's, and distillation keeps most of that
(benchmarks/results/CLIP_PATH.md). Three causes could be at work, and each has its own cure:

- **naming**: the crop namer names a crop wrongly (a better CLIP, or better crops, would help);
- **attribution**: each crop's embedding is spread bilinearly over the pixels about its centre, so a crop
  about an object also speaks for the floor pixels beside it. The cure from the literature is to give a
  crop's embedding to the pixels whose DINO feature is like what the crop shows (joint bilateral
  upsampling guided by a self-supervised feature map, as FeatUp's JBU and ProxyCLIP do): here a crop's
  weight at a pixel of its window is the tent about its centre times max(0, d_p . g_k)^2, g_k the crop's
  tent-weighted mean DINO feature (the square as ``pool_regions`` weighs);
- **pixels**: the finest crop is 0.05 of the image's shorter side, 5 pixels of a 128x96 view; CLIP sees
  such a crop resized to its input, with little in it to name.

For each dev scene, generated at each size with the world preset's settings (`fmgs synth --preset world
--objects 10 --novel 3`, odd seeds open, even seeds in a room), the pyramid's crops (the build's defaults)
are embedded by the CLIP stand-in and without naming error (benchmarks.clip_oracle), brought to the pixels
bilinearly (the build's) and by DINO attribution, blended as the default (``dominant``), as the paper
(``mean``) or taken at the finest scale alone, and scored as benchmarks.clip_targets scores targets. Dev
scenes only: no test seed of CLIP_PATH.md is generated here.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.clip_targets import STANDIN, STANDIN_DINO
from fmgs.features.pyramid import CropGrid, grid_map
from fmgs.vecmath import safe_normalize

POWER = 2.0
"""The attribution's DINO weight: max(0, cosine) ** POWER, as ``pool_regions`` weighs."""
FLOOR = 1e-3
"""Weight of the bilinear map where no crop's DINO feature is like the pixel's (all cosines <= 0)."""
BLENDS = ("dominant", "mean", "finest")
NAMERS = ("stand-in", "no naming error")
ATTRIBUTIONS = ("bilinear", "DINO")


def tent(centers: torch.Tensor, edge: float, out_len: int, src_len: int) -> torch.Tensor:
    """[n, out_len] float32: the tent of half-width edge/2 about each crop centre (pixels of a src_len
    axis) at the centres of out_len output pixels spanning the same axis."""
    x = (torch.arange(out_len, dtype=torch.float64) + 0.5) * (src_len / out_len)
    return (1.0 - (x[None, :] - centers.double()[:, None]).abs() / (edge / 2.0)).clamp(min=0.0).float()


def guided_grid_map(
    emb: torch.Tensor, grid: CropGrid, image_hw: tuple[int, int], dense: torch.Tensor, power: float = POWER
) -> torch.Tensor:
    """The grid's crop embeddings emb [ny,nx,D] brought to the pixels of ``dense`` [h,w,Dd] (the image's
    DINO map) by DINO attribution (module docstring): [h,w,D] float32, not normalised."""
    (H, W), (h, w) = image_hw, dense.shape[:2]
    d = safe_normalize(dense.float())
    ty = tent(grid.centers_y, grid.size, h, H)  # [ny,h]
    tx = tent(grid.centers_x, grid.size, w, W)  # [nx,w]
    g = safe_normalize(torch.einsum("yi,ijc,xj->yxc", ty, d, tx))  # [ny,nx,Dd] what each crop shows
    acc = FLOOR * grid_map(emb, grid, image_hw, (h, w))
    norm = torch.full((h, w), FLOOR)
    for ky in range(ty.shape[0]):
        rows = torch.nonzero(ty[ky] > 0).flatten()
        wgt = (d[rows] @ g[ky].T).clamp(min=0.0) ** power * ty[ky, rows][:, None, None] * tx.T[None]
        acc[rows] += wgt @ emb[ky].float()  # [R,w,nx] @ [nx,D]
        norm[rows] += wgt.sum(-1)
    return acc / norm[..., None]


def guided_grid_map_reference(
    emb: torch.Tensor, grid: CropGrid, image_hw: tuple[int, int], dense: torch.Tensor, power: float = POWER
) -> torch.Tensor:
    """``guided_grid_map`` one pixel and one crop at a time (the twin)."""
    (H, W), (h, w) = image_hw, dense.shape[:2]
    d = safe_normalize(dense.double())
    ny, nx = emb.shape[:2]
    base = grid_map(emb, grid, image_hw, (h, w)).double()

    def t(c: float, i: int, scale: float) -> float:
        return max(0.0, 1.0 - abs((i + 0.5) * scale - c) / (grid.size / 2.0))

    g = torch.zeros(ny, nx, d.shape[-1], dtype=torch.float64)
    for a in range(ny):
        for b in range(nx):
            for i in range(h):
                for j in range(w):
                    wy = t(float(grid.centers_y[a]), i, H / h)
                    wx = t(float(grid.centers_x[b]), j, W / w)
                    g[a, b] += wy * wx * d[i, j]
    g = safe_normalize(g)
    out = torch.zeros(h, w, emb.shape[-1], dtype=torch.float64)
    for i in range(h):
        for j in range(w):
            acc, norm = FLOOR * base[i, j], FLOOR
            for a in range(ny):
                for b in range(nx):
                    wy = t(float(grid.centers_y[a]), i, H / h)
                    wx = t(float(grid.centers_x[b]), j, W / w)
                    k = wy * wx * max(0.0, float(d[i, j] @ g[a, b])) ** power
                    acc = acc + k * emb[a, b].double()
                    norm += k
            out[i, j] = acc / norm
    return out.float()


def scene_counts(data: Path, views: int, standin: Path = STANDIN, standin_dino: Path = STANDIN_DINO) -> dict:
    """{candidate: counts} over the first ``views`` views of generated scene ``data`` (benchmarks.
    clip_targets.tally's counts, pooled by its ``rates``); candidates "namer, attribution, blend"."""
    from PIL import Image

    from benchmarks.clip_oracle import oracle_grid_embeddings
    from benchmarks.clip_targets import novel_labels, standin_scene, tally
    from fmgs.features.pyramid import PyramidConfig, crop_grid, scale_grid_embeddings
    from fmgs.features.scale_blend import blend_scales, scale_weights
    from fmgs.features.standin import WALL, extended_labels

    names, enc, dino, table, points = standin_scene(data, standin, standin_dino)
    cfg = PyramidConfig(crop_px=enc.image_size)
    acc: dict[str, np.ndarray] = {}
    for p in sorted((data / "images").iterdir())[:views]:
        img = torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0)
        lab = torch.from_numpy(np.asarray(Image.open(data / "labels" / p.name)).astype(np.int64))
        H, W = lab.shape
        ext = extended_labels(data, p.stem, names)
        with torch.inference_mode():
            dense = dino.dense(img, (H, W))
            grids = [crop_grid(H, W, s, cfg.overlap, cfg.max_stride) for s in cfg.scales]
            weights = scale_weights("dominant", dense, [g.size for g in grids])
            scores = {}
            for namer in NAMERS:
                if namer == "stand-in":
                    embs = [scale_grid_embeddings(enc, img.permute(2, 0, 1), g, cfg) for g in grids]
                else:
                    embs = [oracle_grid_embeddings(ext, [*names, WALL], points, g) for g in grids]
                for how in ATTRIBUTIONS:
                    pairs = zip(embs, grids, strict=True)
                    if how == "bilinear":
                        maps = [grid_map(e, g, (H, W), (H, W)) for e, g in pairs]
                    else:
                        maps = [guided_grid_map(e, g, (H, W), dense) for e, g in pairs]
                    blended = {
                        "dominant": blend_scales(maps, weights),
                        "mean": blend_scales(maps, None),
                        "finest": safe_normalize(maps[0]),  # cfg.scales is finest first
                    }
                    for b, m in blended.items():
                        scores[f"{namer}, {how}, {b}"] = m @ table.T
        tally(acc, scores, lab, novel_labels(data), len(names))
    return {k: {"counts": v.tolist(), "classes": len(names) - 1} for k, v in acc.items()}


def table(d: dict) -> list[str]:
    sizes = d["sizes"]
    head = " | ".join(f"{s} mIoU | {s} object pixels" for s in sizes)
    lines = [f"| crop namer | attribution | blend | {head} |", "|---|---|---|" + "---:|" * (2 * len(sizes))]
    for namer in NAMERS:
        for how in ATTRIBUTIONS:
            for b in BLENDS:
                k = f"{namer}, {how}, {b}"
                cells = " | ".join(
                    f"{d['rates'][s][k]['miou']:.3f} | {d['rates'][s][k]['object_pixels']:.3f}" for s in sizes
                )
                lines.append(f"| {namer} | {how} | {b} | {cells} |")
    return lines


def report(d: dict) -> str:
    """CROP_ATTRIBUTION.md from the figures ``main`` stores."""
    from benchmarks.common import machine_words

    return "\n".join(
        [
            "# Where the crop targets lose small objects: naming, attribution or pixels",
            "",
            f"Measured {d['machine']['date']} on {machine_words(d['machine'])}, one run of `{d['command']}`.",
            "",
            f"Dev scenes {', '.join(str(s) for s in d['seeds'])} (`fmgs synth --preset world --objects 10 "
            "--novel 3 --views 48`, odd seeds open, even seeds in a room; no test seed of CLIP_PATH.md), "
            f"each generated at every size, the first {d['views']} views of each. Every crop of the hybrid "
            "pyramid (the build's defaults) is embedded by the CLIP stand-in, or without naming error "
            "(benchmarks.clip_oracle: as the stand-in is trained to embed it, from the label map); each "
            "scale's crop embeddings are brought to the pixels bilinearly through the crop centres (the "
            "build's) or by DINO attribution (each crop's embedding given to the pixels of its window in "
            f"proportion to the tent about its centre times max(0, cosine)^{POWER:g} of the pixel's DINO "
            "feature with the crop's tent-weighted mean one: joint bilateral upsampling guided by DINO, as "
            "FeatUp and ProxyCLIP do), then blended as the default (dominant), as the paper (the equal "
            "mean) or the finest scale alone. Scored as CLIP_TARGETS.md scores target maps (argmax over "
            "the floor and the objects' names on pixels with geometry; mIoU the mean of the scenes').",
            "",
            *table(d),
            "",
            "## What it says",
            "",
            *d.get("findings", []),
        ]
    )


def main() -> int:
    from benchmarks.clip_path import synth_flags
    from benchmarks.clip_targets import rates
    from benchmarks.common import machine, save_report
    from benchmarks.unseen import synth_scene

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="scenes and figures go here")
    ap.add_argument("--seeds", default="301,302", help="dev scenes (never CLIP_PATH.md's test seeds)")
    ap.add_argument("--sizes", default="128x96,256x192", help="image sizes, WxH")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--report", action="store_true", help="also publish both to benchmarks/results/")
    ap.add_argument("--findings", help="a text file of the report's conclusions, one bullet per line")
    ap.add_argument("--from-json", action="store_true", help="only write the report again from OUT's figures")
    a = ap.parse_args()
    out = Path(a.out)
    fig = out / "CROP_ATTRIBUTION.json"
    if a.from_json:
        d = json.loads(fig.read_text())
    else:
        seeds, sizes = [int(s) for s in a.seeds.split(",")], a.sizes.split(",")
        d = {"seeds": seeds, "sizes": sizes, "views": a.views, "rates": {},
             "command": "python -m benchmarks.crop_attribution " + " ".join(sys.argv[1:]),
             "machine": {**machine(), "date": time.strftime("%Y-%m-%d")}}  # fmt: skip
        for size in sizes:
            per = []
            for seed in seeds:
                data = synth_scene(out / f"scene-{seed}-{size}", seed, 48, size, synth_flags(seed), "world")
                per.append(scene_counts(data, a.views))
                print(f"seed {seed} {size} done", flush=True)
            d["rates"][size] = rates(per)
    if a.findings:
        d["findings"] = Path(a.findings).read_text().strip().splitlines()
    figures = json.dumps(d, indent=1, default=float)
    save_report(figures, out, fig.name, a.report)  # the figures beside the report, published with it
    save_report(report(d), out, "CROP_ATTRIBUTION.md", a.report)
    print("\n".join(table(d)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
