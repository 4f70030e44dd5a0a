"""FMGS core library: Gaussian scene model, cameras, rasterisers.

Importing this package is cheap: no torch, no compiled kernel is loaded until an export is used.
"""

from fmgs.lazy import lazy_exports

_EXPORTS = {
    "Camera": "fmgs.cameras",
    "FmgsError": "fmgs.errors",
    "ValidationError": "fmgs.errors",
    "GaussianSet": "fmgs.gaussians",
}
__all__ = sorted(_EXPORTS)
__version__ = "0.1.0"
__getattr__ = lazy_exports(__name__, _EXPORTS)
