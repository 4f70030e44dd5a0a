"""A local HTTP server that speaks the part of the Hugging Face hub's protocol huggingface_hub uses to
download a model (``HF_ENDPOINT``): repository info, the file tree, and file downloads with resume.

Tests point the real client code at it over a real socket. It can cut a download short (``cut_after``
bytes of one file) to stand for an interrupted transfer, and counts the requests it served.
"""

from __future__ import annotations

import hashlib
import json
import re
import threading
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlparse

LFS_SUFFIXES = (".safetensors", ".bin", ".pt", ".msgpack", ".h5")
"""Files the hub stores through LFS (their ETag is their sha256)."""


def git_blob_id(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


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
    lock: threading.Lock = field(default_factory=threading.Lock)


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
        if rev not in (repo.branch, repo.commit):
            self._missing("RevisionNotFound", f"Revision {rev} not found")
            return None
        return repo

    def do_HEAD(self) -> None:
        self.do_GET()

    def do_GET(self) -> None:
        url = urlparse(self.path)
        path = unquote(url.path)
        rng = self.headers.get("Range")
        with self.state.lock:
            self.state.requests.append(f"{self.command} {path}" + (f" {rng}" if rng else ""))
        if m := re.fullmatch(r"/api/models/([^/]+/[^/]+)/revision/([^/]+)", path):
            repo = self._repo(m.group(1), m.group(2))
            if repo:
                siblings = [{"rfilename": p} for p in sorted(repo.files)]
                info = {"id": repo.repo_id, "modelId": repo.repo_id, "sha": repo.commit, "siblings": siblings}
                self._json(info)
            return
        if m := re.fullmatch(r"/api/models/([^/]+/[^/]+)/tree/([^/]+)(?:/(.*))?", path):
            repo = self._repo(m.group(1), m.group(2))
            if repo:
                under = (m.group(3) or "").strip("/")
                paths = [p for p in sorted(repo.files) if not under or p.startswith(under + "/")]
                self._json([repo.tree_entry(p) for p in paths])
            return
        if m := re.fullmatch(r"/([^/]+/[^/]+)/resolve/([^/]+)/(.+)", path):
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
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    def __enter__(self) -> HubServer:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()

    @property
    def requests(self) -> list[str]:
        return list(self.state.requests)
