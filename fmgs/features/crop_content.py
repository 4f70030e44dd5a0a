"""What a crop of a generated scene shows, as the CLIP stand-in is trained to say it, from the label map.

A crop's content is each label's share of the crop under a Gaussian window about its centre
(``WINDOW_SIGMA``), with floor, wall and backdrop down-weighted (``STUFF_SALIENCE``): captions name
things more than the surfaces they stand on. Its text is a mixture of captions: an object's weight spread
over its full name, "<colour> <shape>" and "<shape>" (``CAPTION_WEIGHTS``), as image captions vary in
detail. ``scripts/train_standin.py`` trains the stand-in towards that mixture; ``caption_embeddings``
gives the mixture's own point in the text space: what a stand-in with no naming error would answer (the
oracle of benchmarks.clip_oracle).

``window_shares`` computes the shares of a whole crop grid at once (the window is separable: two 1-D
convolutions of each label's indicator); ``window_shares_reference`` is its loop-per-crop twin.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from fmgs.errors import ValidationError

WINDOW_SIGMA = 0.25
"""A crop's content is weighed by a Gaussian window of this sigma (a fraction of the crop edge) about its
centre: what a crop shows, with what lies at its middle counting most."""
CAPTION_WEIGHTS = (0.5, 0.3, 0.2)
"""An object's weight spread over its full name, "<colour> <shape>" and "<shape>" (merged when equal) in
the text-space target."""
STUFF_SALIENCE = 0.25
"""Weight of floor, wall and backdrop against objects in what a crop shows: captions name things more
than the surfaces they stand on, and CLIP follows its captions."""


def window(side: int) -> np.ndarray:
    """[side] float64: the 1-D factor of the crop window (unnormalised Gaussian about the centre)."""
    t = (np.arange(side) + 0.5 - side / 2) / (WINDOW_SIGMA * side)
    return np.exp(-0.5 * t**2)


def world(name: str):
    """The world object (fmgs.synthworld.WorldObject) a label name names, or None for stuff (floor, wall,
    backdrop, background)."""
    from fmgs.synthworld import world_object

    try:
        return world_object(name)
    except ValueError:
        return None


def captions(name: str) -> list[tuple[str, float]]:
    """(caption, weight) of one label name: world objects get captions of varying detail."""
    o = world(name)
    if o is None:
        return [(name, 1.0)]
    out: dict[str, float] = {}
    for cap, w in zip((name, f"{o.colour} {o.shape}", o.shape), CAPTION_WEIGHTS, strict=True):
        out[cap] = out.get(cap, 0.0) + w
    return list(out.items())


def salient(shares: torch.Tensor, names: list[str]) -> torch.Tensor:
    """[N,L] label weights: shares [N,L] with stuff (floor, wall, backdrop) down-weighted, rows summing
    to 1."""
    w = shares * torch.tensor([STUFF_SALIENCE if world(n) is None else 1.0 for n in names])
    return w / w.sum(1, keepdim=True)


def caption_matrix(names: list[str], vocab: dict[str, int]) -> torch.Tensor:
    """[L,V] each label's caption weights over the vocabulary (rows sum to 1)."""
    m = torch.zeros(len(names), len(vocab))
    for i, n in enumerate(names):
        for cap, w in captions(n):
            m[i, vocab[cap]] += w
    return m


def caption_points(names: list[str], text_encoder) -> torch.Tensor:
    """[L,D] each label's caption mixture in the text space (its captions' unit text embeddings, weighted;
    not normalised)."""
    vocab_list = sorted({c for n in names for c, _ in captions(n)})
    with torch.inference_mode():
        table = text_encoder.encode_text(vocab_list).float()  # [V,D] unit
    return caption_matrix(names, {c: i for i, c in enumerate(vocab_list)}) @ table


def caption_embeddings(shares: torch.Tensor, names: list[str], points: torch.Tensor) -> torch.Tensor:
    """[N,D] unit: the text-space point of what each crop shows (shares [N,L] over ``names``; ``points``
    from ``caption_points``): its salient weights over the labels' caption mixtures, normalised."""
    return F.normalize(salient(shares.float(), names) @ points, dim=-1)


def window_shares(
    labels: np.ndarray, side: int, starts_y: np.ndarray, starts_x: np.ndarray, L: int
) -> np.ndarray:
    """[ny,nx,L] each label's share under the window of the square crops of edge ``side`` whose top-left
    corners are (starts_y[i], starts_x[j]) in a label map [H,W] of ids in [0, L); rows sum to 1."""
    H, W = labels.shape
    if side < 1 or side > min(H, W):
        raise ValidationError("side", f"crop edge {side} does not fit a {W}x{H} label map")
    if labels.min() < 0 or labels.max() >= L:
        raise ValidationError("labels", f"ids must lie in [0, {L}), got [{labels.min()}, {labels.max()}]")
    g = torch.from_numpy(window(side))
    onehot = F.one_hot(torch.from_numpy(labels.astype(np.int64)), L).permute(2, 0, 1).double()  # [L,H,W]
    # separable window: along x, then along y ("valid" positions: every top-left corner of a crop)
    along_x = F.conv2d(onehot[:, None], g.view(1, 1, 1, side))  # [L,1,H,W-side+1]
    both = F.conv2d(along_x, g.view(1, 1, side, 1))[:, 0]  # [L,H-side+1,W-side+1]
    sy, sx = torch.as_tensor(starts_y, dtype=torch.int64), torch.as_tensor(starts_x, dtype=torch.int64)
    s = both[:, sy][:, :, sx].permute(1, 2, 0)  # [ny,nx,L]
    return (s / s.sum(-1, keepdim=True)).numpy()


def window_shares_reference(
    labels: np.ndarray, side: int, starts_y: np.ndarray, starts_x: np.ndarray, L: int
) -> np.ndarray:
    """``window_shares`` one crop at a time (the twin; the stand-in's training crops are weighed so)."""
    g = window(side)
    w = g[:, None] * g[None, :]
    out = np.zeros((len(starts_y), len(starts_x), L))
    for i, y0 in enumerate(starts_y):
        for j, x0 in enumerate(starts_x):
            crop = labels[y0 : y0 + side, x0 : x0 + side]
            sh = np.bincount(crop.reshape(-1), w.reshape(-1), minlength=L)
            out[i, j] = sh / sh.sum()
    return out
