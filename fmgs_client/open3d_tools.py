"""Open3D helpers for desktop inspection of text answers (optional extra ``fmgs[open3d]``).

Open3D is imported inside the functions, so ``fmgs_client`` never needs it. Every function wants an
answer queried with the ``mean`` field (``client.query(..., fields=["mean"])``).

Headless screenshots use Open3D's ``OffscreenRenderer`` (Filament; on a machine without a GPU it runs
on Mesa's software Vulkan driver, llvmpipe, from Debian ``libvulkan1 mesa-vulkan-drivers``). Where that
renderer cannot start (Filament then aborts the process, so this is probed once in a subprocess),
:func:`screenshot` falls back to :func:`splat_points`, a small numpy z-buffered point splatter with the
same camera, so a picture is always produced.
"""

from __future__ import annotations

import functools
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from fmgs_client.ply import write_ply
from fmgs_client.types import Box, CameraSpec, TextAnswer
from fmgs_wire.images import colorize, write_png

# The 12 edges of a box as pairs of corner indices (corner bits: x=1, y=2, z=4; see Box.corners).
BOX_EDGES = np.array(
    [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]]
)
AABB_COLOR = (0.1, 0.45, 1.0)
OBB_COLOR = (1.0, 0.2, 0.6)


def require_open3d() -> Any:
    """The ``open3d`` module, imported on first use; ImportError naming the extra that installs it."""
    try:
        import open3d
    except ImportError as e:
        raise ImportError(
            f"fmgs_client.open3d_tools needs Open3D: pip install 'fmgs[open3d]' (open3d-cpu) ({e})"
        ) from e
    return open3d


def _means(answer: TextAnswer) -> np.ndarray:
    if answer.mean is None:
        raise ValueError(f"answer to {answer.text!r} has no means: query it with fields=['mean']")
    return np.asarray(answer.mean, np.float64)


def answer_colors(answer: TextAnswer) -> np.ndarray:
    """[K,3] float64 colours in [0,1] of the answer's Gaussians by relevancy (turbo-like map)."""
    return colorize(answer.relevancy) / 255.0


def box_lines(box: Box, color: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corners [8,3], edges [12,2] and edge colours [12,3] of a box."""
    return box.corners(), BOX_EDGES.copy(), np.tile(np.asarray(color, np.float64), (len(BOX_EDGES), 1))


def answer_geometries(answer: TextAnswer) -> list:
    """Open3D geometries: the Gaussians' means coloured by relevancy, then per instance its AABB and OBB
    as ``LineSet``s (blue and pink)."""
    o3d = require_open3d()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_means(answer)))
    pc.colors = o3d.utility.Vector3dVector(answer_colors(answer))
    geoms: list = [pc]
    for inst in answer.instances:
        for box, col in ((inst.aabb, AABB_COLOR), (inst.obb, OBB_COLOR)):
            pts, edges, cols = box_lines(box, col)
            ls = o3d.geometry.LineSet(o3d.utility.Vector3dVector(pts), o3d.utility.Vector2iVector(edges))
            ls.colors = o3d.utility.Vector3dVector(cols)
            geoms.append(ls)
    return geoms


def export_answer(answer: TextAnswer, path_ply: str | Path) -> list[Path]:
    """Write the point cloud to ``path_ply`` (with ``relevancy`` and ``gaussian`` properties) and, when
    the answer has instances, every box edge to ``<stem>_boxes.ply`` (an Open3D line set).
    Returns the paths written."""
    o3d = require_open3d()
    path = Path(path_ply)
    scalars = {"relevancy": answer.relevancy, "gaussian": answer.index}
    if answer.instance is not None:
        scalars["instance"] = answer.instance
    written = [write_ply(path, _means(answer), colorize(answer.relevancy), scalars)]
    if answer.instances:
        pts, edges, cols = [], [], []
        for inst in answer.instances:
            for box, col in ((inst.aabb, AABB_COLOR), (inst.obb, OBB_COLOR)):
                p, e, c = box_lines(box, col)
                edges.append(e + 8 * len(pts))
                pts.append(p)
                cols.append(c)
        ls = o3d.geometry.LineSet(
            o3d.utility.Vector3dVector(np.concatenate(pts)), o3d.utility.Vector2iVector(np.concatenate(edges))
        )
        ls.colors = o3d.utility.Vector3dVector(np.concatenate(cols))
        box_path = path.with_name(f"{path.stem}_boxes.ply")
        if not o3d.io.write_line_set(str(box_path), ls):
            raise OSError(f"Open3D could not write {box_path}")
        written.append(box_path)
    return written


def show(answer: TextAnswer, window_name: str | None = None) -> None:
    """Open a desktop window with :func:`answer_geometries` (blocks until it is closed)."""
    o3d = require_open3d()
    o3d.visualization.draw_geometries(answer_geometries(answer), window_name=window_name or answer.text)


def view_camera(
    answer: TextAnswer, width: int, height: int, up: tuple[float, float, float] = (0, 0, 1), fov: float = 60.0
) -> CameraSpec:
    """A camera that frames the answer's points (and boxes): from above-diagonal, looking at their centre."""
    if width < 1 or height < 1:
        raise ValueError(f"view_camera: width and height must be at least 1, got {width}x{height}")
    u = np.asarray(up, np.float64)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or not np.any(u):
        raise ValueError(f"view_camera: up must be 3 finite numbers, not all zero, got {u.tolist()}")
    allp = np.concatenate([_means(answer)] + [b.corners() for i in answer.instances for b in (i.aabb, i.obb)])
    if not len(allp):
        allp = np.zeros((1, 3))
    lo, hi = allp.min(0), allp.max(0)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
    # Fit the bounding sphere into the narrower field of view.
    fov_v = 2 * math.degrees(math.atan(math.tan(math.radians(fov) / 2) * height / width))
    dist = 1.15 * radius / math.sin(math.radians(min(fov, fov_v)) / 2)
    u = u / np.linalg.norm(u)
    side = np.cross(u, np.eye(3)[np.argmin(np.abs(u))])
    side /= np.linalg.norm(side)
    d = np.cross(u, side) * 0.6 + side * 0.6 + u * 0.5
    d /= np.linalg.norm(d)
    return CameraSpec.look_at(centre + dist * d, centre, u, width, height, fov)


def splat_points(
    camera: CameraSpec,
    points: np.ndarray,
    colors: np.ndarray,
    radius: int = 2,
    background: tuple[int, int, int] = (255, 255, 255),
    lines: list[tuple[np.ndarray, np.ndarray, tuple[float, float, float]]] | None = None,
) -> np.ndarray:
    """Software render: uint8 [H,W,3] of points [N,3] with colours in [0,1] [N,3] as square splats of
    ``2*radius+1`` pixels, nearest point wins (z-buffer), plus optional line segments
    (corners, edges, colour) drawn on top. The headless fallback when Open3D cannot render."""
    W, H = camera.width, camera.height
    img = np.empty((H, W, 3), np.uint8)
    img[:] = background
    zbuf = np.full((H, W), np.inf)
    uv, z = camera.project(points)
    ok = (z > 1e-6) & np.all(np.isfinite(uv), 1)
    uv, z, col = uv[ok], z[ok], (np.clip(colors[ok], 0, 1) * 255).round().astype(np.uint8)
    # Paint far to near so nearer splats overwrite; the z-buffer only decides between equals.
    order = np.argsort(-z)
    px = np.floor(uv[order]).astype(np.int64)
    z, col = z[order], col[order]
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            x, y = px[:, 0] + dx, px[:, 1] + dy
            inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
            xi, yi, zi, ci = x[inside], y[inside], z[inside], col[inside]
            closer = zi <= zbuf[yi, xi]
            xi, yi, zi, ci = xi[closer], yi[closer], zi[closer], ci[closer]
            zbuf[yi, xi] = zi
            img[yi, xi] = ci
    for corners, edges, color in lines or []:
        c_uv, c_z = camera.project(corners)
        for a, b in edges:
            if c_z[a] <= 1e-6 or c_z[b] <= 1e-6:
                continue  # an edge crossing behind the camera: skip rather than clip
            n = int(max(abs(c_uv[b] - c_uv[a]).max(), 1)) + 1
            t = np.linspace(0, 1, n)[:, None]
            seg = np.floor(c_uv[a] * (1 - t) + c_uv[b] * t).astype(np.int64)
            inside = (seg[:, 0] >= 0) & (seg[:, 0] < W) & (seg[:, 1] >= 0) & (seg[:, 1] < H)
            img[seg[inside, 1], seg[inside, 0]] = (np.asarray(color) * 255).round().astype(np.uint8)
    return img


_PROBE = """
import open3d as o3d
r = o3d.visualization.rendering.OffscreenRenderer(8, 8)
r.render_to_image()
print("ok")
"""


@functools.cache
def open3d_can_render() -> bool:
    """Whether Open3D's OffscreenRenderer works here, tried once per process in a subprocess.

    Filament aborts the whole process (C++ ``terminate``) when it finds no usable Vulkan/EGL device,
    so the first attempt must not happen in this process.
    """
    try:
        import importlib.util

        if importlib.util.find_spec("open3d") is None:
            return False
        done = subprocess.run(
            [sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return False
    return done.returncode == 0 and "ok" in done.stdout


def _render_open3d(answer: TextAnswer, camera: CameraSpec, point_size: float) -> np.ndarray:
    o3d = require_open3d()
    rendering = o3d.visualization.rendering
    r = rendering.OffscreenRenderer(camera.width, camera.height)
    r.scene.set_background([1.0, 1.0, 1.0, 1.0])
    # No tone mapping / colour grading: keep the colour map's colours as they are.
    r.scene.view.set_post_processing(False)
    mat_pts = rendering.MaterialRecord()
    mat_pts.shader = "defaultUnlit"
    mat_pts.point_size = point_size
    mat_lines = rendering.MaterialRecord()
    mat_lines.shader = "unlitLine"
    mat_lines.line_width = 2.0
    for k, g in enumerate(answer_geometries(answer)):
        is_lines = isinstance(g, o3d.geometry.LineSet)
        r.scene.add_geometry(f"g{k}", g, mat_lines if is_lines else mat_pts)
    # Same pinhole as CameraSpec: intrinsics + world-to-camera extrinsics (OpenCV axes).
    r.setup_camera(camera.K, camera.viewmat, camera.width, camera.height)
    return np.asarray(r.render_to_image()).copy()


def screenshot(
    answer: TextAnswer,
    path_png: str | Path,
    width: int = 800,
    height: int = 600,
    camera: CameraSpec | None = None,
    method: str = "auto",
    point_size: float = 4.0,
) -> Path:
    """Render the answer's points and boxes headless to ``path_png`` (RGB PNG).

    ``camera`` defaults to :func:`view_camera`. ``method``: ``"open3d"`` (OffscreenRenderer; where it
    has no Vulkan/EGL device Filament aborts the process), ``"numpy"`` (:func:`splat_points`), or
    ``"auto"``: Open3D when :func:`open3d_can_render` (probed once, in a subprocess), else numpy.
    """
    if method not in ("auto", "open3d", "numpy"):
        raise ValueError(f"method: expected auto, open3d or numpy, got {method!r}")
    cam = camera or view_camera(answer, width, height)
    if method == "open3d" or (method == "auto" and open3d_can_render()):
        img = _render_open3d(answer, cam, point_size)
    else:
        lines = [
            (*box_lines(b, col)[:2], col)
            for i in answer.instances
            for b, col in ((i.aabb, AABB_COLOR), (i.obb, OBB_COLOR))
        ]
        img = splat_points(cam, _means(answer), answer_colors(answer), int(point_size // 2), lines=lines)
    return write_png(path_png, np.ascontiguousarray(img[..., :3], np.uint8))
