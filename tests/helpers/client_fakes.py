"""Fakes of the wire and the service for the thin client's tests: chunk builders (what a server sends),
a query answer with instances, and a small in-process fake of the FMGS service with the standard health
service beside it."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent import futures
from contextlib import contextmanager

import grpc
import numpy as np
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from fmgs_client.types import Box, Instance, TextAnswer
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from fmgs_wire.tensors import from_tensor, row_chunks, to_tensor

# ---------------------------------------------------------------- chunk builders (what a server sends)


def text_chunks(i, text, cols, instances=(), rows_per_chunk=2, elapsed=1.5):
    """Chunks of one text's answer: ``cols`` maps chunk field names to [K,...] arrays."""
    k = len(cols["index"])
    out = []
    for s, e in row_chunks(k, 1, rows_per_chunk):
        c = pb.TextQueryChunk(text_index=i, start=s)
        if s == 0:
            c.text, c.total, c.elapsed_ms = text, k, elapsed
            c.instances.extend(instances)
        for n, a in cols.items():
            getattr(c, n).CopyFrom(to_tensor(a[s:e]))
        out.append(c)
    return out


def interleave(*lists):
    out, lists = [], [list(x) for x in lists]
    while any(lists):
        for x in lists:
            if x:
                out.append(x.pop(0))
    return out


def pb_box(center, extent, rot=None):
    return pb.Box(center=center, extent=extent, rotation=[] if rot is None else list(np.ravel(rot)))


def answer_cols(rng, k, with_fields=True):
    cols = {
        "index": rng.permutation(1000)[:k].astype(np.int64),
        "relevancy": np.sort(rng.random(k).astype(np.float32))[::-1].copy(),
    }
    if with_fields:
        cols["mean"] = rng.normal(size=(k, 3)).astype(np.float32)
        cols["similarity"] = rng.random(k).astype(np.float32)
        cols["instance"] = rng.integers(-1, 2, k).astype(np.int32)
    return cols


def render_chunks(seq, images, rows_per_chunk, argmax=None, png=None):
    """Chunks of one rendered view: ``images`` maps names to [H,W,...] float32 arrays."""
    h, w = (next(iter(images.values())).shape[:2]) if images else (png["shape"])
    spans = row_chunks(h, 1, rows_per_chunk) if images else [(0, 0)]
    out = []
    for s, e in spans:
        c = pb.RenderChunk(sequence=seq, row_start=s)
        if s == 0:
            c.width, c.height, c.elapsed_ms = w, h, 2.5
            if argmax is not None:
                c.argmax.CopyFrom(pb.Pixel(x=argmax[0], y=argmax[1], value=argmax[2]))
            for n, data in (png or {}).items():
                if n != "shape":
                    setattr(c, f"{n}_png", data)
        for n, a in images.items():
            getattr(c, n).CopyFrom(to_tensor(a[s:e]))
        out.append(c)
    out[-1].last = True
    return out


# ---------------------------------------------------------------- a query answer with instances


def answer_with_instances(n=400) -> TextAnswer:
    """A query answer of two point clusters, each an instance with boxes (for the Open3D helpers)."""
    rng = np.random.default_rng(8)
    a = rng.normal(0, 0.1, (n // 2, 3)) + np.array([1, 0, 0])
    b = rng.normal(0, 0.1, (n - n // 2, 3)) + np.array([-1, 0.5, 0])
    mean = np.concatenate([a, b]).astype(np.float32)
    rel = np.linspace(0.95, 0.5, n).astype(np.float32)
    inst = np.r_[np.zeros(n // 2, np.int32), np.ones(n - n // 2, np.int32)]
    c, s = np.cos(0.4), np.sin(0.4)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    insts = tuple(
        Instance(
            k,
            p.mean(0),
            Box(p.mean(0), np.ptp(p, 0), np.eye(3)),
            Box(p.mean(0), np.ptp(p, 0) * 0.8, rot),
            0.8,
            len(p),
        )
        for k, p in enumerate((a, b))
    )
    return TextAnswer("thing", np.arange(n, dtype=np.int64), rel, mean=mean, instance=inst, instances=insts)


# ---------------------------------------------------------------- an in-process fake of the service

SCENE = pb.SceneInfo(
    name="demo",
    state=pb.SCENE_STATE_READY,
    encoder_id="enc",
    embedding_dim=8,
    num_gaussians=1000,
    num_embedded=400,
    canonical_phrases=["object", "stuff"],
    version="v1",
    bounds=[-1, -1, 0, 1, 1, 0.5],
)


class FakeFmgs(pb_grpc.FmgsServicer):
    """Just enough of the service to drive the client: fixed answers, chunked like the real one."""

    def __init__(self) -> None:
        self.auth: list[str | None] = []
        self.requests: list = []

    def _check(self, context, scene=None):
        self.auth.append(dict(context.invocation_metadata()).get("authorization"))
        if scene is not None and scene != "demo":
            context.abort(grpc.StatusCode.NOT_FOUND, f"no scene {scene!r}")

    def ListScenes(self, request, context):
        self._check(context)
        return pb.ListScenesResponse(scenes=[SCENE, pb.SceneInfo(name="broken", state=4, reason="bad file")])

    def GetScene(self, request, context):
        self._check(context, request.scene)
        return SCENE

    def TextQuery(self, request, context):
        self._check(context, request.scene)
        self.requests.append(request)
        rng = np.random.default_rng(0)
        lists = []
        for i, t in enumerate(request.texts):
            cols = answer_cols(rng, min(request.top_k, 9))
            names = {pb.GaussianField.Name(f).removeprefix("GAUSSIAN_FIELD_").lower() for f in request.fields}
            cols = {n: v for n, v in cols.items() if n in ("index", "relevancy") or n in names}
            insts = []
            if request.instances.enabled:
                insts = [
                    pb.Instance(
                        id=0,
                        centroid=[0, 0, 0],
                        aabb=pb_box([0, 0, 0], [1, 1, 1]),
                        obb=pb_box([0, 0, 0], [1, 1, 1]),
                        score=0.5,
                        num_members=3,
                    )
                ]
            lists.append(text_chunks(i, t, cols, insts, rows_per_chunk=4))
        yield from interleave(*lists)

    def _render(self, request):
        cam = request.camera
        h, w = cam.height, cam.width
        rel = (np.arange(h * w, dtype=np.float32).reshape(h, w) / (h * w)).astype(np.float32)
        imgs = {"relevancy": rel}
        if pb.RENDER_OUTPUT_RGB in request.outputs:
            imgs["rgb"] = np.repeat(rel[..., None], 3, -1)
        for out, name in ((pb.RENDER_OUTPUT_DEPTH, "depth"), (pb.RENDER_OUTPUT_ALPHA, "alpha")):
            if out in request.outputs:  # every output asked for comes back, as from the real server
                imgs[name] = np.ones((h, w), np.float32)
        return render_chunks(request.sequence, imgs, 3, argmax=(w - 1, h - 1, float(rel.max())))

    def Render(self, request, context):
        self._check(context, request.scene)
        if not request.text:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "text: required for relevancy")
        yield from self._render(request)

    def StreamRender(self, request_iterator, context):
        self._check(context)
        for req in request_iterator:
            self.requests.append(req)
            yield from self._render(req)

    def PointQuery(self, request, context):
        self._check(context, request.scene)
        p = from_tensor(request.points, "points")
        rel = np.tile(p[:, 0].astype(np.float32), (len(request.texts), 1))
        return pb.PointQueryResponse(relevancy=to_tensor(rel), similarity=to_tensor(rel), elapsed_ms=1.0)

    def Segment(self, request, context):
        self._check(context, request.scene)
        c = pb.SegmentChunk(class_names=request.class_names, last=True)
        if request.HasField("camera"):
            c.width, c.height = request.camera.width, request.camera.height
            c.pixel_labels.CopyFrom(to_tensor(np.zeros((c.height, c.width), np.int32)))
        c.gaussian_index.CopyFrom(to_tensor(np.arange(3, dtype=np.int64)))
        c.gaussian_labels.CopyFrom(to_tensor(np.array([0, 1, 0], np.int32)))
        yield c

    def LoadScene(self, request, context):
        self._check(context, request.scene)
        return SCENE


@contextmanager
def serve_fake() -> Iterator[tuple[FakeFmgs, str]]:
    """A started in-process FakeFmgs on a free port with the standard health service: ``""`` SERVING,
    ``fmgs.v1.Fmgs`` NOT_SERVING. Yields (servicer, address)."""
    server = grpc.server(futures.ThreadPoolExecutor(4))
    svc = FakeFmgs()
    pb_grpc.add_FmgsServicer_to_server(svc, server)
    hs = health.HealthServicer()
    hs.set("", health_pb2.HealthCheckResponse.SERVING)
    hs.set("fmgs.v1.Fmgs", health_pb2.HealthCheckResponse.NOT_SERVING)
    health_pb2_grpc.add_HealthServicer_to_server(hs, server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        yield svc, f"127.0.0.1:{port}"
    finally:
        server.stop(None)
