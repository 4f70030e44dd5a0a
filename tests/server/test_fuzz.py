"""Hostile input against a running server: every request gets a documented status and the server stays up.

Hypothesis draws messages for every RPC (non-finite and huge numbers, zero/negative/huge sizes,
empty/megabyte/unicode texts, tensors with wrong dtypes, shapes and byte counts, deadlines of 0), plus
raw garbage bytes on the wire.
"""

from __future__ import annotations

import grpc
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fmgs_client.client import assemble_render
from fmgs_server.config import ServerConfig
from fmgs_server.server import start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from tests.helpers.query_scenes import CLASS_NAMES, ENCODER_ID, FakeEncoder, blob_scene

C = grpc.StatusCode
# The documented outcomes of a request (docs/serving.md, "Errors"); INTERNAL and UNKNOWN are bugs.
ALLOWED = {
    C.OK,
    C.INVALID_ARGUMENT,
    C.NOT_FOUND,
    C.FAILED_PRECONDITION,
    C.RESOURCE_EXHAUSTED,
    C.DEADLINE_EXCEEDED,
}
FUZZ = settings(max_examples=400, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)


@pytest.fixture(scope="module")
def fuzz_server(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz") / "models"
    root.mkdir()
    blob_scene(root / "blobs", with_field=True)
    cfg = ServerConfig(
        models=root,
        port=0,
        max_image_side=256,
        max_image_pixels=256 * 256,
        max_points=10_000,
        max_top_k=10_000,
    )
    srv = start_server(cfg, encoder_factory=lambda i: FakeEncoder())
    ch = grpc.insecure_channel(srv.address)
    yield srv, ch, pb_grpc.FmgsStub(ch)
    ch.close()
    srv.stop(0)


@pytest.fixture
def fuzzed(fuzz_server):
    """The server, checked healthy after the test's own fuzzing (each test, whatever ran before it)."""
    yield fuzz_server
    _still_healthy(fuzz_server[2])


weird_floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-320, 1e300, -1e300, 5e-324, 40.0]),
)
weird_ints = st.sampled_from([0, 1, 2, 3, 7, 64, 255, 256, 257, 10_000, 2**31 - 1, 2**32 - 1])
texts = st.lists(
    st.one_of(
        st.sampled_from([*CLASS_NAMES, "", " ", "\x00", "é漢字🙂", "a" * 2000]),
        st.text(max_size=40),
    ),
    max_size=70,
)
scenes = st.sampled_from(
    ["blobs", "nope", "", "../blobs", "blobs/../blobs", ".hidden", "a" * 300, "blobs\x00"]
)


@st.composite
def tensors(draw):
    dtype = draw(st.integers(0, 9))
    shape = draw(st.lists(st.sampled_from([0, 1, 2, 3, 16, 100, -1, 2**40]), max_size=4))
    data = draw(
        st.one_of(st.binary(max_size=256), st.sampled_from([b"", np.ones((2, 3), np.float32).tobytes()]))
    )
    return pb.Tensor(dtype=dtype, shape=shape, data=data)


@st.composite
def cameras(draw):
    if draw(st.booleans()):
        vm = np.eye(4)
        vm[:3, 3] = draw(st.lists(weird_floats, min_size=3, max_size=3))
        viewmat = vm.ravel().tolist()
    else:
        viewmat = draw(st.lists(weird_floats, max_size=17))
    return pb.Camera(
        viewmat=viewmat,
        fx=draw(weird_floats),
        fy=draw(weird_floats),
        cx=draw(weird_floats),
        cy=draw(weird_floats),
        width=draw(weird_ints),
        height=draw(weird_ints),
        near=draw(weird_floats),
    )


def _call(fn, req, timeout=10.0):
    try:
        r = fn(req, timeout=timeout)
        if not isinstance(r, pb.SceneInfo | pb.ListScenesResponse | pb.PointQueryResponse):
            list(r)
        return C.OK
    except grpc.RpcError as e:
        assert e.code() in ALLOWED, (e.code(), e.details())
        return e.code()


def _still_healthy(stub):
    r = list(stub.TextQuery(pb.TextQueryRequest(scene="blobs", texts=["red cube"], top_k=1), timeout=30))
    assert r and r[0].total == 1


@FUZZ
@given(
    scene=scenes,
    texts=texts,
    top_k=weird_ints,
    threshold=weird_floats,
    fields=st.lists(st.integers(0, 12), max_size=10),
    eps=weird_floats,
    min_points=weird_ints,
    max_inst=weird_ints,
    canon=st.lists(st.text(max_size=5), max_size=5),
    emb=st.none() | tensors(),
    enc=st.sampled_from(["", ENCODER_ID, "other"]),
)
def test_fuzz_text_query(
    fuzzed, scene, texts, top_k, threshold, fields, eps, min_points, max_inst, canon, emb, enc
):
    _, _, stub = fuzzed
    inst = pb.InstanceOptions(
        enabled=bool(min_points % 2), eps=eps, min_points=min_points, max_instances=max_inst
    )
    req = pb.TextQueryRequest(
        scene=scene, texts=texts, top_k=top_k, threshold=threshold, fields=fields, instances=inst,
        canonical_phrases=canon, encoder_id=enc,
    )  # fmt: skip
    if emb is not None:
        req.embeddings.CopyFrom(emb)
    _call(stub.TextQuery, req)


@FUZZ
@given(
    scene=scenes,
    camera=st.none() | cameras(),
    text=st.sampled_from(["", "red cube", "x" * 3000, "🙂"]),
    outputs=st.lists(st.integers(0, 6), max_size=6),
    encoding=st.integers(0, 4),
)
def test_fuzz_render(fuzzed, scene, camera, text, outputs, encoding):
    _, _, stub = fuzzed
    req = pb.RenderRequest(scene=scene, text=text, outputs=outputs, encoding=encoding)
    if camera is not None:
        req.camera.CopyFrom(camera)
    _call(stub.Render, req)


@FUZZ
@given(
    scene=scenes, texts=texts, points=st.none() | tensors(), canon=st.lists(st.text(max_size=5), max_size=3)
)
def test_fuzz_points(fuzzed, scene, texts, points, canon):
    _, _, stub = fuzzed
    req = pb.PointQueryRequest(scene=scene, texts=texts, canonical_phrases=canon)
    if points is not None:
        req.points.CopyFrom(points)
    _call(stub.PointQuery, req)


@FUZZ
@given(scene=scenes, names=texts, camera=st.none() | cameras(), per_gaussian=st.booleans())
def test_fuzz_segment(fuzzed, scene, names, camera, per_gaussian):
    _, _, stub = fuzzed
    req = pb.SegmentRequest(scene=scene, class_names=names, per_gaussian=per_gaussian)
    if camera is not None:
        req.camera.CopyFrom(camera)
    _call(stub.Segment, req)


@settings(max_examples=200, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(scene=scenes, which=st.sampled_from(["GetScene", "LoadScene", "UnloadScene", "ReloadScene"]))
def test_fuzz_scene_calls(fuzzed, scene, which):
    _, _, stub = fuzzed
    _call(getattr(stub, which), pb.SceneRequest(scene=scene))


@settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(
    method=st.sampled_from(
        ["ListScenes", "GetScene", "TextQuery", "Render", "PointQuery", "Segment", "LoadScene"]
    ),
    data=st.binary(max_size=512),
)
def test_garbage_bytes_on_the_wire(fuzzed, method, data):
    """Bytes that are not a valid message: the runtime answers (INTERNAL when it cannot parse them)."""
    _, ch, _ = fuzzed
    streaming = method in ("TextQuery", "Render", "Segment")
    call = (ch.unary_stream if streaming else ch.unary_unary)(
        f"/fmgs.v1.Fmgs/{method}", request_serializer=lambda b: b, response_deserializer=lambda b: b
    )
    try:
        r = call(data, timeout=10)
        if streaming:
            list(r)
    except grpc.RpcError as e:
        # grpc reports an unparsable request as INTERNAL ("Exception deserializing request!").
        assert e.code() in ALLOWED | {C.INTERNAL}, (e.code(), e.details())
        if e.code() == C.INTERNAL:
            assert "deserializ" in e.details().lower()


def test_zero_deadlines_and_truncated_streams(fuzzed):
    _, _, stub = fuzzed
    cam = pb.Camera(viewmat=np.eye(4).ravel().tolist(), fx=40, fy=40, cx=24, cy=20, width=48, height=40)
    req = pb.RenderRequest(scene="blobs", camera=cam, text="red cube")
    for _ in range(20):  # a deadline already past never reaches the handler
        with pytest.raises(grpc.RpcError) as e:
            list(stub.Render(req, timeout=-1))
        assert e.value.code() == C.DEADLINE_EXCEEDED, e.value.details()
    for timeout in [0.0, 1e-6, 1e-4, 1e-3]:
        # Whether a deadline of "now" fires before a fast answer arrives is a race in grpc's timers:
        # either outcome is fine, but it must be one of them - never another error or a torn image.
        for _ in range(10):
            try:
                got = assemble_render(stub.Render(req, timeout=timeout))
            except grpc.RpcError as e:
                assert e.code() == C.DEADLINE_EXCEEDED, (timeout, e.code(), e.details())
            else:
                assert got.relevancy is not None and got.relevancy.shape == (40, 48)
    for n in range(5):  # a stream whose client stops reading and cancels
        it = stub.StreamRender(
            iter(
                [
                    pb.RenderRequest(scene="blobs", camera=cam, text="red cube", sequence=i)
                    for i in range(n + 1)
                ]
            )
        )
        next(it, None)
        it.cancel()
