"""The float16 refinement pass of text queries: its two decodings side by side, one thread.

    python -m benchmarks.half_dots [--rows 200000] [--dim 512] [--repeats 7]

``half_dots`` decodes by shifting the bits into float32's layout and scaling by 2^112; the field
decoding (``scaled=False``, exact under flush-to-zero) is what it falls back to. Same rows, same
columns, alternating, medians; prints milliseconds per million rows and the ratio.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, default=200_000)
    ap.add_argument("--dim", type=int, default=512)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    import numba

    from fmgs.query import kernels

    numba.set_num_threads(1)
    rng = np.random.default_rng(0)
    A = (rng.standard_normal((args.rows, args.dim)) / np.sqrt(args.dim)).astype(np.float16).view(np.uint16)
    rows = np.sort(rng.choice(args.rows, int(args.rows * 0.95), replace=False)).astype(np.int64)
    print(f"{len(rows):,} of {args.rows:,} rows, D={args.dim}, one thread; ms per million rows (median)")
    for n in (1, 2, 8):
        V = rng.standard_normal((n, args.dim)).astype(np.float32)
        V /= np.linalg.norm(V, axis=1, keepdims=True)
        out, mag = np.empty((len(rows), n), np.float32), np.empty((len(rows), n), np.float32)
        paths = {
            "scaled": functools.partial(kernels.half_dots, A, rows, V, out, mag),
            "fields": functools.partial(kernels.half_dots, A, rows, V, out, mag, scaled=False),
        }
        times = {k: [] for k in paths}
        for f in paths.values():
            f()  # compile
        for _ in range(args.repeats):
            for k, f in paths.items():
                t = time.perf_counter()
                f()
                times[k].append(time.perf_counter() - t)
        ms = {k: statistics.median(v) * 1e9 / len(rows) for k, v in times.items()}
        ratio = ms["fields"] / ms["scaled"]
        print(f"{n} text(s): scaled {ms['scaled']:.0f}, fields {ms['fields']:.0f} ({ratio:.2f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
