"""Server configuration: every limit with a safe default (docs/serving.md lists them with status codes)."""

from __future__ import annotations

import ipaddress
import os
from dataclasses import dataclass, field
from pathlib import Path

from fmgs.query.config import POINT_CHUNK, IndexConfig
from fmgs.scene.manifest import MODELS
from fmgs_wire import DEFAULT_PORT

MiB = 1 << 20
PATH_FIELDS = ("models", "tls_cert", "tls_key", "client_ca", "token_file", "admin_token_file")
"""ServerConfig's fields that hold paths: a str given for one becomes a Path."""


@dataclass(frozen=True)
class ServerConfig:
    """How ``fmgs-server`` runs (every field is a flag and a key of the --config TOML file)."""

    models: Path = Path(MODELS)
    """The scene repository: one folder per scene package."""
    host: str = "127.0.0.1"
    """Interface to bind (loopback unless told otherwise)."""
    port: int = DEFAULT_PORT
    """Port to bind; 0 picks a free one (tests)."""
    workers: int = 0
    """Requests computing at once (renders, ranking); 0 = the machine's CPU count."""
    max_concurrent_rpcs: int = 64
    """Open RPCs (streams included) beyond which new calls get RESOURCE_EXHAUSTED."""
    max_streams: int = 32
    """Concurrent StreamRender calls; more get RESOURCE_EXHAUSTED."""
    queue_timeout_s: float = 10.0
    """A request waiting longer than this for a compute slot gets RESOURCE_EXHAUSTED."""
    max_receive_bytes: int = 16 * MiB
    """Largest request message."""
    chunk_bytes: int = 1 * MiB
    """Payload per streamed chunk (responses are split by rows to stay under it)."""
    max_send_bytes: int = 64 * MiB
    """Largest response message (a PNG answer must fit in one)."""
    max_image_side: int = 4096
    """Largest width or height of a rendered image."""
    max_image_pixels: int = 4096 * 2160
    """Largest width * height."""
    max_top_k: int = 1_000_000
    """Largest top_k of a text query."""
    default_top_k: int = 100
    """top_k when a request leaves it 0."""
    max_texts: int = 64
    """Texts (or class names) per request."""
    max_text_chars: int = 1000
    """Characters per text."""
    max_points: int = 1_000_000
    """Points per point query (texts x points x 8 bytes must also fit max_send_bytes)."""
    default_geometry: int = 200_000
    """Gaussians a geometry call returns when it leaves max_gaussians 0 (a viewer's points)."""
    max_geometry: int = 2_000_000
    """Most Gaussians one geometry call may ask for (48 bytes each on the wire)."""
    max_instance_pairs: int = 1 << 22
    """Most pairs of a text query's answer Gaussians within ``instances.eps`` of each other that instance
    grouping lists (fmgs.query.instances.MAX_NEIGHBOUR_PAIRS); they are counted first, and more are
    INVALID_ARGUMENT before any is listed."""
    point_chunk: int = POINT_CHUNK
    """Points through the field at once: a point query's working memory grows with it, not with the
    request's size (the memory per point: benchmarks/results/TUNING.md); the deadline is checked between
    chunks."""
    memory_budget_bytes: int = 0
    """Resident bytes for loaded scenes; least recently used scenes are unloaded beyond it (0: no limit)."""
    work_memory_bytes: int = 2048 * MiB
    """Working memory of the requests in flight, estimated per request before it allocates and held
    until its answer is consumed; beyond it RESOURCE_EXHAUSTED (0: no limit)."""
    reload_check_s: float = 2.0
    """How often a scene's files are checked for changes (on access)."""
    preload: bool = False
    """Load every scene (and its text encoder) at start instead of on first use, and warm up the render
    kernels on each (numba compiles them on first use and caches them on disk), so no request pays it.
    Health is NOT_SERVING until then: a scene's own name until that scene is warm, the server's ("" and
    fmgs.v1.Fmgs) until every scene's warm-up has ended (docs/serving.md#health-and-readiness)."""
    index: IndexConfig = field(default_factory=IndexConfig)
    """Per-Gaussian query state of every scene (flags --index-rank, --index-exact-below, ...)."""
    device: str = "cpu"
    """Device for scenes and text encoders."""
    backend: str = "auto"
    """Rasteriser backend of renders and segmentation: auto, cpu, reference, cuda (gsplat) or triton (the
    one-pass forward kernel on a CUDA device) (docs/rendering.md)."""
    model_downloads: bool = True
    """Fetch a scene's text encoder from the hub (HF_ENDPOINT) on first use when it is neither a local
    folder nor in the hub cache; off for locked-down deployments (then such a scene's queries fail,
    naming the model, its revision, this setting and the command that pre-fetches it). HF_HUB_OFFLINE=1
    also turns it off. Hub calls time out after FMGS_HUB_TIMEOUT seconds (10)."""
    allow_newer_model: bool = False
    """Query a scene with whatever revision of its text encoder the hub cache (or hub) has now. Off: the
    revision its manifest records, checked against the recorded sha256 of each file; a scene whose
    recorded revision cannot be had, or whose cached files differ, fails its queries naming the model."""
    text_cache: int = 4096
    """Text embeddings cached per encoder."""
    presence_rule: str = "mean"
    """How a text query's best Gaussians decide ``found`` (fmgs.query.presence.PresenceConfig.rule):
    "mean", the mean embedding of presence_pool of them must beat every presence negative; "each",
    presence_quorum of them must each beat it."""
    presence_pool: int = 10
    """With presence_rule "mean": best Gaussians whose mean embedding decides
    (fmgs.query.presence.PresenceConfig.pool)."""
    presence_quorum: int = 1
    """With presence_rule "each": best Gaussians that must each beat every presence negative
    (fmgs.query.presence.PresenceConfig.quorum); 1: one suffices."""
    tls_cert: Path | None = None
    """Server certificate (PEM); with tls_key enables TLS."""
    tls_key: Path | None = None
    """Server private key (PEM)."""
    client_ca: Path | None = None
    """CA bundle (PEM) that client certificates must chain to: mutual TLS."""
    token_file: Path | None = None
    """Bearer tokens allowed to query, one per line (absent: no token needed)."""
    admin_token_file: Path | None = None
    """Bearer tokens allowed to load, unload and reload scenes, one per line. Without it admin calls are
    refused (PERMISSION_DENIED) unless admin_open, or unless the server binds loopback only and has no
    token file at all."""
    admin_open: bool = False
    """Answer admin calls (LoadScene, UnloadScene, ReloadScene) without an admin token (they then need
    what queries need: a read token when token_file is set). For trusted networks only."""
    health_open: bool = True
    """The server's health checks need no token (orchestrators)."""
    scene_health_open: bool = False
    """Per-scene health checks need no token either (with tokens on, they would let anyone probe scene
    names)."""
    grace_s: float = 10.0
    """In-flight requests get this long to finish on SIGTERM."""

    def __post_init__(self) -> None:
        # A caller may spell a path as a str (as TOML and most Python code do); the server calls Path
        # methods on them, so a str models made every call fail with INTERNAL.
        for name in PATH_FIELDS:
            value = getattr(self, name)
            if value is not None and not isinstance(value, Path):
                object.__setattr__(self, name, Path(value))

    @property
    def admin_without_token(self) -> bool:
        """Whether admin calls are answered without an admin token: admin_open, or a server bound to
        loopback only with no token file at all (a developer's own machine)."""
        if self.admin_token_file is not None:
            return False
        return self.admin_open or (self.token_file is None and loopback_only(self.host))

    def presence(self):
        """The text queries' fmgs.query.presence.PresenceConfig (imported here: this module has no torch)."""
        from fmgs.query.presence import PresenceConfig

        return PresenceConfig(rule=self.presence_rule, pool=self.presence_pool, quorum=self.presence_quorum)

    @property
    def compute_slots(self) -> int:
        return self.workers or os.cpu_count() or 1

    def validate(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be in [0, 65535], got {self.port}")
        positive = (
            "max_concurrent_rpcs max_streams max_receive_bytes chunk_bytes max_send_bytes max_image_side "
            "max_image_pixels max_top_k default_top_k max_texts max_text_chars max_points text_cache "
            "point_chunk default_geometry max_geometry max_instance_pairs presence_quorum presence_pool"
        ).split()
        for name in positive:
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")
        rules = ("mean", "each")  # fmgs.query.presence.RULES (no torch here)
        if self.presence_rule not in rules:
            raise ValueError(f"presence_rule must be one of {rules}, got {self.presence_rule!r}")
        if self.presence_pool > 64:  # fmgs.query.presence.PresenceConfig.rows: the rows ranked
            raise ValueError(
                f"presence_pool must be <= 64 (the rows a query ranks for presence), got {self.presence_pool}"
            )
        if self.presence_quorum != 1 and self.presence_rule != "each":
            raise ValueError("presence_quorum needs presence_rule 'each' (the mean decides with one margin)")
        if self.work_memory_bytes < 0 or self.memory_budget_bytes < 0:
            raise ValueError("work_memory_bytes and memory_budget_bytes must be >= 0 (0: no limit)")
        backends = ("auto", "cpu", "reference", "cuda", "triton")  # fmgs.render.BACKENDS (no torch here)
        if self.backend not in backends:
            raise ValueError(f"backend must be one of {backends}, got {self.backend!r}")
        if self.default_top_k > self.max_top_k:
            raise ValueError("default_top_k must not exceed max_top_k")
        if self.default_geometry > self.max_geometry:
            raise ValueError("default_geometry must not exceed max_geometry")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key go together")
        if self.client_ca is not None and self.tls_cert is None:
            raise ValueError("client_ca (mutual TLS) needs tls_cert and tls_key")
        if self.admin_open and self.admin_token_file is not None:
            raise ValueError("admin_open and admin_token_file contradict each other: choose one")


ADMIN_CLOSED = (
    "admin calls are closed: set --admin-token-file (admin_token_file), or --admin-open (admin_open) to "
    "answer them without a token"
)
"""The PERMISSION_DENIED text of an admin call on a server whose admin calls are closed."""


def loopback_only(host: str) -> bool:
    """Whether binding ``host`` accepts connections from this machine only (127.0.0.0/8, ::1, localhost)."""
    if host.strip("[]").lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to any interface
