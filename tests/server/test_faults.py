"""Faults in scene files and in the server process: a clear state per scene, the others keep serving,
no partial file is ever loaded, in-flight requests finish on the version they started with."""

from __future__ import annotations

import errno
import os
import signal
import threading
import time

import grpc
import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from fmgs.errors import ValidationError
from fmgs_server.config import ServerConfig
from fmgs_server.server import start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from fmgs_wire.tensors import from_tensor, join
from tests.helpers.query_scenes import FakeEncoder, blob_scene, serve_process

C = grpc.StatusCode


@pytest.fixture()
def models(tmp_path):
    root = tmp_path / "models"
    root.mkdir()
    for name in ("good", "victim"):
        blob_scene(root / name)
    return root


@pytest.fixture()
def served(models):
    srv = start_server(
        ServerConfig(models=models, port=0, reload_check_s=0.0), encoder_factory=lambda i: FakeEncoder()
    )
    ch = grpc.insecure_channel(srv.address)
    yield srv, pb_grpc.FmgsStub(ch)
    ch.close()
    srv.stop(0)


def _query(stub, scene="good", text="red cube", k=20):
    chunks = list(stub.TextQuery(pb.TextQueryRequest(scene=scene, texts=[text], top_k=k), timeout=30))
    return join([from_tensor(c.index) for c in chunks]), join([from_tensor(c.relevancy) for c in chunks])


def _state(stub, name):
    return {s.name: s for s in stub.ListScenes(pb.ListScenesRequest()).scenes}.get(name)


def _truncate(p):
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])


def _nan_embeddings(p):
    t = load_file(str(p))
    t["embeddings"][3, 1] = float("nan")
    save_file(t, str(p))


def _wrong_shape(p):
    t = load_file(str(p))
    t["embeddings"] = torch.cat([t["embeddings"], t["embeddings"][:, :1]], 1).contiguous()
    save_file(t, str(p))


def _bad_manifest(p):
    p.write_text("{not json")


FILE_FAULTS = [
    ("truncated gaussians", "gaussians.safetensors", _truncate, "gaussians.safetensors"),
    ("truncated embeddings", "embeddings.safetensors", _truncate, "embeddings.safetensors"),
    ("nan embeddings", "embeddings.safetensors", _nan_embeddings, "embeddings"),
    ("wrong shape", "embeddings.safetensors", _wrong_shape, "embeddings"),
    ("corrupt manifest", "manifest.json", _bad_manifest, "manifest"),
    ("garbage gaussians", "gaussians.safetensors", lambda p: p.write_bytes(os.urandom(4096)), "gaussians"),
]


@pytest.mark.parametrize("case", FILE_FAULTS, ids=[c[0] for c in FILE_FAULTS])
def test_broken_file_fails_that_scene_only(served, models, case):
    _, stub = served
    _, fname, breaker, word = case
    breaker(models / "victim" / fname)
    with pytest.raises(grpc.RpcError) as e:
        _query(stub, "victim")
    assert e.value.code() == C.FAILED_PRECONDITION and word in e.value.details()
    st = _state(stub, "victim")
    assert st.state == pb.SCENE_STATE_FAILED and word in st.reason
    assert str(models) not in st.reason and str(models) not in e.value.details()  # no host paths
    _query(stub, "good")
    # Fixing the files brings the scene back (retried because its files changed).
    blob_scene(models / "victim")
    idx, _ = _query(stub, "victim")
    assert len(idx) == 20 and _state(stub, "victim").state == pb.SCENE_STATE_READY


def test_missing_manifest_and_unknown_encoder(models, tmp_path):
    (models / "victim" / "manifest.json").unlink()
    srv = start_server(ServerConfig(models=models, port=0), encoder_factory=_only_fake)
    try:
        with grpc.insecure_channel(srv.address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            assert _state(stub, "victim") is None
            with pytest.raises(grpc.RpcError) as e:
                _query(stub, "victim")
            assert e.value.code() == C.NOT_FOUND
            blob_scene(models / "other")
            m = (
                (models / "other" / "manifest.json")
                .read_text()
                .replace("test/blob-encoder", "missing/encoder")
            )
            (models / "other" / "manifest.json").write_text(m)
            with pytest.raises(grpc.RpcError) as e:
                _query(stub, "other")
            assert e.value.code() == C.FAILED_PRECONDITION and "missing/encoder" in e.value.details()
            _query(stub, "good")
    finally:
        srv.stop(0)


def _only_fake(encoder_id):
    from fmgs.features.models import ModelNotFoundError

    if encoder_id != FakeEncoder.id:
        raise ModelNotFoundError(encoder_id, ["this test"])
    return FakeEncoder()


def test_replaced_while_served_answers_old_or_new(served, models):
    _, stub = served
    answers = {}
    for seed in (0, 5):
        blob_scene(models / "victim", seed=seed)
        answers[seed] = _query(stub, "victim")[0].tolist()
    errors, seen = [], set()
    stop = threading.Event()

    def reader():
        while not stop.is_set():
            try:
                seen.add(tuple(_query(stub, "victim")[0].tolist()))
            except grpc.RpcError as e:
                errors.append((e.code(), e.details()))

    th = [threading.Thread(target=reader) for _ in range(3)]
    for t in th:
        t.start()
    for i in range(12):
        blob_scene(models / "victim", seed=0 if i % 2 else 5)
    stop.set()
    for t in th:
        t.join()
    assert not errors, errors
    assert seen and seen <= {tuple(answers[0]), tuple(answers[5])}


def test_in_flight_request_finishes_on_its_version(served, models):
    srv, stub = served
    cam = pb.Camera(viewmat=np.eye(4).ravel().tolist(), fx=400, fy=400, cx=400, cy=300, width=800, height=600)
    req = pb.RenderRequest(scene="victim", camera=cam, text="red cube")
    before = join([from_tensor(c.relevancy) for c in stub.Render(req)])
    engine = srv.service.repo.get("victim")
    gate, entered = threading.Event(), threading.Event()
    real = type(engine).relevancy_channels

    def slow_channels(self, *a):  # hold the render until the scene has been replaced
        entered.set()
        gate.wait(10)
        return real(self, *a)

    out = {}
    type(engine).relevancy_channels = slow_channels
    try:
        t = threading.Thread(target=lambda: out.setdefault("r", list(stub.Render(req))))
        t.start()
        assert entered.wait(10)
        type(engine).relevancy_channels = real
        blob_scene(models / "victim", seed=9)
        after = join([from_tensor(c.relevancy) for c in stub.Render(req)])
        gate.set()
        t.join(10)
    finally:
        type(engine).relevancy_channels = real
        gate.set()
    during = join([from_tensor(c.relevancy) for c in out["r"]])
    assert np.array_equal(during, before) and not np.array_equal(after, before)


def test_deleted_while_loaded(served, models):
    import shutil

    _, stub = served
    _query(stub, "victim")
    shutil.rmtree(models / "victim")
    with pytest.raises(grpc.RpcError) as e:
        _query(stub, "victim")
    assert e.value.code() == C.NOT_FOUND
    assert _state(stub, "victim") is None
    _query(stub, "good")


def test_disk_full_on_export_keeps_the_old_package(models, monkeypatch):
    import fmgs.scene.package as package

    before = {f.name: f.read_bytes() for f in (models / "victim").iterdir()}
    real = package.save_gaussians

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(package, "save_gaussians", full)
    with pytest.raises(OSError, match="No space"):
        blob_scene(models / "victim", seed=3)
    monkeypatch.setattr(package, "save_gaussians", real)
    assert {f.name: f.read_bytes() for f in (models / "victim").iterdir()} == before
    assert sorted(p.name for p in models.iterdir()) == ["good", "victim"]  # no temporary folder left


def test_loader_never_reads_a_half_written_package(models):
    from fmgs.scene.package import load_scene

    # A folder in the middle of being written (no manifest yet) is not a package.
    half = models / "half"
    half.mkdir()
    (half / "gaussians.safetensors").write_bytes((models / "good" / "gaussians.safetensors").read_bytes())
    with pytest.raises(ValidationError, match="no manifest"):
        load_scene(half)


def test_sigterm_drains_in_flight_and_restart_serves_the_same(tmp_path):
    from fmgs_wire.tensors import to_tensor

    root = tmp_path / "m"
    root.mkdir()
    _, classes, _ = blob_scene(root / "s")
    # The subprocess has no test encoder: query with precomputed embeddings of the scene's encoder.
    q = classes[0].numpy()[None].astype(np.float32)

    req = pb.TextQueryRequest(
        scene="s", texts=["x"], top_k=50, encoder_id=FakeEncoder.id, embeddings=to_tensor(q)
    )
    cam = pb.Camera(
        viewmat=np.eye(4).ravel().tolist(), fx=900, fy=900, cx=2000, cy=1000, width=4000, height=2000
    )
    p, address = serve_process(root)
    try:
        with grpc.insecure_channel(address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            first = _answer(stub, req)
            # A large render (colour and alpha need no text) is in flight when SIGTERM arrives: its
            # first chunk is read and the rest are held back by flow control until the client reads
            # on, so the server cannot have finished it (a sleep raced fast machines).
            r = pb.RenderRequest(
                scene="s", camera=cam, outputs=[pb.RENDER_OUTPUT_ALPHA, pb.RENDER_OUTPUT_RGB]
            )
            chunks = stub.Render(r, timeout=60)
            head = next(chunks)
            assert not head.last  # still streaming when the signal comes
            p.send_signal(signal.SIGTERM)
            time.sleep(0.5)
            rest = list(chunks)
            assert rest and rest[-1].last
        assert p.wait(timeout=60) == 0
    finally:
        if p.poll() is None:
            p.kill()
    # Crash and restart: kill -9, start again, identical answers.
    p, address = serve_process(root)
    try:
        with grpc.insecure_channel(address) as ch:
            assert _answer(pb_grpc.FmgsStub(ch), req) == first
        p.kill()
        p.wait(timeout=30)
        p, address = serve_process(root)
        with grpc.insecure_channel(address) as ch:
            assert _answer(pb_grpc.FmgsStub(ch), req) == first
    finally:
        if p.poll() is None:
            p.kill()


def _answer(stub, req):
    """The answer's arrays (timings left out)."""
    chunks = list(stub.TextQuery(req, timeout=60))
    return [(c.index.data, c.relevancy.data, c.total) for c in chunks]


def test_disconnected_stream_frees_its_slot(models):
    srv = start_server(
        ServerConfig(models=models, port=0, max_streams=1), encoder_factory=lambda i: FakeEncoder()
    )
    cam = pb.Camera(viewmat=np.eye(4).ravel().tolist(), fx=40, fy=40, cx=24, cy=20, width=48, height=40)
    try:
        with grpc.insecure_channel(srv.address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            for _ in range(5):
                gate = threading.Event()

                def poses(gate=gate):
                    yield pb.RenderRequest(scene="good", camera=cam, text="red cube")
                    gate.wait(10)

                it = stub.StreamRender(poses())
                assert next(it).sequence == 0
                it.cancel()  # the client goes away mid-stream
                gate.set()
                deadline = time.monotonic() + 10
                while srv.service.slots.free_streams() == 0 and time.monotonic() < deadline:
                    time.sleep(0.02)
                assert srv.service.slots.free_streams() == 1
    finally:
        srv.stop(0)


def test_atomic_dir_swap_never_leaves_the_path_missing(tmp_path):
    from fmgs.io.atomic import atomic_dir

    target = tmp_path / "scene"
    with atomic_dir(target) as d:
        (d / "manifest.json").write_text("0")
    missing, stop = [], threading.Event()

    def watch():
        while not stop.is_set():
            try:
                (target / "manifest.json").read_text()
            except OSError:
                missing.append(1)

    t = threading.Thread(target=watch)
    t.start()
    for i in range(200):
        with atomic_dir(target) as d:
            (d / "manifest.json").write_text(str(i))
    stop.set()
    t.join()
    assert (target / "manifest.json").read_text() == "199"
    assert not missing, f"the folder was missing {len(missing)} times"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
