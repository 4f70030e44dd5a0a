"""The Triton kernels of the ``triton`` backend (triton_blend.py launches them; imported only when used).

``project_gaussians``: projection.py's float64 projection, one launch.

``blend_tiles`` (the single pass): one program blends BP pixels of one tile into CB channels, walking the
tile's front-to-back list BK Gaussians at a time with reference.py's rule (``blend_chunk``) until every
pixel has terminated.

The weights-once path, for many channels: ``tile_extents`` walks each tile's list with the same rule and
no features and records how far the tile's last pixel got; ``tile_weights`` writes every pixel's weights
over that extent to a buffer; ``blend_weights`` multiplies them by each block of channels in a
software-pipelined loop, evaluating no geometry.

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
def _store_aux(aux_ptr, pix, mask, wsum, zsum, Tcar, W, H):
    """Per pixel: weight sum, weighted depth sum and final transmittance into aux [3,H,W]."""
    HW = H * W
    tl.store(aux_ptr + pix, wsum, mask=mask)
    tl.store(aux_ptr + HW + pix, zsum, mask=mask)
    tl.store(aux_ptr + 2 * HW + pix, Tcar, mask=mask)


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
    _store_aux(aux_ptr, pix, pix_ok & (cb == 0), wsum, zsum, Tcar, W, H)


@triton.jit
def project_gaussians(
    means_ptr,  # [N,3] any float dtype (read as float64)
    quats_ptr,  # [N,4] wxyz, any non-zero norm
    scales_ptr,  # [N,3] positive
    opac_ptr,  # [N] in [0,1]
    cam_ptr,  # [21] float64: R (9, row-major), t (3), fx, fy, cx, cy, near, far, eps2d, fov_clip, alpha_min
    means2d_ptr,  # [N,2] float64 out
    depth_ptr,  # [N] float64 out
    conics_ptr,  # [N,3] float64 out: (A, r, e), Projection.conics
    opac64_ptr,  # [N] float64 out
    radii_ptr,  # [N] int32 out
    bbox_ptr,  # [N,4] int64 out: inclusive pixel box (x0, y0, x1, y1)
    visible_ptr,  # [N] int8 out
    N,
    W,
    H,
    BLOCK: tl.constexpr,
):
    """projection.project (and its _extent) for BLOCK Gaussians per program, operation for operation in
    float64."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    ok = i < N
    i64 = i.to(tl.int64)
    mx = tl.load(means_ptr + 3 * i64, mask=ok, other=0.0).to(tl.float64)
    my = tl.load(means_ptr + 3 * i64 + 1, mask=ok, other=0.0).to(tl.float64)
    mz = tl.load(means_ptr + 3 * i64 + 2, mask=ok, other=0.0).to(tl.float64)
    qw = tl.load(quats_ptr + 4 * i64, mask=ok, other=1.0).to(tl.float64)
    qx = tl.load(quats_ptr + 4 * i64 + 1, mask=ok, other=0.0).to(tl.float64)
    qy = tl.load(quats_ptr + 4 * i64 + 2, mask=ok, other=0.0).to(tl.float64)
    qz = tl.load(quats_ptr + 4 * i64 + 3, mask=ok, other=0.0).to(tl.float64)
    sx = tl.load(scales_ptr + 3 * i64, mask=ok, other=1.0).to(tl.float64)
    sy = tl.load(scales_ptr + 3 * i64 + 1, mask=ok, other=1.0).to(tl.float64)
    sz = tl.load(scales_ptr + 3 * i64 + 2, mask=ok, other=1.0).to(tl.float64)
    o = tl.load(opac_ptr + i64, mask=ok, other=0.0).to(tl.float64)
    r00 = tl.load(cam_ptr)
    r01 = tl.load(cam_ptr + 1)
    r02 = tl.load(cam_ptr + 2)
    r10 = tl.load(cam_ptr + 3)
    r11 = tl.load(cam_ptr + 4)
    r12 = tl.load(cam_ptr + 5)
    r20 = tl.load(cam_ptr + 6)
    r21 = tl.load(cam_ptr + 7)
    r22 = tl.load(cam_ptr + 8)
    fx = tl.load(cam_ptr + 12)
    fy = tl.load(cam_ptr + 13)
    cx = tl.load(cam_ptr + 14)
    cy = tl.load(cam_ptr + 15)
    near = tl.load(cam_ptr + 16)
    far = tl.load(cam_ptr + 17)
    eps = tl.load(cam_ptr + 18)
    fov_clip = tl.load(cam_ptr + 19)
    alpha_min = tl.load(cam_ptr + 20)
    px = mx * r00 + my * r01 + mz * r02 + tl.load(cam_ptr + 9)
    py = mx * r10 + my * r11 + mz * r12 + tl.load(cam_ptr + 10)
    z = mx * r20 + my * r21 + mz * r22 + tl.load(cam_ptr + 11)
    in_depth = (z > near) & (z < far)
    zs = tl.where(in_depth, z, 1.0)
    Wf = W.to(tl.float64)
    Hf = H.to(tl.float64)
    tan_x = 0.5 * Wf / fx
    tan_y = 0.5 * Hf / fy
    lim_xp = (Wf - cx) / fx + fov_clip * tan_x
    lim_xn = cx / fx + fov_clip * tan_x
    lim_yp = (Hf - cy) / fy + fov_clip * tan_y
    lim_yn = cy / fy + fov_clip * tan_y
    tx = zs * tl.minimum(tl.maximum(px / zs, -lim_xn), lim_xp)
    ty = zs * tl.minimum(tl.maximum(py / zs, -lim_yn), lim_yp)
    # J (2x3) @ R: rows a (x) and b (y).
    j00 = fx / zs
    j02 = -fx * tx / (zs * zs)
    j11 = fy / zs
    j12 = -fy * ty / (zs * zs)
    a0 = j00 * r00 + j02 * r20
    a1 = j00 * r01 + j02 * r21
    a2 = j00 * r02 + j02 * r22
    b0 = j11 * r10 + j12 * r20
    b1 = j11 * r11 + j12 * r21
    b2 = j11 * r12 + j12 * r22
    # The unit quaternion (safe_normalize: divide by the largest component first).
    m = tl.maximum(tl.maximum(tl.abs(qw), tl.abs(qx)), tl.maximum(tl.abs(qy), tl.abs(qz)))
    m = tl.where(m > 0, m, 1.0)
    qw, qx, qy, qz = qw / m, qx / m, qy / m, qz / m
    nrm = tl.maximum(tl.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 2.2250738585072014e-308)
    qw, qx, qy, qz = qw / nrm, qx / nrm, qy / nrm, qz / nrm
    # L = R(q) diag(s) (cameras.quat_wxyz_to_rotmat), then M = (J R) L, clamped.
    q00 = (1 - 2 * (qy * qy + qz * qz)) * sx
    q01 = 2 * (qx * qy - qw * qz) * sy
    q02 = 2 * (qx * qz + qw * qy) * sz
    q10 = 2 * (qx * qy + qw * qz) * sx
    q11 = (1 - 2 * (qx * qx + qz * qz)) * sy
    q12 = 2 * (qy * qz - qw * qx) * sz
    q20 = 2 * (qx * qz - qw * qy) * sx
    q21 = 2 * (qy * qz + qw * qx) * sy
    q22 = (1 - 2 * (qx * qx + qy * qy)) * sz
    LIM = 1e75
    m00 = tl.minimum(tl.maximum(a0 * q00 + a1 * q10 + a2 * q20, -LIM), LIM)
    m01 = tl.minimum(tl.maximum(a0 * q01 + a1 * q11 + a2 * q21, -LIM), LIM)
    m02 = tl.minimum(tl.maximum(a0 * q02 + a1 * q12 + a2 * q22, -LIM), LIM)
    m10 = tl.minimum(tl.maximum(b0 * q00 + b1 * q10 + b2 * q20, -LIM), LIM)
    m11 = tl.minimum(tl.maximum(b0 * q01 + b1 * q11 + b2 * q21, -LIM), LIM)
    m12 = tl.minimum(tl.maximum(b0 * q02 + b1 * q12 + b2 * q22, -LIM), LIM)
    a_raw = m00 * m00 + m01 * m01 + m02 * m02
    b = m00 * m10 + m01 * m11 + m02 * m12
    c_raw = m10 * m10 + m11 * m11 + m12 * m12
    n0 = m00 * m11 - m01 * m10
    n1 = m00 * m12 - m02 * m10
    n2 = m01 * m12 - m02 * m11
    det = (n0 * n0 + n1 * n1 + n2 * n2) + eps * (a_raw + c_raw) + eps * eps
    a = a_raw + eps
    c = c_raw + eps
    u = fx * px / zs + cx
    v = fy * py / zs + cy
    # _extent: 3-sigma radius and the box where alpha can reach alpha_min (relative and absolute slack).
    lam = 0.5 * (a + c) + tl.sqrt((0.5 * (a - c)) * (0.5 * (a - c)) + b * b)
    radius = tl.math.ceil(3.0 * tl.sqrt(lam))
    r2 = 2.0 * tl.log(tl.maximum(o / alpha_min, 1.0))
    hx = tl.sqrt(r2 * a) * (1 + 1e-6) + 1e-6
    hy = tl.sqrt(r2 * c) * (1 + 1e-6) + 1e-6
    x0 = tl.maximum(tl.math.ceil(tl.minimum(tl.maximum(u - hx - 0.5, -1.0), Wf + 1.0)), 0.0)
    x1 = tl.minimum(tl.math.floor(tl.minimum(tl.maximum(u + hx - 0.5, -2.0), Wf + 1.0)), Wf - 1.0)
    y0 = tl.maximum(tl.math.ceil(tl.minimum(tl.maximum(v - hy - 0.5, -1.0), Hf + 1.0)), 0.0)
    y1 = tl.minimum(tl.math.floor(tl.minimum(tl.maximum(v + hy - 0.5, -2.0), Hf + 1.0)), Hf - 1.0)
    vis = in_depth & (o >= alpha_min) & (x0 <= x1) & (y0 <= y1)
    rad = tl.where(vis, tl.minimum(tl.maximum(radius, 0.0), 2147483647.0), 0.0)
    tl.store(means2d_ptr + 2 * i64, u, mask=ok)
    tl.store(means2d_ptr + 2 * i64 + 1, v, mask=ok)
    tl.store(depth_ptr + i64, z, mask=ok)
    tl.store(conics_ptr + 3 * i64, c / det, mask=ok)
    tl.store(conics_ptr + 3 * i64 + 1, -b / c, mask=ok)
    tl.store(conics_ptr + 3 * i64 + 2, 1.0 / c, mask=ok)
    tl.store(opac64_ptr + i64, o, mask=ok)
    tl.store(radii_ptr + i64, rad.to(tl.int32), mask=ok)
    tl.store(bbox_ptr + 4 * i64, x0.to(tl.int64), mask=ok)
    tl.store(bbox_ptr + 4 * i64 + 1, y0.to(tl.int64), mask=ok)
    tl.store(bbox_ptr + 4 * i64 + 2, x1.to(tl.int64), mask=ok)
    tl.store(bbox_ptr + 4 * i64 + 3, y1.to(tl.int64), mask=ok)
    tl.store(visible_ptr + i64, vis.to(tl.int8), mask=ok)


@triton.jit
def tile_weights(
    gauss_ids_ptr,  # [I] int64 tile lists, front to back
    offsets_ptr,  # [n_tiles+1] int64
    extent_ptr,  # [n_tiles] int64 from tile_extents
    wbase_ptr,  # [n_tiles] int64: where each tile's weight rows start in w_ptr (elements)
    means2d_ptr,  # [N,2] float64
    conics_ptr,  # [N,3] float64
    opac_ptr,  # [N] float64
    depth_ptr,  # [N] float64
    w_ptr,  # float32 out: per tile, [rows, TILE*TILE] weights, rows = the extent rounded up to BK
    aux_ptr,  # [3,H,W] float64 out: weight sum, weighted depth sum, final transmittance
    W,
    H,
    tiles_x,
    rule_ptr,  # [3] float64: alpha_min, alpha_max, transmittance_min
    TILE: tl.constexpr,
    SUB: tl.constexpr,
    BP: tl.constexpr,
    BK: tl.constexpr,
    GEOM64: tl.constexpr,
):
    """The first pass of the weights-once path: every pixel's blending weights over its tile's extent,
    written once (the second pass, blend_weights, multiplies them by every block of channels)."""
    tile = tl.program_id(0) // SUB
    x0, y0, px, py, cx, cy, pix_ok = _tile_pixels(tile, SUB, BP, TILE, tiles_x, W, H)
    p = (tl.program_id(0) % SUB) * BP + tl.arange(0, BP)
    alpha_min = tl.load(rule_ptr)
    alpha_max = tl.load(rule_ptr + 1)
    t_min = tl.load(rule_ptr + 2)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    rows = (tl.load(extent_ptr + tile) + BK - 1) // BK * BK
    base = tl.load(wbase_ptr + tile)
    Tcar = tl.full([BP], 1.0, tl.float64)
    done = 1 - pix_ok.to(tl.int32)
    wsum = tl.zeros([BP], dtype=tl.float64)
    zsum = tl.zeros([BP], dtype=tl.float64)
    j0 = rows * 0
    while j0 < rows:
        kk = start + j0 + tl.arange(0, BK)
        w, g, kv, Tcar, done = _weights(
            kk, end, x0, y0, cx, cy, gauss_ids_ptr, means2d_ptr, conics_ptr, opac_ptr, Tcar, done,
            alpha_min, alpha_max, t_min, GEOM64,
        )  # fmt: skip
        j = j0 + tl.arange(0, BK)
        tl.store(
            w_ptr + base + j[None, :].to(tl.int64) * (TILE * TILE) + p[:, None],
            w.to(tl.float32),
            mask=(p < TILE * TILE)[:, None],
        )
        z = tl.load(depth_ptr + g, mask=kv, other=0.0)
        wsum += tl.sum(w, axis=1)
        zsum += tl.sum(w * z[None, :], axis=1)
        j0 += BK
    _store_aux(aux_ptr, (py * W + px).to(tl.int64), pix_ok, wsum, zsum, Tcar, W, H)


@triton.jit
def blend_weights(
    gauss_ids_ptr,  # [I] int64 tile lists, front to back
    offsets_ptr,  # [n_tiles+1] int64
    extent_ptr,  # [n_tiles] int64 from tile_extents
    wbase_ptr,  # [n_tiles] int64, as tile_weights
    w_ptr,  # float32 weights from tile_weights
    feat_ptr,  # [N,C] float32 / float16 / bfloat16
    out_ptr,  # [H,W,C] float32
    W,
    H,
    C,
    feat_stride,
    tiles_x,
    TILE: tl.constexpr,
    SUB: tl.constexpr,
    BP: tl.constexpr,
    BK: tl.constexpr,
    CB: tl.constexpr,
    PRECISION: tl.constexpr,
    STAGES: tl.constexpr,
    INTERPRET: tl.constexpr,
):
    """The second pass of the weights-once path: BP pixels x CB channels = stored weights @ features, in a
    software-pipelined loop over the tile's weight rows (no geometry is evaluated here)."""
    tile = tl.program_id(0) // SUB
    cb = tl.program_id(1)
    _x0, _y0, px, py, _cx, _cy, pix_ok = _tile_pixels(tile, SUB, BP, TILE, tiles_x, W, H)
    p = (tl.program_id(0) % SUB) * BP + tl.arange(0, BP)
    ch = cb * CB + tl.arange(0, CB)
    ch_ok = ch < C
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    rows = (tl.load(extent_ptr + tile) + BK - 1) // BK * BK
    base = tl.load(wbase_ptr + tile)
    acc = tl.zeros([BP, CB], dtype=tl.float32)
    if INTERPRET:  # Triton's interpreter cannot take tensor bounds in range(): the same loop as a while
        j0 = rows * 0
        while j0 < rows:
            acc = _blend_rows(
                j0, start, end, base, p, ch, ch_ok, gauss_ids_ptr, w_ptr, feat_ptr, feat_stride, acc,
                TILE, BK, PRECISION,
            )  # fmt: skip
            j0 += BK
    else:
        for j0 in tl.range(0, rows, BK, num_stages=STAGES):
            acc = _blend_rows(
                j0, start, end, base, p, ch, ch_ok, gauss_ids_ptr, w_ptr, feat_ptr, feat_stride, acc,
                TILE, BK, PRECISION,
            )  # fmt: skip
    pix = (py * W + px).to(tl.int64)
    tl.store(out_ptr + pix[:, None] * C + ch[None, :], acc, mask=pix_ok[:, None] & ch_ok[None, :])


@triton.jit
def _blend_rows(
    j0, start, end, base, p, ch, ch_ok, gauss_ids_ptr, w_ptr, feat_ptr, feat_stride, acc,
    TILE: tl.constexpr, BK: tl.constexpr, PRECISION: tl.constexpr,
):  # fmt: skip
    """acc + stored weights of rows j0..j0+BK [BP,BK] @ their Gaussians' features [BK,CB]."""
    j = j0 + tl.arange(0, BK)
    kk = start + j
    kv = kk < end
    g = tl.load(gauss_ids_ptr + kk, mask=kv, other=0)
    w = tl.load(
        w_ptr + base + j[None, :].to(tl.int64) * (TILE * TILE) + p[:, None],
        mask=(p < TILE * TILE)[:, None],
        other=0.0,
    )
    f = tl.load(
        feat_ptr + g[:, None] * feat_stride + ch[None, :], mask=kv[:, None] & ch_ok[None, :], other=0.0
    )
    return acc + tl.dot(w, f.to(tl.float32), input_precision=PRECISION)
