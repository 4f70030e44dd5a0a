"""numpy arrays <-> ``fmgs.v1.Tensor`` (dtype, shape, little-endian C-order bytes), and chunk joining."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

_TO_WIRE = {
    np.dtype("float32"): pb.DTYPE_FLOAT32,
    np.dtype("float16"): pb.DTYPE_FLOAT16,
    np.dtype("float64"): pb.DTYPE_FLOAT64,
    np.dtype("int32"): pb.DTYPE_INT32,
    np.dtype("int64"): pb.DTYPE_INT64,
    np.dtype("uint8"): pb.DTYPE_UINT8,
}
_FROM_WIRE = {v: k.newbyteorder("<") for k, v in _TO_WIRE.items()}
MAX_DIMS = 8


class TensorError(ValueError):
    """A wire tensor whose dtype, shape or byte count is inconsistent; ``field`` names it."""

    def __init__(self, field: str, reason: str) -> None:
        self.field = field
        super().__init__(f"{field}: {reason}")


def to_tensor(a: np.ndarray) -> pb.Tensor:
    """Encode an array (any supported dtype, any byte order) as a little-endian wire tensor."""
    a = np.asarray(a)
    dt = a.dtype.newbyteorder("=") if a.dtype.byteorder not in ("=", "|") else a.dtype
    if dt not in _TO_WIRE:
        raise TensorError("tensor", f"unsupported dtype {a.dtype}")
    le = np.ascontiguousarray(a, dtype=dt.newbyteorder("<"))
    return pb.Tensor(dtype=_TO_WIRE[dt], shape=list(a.shape), data=le.tobytes())


def from_tensor(t: pb.Tensor, field: str = "tensor") -> np.ndarray:
    """Decode a wire tensor into a native-endian array; TensorError names ``field`` when it is malformed."""
    if t.dtype not in _FROM_WIRE:
        raise TensorError(field, f"unsupported or missing dtype {t.dtype}")
    shape = tuple(int(s) for s in t.shape)
    if len(shape) > MAX_DIMS or any(s < 0 for s in shape):
        raise TensorError(field, f"bad shape {list(shape)}")
    dt = _FROM_WIRE[t.dtype]
    n = 1
    for s in shape:
        n *= s
    if n * dt.itemsize != len(t.data):
        raise TensorError(
            field, f"shape {list(shape)} of {dt.name} needs {n * dt.itemsize} bytes, got {len(t.data)}"
        )
    return np.frombuffer(t.data, dtype=dt).reshape(shape).astype(dt.newbyteorder("="), copy=True)


def join(parts: Iterable[np.ndarray], empty_shape: tuple[int, ...] = (0,), dtype=np.float32) -> np.ndarray:
    """Concatenate chunk slices along axis 0 (the chunking convention); ``empty_shape`` when none came."""
    parts = list(parts)
    if not parts:
        return np.zeros(empty_shape, dtype)
    return parts[0] if len(parts) == 1 else np.concatenate(parts, 0)


def row_chunks(n_rows: int, bytes_per_row: int, max_bytes: int) -> list[tuple[int, int]]:
    """[(start, stop)] row ranges covering n_rows with at most ``max_bytes`` of payload each (>= 1 row)."""
    step = max(1, max_bytes // max(1, bytes_per_row))
    return [(s, min(n_rows, s + step)) for s in range(0, n_rows, step)] or [(0, 0)]
