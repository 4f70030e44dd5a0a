"""Structure-from-motion settings (``fmgs sfm`` and the poses stage of ``fmgs build``), torch- and
pycolmap-free so that flags and config files are built from them cheaply."""

from __future__ import annotations

from dataclasses import dataclass

MATCHERS = ("auto", "exhaustive", "sequential")
CAMERA_PARAMS = {
    "SIMPLE_PINHOLE": "f,cx,cy",
    "PINHOLE": "fx,fy,cx,cy",
    "SIMPLE_RADIAL": "f,cx,cy,k",
    "RADIAL": "f,cx,cy,k1,k2",
    "OPENCV": "fx,fy,cx,cy,k1,k2,p1,p2",
    "FULL_OPENCV": "fx,fy,cx,cy,k1,k2,p1,p2,k3,k4,k5,k6",
    "SIMPLE_RADIAL_FISHEYE": "f,cx,cy,k",
    "RADIAL_FISHEYE": "f,cx,cy,k1,k2",
    "OPENCV_FISHEYE": "fx,fy,cx,cy,k1,k2,k3,k4",
    "THIN_PRISM_FISHEYE": "fx,fy,cx,cy,k1,k2,p1,p2,k3,k4,sx1,sy1",
    "RAD_TAN_THIN_PRISM_FISHEYE": "fx,fy,cx,cy,k0,k1,k2,k3,k4,k5,p0,p1,s0,s1,s2,s3",
    "FOV": "fx,fy,cx,cy,omega",
    "SIMPLE_FISHEYE": "f,cx,cy",
    "FISHEYE": "fx,fy,cx,cy",
    "SIMPLE_DIVISION": "f,cx,cy,k",
    "DIVISION": "fx,fy,cx,cy,k",
}
"""COLMAP camera model -> its parameters in COLMAP's order (pixels for focal lengths and centres)."""
CAMERA_MODELS = tuple(CAMERA_PARAMS)
"""COLMAP camera models the photos' camera can be estimated as (all undistorted to PINHOLE after)."""


@dataclass(frozen=True)
class SfMConfig:
    """Structure-from-motion settings."""

    matcher: str = "auto"
    """exhaustive, sequential (ordered captures), or auto: exhaustive up to exhaustive_max images."""
    exhaustive_max: int = 200
    """auto uses exhaustive matching up to this many images."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model of the photos (undistorted to PINHOLE afterwards); the model of camera_params."""
    camera_params: tuple[float, ...] | None = None
    """Known intrinsics shared by all photos, in camera_model's COLMAP order, in pixels of the photos as
    given (PINHOLE: fx,fy,cx,cy; SIMPLE_RADIAL: f,cx,cy,k; OPENCV: fx,fy,cx,cy,k1,k2,p1,p2); held exactly
    unless refine_known. None: estimated, starting from the EXIF focal length when the photos have one
    (else 1.2 x the longest side) and the image centre."""
    intrinsics_file: str | None = None
    """JSON file of per-photo known intrinsics, {photo name: {"model": "OPENCV", "width": W, "height": H,
    "params": [...]}} (params as in camera_params); every photo then gets its own camera: the listed ones
    held like camera_params, the others with camera_params or estimated."""
    refine_focal: bool = True
    """Bundle adjustment refines estimated focal lengths (no: held at EXIF's or the guess)."""
    refine_principal_point: bool = False
    """Bundle adjustment refines estimated principal points (no: held at the image centre; refining
    raised the median rotation error in benchmarks/results/SFM.md, even for an off-centre principal point)."""
    refine_extra: bool = True
    """Bundle adjustment refines estimated distortion parameters (no: held at zero)."""
    refine_known: bool = False
    """Known intrinsics (camera_params, intrinsics_file) are refined too, as the refine_* settings say
    (no: held exactly)."""
    single_camera: bool = True
    """All photos share one camera (one device, fixed zoom)."""
    max_image_size: int = 1600
    """Images are downscaled to this longest side for feature extraction."""
    max_num_features: int = 8192
    """SIFT features per image."""
    min_registered_fraction: float = 0.5
    """Fail when fewer than this fraction of the photos register."""
    seed: int = 0
    """Mapper random seed."""

    def __post_init__(self) -> None:
        if self.matcher not in MATCHERS:
            raise ValueError(f"matcher must be one of {MATCHERS}, got {self.matcher!r}")
        if self.camera_model not in CAMERA_MODELS:
            raise ValueError(f"camera_model must be one of {CAMERA_MODELS}, got {self.camera_model!r}")
        if self.camera_params is not None:
            names = CAMERA_PARAMS[self.camera_model].split(",")
            if len(self.camera_params) != len(names):
                raise ValueError(
                    f"camera_params: {self.camera_model} takes {len(names)} values ({','.join(names)}), "
                    f"got {len(self.camera_params)}"
                )
        if self.exhaustive_max < 1 or self.max_image_size < 16 or self.max_num_features < 16:
            raise ValueError("exhaustive_max must be >= 1, max_image_size and max_num_features >= 16")
        if not 0 <= self.min_registered_fraction <= 1:
            raise ValueError(
                f"min_registered_fraction must lie in [0, 1], not {self.min_registered_fraction!r}"
            )
