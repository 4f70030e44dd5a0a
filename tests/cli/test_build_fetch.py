"""A build's models from a hub (a local server speaking the hub's protocol, HF_ENDPOINT): every model
resolved before the first stage (offline with an empty cache: all missing ones named at once, nothing
trained); a build whose text encoder is fetched on first use, then one offline from the cache; a
CLIP-target build whose manifest records each model's revision and the sha256 of its bytes; a rerun that
keeps the revisions its work folder recorded after the hub moved on."""

from __future__ import annotations

import hashlib
import json

import pytest

from fmgs.cli import main
from tests.helpers.hub_server import HubRepo, HubServer
from tests.helpers.scenes import surface_ply
from tests.helpers.tiny_models import save_clip_folder, tiny_clip_model

pytest.importorskip("huggingface_hub", reason="in requirements/cpu.txt (CI)")
transformers = pytest.importorskip("transformers", reason="in requirements/cpu.txt (CI)")
CLIP = "acme/tiny-clip"
DINO = "acme/tiny-dino"


@pytest.fixture(scope="module")
def repos(bpe_dir, tmp_path_factory):
    """Tiny random-weight CLIP and DINO (ViT, patch 8) repositories in hub layout."""
    import torch

    from fmgs.features.clip_tokenizer import clip_tokenizer_from_bpe_files

    tmp = tmp_path_factory.mktemp("repos")
    vocab = len(clip_tokenizer_from_bpe_files(bpe_dir / "vocab.json", bpe_dir / "merges.txt"))
    clip = HubRepo.from_folder(CLIP, save_clip_folder(tiny_clip_model(vocab), tmp / "clip", bpe_dir))
    torch.manual_seed(3)
    small = dict(hidden_size=16, num_hidden_layers=1, num_attention_heads=2, intermediate_size=32)
    vit = transformers.ViTModel(transformers.ViTConfig(image_size=32, patch_size=8, **small), False)
    vit.save_pretrained(tmp / "dino")
    return clip, HubRepo.from_folder(DINO, tmp / "dino")


@pytest.fixture
def online(tmp_path, monkeypatch):
    """Downloads on, an empty hub cache, hub calls timing out after 2 s."""
    for k in ("FMGS_OFFLINE", "HF_HUB_OFFLINE"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub-cache"))
    monkeypatch.setenv("FMGS_HUB_TIMEOUT", "2")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from fmgs.synth import SynthConfig, generate

    tmp = tmp_path_factory.mktemp("scene")
    generate(tmp / "scene", SynthConfig(views=12, width=40, height=30, points=3000, supersample=1))
    surface_ply(tmp / "scene", tmp / "surface.ply")
    return tmp


def build_args(scene, models, name: str, *extra: str) -> list[str]:
    return ["build", str(scene / "scene"), "--name", name, "--models", str(models), "--feature-scale",
            "0.5", "--device", "cpu", "--ply", str(scene / "surface.ply"), "--field-steps", "60",
            *extra]  # fmt: skip


def test_offline_with_an_empty_cache_names_every_missing_model_before_any_stage(
    tmp_path, monkeypatch, capsys
):
    """The tester's build trained the whole geometry before finding CLIP missing, and named DINO only on
    the next run: now both are named at once, with the flag that turned downloads off, and no stage ran."""
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty-hub-cache"))
    (tmp_path / "photos").mkdir()
    models = tmp_path / "models"
    args = ["build", str(tmp_path / "photos"), "--name", "s", "--models", str(models),
            "--clip-model", CLIP, "--dino-model", DINO, "--device", "cpu", "--offline"]  # fmt: skip
    assert main(args) == 2
    out = capsys.readouterr()
    assert "2 model(s) needed are not available" in out.err and CLIP in out.err and DINO in out.err
    assert out.err.count("downloads are off (fmgs build --offline)") == 2 and "FMGS_OFFLINE" not in out.err
    assert f"hf download {CLIP}" in out.err and f"hf download {DINO}" in out.err
    assert "[1/5]" not in out.out  # no stage started
    work = models / ".work" / "s"
    assert not (work / "gs").exists() and not (work / "sfm").exists() and not (work / "features").exists()
    assert not (models / "s").exists()


def test_a_model_missing_on_the_hub_is_named_before_any_stage(repos, online, tmp_path, monkeypatch, capsys):
    clip, _ = repos
    (tmp_path / "photos").mkdir()
    with HubServer([clip]) as hub:  # CLIP there, DINO not
        monkeypatch.setenv("HF_ENDPOINT", hub.endpoint)
        args = ["build", str(tmp_path / "photos"), "--name", "s", "--models", str(tmp_path / "models"),
                "--clip-model", CLIP, "--dino-model", DINO, "--device", "cpu"]  # fmt: skip
        assert main(args) == 2
    err = capsys.readouterr().err
    assert f"model {DINO!r} not found (the hub at {hub.endpoint} has no such model)" in err
    assert f"downloading model {CLIP} (revision main) from {hub.endpoint}" in err  # fetched meanwhile
    assert not (tmp_path / "models" / ".work" / "s" / "sfm").exists()


def test_a_rerun_keeps_the_revisions_its_work_folder_recorded(repos, online, tmp_path, monkeypatch):
    """The hub moves on between two runs of one build: the rerun takes the commits the first run used
    (its stages reuse what was made with them), on this machine or one with an empty cache, unless
    --allow-newer-model."""
    from fmgs.build.config import TargetSpec
    from fmgs.build.pipeline import WORK_MODELS, resolve_build_models

    clip, dino = repos
    spec = TargetSpec(clip_model=CLIP, dino_model=DINO)
    work = tmp_path / "work"
    work.mkdir()
    with HubServer([clip, dino]) as hub:
        monkeypatch.setenv("HF_ENDPOINT", hub.endpoint)
        first = resolve_build_models(spec, work)
        assert set(first) == {"clip", "dino", "text_encoder"} and first["text_encoder"] is first["clip"]
        recorded = json.loads((work / WORK_MODELS).read_text())
        assert recorded["dino"] == {"encoder": DINO, **first["dino"].record()}
        weights = dino.files["model.safetensors"]
        newer = hub.move_on(DINO, {**dino.files, "model.safetensors": weights[:-4] + bytes(4)})
        assert resolve_build_models(spec, work)["dino"].revision == dino.commit  # from this cache
        monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "other-machine"))  # nothing cached there
        again = resolve_build_models(spec, work)
        assert again["dino"].revision == dino.commit and again["dino"].files == first["dino"].files
        latest = resolve_build_models(spec, work, allow_newer_model=True)
        assert latest["dino"].revision == newer.commit
        assert json.loads((work / WORK_MODELS).read_text())["dino"]["revision"] == newer.commit


@pytest.mark.slow  # a build that downloads, then one offline
def test_a_build_downloads_its_encoder_then_builds_offline_from_the_cache(
    repos, scene, online, tmp_path, monkeypatch, capsys
):
    clip, _ = repos
    models = tmp_path / "models"

    def build(name: str, *extra: str) -> dict:
        args = build_args(scene, models, name, "--targets", "labels", "--text-encoder", CLIP, *extra)
        assert main(args) == 0
        return json.loads((models / name / "manifest.json").read_text())

    with HubServer([clip]) as hub:
        monkeypatch.setenv("HF_ENDPOINT", hub.endpoint)
        first = build("fetched")
        assert f"downloading model {CLIP} (revision main) from {hub.endpoint}" in capsys.readouterr().err
        assert first["encoder"]["id"] == CLIP
        rec = first["extra"]["text_encoder"]
        assert rec == {"id": CLIP, "revision": clip.commit, "files": rec["files"]}
        assert rec["files"]["model.safetensors"] == clip.etag("model.safetensors")  # its sha256
        assert first["extra"]["models"] == {"text_encoder": rec}
        served = len(hub.requests)
        assert any(r.startswith("GET") and r.endswith("/model.safetensors") for r in hub.requests)
        second = build("offline", "--offline")
        assert len(hub.requests) == served  # nothing asked of the hub
    assert second["extra"]["text_encoder"] == rec


@pytest.mark.slow  # a CLIP-target build (crop pyramid and DINO on 12 views)
def test_a_clip_target_build_records_every_model_from_its_bytes(repos, scene, online, tmp_path, monkeypatch):
    clip, dino = repos
    models = tmp_path / "models"
    with HubServer([clip, dino]) as hub:
        monkeypatch.setenv("HF_ENDPOINT", hub.endpoint)
        args = build_args(scene, models, "clipped", "--clip-model", CLIP, "--dino-model", DINO)
        assert main(args) == 0
    m = json.loads((models / "clipped" / "manifest.json").read_text())
    extra = m["extra"]
    assert set(extra["models"]) == {"clip", "dino", "text_encoder"}
    for role, repo in (("clip", clip), ("dino", dino), ("text_encoder", clip)):
        rec = extra["models"][role]
        assert rec["id"] == repo.repo_id and rec["revision"] == repo.commit
        for name, sha in rec["files"].items():
            assert sha == hashlib.sha256(repo.files[name]).hexdigest(), (role, name)
    assert extra["text_encoder"] == extra["models"]["text_encoder"]
    assert extra["targets"]["text_encoder"] == CLIP  # the encoder that answers queries, not MiniLM
