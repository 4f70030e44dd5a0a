"""Structure from motion with pycolmap: photos -> poses, sparse points and undistorted images.

SIFT extraction (one shared camera by default), exhaustive matching for small sets and sequential
matching for larger ones, incremental mapping, then undistortion to PINHOLE. The output folder is a
dataset ``load_dataset`` reads: ``OUT/undistorted/{images, sparse}``; COLMAP's own log is
``OUT/colmap.log``. Known intrinsics (SfMConfig.camera_params, shared, or intrinsics_file, per photo)
are COLMAP priors held fixed by bundle adjustment; the others start from EXIF's focal length when the
photos have one.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path

from fmgs.data.dataset import IMAGE_SUFFIXES
from fmgs.errors import FmgsError, ValidationError
from fmgs.io.atomic import atomic_path
from fmgs.io.capture import output_to
from fmgs.sfm.config import CAMERA_PARAMS, SfMConfig

log = logging.getLogger(__name__)


@dataclass
class SfMResult:
    dataset_dir: Path
    """Folder with images/ and sparse/ (undistorted, PINHOLE)."""
    registered: int
    """Photos with a pose."""
    total: int
    """Photos given."""
    points: int
    """Triangulated 3D points."""
    mean_reprojection_error: float
    """Mean reprojection error in pixels."""
    seconds: float
    """Wall time of the whole run."""
    registered_names: list[str]
    """Names of the registered photos."""
    camera_model: str
    """COLMAP model of the first registered photo's camera (before undistortion)."""
    camera_params: list[float]
    """Its parameters after bundle adjustment, in COLMAP's order (fmgs.sfm.config.CAMERA_PARAMS)."""
    focal_source: str
    """Where the cameras' starting focal lengths came from: given (camera_params or intrinsics_file),
    exif, or default (1.2 x the longest image side); mixed sources are counted ("3 given, 9 exif")."""
    cameras: int
    """Cameras in the reconstruction (1 for one shared camera)."""


def photo_names(images: Path) -> list[str]:
    """The photos directly in ``images``; a missing folder or a dataset root holding images/ is named."""
    if not images.is_dir():
        raise ValidationError(str(images), "does not exist" if not images.exists() else "is not a folder")
    names = sorted(p.name for p in images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    sub = images / "images"
    if len(names) < 3 and sub.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in sub.iterdir()):
        raise ValidationError(str(images), f"photos are in {sub}: pass that")
    if len(names) < 3:
        raise ValidationError(str(images), f"need at least 3 photos, found {len(names)}")
    return names


SFM_RECORD = "sfm.json"
"""The finished run's result, settings and photos' fingerprint, written last in its output folder."""


def photos_fingerprint(images: Path, names: list[str], cfg: SfMConfig) -> str:
    """Name, size and modification time of each photo (and of the intrinsics file): SfM is redone when
    they change."""
    files = [images / n for n in names]
    if cfg.intrinsics_file:
        files.append(Path(cfg.intrinsics_file))
    return ";".join(
        f"{f.name}:{f.stat().st_size}:{f.stat().st_mtime_ns}" if f.is_file() else f"{f.name}:missing"
        for f in files
    )


def completed_sfm(images: str | Path, out: str | Path, cfg: SfMConfig) -> Path | None:
    """The undistorted dataset of an earlier ``run_sfm`` into ``out`` of the same photos with the same
    settings, else None (a run stopped before its record was written counts as not done)."""
    out = Path(out)
    try:
        rec = json.loads((out / SFM_RECORD).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(rec, dict) or not isinstance(rec.get("config"), dict):
        return None
    defaults = json.loads(json.dumps(asdict(SfMConfig())))  # settings added since count at their default
    if {**defaults, **rec["config"]} != json.loads(json.dumps(asdict(cfg))):
        return None
    try:
        names = photo_names(Path(images))
    except ValidationError:
        return None
    if rec.get("photos") != photos_fingerprint(Path(images), names, cfg):
        return None
    return out / "undistorted"


def read_intrinsics(path: str | Path, names: list[str]) -> dict[str, tuple[str, int, int, list[float]]]:
    """Per-photo known intrinsics from a JSON file: {name: {"model", "width", "height", "params"}} ->
    {name: (model, width, height, params)}, checked against CAMERA_PARAMS and the photos' names."""
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValidationError("intrinsics_file", f"cannot read {path}: {e}") from e
    if not isinstance(raw, dict):
        raise ValidationError("intrinsics_file", f"{path} must hold an object {{photo name: intrinsics}}")
    out = {}
    for name, v in raw.items():
        where = f"intrinsics_file {path}: {name}"
        if name not in names:
            raise ValidationError(where, "no such photo")
        try:
            model, w, h, params = (
                v["model"],
                int(v["width"]),
                int(v["height"]),
                [float(x) for x in v["params"]],
            )
        except (TypeError, KeyError, ValueError) as e:
            raise ValidationError(where, f'needs "model", "width", "height" and "params" ({e})') from e
        if model not in CAMERA_PARAMS:
            raise ValidationError(
                where, f"unknown camera model {model!r} (one of {', '.join(CAMERA_PARAMS)})"
            )
        if len(params) != len(CAMERA_PARAMS[model].split(",")):
            raise ValidationError(where, f"{model} takes {CAMERA_PARAMS[model]}, got {len(params)} values")
        out[name] = (model, w, h, params)
    return out


def _cameras_after_extraction(
    db_path: Path, known: dict[str, tuple[str, int, int, list[float]]], shared_given: bool
) -> tuple[int, dict[int, str]]:
    """Give each listed photo's camera (one per photo) its known model and parameters, as a prior; then
    (keypoints, camera id -> where its focal length came from: given | exif | default). COLMAP marks a
    focal length from EXIF or from camera_params as a prior; the others start at 1.2 x the longest side."""
    import pycolmap

    with pycolmap.Database.open(db_path) as db:
        given = set()
        for image in db.read_all_images():
            if image.name not in known:
                continue
            model, w, h, params = known[image.name]
            cam = db.read_camera(image.camera_id)
            if (cam.width, cam.height) != (w, h):
                raise ValidationError(
                    f"intrinsics_file: {image.name}",
                    f"intrinsics are for {w}x{h}, the photo is {cam.width}x{cam.height}",
                )
            new = pycolmap.Camera.create_from_model_name(image.camera_id, model, 1.0, w, h)
            new.params = params
            new.has_prior_focal_length = True  # trusted like camera_params: not re-estimated from scratch
            db.update_camera(new)
            given.add(image.camera_id)
        sources = {
            c.camera_id: "given"
            if c.camera_id in given or shared_given
            else ("exif" if c.has_prior_focal_length else "default")
            for c in db.read_all_cameras()
        }
        return db.num_keypoints(), sources


def _summary(sources: dict[int, str]) -> str:
    counts = Counter(sources.values())
    return next(iter(counts)) if len(counts) == 1 else ", ".join(f"{n} {k}" for k, n in counts.items())


def run_sfm(images: str | Path, out: str | Path, cfg: SfMConfig = SfMConfig()) -> SfMResult:
    """Reconstruct ``images`` into ``out``; raises FmgsError when too few photos register.

    Logs one line per phase (features, matching, mapping, undistortion) with counts and seconds;
    COLMAP's own log goes to OUT/colmap.log.
    """
    import pycolmap

    images, out = Path(images), Path(out)
    names = photo_names(images)
    known = read_intrinsics(cfg.intrinsics_file, names) if cfg.intrinsics_file else {}
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    (out / SFM_RECORD).unlink(missing_ok=True)  # an interrupted rerun must not pass for the last run
    colmap_log = out / "colmap.log"
    colmap_log.unlink(missing_ok=True)
    db = out / "database.db"
    db.unlink(missing_ok=True)  # a fresh database: stale features would mix with new ones
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    if cfg.camera_params is not None:  # COLMAP then marks the focal length as a prior
        reader.camera_params = ",".join(repr(float(v)) for v in cfg.camera_params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = cfg.max_image_size
    extraction.sift.max_num_features = cfg.max_num_features
    if known:  # listed photos get their own camera, so each can take its own intrinsics
        mode = pycolmap.CameraMode.PER_IMAGE
    else:
        mode = pycolmap.CameraMode.SINGLE if cfg.single_camera else pycolmap.CameraMode.AUTO
    t = time.perf_counter()
    with output_to(colmap_log):
        pycolmap.extract_features(
            db,
            images,
            image_names=names,
            camera_mode=mode,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
    keypoints, sources = _cameras_after_extraction(db, known, cfg.camera_params is not None)
    focal_source = _summary(sources)
    log.info(
        "features: %d photos, %d keypoints, focal lengths from %s (%.1f s)",
        len(names),
        keypoints,
        focal_source,
        time.perf_counter() - t,
    )
    if not cfg.refine_focal and "default" in sources.values():
        log.warning(
            "refine_focal is off but some photos have no known or EXIF focal length: theirs is held at "
            "a guess (1.2 x the longest side); give camera_params or intrinsics_file"
        )
    matcher = cfg.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= cfg.exhaustive_max else "sequential"
    t = time.perf_counter()
    with output_to(colmap_log):
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
        elif matcher == "sequential":
            pycolmap.match_sequential(db, device=pycolmap.Device.cpu)
        else:
            raise ValidationError("matcher", f"unknown matcher {matcher!r} (exhaustive, sequential, auto)")
    with pycolmap.Database.open(db) as dbh:
        pairs, verified = dbh.num_matched_image_pairs(), dbh.num_verified_image_pairs()
    log.info(
        "matching (%s): %d image pairs matched, %d geometrically verified (%.1f s)",
        matcher,
        pairs,
        verified,
        time.perf_counter() - t,
    )
    sparse = out / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = cfg.seed
    # Also the mapper's absolute-pose refinement of newly registered photos (get_mapper copies these).
    opts.ba_refine_focal_length = cfg.refine_focal
    opts.ba_refine_principal_point = cfg.refine_principal_point
    opts.ba_refine_extra_params = cfg.refine_extra
    if not cfg.refine_known:  # known intrinsics stay exactly as given, whatever the refine_* settings
        opts.constant_cameras = {i for i, src in sources.items() if src == "given"}
    t = time.perf_counter()
    with output_to(colmap_log):
        maps = pycolmap.incremental_mapping(db, images, sparse, options=opts)
    if not maps:
        raise FmgsError(
            f"structure from motion failed: no two of the {len(names)} photos could be registered "
            f"(too little overlap or texture?); COLMAP's log: {colmap_log}"
        )
    best_id, best = max(maps.items(), key=lambda kv: kv[1].num_reg_images())
    registered = best.num_reg_images()
    log.info(
        "mapping: %d of %d photos registered, %d points, %d model(s) (%.1f s)",
        registered,
        len(names),
        best.num_points3D(),
        len(maps),
        time.perf_counter() - t,
    )
    if registered < cfg.min_registered_fraction * len(names):
        raise FmgsError(
            f"only {registered} of {len(names)} photos registered (need "
            f"{cfg.min_registered_fraction:.0%}); more overlap between photos usually helps; "
            f"COLMAP's log: {colmap_log}"
        )
    und = out / "undistorted"
    shutil.rmtree(und, ignore_errors=True)
    t = time.perf_counter()
    with output_to(colmap_log):
        pycolmap.undistort_images(und, sparse / str(best_id), images)
    log.info("undistortion: %d photos to PINHOLE (%.1f s)", registered, time.perf_counter() - t)
    reg = sorted((best.images[i] for i in best.reg_image_ids()), key=lambda im: im.name)
    cam = best.cameras[reg[0].camera_id]
    res = SfMResult(
        und,
        registered,
        len(names),
        best.num_points3D(),
        float(best.compute_mean_reprojection_error()),
        time.perf_counter() - t0,
        [im.name for im in reg],
        cam.model_name,
        [float(v) for v in cam.params],
        focal_source,
        best.num_cameras(),
    )
    record = {**asdict(res), "dataset_dir": str(und), "config": asdict(cfg)}
    record["photos"] = photos_fingerprint(images, names, cfg)
    with atomic_path(out / SFM_RECORD) as tmp:
        tmp.write_text(json.dumps(record, indent=1))
    return res


@dataclass
class PoseErrors:
    """Errors of estimated poses after a similarity alignment onto reference poses."""

    rotation_deg: list[float]
    """Per image: angle of R_ref^T R_est_aligned, degrees."""
    centre_rel: list[float]
    """Per image: camera-centre distance divided by the reference extent."""
    scale: float
    """Scale of the similarity that maps the estimate onto the reference."""
    extent: float
    """Largest distance between two reference camera centres."""


def align_similarity(src, dst):
    """Least-squares similarity (s, R, t) with dst ~ s R src + t, for [N,3] point sets (Umeyama 1991)."""
    import numpy as np

    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValidationError("points", f"need two [N,3] sets with N >= 3, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1  # a rotation, not a reflection
    R = U @ D @ Vt
    var = (a**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var)
    return s, R, mu_d - s * R @ mu_s


def pose_errors(est_viewmats, ref_viewmats) -> PoseErrors:
    """Align estimated world-to-camera poses [N,4,4] to reference ones by their centres, then compare."""
    import numpy as np

    E, Rf = np.asarray(est_viewmats, dtype=np.float64), np.asarray(ref_viewmats, dtype=np.float64)
    c_est = np.stack([-V[:3, :3].T @ V[:3, 3] for V in E])
    c_ref = np.stack([-V[:3, :3].T @ V[:3, 3] for V in Rf])
    s, R, t = align_similarity(c_est, c_ref)
    rot, cen = [], []
    extent = float(max(np.linalg.norm(c_ref[:, None] - c_ref[None], axis=-1).max(), 1e-12))
    for Ve, Vr, ce, cr in zip(E, Rf, c_est, c_ref, strict=True):
        R_est = Ve[:3, :3] @ R.T  # camera-from-world in the reference frame
        M = Vr[:3, :3].T @ R_est
        # atan2(sin, cos) stays accurate near 0 and 180 degrees, where arccos of the trace does not
        sin = 0.5 * np.linalg.norm([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
        rot.append(float(np.degrees(np.arctan2(sin, (np.trace(M) - 1) / 2))))
        cen.append(float(np.linalg.norm(s * R @ ce + t - cr) / extent))
    return PoseErrors(rot, cen, s, extent)
