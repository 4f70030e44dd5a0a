"""Memory-mapped read-only views of tensors inside a safetensors file (no copy, pages load on touch).

Used to keep a scene's full embeddings on disk while only a compact query state lives in memory.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from fmgs.errors import ValidationError

_DTYPES = {
    "I8": np.int8,
    "F16": np.float16,
    "F32": np.float32,
    "F64": np.float64,
    "I32": np.int32,
    "I64": np.int64,
}


def mmap_tensor(path: str | Path, key: str) -> np.ndarray:
    """A read-only ``np.memmap`` of tensor ``key`` in safetensors file ``path`` (little-endian dtypes)."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            (n,) = struct.unpack("<Q", f.read(8))
            if n > 100_000_000:
                raise ValidationError(str(path), "safetensors header too large")
            header = json.loads(f.read(n))
    except (OSError, struct.error, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValidationError(str(path), f"cannot read safetensors header ({e})") from e
    meta = header.get(key) if isinstance(header, dict) else None
    if not isinstance(meta, dict):
        raise ValidationError(str(path), f"no tensor {key!r}")
    dt = _DTYPES.get(meta.get("dtype"))
    if dt is None:
        raise ValidationError(str(path), f"tensor {key!r}: unsupported dtype {meta.get('dtype')!r}")
    shape = tuple(int(s) for s in meta["shape"])
    start, stop = (int(v) for v in meta["data_offsets"])
    count = int(np.prod(shape, dtype=np.int64))
    if stop - start != count * np.dtype(dt).itemsize:
        raise ValidationError(str(path), f"tensor {key!r}: byte range does not match its shape")
    if count == 0:
        return np.zeros(shape, dt)
    offset = 8 + n + start
    if offset + (stop - start) > path.stat().st_size:
        raise ValidationError(str(path), f"tensor {key!r}: file is truncated")
    return np.memmap(path, dtype=np.dtype(dt).newbyteorder("<"), mode="r", offset=offset, shape=shape)


def mmap_torch(path: str | Path, key: str):
    """A torch tensor over a copy-on-write map of tensor ``key`` (writable for torch, never written back)."""
    import torch

    a = mmap_tensor(path, key)
    if isinstance(a, np.memmap):
        a = np.memmap(a.filename, dtype=a.dtype, mode="c", offset=a.offset, shape=a.shape)
    return torch.from_numpy(a)
