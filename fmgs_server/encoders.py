"""Text encoders by id (and the revision a scene was built with), loaded once, with a bounded cache of
text embeddings per encoder."""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import NamedTuple

import torch

from fmgs.features.models import ModelPin, ModelUnavailableError
from fmgs.features.registry import parse_encoder_id
from fmgs_server.errors import FailedPrecondition

log = logging.getLogger("fmgs_server")


class TextModel(NamedTuple):
    """A scene's text encoder: its id, and the hub revision and files the scene was built with."""

    encoder_id: str
    pin: ModelPin | None = None
    """None: whatever the folder, hub cache or hub has (a local folder, an older manifest, or the server's
    allow_newer_model)."""


_told: set[tuple[str, str]] = set()
"""(scene, recorded revision) pairs whose allow_newer_model load was logged."""


def scene_text_model(
    encoder_id: str, extra: dict, allow_newer_model: bool = False, scene: str = ""
) -> TextModel:
    """The text model of a scene whose manifest's ``extra`` records its text encoder (``text_encoder``:
    id, revision, file hashes): pinned to that revision unless ``allow_newer_model`` (then it says so in
    the log, once per scene and revision)."""
    pin = ModelPin.from_record(extra.get("text_encoder"))
    if pin is None or pin.model_id != parse_encoder_id(encoder_id).ref:
        return TextModel(encoder_id)
    if allow_newer_model:
        if (scene, pin.revision) not in _told:
            _told.add((scene, pin.revision))
            log.warning(
                "scene %s was built with %s at revision %s; allow_newer_model: its queries use the revision "
                "the hub cache (or hub) has now", scene, pin.model_id, pin.revision,
            )  # fmt: skip
        return TextModel(encoder_id)
    return TextModel(encoder_id, pin)


def _key(model: str | TextModel) -> TextModel:
    return model if isinstance(model, TextModel) else TextModel(model)


class EncoderCache:
    """``embed(model, texts) -> [n,D]`` float32 unit rows, ``model`` an encoder id or a TextModel;
    ``factory(id)`` loads an encoder, ``factory(id, pin)`` one pinned to a scene's revision."""

    MAX_NEGATIVE_SETS = 64
    """Presence negative sets kept (one per encoder and label-name list, ~0.5 MB each at 512-D)."""

    def __init__(self, factory: Callable[..., object], max_texts: int = 4096) -> None:
        self.factory = factory
        self.max_texts = max_texts
        self._encoders: dict[TextModel, object] = {}
        self._cache: dict[TextModel, OrderedDict[str, torch.Tensor]] = {}
        self._negatives: dict[tuple[TextModel, tuple[str, ...]], torch.Tensor] = {}
        self._lock = threading.Lock()
        self._load_lock = threading.Lock()

    def encoder(self, model: str | TextModel):
        key = _key(model)
        with self._load_lock:  # one load per id and revision, even under concurrent first requests
            enc = self._encoders.get(key)
            if enc is None:
                at = f" (revision {key.pin.revision}, as the scene was built)" if key.pin else ""
                try:
                    enc = self.factory(key.encoder_id) if key.pin is None else self.factory(*key)
                except (ModelUnavailableError, OSError, ValueError) as e:
                    raise FailedPrecondition(
                        f"text encoder {key.encoder_id!r}{at} is not available here: {e}"
                    ) from e
                self._encoders[key] = enc
                self._cache[key] = OrderedDict()
            return enc

    def negatives(self, model: str | TextModel, names: tuple[str, ...]) -> torch.Tensor | None:
        """[V,D] embeddings of a scene's presence negatives (fmgs.query.presence.negative_names), kept
        per encoder and name list apart from the query cache (a scene asks for the same list each time);
        None when the encoder is not available here."""
        key = (_key(model), names)
        with self._lock:
            hit = self._negatives.get(key)
        if hit is not None:
            return hit
        try:
            enc = self.encoder(model)
        except FailedPrecondition:
            return None
        with torch.no_grad():
            vecs = enc.encode_text(list(names)).float().cpu()
        with self._lock:
            self._negatives[key] = vecs
            while len(self._negatives) > self.MAX_NEGATIVE_SETS:
                self._negatives.pop(next(iter(self._negatives)))
        return vecs

    def embed(self, model: str | TextModel, texts: list[str]) -> torch.Tensor:
        enc = self.encoder(model)
        cache = self._cache[_key(model)]
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
