"""The scene package manifest (``manifest.json``): one typed reader and one writer, validated, versioned.

Torch-free, so a server can describe a scene it has not loaded. The JSON layout (version 1):

    {"format": "fmgs.scene", "version": 1, "name": str,
     "encoder": {"id": str, "dim": int}, "canonical": [str, ...], "sh_degree": int,
     "counts": {"gaussians": int, "selected": int}, "bounds": [6 floats: min xyz, max xyz],
     "embedding_dtype": "float16",
     "field": null | {"config": {...}, "bounds": {...}, "dino_head": bool, "dtype": "float32"|"float16"},
     "extra": {...}}

``extra`` is free-form metadata (a description, how the scene was made, ``label_names``); every other
key is checked on read, and a manifest from another format or version is refused with what it is.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fmgs.errors import ValidationError

FORMAT = "fmgs.scene"
VERSION = 1
FILENAME = "manifest.json"
SHARDS_FILE = "shards.json"
"""A sharded scene's manifest (fmgs.scene.shards), in place of FILENAME."""
MODELS = "models"
"""The default scene repository: one folder per package (fmgs build writes there, fmgs-server serves it)."""
CANONICAL_PHRASES = ("object", "stuff", "things", "texture")
"""The paper's canonical phrases, recorded in each manifest (queries score against them)."""
FIELD_DTYPES = ("float32", "float16")
"""Storage dtypes of the field's floating-point tensors."""


@dataclass(frozen=True)
class FieldInfo:
    """How the package's feature field is stored."""

    config: dict
    """fmgs.field.model.FieldConfig.to_dict()."""
    bounds: dict
    """fmgs.field.bounds.SceneBounds.to_dict()."""
    dino_head: bool = False
    """Whether field.safetensors holds the DINO head."""
    dtype: str = "float32"
    """Storage of the table and heads (one of FIELD_DTYPES; upcast to float32 on load)."""


@dataclass(frozen=True)
class Manifest:
    """What a scene package holds (see the module docstring for the JSON layout)."""

    name: str
    """Scene name the package was built with."""
    encoder_id: str
    """Text encoder the embeddings live in (queries must use it)."""
    dim: int
    """Embedding dimension D."""
    canonical: tuple[str, ...]
    """Canonical phrases whose dot products are stored per embedded Gaussian."""
    num_gaussians: int
    """All Gaussians (geometry)."""
    num_selected: int
    """Gaussians that carry an embedding (M)."""
    sh_degree: int = 0
    """Spherical-harmonics degree of the colours."""
    bounds: tuple[float, ...] = (0.0,) * 6
    """Min xyz, max xyz of all means."""
    embedding_dtype: str = "float16"
    """Storage dtype of the embeddings."""
    field: FieldInfo | None = None
    """The feature field, or None for a per-Gaussian package."""
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)
    """Free-form metadata (description, source, label_names...)."""

    @property
    def label_names(self) -> tuple[str, ...]:
        """Label names of a scene built from label targets (empty otherwise)."""
        names = self.extra.get("label_names", [])
        return tuple(str(n) for n in names) if isinstance(names, list) else ()

    @property
    def frame_id(self) -> str:
        """The frame the scene's positions are in, in metres (``extra.frame.id``: a robot's fixed frame
        for a scene built from its recording); "" when the scene's frame is its own."""
        frame = self.extra.get("frame")
        return str(frame.get("id", "")) if isinstance(frame, dict) else ""

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "name": self.name,
            "encoder": {"id": self.encoder_id, "dim": self.dim},
            "canonical": list(self.canonical),
            "sh_degree": self.sh_degree,
            "counts": {"gaussians": self.num_gaussians, "selected": self.num_selected},
            "bounds": list(self.bounds),
            "embedding_dtype": self.embedding_dtype,
            "field": None
            if self.field is None
            else {
                "config": self.field.config,
                "bounds": self.field.bounds,
                "dino_head": self.field.dino_head,
                "dtype": self.field.dtype,
            },
            "extra": self.extra,
        }

    def write(self, folder: str | Path) -> Path:
        """Write ``folder/manifest.json`` (callers write packages inside fmgs.io.atomic.atomic_dir)."""
        path = Path(folder) / FILENAME
        path.write_text(json.dumps(self.to_dict(), indent=1))
        return path

    @classmethod
    def read(cls, folder: str | Path) -> Manifest:
        """Read and validate ``folder/manifest.json``; ValidationError names the file and what is wrong."""
        folder = Path(folder)
        path = folder / FILENAME
        if not path.is_file():
            raise ValidationError(str(folder), f"not a scene package (no {FILENAME})")
        try:
            raw = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ValidationError(str(path), f"unreadable manifest ({e})") from e
        return cls.from_dict(raw, str(path))

    @classmethod
    def from_dict(cls, m: Any, where: str = FILENAME) -> Manifest:
        if not isinstance(m, dict) or m.get("format") != FORMAT:
            raise ValidationError(where, f"not an {FORMAT} manifest")
        if m.get("version") != VERSION:
            raise ValidationError(where, f"unsupported version {m.get('version')!r} (this reads {VERSION})")
        for key in ("name", "encoder", "canonical", "counts"):
            if key not in m:
                raise ValidationError(where, f"missing key {key!r}")
        enc, counts = m["encoder"], m["counts"]
        if not isinstance(enc, dict) or not isinstance(enc.get("id"), str) or not _is_int(enc.get("dim")):
            raise ValidationError(where, "encoder must be {id: str, dim: int}")
        if not isinstance(counts, dict) or not all(_is_int(counts.get(k)) for k in ("gaussians", "selected")):
            raise ValidationError(where, "counts must be {gaussians: int, selected: int}")
        if not isinstance(m["name"], str):
            raise ValidationError(where, "name must be a string")
        canon = m["canonical"]
        if not isinstance(canon, list) or not all(isinstance(c, str) for c in canon):
            raise ValidationError(where, "canonical must be a list of strings")
        bounds = m.get("bounds", [0.0] * 6)
        if not (isinstance(bounds, list) and len(bounds) == 6 and all(_is_finite(b) for b in bounds)):
            raise ValidationError(where, "bounds must be 6 finite numbers (min xyz, max xyz)")
        sh = m.get("sh_degree", 0)
        if not _is_int(sh) or not 0 <= sh <= 3:
            raise ValidationError(where, f"sh_degree must be an integer in [0, 3], got {sh!r}")
        extra = m.get("extra") or {}
        if not isinstance(extra, dict):
            raise ValidationError(where, "extra must be an object")
        return cls(
            name=m["name"],
            encoder_id=enc["id"],
            dim=int(enc["dim"]),
            canonical=tuple(canon),
            num_gaussians=int(counts["gaussians"]),
            num_selected=int(counts["selected"]),
            sh_degree=int(sh),
            bounds=tuple(float(b) for b in bounds),
            embedding_dtype=str(m.get("embedding_dtype", "float16")),
            field=_field_info(m.get("field"), where),
            extra=extra,
        )


def _field_info(f: Any, where: str) -> FieldInfo | None:
    if not f:
        return None
    if (
        not isinstance(f, dict)
        or not isinstance(f.get("config"), dict)
        or not isinstance(f.get("bounds"), dict)
    ):
        raise ValidationError(where, "field must be {config: {...}, bounds: {...}, dino_head, dtype}")
    dtype = f.get("dtype", "float32")  # manifests written before field.dtype existed hold float32
    if dtype not in FIELD_DTYPES:
        raise ValidationError(
            where, f"field dtype {dtype!r} in the manifest is not one of {sorted(FIELD_DTYPES)}"
        )
    return FieldInfo(f["config"], f["bounds"], bool(f.get("dino_head", False)), dtype)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_finite(v: Any) -> bool:
    if not isinstance(v, int | float) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:  # an integer beyond float's range
        return False
