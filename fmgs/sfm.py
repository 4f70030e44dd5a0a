"""Structure from motion with pycolmap: photos -> poses, sparse points and undistorted images.

SIFT extraction (one shared camera by default), exhaustive matching for small sets and sequential
matching for larger ones, incremental mapping, then undistortion to PINHOLE. The output folder is a
dataset ``load_dataset`` reads: ``OUT/undistorted/{images, sparse}``.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from fmgs.data.dataset import IMAGE_SUFFIXES
from fmgs.errors import FmgsError, ValidationError
from fmgs.io.atomic import atomic_path
from fmgs.sfm_config import SfMConfig

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


def run_sfm(images: str | Path, out: str | Path, cfg: SfMConfig = SfMConfig()) -> SfMResult:
    """Reconstruct ``images`` into ``out``; raises FmgsError when too few photos register."""
    import pycolmap

    images, out = Path(images), Path(out)
    names = (
        sorted(p.name for p in images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if images.is_dir()
        else []
    )
    if len(names) < 3:
        raise ValidationError(str(images), f"need at least 3 photos, found {len(names)}")
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    db = out / "database.db"
    db.unlink(missing_ok=True)  # a fresh database: stale features would mix with new ones
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = cfg.max_image_size
    extraction.sift.max_num_features = cfg.max_num_features
    mode = pycolmap.CameraMode.SINGLE if cfg.single_camera else pycolmap.CameraMode.AUTO
    log.info("extracting features from %d photos", len(names))
    pycolmap.extract_features(
        db,
        images,
        image_names=names,
        camera_mode=mode,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    matcher = cfg.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= cfg.exhaustive_max else "sequential"
    log.info("%s matching", matcher)
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    elif matcher == "sequential":
        pycolmap.match_sequential(db, device=pycolmap.Device.cpu)
    else:
        raise ValidationError("matcher", f"unknown matcher {matcher!r} (exhaustive, sequential, auto)")
    sparse = out / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = cfg.seed
    maps = pycolmap.incremental_mapping(db, images, sparse, options=opts)
    if not maps:
        raise FmgsError(
            f"structure from motion failed: no two of the {len(names)} photos could be registered "
            "(too little overlap or texture?)"
        )
    best_id, best = max(maps.items(), key=lambda kv: kv[1].num_reg_images())
    registered = best.num_reg_images()
    if registered < cfg.min_registered_fraction * len(names):
        raise FmgsError(
            f"only {registered} of {len(names)} photos registered (need "
            f"{cfg.min_registered_fraction:.0%}); more overlap between photos usually helps"
        )
    und = out / "undistorted"
    shutil.rmtree(und, ignore_errors=True)
    pycolmap.undistort_images(und, sparse / str(best_id), images)
    reg_names = sorted(best.images[i].name for i in best.reg_image_ids())
    res = SfMResult(
        und,
        registered,
        len(names),
        best.num_points3D(),
        float(best.compute_mean_reprojection_error()),
        time.perf_counter() - t0,
        reg_names,
    )
    with atomic_path(out / "sfm.json") as tmp:
        tmp.write_text(json.dumps({**asdict(res), "dataset_dir": str(und), "config": asdict(cfg)}, indent=1))
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
