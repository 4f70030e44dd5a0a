"""The DINO stand-in (fmgs.features.standin_dino): saved and loaded as shipped, reached through the
registry as a dense regulariser, and the shipped weights group the pixels of one object on a generated
scene none of its training used."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from fmgs.features.standin_dino import (
    DenseStandinEncoder,
    DenseStandinNet,
    layer_norm,
    load_standin_dino,
    save_standin_dino,
)

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "benchmarks" / "standin_dino"


def _config(**kw) -> dict:
    return {"dim": 8, "width": 4, "short_side": 24, "mean": [0.5] * 3, "std": [0.25] * 3, **kw}


def test_save_and_load_give_the_same_features(tmp_path):
    torch.manual_seed(0)
    net = DenseStandinNet(8, 4)
    save_standin_dino(tmp_path, net, _config())
    enc = load_standin_dino(f"standin-dino:{tmp_path}")
    ref_net = DenseStandinNet(8, 4)
    ref_net.load_state_dict({k: v.half().float() for k, v in net.state_dict().items()})  # shipped float16
    ref = DenseStandinEncoder(ref_net, _config(), "x")
    img = torch.rand(30, 40, 3)
    out = enc.dense(img, (15, 20))
    assert out.shape == (15, 20, 8) and torch.isfinite(out).all()
    torch.testing.assert_close(out, ref.dense(img, (15, 20)), atol=1e-6, rtol=1e-5)
    assert enc.input_size(30, 40) == (24, 32) and enc.files.files["standin_dino.safetensors"]


def test_layer_norm_centres_and_scales_each_vector():
    f = layer_norm(torch.randn(2, 6, 5, 7) * 4 + 3, dim=1)
    torch.testing.assert_close(f.mean(1), torch.zeros(2, 5, 7), atol=1e-5, rtol=0)
    torch.testing.assert_close(f.var(1, unbiased=False), torch.ones(2, 5, 7), atol=1e-3, rtol=0)


def test_the_registry_loads_it_as_the_dense_regulariser(tmp_path):
    from fmgs.features.dino import load_dense_encoder
    from fmgs.features.models import ModelNotFoundError
    from fmgs.features.registry import parse_encoder_id

    save_standin_dino(tmp_path, DenseStandinNet(8, 4), _config())
    eid = f"standin-dino:{tmp_path}"
    assert parse_encoder_id(eid).family == "standin-dino"
    enc = load_dense_encoder(eid)
    assert isinstance(enc, DenseStandinEncoder) and enc.id == eid and enc.dim == 8
    with pytest.raises(ModelNotFoundError, match=r"standin_dino\.json"):
        load_dense_encoder(f"standin-dino:{tmp_path / 'nowhere'}")


def test_the_shipped_standin_groups_an_objects_pixels(tmp_path):
    """On an unseen world scene, two pixels of one object are more alike than two of different objects,
    by a clear margin (the margin measured on held-out scenes is in standin_dino.json)."""
    from PIL import Image

    from fmgs.synth import SynthConfig, generate

    cfg = json.loads((SHIPPED / "standin_dino.json").read_text())
    assert (SHIPPED / "standin_dino.safetensors").stat().st_size < 2**20
    seed = 7  # no training or held-out seed of the stand-ins
    assert seed not in cfg["train_seeds"] + cfg["heldout_seeds"]
    generate(tmp_path, SynthConfig(views=4, width=128, height=96, preset="world", objects=10, seed=seed))
    enc = load_standin_dino(f"standin-dino:{SHIPPED}")
    rng = np.random.default_rng(0)
    within, across = [], []
    for p in sorted((tmp_path / "images").iterdir()):
        img = torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0)
        lab = np.asarray(Image.open(tmp_path / "labels" / p.name)).astype(np.int64)
        f = torch.nn.functional.normalize(enc.dense(img, lab.shape), dim=-1)
        ys, xs = np.nonzero(lab >= 2)
        a, b = rng.integers(len(ys), size=(2, 3000))
        cos = (f[ys[a], xs[a]] * f[ys[b], xs[b]]).sum(-1).numpy()
        same = lab[ys[a], xs[a]] == lab[ys[b], xs[b]]
        within += cos[same].tolist()
        across += cos[~same].tolist()
    assert np.mean(within) > np.mean(across) + 0.3, (np.mean(within), np.mean(across))
