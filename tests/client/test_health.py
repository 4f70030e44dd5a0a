"""``FmgsClient.health`` through the standard grpc.health.v1 stubs, against tiny in-process servers: one
with the standard health servicer (every status), one that answers raw bytes (unknown fields, a status
newer than the client, a malformed answer), and one without the health service."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent import futures
from contextlib import contextmanager

import grpc
import pytest
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from fmgs_client import cli
from fmgs_client.client import FmgsClient, FmgsError, health_status_name
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc

ServingStatus = health_pb2.HealthCheckResponse
# Service name -> the status the standard servicer reports for it (a long name checks the request too).
STATUSES = {
    "": ServingStatus.SERVING,
    "fmgs.v1.Fmgs": ServingStatus.NOT_SERVING,
    "fmgs.v1.Fmgs/gone": ServingStatus.SERVICE_UNKNOWN,
    "x" * 300: ServingStatus.UNKNOWN,
}
# Service name -> the raw HealthCheckResponse bytes the raw server answers.
UNKNOWN_FIELDS = b"\x10\x05" + b"\x19" + b"\0" * 8 + b"\x22\x02ab" + b"\x2d" + b"\0" * 4  # every wire type
RAW_ANSWERS = {
    "unknown-fields": UNKNOWN_FIELDS + b"\x08\x01",
    "newer-status": b"\x08\x07",
    "truncated": b"\x08",
    "empty": b"",
}


@contextmanager
def _server(*register) -> Iterator[str]:
    """An in-process server on a free port with the given registrations; yields its address."""
    server = grpc.server(futures.ThreadPoolExecutor(2))
    for add in register:
        add(server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        yield f"127.0.0.1:{port}"
    finally:
        server.stop(None)


def _standard_health(server: grpc.Server) -> None:
    hs = health.HealthServicer()
    for service, status in STATUSES.items():
        hs.set(service, status)
    health_pb2_grpc.add_HealthServicer_to_server(hs, server)


def _raw_health(seen: list[str]):
    """Registers a Health/Check handler without serializers: it sees the request bytes, answers bytes."""

    def check(request: bytes, context) -> bytes:
        service = health_pb2.HealthCheckRequest.FromString(request).service
        seen.append(service)
        return RAW_ANSWERS[service]

    handler = grpc.method_handlers_generic_handler(
        "grpc.health.v1.Health", {"Check": grpc.unary_unary_rpc_method_handler(check)}
    )
    return lambda server: server.add_generic_rpc_handlers((handler,))


def _fmgs_only(server: grpc.Server) -> None:
    pb_grpc.add_FmgsServicer_to_server(pb_grpc.FmgsServicer(), server)


def test_every_status_of_the_standard_servicer():
    with _server(_standard_health) as address, FmgsClient(address, timeout=10) as c:
        got = {service: c.health(service) for service in STATUSES}
        assert got == {
            "": "SERVING",
            "fmgs.v1.Fmgs": "NOT_SERVING",
            "fmgs.v1.Fmgs/gone": "SERVICE_UNKNOWN",
            "x" * 300: "UNKNOWN",
        }
        assert c.health() == "SERVING"  # the default is the whole server
        with pytest.raises(FmgsError) as e:
            c.health("never registered")
        assert e.value.code == "NOT_FOUND"


def test_health_answers_decoded_by_the_standard_message():
    seen: list[str] = []
    with _server(_raw_health(seen)) as address, FmgsClient(address, timeout=10) as c:
        assert c.health("unknown-fields") == "SERVING"  # unknown fields of every wire type are skipped
        assert c.health("newer-status") == "UNKNOWN(7)"  # a status this client does not know by name
        assert c.health("empty") == "UNKNOWN"  # proto3 default
        with pytest.raises(FmgsError) as e:
            c.health("truncated")
        assert e.value.code == "DATA_LOSS" and "malformed health answer" in e.value.details
    assert seen == ["unknown-fields", "newer-status", "empty", "truncated"]  # service names arrive intact


def test_server_without_health_is_unimplemented():
    with _server(_fmgs_only) as address, FmgsClient(address, timeout=10) as c:
        with pytest.raises(FmgsError) as e:
            c.health()
        assert e.value.code == "UNIMPLEMENTED"


def test_health_status_names():
    assert [health_status_name(s) for s in range(4)] == [
        "UNKNOWN",
        "SERVING",
        "NOT_SERVING",
        "SERVICE_UNKNOWN",
    ]
    assert health_status_name(42) == "UNKNOWN(42)"


def test_cli_health_exit_status(capsys):
    with _server(_standard_health) as address:
        assert cli.main(["--address", address, "health", "fmgs.v1.Fmgs/gone"]) == 1
        assert capsys.readouterr().out.strip() == "SERVICE_UNKNOWN"
    with _server(_fmgs_only) as address:
        assert cli.main(["--address", address, "--timeout", "10", "health"]) == 1
        assert capsys.readouterr().err.startswith("error: UNIMPLEMENTED: ")
