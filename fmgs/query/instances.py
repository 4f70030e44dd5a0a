"""3D localisation: relevant Gaussians grouped into object instances with centroid and boxes.

DBSCAN on the Gaussians' means (scipy KD-tree; no Open3D needed at serve time): points with at least
``min_points`` neighbours within ``eps`` are core points, core points within ``eps`` of each other share an
instance, and the rest join the instance of a core neighbour or stay unassigned (-1). Weights (relevancy
times opacity) set the centroid and the oriented box's axes, not the membership.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from fmgs.errors import ValidationError

MAX_NEIGHBOUR_PAIRS = 1 << 22
"""Default of ``InstanceConfig.max_pairs``: the most pairs of points within eps of each other that
``dbscan`` lists (its memory grows with them)."""


@dataclass(frozen=True)
class InstanceConfig:
    """Grouping of a query's Gaussians into instances."""

    eps: float = 0.0
    """Neighbourhood radius in scene units; 0 picks ``eps_fraction`` of the scene's extent."""
    eps_fraction: float = 0.03
    """Default radius as a fraction of the diagonal of the scene's mean bounds (1st-99th percentile)."""
    min_points: int = 10
    """Neighbours (self included) that make a core point; smaller groups are noise."""
    max_instances: int = 10
    """Most instances returned, best score first."""
    max_pairs: int = MAX_NEIGHBOUR_PAIRS
    """Most pairs of answer Gaussians within eps of each other that the grouping lists; more are refused
    (counted first, before any is listed), since its memory grows with them."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.eps) and self.eps >= 0) or not 0 < self.eps_fraction <= 1:
            raise ValidationError("instances.eps", "must be finite and >= 0 (eps_fraction in (0,1])")
        if self.min_points < 1 or self.max_instances < 1 or self.max_pairs < 1:
            raise ValidationError("instances", "min_points, max_instances and max_pairs must be >= 1")


class Box(NamedTuple):
    """A box: centre [3], full side lengths [3] along its axes, rotation [3,3] (columns are the axes)."""

    center: np.ndarray
    extent: np.ndarray
    rotation: np.ndarray


class Instance(NamedTuple):
    """One object instance."""

    centroid: np.ndarray
    """[3] weighted mean of the members' means."""
    aabb: Box
    """Axis-aligned box of the members' means."""
    obb: Box
    """Oriented box: axes from the weighted covariance of the members' means."""
    score: float
    """Mean relevancy of the members."""
    members: np.ndarray
    """[m] positions (into the query's answer) of the members."""


def dbscan(
    points: np.ndarray, eps: float, min_points: int, max_pairs: int = MAX_NEIGHBOUR_PAIRS
) -> np.ndarray:
    """[n] int64 cluster labels (-1 noise) for points [n,3]; clusters numbered by their first core point.
    More than ``max_pairs`` pairs within eps raise ValidationError before any pair is listed."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(points)
    labels = np.full(n, -1, np.int64)
    if n == 0:
        return labels
    tree = cKDTree(points)
    within = (int(tree.count_neighbors(tree, eps)) - n) // 2  # dual-tree count: nothing listed
    if within > max_pairs:
        raise ValidationError(
            "instances",
            f"{within} pairs of the {n} Gaussians lie within eps {eps:.4g} of each other, more than the "
            f"{max_pairs} the instance grouping lists (the server's max_instance_pairs); ask for a smaller "
            "instances.eps or top_k",
        )
    pairs = tree.query_pairs(eps, output_type="ndarray")  # [p,2] i<j
    deg = np.ones(n, np.int64) + np.bincount(pairs.ravel(), minlength=n)
    core = deg >= min_points
    both = core[pairs[:, 0]] & core[pairs[:, 1]]
    cp = pairs[both]
    g = coo_matrix((np.ones(len(cp)), (cp[:, 0], cp[:, 1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    # Renumber the core components in order of their first point.
    core_idx = np.flatnonzero(core)
    _, first = np.unique(comp[core_idx], return_index=True)
    remap = {int(comp[core_idx[f]]): i for i, f in enumerate(sorted(first))}
    for i in core_idx:
        labels[i] = remap[int(comp[i])]
    # Border points: the cluster of their nearest core neighbour within eps.
    border = np.flatnonzero(~core)
    if len(border) and len(core_idx):
        d, j = cKDTree(points[core_idx]).query(points[border], distance_upper_bound=eps)
        ok = np.isfinite(d)
        labels[border[ok]] = labels[core_idx[j[ok]]]
    return labels


def default_eps(scene_means: np.ndarray, fraction: float) -> float:
    """``fraction`` of the diagonal of the 1st-99th percentile box of the scene's means (> 0)."""
    if len(scene_means) == 0:
        return 1.0
    lo, hi = np.percentile(scene_means, [1, 99], axis=0)
    return float(max(np.linalg.norm(hi - lo) * fraction, 1e-9))


def group_instances(
    means: np.ndarray,
    relevancy: np.ndarray,
    opacity: np.ndarray,
    cfg: InstanceConfig,
    eps: float,
) -> tuple[list[Instance], np.ndarray]:
    """Instances among the answer's Gaussians (means [K,3], relevancy [K], opacity [K]), best score first.

    Returns (instances, [K] int32 instance id per Gaussian, -1 for none or for dropped instances).
    """
    labels = dbscan(np.asarray(means, np.float64), eps, cfg.min_points, cfg.max_pairs)
    found = []
    for c in range(int(labels.max()) + 1 if len(labels) else 0):
        idx = np.flatnonzero(labels == c)
        found.append((float(relevancy[idx].mean()), len(idx), idx))
    found.sort(key=lambda t: (-t[0], -t[1], int(t[2][0])))
    out, ids = [], np.full(len(labels), -1, np.int32)
    for i, (score, _, idx) in enumerate(found[: cfg.max_instances]):
        p = np.asarray(means[idx], np.float64)
        w = np.asarray(relevancy[idx], np.float64) * np.asarray(opacity[idx], np.float64)
        w = w / w.sum() if w.sum() > 0 else np.full(len(idx), 1.0 / len(idx))
        centroid = w @ p
        lo, hi = p.min(0), p.max(0)
        aabb = Box((lo + hi) / 2, hi - lo, np.eye(3))
        out.append(Instance(centroid, aabb, _obb(p, w, centroid), score, idx))
        ids[idx] = i
    return out, ids


def _obb(p: np.ndarray, w: np.ndarray, centroid: np.ndarray) -> Box:
    """Box along the eigenvectors of the weighted covariance, enclosing all points."""
    d = p - centroid
    cov = (d * w[:, None]).T @ d
    _, axes = np.linalg.eigh(cov)
    axes = axes[:, ::-1]
    if np.linalg.det(axes) < 0:  # a proper rotation
        axes[:, 2] *= -1
    local = d @ axes
    lo, hi = local.min(0), local.max(0)
    return Box(centroid + axes @ ((lo + hi) / 2), hi - lo, axes)
