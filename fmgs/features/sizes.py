"""Target-map sizes: a fixed resolution in pixels by default, or a fraction of the image (torch-free)."""

from __future__ import annotations

from fmgs.errors import ValidationError

FEATURE_SIDE = 320
"""Default longer side of the target maps. Objects take the same fraction of a 64-pixel and of a 4K
image, so the maps' resolution in pixels, not their fraction of the image, decides what segmentation
can resolve: a fixed 0.25 made 40x30 maps of 160x120 images (mIoU 0.52 on a user's tabletop scene,
0.94 at full size) and 960x540 maps of 4K ones (0.5 GB of 512-D targets per view)."""


CROP_SCALES = (0.05, 0.125, 0.2, 0.275, 0.35, 0.425, 0.5)
"""Default crop pyramid: each scale's crop edge as a fraction of min(H, W), the 7 scales of the paper's
hybrid target."""


CROP_STRIDE = 0.05
"""Default cap on the crop pyramid's stride as a fraction of min(H, W): the finest crop's edge
(fmgs.features.pyramid explains why)."""


SCALE_BLENDS = ("mean", "coherence", "dominant")
"""The pyramid's scale blends (fmgs.features.scale_blend; kept here so that configs need no torch)."""
SCALE_BLEND = "dominant"
"""The build's default scale blend when a DINO model is given (without one: "mean", the paper's). Chosen
by the target maps' accuracy on generated dev scenes (benchmarks/clip_targets.py; docs/field.md says why
it suits CLIP itself)."""


def check_feature_scale(feature_scale: float | None, feature_side: int) -> None:
    """ValidationError unless feature_scale is None or in (0, 1] and feature_side >= 1."""
    if feature_scale is not None and not 0.0 < feature_scale <= 1.0:
        raise ValidationError("feature_scale", f"must lie in (0, 1] or be none (auto), got {feature_scale}")
    if feature_side < 1:
        raise ValidationError("feature_side", f"must be a positive number of pixels, got {feature_side}")


def feature_scale_for(
    width: int, height: int, feature_scale: float | None, feature_side: int = FEATURE_SIDE
) -> float:
    """The fraction of a width x height image the maps are stored at: ``feature_scale`` when given,
    else the one that makes the longer side ``feature_side`` pixels, never above 1."""
    if feature_scale is not None:
        return feature_scale
    return min(1.0, feature_side / max(width, height))
