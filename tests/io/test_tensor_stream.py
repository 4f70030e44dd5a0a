"""fmgs.io.tensor_stream: safetensors written a block of rows at a time."""

from __future__ import annotations

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

import fmgs.io.tensor_stream as stream
from fmgs.io.mmap_tensors import mmap_torch


def test_blocks_write_the_same_tensors_as_safetensors_reads_back(tmp_path, monkeypatch):
    monkeypatch.setattr(stream, "BLOCK_BYTES", 100)  # many blocks, one of them partial
    g = torch.Generator().manual_seed(0)
    x = torch.randn(997, 7, generator=g)
    tensors = {
        "selected": (torch.arange(997, dtype=torch.int32), torch.int64),
        "embeddings": (x, torch.float16),
        "canonical": x[:, :3],  # a strided view: written as its values
        "empty": torch.zeros(0, 4),
        "flags": torch.tensor([True, False, True]),
        "scalar": torch.tensor(2.5, dtype=torch.float64),
    }
    path = tmp_path / "t.safetensors"
    stream.save_blocks(path, tensors, {"format": "test"})
    back = load_file(str(path))
    assert torch.equal(back["selected"], torch.arange(997)) and back["selected"].dtype == torch.int64
    assert torch.equal(back["embeddings"], x.half())
    assert torch.equal(back["canonical"], x[:, :3])
    assert back["empty"].shape == (0, 4) and torch.equal(back["flags"], tensors["flags"])
    assert float(back["scalar"]) == 2.5 and back["scalar"].shape == ()
    with safe_open(str(path), "pt") as f:
        assert f.metadata() == {"format": "test"}
    assert torch.equal(mmap_torch(path, "embeddings"), x.half())  # the server's memory map reads it too
    assert (8 + int.from_bytes(path.read_bytes()[:8], "little")) % 8 == 0  # data 8-byte aligned


def test_a_dtype_safetensors_cannot_hold_is_refused(tmp_path):
    with pytest.raises(ValueError, match="c: dtype"):
        stream.save_blocks(tmp_path / "t.safetensors", {"c": torch.zeros(2, dtype=torch.complex64)})
