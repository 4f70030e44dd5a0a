"""Thin client for the FMGS query server: grpcio, grpcio-health-checking, protobuf and numpy (no torch).

from fmgs_client import FmgsClient, CameraSpec

with FmgsClient("127.0.0.1:50051") as c:
    [answer] = c.query("kitchen", "blue mug", fields=["mean"], instances=True)
    view = c.render("kitchen", CameraSpec.look_at(eye, target), "blue mug")
"""

from fmgs_client.client import FmgsClient, FmgsError
from fmgs_client.retry import RetryPolicy
from fmgs_client.types import (
    Box,
    CameraSpec,
    Geometry,
    Instance,
    Pixel,
    PointResult,
    Presence,
    RenderResult,
    SceneInfo,
    SegmentResult,
    TextAnswer,
)

__version__ = "0.1.0"

__all__ = [
    "Box",
    "CameraSpec",
    "FmgsClient",
    "FmgsError",
    "Geometry",
    "Instance",
    "Pixel",
    "PointResult",
    "Presence",
    "RenderResult",
    "RetryPolicy",
    "SceneInfo",
    "SegmentResult",
    "TextAnswer",
]
