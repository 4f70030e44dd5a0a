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
