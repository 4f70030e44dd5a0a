"""Shared fixtures: data location, hypothesis profiles, seeding, the one Ray cluster (helpers live in
``tests.helpers``)."""

from __future__ import annotations

import os
from pathlib import Path

# OpenMP threads (torch's pool, and numba's: its threading layer here is OpenMP) wait for work by
# spinning, so whenever they outnumber the idle cores (another job on the machine, or this suite's own
# servers, Ray workers and client threads) they burn the CPU the work needs: on the 2-core CI machine
# under another job, tests/render/test_grad.py, test_certify.py, tests/field, test_kernels.py and
# test_sharded.py took 195 s with the default and 38 s passive. Results do not depend on it. libgomp
# reads it when it loads, so it is set before torch is imported; child processes inherit it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest
import torch
from hypothesis import HealthCheck, settings

settings.register_profile(
    "default", max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile(
    "thorough", max_examples=600, deadline=None, suppress_health_check=list(HealthCheck)
)
settings.load_profile(os.environ.get("FMGS_HYPOTHESIS_PROFILE", "default"))

# Tests never download models: the ones that test downloads turn this off against a local hub server.
os.environ["FMGS_OFFLINE"] = "1"

# Without a GPU, the triton backend's kernel runs in Triton's interpreter (tests/render/test_triton_blend.py);
# the variable must be set before triton is first imported.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get("FMGS_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """../shared/data (or $FMGS_DATA); tests that need it skip with the reason when it is absent."""
    if not DATA_DIR.is_dir():
        pytest.skip(f"test data not found at {DATA_DIR} (set FMGS_DATA)")
    return DATA_DIR


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


@pytest.fixture(scope="module")
def bpe_dir(data_dir):
    """CLIP's BPE tokenizer files (vocab.json, merges.txt) from the shared test data."""
    d = data_dir / "clip_tokenizer" / "hf_format"
    if not (d / "vocab.json").is_file():
        pytest.skip(f"CLIP tokenizer files not found in {d}")
    return d


@pytest.fixture(scope="session")
def ray_cluster():
    """One local Ray cluster for every test that needs one (features fanned out, the service on Serve):
    two nodes of one CPU each on this machine (ray.cluster_utils.Cluster, so replicas can be placed on
    different nodes), the repository on the workers' PYTHONPATH, the driver connected. Starting Ray and
    its workers is the cost, so it starts once; Serve applications come and go per module. Yields the
    Cluster."""
    ray = pytest.importorskip("ray", reason="the fmgs[ray] extra is part of the CI install")
    from ray.cluster_utils import Cluster

    env = {"env_vars": {"PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}}
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1)  # a second raylet: another node as far as Ray's scheduler knows
        ray.init(address=cluster.address, runtime_env=env, log_to_driver=False)
        yield cluster
    finally:
        ray.shutdown()
        cluster.shutdown()
