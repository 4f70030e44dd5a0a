"""Adaptive density control for 3DGS training (graphdeco's schedule), config and state kept apart.

Gaussians whose average view-space positional gradient is large are grown: small ones are cloned,
large ones split in two; transparent and oversized ones are pruned; opacities are reset periodically.
Gradients are measured in NDC units (pixels x W/2, H/2), so thresholds do not depend on image size.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from fmgs.cameras import quat_wxyz_to_rotmat
from fmgs.train.config import DensifyConfig


@dataclass
class DensifyState:
    """Per-Gaussian statistics gathered between refinements."""

    grad_sum: torch.Tensor
    """[N] sum of view-space gradient norms (NDC units)."""
    count: torch.Tensor
    """[N] number of views in which the Gaussian was visible."""
    max_radius: torch.Tensor
    """[N] largest projected radius seen (pixels)."""
    resets: int = 0
    """Opacity resets done so far."""
    history: list[dict] = field(default_factory=list)
    """One entry per refinement: step, grown, split, pruned, total."""

    @classmethod
    def empty(cls, n: int, device: torch.device | str = "cpu") -> DensifyState:
        z = torch.zeros(n, device=device)
        return cls(z.clone(), z.clone(), z.clone())

    def select(self, keep: torch.Tensor, n_new: int) -> None:
        """Keep rows ``keep`` (bool [N]) and append ``n_new`` zero rows."""

        def f(t):
            return torch.cat([t[keep], t.new_zeros(n_new)])

        self.grad_sum, self.count, self.max_radius = f(self.grad_sum), f(self.count), f(self.max_radius)


def accumulate(
    state: DensifyState,
    means2d_grad: torch.Tensor,
    radii: torch.Tensor,
    visible: torch.Tensor,
    width: int,
    height: int,
) -> None:
    """Add one view's statistics. means2d_grad [N,2] in pixels, radii [N], visible [N] bool."""
    g = means2d_grad.detach().to(state.grad_sum.dtype).clone()
    g[:, 0] *= width / 2
    g[:, 1] *= height / 2
    vis = visible & (radii > 0)
    state.grad_sum[vis] += g[vis].norm(dim=-1)
    state.count[vis] += 1
    state.max_radius[vis] = torch.maximum(state.max_radius[vis], radii[vis].to(state.max_radius.dtype))


def refine(
    params: dict[str, torch.Tensor],
    state: DensifyState,
    cfg: DensifyConfig,
    step: int,
    extent: float,
    generator: torch.Generator | None = None,
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Grow and prune at ``step``. Returns the new parameter tensors and the kept mask of the old rows.

    params: means [N,3], quats [N,4], log_scales [N,3], opacity_logits [N], sh_dc [N,1,3], sh_rest [N,K,3].
    New rows are appended after the kept old rows (the optimizer extends its state the same way).
    """
    with torch.no_grad():
        n = params["means"].shape[0]
        avg = state.grad_sum / state.count.clamp_min(1)
        scales = params["log_scales"].exp()
        big = scales.amax(-1) > cfg.dense_percent * extent
        grow = (avg >= cfg.grad_threshold) & (state.count > 0)
        room = max(0, cfg.max_gaussians - n)
        clone = grow & ~big
        split = grow & big
        if int(clone.sum() + split.sum()) > room:  # memory guard: keep the strongest
            order = torch.argsort(torch.where(grow, avg, -1.0), descending=True)
            allowed = torch.zeros_like(grow)
            allowed[order[: room // 2]] = True
            clone, split = clone & allowed, split & allowed
        new = {}
        # clone: an identical copy (the two move apart under their gradients)
        for k, v in params.items():
            new[k] = [v[clone]]
        # split: two samples drawn from the Gaussian, scales divided by 1.6, the original removed
        if split.any():
            idx = torch.nonzero(split).squeeze(1)
            R = quat_wxyz_to_rotmat(params["quats"][idx].double()).to(scales)
            s = scales[idx]
            for _ in range(2):
                # drawn where the generator lives (a CPU generator also drives CUDA training)
                eps = torch.randn(len(idx), 3, generator=generator, dtype=s.dtype).to(s.device)
                new["means"].append(params["means"][idx] + torch.einsum("nij,nj->ni", R, eps * s))
                new["log_scales"].append(params["log_scales"][idx] - torch.log(torch.tensor(1.6)))
                for k in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
                    new[k].append(params[k][idx])
        opac = torch.sigmoid(params["opacity_logits"])
        prune = split | (opac < cfg.prune_opacity)
        if state.resets > 0:
            prune |= state.max_radius > cfg.prune_screen_px
            prune |= scales.amax(-1) > cfg.prune_world * extent
        keep = ~prune
        out = {k: torch.cat([params[k][keep], *new[k]]) for k in params}
        n_new = out["means"].shape[0] - int(keep.sum())
        state.history.append(
            {
                "step": step,
                "cloned": int(clone.sum()),
                "split": int(split.sum()),
                "pruned": int((prune & ~split).sum()),
                "total": out["means"].shape[0],
            }
        )
        state.select(keep, n_new)
        state.grad_sum.zero_()
        state.count.zero_()
        state.max_radius.zero_()
    return out, keep


def reset_opacity(opacity_logits: torch.Tensor, cfg: DensifyConfig) -> torch.Tensor:
    """Opacity logits clamped so every opacity is at most cfg.reset_opacity."""
    cap = torch.logit(torch.tensor(cfg.reset_opacity, dtype=opacity_logits.dtype))
    return torch.minimum(opacity_logits, cap.to(opacity_logits.device))
