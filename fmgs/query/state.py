"""The compact query state of a scene and what bounds its error, saved in the package.

For stored embeddings f_i [M,D] and an orthonormal basis B [r,D] (top eigenvectors of E^T E):
    c_i = B f_i (exact coefficients), c'_i = s * round(c_i / s) (int8 codes, one scale per basis vector),
    f_i = B^T c'_i + B^T (c_i - c'_i) + (f_i - B^T c_i).
So for any vector v with w = B v and v_perp = v - B^T w:
    |f_i.v - c'_i.w| <= |c_i - c'_i| |w| + |f_i - B^T c_i| |v_perp|,
the two per-row norms (quantisation error, residual) being stored rounded up. The query index turns these
into certified bounds (fmgs.query.certify).

A second tier (``Tier2``) codes the next basis vectors B2 [r2,D] (orthonormal to B and each other) the
same way, for the rows the first bound cannot settle: with w2 = B2 v, v_perp2 = v - B^T w - B2^T w2 and
e2 = c2_i - c2'_i,
    |f_i.v - c'_i.w - c2'_i.w2| <= |c_i - c'_i| |w| + |e2| |w2| + |f_i - B^T c_i - B2^T c2_i| |v_perp2|.
Field embeddings have low rank (the language head's hidden width + 1, e.g. 257 of 512), so r + r2 basis
vectors up to that rank leave a residual near float16 rounding and bound CLIP-like queries tightly. The
second tier stays memory-mapped: it is read only for the rows the first one leaves.

The second tier is stored in two tables, its first ``head`` basis vectors' codes (B2a, c2a) and the rest
(B2b, c2b), with the head's own norms |c2a - c2a'| and |f_i - B^T c_i - B2a^T c2a_i|: texts the first tier
cannot settle (CLIP-like, absent) take their pass over every row through the first tier and the head
alone (128 + 64 of 256 bytes per row at the defaults), and only the rows that leaves read the tail.

File ``query_state.safetensors`` in the package (written by ``export_scene``):
  basis [r,D] float64, scales [r] float32, codes [M,r] int8, err_norm [M] float16, res_norm [M] float16,
  and with a second tier basis2 [r2,D] float64, scales2 [r2] float32, codes2 [M,h] int8 (its head: all
  r2 when it is stored whole), bounds2 [M,2] float32 (its error and residual norms, rounded up), and when
  h < r2 codes2_tail [M,r2-h] int8 and bounds2_head [M,2] float32 (the head's error and residual norms);
  metadata {format: "fmgs-query-state", version, rank, rank2, head2, num, dim, code_norm_max,
  code_norm_max2, source}. Only the current version (STATE_VERSION) is read: an older file is refused
  with what to do (``fmgs build`` exports the package again), and the server builds the state in memory.
``source`` fingerprints the embeddings file (size and sampled blocks), so a state that does not belong to
the embeddings beside it is refused and rebuilt in memory.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fmgs.errors import ValidationError
from fmgs.io.mmap_tensors import mmap_torch
from fmgs.io.tensor_stream import save_blocks
from fmgs.query import tuning

STATE_FILE = "query_state.safetensors"
STATE_FORMAT = "fmgs-query-state"
STATE_VERSION = 3
"""The version written, and the only one read (1: no second tier; 2: no head2, the tier stored whole)."""
REEXPORT = "fmgs build SOURCE --name NAME"
"""The command that exports a package again (its completed stages are reused: only the package is
written anew)."""
TIER2_RANK = 256
"""Default total rank of both tiers (first tier + second tier basis vectors)."""
TIER2_ENERGY = 1e-6
"""The second tier stops at the embeddings' numerical rank: where the sample's remaining energy falls
below this fraction (float16 rounding leaves about 1e-8)."""
_CHUNK = 16384  # rows per pass at export: about 0.3 GB of float64 temporaries at D = 512


@dataclass
class Tier2:
    """Second-tier codes: the basis vectors after the first tier's, read only for unsettled rows."""

    basis: torch.Tensor
    """[r2,D] float64 orthonormal rows, orthogonal to the first tier's basis."""
    scales: torch.Tensor
    """[r2] float32 dequantisation scale per basis vector."""
    codes: torch.Tensor
    """[M,r2] int8 coefficients (memory-mapped when loaded from a package)."""
    bounds: torch.Tensor
    """[M,2] float32: |c2_i - c2'_i| and the residual |f_i - B^T c_i - B2^T c2_i|, both rounded up
    (memory-mapped when loaded)."""
    code_norm_max: float
    """max_i |(c'_i, c2'_i)| over both tiers' dequantised codes (bounds the float32 rounding)."""
    mapped: bool = False
    """Codes and bounds are memory-mapped (not resident)."""
    tail: torch.Tensor | None = None
    """[M,r2-h] int8 coefficients of the basis vectors after the head (None: ``codes`` holds all r2)."""
    head_bounds: torch.Tensor | None = None
    """[M,2] float32: |c2a_i - c2a'_i| and |f_i - B^T c_i - B2a^T c2a_i| for the head alone, rounded up
    (None when the tier is stored whole)."""

    @property
    def rank(self) -> int:
        return int(self.basis.shape[0])

    @property
    def head(self) -> int:
        """Basis vectors in ``codes`` (all of them when there is no tail)."""
        return int(self.codes.shape[1])


@dataclass
class QueryState:
    """Compact codes of the embedded Gaussians and the norms that bound their error."""

    basis: torch.Tensor
    """[r,D] float64 orthonormal rows."""
    scales: torch.Tensor
    """[r] float32 dequantisation scale per basis vector."""
    codes: torch.Tensor
    """[M,r] int8 coefficients (memory-mapped when loaded from a package)."""
    err_norm: torch.Tensor
    """[M] float16 |c_i - c'_i| rounded up (quantisation error, in the basis)."""
    res_norm: torch.Tensor
    """[M] float16 |f_i - B^T c_i| rounded up (what the basis misses)."""
    code_norm_max: float
    """max_i |c'_i| (bounds the float32 rounding of the scan)."""
    tier2: Tier2 | None = None
    """The second tier, when the package has one."""

    @property
    def rank(self) -> int:
        return int(self.basis.shape[0])

    @property
    def num(self) -> int:
        return int(self.codes.shape[0])


def build_state(
    embeddings: torch.Tensor,
    rank: int,
    basis_sample: int = 100_000,
    rank2: int = TIER2_RANK,
    head: int = tuning.TIER2_HEAD,
) -> QueryState:
    """From embeddings [M,D] (any float dtype, e.g. a float16 memory map); two chunked passes, never a
    float32 copy of the whole table. ``rank2``: the total rank of both tiers at most (capped at the
    embeddings' numerical rank; no second tier when that leaves nothing beyond ``rank``). ``head``: basis
    vectors of the second tier's head (split only when at least tuning.TIER2_TAIL_MIN remain; 0: never
    split)."""
    M, D = embeddings.shape
    if not 0 < rank < D:
        raise ValueError(f"rank must lie in (0, {D}), got {rank}")
    if rank2 < 0 or head < 0:
        raise ValueError(f"rank2 and head must be >= 0, got {rank2}, {head}")
    full, energy = _basis(embeddings, basis_sample)
    top = max(rank, _tier2_rank(energy, rank, rank2))
    basis = torch.linalg.qr(full[:top].T).Q.T.contiguous()  # orthonormal to float64 rounding
    amax = torch.zeros(top, dtype=torch.float64)
    for s in range(0, M, _CHUNK):
        amax = torch.maximum(amax, (embeddings[s : s + _CHUNK].double() @ basis.T).abs().amax(0))
    scales = (amax / 127).clamp_min(1e-30).float()
    s64 = scales.double()
    codes = torch.empty(M, rank, dtype=torch.int8)
    h = head if 0 < head and top - rank - head >= tuning.TIER2_TAIL_MIN else top - rank
    split = rank + h  # the head's last basis vector + 1
    codes2 = torch.empty(M, h, dtype=torch.int8)
    tail = torch.empty(M, top - split, dtype=torch.int8)
    norms = torch.empty(M, 6, dtype=torch.float64)  # err, res (first tier), err2, res2, err2a, res2a
    cmax = cmax2 = 0.0
    for s in range(0, M, _CHUNK):
        f = embeddings[s : s + _CHUNK].double()
        c = f @ basis.T
        q = (c / s64).round().clamp(-127, 127)
        codes[s : s + _CHUNK] = q[:, :rank].to(torch.int8)
        codes2[s : s + _CHUNK] = q[:, rank:split].to(torch.int8)
        tail[s : s + _CHUNK] = q[:, split:].to(torch.int8)
        deq = q * s64
        n = norms[s : s + _CHUNK]
        n[:, 0] = (c[:, :rank] - deq[:, :rank]).norm(dim=1)
        n[:, 1] = (f - c[:, :rank] @ basis[:rank]).norm(dim=1)
        n[:, 2] = (c[:, rank:] - deq[:, rank:]).norm(dim=1)
        n[:, 3] = (f - c @ basis).norm(dim=1)
        n[:, 4] = (c[:, rank:split] - deq[:, rank:split]).norm(dim=1)
        n[:, 5] = (f - c[:, :split] @ basis[:split]).norm(dim=1)
        if len(deq):
            cmax = max(cmax, float(deq[:, :rank].norm(dim=1).max()))
            cmax2 = max(cmax2, float(deq.norm(dim=1).max()))
    tier2 = None
    if top > rank:
        bounds = torch.from_numpy(round_up_single(norms[:, 2:4].numpy()))
        tier2 = Tier2(basis[rank:].contiguous(), scales[rank:].contiguous(), codes2, bounds, cmax2)
        if split < top:
            tier2.tail = tail
            tier2.head_bounds = torch.from_numpy(round_up_single(norms[:, 4:].numpy()))
    return QueryState(
        basis[:rank].contiguous(),
        scales[:rank].contiguous(),
        codes,
        round_up_half(norms[:, 0].contiguous()),
        round_up_half(norms[:, 1].contiguous()),
        cmax,
        tier2,
    )


def _tier2_rank(energy: torch.Tensor, rank: int, rank2: int) -> int:
    """Total rank of both tiers: the numerical rank of the sample (eigenvalues ``energy`` of E^T E,
    descending) rounded up to a multiple of 8, at most rank2 and D - 1; 0 when no more than ``rank``."""
    D = len(energy)
    e = energy.clamp_min(0)
    tail = e.flip(0).cumsum(0).flip(0)  # tail[j] = energy beyond the first j vectors
    num = int((tail > TIER2_ENERGY * float(tail[0])).sum()) if float(tail[0]) > 0 else 0
    r = min(rank2, D - 1, -(-num // 8) * 8)
    return r if r > rank else 0


def round_up_half(x: torch.Tensor) -> torch.Tensor:
    """float16 values >= x (x [n] float64, >= 0), so a stored bound never shrinks."""
    a = x.numpy()
    h = a.astype(np.float16)
    low = h.astype(np.float64) < a
    h[low] = np.nextafter(h[low], np.float16(np.inf))
    return torch.from_numpy(h)


def round_up_single(x: np.ndarray) -> np.ndarray:
    """float32 values >= x (float64, >= 0), so a stored bound never shrinks."""
    h = x.astype(np.float32)
    low = h.astype(np.float64) < x
    h[low] = np.nextafter(h[low], np.float32(np.inf))
    return h


def _basis(embeddings: torch.Tensor, sample: int) -> tuple[torch.Tensor, torch.Tensor]:
    """All [D,D] eigenvectors of E^T E as rows, largest eigenvalue first (the best rank-r subspace for dot
    products is the first r), and the eigenvalues [D] descending, from a seeded sample of rows."""
    M = embeddings.shape[0]
    if M > sample:
        g = torch.Generator().manual_seed(0)
        rows = torch.randperm(M, generator=g)[:sample].sort().values
        E = embeddings[rows].double()
    else:
        E = embeddings.double()
    vals, vecs = torch.linalg.eigh(E.T @ E)  # ascending eigenvalues
    return vecs.flip(1).T.contiguous(), vals.flip(0)


def fingerprint(path: Path, blocks: int = 64, block: int = 4096) -> str:
    """sha256 of a file's size and ``blocks`` evenly spaced blocks: cheap, and changes when the file is
    replaced by another one (not a full checksum)."""
    size = path.stat().st_size
    h = hashlib.sha256(str(size).encode())
    with path.open("rb") as f:
        for i in range(blocks):
            f.seek(max(0, (size - block) * i // max(1, blocks - 1)))
            h.update(f.read(block))
    return h.hexdigest()


def save_state(state: QueryState, path: Path, source: str) -> None:
    """Write ``state`` to ``path`` (inside a package being written atomically), a block at a time (no
    bytes copy of the codes: 2.6 GB at 10M Gaussians)."""

    meta = {
        "format": STATE_FORMAT,
        "version": str(STATE_VERSION),
        "rank": str(state.rank),
        "num": str(state.num),
        "dim": str(int(state.basis.shape[1])),
        "code_norm_max": repr(float(state.code_norm_max)),
        "source": source,
        "rank2": "0",
    }
    tensors = {
        "basis": state.basis.contiguous(),
        "scales": state.scales.contiguous(),
        "codes": state.codes.contiguous(),
        "err_norm": state.err_norm.contiguous(),
        "res_norm": state.res_norm.contiguous(),
    }
    t2 = state.tier2
    if t2 is not None:
        meta["rank2"] = str(t2.rank)
        meta["code_norm_max2"] = repr(float(t2.code_norm_max))
        meta["head2"] = str(t2.head)
        tensors |= {
            "basis2": t2.basis.contiguous(),
            "scales2": t2.scales.contiguous(),
            "codes2": t2.codes.contiguous(),
            "bounds2": t2.bounds.contiguous(),
        }
        if t2.tail is not None:
            tensors |= {"codes2_tail": t2.tail.contiguous(), "bounds2_head": t2.head_bounds.contiguous()}
    save_blocks(path, tensors, meta)


def load_state(path: Path, num: int, dim: int, source: str) -> QueryState:
    """The state in ``path``, codes memory-mapped; ValidationError names the file and what is wrong
    (wrong format or version, shapes that disagree with the package, non-finite or negative bounds,
    a state written for other embeddings)."""
    from safetensors import SafetensorError, safe_open

    where = str(path)
    try:
        with safe_open(where, framework="pt") as f:
            meta = f.metadata() or {}
            small = {k: f.get_tensor(k) for k in ("basis", "scales", "err_norm", "res_norm")}
    except (SafetensorError, OSError) as e:
        raise ValidationError(where, f"cannot read ({e})") from e
    if meta.get("format") != STATE_FORMAT:
        raise ValidationError(where, f"not a query state (format {meta.get('format')!r})")
    if meta.get("version") != str(STATE_VERSION):
        raise ValidationError(
            where,
            f"query state version {meta.get('version')!r}, this build reads version {STATE_VERSION} only: "
            f"export the package again ({REEXPORT}) or delete this file (the state is then built at load)",
        )
    if meta.get("source") != source:
        raise ValidationError(where, "written for other embeddings than the package's (stale)")
    try:
        r, n, d, cmax = int(meta["rank"]), int(meta["num"]), int(meta["dim"]), float(meta["code_norm_max"])
    except (KeyError, ValueError) as e:
        raise ValidationError(where, f"bad metadata ({e})") from e
    if (n, d) != (num, dim) or not 0 < r < d:
        raise ValidationError(where, f"state for [{n},{d}] rank {r}, the package has [{num},{dim}]")
    codes = mmap_torch(path, "codes")
    want = {
        "basis": ((r, d), torch.float64),
        "scales": ((r,), torch.float32),
        "err_norm": ((n,), torch.float16),
        "res_norm": ((n,), torch.float16),
    }
    for k, (shape, dtype) in want.items():
        t = small[k]
        if tuple(t.shape) != shape or t.dtype != dtype:
            raise ValidationError(where, f"{k} must be {dtype} {list(shape)}, got {t.dtype} {list(t.shape)}")
        if not bool(torch.isfinite(t).all()) or (k != "basis" and bool((t < 0).any())):
            raise ValidationError(where, f"{k} must be finite and non-negative")
    if tuple(codes.shape) != (n, r) or codes.dtype != torch.int8:
        raise ValidationError(where, f"codes must be int8 [{n},{r}], got {codes.dtype} {list(codes.shape)}")
    if not np.isfinite(cmax) or cmax < 0:
        raise ValidationError(where, "code_norm_max must be finite and non-negative")
    tier2 = _load_tier2(path, meta, n, d, r)
    err, res = small["err_norm"], small["res_norm"]
    return QueryState(small["basis"], small["scales"], codes, err, res, cmax, tier2)


def _load_tier2(path: Path, meta: dict, n: int, d: int, r: int) -> Tier2 | None:
    """The second tier of a state (None when it has none), codes and bounds memory-mapped; head2 = rank2
    when the tier is stored whole."""
    from safetensors import safe_open

    where = str(path)
    try:
        r2 = int(meta["rank2"])
        if r2 == 0:
            return None
        cmax2, h = float(meta["code_norm_max2"]), int(meta["head2"])
    except (KeyError, ValueError) as e:
        raise ValidationError(where, f"bad metadata ({e})") from e
    if not 0 < r + r2 < d or not np.isfinite(cmax2) or cmax2 < 0:
        raise ValidationError(where, f"second tier rank {r2} (first {r}, dim {d}) or code_norm_max2 invalid")
    if not 0 < h <= r2:
        raise ValidationError(where, f"second tier head {h} must lie in [1, rank2 = {r2}]")
    names = {"basis2", "scales2", "codes2", "bounds2"}
    names |= {"codes2_tail", "bounds2_head"} if h < r2 else set()
    with safe_open(where, framework="pt") as f:
        if not names <= set(f.keys()):
            raise ValidationError(where, "second tier declared (rank2, head2) but its tensors are missing")
        basis2, scales2 = f.get_tensor("basis2"), f.get_tensor("scales2")
    codes2, bounds2 = mmap_torch(path, "codes2"), mmap_torch(path, "bounds2")
    want = {
        "basis2": (basis2, (r2, d), torch.float64),
        "scales2": (scales2, (r2,), torch.float32),
        "codes2": (codes2, (n, h), torch.int8),
        "bounds2": (bounds2, (n, 2), torch.float32),
    }
    tail = head_bounds = None
    if h < r2:
        tail, head_bounds = mmap_torch(path, "codes2_tail"), mmap_torch(path, "bounds2_head")
        want |= {
            "codes2_tail": (tail, (n, r2 - h), torch.int8),
            "bounds2_head": (head_bounds, (n, 2), torch.float32),
        }
    for k, (t, shape, dtype) in want.items():
        if tuple(t.shape) != shape or t.dtype != dtype:
            raise ValidationError(where, f"{k} must be {dtype} {list(shape)}, got {t.dtype} {list(t.shape)}")
    checked = [("basis2", basis2), ("scales2", scales2), ("bounds2", bounds2)]
    for k, t in checked + ([("bounds2_head", head_bounds)] if head_bounds is not None else []):
        for s in range(0, len(t), 1 << 20):  # chunked: a memory map is paged, not copied
            part = t[s : s + (1 << 20)]
            if not bool(torch.isfinite(part).all()) or (k != "basis2" and bool((part < 0).any())):
                raise ValidationError(where, f"{k} must be finite and non-negative")
    return Tier2(basis2, scales2, codes2, bounds2, cmax2, mapped=True, tail=tail, head_bounds=head_bounds)
