"""benchmarks.distill_gap: the targets' per-class IoU, their mean squares and the loss-balance ratio."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from benchmarks.distill_gap import class_ious, confusions, dino_weight, mean_squares, report, target_ious
from fmgs.features.cache import FeatureCache, FeatureCacheWriter, TargetInfo


def _cache(tmp_path):
    """Two 4x4 views of labels background/floor/mug; the language targets name the mug right in view 0
    and call its left column floor in view 1."""
    table = torch.eye(3)[:, :3][1:]  # names[1:] = floor, mug as unit vectors e1, e2
    (tmp_path / "labels").mkdir()
    lab = np.ones((4, 4), np.uint8)
    lab[1:3, 1:3] = 2
    lab[0, 0] = 0  # background: no geometry, not scored
    targets = {"clip": TargetInfo("t/clip", 3, True), "dino": TargetInfo("t/dino", 2, False)}
    with FeatureCacheWriter(tmp_path / "cache", targets) as w:
        for v in range(2):
            Image.fromarray(lab).save(tmp_path / "labels" / f"{v}.png")
            pred = lab.copy()
            pred[pred == 0] = 1
            if v == 1:
                pred[1:3, 1] = 1
            clip = torch.nn.functional.one_hot(torch.from_numpy(pred).long(), 3).float()
            dino = torch.full((4, 4, 2), 3.0)
            w.add(f"images/{v}.png", clip=clip, dino=dino)
    return FeatureCache.open(tmp_path / "cache"), table


def test_target_ious_count_the_argmax_against_the_labels(tmp_path):
    cache, table = _cache(tmp_path)
    names = ["background", "floor", "mug"]
    ious = target_ious(tmp_path, cache, names, table, ["images/0.png", "images/1.png"])
    # mug: 4 + 2 right of 8 labelled, predicted 6 -> 6/8; floor: 11 + 11 labelled, 11 + 13 predicted.
    assert ious[2] == pytest.approx(6 / 8)
    assert ious[1] == pytest.approx(22 / 24)
    ms = mean_squares(cache, ["images/0.png", "images/1.png"])
    assert ms["clip"] == pytest.approx(1 / 3) and ms["dino"] == pytest.approx(9.0)


def test_dino_weight_and_the_report():
    b = {"mean_squares": {"clip": 1 / 384, "dino": 0.96}, "lam": 0.2, "balance": "paper"}
    assert dino_weight(b) == pytest.approx(0.8 * 0.96 / (0.2 / 384 / 2))
    assert dino_weight({**b, "balance": "scale"}) == pytest.approx(0.8 / 0.1)
    assert dino_weight({**b, "mean_squares": {"clip": 1 / 384}}) is None
    names = ["background", "floor", "mug"]
    per = {"floor": 0.9, "mug": 0.5}
    build = {**b, "targets": per, "train": per, "heldout": {"floor": 0.8, "mug": 0.2},
             "localisation_2d": 0.9, "localisation_3d": 1.0,
             "confusions": {"floor": {"floor": 1.0}, "mug": {"floor": 0.7, "mug": 0.3}}}  # fmt: skip
    d = {"names": names, "scene": "S", "builds": {"x": build},
         "machine": {"date": "d", "cpu": "c", "cores": 2, "gpu": None, "commit": "abc"}}  # fmt: skip
    text = report(d, "cmd")
    assert "| mean | 0.70 / 0.70 / 0.50 |" in text and "| mug | 0.50 / 0.50 / 0.20 |" in text
    assert "| x | 0.700 | 0.700 | 0.500 | 0.900 | 1.000 |" in text
    assert "mug: floor 0.70, mug 0.30" in text and f"{dino_weight(b):.0f}" in text


def test_class_ious_and_confusions_come_from_one_confusion_matrix():
    names = ["background", "floor", "mug"]
    # rows: label 0..2; columns: served 0..2 and unlabelled (3); row 0 (no geometry) is not scored
    conf = np.array([[5, 1, 1, 0], [0, 8, 2, 0], [0, 1, 3, 2]])
    ious = class_ious(conf, names)
    assert ious["floor"] == pytest.approx(8 / (10 + 9 - 8))  # label row + served column (labelled) - both
    assert ious["mug"] == pytest.approx(3 / (6 + 5 - 3))
    conf_ = confusions(conf, names)
    assert conf_["mug"] == {"mug": 0.5, "none": pytest.approx(0.333), "floor": pytest.approx(0.167)}
    assert "background" not in ious and class_ious(np.zeros((3, 4), np.int64), names) == {}
