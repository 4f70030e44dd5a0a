"""Errors the service raises on purpose, each with its gRPC status code."""

from __future__ import annotations

import grpc


class ServiceError(Exception):
    """An error with a status code; the message is sent to the client."""

    code = grpc.StatusCode.INTERNAL
    final = False
    """True when the transport has already ended the call with ``code`` (logs then report it as is)."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class NotFound(ServiceError):
    code = grpc.StatusCode.NOT_FOUND


class InvalidArgument(ServiceError):
    code = grpc.StatusCode.INVALID_ARGUMENT


class FailedPrecondition(ServiceError):
    code = grpc.StatusCode.FAILED_PRECONDITION


class ResourceExhausted(ServiceError):
    code = grpc.StatusCode.RESOURCE_EXHAUSTED


class Unavailable(ServiceError):
    code = grpc.StatusCode.UNAVAILABLE


class DeadlineExceeded(ServiceError):
    code = grpc.StatusCode.DEADLINE_EXCEEDED


class Cancelled(ServiceError):
    code = grpc.StatusCode.CANCELLED


class UndecodableRequest(ServiceError):
    """grpc could not decode a message of the request stream and ended the call with INTERNAL itself."""

    code = grpc.StatusCode.INTERNAL
    final = True
