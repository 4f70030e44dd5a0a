"""The CPU and CUDA engines' relevancy images compared per query set, and each against a float64
dot-then-render of the stored embeddings (the GPU pose part, benchmarks/gpu_parts.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch


def device_agreement(package: Path, cpu, emb: torch.Tensor, cam, device: str) -> dict:
    """Per query set (benchmarks/query_sets.py): max |relevancy difference| between the CPU engine
    ``cpu`` and a CUDA engine on ``device`` opened on the same package, for the same camera, and of each
    against a float64 dot-then-render of the stored embeddings (float64 channels blended in float64 by
    the cpu backend). Target: all <= 1e-4."""
    from benchmarks.query_sets import query_sets
    from fmgs.query.engine import EngineConfig, SceneEngine
    from fmgs.query.pose import render_pose
    from fmgs.query.relevancy import TEMPERATURE, relevancy
    from fmgs.render import rasterize

    stored = cpu.index.half  # the package's float16 embeddings, as the engines read them
    f16 = torch.from_numpy(stored.view(np.float16)) if stored is not None else emb.half()
    gpu = SceneEngine.open(package, EngineConfig(device=device))
    geom = [t.double().cpu() for t in cpu.geometry]
    out = {}
    for name, qs in query_sets(emb, torch.zeros(0, dtype=torch.int64), 2).items():
        if name == "ties":
            continue
        worst = {"cpu_vs_cuda": 0.0, "cpu_vs_f64": 0.0, "cuda_vs_f64": 0.0}
        for q in qs:
            u = cpu.unit(q[None])[0].double()
            chans = torch.cat([(f16.double() @ u)[:, None], cpu.index.canonical.double()], 1)
            img = rasterize(*geom, chans, cam, backend="cpu").image
            ref = relevancy(img[..., 0], img[..., 1:], TEMPERATURE)
            a = render_pose(cpu, cam, q).relevancy.double()
            b = render_pose(gpu, cam, q).relevancy.double().cpu()
            for key, d in (("cpu_vs_cuda", a - b), ("cpu_vs_f64", a - ref), ("cuda_vs_f64", b - ref)):
                worst[key] = max(worst[key], float(d.abs().max()))
        out[name] = worst
    del gpu
    return out
