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

    MAX_NEGATIVE_SETS = 64
    """Presence negative sets kept (one per encoder and label-name list, ~0.5 MB each at 512-D)."""

    def __init__(self, factory: Callable[[str], object], max_texts: int = 4096) -> None:
        self.factory = factory
        self.max_texts = max_texts
        self._encoders: dict[str, object] = {}
        self._cache: dict[str, OrderedDict[str, torch.Tensor]] = {}
        self._negatives: dict[tuple[str, tuple[str, ...]], torch.Tensor] = {}
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

    def negatives(self, encoder_id: str, names: tuple[str, ...]) -> torch.Tensor | None:
        """[V,D] embeddings of a scene's presence negatives (fmgs.query.presence.negative_names), kept
        per encoder and name list apart from the query cache (a scene asks for the same list each time);
        None when the encoder is not available here."""
        key = (encoder_id, names)
        with self._lock:
            hit = self._negatives.get(key)
        if hit is not None:
            return hit
        try:
            enc = self.encoder(encoder_id)
        except FailedPrecondition:
            return None
        with torch.no_grad():
            vecs = enc.encode_text(list(names)).float().cpu()
        with self._lock:
            self._negatives[key] = vecs
            while len(self._negatives) > self.MAX_NEGATIVE_SETS:
                self._negatives.pop(next(iter(self._negatives)))
        return vecs

    def embed(self, encoder_id: str, texts: list[str]) -> torch.Tensor:
        enc = self.encoder(encoder_id)
        cache = self._cache[encoder_id]
        with self._lock:
            have = {t: cache[t] for t in texts if t in cache}
            for t in have:
                cache.move_to_end(t)
        missing = list(dict.fromkeys(t for t in texts if t not in have))
        if missing:
            # One text per pass: a transformer's output for a text changes in its last bits with the
            # batch it is padded into (other matrix shapes), so a batch would make a text's vector, and
            # the answer, depend on which texts came with it first (replicas would not agree).
            with torch.no_grad():
                vecs = torch.cat([enc.encode_text([t]).float().cpu() for t in missing])
            with self._lock:
                for t, v in zip(missing, vecs, strict=True):
                    cache[t] = v
                    have[t] = v
                while len(cache) > self.max_texts:
                    cache.popitem(last=False)
        return torch.stack([have[t] for t in texts])
