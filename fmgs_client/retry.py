"""How the client's channel retries reads and finds a restarted server: gRPC's own retry policy (a
service config) and its reconnect back-off, set as channel options.

A read (scene info, queries, renders, segmentation, health) that fails with ``UNAVAILABLE`` is tried
again with exponential back-off, as long as no answer message has arrived yet: unary reads by gRPC's
retry policy (the service config below), streamed reads by ``FmgsClient`` itself with the same settings
(grpcio's stream retries can leave a call hanging past its deadline when the connection drops). Calls
that change state (load, unload, reload) and pose streams are tried once.

The reconnect back-off is capped at about a second, so a server or cluster proxy that listens again is
found within that (gRPC's default cap is 120 s; its default back-off added 13 s after a 30 s outage).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

UNARY_READS = ("ListScenes", "GetScene", "PointQuery")
"""fmgs.v1.Fmgs unary methods that change nothing: gRPC's retry policy tries them again
(grpc.health.v1.Health/Check too)."""
STREAM_READS = ("TextQuery", "Render", "Segment", "Geometry")
"""Server-streaming methods that change nothing: FmgsClient tries them again itself, with the same
policy, while no message has arrived (grpcio's own stream retries can outlive the call's deadline when
the connection drops)."""
READS = UNARY_READS + STREAM_READS
MAX_ATTEMPTS = 5
"""gRPC's own cap on maxAttempts."""


@dataclass(frozen=True)
class RetryPolicy:
    """Retry and reconnect settings of a client channel."""

    attempts: int = 4
    """Tries of a read that fails with UNAVAILABLE (1: no retries; at most 5, gRPC's cap)."""
    initial_backoff_s: float = 0.2
    """Pause before the second try; each later pause is multiplied by ``backoff_multiplier`` (gRPC adds
    random jitter to each)."""
    max_backoff_s: float = 2.0
    backoff_multiplier: float = 2.0
    reconnect_initial_s: float = 0.25
    """First pause before reconnecting to a server that went away."""
    reconnect_max_s: float = 1.0
    """Longest pause between reconnection tries: a restarted server is found within about this."""

    def validate(self) -> None:
        if not 1 <= self.attempts <= MAX_ATTEMPTS:
            raise ValueError(f"retry attempts must be 1..{MAX_ATTEMPTS}, not {self.attempts}")
        if min(self.initial_backoff_s, self.max_backoff_s, self.reconnect_initial_s) <= 0:
            raise ValueError("retry and reconnect back-offs must be > 0")
        if self.max_backoff_s < self.initial_backoff_s or self.reconnect_max_s < self.reconnect_initial_s:
            raise ValueError("a maximum back-off must be >= its initial back-off")
        if self.backoff_multiplier < 1:
            raise ValueError("backoff_multiplier must be >= 1")


def service_config(policy: RetryPolicy) -> dict[str, Any]:
    """The gRPC service config (JSON object) of ``policy``: a retry policy on the unary reads."""
    policy.validate()
    if policy.attempts == 1:
        return {}
    names = [{"service": "fmgs.v1.Fmgs", "method": m} for m in UNARY_READS]
    names.append({"service": "grpc.health.v1.Health", "method": "Check"})
    return {
        "methodConfig": [
            {
                "name": names,
                "retryPolicy": {
                    "maxAttempts": policy.attempts,
                    "initialBackoff": f"{policy.initial_backoff_s:.3f}s",
                    "maxBackoff": f"{policy.max_backoff_s:.3f}s",
                    "backoffMultiplier": policy.backoff_multiplier,
                    "retryableStatusCodes": ["UNAVAILABLE"],
                },
            }
        ]
    }


def channel_options(policy: RetryPolicy) -> list[tuple[str, Any]]:
    """grpcio channel options: the service config above and the reconnect back-off."""
    ms = round(policy.reconnect_initial_s * 1000)
    opts: list[tuple[str, Any]] = [
        ("grpc.enable_retries", 1 if policy.attempts > 1 else 0),
        ("grpc.initial_reconnect_backoff_ms", ms),
        ("grpc.min_reconnect_backoff_ms", ms),
        ("grpc.max_reconnect_backoff_ms", round(policy.reconnect_max_s * 1000)),
    ]
    config = service_config(policy)
    if config:
        opts.append(("grpc.service_config", json.dumps(config)))
    return opts
