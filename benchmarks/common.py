"""What the benchmark scripts share: where the repository and the reports are, the machine stamp, timing,
field-like scenes exported as packages, and a fixed-table text encoder.

Run every script from the repository root as a module (``python -m benchmarks.raster``), so that
``benchmarks`` and the project's packages import from this checkout. torch and the project's packages are
imported inside the functions that need them: a script that only reads stored figures (``benchmarks.gpu
--report-only``) runs without them.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import platform
import statistics
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

    from fmgs.gaussians import GaussianSet

ROOT = Path(__file__).resolve().parents[1]
"""The repository root (scripts run from it, subprocesses start in it)."""
RESULTS = ROOT / "benchmarks" / "results"
"""Where the committed reports live (each script's default output)."""

D = 512
"""Embedding width of the benchmark scenes (the FMGS CLIP head's)."""
ENC = "bench/fixed-table"
"""Encoder id of packages made with ``export`` (served with ``TableEncoder``)."""


def machine() -> dict:
    """The machine, library versions, date and commit every report is stamped with."""
    import numba
    import numpy
    import torch

    cpu = next(
        (
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        ),
        platform.processor(),
    )
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    return {
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "ram_gb": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1),
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numba": numba.__version__,
        "numpy": numpy.__version__,
        "commit": commit.stdout.strip(),
    }


def machine_words(info: dict) -> str:
    """'CPU (N cores, GPU g), commit c' (or 'no GPU') from ``machine()``'s dict, as reports print it."""
    gpu = f"GPU {info['gpu']}" if info["gpu"] else "no GPU"
    return f"{info['cpu']} ({info['cores']} cores, {gpu}), commit {info['commit']}"


def save_report(text: str, out: Path | str, name: str, publish: bool) -> None:
    """Writes ``text`` to OUT/NAME and, when ``publish``, to the committed report RESULTS/NAME too."""
    Path(out).mkdir(parents=True, exist_ok=True)
    (Path(out) / name).write_text(text)
    if publish:
        (RESULTS / name).write_text(text)


def command_line(module: str) -> str:
    """The command this process runs, as a report quotes it: ``python -m MODULE`` and its arguments
    without the ``--note`` options (the notes are printed in the report themselves)."""
    import shlex
    import sys

    argv = sys.argv[1:]
    argv = [x for i, x in enumerate(argv) if x != "--note" and (i == 0 or argv[i - 1] != "--note")]
    return f"python -m {module} " + shlex.join(argv)


def save_result(d: dict, out: Path | str, name: str, text: str, publish: bool) -> None:
    """Writes a report's data ``d`` to OUT/name.json (lower case), its ``text`` to OUT/NAME.md and, when
    ``publish``, both to RESULTS (NAME.json, NAME.md)."""
    Path(out).mkdir(parents=True, exist_ok=True)
    (Path(out) / f"{name.lower()}.json").write_text(json.dumps(d, indent=1, default=float))
    if publish:
        (RESULTS / f"{name}.json").write_text(json.dumps(d, indent=1, default=float))
    save_report(text, out, f"{name}.md", publish)


def rss_gb() -> float:
    """This process's resident memory now, in GB."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e9


def med_ms(ts) -> float:
    """Median of times in seconds, in milliseconds."""
    return statistics.median(ts) * 1e3


def page_in(folder: Path) -> None:
    """Read every file under ``folder`` once, into the page cache: the steady state of a served package.
    Building other indexes may have pushed its pages out, and the first queries would then time the
    disk."""
    for f in sorted(folder.rglob("*")):
        if f.is_file():
            with f.open("rb") as fh:
                while fh.read(1 << 24):
                    pass


def fieldlike(
    means: torch.Tensor,
    dim: int = D,
    seed: int = 0,
    device: str | torch.device = "cpu",
    box: torch.Tensor | None = None,
) -> torch.Tensor:
    """[N,dim] unit embeddings that vary smoothly with position, of rank <= 257 like the real head: a random
    two-layer MLP (256 hidden, as the FMGS language head) over Fourier features of the positions.

    Computed on ``device`` in chunks, returned there. ``box`` [2,3] (min, max) fixes the normalisation
    box (default: the means' own), so a scene made chunk by chunk gets the embeddings of one call.
    """
    import torch

    from fmgs.vecmath import safe_normalize

    g = torch.Generator().manual_seed(seed)
    lo, hi = (means.min(0).values, means.max(0).values) if box is None else (box[0], box[1])
    B = torch.randn(3, 32, generator=g) * torch.linspace(1, 12, 32)
    W1, b1 = torch.randn(64, 256, generator=g) / 8, torch.randn(256, generator=g) * 0.1
    W2, b2 = torch.randn(256, dim, generator=g) / 16, torch.randn(dim, generator=g) * 0.3
    lo, hi, B, W1, b1, W2, b2 = (t.to(device) for t in (lo, hi, B, W1, b1, W2, b2))
    out = torch.empty(len(means), dim, device=device)
    for s in range(0, len(means), 65536):
        x = (means[s : s + 65536].to(device) - lo) / (hi - lo).clamp_min(1e-9) @ B
        h = torch.relu(torch.cat([x.sin(), x.cos()], 1) @ W1 + b1)
        out[s : s + 65536] = safe_normalize(h @ W2 + b2)
    return out


def canonical_vectors(dim: int = D) -> torch.Tensor:
    """[4,dim] unit canonical vectors (seed 9): the canonical phrases' embeddings of every benchmark scene."""
    import torch

    from fmgs.vecmath import safe_normalize

    return safe_normalize(torch.randn(4, dim, generator=torch.Generator().manual_seed(9)))


def make_queries(emb: torch.Tensor, n: int, seed: int = 1) -> torch.Tensor:
    """Queries near random scene embeddings (each has a clear best region)."""
    import torch

    from fmgs.vecmath import safe_normalize

    g = torch.Generator().manual_seed(seed)
    rows = torch.randint(0, len(emb), (n,), generator=g)
    return safe_normalize(emb[rows] + 0.6 * safe_normalize(torch.randn(n, emb.shape[1], generator=g)))


class TableEncoder:
    """Texts 'q<i>' map to fixed query vectors (the embedding cost is not what is measured).

    Any other text (the presence score's vocabulary of negatives) gets a random unit vector seeded
    by the text's bytes, so the server's whole text path runs, presence included.
    """

    id, dim = ENC, D

    def __init__(self, queries: torch.Tensor, canonical: torch.Tensor) -> None:
        self.table = {f"q{i}": v for i, v in enumerate(queries)}
        self.table.update(zip(("object", "stuff", "things", "texture"), canonical, strict=True))

    def _vector(self, text: str) -> torch.Tensor:
        import torch

        from fmgs.vecmath import safe_normalize

        if text not in self.table:
            seed = int.from_bytes(hashlib.blake2b(text.encode(), digest_size=8).digest(), "little")
            g = torch.Generator().manual_seed(seed)
            self.table[text] = safe_normalize(torch.randn(self.dim, generator=g))
        return self.table[text]

    def encode_text(self, texts):
        import torch

        return torch.stack([self._vector(t) for t in texts])


def gaussians_from(scene) -> GaussianSet:
    """The GaussianSet of a benchmarks.scenes.Scene (its colours as degree-0 SH)."""
    from fmgs.gaussians import SH_C0, GaussianSet

    sh = ((scene.colors - 0.5) / SH_C0)[:, None, :]
    return GaussianSet.from_activated(scene.means, scene.quats, scene.scales, scene.opacities, sh=sh)


def export(folder: Path, g: GaussianSet, emb: torch.Tensor, canon: torch.Tensor, sel=None) -> Path:
    """Export ``g`` with embeddings ``emb`` (rows ``sel``, default all) as a package encoded by ``ENC``."""
    import torch

    from fmgs.scene.package import export_scene

    sel = torch.arange(g.num) if sel is None else sel
    return export_scene(folder, g, sel, emb, ENC, canon)


def proto_camera(cam):
    """The wire Camera of an fmgs Camera."""
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

    v = cam.viewmat.reshape(-1).tolist()
    return pb.Camera(
        viewmat=v, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, width=cam.width, height=cam.height
    )
