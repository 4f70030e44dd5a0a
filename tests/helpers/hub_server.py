"""A local HTTP server that speaks the part of the Hugging Face hub's protocol huggingface_hub uses to
download a model (``HF_ENDPOINT``): repository info, the file tree, and file downloads with resume.

Tests point the real client code at it over a real socket. It counts the requests it served, and it
can misbehave the ways a real hub or mirror does (``HubState``): cut a download short (``cut_after``
bytes of one file, some number of times), serve bytes other than the ones it advertises (``serve_instead``),
answer an endpoint with an HTTP error (``fail``), or never answer one (``stall``); a repository can move on
to a new commit while its old ones stay reachable by hash (``HubServer.move_on``). ``SilentHub`` is a socket
that accepts connections and never answers at all.
"""

from __future__ import annotations

import hashlib
import json
import re
import socket
import threading
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlparse

LFS_SUFFIXES = (".safetensors", ".bin", ".pt", ".msgpack", ".h5")
"""Files the hub stores through LFS (their ETag is their sha256)."""


ENDPOINTS = ("info", "tree", "head", "get")
"""The hub's endpoints a download uses, as ``fail`` and ``stall`` name them: the revision's info
(/api/models/ID/revision/REV), its file tree (/api/models/ID/tree/REV), and a file's metadata (HEAD) and
bytes (GET) (/ID/resolve/REV/FILE)."""


def git_blob_id(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def garble_header(data: bytes) -> bytes:
    """A safetensors file with its JSON header overwritten by junk (same length, so the size matches)."""
    n = int.from_bytes(data[:8], "little")
    return data[:8] + b"\xff" * n + data[8 + n :]


def flip_tail(data: bytes, n: int = 256) -> bytes:
    """``data`` with its last ``n`` bytes inverted: same size and header, other weights."""
    return data[:-n] + bytes(b ^ 0xFF for b in data[-n:])


@dataclass
class HubRepo:
    """One model repository at one commit: {path in repo: bytes}."""

    repo_id: str
    files: dict[str, bytes]
    commit: str = ""
    branch: str = "main"

    def __post_init__(self) -> None:
        if not self.commit:
            digest = hashlib.sha1(self.repo_id.encode())
            for p in sorted(self.files):
                digest.update(p.encode() + self.files[p])
            self.commit = digest.hexdigest()

    @classmethod
    def from_folder(cls, repo_id: str, folder: Path) -> HubRepo:
        files = {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}
        return cls(repo_id, files)

    def etag(self, path: str) -> str:
        data = self.files[path]
        return hashlib.sha256(data).hexdigest() if path.endswith(LFS_SUFFIXES) else git_blob_id(data)

    def tree_entry(self, path: str) -> dict:
        data = self.files[path]
        entry = {"type": "file", "oid": git_blob_id(data), "size": len(data), "path": path}
        if path.endswith(LFS_SUFFIXES):
            entry["lfs"] = {"oid": self.etag(path), "size": len(data), "pointerSize": 134}
        return entry


@dataclass
class HubState:
    repos: dict[str, HubRepo] = field(default_factory=dict)
    requests: list[str] = field(default_factory=list)
    cut_after: dict[str, tuple[int, int]] = field(default_factory=dict)
    """{path in repo: (bytes, times)}: the next ``times`` GETs of that file send at most this many bytes
    of the body, then drop the connection (an interrupted transfer)."""
    serve_instead: dict[str, bytes] = field(default_factory=dict)
    """{path in repo: bytes}: GETs of that file send these bytes (of the same length) while the tree,
    HEAD and ETag still advertise the repository's own (a corrupting mirror)."""
    fail: dict[str, int] = field(default_factory=dict)
    """{endpoint (ENDPOINTS): HTTP status}: that endpoint answers every request with this status."""
    stall: set[str] = field(default_factory=set)
    """Endpoints (ENDPOINTS) that read the request and never answer (until the server stops)."""
    history: dict[tuple[str, str], HubRepo] = field(default_factory=dict)
    """{(repo id, commit): repository}: earlier commits, still served by hash after ``move_on``."""
    lock: threading.Lock = field(default_factory=threading.Lock)
    stopping: threading.Event = field(default_factory=threading.Event)


class _Handler(BaseHTTPRequestHandler):
    state: HubState
    protocol_version = "HTTP/1.1"

    def log_message(self, *args) -> None:  # quiet
        pass

    def _json(self, obj, status: int = 200, headers: dict | None = None) -> None:
        body = json.dumps(obj).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _missing(self, code: str, message: str) -> None:
        self._json({"error": message}, 404, {"X-Error-Code": code, "X-Error-Message": message})

    def _repo(self, repo_id: str, rev: str) -> HubRepo | None:
        repo = self.state.repos.get(repo_id)
        if repo is None:
            self._missing("RepoNotFound", f"Repository {repo_id} not found")
            return None
        if rev in (repo.branch, repo.commit):
            return repo
        if (old := self.state.history.get((repo_id, rev))) is not None:
            return old
        self._missing("RevisionNotFound", f"Revision {rev} not found")
        return None

    def _misbehave(self, endpoint: str) -> bool:
        """Stall or fail ``endpoint`` when the state says so; True when the request is answered."""
        if endpoint in self.state.stall:
            self.state.stopping.wait()
            self.close_connection = True
            return True
        if status := self.state.fail.get(endpoint):
            self._json({"error": f"failing {endpoint} on purpose"}, status)
            return True
        return False

    def do_HEAD(self) -> None:
        self.do_GET()

    def do_GET(self) -> None:
        url = urlparse(self.path)
        path = unquote(url.path)
        rng = self.headers.get("Range")
        with self.state.lock:
            self.state.requests.append(f"{self.command} {path}" + (f" {rng}" if rng else ""))
        if m := re.fullmatch(r"/api/models/([^/]+/[^/]+)/revision/([^/]+)", path):
            if self._misbehave("info"):
                return
            repo = self._repo(m.group(1), m.group(2))
            if repo:
                siblings = [{"rfilename": p} for p in sorted(repo.files)]
                info = {"id": repo.repo_id, "modelId": repo.repo_id, "sha": repo.commit, "siblings": siblings}
                self._json(info)
            return
        if m := re.fullmatch(r"/api/models/([^/]+/[^/]+)/tree/([^/]+)(?:/(.*))?", path):
            if self._misbehave("tree"):
                return
            repo = self._repo(m.group(1), m.group(2))
            if repo:
                under = (m.group(3) or "").strip("/")
                paths = [p for p in sorted(repo.files) if not under or p.startswith(under + "/")]
                self._json([repo.tree_entry(p) for p in paths])
            return
        if m := re.fullmatch(r"/([^/]+/[^/]+)/resolve/([^/]+)/(.+)", path):
            if self._misbehave("head" if self.command == "HEAD" else "get"):
                return
            repo = self._repo(m.group(1), m.group(2))
            if repo is None:
                return
            name = m.group(3)
            if name not in repo.files:
                self._missing("EntryNotFound", f"{name} not found")
                return
            self._file(repo, name)
            return
        self._missing("NotFound", f"no route for {path}")

    def _file(self, repo: HubRepo, name: str) -> None:
        data = repo.files[name]
        if self.command == "GET":
            data = self.state.serve_instead.get(name, data)
        start = 0
        if rng := re.fullmatch(r"bytes=(\d+)-", self.headers.get("Range", "")):
            start = min(int(rng.group(1)), len(data))
        body = data[start:]
        self.send_response(206 if start else 200)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Accept-Ranges", "bytes")
        self.send_header("ETag", f'"{repo.etag(name)}"')
        self.send_header("X-Repo-Commit", repo.commit)
        if name.endswith(LFS_SUFFIXES):
            self.send_header("X-Linked-Etag", f'"{repo.etag(name)}"')
            self.send_header("X-Linked-Size", str(len(data)))
        if start:
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        self.end_headers()
        if self.command == "HEAD":
            return
        with self.state.lock:
            cut, times = self.state.cut_after.get(name, (None, 0))
            if times > 1:
                self.state.cut_after[name] = (cut, times - 1)
            else:
                self.state.cut_after.pop(name, None)
        if cut is not None:
            self.wfile.write(body[:cut])
            self.wfile.flush()
            self.close_connection = True
            self.connection.shutdown(2)
            return
        self.wfile.write(body)


class HubServer:
    """``with HubServer(repos) as hub: os.environ["HF_ENDPOINT"] = hub.endpoint``."""

    def __init__(self, repos: list[HubRepo]) -> None:
        self.state = HubState(repos={r.repo_id: r for r in repos})
        handler = type("Handler", (_Handler,), {"state": self.state})
        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.endpoint = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, args=(0.05,), daemon=True)

    def __enter__(self) -> HubServer:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.state.stopping.set()  # stalled handlers return
        self.httpd.shutdown()
        self.httpd.server_close()

    @property
    def requests(self) -> list[str]:
        return list(self.state.requests)

    def move_on(self, repo_id: str, files: dict[str, bytes]) -> HubRepo:
        """Push a new commit of ``repo_id`` holding ``files``: its branch now points there, and the
        commit it pointed to stays reachable by hash (as on the real hub). Returns the new repository."""
        with self.state.lock:
            old = self.state.repos[repo_id]
            self.state.history[(repo_id, old.commit)] = old
            new = HubRepo(repo_id, files, branch=old.branch)
            self.state.repos[repo_id] = new
        return new


class SilentHub:
    """A socket on loopback that accepts connections and never answers (a stuck mirror):
    ``with SilentHub() as hub: os.environ["HF_ENDPOINT"] = hub.endpoint``."""

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.endpoint = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self.accepted = 0
        self._held: list[socket.socket] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._accept, daemon=True)

    def _accept(self) -> None:
        self.sock.settimeout(0.1)
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self.accepted += 1
            self._held.append(conn)  # read nothing, answer nothing

    def __enter__(self) -> SilentHub:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self.thread.join()
        for c in self._held:
            c.close()
        self.sock.close()


def skip_backoff(monkeypatch) -> None:
    """Make huggingface_hub's retries of a failing hub (HTTP 5xx: up to 5, waiting 1, 2, 4, 8, 8 s) and of
    a broken-off transfer (1 s each) not wait, so a test of them takes no half minute."""
    import time
    import types

    from huggingface_hub import file_download
    from huggingface_hub.utils import _http

    fast = types.SimpleNamespace(**{k: getattr(time, k) for k in dir(time) if not k.startswith("_")})
    fast.sleep = lambda s: None
    monkeypatch.setattr(_http, "time", fast)
    monkeypatch.setattr(file_download, "time", fast)
