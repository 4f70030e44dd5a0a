"""``FmgsClient`` end to end against a small in-process fake of the service: every call, tokens, errors."""

from __future__ import annotations

import numpy as np
import pytest

from fmgs_client.client import FmgsClient, FmgsError
from fmgs_client.types import CameraSpec
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from tests.helpers.client_fakes import serve_fake


@pytest.fixture(scope="module")
def fake():
    with serve_fake() as served:
        yield served


def test_client_against_fake(fake):
    svc, address = fake
    with FmgsClient(address, token="s3cret", timeout=10) as c:
        scenes = c.list_scenes()
        assert [s.state for s in scenes] == ["ready", "failed"] and scenes[1].reason == "bad file"
        info = c.scene("demo")
        np.testing.assert_array_equal(info.bounds, [[-1, -1, 0], [1, 1, 0.5]])
        assert info.canonical_phrases == ("object", "stuff")
        with pytest.raises(FmgsError) as e:
            c.scene("nope")
        assert e.value.code == "NOT_FOUND" and "nope" in e.value.details
        answers = c.query("demo", ["a", "b"], top_k=6, fields=["mean"], instances={"eps": 0.1})
        req = svc.requests[-1]
        assert req.instances.enabled and req.instances.eps == 0.1 and pb.GAUSSIAN_FIELD_INSTANCE in req.fields
        assert [len(a) for a in answers] == [6, 6] and answers[0].mean.shape == (6, 3)
        assert answers[1].instance.dtype == np.int32 and len(answers[1].instances) == 1
        cam = CameraSpec.look_at((0, -3, 1), (0, 0, 0), width=8, height=7)
        r = c.render("demo", cam, "a", outputs=("relevancy", "rgb"))
        assert r.relevancy.shape == (7, 8) and r.rgb.shape == (7, 8, 3) and r.argmax.x == 7
        with pytest.raises(FmgsError, match="INVALID_ARGUMENT: text"):
            c.render("demo", cam, "")
        cams = [CameraSpec.look_at((0, -3, k), (0, 0, 0), width=4, height=5) for k in range(5)]
        seqs = [x.sequence for x in c.stream("demo", iter(cams), "a")]
        assert seqs == [0, 1, 2, 3, 4]
        assert [q.sequence for q in svc.requests[-5:]] == [0, 1, 2, 3, 4]
        with pytest.raises(TypeError, match="CameraSpec"):
            list(c.stream("demo", [cams[0], "not a camera"], "a"))
        p = c.points("demo", ["a", "b", "c"], np.array([[1.0, 2, 3], [4, 5, 6]]))
        assert p.relevancy.shape == (3, 2) and p.relevancy[2, 1] == 4
        s = c.segment("demo", ["x", "y"], camera=cam)
        assert s.pixel_labels.shape == (7, 8) and list(s.gaussian_labels) == [0, 1, 0]
        assert c.load("demo").name == "demo"
        with pytest.raises(FmgsError) as e:
            c.unload("demo")
        assert e.value.code == "UNIMPLEMENTED"
        assert c.health() == "SERVING" and c.health("fmgs.v1.Fmgs") == "NOT_SERVING"
        with pytest.raises(FmgsError, match="NOT_FOUND"):
            c.health("other")
    assert set(svc.auth) == {"Bearer s3cret"}
    with FmgsClient(address) as c:
        c.list_scenes()
    assert svc.auth[-1] is None


def test_unreachable_server_is_an_fmgs_error():
    with FmgsClient("127.0.0.1:1", timeout=2) as c, pytest.raises(FmgsError) as e:
        c.list_scenes()
    assert e.value.code in ("UNAVAILABLE", "DEADLINE_EXCEEDED")
