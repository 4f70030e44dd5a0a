"""The inspector on a 1M-Gaussian scene: geometry fetch time, frame time while orbiting, memory.

    python -m benchmarks.viewer --out OUT [--gaussians 1000000] [--report]

Makes a synthetic scene of N Gaussians (benchmarks.scenes.synthetic, embeddings that vary smoothly with
position), serves it with the real server on loopback (a table text encoder: embedding cost is not what
is measured), and opens ``fmgs_client.viewer.Inspector`` under ``xvfb-run`` (Mesa's llvmpipe: a software
renderer, so frame times are an upper bound for a machine with a GPU), once per point cap (50,000, the
default 200,000 and every Gaussian). Each run measures: the Geometry call alone (median of 3), the time from
opening the scene to its points drawn, the frame time (one event-loop tick that draws a moved camera;
median and 95th percentile over 60 frames of an orbit), a text query answered and drawn, and the viewer
process's resident memory. Writes viewer.json and VIEWER.md (with --report, also VIEWER.json and VIEWER.md in
benchmarks/results/).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import ROOT, machine, machine_words, save_report

SCENE = "big"
CAPS = (50_000, 200_000, None)
"""Point caps measured: a quarter of the default, the viewer's default (ViewerConfig.max_points) and none
(every Gaussian)."""


def make_scene(models: Path, n: int) -> None:
    from benchmarks.common import canonical_vectors, export, fieldlike, gaussians_from
    from benchmarks.scenes import synthetic

    if (models / SCENE / "manifest.json").is_file():
        return
    s = synthetic(n)
    export(models / SCENE, gaussians_from(s), fieldlike(s.means), canonical_vectors())


def child(address: str, max_points: int, out: Path) -> int:
    """Under a display: open the scene in the inspector and measure (one process per cap: Open3D's
    application starts once per process)."""
    import open3d as o3d
    import psutil

    from fmgs_client.client import FmgsClient
    from fmgs_client.viewer import Inspector
    from fmgs_client.viewer_model import ViewerConfig

    proc = psutil.Process()
    rss0 = proc.memory_info().rss
    client = FmgsClient(address, timeout=300)
    fetch = []
    for _ in range(3):
        t0 = time.perf_counter()
        g = client.geometry(SCENE, max_points, 0.1)
        fetch.append(time.perf_counter() - t0)
    n_drawn, n_total = len(g), g.num_gaussians
    del g
    app = o3d.visualization.gui.Application.instance
    app.initialize()
    cfg = ViewerConfig(max_points=max_points)
    t0 = time.perf_counter()
    insp = Inspector(client, address, SCENE, cfg, size=(1280, 800), out_dir=out)
    while insp.geometry is None or not insp.idle:
        app.run_one_tick()
    app.run_one_tick()
    open_s = time.perf_counter() - t0
    rss_open = proc.memory_info().rss
    lo, hi = insp.geometry.bounds[:3], insp.geometry.bounds[3:]
    centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    frames = []
    for k in range(60):
        a = 2 * np.pi * k / 60
        eye = centre + 2.2 * radius * np.array([np.cos(a), np.sin(a), 0.6])
        insp.view.look_at(centre, eye, np.array([0.0, 0.0, 1.0]))
        t = time.perf_counter()
        app.run_one_tick()
        frames.append(time.perf_counter() - t)
    t0 = time.perf_counter()
    insp.on_query("q0")
    while insp.idle is False or not insp.answers:
        app.run_one_tick()
    app.run_one_tick()
    query_s = time.perf_counter() - t0
    rss_end = proc.memory_info().rss
    # A frame certainly drawn: render_to_image's callback comes with the frame's pixels read back.
    drawn = []
    for k in range(20):
        a = 2 * np.pi * k / 20 + 0.1
        eye = centre + 2.2 * radius * np.array([np.cos(a), np.sin(a), 0.6])
        insp.view.look_at(centre, eye, np.array([0.0, 0.0, 1.0]))
        got: list = []
        t = time.perf_counter()
        insp.view.scene.scene.render_to_image(got.append)
        insp.window.post_redraw()
        while not got:
            app.run_one_tick()
        drawn.append(time.perf_counter() - t)
    res = {
        "max_points": max_points,
        "drawn": n_drawn,
        "gaussians": n_total,
        "geometry_call_s": fetch,
        "open_to_drawn_s": open_s,
        "frame_ms": [f * 1e3 for f in frames],
        "frame_readback_ms": [f * 1e3 for f in drawn],
        "query_to_drawn_s": query_s,
        "answer": len(insp.answers[0].answer),
        "rss_start_mb": rss0 / 2**20,
        "rss_open_mb": rss_open / 2**20,
        "rss_end_mb": rss_end / 2**20,
    }
    (out / f"viewer-{max_points}.json").write_text(json.dumps(res))
    if insp.feed is not None:
        insp.feed.close()
    sys.stdout.flush()
    os._exit(0)  # Open3D's teardown can hang at exit; the results are written


def report(rows: list[dict], info: dict, cmd: str, n: int) -> str:
    lines = [
        "# The inspector on a large scene",
        "",
        f"Measured {info['date']} on {machine_words(info)}, `{cmd}`: a synthetic scene of {n:,} Gaussians "
        "served on loopback by the real server, the inspector (`fmgs-client view`) under `xvfb-run` with "
        "Mesa's llvmpipe (software rendering on the CPU: a machine with a GPU draws faster), 1280x800 "
        "window. Tick: one event-loop tick after the camera moved (60 frames of an orbit; what an orbit "
        "feels like, though the renderer may still be drawing when it returns). Frame read back: the camera "
        "moved, then Open3D's render_to_image until its callback has the frame's pixels (20 frames; an "
        "upper bound on drawing one frame). Memory: the viewer process's resident set (Open3D, the client, "
        "the points) after the orbit and the query, before the read-back frames.",
        "",
        "| points drawn | Geometry call (median of 3) | open to drawn | tick median | tick p95 "
        "| frame read back (median, p95) | query to drawn | viewer RSS |",
        "|---|---|---|---|---|---|---|---|",
    ]
    from fmgs_client.viewer_model import ViewerConfig

    default = ViewerConfig().max_points
    for r in rows:
        f, rb = np.asarray(r["frame_ms"]), np.asarray(r["frame_readback_ms"])
        sampled = r["max_points"] < r["gaussians"]
        which = " (the default cap)" if r["max_points"] == default else "" if sampled else " (all)"
        cap = f"{r['drawn']:,} of {r['gaussians']:,}{which}"
        lines.append(
            f"| {cap} | {np.median(r['geometry_call_s']):.2f} s | {r['open_to_drawn_s']:.2f} s | "
            f"{np.median(f):.0f} ms | {np.percentile(f, 95):.0f} ms | {np.median(rb):.0f} ms, "
            f"{np.percentile(rb, 95):.0f} ms | {r['query_to_drawn_s']:.2f} s "
            f"({r['answer']:,} Gaussians) | {r['rss_end_mb']:.0f} MiB |"
        )
    lines += [
        "",
        "The cap is the viewer's `--max-points`: the server samples the Gaussians above `--min-opacity` "
        "uniformly with a fixed seed (the `Geometry` call), so the points keep the scene's density and the "
        "same view of the same scene draws the same points. Query answers are drawn in full over them.",
        "",
    ]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--gaussians", type=int, default=1_000_000)
    ap.add_argument("--report", action="store_true", help="also write benchmarks/results/VIEWER.md")
    ap.add_argument("--child", nargs=2, metavar=("ADDRESS", "MAX_POINTS"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    if a.child:
        return child(a.child[0], int(a.child[1]), a.out)
    xvfb = shutil.which("xvfb-run")
    if xvfb is None:
        raise SystemExit("needs xvfb-run (Debian: xvfb xauth)")
    from benchmarks.common import TableEncoder, canonical_vectors, make_queries
    from fmgs.scene.package import load_scene
    from fmgs_server.config import ServerConfig
    from fmgs_server.server import start_server

    models = a.out / "models"
    make_scene(models, a.gaussians)
    pkg = load_scene(models / SCENE)
    enc = TableEncoder(make_queries(pkg.embeddings.float(), 1), canonical_vectors())
    del pkg
    srv = start_server(
        ServerConfig(models=models, port=0, preload=True, max_geometry=max(2_000_000, a.gaussians)),
        encoder_factory=lambda i: enc,
    )
    rows = []
    try:
        for cap in CAPS:
            mp = a.gaussians if cap is None else cap
            cmd = [xvfb, "-a", "-s", "-screen 0 1280x800x24", sys.executable, "-m", "benchmarks.viewer"]
            p = subprocess.run(
                [*cmd, "--out", str(a.out), "--child", srv.address, str(mp)],
                cwd=ROOT, capture_output=True, text=True, timeout=1800,
            )  # fmt: skip
            if p.returncode != 0:
                raise SystemExit(p.stdout[-2000:] + p.stderr[-2000:])
            rows.append(json.loads((a.out / f"viewer-{mp}.json").read_text()))
    finally:
        srv.stop(0)
    info = {**machine(), "date": time.strftime("%Y-%m-%d")}
    cmd = "python -m benchmarks.viewer " + " ".join(sys.argv[1:])
    record = json.dumps({"rows": rows, "machine": info, "command": cmd}, indent=1)
    (a.out / "viewer.json").write_text(record)
    if a.report:
        (ROOT / "benchmarks" / "results" / "VIEWER.json").write_text(record)
    text = report(rows, info, cmd, a.gaussians)
    save_report(text, a.out, "VIEWER.md", a.report)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
