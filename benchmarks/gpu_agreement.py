"""The CPU and CUDA engines' relevancy images compared per query set, and each against a float64
dot-then-render of the stored embeddings (the GPU pose part, benchmarks/gpu_parts.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch


def device_agreement(package: Path, cpu, emb: torch.Tensor, cam, device: str) -> dict:
    """Per query set (benchmarks/query_sets.py): max |relevancy difference| between the CPU engine
    ``cpu`` and CUDA engines on ``device`` opened on the same package (rendering with the triton backend,
    the default, and with gsplat), for the same camera, and of each against a float64 dot-then-render of
    the stored embeddings (float64 channels blended in float64 by the cpu backend). Target: all <= 1e-4."""
    from benchmarks.query_sets import query_sets
    from fmgs.query.engine import EngineConfig, SceneEngine
    from fmgs.query.pose import render_pose
    from fmgs.query.relevancy import TEMPERATURE, relevancy
    from fmgs.render import rasterize

    stored = cpu.index.half  # the package's float16 embeddings, as the engines read them
    f16 = torch.from_numpy(stored.view(np.float16)) if stored is not None else emb.half()
    backends = ("triton", "cuda") if device == "cuda" else ("triton",)  # gsplat needs CUDA
    gpus = {b: SceneEngine.open(package, EngineConfig(device=device, backend=b)) for b in backends}
    geom = [t.double().cpu() for t in cpu.geometry]
    out = {}
    for name, qs in query_sets(emb, torch.zeros(0, dtype=torch.int64), 2).items():
        if name == "ties":
            continue
        worst: dict[str, float] = {}
        for q in qs:
            u = cpu.unit(q[None])[0].double()
            chans = torch.cat([(f16.double() @ u)[:, None], cpu.index.canonical.double()], 1)
            img = rasterize(*geom, chans, cam, backend="cpu").image
            ref = relevancy(img[..., 0], img[..., 1:], TEMPERATURE)
            a = render_pose(cpu, cam, q).relevancy.double()
            diffs = {"cpu_vs_f64": a - ref}
            for b, gpu in gpus.items():
                g = render_pose(gpu, cam, q).relevancy.double().cpu()
                diffs[f"cpu_vs_{b}"], diffs[f"{b}_vs_f64"] = a - g, g - ref
            for key, d in diffs.items():
                worst[key] = max(worst.get(key, 0.0), float(d.abs().max()))
        out[name] = worst
    del gpus
    return out
