"""Train the segmenter stand-in (fmgs.features.standin_seg, SAM's role), once; its weights ship in
benchmarks/standin_seg/ (about 150 KB).

    python scripts/train_standin_seg.py [--out benchmarks/standin_seg] [--seeds 9121-9200] [--steps 1500]

Training data: generated world scenes like those the CLIP and DINO stand-ins train on (odd seeds in a
room of walls, even ones open, 12 views at 128x96), seeds no benchmark scores, none with a held-out
colour-shape pair. Like SAM, the segmenter learns from masks and never from names: the target of each
pair of neighbouring pixels is whether they lie on one surface (one object, the floor, a wall, the
backdrop), from the scene's instance map; the loss is the binary cross-entropy of the affinities,
class-balanced (boundaries are a few percent of the pairs, and a missed boundary merges an object into
the floor).

Measured on scenes of other seeds (9901-9904, three held-out names each) and written into
standin_seg.json: per object, the best IoU of a segment with its mask (mean, and the share of objects
with one above 0.5), and the share of object pixels whose segment is mostly of their own object.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
HELDOUT = (9901, 9902, 9903, 9904)
MEAN, STD = (0.5, 0.5, 0.5), (0.25, 0.25, 0.25)
SHORT_SIDE = 96


def load(folders: list[Path]) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
    """([N,3,H,W] float RGB in [0,1], [N,H,W] int64 instance ids: labels with walls apart from the
    backdrop, [N] the wall's id: object ids are 2 up to it) of every view in ``folders``."""
    from PIL import Image

    from fmgs.features.standin import extended_labels

    ims, labs, walls = [], [], []
    for d in folders:
        names = json.loads((d / "scene.json").read_text())["label_names"]
        for p in sorted((d / "images").iterdir()):
            ims.append(torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0))
            labs.append(torch.from_numpy(extended_labels(d, p.stem, names)))
            walls.append(len(names))
    return torch.stack(ims).permute(0, 3, 1, 2).contiguous(), torch.stack(labs), walls


def measure(encoder, folders: list[Path]) -> dict[str, float]:
    """Segment quality on scenes' views against their object masks (see the module docstring)."""
    from fmgs.features.standin_seg import object_segment_scores

    ims, labs, walls = load(folders)
    ious, own, total = [], 0, 0
    for img, lab, wall in zip(ims, labs, walls, strict=True):
        lab = lab.numpy()
        i, o, t = object_segment_scores(encoder.segments(img.permute(1, 2, 0)), lab, range(2, wall))
        ious, own, total = ious + i, own + o, total + t
    ious_a = np.array(ious)
    return {
        "object_best_iou": float(ious_a.mean()),
        "objects_iou_over_half": float((ious_a > 0.5).mean()),
        "object_pixels_in_own_segment": own / max(total, 1),
        "objects": len(ious),
    }


def main() -> int:
    import sys

    sys.path.insert(0, str(ROOT / "scripts"))
    from train_standin import scene, seeds

    from fmgs.features.standin_seg import (
        JOIN,
        SegStandinEncoder,
        SegStandinNet,
        affinity_targets,
        save_standin_seg,
    )

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "standin_seg"))
    ap.add_argument("--work", default="/tmp/fmgs-standin")
    ap.add_argument("--seeds", default="9121-9200")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--width", type=int, default=24)
    ap.add_argument("--join", type=float, default=JOIN, help="affinity that joins two pixels (shipped)")
    ap.add_argument("--evaluate", metavar="FOLDER", help="only measure FOLDER's held-out figures again")
    a = ap.parse_args()
    if a.evaluate:
        from fmgs.features.standin_seg import CONFIG, load_standin_seg

        enc = load_standin_seg(f"standin-seg:{a.evaluate}")
        enc.config["heldout"] = measure(enc, [scene(Path(a.work), s, novel=3) for s in HELDOUT])
        print(enc.config["heldout"], flush=True)
        (Path(a.evaluate) / CONFIG).write_text(json.dumps(enc.config, indent=1))
        return 0

    torch.manual_seed(0)
    work = Path(a.work)
    t0 = time.perf_counter()
    x, lab, _ = load([scene(work, s) for s in seeds(a.seeds)])
    held = [scene(work, s, novel=3) for s in HELDOUT]
    xn = (x - torch.tensor(MEAN).view(1, 3, 1, 1)) / torch.tensor(STD).view(1, 3, 1, 1)
    target = affinity_targets(lab)
    valid = torch.ones_like(target)
    valid[:, 0, :, -1] = 0
    valid[:, 1, -1, :] = 0
    print(f"{len(x)} views from {len(seeds(a.seeds))} scenes, boundary share "
          f"{float(((1 - target) * valid).sum() / valid.sum()):.3f}", flush=True)  # fmt: skip

    net = SegStandinNet(a.width)
    opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, 2e-3, total_steps=a.steps)
    gen = torch.Generator().manual_seed(0)
    total = 0.0
    for step in range(a.steps):
        i = torch.randint(len(x), (a.batch,), generator=gen)
        xb, tb, vb = xn[i], target[i], valid[i]
        if torch.rand((), generator=gen) < 0.5:  # mirrored: right-neighbour pairs shift by one column
            xb = xb.flip(-1)
            lb = lab[i].flip(-1)
            tb = affinity_targets(lb)
        logits = net(xb)
        pos = (tb * vb).sum().clamp(min=1)
        neg = ((1 - tb) * vb).sum().clamp(min=1)
        weight = vb * (tb / pos + (1 - tb) / neg) / 2  # each class half of the loss
        loss = (F.binary_cross_entropy_with_logits(logits, tb, reduction="none") * weight).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        total += loss.item()
        if (step + 1) % 100 == 0:
            print(f"step {step + 1}/{a.steps}: loss {total / 100:.4f}, {time.perf_counter() - t0:.0f} s",
                  flush=True)  # fmt: skip
            total = 0.0

    config = {
        "width": a.width,
        "short_side": SHORT_SIDE,
        "mean": list(MEAN),
        "std": list(STD),
        "join": a.join,
        "world": "fmgs synth --preset world (fmgs.synthworld), 10 objects, 12 views, 128x96",
        "train_seeds": seeds(a.seeds),
        "heldout_seeds": list(HELDOUT),
        "train_views": len(x),
        "steps": a.steps,
        "batch": a.batch,
        "command": "python scripts/train_standin_seg.py " + " ".join(sys.argv[1:]),
    }
    net.eval()
    config["heldout"] = measure(SegStandinEncoder(net, config, "standin-seg:training"), held)
    config["train_seconds"] = round(time.perf_counter() - t0)
    print(config["heldout"], flush=True)
    save_standin_seg(a.out, net, config)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
