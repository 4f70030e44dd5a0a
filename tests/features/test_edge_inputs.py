"""Inputs at the edges of what the feature extraction accepts: label ids outside the names, caches
resumed with other settings, stand-in folders and checkpoints that are not what their id says. Tiny,
offline and CPU."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from fmgs.cameras import Camera
from fmgs.errors import ValidationError
from fmgs.features import ExtractConfig, FeatureCache, FeatureCacheWriter, PyramidConfig, TargetInfo
from fmgs.features.extract import extract_labels, extract_targets, image_label_targets
from fmgs.features.labels import label_embedding_map

ROOT = Path(__file__).resolve().parents[2]


class EyeEncoder:
    """A fake text encoder: name i -> unit vector e_i."""

    id = "test/eye"
    dim = 4

    def encode_text(self, texts: list[str]) -> torch.Tensor:
        return torch.eye(self.dim)[: len(texts)]


class ColourEncoder:
    """A fake image encoder: a crop's mean colour plus a constant, normalised."""

    id = "test/colour"
    dim = 4
    image_size = 8

    def __call__(self, crops: torch.Tensor) -> torch.Tensor:
        m = crops.mean((2, 3))
        return torch.nn.functional.normalize(torch.cat([m, torch.full_like(m[:, :1], 0.1)], 1), dim=-1)


def _camera(w: int, h: int) -> Camera:
    K = torch.tensor([[w / 2, 0, w / 2], [0, w / 2, h / 2], [0, 0, 1.0]], dtype=torch.float64)
    return Camera(K, torch.eye(4, dtype=torch.float64), w, h)


class FakeDataset:
    """Frames of random 8x6 images with label PNGs (ids 0..2) in ``folder``/labels."""

    def __init__(self, folder: Path, n: int = 2) -> None:
        from PIL import Image

        self.root = folder
        self.frames = [SimpleNamespace(name=f"images/{k}.png", camera=_camera(8, 6)) for k in range(n)]
        g = torch.Generator().manual_seed(3)
        self.images = [torch.rand(6, 8, 3, generator=g) for _ in range(n)]
        (folder / "labels").mkdir(parents=True, exist_ok=True)
        for k in range(n):
            lab = (np.arange(48).reshape(6, 8) + k) % 3
            Image.fromarray(lab.astype(np.uint8)).save(folder / "labels" / f"{k}.png")

    def __len__(self) -> int:
        return len(self.frames)

    def image(self, i: int, scale: float = 1.0):
        return self.images[i], None


def test_an_ignored_label_id_needs_no_name():
    """255 ("void") ignored with three names: unsupervised, like 0, instead of an out-of-range error."""
    e = torch.eye(3)
    labels = torch.tensor([[1, 255], [2, 255]])
    t = label_embedding_map(labels, e, (2, 2), ignore={0, 255})
    assert t.mask.tolist() == [[True, False], [True, False]]
    assert torch.equal(t.clip[:, 1], torch.zeros(2, 3)) and torch.equal(t.clip[0, 0], e[1])
    with pytest.raises(ValidationError, match="label value 255"):  # not ignored: still refused
        label_embedding_map(labels, e, (2, 2))


def test_a_label_beyond_the_names_is_reported_with_its_label_image(tmp_path):
    from PIL import Image

    ds = FakeDataset(tmp_path, 1)
    bad = np.zeros((6, 8), np.uint16)
    bad[2, 3] = 7  # a 16-bit label PNG with an id the three names do not cover
    Image.fromarray(bad).save(tmp_path / "labels" / "0.png")
    cfg = ExtractConfig(progress=False)
    with pytest.raises(ValidationError, match=r"labels/0\.png.*label value 7 outside \[0, 3\)"):
        image_label_targets(ds, 0, tmp_path / "labels", torch.eye(3, 4), frozenset({0}), cfg)


def test_a_cache_resumed_with_other_label_settings_is_refused(tmp_path):
    ds = FakeDataset(tmp_path)
    out, labels, names = tmp_path / "c", tmp_path / "labels", ["bg", "a", "b"]
    cfg = ExtractConfig(feature_side=4, progress=False)
    cache = extract_labels(ds, out, labels, names, EyeEncoder(), cfg=cfg, indices=[0])
    assert cache.settings["feature_side"] == 4 and cache.settings["names"] == names
    files = sorted(p.name for p in out.iterdir())
    for other, change in (
        (dict(cfg=ExtractConfig(feature_side=8, progress=False)), "feature_side: 4 then, 8 now"),
        (dict(names=["bg", "b", "a"], cfg=cfg), "names"),
        (dict(ignore=frozenset(), cfg=cfg), "ignore"),
    ):
        kw = {"names": names, **other}
        with pytest.raises(ValidationError, match=f"other settings.*{change}.*new cache folder"):
            extract_labels(ds, out, labels, kw.pop("names"), EyeEncoder(), **kw)
        assert sorted(p.name for p in out.iterdir()) == files  # nothing written
        assert FeatureCache.open(out).image_names == [ds.frames[0].name]
    cache = extract_labels(ds, out, labels, names, EyeEncoder(), cfg=cfg)  # the same settings resume
    assert cache.complete(f.name for f in ds.frames) and cache.size(ds.frames[1].name) == (3, 4)


def test_a_cache_resumed_with_other_crop_scales_is_refused(tmp_path):
    ds = FakeDataset(tmp_path)
    out, cfg = tmp_path / "c", ExtractConfig(progress=False)
    extract_targets(ds, out, ColourEncoder(), pyramid=PyramidConfig(crop_px=8), cfg=cfg, indices=[0])
    other = PyramidConfig(scales=(0.25, 0.5), crop_px=8)
    with pytest.raises(ValidationError, match=r"other settings.*crop_scales"):
        extract_targets(ds, out, ColourEncoder(), pyramid=other, cfg=cfg)
    assert FeatureCache.open(out).image_names == [ds.frames[0].name]
    # the batch size does not change the maps: a resume with another one carries on
    cache = extract_targets(ds, out, ColourEncoder(), pyramid=PyramidConfig(crop_px=8, batch_size=1), cfg=cfg)
    assert len(cache) == 2


def test_settings_are_kept_when_not_given_and_adopted_by_an_unrecorded_cache(tmp_path):
    clip = {"clip": TargetInfo("test/clip", 2, True)}
    one = torch.tensor([[[1.0, 0.0]]])
    with FeatureCacheWriter(tmp_path / "old", clip) as w:  # made before caches recorded settings
        w.add("a", one)
    assert FeatureCache.open(tmp_path / "old").settings is None
    with FeatureCacheWriter(tmp_path / "old", clip, {"feature_side": 4}) as w:  # trusted, then recorded
        w.add("b", one)
    with FeatureCacheWriter(tmp_path / "old", clip) as w:  # a writer without settings keeps them
        assert w.settings == {"feature_side": 4}
    assert FeatureCache.open(tmp_path / "old").settings == {"feature_side": 4}
    with pytest.raises(ValidationError, match="feature_side: 4 then, 5 now"):
        FeatureCacheWriter(tmp_path / "old", clip, {"feature_side": 5})
    with pytest.raises(ValidationError, match="settings must be plain JSON"):
        FeatureCacheWriter(tmp_path / "new", clip, {"scale": float("nan")})
    man = tmp_path / "old" / "manifest.json"
    man.write_text(json.dumps({**json.loads(man.read_text()), "settings": [1]}))
    with pytest.raises(ValidationError, match="'settings' must be an object"):
        FeatureCache.open(tmp_path / "old")


def _copy(src: str, dst: Path) -> Path:
    return Path(shutil.copytree(ROOT / "benchmarks" / src, dst))


def test_broken_standin_folders_are_named(tmp_path):
    from fmgs.features.clip import load_image_encoder
    from fmgs.features.standin_dino import load_standin_dino
    from fmgs.features.standin_seg import load_standin_seg

    with pytest.raises(ValidationError, match="names no folder"):
        load_image_encoder("standin:")  # not the working directory
    s = _copy("standin", tmp_path / "s")
    (s / "standin.json").write_text("{")
    with pytest.raises(ValidationError, match=r"standin\.json: cannot read the config"):
        load_image_encoder(f"standin:{s}")
    (s / "standin.json").write_text("{}")
    with pytest.raises(ValidationError, match=r"do not make the model \(KeyError: 'dim'"):
        load_image_encoder(f"standin:{s}")
    shutil.copy(ROOT / "benchmarks" / "standin" / "standin.json", s / "standin.json")
    (s / "standin.safetensors").write_bytes(b"truncated")
    with pytest.raises(ValidationError, match=r"standin\.safetensors: cannot read the weights"):
        load_image_encoder(f"standin:{s}")
    d = _copy("standin_dino", tmp_path / "d")
    cfg = json.loads((d / "standin_dino.json").read_text())
    (d / "standin_dino.json").write_text(json.dumps({**cfg, "dim": cfg["dim"] + 1}))
    with pytest.raises(ValidationError, match=r"do not make the model \(RuntimeError"):
        load_standin_dino(f"standin-dino:{d}")
    g = _copy("standin_seg", tmp_path / "g")
    (g / "standin_seg.json").write_text("[]")
    with pytest.raises(ValidationError, match="expected a JSON object"):
        load_standin_seg(f"standin-seg:{g}")


def test_ids_that_name_no_clip_checkpoint_are_refused_by_name(tmp_path):
    from fmgs.features.clip import load_image_encoder

    bad = tmp_path / "open_clip_model.safetensors"
    bad.write_bytes(b"<html>not found</html>")  # what a failed download leaves
    with pytest.raises(ValidationError, match=r"open_clip_model\.safetensors: not a readable safetensors"):
        load_image_encoder(f"openclip-file:{bad}")
    dino = ROOT / "benchmarks" / "standin_dino"
    with pytest.raises(ValidationError, match="standin-dino model cannot serve as the image encoder"):
        load_image_encoder(f"standin-dino:{dino}")


def test_the_ray_driver_records_the_settings_the_serial_driver_does(tmp_path):
    """extract_features_ray writes its manifest from the spec alone (no encoder loaded there): the same
    settings as the serial build's, so the two caches stay equal and either resumes the other."""
    from fmgs.build import extract_features
    from fmgs.build.config import TargetSpec
    from fmgs.features.distributed import TargetJob, job_settings

    ds = FakeDataset(tmp_path)
    (tmp_path / "scene.json").write_text(json.dumps({"label_names": ["bg", "a", "b"]}))
    bench = ROOT / "benchmarks"
    clip = {
        "clip_model": f"standin:{bench / 'standin'}",
        "dino_model": f"standin-dino:{bench / 'standin_dino'}",
    }
    seg = f"standin-seg:{bench / 'standin_seg'}"
    specs = [
        TargetSpec(kind="labels", text_encoder="sentence-transformers/all-MiniLM-L6-v2", feature_side=4),
        TargetSpec(**clip, segmenter=seg, crop_scales=(0.25, 0.5), feature_scale=0.5),
    ]
    for k, spec in enumerate(specs):
        cache = extract_features(ds, tmp_path / f"c{k}", spec, "cpu", progress=False)
        assert cache.settings == job_settings(TargetJob(str(tmp_path), spec), ds)
        assert cache.settings["kind"] == spec.kind
