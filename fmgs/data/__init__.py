"""Datasets: COLMAP models and transforms.json read into one posed-image dataset type."""

HOLDOUT_EVERY = 8
"""Every n-th frame (0, n, 2n, ...) is held out for evaluation and never trained on (the 3DGS convention)."""

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
"""Photo file extensions we read (compared case-insensitively)."""
