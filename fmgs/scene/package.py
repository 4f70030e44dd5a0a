"""Scene packages (``models/<scene>/``): only what serving needs, validated on load.

Layout:
  manifest.json            format, version, name, encoder {id, dim}, canonical phrases, counts, field config
                           (fmgs.scene.manifest: the one reader and writer)
  gaussians.safetensors    the frozen 3DGS geometry and SH of every Gaussian (fmgs.io.tensors format)
  embeddings.safetensors   selected [M] int64 (indices into the Gaussians), embeddings [M,D] float16
                           (decoded once, unit norm before rounding), canonical [M,C] float32 (the
                           stored embeddings' dot products with the canonical phrases)
  query_state.safetensors  the compact query state (fmgs.query.state): rank-r int8 codes of the embeddings
                           and the norms that bound their error, so a server opens the scene without
                           rebuilding it; absent in packages from before it (built in memory at load)
  field.safetensors        hash-grid keys and table, language head (and DINO head only if asked), so the
                           field can be queried at arbitrary 3D points; absent for the per-Gaussian ablation.
                           Its floating-point tensors are float32, or float16 where the manifest's
                           field.dtype says so (smaller packages; upcast to float32 on load)
No optimiser state, no training images, no targets.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch

from fmgs.checks import check_finite, first_bad_row
from fmgs.errors import FmgsError, ValidationError
from fmgs.field.bounds import SceneBounds
from fmgs.field.hashgrid import HashGrid
from fmgs.field.model import FeatureField, FieldConfig
from fmgs.gaussians import GaussianSet
from fmgs.io.atomic import atomic_dir
from fmgs.io.mmap_tensors import mmap_torch
from fmgs.io.tensor_stream import save_blocks
from fmgs.io.tensors import load_gaussians, save_gaussians
from fmgs.query.state import STATE_FILE, QueryState, build_state, fingerprint, load_state, save_state
from fmgs.scene.manifest import CANONICAL_PHRASES, FILENAME, SHARDS_FILE, FieldInfo, Manifest

FIELD_DTYPES = {"float32": torch.float32, "float16": torch.float16}
"""Storage dtypes of the field's floating-point tensors (a manifest without field.dtype means float32)."""
_SCENE_FILES = (FILENAME, SHARDS_FILE, "gaussians.safetensors", "embeddings.safetensors")
"""A folder holding any of these is a scene (a package or a sharded scene) that a write may replace."""
_INDEX_DTYPES = (torch.int64, torch.int32, torch.int16, torch.int8, torch.uint8)
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


@dataclass
class ScenePackage:
    """A loaded scene."""

    name: str
    """Scene name (the folder name)."""
    manifest: Manifest
    """The manifest as read (validated)."""
    gaussians: GaussianSet
    """All Gaussians (geometry for rendering)."""
    selected: torch.Tensor
    """[M] int64 indices of the Gaussians that carry embeddings."""
    embeddings: torch.Tensor
    """[M,D] float32 embeddings (stored float16)."""
    canonical: torch.Tensor
    """[M,C] float32 dot products with the canonical phrases."""
    field: FeatureField | None
    """The field for queries at arbitrary points (None if the package has none)."""
    query_state: QueryState | None = None
    """The stored compact query state (loaded with ``mmap``; None when absent or stale)."""

    @property
    def encoder_id(self) -> str:
        return self.manifest.encoder_id

    @property
    def dim(self) -> int:
        return self.manifest.dim

    @property
    def canonical_phrases(self) -> list[str]:
        return list(self.manifest.canonical)


def check_scene_name(name: str) -> str:
    """Scene names are folder names: letters, digits, '.', '_', '-', not starting with '.'."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValidationError(
            "scene name", f"{shown_name(name)} is not a valid name (letters, digits, . _ -; max 128)"
        )
    return name


def shown_name(name, limit: int = 64) -> str:
    """repr of a (possibly hostile) name, cut to ``limit`` characters for messages and metadata."""
    text = repr(name if isinstance(name, str) else str(type(name)))
    return text if len(text) <= limit else text[: limit - 4] + "...'"


def check_replaceable(out: str | Path) -> Path:
    """``out`` as a Path, when a scene may be written there: nothing there yet, an empty folder, or a
    scene to replace (a folder holding a package's or a sharded scene's files, damaged or not);
    ValidationError otherwise, so a mistyped path never deletes a file or a folder of other things (a
    dataset, the whole scene repository)."""
    out = Path(out)
    if not out.exists():
        return out
    if out.is_dir():
        if any((out / f).is_file() for f in _SCENE_FILES) or not any(out.iterdir()):
            return out
        what = "a folder that holds no scene package"
    else:
        what = "a file"
    raise ValidationError(
        str(out), f"exists and is {what}: a scene is not written over it (remove it or choose another path)"
    )


class SceneWriteError(FmgsError, OSError):
    """A scene could not be written (disk full, no permission); the message names its folder, and what
    was there is left as it was."""


@contextlib.contextmanager
def scene_folder(out: Path, what: str) -> Iterator[Path]:
    """fmgs.io.atomic.atomic_dir(out) for a scene (``what`` names it in errors): refused where
    check_replaceable refuses, and a write that fails raises SceneWriteError naming ``out``, with what
    was there left as it was and nothing half-written."""
    from safetensors import SafetensorError

    check_replaceable(out)
    try:
        with atomic_dir(out) as tmp:
            yield tmp
    except (OSError, SafetensorError) as e:
        raise SceneWriteError(
            f"{out}: writing the {what} failed ({e}); what was there is left as it was"
        ) from e


@torch.no_grad()
def export_scene(
    out: str | Path,
    gaussians: GaussianSet,
    selected: torch.Tensor,
    embeddings: torch.Tensor,
    encoder_id: str,
    canonical_embeddings: torch.Tensor,
    field: FeatureField | None = None,
    include_dino: bool = False,
    canonical_phrases: tuple[str, ...] = CANONICAL_PHRASES,
    extra: dict | None = None,
    field_dtype: str = "float32",
    query_rank: int = 64,
    query_rank2: int = 256,
) -> Path:
    """Write a package to folder ``out`` (replaced atomically) and return it.

    selected [M] indices into ``gaussians``; embeddings [M,D] decoded per selected Gaussian (float32,
    unit norm); canonical_embeddings [C,D] the encoder's embeddings of ``canonical_phrases``.
    field_dtype: storage of the field's table and heads, "float32" (exact) or "float16" (half the size;
    the stored embeddings are decoded before rounding, so only queries at arbitrary points see it).
    query_rank: basis size of the stored compact query state (0: none; servers then build it at load).
    query_rank2: total rank of its two tiers at most (fmgs.query.state; 0: first tier only).
    """
    out = check_replaceable(out)
    check_scene_name(out.name)
    gaussians.validate()  # Gaussians load_scene refuses are never written (nor swapped in for a good package)
    if field_dtype not in FIELD_DTYPES:
        raise ValidationError("field_dtype", f"{field_dtype!r} is not one of {sorted(FIELD_DTYPES)}")
    M, D = embeddings.shape
    if selected.shape != (M,) or selected.dtype not in _INDEX_DTYPES:
        raise ValidationError(
            "selected", f"expected [{M}] integer indices, got {selected.dtype} {list(selected.shape)}"
        )
    if M and (int(selected.min()) < 0 or int(selected.max()) >= gaussians.num):
        raise ValidationError("selected", f"indices must lie in [0, {gaussians.num}) (the Gaussians)")
    if canonical_embeddings.shape != (len(canonical_phrases), D):
        raise ValidationError("canonical_embeddings", f"expected [{len(canonical_phrases)},{D}]")
    check_finite("embeddings", embeddings)
    canon = _canonical_dots(embeddings, canonical_embeddings.detach().float().cpu())
    from safetensors.torch import save_file

    field_info = None
    with scene_folder(out, "scene package") as tmp:
        save_gaussians(gaussians, tmp / "gaussians.safetensors")
        efile = tmp / "embeddings.safetensors"
        # Written and read back in blocks: a large scene's embeddings are never copied whole (a 10M x
        # 512 scene would need 20 GB for a float32 copy and 10 GB more for its bytes).
        save_blocks(
            efile,
            {
                "selected": (selected, torch.int64),
                "embeddings": (embeddings, torch.float16),
                "canonical": canon,
            },
        )
        if 0 < query_rank < D and M > 0:
            state = build_state(mmap_torch(efile, "embeddings"), query_rank, rank2=query_rank2)
            save_state(state, tmp / STATE_FILE, fingerprint(efile))
        if field is not None:
            fdt = FIELD_DTYPES[field_dtype]
            state = {
                k: (v.to(fdt) if v.is_floating_point() else v).detach().cpu().contiguous()
                for k, v in field.state_dict().items()
                if include_dino or not k.startswith("dino_head.")
            }
            for k, v in state.items():
                if v.is_floating_point():
                    check_finite(f"field {k} as {field_dtype}", v)  # float16 overflows beyond 65504
            save_file(state, str(tmp / "field.safetensors"))
            field_info = FieldInfo(
                field.cfg.to_dict(),
                field.bounds.to_dict(),
                include_dino and field.dino_head is not None,
                field_dtype,
            )
        Manifest(
            name=out.name,
            encoder_id=encoder_id,
            dim=D,
            canonical=tuple(canonical_phrases),
            num_gaussians=gaussians.num,
            num_selected=M,
            sh_degree=gaussians.sh_degree,
            bounds=tuple(_bounds(gaussians.means)),
            field=field_info,
            extra=dict(extra or {}),
        ).write(tmp)
    return out


def _canonical_dots(embeddings: torch.Tensor, canonical: torch.Tensor, block: int = 1 << 16) -> torch.Tensor:
    """[M,C] float32 dots of the stored (float16-rounded) embeddings [M,D] with canonical [C,D], a block
    of rows at a time: the precomputed channels equal what a query computes from the stored rows."""
    out = torch.empty(embeddings.shape[0], canonical.shape[0])
    for s in range(0, embeddings.shape[0], block):
        h = embeddings[s : s + block].detach().cpu().half()
        row = first_bad_row(~torch.isfinite(h))
        if row is not None:
            raise ValidationError("embeddings", "exceeds the float16 range the package stores", s + row)
        out[s : s + block] = h.float() @ canonical.T
    return out


def _bounds(means: torch.Tensor) -> list[float]:
    """[min x, min y, min z, max x, max y, max z] of the means (zeros for an empty scene)."""
    if means.shape[0] == 0:
        return [0.0] * 6
    m = means.detach().double().cpu()
    return [float(v) for v in torch.cat([m.amin(0), m.amax(0)])]


def load_scene(path: str | Path, device: str | torch.device = "cpu", mmap: bool = False) -> ScenePackage:
    """Read and validate a package; ValidationError names the file and what is wrong.

    ``mmap``: leave the embeddings in the file as a float16 memory map (CPU; pages load on touch), for
    servers that keep only a compact query state in memory (fmgs.query.index).
    """

    if mmap and torch.device(device).type != "cpu":
        raise ValidationError("device", "memory-mapped embeddings live on the CPU")
    path = Path(path)
    manifest = Manifest.read(path)
    D, C = manifest.dim, len(manifest.canonical)

    gaussians = load_gaussians(path / "gaussians.safetensors", device)
    gaussians.validate()
    efile = path / "embeddings.safetensors"
    t = read_tensors(efile, ("selected", *(() if mmap else ("canonical", "embeddings"))), device)
    sel = t["selected"]
    if mmap:  # only the compact state is resident; pose renders page the canonical dots in
        emb, canon = _mmap_embeddings(efile), mmap_torch(efile, "canonical")
        if canon.dtype != torch.float32:
            raise ValidationError(str(efile), f"canonical must be float32, got {canon.dtype}")
    else:
        emb, canon = t["embeddings"].float(), t["canonical"].float()
    M = manifest.num_selected
    where = str(path / "embeddings.safetensors")
    if sel.dtype != torch.int64 or sel.shape != (M,):
        raise ValidationError(where, f"selected must be int64 [{M}], got {sel.dtype} {list(sel.shape)}")
    if emb.shape != (M, D):
        raise ValidationError(where, f"embeddings must be [{M},{D}] (manifest), got {list(emb.shape)}")
    if canon.shape != (M, C):
        raise ValidationError(where, f"canonical must be [{M},{C}], got {list(canon.shape)}")
    if M and (int(sel.min()) < 0 or int(sel.max()) >= gaussians.num):
        raise ValidationError(where, f"selected indices must lie in [0, {gaussians.num})")
    state = _load_state(path, M, D)
    if state is None or not mmap:
        # With a stored state the embeddings are read only where a query rescores them, and checked
        # there (fmgs.query.index.EmbeddingIndex.exact_dots): opening stays fast.
        for s0 in range(0, M, 65536):  # chunked: no float32 copy of a memory map
            check_finite(f"{where}: embeddings", emb[s0 : s0 + 65536])
    check_finite(f"{where}: canonical", canon)

    field = None
    if manifest.field is not None:
        field = _load_field(path / "field.safetensors", manifest.field, device)
        if field.cfg.clip_dim != D:
            raise ValidationError(
                str(path / "manifest.json"),
                f"field clip_dim {field.cfg.clip_dim} differs from encoder dim {D}",
            )
    return ScenePackage(manifest.name, manifest, gaussians, sel, emb, canon, field, state)


def _load_state(path: Path, M: int, D: int) -> QueryState | None:
    """The package's stored query state, or None (absent; or stale or damaged: logged, and the
    server builds one in memory)."""
    import logging

    fpath = path / STATE_FILE
    if not fpath.is_file():
        return None
    try:
        return load_state(fpath, M, D, fingerprint(path / "embeddings.safetensors"))
    except ValidationError as e:
        logging.getLogger(__name__).warning("%s; building the query state in memory instead", e)
        return None


def read_tensors(fpath: Path, keys: tuple[str, ...], device) -> dict[str, torch.Tensor]:
    """The named tensors of a safetensors file (only those are read)."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(fpath), framework="pt", device=str(device)) as f:
            have = set(f.keys())
            for key in keys:
                if key not in have:
                    raise ValidationError(str(fpath), f"missing tensor {key!r}")
            return {k: f.get_tensor(k) for k in keys}
    except (SafetensorError, OSError) as e:
        raise ValidationError(str(fpath), f"cannot read ({e})") from e


def _mmap_embeddings(fpath: Path) -> torch.Tensor:
    """[M,D] float16 tensor over a copy-on-write memory map of the stored embeddings."""

    a = mmap_torch(fpath, "embeddings")
    if a.dtype != torch.float16:
        raise ValidationError(str(fpath), f"embeddings must be float16, got {a.dtype}")
    return a


def _load_field(fpath: Path, meta: FieldInfo, device) -> FeatureField:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        cfg = FieldConfig.from_dict(meta.config)
        bounds = SceneBounds.from_dict(meta.bounds)
    except (KeyError, TypeError, ValueError) as e:
        raise ValidationError(str(fpath), f"bad field description in the manifest ({e})") from e
    if not meta.dino_head:
        cfg = FieldConfig(**{**cfg.__dict__, "dino_dim": 0})
    dtype = meta.dtype
    try:
        state = load_file(str(fpath), device=str(device))
    except (SafetensorError, OSError) as e:
        raise ValidationError(str(fpath), f"cannot read ({e})") from e
    if "grid.keys" not in state:
        raise ValidationError(str(fpath), "missing tensor 'grid.keys'")
    for k, v in state.items():
        if v.is_floating_point() and v.dtype != FIELD_DTYPES[dtype]:
            raise ValidationError(str(fpath), f"tensor {k!r} is {v.dtype}, the manifest says {dtype}")
    state = {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
    try:
        grid = HashGrid(cfg.grid, state["grid.keys"].cpu())
        model = FeatureField(cfg, bounds, grid)
        model.load_state_dict(state)
    except (ValueError, RuntimeError) as e:
        raise ValidationError(str(fpath), f"field tensors do not match the manifest ({e})") from e
    for k, v in state.items():
        if v.is_floating_point():
            check_finite(f"{fpath}: {k}", v)
    return model.to(device).eval()
