"""A build whose text encoder is fetched on first use from a hub (a local server speaking the hub's
protocol, HF_ENDPOINT), then a second build offline from the cache; the manifest records which files."""

from __future__ import annotations

import json

import pytest

from fmgs.cli import main
from tests.helpers.hub_server import HubRepo, HubServer
from tests.helpers.scenes import surface_ply
from tests.helpers.tiny_models import save_clip_folder, tiny_clip_model

pytest.importorskip("huggingface_hub")
pytestmark = pytest.mark.slow  # a build that downloads, then one offline
REPO = "acme/tiny-clip"


def test_a_build_downloads_its_encoder_then_builds_offline_from_the_cache(bpe_dir, tmp_path, monkeypatch):
    from fmgs.features.clip_tokenizer import clip_tokenizer_from_bpe_files
    from fmgs.synth import SynthConfig, generate

    bpe = bpe_dir
    vocab = len(clip_tokenizer_from_bpe_files(bpe / "vocab.json", bpe / "merges.txt"))
    repo = HubRepo.from_folder(REPO, save_clip_folder(tiny_clip_model(vocab), tmp_path / "clip", bpe))
    generate(tmp_path / "scene", SynthConfig(views=12, width=40, height=30, points=3000, supersample=1))
    surface_ply(tmp_path / "scene", tmp_path / "surface.ply")
    for k in ("FMGS_OFFLINE", "HF_HUB_OFFLINE"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty-hub-cache"))

    def build(name: str, *extra: str) -> dict:
        args = ["build", str(tmp_path / "scene"), "--name", name, "--models", str(tmp_path / "models"),
                "--targets", "labels", "--text-encoder", REPO, "--feature-scale", "0.5", "--device", "cpu",
                "--ply", str(tmp_path / "surface.ply"), "--field-steps", "60", *extra]  # fmt: skip
        assert main(args) == 0
        return json.loads((tmp_path / "models" / name / "manifest.json").read_text())

    with HubServer([repo]) as hub:
        monkeypatch.setenv("HF_ENDPOINT", hub.endpoint)
        first = build("fetched")
        assert first["encoder"]["id"] == REPO
        rec = first["extra"]["text_encoder"]
        assert rec == {"id": REPO, "revision": repo.commit, "files": rec["files"]}
        assert rec["files"]["model.safetensors"] == repo.etag("model.safetensors")  # its sha256
        served = len(hub.requests)
        assert any(r.startswith("GET") and r.endswith("/model.safetensors") for r in hub.requests)
        second = build("offline", "--offline")
        assert len(hub.requests) == served  # nothing asked of the hub
    rec2 = second["extra"]["text_encoder"]
    assert rec2 == rec
