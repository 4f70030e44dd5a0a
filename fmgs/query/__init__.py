"""Queries on a scene package, all through one engine (the one the server runs): Gaussians ranked for a
text, relevancy images for a camera, segmentation, relevancy at arbitrary points.

    engine = SceneEngine.open("models/demo")            # the server's configuration by default
    answer = engine.text_query(vector, top_k=100)        # TextAnswer: scene indices, relevancy, ...
    image = render_pose(engine, camera, vector).relevancy

Exports resolve on first use, so importing a submodule (``fmgs.query.config``) stays free of torch.
"""

from importlib import import_module

_EXPORTS = {
    "CANONICAL_PHRASES": "fmgs.query.relevancy",
    "relevancy": "fmgs.query.relevancy",
    "EngineConfig": "fmgs.query.engine",
    "SceneEngine": "fmgs.query.engine",
    "TextAnswer": "fmgs.query.engine",
    "IndexConfig": "fmgs.query.config",
    "InstanceConfig": "fmgs.query.instances",
    "PoseRender": "fmgs.query.pose",
    "render_pose": "fmgs.query.pose",
    "Segmentation": "fmgs.query.segment",
    "segment": "fmgs.query.segment",
    "PointAnswer": "fmgs.query.points",
    "query_points": "fmgs.query.points",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'fmgs.query' has no attribute {name!r}")
