"""Queries on a scene package, all through one engine (the one the server runs): Gaussians ranked for a
text, relevancy images for a camera, segmentation, relevancy at arbitrary points.

    engine = SceneEngine.open("models/demo")            # the server's configuration by default
    answer = engine.text_query(vector, top_k=100)        # TextAnswer: scene indices, relevancy, ...
    image = render_pose(engine, camera, vector).relevancy

Exports resolve on first use, so importing a submodule (``fmgs.query.config``) stays free of torch. Functions
named like their module (``segment``, ``relevancy``) are imported from the module: once a submodule is
imported, Python binds its name on the package, so a package export of that name would be the module.
"""

from fmgs.lazy import lazy_exports

_EXPORTS = {
    "CANONICAL_PHRASES": "fmgs.query.relevancy",
    "EngineConfig": "fmgs.query.engine",
    "SceneEngine": "fmgs.query.engine",
    "TextAnswer": "fmgs.query.engine",
    "IndexConfig": "fmgs.query.config",
    "InstanceConfig": "fmgs.query.instances",
    "PoseRender": "fmgs.query.pose",
    "render_pose": "fmgs.query.pose",
    "Segmentation": "fmgs.query.segment",
    "PointAnswer": "fmgs.query.points",
    "query_points": "fmgs.query.points",
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
