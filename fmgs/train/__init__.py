"""Training: 3DGS geometry (gaussians.py, strategy.py) and held-out evaluation (evaluate.py)."""
