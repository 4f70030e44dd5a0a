"""The parts of benchmarks/gpu.py, one per subprocess: ``python -m benchmarks.gpu_parts NAME --work DIR``.

Each part measures the code path users run (SceneEngine, render_pose, the gRPC server, train_gaussians,
extract_targets, train_field) on the CUDA device and writes WORK/part-NAME.json. Timings synchronise
the device before reading the clock, follow warm-up runs, and report medians.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import (
    ENC,
    ROOT,
    TableEncoder,
    canonical_vectors,
    fieldlike,
    gaussians_from,
    machine,
    med_ms,
    proto_camera,
)
from benchmarks.gpu_grpc import grpc_breakdown, grpc_concurrent
from benchmarks.gpu_timing import (
    DEVICE,
    FAST,
    PAPER_FIELD_HOURS,
    PAPER_FPS,
    peak_gib,
    rel_l2,
    rel_max,
    reset_peak,
    sync,
    timed,
)
from benchmarks.scenes import DATA, garden, synthetic
from fmgs.vecmath import safe_normalize


def clip_like_queries(emb: torch.Tensor, n: int, cos: float = 0.3, seed: int = 1) -> torch.Tensor:
    """Unit queries at cosine ~``cos`` to a random scene embedding each (real CLIP text-to-image range)."""
    g = torch.Generator().manual_seed(seed)
    rows = torch.randint(0, len(emb), (n,), generator=g)
    e = emb[rows].float().cpu()
    noise = torch.randn(n, emb.shape[1], generator=g)
    noise = safe_normalize(noise - (noise * e).sum(1, keepdim=True) * e)  # orthogonal to e
    return safe_normalize(cos * e + (1 - cos**2) ** 0.5 * noise)


def _exported_scene(folder: Path, n: int, seed: int, n_queries: int):
    """A synthetic n-Gaussian scene with field-like embeddings exported to ``folder``:
    (scene, CLIP-like queries [n_queries,D], canonical embeddings [4,D], embeddings [n,D])."""
    from fmgs.scene.package import export_scene

    s = synthetic(n, seed=seed)
    emb = fieldlike(s.means)
    canon = canonical_vectors(emb.shape[1])
    queries = clip_like_queries(emb, n_queries)
    export_scene(folder, gaussians_from(s), torch.arange(n), emb, ENC, canon)
    return s, queries, canon, emb


# ---------------------------------------------------------------- env and build


def part_env(work: Path, quick: bool) -> dict:
    info = machine()
    info["commit"] = os.environ.get("FMGS_COMMIT", info.get("commit") or "unknown")
    info["torch_cuda"] = torch.version.cuda
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        info["gpu_memory_gib"] = round(p.total_memory / 2**30, 1)
        info["capability"] = f"{p.major}.{p.minor}"
        info["multiprocessors"] = p.multi_processor_count
    import shutil

    def tool(cmd: list[str]) -> str:
        if shutil.which(cmd[0]) is None:
            return "absent"
        p = subprocess.run(cmd, capture_output=True, text=True, check=False)
        return (p.stdout.strip().splitlines() or ["?"])[-1]

    info["nvidia_smi"] = tool(
        ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"]
    )
    info["nvcc"] = tool(["nvcc", "--version"])
    from importlib.metadata import version

    for pkg in ("gsplat", "triton", "grpcio"):
        try:
            info[pkg] = version(pkg)
        except Exception as e:
            info[pkg] = f"absent ({e})"
    return info


def part_build(work: Path, quick: bool) -> dict:
    """Compile (or load the cached) gsplat extension; the first CUDA call pays this once per machine."""
    ext = Path(os.environ.get("TORCH_EXTENSIONS_DIR", "~/.cache/torch_extensions")).expanduser()
    cached = any(ext.glob("**/gsplat_cuda.so"))
    t0 = time.perf_counter()
    from gsplat.cuda._backend import _C

    secs = time.perf_counter() - t0
    if _C is None:
        raise RuntimeError("gsplat's CUDA extension did not build (see the log above)")
    return {"seconds": secs, "was_cached": cached, "arch": os.environ.get("TORCH_CUDA_ARCH_LIST")}


def part_tests(work: Path, quick: bool) -> dict:
    """The CUDA tests (pytest -m cuda); counts from the JUnit XML."""
    import xml.etree.ElementTree as ET

    xml = work / "cuda-tests.xml"
    # Only the modules that hold CUDA tests: others may import packages the GPU image lacks (pycolmap).
    files = sorted(str(p) for p in (ROOT / "tests").rglob("test_*.py") if "mark.cuda" in p.read_text())
    cmd = [sys.executable, "-X", "faulthandler", "-m", "pytest", "-v", "-m", "cuda", "-p", "no:cacheprovider"]
    cmd += ["--junitxml", str(xml)]
    cmd += files
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    secs = time.perf_counter() - t0
    (work / "cuda-tests.log").write_text(p.stdout + "\n" + p.stderr)
    print(p.stdout[-6000:], p.stderr[-6000:])
    root = ET.parse(xml).getroot()
    suite = root if root.tag == "testsuite" else root.find("testsuite")
    failures = []
    for case in suite.iter("testcase"):
        for bad in list(case.findall("failure")) + list(case.findall("error")):
            msg = (bad.get("message") or "").splitlines()[0][:300] if bad.get("message") else ""
            failures.append(f"{case.get('classname')}::{case.get('name')}: {msg}")
    n = int(suite.get("tests", 0))
    res = {
        "collected": n,
        "failed": int(suite.get("failures", 0)),
        "errors": int(suite.get("errors", 0)),
        "skipped": int(suite.get("skipped", 0)),
        "seconds": secs,
        "failures": failures[:40],
        "summary": (p.stdout.strip().splitlines() or [""])[-1],
    }
    res["passed"] = n - res["failed"] - res["errors"] - res["skipped"]
    return res


# ---------------------------------------------------------------- pose queries, 1M Gaussians


def part_pose(work: Path, quick: bool) -> dict:
    """Relevancy images 480x270 of a 1M-Gaussian scene: the engine (CUDA with gsplat and with the triton
    backend, and the CPU) and gRPC on loopback, with where a served image's time goes."""
    from benchmarks.gpu_agreement import device_agreement
    from fmgs.query.engine import EngineConfig, SceneEngine
    from fmgs.query.pose import render_pose
    from fmgs_server.config import ServerConfig
    from fmgs_server.server import start_server
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

    n = 20_000 if quick else 1_000_000
    models = work / "models-pose"
    s, queries, canon, emb = _exported_scene(models / "pose", n, seed=4, n_queries=64)
    W, H = (64, 36) if quick else (480, 270)  # --quick checks the script (triton in its interpreter)
    cam = s.cameras[0].resized(W, H)
    res: dict = {"gaussians": n, "size": f"{W}x{H}", "target_images_per_s": 300}
    frames = 5 if quick else 300
    gpu_img = None
    for backend, tag in (("cuda", "engine_cuda"), ("triton", "engine_triton")):  # gsplat, then triton
        try:
            eng = SceneEngine.open(models / "pose", EngineConfig(device=DEVICE, backend=backend))
            reset_peak()
            # cached text (a pose stream: one text, many poses) and a new text every frame
            ts = timed(lambda e=eng: render_pose(e, cam, queries[0]), frames)
            res[f"{tag}_cached_ms"] = med_ms(ts)
            res[f"{tag}_cached_images_per_s"] = 1e3 / med_ms(ts)
            it = iter(range(10**9))
            ts = timed(lambda e=eng, it=it: render_pose(e, cam, queries[next(it) % 64]), frames)
            res[f"{tag}_new_text_ms"] = med_ms(ts)
            res[f"{tag}_new_text_images_per_s"] = 1e3 / med_ms(ts)
            ts = timed(
                lambda e=eng: render_pose(e, cam, queries[0], ("relevancy", "rgb", "depth")), frames // 3
            )
            res[f"{tag}_rel_rgb_depth_ms"] = med_ms(ts)
            res[f"{tag}_peak_gib"] = peak_gib()
            img = render_pose(eng, cam, queries[5]).relevancy
            if gpu_img is None:
                gpu_img = img
            else:
                res["triton_vs_gsplat_relevancy_max_abs"] = float((img - gpu_img).abs().max())
            del eng
        except Exception as e:  # a failed backend must not lose the rest of the part
            res[f"{tag}_error"] = f"{type(e).__name__}: {e}"[:300]
        print(f"[pose] {tag}: {res.get(f'{tag}_cached_ms', res.get(f'{tag}_error'))}", flush=True)
    res["cuda_peak_gib"] = res.get("engine_cuda_peak_gib")
    cpu = SceneEngine.open(models / "pose", EngineConfig(device="cpu"))
    ts = timed(lambda e=cpu: render_pose(e, cam, queries[0]), 3, warm=1)
    res["engine_cpu_ms"] = med_ms(ts)
    res["engine_cpu_images_per_s"] = 1e3 / med_ms(ts)
    res["cuda_vs_cpu_relevancy_max_abs"] = float(
        (render_pose(cpu, cam, queries[5]).relevancy - gpu_img).abs().max()
    )
    res["speedup_cuda_vs_cpu"] = res["engine_cpu_ms"] / res["engine_cuda_cached_ms"]
    res["agreement"] = device_agreement(models / "pose", cpu, emb, cam, DEVICE)
    print(f"[pose] agreement: {res['agreement']}", flush=True)
    del cpu
    (work / "part-pose.partial.json").write_text(json.dumps(res, default=str))

    enc = TableEncoder(queries, canon)
    pcam = proto_camera(cam)
    req = lambda i: pb.RenderRequest(scene="pose", camera=pcam, text=f"q{i % 64}", sequence=i)  # noqa: E731
    for backend in ("cuda", "triton"):
        if f"{'engine_cuda' if backend == 'cuda' else 'engine_triton'}_error" in res:
            continue
        key = "grpc" if backend == "cuda" else "grpc_triton"
        srv = start_server(
            ServerConfig(models=models, port=0, device=DEVICE, backend=backend), encoder_factory=lambda i: enc
        )
        try:
            res[key] = grpc_breakdown(srv.address, req, cam, frames, quick)
            res[key].update(grpc_concurrent(srv.address, req, 8, 3.0 if quick else 8.0))
        finally:
            srv.stop(0)
        print(f"[pose] {key}: {res[key]}", flush=True)
        (work / "part-pose.partial.json").write_text(json.dumps(res, default=str))
    # The headline figures of the gsplat server, under the names earlier runs used.
    g = res.get("grpc", {})
    res["grpc_sequential_ms"] = g.get("sequential_ms")
    res["grpc_sequential_images_per_s"] = g.get("sequential_images_per_s")
    for k in ("grpc_concurrent_clients", "grpc_concurrent_images_per_s", "grpc_concurrent_errors"):
        res[k] = g.get(k)
    return res


def part_paper(work: Path, quick: bool) -> dict:
    """CLIP 512 + DINO 384 + RGB of the garden scene through ``rasterize``: gsplat (``cuda``, passes of
    CHANNEL_CHUNK channels) against the one-pass ``triton`` backend, each image's error against the float64
    reference, the triton launch sweep, and the 5-channel relevancy-sized render."""
    from fmgs.field.model import FeatureField, FieldConfig
    from fmgs.render import rasterize
    from fmgs.render import triton_blend as tb
    from fmgs.render.binning import bin_tiles
    from fmgs.render.projection import project
    from fmgs.render.types import RasterConfig

    s = garden()
    if quick:  # a check of the script (on the CPU, triton in its interpreter): a slice of the scene
        cut = ("means", "quats", "scales", "opacities", "colors")
        s = s._replace(**{k: getattr(s, k)[:1500] for k in cut})
    dev = torch.device(DEVICE)
    n = len(s.means)
    geo = [t.to(dev) for t in (s.means, s.quats, s.scales, s.opacities)]
    clip = fieldlike(s.means, 512, seed=1).to(dev)
    dino = fieldlike(s.means, 384, seed=2).to(dev) * 3
    rgb = s.colors.to(dev)
    feats = torch.cat([clip, dino, rgb], 1)
    field = FeatureField.for_points(FieldConfig(), s.means).to(dev).eval()
    look = field.lookup(geo[0])
    res: dict = {
        "gaussians": n,
        "paper_fps": PAPER_FPS,
        "target_fps": 2 * PAPER_FPS,
        "channels": feats.shape[1],
    }
    runs = 2 if quick else 100
    # --quick (a check of the script on the CPU, triton in its interpreter): tiny pictures
    sizes = ((48, 27), (64, 42)) if quick else ((480, 270), (648, 420))
    cam = s.cameras[0].resized(*sizes[0])
    main = f"{sizes[0][0]}x{sizes[0][1]}"
    with torch.no_grad():
        truth = rasterize(*[t.double() for t in geo], feats.double(), cam, backend="reference").image
        sync()
        for backend in (FAST, "triton"):
            img = rasterize(*geo, feats, cam, backend=backend).image
            res[f"{main}_{backend}_relmax_vs_f64"] = rel_max(img, truth)
            del img
        del truth
        # Where a triton frame's time goes: the float64 projection and binning (torch) before the kernel.
        rc = RasterConfig()
        res[f"{main}_project_bin_ms"] = med_ms(
            timed(lambda: bin_tiles(project(*geo, cam, rc), cam.width, cam.height, rc.tile_size), runs)
        )
    for W, H in sizes:
        c = s.cameras[0].resized(W, H)
        tag = f"{W}x{H}"
        for backend in (FAST, "triton"):

            @torch.no_grad()
            def stored(c=c, backend=backend):
                return rasterize(*geo, feats, c, backend=backend)

            @torch.no_grad()
            def separate(c=c, backend=backend):
                return [rasterize(*geo, f, c, backend=backend) for f in (clip, dino, rgb)]

            @torch.no_grad()
            def decoded(c=c, backend=backend):
                out = field.decode(look)
                return rasterize(*geo, torch.cat([out.clip, out.dino, rgb], 1), c, backend=backend)

            @torch.no_grad()
            def five(c=c, backend=backend):
                return rasterize(*geo, feats[:, :5], c, backend=backend)

            for name, fn in (
                ("stored_one_call", stored),
                ("stored_three_calls", separate),
                ("field_decoded", decoded),
                ("5ch", five),
            ):
                ms = med_ms(timed(fn, runs))
                key = f"{tag}_{name}" if backend == FAST else f"{tag}_triton_{name}"
                res[f"{key}_ms"] = ms
                res[f"{key}_fps"] = 1e3 / ms
            print(
                f"[paper] {tag} {backend}: {res[key.replace('5ch', 'stored_one_call') + '_fps']:.1f} FPS",
                flush=True,
            )
    # The launch sweep at the first size through rasterize (the module's TUNING is what rasterize uses).
    res["sweep"] = {}
    keep = tb.TUNING
    with torch.no_grad():
        truth = rasterize(*[t.double() for t in geo], feats.double(), cam, backend="reference").image
        for name, tuning in tb.SWEEP.items():
            tb.TUNING = tuning
            try:
                t0 = time.perf_counter()
                img = rasterize(*geo, feats, cam, backend="triton").image
                sync()
                first_s = time.perf_counter() - t0  # includes compiling this launch
                err = rel_max(img, truth)
                del img
                ms = med_ms(timed(lambda: rasterize(*geo, feats, cam, backend="triton"), runs))
                ms5 = med_ms(timed(lambda: rasterize(*geo, feats[:, :5], cam, backend="triton"), runs))
                res["sweep"][name] = {
                    "tuning": tuning._asdict(), "ms": ms, "fps": 1e3 / ms, "relmax_vs_f64": err,
                    "5ch_ms": ms5, "first_call_s": first_s,
                }  # fmt: skip
            except Exception as e:  # one launch that fails to compile must not lose the others
                res["sweep"][name] = {"tuning": tuning._asdict(), "error": f"{type(e).__name__}: {e}"[:300]}
            print(f"[paper] sweep {name}: {res['sweep'][name]}", flush=True)
            (work / "part-paper.partial.json").write_text(json.dumps(res, default=str))
    tb.TUNING = keep
    res["cuda_peak_gib"] = peak_gib()
    return res


# ---------------------------------------------------------------- agreement with the reference


def part_agreement(work: Path, quick: bool) -> dict:
    """gsplat against the reference backend (same float32 inputs) and the float64 truth, with gradients."""
    from fmgs.render import RasterConfig, rasterize

    dev = torch.device(DEVICE)
    res: dict = {}
    n, (W, H) = (3000, (160, 120)) if quick else (20_000, (480, 270))
    s = synthetic(n, seed=5, width=W, height=H)  # opacities 0.1-0.9: no alpha clamp differences
    cam = s.cameras[1]
    gen = torch.Generator().manual_seed(0)
    for D in (3, 5, 896):
        feats = torch.rand(n, D, generator=gen)
        args32 = [t.float().to(dev) for t in (s.means, s.quats, s.scales, s.opacities, feats)]
        truth = rasterize(
            *[t.double() for t in (s.means, s.quats, s.scales, s.opacities, feats)], cam, backend="cpu"
        )
        with torch.no_grad():
            gs = rasterize(*args32, cam, backend=FAST)
            ref = rasterize(*args32, cam, backend="reference")
        res[f"fwd_D{D}_gsplat_vs_ref32_relmax"] = rel_max(gs.image, ref.image)
        res[f"fwd_D{D}_gsplat_vs_f64_relmax"] = rel_max(gs.image, truth.image)
        res[f"fwd_D{D}_ref32_vs_f64_relmax"] = rel_max(ref.image, truth.image)
        res[f"fwd_D{D}_alpha_gsplat_vs_f64_max_abs"] = float(
            (gs.alpha.double().cpu() - truth.alpha).abs().max()
        )
    # gradients: a smaller scene, a random cotangent, every input
    ng = 2000 if quick else 5000
    s2 = synthetic(ng, seed=6, width=160, height=120)
    cam2 = s2.cameras[0]
    for D in (3, 5, 896):
        feats = torch.rand(ng, D, generator=gen)
        cot = torch.randn(120, 160, D, generator=gen).to(dev)
        grads = {}
        for backend, dt in (
            (FAST, torch.float32),
            ("reference", torch.float32),
            ("reference", torch.float64),
        ):
            ins = [
                t.to(dev, dt).detach().clone().requires_grad_(True)
                for t in (s2.means, s2.quats, s2.scales, s2.opacities, feats)
            ]
            out = rasterize(*ins, cam2, backend=backend)
            (out.image * cot.to(dt)).sum().backward()
            grads[(backend, dt)] = [t.grad for t in ins]
        names = ("means", "quats", "scales", "opacities", "features")
        for i, nm in enumerate(names):
            truth = grads[("reference", torch.float64)][i]
            res[f"grad_D{D}_{nm}_gsplat_vs_f64_rel_l2"] = rel_l2(grads[(FAST, torch.float32)][i], truth)
            res[f"grad_D{D}_{nm}_ref32_vs_f64_rel_l2"] = rel_l2(grads[("reference", torch.float32)][i], truth)
    # rule 1: alpha clamp (gsplat 0.999, ours alpha_max 0.99): fully opaque Gaussians
    sat = synthetic(n // 4, seed=7, width=W, height=H)
    feats = torch.rand(len(sat.means), 3, generator=gen)
    ones = torch.ones(len(sat.means))
    a32 = [t.float().to(dev) for t in (sat.means, sat.quats, sat.scales, ones, feats)]
    with torch.no_grad():
        gs, ref = (
            rasterize(*a32, sat.cameras[0], backend=FAST),
            rasterize(*a32, sat.cameras[0], backend="reference"),
        )
    res["rule_alpha_clamp_opacity1_relmax"] = rel_max(gs.image, ref.image)
    res["rule_alpha_clamp_pixels_differing_1e-3"] = float(
        ((gs.image - ref.image).abs().amax(-1) > 1e-3).float().mean()
    )
    cfg999 = RasterConfig(alpha_max=0.999)
    with torch.no_grad():
        ref999 = rasterize(*a32, sat.cameras[0], config=cfg999, backend="reference")
    res["rule_alpha_clamp_with_alpha_max_0.999_relmax"] = rel_max(gs.image, ref999.image)
    # rule 2: termination (T <= 1e-4 vs T < 1e-4): a deep stack of 2,000 layers at opacity 0.5
    k = 2000
    means = torch.zeros(k, 3)
    means[:, 2] = torch.linspace(2.0, 6.0, k)
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(k, 1)
    scales = torch.full((k, 3), 0.5)
    op = torch.full((k,), 0.5)
    f = torch.rand(k, 3, generator=gen)
    from fmgs.cameras import Camera

    c = Camera(Camera.intrinsics(60.0, 60.0, 32.0, 24.0), torch.eye(4, dtype=torch.float64), 64, 48)
    a32 = [t.float().to(dev) for t in (means, quats, scales, op, f)]
    with torch.no_grad():
        gs, ref = rasterize(*a32, c, backend=FAST), rasterize(*a32, c, backend="reference")
    res["rule_termination_deep_stack_relmax"] = rel_max(gs.image, ref.image)
    res["rule_termination_bound"] = (
        "at most 1e-4 * max|feature| per pixel (one more or one fewer layer at T=1e-4)"
    )
    # rule 3: float32 fast-math geometry, stiff case: needle Gaussians (scale ratio 1e4)
    st = synthetic(n // 4, seed=8, width=W, height=H)
    sc = st.scales.clone()
    sc[:, 0] *= 100.0
    sc[:, 1] /= 100.0
    feats = torch.rand(len(st.means), 3, generator=gen)
    truth = rasterize(
        *[t.double() for t in (st.means, st.quats, sc, st.opacities, feats)], st.cameras[0], backend="cpu"
    )
    a32 = [t.float().to(dev) for t in (st.means, st.quats, sc, st.opacities, feats)]
    with torch.no_grad():
        gs, ref = (
            rasterize(*a32, st.cameras[0], backend=FAST),
            rasterize(*a32, st.cameras[0], backend="reference"),
        )
    res["rule_fastmath_needles_gsplat_vs_f64_relmax"] = rel_max(gs.image, truth.image)
    res["rule_fastmath_needles_ref32_vs_f64_relmax"] = rel_max(ref.image, truth.image)
    res.update(_engine_agreement(work, quick))
    return res


def _engine_agreement(work: Path, quick: bool) -> dict:
    """The query engine on CUDA against the same engine on the CPU (exact state both sides)."""
    from fmgs.query.engine import EngineConfig, SceneEngine
    from fmgs.query.index import IndexConfig
    from fmgs.query.pose import render_pose

    n = 20_000 if quick else 200_000
    s, queries, *_ = _exported_scene(work / "models-agree" / "agree", n, seed=11, n_queries=20)
    exact = IndexConfig(rank=0)
    cpu = SceneEngine.open(work / "models-agree" / "agree", EngineConfig(index=exact))
    gpu = SceneEngine.open(work / "models-agree" / "agree", EngineConfig(index=exact, device=DEVICE))
    same, rel_err = 0, 0.0
    for q in queries:
        a, b = cpu.text_query(q, 100), gpu.text_query(q, 100)
        same += int(torch.equal(a.index, b.index))
        rel_err = max(rel_err, float((a.relevancy - b.relevancy).abs().max()))
    cam = s.cameras[0].resized(480, 270)
    img_err = max(
        float((render_pose(cpu, cam, q).relevancy - render_pose(gpu, cam, q).relevancy).abs().max())
        for q in queries[:5]
    )
    return {
        "engine_gaussians": n,
        "engine_text_top100_identical": same / len(queries),
        "engine_text_relevancy_max_abs": rel_err,
        "engine_pose_relevancy_max_abs": img_err,
    }


# ---------------------------------------------------------------- text queries at 10M Gaussians


def part_text10m(work: Path, quick: bool) -> dict:
    """Top-100 text queries over 10M embedded Gaussians: CUDA engine (exact) against CPU engines."""
    from fmgs.gaussians import GaussianSet
    from fmgs.query.engine import EngineConfig, SceneEngine
    from fmgs.query.index import IndexConfig
    from fmgs.scene.manifest import CANONICAL_PHRASES, Manifest
    from fmgs.scene.package import ScenePackage

    n = 200_000 if quick else 10_000_000
    D = 512
    gen = torch.Generator().manual_seed(3)
    means = torch.rand(n, 3, generator=gen) * torch.tensor([40.0, 20.0, 10.0])
    dev = torch.device(DEVICE)
    emb = torch.empty(n, D, dtype=torch.float16)
    step = 1 << 20
    ref_means = means[torch.randperm(n, generator=gen)[:100_000]]
    box = torch.stack([ref_means.min(0).values, ref_means.max(0).values])
    for i in range(0, n, step):  # fieldlike embeddings, computed on the GPU, stored float16 like a package
        emb[i : i + step] = fieldlike(means[i : i + step], D, device=dev, box=box).half().cpu()
    canon = canonical_vectors(D)
    canon_dots = torch.empty(n, 4)
    for i in range(0, n, step):
        canon_dots[i : i + step] = emb[i : i + step].float() @ canon.T
    queries = clip_like_queries(emb, 30)
    g = GaussianSet.from_activated(
        means, torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4), torch.full((n, 3), 0.01), torch.full((n,), 0.5)
    )
    manifest = Manifest("text10m", ENC, D, CANONICAL_PHRASES, num_gaussians=n, num_selected=n)
    pkg = ScenePackage("text10m", manifest, g, torch.arange(n), emb, canon_dots, None)
    res: dict = {"gaussians": n, "dim": D, "top_k": 100}
    best = []
    for q in queries[:5]:
        best.append(max(float((emb[i : i + step].float() @ q).max()) for i in range(0, n, step)))
    res["query_best_cosine_median"] = statistics.median(best)

    t0 = time.perf_counter()
    gpu = SceneEngine(pkg, EngineConfig(device=DEVICE))
    sync()
    res["cuda_open_s"] = time.perf_counter() - t0
    res["cuda_state_gib"] = gpu.index.nbytes() / 2**30
    it = iter(range(10**9))
    ts = timed(lambda e=gpu: e.text_query(queries[next(it) % len(queries)], 100), 100 if not quick else 20)
    res["cuda_ms_median"] = med_ms(ts)
    res["cuda_ms_p90"] = float(np.percentile(ts, 90) * 1e3)
    gpu_answers = [gpu.text_query(q, 100) for q in queries[:10]]
    del gpu
    if DEVICE == "cuda":
        torch.cuda.empty_cache()

    t0 = time.perf_counter()
    compact = SceneEngine(pkg, EngineConfig())
    res["cpu_compact_open_s"] = time.perf_counter() - t0
    ts = timed(lambda e=compact: e.text_query(queries[next(it) % len(queries)], 100), 10, warm=2)
    res["cpu_compact_ms_median"] = med_ms(ts)
    overlap = [
        len(set(compact.text_query(q, 100).index.tolist()) & set(a.index.tolist())) / 100
        for q, a in zip(queries[:10], gpu_answers, strict=True)
    ]
    res["cpu_compact_top100_overlap_with_exact_mean"] = float(np.mean(overlap))
    res["cpu_compact_top100_overlap_with_exact_min"] = float(np.min(overlap))
    del compact
    t0 = time.perf_counter()
    exact = SceneEngine(pkg, EngineConfig(index=IndexConfig(rank=0)))
    res["cpu_exact_open_s"] = time.perf_counter() - t0
    ts = timed(lambda: exact.text_query(queries[next(it) % len(queries)], 100), 5, warm=1)
    res["cpu_exact_ms_median"] = med_ms(ts)
    same = sum(
        int(torch.equal(exact.text_query(q, 100).index, a.index))
        for q, a in zip(queries[:10], gpu_answers, strict=True)
    )
    res["cuda_vs_cpu_exact_top100_identical"] = same / 10
    res["speedup_cuda_vs_cpu_compact"] = res["cpu_compact_ms_median"] / res["cuda_ms_median"]
    res["speedup_cuda_vs_cpu_exact"] = res["cpu_exact_ms_median"] / res["cuda_ms_median"]
    return res


# ---------------------------------------------------------------- training


def part_gs_train(work: Path, quick: bool) -> dict:
    """3DGS on snowmiku_small at full resolution, 30K steps (fewer only if the part's time would not fit)."""
    from fmgs.data.dataset import load_dataset
    from fmgs.io.ply import read_ply
    from fmgs.train.evaluate import evaluate
    from fmgs.train.gaussians import GSTrainConfig, train_gaussians

    ds = load_dataset(DATA / "snowmiku_small")
    budget = float(os.environ.get("FMGS_PART_LIMIT_S", "480")) - 90  # room for the probe and the evaluation
    probe_steps = 50 if quick else 500
    probe = train_gaussians(
        ds, work / "gs-probe", GSTrainConfig.reduced(probe_steps, device=DEVICE), progress=False, resume=False
    )
    per_step = probe.seconds / probe_steps
    steps = 30_000 if not quick else 200
    if per_step * steps * 1.6 > budget:  # densification grows the scene: later steps cost more
        steps = int(budget / (per_step * 1.6)) // 1000 * 1000
    cfg = GSTrainConfig.reduced(steps, device=DEVICE)  # the defaults at 30,000
    reset_peak()
    r = train_gaussians(ds, work / "gs", cfg, progress=False, resume=False)
    res = {
        "steps": steps,
        "full_schedule": steps == 30_000,
        "probe_s_per_step": per_step,
        "train_s": r.seconds,
        "gaussians": r.gaussians.num,
        "peak_gpu_gib": peak_gib(),
        "image_size": f"{ds.frames[0].camera.width}x{ds.frames[0].camera.height}",
        "views_train": len(ds.split(8)[0]),
        "views_heldout": len(ds.split(8)[1]),
        "target_psnr_db": 25.0,
    }
    g = read_ply(work / "gs" / "point_cloud.ply").to(DEVICE)
    t0 = time.perf_counter()
    ev = evaluate(g, ds, background=r.background)
    res["heldout_psnr_db"] = ev.psnr
    res["heldout_ssim"] = ev.ssim
    res["eval_s"] = time.perf_counter() - t0
    return res


def part_field_train(work: Path, quick: bool) -> dict:
    """Targets from random-weight CLIP ViT-B/16 + DINO ViT-S/8 (same cost as trained weights), then 4.2K
    field steps with 512+384-channel targets, all on the GPU, on the 3DGS fit from gs_train."""
    import transformers

    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCache
    from fmgs.features.clip import ClipImageEncoder
    from fmgs.features.dino import DinoEncoder
    from fmgs.features.extract import ExtractConfig, extract_targets
    from fmgs.io.ply import read_ply
    from fmgs.train.field import FieldTrainConfig, train_field

    start = time.perf_counter()
    ds = load_dataset(DATA / "snowmiku_small")
    ply = work / "gs" / "point_cloud.ply"
    fit = "gs_train's fit"
    if (
        not ply.is_file()
    ):  # a shorter fit of its own (the field's cost depends on the scene, not the fit's length)
        from fmgs.train.gaussians import GSTrainConfig, train_gaussians

        steps = 100 if quick else 3000
        train_gaussians(ds, work / "gs-field", GSTrainConfig.reduced(steps, device=DEVICE), progress=False)
        ply, fit = work / "gs-field" / "point_cloud.ply", f"a {steps}-step fit of its own"
    gaussians = read_ply(ply)
    torch.manual_seed(0)
    layers = 1 if quick else 12  # --quick checks the script: tiny towers of the same kind
    vision = transformers.CLIPVisionConfig(
        patch_size=16, image_size=224, hidden_size=768, num_hidden_layers=layers
    )
    clip_cfg = transformers.CLIPConfig(vision_config=vision.to_dict(), projection_dim=512)
    clip = ClipImageEncoder(
        transformers.CLIPModel(clip_cfg),
        "random/clip-vit-b-16",
        DEVICE,
        dtype=torch.float16 if DEVICE == "cuda" else torch.float32,
    )
    vit_cfg = transformers.ViTConfig(
        hidden_size=384,
        num_hidden_layers=layers,
        num_attention_heads=6,
        intermediate_size=1536,
        patch_size=8,
        image_size=224,
    )
    dino = DinoEncoder(
        transformers.ViTModel(vit_cfg, add_pooling_layer=False),
        "random/dino-vits8",
        DEVICE,
        dtype=torch.float16 if DEVICE == "cuda" else torch.float32,
    )
    cache_dir = work / "features"
    # The build's default map size (feature_side); --quick (a check of the script) small maps.
    xcfg = ExtractConfig(device=DEVICE, progress=False, **({"feature_side": 48} if quick else {}))
    train_idx = ds.split(8)[0]
    t0 = time.perf_counter()
    cache = extract_targets(ds, cache_dir, clip, dino, cfg=xcfg)
    sync()
    extract_s = time.perf_counter() - t0
    cache = FeatureCache.open(cache_dir)
    # A short probe sizes the run to the part's time limit: all 4.2K steps when they fit, else a
    # compressed schedule of what fits, with the full run's time projected from its ms per step.
    probe_steps = 20 if quick else 100
    t_probe = time.perf_counter()
    probe = train_field(
        gaussians,
        ds,
        cache,
        work / "field-probe",
        FieldTrainConfig().reduced(probe_steps, device=DEVICE, checkpoint_every=0),
        progress=False,
        resume=False,
    )
    per_step = probe.seconds / probe_steps
    prepare = time.perf_counter() - t_probe - probe.seconds  # selection and blending weights, once a run
    # Phase times on the console, so that a part cut off at its limit still says where its time went.
    print(
        f"[field_train] extract {extract_s:.1f} s; probe {probe_steps} steps {probe.seconds:.1f} s "
        f"+ prepare {prepare:.1f} s",
        flush=True,
    )
    left = float(os.environ.get("FMGS_PART_LIMIT_S", "420")) - (time.perf_counter() - start) - 20
    full = 200 if quick else 4200
    steps = full
    if per_step * full * 1.2 + prepare > left:
        steps = max(probe_steps, int((left - prepare) / (per_step * 1.2)) // 100 * 100)
    cfg = FieldTrainConfig(steps=steps, device=DEVICE, checkpoint_every=0)
    if quick or steps != full:
        cfg = FieldTrainConfig().reduced(steps, device=DEVICE, checkpoint_every=0)
    reset_peak()
    t0 = time.perf_counter()
    print(f"[field_train] {steps} steps", flush=True)
    r = train_field(gaussians, ds, cache, work / "field", cfg, progress=True, resume=False)
    total = time.perf_counter() - t0
    h, w = cache.size(ds.frames[train_idx[0]].name)
    return {
        "images": len(ds),
        "geometry": fit,
        "extract_s": extract_s,
        "extract_images_per_s": len(ds) / extract_s,
        "feature_scale": xcfg.feature_scale,
        "feature_side": xcfg.feature_side,
        "map_size": f"{w}x{h}",
        "steps": steps,
        "full_schedule": steps == full,
        "probe_ms_per_step": per_step * 1e3,
        "projected_full_s": r.seconds / steps * full,
        "selected_gaussians": len(r.selection.index),
        "gaussians": gaussians.num,
        "train_loop_s": r.seconds,
        "train_total_s": total,
        "prepare_s": total - r.seconds,
        "ms_per_step": r.seconds / steps * 1e3,
        "peak_gpu_gib": peak_gib(),
        "final_loss": r.losses[-1],
        "target_s": 600,
        "paper_s": PAPER_FIELD_HOURS * 3600,
    }


def part_chunks(work: Path, quick: bool) -> dict:
    """gsplat's channels per pass against render time: the 899-channel garden render and a 5-channel one."""
    import fmgs.render.cuda_gsplat as cg
    from fmgs.render import rasterize

    s = garden()
    dev = torch.device(DEVICE)
    geo = [t.to(dev) for t in (s.means, s.quats, s.scales, s.opacities)]
    feats = torch.cat([fieldlike(s.means, 512, seed=1), fieldlike(s.means, 384, seed=2), s.colors], 1).to(dev)
    cam = s.cameras[0].resized(480, 270)
    res: dict = {}
    with torch.no_grad():
        truth = rasterize(*geo, feats, cam, backend="reference").image
        for chunk in (8, 16, 32, 64, 128, 256, 513):
            cg.CHANNEL_CHUNK = chunk
            out = rasterize(*geo, feats, cam, backend=FAST).image
            res[f"chunk{chunk}_relmax_vs_reference"] = rel_max(out, truth)
            res[f"chunk{chunk}_899ch_ms"] = med_ms(
                timed(lambda: rasterize(*geo, feats, cam, backend=FAST), 30)
            )
            res[f"chunk{chunk}_5ch_ms"] = med_ms(
                timed(lambda: rasterize(*geo, feats[:, :5], cam, backend=FAST), 30)
            )
    return res


PARTS = {
    "chunks": part_chunks,
    "env": part_env,
    "build": part_build,
    "tests": part_tests,
    "pose": part_pose,
    "paper": part_paper,
    "agreement": part_agreement,
    "text10m": part_text10m,
    "gs_train": part_gs_train,
    "field_train": part_field_train,
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("part", choices=list(PARTS))
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    out = a.work / f"part-{a.part}.json"
    try:
        res = PARTS[a.part](a.work, a.quick)
    except Exception as e:
        import traceback

        traceback.print_exc()
        out.write_text(json.dumps({"error": f"{type(e).__name__}: {e}"[:2000]}))
        return 1
    out.write_text(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
