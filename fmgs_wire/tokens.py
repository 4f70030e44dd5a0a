"""Bearer-token files, one format for the server's allow-lists and the client's credential: one token per
line, blank lines and ``#`` comments ignored, UTF-8 with or without a byte order mark (Windows editors
write one)."""

from __future__ import annotations

from pathlib import Path


def read_token_file(path: str | Path) -> list[str]:
    """The tokens in ``path``, in order; ValueError naming the file when it holds none."""
    tokens = [ln.strip() for ln in Path(path).read_text(encoding="utf-8-sig").splitlines()]
    tokens = [t for t in tokens if t and not t.startswith("#")]
    if not tokens:
        raise ValueError(f"{path}: no tokens in the file")
    return tokens
