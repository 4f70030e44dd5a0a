"""Vanilla 3D Gaussian Splatting training on a posed dataset, on any device and backend.

L1 + D-SSIM photometric loss, SH degree raised over training, adaptive density control
(fmgs.train.strategy), Adam with graphdeco's learning rates, checkpoints (safetensors + JSON) and
resume. The same loop runs the gsplat backend on CUDA and the numba cpu backend (or the reference) elsewhere.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from fmgs.data.dataset import PosedDataset
from fmgs.errors import ValidationError
from fmgs.gaussians import SH_C0, GaussianSet, num_sh_bases
from fmgs.io.atomic import atomic_path
from fmgs.io.ply import write_ply
from fmgs.metrics import ssim
from fmgs.render import RasterConfig, rasterize
from fmgs.sh import sh_to_rgb
from fmgs.train.config import GSTrainConfig
from fmgs.train.strategy import DensifyState, accumulate, refine, reset_opacity
from fmgs.train.threads import thread_count
from fmgs.train.viewed import focus_point, viewed_points

log = logging.getLogger(__name__)
PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


@dataclass
class TrainResult:
    gaussians: GaussianSet
    steps: int
    seconds: float
    final_loss: float
    history: list[dict]
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The background colour the scene was trained with (given, declared or learned)."""
    background_source: str = "black"
    """Where it came from: "config", "declared" (transforms.json), "learned" or "black"."""


DEGENERATE_SPREAD = 1e-3
"""Cameras whose radius about their centre is below this fraction of their median distance to the sparse
points have no spread to measure the scene by (one view, or a camera turning on the spot)."""


def scene_extent(ds: PosedDataset, train: list[int]) -> float:
    """Radius of the training cameras around their centre, times 1.1 (graphdeco's normalisation). Where
    the cameras have no spread (DEGENERATE_SPREAD) the scene is measured by its sparse points instead:
    their median distance from the cameras' centre, times 1.1; the means' learning rate and the
    densification thresholds scale with it, so a zero radius would freeze the means and prune every
    grown Gaussian as too large."""
    c = torch.stack([ds.frames[i].camera.center for i in train])
    radius = (c - c.mean(0)).norm(dim=1).max()
    if ds.points is not None and len(ds.points):
        centre = c.double().mean(0).cpu().numpy()
        depth = float(np.median(np.linalg.norm(ds.points - centre, axis=1)))
        if float(radius) < DEGENERATE_SPREAD * depth:
            return 1.1 * depth
    return float(1.1 * radius.clamp_min(1e-6))


def init_params(ds: PosedDataset, cfg: GSTrainConfig, g: torch.Generator) -> dict[str, torch.Tensor]:
    """Initial parameters: sparse points (subsampled) or random points in the bounds."""
    from scipy.spatial import cKDTree

    if ds.points is not None and len(ds.points) >= 4:
        pts, cols = ds.points, ds.colors.astype(np.float64) / 255.0
        if len(pts) > cfg.max_init_points:
            pick = np.random.default_rng(cfg.seed).choice(len(pts), cfg.max_init_points, replace=False)
            pts, cols = pts[pick], cols[pick]
    else:
        pts, cols = _viewed_init(ds, cfg)
    d2, _ = cKDTree(pts).query(pts, k=4)
    scale = np.sqrt((d2[:, 1:] ** 2).mean(1)).clip(1e-7)
    n = len(pts)
    f = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    k = num_sh_bases(cfg.sh_degree)
    return {
        "means": f(pts),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        "log_scales": f(np.log(scale))[:, None].repeat(1, 3),
        "opacity_logits": torch.full((n,), math.log(cfg.init_opacity / (1 - cfg.init_opacity))),
        "sh_dc": ((f(cols) - 0.5) / SH_C0)[:, None, :],
        "sh_rest": torch.zeros(n, k - 1, 3),
    }


def _no_volume(ds: PosedDataset, e: ValidationError) -> ValidationError:
    return ValidationError(
        str(ds.root),
        f"has no sparse points and no volume to start from: {e.field} {e.reason}; give the dataset "
        "points (COLMAP points3D, or a transforms.json ply_file_path), or build from the photos so "
        "that structure from motion makes them",
    )


INIT_IMAGES = 32
"""Training images (evenly spread, at most INIT_IMAGE_SIDE pixels on the longer side) that colour and
carve points-free initial Gaussians."""
INIT_IMAGE_SIDE = 160


def _viewed_init(ds: PosedDataset, cfg: GSTrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """[random_init,3] points in the cameras' common view (outside a declared background) and their
    mean colours in [0,1] over INIT_IMAGES training images (fmgs.train.viewed), announced; a dataset
    whose cameras share no view is refused with what to supply."""

    try:
        focus_point([f.camera for f in ds.frames])  # refuse before reading any image
    except ValidationError as e:
        raise _no_volume(ds, e) from e
    train, _ = ds.split(cfg.holdout_every)
    pick = [
        train[i] for i in np.linspace(0, len(train) - 1, min(INIT_IMAGES, len(train))).round().astype(int)
    ]
    images, cams = [], []
    for i in dict.fromkeys(pick):
        c = ds.frames[i].camera
        img, cam = ds.image(i, min(1.0, INIT_IMAGE_SIDE / max(c.width, c.height)))
        images.append(img.numpy())
        cams.append(cam)
    bg = declared_background(ds)
    try:
        vol = viewed_points(
            [f.camera for f in ds.frames], cfg.random_init, cfg.seed, images=images, image_cameras=cams,
            background=bg,
        )  # fmt: skip
    except ValidationError as e:
        raise _no_volume(ds, e) from e
    log.warning(
        "%s has no sparse points: starting from %d random Gaussians in the cameras' common view%s "
        "(around %s, seen by %d-%d of %d cameras), coloured from the images; points from structure from "
        "motion usually train better and faster",
        ds.root, len(vol.points), ", outside the declared background" if bg is not None else "",
        np.round(vol.focus, 3).tolist(),
        int(vol.seen_by.min()), int(vol.seen_by.max()), len(ds.frames),
    )  # fmt: skip
    return vol.points, vol.colours


def _make_optimizer(params: dict[str, torch.nn.Parameter], cfg: GSTrainConfig, extent: float):
    lrs = {
        "means": cfg.lr_means * extent,
        "quats": cfg.lr_quats,
        "log_scales": cfg.lr_scales,
        "opacity_logits": cfg.lr_opacity,
        "sh_dc": cfg.lr_sh_dc,
        "sh_rest": cfg.lr_sh_dc / 20,
    }
    return torch.optim.Adam(
        [{"params": [params[k]], "lr": lrs[k], "name": k} for k in PARAM_NAMES], eps=1e-15
    )


def _swap_params(opt: torch.optim.Optimizer, new: dict[str, torch.Tensor], keep: torch.Tensor) -> dict:
    """Replace each group's tensor, carrying Adam moments for kept rows and zeros for new rows."""
    out = {}
    for group in opt.param_groups:
        old = group["params"][0]
        p = torch.nn.Parameter(new[group["name"]].detach().clone())
        st = opt.state.pop(old, None)
        if st is not None:
            n_new = p.shape[0] - int(keep.sum())
            for key in ("exp_avg", "exp_avg_sq"):
                t = st[key]
                st[key] = torch.cat([t[keep], t.new_zeros((n_new, *t.shape[1:]))])
            opt.state[p] = st
        group["params"][0] = p
        out[group["name"]] = p
    return out


def train_gaussians(
    ds: PosedDataset,
    out_dir: str | Path,
    cfg: GSTrainConfig = GSTrainConfig(),
    progress: bool = True,
    resume: bool = True,
) -> TrainResult:
    """Train 3DGS on the dataset's training frames; writes ``out_dir/point_cloud.ply`` and a checkpoint.

    Runs with ``cfg.threads`` CPU threads (torch and numba); train.json records the count in effect."""
    with thread_count(cfg.threads) as threads:
        return _train(ds, Path(out_dir), cfg, progress, resume, threads)


def _train(
    ds: PosedDataset, out_dir: Path, cfg: GSTrainConfig, progress: bool, resume: bool, threads: int
) -> TrainResult:
    out_dir.mkdir(parents=True, exist_ok=True)
    dev = torch.device(cfg.device)
    g = torch.Generator().manual_seed(cfg.seed)
    train, _ = ds.split(cfg.holdout_every)
    extent = scene_extent(ds, train)
    images = [ds.image(i, cfg.image_scale) for i in train]
    images = [(im.to(dev), cam) for im, cam in images]
    bg_source, bg_value = _background_choice(ds, cfg)
    bg_logit = bg_opt = None
    if bg_source == "learned":  # three logits, their own Adam: densification never touches them
        start_colour = border_colour([im for im, _ in images]).clamp(0.02, 0.98)
        bg_logit = torch.nn.Parameter(torch.logit(start_colour).to(dev))
        bg_opt = torch.optim.Adam([bg_logit], lr=cfg.lr_background)
    bg = torch.tensor(bg_value, dtype=torch.float32, device=dev)
    backend = cfg.backend
    if backend == "auto":
        backend = "cuda" if dev.type == "cuda" else "cpu"

    ckpt = out_dir / "checkpoint.safetensors"
    start = 0
    if resume and ckpt.is_file():
        raw, opt_state, state, start = load_checkpoint(ckpt)
        if bg_logit is not None and "background" in raw:  # the colour learned so far (its moments restart)
            bg_logit.data = raw.pop("background").to(dev)
        raw.pop("background", None)
    else:
        raw = init_params(ds, cfg, g)
        state, opt_state = DensifyState.empty(raw["means"].shape[0]), None
    params = {k: torch.nn.Parameter(v.to(dev)) for k, v in raw.items()}
    opt = _make_optimizer(params, cfg, extent)
    if opt_state is not None:
        for group in opt.param_groups:
            opt.state[group["params"][0]] = {
                k: v.to(dev) if torch.is_tensor(v) else v for k, v in opt_state[group["name"]].items()
            }
    state = DensifyState(
        state.grad_sum.to(dev), state.count.to(dev), state.max_radius.to(dev), state.resets, state.history
    )
    raster = RasterConfig(tile_size=cfg.reference_tile) if backend == "reference" else RasterConfig()
    d = cfg.densify
    order = torch.randperm(len(images), generator=g).tolist()
    t0 = time.perf_counter()
    loss_val = float("nan")
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.steps, initial=start, desc="train-gs", unit="step", dynamic_ncols=True)
    for step in range(start, cfg.steps):
        if not order:
            order = torch.randperm(len(images), generator=g).tolist()
        img, cam = images[order.pop()]
        decay = step / max(cfg.steps - 1, 1)
        opt.param_groups[0]["lr"] = extent * cfg.lr_means * (cfg.lr_means_final / cfg.lr_means) ** decay
        degree = min(cfg.sh_degree, step // cfg.sh_every)
        sh = torch.cat([params["sh_dc"], params["sh_rest"]], 1)
        rgb = sh_to_rgb(sh, params["means"], cam.center.to(dev), degree)
        if bg_logit is not None:
            bg = torch.sigmoid(bg_logit).detach()  # its gradient is taken below, from background pixels only
        out = rasterize(
            params["means"],
            params["quats"],
            params["log_scales"].exp(),
            torch.sigmoid(params["opacity_logits"]),
            rgb,
            cam,
            background=bg,
            config=raster,
            backend=backend,
        )
        out.means2d.retain_grad()
        if bg_logit is not None:
            out.image.retain_grad()
        l1 = (out.image - img).abs().mean()
        loss = (1 - cfg.ssim_weight) * l1 + cfg.ssim_weight * (1 - ssim(out.image, img))
        loss.backward()
        if bg_logit is not None:
            bg_logit.grad = background_grad(
                out.image.grad, out.alpha.detach(), bg_logit, cfg.background_transmittance
            )
        with torch.no_grad():
            if step < d.refine_stop and out.means2d.grad is not None:
                accumulate(state, out.means2d.grad, out.radii, out.visible, cam.width, cam.height)
            opt.step()
            opt.zero_grad(set_to_none=True)
            if bg_opt is not None:
                bg_opt.step()
                bg_opt.zero_grad(set_to_none=True)
            if d.refine_start <= step < d.refine_stop and step % d.refine_every == 0 and step > 0:
                new, keep = refine({k: p.data for k, p in params.items()}, state, d, step, extent, g)
                params = _swap_params(opt, new, keep)
            if step > 0 and step % d.reset_every == 0 and step < d.refine_stop:
                params["opacity_logits"].data = reset_opacity(params["opacity_logits"].data, d)
                opt.state[params["opacity_logits"]] = {}  # moments of a reset parameter restart
                state.resets += 1
        loss_val = float(loss.detach())
        if bar is not None:
            bar.set_postfix(loss=f"{loss_val:.4f}", n=params["means"].shape[0], refresh=False)
            bar.update(1)
        if cfg.checkpoint_every and (step + 1) % cfg.checkpoint_every == 0 and step + 1 < cfg.steps:
            save_checkpoint(ckpt, params, opt, state, step + 1, cfg, bg_logit)
    if bar is not None:
        bar.close()
    save_checkpoint(ckpt, params, opt, state, cfg.steps, cfg, bg_logit)
    if bg_logit is not None:
        bg_value = tuple(float(x) for x in torch.sigmoid(bg_logit.detach()).cpu())
    gs = to_gaussian_set(params)
    write_ply(gs, out_dir / "point_cloud.ply")
    secs = time.perf_counter() - t0
    with atomic_path(out_dir / "train.json") as tmp:
        tmp.write_text(
            json.dumps(
                {
                    "steps": cfg.steps,
                    "seconds": secs,
                    "final_loss": loss_val,
                    "backend": backend,
                    "threads": threads,
                    "gaussians": gs.num,
                    "extent": extent,
                    "background": list(bg_value),
                    "background_source": bg_source,
                    "config": config_record(cfg),
                    "densify_history": state.history,
                },
                indent=1,
            )
        )
    return TrainResult(gs, cfg.steps, secs, loss_val, state.history, bg_value, bg_source)


def to_gaussian_set(params: dict[str, torch.Tensor]) -> GaussianSet:
    p = {k: v.detach().float().cpu() for k, v in params.items()}
    return GaussianSet(
        p["means"], p["quats"], p["log_scales"], p["opacity_logits"], torch.cat([p["sh_dc"], p["sh_rest"]], 1)
    )


def _background_choice(ds: PosedDataset, cfg: GSTrainConfig) -> tuple[str, tuple[float, float, float]]:
    """(source, colour) of the background to train with: the config's, the dataset's declared one, a
    learned one (its colour here is a placeholder, set from the images by the caller), or black."""
    if cfg.background is not None:
        return "config", tuple(cfg.background)
    declared = declared_background(ds)
    if declared is not None:
        return "declared", declared
    return ("learned", (0.0, 0.0, 0.0)) if cfg.learn_background else ("black", (0.0, 0.0, 0.0))


def background_grad(
    image_grad: torch.Tensor, alpha: torch.Tensor, bg_logit: torch.Tensor, min_transmittance: float
) -> torch.Tensor:
    """[3] gradient of the loss for the background's logits, from the pixels the Gaussians leave at least
    ``min_transmittance`` transparent. The rasteriser's own gradient sums transmittance x dL/dpixel over every
    pixel: under an L1 loss each half-covered pixel of a wall or floor pulls as hard as a sky pixel, scaled
    only by its transmittance, and thousands of them dragged a learned sky off its colour while textured
    surroundings were still half built (BACKGROUND.md). ``image_grad`` [H,W,3] dL/dpixel, ``alpha`` [H,W]."""
    t = (1 - alpha).clamp(0, 1)
    w = torch.where(t >= min_transmittance, t, torch.zeros_like(t))  # threshold 0 keeps every pixel
    g = (w[..., None] * image_grad).sum((0, 1))
    s = torch.sigmoid(bg_logit.detach())
    return g * s * (1 - s)  # d sigmoid / d logit


def border_colour(images: list[torch.Tensor], levels: int = 16) -> torch.Tensor:
    """[3] the commonest colour of the images' border pixels (one pixel wide; images [H,W,3] in [0,1]):
    the mean of the pixels in the most populated cell of a levels^3 colour grid. Where a constant backdrop
    shows (sky, a studio wall) it fills more of the border than any one surface does, and this is its colour;
    a median would mix it with the floor's."""
    edges = []
    for im in images:
        edges += [im[0], im[-1], im[:, 0], im[:, -1]]
    px = torch.cat(edges).float().cpu().clamp(0, 1)
    cell = (px * (levels - 1e-6)).long()
    key = (cell[:, 0] * levels + cell[:, 1]) * levels + cell[:, 2]
    return px[key == torch.bincount(key).argmax()].mean(0)


def trained_background(run_dir: str | Path, ds: PosedDataset) -> tuple[float, float, float]:
    """The background colour a 3DGS run in ``run_dir`` trained with (its train.json), else the dataset's
    (declared, or black): what its renders should be compared with."""
    meta = Path(run_dir) / "train.json"
    if meta.is_file():
        bg = json.loads(meta.read_text()).get("background")
        if bg is not None:
            return tuple(float(x) for x in bg)
    return dataset_background(ds)


def declared_background(ds: PosedDataset) -> tuple[float, float, float] | None:
    """The background colour a transforms.json declares (synthetic scenes do), else None."""
    meta = ds.root / "transforms.json"
    if meta.is_file():
        bg = json.loads(meta.read_text()).get("background")
        if bg and len(bg) == 3:
            return tuple(float(x) for x in bg)
    return None


def dataset_background(ds: PosedDataset) -> tuple[float, float, float]:
    """The background colour a transforms.json declares (synthetic scenes do), else black."""
    return declared_background(ds) or (0.0, 0.0, 0.0)


def config_record(cfg: GSTrainConfig) -> dict:
    """The settings that decide what a run trains, as JSON values: all but ``threads`` (speed only), so
    a finished run or checkpoint is reused whatever thread count it ran with."""
    d = json.loads(json.dumps(asdict(cfg)))
    del d["threads"]
    return d


def save_checkpoint(
    path: Path, params, opt, state: DensifyState, step: int, cfg: GSTrainConfig, background=None
) -> None:
    """Parameters, Adam moments and densification statistics as safetensors; counters as JSON metadata.
    ``background``: the learned background's logits [3], when one is learned."""
    from safetensors.torch import save_file

    t = {f"param/{k}": v.detach().cpu().contiguous() for k, v in params.items()}
    if background is not None:
        t["param/background"] = background.detach().cpu().contiguous()
    steps = {}
    for group in opt.param_groups:
        st = opt.state.get(group["params"][0], {})
        for key in ("exp_avg", "exp_avg_sq"):
            if key in st:
                t[f"adam/{group['name']}/{key}"] = st[key].detach().cpu().contiguous()
        if "step" in st:
            steps[group["name"]] = float(st["step"])
    for k in ("grad_sum", "count", "max_radius"):
        t[f"densify/{k}"] = getattr(state, k).detach().cpu().contiguous()
    meta = {
        "format": "fmgs.gs_checkpoint",
        "version": "1",
        "step": str(step),
        "adam_steps": json.dumps(steps),
        "resets": str(state.resets),
        "history": json.dumps(state.history),
        "config": json.dumps(config_record(cfg)),
    }
    with atomic_path(path) as tmp:
        save_file(t, str(tmp), metadata=meta)


def load_checkpoint(path: Path):
    """(params, adam state by group name, DensifyState, step) from save_checkpoint's file; params hold
    "background" too when the run learns one."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata()
        if meta.get("format") != "fmgs.gs_checkpoint":
            raise ValueError(f"{path}: not an fmgs 3DGS checkpoint")
        t = {k: f.get_tensor(k) for k in f.keys()}
    params = {k: t[f"param/{k}"] for k in PARAM_NAMES}
    if "param/background" in t:  # a learned background's logits
        params["background"] = t["param/background"]
    steps = json.loads(meta["adam_steps"])
    opt_state = {}
    for k in PARAM_NAMES:
        if f"adam/{k}/exp_avg" in t:
            opt_state[k] = {
                "step": torch.tensor(steps.get(k, 0.0)),
                "exp_avg": t[f"adam/{k}/exp_avg"],
                "exp_avg_sq": t[f"adam/{k}/exp_avg_sq"],
            }
        else:
            opt_state[k] = {}
    state = DensifyState(
        t["densify/grad_sum"],
        t["densify/count"],
        t["densify/max_radius"],
        int(meta["resets"]),
        json.loads(meta["history"]),
    )
    return params, opt_state, state, int(meta["step"])
