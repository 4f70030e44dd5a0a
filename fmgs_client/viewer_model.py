"""What the inspector shows, without a window (numpy only): the scene's points, answers recoloured by
relevancy, boxes, presence lines, the picture panel's modes, segmentation colours, camera conversion.

``fmgs_client.viewer`` draws these with Open3D's GUI; keeping them here lets tests check each against the
server's own answers without a display.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fmgs_client.open3d_tools import BOX_EDGES
from fmgs_client.types import Box, CameraSpec, Geometry, Instance, SegmentResult, TextAnswer
from fmgs_wire.images import colorize, label_colors

PICTURE_MODES = ("composite", "relevancy", "rgb")
"""What the picture panel shows: relevancy colour over RGB where relevancy >= 0.5 (as LERF shows it),
relevancy alone, the colour render."""
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
"""OpenGL camera axes (y up, looking down -z) to OpenCV's (y down, looking down +z), and back."""


@dataclass(frozen=True)
class ViewerConfig:
    """What the inspector asks the server for."""

    max_points: int = 200_000
    """Points drawn for the scene: a uniform sample (the server's, fixed seed) of the Gaussians above the
    opacity floor when there are more."""
    min_opacity: float = 0.1
    """Gaussians fainter than this are not drawn."""
    top_k: int = 2000
    """Gaussians per phrase of a text query."""
    threshold: float = 0.6
    """Only Gaussians with relevancy at least this (0: the top_k regardless). Above 0.5 the phrase beats
    every canonical phrase; a margin keeps weakly related Gaussians out of the answer's instances."""
    picture_side: int = 320
    """Longer side of the picture panel's render, pixels (the server renders at this size)."""
    dim: float = 0.3
    """How much of their colour the scene's points keep while an answer is shown."""

    def __post_init__(self) -> None:
        if self.max_points < 1 or self.top_k < 1 or self.picture_side < 8:
            raise ValueError("max_points and top_k must be >= 1, picture_side >= 8")
        if not 0.0 <= self.min_opacity < 1.0 or not 0.0 <= self.threshold <= 1.0 or not 0.0 <= self.dim <= 1:
            raise ValueError("min_opacity must lie in [0, 1), threshold and dim in [0, 1]")


def parse_phrases(line: str) -> list[str]:
    """Phrases separated by ";" (as LERF takes them), stripped, empty ones dropped."""
    return [p.strip() for p in line.split(";") if p.strip()]


def dimmed(colors: np.ndarray, keep: float) -> np.ndarray:
    """[N,3] colours faded towards mid grey, keeping ``keep`` of each."""
    return keep * np.asarray(colors, np.float64) + (1.0 - keep) * 0.5


@dataclass(frozen=True, eq=False)
class AnswerView:
    """One phrase's answer as drawn: its Gaussians recoloured by relevancy over a legend's range."""

    answer: TextAnswer
    points: np.ndarray
    """[K,3] float64 the answer's Gaussians' means."""
    colors: np.ndarray
    """[K,3] float64 in [0,1]: colorize(relevancy) over [vmin, vmax]; the most relevant carry the high end."""
    vmin: float
    vmax: float

    @property
    def presence_line(self) -> str:
        a, p = self.answer, self.answer.presence
        if p is None:
            return f"{a.text}: {len(a)} Gaussians (presence unknown)"
        if p.found:
            return f"{a.text}: found ({p.score:.2f})"
        return f"{a.text}: NOT FOUND: the scene has {p.rival!r} there ({p.score:.2f})"


def answer_view(answer: TextAnswer) -> AnswerView:
    """The answer's points coloured over [max(0.5, lowest relevancy), highest]: relevancy below 0.5 says
    the canonical phrases win, so the legend starts no lower; a flat answer maps to the high end."""
    if answer.mean is None:
        raise ValueError(f"answer to {answer.text!r} has no means: query it with fields=['mean']")
    r = np.asarray(answer.relevancy, np.float64)
    vmax = float(r.max()) if len(r) else 1.0
    vmin = min(max(0.5, float(r.min()) if len(r) else 0.5), vmax)
    if vmax - vmin < 1e-6:
        vmin = vmax - 1e-6  # every point at the top of the map
    return AnswerView(
        answer, np.asarray(answer.mean, np.float64), colorize(r, vmin, vmax) / 255.0, vmin, vmax
    )


def legend(vmin: float, vmax: float, width: int = 256, height: int = 16) -> np.ndarray:
    """[height, width, 3] uint8 colour bar of colorize from vmin (left) to vmax (right)."""
    row = colorize(np.linspace(vmin, vmax, width), vmin, vmax)
    return np.ascontiguousarray(np.broadcast_to(row, (height, width, 3)))


def box_lines(boxes: Sequence[Box]) -> tuple[np.ndarray, np.ndarray]:
    """Corners [8B,3] and edges [12B,2] of boxes, for one line set."""
    if not boxes:
        return np.zeros((0, 3)), np.zeros((0, 2), np.int64)
    pts = np.concatenate([b.corners() for b in boxes])
    edges = np.concatenate([BOX_EDGES + 8 * i for i in range(len(boxes))])
    return pts, edges


def instance_line(i: Instance) -> str:
    ext = " x ".join(f"{v:.2f}" for v in i.obb.extent)
    return f"  instance {i.id}: score {i.score:.2f}, {i.num_members} Gaussians, {ext}"


def composite(rgb: np.ndarray, relevancy: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """[H,W,3] uint8: relevancy colour (over [0.5, its highest]) where relevancy >= 0.5 and something is
    drawn (alpha >= 0.1), the colour render elsewhere."""
    rgb8 = np.round(np.clip(np.asarray(rgb, np.float64), 0, 1) * 255).astype(np.uint8)
    r = np.asarray(relevancy, np.float64)
    top = max(float(np.nan_to_num(r, nan=0.0).max()) if r.size else 0.5, 0.5 + 1e-6)
    over = r >= 0.5
    if alpha is not None:
        over &= np.asarray(alpha) >= 0.1
    out = rgb8.copy()
    out[over] = colorize(r[over], 0.5, top)
    return out


def picture(mode: str, rgb: np.ndarray, relevancy: np.ndarray, alpha: np.ndarray | None) -> np.ndarray:
    """The picture panel's image in ``mode`` (PICTURE_MODES), [H,W,3] uint8."""
    if mode == "rgb":
        return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
    if mode == "relevancy":
        c = colorize(relevancy).astype(np.float64)
        if alpha is not None:  # nothing drawn: no feature, fade to black
            c *= np.clip(alpha, 0, 1)[..., None]
        return np.round(c).astype(np.uint8)
    if mode == "composite":
        return composite(rgb, relevancy, alpha)
    raise ValueError(f"picture mode must be one of {PICTURE_MODES}, got {mode!r}")


def segment_colors(geometry: Geometry, seg: SegmentResult, keep: float) -> np.ndarray:
    """[k,3] colours in [0,1] of the drawn points: each labelled Gaussian its class's colour, the others
    (not embedded) dimmed."""
    out = dimmed(geometry.color, keep)
    if seg.gaussian_index is None or not len(seg.gaussian_index):
        return out
    order = np.argsort(seg.gaussian_index)
    sidx = seg.gaussian_index[order]
    pos = np.clip(np.searchsorted(sidx, geometry.index), 0, len(sidx) - 1)
    hit = sidx[pos] == geometry.index
    out[hit] = label_colors(seg.gaussian_labels[order][pos[hit]]) / 255.0
    return out


def camera_from_gl(view_gl: np.ndarray, proj_gl: np.ndarray, width: int, height: int) -> CameraSpec:
    """The pinhole camera of an OpenGL view matrix (world to camera, looking down -z) and a symmetric
    perspective projection, at width x height pixels."""
    vm = GL_TO_CV @ np.asarray(view_gl, np.float64)
    # Open3D keeps its matrices in float32: make the rotation orthonormal again and the last row exact.
    u, _, vt = np.linalg.svd(vm[:3, :3])
    vm[:3, :3] = u @ vt
    vm[3] = (0.0, 0.0, 0.0, 1.0)
    p = np.asarray(proj_gl, np.float64)
    fx, fy = p[0, 0] * width / 2.0, p[1, 1] * height / 2.0
    return CameraSpec(vm, fx, fy, width / 2.0, height / 2.0, int(width), int(height))


def picture_size(width: int, height: int, side: int) -> tuple[int, int]:
    """The panel render's size: the 3D view's aspect with its longer side ``side``."""
    s = side / max(width, height, 1)
    return max(8, round(width * s)), max(8, round(height * s))


def scaled(cam: CameraSpec, width: int, height: int) -> CameraSpec:
    """The same view at another image size (intrinsics scaled)."""
    sx, sy = width / cam.width, height / cam.height
    return CameraSpec(
        cam.viewmat, cam.fx * sx, cam.fy * sy, cam.cx * sx, cam.cy * sy, width, height, cam.near
    )


def framing(box: Box, view_dir: np.ndarray, fov_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(eye, centre): a camera along ``view_dir`` (from the eye towards the box) that fits the box."""
    d = np.asarray(view_dir, np.float64)
    d = d / max(np.linalg.norm(d), 1e-12)
    c = np.asarray(box.center, np.float64)
    radius = max(0.5 * float(np.linalg.norm(box.extent)), 1e-3)
    dist = 1.4 * radius / math.sin(math.radians(min(fov_deg, 170.0)) / 2)
    return c - dist * d, c


def robust_bounds(points: np.ndarray, q: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) [3] of the points between the q and 1-q quantiles per axis: a few floaters far out do not
    decide how the view frames the scene."""
    if not len(points):
        return np.zeros(3), np.ones(3)
    lo, hi = np.quantile(np.asarray(points, np.float64), [q, 1 - q], axis=0)
    return lo, np.maximum(hi, lo + 1e-6)


def home_view(lo: np.ndarray, hi: np.ndarray, fov_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(eye, centre): an above-diagonal view (z up) that fits the box lo..hi."""
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
    d = np.array([0.5, -0.75, 0.55])
    d /= np.linalg.norm(d)
    return centre + d * 1.1 * radius / math.sin(math.radians(fov_deg) / 2), centre
