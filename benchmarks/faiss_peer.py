"""Text queries against faiss: the peer indexes every text report compares with, and the float64 truth
that ours and theirs are scored against.

The margin trick: faiss indexes x' = [f, -max_n f.c_n] for each stored float16 embedding f (c_n the
canonical vectors) and searches with q' = [q, 1], so its inner product is the served margin
f.q - max_n f.c_n by which our engine ranks. Two indexes, the same for every report (benchmarks/text.py:
TEXT.md, TEXT_1M.md, TEXT_10M.md; benchmarks/workprec/text.py: REPORT.md's text section):

    faiss_flat            IndexFlatIP: exact float32 (TEXT.md skips it where it would not fit in memory)
    faiss_ivf_sq8_refine  IVF<nlist>,SQ8,Refine(SQfp16): nlist the power of two nearest sqrt(M), trained on
                          max(100,000, 40 x nlist) sampled rows, nprobe 64, float16 refinement of 1,000
                          candidates per query (k_factor 1000 / k, at least 1)

faiss-cpu is a benchmark-only dependency (``pip install faiss-cpu``); it is imported only when an index is
built or searched.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from benchmarks.common import D

FLAT, IVF = "faiss_flat", "faiss_ivf_sq8_refine"
"""The peers' names (keys of ``build``'s dict and of the reports' figures)."""
NPROBE = 64
"""IVF lists searched per query."""
REFINE = 1000
"""Candidates refined in float16 per query."""


# ---------------------------------------------------------------- the float64 truth


def margins(emb: torch.Tensor, cmax: torch.Tensor, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """float64 margins f.q - cmax [n,M] for queries q [n,D] (one pass over the rows for all of them) and
    each query's best cosine [n]."""
    M = len(emb)
    out = torch.empty(len(q), M, dtype=torch.float64)
    best = torch.full((len(q),), -2.0, dtype=torch.float64)
    q64 = q.double()
    for s in range(0, M, 262144):
        d = emb[s : s + 262144].double() @ q64.T  # [b,n]
        best = torch.maximum(best, d.amax(0))
        out[:, s : s + 262144] = (d - cmax[s : s + 262144].double()[:, None]).T
    return out, best


def top_of(m: torch.Tensor, k: int) -> np.ndarray:
    """Rows of the k largest margins m [M], best first, ties by row: rows tied at the k-th margin are
    taken lowest row first (topk alone picks any of them)."""
    v = torch.topk(m, k, sorted=False).values.min()
    above = torch.nonzero(m > v).reshape(-1)
    tied = torch.nonzero(m == v).reshape(-1)[: k - len(above)]  # ascending rows
    return np.array(sorted(torch.cat([above, tied]).tolist(), key=lambda i: (-float(m[i]), i)))


def exact_top(
    emb: torch.Tensor, cmax: torch.Tensor, q: torch.Tensor, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the exact top k by float64 margin (ties by row), and all margins [M]."""
    m = margins(emb, cmax, q[None])[0][0]
    return top_of(m, k), m.numpy()


def recall(ids: np.ndarray, truth: np.ndarray, margin: np.ndarray) -> float:
    """Tie-aware recall: the fraction of the k answers whose exact margin reaches the k-th exact margin
    (another copy of a tied row counts as correct)."""
    ids = ids[ids >= 0]
    return float((margin[ids] >= margin[truth[-1]]).sum()) / len(truth)


# ---------------------------------------------------------------- the peer indexes


def nlist(n: int) -> int:
    """IVF lists: the power of two nearest sqrt(n) (faiss's rule of thumb; 1,024 at 1M, 4,096 at 10M)."""
    return max(64, 1 << round(math.log2(math.sqrt(n))))


def build(emb: torch.Tensor, cmax: torch.Tensor, flat: bool = True, block: int = 262144) -> dict:
    """IndexFlatIP (when ``flat``) and IVF-SQ8 + float16 refinement over [f, -cmax], added a block of
    rows at a time from emb [M,D] (any dtype, e.g. the package's memory map). Returns name -> {"index",
    "build_s", "bytes" (per row), "refine" (search with refinement), and "nlist" for the IVF index}."""
    import faiss

    M = len(emb)

    def rows(s: int, e: int) -> np.ndarray:
        return np.concatenate([emb[s:e].float().numpy(), -cmax[s:e].float().numpy()[:, None]], 1)

    out = {}
    if flat:
        t0 = time.perf_counter()
        index = faiss.IndexFlatIP(D + 1)
        for s in range(0, M, block):
            index.add(rows(s, min(M, s + block)))
        out[FLAT] = {
            "index": index,
            "build_s": time.perf_counter() - t0,
            "bytes": 4 * (D + 1),
            "refine": False,
        }
    t0 = time.perf_counter()
    lists = nlist(M)
    ivf = faiss.index_factory(D + 1, f"IVF{lists},SQ8,Refine(SQfp16)", faiss.METRIC_INNER_PRODUCT)
    rng = np.random.default_rng(0)
    sample = torch.from_numpy(np.sort(rng.choice(M, min(M, max(100_000, 40 * lists)), replace=False)))
    ivf.train(np.concatenate([emb[sample].float().numpy(), -cmax[sample].float().numpy()[:, None]], 1))
    for s in range(0, M, block):
        ivf.add(rows(s, min(M, s + block)))
    faiss.extract_index_ivf(ivf).nprobe = NPROBE
    out[IVF] = {
        "index": ivf,
        "build_s": time.perf_counter() - t0,
        "bytes": (D + 1) + 8 + 2 * (D + 1),
        "nlist": lists,
        "refine": True,
    }
    return out


def query_row(q: torch.Tensor) -> np.ndarray:
    """[1,D+1] float32 [q, 1]: a query [D] as the peers search for it."""
    return np.concatenate([q.numpy(), [1.0]]).astype(np.float32)[None]


def search_params(entry: dict, k: int):
    """faiss search parameters of a ``build`` entry for top k (None: the index's own)."""
    import faiss

    return faiss.IndexRefineSearchParameters(k_factor=max(1.0, REFINE / k)) if entry["refine"] else None


def search(entry: dict, qx: np.ndarray, k: int, params) -> tuple[np.ndarray, np.ndarray]:
    """(inner products [1,k], ids [1,k]) of the query rows ``qx`` through one ``build`` entry."""
    if params is not None:
        return entry["index"].search(qx, k, params=params)
    return entry["index"].search(qx, k)


def timed_search(entry: dict, q: torch.Tensor, k: int) -> tuple[np.ndarray, float]:
    """One query through one peer: ids [k] and the milliseconds of the search call alone (TEXT.md)."""
    qx, params = query_row(q), search_params(entry, k)
    t0 = time.perf_counter()
    _, ids = search(entry, qx, k, params)
    return ids[0], (time.perf_counter() - t0) * 1e3


class FaissRanker:
    """A peer with the ranker interface of REPORT.md's text settings (``rank``, ``nbytes``): ``rank`` returns
    fmgs.query.index.Ranked with the peer's inner products as margins."""

    def __init__(self, entry: dict, n: int) -> None:
        self.entry, self.bytes = entry, entry["bytes"] * n

    def rank(self, q: torch.Tensor, k: int):
        from fmgs.query.index import Ranked, served_relevancy

        dist, ids = search(self.entry, query_row(q), k, search_params(self.entry, k))
        keep = ids[0] >= 0
        m = torch.from_numpy(dist[0][keep]).float()
        return Ranked(torch.from_numpy(ids[0][keep]), served_relevancy(m), m)

    def nbytes(self) -> int:
        return self.bytes
