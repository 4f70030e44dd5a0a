"""How the service runs on a Ray cluster (``fmgs-server --ray``); every field is a ``--ray-*`` flag."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ClusterConfig:
    """Ray Serve settings of the cluster deployment (the ServerConfig limits apply in every replica)."""

    app_name: str = "fmgs"
    """Serve application name (clients need no metadata while it is the cluster's only application)."""
    min_replicas: int = 1
    """Fewest scene replicas (autoscaling lower bound; 0 lets the deployment scale to zero)."""
    max_replicas: int = 4
    """Most scene replicas (autoscaling upper bound)."""
    target_ongoing_requests: float = 2.0
    """Requests in flight per scene replica that autoscaling aims for."""
    max_ongoing_requests: int = 16
    """Requests one scene replica accepts at once; more wait in the router's queue."""
    max_queued_requests: int = -1
    """Requests queued per caller beyond which new ones get RESOURCE_EXHAUSTED (-1: no limit)."""
    scenes_per_replica: int = 8
    """Scenes (or shards) one replica holds before Ray's multiplexer evicts its least recently used
    (memory_budget_bytes still unloads earlier within a replica)."""
    replica_cpus: float = 1.0
    """CPUs reserved per scene replica (Ray scheduling; size it to --workers)."""
    replica_gpus: float = 0.0
    """GPUs per scene replica (with --device cuda)."""
    ingress_replicas: int = 1
    """Replicas of the ingress deployment (light: it routes, checks tokens, merges shard answers)."""
    read_attempts: int = 3
    """Tries of a read (queries, renders, scene info) whose scene replica is lost while answering; the
    later tries go to another replica. Calls that change state are tried once."""
    health_timeout_s: float = 5.0
    """How long a health check waits for a scene replica to answer before it says NOT_SERVING."""
    request_timeout_s: float = 0.0
    """End-to-end cap per request at the proxy (0: none). Clients' deadlines are not forwarded by
    Ray Serve's proxy: the client still gives up at its deadline, the cluster stops at this cap."""

    def validate(self) -> None:
        if not self.app_name or not 0 <= self.min_replicas <= self.max_replicas or self.max_replicas < 1:
            raise ValueError("ray: a name and 0 <= min_replicas <= max_replicas, max_replicas >= 1 required")
        if self.target_ongoing_requests <= 0 or self.max_ongoing_requests < 1:
            raise ValueError("ray: target_ongoing_requests > 0 and max_ongoing_requests >= 1 required")
        if self.scenes_per_replica < 1 or self.ingress_replicas < 1:
            raise ValueError("ray: scenes_per_replica >= 1 and ingress_replicas >= 1 required")
        if self.replica_cpus < 0 or self.replica_gpus < 0 or self.request_timeout_s < 0:
            raise ValueError("ray: replica_cpus, replica_gpus and request_timeout_s must be >= 0")
        if self.read_attempts < 1 or self.health_timeout_s <= 0:
            raise ValueError("ray: read_attempts >= 1 and health_timeout_s > 0 required")
