"""Text encoders by id, loaded once, with a bounded cache of text embeddings per encoder."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable

import torch

from fmgs.features.models import ModelNotFoundError
from fmgs_server.errors import FailedPrecondition


class EncoderCache:
    """``embed(encoder_id, texts) -> [n,D]`` float32 unit rows; ``factory(id)`` loads an encoder."""

    def __init__(self, factory: Callable[[str], object], max_texts: int = 4096) -> None:
        self.factory = factory
        self.max_texts = max_texts
        self._encoders: dict[str, object] = {}
        self._cache: dict[str, OrderedDict[str, torch.Tensor]] = {}
        self._lock = threading.Lock()
        self._load_lock = threading.Lock()

    def encoder(self, encoder_id: str):
        with self._load_lock:  # one load per id, even under concurrent first requests
            enc = self._encoders.get(encoder_id)
            if enc is None:
                try:
                    enc = self.factory(encoder_id)
                except (ModelNotFoundError, OSError, ValueError) as e:
                    raise FailedPrecondition(f"text encoder {encoder_id!r} is not available here: {e}") from e
                self._encoders[encoder_id] = enc
                self._cache[encoder_id] = OrderedDict()
            return enc

    def embed(self, encoder_id: str, texts: list[str]) -> torch.Tensor:
        enc = self.encoder(encoder_id)
        cache = self._cache[encoder_id]
        with self._lock:
            have = {t: cache[t] for t in texts if t in cache}
            for t in have:
                cache.move_to_end(t)
        missing = list(dict.fromkeys(t for t in texts if t not in have))
        if missing:
            with torch.no_grad():
                vecs = enc.encode_text(missing).float().cpu()
            with self._lock:
                for t, v in zip(missing, vecs, strict=True):
                    cache[t] = v
                    have[t] = v
                while len(cache) > self.max_texts:
                    cache.popitem(last=False)
        return torch.stack([have[t] for t in texts])
