"""The gRPC server on port 0: answers, chunking, streams, the error table, reloads, access control."""

from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path

import grpc
import numpy as np
import pytest
import torch
from grpc_health.v1 import health_pb2, health_pb2_grpc

from fmgs.query.engine import SceneEngine
from fmgs.query.pose import render_pose
from fmgs_server.config import ADMIN_CLOSED, ServerConfig
from fmgs_server.server import scene_health_name, start_server, warm_scene
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from fmgs_wire.tensors import from_tensor, join, to_tensor
from tests.helpers.query_scenes import (
    CLASS_NAMES,
    ENCODER_ID,
    FakeEncoder,
    blob_scene,
    camera,
    serve_process,
)

C = grpc.StatusCode


def _cam(w=48, h=40, **kw) -> pb.Camera:
    c = dict(viewmat=np.eye(4).ravel().tolist(), fx=40.0, fy=40.0, cx=w / 2, cy=h / 2, width=w, height=h)
    c.update(kw)
    return pb.Camera(**c)


@pytest.fixture()
def models(tmp_path):
    root = tmp_path / "models"
    root.mkdir()
    blob_scene(root / "blobs", with_field=True)
    blob_scene(root / "plain", seed=1)
    return root


def _start(models, **kw):
    kw.setdefault("reload_check_s", 0.0)
    return start_server(ServerConfig(models=models, port=0, **kw), encoder_factory=lambda i: FakeEncoder())


@pytest.fixture()
def server(models):
    srv = _start(models, chunk_bytes=512)
    yield srv
    srv.stop(0)


@pytest.fixture()
def stub(server):
    with grpc.insecure_channel(server.address) as ch:
        yield pb_grpc.FmgsStub(ch)


def _code(fn, *a, **kw) -> grpc.StatusCode:
    with pytest.raises(grpc.RpcError) as e:
        r = fn(*a, **kw)
        if not isinstance(r, pb.SceneInfo | pb.ListScenesResponse | pb.PointQueryResponse):
            list(r)
    return e.value.code(), e.value.details()


def _healthy(stub, server):
    with grpc.insecure_channel(server.address) as ch:
        h = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(service=""))
        assert h.status == health_pb2.HealthCheckResponse.SERVING
    assert len(list(stub.TextQuery(pb.TextQueryRequest(scene="blobs", texts=["red cube"], top_k=3)))) >= 1


def test_listing_and_lazy_load(stub):
    r = stub.ListScenes(pb.ListScenesRequest())
    assert [s.name for s in r.scenes] == ["blobs", "plain"]
    assert all(s.state == pb.SCENE_STATE_UNLOADED for s in r.scenes)
    assert r.scenes[0].encoder_id == ENCODER_ID and r.scenes[0].num_gaussians == 180
    assert list(r.scenes[0].label_names) == list(CLASS_NAMES) and r.scenes[0].has_field
    assert len(r.scenes[0].bounds) == 6  # from the manifest, before loading
    list(stub.TextQuery(pb.TextQueryRequest(scene="blobs", texts=["red cube"])))
    info = stub.GetScene(pb.SceneRequest(scene="blobs"))
    assert info.state == pb.SCENE_STATE_READY and info.resident_bytes > 0 and len(info.bounds) == 6


def _text_answers(chunks):
    out = {}
    for c in chunks:
        a = out.setdefault(c.text_index, {"text": None, "instances": [], "parts": {}})
        if c.text:
            a["text"], a["total"] = c.text, c.total
            a["instances"] = list(c.instances)
        for f, _ in c.ListFields():
            if f.message_type is not None and f.message_type.name == "Tensor":
                a["parts"].setdefault(f.name, []).append(from_tensor(getattr(c, f.name), f.name))
    return out


def test_text_query_chunked_equals_engine(stub, models):
    req = pb.TextQueryRequest(
        scene="blobs",
        texts=list(CLASS_NAMES),
        top_k=60,
        fields=[pb.GAUSSIAN_FIELD_MEAN, pb.GAUSSIAN_FIELD_SIMILARITY, pb.GAUSSIAN_FIELD_INSTANCE],
        instances=pb.InstanceOptions(enabled=True, min_points=5),
    )
    chunks = list(stub.TextQuery(req))
    assert len(chunks) > 3  # 512-byte chunks
    answers = _text_answers(chunks)
    eng = SceneEngine.open(models / "blobs")
    vecs = FakeEncoder().encode_text(list(CLASS_NAMES))
    for i, name in enumerate(CLASS_NAMES):
        a = answers[i]
        assert a["text"] == name and a["total"] == 60
        idx = join(a["parts"]["index"])
        ref = eng.text_query(vecs[i], 60)
        assert np.array_equal(idx, ref.index.numpy())
        assert np.allclose(join(a["parts"]["relevancy"]), ref.relevancy.numpy())
        assert np.allclose(join(a["parts"]["mean"]), eng.gaussians.means[ref.index].numpy())
        assert a["instances"] and a["instances"][0].num_members >= 5
        inst = join(a["parts"]["instance"])
        assert (inst == 0).sum() == a["instances"][0].num_members


def test_render_float_and_png(stub, models):
    req = pb.RenderRequest(scene="blobs", camera=_cam(), text="green ball", outputs=[1, 2, 3, 4], sequence=7)
    chunks = list(stub.Render(req))
    assert len(chunks) > 1 and chunks[-1].last and all(c.sequence == 7 for c in chunks)
    rel = join([from_tensor(c.relevancy) for c in chunks if c.HasField("relevancy")])
    rgb = join([from_tensor(c.rgb) for c in chunks if c.HasField("rgb")])
    eng = SceneEngine.open(models / "blobs")
    ref = render_pose(eng, camera(), FakeEncoder().encode_text(["green ball"])[0], ("relevancy", "rgb"))
    assert rel.shape == (40, 48) and rgb.shape == (40, 48, 3)
    assert np.allclose(rel, ref.relevancy.numpy(), atol=1e-6)
    assert (chunks[0].argmax.x, chunks[0].argmax.y) == ref.argmax[:2]
    png = list(stub.Render(pb.RenderRequest(scene="blobs", camera=_cam(), text="green ball", encoding=2)))
    assert len(png) == 1 and png[0].relevancy_png.startswith(b"\x89PNG")


def test_stream_latest_pose_wins(stub):
    def poses():
        for i in range(30):
            yield pb.RenderRequest(scene="blobs", camera=_cam(), text="red cube", sequence=i)

    seqs = [c.sequence for c in stub.StreamRender(poses()) if c.last]
    assert seqs and seqs == sorted(seqs) and seqs[-1] == 29 and len(seqs) <= 30


def test_point_query_and_segment(stub):
    pts = np.array([[-1.0, 0.0, 4.0], [1.0, 0.0, 4.0]], np.float32)
    req = pb.PointQueryRequest(scene="blobs", texts=["red cube", "green ball"], points=to_tensor(pts))
    r = stub.PointQuery(req)
    rel = from_tensor(r.relevancy)
    assert rel.shape == (2, 2) and np.isfinite(rel).all()
    seg = pb.SegmentRequest(scene="blobs", class_names=list(CLASS_NAMES), camera=_cam(), per_gaussian=True)
    chunks = list(stub.Segment(seg))
    labels = join([from_tensor(c.gaussian_labels) for c in chunks if c.HasField("gaussian_labels")])
    index = join([from_tensor(c.gaussian_index) for c in chunks if c.HasField("gaussian_index")])
    pix = join([from_tensor(c.pixel_labels) for c in chunks if c.HasField("pixel_labels")])
    assert (labels == index // 60).mean() > 0.9 and pix.shape == (40, 48) and chunks[-1].last


def _tq(**kw):
    kw.setdefault("scene", "blobs")
    return lambda s: s.TextQuery(pb.TextQueryRequest(**kw))


def _rd(text="a", **cam):
    return lambda s: s.Render(pb.RenderRequest(scene="blobs", text=text, camera=_cam(**cam)))


def _pq(points, scene="blobs"):
    return lambda s: s.PointQuery(pb.PointQueryRequest(scene=scene, texts=["a"], points=to_tensor(points)))


def _emb(enc, t):
    return _tq(texts=["a"], encoder_id=enc, embeddings=t)


F32 = np.float32
IA, FP = C.INVALID_ARGUMENT, C.FAILED_PRECONDITION
BAD = [
    ("unknown scene", _tq(scene="nope", texts=["a"]), C.NOT_FOUND, "nope"),
    ("path scene", lambda s: s.GetScene(pb.SceneRequest(scene="../models")), C.NOT_FOUND, "scene"),
    ("empty text", _tq(texts=[" "]), IA, "texts[0]"),
    ("no texts", _tq(), IA, "texts"),
    ("long text", _tq(texts=["a" * 5000]), IA, "texts[0]"),
    ("top_k", _tq(texts=["a"], top_k=10**8), IA, "top_k"),
    ("threshold", _tq(texts=["a"], threshold=float("nan")), IA, "threshold"),
    ("nan pose", _rd(viewmat=[float("nan")] * 16), IA, "camera.viewmat"),
    ("non-rigid", _rd(viewmat=(2 * np.eye(4)).ravel().tolist()), IA, "camera.viewmat"),
    ("short pose", _rd(viewmat=[1.0] * 15), IA, "camera.viewmat"),
    ("fx", _rd(fx=0.0), IA, "camera.fx"),
    ("inf cx", _rd(cx=float("inf")), IA, "camera.cx"),
    ("zero size", _rd(width=0), IA, "camera.width"),
    ("giant", _rd(w=100000, h=100000), IA, "image cap"),
    ("no camera", lambda s: s.Render(pb.RenderRequest(scene="blobs", text="a")), IA, "camera"),
    ("no text", _rd(text=""), IA, "text"),
    (
        "bad output",
        lambda s: s.Render(pb.RenderRequest(scene="blobs", text="a", camera=_cam(), outputs=[99])),
        IA,
        "outputs",
    ),
    ("bad field", _tq(texts=["a"], fields=[99]), IA, "fields"),
    ("unspecified field", _tq(texts=["a"], fields=[0]), IA, "fields"),
    ("encoder", _emb("other/enc", to_tensor(np.ones((1, 16), F32))), FP, "encoder"),
    ("emb shape", _emb(ENCODER_ID, to_tensor(np.ones((1, 5), F32))), IA, "embeddings"),
    ("emb bytes", _emb(ENCODER_ID, pb.Tensor(dtype=1, shape=[1, 16], data=b"x")), IA, "embeddings"),
    ("nan points", _pq(np.full((2, 3), np.nan, F32)), IA, "points"),
    ("points shape", _pq(np.zeros((2, 2), F32)), IA, "points"),
    ("no field", _pq(np.zeros((2, 3), F32), scene="plain"), FP, "field"),
    (
        "segment nothing",
        lambda s: s.Segment(pb.SegmentRequest(scene="blobs", class_names=["a"])),
        IA,
        "per_gaussian",
    ),
]


@pytest.mark.parametrize("case", BAD, ids=[b[0] for b in BAD])
def test_error_table(stub, server, case):
    _, call, code, word = case
    got, details = _code(call, stub)
    assert got == code, details
    assert word in details
    _healthy(stub, server)


def test_instances_over_too_many_neighbour_pairs_are_invalid_argument(models):
    """A huge instances.eps over a large top_k: a clear INVALID_ARGUMENT naming the setting, not a server
    out of memory; the server's max_instance_pairs sets the limit."""
    srv = _start(models, max_instance_pairs=1000)
    inst = pb.InstanceOptions(enabled=True, eps=1e12)
    try:
        with grpc.insecure_channel(srv.address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            got, details = _code(_tq(texts=["red cube"], top_k=180, instances=inst), stub)
            assert got == IA and "max_instance_pairs" in details and "instances.eps or top_k" in details
            answer = list(_tq(texts=["red cube"], top_k=40, instances=inst)(stub))  # 780 pairs: grouped
            assert len(answer[0].instances) == 1, answer[0].instances
    finally:
        srv.stop(0)


def test_overload_is_resource_exhausted(models):
    srv = _start(models, max_streams=1)
    try:
        with grpc.insecure_channel(srv.address) as ch:
            s = pb_grpc.FmgsStub(ch)
            gate = threading.Event()

            def slow():
                yield pb.RenderRequest(scene="blobs", camera=_cam(), text="red cube")
                gate.wait(10)

            first = s.StreamRender(slow())
            next(first)  # the first stream is open and holds the only slot
            again = iter([pb.RenderRequest(scene="blobs", camera=_cam(), text="a")])
            got, details = _code(lambda: s.StreamRender(again))
            assert got == C.RESOURCE_EXHAUSTED and "streams" in details
            gate.set()
            list(first)
            _healthy(s, srv)
    finally:
        srv.stop(0)


def test_broken_scene_is_failed_and_others_serve(stub, server, models):
    shutil.copytree(models / "plain", models / "broken")
    (models / "broken" / "embeddings.safetensors").write_bytes(b"garbage")
    got, details = _code(lambda: stub.TextQuery(pb.TextQueryRequest(scene="broken", texts=["a"])))
    assert got == C.FAILED_PRECONDITION and "embeddings.safetensors" in details
    states = {s.name: s for s in stub.ListScenes(pb.ListScenesRequest()).scenes}
    assert states["broken"].state == pb.SCENE_STATE_FAILED and "embeddings" in states["broken"].reason
    with grpc.insecure_channel(server.address) as ch:
        req = health_pb2.HealthCheckRequest(service=scene_health_name("broken"))
        h = health_pb2_grpc.HealthStub(ch).Check(req)
        assert h.status == health_pb2.HealthCheckResponse.NOT_SERVING
    _healthy(stub, server)


def test_reload_when_files_change_and_delete(stub, models):
    first = _text_answers(stub.TextQuery(pb.TextQueryRequest(scene="plain", texts=["red cube"], top_k=5)))
    blob_scene(models / "plain", seed=7)  # replaced atomically
    time.sleep(0.01)
    second = _text_answers(stub.TextQuery(pb.TextQueryRequest(scene="plain", texts=["red cube"], top_k=5)))
    eng = SceneEngine.open(models / "plain")
    ref = eng.text_query(FakeEncoder().encode_text(["red cube"])[0], 5)
    assert np.array_equal(join(second[0]["parts"]["index"]), ref.index.numpy())
    assert not np.array_equal(join(first[0]["parts"]["relevancy"]), join(second[0]["parts"]["relevancy"]))
    shutil.rmtree(models / "plain")
    got, _ = _code(lambda: stub.TextQuery(pb.TextQueryRequest(scene="plain", texts=["a"])))
    assert got == C.NOT_FOUND
    assert [s.name for s in stub.ListScenes(pb.ListScenesRequest()).scenes] == ["blobs"]


def test_tokens(models, tmp_path):
    (tmp_path / "read").write_text("reader-token\n")
    (tmp_path / "admin").write_text("# admins\nadmin-token\n")
    srv = _start(models, token_file=tmp_path / "read", admin_token_file=tmp_path / "admin")
    try:
        with grpc.insecure_channel(srv.address) as ch:
            s = pb_grpc.FmgsStub(ch)
            q = pb.TextQueryRequest(scene="blobs", texts=["red cube"])
            assert _code(lambda: s.TextQuery(q))[0] == C.UNAUTHENTICATED
            bad = [("authorization", "Bearer nope")]
            assert _code(lambda: s.TextQuery(q, metadata=bad))[0] == C.UNAUTHENTICATED
            assert list(s.TextQuery(q, metadata=[("authorization", "Bearer reader-token")]))
            load = pb.SceneRequest(scene="blobs")
            got = _code(lambda: s.LoadScene(load, metadata=[("authorization", "Bearer reader-token")]))[0]
            assert got == C.PERMISSION_DENIED
            info = s.LoadScene(load, metadata=[("authorization", "Bearer admin-token")])
            assert info.state == pb.SCENE_STATE_READY
            h = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(service=""))
            assert h.status == health_pb2.HealthCheckResponse.SERVING
    finally:
        srv.stop(0)


def test_admin_calls_are_closed_by_default_off_loopback(models):
    """The defaults on 0.0.0.0 (as the image runs): anyone who reaches the port could unload every scene."""
    for admin_open in (False, True):
        srv = _start(models, host="0.0.0.0", admin_open=admin_open)
        try:
            assert srv.bound == f"0.0.0.0:{srv.port}" and srv.describe().endswith(f"127.0.0.1:{srv.port})")
            with grpc.insecure_channel(srv.address) as ch:
                s = pb_grpc.FmgsStub(ch)
                list(s.TextQuery(pb.TextQueryRequest(scene="blobs", texts=["red cube"], top_k=3)))  # loads
                blobs = pb.SceneRequest(scene="blobs")
                if admin_open:
                    assert s.UnloadScene(blobs).state == pb.SCENE_STATE_UNLOADED
                    assert s.LoadScene(blobs).state == pb.SCENE_STATE_READY
                    continue
                for call in (s.UnloadScene, s.LoadScene, s.ReloadScene):
                    assert _code(lambda call=call: call(pb.SceneRequest(scene="blobs"))) == (
                        C.PERMISSION_DENIED,
                        ADMIN_CLOSED,
                    )
                assert s.GetScene(blobs).state == pb.SCENE_STATE_READY  # still loaded
                assert list(s.TextQuery(pb.TextQueryRequest(scene="blobs", texts=["a"], top_k=3)))
        finally:
            srv.stop(0)


def _health(ch, service: str = "") -> int:
    return (
        health_pb2_grpc.HealthStub(ch)
        .Check(health_pb2.HealthCheckRequest(service=service), timeout=10)
        .status
    )


def test_health_is_not_serving_until_the_preload_warm_up_ends(models):
    """Each scene is NOT_SERVING until its own warm-up ends, the server until every scene's has; a scene
    whose warm-up failed stays NOT_SERVING while the server says SERVING."""
    SERVING, NOT_SERVING = health_pb2.HealthCheckResponse.SERVING, health_pb2.HealthCheckResponse.NOT_SERVING
    entered = {name: threading.Event() for name in ("blobs", "plain")}
    release = {name: threading.Event() for name in ("blobs", "plain")}

    def warm(service, name):  # the warm-up, held until the test lets it end
        entered[name].set()
        assert release[name].wait(60)
        if name == "plain":
            raise RuntimeError("no encoder here")
        service.repo.get(name)
        return 0.0

    srv = start_server(
        ServerConfig(models=models, port=0, preload=True), lambda i: FakeEncoder(), warm=warm, wait=False
    )
    try:
        with grpc.insecure_channel(srv.address) as ch:
            assert entered["blobs"].wait(60)
            names = ("", "fmgs.v1.Fmgs", "fmgs.v1.Fmgs/blobs", "fmgs.v1.Fmgs/plain")

            def state():
                return [_health(ch, n) for n in names]

            assert state() == [NOT_SERVING] * 4 and not srv.ready.is_set()
            release["blobs"].set()
            assert entered["plain"].wait(60)
            assert state() == [NOT_SERVING, NOT_SERVING, SERVING, NOT_SERVING]
            release["plain"].set()
            assert srv.ready.wait(60)
            assert state() == [SERVING, SERVING, SERVING, NOT_SERVING]
    finally:
        srv.stop(0)


def test_preload_warms_each_scene_before_returning(models):
    loaded = []

    def encoder(encoder_id):
        loaded.append(encoder_id)
        return FakeEncoder()

    srv = start_server(ServerConfig(models=models, port=0, preload=True), encoder)
    try:
        assert srv.ready.is_set() and loaded == [ENCODER_ID]
        with grpc.insecure_channel(srv.address) as ch:
            assert [_health(ch, n) for n in ("", "fmgs.v1.Fmgs/blobs", "fmgs.v1.Fmgs/plain")] == [
                health_pb2.HealthCheckResponse.SERVING
            ] * 3
            scenes = pb_grpc.FmgsStub(ch).ListScenes(pb.ListScenesRequest()).scenes
            assert all(s.state == pb.SCENE_STATE_READY for s in scenes)
        assert warm_scene(srv.service, "blobs") >= 0.0  # warm again: the kernels are compiled already
    finally:
        srv.stop(0)


def test_memory_budget_unloads_least_recently_used(models):
    one = SceneEngine.open(models / "blobs").nbytes()
    srv = _start(models, memory_budget_bytes=int(one * 1.5))
    try:
        with grpc.insecure_channel(srv.address) as ch:
            s = pb_grpc.FmgsStub(ch)
            list(s.TextQuery(pb.TextQueryRequest(scene="blobs", texts=["a"])))
            list(s.TextQuery(pb.TextQueryRequest(scene="plain", texts=["a"])))
            st = {x.name: x.state for x in s.ListScenes(pb.ListScenesRequest()).scenes}
            assert st == {"blobs": pb.SCENE_STATE_UNLOADED, "plain": pb.SCENE_STATE_READY}
    finally:
        srv.stop(0)


def test_deadline_is_honoured(stub):
    with pytest.raises(grpc.RpcError) as e:
        req = pb.RenderRequest(scene="blobs", camera=_cam(w=2000, h=2000), text="a")
        list(stub.Render(req, timeout=1e-4))
    assert e.value.code() == C.DEADLINE_EXCEEDED


def test_cli_serve_parser_defaults_bind_loopback():
    from fmgs_server.cli import build_parser, config_from_args

    cfg = config_from_args(build_parser().parse_args([]))
    assert cfg.host == "127.0.0.1" and cfg.models == Path("models")
    assert torch.get_num_threads() >= 1


def test_fmgs_serve_process_answers_and_stops_on_sigterm(models):
    import signal

    p, address = serve_process(models)
    try:
        with grpc.insecure_channel(address) as ch:
            r = pb_grpc.FmgsStub(ch).ListScenes(pb.ListScenesRequest(), timeout=30)
            assert [s.name for s in r.scenes] == ["blobs", "plain"]
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=30) == 0
    finally:
        if p.poll() is None:
            p.kill()


def test_health_can_require_a_token(models, tmp_path):
    (tmp_path / "read").write_text("t0k3n\n")
    srv = _start(models, token_file=tmp_path / "read", health_open=False)
    try:
        with grpc.insecure_channel(srv.address) as ch:
            h = health_pb2_grpc.HealthStub(ch)
            with pytest.raises(grpc.RpcError) as e:
                h.Check(health_pb2.HealthCheckRequest(service=""))
            assert e.value.code() == C.UNAUTHENTICATED
            ok = h.Check(
                health_pb2.HealthCheckRequest(service=""), metadata=[("authorization", "Bearer t0k3n")]
            )
            assert ok.status == health_pb2.HealthCheckResponse.SERVING
    finally:
        srv.stop(0)


def test_nothing_unpickles():
    """No code path that reads user or network data can run pickle."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    bad = re.compile(r"\bpickle\b|torch\.load\(|np\.load\((?![^)]*allow_pickle=False)|allow_pickle=True")
    hits = []
    for pkg in ("fmgs", "fmgs_server", "fmgs_client"):
        for f in (root / pkg).rglob("*.py"):
            if "_proto" in f.parts:
                continue
            for i, line in enumerate(f.read_text().splitlines(), 1):
                if bad.search(line) and "no pickle" not in line.lower() and "No pickle" not in line:
                    hits.append(f"{f.relative_to(root)}:{i}: {line.strip()}")
    assert not hits, hits


_KERNEL_RUN = """
import json, numpy as np
from fmgs.render.cpu_kernels import stable_argsort_positive as k
k(np.array([3.0, 1.0, 2.0]))
print(json.dumps([sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values())]))
"""


@pytest.mark.slow
def test_compiled_kernels_are_kept_for_the_next_start(tmp_path):
    """numba's cache (NUMBA_CACHE_DIR in the image): the first process compiles and writes the cache, a
    second one loads the machine code from it instead of compiling again."""
    import json
    import os
    import subprocess
    import sys

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}

    def run() -> list[int]:
        out = subprocess.run([sys.executable, "-c", _KERNEL_RUN], env=env, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout.splitlines()[-1])

    assert run() == [0, 1]  # compiled
    assert list((tmp_path / "numba").rglob("*stable_argsort_positive*.nbi"))
    assert run() == [1, 0]  # read from the cache


def test_precompile_runs_every_scene_and_says_when_one_fails(models, tmp_path):
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "fmgs_server.cli", "--models", str(models), "--precompile"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "scene blobs: kernels compiled" in done.stderr and "scene plain: kernels compiled" in done.stderr
    (models / "plain" / "gaussians.safetensors").write_bytes(b"broken")
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 1 and "scene plain:" in done.stderr


def test_a_ray_replica_warms_the_kernels_once_and_every_encoder(models):
    """preload on a Ray scene replica (fmgs_server.cluster.host, no Ray needed): the first scene is warmed
    and unloaded again (the multiplexer places scenes), the other scenes' encoders are loaded."""
    from fmgs_server.cluster.host import HostCore

    loaded, warmed = [], []

    def encoder(encoder_id):
        loaded.append(encoder_id)
        return FakeEncoder()

    def warm(service, name):
        warmed.append(name)
        service.repo.get(name)
        return 0.0

    core = HostCore(ServerConfig(models=models, preload=True), encoder)
    core.warm_up(warm)
    assert warmed == ["blobs"] and loaded == [ENCODER_ID]
    assert [s.state for s in core.service.repo.scan()] == ["unloaded", "unloaded"]
