"""Reference rasteriser: pure PyTorch, differentiable, any device, float32 or float64 features.

Per tile, the front-to-back list of Gaussians is evaluated in chunks (pixels x Gaussians x channels
bounded by ``RasterConfig.chunk_elems``) with the transmittance carried between chunks, so memory
stays bounded for any scene. Geometry and blending weights are float64 (see projection.py); features
are blended in their own dtype.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from fmgs.cameras import Camera
from fmgs.render.binning import bin_tiles
from fmgs.render.projection import gaussian_alpha, project
from fmgs.render.types import RasterConfig, RenderOutput


def rasterize_reference(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | None = None,
    config: RasterConfig = RasterConfig(),
) -> RenderOutput:
    """Render features [N,D] of Gaussians (means [N,3], quats [N,4] wxyz, scales [N,3], opacities [N])."""
    N, D = features.shape
    W, H, T = camera.width, camera.height, config.tile_size
    dev, fdt = features.device, features.dtype
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means, quats, scales, opacities, features)
    )
    proj = project(means, quats, scales, opacities, camera, config)
    bins = bin_tiles(proj, W, H, T)
    n_tiles = bins.tiles_x * bins.tiles_y
    P = T * T

    # Pixel offsets inside a tile; pixels past the image edge are evaluated and cropped.
    ly, lx = torch.meshgrid(torch.arange(T, device=dev), torch.arange(T, device=dev), indexing="ij")
    lx, ly = lx.reshape(1, P), ly.reshape(1, P)

    counts = (bins.offsets[1:] - bins.offsets[:-1]).tolist()
    offsets = bins.offsets.tolist()
    done_tiles, parts = [], []  # per batch: tile ids and (features, weight sum, depth sum, final T)
    n_contrib = torch.zeros(N, dtype=torch.int64, device=dev)
    weight_sum = torch.zeros(N, dtype=torch.float64, device=dev)

    for tiles, kmax in tile_batches(counts, P, D, config.chunk_elems):
        tb = torch.tensor(tiles, device=dev)
        B = len(tiles)
        # Padded [B, kmax] list of Gaussian ids; padding points at Gaussian 0 with opacity 0.
        k = torch.arange(kmax, device=dev)
        starts = torch.tensor([offsets[t] for t in tiles], device=dev)
        lens = torch.tensor([counts[t] for t in tiles], device=dev)
        valid = k[None, :] < lens[:, None]
        flat = (starts[:, None] + k[None, :]).clamp_max(max(len(bins.gauss_ids) - 1, 0))
        gid = torch.where(valid, bins.gauss_ids[flat], 0)
        kc = max(1, config.chunk_elems // (B * max(P, D)))
        Tcar = torch.ones(B, P, dtype=torch.float64, device=dev)
        done = torch.zeros(B, P, dtype=torch.bool, device=dev)
        acc_f = torch.zeros(B, P, D, dtype=fdt, device=dev)
        acc_w = torch.zeros(B, P, dtype=torch.float64, device=dev)
        acc_z = torch.zeros(B, P, dtype=torch.float64, device=dev)
        px = (tb % bins.tiles_x * T)[:, None] + lx  # [B,P] pixel column
        py = (tb // bins.tiles_x * T)[:, None] + ly  # [B,P] pixel row
        ok_pix = (px < W) & (py < H)
        pix_b = (torch.stack([px, py], -1).to(torch.float64) + 0.5)[:, :, None, :]  # [B,P,1,2] centres
        for k0 in range(0, kmax, kc):
            if bool(done[ok_pix].all()):
                break  # every pixel of these tiles has terminated
            g = gid[:, k0 : k0 + kc]
            gv = valid[:, k0 : k0 + kc]
            args = (
                pix_b,
                g,
                gv,
                proj.means2d,
                proj.conics,
                proj.opacities,
                proj.depths,
                features,
                Tcar,
                done,
            )
            if needs_grad:
                # Recompute the chunk in backward instead of keeping its [B,P,k] intermediates: the
                # saved inputs are references to the shared tensors, so memory stays one chunk deep.
                df, dw, dz, Tcar, stop, w = checkpoint(blend_chunk, *args, config, use_reentrant=False)
            else:
                df, dw, dz, Tcar, stop, w = blend_chunk(*args, config)
            acc_f = acc_f + df
            acc_w = acc_w + dw
            acc_z = acc_z + dz
            done = done | stop
            with torch.no_grad():
                wk = torch.where(ok_pix[..., None], w.detach(), 0.0)
                n_contrib.index_add_(0, g.reshape(-1), (wk > 0).sum(1).reshape(-1))
                weight_sum.index_add_(0, g.reshape(-1), wk.sum(1).reshape(-1))
        done_tiles.append(tb)
        parts.append((acc_f, acc_w, acc_z, Tcar))

    # One scatter per output (tiles without Gaussians keep zero sums and T = 1).
    tb_all = torch.cat(done_tiles) if done_tiles else torch.zeros(0, dtype=torch.int64, device=dev)
    # With no Gaussian in any tile the outputs are constants; tie them to the inputs by an exact zero
    # so a loss on them still backpropagates (zero gradients, as the cpu backend gives), not raises.
    tie = None
    if needs_grad and not parts:
        tie = sum(t[:0].sum() for t in (proj.means2d, proj.conics, proj.opacities, proj.depths, features))

    def assemble(i: int, fill: float, dtype: torch.dtype, *shape: int) -> torch.Tensor:
        base = torch.full((n_tiles, P, *shape), fill, dtype=dtype, device=dev)
        if tie is not None:
            base = base + tie.to(dtype)
        return base.index_copy(0, tb_all, torch.cat([p[i] for p in parts])) if parts else base

    feat_out = assemble(0, 0.0, fdt, D)
    wsum_out = assemble(1, 0.0, torch.float64)
    zsum_out = assemble(2, 0.0, torch.float64)
    T_out = assemble(3, 1.0, torch.float64)

    def untile(x: torch.Tensor) -> torch.Tensor:
        x = x.reshape(bins.tiles_y, bins.tiles_x, T, T, *x.shape[2:]).transpose(1, 2)
        return x.reshape(bins.tiles_y * T, bins.tiles_x * T, *x.shape[4:])[:H, :W]

    image = untile(feat_out)
    if background is not None:
        image = image + untile(T_out)[..., None].to(fdt) * background.to(device=dev, dtype=fdt)
    alpha_img = untile(wsum_out)
    zsum = untile(zsum_out)
    depth = zsum / torch.where(alpha_img > 0, alpha_img, torch.ones_like(alpha_img))
    return RenderOutput(
        image=image,
        alpha=alpha_img.to(fdt),
        depth=depth.to(fdt),
        radii=proj.radii,
        means2d=proj.means2d,
        visible=proj.visible,
        n_contrib=n_contrib.to(torch.int32),
        weight_sum=weight_sum,
    )


def blend_chunk(pix_b, g, gv, means2d, conics, opacities, depths, features, Tcar, done, config: RasterConfig):
    """Blend one chunk of k Gaussians into B tiles of P pixels, front to back.

    pix_b [B,P,1,2] pixel centres; g [B,k] Gaussian ids (gv marks real entries, the rest is padding);
    Tcar [B,P] transmittance carried in; done [B,P] pixels already terminated.
    Returns feature, weight and depth sums [B,P,D], [B,P], [B,P], the carried-out transmittance, the
    pixels that terminated here, and the weights [B,P,k] (for statistics).
    """
    B, P = Tcar.shape
    d = pix_b - means2d[g][:, None, :, :]  # [B,P,k,2]
    con = conics[g][:, None]  # [B,1,k,3] completed-square form (A, r, e), see Projection.conics
    s = d[..., 0] + con[..., 1] * d[..., 1]
    power = con[..., 0] * s**2 + con[..., 2] * d[..., 1] ** 2
    opac = torch.where(gv, opacities[g], 0.0)[:, None, :]
    alpha = gaussian_alpha(power, opac, config)
    # Transmittance after each Gaussian, carried in as the first factor so the product is formed in
    # the same sequential order as the compiled kernel's loop.
    Tseq = torch.cumprod(torch.cat([Tcar[..., None], 1.0 - alpha], -1), -1)
    T_before, T_after = Tseq[..., :-1], Tseq[..., 1:]
    keep = (T_after >= config.transmittance_min) & ~done[..., None] & (alpha > 0)
    w = torch.where(keep, alpha * T_before, 0.0)
    df = torch.bmm(w.reshape(B, -1, w.shape[-1]).to(features.dtype), features[g]).reshape(B, P, -1)
    dw = w.sum(-1)
    dz = (w * depths[g][:, None, :]).sum(-1)
    stop = ((T_after < config.transmittance_min) & (alpha > 0)).any(-1)
    # Kept entries are a prefix and T_after falls along it: the carry is the last kept T_after.
    last = torch.where(keep, T_after, torch.full_like(T_after, 2.0)).amin(-1)
    return df, dw, dz, torch.where(keep.any(-1), last, Tcar), stop, w


def tile_batches(counts: list[int], P: int, D: int, budget: int):
    """Group non-empty tiles into batches of similar list length so B * P * kmax stays near budget.

    Yields (tile indices, longest list in the batch). Sorting by length keeps padding small.
    """
    tiles = sorted((c, t) for t, c in enumerate(counts) if c > 0)
    i = 0
    while i < len(tiles):
        kmax = tiles[i][0]
        batch = []
        while i < len(tiles):
            c, t = tiles[i]
            if batch and (len(batch) + 1) * max(P, D) * max(kmax, c) > budget:
                break
            kmax = max(kmax, c)
            batch.append(t)
            i += 1
        yield batch, kmax
