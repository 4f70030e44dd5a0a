"""Train the CLIP stand-in (fmgs.features.standin) into MiniLM's text space, once; its weights ship in
benchmarks/standin/ (about 2 MB).

    python scripts/train_standin.py [--out benchmarks/standin] [--seeds 9001-9012] [--epochs 8]

Training data: generated cluttered scenes (fmgs synth) with seeds no evaluation uses (the benchmarks
score seeds 7 and 101-199), rendered at 128x96. From each view, square crops at the CLIP pyramid's
scales (fmgs.features.pyramid.PyramidConfig.scales x the image's short side), centred at random pixels;
each crop's target is the MiniLM embedding of the label name under its centre ("background" for the
backdrop). The loss is a softmax over every label name's embedding (temperature 0.05), so each crop's
embedding lands nearest its own name's. Crop accuracy (top-1 among the scene's own names) is measured
on scenes of other seeds (9901-9903) and written into standin.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from fmgs.features.standin import sample_crops

ROOT = Path(__file__).resolve().parents[1]
HELDOUT = (9901, 9902, 9903)
SIZE = "128x96"
IMAGE_SIZE = 32
MEAN, STD = (0.5, 0.5, 0.5), (0.25, 0.25, 0.25)


def seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b) + 1)) if b else [int(s) for s in a.split(",")]


def scene(work: Path, seed: int) -> Path:
    from fmgs.cli import main as fmgs

    data = work / f"scene-{seed}"
    if not (data / "scene.json").is_file():
        cmd = ["synth", "--out", str(data), "--preset", "cluttered", "--objects", "10", "--seed", str(seed)]
        assert fmgs([*cmd, "--views", "24", "--size", SIZE]) == 0
    return data


def dataset(work: Path, seed_list: list[int], per_view: int, rng) -> tuple[torch.Tensor, list[str]]:
    xs, ys = [], []
    for s in seed_list:
        x, y = sample_crops(scene(work, s), per_view, rng, IMAGE_SIZE)
        xs.append(x)
        ys += y
    return torch.cat(xs), ys


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "standin"))
    ap.add_argument("--work", default="/tmp/fmgs-standin")
    ap.add_argument("--seeds", default="9001-9012")
    ap.add_argument("--per-view", type=int, default=120)
    ap.add_argument("--epochs", type=int, default=8)
    ap.add_argument("--width", type=int, default=32)
    a = ap.parse_args()

    from fmgs.features.models import MINILM_ID
    from fmgs.features.standin import StandinImageEncoder, StandinNet, crop_accuracy, save_standin
    from fmgs.features.text import MiniLMTextEncoder

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    work = Path(a.work)
    t0 = time.perf_counter()
    x, y = dataset(work, seeds(a.seeds), a.per_view, rng)
    xv, yv = dataset(work, list(HELDOUT), a.per_view // 2, rng)
    vocab = sorted(set(y) | set(yv))
    text = MiniLMTextEncoder()
    table = text.encode_text(vocab).clone()  # [V, 384] unit (a normal tensor: autograd uses it)
    index = {n: i for i, n in enumerate(vocab)}
    target = torch.tensor([index[n] for n in y])
    mean, std = torch.tensor(MEAN).view(1, 3, 1, 1), torch.tensor(STD).view(1, 3, 1, 1)
    xn = (x - mean) / std
    print(f"{len(x)} training crops from {len(seeds(a.seeds))} scenes, {len(vocab)} names", flush=True)

    net = StandinNet(table.shape[1], IMAGE_SIZE, a.width)
    opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, 2e-3, total_steps=a.epochs * ((len(x) + 255) // 256))
    for epoch in range(a.epochs):
        net.train()
        perm = torch.randperm(len(x))
        total = 0.0
        for s in range(0, len(x), 256):
            i = perm[s : s + 256]
            xb = xn[i]
            if torch.rand(()) < 0.5:
                xb = xb.flip(-1)  # a mirrored crop has the same label at its centre
            logits = F.normalize(net(xb), dim=-1) @ table.T / 0.05
            loss = F.cross_entropy(logits, target[i])
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(i)
        print(f"epoch {epoch + 1}/{a.epochs}: loss {total / len(x):.3f}", flush=True)

    config = {
        "dim": int(table.shape[1]),
        "image_size": IMAGE_SIZE,
        "width": a.width,
        "mean": list(MEAN),
        "std": list(STD),
        "text_encoder": MINILM_ID,
        "train_seeds": seeds(a.seeds),
        "heldout_seeds": list(HELDOUT),
        "train_crops": len(x),
        "heldout_crops": len(xv),
        "names": vocab,
        "epochs": a.epochs,
        "command": "python scripts/train_standin.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(a).items() if k not in ("out", "work")),
    }
    # Top-1 among each held-out crop's own scene's names (as a query ranks a scene's objects), through
    # the encoder as the build loads it; every held-out scene gave the same number of crops.
    encoder = StandinImageEncoder(net, config, "standin:training")
    n = len(xv) // len(HELDOUT)
    accs = []
    for k, s in enumerate(HELDOUT):
        names = json.loads((work / f"scene-{s}" / "scene.json").read_text())["label_names"]
        sl = slice(k * n, (k + 1) * n)
        accs.append(crop_accuracy(encoder, table[[index[m] for m in names]], xv[sl], yv[sl], names))
    accuracy = float(np.mean(accs))
    config["heldout_crop_accuracy"] = round(accuracy, 4)
    config["train_seconds"] = round(time.perf_counter() - t0, 1)
    save_standin(a.out, net, config)
    print(f"held-out crop accuracy {accuracy:.3f} ({len(xv)} crops); wrote {a.out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
