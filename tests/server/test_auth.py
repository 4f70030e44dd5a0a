"""Bearer-token access control (``fmgs_server.auth``): token files, and the interceptor on a tiny in-process
server: read and admin tokens, unary and streaming calls, open or closed health checks."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent import futures
from contextlib import contextmanager

import grpc
import pytest
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from fmgs_server.auth import ADMIN_METHODS, TokenAuth, read_tokens
from fmgs_server.config import ADMIN_CLOSED
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc

C = grpc.StatusCode
READ, ADMIN = b"r3ad", b"adm1n"


def test_read_tokens(tmp_path):
    assert read_tokens(None) == []
    f = tmp_path / "tokens"
    f.write_text("# readers\n\n  alpha  \nbeta\n# old: gamma\n")
    assert read_tokens(f) == [b"alpha", b"beta"]
    f.write_text("# nothing but comments\n\n")
    with pytest.raises(ValueError, match="no tokens in the file") as e:
        read_tokens(f)
    assert str(f) in str(e.value)


def test_token_files_saved_with_a_byte_order_mark_or_crlf(tmp_path):
    """Regression: a file saved with a UTF-8 byte order mark (Windows editors, PowerShell) kept it in its
    first token, which then never matched; CRLF line ends and blank lines are ignored."""
    f = tmp_path / "tokens"
    f.write_bytes(b"\xef\xbb\xbfalpha\r\n  beta \r\n\r\n# old\r\n")
    assert read_tokens(f) == [b"alpha", b"beta"]
    f.write_bytes(b"\xef\xbb\xbf# readers\r\ngamma\r\n")
    assert read_tokens(f) == [b"gamma"]
    f.write_bytes(b"\xef\xbb\xbf\r\n\r\n")  # nothing but the mark: refused, never an open server
    with pytest.raises(ValueError, match="no tokens in the file"):
        read_tokens(f)


def test_admin_methods_are_the_scene_admin_rpcs():
    names = {f"/fmgs.v1.Fmgs/{m.name}" for m in pb.DESCRIPTOR.services_by_name["Fmgs"].methods}
    assert ADMIN_METHODS == {
        "/fmgs.v1.Fmgs/LoadScene",
        "/fmgs.v1.Fmgs/UnloadScene",
        "/fmgs.v1.Fmgs/ReloadScene",
    }
    assert ADMIN_METHODS <= names


class _Scenes(pb_grpc.FmgsServicer):
    """Answers a read call (unary and streaming) and an admin call; the rest stay unimplemented."""

    def ListScenes(self, request, context):
        return pb.ListScenesResponse(scenes=[pb.SceneInfo(name="s")])

    def TextQuery(self, request, context):
        yield pb.TextQueryChunk(text="t")

    def LoadScene(self, request, context):
        return pb.SceneInfo(name=request.scene)


@contextmanager
def _served(auth: TokenAuth) -> Iterator[grpc.Channel]:
    server = grpc.server(futures.ThreadPoolExecutor(2), interceptors=[auth])
    pb_grpc.add_FmgsServicer_to_server(_Scenes(), server)
    hs = health.HealthServicer()
    hs.set("", health_pb2.HealthCheckResponse.SERVING)
    hs.set("fmgs.v1.Fmgs/s", health_pb2.HealthCheckResponse.SERVING)
    health_pb2_grpc.add_HealthServicer_to_server(hs, server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
            yield ch
    finally:
        server.stop(None)


def _calls(ch: grpc.Channel):
    """name -> call(metadata) for a read unary, a read stream, an admin call and a health check."""
    stub, hstub = pb_grpc.FmgsStub(ch), health_pb2_grpc.HealthStub(ch)
    return {
        "list": lambda md: stub.ListScenes(pb.ListScenesRequest(), metadata=md, timeout=10).scenes[0].name,
        "query": lambda md: [c.text for c in stub.TextQuery(pb.TextQueryRequest(), metadata=md, timeout=10)],
        "load": lambda md: stub.LoadScene(pb.SceneRequest(scene="s"), metadata=md, timeout=10).name,
        "health": lambda md: hstub.Check(health_pb2.HealthCheckRequest(), metadata=md, timeout=10).status,
    }


def _outcome(call, token: bytes | str | None):
    md = (
        ()
        if token is None
        else (("authorization", token if isinstance(token, str) else f"Bearer {token.decode()}"),)
    )
    try:
        call(md)
        return "OK"
    except grpc.RpcError as e:
        return e.code(), e.details()


SERVING = health_pb2.HealthCheckResponse.SERVING


def test_read_and_admin_tokens():
    with _served(TokenAuth([READ], [ADMIN])) as ch:
        calls = _calls(ch)
        missing = (C.UNAUTHENTICATED, "missing bearer token")
        invalid = (C.UNAUTHENTICATED, "invalid bearer token")
        expect = {
            None: {"list": missing, "query": missing, "load": missing, "health": "OK"},
            b"wrong": {"list": invalid, "query": invalid, "load": invalid, "health": "OK"},
            READ: {"list": "OK", "query": "OK", "load": (C.PERMISSION_DENIED, "admin token required")},
            ADMIN: {"list": "OK", "query": "OK", "load": "OK"},
        }
        for token, want in expect.items():
            got = {name: _outcome(calls[name], token) for name in want}
            assert got == want, token
        # The scheme is case-insensitive and surrounding spaces are ignored; other schemes are no token.
        assert _outcome(calls["load"], "bearer  adm1n ") == "OK"
        assert _outcome(calls["list"], "Basic r3ad") == missing
        assert calls["load"]((("authorization", "Bearer adm1n"),)) == "s"
        assert calls["query"]((("authorization", "Bearer r3ad"),)) == ["t"]


def test_read_only_tokens_have_no_admin():
    closed = (C.PERMISSION_DENIED, ADMIN_CLOSED)
    with _served(TokenAuth([READ], [])) as ch:
        calls = _calls(ch)
        assert _outcome(calls["list"], READ) == "OK"
        assert {_outcome(calls["load"], t) for t in (READ, ADMIN, None)} == {closed}
    with _served(TokenAuth([READ], [], admin_open=True)) as ch:  # opened: admin calls as queries
        calls = _calls(ch)
        assert _outcome(calls["load"], READ) == "OK"
        assert _outcome(calls["load"], ADMIN) == (C.UNAUTHENTICATED, "invalid bearer token")
        assert _outcome(calls["load"], None) == (C.UNAUTHENTICATED, "missing bearer token")


def test_without_tokens_admin_calls_are_closed_unless_opened():
    with _served(TokenAuth([], [])) as ch:
        calls = _calls(ch)
        got = {name: _outcome(call, None) for name, call in calls.items()}
        assert got == {**dict.fromkeys(calls, "OK"), "load": (C.PERMISSION_DENIED, ADMIN_CLOSED)}
        assert "--admin-token-file" in ADMIN_CLOSED and "--admin-open" in ADMIN_CLOSED
    # admin_open does not weaken admin tokens: with them, an admin token is still needed.
    with _served(TokenAuth([READ], [ADMIN], admin_open=True)) as ch:
        assert _outcome(_calls(ch)["load"], READ) == (C.PERMISSION_DENIED, "admin token required")


def test_health_can_need_a_token():
    with _served(TokenAuth([READ], [ADMIN], health_open=False)) as ch:
        check = _calls(ch)["health"]
        assert _outcome(check, None) == (C.UNAUTHENTICATED, "missing bearer token")
        assert _outcome(check, b"wrong") == (C.UNAUTHENTICATED, "invalid bearer token")
        assert check((("authorization", "Bearer r3ad"),)) == SERVING
        assert check((("authorization", "Bearer adm1n"),)) == SERVING


def test_no_tokens_means_open_and_unknown_methods_stay_unimplemented():
    with _served(TokenAuth([], [], admin_open=True)) as ch:
        calls = _calls(ch)
        assert {name: _outcome(call, None) for name, call in calls.items()} == dict.fromkeys(calls, "OK")
    with _served(TokenAuth([READ], [ADMIN])) as ch:
        # Not a method of the server: UNIMPLEMENTED, whatever the token (the interceptor passes it on).
        unknown = ch.unary_unary("/fmgs.v1.Fmgs/NoSuchMethod")
        assert _outcome(lambda md: unknown(b"", metadata=md, timeout=10), None)[0] == C.UNIMPLEMENTED
        # Implemented by no one in _Scenes: the token is checked first, then the default servicer answers.
        segment = pb_grpc.FmgsStub(ch).Segment
        assert (
            _outcome(lambda md: list(segment(pb.SegmentRequest(), metadata=md, timeout=10)), None)[0]
            == C.UNAUTHENTICATED
        )
        assert (
            _outcome(lambda md: list(segment(pb.SegmentRequest(), metadata=md, timeout=10)), READ)[0]
            == C.UNIMPLEMENTED
        )


def test_scene_health_needs_a_token_unless_opened():
    def scene_health(ch, md):
        stub = health_pb2_grpc.HealthStub(ch)
        return stub.Check(
            health_pb2.HealthCheckRequest(service="fmgs.v1.Fmgs/s"), metadata=md, timeout=10
        ).status

    with _served(TokenAuth([READ], [ADMIN])) as ch:
        server_health = _calls(ch)["health"]
        assert _outcome(server_health, None) == "OK"  # orchestrators need no token
        refused = (C.UNAUTHENTICATED, "a scene's health needs a bearer token")
        assert _outcome(lambda md: scene_health(ch, md), None) == refused
        assert _outcome(lambda md: scene_health(ch, md), b"wrong") == refused
        assert scene_health(ch, (("authorization", "Bearer r3ad"),)) == SERVING
    with _served(TokenAuth([READ], [ADMIN], scene_health_open=True)) as ch:
        assert scene_health(ch, None) == SERVING
