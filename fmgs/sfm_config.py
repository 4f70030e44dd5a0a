"""Structure-from-motion settings (``fmgs sfm`` and the poses stage of ``fmgs build``), torch- and
pycolmap-free so that flags and config files are built from them cheaply."""

from __future__ import annotations

from dataclasses import dataclass

MATCHERS = ("auto", "exhaustive", "sequential")
CAMERA_MODELS = (
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "FULL_OPENCV",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "OPENCV_FISHEYE",
    "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE",
    "FOV",
    "SIMPLE_FISHEYE",
    "FISHEYE",
    "SIMPLE_DIVISION",
    "DIVISION",
)
"""COLMAP camera models the photos' camera can be estimated as (all undistorted to PINHOLE after)."""


@dataclass(frozen=True)
class SfMConfig:
    """Structure-from-motion settings."""

    matcher: str = "auto"
    """exhaustive, sequential (ordered captures), or auto: exhaustive up to exhaustive_max images."""
    exhaustive_max: int = 200
    """auto uses exhaustive matching up to this many images."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model estimated for the photos (undistorted to PINHOLE afterwards)."""
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
        if self.exhaustive_max < 1 or self.max_image_size < 16 or self.max_num_features < 16:
            raise ValueError("exhaustive_max must be >= 1, max_image_size and max_num_features >= 16")
        if not 0 <= self.min_registered_fraction <= 1:
            raise ValueError(
                f"min_registered_fraction must lie in [0, 1], not {self.min_registered_fraction!r}"
            )
