"""Numba kernels of the differentiable CPU path: blending forward (with what backward needs) and backward.

The twin is ``reference.py``'s ``blend_chunk`` under autograd: same rule (alpha = min(alpha_max,
o exp(-power/2)), skipped below alpha_min, a pixel stops before the Gaussian that would take its
transmittance below t_min), float64 throughout, exact ``exp``. Tiles run in parallel; within a tile,
Gaussians are the outer loop and only the pixels inside each one's box the inner loop (outside it
alpha is below alpha_min by construction of the box). Backward walks each tile's list back to front,
recovering each transmittance by division (alpha <= alpha_max < 1), and writes one gradient row per
list entry; the caller sums the rows of each Gaussian, so no two threads ever write the same row.
Imported lazily; compiled on first call and cached on disk.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from fmgs.render.cpu_kernels import tile_extent


@njit(cache=True, parallel=True)
def blend_forward(
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
    bbox,
    features,
    alpha_max,
    alpha_min,
    t_min,
    feat_img,
    wsum_img,
    zsum_img,
    t_img,
    last_img,
    pair_cnt,
    pair_w,
):  # pragma: no cover
    """Blend front to back. Writes sums of w f, w, w z, the final transmittance, and per pixel the list
    position one past its last blended Gaussian (``last_img``, -1 for an empty tile)."""
    D = features.shape[1]
    P = tile * tile
    for q in prange(tile_order.shape[0]):
        t = tile_order[q]
        start, end = offsets[t], offsets[t + 1]
        x_0, y_0, x_e, y_e = tile_extent(t, tiles_x, tile, W, H)
        npix = (x_e - x_0 + 1) * (y_e - y_0 + 1)
        T = np.ones(P)
        done = np.zeros(P, dtype=np.bool_)
        last = np.full(P, start)
        acc = np.zeros((P, D))
        wsum = np.zeros(P)
        zsum = np.zeros(P)
        ndone = 0
        for k in range(start, end):
            g = ids[k]
            u, v = means2d[g, 0], means2d[g, 1]
            qa, qr, qe = conics[g, 0], conics[g, 1], conics[g, 2]
            o, z = opac[g], depths[g]
            xlo, xhi = max(bbox[g, 0], x_0), min(bbox[g, 2], x_e)
            cnt = 0
            wk = 0.0
            for yy in range(max(bbox[g, 1], y_0), min(bbox[g, 3], y_e) + 1):
                dy = yy + 0.5 - v
                row = (yy - y_0) * tile - x_0
                for xx in range(xlo, xhi + 1):
                    p = row + xx
                    if done[p]:
                        continue
                    s = xx + 0.5 - u + qr * dy
                    power = qa * s * s + qe * dy * dy
                    alpha = min(o * math.exp(-0.5 * power), alpha_max)
                    if alpha < alpha_min:
                        continue
                    Tp = T[p]
                    t_next = Tp * (1.0 - alpha)
                    if t_next < t_min:
                        done[p] = True
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
                    last[p] = k + 1
            pair_cnt[k] = cnt
            pair_w[k] = wk
            if ndone == npix:
                break
        for yy in range(y_0, y_e + 1):
            for xx in range(x_0, x_e + 1):
                p = (yy - y_0) * tile + (xx - x_0)
                for c in range(D):
                    feat_img[yy, xx, c] = acc[p, c]
                wsum_img[yy, xx] = wsum[p]
                zsum_img[yy, xx] = zsum[p]
                t_img[yy, xx] = T[p]
                last_img[yy, xx] = last[p]


@njit(cache=True, parallel=True)
def blend_backward(
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
    bbox,
    features,
    alpha_max,
    alpha_min,
    t_img,
    last_img,
    g_feat,
    g_wsum,
    g_zsum,
    g_t,
    d_means2d,
    d_conics,
    d_opac,
    d_depths,
    d_features,
):  # pragma: no cover
    """Gradients per list entry (rows of the ``d_*`` outputs, aligned with ``ids``) from the gradients of
    the four blended images. With e_i = g_feat . f_i + g_wsum + g_zsum z_i and the suffix sum
    S_i = sum_{j>i} e_j w_j + g_t T_final: dL/dalpha_i = T_i e_i - S_i / (1 - alpha_i)."""
    D = features.shape[1]
    P = tile * tile
    for q in prange(tile_order.shape[0]):
        t = tile_order[q]
        start = offsets[t]
        x_0, y_0, x_e, y_e = tile_extent(t, tiles_x, tile, W, H)
        T = np.empty(P)
        S = np.empty(P)
        last = np.full(P, start)
        kmax = start
        for yy in range(y_0, y_e + 1):
            for xx in range(x_0, x_e + 1):
                p = (yy - y_0) * tile + (xx - x_0)
                T[p] = t_img[yy, xx]
                S[p] = g_t[yy, xx] * t_img[yy, xx]
                last[p] = last_img[yy, xx]
                kmax = max(kmax, last[p])
        for k in range(kmax - 1, start - 1, -1):
            g = ids[k]
            u, v = means2d[g, 0], means2d[g, 1]
            qa, qr, qe = conics[g, 0], conics[g, 1], conics[g, 2]
            o, z = opac[g], depths[g]
            xlo, xhi = max(bbox[g, 0], x_0), min(bbox[g, 2], x_e)
            gu = gv = ga = gb = gc = go = gz = 0.0
            for yy in range(max(bbox[g, 1], y_0), min(bbox[g, 3], y_e) + 1):
                dy = yy + 0.5 - v
                row = (yy - y_0) * tile - x_0
                for xx in range(xlo, xhi + 1):
                    p = row + xx
                    if k >= last[p]:
                        continue  # past this pixel's last blended Gaussian
                    s = xx + 0.5 - u + qr * dy
                    power = qa * s * s + qe * dy * dy
                    ex = math.exp(-0.5 * power)
                    raw = o * ex
                    alpha = min(raw, alpha_max)
                    if alpha < alpha_min:
                        continue
                    one_m = 1.0 - alpha
                    Ti = T[p] / one_m
                    w = alpha * Ti
                    e = g_wsum[yy, xx] + g_zsum[yy, xx] * z
                    for c in range(D):
                        e += g_feat[yy, xx, c] * features[g, c]
                        d_features[k, c] += w * g_feat[yy, xx, c]
                    gz += w * g_zsum[yy, xx]
                    d_alpha = Ti * e - S[p] / one_m
                    S[p] += e * w
                    T[p] = Ti
                    if raw > alpha_max:
                        continue  # clamped: alpha does not depend on o or the power here
                    go += d_alpha * ex
                    d_power = -0.5 * alpha * d_alpha
                    # power = A s^2 + e dy^2 with s = dx + r dy, dx = px - u, dy = py - v
                    ga += d_power * s * s
                    gb += d_power * 2.0 * qa * s * dy
                    gc += d_power * dy * dy
                    gu -= d_power * 2.0 * qa * s
                    gv -= d_power * 2.0 * (qa * s * qr + qe * dy)
            d_means2d[k, 0] = gu
            d_means2d[k, 1] = gv
            d_conics[k, 0] = ga
            d_conics[k, 1] = gb
            d_conics[k, 2] = gc
            d_opac[k] = go
            d_depths[k] = gz
