"""Write a safetensors file a block of rows at a time, converting each block to its stored dtype.

``safetensors.torch.save_file`` needs every tensor converted in memory and then copies it to bytes: for
a 10M-Gaussian scene's float32 embeddings that is 20 GB of input plus 10 GB of float16 plus 10 GB of
bytes. Here the peak beyond the caller's tensors is one block. The file is plain safetensors (readable
by ``safetensors.safe_open`` and ``fmgs.io.mmap_tensors``).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import torch

_NAMES = {
    torch.float16: "F16",
    torch.bfloat16: "BF16",
    torch.float32: "F32",
    torch.float64: "F64",
    torch.int8: "I8",
    torch.uint8: "U8",
    torch.int32: "I32",
    torch.int64: "I64",
    torch.bool: "BOOL",
}
BLOCK_BYTES = 64 << 20  # rows per block: about this many bytes of the source tensor


def save_blocks(
    path: str | Path,
    tensors: dict[str, torch.Tensor | tuple[torch.Tensor, torch.dtype]],
    metadata: dict[str, str] | None = None,
) -> None:
    """Write ``tensors`` (name -> tensor, or (tensor, stored dtype)) to ``path`` (not atomic: callers
    write inside fmgs.io.atomic). Tensors may live on any device or be memory maps; each is read and
    converted in blocks of leading-dimension rows."""
    items = []
    offset = 0
    header: dict = {}
    for name, spec in tensors.items():
        t, dtype = spec if isinstance(spec, tuple) else (spec, spec.dtype)
        if dtype not in _NAMES:
            raise ValueError(f"{name}: dtype {dtype} cannot be stored")
        size = t.numel() * torch.empty(0, dtype=dtype).element_size()
        header[name] = {
            "dtype": _NAMES[dtype],
            "shape": list(t.shape),
            "data_offsets": [offset, offset + size],
        }
        items.append((t, dtype))
        offset += size
    if metadata:
        header["__metadata__"] = {str(k): str(v) for k, v in metadata.items()}
    raw = json.dumps(header, separators=(",", ":")).encode()
    raw += b" " * (-len(raw) % 8)  # the data starts 8-byte aligned, as safetensors writes it
    with Path(path).open("wb") as f:
        f.write(struct.pack("<Q", len(raw)))
        f.write(raw)
        for t, dtype in items:
            if t.numel() == 0:
                continue
            if t.ndim == 0:
                t = t.reshape(1)
            row_bytes = max(1, t[0].numel() * t.element_size())
            step = max(1, BLOCK_BYTES // row_bytes)
            for s in range(0, t.shape[0], step):
                block = t[s : s + step].detach().to("cpu", dtype).contiguous()
                f.write(block.reshape(-1).view(torch.uint8).numpy().data)
