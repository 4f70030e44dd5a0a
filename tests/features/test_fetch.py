"""Models fetched on first use: the real huggingface_hub client over a real socket to a local server that
speaks the hub's download protocol (tests/helpers/hub_server.py), serving random-weight models saved in
hub layout. Download, then offline from the cache; offline with an empty cache; an interrupted download;
what a download takes; the text encoder loaded through it; the server's switch."""

from __future__ import annotations

import hashlib

import pytest
import torch

from fmgs.features.models import (
    ModelNotFoundError,
    fetch_command,
    fetch_model,
    offline_mode,
)
from tests.helpers.hub_server import HubRepo, HubServer
from tests.helpers.tiny_models import save_clip_folder, tiny_clip_model

transformers = pytest.importorskip("transformers")
pytest.importorskip("huggingface_hub")

REPO = "acme/tiny-clip"


@pytest.fixture(scope="module")
def clip_repo(bpe_dir, tmp_path_factory):
    """A tiny random-weight CLIP in hub layout, plus an open_clip checkpoint and flax weights beside it
    (which a download must leave behind)."""
    from fmgs.features.clip_tokenizer import clip_tokenizer_from_bpe_files

    bpe = bpe_dir
    vocab = len(clip_tokenizer_from_bpe_files(bpe / "vocab.json", bpe / "merges.txt"))
    model = tiny_clip_model(vocab)
    folder = save_clip_folder(model, tmp_path_factory.mktemp("hub") / "tiny-clip", bpe)
    repo = HubRepo.from_folder(REPO, folder)
    repo.files["open_clip_model.safetensors"] = b"\0" * 4096
    repo.files["flax_model.msgpack"] = b"\1" * 4096
    return repo, model


@pytest.fixture
def hub(clip_repo, tmp_path, monkeypatch):
    """The hub server on loopback, HF_ENDPOINT pointing at it, an empty hub cache, downloads on."""
    repo, _ = clip_repo
    with HubServer([repo, HubRepo("acme/no-weights", {"config.json": b"{}", "README.md": b"hi"})]) as server:
        monkeypatch.setenv("HF_ENDPOINT", server.endpoint)
        monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub-cache"))
        for k in ("FMGS_OFFLINE", "HF_HUB_OFFLINE"):
            monkeypatch.delenv(k, raising=False)
        yield server, repo


def test_download_then_offline_from_the_cache(hub, monkeypatch):
    server, repo = hub
    got = fetch_model(REPO)
    assert got.source == "download" and got.revision == repo.commit
    assert (got.path / "config.json").is_file()
    weights = repo.files["model.safetensors"]
    assert got.files["model.safetensors"] == hashlib.sha256(weights).hexdigest()
    assert (got.path / "model.safetensors").read_bytes() == weights
    # Only the transformers files: not the open_clip checkpoint, not the flax weights.
    fetched = {r.rsplit("/", 1)[1] for r in server.requests if r.startswith("GET") and "/resolve/" in r}
    assert "model.safetensors" in fetched and "vocab.json" in fetched
    assert not {"open_clip_model.safetensors", "flax_model.msgpack"} & fetched
    # Second run, offline: from the cache, no request.
    n = len(server.requests)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    again = fetch_model(REPO)
    assert again.source == "cache" and again.path == got.path and again.files == got.files
    assert len(server.requests) == n
    assert again.record() == {"id": REPO, "revision": repo.commit, "files": got.files}


def test_offline_with_an_empty_cache_names_the_model_revision_and_command(hub, monkeypatch):
    server, _ = hub
    monkeypatch.setenv("FMGS_OFFLINE", "1")
    with pytest.raises(ModelNotFoundError) as e:
        fetch_model(REPO, revision="v1.0")
    msg = str(e.value)
    assert REPO in msg and "revision v1.0" in msg and "FMGS_OFFLINE=1" in msg
    assert fetch_command(REPO, "v1.0") in msg and fetch_command(REPO, "v1.0").startswith(
        f"hf download {REPO}"
    )
    assert server.requests == []
    with pytest.raises(ModelNotFoundError, match="--offline"):
        fetch_model(REPO, offline=True)
    assert offline_mode() and not offline_mode(False)


def test_a_dropped_connection_resumes_where_it_stopped(hub):
    """huggingface_hub resumes a transfer cut short with a Range request from the last whole 10 MiB chunk
    it wrote (a smaller file starts again), within the same run."""
    server, _ = hub
    weights = bytes(range(256)) * 100_000  # 25.6 MB
    server.state.repos["acme/big"] = HubRepo("acme/big", {"config.json": b"{}", "model.safetensors": weights})
    server.state.cut_after["model.safetensors"] = (12_000_000, 2)  # two tries cut short, the third whole
    got = fetch_model("acme/big")
    assert (got.path / "model.safetensors").read_bytes() == weights
    gets = [r for r in server.requests if r.startswith("GET") and "/model.safetensors" in r]
    assert len(gets) == 3 and "bytes=" not in gets[0]
    assert gets[1].endswith("bytes=10485760-") and gets[2].endswith("bytes=20971520-")


def test_a_failed_download_leaves_nothing_half_written(hub, tmp_path):
    server, repo = hub
    size = len(repo.files["model.safetensors"])
    server.state.cut_after["model.safetensors"] = (size // 3, 100)  # every try cut short
    with pytest.raises(ModelNotFoundError, match=r"download from .* failed"):
        fetch_model(REPO)
    cache = tmp_path / "hub-cache"
    blobs = [p for p in cache.rglob("*") if p.is_file() and "blobs" in p.parts]
    assert all(p.stat().st_size != size // 3 for p in blobs) and not list(cache.rglob("*.incomplete"))
    assert not list(cache.rglob("model.safetensors"))  # no snapshot entry for the cut file
    with pytest.raises(ModelNotFoundError):  # offline, nothing usable is found
        fetch_model(REPO, offline=True)
    server.state.cut_after.clear()
    got = fetch_model(REPO)
    assert (got.path / "model.safetensors").read_bytes() == repo.files["model.safetensors"]


def test_unknown_repositories_revisions_and_weightless_repos_are_named(hub):
    with pytest.raises(ModelNotFoundError, match="acme/nothing-here"):
        fetch_model("acme/nothing-here")
    with pytest.raises(ModelNotFoundError, match="revision no-such-tag"):
        fetch_model(REPO, revision="no-such-tag")
    with pytest.raises(ModelNotFoundError, match="no transformers weights"):
        fetch_model("acme/no-weights")


def test_the_text_encoder_loads_through_a_download_and_matches_the_model(hub, clip_repo, monkeypatch):
    from fmgs.features.text import load_text_encoder

    _, model = clip_repo
    enc = load_text_encoder(REPO)
    assert enc.files is not None and enc.files.source == "download"
    tok = enc.tokenizer(["a red cube"], padding=True, return_tensors="pt")
    with torch.inference_mode():
        ref = model.get_text_features(**tok)
        ref = getattr(ref, "pooler_output", ref)
    assert torch.allclose(
        enc.encode_text(["a red cube"]), torch.nn.functional.normalize(ref, dim=-1), atol=1e-5
    )
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    assert load_text_encoder(REPO).files.source == "cache"


def test_the_server_setting_forbids_downloads(hub):
    from fmgs_server.server import _text_encoder

    server, _ = hub
    with pytest.raises(ModelNotFoundError, match="downloads are off"):
        _text_encoder("cpu", downloads=False)(REPO)
    assert server.requests == []
    assert _text_encoder("cpu", downloads=True)(REPO).files.source == "download"
