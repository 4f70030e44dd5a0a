"""Training settings: 3DGS geometry (with its density control schedule) and feature-field distillation.

Kept free of torch so that command-line flags and config files can be built from them cheaply.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass, replace

from fmgs.data import HOLDOUT_EVERY
from fmgs.field.config import FieldConfig, SelectConfig


def _check(cfg, *, positive: str = "", non_negative: str = "", unit: str = "") -> None:
    """ValueError naming every field of ``cfg`` outside its range: ``positive`` (> 0), ``non_negative``
    (>= 0) and ``unit`` ([0, 1]) are space-separated field names (NaN fails every range)."""
    bad = [
        f"{name} must be {want}, got {getattr(cfg, name)!r}"
        for names, want, ok in (
            (positive, "> 0", lambda v: v > 0),
            (non_negative, ">= 0", lambda v: v >= 0),
            (unit, "in [0, 1]", lambda v: 0 <= v <= 1),
        )
        for name in names.split()
        if not ok(getattr(cfg, name))
    ]
    if bad:
        raise ValueError(f"{type(cfg).__name__}: " + "; ".join(bad))


@dataclass(frozen=True)
class DensifyConfig:
    """When and how to grow and prune (defaults: graphdeco 3DGS for 30K steps)."""

    refine_start: int = 500
    """First step that grows or prunes."""
    refine_stop: int = 15_000
    """No growing after this step (pruning of transparent Gaussians too)."""
    refine_every: int = 100
    """Steps between two refinements."""
    reset_every: int = 3_000
    """Steps between opacity resets."""
    grad_threshold: float = 0.0002
    """Grow a Gaussian whose mean view-space gradient (NDC units) exceeds this."""
    dense_percent: float = 0.01
    """Clone when the largest scale is below this fraction of the scene extent, else split."""
    prune_opacity: float = 0.005
    """Prune Gaussians more transparent than this."""
    prune_screen_px: float = 20.0
    """After the first reset, prune Gaussians whose projected radius exceeded this (pixels)."""
    prune_world: float = 0.1
    """After the first reset, prune Gaussians larger than this fraction of the scene extent."""
    reset_opacity: float = 0.01
    """Opacities are clamped to at most this at each reset."""
    max_gaussians: int = 3_000_000
    """Growth stops at this count (memory guard)."""

    def __post_init__(self) -> None:
        _check(
            self,
            positive="refine_every reset_every max_gaussians reset_opacity",
            non_negative="refine_start refine_stop grad_threshold dense_percent prune_screen_px prune_world",
            unit="prune_opacity reset_opacity",
        )

    def scaled(self, factor: float) -> DensifyConfig:
        """The same schedule compressed to ``factor`` times as many steps (for reduced runs).

        Refinements stay at least 10 steps apart (gradient statistics need several views) and opacity
        resets at least 100 (the scene needs time to recover from one).
        """

        def s(v: int, floor: int = 1) -> int:
            return max(floor, round(v * factor))

        return replace(
            self,
            refine_start=s(self.refine_start),
            refine_stop=s(self.refine_stop),
            refine_every=s(self.refine_every, 10),
            reset_every=s(self.reset_every, 100),
        )


@dataclass(frozen=True)
class GSTrainConfig:
    """3DGS training settings (defaults: graphdeco's 30K-step recipe)."""

    steps: int = 30_000
    """Optimisation steps (one training view each)."""
    image_scale: float = 1.0
    """Train on images resized by this factor."""
    sh_degree: int = 3
    """Final spherical-harmonics degree."""
    sh_every: int = 1_000
    """Raise the active SH degree by one every this many steps."""
    ssim_weight: float = 0.2
    """Loss = (1 - w) L1 + w (1 - SSIM)."""
    lr_means: float = 1.6e-4
    """Initial learning rate of the means, times the scene extent."""
    lr_means_final: float = 1.6e-6
    """Final learning rate of the means (exponential decay), times the scene extent."""
    lr_sh_dc: float = 2.5e-3
    """Learning rate of the DC colour coefficients (the higher orders get 1/20 of it)."""
    lr_opacity: float = 0.05
    """Learning rate of the opacity logits."""
    lr_scales: float = 5e-3
    """Learning rate of the log scales."""
    lr_quats: float = 1e-3
    """Learning rate of the quaternions."""
    densify: DensifyConfig = dataclasses.field(default_factory=DensifyConfig)
    """Adaptive density control schedule."""
    init_opacity: float = 0.1
    """Opacity of the initial Gaussians."""
    random_init: int = 50_000
    """Random initial Gaussians in the scene bounds when the dataset has no sparse points."""
    max_init_points: int = 200_000
    """Subsample the sparse points to at most this many."""
    backend: str = "auto"
    """Rasteriser backend: auto picks cuda on a GPU, else cpu (numba blending with gradients, about 10x
    the reference's speed at 128x96, tests/render/test_cpu_grad.py holds it to the reference)."""
    reference_tile: int = 4
    """Tile edge for the reference backend: small tiles waste less dense work per Gaussian (measured on
    snowmiku at 124x93: 0.80 s per step with 16, 0.44 with 8, 0.31 with 4)."""
    background: tuple[float, float, float] | None = None
    """Background colour; None uses the one the dataset declares (transforms.json "background"), else
    learns one (``learn_background``) or uses black."""
    learn_background: bool = True
    """When no background colour is given or declared, learn one with the scene (three values, started from
    the commonest colour of the training images' borders), so a constant backdrop (sky, studio wall) is not
    explained by floaters in front of the cameras; train.json records it. False: black."""
    lr_background: float = 0.01
    """Adam learning rate of the learned background colour (its logits)."""
    background_transmittance: float = 0.9
    """The learned colour is fitted only to pixels the Gaussians leave at least this transparent (where the
    background is what the image shows); 0 fits it to every pixel, weighted by transmittance."""
    holdout_every: int = HOLDOUT_EVERY
    """Every n-th frame is held out (not trained on)."""
    checkpoint_every: int = 0
    """Write a resumable checkpoint every this many steps (0: only at the end)."""
    seed: int = 0
    """Seeds initialisation, view order and splitting."""
    device: str = "cpu"
    """Torch device for parameters and images."""
    threads: int = 0
    """CPU threads for torch and numba during the run; 0: auto, the cores idle when it starts (cores
    minus the whole part of the load average, at least 1). torch's and numba's own default, every core,
    oversubscribes a busy machine: train-gs made 0.26 steps/s with 2 threads on a 2-core EPYC under a
    load of 6-8 against 2.6 with 1; idle, 2 threads won (benchmarks/results/THREADS.md)."""

    def __post_init__(self) -> None:
        _check(
            self,
            positive="steps image_scale sh_every lr_means lr_means_final max_init_points reference_tile",
            non_negative="lr_sh_dc lr_opacity lr_scales lr_quats random_init lr_background holdout_every "
            "checkpoint_every threads",
            unit="ssim_weight background_transmittance",
        )
        if not 0 <= self.sh_degree <= 3 or not 0 < self.init_opacity < 1:
            raise ValueError(
                f"GSTrainConfig: sh_degree must be in 0..3 and init_opacity in (0, 1), got "
                f"{self.sh_degree!r} and {self.init_opacity!r}"
            )

    @classmethod
    def reduced(cls, steps: int, **kw) -> GSTrainConfig:
        """A run whose SH and densification schedule are compressed by steps / 30,000 (the defaults at
        30,000)."""
        f = steps / cls.steps  # the dataclass default: graphdeco's schedule length
        return cls(steps=steps, sh_every=max(1, round(1_000 * f)), densify=DensifyConfig().scaled(f), **kw)


BALANCES = ("paper", "scale")


@dataclass(frozen=True)
class FieldTrainConfig:
    """Distillation settings (defaults: the FMGS paper)."""

    steps: int = 4200
    """Optimiser steps (one training view per step)."""
    lam: float = 0.2
    """Weight of the language (Huber) loss; the DINO (MSE) loss gets 1 - lam."""
    huber_delta: float = 1.25
    """Huber threshold of the language loss."""
    balance: str = "paper"
    """How the two target terms are scaled before ``lam`` weighs them. "paper": as they come (the DINO
    term then outweighs the language term by the ratio of the targets' squared magnitudes, which depends
    on the encoders); "scale": each divided by its targets' mean square per element over the training
    views, so ``lam`` weighs relative errors whatever the encoders' feature scales."""
    dotsim_weight: float = 0.01
    """gamma: weight of the dot-product-similarity loss (0 switches it off)."""
    dotsim_start: int = 2500
    """Step at which dotsim switches on."""
    dotsim_kernel: int = 3
    """Neighbourhood edge K (odd) of dotsim."""
    lr: float = 5e-3
    """Initial learning rate (RAdam)."""
    lr_final: float = 4e-3
    """Learning rate at the last step (exponential decay)."""
    weight_decay: float = 1e-9
    """RAdam weight decay."""
    adam_eps: float = 1e-15
    """RAdam epsilon. The per-element losses are means over h*w*D values, so gradients are tiny; the
    usual 1e-8 would swamp them (Instant-NGP uses 1e-15 for the same reason)."""
    seed: int = 0
    """Seeds initialisation and view order."""
    device: str = "cpu"
    """Torch device."""
    threads: int = 0
    """CPU threads for torch and numba during the run; 0: auto, as GSTrainConfig.threads."""
    holdout_every: int = HOLDOUT_EVERY
    """Every n-th frame is held out (as in the geometry stage); 0 or 1 trains on all."""
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    """Encoding and heads (clip_dim and dino_dim are taken from the feature cache)."""
    select: SelectConfig = dataclasses.field(default_factory=SelectConfig)
    """Which Gaussians carry features."""
    per_gaussian: bool = False
    """Ablation: free per-Gaussian vectors instead of the hash-grid field."""
    adaptive_resolution: bool = False
    """Scene-adaptive: lower the finest level to the Gaussians' median spacing (``scene_max_res``)."""
    checkpoint_every: int = 500
    """Steps between checkpoints (0: only at the end)."""

    def __post_init__(self) -> None:
        if self.steps < 1 or not 0 <= self.lam <= 1 or self.dotsim_kernel < 3 or self.dotsim_kernel % 2 == 0:
            raise ValueError("need steps >= 1, 0 <= lam <= 1 and an odd dotsim_kernel >= 3")
        if self.balance not in BALANCES:
            raise ValueError(f"balance must be one of {BALANCES}, not {self.balance!r}")
        _check(
            self,
            positive="huber_delta lr lr_final adam_eps",
            non_negative="dotsim_weight dotsim_start weight_decay threads holdout_every checkpoint_every",
        )

    def reduced(self, steps: int, **kw) -> FieldTrainConfig:
        """The same schedule compressed to ``steps`` (dotsim starts at the same fraction; unchanged at
        ``self.steps``)."""
        start = round(self.dotsim_start * steps / self.steps)
        return replace(self, steps=steps, dotsim_start=start, **kw)

    def to_dict(self) -> dict:
        return asdict(self)
