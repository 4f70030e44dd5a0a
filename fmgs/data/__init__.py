"""Datasets: COLMAP models and transforms.json read into one posed-image dataset type."""

HOLDOUT_EVERY = 8
"""Every n-th frame (0, n, 2n, ...) is held out for evaluation and never trained on (the 3DGS convention)."""
