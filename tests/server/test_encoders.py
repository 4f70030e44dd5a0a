"""Text encoders by id with a bounded embedding cache (``fmgs_server.encoders``)."""

from __future__ import annotations

import threading
import time

import grpc
import pytest
import torch

from fmgs.features.models import ModelNotFoundError
from fmgs_server import errors
from fmgs_server.encoders import EncoderCache


class CountingEncoder:
    """A text encoder whose vectors identify the text (its length and first letter); it counts what it
    was asked to encode."""

    def __init__(self) -> None:
        self.asked: list[list[str]] = []

    def encode_text(self, texts: list[str]) -> torch.Tensor:
        self.asked.append(list(texts))
        return torch.tensor([[float(len(t)), float(ord(t[0]))] for t in texts], dtype=torch.float64)


def _factory(made: list[str], fail: dict[str, Exception] | None = None):
    def make(encoder_id: str) -> CountingEncoder:
        made.append(encoder_id)
        if fail and encoder_id in fail:
            raise fail[encoder_id]
        return CountingEncoder()

    return make


def _vec(t: str) -> list[float]:
    return [float(len(t)), float(ord(t[0]))]


def test_embeddings_in_order_and_cached():
    made: list[str] = []
    cache = EncoderCache(_factory(made), max_texts=10)
    out = cache.embed("enc", ["cup", "chair", "cup"])
    assert out.dtype == torch.float32 and out.shape == (3, 2)
    assert out.tolist() == [_vec("cup"), _vec("chair"), _vec("cup")]
    enc = cache.encoder("enc")
    assert enc.asked == [["cup"], ["chair"]]  # duplicates encoded once, each text alone
    assert cache.embed("enc", ["chair", "mug"]).tolist() == [_vec("chair"), _vec("mug")]
    assert enc.asked == [["cup"], ["chair"], ["mug"]]  # only what is not cached
    assert made == ["enc"]  # loaded once
    cache.embed("other", ["cup"])
    assert made == ["enc", "other"] and cache.encoder("other").asked == [["cup"]]  # a cache per encoder


class BatchSensitiveEncoder(CountingEncoder):
    """Like a transformer on a CPU: a text's vector moves in its last bits with the batch it is in."""

    def encode_text(self, texts: list[str]) -> torch.Tensor:
        return super().encode_text(texts) * (1 + 1e-7 * len(texts))


def test_a_texts_vector_does_not_depend_on_what_came_with_it():
    """Two caches (two replicas) that met the same text in different company return the same bits."""
    a = EncoderCache(lambda _: BatchSensitiveEncoder())
    b = EncoderCache(lambda _: BatchSensitiveEncoder())
    a.embed("enc", ["red cube", "laptop", "mug"])
    b.embed("enc", ["laptop"])
    for texts in (["red cube", "laptop"], ["laptop"], ["mug", "red cube"]):
        assert torch.equal(a.embed("enc", texts), b.embed("enc", texts))


def test_cache_is_bounded_least_recently_used_first():
    cache = EncoderCache(_factory([]), max_texts=2)
    cache.embed("enc", ["a", "bb"])
    cache.embed("enc", ["a"])  # "a" is now the most recently used
    cache.embed("enc", ["ccc"])  # evicts "bb"
    enc = cache.encoder("enc")
    cache.embed("enc", ["a", "ccc"])
    assert enc.asked == [["a"], ["bb"], ["ccc"]]
    assert cache.embed("enc", ["bb"]).tolist() == [_vec("bb")]
    assert enc.asked[-1] == ["bb"]


@pytest.mark.parametrize(
    "error",
    [ModelNotFoundError("m/x", ["/nowhere"]), OSError("disk"), ValueError("bad config")],
    ids=["missing-model", "oserror", "valueerror"],
)
def test_unavailable_encoder_is_failed_precondition(error):
    made: list[str] = []
    cache = EncoderCache(_factory(made, {"m/x": error}))
    with pytest.raises(errors.FailedPrecondition, match=r"^text encoder 'm/x' is not available here: ") as e:
        cache.embed("m/x", ["cup"])
    assert e.value.code == grpc.StatusCode.FAILED_PRECONDITION and str(error) in e.value.message
    with pytest.raises(errors.FailedPrecondition):
        cache.encoder("m/x")
    assert made == ["m/x", "m/x"]  # a failure is not remembered: the next request tries again


def test_one_load_under_concurrent_first_requests():
    made: list[str] = []

    def slow(encoder_id: str) -> CountingEncoder:
        made.append(encoder_id)
        time.sleep(0.05)
        return CountingEncoder()

    cache = EncoderCache(slow)
    out: list[torch.Tensor] = []
    threads = [threading.Thread(target=lambda: out.append(cache.embed("enc", ["cup"]))) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert made == ["enc"] and len(out) == 8
    assert all(o.tolist() == [_vec("cup")] for o in out)


# ---------------------------------------------------------------- the revision a scene was built with

SHA_A, SHA_B = "a" * 64, "b" * 64


def test_a_scenes_text_model_is_the_revision_its_manifest_records(caplog):
    from fmgs_server.encoders import TextModel, scene_text_model

    rec = {
        "id": "acme/clip",
        "revision": "c0ffee",
        "files": {"model.safetensors": SHA_A, "vocab.json": "1" * 40},
    }
    model = scene_text_model("acme/clip", {"text_encoder": rec})
    assert model.encoder_id == "acme/clip" and model.pin.revision == "c0ffee"
    assert model.pin.expect == {"model.safetensors": SHA_A}  # an older manifest's git ids are left out
    assert scene_text_model("hf:acme/clip", {"text_encoder": rec}).pin == model.pin  # the same model
    assert scene_text_model("acme/clip", {}) == TextModel("acme/clip")  # nothing recorded
    assert scene_text_model("acme/clip", {"text_encoder": {**rec, "revision": ""}}).pin is None  # a folder
    assert scene_text_model("other/clip", {"text_encoder": rec}).pin is None  # another model's record
    with caplog.at_level("WARNING", logger="fmgs_server"):
        assert scene_text_model("acme/clip", {"text_encoder": rec}, True, "kitchen").pin is None
        scene_text_model("acme/clip", {"text_encoder": rec}, True, "kitchen")
    said = [r.getMessage() for r in caplog.records if "kitchen" in r.getMessage()]
    assert len(said) == 1 and "c0ffee" in said[0] and "allow_newer_model" in said[0]


def test_an_encoder_is_loaded_per_recorded_revision():
    from fmgs.features.models import ModelPin
    from fmgs_server.encoders import TextModel

    made = []

    def factory(encoder_id, pin=None):
        made.append((encoder_id, pin.revision if pin else None))
        return CountingEncoder()

    cache = EncoderCache(factory)
    a = TextModel("enc", ModelPin("enc", "rev-a", (("model.safetensors", SHA_A),)))
    b = TextModel("enc", ModelPin("enc", "rev-b", (("model.safetensors", SHA_B),)))
    for model in (a, b, "enc", a, TextModel("enc")):
        cache.embed(model, ["cup"])
    assert made == [("enc", "rev-a"), ("enc", "rev-b"), ("enc", None)]
    assert cache.encoder(a) is not cache.encoder(b) and cache.encoder("enc") is cache.encoder(
        TextModel("enc")
    )


# ---------------------------------------------------------------- against a hub that moved on

REPO = "acme/tiny-clip"


@pytest.fixture(scope="module")
def clip_repos(bpe_dir, tmp_path_factory):
    """A tiny CLIP repository (16-D, as the blob scene) and the weights of its next commit."""
    pytest.importorskip("transformers", reason="in requirements/cpu.txt (CI)")
    pytest.importorskip("huggingface_hub", reason="in requirements/cpu.txt (CI)")
    from fmgs.features.clip_tokenizer import clip_tokenizer_from_bpe_files
    from tests.helpers.hub_server import HubRepo
    from tests.helpers.tiny_models import save_clip_folder, tiny_clip_model

    tmp = tmp_path_factory.mktemp("clip")
    vocab = len(clip_tokenizer_from_bpe_files(bpe_dir / "vocab.json", bpe_dir / "merges.txt"))
    repo = HubRepo.from_folder(REPO, save_clip_folder(tiny_clip_model(vocab), tmp / "a", bpe_dir))
    newer = save_clip_folder(tiny_clip_model(vocab, seed=7), tmp / "b", bpe_dir)
    return repo, {**repo.files, "model.safetensors": (newer / "model.safetensors").read_bytes()}


@pytest.fixture
def built_then_moved_on(clip_repos, tmp_path, monkeypatch):
    """A scene built with REPO at its first commit (fetched into the hub cache as the build does, its
    record in the manifest), then the hub's branch moved on to other weights. Yields (hub, models, the
    scene's record, the new commit)."""
    import json

    from fmgs.features.models import fetch_model
    from tests.helpers.hub_server import HubServer
    from tests.helpers.query_scenes import ENCODER_ID, blob_scene

    repo, newer_files = clip_repos
    for k in ("FMGS_OFFLINE", "HF_HUB_OFFLINE"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub-cache"))
    monkeypatch.setenv("FMGS_HUB_TIMEOUT", "2")
    models = tmp_path / "models"
    with HubServer([repo]) as hub:
        monkeypatch.setenv("HF_ENDPOINT", hub.endpoint)
        record = fetch_model(REPO).record()
        blob_scene(models / "kitchen")
        m = json.loads((models / "kitchen" / "manifest.json").read_text())
        m["encoder"]["id"] = REPO
        m["extra"]["text_encoder"] = record
        (models / "kitchen" / "manifest.json").write_text(json.dumps(m))
        assert ENCODER_ID not in (models / "kitchen" / "manifest.json").read_text()
        newer = hub.move_on(REPO, newer_files)
        yield hub, models, record, newer.commit


def _serve_and_query(models, **settings):
    """(the revision of the text encoder a query on the scene loaded, or the gRPC error)."""
    import grpc

    from fmgs_server.config import ServerConfig
    from fmgs_server.server import start_server
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc

    srv = start_server(ServerConfig(models=models, port=0, **settings))
    try:
        with grpc.insecure_channel(srv.address) as ch:
            req = pb.TextQueryRequest(scene="kitchen", texts=["red cube"], top_k=5)
            try:
                list(pb_grpc.FmgsStub(ch).TextQuery(req, timeout=60))
            except grpc.RpcError as e:
                return e
        service = srv.service
        return service.encoders.encoder(service.text_model(service.repo.get("kitchen"))).files.revision
    finally:
        srv.stop(0)


def test_the_server_loads_the_revision_the_scene_was_built_with(built_then_moved_on, tmp_path, monkeypatch):
    hub, models, record, newer = built_then_moved_on
    asked = len(hub.requests)
    assert _serve_and_query(models) == record["revision"]  # from the cache, not the branch's new head
    assert hub.requests[asked:] == []
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "fresh-cache"))  # a server with an empty cache
    assert _serve_and_query(models) == record["revision"]  # downloaded by its commit
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "another-cache"))
    assert _serve_and_query(models, allow_newer_model=True) == newer  # the explicit choice


def test_the_server_refuses_cached_files_other_than_the_recorded_ones(built_then_moved_on):
    import json

    import grpc

    _, models, record, _ = built_then_moved_on
    m = json.loads((models / "kitchen" / "manifest.json").read_text())
    m["extra"]["text_encoder"]["files"]["model.safetensors"] = SHA_B  # built with other weights
    (models / "kitchen" / "manifest.json").write_text(json.dumps(m))
    e = _serve_and_query(models)
    assert isinstance(e, grpc.RpcError) and e.code() == grpc.StatusCode.FAILED_PRECONDITION
    msg = e.details()
    assert f"text encoder {REPO!r} (revision {record['revision']}, as the scene was built)" in msg
    assert "model.safetensors" in msg and SHA_B in msg and "--allow-newer-model" in msg
    assert _serve_and_query(models, allow_newer_model=True) == record["revision"]  # taken as it is


def test_a_server_without_downloads_says_which_setting_and_how_to_pre_fetch(
    built_then_moved_on, tmp_path, monkeypatch
):
    import grpc

    _, models, record, _ = built_then_moved_on
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "fresh-cache"))
    e = _serve_and_query(models, model_downloads=False)
    assert isinstance(e, grpc.RpcError) and e.code() == grpc.StatusCode.FAILED_PRECONDITION
    msg = e.details()
    assert "--no-model-downloads" in msg and "restart it with --model-downloads" in msg
    assert f"hf download {REPO} --revision {record['revision']}" in msg
    assert "(--offline)" not in msg and "folder as its id" not in msg
