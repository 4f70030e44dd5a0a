"""Rasteriser benchmark: frames per second, peak memory and error against float64, per backend.

    python -m benchmarks.raster            # full report -> benchmarks/results/RASTER.md (+ RASTER.json)
    python -m benchmarks.raster --quick    # small CI-sized run -> benchmarks/out/RASTER-quick.md

Every configuration runs in its own subprocess so its peak memory (ru_maxrss) is its own. The float64
truth for the error column is the CPU backend with float64 features: its geometry and weights are
float64 and tests/render/test_agreement.py checks it against the brute-force renderer to 1e-10.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from benchmarks.common import RESULTS, ROOT, machine, rss_gb


@dataclass(frozen=True)
class Config:
    """One measured configuration."""

    scene: str
    """'garden' (gsplat test_garden, 138,766 points) or 'synthetic-<N>'."""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    channels: int
    """Feature channels D."""
    backend: str
    """'cpu', 'reference', 'reference+grad' (forward and backward) or 'cuda'."""
    runs: int
    """Timed runs after one warm-up run (the median is reported)."""
    opacity: float = 0.8
    """Opacity of every garden Gaussian (synthetic scenes draw theirs)."""


def make_scene(cfg: Config):
    """(means, quats, scales, opacities, camera) for a configuration."""
    from benchmarks.scenes import view

    return view(cfg.scene, cfg.width, cfg.height, cfg.opacity)


def run_one(cfg: Config) -> dict:
    """Measure one configuration in this process; returns a JSON-able dict."""
    import numpy as np
    import torch

    from fmgs.render import rasterize

    torch.set_grad_enabled(False)
    means, quats, scales, opac, cam = make_scene(cfg)
    g = torch.Generator().manual_seed(0)
    feats = torch.rand(means.shape[0], cfg.channels, generator=g)
    cuda = cfg.backend == "cuda"
    if cuda:
        means, quats, scales, opac, feats = (t.cuda() for t in (means, quats, scales, opac, feats))
    base_rss = rss_gb()

    def once():
        if cfg.backend == "reference+grad":
            with torch.enable_grad():
                leaves = [t.clone().requires_grad_(True) for t in (means, scales, feats)]
                out = rasterize(leaves[0], quats, leaves[1], opac, leaves[2], cam, backend="reference")
                out.image.sum().backward()
            return out
        out = rasterize(means, quats, scales, opac, feats, cam, backend=cfg.backend.split("+")[0])
        if cuda:
            torch.cuda.synchronize()
        return out

    t0 = time.perf_counter()
    out = once()  # warm-up: compiles kernels, fills caches
    warm = time.perf_counter() - t0
    times = []
    for _ in range(cfg.runs):
        t0 = time.perf_counter()
        out = once()
        times.append(time.perf_counter() - t0)
    peak_rss = _peak_rss_gb()
    gpu_peak = torch.cuda.max_memory_allocated() / 1e9 if cuda else None
    image = out.image.detach().cpu().double()
    truth = rasterize(
        means.cpu(), quats.cpu(), scales.cpu(), opac.cpu(), feats.cpu().double(), cam, backend="cpu"
    ).image
    err = float((image - truth).abs().max() / truth.abs().max())
    med = statistics.median(times) if times else warm
    return {
        **asdict(cfg),
        "gaussians": int(means.shape[0]),
        "median_s": med,
        "min_s": min(times) if times else warm,
        "fps": 1.0 / med,
        "warmup_s": warm,
        "peak_rss_gb": peak_rss,
        "render_rss_gb": peak_rss - base_rss,
        "gpu_peak_gb": gpu_peak,
        "max_rel_err_vs_f64": err,
        "alpha_mean": float(out.alpha.detach().double().mean()),
        "contrib_per_pixel": float(np.asarray(out.n_contrib.cpu()).sum()) / (cfg.width * cfg.height)
        if out.n_contrib is not None
        else None,
    }


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6  # KiB on Linux


def configs(quick: bool, with_cuda: bool) -> list[Config]:
    if quick:
        return [
            Config("garden", 240, 135, 5, "cpu", 3),
            Config("garden", 240, 135, 3, "reference", 1),
            Config("garden", 240, 135, 3, "reference+grad", 1),
        ]
    out = []
    for scene in ("garden", "synthetic-1000000"):
        for w, h in ((480, 270), (648, 420)):
            for d in (3, 5, 32, 512):
                out.append(Config(scene, w, h, d, "cpu", 7 if d < 512 else 3))
                if with_cuda:
                    out.append(Config(scene, w, h, d, "cuda", 20))
    for scene in ("garden", "synthetic-200000", "synthetic-1000000"):
        for d in (3, 5, 32, 512):
            out.append(Config(scene, 480, 270, d, "reference", 1))
    for d in (3, 32, 512):
        out.append(Config("garden", 480, 270, d, "reference+grad", 1))
    for o in (0.1, 0.5, 0.8):  # how the CPU path depends on how soon pixels saturate
        out.append(Config("garden", 480, 270, 5, "cpu", 7, opacity=o))
    return out


def summary(results: list[dict], info: dict) -> list[str]:
    """The issue's targets, read off the measured rows."""
    ok = [r for r in results if "error" not in r]
    out = ["", "## Targets", ""]
    garden5 = [
        r
        for r in ok
        if r["scene"] == "garden"
        and r["backend"] == "cpu"
        and r["channels"] == 5
        and (r["width"], r["height"]) == (480, 270)
    ]
    for r in sorted(garden5, key=lambda r: r["opacity"]):
        verdict = "meets" if r["fps"] >= 10 else "misses"
        out.append(
            f"- CPU fast path, garden, 480x270, 5 channels, opacity {r['opacity']}: **{r['fps']:.1f} FPS** "
            f"({verdict} the 10 FPS target; {r['contrib_per_pixel']:.0f} blended Gaussians per pixel)."
        )
    ref512 = [r for r in ok if r["backend"].startswith("reference") and r["channels"] == 512]
    if ref512:
        worst = max(ref512, key=lambda r: r["peak_rss_gb"])
        verdict = "within" if worst["peak_rss_gb"] <= 8 else "over"
        out.append(
            f"- Reference path, 512 channels: largest process peak {worst['peak_rss_gb']:.2f} GB "
            f"({worst['scene']}, {worst['width']}x{worst['height']}, {worst['backend']}), {verdict} 8 GB."
        )
    if ok:
        e = max(ok, key=lambda r: r["max_rel_err_vs_f64"])
        out.append(
            f"- Largest error against float64 over all rows: {e['max_rel_err_vs_f64']:.1e} "
            f"({e['backend']}, {e['scene']}, D={e['channels']}); the agreement tests bound it by 1e-5."
        )
    if not info.get("gpu"):
        out.append("- GPU (gsplat) columns: not measured; this run had no GPU.")
    return out


def write_report(results: list[dict], info: dict, path: Path, quick: bool) -> None:
    def mem(r):
        return f"{r['gpu_peak_gb']:.2f} (GPU)" if r["gpu_peak_gb"] is not None else f"{r['peak_rss_gb']:.2f}"

    lines = [
        "# Rasteriser benchmark" + (" (quick)" if quick else ""),
        "",
        f"Measured {info['date']} on {info['cpu']} ({info['cores']} cores, {info['ram_gb']} GiB RAM"
        + (f", GPU {info['gpu']}" if info["gpu"] else ", no GPU")
        + f"); Python {info['python']}, torch {info['torch']}, numba {info['numba']}, numpy {info['numpy']}, "
        f"commit {info['commit']}.",
        "",
        "Regenerate: `python -m benchmarks.raster` (about 15 minutes on 2 cores); "
        "`--from-json benchmarks/results/RASTER.json` rewrites this file from the stored figures.",
        "",
        "- **FPS**: 1 / median wall time of the timed runs after a warm-up run (compilation excluded; "
        "its time is in RASTER.json). Features float32, no gradients unless the backend says +grad "
        "(then forward plus backward of sum(image)).",
        "- **peak GB**: peak resident memory of the whole measuring process (Python, torch, the scene and "
        "its features included); **render GB**: that peak minus the resident size just before rendering.",
        "- **rel err**: max |image - truth| / max |truth|, truth = the same render with float64 features "
        "on the CPU backend (float64 geometry and weights; checked against the brute-force renderer in "
        "the test suite).",
        "- garden: gsplat's test_garden points (138,766), isotropic scales = mean distance to the 3 nearest "
        "neighbours, opacity 0.8 unless stated, view 0; 480x270 is the 648x420 view resized to width 480 "
        "and centre-cropped. synthetic-N: N anisotropic Gaussians in a box in front of the camera.",
        "",
    ]
    lines += summary(results, info)
    lines += [
        "",
        "## All configurations",
        "",
        "| scene | N | size | D | backend | opacity | runs | FPS | median s | peak GB | render GB | rel err "
        "| contrib/px |",
        "|---|---:|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        if "error" in r:
            lines.append(
                f"| {r['scene']} | | {r['width']}x{r['height']} | {r['channels']} | {r['backend']} | "
                f"| | failed: {r['error']} | | | | | |"
            )
            continue
        cpp = f"{r['contrib_per_pixel']:.1f}" if r["contrib_per_pixel"] is not None else "-"
        opac = f"{r['opacity']}" if r["scene"] == "garden" else "U(0.1,0.9)"
        lines.append(
            f"| {r['scene']} | {r['gaussians']:,} | {r['width']}x{r['height']} | {r['channels']} "
            f"| {r['backend']} | {opac} | {r['runs']} | {r['fps']:.2f} | {r['median_s']:.3f} | {mem(r)} | "
            f"{r['render_rss_gb']:.2f} | {r['max_rel_err_vs_f64']:.1e} | {cpp} |"
        )
    path.write_text("\n".join(lines) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="CI-sized run")
    ap.add_argument("--out", type=Path, help="markdown report path")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # internal: measure one JSON config and print JSON
    ap.add_argument("--timeout", type=float, default=1800, help="seconds allowed per configuration")
    ap.add_argument("--from-json", type=Path, help="rewrite the markdown from a stored RASTER.json")
    args = ap.parse_args()
    if args.from_json:
        stored = json.loads(args.from_json.read_text())
        out = args.out or args.from_json.with_suffix(".md")
        write_report(stored["results"], stored["machine"], out, quick=False)
        print(f"wrote {out}")
        return 0
    if args.one:
        print(json.dumps(run_one(Config(**json.loads(args.one)))))
        return 0
    import torch

    out = args.out or (
        ROOT / "benchmarks" / "out" / "RASTER-quick.md" if args.quick else RESULTS / "RASTER.md"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    results = []
    for cfg in configs(args.quick, torch.cuda.is_available()):
        cmd = [sys.executable, "-m", "benchmarks.raster", "--one", json.dumps(asdict(cfg))]
        try:
            p = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout, cwd=ROOT)
            r = (
                json.loads(p.stdout.strip().splitlines()[-1])
                if p.returncode == 0
                else {**asdict(cfg), "error": (p.stderr.strip().splitlines() or ["?"])[-1][:120]}
            )
        except subprocess.TimeoutExpired:
            r = {**asdict(cfg), "error": f"timed out after {args.timeout:.0f} s"}
        results.append(r)
        shown = (
            f"{r['fps']:.2f} FPS, {r['peak_rss_gb']:.2f} GB, err {r['max_rel_err_vs_f64']:.1e}"
            if "fps" in r
            else r["error"]
        )
        print(
            f"{cfg.scene:>18} {cfg.width}x{cfg.height} D={cfg.channels:<3} {cfg.backend:<14} "
            f"o={cfg.opacity}: {shown}",
            flush=True,
        )
    info = machine()
    out.with_suffix(".json").write_text(json.dumps({"machine": info, "results": results}, indent=1))
    write_report(results, info, out, args.quick)
    print(f"wrote {out}")
    return 0 if all("error" not in r for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
