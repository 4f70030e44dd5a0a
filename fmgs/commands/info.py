"""``fmgs info``: validate a scene file and print a summary, or describe a scene package folder."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from fmgs.commands.common import load_scene

PACKAGE_BUILD_KEYS = (
    "description", "source", "build_seconds", "made_by", "targets", "embedding_neighbours", "recording",
)  # fmt: skip
"""Keys of a package manifest's ``extra`` that ``fmgs info`` shows as how the package was built."""


def add_parser(sub) -> None:
    i = sub.add_parser(
        "info",
        help="validate a scene (.ply, .splat or .safetensors) and print a summary, or describe a scene "
        "package folder (e.g. models/demo) or a sharded scene (`fmgs shard`)",
    )
    i.add_argument("scene", help="scene file, scene package folder, or sharded scene folder")
    i.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Validate a scene file and print its size, SH degree, bounds and opacity statistics; or describe a
    scene package folder from its manifest."""
    from fmgs.scene.manifest import FILENAME, SHARDS_FILE

    if Path(args.scene).is_dir() and (Path(args.scene) / FILENAME).is_file():
        print(json.dumps(package_info(Path(args.scene)), indent=2))
        return 0
    if Path(args.scene).is_dir() and (Path(args.scene) / SHARDS_FILE).is_file():
        print(json.dumps(sharded_info(Path(args.scene)), indent=2, allow_nan=False))
        return 0
    g = load_scene(Path(args.scene))
    lo, hi = g.means.min(0).values.tolist(), g.means.max(0).values.tolist()
    op = g.opacities
    info = {
        "file": str(args.scene),
        "gaussians": g.num,
        "sh_degree": g.sh_degree,
        "bounds_min": [round(v, 4) for v in lo],
        "bounds_max": [round(v, 4) for v in hi],
        "opacity_median": round(float(op.median()), 4),
        "opacity_above_0.25": int((op > 0.25).sum()),
    }
    print(json.dumps(info, indent=2))
    return 0


def package_info(path: Path) -> dict:
    """What a scene package holds, from its manifest (validated; no tensor is read): name, encoder, counts,
    bounds and the frame they are in (None: the scene's own), the field's storage, label names, how it was
    built, and its files with their sizes."""
    from fmgs.errors import ValidationError
    from fmgs.scene.manifest import Manifest

    m = Manifest.read(path)
    missing = [f for f in ("gaussians.safetensors", "embeddings.safetensors") if not (path / f).is_file()]
    if missing:
        raise ValidationError(str(path), f"scene package without {', '.join(missing)}")
    build = {k: m.extra[k] for k in PACKAGE_BUILD_KEYS if k in m.extra}
    enc = m.extra.get("text_encoder")
    if isinstance(enc, dict) and enc.get("revision"):
        build["text_encoder_revision"] = enc["revision"]
    return {
        "package": str(path),
        "name": m.name,
        "encoder": {"id": m.encoder_id, "dim": m.dim},
        "gaussians": m.num_gaussians,
        "embedded": m.num_selected,
        "sh_degree": m.sh_degree,
        "bounds_min": [round(v, 4) for v in m.bounds[:3]],
        "bounds_max": [round(v, 4) for v in m.bounds[3:]],
        "frame": m.frame_id or None,
        "embedding_dtype": m.embedding_dtype,
        "field": None if m.field is None else {"dtype": m.field.dtype, "dino_head": m.field.dino_head},
        "label_names": list(m.label_names),
        "build": build,
        "files": {p.name: p.stat().st_size for p in sorted(path.iterdir()) if p.is_file()},
    }


def sharded_info(path: Path) -> dict:
    """What a sharded scene (``fmgs shard``) holds, from its shards.json (validated; no tensor is read):
    the source's name, encoder and counts, and each shard's folder, counts and k-d cell (an open side
    as "inf" or "-inf", as shards.json writes it)."""
    from fmgs.scene.shards import ShardManifest

    d = ShardManifest.read(path).to_dict()
    return {
        "sharded_scene": str(path),
        "name": d["name"],
        "encoder": d["encoder"],
        "gaussians": d["counts"]["gaussians"],
        "embedded": d["counts"]["selected"],
        "shards": [
            {"folder": s["folder"], "gaussians": s["counts"]["gaussians"],
             "embedded": s["counts"]["selected"], "cell": s["cell"]}
            for s in d["shards"]
        ],
    }  # fmt: skip
