"""Request validation and proto <-> library conversions (every failure names the field)."""

from __future__ import annotations

import math

import numpy as np
import torch

from fmgs.cameras import Camera
from fmgs.errors import ValidationError
from fmgs.query.instances import Instance, InstanceConfig
from fmgs_server.config import ServerConfig
from fmgs_server.errors import InvalidArgument
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.tensors import TensorError, from_tensor

OUTPUT_NAMES = {
    pb.RENDER_OUTPUT_RELEVANCY: "relevancy",
    pb.RENDER_OUTPUT_RGB: "rgb",
    pb.RENDER_OUTPUT_DEPTH: "depth",
    pb.RENDER_OUTPUT_ALPHA: "alpha",
}


def outputs(values) -> tuple[str, ...]:
    """Render outputs by name, once each in the order asked; relevancy when none are named."""
    names = tuple(dict.fromkeys(OUTPUT_NAMES.get(o, "?") for o in values)) or ("relevancy",)
    if "?" in names:
        raise InvalidArgument(f"outputs: unknown value in {list(values)}")
    return names


def fields(values) -> set[int]:
    """The per-Gaussian fields a text answer carries (GaussianField values)."""
    known = set(pb.GaussianField.values()) - {pb.GAUSSIAN_FIELD_UNSPECIFIED}
    asked = set(values)
    if not asked <= known:
        raise InvalidArgument(f"fields: unknown value in {list(values)}")
    return asked


def encoding(value: int) -> int:
    """The image encoding (float32 when left unset)."""
    value = value or pb.IMAGE_ENCODING_FLOAT32
    if value not in (pb.IMAGE_ENCODING_FLOAT32, pb.IMAGE_ENCODING_PNG):
        raise InvalidArgument(f"encoding: unknown value {value}")
    return value


def texts(values, cfg: ServerConfig, field: str = "texts", allow_empty: bool = False) -> list[str]:
    """Non-empty, bounded texts."""
    out = list(values)
    if not out and not allow_empty:
        raise InvalidArgument(f"{field}: at least one text is needed")
    if len(out) > cfg.max_texts:
        raise InvalidArgument(f"{field}: {len(out)} texts, at most {cfg.max_texts} per request")
    for i, t in enumerate(out):
        if not t.strip():
            raise InvalidArgument(f"{field}[{i}]: empty text")
        if len(t) > cfg.max_text_chars:
            raise InvalidArgument(f"{field}[{i}]: {len(t)} characters, at most {cfg.max_text_chars}")
    return out


def top_k(value: int, cfg: ServerConfig) -> int:
    if value == 0:
        return cfg.default_top_k
    if value > cfg.max_top_k:
        raise InvalidArgument(f"top_k: {value} is over the limit {cfg.max_top_k}")
    return value


def geometry_cap(value: int, cfg: ServerConfig) -> int:
    """A geometry call's max_gaussians: 0 -> the default; over the limit -> INVALID_ARGUMENT."""
    if value == 0:
        return cfg.default_geometry
    if value > cfg.max_geometry:
        raise InvalidArgument(f"max_gaussians: {value} is over the limit {cfg.max_geometry}")
    return int(value)


def min_opacity(value: float) -> float:
    if not (math.isfinite(value) and 0.0 <= value < 1.0):
        raise InvalidArgument(f"min_opacity: must lie in [0, 1), got {value}")
    return float(value)


def threshold(value: float) -> float:
    if not math.isfinite(value) or not 0 <= value <= 1:
        raise InvalidArgument(f"threshold: must be in [0, 1], got {value}")
    return value


def camera(c: pb.Camera, cfg: ServerConfig, present: bool = True) -> Camera:
    """A validated camera: rigid finite pose, positive focal lengths, size within the caps."""
    if not present:
        raise InvalidArgument("camera: missing")
    if len(c.viewmat) != 16:
        raise InvalidArgument(f"camera.viewmat: expected 16 numbers (row-major 4x4), got {len(c.viewmat)}")
    w, h = int(c.width), int(c.height)
    if w < 1 or h < 1:
        raise InvalidArgument(f"camera.width/height: must be >= 1, got {w}x{h}")
    if w > cfg.max_image_side or h > cfg.max_image_side or w * h > cfg.max_image_pixels:
        raise InvalidArgument(
            f"camera.width/height: {w}x{h} is over the image cap ({cfg.max_image_side} per side, "
            f"{cfg.max_image_pixels} pixels)"
        )
    for name in ("fx", "fy", "cx", "cy", "near"):
        v = getattr(c, name)
        if not math.isfinite(v) or abs(v) > 1e12:
            raise InvalidArgument(f"camera.{name}: must be finite and reasonable, got {v}")
    if not (c.fx > 0 and c.fy > 0):
        raise InvalidArgument(f"camera.fx/fy: focal lengths must be positive, got {c.fx}, {c.fy}")
    if c.near < 0:
        raise InvalidArgument(f"camera.near: must be >= 0, got {c.near}")
    V = torch.tensor(list(c.viewmat), dtype=torch.float64).reshape(4, 4)
    if not bool(torch.isfinite(V).all()) or float(V.abs().max()) > 1e12:
        raise InvalidArgument("camera.viewmat: must be finite and reasonable")
    K = torch.tensor([[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1]], dtype=torch.float64)
    try:
        return Camera(K, V, w, h, near=c.near or 0.01)
    except ValidationError as e:
        raise InvalidArgument(f"camera.{e.field}: {e.reason}") from e


def tensor(t: pb.Tensor, field: str, shape: tuple[int | None, ...], max_rows: int) -> torch.Tensor:
    """A finite float tensor with the given shape (None: any size, at most max_rows)."""
    try:
        a = from_tensor(t, field)
    except TensorError as e:
        raise InvalidArgument(str(e)) from e
    if a.dtype not in (np.float32, np.float64, np.float16):
        raise InvalidArgument(f"{field}: must be float32 or float64, got {a.dtype}")
    if a.ndim != len(shape) or any(s is not None and a.shape[i] != s for i, s in enumerate(shape)):
        want = "x".join("n" if s is None else str(s) for s in shape)
        raise InvalidArgument(f"{field}: expected shape [{want}], got {list(a.shape)}")
    if a.ndim and a.shape[0] > max_rows:
        raise InvalidArgument(f"{field}: {a.shape[0]} rows, at most {max_rows}")
    if not np.isfinite(a).all():
        raise InvalidArgument(f"{field}: contains NaN or infinity")
    return torch.from_numpy(a.astype(np.float64))


def instance_config(o: pb.InstanceOptions, max_pairs: int) -> InstanceConfig:
    """The request's grouping; ``max_pairs``: the server's ``max_instance_pairs``."""
    if not math.isfinite(o.eps) or o.eps < 0 or o.eps > 1e12:
        raise InvalidArgument(f"instances.eps: must be finite and >= 0, got {o.eps}")
    if o.max_instances > 1000:
        raise InvalidArgument("instances.max_instances: at most 1000")
    return InstanceConfig(
        eps=o.eps, min_points=o.min_points or 10, max_instances=o.max_instances or 10, max_pairs=max_pairs
    )


def box(b) -> pb.Box:
    return pb.Box(
        center=b.center.tolist(), extent=b.extent.tolist(), rotation=b.rotation.reshape(-1).tolist()
    )


def instance(i: int, inst: Instance) -> pb.Instance:
    return pb.Instance(
        id=i,
        centroid=inst.centroid.tolist(),
        aabb=box(inst.aabb),
        obb=box(inst.obb),
        score=inst.score,
        num_members=len(inst.members),
    )
