"""Train the DINO stand-in (fmgs.features.standin_dino) without labels, once; its weights ship in
benchmarks/standin_dino/ (150 KB).

    python scripts/train_standin_dino.py [--out benchmarks/standin_dino] [--seeds 9121-9160] [--steps 1500]

Training data: the RGB renders of generated world scenes like those the CLIP stand-in trains on
(scripts/train_standin.py) but of other seeds (9121-9160), 128x96: images only; no label map, depth or
pose is read.

Objective (dense clustering across augmented views, in the manner of SwAV and PiCIE): two views of a
random window of a render, each its own random resized crop, flip and colour jitter; at points both views
show, each view's features are scored against K learned prototypes, and each view must predict the
other's balanced assignment (Sinkhorn-Knopp over the batch, which keeps every prototype in use, so the
features cannot collapse). Features that survive this are invariant to the augmentations and cluster
what looks alike: within one surface, alike; across surfaces of other colour or pattern, apart.

What it carries is measured on scenes no training used (9901-9904): the mean cosine of two pixels' features
within one object and across two objects, and how often a pixel's nearest neighbour in feature space
(at least 8 pixels away) has its label; against the same network with random weights and against raw
colour. Written into standin_dino.json.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
HELDOUT = (9901, 9902, 9903, 9904)
MEAN, STD = (0.5, 0.5, 0.5), (0.25, 0.25, 0.25)
SHORT_SIDE = 96
WINDOW = 64
"""Edge of the window both views are cut from (pixels of a 128x96 render)."""
POINTS = 256
"""Points per view pair where the two views' assignments are compared."""


def load_images(folders: list[Path]) -> torch.Tensor:
    """[N,3,H,W] float RGB in [0,1] of every render in ``folders``/images."""
    from PIL import Image

    ims = []
    for d in folders:
        for p in sorted((d / "images").iterdir()):
            ims.append(torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0))
    return torch.stack(ims).permute(0, 3, 1, 2).contiguous()


def jitter(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Brightness, contrast and saturation jitter (each within +-30%) per image of x [B,3,h,w]; colour
    is what tells this world's surfaces apart, so hue is left alone."""
    B = x.shape[0]

    def u(lo: float, hi: float) -> torch.Tensor:
        return (lo + (hi - lo) * torch.rand(B, 1, 1, 1, generator=gen)).to(x)

    x = x * u(0.7, 1.3)
    m = x.mean((1, 2, 3), keepdim=True)
    x = (x - m) * u(0.7, 1.3) + m
    g = x.mean(1, keepdim=True)
    x = (x - g) * u(0.7, 1.3) + g
    return x.clamp(0, 1)


def views(images: torch.Tensor, batch: int, gen: torch.Generator):
    """Two augmented views of ``batch`` random windows, and for each view the window coordinates (in
    [-1, 1]) of POINTS points both views show: (v1 [B,3,S,S], v2, p1 [B,P,2], p2 [B,P,2])."""
    N, _, H, W = images.shape
    S = WINDOW
    idx = torch.randint(N, (batch,), generator=gen)
    y0 = torch.randint(H - S + 1, (batch,), generator=gen)
    x0 = torch.randint(W - S + 1, (batch,), generator=gen)
    win = torch.stack([images[i, :, y : y + S, x : x + S] for i, y, x in zip(idx, y0, x0, strict=True)])
    out, boxes = [], []
    for _ in range(2):
        # a random resized crop of the window: side 0.5-1 of it, anywhere inside, maybe mirrored
        side = 0.5 + 0.5 * torch.rand(batch, generator=gen)
        cx = (1 - side) * (2 * torch.rand(batch, generator=gen) - 1)
        cy = (1 - side) * (2 * torch.rand(batch, generator=gen) - 1)
        flip = torch.rand(batch, generator=gen) < 0.5
        sx = torch.where(flip, -side, side)
        theta = torch.zeros(batch, 2, 3)
        theta[:, 0, 0], theta[:, 0, 2], theta[:, 1, 1], theta[:, 1, 2] = sx, cx, side, cy
        grid = F.affine_grid(theta, (batch, 3, S, S), align_corners=False)
        out.append(jitter(F.grid_sample(win, grid, align_corners=False), gen))
        boxes.append((sx, side, cx, cy))
    # points in the window both crops contain, mapped into each crop's own coordinates
    lo = torch.maximum(boxes[0][2] - boxes[0][1], boxes[1][2] - boxes[1][1])
    hi = torch.minimum(boxes[0][2] + boxes[0][1], boxes[1][2] + boxes[1][1])
    loy = torch.maximum(boxes[0][3] - boxes[0][1], boxes[1][3] - boxes[1][1])
    hiy = torch.minimum(boxes[0][3] + boxes[0][1], boxes[1][3] + boxes[1][1])
    r = torch.rand(batch, POINTS, 2, generator=gen)
    px = lo[:, None] + (hi - lo).clamp(min=0)[:, None] * r[..., 0]
    py = loy[:, None] + (hiy - loy).clamp(min=0)[:, None] * r[..., 1]
    pts = []
    for sx, side, cx, cy in boxes:
        pts.append(torch.stack([(px - cx[:, None]) / sx[:, None], (py - cy[:, None]) / side[:, None]], -1))
    return out[0], out[1], pts[0], pts[1]


@torch.no_grad()
def sinkhorn(scores: torch.Tensor, eps: float = 0.05, iters: int = 3) -> torch.Tensor:
    """[M,K] balanced soft assignments of M points to K prototypes (each prototype gets M/K)."""
    q = torch.exp((scores - scores.max()) / eps).T  # [K,M]
    q /= q.sum()
    K, M = q.shape
    for _ in range(iters):
        q /= q.sum(1, keepdim=True) * K
        q /= q.sum(0, keepdim=True) * M
    return (q * M).T


def point_features(net, x: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Unit features [B*P,D] of net's map of x at window coordinates pts [B,P,2]."""
    from fmgs.features.standin_dino import layer_norm

    mean, std = torch.tensor(MEAN).view(1, 3, 1, 1), torch.tensor(STD).view(1, 3, 1, 1)
    f = layer_norm(net((x - mean) / std), dim=1)
    z = F.grid_sample(f, pts[:, :, None, :], align_corners=False)[..., 0]  # [B,D,P]
    return F.normalize(z.permute(0, 2, 1).reshape(-1, f.shape[1]), dim=-1)


def carried(features_of, folders: list[Path], rng: np.random.Generator, pairs: int = 4000) -> dict:
    """Within-object and across-object cosine, and nearest-neighbour label agreement, of the dense
    features ``features_of(image [H,W,3]) -> [H,W,D]`` on the labelled scenes ``folders``."""
    from PIL import Image

    within, across, nn_hits, nn_total = [], [], 0, 0
    for d in folders:
        for p in sorted((d / "images").iterdir())[::4]:
            img = torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0)
            lab = np.asarray(Image.open(d / "labels" / p.name)).astype(np.int64)
            f = F.normalize(features_of(img).float(), dim=-1)
            ys, xs = np.nonzero(lab >= 1)  # floor and objects
            a = rng.integers(len(ys), size=pairs)
            b = rng.integers(len(ys), size=pairs)
            cos = (f[ys[a], xs[a]] * f[ys[b], xs[b]]).sum(-1).numpy()
            same = lab[ys[a], xs[a]] == lab[ys[b], xs[b]]
            objects = (lab[ys[a], xs[a]] >= 2) & (lab[ys[b], xs[b]] >= 2)
            within += cos[same & objects].tolist()
            across += cos[~same & objects].tolist()
            q = rng.integers(len(ys), size=300)
            sims = f[ys[q], xs[q]] @ f[ys, xs].T  # [300, M]
            far = (np.abs(ys[q][:, None] - ys[None]) + np.abs(xs[q][:, None] - xs[None])) < 8
            sims[torch.from_numpy(far)] = -2.0
            best = sims.argmax(1).numpy()
            nn_hits += int((lab[ys[best], xs[best]] == lab[ys[q], xs[q]]).sum())
            nn_total += len(q)
    return {
        "within_object_cosine": float(np.mean(within)),
        "across_object_cosine": float(np.mean(across)),
        "nearest_neighbour_label_agreement": nn_hits / nn_total,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "standin_dino"))
    ap.add_argument("--work", default="/tmp/fmgs-standin")
    ap.add_argument("--seeds", default="9121-9160")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--dim", type=int, default=64)
    ap.add_argument("--width", type=int, default=24)
    ap.add_argument("--prototypes", type=int, default=64)
    a = ap.parse_args()

    import importlib.util

    from fmgs.features.standin_dino import DenseStandinEncoder, DenseStandinNet, save_standin_dino

    spec = importlib.util.spec_from_file_location("train_standin", ROOT / "scripts" / "train_standin.py")
    clip_script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(clip_script)  # the same scenes as the CLIP stand-in

    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    work = Path(a.work)
    t0 = time.perf_counter()
    images = load_images([clip_script.scene(work, s) for s in clip_script.seeds(a.seeds)])
    held = [clip_script.scene(work, s, novel=3) for s in HELDOUT]
    print(f"{len(images)} training renders", flush=True)
    net = DenseStandinNet(a.dim, a.width)
    random_net = DenseStandinNet(a.dim, a.width)
    random_net.load_state_dict(net.state_dict())
    protos = torch.nn.Parameter(F.normalize(torch.randn(a.prototypes, a.dim, generator=gen), dim=-1))
    opt = torch.optim.AdamW([*net.parameters(), protos], lr=2e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, 2e-3, total_steps=a.steps)
    temp = 0.1
    for step in range(a.steps):
        v1, v2, p1, p2 = views(images, a.batch, gen)
        z1, z2 = point_features(net, v1, p1), point_features(net, v2, p2)
        c = F.normalize(protos, dim=-1)
        s1, s2 = z1 @ c.T, z2 @ c.T
        q1, q2 = sinkhorn(s1), sinkhorn(s2)
        loss = -0.5 * ((q1 * F.log_softmax(s2 / temp, -1)).sum(-1).mean()
                       + (q2 * F.log_softmax(s1 / temp, -1)).sum(-1).mean())  # fmt: skip
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if (step + 1) % 250 == 0:
            print(f"step {step + 1}/{a.steps}: loss {loss.item():.3f}", flush=True)

    config = {
        "dim": a.dim,
        "width": a.width,
        "short_side": SHORT_SIDE,
        "mean": list(MEAN),
        "std": list(STD),
        "train_seeds": clip_script.seeds(a.seeds),
        "heldout_seeds": list(HELDOUT),
        "train_renders": len(images),
        "steps": a.steps,
        "prototypes": a.prototypes,
        "command": "python scripts/train_standin_dino.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(a).items() if k not in ("out", "work")),
    }
    rng = np.random.default_rng(1)
    trained = DenseStandinEncoder(net, config, "standin-dino:training")
    untrained = DenseStandinEncoder(random_net, config, "standin-dino:random")
    measures = {
        "trained": carried(lambda im: trained.dense(im, im.shape[:2]), held, rng),
        "random_weights": carried(lambda im: untrained.dense(im, im.shape[:2]), held, rng),
        "raw_colour": carried(lambda im: im - im.mean((0, 1)), held, rng),
    }
    config["heldout"] = {k: {m: round(v, 4) for m, v in d.items()} for k, d in measures.items()}
    config["train_seconds"] = round(time.perf_counter() - t0, 1)
    save_standin_dino(a.out, net, config)
    for k, d in measures.items():
        print(f"{k}: " + ", ".join(f"{m} {v:.3f}" for m, v in d.items()), flush=True)
    print(f"wrote {a.out} in {config['train_seconds']:.0f} s", flush=True)
    assert math.isfinite(loss.item())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
