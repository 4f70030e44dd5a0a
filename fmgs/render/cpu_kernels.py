"""Numba kernels of the CPU fast path: projection, tile binning, per-pixel blending.

Each kernel mirrors a PyTorch twin (projection.py, binning.py, reference.py) operation for operation
in float64, so decisions (alpha >= alpha_min, termination) match the reference. Imported lazily:
importing this module compiles nothing until a kernel is first called (then cached on disk).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_M_LIMIT = 1e75
_BOX_REL, _BOX_ABS = 1e-6, 1e-6
# The power prefilter skips exp() only where alpha is surely below alpha_min; the exact test follows.
_PREFILTER_SLACK = 1e-6


@njit(cache=True, inline="always")
def _clampm(v):  # pragma: no cover
    return min(max(v, -_M_LIMIT), _M_LIMIT)


@njit(cache=True, parallel=True)
def project_kernel(
    means,
    quats,
    scales,
    opac,
    R,
    t,
    fx,
    fy,
    cx,
    cy,
    W,
    H,
    near,
    far,
    fov_clip,
    eps2d,
    alpha_min,
    tile,
    means2d,
    depths,
    conics,
    radii,
    bbox,
    tbox,
    visible,
    pmax,
):  # pragma: no cover
    n = means.shape[0]
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    lim_xp, lim_xn = (W - cx) / fx + fov_clip * tan_x, cx / fx + fov_clip * tan_x
    lim_yp, lim_yn = (H - cy) / fy + fov_clip * tan_y, cy / fy + fov_clip * tan_y
    for i in prange(n):
        # Inputs may be float32: every value is widened to float64 explicitly.
        mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        px = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz + t[0]
        py = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz + t[1]
        z = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz + t[2]
        depths[i] = z
        in_depth = z > near and z < far
        zs = z if in_depth else 1.0
        if not in_depth:  # culled: only the (unused) centre is reported, as the PyTorch twin does
            means2d[i, 0] = fx * px / zs + cx
            means2d[i, 1] = fy * py / zs + cy
            conics[i, 0] = conics[i, 1] = conics[i, 2] = 0.0
            radii[i] = 0
            visible[i] = False
            pmax[i] = 0.0
            bbox[i, 0] = bbox[i, 1] = bbox[i, 2] = bbox[i, 3] = 0
            continue
        # rotation from the quaternion, scaled by its largest component first (denormal-safe)
        qw, qx, qy, qz = (
            np.float64(quats[i, 0]),
            np.float64(quats[i, 1]),
            np.float64(quats[i, 2]),
            np.float64(quats[i, 3]),
        )
        qm = max(abs(qw), abs(qx), abs(qy), abs(qz))
        if qm > 0:
            qw, qx, qy, qz = qw / qm, qx / qm, qy / qm, qz / qm
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qn = max(qn, 2.2250738585072014e-308)
        qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
        r00 = 1 - 2 * (qy * qy + qz * qz)
        r01 = 2 * (qx * qy - qw * qz)
        r02 = 2 * (qx * qz + qw * qy)
        r10 = 2 * (qx * qy + qw * qz)
        r11 = 1 - 2 * (qx * qx + qz * qz)
        r12 = 2 * (qy * qz - qw * qx)
        r20 = 2 * (qx * qz - qw * qy)
        r21 = 2 * (qy * qz + qw * qx)
        r22 = 1 - 2 * (qx * qx + qy * qy)
        tx = zs * min(max(px / zs, -lim_xn), lim_xp)
        ty = zs * min(max(py / zs, -lim_yn), lim_yp)
        j00, j02 = fx / zs, -fx * tx / zs**2
        j11, j12 = fy / zs, -fy * ty / zs**2
        # rows of J @ R (2x3); then M = (J @ R) @ Rq @ diag(s), entries clamped
        a0, a1, a2 = (
            j00 * R[0, 0] + j02 * R[2, 0],
            j00 * R[0, 1] + j02 * R[2, 1],
            j00 * R[0, 2] + j02 * R[2, 2],
        )
        b0, b1, b2 = (
            j11 * R[1, 0] + j12 * R[2, 0],
            j11 * R[1, 1] + j12 * R[2, 1],
            j11 * R[1, 2] + j12 * R[2, 2],
        )
        s0, s1, s2 = np.float64(scales[i, 0]), np.float64(scales[i, 1]), np.float64(scales[i, 2])
        m00 = _clampm((a0 * r00 + a1 * r10 + a2 * r20) * s0)
        m01 = _clampm((a0 * r01 + a1 * r11 + a2 * r21) * s1)
        m02 = _clampm((a0 * r02 + a1 * r12 + a2 * r22) * s2)
        m10 = _clampm((b0 * r00 + b1 * r10 + b2 * r20) * s0)
        m11 = _clampm((b0 * r01 + b1 * r11 + b2 * r21) * s1)
        m12 = _clampm((b0 * r02 + b1 * r12 + b2 * r22) * s2)
        a_raw = m00 * m00 + m01 * m01 + m02 * m02
        b = m00 * m10 + m01 * m11 + m02 * m12
        c_raw = m10 * m10 + m11 * m11 + m12 * m12
        n01 = m00 * m11 - m01 * m10
        n02 = m00 * m12 - m02 * m10
        n12 = m01 * m12 - m02 * m11
        det = (n01 * n01 + n02 * n02 + n12 * n12) + eps2d * (a_raw + c_raw) + eps2d * eps2d
        a, c_ = a_raw + eps2d, c_raw + eps2d
        conics[i, 0] = c_ / det  # completed-square form (A, r, e), see Projection.conics
        conics[i, 1] = -b / c_
        conics[i, 2] = 1.0 / c_
        u = fx * px / zs + cx
        v = fy * py / zs + cy
        means2d[i, 0] = u
        means2d[i, 1] = v
        o = np.float64(opac[i])
        lam = 0.5 * (a + c_) + math.sqrt((0.5 * (a - c_)) ** 2 + b * b)
        radius = math.ceil(3.0 * math.sqrt(lam))
        r2 = 2.0 * math.log(max(o / alpha_min, 1.0))
        pmax[i] = r2 * (1 + _PREFILTER_SLACK) + _PREFILTER_SLACK
        hx = math.sqrt(r2 * a) * (1 + _BOX_REL) + _BOX_ABS
        hy = math.sqrt(r2 * c_) * (1 + _BOX_REL) + _BOX_ABS
        x0 = max(math.ceil(min(max(u - hx - 0.5, -1.0), W + 1.0)), 0.0)
        x1 = min(math.floor(min(max(u + hx - 0.5, -2.0), W + 1.0)), W - 1.0)
        y0 = max(math.ceil(min(max(v - hy - 0.5, -1.0), H + 1.0)), 0.0)
        y1 = min(math.floor(min(max(v + hy - 0.5, -2.0), H + 1.0)), H - 1.0)
        vis = in_depth and o >= alpha_min and x0 <= x1 and y0 <= y1
        visible[i] = vis
        bbox[i, 0], bbox[i, 1], bbox[i, 2], bbox[i, 3] = int(x0), int(y0), int(x1), int(y1)
        if vis:  # inclusive tile range, so binning does no integer division
            tbox[i, 0], tbox[i, 1] = int(x0) // tile, int(y0) // tile
            tbox[i, 2], tbox[i, 3] = int(x1) // tile, int(y1) // tile
        radii[i] = int(min(max(radius, 0.0), 2147483647.0)) if vis else 0


@njit(cache=True)
def stable_argsort_positive(keys):  # pragma: no cover
    """Stable argsort of positive finite float64 keys: LSD radix sort on their bit patterns.

    For positive IEEE doubles the bit pattern orders like the value; equal keys keep index order,
    the same order as torch.sort(stable=True) and numpy's kind="stable".
    """
    n = keys.shape[0]
    bits = keys.view(np.uint64)
    idx = np.arange(n)
    tmp = np.empty(n, dtype=np.int64)
    count = np.empty(65537, dtype=np.int64)
    for shift in range(0, 64, 16):
        count[:] = 0
        for i in range(n):
            count[((bits[idx[i]] >> np.uint64(shift)) & np.uint64(0xFFFF)) + 1] += 1
        if count[1:].max() == n:
            continue  # every key has the same digit here: the pass would not move anything
        for d in range(65536):
            count[d + 1] += count[d]
        for i in range(n):
            d = (bits[idx[i]] >> np.uint64(shift)) & np.uint64(0xFFFF)
            tmp[count[d]] = idx[i]
            count[d] += 1
        idx, tmp = tmp, idx
    return idx


@njit(cache=True, parallel=True)
def bin_kernel_parallel(order, tbox, tiles_x, tiles_y, chunks):  # pragma: no cover
    """``bin_kernel``'s output, by a counting sort over ``chunks`` consecutive slices of ``order``: each
    slice counts its pairs per tile, then writes them after every earlier slice's pairs of that tile, so
    each tile's list keeps the front-to-back order."""
    n_tiles = tiles_x * tiles_y
    n = order.shape[0]
    counts = np.zeros((chunks, n_tiles), dtype=np.int64)
    for c in prange(chunks):
        for k in range(c * n // chunks, (c + 1) * n // chunks):
            g = order[k]
            for ty in range(tbox[g, 1], tbox[g, 3] + 1):
                for tx in range(tbox[g, 0], tbox[g, 2] + 1):
                    counts[c, ty * tiles_x + tx] += 1
    offsets = np.zeros(n_tiles + 1, dtype=np.int64)
    starts = np.empty((chunks, n_tiles), dtype=np.int64)
    pos = 0
    for tid in range(n_tiles):
        offsets[tid] = pos
        for c in range(chunks):
            starts[c, tid] = pos
            pos += counts[c, tid]
    offsets[n_tiles] = pos
    ids = np.empty(pos, dtype=np.int64)
    for c in prange(chunks):
        fill = starts[c]
        for k in range(c * n // chunks, (c + 1) * n // chunks):
            g = order[k]
            for ty in range(tbox[g, 1], tbox[g, 3] + 1):
                for tx in range(tbox[g, 0], tbox[g, 2] + 1):
                    tid = ty * tiles_x + tx
                    ids[fill[tid]] = g
                    fill[tid] += 1
    return ids, offsets


@njit(cache=True)
def bin_kernel(order, tbox, tiles_x, tiles_y):  # pragma: no cover
    """Counting sort of (tile, Gaussian) pairs; ``order`` is already front to back."""
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, dtype=np.int64)
    for k in range(order.shape[0]):
        g = order[k]
        for ty in range(tbox[g, 1], tbox[g, 3] + 1):
            for tx in range(tbox[g, 0], tbox[g, 2] + 1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    ids = np.empty(offsets[-1], dtype=np.int64)
    for k in range(order.shape[0]):
        g = order[k]
        for ty in range(tbox[g, 1], tbox[g, 3] + 1):
            for tx in range(tbox[g, 0], tbox[g, 2] + 1):
                tid = ty * tiles_x + tx
                ids[fill[tid]] = g
                fill[tid] += 1
    return ids, offsets


@njit(cache=True, inline="always")
def exp_neg_table(x, table):  # pragma: no cover
    """exp(x) for x <= 0 within 2 ulp: exp(-j/256) from ``table`` times a degree-5 Taylor term.

    The reduction r = x + j/256 is exact, |r| < 1/256, so the truncation error is below 1e-17.
    Arguments past the table, and positive ones (rounding can make a power slightly positive), fall back
    to math.exp.
    """
    y = -x * 256.0
    j = int(y)
    if j < 0 or j >= table.shape[0]:
        return math.exp(x)
    r = (j - y) * 0.00390625
    return table[j] * (1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0))))))


def exp_table(alpha_min: float) -> np.ndarray:
    """exp(-j/256) for j = 0..J, covering every exponent the alpha_min prefilter lets through."""
    x_max = math.log(1.0 / alpha_min) * (1 + _PREFILTER_SLACK) + _PREFILTER_SLACK
    return np.exp(-np.arange(int(x_max * 256) + 2) / 256.0)


@njit(cache=True, inline="always")
def tile_extent(t, tiles_x, tile, W, H):  # pragma: no cover
    """First column and row of tile ``t`` and its last ones inside the W x H image (inclusive)."""
    x_0 = (t % tiles_x) * tile
    y_0 = (t // tiles_x) * tile
    return x_0, y_0, min(x_0 + tile, W) - 1, min(y_0 + tile, H) - 1


@njit(cache=True, parallel=True, fastmath={"contract"})
def raster_kernel(
    ids,
    offsets,
    tile_order,
    tile,
    tiles_x,
    W,
    H,
    means2d,
    conics,
    opac,
    depths,
    pmax,
    bbox,
    features,
    background,
    use_bg,
    alpha_max,
    alpha_min,
    t_min,
    exp_tab,
    image,
    alpha_img,
    depth_img,
    pair_cnt,
    pair_w,
):  # pragma: no cover
    """Blend each tile front to back: Gaussians outer, only the pixels inside each one's box inner.

    Every pixel sees its Gaussians in list order and applies the reference's rule in float64; a
    terminated pixel is marked by a negative transmittance, which also skips it cheaply.
    """
    D = features.shape[1]
    P = tile * tile
    for q in prange(tile_order.shape[0]):
        t = tile_order[q]
        start, end = offsets[t], offsets[t + 1]
        x_0, y_0, x_e, y_e = tile_extent(t, tiles_x, tile, W, H)
        npix = (x_e - x_0 + 1) * (y_e - y_0 + 1)
        T = np.ones(P)
        acc = np.zeros((P, D))
        wsum = np.zeros(P)
        zsum = np.zeros(P)
        ndone = 0
        for k in range(start, end):
            g = ids[k]
            u, v = means2d[g, 0], means2d[g, 1]
            qa, qr, qe = conics[g, 0], conics[g, 1], conics[g, 2]
            o, z, pm = np.float64(opac[g]), depths[g], pmax[g]
            xlo, xhi = max(bbox[g, 0], x_0), min(bbox[g, 2], x_e)
            cnt = 0
            wk = 0.0
            for yy in range(max(bbox[g, 1], y_0), min(bbox[g, 3], y_e) + 1):
                dy = yy + 0.5 - v
                rdy = qr * dy
                edy = qe * dy * dy
                row = (yy - y_0) * tile - x_0
                for xx in range(xlo, xhi + 1):
                    p = row + xx
                    Tp = T[p]
                    if Tp < 0.0:
                        continue  # terminated
                    dx = xx + 0.5 - u
                    s = dx + rdy
                    power = qa * s * s + edy
                    if power > pm:
                        continue  # alpha surely below alpha_min
                    alpha = min(o * exp_neg_table(-0.5 * power, exp_tab), alpha_max)
                    if alpha < alpha_min:
                        continue
                    t_next = Tp * (1.0 - alpha)
                    if t_next < t_min:
                        T[p] = -Tp  # keep |T| for the background term
                        ndone += 1
                        continue
                    w = alpha * Tp
                    for c in range(D):
                        acc[p, c] += w * features[g, c]
                    wsum[p] += w
                    zsum[p] += w * z
                    cnt += 1
                    wk += w
                    T[p] = t_next
            pair_cnt[k] = cnt
            pair_w[k] = wk
            if ndone == npix:
                break
        for yy in range(y_0, y_e + 1):
            for xx in range(x_0, x_e + 1):
                p = (yy - y_0) * tile + (xx - x_0)
                Tf = abs(T[p])
                for c in range(D):
                    image[yy, xx, c] = acc[p, c] + (Tf * background[c] if use_bg else 0.0)
                alpha_img[yy, xx] = wsum[p]
                depth_img[yy, xx] = zsum[p] / wsum[p] if wsum[p] > 0 else 0.0
