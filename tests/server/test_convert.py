"""Request validation and conversions of the server (``fmgs_server.convert``): every bad input raises
InvalidArgument naming the field; good inputs come back converted."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fmgs.query.instances import Box, Instance
from fmgs_client.types import Instance as ClientInstance
from fmgs_server import convert
from fmgs_server.config import ServerConfig
from fmgs_server.errors import InvalidArgument
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.tensors import to_tensor

CFG = ServerConfig(max_texts=3, max_text_chars=10, max_top_k=50, default_top_k=7, max_image_side=64)
CFG_PIXELS = ServerConfig(max_image_side=64, max_image_pixels=1000)


def _camera(**kw) -> pb.Camera:
    args = dict(viewmat=np.eye(4).ravel().tolist(), fx=20.0, fy=21.0, cx=8.0, cy=6.0, width=16, height=12)
    args.update(kw)
    return pb.Camera(**args)


def _raises(match: str):
    return pytest.raises(InvalidArgument, match=match)


def test_texts():
    assert convert.texts(["a cup", "chair"], CFG) == ["a cup", "chair"]
    assert convert.texts([], CFG, allow_empty=True) == []
    with _raises(r"^texts: at least one text is needed$"):
        convert.texts([], CFG)
    with _raises(r"^class_names: 4 texts, at most 3 per request$"):
        convert.texts(["a", "b", "c", "d"], CFG, field="class_names")
    with _raises(r"^texts\[1\]: empty text$"):
        convert.texts(["a", "  "], CFG)
    with _raises(r"^canonical_phrases\[0\]: 11 characters, at most 10$"):
        convert.texts(["x" * 11], CFG, field="canonical_phrases")


def test_top_k_and_threshold():
    assert convert.top_k(0, CFG) == 7  # 0 means the server's default
    assert convert.top_k(50, CFG) == 50
    with _raises(r"^top_k: 51 is over the limit 50$"):
        convert.top_k(51, CFG)
    assert convert.threshold(0.0) == 0.0 and convert.threshold(1.0) == 1.0
    for bad in (-0.1, 1.5, math.nan, math.inf):
        with _raises(r"^threshold: must be in \[0, 1\]"):
            convert.threshold(bad)


def test_good_camera():
    cam = convert.camera(_camera(), CFG)
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (16, 12, 20.0, 21.0, 8.0, 6.0)
    assert cam.near == 0.01  # 0 on the wire: the default
    torch.testing.assert_close(cam.viewmat, torch.eye(4, dtype=torch.float64))
    assert convert.camera(_camera(near=0.5), CFG).near == 0.5


@pytest.mark.parametrize(
    "cam, match",
    [
        (_camera(viewmat=[1.0] * 12), r"^camera\.viewmat: expected 16 numbers \(row-major 4x4\), got 12$"),
        (_camera(width=0), r"^camera\.width/height: must be >= 1, got 0x12$"),
        (_camera(width=65), r"^camera\.width/height: 65x12 is over the image cap"),
        (_camera(fx=math.nan), r"^camera\.fx: must be finite and reasonable"),
        (_camera(cy=1e13), r"^camera\.cy: must be finite and reasonable"),
        (_camera(fy=0.0), r"^camera\.fx/fy: focal lengths must be positive"),
        (_camera(near=-1.0), r"^camera\.near: must be >= 0"),
        (_camera(viewmat=[math.inf] + [0.0] * 15), r"^camera\.viewmat: must be finite and reasonable$"),
        (_camera(viewmat=np.diag([2.0, 2, 2, 1]).ravel().tolist()), r"^camera\.viewmat: rotation is not a"),
    ],
)
def test_bad_camera_names_the_field(cam, match):
    with _raises(match):
        convert.camera(cam, CFG)


def test_camera_pixel_cap_and_presence():
    with _raises(r"^camera\.width/height: 40x30 is over the image cap \(64 per side, 1000 pixels\)$"):
        convert.camera(_camera(width=40, height=30), CFG_PIXELS)
    with _raises(r"^camera: missing$"):
        convert.camera(_camera(), CFG, present=False)


def test_tensor():
    a = np.arange(6, dtype=np.float32).reshape(2, 3)
    t = convert.tensor(to_tensor(a), "points", (None, 3), max_rows=2)
    assert t.dtype == torch.float64
    np.testing.assert_array_equal(t.numpy(), a)
    with _raises(r"^points: shape \[2\] of float32 needs 8 bytes, got 4$"):
        convert.tensor(pb.Tensor(dtype=pb.DTYPE_FLOAT32, shape=[2], data=b"\0" * 4), "points", (None,), 9)
    with _raises(r"^points: must be float32 or float64, got int32$"):
        convert.tensor(to_tensor(a.astype(np.int32)), "points", (None, 3), 9)
    with _raises(r"^embeddings: expected shape \[nx4\], got \[2, 3\]$"):
        convert.tensor(to_tensor(a), "embeddings", (None, 4), 9)
    with _raises(r"^points: expected shape \[nx3\], got \[6\]$"):
        convert.tensor(to_tensor(a.ravel()), "points", (None, 3), 9)
    with _raises(r"^points: 2 rows, at most 1$"):
        convert.tensor(to_tensor(a), "points", (None, 3), max_rows=1)
    a[1, 2] = np.nan
    with _raises(r"^points: contains NaN or infinity$"):
        convert.tensor(to_tensor(a), "points", (None, 3), 9)


def test_instance_config():
    cfg = convert.instance_config(pb.InstanceOptions(enabled=True), 1000)
    assert (cfg.eps, cfg.min_points, cfg.max_instances, cfg.max_pairs) == (0.0, 10, 10, 1000)  # 0: defaults
    cfg = convert.instance_config(pb.InstanceOptions(eps=0.2, min_points=3, max_instances=1000), 1000)
    assert (cfg.eps, cfg.min_points, cfg.max_instances) == (0.2, 3, 1000)
    for eps in (-1.0, math.nan, 1e13):
        with _raises(r"^instances\.eps: must be finite and >= 0"):
            convert.instance_config(pb.InstanceOptions(eps=eps), 1000)
    with _raises(r"^instances\.max_instances: at most 1000$"):
        convert.instance_config(pb.InstanceOptions(max_instances=1001), 1000)


def test_instance_to_proto_reads_back_on_the_client():
    rot = np.eye(3)[[1, 0, 2]] * np.array([1.0, 1.0, -1.0])
    inst = Instance(
        centroid=np.array([1.0, 2.0, 3.0]),
        aabb=Box(np.array([1.0, 2.0, 3.0]), np.array([0.5, 0.6, 0.7]), np.eye(3)),
        obb=Box(np.array([1.1, 2.1, 3.1]), np.array([0.2, 0.3, 0.4]), rot),
        score=0.75,
        members=np.arange(12),
    )
    m = convert.instance(4, inst)
    assert m.id == 4 and m.num_members == 12 and m.score == 0.75
    back = ClientInstance.from_proto(m)
    np.testing.assert_array_equal(back.centroid, [1, 2, 3])
    np.testing.assert_array_equal(back.aabb.extent, [0.5, 0.6, 0.7])
    np.testing.assert_array_equal(back.obb.center, [1.1, 2.1, 3.1])
    np.testing.assert_array_equal(back.obb.rotation, rot)  # row-major on the wire, the same matrix back


def test_render_outputs_and_encoding():
    assert convert.outputs([]) == ("relevancy",)
    both = [pb.RENDER_OUTPUT_RGB, pb.RENDER_OUTPUT_RELEVANCY, pb.RENDER_OUTPUT_RGB]
    assert convert.outputs(both) == ("rgb", "relevancy")  # once each, in the order asked
    with _raises("outputs: unknown value"):
        convert.outputs([pb.RENDER_OUTPUT_RGB, 99])
    assert convert.encoding(0) == pb.IMAGE_ENCODING_FLOAT32
    assert convert.encoding(pb.IMAGE_ENCODING_PNG) == pb.IMAGE_ENCODING_PNG
    with _raises("encoding: unknown value 42"):
        convert.encoding(42)
