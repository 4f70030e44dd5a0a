"""Open-vocabulary quality of a scene package on a labelled scene (the synthetic generator's output).

Scored through the query engine the server runs (fmgs.query.engine.SceneEngine), so the figures are
those of the served answers. Three measures, on held-out views:
- LERF localisation: a query (an object's name) is correct when the highest-relevancy pixel of its
  relevancy image lies inside the object's 2D box;
- 3D localisation: the top-ranked Gaussian of the query lies inside the object's 3D box;
- segmentation: the served pixel labels (fmgs.query.segment: the label name whose embedding has the
  highest dot with the rendered feature, unlabelled where the embedded Gaussians barely cover the pixel);
  mean IoU over the labelled classes (pixels of the "background" label, with no geometry, are left out;
  an unlabelled pixel counts as a miss).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from fmgs.data.dataset import PosedDataset
from fmgs.query.engine import SceneEngine
from fmgs.query.pose import render_pose
from fmgs.query.segment import segment


@dataclass
class FieldQuality:
    """Scores of one scene (fractions in [0, 1])."""

    localisation_2d: float
    """Share of (view, object) queries whose highest-relevancy pixel is inside the object's box."""
    localisation_3d: float
    """Share of objects whose top-ranked Gaussian's mean lies inside the object's 3D box."""
    localisation_3d_overlap: float
    """Share of objects whose top-ranked Gaussian reaches into the box: its mean is within its largest
    1-sigma scale of the box (surface Gaussians of a flat face straddle it, so their means can sit just
    outside)."""
    miou: float
    """Mean IoU of the per-pixel argmax segmentation over the labelled classes."""
    queries_2d: int
    """Number of (view, object) queries."""
    per_class_iou: dict[str, float] = field(default_factory=dict)
    """IoU per class name."""
    failures: list[str] = field(default_factory=list)
    """Which queries failed, for reading the report."""
    per_view_2d: dict[str, list[int]] = field(default_factory=dict)
    """View name -> [2D hits, 2D queries] in that view (a mean can hide one view where every query fails)."""
    per_object_2d: dict[str, list[int]] = field(default_factory=dict)
    """Object name -> [2D hits, 2D queries] over the views."""
    per_object_3d: dict[str, bool] = field(default_factory=dict)
    """Object name -> whether its top Gaussian's mean lies inside its 3D box."""

    def to_dict(self) -> dict:
        return asdict(self)


def add_overlaps(lab: np.ndarray, gt: np.ndarray, inter: np.ndarray, union: np.ndarray) -> None:
    """Add one view's per-label intersections and unions (in place, [K] each, label 0 the background) of
    the served labels lab [H,W] (class i is label i + 1; -1: no geometry) against the label map gt [H,W]."""
    pred = np.where(lab >= 0, lab + 1, -1)  # label ids; -1 (no geometry) matches no class
    valid = gt > 0
    for c in range(1, len(inter)):
        p, t = (pred == c) & valid, (gt == c) & valid
        inter[c] += np.sum(p & t)
        union[c] += np.sum(p | t)


def class_ious(inter: np.ndarray, union: np.ndarray, names: list[str]) -> dict[str, float]:
    """{name: IoU} of every label present in the label maps or the predictions (union > 0)."""
    return {names[c]: float(inter[c] / union[c]) for c in range(len(names)) if union[c] > 0}


@torch.no_grad()
def evaluate_field(
    engine: SceneEngine, ds: PosedDataset, encoder, views: list[int], scene_json: str | Path
) -> FieldQuality:
    """Score ``engine`` (open it as the server does: ``SceneEngine.open(package)``) on frames ``views`` of
    a labelled dataset (``scene.json`` beside)."""
    from PIL import Image

    meta = json.loads(Path(scene_json).read_text())
    names: list[str] = meta["label_names"]
    boxes = {v["file_path"]: v["boxes_2d"] for v in meta["views"]}
    objects = {o["name"]: o for o in meta["objects"]}
    emb = encoder.encode_text(names).float()  # [K,D]
    classes = list(range(1, len(names)))  # label 0 is background (no geometry)
    failures: list[str] = []
    per_view: dict[str, list[int]] = {}
    per_object: dict[str, list[int]] = {}
    per_object_3d: dict[str, bool] = {}

    hit2d = n2d = 0
    inter = np.zeros(len(names))
    union = np.zeros(len(names))
    for i in views:
        fr = ds.frames[i]
        cam = fr.camera
        here = per_view.setdefault(fr.name, [0, 0])
        for name, (x0, y0, x1, y1) in boxes.get(fr.name, {}).items():
            x, y, _ = render_pose(engine, cam, emb[names.index(name)]).argmax
            ok = x0 <= x <= x1 and y0 <= y <= y1
            hit2d += ok
            n2d += 1
            here[0] += int(ok)
            here[1] += 1
            mine = per_object.setdefault(name, [0, 0])
            mine[0] += int(ok)
            mine[1] += 1
            if not ok:
                failures.append(f"2d {fr.name} {name!r}: peak at ({x},{y}) outside {[x0, y0, x1, y1]}")
        label_path = ds.root / "labels" / Path(fr.name).name
        gt = np.asarray(Image.open(label_path)).astype(np.int64)
        lab = segment(engine, emb[classes], cam, per_gaussian=False).pixel_labels.numpy()  # [H,W]
        add_overlaps(lab, gt, inter, union)

    hit3d = near3d = 0
    for name, o in objects.items():
        if o["label"] < 2:
            continue  # the floor is a label, not an object to localise
        top = int(engine.text_query(emb[names.index(name)], top_k=1).index[0])
        p = engine.gaussians.means[top].double().cpu().numpy()
        lo, hi = np.array(o["aabb_min"]), np.array(o["aabb_max"])
        dist = float(np.linalg.norm(np.maximum(lo - p, 0) + np.maximum(p - hi, 0)))
        reach = float(engine.gaussians.scales[top].max())
        hit3d += dist == 0
        near3d += dist <= reach
        per_object_3d[name] = dist == 0
        if dist > 0:
            failures.append(
                f"3d {name!r}: top Gaussian's mean {dist:.3f} outside its box (its largest scale {reach:.3f})"
            )
    n3d = sum(1 for o in objects.values() if o["label"] >= 2)
    ious = class_ious(inter, union, names)
    return FieldQuality(
        localisation_2d=hit2d / max(n2d, 1),
        localisation_3d=hit3d / max(n3d, 1),
        localisation_3d_overlap=near3d / max(n3d, 1),
        miou=float(np.mean(list(ious.values()))) if ious else 0.0,
        queries_2d=n2d,
        per_class_iou=ious,
        failures=failures,
        per_view_2d=per_view,
        per_object_2d=per_object,
        per_object_3d=per_object_3d,
    )
