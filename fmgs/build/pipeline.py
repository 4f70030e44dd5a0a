"""Every stage from photos (or a posed dataset, or a 3DGS .ply with its posed images) to a scene package.

Before the first stage, every model the build loads (CLIP, DINO, the text encoder) is found in the hub
cache or downloaded, and checked (fmgs.features.registry.resolve_encoders): one error names every model
that is missing, before any work. The revisions found are kept in WORK/models.json; the stages load
exactly those, a later run of the same build too (unless ``allow_newer_model``), and the manifest records
each model's revision and the sha256 of its files (``extra.models``).

Stages, each skipped when its output is already complete in the work folder:
  1 poses     photos -> pycolmap SfM -> WORK/sfm/undistorted   (skipped for a posed dataset; redone, and
              the later stages with it, when the photos or the SfM settings changed)
              a ROS 2 recording -> poses from tf -> WORK/recording (SfM when it has no usable tf)
  2 geometry  3DGS training -> WORK/gs/point_cloud.ply         (skipped when a .ply is given)
  3 features  targets -> WORK/features (CLIP + DINO, or label masks) (resumes per image)
  4 field     distillation -> WORK/field                        (resumes from its checkpoint)
  5 package   models/<name>
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import replace
from pathlib import Path

import torch

from fmgs.build.config import EMBEDDING_NEIGHBOURS, MAX_EMBEDDING_NEIGHBOURS, BuildConfig, TargetSpec
from fmgs.data.dataset import load_dataset
from fmgs.data.rosbag import (
    ImportResult,
    completed_import,
    import_recording,
    is_recording,
    source_fingerprint,
)
from fmgs.errors import ValidationError
from fmgs.features.cache import FeatureCache
from fmgs.features.clip import load_image_encoder
from fmgs.features.dino import load_dense_encoder
from fmgs.features.distributed import TargetJob, extract_features_ray
from fmgs.features.extract import ExtractConfig, extract_labels, extract_targets, read_label_names
from fmgs.features.models import DEFAULT_REVISION, ModelFiles, ModelPin
from fmgs.features.pyramid import spec_pyramid
from fmgs.features.registry import query_encoder_id, resolve_encoders
from fmgs.features.standin_seg import load_segmenter
from fmgs.features.text import load_text_encoder
from fmgs.field.model import FeatureField
from fmgs.field.neighbours import neighbour_mean, reach_of
from fmgs.gaussians import GaussianSet
from fmgs.io.atomic import atomic_path
from fmgs.io.ply import read_ply
from fmgs.query.relevancy import CANONICAL_PHRASES
from fmgs.scene.package import check_replaceable, check_scene_name, export_scene
from fmgs.sfm import completed_sfm, run_sfm
from fmgs.train.evaluate import LOW_VIEW_PSNR_DB, evaluate
from fmgs.train.field import FieldTrainResult, train_field
from fmgs.train.floaters import floater_mask
from fmgs.train.gaussians import config_record, dataset_background, train_gaussians, trained_background
from fmgs.train.threads import auto_threads

log = logging.getLogger(__name__)


def package_from_field(
    out: str | Path,
    gaussians: GaussianSet,
    result: FieldTrainResult,
    encoder,
    include_dino: bool = False,
    extra: dict | None = None,
    field_dtype: str = "float32",
    neighbours: int = EMBEDDING_NEIGHBOURS,
) -> Path:
    """Decode each selected Gaussian's embedding once, average it over its ``neighbours`` nearest
    selected Gaussians within its reach (fmgs.field.neighbours; 1: none) and write the scene package
    to ``out`` (``field_dtype``: storage of the field's tensors, see ``export_scene``). The manifest's
    extra records ``embedding_neighbours``."""

    if not 1 <= neighbours <= MAX_EMBEDDING_NEIGHBOURS:
        raise ValidationError(
            "embedding neighbours", f"must lie in [1, {MAX_EMBEDDING_NEIGHBOURS}], got {neighbours}"
        )
    g = gaussians.subset(result.selection.index)
    model = result.model.cpu()
    with torch.no_grad():
        if isinstance(model, FeatureField):
            emb = model(g.means.float(), dino=False).clip
            field = model
        else:
            emb = model.decode_index(torch.arange(g.num), dino=False).clip
            field = None
        canon = encoder.encode_text(list(CANONICAL_PHRASES)).float().cpu()
    emb = neighbour_mean(g.means, reach_of(g.scales), emb, neighbours, workers=torch.get_num_threads())
    return export_scene(
        out,
        gaussians,
        result.selection.index,
        emb,
        encoder.id,
        canon,
        field=field,
        include_dino=include_dino,
        extra={**(extra or {}), "embedding_neighbours": neighbours},
        field_dtype=field_dtype,
    )


def _stage(i: int, name: str, msg: str) -> None:
    print(f"[{i}/5] {name}: {msg}", flush=True)


def _is_dataset(path: Path) -> bool:
    return (path / "transforms.json").is_file() or any(
        (path / s).is_dir() for s in ("sparse/0", "sparse", "colmap/sparse/0")
    )


TARGETS_RECORD = "targets.json"
"""The target settings (TargetSpec) the work folder's feature cache and field were made with."""


def restart_on_new_targets(work: Path, spec: TargetSpec) -> bool:
    """Remove WORK/features and WORK/field when WORK/targets.json records other target settings than
    ``spec`` (the cache resumes by file, so a changed blend or segmenter would otherwise be distilled from
    the old maps); then record ``spec``. Returns whether anything was removed. A work folder without a
    record (made before it existed) is trusted as it is, and a setting its record lacks (added to
    TargetSpec since) is taken at its default, which is what that record's build ran."""
    import shutil

    path = work / TARGETS_RECORD
    now = json.loads(json.dumps(dataclasses.asdict(spec)))
    before = json.loads(path.read_text()) if path.is_file() else None
    if before is not None:
        fields = dataclasses.fields(TargetSpec)
        defaults = {f.name: f.default for f in fields if f.default is not dataclasses.MISSING}
        before = {**json.loads(json.dumps(defaults)), **before}
    removed = False
    if before is not None and before != now:
        for d in (work / "features", work / "field"):
            if d.exists():
                shutil.rmtree(d)
                removed = True
    work.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(now, indent=1))
    return removed


WORK_MODELS = "models.json"
"""The models a build resolved, {role: {encoder, id, revision, files}}, in its work folder: a later run
of the same build loads these revisions (its stages reuse what the earlier run made with them)."""


def build_models(spec: TargetSpec) -> dict[str, str]:
    """{role: encoder id} of every model a build with ``spec`` loads: "text_encoder" (label names, or
    the queries a CLIP-target scene answers), and for CLIP targets "clip" and "dino" (when it has one)."""

    if spec.kind == "labels":
        return {"text_encoder": spec.text_encoder}
    out = {"clip": spec.clip_model}
    if spec.dino_model:
        out["dino"] = spec.dino_model
    if spec.segmenter:
        out["segmenter"] = spec.segmenter
    out["text_encoder"] = query_encoder_id(spec.clip_model)
    return out


def resolve_build_models(
    spec: TargetSpec,
    work: Path | None = None,
    offline: bool | str | None = None,
    allow_newer_model: bool = False,
) -> dict[str, ModelFiles]:
    """{role: ModelFiles} of every model a build with ``spec`` loads (build_models), found or downloaded
    and checked now, every missing one named in one error. With a ``work`` folder, the revisions an
    earlier run recorded in WORK/models.json are the ones taken (unless ``allow_newer_model``), and the
    ones taken are recorded there."""

    named = build_models(spec)
    path = Path(work) / WORK_MODELS if work is not None else None
    pins: dict[str, ModelPin] = {}
    if path is not None and path.is_file() and not allow_newer_model:
        try:
            recorded = json.loads(path.read_text())
        except (OSError, ValueError):
            recorded = {}
        for role, encoder_id in named.items():
            rec = recorded.get(role) if isinstance(recorded, dict) else None
            if isinstance(rec, dict) and rec.get("encoder") == encoder_id:
                if (pin := ModelPin.from_record(rec)) is not None:
                    pins[role] = pin
    resolved = resolve_encoders(
        named, offline=offline, pins=pins,
        pinned_by=f"an earlier run of this build used ({path}); --allow-newer-model takes the current one",
    )  # fmt: skip
    if path is not None:
        with atomic_path(path) as tmp:
            records = {role: {"encoder": named[role], **f.record()} for role, f in resolved.items()}
            tmp.write_text(json.dumps(records, indent=1))
    return resolved


def model_revisions(spec: TargetSpec, resolved: dict[str, ModelFiles]) -> dict[str, str]:
    """{encoder id: hub revision} of the resolved models that come from the hub (the stages load these)."""
    named = build_models(spec)
    return {named[role]: f.revision for role, f in resolved.items() if f.revision}


def _models_line(resolved: dict[str, ModelFiles]) -> str:
    parts = []
    for role, f in resolved.items():
        at = f"@{f.revision[:12]}" if f.revision else ""
        parts.append(f"{role} {f.model_id}{at} ({f.source})")
    return "models: " + "; ".join(parts)


def extract_features(
    ds,
    cache_dir: Path,
    spec: TargetSpec,
    device: str,
    progress: bool = True,
    revisions: dict[str, str] | None = None,
):
    """Fill ``cache_dir`` with the targets ``spec`` names (resuming); returns the FeatureCache.
    ``revisions`` ({encoder id: hub revision}, model_revisions) pins the models loaded."""

    rev = revisions or {}
    ecfg = ExtractConfig(
        feature_scale=spec.feature_scale, feature_side=spec.feature_side, device=device, progress=progress
    )
    if spec.kind == "labels":
        names = read_label_names(spec.names or ds.root / "scene.json")
        text_rev = rev.get(spec.text_encoder, DEFAULT_REVISION)
        enc = load_text_encoder(spec.text_encoder, device=device, revision=text_rev)
        return extract_labels(ds, cache_dir, spec.labels or ds.root / "labels", names, enc, cfg=ecfg)
    if spec.kind != "clip":
        raise ValidationError("targets", f"unknown target kind {spec.kind!r}; choose 'clip' or 'labels'")

    clip = load_image_encoder(
        spec.clip_model, device=device, revision=rev.get(spec.clip_model, DEFAULT_REVISION)
    )
    dino = None
    if spec.dino_model:
        dino = load_dense_encoder(
            spec.dino_model, device, revision=rev.get(spec.dino_model, DEFAULT_REVISION)
        )
    seg = None
    if spec.segmenter:
        seg = load_segmenter(spec.segmenter, device, revision=rev.get(spec.segmenter, DEFAULT_REVISION))
    return extract_targets(ds, cache_dir, clip, dino, spec_pyramid(clip, spec), ecfg, segmenter=seg)


LOW_PSNR_DB = LOW_VIEW_PSNR_DB
"""Held-out PSNR below which the build warns: the mean (the geometry is poor, the field can only be as
good), and each held-out view (the geometry fails from there, whatever the mean)."""


GEOMETRY_REPORT = "geometry.json"
"""The geometry's held-out scores, written in the build's work folder."""


def _import_recording(source: Path, work: Path, cfg: BuildConfig) -> ImportResult:
    """The recording's keyframes as a dataset in WORK/recording (reused when the files and settings are
    the same as the last import's)."""
    out = work / "recording"
    fp = source_fingerprint(source)
    done = completed_import(out, cfg.recording, fp)
    if done is not None:
        return done
    _stage(1, "poses", f"reading the recording {source}")
    return import_recording(source, out, cfg.recording, fp)


def _forget_posed_stages(work: Path) -> None:
    """Remove what an earlier run made from other poses (WORK/gs, features, field) before SfM runs:
    stages 2 to 4 resume by their settings alone, so they would carry on from the old poses."""
    import shutil

    old = [d for d in (work / "gs", work / "features", work / "field") if d.exists()]
    for d in old:
        shutil.rmtree(d)
    if old:
        _stage(1, "poses", "new poses: the geometry, features and field of the last run start over")


def _report_geometry(gaussians, ds, cfg: BuildConfig, work: Path, background, rec=None) -> None:
    """Print the geometry's held-out PSNR/SSIM (every HOLDOUT_EVERY-th view; the mean and the worst view)
    and the floaters it leaves (fmgs.train.floaters), and store them in WORK/geometry.json with every view's;
    warn naming each view below LOW_PSNR_DB, and when the mean is."""

    train, test = ds.split(cfg.gs.holdout_every)
    if not test:
        _stage(2, "geometry", "no held-out views to score")
        return
    r = evaluate(gaussians, ds, None, cfg.gs.image_scale, background, cfg.gs.holdout_every)
    n = f"{gaussians.num:,} Gaussians"
    w = r.worst
    _stage(
        2, "geometry",
        f"{n}; held-out PSNR {r.psnr:.2f} dB, SSIM {r.ssim:.3f} ({len(test)} views; worst {w['name']} "
        f"{w['psnr']:.2f} dB)",
    )  # fmt: skip
    _, floaters = floater_mask(gaussians, ds, train)
    _stage(2, "geometry", floaters.line())
    scores = {**r.summary(LOW_PSNR_DB), "views": len(test), "gaussians": gaussians.num}
    scores["floaters"] = floaters.summary()
    if rec is not None:  # how the recording's frames were chosen
        scores["recording"] = {k: v for k, v in dataclasses.asdict(rec).items() if k != "dataset"}
    with atomic_path(work / GEOMETRY_REPORT) as tmp:
        tmp.write_text(json.dumps(scores, indent=1))
    if r.warning(LOW_PSNR_DB):
        log.warning("%s", r.warning(LOW_PSNR_DB))
    if r.psnr < LOW_PSNR_DB:
        log.warning(
            "held-out PSNR %.1f dB is below %.0f dB: the geometry is poor, and the feature field will be too "
            "(no sparse points? too few steps? wrong poses?)", r.psnr, LOW_PSNR_DB,
        )  # fmt: skip


def build_scene(
    source: str | Path,
    cfg: BuildConfig,
    progress: bool = True,
    *,
    offline: bool | str | None = None,
    allow_newer_model: bool = False,
) -> Path:
    """Run the stages for ``source`` (a photo folder or a posed dataset) and return the package path.

    The models come first (resolve_build_models): found, or downloaded unless ``offline`` (True, or the
    words naming the flag that said so), before any stage; ``allow_newer_model`` takes their current
    revisions even where an earlier run of this build recorded others."""

    check_scene_name(cfg.name)
    check_replaceable(Path(cfg.models) / cfg.name)  # refused now, not after hours of training
    source = Path(source)
    # "auto" threads are counted once, before any stage: counted at each stage, the load of the build's
    # own 3DGS stage left its field stage one thread on an otherwise idle 2-core machine.
    threads = auto_threads()
    recording = is_recording(source)
    if not source.is_dir() and not recording:
        raise ValidationError(
            "source",
            f"{source} is not a folder (photos or a posed dataset) or a ROS 2 recording (.mcap, .db3)",
        )
    work = Path(cfg.work) if cfg.work else Path(cfg.models) / ".work" / cfg.name
    for what, folder in (("model repository", Path(cfg.models)), ("work folder", work)):
        try:  # before any stage: a file in the way, or no permission, would stop the build at its end
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValidationError(what, f"cannot create {folder} ({e})") from e
    t0 = time.perf_counter()
    models = resolve_build_models(cfg.targets, work, offline, allow_newer_model)
    revisions = model_revisions(cfg.targets, models)
    print(_models_line(models), flush=True)

    rec = None
    if recording:
        rec = _import_recording(source, work, cfg)
        data = Path(rec.dataset)
        _stage(1, "poses", rec.line())
        if not rec.posed:
            _stage(
                1,
                "poses",
                "the scene's frame will be SfM's, not the robot's: answers need aligning to its map",
            )
            sfm_data = completed_sfm(data / "images", work / "sfm", cfg.sfm)
            if sfm_data is not None and _is_dataset(sfm_data):
                data = sfm_data
            else:
                _forget_posed_stages(work)
                data = Path(run_sfm(data / "images", work / "sfm", cfg.sfm).dataset_dir)
    elif _is_dataset(source):
        _stage(1, "poses", f"posed dataset {source}")
        data = source
    else:
        data = completed_sfm(source, work / "sfm", cfg.sfm)
        if data is not None and _is_dataset(data):  # the same photos and settings as the last run's
            _stage(1, "poses", f"complete ({data})")
        else:
            _stage(1, "poses", f"pycolmap SfM on {source}")
            _forget_posed_stages(work)
            r = run_sfm(source, work / "sfm", cfg.sfm)
            data = Path(r.dataset_dir)
    ds = load_dataset(data)
    if not cfg.ply and (ds.points is None or len(ds.points) < 4) and not cfg.allow_random_init:
        raise ValidationError(
            str(data),
            "has no sparse points to start the 3DGS stage from (random starts trained 6 dB below points on "
            "a synthetic tabletop); give the dataset points (COLMAP points3D, or a transforms.json "
            "ply_file_path), build from the photos so that structure from motion makes them, pass a 3DGS "
            "scene trained elsewhere with --ply, or accept random Gaussians with --allow-random-init",
        )

    if cfg.ply:
        _stage(2, "geometry", f"given {cfg.ply}")
        ply = Path(cfg.ply)
    else:
        gcfg = replace(cfg.gs, device=cfg.device, threads=cfg.gs.threads or threads)
        ply = work / "gs" / "point_cloud.ply"
        done = work / "gs" / "train.json"
        record = json.loads(done.read_text()) if ply.is_file() and done.is_file() else {}
        if record.get("config") == config_record(gcfg):  # same steps and settings
            _stage(2, "geometry", f"complete ({ply})")
        else:
            _stage(2, "geometry", f"3DGS, {gcfg.steps} steps")
            # A finished run with other settings starts over; an interrupted one (no train.json) resumes.
            train_gaussians(ds, work / "gs", gcfg, progress=progress, resume=not record)
    gaussians = read_ply(ply)
    if gaussians.num == 0:
        raise ValidationError(str(ply), "holds no Gaussians: there is no geometry to distil features into")

    # A given .ply is scored on the dataset's background; our own run on the one it trained with.
    background = dataset_background(ds) if cfg.ply else trained_background(ply.parent, ds)
    _report_geometry(gaussians, ds, cfg, work, background, rec)

    cache_dir = work / "features"
    _stage(3, "features", f"{cfg.targets.kind} targets -> {cache_dir}")
    if restart_on_new_targets(work, cfg.targets):
        _stage(3, "features", "the targets' settings changed since the last run: cache and field start over")
    if cfg.ray:
        job = TargetJob(str(data), cfg.targets, cfg.device, revisions=tuple(sorted(revisions.items())))
        extract_features_ray(job, cache_dir, None if cfg.ray == "local" else cfg.ray, progress=progress)
    else:
        extract_features(ds, cache_dir, cfg.targets, cfg.device, progress, revisions)
    cache = FeatureCache.open(cache_dir)

    fcfg = replace(cfg.field, device=cfg.device, threads=cfg.field.threads or threads)
    done = work / "field" / "field_train.json"
    complete = done.is_file() and json.loads(done.read_text()).get("steps") == fcfg.steps
    _stage(
        4, "field", "complete (loading the checkpoint)" if complete else f"{fcfg.steps} steps on {cfg.device}"
    )
    res = train_field(gaussians, ds, cache, work / "field", fcfg, progress=progress)

    out = Path(cfg.models) / cfg.name
    _stage(5, "package", str(out))
    query_id = cache.targets["clip"].encoder
    encoder = load_text_encoder(query_id, device="cpu", revision=revisions.get(query_id, DEFAULT_REVISION))
    extra = {"source": str(source), "build_seconds": round(time.perf_counter() - t0, 1)}
    extra["targets"] = dataclasses.asdict(cfg.targets)  # how the targets were made: kind, models, pyramid
    extra["targets"]["text_encoder"] = encoder.id  # the one that answers queries (CLIP's own for CLIP)
    extra["models"] = {role: f.record() for role, f in models.items()}  # revisions, sha256 of the bytes
    if getattr(encoder, "files", None) is not None:  # the query encoder: id, revision, file hashes
        extra["text_encoder"] = encoder.files.record()
    if rec is not None:
        extra["recording"] = {k: v for k, v in dataclasses.asdict(rec).items() if k != "dataset"}
        if rec.posed:  # positions are the robot's: its fixed frame, metres
            extra["frame"] = {"id": rec.fixed_frame, "units": "m", "camera_frame": rec.camera_frame}
    if cfg.targets.kind == "labels":
        extra["label_names"] = read_label_names(cfg.targets.names or ds.root / "scene.json")
    extra.update(cfg.extra)
    return package_from_field(
        out, gaussians, res, encoder, cfg.include_dino, extra, cfg.field_dtype, cfg.embedding_neighbours
    )
