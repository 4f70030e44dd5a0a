"""What differs between the quick (CI) and the full run: one frozen dataclass per section."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TextSizes:
    """Text-query work-precision sizes."""

    gaussians: int
    """Embedded Gaussians of the field-like scene (D = 512)."""
    queries: int
    """Queries per query set (benchmarks/query_sets.py), each timed once per setting (settings interleaved
    per query)."""
    top_k: int = 100
    """K of the top-K lists compared."""
    ranks: tuple[int, ...] = (16, 32, 64, 128)
    """First-tier ranks of the compact (int8) state."""
    subsets: tuple[float, ...] = (0.25, 0.5, 0.75)
    """Fractions of the most opaque Gaussians ranked by the subset knob."""


@dataclass(frozen=True)
class PoseSizes:
    """Pose-query work-precision sizes."""

    scene: str
    """'garden' or 'synthetic-<N>' (benchmarks/raster.py make_scene)."""
    width: int
    """Image width."""
    height: int
    """Image height."""
    queries: int
    """Query texts (vectors near scene embeddings)."""
    reps: int
    """Timed passes over the queries (settings interleaved)."""


@dataclass(frozen=True)
class SceneSizes:
    """The synthetic labelled scene (fmgs synth) and its 3DGS fits."""

    views: int
    """Cameras (every 8th held out)."""
    width: int
    """Image width."""
    height: int
    """Image height."""
    points: int = 6000
    """Surface samples written for initialisation."""
    init_points: int = 3000
    """Initial Gaussians (the samples subsampled)."""
    grad_threshold: float = 0.001
    """Densification threshold (GS.md: the default 0.0002 grows ~45K Gaussians in 200 steps here)."""
    max_gaussians: int = 30_000
    """Growth cap (bounds the CPU time per step)."""


@dataclass(frozen=True)
class FieldSizes:
    """Feature-field training sizes."""

    steps: tuple[int, ...]
    """Step counts of the steps curve (default settings otherwise)."""
    base_steps: int
    """Steps of every other knob's runs."""
    paper_steps: int
    """The paper's step count (a point of the steps curve when it is in ``steps``)."""
    gs_steps: int
    """Which 3DGS fit (of GSSizes.steps) provides the frozen geometry."""
    feature_scales: tuple[float, ...] = (0.25, 0.5, 1.0)
    """Feature-map resolution (fraction of the image) of the targets."""
    log2_tables: tuple[int, ...] = (12, 16, 20)
    """Hash-table sizes per level (log2)."""
    levels: tuple[int, ...] = (8, 16, 24)
    """Hash-grid levels (resolutions 16 to 512 in every case)."""


@dataclass(frozen=True)
class GSSizes:
    """3DGS training sizes."""

    steps: tuple[int, ...]
    """Step counts (each a full run of the schedule compressed to it)."""


@dataclass(frozen=True)
class ScalingSizes:
    """Scaling sizes."""

    text_built: tuple[int, ...]
    """Sizes built from field-like embeddings like a package (compact and exact states)."""
    text_tiled: tuple[int, ...]
    """Larger sizes: the largest built state's int8 coefficients tiled (latency and memory only)."""
    text_queries: int
    """Queries per size."""
    render_counts: tuple[int, ...]
    """Gaussian counts of the synthetic render scene."""
    render_size: tuple[int, int]
    """Image size of the count sweep."""
    render_pixels_scene: str
    """Scene of the pixel sweep."""
    render_pixel_sizes: tuple[tuple[int, int], ...]
    """Image sizes of the pixel sweep."""
    render_reps: int
    """Timed renders per setting."""
    grpc_gaussians: int
    """Gaussians of the scene served over gRPC."""
    grpc_clients: tuple[int, ...] = (1, 2, 4, 8, 16, 32)
    """Concurrent clients."""
    grpc_requests_per_client: int = 10
    """Text queries per client per level (at least 40 per level)."""


@dataclass(frozen=True)
class FloorSizes:
    """Physical-limit sizes."""

    stream_bytes: int
    """Array read to measure memory bandwidth."""
    matmul_n: int
    """Edge of the float32 matmul that measures the arithmetic rate."""
    compact_gaussians: int
    """Gaussians of the compact (int8, rank 64) scan measured against its floor."""
    exact_gaussians: int
    """Gaussians of the exact float32 scan measured against its floor."""
    render_scene: str
    """Scene of the render measured against its floor."""
    render_size: tuple[int, int]
    """Its image size."""
    reps: int = 7
    """Repetitions (rates: best run; measured times: median)."""


@dataclass(frozen=True)
class TargetSizes:
    """CLIP target blends: generated world scenes (fmgs synth --preset world) and views per scene."""

    seeds: tuple[int, ...]
    """Scene seeds (odd: open, even: in a room); the dev scenes of CLIP_TARGETS.md, no benchmark's seed."""
    views: int
    """Views per scene whose targets are made and scored (the first of the scene's cameras)."""
    width: int
    """Image width."""
    height: int
    """Image height."""
    scene_views: int = 12
    """Cameras each scene is generated with (the camera ring depends on it)."""


@dataclass(frozen=True)
class Sizes:
    """Everything that differs between the quick (CI) and the full run."""

    text: TextSizes
    pose: PoseSizes
    scene: SceneSizes
    field: FieldSizes
    gs: GSSizes
    scaling: ScalingSizes
    floor: FloorSizes
    targets: TargetSizes


QUICK = Sizes(
    text=TextSizes(gaussians=20_000, queries=2),
    pose=PoseSizes("synthetic-20000", 120, 68, queries=3, reps=1),
    scene=SceneSizes(views=24, width=64, height=48),
    field=FieldSizes(
        steps=(10, 20),
        base_steps=10,
        paper_steps=4200,
        gs_steps=80,
        feature_scales=(0.25, 0.5),
        log2_tables=(12, 20),
        levels=(8, 24),
    ),
    gs=GSSizes(steps=(20, 40, 80)),
    scaling=ScalingSizes(
        text_built=(10_000, 100_000),
        text_tiled=(300_000,),
        text_queries=5,
        render_counts=(10_000, 30_000, 100_000),
        render_size=(240, 135),
        render_pixels_scene="synthetic-20000",
        render_pixel_sizes=((120, 68), (240, 135), (480, 270)),
        render_reps=3,
        grpc_gaussians=20_000,
        grpc_clients=(1, 2, 4),
        grpc_requests_per_client=8,
    ),
    floor=FloorSizes(
        stream_bytes=256 << 20,
        matmul_n=1024,
        compact_gaussians=1_000_000,
        exact_gaussians=100_000,
        render_scene="synthetic-20000",
        render_size=(240, 135),
        reps=5,
    ),
    targets=TargetSizes(seeds=(301,), views=1, width=64, height=48),
)

FULL = Sizes(
    text=TextSizes(gaussians=1_000_000, queries=8),
    pose=PoseSizes("garden", 480, 270, queries=4, reps=3),
    scene=SceneSizes(views=32, width=64, height=48),
    field=FieldSizes(steps=(250, 500, 1000, 2000, 4200), base_steps=1000, paper_steps=4200, gs_steps=2000),
    gs=GSSizes(steps=(100, 300, 1000, 2000)),
    scaling=ScalingSizes(
        text_built=(10_000, 30_000, 100_000, 300_000, 1_000_000),
        text_tiled=(3_000_000, 10_000_000),
        text_queries=20,
        render_counts=(10_000, 30_000, 100_000, 300_000, 1_000_000, 3_000_000),
        render_size=(480, 270),
        render_pixels_scene="garden",
        render_pixel_sizes=((240, 135), (480, 270), (960, 540), (1920, 1080)),
        render_reps=5,
        grpc_gaussians=1_000_000,
    ),
    floor=FloorSizes(
        stream_bytes=1 << 30,
        matmul_n=2048,
        compact_gaussians=10_000_000,
        exact_gaussians=1_000_000,
        render_scene="garden",
        render_size=(480, 270),
    ),
    targets=TargetSizes(seeds=(301, 302, 303, 304), views=4, width=128, height=96),
)
