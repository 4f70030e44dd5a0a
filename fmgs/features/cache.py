"""The feature cache: dense per-image training targets for the feature field, in one folder.

Layout::

    <cache>/manifest.json       {"format": "fmgs.feature_cache", "version": 1,
                                 "targets": {"clip": {"encoder": id, "dim": Dc, "unit_norm": true},
                                             "dino": {"encoder": id, "dim": Dd, "unit_norm": false}},
                                 "images": {<Frame.name>: {"file": <name>.safetensors,
                                                           "height": h, "width": w}},
                                 "settings": {...}}  (optional)
    <cache>/<name>.safetensors  clip [h,w,Dc] float16, optional dino [h,w,Dd] float16,
                                optional mask [h,w] uint8 (1 = supervise, 0 = ignore; absent = all);
                                metadata {"format", "version", "image"}

``clip`` is the language-aligned target (hybrid CLIP, label-name text embeddings, ...; the encoder id
says which) and is unit-norm wherever the mask is set. ``dino`` is present exactly when the manifest
lists a dino target. Each image file is written atomically and the manifest is rewritten (atomically)
after every image, so an interrupted extraction leaves a valid cache that can be resumed. ``settings``
(optional, any JSON object) records what besides the encoders decided the maps (the extraction drivers:
crop scales, blend, map size, label names, ...); a resumed run with other settings is refused, as it
would mix maps of both.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import torch

from fmgs.errors import ValidationError
from fmgs.io.atomic import atomic_path

FORMAT = "fmgs.feature_cache"
VERSION = 1
MANIFEST = "manifest.json"
TARGET_NAMES = ("clip", "dino")
"""Target maps a cache may hold; ``clip`` is required."""
UNIT_NORM_TOL = 1e-2
"""Allowed deviation of a unit-norm target's per-pixel length from 1 (fp16 storage rounds ~5e-4)."""
FP16_MAX = 65504.0


@dataclass(frozen=True)
class TargetInfo:
    """What produced one target map."""

    encoder: str
    """Encoder id (a model id, e.g. the CLIP or text encoder the server must use for queries)."""
    dim: int
    """Feature size D of the map."""
    unit_norm: bool
    """Whether each supervised pixel's vector has unit length."""

    def to_json(self) -> dict[str, Any]:
        return {"encoder": self.encoder, "dim": self.dim, "unit_norm": self.unit_norm}

    @staticmethod
    def from_json(where: str, obj: Any) -> TargetInfo:
        if (
            not isinstance(obj, dict)
            or not isinstance(obj.get("encoder"), str)
            or not isinstance(obj.get("dim"), int)
            or isinstance(obj.get("dim"), bool)
            or obj["dim"] < 1
            or not isinstance(obj.get("unit_norm"), bool)
        ):
            raise ValidationError(
                where, f"expected {{encoder: str, dim: int > 0, unit_norm: bool}}, got {obj!r}"
            )
        return TargetInfo(obj["encoder"], obj["dim"], obj["unit_norm"])


@dataclass(frozen=True)
class ImageEntry:
    """One image's record in the manifest."""

    file: str
    """Safetensors file name inside the cache folder."""
    height: int
    """Map height h."""
    width: int
    """Map width w."""


class FeatureMaps(NamedTuple):
    """One image's targets, as float32/bool tensors."""

    clip: torch.Tensor
    """[h,w,Dc] float32 language-aligned target."""
    dino: torch.Tensor | None
    """[h,w,Dd] float32 DINO target, or None when the cache has none."""
    mask: torch.Tensor | None
    """[h,w] bool, True = supervise; None = every pixel."""


def cache_file_name(image_name: str) -> str:
    """A flat, filesystem-safe, collision-free file name for ``image_name`` (which may hold folders)."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", image_name).lstrip(".")[:100] or "image"
    digest = hashlib.sha1(image_name.encode("utf-8")).hexdigest()[:10]
    return f"{safe}.{digest}.safetensors"


def _check_targets(where: str, targets: Mapping[str, TargetInfo]) -> dict[str, TargetInfo]:
    unknown = sorted(set(targets) - set(TARGET_NAMES))
    if "clip" not in targets or unknown:
        raise ValidationError(
            where, f"targets must include 'clip' and only {TARGET_NAMES}; got {sorted(targets)}"
        )
    return {k: targets[k] for k in TARGET_NAMES if k in targets}


def _check_map(where: str, name: str, t: torch.Tensor, hw: tuple[int, int] | None, dim: int) -> None:
    if t.ndim != 3 or t.shape[-1] != dim or t.shape[0] < 1 or t.shape[1] < 1:
        raise ValidationError(where, f"{name} has shape {tuple(t.shape)}, expected [h,w,{dim}]")
    if hw is not None and tuple(t.shape[:2]) != hw:
        raise ValidationError(where, f"{name} is {t.shape[0]}x{t.shape[1]}, expected {hw[0]}x{hw[1]}")
    if not t.dtype.is_floating_point:
        raise ValidationError(where, f"{name} has dtype {t.dtype}, expected floating point")
    if not torch.isfinite(t).all():
        raise ValidationError(where, f"{name} contains NaN or Inf")


def _check_unit_norm(where: str, name: str, t: torch.Tensor, mask: torch.Tensor | None) -> None:
    err = (torch.linalg.vector_norm(t.float(), dim=-1) - 1.0).abs()
    if mask is not None:
        err = err[mask]
    if err.numel() and float(err.max()) > UNIT_NORM_TOL:
        raise ValidationError(
            where,
            f"{name} is declared unit-norm but a supervised pixel has length off by {float(err.max()):.3g}",
        )


def _check_mask(where: str, mask: torch.Tensor, hw: tuple[int, int]) -> torch.Tensor:
    if mask.ndim != 2 or tuple(mask.shape) != hw:
        raise ValidationError(where, f"mask has shape {tuple(mask.shape)}, expected {hw[0]}x{hw[1]}")
    if mask.dtype != torch.bool:
        if mask.dtype.is_floating_point or mask.dtype.is_complex:
            raise ValidationError(where, f"mask has dtype {mask.dtype}, expected bool or uint8")
        if ((mask != 0) & (mask != 1)).any():
            raise ValidationError(where, "mask values must be 0 or 1")
    return mask != 0


class FeatureCacheWriter:
    """Fills a cache folder image by image; reopening a folder with a manifest resumes it.

    Usage: ``with FeatureCacheWriter(d, {"clip": TargetInfo(...)}) as w: w.add(name, clip=...)``.
    """

    def __init__(
        self,
        cache_dir: str | os.PathLike,
        targets: Mapping[str, TargetInfo],
        settings: Mapping[str, Any] | None = None,
    ) -> None:
        """Create ``cache_dir`` (or resume it: its manifest's targets must equal ``targets``, and its
        recorded ``settings``, when it holds images made with some, must equal these; None keeps the
        recorded ones)."""
        self.root = Path(cache_dir)
        self.targets = _check_targets("targets", targets)
        self.settings = _check_settings("settings", settings)
        self._images: dict[str, ImageEntry] = {}
        if (self.root / MANIFEST).is_file():
            existing = FeatureCache.open(self.root)
            if existing.targets != self.targets:
                raise ValidationError(
                    str(self.root / MANIFEST),
                    f"cache holds targets {_describe(existing.targets)}, this run writes "
                    f"{_describe(self.targets)}; use a new cache folder",
                )
            if self.settings is None:
                self.settings = existing.settings
            elif existing.settings not in (None, self.settings) and existing.entries:
                raise ValidationError(
                    str(self.root / MANIFEST),
                    f"cache was made with other settings ({_settings_diff(existing.settings, self.settings)})"
                    "; use a new cache folder",
                )
            self._images = dict(existing.entries)
        self._write_manifest()

    def __enter__(self) -> FeatureCacheWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def image_names(self) -> list[str]:
        """Images written so far (sorted)."""
        return sorted(self._images)

    def has(self, image_name: str) -> bool:
        """Whether ``image_name`` is already in the cache (listed and its file present)."""
        e = self._images.get(image_name)
        return e is not None and (self.root / e.file).is_file()

    def add(
        self,
        image_name: str,
        clip: torch.Tensor,
        dino: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
    ) -> None:
        """Validate and store one image's maps: clip [h,w,Dc], dino [h,w,Dd] (iff a dino target), mask [h,w].

        Values are stored as float16 (they must fit its range); replaces an earlier entry of the same name.
        """
        where = f"feature maps of {image_name!r}"
        _check_map(where, "clip", clip, None, self.targets["clip"].dim)
        hw = (int(clip.shape[0]), int(clip.shape[1]))
        if ("dino" in self.targets) != (dino is not None):
            need = "needs a dino map" if dino is None else "has no dino target; got a dino map"
            raise ValidationError(where, f"this cache {need}")
        tensors = {"clip": clip}
        if dino is not None:
            _check_map(where, "dino", dino, hw, self.targets["dino"].dim)
            tensors["dino"] = dino
        valid = _check_mask(where, mask, hw) if mask is not None else None
        out: dict[str, torch.Tensor] = {}
        for name, t in tensors.items():
            big = float(t.abs().max())
            if big > FP16_MAX:
                raise ValidationError(where, f"{name} has |value| {big:.3g}, beyond float16 range")
            out[name] = t.detach().to("cpu", torch.float16).contiguous()
            if self.targets[name].unit_norm:
                _check_unit_norm(where, name, out[name], valid.cpu() if valid is not None else None)
        if valid is not None:
            out["mask"] = valid.to("cpu", torch.uint8).contiguous()
        from safetensors.torch import save_file

        entry = ImageEntry(cache_file_name(image_name), hw[0], hw[1])
        meta = {"format": FORMAT, "version": str(VERSION), "image": image_name}
        with atomic_path(self.root / entry.file) as tmp:
            save_file(out, str(tmp), metadata=meta)
        self._images[image_name] = entry
        self._write_manifest()

    def close(self) -> None:
        """Write the manifest (it is already current after each ``add``)."""
        self._write_manifest()

    def _write_manifest(self) -> None:
        doc = {
            "format": FORMAT,
            "version": VERSION,
            "targets": {k: v.to_json() for k, v in self.targets.items()},
            "images": {
                n: {"file": e.file, "height": e.height, "width": e.width}
                for n, e in sorted(self._images.items())
            },
        }
        if self.settings is not None:
            doc["settings"] = self.settings
        with atomic_path(self.root / MANIFEST) as tmp:
            tmp.write_text(json.dumps(doc, indent=1))


def _check_settings(where: str, settings: Any) -> dict[str, Any] | None:
    """``settings`` as JSON reads it back (tuples as lists), or None; a JSON object is required."""
    if settings is None:
        return None
    if not isinstance(settings, Mapping):
        raise ValidationError(where, f"settings must be an object, got {type(settings).__name__}")
    try:
        return json.loads(json.dumps(dict(settings), allow_nan=False))
    except (TypeError, ValueError) as e:
        raise ValidationError(where, f"settings must be plain JSON ({e})") from e


def _settings_diff(then: Mapping[str, Any], now: Mapping[str, Any]) -> str:
    keys = [k for k in {**then, **now} if then.get(k) != now.get(k)]
    return "; ".join(f"{k}: {then.get(k)!r} then, {now.get(k)!r} now" for k in keys)


def _describe(targets: Mapping[str, TargetInfo]) -> str:
    return ", ".join(f"{k}={v.encoder} ({v.dim}-D)" for k, v in targets.items())


class FeatureCache:
    """Read access to a cache folder written by ``FeatureCacheWriter`` (or any producer of the format)."""

    def __init__(
        self,
        root: Path,
        targets: dict[str, TargetInfo],
        entries: dict[str, ImageEntry],
        settings: dict[str, Any] | None = None,
    ) -> None:
        """Prefer ``FeatureCache.open``."""
        self.root = root
        self.targets = targets
        self.entries = entries
        self.settings = settings
        """What besides the encoders made the maps (FeatureCacheWriter), None when not recorded."""

    @classmethod
    def open(cls, cache_dir: str | os.PathLike) -> FeatureCache:
        """Read and validate ``cache_dir/manifest.json``; ValidationError naming the file and the problem."""
        root = Path(cache_dir)
        path = root / MANIFEST
        if not path.is_file():
            why = "folder does not exist" if not root.is_dir() else "no manifest.json in it"
            raise ValidationError(
                str(path), f"not a feature cache ({why}); run feature extraction into {root} first"
            )
        try:
            doc = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ValidationError(str(path), f"cannot read manifest ({e})") from e
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
            raise ValidationError(str(path), f"not a {FORMAT} manifest (format={got!r})")
        if doc.get("version") != VERSION:
            raise ValidationError(
                str(path), f"unsupported version {doc.get('version')!r} (this reader: {VERSION})"
            )
        raw_t = doc.get("targets")
        if not isinstance(raw_t, dict):
            raise ValidationError(str(path), "'targets' must be an object")
        targets = _check_targets(
            str(path), {k: TargetInfo.from_json(f"{path}: targets.{k}", v) for k, v in raw_t.items()}
        )
        raw_i = doc.get("images")
        if not isinstance(raw_i, dict):
            raise ValidationError(str(path), "'images' must be an object")
        entries = {}
        for name, e in raw_i.items():
            ok = (
                isinstance(e, dict)
                and isinstance(e.get("file"), str)
                and Path(e["file"]).name == e["file"]
                and not e["file"].startswith(".")
                and all(
                    isinstance(e.get(k), int) and not isinstance(e[k], bool) and e[k] > 0
                    for k in ("height", "width")
                )
            )
            if not ok:
                raise ValidationError(
                    str(path),
                    f"images[{name!r}] must be {{file: plain file name, height: int, width: int}}, got {e!r}",
                )
            entries[name] = ImageEntry(e["file"], e["height"], e["width"])
        settings = doc.get("settings")
        if settings is not None and not isinstance(settings, dict):
            raise ValidationError(str(path), f"'settings' must be an object, got {settings!r}")
        return cls(root, targets, entries, settings)

    @property
    def image_names(self) -> list[str]:
        """Images the manifest lists (sorted)."""
        return sorted(self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def __contains__(self, image_name: object) -> bool:
        return image_name in self.entries

    def size(self, image_name: str) -> tuple[int, int]:
        """(h, w) of ``image_name``'s maps."""
        e = self._entry(image_name)
        return e.height, e.width

    def missing(self, names: Iterable[str]) -> list[str]:
        """Those of ``names`` the cache lacks (not listed, or file absent)."""
        return [n for n in names if n not in self.entries or not (self.root / self.entries[n].file).is_file()]

    def complete(self, names: Iterable[str]) -> bool:
        """Whether every one of ``names`` is in the cache."""
        return not self.missing(names)

    def _entry(self, image_name: str) -> ImageEntry:
        e = self.entries.get(image_name)
        if e is None:
            raise ValidationError(str(self.root / MANIFEST), f"image {image_name!r} is not in the cache")
        return e

    def load(self, image_name: str, device: str | torch.device = "cpu") -> FeatureMaps:
        """One image's maps (float32 / bool), validated against the manifest."""
        from safetensors import SafetensorError, safe_open

        e = self._entry(image_name)
        path = self.root / e.file
        where = str(path)
        if not path.is_file():
            raise ValidationError(
                where, f"feature file of image {image_name!r} is missing (listed in {MANIFEST})"
            )
        try:
            with safe_open(str(path), framework="pt", device="cpu") as f:
                meta = f.metadata() or {}
                data = {k: f.get_tensor(k) for k in f.keys()}
        except (SafetensorError, OSError) as ex:
            raise ValidationError(where, f"cannot read safetensors file ({ex})") from ex
        if meta.get("format") != FORMAT or meta.get("version") != str(VERSION):
            raise ValidationError(
                where,
                f"not a {FORMAT} v{VERSION} file "
                f"(format={meta.get('format')!r}, version={meta.get('version')!r})",
            )
        if meta.get("image") != image_name:
            raise ValidationError(where, f"holds image {meta.get('image')!r}, manifest says {image_name!r}")
        expected = {*self.targets, "mask"}
        extra = sorted(set(data) - expected)
        absent = sorted(set(self.targets) - set(data))
        if extra or absent:
            raise ValidationError(where, f"tensors {sorted(data)}: missing {absent}, unexpected {extra}")
        hw = (e.height, e.width)
        for name, info in self.targets.items():
            t = data[name]
            if t.dtype != torch.float16:
                raise ValidationError(where, f"{name} has dtype {t.dtype}, expected float16")
            _check_map(where, name, t, hw, info.dim)
        mask = None
        if "mask" in data:
            if data["mask"].dtype != torch.uint8:
                raise ValidationError(where, f"mask has dtype {data['mask'].dtype}, expected uint8")
            mask = _check_mask(where, data["mask"], hw)
        for name, info in self.targets.items():
            if info.unit_norm:
                _check_unit_norm(where, name, data[name], mask)
        dino = data["dino"].to(device, torch.float32) if "dino" in data else None
        return FeatureMaps(
            data["clip"].to(device, torch.float32), dino, mask.to(device) if mask is not None else None
        )
