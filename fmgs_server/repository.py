"""The scene repository ``models/<scene>/``: listing, lazy loads, per-scene state, memory budget, reloads.

A request takes a reference to a scene's engine and keeps it to the end, so a reload or an unload never
disturbs requests in flight: they finish on the version they started with.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from fmgs.errors import FmgsError
from fmgs.query.engine import SceneEngine
from fmgs.scene.manifest import FILENAME as MANIFEST
from fmgs.scene.package import check_scene_name, shown_name
from fmgs_server.errors import FailedPrecondition, NotFound, ResourceExhausted

log = logging.getLogger("fmgs_server")

UNLOADED, LOADING, READY, FAILED = "unloaded", "loading", "ready", "failed"
_FILES = (MANIFEST, "gaussians.safetensors", "embeddings.safetensors", "field.safetensors")


def scene_version(folder: Path) -> str:
    """A fingerprint of the package's files (name, size, mtime, inode); '' when there is no manifest."""
    parts = []
    for name in _FILES:
        try:
            st = (folder / name).stat()
        except OSError:
            if name == MANIFEST:
                return ""
            continue
        parts.append(f"{name}:{st.st_size}:{st.st_mtime_ns}:{st.st_ino}")
    return hashlib.sha1("|".join(parts).encode()).hexdigest()[:16]


@dataclass
class SceneSlot:
    """What the repository knows about one scene."""

    name: str
    state: str = UNLOADED
    reason: str = ""
    version: str = ""
    engine: SceneEngine | None = None
    loaded_version: str = ""
    last_used: float = 0.0
    checked: float = 0.0
    lock: threading.Lock = field(default_factory=threading.Lock)


class SceneRepository:
    """Scenes under ``root``; ``loader(path) -> SceneEngine`` builds an engine."""

    def __init__(
        self,
        root: Path,
        loader: Callable[[Path], SceneEngine],
        memory_budget: int = 0,
        reload_check_s: float = 2.0,
        on_change: Callable[[str, str], None] | None = None,
    ) -> None:
        self.root = Path(root)
        self.loader = loader
        self.memory_budget = memory_budget
        self.reload_check_s = reload_check_s
        self.on_change = on_change or (lambda name, state: None)
        self._slots: dict[str, SceneSlot] = {}
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ listing

    def scan(self) -> list[SceneSlot]:
        """Current scenes (folders with a manifest; hidden and temporary folders skipped), by name."""
        found = {}
        if self.root.is_dir():
            for p in sorted(self.root.iterdir()):
                if p.name.startswith(".") or not p.is_dir() or not (p / MANIFEST).is_file():
                    continue
                try:
                    check_scene_name(p.name)
                except FmgsError:
                    continue
                found[p.name] = p
        with self._lock:
            for name in list(self._slots):
                if name not in found:
                    self._drop(name)
            for name in found:
                self._slots.setdefault(name, SceneSlot(name))
            return [self._slots[n] for n in sorted(found)]

    def _drop(self, name: str) -> None:
        self._slots.pop(name, None)
        self.on_change(name, "removed")

    def slot(self, name: str) -> SceneSlot:
        """The slot for a valid, existing scene name (NOT_FOUND otherwise; names never reach outside)."""
        try:
            check_scene_name(name)
        except FmgsError as e:
            raise NotFound(f"scene {shown_name(name)} not found (invalid name)") from e
        folder = self.root / name
        if not (folder / MANIFEST).is_file():
            with self._lock:
                if name in self._slots:
                    self._drop(name)
            raise NotFound(f"scene {name!r} not found in the model repository")
        with self._lock:
            return self._slots.setdefault(name, SceneSlot(name))

    # ------------------------------------------------------------------ use

    def get(self, name: str) -> SceneEngine:
        """The scene's engine, loading or reloading it as needed."""
        s = self.slot(name)
        now = time.monotonic()
        with s.lock:
            s.last_used = now
            if s.engine is not None and now - s.checked < self.reload_check_s:
                return s.engine
            s.checked = now
            v = scene_version(self.root / name)
            if s.engine is not None and v in (s.loaded_version, s.version):
                return s.engine  # unchanged, or a replacement that failed to load (tried once per version)
            if s.engine is None and s.state == FAILED and v == s.version:
                raise FailedPrecondition(f"scene {name!r} failed to load: {s.reason}")
            self._load_locked(s, v)
            if s.engine is None:
                raise FailedPrecondition(f"scene {name!r} failed to load: {s.reason}")
            engine = s.engine
        self._enforce_budget(keep=name)
        return engine

    def load(self, name: str) -> SceneSlot:
        """Load now (admin); a loaded current scene is left as is."""
        self.get(name)
        return self.slot(name)

    def reload(self, name: str) -> SceneSlot:
        """Reload from disk now (admin), even if unchanged."""
        s = self.slot(name)
        with s.lock:
            self._load_locked(s, scene_version(self.root / name))
            s.checked = time.monotonic()
            if s.engine is None:
                raise FailedPrecondition(f"scene {name!r} failed to load: {s.reason}")
        self._enforce_budget(keep=name)
        return s

    def unload(self, name: str) -> SceneSlot:
        """Free the scene's memory (requests in flight keep their reference)."""
        s = self.slot(name)
        with s.lock:
            s.engine, s.loaded_version, s.state, s.reason = None, "", UNLOADED, ""
        self.on_change(name, UNLOADED)
        return s

    def _load_locked(self, s: SceneSlot, version: str) -> None:
        old = s.engine
        s.state, s.version = LOADING, version
        t0 = time.perf_counter()
        try:
            engine = self.loader(self.root / s.name)
            if scene_version(self.root / s.name) != version:  # it may mix two versions' files
                raise FmgsError("the scene's files changed while loading; retry")
            need = engine.nbytes()
            if self.memory_budget and need > self.memory_budget:
                raise ResourceExhausted(
                    f"needs {need} bytes, more than the memory budget {self.memory_budget}"
                )
        except (FmgsError, ResourceExhausted, OSError, ValueError, RuntimeError) as e:
            msg = getattr(e, "message", None) or str(e)
            log.warning("scene %s: load failed: %s", s.name, msg)
            msg = msg.replace(str(self.root.resolve()) + "/", "").replace(
                str(self.root) + "/", ""
            )  # no host paths
            if old is not None:  # keep serving the version that works; say why the new one does not
                s.state, s.reason = READY, f"reload failed, serving the previous version: {msg}"
            else:
                s.state, s.reason = FAILED, msg
            self.on_change(s.name, s.state)
            return
        s.engine, s.loaded_version, s.state, s.reason = engine, version, READY, ""
        log.info(
            "scene %s: loaded version %s in %.2f s (%d bytes)",
            s.name,
            version,
            time.perf_counter() - t0,
            need,
        )
        self.on_change(s.name, READY)

    def _enforce_budget(self, keep: str) -> None:
        if not self.memory_budget:
            return
        with self._lock:
            loaded = [s for s in self._slots.values() if s.engine is not None]
        total = sum(s.engine.nbytes() for s in loaded if s.engine is not None)
        for s in sorted(loaded, key=lambda s: s.last_used):
            if total <= self.memory_budget:
                break
            if s.name == keep:
                continue
            with s.lock:
                if s.engine is None:
                    continue
                total -= s.engine.nbytes()
                s.engine, s.loaded_version, s.state = None, "", UNLOADED
            log.info("scene %s: unloaded (memory budget)", s.name)
            self.on_change(s.name, UNLOADED)

    def resident_bytes(self, s: SceneSlot) -> int:
        e = s.engine
        return e.nbytes() if e is not None else 0
