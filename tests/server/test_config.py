"""ServerConfig: path fields given as strings (a Python caller's natural spelling) are paths."""

from __future__ import annotations

from pathlib import Path

import grpc

from fmgs_server.config import ServerConfig
from fmgs_server.server import start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from tests.helpers.query_scenes import FakeEncoder, blob_scene


def test_path_fields_given_as_str_become_paths(tmp_path):
    names = ("tls_cert", "tls_key", "client_ca", "token_file", "admin_token_file")
    cfg = ServerConfig(models="models", **{n: f"{n}.pem" for n in names})
    assert cfg.models == Path("models") and all(getattr(cfg, n) == Path(f"{n}.pem") for n in names)
    assert ServerConfig().token_file is None and ServerConfig(models=Path("m")).models == Path("m")


def test_a_server_on_a_str_repository_answers(tmp_path):
    """Given a str, every call used to fail with INTERNAL (the scene listing called Path methods on it)."""
    blob_scene(tmp_path / "blobs", with_field=True)
    cfg = ServerConfig(models=str(tmp_path), port=0, reload_check_s=0.0)
    srv = start_server(cfg, encoder_factory=lambda i: FakeEncoder())
    try:
        with grpc.insecure_channel(srv.address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            assert [s.name for s in stub.ListScenes(pb.ListScenesRequest()).scenes] == ["blobs"]
            chunks = list(stub.TextQuery(pb.TextQueryRequest(scene="blobs", texts=["red cube"], top_k=3)))
            assert chunks and chunks[0].text == "red cube"
    finally:
        srv.stop(0)


def test_admin_calls_need_a_token_unless_opened_or_on_loopback_alone():
    import pytest

    from fmgs_server.config import loopback_only

    for host in ("127.0.0.1", "127.0.0.2", "::1", "[::1]", "localhost"):
        assert loopback_only(host), host
    for host in ("0.0.0.0", "::", "[::]", "10.1.2.3", "example.org"):
        assert not loopback_only(host), host
    assert ServerConfig().admin_without_token  # the default binds 127.0.0.1
    assert not ServerConfig(host="0.0.0.0").admin_without_token
    assert ServerConfig(host="0.0.0.0", admin_open=True).admin_without_token
    # Tokens in use: loopback alone no longer opens admin calls; an admin token file closes them.
    assert not ServerConfig(token_file="read").admin_without_token
    assert ServerConfig(token_file="read", admin_open=True).admin_without_token
    assert not ServerConfig(admin_token_file="admin").admin_without_token
    with pytest.raises(ValueError, match="admin_open and admin_token_file"):
        ServerConfig(admin_open=True, admin_token_file="admin").validate()
