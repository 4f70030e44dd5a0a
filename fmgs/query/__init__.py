"""Text queries against a scene package: per-Gaussian ranking and rendered relevancy images.

Exports resolve on first use, so importing a submodule (``fmgs.query.config``) stays free of torch.
"""

from importlib import import_module

_EXPORTS = {
    "CANONICAL_PHRASES": "fmgs.query.relevancy",
    "relevancy": "fmgs.query.relevancy",
    "QueryResult": "fmgs.query.text",
    "rank_gaussians": "fmgs.query.text",
    "relevancy_image": "fmgs.query.text",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'fmgs.query' has no attribute {name!r}")
