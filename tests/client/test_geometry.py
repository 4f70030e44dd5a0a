"""Geometry: a scene's Gaussians as points over the wire (the viewer's scene), against the real server."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fmgs.query.engine import SceneEngine
from fmgs.query.geometry import select_geometry
from fmgs_client.client import ChunkError, FmgsClient, FmgsError, assemble_geometry
from fmgs_server.config import ServerConfig
from fmgs_server.server import start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.tensors import to_tensor
from tests.helpers.query_scenes import FakeEncoder, blob_scene


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("geometry") / "models"
    root.mkdir()
    blob_scene(
        root / "blobs",
        opacity_logits=torch.linspace(-4.0, 4.0, 180)[
            torch.randperm(180, generator=torch.Generator().manual_seed(0))
        ],
    )
    return root


@pytest.fixture(scope="module")
def server(models):
    cfg = ServerConfig(
        models=models, port=0, reload_check_s=0.0, chunk_bytes=512, max_geometry=200, default_geometry=100
    )
    srv = start_server(cfg, encoder_factory=lambda i: FakeEncoder())
    yield srv
    srv.stop(0)


@pytest.fixture()
def client(server):
    with FmgsClient(server.address, timeout=30) as c:
        yield c


def _reference(engine: SceneEngine, floor: float) -> np.ndarray:
    """Every Gaussian whose opacity (as the columns report it) reaches the floor."""
    op = engine.gaussian_columns(torch.arange(engine.num_gaussians), ["opacity"])["opacity"]
    return np.flatnonzero(op >= floor)


def test_whole_scene_arrives_as_the_engine_holds_it(client, models):
    engine = SceneEngine.open(models / "blobs")
    g = client.geometry("blobs", max_gaussians=200)  # 512-byte chunks: the answer comes in pieces
    n = engine.num_gaussians
    assert g.num_gaussians == n == g.qualified == len(g) and np.array_equal(g.index, np.arange(n))
    cols = engine.gaussian_columns(torch.arange(n), ["mean", "color", "opacity", "scale"])
    for name, want in cols.items():
        assert np.array_equal(getattr(g, name), want), name
    assert np.allclose(g.bounds, engine.bounds)
    assert g.mean.dtype == np.float32 and g.index.dtype == np.int64


def test_cap_and_opacity_floor(client, models):
    engine = SceneEngine.open(models / "blobs")
    opacity = engine.gaussian_columns(torch.arange(engine.num_gaussians), ["opacity"])["opacity"]
    floor = float(np.median(opacity))
    want = _reference(engine, floor)
    assert 0 < len(want) < engine.num_gaussians
    g = client.geometry("blobs", max_gaussians=200, min_opacity=floor)
    assert g.qualified == len(want) and np.array_equal(g.index, want)
    assert (g.opacity >= floor).all()
    cap = len(want) // 3
    a = client.geometry("blobs", max_gaussians=cap, min_opacity=floor)
    b = client.geometry("blobs", max_gaussians=cap, min_opacity=floor)
    assert len(a) == cap and a.qualified == len(want)
    assert np.array_equal(a.index, b.index)  # the same request gives the same sample
    assert np.all(np.diff(a.index) > 0) and np.isin(a.index, want).all()
    # The server's sample is the library's.
    sel = select_geometry(engine.gaussians.opacity_logits, cap, floor)
    assert np.array_equal(sel.index, a.index)


def test_default_cap_and_limits(client):
    g = client.geometry("blobs")  # 0: the server's default (100 here) of the scene's 180
    assert len(g) == 100 and g.qualified == g.num_gaussians == 180
    with pytest.raises(FmgsError) as e:
        client.geometry("blobs", max_gaussians=201)
    assert e.value.code == "INVALID_ARGUMENT" and "max_gaussians" in e.value.details
    with pytest.raises(FmgsError) as e:
        client.geometry("nope")
    assert e.value.code == "NOT_FOUND"
    stub_req = pb.GeometryRequest(scene="blobs", min_opacity=1.5)
    with pytest.raises(Exception) as e:
        list(client._stub.Geometry(stub_req, timeout=10))
    assert "min_opacity" in e.value.details()
    with pytest.raises(ValueError):
        client.geometry("blobs", min_opacity=-0.1)


def test_select_geometry_edges():
    logits = torch.tensor([0.0, 10.0, -10.0, 2.0, float("nan")])
    assert select_geometry(logits, 10, 0.5).index.tolist() == [0, 1, 3]  # sigmoid(0) = 0.5 qualifies
    assert select_geometry(logits, 10, 0.0).qualified == 5
    s = select_geometry(torch.zeros(1000), 10, 0.0)
    assert len(s.index) == 10 and s.qualified == 1000
    assert len(select_geometry(torch.zeros(0), 10, 0.0).index) == 0
    for bad in ((0, 0.0), (10, 1.0), (10, -0.5)):
        with pytest.raises(ValueError):
            select_geometry(logits, *bad)


def _chunk(start, k, total=None, last=False):
    c = pb.GeometryChunk(start=start, last=last)
    if total is not None:
        c.total, c.num_gaussians, c.qualified = total, total, total
        c.bounds.extend([0, 0, 0, 1, 1, 1])
    c.index.CopyFrom(to_tensor(np.arange(start, start + k, dtype=np.int64)))
    for n, tail in (("mean", (3,)), ("color", (3,)), ("opacity", ()), ("scale", (3,))):
        getattr(c, n).CopyFrom(to_tensor(np.zeros((k, *tail), np.float32)))
    return c


def test_assemble_geometry_refuses_what_does_not_fit():
    g = assemble_geometry([_chunk(0, 2, total=4), _chunk(2, 2, last=True)])
    assert g.index.tolist() == [0, 1, 2, 3]
    with pytest.raises(ChunkError, match="expected row 2"):
        assemble_geometry([_chunk(0, 2, total=4), _chunk(3, 1, last=True)])
    with pytest.raises(ChunkError, match="announced 4"):
        assemble_geometry([_chunk(0, 2, total=4, last=True)])
    with pytest.raises(ChunkError, match="expected row"):
        assemble_geometry([_chunk(0, 2, total=2), _chunk(2, 2, last=True)])  # more rows than announced
    with pytest.raises(ChunkError, match="asked for at most"):
        assemble_geometry([_chunk(0, 2, total=10**12)], max_rows=100)  # refused before allocating
    with pytest.raises(ChunkError, match="empty"):
        assemble_geometry([])
