"""Train the CLIP stand-in (fmgs.features.standin) into MiniLM's text space, once; its weights ship in
benchmarks/standin/ (about 2 MB).

    python scripts/train_standin.py [--out benchmarks/standin] [--seeds 9001-9100] [--epochs 12]

Training data: generated scenes of the wider world (``fmgs synth --preset world``: 15 shapes, 12 colours,
11 textures; odd seeds in a room of walls, even ones open), rendered at 128x96, none with a held-out
colour-shape pair (fmgs.synthworld.HELD_OUT): the stand-in never sees those names, in images or text.
Seeds no evaluation uses (the benchmarks score 7 and 101-299).

From each view, square crops at the CLIP pyramid's scales (PyramidConfig.scales x the image's short
side), centred at random pixels. What a crop shows is its content, not only its centre, as with CLIP: each
label's share of the crop under a Gaussian window about the centre (fmgs.features.crop_content.WINDOW_SIGMA)
is its weight in a soft target over captions, and an object's weight is spread over captions of varying
detail, as image captions vary ("red striped cube", "red cube", "cube"), so that colour and shape words
each get a direction of their own. The loss is the cross-entropy of a softmax over every training
caption's MiniLM embedding (temperature 0.05) against that target.

Crop accuracy (top-1 among the scene's own names, against the name with the largest share) is measured on
scenes of other seeds (9901-9904), each placing three objects with held-out pairs, overall and on crops
of those objects alone; both are written into standin.json.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from fmgs.features.crop_content import caption_matrix, captions, salient, world
from fmgs.features.standin import sample_crop_targets

ROOT = Path(__file__).resolve().parents[1]
HELDOUT = (9901, 9902, 9903, 9904)
SIZE = "128x96"
VIEWS = 12
"""Views per training scene: many scenes (object instances, layouts) generalise better than many views."""
IMAGE_SIZE = 32
MEAN, STD = (0.5, 0.5, 0.5), (0.25, 0.25, 0.25)
OBJECT_SHARE = 0.5
"""Fraction of training crops centred on an object pixel (objects are a small part of most views)."""
TEMPERATURE = 0.05


def seeds(text: str) -> list[int]:
    """'9001-9100,9201-9400,9500' -> the seeds, in order."""
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += range(int(a), int(b) + 1) if b else [int(a)]
    return out


def scene(work: Path, seed: int, novel: int = 0, views: int = VIEWS) -> Path:
    """Generate (once) the world scene of ``seed``: odd seeds in a room, even ones open."""
    from fmgs.cli import main as fmgs

    data = work / f"world-{seed}"
    if not (data / "scene.json").is_file():
        cmd = ["synth", "--out", str(data), "--preset", "world", "--objects", "10", "--seed", str(seed)]
        cmd += ["--novel", str(novel), "--views", str(views), "--size", SIZE]
        cmd += ["--backdrop", "walls" if seed % 2 else "constant"]
        assert fmgs(cmd) == 0
    return data


def soft_targets(
    weights: torch.Tensor, names: list[str], vocab: dict[str, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """From label weights [N,L]: the softmax target over the vocabulary [N,V] (each label's weight on
    its own name), and the text-space target's caption mixture [N,V] (objects spread over captions of
    varying detail)."""
    name_m = torch.zeros(len(names), len(vocab))
    for i, n in enumerate(names):
        name_m[i, vocab[n]] = 1.0
    return weights @ name_m, weights @ caption_matrix(names, vocab)


def dataset(work: Path, seed_list: list[int], per_view: int, rng, novel: int = 0) -> list:
    return [
        sample_crop_targets(scene(work, s, novel), per_view, rng, IMAGE_SIZE, object_share=OBJECT_SHARE)
        for s in seed_list
    ]


def accuracy(encoder, text, samples, which: str = "all") -> float:
    """Top-1 among each scene's names (and WALL) against the largest salient weight, over the crops whose
    largest weight is ``which``: "all", "objects" (seen colour-shape pairs) or "novel" (held-out ones)."""

    def kind(n: str) -> str:
        o = world(n)
        return "stuff" if o is None else "novel" if o.novel else "objects"

    hits = total = 0
    for s in samples:
        table = text.encode_text(s.names)
        want = salient(s.shares, s.names).argmax(1)
        kinds = [kind(n) for n in s.names]
        keep = torch.tensor([which == "all" or kinds[w] == which for w in want.tolist()])
        if not keep.any():
            continue
        pred = (encoder(s.crops[keep]) @ table.T).argmax(1)
        hits += int((pred == want[keep]).sum())
        total += int(keep.sum())
    return hits / max(total, 1)


def heldout(work: Path, per_view: int) -> list:
    """The held-out scenes' crops, drawn with a fixed generator: every stand-in is measured on the same."""
    return dataset(work, list(HELDOUT), per_view, np.random.default_rng(1), novel=3)


def heldout_figures(encoder, text, work: Path, per_view: int, held: list) -> dict:
    """Held-out crop accuracy on ``held`` (all, seen objects, held-out names); per pyramid scale, the
    accuracy on crops whose most salient label is an object; and, of the object crops named wrongly, the
    share named as stuff (floor, wall, backdrop) rather than as another object."""
    from fmgs.features.pyramid import PyramidConfig
    from fmgs.features.standin import sample_crop_targets

    out = {
        "heldout_crop_accuracy": round(accuracy(encoder, text, held), 4),
        "heldout_object_crop_accuracy": round(accuracy(encoder, text, held, "objects"), 4),
        "heldout_novel_crop_accuracy": round(accuracy(encoder, text, held, "novel"), 4),
    }
    tables = {seed: text.encode_text(s.names) for seed, s in zip(HELDOUT, held, strict=True)}
    per_scale, wrong, as_stuff = {}, 0, 0
    for scale in PyramidConfig.scales:
        hits = total = 0
        for seed in HELDOUT:
            s = sample_crop_targets(scene(work, seed, novel=3), per_view // 2, np.random.default_rng(seed),
                                    IMAGE_SIZE, object_share=OBJECT_SHARE, scales=(scale,))  # fmt: skip
            want = salient(s.shares, s.names).argmax(1)
            obj = torch.tensor([world(s.names[w]) is not None for w in want.tolist()])
            if not obj.any():
                continue
            pred = (encoder(s.crops[obj]) @ tables[seed].T).argmax(1)
            ok = pred == want[obj]
            hits, total = hits + int(ok.sum()), total + int(obj.sum())
            wrong += int((~ok).sum())
            as_stuff += sum(world(s.names[p]) is None for p in pred[~ok].tolist())
        per_scale[str(scale)] = round(hits / max(total, 1), 4)
    out["heldout_object_crop_accuracy_per_scale"] = per_scale
    out["heldout_object_errors_named_as_stuff"] = round(as_stuff / max(wrong, 1), 4)
    return out


def evaluate(folder: Path, work: Path, per_view: int) -> int:
    """Measure a trained stand-in's held-out figures again and write them into its standin.json."""
    import json

    from fmgs.features.standin import CONFIG, load_standin
    from fmgs.features.text import MiniLMTextEncoder

    encoder = load_standin(f"standin:{folder}")
    with torch.inference_mode():
        figures = heldout_figures(encoder, MiniLMTextEncoder(), work, per_view, heldout(work, per_view))
    config = json.loads((folder / CONFIG).read_text())
    config.update(figures)
    (folder / CONFIG).write_text(json.dumps(config, indent=1))
    print(json.dumps(figures, indent=1))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "standin"))
    ap.add_argument("--work", default="/tmp/fmgs-standin")
    ap.add_argument("--seeds", default="9001-9100")
    ap.add_argument("--per-view", type=int, default=60)
    ap.add_argument("--epochs", type=int, default=12)
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--blocks", type=int, default=2, help="convs per halving stage (StandinNet)")
    ap.add_argument("--loss", default="softmax", choices=("softmax", "cosine", "both"))
    ap.add_argument("--target", default="mixture", choices=("mixture", "dominant"))
    ap.add_argument("--evaluate", metavar="FOLDER", help="only measure FOLDER's held-out figures again")
    a = ap.parse_args()
    if a.evaluate:
        return evaluate(Path(a.evaluate), Path(a.work), a.per_view)

    from fmgs.features.models import MINILM_ID
    from fmgs.features.standin import StandinImageEncoder, StandinNet, save_standin
    from fmgs.features.text import MiniLMTextEncoder

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    work = Path(a.work)
    t0 = time.perf_counter()
    train = dataset(work, seeds(a.seeds), a.per_view, rng)
    held = heldout(work, a.per_view)
    seen = sorted({n for s in train for n in s.names})
    vocab_list = sorted({c for n in seen for c, _ in captions(n)} | set(seen))
    vocab = {c: i for i, c in enumerate(vocab_list)}
    text = MiniLMTextEncoder()
    table = text.encode_text(vocab_list).clone()  # [V, 384] unit (a normal tensor: autograd uses it)
    x = torch.cat([s.crops for s in train])

    def weights(s):
        w = salient(s.shares, s.names)
        if a.target == "dominant":  # all of a crop's weight on its most salient label
            w = F.one_hot(w.argmax(1), w.shape[1]).float()
        return w

    pairs = [soft_targets(weights(s), s.names, vocab) for s in train]
    target = torch.cat([p[0] for p in pairs])
    caption_target = F.normalize(torch.cat([p[1] for p in pairs]) @ table, dim=-1)  # [N,384]
    mean, std = torch.tensor(MEAN).view(1, 3, 1, 1), torch.tensor(STD).view(1, 3, 1, 1)
    xn = (x - mean) / std
    print(f"{len(x)} training crops from {len(train)} scenes, {len(vocab)} captions", flush=True)

    net = StandinNet(table.shape[1], IMAGE_SIZE, a.width, a.blocks)
    opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, 2e-3, total_steps=a.epochs * ((len(x) + 255) // 256))
    watch_config = {"dim": table.shape[1], "image_size": IMAGE_SIZE, "mean": MEAN, "std": STD}
    watch = StandinImageEncoder(net, watch_config, "standin:training")  # the net itself, as it trains
    for epoch in range(a.epochs):
        net.train()
        perm = torch.randperm(len(x))
        total = 0.0
        for s in range(0, len(x), 256):
            i = perm[s : s + 256]
            xb = xn[i]
            if torch.rand(()) < 0.5:
                xb = xb.flip(-1)  # the window is symmetric: a mirrored crop shows the same shares
            emb = F.normalize(net(xb), dim=-1)
            loss = torch.zeros(())
            if a.loss in ("softmax", "both"):
                loss = loss - (target[i] * F.log_softmax(emb @ table.T / TEMPERATURE, -1)).sum(-1).mean()
            if a.loss in ("cosine", "both"):  # the crop's caption mixture as one point of the text space
                loss = loss + (1 - (emb * caption_target[i]).sum(-1)).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(i)
        net.eval()
        with torch.inference_mode():
            acc = accuracy(watch, text, held)
        print(f"epoch {epoch + 1}/{a.epochs}: loss {total / len(x):.3f}, held-out crop accuracy {acc:.3f}, "
              f"{time.perf_counter() - t0:.0f} s", flush=True)  # fmt: skip

    config = {
        "dim": int(table.shape[1]),
        "image_size": IMAGE_SIZE,
        "width": a.width,
        "blocks": a.blocks,
        "mean": list(MEAN),
        "std": list(STD),
        "text_encoder": MINILM_ID,
        "world": f"fmgs synth --preset world (fmgs.synthworld), 10 objects, {VIEWS} views, {SIZE}",
        "train_seeds": seeds(a.seeds),
        "heldout_seeds": list(HELDOUT),
        "train_crops": len(x),
        "heldout_crops": sum(len(s.crops) for s in held),
        "captions": len(vocab),
        "names_seen": seen,
        "epochs": a.epochs,
        "command": "python scripts/train_standin.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(a).items() if k not in ("out", "work")),
    }
    encoder = StandinImageEncoder(net, config, "standin:training")
    with torch.inference_mode():
        config.update(heldout_figures(encoder, text, work, a.per_view, held))
    config["train_seconds"] = round(time.perf_counter() - t0, 1)
    save_standin(a.out, net, config)
    print(
        f"held-out crop accuracy {config['heldout_crop_accuracy']:.3f}, objects "
        f"{config['heldout_object_crop_accuracy']:.3f}, held-out names "
        f"{config['heldout_novel_crop_accuracy']:.3f} ({config['heldout_crops']} crops); wrote {a.out}",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
