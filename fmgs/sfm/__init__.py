"""``fmgs sfm`` and the poses stage of ``fmgs build``: photos -> poses, sparse points and undistorted
images with pycolmap.

The reconstruction runs in ``fmgs.sfm.pipeline``; its settings are ``fmgs.sfm.config`` (torch- and
pycolmap-free). Exports resolve on first use, so importing the package or its config stays cheap.
"""

from fmgs.lazy import lazy_exports

_EXPORTS = {
    "CAMERA_PARAMS": "fmgs.sfm.config",
    "SfMConfig": "fmgs.sfm.config",
    "PoseErrors": "fmgs.sfm.pipeline",
    "SfMResult": "fmgs.sfm.pipeline",
    "align_similarity": "fmgs.sfm.pipeline",
    "completed_sfm": "fmgs.sfm.pipeline",
    "photo_names": "fmgs.sfm.pipeline",
    "pose_errors": "fmgs.sfm.pipeline",
    "read_intrinsics": "fmgs.sfm.pipeline",
    "run_sfm": "fmgs.sfm.pipeline",
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
