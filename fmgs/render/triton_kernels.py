"""The Triton kernels of the ``triton`` backend (triton_blend.py launches them; imported only when used).

``blend_tiles``: one program blends BP pixels of one tile into CB channels, walking the tile's
front-to-back list BK Gaussians at a time with reference.py's rule (``_blend_chunk``). It stops either
when every pixel has terminated (a ``while`` loop) or, with PIPELINED, after the tile's extent measured
by ``tile_extents`` (a ``for`` loop, which Triton software-pipelines: the next batch's loads overlap
this batch's work). ``tile_extents`` walks each tile's list with the same rule and no features and
records how far the tile's last pixel got.

Under ``TRITON_INTERPRET=1`` (set before triton is first imported) the kernels run in Triton's
interpreter on CPU tensors: that is how the CPU test suite checks them.
"""

from __future__ import annotations

import triton
import triton.language as tl


@triton.jit
def _tile_pixels(tile, SUB: tl.constexpr, BP: tl.constexpr, TILE: tl.constexpr, tiles_x, W, H):
    """This program's pixels of ``tile``: (x0, y0, px, py, centre x, centre y, inside the image)."""
    p = (tl.program_id(0) % SUB) * BP + tl.arange(0, BP)  # pixel index inside the tile
    x0 = (tile % tiles_x) * TILE
    y0 = (tile // tiles_x) * TILE
    lx = p % TILE
    ly = p // TILE
    px = x0 + lx
    py = y0 + ly
    ok = (p < TILE * TILE) & (px < W) & (py < H)
    # Pixel centres relative to the tile origin (exact in float32 and float64).
    return x0, y0, px, py, lx.to(tl.float64) + 0.5, ly.to(tl.float64) + 0.5, ok


@triton.jit
def _weights(
    kk, end, x0, y0, cx, cy, gauss_ids_ptr, means2d_ptr, conics_ptr, opac_ptr, Tcar, done,
    alpha_min, alpha_max, t_min, GEOM64: tl.constexpr,
):  # fmt: skip
    """Blending weights [BP,BK] (float64) of list entries kk [BK] and the updated carry (Tcar, done)."""
    kv = kk < end
    g = tl.load(gauss_ids_ptr + kk, mask=kv, other=0)
    # Means relative to the tile origin, formed in float64: small numbers, so float32 keeps them.
    mx = tl.load(means2d_ptr + 2 * g, mask=kv, other=0.0) - x0.to(tl.float64)
    my = tl.load(means2d_ptr + 2 * g + 1, mask=kv, other=0.0) - y0.to(tl.float64)
    ca = tl.load(conics_ptr + 3 * g, mask=kv, other=0.0)
    cr = tl.load(conics_ptr + 3 * g + 1, mask=kv, other=0.0)
    ce = tl.load(conics_ptr + 3 * g + 2, mask=kv, other=0.0)
    op = tl.load(opac_ptr + g, mask=kv, other=0.0)
    if GEOM64:
        dx = cx[:, None] - mx[None, :]
        dy = cy[:, None] - my[None, :]
        s = dx + cr[None, :] * dy
        power = ca[None, :] * s * s + ce[None, :] * dy * dy
        alpha = op[None, :] * tl.exp(-0.5 * power)
    else:
        dx = cx.to(tl.float32)[:, None] - mx.to(tl.float32)[None, :]
        dy = cy.to(tl.float32)[:, None] - my.to(tl.float32)[None, :]
        s = dx + cr.to(tl.float32)[None, :] * dy
        power = ca.to(tl.float32)[None, :] * s * s + ce.to(tl.float32)[None, :] * dy * dy
        alpha = (op.to(tl.float32)[None, :] * tl.exp(-0.5 * power)).to(tl.float64)
    alpha = tl.minimum(alpha, alpha_max)
    alpha = tl.where((alpha >= alpha_min) & kv[None, :], alpha, 0.0)
    # Transmittance after each Gaussian of the batch, then before it (alpha <= alpha_max < 1).
    t_after = Tcar[:, None] * tl.cumprod(1.0 - alpha, axis=1)
    t_before = t_after / (1.0 - alpha)
    live = alpha > 0.0
    keep = (t_after >= t_min) & (done == 0)[:, None] & live
    w = tl.where(keep, alpha * t_before, 0.0)
    stop = tl.max(((t_after < t_min) & live).to(tl.int32), axis=1)
    # Kept entries are a prefix along which t_after falls: carry the last kept one.
    last = tl.min(tl.where(keep, t_after, 2.0), axis=1)
    return w, g, kv, tl.where(last < 2.0, last, Tcar), tl.maximum(done, stop)


@triton.jit
def _blend_step(
    kk, end, x0, y0, cx, cy, ch, ch_ok, gauss_ids_ptr, means2d_ptr, conics_ptr, opac_ptr, depth_ptr, feat_ptr,
    feat_stride, acc, wsum, zsum, Tcar, done, alpha_min, alpha_max, t_min, GEOM64: tl.constexpr,
    PRECISION: tl.constexpr,
):  # fmt: skip
    """Blend list entries kk [BK] into the accumulators: features [BP,CB] (one tl.dot), weight and depth
    sums [BP]; returns them with the carry (Tcar, done)."""
    w, g, kv, Tcar, done = _weights(
        kk, end, x0, y0, cx, cy, gauss_ids_ptr, means2d_ptr, conics_ptr, opac_ptr, Tcar, done,
        alpha_min, alpha_max, t_min, GEOM64,
    )  # fmt: skip
    f = tl.load(
        feat_ptr + g[:, None] * feat_stride + ch[None, :], mask=kv[:, None] & ch_ok[None, :], other=0.0
    )
    acc += tl.dot(w.to(tl.float32), f.to(tl.float32), input_precision=PRECISION)
    z = tl.load(depth_ptr + g, mask=kv, other=0.0)
    return acc, wsum + tl.sum(w, axis=1), zsum + tl.sum(w * z[None, :], axis=1), Tcar, done


@triton.jit
def tile_extents(
    gauss_ids_ptr,  # [I] int64 tile lists, front to back (TileBins.gauss_ids)
    offsets_ptr,  # [n_tiles+1] int64
    means2d_ptr,  # [N,2] float64
    conics_ptr,  # [N,3] float64 (A, r, e), Projection.conics
    opac_ptr,  # [N] float64
    extent_ptr,  # [n_tiles] int64 out: list entries walked before every pixel of the tile terminated
    W,
    H,
    tiles_x,
    rule_ptr,  # [3] float64: alpha_min, alpha_max, transmittance_min
    TILE: tl.constexpr,
    BP: tl.constexpr,  # a power of two >= TILE * TILE: the whole tile
    BK: tl.constexpr,
    GEOM64: tl.constexpr,
):
    tile = tl.program_id(0)
    x0, y0, _px, _py, cx, cy, ok = _tile_pixels(tile, 1, BP, TILE, tiles_x, W, H)
    alpha_min = tl.load(rule_ptr)
    alpha_max = tl.load(rule_ptr + 1)
    t_min = tl.load(rule_ptr + 2)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    Tcar = tl.full([BP], 1.0, tl.float64)
    done = 1 - ok.to(tl.int32)
    k0 = start
    go = (k0 < end) & (tl.sum(1 - done, axis=0) > 0)
    while go:
        _w, _g, _kv, Tcar, done = _weights(
            k0 + tl.arange(0, BK), end, x0, y0, cx, cy, gauss_ids_ptr, means2d_ptr, conics_ptr, opac_ptr,
            Tcar, done, alpha_min, alpha_max, t_min, GEOM64,
        )  # fmt: skip
        k0 += BK
        go = (k0 < end) & (tl.sum(1 - done, axis=0) > 0)
    tl.store(extent_ptr + tile, tl.minimum(k0, end) - start)


@triton.jit
def blend_tiles(
    gauss_ids_ptr,  # [I] int64 tile lists, front to back (TileBins.gauss_ids)
    offsets_ptr,  # [n_tiles+1] int64
    extent_ptr,  # [n_tiles] int64 from tile_extents (read only when PIPELINED)
    means2d_ptr,  # [N,2] float64
    conics_ptr,  # [N,3] float64 (A, r, e), Projection.conics
    opac_ptr,  # [N] float64
    depth_ptr,  # [N] float64
    feat_ptr,  # [N,C] float32 / float16 / bfloat16
    out_ptr,  # [H,W,C] float32
    aux_ptr,  # [3,H,W] float64: weight sum, weighted depth sum, final transmittance
    W,
    H,
    C,
    feat_stride,
    tiles_x,
    rule_ptr,  # [3] float64: alpha_min, alpha_max, transmittance_min (float64, as the reference compares)
    TILE: tl.constexpr,
    SUB: tl.constexpr,
    BP: tl.constexpr,
    BK: tl.constexpr,
    CB: tl.constexpr,
    GEOM64: tl.constexpr,
    PRECISION: tl.constexpr,
    PIPELINED: tl.constexpr,
    STAGES: tl.constexpr,
    INTERPRET: tl.constexpr,
):
    tile = tl.program_id(0) // SUB
    cb = tl.program_id(1)
    x0, y0, px, py, cx, cy, pix_ok = _tile_pixels(tile, SUB, BP, TILE, tiles_x, W, H)
    ch = cb * CB + tl.arange(0, CB)
    ch_ok = ch < C
    alpha_min = tl.load(rule_ptr)
    alpha_max = tl.load(rule_ptr + 1)
    t_min = tl.load(rule_ptr + 2)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)

    Tcar = tl.full([BP], 1.0, tl.float64)
    done = 1 - pix_ok.to(tl.int32)  # 1: the pixel has terminated (padding pixels never hold the tile back)
    acc = tl.zeros([BP, CB], dtype=tl.float32)
    wsum = tl.zeros([BP], dtype=tl.float64)
    zsum = tl.zeros([BP], dtype=tl.float64)
    if PIPELINED:
        stop_at = start + tl.load(extent_ptr + tile)
        if INTERPRET:  # Triton's interpreter cannot take tensor bounds in range(): the same loop as a while
            k0 = start
            while k0 < stop_at:
                acc, wsum, zsum, Tcar, done = _blend_step(
                    k0 + tl.arange(0, BK), end, x0, y0, cx, cy, ch, ch_ok, gauss_ids_ptr, means2d_ptr,
                    conics_ptr, opac_ptr, depth_ptr, feat_ptr, feat_stride, acc, wsum, zsum, Tcar, done,
                    alpha_min, alpha_max, t_min, GEOM64, PRECISION,
                )  # fmt: skip
                k0 += BK
        else:
            for k0 in tl.range(start, stop_at, BK, num_stages=STAGES):
                acc, wsum, zsum, Tcar, done = _blend_step(
                    k0 + tl.arange(0, BK), end, x0, y0, cx, cy, ch, ch_ok, gauss_ids_ptr, means2d_ptr,
                    conics_ptr, opac_ptr, depth_ptr, feat_ptr, feat_stride, acc, wsum, zsum, Tcar, done,
                    alpha_min, alpha_max, t_min, GEOM64, PRECISION,
                )  # fmt: skip
    else:
        k0 = start
        go = (k0 < end) & (tl.sum(1 - done, axis=0) > 0)
        while go:
            acc, wsum, zsum, Tcar, done = _blend_step(
                k0 + tl.arange(0, BK), end, x0, y0, cx, cy, ch, ch_ok, gauss_ids_ptr, means2d_ptr, conics_ptr,
                opac_ptr, depth_ptr, feat_ptr, feat_stride, acc, wsum, zsum, Tcar, done, alpha_min, alpha_max,
                t_min, GEOM64, PRECISION,
            )  # fmt: skip
            k0 += BK
            go = (k0 < end) & (tl.sum(1 - done, axis=0) > 0)

    pix = (py * W + px).to(tl.int64)
    tl.store(out_ptr + pix[:, None] * C + ch[None, :], acc, mask=pix_ok[:, None] & ch_ok[None, :])
    first = pix_ok & (cb == 0)
    HW = H * W
    tl.store(aux_ptr + pix, wsum, mask=first)
    tl.store(aux_ptr + HW + pix, zsum, mask=first)
    tl.store(aux_ptr + 2 * HW + pix, Tcar, mask=first)
