"""How ``fmgs build`` reads a robot's recording (fmgs.data.rosbag). Torch-free: flags and config files
are built from it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RecordingConfig:
    """How a robot's recording becomes a dataset (``fmgs build RECORDING``)."""

    image_topic: str = ""
    """The camera's image topic (sensor_msgs Image or CompressedImage); "" takes the only colour camera."""
    camera_info_topic: str = ""
    """Its CameraInfo; "" takes the camera_info beside the image topic."""
    depth_topic: str = ""
    """A depth image topic for the sparse points; "" takes the one depth topic there is, "none" uses none."""
    fixed_frame: str = ""
    """The frame poses and answers live in; "" takes map, else odom."""
    max_frames: int = 300
    """At most this many keyframes (evenly spread over the kept ones), so a long recording builds in bounded
    time."""
    min_translation: float = 0.05
    """A frame is kept once the camera has moved this far (metres) since the last kept one ..."""
    min_rotation_deg: float = 5.0
    """... or turned this much."""
    blur_ratio: float = 0.5
    """Frames whose sharpness (variance of the Laplacian) is below this fraction of their neighbours'
    median are dropped as blurred; 0 keeps every frame."""
    max_tf_gap_s: float = 0.2
    """An image whose stamp falls between two samples of a moving transform further apart than this (and
    than 3 of that transform's usual intervals, for one published slowly) is dropped (a tf dropout): tf2
    would interpolate across it, but the pose there is a guess."""
    max_depth_points: int = 100_000
    """Cap on the sparse points from depth (pixels are taken on a regular stride)."""

    def __post_init__(self) -> None:
        if self.max_frames < 2:
            raise ValueError("max_frames must be >= 2")
        if min(self.min_translation, self.min_rotation_deg, self.blur_ratio, self.max_tf_gap_s) < 0:
            raise ValueError("min_translation, min_rotation_deg, blur_ratio and max_tf_gap_s must be >= 0")
        if self.max_depth_points < 1:
            raise ValueError("max_depth_points must be >= 1")
