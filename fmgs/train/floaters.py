"""Floaters: Gaussians that lie between a training camera and everything the scene's sparse points say it
sees. A fit that cannot explain part of an image (a backdrop, a view too few others share) puts Gaussians
there: they match the training images and spoil every other view, and a text query's argmax lands on them.

Structure from motion only triangulates what several views agree on, so a training camera's nearest sparse
points bound how close real surfaces come to it: a Gaussian in that camera's view and nearer than them
(a margin inside a low quantile of their depths, so that one stray point does not hide every floater and
the Gaussians that start at the nearest points do not count) is a floater.

A fit can also explain what the sparse points never reached (a sky, a backdrop) with Gaussians far
beyond them: those are counted apart, as lying beyond the sparse points' extent.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fmgs.data.dataset import PosedDataset
from fmgs.gaussians import GaussianSet

NEAR_QUANTILE = 0.01
"""Depth quantile of a camera's sparse points that stands for the nearest real surface it sees: the minimum
would let one mistriangulated point near the camera hide every floater in front of it."""
NEAR_MARGIN = 0.8
"""A floater is nearer than NEAR_MARGIN times that depth: at 1.0 the Gaussians that sit on the nearest points
themselves counted, and removing them cost held-out PSNR (the margins are compared in BACKGROUND.md)."""
EXTENT_QUANTILE = 0.005
"""The sparse points' extent is their [q, 1 - q] quantile box per axis (stray points do not widen it)."""
EXTENT_MARGIN = 0.05
"""A Gaussian is beyond the sparse points when it lies outside their extent grown by this fraction of the
extent's diagonal on every side."""
MIN_POINTS = 20
"""A camera that sees fewer sparse points than this gets no bound (it counts no floaters)."""


@dataclass
class FloaterReport:
    """What lies in front of the training cameras' nearest sparse points."""

    count: int
    """Gaussians nearer to at least one training camera than that camera's sparse points (floaters)."""
    total: int
    """Gaussians checked."""
    opacity: float
    """Sum of the floaters' opacities (a floater of opacity 0.01 hides little; one of 0.9 hides a lot)."""
    cameras_checked: int
    """Training cameras that saw at least MIN_POINTS sparse points (the others bound nothing)."""
    beyond: int = 0
    """Gaussians beyond the sparse points' extent (a backdrop or sky explained by Gaussians lands there)."""
    beyond_opacity: float = 0.0
    """Sum of their opacities."""
    margin: float = NEAR_MARGIN
    """The NEAR_MARGIN the count used."""
    per_view: list[dict] = field(default_factory=list)
    """name, floaters, near (the depth bound) of each checked camera with floaters, most first."""

    @property
    def fraction(self) -> float:
        return self.count / self.total if self.total else 0.0

    def summary(self, views: int = 5) -> dict:
        """As JSON: totals and the ``views`` cameras with the most floaters."""
        return {
            "count": self.count,
            "total": self.total,
            "fraction": self.fraction,
            "opacity": self.opacity,
            "cameras_checked": self.cameras_checked,
            "near_quantile": NEAR_QUANTILE,
            "near_margin": self.margin,
            "beyond": self.beyond,
            "beyond_opacity": self.beyond_opacity,
            "worst_views": self.per_view[:views],
        }

    def line(self) -> str:
        """One line for the terminal."""
        if not self.cameras_checked:
            return "floaters: not checked (no training camera sees enough sparse points)"
        s = f"floaters: {self.count:,} of {self.total:,} Gaussians ({100 * self.fraction:.2f}%, opacity sum "
        s += f"{self.opacity:.1f}) lie in front of what a training camera's sparse points see"
        if self.per_view:
            w = self.per_view[0]
            s += f" (most before {w['name']}: {w['floaters']:,})"
        return s + f"; {self.beyond:,} (opacity sum {self.beyond_opacity:.1f}) lie beyond the sparse points"


def _project(points: np.ndarray, viewmat: np.ndarray, K: np.ndarray, w: int, h: int):
    """Camera-frame depth [N] and whether each point is in front of the camera and inside the image [N]."""
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = K[0, 0] * cam[:, 0] / zs + K[0, 2]
    v = K[1, 1] * cam[:, 1] / zs + K[1, 2]
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return z, inside


def floater_mask(
    gaussians: GaussianSet, ds: PosedDataset, views: list[int] | None = None, margin: float = NEAR_MARGIN
) -> tuple[np.ndarray, FloaterReport]:
    """([N] bool: floaters, the report) for ``gaussians`` against the training ``views`` of ``ds`` (default:
    every frame not held out) and its sparse points; the report also counts the Gaussians beyond the points'
    extent (not in the mask: they may be the backdrop the images show). With no sparse points nothing is
    counted and the report says no camera was checked. ``margin``: NEAR_MARGIN. Cost: O(N) per camera."""
    means = gaussians.means.detach().cpu().double().numpy()
    opac = gaussians.opacities.detach().cpu().double().numpy().reshape(-1)
    n = len(means)
    mask = np.zeros(n, dtype=bool)
    pts = ds.points
    if views is None:
        views = ds.split()[0]
    checked, rows = 0, []
    beyond = np.zeros(n, dtype=bool)
    if pts is not None and len(pts) >= MIN_POINTS:
        pts = np.asarray(pts, dtype=np.float64)
        lo, hi = np.quantile(pts, EXTENT_QUANTILE, 0), np.quantile(pts, 1 - EXTENT_QUANTILE, 0)
        grow = EXTENT_MARGIN * float(np.linalg.norm(hi - lo))
        beyond = ((means < lo - grow) | (means > hi + grow)).any(1)
        for i in views:
            cam = ds.frames[i].camera
            V, K = cam.viewmat.numpy(), cam.K.numpy()
            zp, inp = _project(pts, V, K, cam.width, cam.height)
            if inp.sum() < MIN_POINTS:
                continue
            checked += 1
            near = float(np.quantile(zp[inp], NEAR_QUANTILE))
            zg, ing = _project(means, V, K, cam.width, cam.height)
            here = ing & (zg < margin * near)
            if here.any():
                rows.append({"name": ds.frames[i].name, "floaters": int(here.sum()), "near": near})
                mask |= here
    rows.sort(key=lambda r: -r["floaters"])
    rep = FloaterReport(
        int(mask.sum()),
        n,
        float(opac[mask].sum()),
        checked,
        int(beyond.sum()),
        float(opac[beyond].sum()),
        margin,
        rows,
    )
    return mask, rep
