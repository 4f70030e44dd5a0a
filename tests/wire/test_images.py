"""The image encodings (``fmgs_wire.images``): the PNG writer read by Pillow, the pure decoder on every
filter type, the colour map, and the PNG file round trip."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest

from fmgs_wire.images import colorize, decode_png, encode_png, read_png, write_png

# ---------------------------------------------------------------- images and PLY


def _png_with_filters(img: np.ndarray, ftypes) -> bytes:
    """An 8-bit PNG whose rows use the given filter types (0-4 in turn), to exercise the decoder."""
    h = img.shape[0]
    bpp = 3 if img.ndim == 3 else 1
    rows = img.reshape(h, -1).astype(np.int64)
    raw = bytearray()
    prev = np.zeros(rows.shape[1], np.int64)
    for i in range(h):
        f = ftypes[i % len(ftypes)]
        x = rows[i]
        a = np.concatenate([np.zeros(bpp, np.int64), x[:-bpp]])
        c = np.concatenate([np.zeros(bpp, np.int64), prev[:-bpp]])
        if f == 0:
            pred = 0
        elif f == 1:
            pred = a
        elif f == 2:
            pred = prev
        elif f == 3:
            pred = (a + prev) // 2
        else:
            p = a + prev - c
            pa, pb_, pc = abs(p - a), abs(p - prev), abs(p - c)
            pred = np.where((pa <= pb_) & (pa <= pc), a, np.where(pb_ <= pc, prev, c))
        raw += bytes([f]) + ((x - pred) % 256).astype(np.uint8).tobytes()
        prev = x
    ihdr = struct.pack(">IIBBBBB", img.shape[1], h, 8, 2 if bpp == 3 else 0, 0, 0, 0)

    def chunk(k, d):
        return struct.pack(">I", len(d)) + k + d + struct.pack(">I", zlib.crc32(k + d))

    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(bytes(raw)))
        + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize(
    "dtype, shape, mode",
    [(np.uint8, (17, 23), "L"), (np.uint8, (17, 23, 3), "RGB"), (np.uint16, (17, 23), "I;16")],
)
def test_png_writer_read_by_pillow(tmp_path, dtype, shape, mode):
    from PIL import Image

    rng = np.random.default_rng(5)
    img = rng.integers(0, np.iinfo(dtype).max + 1, shape).astype(dtype)
    path = write_png(tmp_path / "x.png", img)
    with Image.open(path) as im:
        assert im.mode == mode and im.size == (shape[1], shape[0])
        back = np.asarray(im)
    np.testing.assert_array_equal(back, img)
    for use_pillow in (False, True):
        np.testing.assert_array_equal(decode_png(path.read_bytes(), use_pillow), img)
    # PNGs from another encoder (pillow: adaptive filters) decode with the pure decoder too.
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", optimize=True)
    for use_pillow in (False, True):
        back = decode_png(buf.getvalue(), use_pillow)
        assert back.dtype == img.dtype
        np.testing.assert_array_equal(back, img)


def test_png_decoder_all_filters():
    rng = np.random.default_rng(6)
    for img in (
        rng.integers(0, 256, (10, 9, 3), dtype=np.uint8),
        rng.integers(0, 256, (10, 9), dtype=np.uint8),
    ):
        np.testing.assert_array_equal(decode_png(_png_with_filters(img, [0, 1, 2, 3, 4]), False), img)
        np.testing.assert_array_equal(decode_png(_png_with_filters(img, [4, 3, 1]), False), img)
    with pytest.raises(ValueError, match="signature"):
        decode_png(b"GIF89a")
    with pytest.raises(ValueError, match="need uint8"):
        encode_png(np.zeros((2, 2), np.float32))


def test_colour_map():
    c = colorize(np.array([[-1.0, 0.0, 0.5], [1.0, 2.0, np.nan]]))
    assert c.shape == (2, 3, 3) and c.dtype == np.uint8
    np.testing.assert_array_equal(c[0, 0], c[0, 1])  # clipped below
    np.testing.assert_array_equal(c[1, 0], c[1, 1])  # clipped above
    np.testing.assert_array_equal(c[1, 2], c[0, 1])  # NaN -> lowest
    lo, hi = c[0, 1].astype(int), c[1, 0].astype(int)
    assert lo[2] > lo[0] and hi[0] > hi[2]  # blue-ish low end, red high end
    assert len({tuple(v) for v in colorize(np.linspace(0, 1, 50))}) > 40  # no flat stretches


def test_png_file_round_trip(tmp_path):
    img = np.arange(24, dtype=np.uint8).reshape(4, 6)
    path = write_png(tmp_path / "c.png", img)
    np.testing.assert_array_equal(read_png(path), img)
