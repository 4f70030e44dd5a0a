"""fmgs.io.atomic.atomic_dir: what is at the path is replaced whole or kept whole, whichever way the swap
goes (Linux's exchange, or the move aside where that call is missing)."""

from __future__ import annotations

import os

import pytest

from fmgs.io import atomic
from fmgs.io.atomic import atomic_dir


def _write(folder, text):
    with atomic_dir(folder) as tmp:
        (tmp / "a.txt").write_text(text)


@pytest.mark.parametrize("exchange", [True, False], ids=["exchange", "move aside"])
def test_a_folder_is_replaced_and_nothing_is_left_beside_it(tmp_path, monkeypatch, exchange):
    if not exchange:
        monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    _write(tmp_path / "x", "old")
    _write(tmp_path / "x", "new")
    assert (tmp_path / "x" / "a.txt").read_text() == "new"
    assert sorted(os.listdir(tmp_path)) == ["x"]


def test_a_file_swapped_out_leaves_no_temporary_file(tmp_path):
    """The exchange swaps a file at the path into the temporary name: it is removed as a folder would be."""
    (tmp_path / "x").write_text("a file")
    _write(tmp_path / "x", "new")
    assert (tmp_path / "x" / "a.txt").read_text() == "new"
    assert sorted(os.listdir(tmp_path)) == ["x"]


def test_a_failed_move_puts_the_old_folder_back(tmp_path, monkeypatch):
    """Without the exchange the old folder is moved aside first; when moving the new one in fails, the
    old one returns to its path (before, the path was left empty and the old folder hidden)."""
    monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    _write(tmp_path / "x", "old")
    real = os.replace

    def failing(src, dst):
        if str(src).endswith(".tmp"):
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(atomic.os, "replace", failing)
    with pytest.raises(OSError, match="No space"):
        _write(tmp_path / "x", "new")
    assert (tmp_path / "x" / "a.txt").read_text() == "old"
    assert sorted(os.listdir(tmp_path)) == ["x"]
