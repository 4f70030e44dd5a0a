"""The compact query state of a scene and what bounds its error, saved in the package.

For stored embeddings f_i [M,D] and an orthonormal basis B [r,D] (top eigenvectors of E^T E):
    c_i = B f_i (exact coefficients), c'_i = s * round(c_i / s) (int8 codes, one scale per basis vector),
    f_i = B^T c'_i + B^T (c_i - c'_i) + (f_i - B^T c_i).
So for any vector v with w = B v and v_perp = v - B^T w:
    |f_i.v - c'_i.w| <= |c_i - c'_i| |w| + |f_i - B^T c_i| |v_perp|,
the two per-row norms (quantisation error, residual) being stored rounded up. The query index turns these
into certified bounds (fmgs.query.certify).

File ``query_state.safetensors`` in the package (written by ``export_scene``):
  basis [r,D] float64, scales [r] float32, codes [M,r] int8, err_norm [M] float16, res_norm [M] float16,
  metadata {format: "fmgs-query-state", version, rank, num, dim, code_norm_max, source}.
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

STATE_FILE = "query_state.safetensors"
STATE_FORMAT = "fmgs-query-state"
STATE_VERSION = 1
_CHUNK = 65536


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

    @property
    def rank(self) -> int:
        return int(self.basis.shape[0])

    @property
    def num(self) -> int:
        return int(self.codes.shape[0])


def build_state(embeddings: torch.Tensor, rank: int, basis_sample: int = 100_000) -> QueryState:
    """From embeddings [M,D] (any float dtype, e.g. a float16 memory map); two chunked passes, never a
    float32 copy of the whole table."""
    M, D = embeddings.shape
    if not 0 < rank < D:
        raise ValueError(f"rank must lie in (0, {D}), got {rank}")
    basis = _basis(embeddings, rank, basis_sample)
    amax = torch.zeros(rank, dtype=torch.float64)
    for s in range(0, M, _CHUNK):
        amax = torch.maximum(amax, (embeddings[s : s + _CHUNK].double() @ basis.T).abs().amax(0))
    scales = (amax / 127).clamp_min(1e-30).float()
    s64 = scales.double()
    codes = torch.empty(M, rank, dtype=torch.int8)
    err = torch.empty(M, dtype=torch.float64)
    res = torch.empty(M, dtype=torch.float64)
    cmax = 0.0
    for s in range(0, M, _CHUNK):
        f = embeddings[s : s + _CHUNK].double()
        c = f @ basis.T
        q = (c / s64).round().clamp(-127, 127)
        codes[s : s + _CHUNK] = q.to(torch.int8)
        deq = q * s64
        err[s : s + _CHUNK] = (c - deq).norm(dim=1)
        res[s : s + _CHUNK] = (f - c @ basis).norm(dim=1)
        if len(deq):
            cmax = max(cmax, float(deq.norm(dim=1).max()))
    return QueryState(basis, scales, codes, round_up_half(err), round_up_half(res), cmax)


def round_up_half(x: torch.Tensor) -> torch.Tensor:
    """float16 values >= x (x [n] float64, >= 0), so a stored bound never shrinks."""
    a = x.numpy()
    h = a.astype(np.float16)
    low = h.astype(np.float64) < a
    h[low] = np.nextafter(h[low], np.float16(np.inf))
    return torch.from_numpy(h)


def _basis(embeddings: torch.Tensor, rank: int, sample: int) -> torch.Tensor:
    """[rank,D] float64 top eigenvectors of E^T E (best rank-r subspace for dot products), from a seeded
    sample of rows."""
    M = embeddings.shape[0]
    if M > sample:
        g = torch.Generator().manual_seed(0)
        rows = torch.randperm(M, generator=g)[:sample].sort().values
        E = embeddings[rows].double()
    else:
        E = embeddings.double()
    _, vecs = torch.linalg.eigh(E.T @ E)  # ascending eigenvalues
    B = vecs[:, -rank:].flip(1).T.contiguous()
    return torch.linalg.qr(B.T).Q.T.contiguous()  # orthonormal to float64 rounding


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
    """Write ``state`` to ``path`` (inside a package being written atomically)."""
    from safetensors.torch import save_file

    meta = {
        "format": STATE_FORMAT,
        "version": str(STATE_VERSION),
        "rank": str(state.rank),
        "num": str(state.num),
        "dim": str(int(state.basis.shape[1])),
        "code_norm_max": repr(float(state.code_norm_max)),
        "source": source,
    }
    tensors = {
        "basis": state.basis.contiguous(),
        "scales": state.scales.contiguous(),
        "codes": state.codes.contiguous(),
        "err_norm": state.err_norm.contiguous(),
        "res_norm": state.res_norm.contiguous(),
    }
    save_file(tensors, str(path), metadata=meta)


def load_state(path: Path, num: int, dim: int, source: str) -> QueryState:
    """The state in ``path``, codes memory-mapped; ValidationError names the file and what is wrong
    (wrong format or version, shapes that disagree with the package, non-finite or negative bounds,
    a state written for other embeddings)."""
    from safetensors import SafetensorError, safe_open

    from fmgs.io.mmap_tensors import mmap_torch

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
            where, f"query state version {meta.get('version')!r}, this build reads {STATE_VERSION}"
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
    return QueryState(small["basis"], small["scales"], codes, small["err_norm"], small["res_norm"], cmax)
