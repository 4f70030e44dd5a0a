"""How well CLIP target maps place names before any distillation, per way of blending the pyramid's scales.

    python -m benchmarks.clip_targets DATA [DATA ...] [--views 6] [--standin DIR] [--standin-dino DIR]

For generated scenes (fmgs synth, with labels): every crop of the hybrid pyramid (the build's defaults)
embedded by the CLIP stand-in, the DINO stand-in's dense map, then each candidate target map, scored
against the label maps as segmentation is scored (argmax over the scene's names but the background, on
pixels with geometry): pixel accuracy on all of them and on object pixels, object pixels of novel objects
(held-out colour-shape pairs), and mIoU. Candidates: every scale alone, the blends of
fmgs.features.scale_blend, each blend pooled within DINO-coherent neighbourhoods (pool_regions), and
LERF's query-time scale selection (each name's score the best over the scales' maps: what a multi-scale
field would answer, with a map per scale), and region crops (benchmarks.region_crops: one tight crop per
DINO-grown region, and per label mask as the upper bound better masks could reach; each also masked, black
outside its region, as LangSplat crops its SAM masks).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
STANDIN = ROOT / "benchmarks" / "standin"
STANDIN_DINO = ROOT / "benchmarks" / "standin_dino"
STANDIN_SEG = ROOT / "benchmarks" / "standin_seg"
POOL_RADIUS = 0.1
"""pool_regions' window half-edge, a fraction of the map's shorter side (the scale of the median crop)."""
REGIONS_DINO = "region crops (DINO regions)"
REGIONS_MASKS = "region crops (label masks: upper bound)"
MASKED = "masked {regions}"
"""The region-crop candidates with every crop black outside its region."""
SEGMENTS = "{what} pooled in segments ({by})"
"""Mask pooling (fmgs.features.segment_pool) of a map within the segmenter stand-in's segments or, as the
bound a perfect segmenter reaches, the label masks."""
SEGMENTER = "segmenter stand-in"
LABEL_MASKS = "label masks: upper bound"
SEGMENTED = SEGMENTS.format(what="finest", by=SEGMENTER)
"""The build's ``--segmenter`` targets."""
CANDIDATE_SET = 3
"""Bumped when candidates are added, so that kept target tables (benchmarks.clip_path) are computed again."""
ORACLE = "no naming error ({blend})"
"""The oracle candidates (benchmarks.clip_oracle): every crop named as the stand-in is trained to name it."""


def has_oracle_rows(rates_or_candidates: dict) -> bool:
    """Whether a target table (candidate name -> figures) holds the oracle candidates."""
    head = ORACLE.split("{")[0]
    return any(k.startswith(head) for k in rates_or_candidates)


def novel_labels(data: Path) -> set[int]:
    meta = json.loads((data / "scene.json").read_text())
    return {o["label"] for o in meta["objects"] if o.get("novel")}


def standin_scene(data: Path, standin: Path = STANDIN, standin_dino: Path = STANDIN_DINO):
    """(names, CLIP stand-in, DINO stand-in, [C-1,D] text table of the floor and objects (segmentation's
    classes), [C+1,D] caption points of the names and the stand-in's WALL) for scene ``data``: what the
    oracle and stand-in target studies share."""
    from fmgs.features.crop_content import caption_points
    from fmgs.features.dino import load_dense_encoder
    from fmgs.features.standin import WALL, load_standin
    from fmgs.features.text import MiniLMTextEncoder

    names = json.loads((data / "scene.json").read_text())["label_names"]
    text = MiniLMTextEncoder()
    with torch.inference_mode():
        table = text.encode_text(names[1:])
        points = caption_points([*names, WALL], text)
    enc = load_standin(f"standin:{standin}")
    return names, enc, load_dense_encoder(f"standin-dino:{standin_dino}"), table, points


def candidate_scores(maps: dict[str, torch.Tensor | list[torch.Tensor]], table: torch.Tensor) -> dict:
    """{candidate: [h,w,C] scores of each name} from unit target maps, or from a list of per-scale maps
    (LERF: the best score over the scales)."""
    out = {}
    for k, m in maps.items():
        if isinstance(m, list):
            out[k] = torch.stack([torch.nn.functional.normalize(s, dim=-1) @ table.T for s in m]).amax(0)
        else:
            out[k] = m @ table.T
    return out


def target_candidates(
    data: Path,
    standin: Path = STANDIN,
    standin_dino: Path = STANDIN_DINO,
    views: int = 6,
    seconds: dict[str, float] | None = None,
    regions: bool = True,
    oracle: bool = False,
    segmenter: Path | None = STANDIN_SEG,
) -> dict[str, dict]:
    """{candidate: scores} over the first ``views`` views of scene ``data`` (see the module docstring):
    hits and totals, to be pooled over scenes by ``rates``. ``seconds``, when given, gathers the time
    spent (added to what it holds): "views", "pyramid" (every crop through the CLIP stand-in), "dino" (the
    dense map) and each candidate's own (its weights, blend and pooling on top of those), in CPU seconds
    of this process. ``regions``: also the region-crop candidates; ``oracle``: also each blend with every
    crop named without error (benchmarks.clip_oracle); ``segmenter``: the segmenter stand-in's folder
    for the mask-pooled candidates (SEGMENTS; None: none)."""
    import time

    from PIL import Image

    from benchmarks.region_crops import grow_regions, label_regions, region_target
    from fmgs.features.dino import load_dense_encoder
    from fmgs.features.pyramid import PyramidConfig, hybrid_map, pyramid_for, scale_maps
    from fmgs.features.scale_blend import BLENDS, blend_scales, pool_regions, scale_weights
    from fmgs.features.standin import load_standin
    from fmgs.features.text import MiniLMTextEncoder

    names = json.loads((data / "scene.json").read_text())["label_names"]
    novel = novel_labels(data)
    if oracle:
        from benchmarks.clip_oracle import oracle_scale_maps
        from fmgs.features.crop_content import caption_points
        from fmgs.features.standin import WALL, extended_labels

        points = caption_points([*names, WALL], MiniLMTextEncoder())
    enc = load_standin(f"standin:{standin}")
    dino = load_dense_encoder(f"standin-dino:{standin_dino}")
    seg_enc = None
    if segmenter is not None:
        from fmgs.features.segment_pool import pool_segments
        from fmgs.features.standin_seg import load_standin_seg

        seg_enc = load_standin_seg(f"standin-seg:{segmenter}")
    with torch.inference_mode():
        table = MiniLMTextEncoder().encode_text(names[1:])  # floor and objects: segmentation's classes
    cfg = PyramidConfig(crop_px=enc.image_size)
    C = len(names)
    acc: dict[str, np.ndarray] = {}
    took = {} if seconds is None else seconds
    clock = time.process_time  # CPU time: other jobs on a shared machine do not count

    def add(key: str, value: float) -> None:
        took[key] = took.get(key, 0.0) + value

    for p in sorted((data / "images").iterdir())[:views]:
        img = torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0)
        lab = torch.from_numpy(np.asarray(Image.open(data / "labels" / p.name)).astype(np.int64))
        H, W = lab.shape
        with torch.inference_mode():
            t0 = clock()
            sm = scale_maps(enc, img, cfg, (H, W))
            t1 = clock()
            dense = dino.dense(img, (H, W))
            t2 = clock()
            add("views", 1.0)
            add("pyramid", t1 - t0)
            add("dino", t2 - t1)
            radius = max(1, round(POOL_RADIUS * min(H, W)))
            maps: dict = {f"{s} alone": torch.nn.functional.normalize(m, dim=-1)
                          for s, m in zip(cfg.scales, sm.maps, strict=True)}  # fmt: skip
            for b in BLENDS:
                t0 = clock()
                t = blend_scales(sm.maps, scale_weights(b, dense, sm.edges))
                t1 = clock()
                maps[b] = t
                maps[f"{b} + pooled"] = pool_regions(t, dense, radius)
                t2 = clock()
                add(b, t1 - t0)
                add(f"{b} + pooled", t2 - t0)
            maps["lerf (max over scales)"] = list(sm.maps)
            if regions:
                finest = sm.maps[int(torch.tensor(sm.edges).argmin())]
                t0 = clock()
                grown = grow_regions(dense)
                maps[REGIONS_DINO] = region_target(enc, img, grown, finest, enc.image_size)
                add(REGIONS_DINO, clock() - t0)
                masks = label_regions(lab)
                maps[REGIONS_MASKS] = region_target(enc, img, masks, finest, enc.image_size)
                for name, seg in ((REGIONS_DINO, grown), (REGIONS_MASKS, masks)):
                    maps[MASKED.format(regions=name)] = region_target(
                        enc, img, seg, finest, enc.image_size, masked=True
                    )
            if seg_enc is not None:
                # the build's own path (--segmenter): the finest scale alone, cut again, then pooled
                t0 = clock()
                finest = hybrid_map(enc, img, pyramid_for(enc, finest_only=True), (H, W))
                segs = torch.from_numpy(seg_enc.segments(img))
                maps[SEGMENTED] = pool_segments(finest, segs)
                add(SEGMENTED, clock() - t0)  # all of it: this target needs no other pyramid
                masks = torch.from_numpy(label_regions(lab))
                maps[SEGMENTS.format(what="dominant", by=SEGMENTER)] = pool_segments(maps["dominant"], segs)
                for what, m in (("finest", finest), ("dominant", maps["dominant"])):
                    maps[SEGMENTS.format(what=what, by=LABEL_MASKS)] = pool_segments(m, masks)
            if oracle:
                ext = extended_labels(data, p.stem, names)
                omaps, oedges = oracle_scale_maps(ext, [*names, WALL], points, cfg, (H, W))
                for b in BLENDS:
                    maps[ORACLE.format(blend=b)] = blend_scales(omaps, scale_weights(b, dense, oedges))
            scores = candidate_scores(maps, table)
        tally(acc, scores, lab, novel, C)
    return {k: {"counts": v.tolist(), "classes": C - 1} for k, v in acc.items()}


def tally(acc: dict[str, np.ndarray], scores: dict[str, torch.Tensor], lab: torch.Tensor, novel: set[int],
          C: int) -> None:  # fmt: skip
    """Adds one view's counts to ``acc`` per candidate: ``scores`` [h,w,C-1] of the floor and the objects
    (label ids 1..C-1), ``lab`` [h,w] the label map, ``novel`` the held-out names' ids. Counts: pixels
    right and with geometry, the same on object and on novel-object pixels, then each class's
    intersection and union (``rates`` pools them)."""
    valid = lab >= 1
    obj = lab >= 2
    nov = torch.zeros_like(lab, dtype=torch.bool)
    for n in novel:
        nov |= lab == n
    for k, s in scores.items():
        pred = s.argmax(-1) + 1
        ok = (pred == lab) & valid
        row = [ok.sum(), valid.sum(), (ok & obj).sum(), obj.sum(), (ok & nov).sum(), nov.sum()]
        inter = [((pred == c) & (lab == c) & valid).sum() for c in range(1, C)]
        union = [(((pred == c) | (lab == c)) & valid).sum() for c in range(1, C)]
        acc[k] = acc.get(k, 0) + np.array([float(v) for v in row + inter + union])


def rates(per_scene: list[dict[str, dict]]) -> dict[str, dict[str, float]]:
    """Pooled pixel accuracies and the mean of per-scene mIoUs, per candidate."""
    out = {}
    for k in per_scene[0]:
        tot = np.zeros(6)
        mious = []
        for sc in per_scene:
            c = np.array(sc[k]["counts"])
            n = sc[k]["classes"]
            tot += c[:6]
            inter, union = c[6 : 6 + n], c[6 + n :]
            mious.append(float(np.mean(inter[union > 0] / union[union > 0])))
        out[k] = {
            "pixels": tot[0] / tot[1],
            "object_pixels": tot[2] / tot[3],
            "novel_object_pixels": tot[4] / max(tot[5], 1.0),
            "miou": float(np.mean(mious)),
        }
    return out


def table(r: dict[str, dict[str, float]]) -> list[str]:
    lines = [
        "| targets | pixels | object pixels | novel-object pixels | mIoU |",
        "|---|---:|---:|---:|---:|",
    ]
    for k, v in r.items():
        lines.append(
            f"| {k} | {v['pixels']:.3f} | {v['object_pixels']:.3f} | {v['novel_object_pixels']:.3f} | "
            f"{v['miou']:.3f} |"
        )
    return lines


def report(d: dict) -> str:
    """CLIP_TARGETS.md from the figures ``main`` stores (rates, scenes, views, command, machine)."""
    from benchmarks.common import machine_words

    return "\n".join(
        [
            "# CLIP target maps before distillation, per blend of the scales",
            "",
            f"Measured {d['machine']['date']} on {machine_words(d['machine'])}, one run of `{d['command']}`.",
            "",
            f"Scenes: {', '.join(Path(x).name for x in d['scenes'])} (`fmgs synth --preset world "
            "--objects 10 --novel 3 --views 12 --size 128x96`, odd seeds open, even seeds in a room; no "
            f"stand-in training or benchmark seed), the first {d['views']} views of each. The CLIP stand-in "
            "embeds every crop of the hybrid pyramid at the build's defaults, the DINO stand-in gives the "
            "dense map; each "
            "candidate's target map is scored as segmentation is (argmax over the scene's names but the "
            "background, on pixels with geometry): pixel accuracy on all of them, on object pixels and on "
            "the held-out-name objects' pixels, pooled over the scenes; mIoU averaged over the scenes. "
            "These are the dev scenes the build's default blend was chosen on. Region crops "
            "(benchmarks.region_crops, the mask-based methods' way): one tight square crop per region "
            "grown over the DINO map, its embedding averaged with the finest scale's map; with the label "
            "masks as the regions, the bound that better masks (SAM's) could reach.",
            "",
            *table(d["rates"]),
            "",
        ]
    )


def main() -> int:
    import sys
    import time

    from benchmarks.common import machine, save_report

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="*", help="generated scene folders")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--standin", default=str(STANDIN))
    ap.add_argument("--standin-dino", default=str(STANDIN_DINO))
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument(
        "--report", metavar="OUT", help="also write CLIP_TARGETS.md into OUT and benchmarks/results/"
    )
    ap.add_argument("--from-json", metavar="JSON", help="only write the report again from --json's figures")
    a = ap.parse_args()
    if a.from_json:
        d = json.loads(Path(a.from_json).read_text())
    else:
        if not a.data:
            ap.error("give generated scene folders (or --from-json)")
        per = [target_candidates(Path(x), Path(a.standin), Path(a.standin_dino), a.views) for x in a.data]
        d = {
            "rates": rates(per),
            "scenes": a.data,
            "views": a.views,
            "command": "python -m benchmarks.clip_targets " + " ".join(sys.argv[1:]),
            "machine": {**machine(), "date": time.strftime("%Y-%m-%d")},
        }
        print("\n".join(table(d["rates"])))
        if a.json:
            Path(a.json).write_text(json.dumps(d, indent=1, default=float))
    if a.report:
        save_report(report(d), Path(a.report), "CLIP_TARGETS.md", True)
        (ROOT / "benchmarks" / "results" / "CLIP_TARGETS.json").write_text(
            json.dumps(d, indent=1, default=float)
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
