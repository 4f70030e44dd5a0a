"""DINO attribution of crop embeddings (benchmarks/crop_attribution.py) against its twin and its purpose."""

from __future__ import annotations

import torch

from benchmarks.crop_attribution import guided_grid_map, guided_grid_map_reference
from fmgs.features.pyramid import crop_grid, grid_map


def _scene(h: int = 12, w: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """A dense map [h,w,3]: floor along e0, a 4x5 object block along e1; and the object's mask."""
    d = torch.zeros(h, w, 3)
    d[..., 0] = 1.0
    obj = torch.zeros(h, w, dtype=torch.bool)
    obj[3:7, 8:13] = True
    d[obj] = torch.tensor([0.0, 1.0, 0.0])
    return d, obj


def test_matches_the_twin_on_random_inputs():
    g = torch.Generator().manual_seed(0)
    dense = torch.randn(9, 13, 5, generator=g)
    dense[2:5, 3:8] = 0.0  # zero features: no crop is like them, the bilinear floor decides
    for scale, (H, W) in ((0.3, (9, 13)), (0.5, (18, 26))):  # the map at the image's size and at half
        grid = crop_grid(H, W, scale, 0.5)
        emb = torch.randn(*grid.boxes.shape[:2], 7, generator=g)
        fast = guided_grid_map(emb, grid, (H, W), dense)
        ref = guided_grid_map_reference(emb, grid, (H, W), dense)
        assert torch.isfinite(fast).all()
        torch.testing.assert_close(fast, ref, atol=1e-5, rtol=1e-4)


def test_uniform_features_give_the_tent_average():
    # one DINO feature everywhere: every crop is like every pixel, so each pixel gets its crops' embeddings
    # weighed by the tents alone; a constant embedding comes back unchanged
    d = torch.ones(12, 16, 3)
    grid = crop_grid(12, 16, 0.5, 0.5)
    emb = torch.zeros(*grid.boxes.shape[:2], 2)
    emb[..., 0] = 1.0
    out = guided_grid_map(emb, grid, (12, 16), d)
    torch.testing.assert_close(out, emb[0, 0].expand(12, 16, 2))


def test_floor_pixels_take_the_floor_crops():
    # crops embedded by what they are centred on: the object's embedding must not bleed onto the floor
    # beside it as bilinear interpolation makes it, and the object keeps its own
    d, obj = _scene()
    grid = crop_grid(12, 16, 0.25, 0.5)
    cy = grid.centers_y.floor().long().clamp(max=11)
    cx = grid.centers_x.floor().long().clamp(max=15)
    on_obj = obj[cy][:, cx]  # [ny,nx] crops centred on the object
    emb = torch.stack([(~on_obj).float(), on_obj.float()], -1)
    guided = guided_grid_map(emb, grid, (12, 16), d)
    bilinear = grid_map(emb, grid, (12, 16), (12, 16))
    named = guided.argmax(-1) == 1
    assert (named == obj).all()
    assert ((bilinear.argmax(-1) == 1) != obj).any()  # the bleed the attribution removes


def test_committed_report_is_written_from_its_figures_and_its_findings_quote_them():
    import json
    from pathlib import Path

    from benchmarks.crop_attribution import report

    results = Path(__file__).resolve().parents[2] / "benchmarks" / "results"
    d = json.loads((results / "CROP_ATTRIBUTION.json").read_text())
    assert report(d) == (results / "CROP_ATTRIBUTION.md").read_text()
    r = {s: {k: v["miou"] for k, v in d["rates"][s].items()} for s in d["sizes"]}
    small, large = d["sizes"]
    said = "\n".join(d["findings"])
    quoted = [
        r[small]["stand-in, bilinear, dominant"],
        r[small]["stand-in, DINO, dominant"],
        r[small]["no naming error, bilinear, dominant"],
        r[small]["no naming error, DINO, dominant"],
        r[small]["no naming error, bilinear, finest"],
        r[large]["stand-in, bilinear, dominant"],
        r[large]["no naming error, bilinear, dominant"],
    ]
    for v in quoted:
        assert f"{v:.3f}" in said, v
    # what the findings conclude, checked on the figures: attribution moves the default by under 0.01,
    # naming costs more than 0.1, and more pixels help the stand-in but not the namer without error
    for namer in ("stand-in", "no naming error"):
        gain = r[small][f"{namer}, DINO, dominant"] - r[small][f"{namer}, bilinear, dominant"]
        assert 0 <= gain < 0.01
    assert r[small]["no naming error, bilinear, dominant"] - r[small]["stand-in, bilinear, dominant"] > 0.1
    assert r[large]["stand-in, bilinear, dominant"] > r[small]["stand-in, bilinear, dominant"] + 0.02
    exact = "no naming error, bilinear, dominant"
    assert abs(r[large][exact] - r[small][exact]) < 0.01
    docs = (results.parents[1] / "docs" / "field.md").read_text()
    assert "CROP_ATTRIBUTION.md" in docs
    for v in quoted[:3]:
        assert f"{v:.3f}" in docs, v
