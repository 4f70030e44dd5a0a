"""Models fetched on first use: the real huggingface_hub client over a real socket to a local server that
speaks the hub's download protocol (tests/helpers/hub_server.py), serving random-weight models saved in
hub layout. Download, then offline from the cache; offline with an empty cache; an interrupted download;
what a download takes; the text encoder loaded through it; the server's switch. Then what must not be
trusted: bytes other than the advertised ones, a garbled header (from the hub, and gone bad in the
cache), a transfer broken off on every try, HTTP 500 from each endpoint, a hub that never answers or
refuses connections, and a repository that moved on (the recorded revision is loaded, other bytes are
refused). Each ends in a clear error, nothing bad in the cache, and a working next run."""

from __future__ import annotations

import hashlib
import socket
import time

import numpy as np
import pytest
import torch

from fmgs.errors import ValidationError
from fmgs.features.models import (
    HubUnreachableError,
    ModelIntegrityError,
    ModelMismatchError,
    ModelNotFoundError,
    ModelPin,
    fetch_command,
    fetch_model,
    hub_timeout,
    offline_mode,
)
from tests.helpers.hub_server import (
    ENDPOINTS,
    HubRepo,
    HubServer,
    SilentHub,
    flip_tail,
    garble_header,
    skip_backoff,
)
from tests.helpers.tiny_models import save_clip_folder, tiny_clip_model

transformers = pytest.importorskip("transformers", reason="in requirements/cpu.txt (CI)")
pytest.importorskip("huggingface_hub", reason="in requirements/cpu.txt (CI)")

REPO = "acme/tiny-clip"
WEIGHTS = "model.safetensors"


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


@pytest.fixture(scope="module")
def newer_weights(clip_repo, tmp_path_factory):
    """model.safetensors of another tiny CLIP of the same shape (the repository's next commit)."""
    _, model = clip_repo
    other = tiny_clip_model(model.config.text_config.vocab_size, seed=7)
    d = tmp_path_factory.mktemp("newer")
    other.save_pretrained(d)
    return (d / WEIGHTS).read_bytes()


@pytest.fixture
def hub(clip_repo, tmp_path, monkeypatch):
    """The hub server on loopback, HF_ENDPOINT pointing at it, an empty hub cache, downloads on, hub calls
    timing out after 2 s."""
    repo, _ = clip_repo
    with HubServer([repo, HubRepo("acme/no-weights", {"config.json": b"{}", "README.md": b"hi"})]) as server:
        monkeypatch.setenv("HF_ENDPOINT", server.endpoint)
        monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub-cache"))
        monkeypatch.setenv("FMGS_HUB_TIMEOUT", "2")
        for k in ("FMGS_OFFLINE", "HF_HUB_OFFLINE"):
            monkeypatch.delenv(k, raising=False)
        yield server, repo


def cached(tmp_path) -> dict[str, bytes]:
    """{name: bytes} of every file in the hub cache's blobs and snapshots (links followed)."""
    root = tmp_path / "hub-cache"
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in root.rglob("*")
        if p.is_file() and {"blobs", "snapshots"} & set(p.parts)
    }


def assert_nothing_bad_cached(tmp_path, bad: bytes | None = None) -> None:
    """No weights in the cache but good ones (with ``bad``: not those bytes), no partial file."""
    files = cached(tmp_path)
    assert not [n for n in files if n.endswith(".incomplete")]
    if bad is not None:
        assert bad not in files.values()
    for name, data in files.items():
        if name.endswith(WEIGHTS):  # a snapshot's link: its blob holds what the hub advertised
            assert name.startswith("models--") and hashlib.sha256(data).hexdigest() in {
                hashlib.sha256(v).hexdigest() for v in files.values()
            }


def test_download_then_offline_from_the_cache(hub, monkeypatch, capsys):
    server, repo = hub
    got = fetch_model(REPO)
    assert got.source == "download" and got.revision == repo.commit
    assert (got.path / "config.json").is_file()
    weights = repo.files[WEIGHTS]
    assert got.files[WEIGHTS] == hashlib.sha256(weights).hexdigest()
    assert got.files["config.json"] == hashlib.sha256(repo.files["config.json"]).hexdigest()  # the bytes'
    assert (got.path / WEIGHTS).read_bytes() == weights
    said = capsys.readouterr().err
    assert f"downloading model {REPO} (revision main) from {server.endpoint}" in said  # one line says it
    # Only the transformers files: not the open_clip checkpoint, not the flax weights.
    fetched = {r.rsplit("/", 1)[1] for r in server.requests if r.startswith("GET") and "/resolve/" in r}
    assert WEIGHTS in fetched and "vocab.json" in fetched
    assert not {"open_clip_model.safetensors", "flax_model.msgpack"} & fetched
    # Second run, offline: from the cache, no request.
    n = len(server.requests)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    again = fetch_model(REPO)
    assert again.source == "cache" and again.path == got.path and again.files == got.files
    assert len(server.requests) == n
    assert again.record() == {"id": REPO, "revision": repo.commit, "files": got.files}
    assert "downloading" not in capsys.readouterr().err


def test_offline_with_an_empty_cache_names_the_model_revision_what_said_so_and_command(hub, monkeypatch):
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
    monkeypatch.delenv("FMGS_OFFLINE")
    with pytest.raises(ModelNotFoundError) as e:  # the flag that said so, not an env var it set
        fetch_model(REPO, offline="fmgs build --offline")
    assert "downloads are off (fmgs build --offline)" in str(e.value) and "FMGS_OFFLINE" not in str(e.value)
    assert server.requests == []
    monkeypatch.setenv("FMGS_OFFLINE", "1")
    assert offline_mode() and not offline_mode(False) and offline_mode("--offline")


def test_a_dropped_connection_resumes_where_it_stopped(hub):
    """huggingface_hub resumes a transfer cut short with a Range request from the last whole 10 MiB chunk
    it wrote (a smaller file starts again), within the same run."""
    from safetensors.numpy import save

    server, _ = hub
    weights = save({"w": np.frombuffer(bytes(range(256)) * 100_000, dtype=np.uint8)})  # 25.6 MB
    server.state.repos["acme/big"] = HubRepo("acme/big", {"config.json": b"{}", WEIGHTS: weights})
    server.state.cut_after[WEIGHTS] = (12_000_000, 2)  # two tries cut short, the third whole
    got = fetch_model("acme/big")
    assert (got.path / WEIGHTS).read_bytes() == weights
    gets = [r for r in server.requests if r.startswith("GET") and "/model.safetensors" in r]
    assert len(gets) == 3 and "bytes=" not in gets[0]
    assert gets[1].endswith("bytes=10485760-") and gets[2].endswith("bytes=20971520-")


def test_a_transfer_broken_off_on_every_try_fails_clearly_and_leaves_nothing(hub, tmp_path, monkeypatch):
    server, repo = hub
    skip_backoff(monkeypatch)
    size = len(repo.files[WEIGHTS])
    server.state.cut_after[WEIGHTS] = (size // 3, 100)  # every try cut short
    with pytest.raises(HubUnreachableError) as e:
        fetch_model(REPO)
    msg = str(e.value)
    assert f"download of model {REPO!r} (revision main) from {server.endpoint} failed" in msg
    assert "nothing partial was kept: the next run starts the file again" in msg and "resume" not in msg
    assert_nothing_bad_cached(tmp_path)
    assert not list((tmp_path / "hub-cache").rglob(WEIGHTS))  # no snapshot entry for the cut file
    with pytest.raises(ModelNotFoundError):  # offline, nothing usable is found
        fetch_model(REPO, offline=True)
    server.state.cut_after.clear()
    got = fetch_model(REPO)
    assert (got.path / WEIGHTS).read_bytes() == repo.files[WEIGHTS]


def test_bytes_other_than_the_advertised_ones_are_refused_and_deleted(hub, tmp_path, capsys):
    """A mirror serving other bytes than the sha256 it advertises (the last 256 bytes flipped: the header
    parses, the weights differ): the download is refused, deleted, and the next run takes good bytes."""
    server, repo = hub
    bad = flip_tail(repo.files[WEIGHTS])
    server.state.serve_instead[WEIGHTS] = bad
    with pytest.raises(ModelIntegrityError) as e:
        fetch_model(REPO)
    msg = str(e.value)
    good_sha, bad_sha = repo.etag(WEIGHTS), hashlib.sha256(bad).hexdigest()
    assert REPO in msg and WEIGHTS in msg and bad_sha in msg and good_sha in msg
    assert "Deleted from the hub cache" in msg and server.endpoint in msg
    assert_nothing_bad_cached(tmp_path, bad)
    with pytest.raises(ModelNotFoundError):  # nothing a later offline run could take for the model
        fetch_model(REPO, offline=True)
    server.state.serve_instead.clear()
    got = fetch_model(REPO)
    assert got.source == "download" and got.files[WEIGHTS] == good_sha


def test_a_garbled_header_from_the_hub_is_a_clear_error_and_is_not_kept(hub, tmp_path):
    """A repository whose safetensors header is garbled (its advertised sha256 is that of the garbled
    file: nothing to catch but the header): refused on download, not left in the cache."""
    server, repo = hub
    broken = garble_header(repo.files[WEIGHTS])
    server.state.repos["acme/garbled"] = HubRepo("acme/garbled", {**repo.files, WEIGHTS: broken})
    for _ in range(2):  # every run says so, none finds it cached
        with pytest.raises(ModelIntegrityError, match="garbled header") as e:
            fetch_model("acme/garbled")
        assert "acme/garbled" in str(e.value) and WEIGHTS in str(e.value)
        assert_nothing_bad_cached(tmp_path, broken)


def test_a_cached_copy_gone_bad_is_caught_when_first_used_then_fetched_again(hub, tmp_path, monkeypatch):
    """Weights damaged in the cache after the download (content, then the header): the first load in a
    process checks them against the hub's sha256, deletes them and says so; offline that is the error,
    online the next fetch downloads them again. A second load of good files reads no byte again."""
    from fmgs.features import models
    from fmgs.features.text import load_text_encoder

    _, repo = hub
    got = fetch_model(REPO)
    blob = (got.path / WEIGHTS).resolve()
    for damage in (flip_tail, garble_header):
        blob.write_bytes(damage(repo.files[WEIGHTS]))
        with pytest.raises(ModelIntegrityError) as e:  # the loader, not safetensors' own traceback
            load_text_encoder(REPO, offline=True)
        assert WEIGHTS in str(e.value) and "Deleted from the hub cache" in str(e.value)
        assert not blob.exists() and not (got.path / WEIGHTS).exists()
        again = fetch_model(REPO)  # downloads are on: fetched again in this run
        assert again.source == "download" and blob.read_bytes() == repo.files[WEIGHTS]
    hashed = []
    real = models.hashlib.sha256
    monkeypatch.setattr(models.hashlib, "sha256", lambda *a: hashed.append(1) or real(*a))
    assert fetch_model(REPO, offline=True).source == "cache"
    assert hashed == []  # checked once per process: the same file, size and time are not read again


def test_weights_that_fail_to_load_are_evicted_with_a_clear_error(hub, tmp_path):
    """A header that parses but describes tensors the bytes cannot hold (F32 [10] in 8 bytes): the
    transformers load fails in safetensors; the loader names the model and drops the cached weights."""
    import json

    from fmgs.features.text import load_text_encoder

    server, repo = hub
    header = json.dumps({"w": {"dtype": "F32", "shape": [10], "data_offsets": [0, 8]}}).encode()
    odd = len(header).to_bytes(8, "little") + header + b"\0" * 8
    server.state.repos["acme/odd"] = HubRepo("acme/odd", {**repo.files, WEIGHTS: odd})
    with pytest.raises(ModelIntegrityError) as e:
        load_text_encoder("acme/odd")
    assert "acme/odd" in str(e.value) and "cannot be read" in str(e.value) and "deleted" in str(e.value)
    assert odd not in cached(tmp_path).values()


@pytest.mark.parametrize("endpoint", ENDPOINTS)
def test_an_http_500_from_each_endpoint_names_the_hub_and_the_url(hub, tmp_path, monkeypatch, endpoint):
    server, repo = hub
    skip_backoff(monkeypatch)
    server.state.fail[endpoint] = 500
    with pytest.raises(HubUnreachableError) as e:
        fetch_model(REPO)
    msg = str(e.value)
    assert f"the hub at {server.endpoint} failed for model {REPO!r}" in msg and "HTTP 500" in msg
    assert "not found" not in msg
    assert_nothing_bad_cached(tmp_path)
    server.state.fail.clear()
    assert fetch_model(REPO).files[WEIGHTS] == repo.etag(WEIGHTS)


def test_a_hub_that_never_answers_fails_within_the_timeout(clip_repo, tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub-cache"))
    monkeypatch.setenv("FMGS_HUB_TIMEOUT", "1")
    monkeypatch.delenv("FMGS_OFFLINE")
    with SilentHub() as silent:
        monkeypatch.setenv("HF_ENDPOINT", silent.endpoint)
        t0 = time.perf_counter()
        with pytest.raises(HubUnreachableError) as e:
            fetch_model(REPO)
        took = time.perf_counter() - t0
    msg = str(e.value)
    assert took < 3, took  # one 1 s timeout, not huggingface_hub's retries with backoff
    assert f"cannot reach the hub at {silent.endpoint} for model {REPO!r}" in msg
    assert "no answer within 1 s" in msg and "FMGS_HUB_TIMEOUT" in msg and silent.accepted >= 1
    assert_nothing_bad_cached(tmp_path)


@pytest.mark.parametrize("endpoint", ["head", "get"])
def test_an_endpoint_that_stops_answering_mid_download_fails_within_the_timeout(hub, tmp_path, endpoint):
    server, repo = hub
    server.state.stall.add(endpoint)
    t0 = time.perf_counter()
    with pytest.raises(HubUnreachableError, match=r"no answer within 2 s"):
        fetch_model(REPO)
    assert time.perf_counter() - t0 < 6
    assert_nothing_bad_cached(tmp_path)
    server.state.stall.clear()
    assert fetch_model(REPO).files[WEIGHTS] == repo.etag(WEIGHTS)


def test_a_refused_connection_says_cannot_reach_not_not_found(tmp_path, monkeypatch):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setenv("HF_ENDPOINT", f"http://127.0.0.1:{port}")
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub-cache"))
    monkeypatch.delenv("FMGS_OFFLINE")
    with pytest.raises(HubUnreachableError) as e:
        fetch_model(REPO)
    assert f"cannot reach the hub at http://127.0.0.1:{port}" in str(e.value)
    assert "not found" not in str(e.value)


def test_the_hub_timeout_is_read_from_the_environment(monkeypatch):
    monkeypatch.delenv("FMGS_HUB_TIMEOUT", raising=False)
    assert hub_timeout() == 10.0
    monkeypatch.setenv("FMGS_HUB_TIMEOUT", "2.5")
    assert hub_timeout() == 2.5
    for bad in ("0", "-1", "soon", "inf"):
        monkeypatch.setenv("FMGS_HUB_TIMEOUT", bad)
        with pytest.raises(ValidationError, match="FMGS_HUB_TIMEOUT"):
            hub_timeout()


def test_unknown_repositories_revisions_and_weightless_repos_are_named(hub):
    server, _ = hub
    with pytest.raises(ModelNotFoundError, match=f"the hub at {server.endpoint} has no such model"):
        fetch_model("acme/nothing-here")
    with pytest.raises(ModelNotFoundError, match="has the model but no revision no-such-tag"):
        fetch_model(REPO, revision="no-such-tag")
    with pytest.raises(ModelNotFoundError, match="no transformers weights"):
        fetch_model("acme/no-weights")


def test_a_repository_that_moved_on_still_gives_the_recorded_revision(hub, tmp_path, newer_weights):
    """Built at one commit, the hub then moves on: asking for the recorded commit and hashes gives those
    files, from the cache or (an empty cache) the hub; other bytes under that name are refused, and not
    deleted (they may serve another scene)."""
    server, repo = hub
    first = fetch_model(REPO)
    pin = ModelPin.from_record(first.record())
    assert pin.revision == repo.commit and dict(pin.files) == first.files
    newer = server.move_on(REPO, {**repo.files, WEIGHTS: newer_weights})
    same = fetch_model(REPO, revision=pin.revision, expect=pin.expect)
    assert same.source == "cache" and same.revision == repo.commit and same.files == first.files
    # Another machine, empty cache: the recorded commit is downloaded, not the branch's new head.
    elsewhere = fetch_model(REPO, cache_dir=tmp_path / "cache-2", revision=pin.revision, expect=pin.expect)
    assert elsewhere.source == "download" and elsewhere.files == first.files
    latest = fetch_model(REPO, cache_dir=tmp_path / "cache-3")
    assert latest.revision == newer.commit and latest.files[WEIGHTS] != first.files[WEIGHTS]
    # A record whose weights differ from the cached files (another build's, or tampered): refused by name.
    other = {**pin.expect, WEIGHTS: hashlib.sha256(newer_weights).hexdigest()}
    with pytest.raises(ModelMismatchError) as e:
        fetch_model(REPO, revision=pin.revision, expect=other)
    assert REPO in str(e.value) and WEIGHTS in str(e.value) and "--allow-newer-model" in str(e.value)
    assert (first.path / WEIGHTS).read_bytes() == repo.files[WEIGHTS]  # kept


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


def test_the_server_setting_forbids_downloads_and_says_which_setting(hub):
    from fmgs_server.server import _text_encoder

    server, _ = hub
    with pytest.raises(ModelNotFoundError) as e:
        _text_encoder("cpu", downloads=False)(REPO)
    msg = str(e.value)
    assert "downloads are off (this server's --no-model-downloads" in msg and "--model-downloads" in msg
    assert "--offline" not in msg and "folder" not in msg and fetch_command(REPO) in msg
    assert server.requests == []
    assert _text_encoder("cpu", downloads=True)(REPO).files.source == "download"


def test_files_a_load_does_not_read_are_neither_checked_nor_recorded(hub):
    """A snapshot may also hold files another tool fetched (here the open_clip copy, 4 KiB of zeros: no
    safetensors file); the check and the record cover the files a transformers load reads."""
    from huggingface_hub import hf_hub_download

    server, repo = hub
    got = fetch_model(REPO)
    cache = got.path.parents[2]  # the hub cache (hf_hub_download read HF_HUB_CACHE at its import)
    hf_hub_download(
        REPO, "open_clip_model.safetensors", revision=repo.commit, endpoint=server.endpoint, cache_dir=cache
    )
    assert (got.path / "open_clip_model.safetensors").is_file()
    again = fetch_model(REPO, offline=True)
    assert again.files == got.files and "open_clip_model.safetensors" not in again.files


@pytest.mark.parametrize("offline", [True, False])
def test_a_weights_file_given_as_the_model_is_named_a_file_not_sought_on_the_hub(hub, tmp_path, offline):
    """A path to a file (not the model's folder) is no hub id: the error says it is a file, not that the
    hub failed or that the path is absent; nothing is asked of the hub."""
    server, _ = hub
    f = tmp_path / WEIGHTS
    f.write_bytes(b"\0" * 64)
    for kw in ({"model_id": str(f)}, {"model_id": REPO, "model_dir": f}):
        with pytest.raises(ModelNotFoundError, match=r"a file, not a") as e:
            fetch_model(**kw, offline=offline)
        assert str(f) in str(e.value) and "absent" not in str(e.value) and "hf download" not in str(e.value)
    assert server.requests == [] and not (tmp_path / "hub-cache").exists()
