"""The Gaussian scene model: parameters as stored (log scales, logit opacities, raw quaternions)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from fmgs.checks import check_finite, check_shape, first_bad_row
from fmgs.errors import ValidationError

MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per colour channel for ``degree`` (0..3): (degree+1)^2."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValidationError("sh_degree", f"must be in 0..{MAX_SH_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def sh_degree_from_bases(k: int) -> int:
    """Inverse of ``num_sh_bases``; ValidationError if ``k`` is not a square of 1..4."""
    d = math.isqrt(k) - 1
    if k < 1 or (d + 1) ** 2 != k or d > MAX_SH_DEGREE:
        raise ValidationError("sh", f"SH coefficient count must be 1, 4, 9 or 16, got {k}")
    return d


@dataclass
class GaussianSet:
    """N 3D Gaussians in world space, stored in the graphdeco parametrisation."""

    means: torch.Tensor
    """[N,3] centres in world coordinates."""
    quats: torch.Tensor
    """[N,4] rotations as quaternions, wxyz (real part first); any non-zero norm."""
    log_scales: torch.Tensor
    """[N,3] natural log of the standard deviations along the local axes."""
    opacity_logits: torch.Tensor
    """[N] opacity before the sigmoid."""
    sh: torch.Tensor
    """[N,K,3] spherical-harmonics colour coefficients, K = (degree+1)^2; sh[:,0] is the DC term."""

    def __post_init__(self) -> None:
        self.validate()

    @property
    def num(self) -> int:
        """N, the number of Gaussians."""
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(int(self.sh.shape[1]))

    @property
    def scales(self) -> torch.Tensor:
        """[N,3] standard deviations (exp of the log scales)."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        """[N] opacities in [0,1] (sigmoid of the logits)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    def validate(self) -> None:
        """Raise ValidationError naming the field and first bad index on any broken contract."""
        for f in fields(self):
            t = getattr(self, f.name)
            if not isinstance(t, torch.Tensor):
                raise ValidationError(f.name, f"expected a torch.Tensor, got {type(t).__name__}")
        n = self.means.shape[0] if self.means.ndim else -1
        check_shape("means", self.means, (n, 3))
        check_shape("quats", self.quats, (n, 4))
        check_shape("log_scales", self.log_scales, (n, 3))
        check_shape("opacity_logits", self.opacity_logits, (n,))
        check_shape("sh", self.sh, (n, None, 3))
        sh_degree_from_bases(int(self.sh.shape[1]))
        dtypes = {getattr(self, f.name).dtype for f in fields(self)}
        devices = {getattr(self, f.name).device for f in fields(self)}
        if len(dtypes) != 1 or len(devices) != 1:
            raise ValidationError(
                "GaussianSet", f"all tensors must share dtype and device, got {dtypes} {devices}"
            )
        for f in fields(self):
            check_finite(f.name, getattr(self, f.name))
        row = first_bad_row((self.quats == 0).all(dim=1))
        if row is not None:
            raise ValidationError("quats", "zero quaternion (no rotation defined)", row)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> GaussianSet:
        return GaussianSet(*(getattr(self, f.name).to(device=device, dtype=dtype) for f in fields(self)))

    def subset(self, index: torch.Tensor) -> GaussianSet:
        """The Gaussians selected by a boolean mask [N] or an index tensor [M]."""
        return GaussianSet(*(getattr(self, f.name)[index] for f in fields(self)))

    def tensors(self) -> dict[str, torch.Tensor]:
        """Field name -> tensor, in declaration order."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_activated(
        cls,
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        colors: torch.Tensor | None = None,
        sh: torch.Tensor | None = None,
    ) -> GaussianSet:
        """Build from linear scales [N,3], opacities in (0,1) [N], and either RGB colours [N,3] or SH."""
        eps = torch.finfo(means.dtype).eps
        if sh is None:
            rgb = colors if colors is not None else torch.full_like(means, 0.5)
            sh = ((rgb - 0.5) / SH_C0).unsqueeze(1)
        if (scales <= 0).any():
            raise ValidationError("scales", "must be positive", first_bad_row(scales <= 0))
        return cls(
            means=means,
            quats=quats,
            log_scales=torch.log(scales),
            opacity_logits=torch.logit(opacities.clamp(eps, 1 - eps)),
            sh=sh,
        )


# Zeroth-order SH basis constant: colour = SH_C0 * f_dc + 0.5 (graphdeco convention).
SH_C0 = 0.28209479177387814
