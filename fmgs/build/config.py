"""What ``fmgs build`` runs: targets, the 3DGS and field stages, the package. Torch-free (flags and
config files are built from these fields)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from fmgs.data.rosbag_config import RecordingConfig
from fmgs.features.models import DEFAULT_CLIP_ID, DEFAULT_DINO_ID, MINILM_ID
from fmgs.features.sizes import (
    CROP_SCALES,
    CROP_STRIDE,
    FEATURE_SIDE,
    SCALE_BLEND,
    SCALE_BLENDS,
    check_feature_scale,
)
from fmgs.scene.manifest import FIELD_DTYPES, MODELS
from fmgs.sfm.config import SfMConfig
from fmgs.train.config import FieldTrainConfig, GSTrainConfig

TARGET_KINDS = ("clip", "labels")
SEGMENT_MAPS = ("blend", "finest")
EMBEDDING_NEIGHBOURS = 8
"""Default k of the stored embeddings' neighbour mean (fmgs.field.neighbours): 8, so that a text
query's first Gaussian lies in the object's midst; Gaussians without a dense neighbourhood keep the
field at their mean (1 everywhere: the paper)."""
MAX_EMBEDDING_NEIGHBOURS = 256
"""Upper bound on k: the package stage gathers k [block, D] slices per block of Gaussians."""


@dataclass(frozen=True)
class TargetSpec:
    """Which targets to distil."""

    kind: str = "clip"
    """"clip" (hybrid CLIP + DINO from pretrained models) or "labels" (label masks + a text encoder)."""
    clip_model: str = DEFAULT_CLIP_ID
    """CLIP model id (a local folder, the hub cache, else downloaded on first use) or a local folder."""
    dino_model: str | None = DEFAULT_DINO_ID
    """DINO model id or local folder; None for no DINO target."""
    single_scale: bool = False
    """Ablation: one crop scale instead of the 7-scale pyramid."""
    crop_scales: tuple[float, ...] = CROP_SCALES
    """The crop pyramid's scales (kind "clip"): each crop edge as a fraction of the image's shorter side.
    The default is the paper's 7; a finer first scale suits photos much larger than the feature maps,
    where it still spans enough pixels for the model to name (docs/field.md)."""
    crop_stride: float | None = CROP_STRIDE
    """Cap on the crop pyramid's stride, a fraction of the image's shorter side (kind "clip"): every
    scale's crops start at most this far apart; none: half the crop edge (the paper's, sparse at the
    coarse scales; fewer crops, small objects washed out)."""
    scale_blend: str | None = None
    """How the pyramid's scales become one target per pixel (kind "clip"; fmgs.features.scale_blend):
    "mean" (the paper's equal mean), "coherence" or "dominant" (each scale weighed by how much of its
    crop the DINO map groups with the pixel; need a dino_model); none (default): "dominant" with a
    dino_model, "mean" without (set on construction)."""
    segmenter: str | None = None
    """Class-agnostic segmenter id (kind "clip"; ``standin-seg:FOLDER``, SAM's role): the target of each
    pixel of a segment is the target map (segment_map) pooled over the segment
    (fmgs.features.segment_pool); none (default): no pooling."""
    segment_map: str = "blend"
    """What a segmenter pools: "blend" (the pyramid's scales blended by scale_blend) or "finest" (the
    finest scale alone, a seventh of the crops; scale_blend then does not apply)."""
    labels: str | None = None
    """Label image folder (kind "labels"); default DATA/labels."""
    names: str | None = None
    """scene.json (or a folder holding it) with label_names (kind "labels"); default DATA/scene.json."""
    text_encoder: str = MINILM_ID
    """Text encoder id for label names (kind "labels"): MiniLM from its wheel, or a CLIP model id
    (fetched on first use)."""
    feature_scale: float | None = None
    """Feature maps at this fraction of the image resolution; none (default): sized by feature_side."""
    feature_side: int = FEATURE_SIDE
    """Longer side of the feature maps in pixels when feature_scale is none (smaller images: full size)."""

    def __post_init__(self) -> None:
        if self.kind not in TARGET_KINDS:
            raise ValueError(f"targets kind must be one of {TARGET_KINDS}, got {self.kind!r}")
        check_feature_scale(self.feature_scale, self.feature_side)
        object.__setattr__(self, "crop_scales", tuple(float(c) for c in self.crop_scales))  # a TOML list
        if not self.crop_scales or not all(0.0 < c <= 1.0 for c in self.crop_scales):
            raise ValueError(f"crop_scales must be one or more fractions in (0, 1], got {self.crop_scales}")
        if len(set(self.crop_scales)) != len(self.crop_scales):
            raise ValueError(f"crop_scales must not repeat a scale, got {self.crop_scales}")
        if self.single_scale and self.crop_scales != CROP_SCALES:
            raise ValueError(
                "single_scale (the one-scale ablation, 0.25) replaces the pyramid: leave crop_scales at "
                "its default"
            )
        if self.crop_stride is not None and not 0.0 < self.crop_stride <= 1.0:
            raise ValueError(f"crop_stride must lie in (0, 1] or be none, got {self.crop_stride}")
        if self.segment_map not in SEGMENT_MAPS:
            raise ValueError(f"segment_map must be one of {SEGMENT_MAPS}, got {self.segment_map!r}")
        finest = self.pools_finest
        if finest and self.single_scale:
            raise ValueError(
                "single_scale (the one-scale ablation) and segment_map finest exclude each other"
            )
        if finest and self.scale_blend not in (None, "mean"):
            raise ValueError(
                f"scale_blend {self.scale_blend!r} blends the pyramid's scales; segment_map finest pools the "
                "finest scale alone: leave scale_blend unset (or mean), or choose segment_map blend"
            )
        if self.scale_blend is None:  # frozen: the default is resolved once, so manifests record it
            blend = SCALE_BLEND if self.dino_model and not finest else "mean"
            object.__setattr__(self, "scale_blend", blend)
        if self.scale_blend not in SCALE_BLENDS:
            raise ValueError(f"scale_blend must be one of {SCALE_BLENDS}, got {self.scale_blend!r}")
        if self.kind == "clip" and self.scale_blend != "mean" and not self.dino_model:
            raise ValueError(
                f"scale_blend {self.scale_blend!r} weighs the scales by DINO coherence and needs a "
                "dino_model; give one, or choose --scale-blend mean"
            )

    @property
    def pools_finest(self) -> bool:
        """A segmenter pools the finest scale alone: the pyramid cuts that scale only."""
        return self.segmenter is not None and self.segment_map == "finest"


@dataclass(frozen=True)
class BuildConfig:
    """What ``build_scene`` runs."""

    name: str
    """Scene name (folder under the model repository)."""
    models: str = MODELS
    """The model repository."""
    work: str | None = None
    """Work folder for intermediate outputs (default: WORK = <models>/.work/<name>)."""
    ply: str | None = None
    """An existing 3DGS scene (skip geometry training): .ply (graphdeco or compressed) or .splat."""
    recording: RecordingConfig = dataclasses.field(default_factory=RecordingConfig)
    """How a robot's ROS 2 recording (a bag folder, .mcap or .db3) given as the source becomes a dataset."""
    sfm: SfMConfig = dataclasses.field(default_factory=SfMConfig)
    """The poses stage (photos only; a posed dataset skips it)."""
    gs: GSTrainConfig = dataclasses.field(default_factory=GSTrainConfig)
    """The 3DGS stage (its device is ``device``; fewer steps compress its schedule, see ``scheduled``)."""
    allow_random_init: bool = False
    """Train the 3DGS stage of a posed dataset without sparse points from random Gaussians (in the
    cameras' common view); without it such a build stops and says what to supply, because random
    starts trained 6 dB below points (25.2-25.5 dB against 31.5 dB held-out, 2,000 steps, synthetic
    tabletop)."""
    targets: TargetSpec = dataclasses.field(default_factory=TargetSpec)
    """Feature targets."""
    field: FieldTrainConfig = dataclasses.field(default_factory=FieldTrainConfig)
    """Distillation settings."""
    include_dino: bool = False
    """Keep the DINO head in the package."""
    field_dtype: str = "float32"
    """Storage of the field's table and heads in the package: "float32" or "float16" (half the size)."""
    embedding_neighbours: int = EMBEDDING_NEIGHBOURS
    """Each stored embedding of a Gaussian whose k-1 nearest embedded Gaussians all lie within twice
    its largest scale is the unit mean of the field at its mean and theirs; the others keep the field
    at their mean (fmgs.field.neighbours). A text query's first Gaussian then lies in the object's
    midst, not at its rim; 1: the field at each mean alone (the paper)."""
    extra: dict = dataclasses.field(default_factory=dict)
    """Merged into the manifest's ``extra`` (e.g. a description); label targets add ``label_names``."""
    device: str = "cpu"
    """Torch device for every stage."""
    ray: str | None = None
    """Run the features stage on a Ray cluster's workers (fmgs[ray]): the address of a running cluster
    ("auto": the local node's), or "local" to start one here; none: in this process. 3DGS and field
    training stay in this process (each step needs the whole scene's gradients)."""

    def __post_init__(self) -> None:
        if self.field_dtype not in FIELD_DTYPES:
            raise ValueError(f"field_dtype must be one of {FIELD_DTYPES}, got {self.field_dtype!r}")
        k = self.embedding_neighbours
        if not 1 <= k <= MAX_EMBEDDING_NEIGHBOURS:
            raise ValueError(f"embedding_neighbours must lie in [1, {MAX_EMBEDDING_NEIGHBOURS}], got {k}")

    @classmethod
    def scheduled(cls, name: str, gs_steps: int | None = None, field_steps: int | None = None) -> BuildConfig:
        """Defaults with the 3DGS and field schedules compressed to the given step counts (the base that
        ``fmgs build`` applies its other settings to)."""
        gs = GSTrainConfig() if gs_steps is None else GSTrainConfig.reduced(gs_steps)
        fd = FieldTrainConfig() if field_steps is None else FieldTrainConfig().reduced(field_steps)
        return cls(name=name, gs=gs, field=fd)
