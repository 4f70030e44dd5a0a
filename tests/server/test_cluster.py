"""The service on a local Ray cluster answers as ``fmgs serve`` does, through Ray Serve's gRPC proxy.

The session's Ray cluster (tests/conftest.py: two nodes of one CPU each on this machine) with one Serve
application for the module: two scene replicas of one CPU each, so one on each node; the same repository
served directly and through Ray; every RPC compared on the wire, answers and errors alike. A client on
the head's gRPC port is answered by replicas on either node, as by one process.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from fmgs.scene.shards import write_shards
from fmgs_client import FmgsClient
from fmgs_server.cluster.app import REPLICA_KEY
from fmgs_server.cluster.config import ClusterConfig
from fmgs_server.config import ServerConfig
from fmgs_server.server import start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from fmgs_wire.tensors import from_tensor
from tests.helpers.query_scenes import CENTRES, CLASS_NAMES, ENCODER_ID, FakeEncoder, blob_scene

ray = pytest.importorskip("ray", reason="the fmgs[ray] extra is part of the CI install")
pytestmark = pytest.mark.slow  # a Ray cluster and a Serve application
ROOT = Path(__file__).resolve().parents[2]
READ, ADMIN = "read-token", "admin-token"


def encoder_factory(encoder_id: str):
    """The blob scenes' encoder, or the real one (the demo's MiniLM)."""
    if encoder_id == ENCODER_ID:
        return FakeEncoder()
    from fmgs.features.text import load_text_encoder

    return load_text_encoder(encoder_id, device="cpu")


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("cluster") / "models"
    root.mkdir()
    blob_scene(root / "blobs", with_field=True)
    blob_scene(root / "plain", seed=1)
    blob_scene(root / "third", seed=2)
    shutil.copytree(ROOT / "models" / "demo", root / "demo")
    write_shards(root / "blobs", root / "blobs-4shards", 4)
    (root / "tokens").write_text(READ + "\n")
    (root / "admin").write_text(ADMIN + "\n")
    return root


def _cfg(models, port=0):
    return ServerConfig(
        models=models, port=port, reload_check_s=0.0, chunk_bytes=512,
        token_file=models / "tokens", admin_token_file=models / "admin",
    )  # fmt: skip


@pytest.fixture(scope="module")
def direct(models):
    srv = start_server(_cfg(models), encoder_factory=encoder_factory)
    yield srv.address
    srv.stop(0)


@pytest.fixture(scope="module")
def cluster(models, ray_cluster):
    from ray import serve

    from fmgs_server.cluster.launch import start_ray_serve

    # One CPU per replica on nodes of one CPU each: one replica on each node.
    cc = ClusterConfig(min_replicas=2, max_replicas=2, replica_cpus=1.0, scenes_per_replica=8)
    try:
        port = start_ray_serve(_cfg(models), cc, ray_cluster.address, encoder_factory)
        yield f"127.0.0.1:{port}"
    finally:
        serve.shutdown()


def _stub(address):
    return pb_grpc.FmgsStub(grpc.insecure_channel(address))


MD = (("authorization", f"Bearer {READ}"),)
ADMIN_MD = (("authorization", f"Bearer {ADMIN}"),)


def _norm(msg):
    """A message without its timings (and resident bytes, which differ by replica)."""
    m = type(msg)()
    m.CopyFrom(msg)
    for f in ("elapsed_ms",):
        if f in m.DESCRIPTOR.fields_by_name:
            m.ClearField(f)
    if isinstance(m, pb.SceneInfo):
        m.ClearField("resident_bytes")
    if isinstance(m, pb.ListScenesResponse):
        for s in m.scenes:
            s.ClearField("resident_bytes")
    return m


def _call(stub, method, request, md=MD):
    """(code name, details, [normalised messages]) of one call."""
    fn = getattr(stub, method)
    try:
        out = fn(request, metadata=md, timeout=120)
        msgs = list(out) if not hasattr(out, "SerializeToString") else [out]
        return "OK", "", [_norm(m) for m in msgs]
    except grpc.RpcError as e:
        return e.code().name, e.details(), []


def _cam():
    return pb.Camera(
        width=24, height=20, fx=20.0, fy=20.0, cx=12.0, cy=10.0,
        viewmat=[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
    )  # fmt: skip


def _requests():
    """Every RPC, on scenes and with arguments that succeed and that fail."""
    names = list(CLASS_NAMES)
    fields = [pb.GAUSSIAN_FIELD_MEAN, pb.GAUSSIAN_FIELD_SIMILARITY, pb.GAUSSIAN_FIELD_INSTANCE]
    inst = pb.InstanceOptions(enabled=True)
    yield "ListScenes", pb.ListScenesRequest()
    for scene in ("blobs", "plain", "third", "demo", "missing", "../x", "blobs-4shards"):
        yield "GetScene", pb.SceneRequest(scene=scene)
        yield (
            "TextQuery",
            pb.TextQueryRequest(scene=scene, texts=names, top_k=25, fields=fields, instances=inst),
        )
    yield "TextQuery", pb.TextQueryRequest(scene="demo", texts=["a red cube", "laptop"], top_k=10)
    yield "TextQuery", pb.TextQueryRequest(scene="blobs", texts=names[:1], top_k=5, threshold=0.2)
    yield "TextQuery", pb.TextQueryRequest(scene="blobs", texts=[], top_k=5)
    yield "TextQuery", pb.TextQueryRequest(scene="blobs", texts=names, top_k=10_000_000)
    yield (
        "Render",
        pb.RenderRequest(
            scene="blobs",
            camera=_cam(),
            text="red cube",
            outputs=[pb.RENDER_OUTPUT_RELEVANCY, pb.RENDER_OUTPUT_RGB],
        ),
    )
    yield "Render", pb.RenderRequest(scene="blobs", camera=_cam(), encoding=pb.IMAGE_ENCODING_PNG)
    yield "Render", pb.RenderRequest(scene="blobs")
    rel_alpha = [pb.RENDER_OUTPUT_RELEVANCY, pb.RENDER_OUTPUT_ALPHA]
    yield "Render", pb.RenderRequest(scene="blobs-4shards", camera=_cam(), text="red cube", outputs=rel_alpha)
    yield (
        "Render",
        pb.RenderRequest(
            scene="blobs-4shards", camera=_cam(), text="green ball", outputs=[pb.RENDER_OUTPUT_RELEVANCY]
        ),
    )
    yield "LoadScene", pb.SceneRequest(scene="blobs-4shards")
    pts = pb.Tensor(dtype=pb.DTYPE_FLOAT32, shape=[2, 3], data=CENTRES[:2].float().numpy().tobytes())
    yield "PointQuery", pb.PointQueryRequest(scene="blobs", texts=names, points=pts)
    yield "PointQuery", pb.PointQueryRequest(scene="plain", texts=names, points=pts)
    yield "Segment", pb.SegmentRequest(scene="blobs", class_names=names, camera=_cam(), per_gaussian=True)
    yield "Segment", pb.SegmentRequest(scene="blobs", class_names=names)
    yield "Geometry", pb.GeometryRequest(scene="blobs", max_gaussians=50, min_opacity=0.2)
    yield "Geometry", pb.GeometryRequest(scene="blobs", max_gaussians=10**12)
    yield "Geometry", pb.GeometryRequest(scene="blobs-4shards")


def _split_floats(result):
    """(result with every presence score and margin and every float tensor's data cleared, the floats
    cleared in message order)."""
    code, details, msgs = result
    out, floats = [], []

    def walk(m):
        for fd, value in m.ListFields():
            if fd.type != fd.TYPE_MESSAGE:
                continue
            for sub in value if fd.is_repeated else [value]:
                if not isinstance(sub, pb.Tensor):
                    walk(sub)
                elif (arr := from_tensor(sub)).dtype.kind == "f":
                    floats.append(arr.astype(np.float64))
                    sub.ClearField("data")

    for m in msgs:
        c = type(m)()
        c.CopyFrom(m)
        if "presence" in c.DESCRIPTOR.fields_by_name and c.HasField("presence"):
            floats.append(np.array([c.presence.score, c.presence.margin]))
            c.presence.ClearField("score")
            c.presence.ClearField("margin")
        walk(c)
        out.append(c)
    return (code, details, out), floats


def test_replicas_on_two_nodes_answer_alike(direct, cluster, models):
    """Replicas spread over both nodes, and scenes no replica holds yet go to the one holding the fewest:
    four new scenes are answered from both nodes, each as fmgs serve answers it. (First in the module:
    no other test has given a replica a scene yet.)"""
    from ray import serve

    details = serve.context._get_global_client().get_serve_details()
    replicas = details["applications"]["fmgs"]["deployments"]["SceneHost"]["replicas"]
    assert len({r["node_id"] for r in replicas}) == 2  # spread over both nodes
    stub, one = _stub(cluster), _stub(direct)
    names = [f"nodes{i}" for i in range(4)]
    for i, name in enumerate(names):
        blob_scene(models / name, seed=i)
    try:
        seen = set()
        for name in names:
            req = pb.TextQueryRequest(scene=name, texts=list(CLASS_NAMES), top_k=20)
            call = stub.TextQuery(req, metadata=MD, timeout=120)
            got = [(c.text_index, c.index.data, c.relevancy.data) for c in call]
            seen |= {v for k, v in call.trailing_metadata() if k == REPLICA_KEY}
            want = [
                (c.text_index, c.index.data, c.relevancy.data)
                for c in one.TextQuery(req, metadata=MD, timeout=120)
            ]
            assert got == want and len(got) >= 3
        assert len(seen) == 2  # scenes go to the replica holding the fewest: both nodes answer
    finally:
        for name in names:
            shutil.rmtree(models / name)


def test_every_rpc_answers_as_fmgs_serve_does(direct, cluster):
    a, b = _stub(direct), _stub(cluster)
    for method, req in _requests():
        want, want_f = _split_floats(_call(a, method, req))
        got, got_f = _split_floats(_call(b, method, req))
        assert got == want, f"{method} {req}"
        # The demo's real text encoder (MiniLM) sums in float32, and the same text's embedding can differ
        # in its last bits between the replicas and the server in this process (on Intel: 1 against 2
        # torch threads, up to 1.1e-7 per component, measured; CI saw presence differ in its 8th digit
        # and, on AMD, one relevancy in its last float32 bit, with 1 and 2 threads giving identical
        # embeddings there: the cause on that machine is not established). So presence and every float
        # tensor (relevancy, similarity, images) agree to 1e-6; rows, shapes, names and counts bit for bit.
        assert len(got_f) == len(want_f), f"{method} {req}"
        for g, w in zip(got_f, want_f, strict=True):
            assert g.shape == w.shape and np.allclose(g, w, rtol=1e-6, atol=1e-7), f"{method} {req}"
    assert any(_call(a, m, r)[0] != "OK" for m, r in _requests())  # the error table is exercised too


def test_sharded_text_queries_equal_the_unsharded_scene(cluster):
    s = _stub(cluster)
    for texts, k, thr in [
        (list(CLASS_NAMES), 40, 0.0),
        (["nothing like it"], 180, 0.0),
        (["red cube"], 50, 0.6),
    ]:
        fields = [pb.GAUSSIAN_FIELD_MEAN, pb.GAUSSIAN_FIELD_SIMILARITY, pb.GAUSSIAN_FIELD_INSTANCE]
        req = dict(
            texts=texts, top_k=k, threshold=thr, fields=fields, instances=pb.InstanceOptions(enabled=True)
        )
        one = _call(s, "TextQuery", pb.TextQueryRequest(scene="blobs", **req))
        many = _call(s, "TextQuery", pb.TextQueryRequest(scene="blobs-4shards", **req))
        assert one[0] == "OK" and len(one[2]) > 0
        for x, y in zip(one[2], many[2], strict=True):
            x.ClearField("rescored")  # rows rescored differ: each shard certifies its own answer
            y.ClearField("rescored")
        assert one == many


def test_sharded_scenes_answer_text_and_relevancy_renders_only(cluster, models):
    import numpy as np

    from fmgs.query.sharded import ShardedSceneEngine
    from fmgs_client.client import assemble_render
    from fmgs_server.convert import camera as to_camera

    s = _stub(cluster)
    rgb = pb.RenderRequest(scene="blobs-4shards", camera=_cam(), outputs=[pb.RENDER_OUTPUT_RGB])
    code, details, _ = _call(s, "Render", rgb)
    assert code == "FAILED_PRECONDITION" and "sharded" in details  # colour needs every Gaussian
    for name, fn in (("Segment", pb.SegmentRequest), ("PointQuery", pb.PointQueryRequest)):
        code, details, _ = _call(s, name, fn(scene="blobs-4shards", class_names=["x"]) if name == "Segment"
                                 else fn(scene="blobs-4shards", texts=["x"]))  # fmt: skip
        assert code == "FAILED_PRECONDITION" and "sharded" in details, name
    req = pb.RenderRequest(
        scene="blobs-4shards", camera=_cam(), text="red cube",
        outputs=[pb.RENDER_OUTPUT_RELEVANCY, pb.RENDER_OUTPUT_ALPHA],
    )  # fmt: skip
    code, _, chunks = _call(s, "Render", req)
    assert code == "OK"
    got = assemble_render(chunks)
    local = ShardedSceneEngine(models / "blobs-4shards").render_pose(
        to_camera(_cam(), _cfg(models)), FakeEncoder().encode_text(["red cube"])[0], ("relevancy", "alpha")
    )
    assert np.array_equal(got.relevancy, local.relevancy.numpy())  # the same layers, composited alike
    assert np.array_equal(got.alpha, local.alpha.numpy())
    code, _, (info,) = _call(s, "GetScene", pb.SceneRequest(scene="blobs-4shards"))
    assert code == "OK" and info.num_gaussians == 180 and info.encoder_id == ENCODER_ID


def test_the_thin_client_and_health_work_unchanged(direct, cluster):
    for address in (direct, cluster):
        with FmgsClient(address, timeout=60, token=READ) as c:
            names = [s.name for s in c.list_scenes()]
            assert names == ["blobs", "blobs-4shards", "demo", "plain", "third"]
            ans = c.query("blobs", ["red cube"], top_k=10)[0]
            assert len(ans.index) == 10
            assert c.health() == "SERVING"
            assert c.health("fmgs.v1.Fmgs/blobs") == "SERVING"
    h = health_pb2_grpc.HealthStub(grpc.insecure_channel(cluster))
    with pytest.raises(grpc.RpcError) as e:
        h.Check(health_pb2.HealthCheckRequest(service="fmgs.v1.Fmgs/blobs"))
    assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED  # scene names are not probed without a token


def test_tokens_and_admin_rpcs_follow_the_same_rules(direct, cluster):
    for method, req, md in [
        ("GetScene", pb.SceneRequest(scene="blobs"), ()),
        ("GetScene", pb.SceneRequest(scene="blobs"), (("authorization", "Bearer wrong"),)),
        ("LoadScene", pb.SceneRequest(scene="plain"), MD),
        ("UnloadScene", pb.SceneRequest(scene="plain"), ADMIN_MD),
        ("ReloadScene", pb.SceneRequest(scene="missing"), ADMIN_MD),
    ]:
        assert _call(_stub(cluster), method, req, md)[:2] == _call(_stub(direct), method, req, md)[:2]


def test_a_scene_is_answered_by_the_replica_that_holds_it(cluster, models):
    import time

    ch = grpc.insecure_channel(cluster)
    s = pb_grpc.FmgsStub(ch)
    for scene in ("fresh1", "fresh2"):  # scenes no other test touches: held by no replica yet
        shutil.copytree(models / "plain", models / scene)
        first = set()
        _, call = s.GetScene.with_call(pb.SceneRequest(scene=scene), metadata=MD, timeout=60)
        first |= {v for k, v in call.trailing_metadata() if k == REPLICA_KEY}
        time.sleep(1.0)  # replicas report the scenes they hold to the routers every 0.1 s
        seen = set()
        for _ in range(8):
            _, call = s.GetScene.with_call(pb.SceneRequest(scene=scene), metadata=MD, timeout=60)
            seen |= {v for k, v in call.trailing_metadata() if k == REPLICA_KEY}
        assert len(first) == 1 and seen == first, f"{scene}: first on {first}, then on {seen}"
        shutil.rmtree(models / scene)


def test_killing_a_replica_under_load_fails_only_calls_the_client_sees_fail(cluster):
    import threading
    import time

    from ray import serve

    req = pb.TextQueryRequest(scene="blobs", texts=list(CLASS_NAMES), top_k=30)
    s = _stub(cluster)
    ref = _call(s, "TextQuery", req)
    assert ref[0] == "OK"
    details = serve.context._get_global_client().get_serve_details()
    replicas = details["applications"]["fmgs"]["deployments"]["SceneHost"]["replicas"]
    victim = ray.get_actor(replicas[0]["actor_name"], namespace="serve")
    results, stop = [], threading.Event()

    def load():
        stub = _stub(cluster)
        while not stop.is_set():
            results.append(_call(stub, "TextQuery", req))

    threads = [threading.Thread(target=load) for _ in range(3)]
    for t in threads:
        t.start()
    time.sleep(2.0)
    ray.kill(victim, no_restart=True)
    time.sleep(4.0)
    stop.set()
    for t in threads:
        t.join(120)
    assert results and all(not t.is_alive() for t in threads)
    # Every call either brought the whole, right answer or (only a call the dead replica had begun to
    # stream) failed with UNAVAILABLE and our short text: nothing of Ray's exception reaches the client.
    from fmgs_server.cluster.faults import REPLICA_LOST

    for r in results:
        assert r == ref or (r[:2] == ("UNAVAILABLE", REPLICA_LOST.details) and r[2] == []), r[:2]
    # Service recovers without intervention: the controller replaces the replica.
    deadline = time.monotonic() + 90
    ok = 0
    while ok < 5 and time.monotonic() < deadline:
        ok = ok + 1 if _call(s, "TextQuery", req) == ref else 0
    assert ok == 5


def test_pose_streams_answer_as_fmgs_serve_does(direct, cluster):
    """Every frame a pose stream returns is the frame fmgs serve renders for that pose."""
    import queue

    def stream(address):
        s = _stub(address)
        reqs = queue.Queue()
        out = s.StreamRender(iter(reqs.get, None), metadata=MD, timeout=120)
        chunks = []
        for seq in range(3):
            req = pb.RenderRequest(
                scene="blobs", camera=_cam(), text=CLASS_NAMES[seq], sequence=seq,
                outputs=[pb.RENDER_OUTPUT_RELEVANCY],
            )  # fmt: skip
            reqs.put(req)
            while not (chunks and chunks[-1].width and chunks[-1].sequence == seq):
                chunks.append(_norm(next(out)))  # until this pose's frame starts: then the next pose
        reqs.put(None)
        chunks += [_norm(c) for c in out]
        return chunks

    want, got = stream(direct), stream(cluster)
    starts = [c.sequence for c in want if c.width]  # a frame's first chunk carries its size
    assert starts == [0, 1, 2] and got == want


def test_a_package_replaced_in_place_is_served_in_its_new_version(direct, cluster, models):
    """The atomic swap (fmgs.io.atomic.atomic_dir) reaches the replicas: after it, both servers answer
    from the new package."""
    import time

    s, d = _stub(cluster), _stub(direct)
    req = pb.TextQueryRequest(scene="swap", texts=list(CLASS_NAMES), top_k=15)
    blob_scene(models / "swap", seed=5)
    before = _call(s, "TextQuery", req)
    assert before == _call(d, "TextQuery", req)
    time.sleep(1.0)  # the routers learn which replica holds it
    v0 = _call(s, "GetScene", pb.SceneRequest(scene="swap"))[2][0].version
    assert v0
    blob_scene(models / "swap", seed=6)  # written beside it, swapped in one rename
    after = _call(s, "TextQuery", req)
    assert after[0] == "OK" and after != before and after == _call(d, "TextQuery", req)
    assert _call(s, "GetScene", pb.SceneRequest(scene="swap"))[2][0].version != v0
