"""FMGS core library: Gaussian scene model, cameras, rasterisers.

Importing this package is cheap: no torch, no compiled kernel is loaded until an export is used.
"""

from importlib import import_module

_EXPORTS = {
    "Camera": "fmgs.cameras",
    "FmgsError": "fmgs.errors",
    "ValidationError": "fmgs.errors",
    "GaussianSet": "fmgs.gaussians",
}
__all__ = sorted(_EXPORTS)
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'fmgs' has no attribute {name!r}")
