"""Datasets: COLMAP models and transforms.json read into one posed-image dataset type."""
