"""``fmgs-client``: the command line of the thin client (list, info, query, render, stream, segment, health).

Failures print ``error: CODE: details`` to stderr and exit with status 1.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from fmgs_client.client import DEFAULT_ADDRESS, FmgsClient, FmgsError
from fmgs_client.jsonout import emit
from fmgs_client.ply import write_ply
from fmgs_client.retry import MAX_ATTEMPTS, RetryPolicy
from fmgs_client.types import CameraSpec, SceneInfo, TextAnswer
from fmgs_client.viewer_model import ViewerConfig
from fmgs_wire.images import colorize, depth_to_uint16, label_colors, relevancy_png, to_uint8, write_png
from fmgs_wire.tokens import read_token_file


def _size(s: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in s.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WxH, e.g. 640x480, got {s!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {s!r}")
    return w, h


def _count(s: str) -> int:
    try:
        n = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {s!r}") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {n}")
    return n


def _table(rows: Sequence[Sequence[object]], header: Sequence[str]) -> str:
    """Plain-text table: columns padded to their widest cell, numbers right-aligned."""
    cells = [[str(h) for h in header]] + [[_fmt(v) for v in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    numeric = [all(isinstance(r[i], int | float | np.number) for r in rows) for i in range(len(header))]
    lines = []
    for r in cells:
        lines.append(
            "  ".join(c.rjust(w) if num else c.ljust(w) for c, w, num in zip(r, widths, numeric, strict=True))
        )
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(line.rstrip() for line in lines)


def _fmt(v: object) -> str:
    if isinstance(v, float | np.floating):
        return f"{v:.4f}"
    return str(v)


def _vec(v: np.ndarray) -> str:
    return " ".join(f"{x:.3f}" for x in v)


# ---------------------------------------------------------------- cameras


def default_camera(info: SceneInfo, up: Sequence[float], size: tuple[int, int], fov: float) -> CameraSpec:
    """Look at the centre of the scene's bounds from outside them (up-tilted diagonal view)."""
    if info.bounds is None:
        raise ValueError(f"scene {info.name!r} reports no bounds: give --eye and --target")
    return orbit(info, 1, up, size, fov)[0]


def orbit(
    info: SceneInfo, n: int, up: Sequence[float], size: tuple[int, int], fov: float, turns: float = 1.0
) -> list[CameraSpec]:
    """``n`` cameras on a circle around the bounds' centre, raised along ``up``, all looking at the centre.

    The radius keeps the whole bounding sphere inside the horizontal field of view.
    """
    if info.bounds is None:
        raise ValueError(f"scene {info.name!r} reports no bounds")
    if not 0 < fov < 180:
        raise ValueError(f"--fov: the field of view must lie between 0 and 180 degrees, got {fov}")
    u = np.asarray(up, np.float64)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or not u.any():
        raise ValueError(f"--up: must be a finite non-zero vector, got {u.tolist()}")
    lo, hi = info.bounds
    centre = (lo + hi) / 2
    half_diag = max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
    dist = 1.1 * half_diag / math.sin(math.radians(min(fov, 170.0)) / 2)
    u = u / np.linalg.norm(u)
    # Two axes perpendicular to up span the orbit's plane.
    a = np.cross(u, np.eye(3)[np.argmin(np.abs(u))])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    elev = math.radians(30.0)
    cams = []
    for k in range(n):
        ang = 2 * math.pi * turns * k / max(n, 1)
        d = math.cos(elev) * (math.cos(ang) * a + math.sin(ang) * b) + math.sin(elev) * u
        cams.append(CameraSpec.look_at(centre + dist * d, centre, u, size[0], size[1], fov))
    return cams


def scene_with_bounds(client: FmgsClient, name: str) -> SceneInfo:
    """The scene's info with its bounds. The server knows a scene's bounds once it is loaded and loads
    scenes lazily on their first query, so an unloaded scene is touched with a one-Gaussian query."""
    info = client.scene(name)
    if info.bounds is None and info.state in ("unloaded", "loading"):
        client.query(name, "object", top_k=1)
        info = client.scene(name)
    return info


def _camera(args: argparse.Namespace, client: FmgsClient) -> CameraSpec:
    if args.camera is not None:
        try:
            return CameraSpec.from_dict(json.loads(args.camera.read_text()))
        except json.JSONDecodeError as e:
            raise ValueError(f"{args.camera}: not JSON ({e})") from None
        except ValueError as e:
            raise ValueError(f"{args.camera}: {e}") from None
    if args.eye is None:
        return default_camera(scene_with_bounds(client, args.scene), args.up, args.size, args.fov)
    if args.target is None:
        raise ValueError("--eye needs --target")
    return CameraSpec.look_at(args.eye, args.target, args.up, args.size[0], args.size[1], args.fov)


# ---------------------------------------------------------------- commands


def cmd_list(client: FmgsClient, args: argparse.Namespace) -> int:
    scenes = client.list_scenes()
    if args.json:
        emit({"scenes": scenes})
        return 0
    if not scenes:
        print("no scenes")
        return 0
    rows = [
        (s.name, s.state, s.num_gaussians, s.num_embedded, s.encoder_id, s.version, s.reason) for s in scenes
    ]
    print(_table(rows, ("scene", "state", "gaussians", "embedded", "encoder", "version", "reason")))
    return 0


def cmd_info(client: FmgsClient, args: argparse.Namespace) -> int:
    s = client.scene(args.scene)
    if args.json:
        emit(s)
        return 0
    items = [
        ("name", s.name),
        ("state", s.state + (f" ({s.reason})" if s.reason else "")),
        ("version", s.version),
        ("encoder", f"{s.encoder_id} ({s.embedding_dim}-D)"),
        ("gaussians", f"{s.num_gaussians} ({s.num_embedded} embedded)"),
        ("sh degree", s.sh_degree),
        ("feature field", "yes" if s.has_field else "no"),
        ("canonical phrases", ", ".join(s.canonical_phrases)),
        ("label names", ", ".join(s.label_names) or "-"),
        ("resident", f"{s.resident_bytes / 2**20:.1f} MiB"),
        (
            "bounds",
            "(once loaded)" if s.bounds is None else f"min {_vec(s.bounds[0])}  max {_vec(s.bounds[1])}",
        ),
        ("frame", f"{s.frame_id} (metres)" if s.frame_id else "the scene's own"),
    ]
    width = max(len(k) for k, _ in items)
    for k, v in items:
        print(f"{k.ljust(width)}  {v}")
    return 0


def _print_answer(a: TextAnswer, rows: int) -> None:
    print(f"{a.text!r}: {len(a)} Gaussians, {a.elapsed_ms:.1f} ms")
    p = a.presence
    if p is not None:
        verdict = "found" if p.found else f"NOT FOUND (the scene has {p.rival!r} there)"
        print(f"presence {p.score:.3f}: {verdict}")
    n = min(rows, len(a))
    if n:
        table = []
        for r in range(n):
            row: list[object] = [r + 1, int(a.index[r]), float(a.relevancy[r])]
            row.append(float(a.similarity[r]) if a.similarity is not None else "")
            row += [_vec(a.mean[r]) if a.mean is not None else ""]
            if a.instance is not None:
                row.append(int(a.instance[r]))
            table.append(row)
        header = ["rank", "gaussian", "relevancy", "similarity", "mean x y z"]
        if a.instance is not None:
            header.append("instance")
        print(_table(table, header))
        if n < len(a):
            print(f"... {len(a) - n} more")
    if a.instances:
        print(f"{len(a.instances)} instances:")
        rows_i = [
            (i.id, i.score, i.num_members, _vec(i.centroid), _vec(i.aabb.extent), _vec(i.obb.extent))
            for i in a.instances
        ]
        print(_table(rows_i, ("id", "score", "members", "centroid", "aabb extent", "obb extent")))


def cmd_query(client: FmgsClient, args: argparse.Namespace) -> int:
    fields = ["similarity", "mean"]
    answers = client.query(
        args.scene,
        args.texts,
        top_k=args.top_k,
        threshold=args.threshold,
        fields=fields,
        instances=args.instances,
    )
    for k, a in enumerate(answers):
        if args.json:
            emit(a)  # one object per text: indices, relevancy, similarity, means, presence, instances
            continue
        if k:
            print()
        _print_answer(a, args.rows)
    if args.ply is not None:
        for k, a in enumerate(answers):
            out = (
                args.ply if len(answers) == 1 else args.ply.with_name(f"{args.ply.stem}-{k}{args.ply.suffix}")
            )
            scalars = {"relevancy": a.relevancy, "gaussian": a.index}
            if a.similarity is not None:
                scalars["similarity"] = a.similarity
            if a.instance is not None:
                scalars["instance"] = a.instance
            write_ply(out, a.mean, colorize(a.relevancy), scalars)
            if not args.json:
                print(f"wrote {out} ({len(a)} points, {a.text!r})")
    return 0


def cmd_render(client: FmgsClient, args: argparse.Namespace) -> int:
    cam = _camera(args, client)
    outputs = ["relevancy", "alpha"] + ["rgb"] * (args.rgb is not None) + ["depth"] * (args.depth is not None)
    t0 = time.perf_counter()
    r = client.render(args.scene, cam, args.text, outputs=outputs)
    wall = (time.perf_counter() - t0) * 1e3
    colours = colorize(r.relevancy).astype(np.float32)
    if not args.raw and r.alpha is not None:
        # Empty pixels have no feature and a meaningless relevancy (0.5): fade them to black.
        colours *= np.clip(r.alpha, 0, 1)[..., None]
    write_png(args.out, np.round(colours).astype(np.uint8))
    written = {"relevancy": str(args.out)}
    if args.rgb is not None and r.rgb is not None:
        write_png(args.rgb, to_uint8(r.rgb))
        written["rgb"] = str(args.rgb)
    if args.depth is not None and r.depth is not None:
        write_png(args.depth, depth_to_uint16(r.depth))
        written["depth"] = str(args.depth)
    if args.json:
        emit({"text": args.text, "width": r.width, "height": r.height, "argmax": r.argmax, "files": written,
              "camera": cam.to_dict(), "elapsed_ms": r.elapsed_ms, "round_trip_ms": wall})  # fmt: skip
        return 0
    for kind, path in written.items():
        print(f"wrote {path}" + (f" ({r.width}x{r.height})" if kind == "relevancy" else ""))
    if r.argmax is not None:
        print(f"argmax pixel x={r.argmax.x} y={r.argmax.y} relevancy={r.argmax.value:.4f}")
    print(f"server {r.elapsed_ms:.1f} ms, round trip {wall:.1f} ms")
    return 0


def paced(
    cams: Sequence[CameraSpec], window: threading.Semaphore, stop: threading.Event
) -> Iterator[CameraSpec]:
    """Yield cameras only while fewer than the window's size are unanswered (a closed loop): sending
    every pose at once would just make the server skip to the newest one."""
    for cam in cams:
        while not window.acquire(timeout=0.2):
            if stop.is_set():
                return
        yield cam


def cmd_stream(client: FmgsClient, args: argparse.Namespace) -> int:
    info = scene_with_bounds(client, args.scene)
    cams = orbit(info, args.frames, args.up, args.size, args.fov)
    if args.out_dir is not None:
        args.out_dir.mkdir(parents=True, exist_ok=True)
    window, stop = threading.Semaphore(max(1, args.in_flight)), threading.Event()
    n, server_ms, done = 0, 0.0, -1
    t0 = time.perf_counter()
    try:
        for r in client.stream(args.scene, paced(cams, window, stop), args.text, encoding=args.encoding):
            # An answer settles its pose and every older one (skipped by latest-pose-wins).
            window.release(max(0, r.sequence - done))
            done = max(done, r.sequence)
            n += 1
            server_ms += r.elapsed_ms
            if args.out_dir is not None and r.relevancy is not None:
                relevancy_png(args.out_dir / f"frame_{r.sequence:05d}.png", r.relevancy)
    finally:
        stop.set()
    wall = time.perf_counter() - t0
    fps = n / wall if wall > 0 else float("inf")
    w, h = args.size
    if args.json:
        per_frame = server_ms / n if n else None
        emit({"poses": len(cams), "rendered": n, "seconds": wall, "frames_per_s": fps, "width": w,
              "height": h, "server_ms_per_frame": per_frame})  # fmt: skip
        return 0
    print(f"{n} of {len(cams)} poses rendered in {wall:.2f} s: {fps:.1f} frames/s at {w}x{h}")
    if n:
        print(f"server {server_ms / n:.1f} ms per frame")
    return 0


def cmd_segment(client: FmgsClient, args: argparse.Namespace) -> int:
    wants = args.eye is not None or args.out is not None or args.camera is not None
    cam = _camera(args, client) if wants else None
    r = client.segment(args.scene, args.names, camera=cam, per_gaussian=True)
    image = args.out if args.out is not None and r.pixel_labels is not None else None
    if image is not None:
        write_png(image, label_colors(r.pixel_labels))
    counts = r.counts()
    if args.json:
        classes = [
            {"label": k, "name": name, "gaussians": g, "pixels": p}
            for k, (name, (g, p)) in enumerate(zip(r.class_names, counts, strict=True))
        ]
        emit({"classes": classes, "gaussian_index": r.gaussian_index, "gaussian_labels": r.gaussian_labels,
              "image": str(image) if image is not None else None, "elapsed_ms": r.elapsed_ms})  # fmt: skip
        return 0
    print(f"segmented in {r.elapsed_ms:.1f} ms")
    rows = []
    for k, (name, (g, p)) in enumerate(zip(r.class_names, counts, strict=True)):
        colour = "#" + bytes(label_colors(np.array([k]))[0]).hex() if r.pixel_labels is not None else ""
        rows.append((k, name, g, p, colour))
    print(_table(rows, ("label", "class", "gaussians", "pixels", "colour")))
    if image is not None:
        print(f"wrote {image}")
    return 0


def cmd_view(client: FmgsClient, args: argparse.Namespace) -> int:
    from fmgs_client.viewer import run

    cfg = ViewerConfig(
        max_points=args.max_points,
        min_opacity=args.min_opacity,
        top_k=args.top_k,
        threshold=args.threshold,
        picture_side=args.picture_side,
    )
    args.out_dir.mkdir(parents=True, exist_ok=True)
    return run(args.address, args.scene, client, cfg, args.out_dir)


def cmd_health(client: FmgsClient, args: argparse.Namespace) -> int:
    status = client.health(args.service)
    if args.json:
        emit({"service": args.service, "status": status})
    else:
        print(status)
    return 0 if status == "SERVING" else 1


# ---------------------------------------------------------------- parser


def _camera_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--camera", type=Path,
        help="camera JSON (viewmat, fx, fy, cx, cy, width, height; what `view` exports and `render --json` "
        "prints); overrides --eye/--target/--size/--fov (default: none)",
    )  # fmt: skip
    p.add_argument(
        "--eye", type=float, nargs=3, metavar=("X", "Y", "Z"),
        help="camera position (default: outside the scene's bounds, looking at their centre)",
    )  # fmt: skip
    p.add_argument(
        "--target",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="point looked at, with --eye (default: none)",
    )
    _view_options(p)


def _view_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--up", type=float, nargs=3, default=(0.0, 0.0, 1.0), metavar=("X", "Y", "Z"),
        help="the world direction that points up in the image (default 0 0 1)",
    )  # fmt: skip
    p.add_argument(
        "--size", type=_size, default=(640, 480), help="image size WxH in pixels (default 640x480)"
    )
    p.add_argument("--fov", type=float, default=60.0, help="horizontal field of view in degrees (default 60)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="fmgs-client", description="Query an FMGS server.")
    ap.add_argument(
        "--address", default=DEFAULT_ADDRESS, help=f"server host:port (default {DEFAULT_ADDRESS})"
    )
    ap.add_argument(
        "--token-file",
        type=Path,
        help="file holding the bearer token (the first line that is not blank or #; default: no token)",
    )
    ap.add_argument("--root-cert", type=Path, help="CA certificate (PEM): use TLS (default: plaintext)")
    ap.add_argument(
        "--client-cert", type=Path, help="client certificate (PEM) for mutual TLS (default: none)"
    )
    ap.add_argument("--client-key", type=Path, help="client private key (PEM) for mutual TLS (default: none)")
    ap.add_argument("--timeout", type=float, default=30.0, help="seconds per call; 0: none (default 30)")
    ap.add_argument(
        "--attempts",
        type=int,
        default=RetryPolicy.attempts,
        help=f"tries of a read that fails with UNAVAILABLE, by gRPC's retry policy (1: none; at most "
        f"{MAX_ATTEMPTS}; default {RetryPolicy.attempts})",
    )
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--json", action="store_true",
        help="print each answer as one JSON object per line instead of tables (default: tables)",
    )  # fmt: skip
    sub = ap.add_subparsers(dest="command", required=True)

    def command(name: str, help: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help, description=help, parents=[common])

    p = command("list", "list the server's scenes")
    p.set_defaults(fn=cmd_list)

    p = command("info", "one scene's metadata")
    p.add_argument("scene", help="scene name")
    p.set_defaults(fn=cmd_info)

    p = command("query", "Gaussians most relevant to each text")
    p.add_argument("scene", help="scene name")
    p.add_argument("texts", nargs="+", metavar="TEXT", help="one or more texts, each answered on its own")
    p.add_argument(
        "--top-k", type=int, default=100, help="Gaussians returned per text, best first (default 100)"
    )
    p.add_argument(
        "--threshold", type=float, default=0.0,
        help="only Gaussians with relevancy at least this, in [0, 1]; 0: the top-k regardless (default 0)",
    )  # fmt: skip
    p.add_argument(
        "--instances", action="store_true", help="group the Gaussians into object instances (default: off)"
    )
    p.add_argument("--rows", type=_count, default=10, help="table rows to print per text (default 10)")
    p.add_argument(
        "--ply",
        type=Path,
        help="write the Gaussians coloured by relevancy, one file per text (default: none)",
    )
    p.set_defaults(fn=cmd_query)

    p = command("render", "relevancy image of one view")
    p.add_argument("scene", help="scene name")
    p.add_argument("text", help="the query whose relevancy is rendered")
    _camera_options(p)
    p.add_argument("--out", type=Path, required=True, help="relevancy PNG (colour-mapped, faded by alpha)")
    p.add_argument(
        "--raw",
        action="store_true",
        help="do not fade empty pixels: colours of relevancy only (default: off)",
    )
    p.add_argument("--rgb", type=Path, help="also write the colour image here (default: none)")
    p.add_argument(
        "--depth", type=Path, help="also write depth here, 16-bit PNG in millimetres (default: none)"
    )
    p.set_defaults(fn=cmd_render)

    p = command("stream", "stream an orbit of poses; report frames per second")
    p.add_argument("scene", help="scene name")
    p.add_argument("text", help="the query whose relevancy is rendered")
    p.add_argument("--frames", type=int, default=60, help="poses on the orbit (default 60)")
    _view_options(p)
    p.add_argument(
        "--encoding", choices=("float32", "png"), default="float32",
        help="how frames travel: float32 arrays or PNG (default float32)",
    )  # fmt: skip
    p.add_argument("--in-flight", type=int, default=1, help="poses sent ahead of their answers (default 1)")
    p.add_argument(
        "--out-dir", type=Path, help="write each received frame's relevancy PNG here (default: none)"
    )
    p.set_defaults(fn=cmd_stream)

    p = command("segment", "label Gaussians (and a view's pixels) with class names")
    p.add_argument("scene", help="scene name")
    p.add_argument("names", nargs="+", metavar="NAME", help="class names")
    _camera_options(p)
    p.add_argument("--out", type=Path, help="label image PNG, a colour per class (default: none)")
    p.set_defaults(fn=cmd_segment)

    p = command("view", "open the inspector window (Open3D; needs a display)")
    p.add_argument("scene", nargs="?", help="scene to open (default: the first the server lists)")
    d = ViewerConfig()
    p.add_argument(
        "--max-points", type=int, default=d.max_points,
        help=f"most Gaussians drawn: a uniform sample above the opacity floor (default {d.max_points})",
    )  # fmt: skip
    p.add_argument(
        "--min-opacity", type=float, default=d.min_opacity,
        help=f"Gaussians fainter than this are not drawn (default {d.min_opacity})",
    )  # fmt: skip
    p.add_argument("--top-k", type=int, default=d.top_k, help=f"Gaussians per phrase (default {d.top_k})")
    p.add_argument(
        "--threshold", type=float, default=d.threshold,
        help=f"only Gaussians with relevancy at least this; 0: the top-k regardless (default {d.threshold})",
    )  # fmt: skip
    p.add_argument(
        "--picture-side", type=int, default=d.picture_side,
        help=f"longer side of the picture panel's render in pixels (default {d.picture_side})",
    )  # fmt: skip
    p.add_argument(
        "--out-dir",
        type=Path,
        default=Path("."),
        help="where exports are written (default: the current folder)",
    )
    p.set_defaults(fn=cmd_view)

    p = command("health", "gRPC health check (exit 0 when SERVING)")
    p.add_argument("service", nargs="?", default="", help='service name (default "": the whole server)')
    p.set_defaults(fn=cmd_health)
    return ap


def _client(args: argparse.Namespace) -> FmgsClient:
    token = read_token_file(args.token_file)[0] if args.token_file else None  # the server's file format
    return FmgsClient(
        args.address,
        token=token,
        root_cert=args.root_cert,
        client_cert=args.client_cert,
        client_key=args.client_key,
        timeout=args.timeout if args.timeout > 0 else None,
        retry=RetryPolicy(attempts=args.attempts),
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status (0 ok, 1 failure, 2 bad usage)."""
    args = build_parser().parse_args(argv)
    try:
        with _client(args) as client:
            return args.fn(client, args)
    except FmgsError as e:
        print(f"error: {e.code}: {e.details}", file=sys.stderr)
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
