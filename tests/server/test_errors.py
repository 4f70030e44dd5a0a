"""The service's deliberate errors (``fmgs_server.errors``): each carries its gRPC status code and the
message the client sees."""

from __future__ import annotations

import grpc
import pytest

from fmgs_server import errors


@pytest.mark.parametrize(
    "cls, code",
    [
        (errors.ServiceError, grpc.StatusCode.INTERNAL),
        (errors.NotFound, grpc.StatusCode.NOT_FOUND),
        (errors.InvalidArgument, grpc.StatusCode.INVALID_ARGUMENT),
        (errors.FailedPrecondition, grpc.StatusCode.FAILED_PRECONDITION),
        (errors.ResourceExhausted, grpc.StatusCode.RESOURCE_EXHAUSTED),
        (errors.Unavailable, grpc.StatusCode.UNAVAILABLE),
        (errors.DeadlineExceeded, grpc.StatusCode.DEADLINE_EXCEEDED),
    ],
)
def test_service_errors_carry_their_status_code(cls, code):
    e = cls("scene 'x' not found")
    assert isinstance(e, errors.ServiceError) and e.code == code
    assert e.message == str(e) == "scene 'x' not found"
