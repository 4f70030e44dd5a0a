"""Distil 2D feature targets into the feature field through the frozen 3DGS geometry (FMGS training).

Each step renders the language (and DINO) features of one training view from the features decoded at
the selected Gaussians' means and compares them with the view's cached targets:
    L = lam * Huber_delta(F_hat, F) + (1 - lam) * MSE(D_hat, D) + gamma * dotsim
with dotsim switched on after ``dotsim_start`` steps. Geometry is frozen, so each view's blending
weights are computed once (``fmgs.render.weights``) and a render is one sparse product with exactly the
rasteriser's weights; only the Gaussians that reach the view are decoded.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import torch
import torch.nn.functional as F

from fmgs.data.dataset import PosedDataset
from fmgs.errors import ValidationError
from fmgs.field.bounds import SceneBounds
from fmgs.field.hashgrid import scene_max_res
from fmgs.field.model import FeatureField, FieldOutput, PerGaussianFeatures
from fmgs.field.select import Selection, select_gaussians
from fmgs.gaussians import GaussianSet
from fmgs.io.atomic import atomic_path
from fmgs.io.checkpoint import load_training_state, save_training_state
from fmgs.render.weights import ViewWeights, view_weights, weights_config
from fmgs.sparse import SparseMatrix
from fmgs.train.config import FieldTrainConfig
from fmgs.train.threads import thread_count
from fmgs.vecmath import safe_normalize

CHECKPOINT_FORMAT = "fmgs.field_checkpoint"


class FieldTrainResult(NamedTuple):
    """What training produced."""

    model: torch.nn.Module
    """The trained FeatureField (or PerGaussianFeatures for the ablation)."""
    selection: Selection
    """The Gaussians that carry features."""
    seconds: float
    """Wall time of the optimisation loop."""
    losses: list[float]
    """Total loss per step."""


class ViewTarget(NamedTuple):
    """One training view at feature-map resolution."""

    weights: ViewWeights
    clip: torch.Tensor  # [h*w, Dc] float16
    dino: torch.Tensor | None  # [h*w, Dd] float16
    mask: torch.Tensor | None  # [h*w] bool


def dotsim_loss(clip: torch.Tensor, dino: torch.Tensor, k: int) -> torch.Tensor:
    """Mean |d_i.d_j - f_i.f_j| over pixels i and their k x k neighbours j, on unit-normalised rendered
    maps clip [h,w,Dc] and dino [h,w,Dd]; the DINO side carries no gradient."""
    f = safe_normalize(clip)
    d = safe_normalize(dino.detach())
    h, w = f.shape[:2]
    r = k // 2
    terms = []
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if (dy, dx) == (0, 0) or abs(dy) >= h or abs(dx) >= w:
                continue
            ys, yt = slice(max(0, -dy), h - max(0, dy)), slice(max(0, dy), h - max(0, -dy))
            xs, xt = slice(max(0, -dx), w - max(0, dx)), slice(max(0, dx), w - max(0, -dx))
            sf = (f[ys, xs] * f[yt, xt]).sum(-1)
            sd = (d[ys, xs] * d[yt, xt]).sum(-1)
            terms.append((sd - sf).abs().reshape(-1))
    if not terms:
        return clip.sum() * 0.0
    return torch.cat(terms).mean()


def prepare_views(
    gaussians: GaussianSet, ds: PosedDataset, cache, frames: list[int], device: torch.device
) -> list[ViewTarget]:
    """Blending weights and targets of each frame at the cache's map resolution."""
    views = []
    raster = weights_config(device)
    for i in frames:
        name = ds.frames[i].name
        maps = cache.load(name)
        h, w = maps.clip.shape[:2]
        cam = ds.frames[i].camera.resized(w, h)
        vw = view_weights(
            gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, cam, raster
        )
        vw = vw.to(device)
        mask = None if maps.mask is None else maps.mask.reshape(-1).to(device)
        dino = None if maps.dino is None else maps.dino.reshape(h * w, -1).half().to(device)
        views.append(ViewTarget(vw, maps.clip.reshape(h * w, -1).half().to(device), dino, mask))
    return views


def _decode(
    model: torch.nn.Module, interp: SparseMatrix | None, idx: torch.Tensor, dino: bool
) -> FieldOutput:
    """Features of the selected Gaussians idx [M]: encode all (one sparse product), decode only idx."""
    if isinstance(model, PerGaussianFeatures):
        return model.decode_index(idx, dino)
    return model.heads(model.grid.encode_matrix(interp)[idx], dino)


def target_scales(views: list[ViewTarget], balance: str) -> tuple[float, float]:
    """(language, DINO) divisors of the two target terms: 1 under "paper"; under "scale" each target's
    mean square per element over the views' (masked) pixels."""
    if balance == "paper":
        return 1.0, 1.0

    def mean_square(pick, name: str) -> float:
        total = count = 0.0
        for v in views:
            t = pick(v)
            if t is None:
                return 1.0
            t = t[v.mask] if v.mask is not None else t
            total += float(t.float().square().sum())
            count += t.numel()
        if not total > 0:  # dividing by a vanishing scale would multiply the term by 1e12 or more
            raise ValidationError(
                "balance", f'"scale" needs {name} targets that are not all zero on the supervised pixels'
            )
        return total / count

    return mean_square(lambda v: v.clip, "language"), mean_square(lambda v: v.dino, "DINO")


def _mean_loss(fn, pred: torch.Tensor, tgt: torch.Tensor, **kw) -> torch.Tensor:
    """``fn(pred, tgt)`` (a mean over elements), or zero, tied to ``pred``, where the mask keeps no pixel
    (a mean over no element is NaN)."""
    return fn(pred, tgt, **kw) if pred.numel() else pred.sum()


def view_loss(
    model: torch.nn.Module,
    interp: SparseMatrix | None,
    v: ViewTarget,
    cfg: FieldTrainConfig,
    dotsim: bool,
    scales: tuple[float, float] = (1.0, 1.0),
) -> tuple[torch.Tensor, dict[str, float]]:
    """The loss of one view and its parts; ``scales`` divide the language and DINO terms
    (``target_scales``)."""
    use_dino = v.dino is not None
    out = _decode(model, interp, v.weights.gaussians, use_dino)
    clip = v.weights.render(out.clip)  # [h,w,Dc]
    h, w = clip.shape[:2]
    sel = v.mask if v.mask is not None else slice(None)
    pred, tgt = clip.reshape(h * w, -1)[sel], v.clip[sel].float()
    l_clip = _mean_loss(F.huber_loss, pred, tgt, delta=cfg.huber_delta) / scales[0]
    parts = {"clip": float(l_clip.detach())}
    if use_dino:
        dino = v.weights.render(out.dino)
        l_dino = _mean_loss(F.mse_loss, dino.reshape(h * w, -1)[sel], v.dino[sel].float()) / scales[1]
        loss = cfg.lam * l_clip + (1 - cfg.lam) * l_dino
        parts["dino"] = float(l_dino.detach())
        if dotsim and cfg.dotsim_weight > 0:
            l_dot = dotsim_loss(clip, dino, cfg.dotsim_kernel)
            loss = loss + cfg.dotsim_weight * l_dot
            parts["dotsim"] = float(l_dot.detach())
    else:
        loss = l_clip  # without DINO targets only the language term is left (its weight is moot)
    return loss, parts


def train_field(
    gaussians: GaussianSet,
    ds: PosedDataset,
    cache,
    out_dir: str | Path,
    cfg: FieldTrainConfig = FieldTrainConfig(),
    progress: bool = True,
    resume: bool = True,
) -> FieldTrainResult:
    """Train the field on the dataset's training frames with targets from ``cache`` (a FeatureCache).

    Writes ``out_dir/field_checkpoint.safetensors`` (resumable) and ``out_dir/field_train.json``. Runs
    with ``cfg.threads`` CPU threads (torch and numba); field_train.json records the count in effect.
    """
    with thread_count(cfg.threads) as threads:
        return _train(gaussians, ds, cache, Path(out_dir), cfg, progress, resume, threads)


def _train(
    gaussians: GaussianSet,
    ds: PosedDataset,
    cache,
    out_dir: Path,
    cfg: FieldTrainConfig,
    progress: bool,
    resume: bool,
    threads: int,
) -> FieldTrainResult:
    out_dir.mkdir(parents=True, exist_ok=True)
    dev = torch.device(cfg.device)
    train, _ = ds.split(cfg.holdout_every)
    missing = [ds.frames[i].name for i in train if ds.frames[i].name not in cache.image_names]
    if missing:
        raise ValidationError(
            "feature cache", f"no targets for {len(missing)} training images, e.g. {missing[:3]}"
        )
    clip_dim = cache.targets["clip"].dim
    dino_dim = cache.targets["dino"].dim if "dino" in cache.targets else 0
    fcfg = replace(cfg.field, clip_dim=clip_dim, dino_dim=dino_dim)

    cams = [ds.frames[i].camera for i in train]
    if cfg.select.rule == "coverage":  # at the resolution the features are trained at
        cams = [c.resized(*reversed(cache.size(ds.frames[i].name))) for c, i in zip(cams, train, strict=True)]
    # On the training device: the coverage rule computes every training view's blending weights.
    selection = select_gaussians(gaussians.to(dev), cams, cfg.select)
    if len(selection.index) == 0:
        raise ValidationError("gaussians", f"no Gaussian passes the {cfg.select.rule!r} selection")
    g = gaussians.subset(selection.index).to(dev)

    if cfg.per_gaussian:
        model: torch.nn.Module = PerGaussianFeatures(g.num, clip_dim, dino_dim, cfg.seed)
        interp = None
    else:
        if cfg.adaptive_resolution:
            bounds = SceneBounds.around(g.means.cpu())
            top = scene_max_res(bounds.normalise(g.means.cpu().double()), fcfg.grid)
            fcfg = replace(fcfg, grid=replace(fcfg.grid, max_res=top))
        model = FeatureField.for_points(fcfg, g.means.cpu(), seed=cfg.seed)
    model = model.to(dev)
    if not cfg.per_gaussian:
        with torch.no_grad():
            interp = model.grid.interpolation_matrix(model.lookup(g.means))
    opt = torch.optim.RAdam(
        model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, eps=cfg.adam_eps, foreach=True
    )
    gen = torch.Generator().manual_seed(cfg.seed)

    ckpt = out_dir / "field_checkpoint.safetensors"
    start, losses = 0, []
    if resume and ckpt.is_file():
        tensors, opt_sd, meta = load_training_state(ckpt, CHECKPOINT_FORMAT)
        if meta.get("selected") != len(selection.index) or meta.get("config") != _jsonable(cfg):
            raise ValidationError(
                str(ckpt), "checkpoint was written for other settings; remove it to restart"
            )
        model.load_state_dict(tensors)
        opt.load_state_dict(opt_sd)
        start, losses = int(meta["step"]), list(meta["losses"])
        gen.set_state(torch.tensor(meta["rng"], dtype=torch.uint8))

    if start >= cfg.steps:  # a finished run: nothing to prepare or write
        return FieldTrainResult(model.cpu(), selection, 0.0, losses)
    views = prepare_views(g, ds, cache, train, dev)
    scales = target_scales(views, cfg.balance)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.steps, initial=start, desc="train-field", unit="step", dynamic_ncols=True)
    t0 = time.perf_counter()
    for step in range(start, cfg.steps):
        v = views[int(torch.randint(len(views), (1,), generator=gen))]
        for group in opt.param_groups:
            group["lr"] = cfg.lr * (cfg.lr_final / cfg.lr) ** (step / max(cfg.steps - 1, 1))
        loss, parts = view_loss(model, interp, v, cfg, step >= cfg.dotsim_start, scales)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        if bar is not None:
            bar.set_postfix({k: f"{x:.4g}" for k, x in parts.items()}, refresh=False)
            bar.update(1)
        done = step + 1
        if cfg.checkpoint_every and done % cfg.checkpoint_every == 0 and done < cfg.steps:
            _save(ckpt, model, opt, done, losses, gen, selection, cfg)
    secs = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    _save(ckpt, model, opt, cfg.steps, losses, gen, selection, cfg)
    with atomic_path(out_dir / "field_train.json") as tmp:
        tmp.write_text(
            json.dumps(
                {
                    "steps": cfg.steps,
                    "seconds": secs,
                    "selected": len(selection.index),
                    "total": selection.total,
                    "final_loss": losses[-1] if losses else None,
                    "threads": threads,
                    # What ran: the field's dims come from the cache, its finest level from the scene
                    # when adaptive (the requested defaults, 512/384, were recorded before).
                    "config": _jsonable(replace(cfg, field=fcfg)),
                },
                indent=1,
            )
        )
    return FieldTrainResult(model.cpu(), selection, secs, losses)


def _jsonable(cfg: FieldTrainConfig) -> dict:
    """What decides the result: every setting but ``threads`` (speed only; a resume may change it)."""
    d = json.loads(json.dumps(cfg.to_dict()))
    del d["threads"]
    return d


def _save(path, model, opt, step, losses, gen, selection, cfg) -> None:
    meta = {
        "step": step,
        "losses": losses,
        "rng": gen.get_state().tolist(),
        "selected": len(selection.index),
        "config": _jsonable(cfg),
    }
    save_training_state(path, CHECKPOINT_FORMAT, model.state_dict(), opt, meta)
