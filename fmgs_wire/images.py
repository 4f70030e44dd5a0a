"""Minimal PNG writing and reading (zlib + struct only) and the relevancy colour map.

Supported images: 8-bit grey ``uint8 [H,W]``, 8-bit RGB ``uint8 [H,W,3]`` and 16-bit grey
``uint16 [H,W]`` (the modes the server emits). No pillow needed.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# (bit depth, colour type) -> (numpy dtype, channels)
_MODES = {(8, 0): (np.uint8, 1), (8, 2): (np.uint8, 3), (16, 0): (np.dtype(">u2"), 1)}

# Turbo-like colour map: 17 samples of Google's turbo polynomial at t = 0, 1/16, ..., 1 (the two ends
# from the turbo table itself), interpolated linearly: dark blue -> cyan -> green -> yellow -> dark red.
_TURBO = np.array(
    [
        (0.190, 0.072, 0.232),
        (0.288, 0.244, 0.686),
        (0.269, 0.415, 0.935),
        (0.197, 0.586, 0.970),
        (0.148, 0.740, 0.881),
        (0.162, 0.866, 0.733),
        (0.250, 0.953, 0.573),
        (0.401, 0.993, 0.428),
        (0.589, 0.982, 0.313),
        (0.777, 0.921, 0.231),
        (0.932, 0.814, 0.177),
        (1.000, 0.670, 0.142),
        (1.000, 0.502, 0.114),
        (0.935, 0.329, 0.084),
        (0.786, 0.175, 0.047),
        (0.632, 0.070, 0.006),
        (0.480, 0.016, 0.011),
    ]
)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def encode_png(image: np.ndarray, level: int = 6) -> bytes:
    """PNG bytes of ``uint8 [H,W]`` (grey), ``uint8 [H,W,3]`` (RGB) or ``uint16 [H,W]`` (16-bit grey)."""
    a = np.asarray(image)
    if a.ndim == 2 and a.dtype == np.uint8:
        depth, ctype = 8, 0
    elif a.ndim == 3 and a.shape[2] == 3 and a.dtype == np.uint8:
        depth, ctype = 8, 2
    elif a.ndim == 2 and a.dtype == np.uint16:
        depth, ctype = 16, 0
        a = a.astype(">u2")  # PNG samples are big-endian
    else:
        raise ValueError(
            f"encode_png: need uint8 [H,W], uint8 [H,W,3] or uint16 [H,W], got {a.dtype} {a.shape}"
        )
    h, w = a.shape[:2]
    if h < 1 or w < 1:
        raise ValueError(f"encode_png: empty image {a.shape}")
    rows = np.ascontiguousarray(a).reshape(h, -1).view(np.uint8)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], 1)  # filter type 0 (None) on each row
    ihdr = struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, 0)
    return (
        _SIGNATURE
        + _chunk(b"IHDR", ihdr)
        + _chunk(b"IDAT", zlib.compress(raw.tobytes(), level))
        + _chunk(b"IEND", b"")
    )


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write ``image`` (see :func:`encode_png`) to ``path``; returns the path."""
    path = Path(path)
    path.write_bytes(encode_png(image))
    return path


def _unfilter(raw: np.ndarray, h: int, stride: int, bpp: int) -> np.ndarray:
    """Undo the per-row PNG filters (types 0-4) of ``raw`` [h, 1 + stride]."""
    out = np.zeros((h, stride), np.uint8)
    prev = np.zeros(stride, np.uint8)
    for i in range(h):
        ftype, line = int(raw[i, 0]), raw[i, 1:]
        if ftype == 0:  # None
            cur = line
        elif ftype == 1:  # Sub: a running sum along each channel
            cur = np.cumsum(line.reshape(-1, bpp), 0, dtype=np.int64).reshape(-1).astype(np.uint8)
        elif ftype == 2:  # Up
            cur = line + prev  # uint8 arithmetic wraps modulo 256, as PNG wants
        elif ftype in (3, 4):
            # Average and Paeth depend on the reconstructed left neighbour: a sequential walk.
            # Plain Python ints are much faster than tiny numpy slices here.
            x, up, c = line.tolist(), prev.tolist(), [0] * stride
            for j in range(stride):
                a = c[j - bpp] if j >= bpp else 0
                b = up[j]
                if ftype == 3:
                    pred = (a + b) >> 1
                else:
                    ul = up[j - bpp] if j >= bpp else 0
                    p = a + b - ul
                    pa, pb_, pc = abs(p - a), abs(p - b), abs(p - ul)
                    pred = a if pa <= pb_ and pa <= pc else (b if pb_ <= pc else ul)
                c[j] = (x[j] + pred) & 0xFF
            cur = np.asarray(c, np.uint8)
        else:
            raise ValueError(f"decode_png: bad filter type {ftype} in row {i}")
        out[i] = cur
        prev = out[i]
    return out


def _decode_with_pillow(data: bytes) -> np.ndarray | None:
    """Pillow's decoder (C, ~50x faster on adaptively filtered images) when installed and the mode fits."""
    try:
        from PIL import Image
    except ImportError:
        return None
    import io

    with Image.open(io.BytesIO(data)) as im:
        if im.format != "PNG" or im.mode not in ("L", "RGB", "I;16"):
            return None
        return np.asarray(im).copy()


def decode_png(data: bytes, use_pillow: bool = True) -> np.ndarray:
    """Decode a non-interlaced 8-bit grey/RGB or 16-bit grey PNG into ``uint8``/``uint16`` arrays.

    The pure zlib/numpy decoder needs nothing else but walks Average/Paeth-filtered rows in Python
    (~0.4 s for a 640x480 RGB image); with ``use_pillow`` and Pillow installed, Pillow decodes instead.
    """
    if not data.startswith(_SIGNATURE):
        raise ValueError("decode_png: not a PNG (bad signature)")
    if use_pillow:
        img = _decode_with_pillow(data)
        if img is not None:
            return img
    pos, ihdr, idat = len(_SIGNATURE), None, []
    while pos + 8 <= len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        if len(body) != n:
            raise ValueError("decode_png: truncated chunk")
        pos += 12 + n
        if kind == b"IHDR":
            ihdr = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    if ihdr is None or not idat:
        raise ValueError("decode_png: missing IHDR or IDAT")
    w, h, depth, ctype, _, _, interlace = ihdr
    if (depth, ctype) not in _MODES or interlace:
        raise ValueError(f"decode_png: unsupported bit depth {depth} / colour type {ctype} / interlace")
    dtype, ch = _MODES[(depth, ctype)]
    bpp = ch * np.dtype(dtype).itemsize
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8)
    if raw.size != h * (1 + w * bpp):
        raise ValueError("decode_png: pixel data size does not match the header")
    rows = _unfilter(raw.reshape(h, 1 + w * bpp), h, w * bpp, bpp)
    img = rows.view(dtype).reshape((h, w, ch) if ch > 1 else (h, w))
    return img.astype(np.dtype(dtype).newbyteorder("="))


def read_png(path: str | Path) -> np.ndarray:
    """Read a PNG written by :func:`write_png` (or the server)."""
    return decode_png(Path(path).read_bytes())


def colorize(values: np.ndarray, vmin: float = 0.0, vmax: float = 1.0) -> np.ndarray:
    """``uint8 [...,3]`` turbo-like colours of ``values`` mapped from [vmin, vmax] to [0, 1] and clipped.

    NaN maps to the lowest colour.
    """
    v = np.asarray(values, np.float64)
    t = (v - vmin) / (vmax - vmin) if vmax > vmin else np.zeros_like(v)
    t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)
    x = t * (len(_TURBO) - 1)
    lo = np.minimum(x.astype(np.int64), len(_TURBO) - 2)
    f = (x - lo)[..., None]
    rgb = _TURBO[lo] * (1 - f) + _TURBO[lo + 1] * f
    return np.round(rgb * 255).astype(np.uint8)


def relevancy_png(path: str | Path, relevancy: np.ndarray, vmin: float = 0.0, vmax: float = 1.0) -> Path:
    """Write a relevancy image [H,W] as an RGB PNG coloured with :func:`colorize`."""
    return write_png(path, colorize(relevancy, vmin, vmax))


PNG_SCALE = {"relevancy": 255.0, "rgb": 255.0, "alpha": 255.0, "depth": 1000.0}
"""PNG outputs on the wire: value = sample / scale (8-bit relevancy, rgb and alpha; 16-bit depth in mm)."""


def encode_output_png(kind: str, image: np.ndarray) -> bytes:
    """PNG bytes of a rendered output ``kind`` (a key of PNG_SCALE) as the wire encodes it."""
    if kind not in PNG_SCALE:
        raise ValueError(f"encode_output_png: unknown output {kind!r}; choose from {sorted(PNG_SCALE)}")
    if kind == "depth":
        return encode_png(depth_to_uint16(image, PNG_SCALE["depth"]))
    return encode_png(to_uint8(image))


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float image in [0,1] (clipped; NaN -> 0) to uint8."""
    return np.round(np.clip(np.nan_to_num(np.asarray(image, np.float64)), 0, 1) * 255).astype(np.uint8)


def depth_to_uint16(depth: np.ndarray, scale: float = 1000.0) -> np.ndarray:
    """Depth [H,W] in scene units to uint16 ``depth * scale`` (millimetres by default), clipped; NaN -> 0."""
    d = np.nan_to_num(np.asarray(depth, np.float64) * scale, nan=0.0, posinf=65535)
    return np.round(np.clip(d, 0, 65535)).astype(np.uint16)


def label_colors(labels: np.ndarray) -> np.ndarray:
    """``uint8 [...,3]`` distinct colours for integer labels; negative labels (nothing) are black."""
    lab = np.asarray(labels, np.int64)
    # Golden-ratio hue steps keep neighbouring labels far apart in colour.
    hue = (np.maximum(lab, 0) * 0.618033988749895) % 1.0
    rgb = _hsv_to_rgb(hue, 0.75, 0.95)
    rgb[lab < 0] = 0
    return np.round(rgb * 255).astype(np.uint8)


def _hsv_to_rgb(h: np.ndarray, s: float, v: float) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0]) + h[..., None] * 6) % 6
    return v - v * s * np.clip(np.minimum(k, 4 - k), 0, 1)
