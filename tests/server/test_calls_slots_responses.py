"""The server's transport pieces by name: status mapping (calls), compute and stream slots (slots), and the
messages built from engine answers (responses): chunks under the byte cap, the scene description."""

from __future__ import annotations

import dataclasses
import threading

import grpc
import numpy as np
import pytest
import torch

from fmgs.errors import FmgsError, ValidationError
from fmgs.query.engine import SceneEngine
from fmgs.query.points import NoFieldError
from fmgs.query.pose import render_pose
from fmgs.query.segment import segment
from fmgs.scene.manifest import Manifest
from fmgs_client.types import SceneInfo as ClientSceneInfo
from fmgs_server import responses
from fmgs_server.calls import DEADLINE_SLACK_S, seen_by_client, status_of
from fmgs_server.errors import DeadlineExceeded, NotFound, ResourceExhausted
from fmgs_server.repository import READY, UNLOADED, SceneSlot
from fmgs_server.service import FmgsService
from fmgs_server.slots import Slots
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.tensors import from_tensor
from tests.helpers.contexts import FakeContext as Ctx
from tests.helpers.query_scenes import blob_scene, camera


@pytest.mark.parametrize(
    "error, code",
    [
        (NotFound("x"), grpc.StatusCode.NOT_FOUND),
        (NoFieldError("scene", "no field"), grpc.StatusCode.FAILED_PRECONDITION),
        (ValidationError("top_k", "bad"), grpc.StatusCode.INVALID_ARGUMENT),
        (FmgsError("broken"), grpc.StatusCode.FAILED_PRECONDITION),
        (MemoryError(), grpc.StatusCode.RESOURCE_EXHAUSTED),
        (RuntimeError("secret detail"), grpc.StatusCode.INTERNAL),
    ],
)
def test_status_of_each_error(error, code):
    got, message = status_of(error)
    assert got == code
    assert "secret" not in message  # internal details stay in the server log


def test_compute_slots_shed_and_honour_deadlines():
    slots = Slots(compute=1, streams=1, queue_timeout_s=0.05)
    with slots.compute(Ctx()):
        with pytest.raises(ResourceExhausted, match="no compute slot"):
            with slots.compute(Ctx()):
                pass
        with pytest.raises(DeadlineExceeded, match="while waiting"):
            with slots.compute(Ctx(remaining=0.01)):
                pass
        with pytest.raises(ResourceExhausted, match="went away"):
            with slots.compute(Ctx(active=False), patient=True):
                pass
    with pytest.raises(DeadlineExceeded, match="before the work could start"):
        with slots.compute(Ctx(remaining=0.0)):
            pass
    with slots.compute(Ctx(remaining=5.0)):  # the slot came back after every failure
        pass


def test_patient_compute_waits_for_a_free_slot():
    slots = Slots(compute=1, streams=1, queue_timeout_s=0.01)
    got = threading.Event()

    def wait_then_mark() -> None:
        with slots.compute(Ctx(), patient=True):
            got.set()

    with slots.compute(Ctx()):
        t = threading.Thread(target=wait_then_mark)
        t.start()
        t.join(0.5)
        assert not got.is_set()  # still waiting (a stream's frame just comes later)
    t.join(5)
    assert got.is_set()


def test_stream_slots():
    slots = Slots(compute=1, streams=2, queue_timeout_s=1)
    with slots.stream(), slots.stream():
        assert slots.free_streams() == 0
        with pytest.raises(ResourceExhausted, match="limit 2"):
            with slots.stream():
                pass
    assert slots.free_streams() == 2


@pytest.fixture(scope="module")
def engine(tmp_path_factory):
    return SceneEngine.open(blob_scene(tmp_path_factory.mktemp("m") / "blobs")[0])


def test_text_chunks_stay_under_the_cap_and_join_to_the_answer(engine):
    q = torch.randn(engine.dim)
    a = engine.text_query(q, 150)
    fields = {pb.GAUSSIAN_FIELD_MEAN, pb.GAUSSIAN_FIELD_COLOR, pb.GAUSSIAN_FIELD_SIMILARITY}
    chunks = list(responses.text_chunks(engine, 2, "q", a, fields, 1.5, chunk_bytes=1024))
    assert len(chunks) > 1 and all(c.ByteSize() < 1024 + 512 for c in chunks)
    assert chunks[0].text == "q" and chunks[0].total == 150 and all(c.text_index == 2 for c in chunks)
    index = np.concatenate([from_tensor(c.index, "index") for c in chunks])
    mean = np.concatenate([from_tensor(c.mean, "mean") for c in chunks])
    assert np.array_equal(index, a.index.numpy())
    assert np.array_equal(mean, engine.gaussian_columns(a.index, ["mean"])["mean"])
    assert [c.start for c in chunks] == sorted(c.start for c in chunks)


def test_render_and_segment_chunks(engine):
    cam = camera()
    out = render_pose(engine, cam, torch.randn(engine.dim), ("relevancy", "alpha"))
    chunks = list(responses.render_chunks(7, cam, out, pb.IMAGE_ENCODING_FLOAT32, 2.0, chunk_bytes=2000))
    assert len(chunks) > 1 and chunks[-1].last and not any(c.last for c in chunks[:-1])
    rel = np.concatenate([from_tensor(c.relevancy, "relevancy") for c in chunks])
    assert np.array_equal(rel, out.relevancy.numpy()) and chunks[0].argmax.value == out.argmax[2]
    png = list(responses.render_chunks(7, cam, out, pb.IMAGE_ENCODING_PNG, 2.0, chunk_bytes=2000))
    assert len(png) == 1 and png[0].last and png[0].relevancy_png[:4] == b"\x89PNG"
    s = segment(engine, torch.randn(3, engine.dim), cam, per_gaussian=True)
    seg = responses.segment_chunks(["a", "b", "c"], cam, s, 1.0, chunk_bytes=512)
    assert seg[0].width == cam.width and seg[-1].last and sum(c.last for c in seg) == 1
    labels = np.concatenate(
        [from_tensor(c.gaussian_labels, "l") for c in seg if c.HasField("gaussian_labels")]
    )
    assert np.array_equal(labels, s.gaussian_labels.numpy())


def test_scene_info_from_the_manifest_or_the_engine(engine, tmp_path):
    m = engine.manifest
    info = responses.scene_info(SceneSlot("blobs", UNLOADED), m)
    assert info.state == pb.SCENE_STATE_UNLOADED and info.resident_bytes == 0
    assert (info.num_gaussians, info.num_embedded, info.embedding_dim) == (
        m.num_gaussians,
        m.num_selected,
        m.dim,
    )
    assert list(info.canonical_phrases) == list(m.canonical) and len(info.bounds) == 6
    loaded = responses.scene_info(SceneSlot("blobs", READY, engine=engine), None)
    assert loaded.state == pb.SCENE_STATE_READY and loaded.resident_bytes == engine.nbytes() > 0
    assert responses.scene_info(SceneSlot("x", UNLOADED), None).num_gaussians == 0  # unreadable manifest
    assert FmgsService.__name__ == "FmgsService" and isinstance(m, Manifest)
    # A scene built from a robot's recording says which frame its positions are in; others say none.
    assert info.frame_id == "" and m.frame_id == ""
    robot = dataclasses.replace(m, extra={**m.extra, "frame": {"id": "map", "units": "m"}})
    wire = responses.scene_info(SceneSlot("robot", UNLOADED), robot)
    assert wire.frame_id == "map" and ClientSceneInfo.from_proto(wire).frame_id == "map"
    assert ClientSceneInfo.from_proto(info).frame_id == ""


def test_a_request_stream_ended_by_a_late_cancel_is_logged_cancelled(caplog):
    """grpc ends a cancelled client's request stream before it marks the call inactive: the handler's
    normal end must wait briefly for that mark before reporting OK."""
    import logging
    import threading

    from fmgs_server.calls import rpc_stream

    class Svc:
        @rpc_stream
        def Stream(self, requests, context):
            for _ in requests:
                yield "frame"

    def poses(ctx, cancelled: bool):
        yield "pose"
        if cancelled:  # the cancellation lands 10 ms after the request stream ended
            threading.Timer(0.01, lambda: setattr(ctx, "active", False)).start()

    caplog.set_level(logging.INFO, logger="fmgs_server")
    for cancelled, expected in ((True, "CANCELLED"), (False, "OK")):
        ctx = Ctx()
        assert list(Svc().Stream(poses(ctx, cancelled), ctx)) == ["frame"]
        assert f" {expected} 1 msgs" in caplog.records[-1].getMessage()


def test_a_call_gone_at_its_deadline_is_logged_as_deadline_exceeded():
    """The client's cancel at its deadline can reach the server a few ms before the server's deadline."""
    ok = grpc.StatusCode.OK
    assert seen_by_client(Ctx(remaining=0.011, active=False), ok) == grpc.StatusCode.DEADLINE_EXCEEDED
    assert seen_by_client(Ctx(remaining=-0.2, active=False), ok) == grpc.StatusCode.DEADLINE_EXCEEDED
    assert seen_by_client(Ctx(remaining=10 * DEADLINE_SLACK_S, active=False), ok) == grpc.StatusCode.CANCELLED
    assert seen_by_client(Ctx(remaining=None, active=False), ok) == grpc.StatusCode.CANCELLED
    assert seen_by_client(Ctx(remaining=0.011, active=True), ok) == ok  # still there: the handler's code
