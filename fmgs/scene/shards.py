"""Spatial shards of a scene package: a balanced k-d split of the means, each piece a valid package.

Layout of a sharded scene (``fmgs shard models/NAME --shards K --out DIR``):

  DIR/shards.json               format "fmgs.shards", version, the source's name, counts and encoder,
                                the scene box that instance grouping needs, and one entry per shard
                                (folder, counts, its cell: the k-d box its means lie in)
  DIR/shard-000/ ...            scene packages (fmgs.scene.package layout), each loadable on its own,
                                plus ``shard_ids.safetensors``: the source's index of each of its
                                Gaussians and embedded rows (int64, ascending)

A shard keeps the source's stored values byte for byte (float16 embeddings, float32 canonical dots,
the field), so scoring a row in a shard gives the bits the source gives (fmgs.query.sharded merges
answers exactly). Its query state is rebuilt from its own rows: the state only bounds, it never
decides an answer.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fmgs.errors import ValidationError
from fmgs.io.tensors import load_gaussians, save_gaussians
from fmgs.query.state import STATE_FILE, TIER2_RANK, build_state, fingerprint, load_state, save_state
from fmgs.scene.manifest import FILENAME, SHARDS_FILE, Manifest
from fmgs.scene.package import check_replaceable, read_tensors, scene_folder

IDS_FILE = "shard_ids.safetensors"
FORMAT = "fmgs.shards"
VERSION = 1
MAX_SHARDS = 4096


@dataclass(frozen=True)
class ShardInfo:
    """One shard as listed in ``shards.json``."""

    folder: str
    """Package folder inside the sharded scene."""
    num_gaussians: int
    num_selected: int
    cell: tuple[float, ...]
    """[6] min xyz, max xyz of the k-d cell (infinite at the scene's outer faces)."""


@dataclass(frozen=True)
class ShardManifest:
    """A sharded scene's ``shards.json``."""

    name: str
    """The source scene's name."""
    encoder_id: str
    dim: int
    num_gaussians: int
    num_selected: int
    means_box: tuple[float, ...]
    """[6] the 1st and 99th percentile box of all means (fmgs.query.instances.default_eps)."""
    shards: tuple[ShardInfo, ...]
    tree: object = None
    """The k-d splits: a shard index (leaf) or [axis, plane, left, right]; gives each camera its
    front-to-back order of the shards (``front_to_back``). None in manifests written without it."""

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "name": self.name,
            "encoder": {"id": self.encoder_id, "dim": self.dim},
            "counts": {"gaussians": self.num_gaussians, "selected": self.num_selected},
            "means_box": list(self.means_box),
            "shards": [
                {
                    "folder": s.folder,
                    "counts": {"gaussians": s.num_gaussians, "selected": s.num_selected},
                    "cell": [_json_float(c) for c in s.cell],
                }
                for s in self.shards
            ],
            "tree": self.tree,
        }

    @classmethod
    def read(cls, folder: str | Path) -> ShardManifest:
        """Read and check ``folder/shards.json``; ValidationError names the file and what is wrong."""
        path = Path(folder) / SHARDS_FILE
        try:
            m = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ValidationError(str(path), f"not a sharded scene ({e})") from e
        try:
            if m.get("format") != FORMAT or m.get("version") != VERSION:
                raise ValueError(f"format {m.get('format')!r} version {m.get('version')!r}")
            shards = tuple(
                ShardInfo(
                    str(s["folder"]),
                    int(s["counts"]["gaussians"]),
                    int(s["counts"]["selected"]),
                    tuple(float(c) for c in s["cell"]),
                )
                for s in m["shards"]
            )
            out = cls(
                str(m["name"]),
                str(m["encoder"]["id"]),
                int(m["encoder"]["dim"]),
                int(m["counts"]["gaussians"]),
                int(m["counts"]["selected"]),
                tuple(float(c) for c in m["means_box"]),
                shards,
                _check_tree(m.get("tree"), len(shards)),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise ValidationError(str(path), f"malformed shard manifest ({e})") from e
        if not 1 <= len(shards) <= MAX_SHARDS or len(out.means_box) != 6:
            raise ValidationError(str(path), f"expected 1..{MAX_SHARDS} shards and a 6-number means_box")
        for s in shards:
            if "/" in s.folder or s.folder.startswith(".") or len(s.cell) != 6:
                raise ValidationError(str(path), f"bad shard entry {s.folder!r}")
        if sum(s.num_gaussians for s in shards) != out.num_gaussians:
            raise ValidationError(str(path), "shard Gaussian counts do not add up to the scene's")
        return out


def _check_tree(t, n: int):
    """The tree as read, checked to hold every shard index once (ValueError otherwise)."""
    if t is None:
        return None
    seen: list[int] = []

    def walk(node) -> None:
        if isinstance(node, int) and not isinstance(node, bool):
            seen.append(node)
            return
        if not (isinstance(node, list) and len(node) == 4 and node[0] in (0, 1, 2)):
            raise ValueError(f"bad tree node {str(node)[:60]}")
        float(node[1])
        walk(node[2])
        walk(node[3])

    walk(t)
    if sorted(seen) != list(range(n)):
        raise ValueError("the tree must hold every shard index once")
    return t


def front_to_back(tree, eye) -> list[int]:
    """Shard indices in an order in which no shard's cell lies behind a later one's, seen from ``eye``
    [3] (the k-d cells are convex: at each split the side holding the eye comes first)."""
    out: list[int] = []

    def walk(node) -> None:
        if isinstance(node, int):
            out.append(node)
            return
        axis, plane, left, right = node
        near, far = (left, right) if float(eye[axis]) < float(plane) else (right, left)
        walk(near)
        walk(far)

    walk(tree)
    return out


def _json_float(x: float) -> float | str:
    return x if np.isfinite(x) else ("inf" if x > 0 else "-inf")


def is_sharded(folder: str | Path) -> bool:
    """Whether ``folder`` holds a sharded scene (a shards.json)."""
    return (Path(folder) / SHARDS_FILE).is_file()


def kd_split(means: np.ndarray, k: int) -> tuple[list[np.ndarray], list[np.ndarray], object]:
    """Split points [N,3] into k cells of balanced size (sizes differ by at most one... per level).

    Each cell is cut across its widest axis at the rank that gives the two halves k//2 and k - k//2
    cells' worth of points; ties in a coordinate are broken by index, so the split is reproducible.
    Returns (per cell: ascending point indices [n_i] int64, per cell: [6] float64 box min xyz, max xyz,
    unbounded where the cell reaches the scene's outside, the tree: a cell index or [axis, plane, left,
    right] with the left side's coordinates <= plane <= the right side's).
    """
    if not 1 <= k <= MAX_SHARDS:
        raise ValidationError("shards", f"must be in 1..{MAX_SHARDS}, got {k}")
    means = np.asarray(means, np.float64)
    if len(means) < k:
        raise ValidationError("shards", f"{k} shards for {len(means)} Gaussians: at most one shard each")
    cells, boxes = [], []

    def split(idx: np.ndarray, box: np.ndarray, k: int):
        if k == 1:
            cells.append(np.sort(idx))
            boxes.append(box)
            return len(cells) - 1
        p = means[idx]
        axis = int(np.argmax(p.max(0) - p.min(0)))
        order = idx[np.lexsort((idx, p[:, axis]))]  # by coordinate, ties by index
        kl = k // 2
        cut = len(idx) * kl // k
        left, right = order[:cut], order[cut:]
        plane = means[order[cut], axis]  # right cell: coordinate >= plane (ties may fall either side)
        lbox, rbox = box.copy(), box.copy()
        lbox[3 + axis] = plane
        rbox[axis] = plane
        a = split(left, lbox, kl)
        b = split(right, rbox, k - kl)
        return [axis, float(plane), a, b]

    tree = split(np.arange(len(means)), np.array([-np.inf] * 3 + [np.inf] * 3), k)
    return cells, boxes, tree


def write_shards(
    source: str | Path, out: str | Path, k: int, query_rank: int | None = None, query_rank2: int | None = None
) -> Path:
    """Split package ``source`` into ``k`` spatial shards under folder ``out`` (written atomically).

    query_rank: rank of each shard's compact query state (default: the source's, or 64); query_rank2: the
    total rank of its two tiers at most (default: the source's when it has a second tier, else 256).
    """
    from safetensors.torch import save_file

    source, out = Path(source), check_replaceable(out)
    if out.resolve() == source.resolve():
        raise ValidationError(str(out), "is the source package: the shards go to another folder")
    man = Manifest.read(source)
    g = load_gaussians(source / "gaussians.safetensors")
    efile = source / "embeddings.safetensors"
    t = read_tensors(efile, ("selected", "embeddings", "canonical"), "cpu")
    sel, emb, canon = t["selected"], t["embeddings"], t["canonical"]
    if emb.dtype != torch.float16 or sel.dtype != torch.int64:
        raise ValidationError(str(efile), "expected float16 embeddings and int64 selected indices")
    M = man.num_selected
    if (
        sel.shape != (M,)
        or emb.shape != (M, man.dim)
        or canon.shape[:1] != (M,)
        or g.num != man.num_gaussians
    ):
        raise ValidationError(str(source), "its tensors do not match its manifest's counts and dimension")
    if M and (int(sel.min()) < 0 or int(sel.max()) >= g.num):
        raise ValidationError(str(efile), f"selected indices must lie in [0, {g.num})")
    stored = None
    if (source / STATE_FILE).is_file():
        try:
            stored = load_state(source / STATE_FILE, len(sel), man.dim, fingerprint(efile))
        except ValidationError:
            pass  # stale state: the default ranks
    if query_rank is None:
        query_rank = 64 if stored is None else stored.rank
    if query_rank2 is None:
        query_rank2 = (
            TIER2_RANK if stored is None or stored.tier2 is None else stored.rank + stored.tier2.rank
        )
    means = g.means.detach().double().numpy()
    cells, boxes, tree = kd_split(means, k)
    row_of = np.full(g.num, -1, np.int64)  # source Gaussian -> its embedded row (or -1)
    row_of[sel.numpy()] = np.arange(len(sel))
    infos = []
    with scene_folder(out, "sharded scene") as tmp:
        for i, (cell, box) in enumerate(zip(cells, boxes, strict=True)):
            folder = f"shard-{i:03d}"
            d = tmp / folder
            d.mkdir()
            gi = torch.from_numpy(cell)
            save_gaussians(g.subset(gi), d / "gaussians.safetensors")
            rows = row_of[cell]
            local_sel = np.flatnonzero(rows >= 0)  # local Gaussian of each shard row, ascending
            rows = rows[local_sel]
            # Source rows in ascending order keep the source's tie order (ties go by row).
            order = np.argsort(rows, kind="stable")
            rows, local_sel = rows[order], local_sel[order]
            r = torch.from_numpy(rows)
            e = emb[r].contiguous()
            save_file(
                {
                    "selected": torch.from_numpy(local_sel).to(torch.int64).contiguous(),
                    "embeddings": e,
                    "canonical": canon[r].contiguous(),
                },
                str(d / "embeddings.safetensors"),
            )
            save_file(
                {"gaussians": gi.to(torch.int64).contiguous(), "rows": r.to(torch.int64).contiguous()},
                str(d / IDS_FILE),
            )
            if 0 < query_rank < man.dim and len(rows):
                state = build_state(e.float(), query_rank, rank2=query_rank2)
                save_state(state, d / STATE_FILE, fingerprint(d / "embeddings.safetensors"))
            if man.field is not None:
                shutil.copyfile(source / "field.safetensors", d / "field.safetensors")
            sub_means = means[cell]
            Manifest(
                **{
                    **man.__dict__,
                    "name": folder,
                    "num_gaussians": len(cell),
                    "num_selected": len(rows),
                    "bounds": tuple(float(v) for v in np.concatenate([sub_means.min(0), sub_means.max(0)])),
                    "extra": {**man.extra, "shard_of": man.name, "shard": i, "shards": k},
                }
            ).write(d)
            infos.append(ShardInfo(folder, len(cell), len(rows), tuple(float(v) for v in box)))
        lo, hi = np.percentile(means, [1, 99], axis=0) if len(means) else (np.zeros(3), np.zeros(3))
        sm = ShardManifest(
            man.name,
            man.encoder_id,
            man.dim,
            g.num,
            len(sel),
            tuple(float(v) for v in np.concatenate([lo, hi])),
            tuple(infos),
            tree,
        )
        (tmp / SHARDS_FILE).write_text(json.dumps(sm.to_dict(), indent=1))
    return out


def read_shard_ids(
    folder: str | Path, num_gaussians: int, num_selected: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The source indices of a shard's Gaussians [n] and embedded rows [m] (int64), checked."""

    path = Path(folder) / IDS_FILE
    t = read_tensors(path, ("gaussians", "rows"), "cpu")
    gi, rows = t["gaussians"], t["rows"]
    if gi.dtype != torch.int64 or gi.shape != (num_gaussians,) or rows.dtype != torch.int64:
        raise ValidationError(str(path), f"expected int64 gaussians [{num_gaussians}] and rows")
    if rows.shape != (num_selected,):
        raise ValidationError(str(path), f"expected [{num_selected}] rows, got {list(rows.shape)}")
    return gi, rows


def shard_folders(folder: str | Path) -> list[Path]:
    """The package folders of a sharded scene, in shard order (each checked to hold a manifest)."""
    folder = Path(folder)
    sm = ShardManifest.read(folder)
    out = []
    for s in sm.shards:
        p = folder / s.folder
        if not (p / FILENAME).is_file():
            raise ValidationError(str(p), "shard listed in shards.json is missing")
        out.append(p)
    return out
