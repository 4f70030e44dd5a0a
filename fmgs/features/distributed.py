"""Per-image target extraction fanned out as Ray tasks (``fmgs features --ray``, ``fmgs build --ray``).

Workers compute an image's maps with the same functions as the serial driver
(fmgs.features.extract.image_targets / image_label_targets) and send them back; the driver alone writes
the cache (FeatureCacheWriter: one atomic file per image, then the manifest), so the cache equals the
serial one bit for bit and stays resumable. A task lost with its worker is retried by Ray (``max_retries``)
and recomputes the same maps; images already in the cache are never sent out again.

Workers keep the dataset and the encoders they loaded for the next task of the same job (a per-process
cache filled on first use, nothing at import).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fmgs.build.config import TargetSpec
from fmgs.data.dataset import load_dataset
from fmgs.features.cache import FeatureCache, FeatureCacheWriter, TargetInfo
from fmgs.features.clip import load_image_encoder
from fmgs.features.dino import load_dense_encoder
from fmgs.features.extract import (
    ExtractConfig,
    clip_settings,
    image_label_targets,
    image_targets,
    label_embeddings,
    label_settings,
    read_label_names,
)
from fmgs.features.models import DEFAULT_REVISION
from fmgs.features.pyramid import spec_pyramid
from fmgs.features.standin_seg import load_segmenter
from fmgs.features.text import load_text_encoder


@dataclass(frozen=True)
class TargetJob:
    """What every worker needs to compute any image's targets (a path every node reads)."""

    data: str
    """Posed dataset folder."""
    spec: TargetSpec
    device: str = "cpu"
    """"cpu", "cuda" or "auto" (a worker's first CUDA device when it has one)."""
    undistort_dir: str | None = None
    revisions: tuple[tuple[str, str], ...] = ()
    """(encoder id, hub revision) pairs: the revisions the driver resolved (every worker loads these)."""


class _Worker:
    """A process's loaded dataset and encoders for one job."""

    def __init__(self, job: TargetJob) -> None:

        spec = job.spec
        rev = dict(job.revisions)
        self.kind = spec.kind
        device = job.device
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.ds = load_dataset(job.data, undistort_dir=job.undistort_dir)
        self.cfg = ExtractConfig(spec.feature_scale, spec.feature_side, device=device, progress=False)
        if spec.kind == "labels":
            names = read_label_names(spec.names or self.ds.root / "scene.json")
            text_rev = rev.get(spec.text_encoder, DEFAULT_REVISION)
            enc = load_text_encoder(spec.text_encoder, device=device, revision=text_rev)
            self.emb = label_embeddings(names, enc, device)
            self.labels = spec.labels or self.ds.root / "labels"
            self.targets = {"clip": TargetInfo(enc.id, enc.dim, True)}
        else:
            clip_rev = rev.get(spec.clip_model, DEFAULT_REVISION)
            self.clip = load_image_encoder(spec.clip_model, device=device, revision=clip_rev)
            self.dino = None
            if spec.dino_model:
                dino_rev = rev.get(spec.dino_model, DEFAULT_REVISION)
                self.dino = load_dense_encoder(spec.dino_model, device=device, revision=dino_rev)
            self.seg = None
            if spec.segmenter:
                seg_rev = rev.get(spec.segmenter, DEFAULT_REVISION)
                self.seg = load_segmenter(spec.segmenter, device, revision=seg_rev)
            self.pyramid = spec_pyramid(self.clip, spec)
            self.targets = {"clip": TargetInfo(self.clip.id, self.clip.dim, True)}
            if self.dino is not None:
                self.targets["dino"] = TargetInfo(self.dino.id, self.dino.dim, False)

    def maps(self, i: int) -> dict:
        """Image i's maps as numpy arrays (add()'s keyword arguments)."""

        if self.kind == "labels":
            out = image_label_targets(self.ds, i, self.labels, self.emb, frozenset({0}), self.cfg)
        else:
            out = image_targets(self.ds, i, self.clip, self.dino, self.pyramid, self.cfg, self.seg)
        return {k: (v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else v) for k, v in out.items()}


_WORKERS: dict[TargetJob, _Worker] = {}


def _worker(job: TargetJob) -> _Worker:
    w = _WORKERS.get(job)
    if w is None:
        _WORKERS.clear()  # one job per worker process at a time: free the previous encoders
        w = _WORKERS[job] = _Worker(job)
    return w


def describe_task(job: TargetJob) -> dict[str, TargetInfo]:
    """The cache's targets (the encoders' ids and sizes), computed where the encoders load."""
    return _worker(job).targets


def maps_task(job: TargetJob, indices: list[int]) -> list[dict]:
    """The maps of the images ``indices`` (a Ray task; retried whole if its worker is lost)."""
    w = _worker(job)
    return [w.maps(i) for i in indices]


def job_settings(job: TargetJob, ds) -> dict:
    """The settings the serial driver records for ``job``'s cache (fmgs.features.extract.clip_settings /
    label_settings), computed without loading an encoder: the recorded ones leave out the crops' pixel
    size, which the encoder's id (in the targets) decides."""
    spec = job.spec
    cfg = ExtractConfig(spec.feature_scale, spec.feature_side, progress=False)
    if spec.kind == "labels":
        names = read_label_names(spec.names or ds.root / "scene.json")
        return label_settings(names, frozenset({0}), cfg)
    return clip_settings(spec_pyramid(None, spec), cfg, spec.segmenter)


def extract_features_ray(
    job: TargetJob,
    cache_dir: str | os.PathLike,
    address: str | None = None,
    batch: int = 2,
    max_retries: int = 3,
    task: Callable | None = None,
    progress: bool = True,
) -> FeatureCache:
    """Fill ``cache_dir`` with ``job``'s targets using the tasks of a Ray cluster (``address``: a running
    cluster, "auto" for the local node's, None to start one here); returns the opened cache.

    batch: images per task (fewer round trips; a lost task redoes that many). Tasks ask for one GPU each
    when the job's device is not "cpu" and the cluster has GPUs. ``task`` replaces maps_task (tests).
    """
    import ray

    if batch < 1 or max_retries < 0:
        raise ValueError("batch >= 1 and max_retries >= 0 required")
    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    gpus = 1 if job.device != "cpu" and ray.cluster_resources().get("GPU", 0) > 0 else 0
    remote = lambda fn: ray.remote(num_gpus=gpus, max_retries=max_retries)(fn)  # noqa: E731
    ds = load_dataset(job.data, undistort_dir=job.undistort_dir)
    targets = ray.get(remote(describe_task).remote(job))
    from tqdm.auto import tqdm

    with FeatureCacheWriter(cache_dir, targets, job_settings(job, ds)) as writer:
        todo = [i for i in range(len(ds)) if not writer.has(ds.frames[i].name)]
        fn = remote(task or maps_task)
        pending = [fn.remote(job, todo[s : s + batch]) for s in range(0, len(todo), batch)]
        with tqdm(total=len(todo), desc="features (ray)", unit="image", disable=not progress) as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for m in ray.get(done[0]):
                    # Ray hands back read-only arrays: copied before torch wraps them.
                    arrays = {
                        k: torch.from_numpy(v.copy()) for k, v in m.items() if isinstance(v, np.ndarray)
                    }
                    writer.add(**{**m, **arrays})
                    bar.update(1)
    return FeatureCache.open(Path(cache_dir))
