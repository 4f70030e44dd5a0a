"""FMGS core library: Gaussian scene model, cameras, rasterisers.

Importing this package is cheap: no compiled kernel is built or loaded until a backend is used.
"""

from fmgs.cameras import Camera
from fmgs.errors import FmgsError, ValidationError
from fmgs.gaussians import GaussianSet

__all__ = ["Camera", "FmgsError", "GaussianSet", "ValidationError"]
__version__ = "0.1.0"
