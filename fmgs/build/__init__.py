"""``fmgs build``: every stage from photos (or a posed dataset, or a 3DGS .ply) to a scene package.

The stages run in ``fmgs.build.pipeline``; their settings are ``fmgs.build.config`` (torch-free, so flags
and config files are built from them cheaply). Exports resolve on first use, so importing the package or
its config imports no torch.
"""

from fmgs.lazy import lazy_exports

_EXPORTS = {
    "EMBEDDING_NEIGHBOURS": "fmgs.build.config",
    "MAX_EMBEDDING_NEIGHBOURS": "fmgs.build.config",
    "BuildConfig": "fmgs.build.config",
    "TargetSpec": "fmgs.build.config",
    "GEOMETRY_REPORT": "fmgs.build.pipeline",
    "LOW_PSNR_DB": "fmgs.build.pipeline",
    "build_scene": "fmgs.build.pipeline",
    "extract_features": "fmgs.build.pipeline",
    "package_from_field": "fmgs.build.pipeline",
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
