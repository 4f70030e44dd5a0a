"""Text queries against a scene package: per-Gaussian ranking and rendered relevancy images."""

from fmgs.query.relevancy import CANONICAL_PHRASES, relevancy
from fmgs.query.text import QueryResult, rank_gaussians, relevancy_image

__all__ = ["CANONICAL_PHRASES", "QueryResult", "rank_gaussians", "relevancy", "relevancy_image"]
