"""The ``fmgs.v1.Fmgs`` service: requests to engine calls, results to messages (transport only).

Validation of request fields lives in ``convert``, the chunked answers in ``responses``, status codes and
log lines in ``calls``, compute and stream slots in ``slots``; the work itself in ``fmgs.query``.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import torch

from fmgs.errors import FmgsError
from fmgs.query.geometry import select_geometry
from fmgs.query.points import query_points
from fmgs.query.pose import render_pose
from fmgs.query.presence import negative_names
from fmgs.query.presence import probes as presence_probes
from fmgs.query.segment import segment
from fmgs.scene.manifest import Manifest
from fmgs_server import budget, convert, responses
from fmgs_server.calls import rpc, rpc_stream, stop_if_gone
from fmgs_server.config import ServerConfig
from fmgs_server.encoders import EncoderCache, TextModel, scene_text_model
from fmgs_server.errors import FailedPrecondition, InvalidArgument
from fmgs_server.repository import SceneRepository, SceneSlot
from fmgs_server.sharded import ShardedSceneService, not_supported
from fmgs_server.slots import Slots
from fmgs_server.streams import LatestRequest
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from fmgs_wire.tensors import to_tensor


class FmgsService(pb_grpc.FmgsServicer):
    """The service over a scene repository and a text-encoder cache."""

    def __init__(self, cfg: ServerConfig, repo: SceneRepository, encoders: EncoderCache) -> None:
        self.cfg = cfg
        self.repo = repo
        self.encoders = encoders
        self.slots = Slots(cfg.compute_slots, cfg.max_streams, cfg.queue_timeout_s)
        self.budget = budget.WorkBudget(cfg.work_memory_bytes, cfg.queue_timeout_s)
        self.sharded = ShardedSceneService(cfg, encoders, self.slots)
        """Sharded scenes (folders with a shards.json): text queries and relevancy renders."""

    def _refuse_sharded(self, method: str, scene: str) -> None:
        if self.sharded.is_sharded(scene):
            raise not_supported(method, scene)

    def text_model(self, engine) -> TextModel:
        """The text encoder of ``engine``'s scene: its id, at the revision its manifest records
        (fmgs_server.encoders.scene_text_model; any with ServerConfig.allow_newer_model)."""
        return scene_text_model(
            engine.encoder_id, engine.manifest.extra, self.cfg.allow_newer_model, engine.name
        )

    def _canonical(self, engine, phrases) -> torch.Tensor | None:
        phrases = convert.texts(phrases, self.cfg, "canonical_phrases", allow_empty=True)
        return self.encoders.embed(self.text_model(engine), phrases) if phrases else None

    def _info(self, slot: SceneSlot) -> pb.SceneInfo:
        manifest = None
        if slot.engine is None:  # not loaded: describe it from its manifest
            try:
                manifest = Manifest.read(self.repo.root / slot.name)
            except FmgsError:
                pass  # a broken manifest shows as FAILED, with the reason, once loading is tried
        return responses.scene_info(slot, manifest)

    # ------------------------------------------------------------------ scenes

    @rpc
    def ListScenes(self, request, context):
        scenes = [self._info(s) for s in self.repo.scan()]
        scenes += [self.sharded.info(n) for n in self.sharded.names()]
        return pb.ListScenesResponse(scenes=sorted(scenes, key=lambda i: i.name))

    @rpc
    def GetScene(self, request, context):
        if self.sharded.is_sharded(request.scene):
            return self.sharded.info(request.scene)
        return self._info(self.repo.slot(request.scene))

    @rpc
    def LoadScene(self, request, context):
        self._refuse_sharded("LoadScene", request.scene)
        with self.slots.compute(context):
            return self._info(self.repo.load(request.scene))

    @rpc
    def UnloadScene(self, request, context):
        self._refuse_sharded("UnloadScene", request.scene)
        return self._info(self.repo.unload(request.scene))

    @rpc
    def ReloadScene(self, request, context):
        self._refuse_sharded("ReloadScene", request.scene)
        with self.slots.compute(context):
            return self._info(self.repo.reload(request.scene))

    # ------------------------------------------------------------------ text query

    @rpc_stream
    def TextQuery(self, request, context):
        cfg = self.cfg
        values = convert.texts(request.texts, cfg)
        k = convert.top_k(request.top_k, cfg)
        thr = convert.threshold(request.threshold)
        fields = convert.fields(request.fields)
        inst_cfg = (
            convert.instance_config(request.instances, cfg.max_instance_pairs)
            if request.instances.enabled
            else None
        )
        if self.sharded.is_sharded(request.scene):
            yield from self._sharded_text(request, context, k, len(values), len(fields))
            return
        engine = self.repo.get(request.scene)
        need = budget.text_bytes(
            min(k, engine.num_embedded), len(values), 3 * len(fields), engine.num_embedded, engine.dim
        )
        with self.budget.reserve(need, context, "this text query"):
            yield from self._text_query(request, context, engine, values, k, thr, fields, inst_cfg)

    def _sharded_text(self, request, context, k: int, n: int, columns: int):
        from fmgs.scene.shards import ShardManifest

        sm = ShardManifest.read(self.cfg.models / request.scene)
        need = budget.text_bytes(min(k, sm.num_selected), n, 3 * columns, 0, sm.dim)
        with self.budget.reserve(need * max(2, len(sm.shards)), context, "this text query"):
            between = lambda: stop_if_gone(context, "the sharded text query")  # noqa: E731
            yield from self.sharded.text_query(request, context, between)

    def _text_query(self, request, context, engine, values, k, thr, fields, inst_cfg):
        cfg = self.cfg
        with self.slots.compute(context):
            if request.HasField("embeddings"):
                if request.encoder_id != engine.encoder_id:
                    raise FailedPrecondition(
                        f"encoder_id: {request.encoder_id!r} differs from the scene's {engine.encoder_id!r}"
                    )
                q = convert.tensor(request.embeddings, "embeddings", (len(values), engine.dim), cfg.max_texts)
            else:
                q = self.encoders.embed(self.text_model(engine), values)
            canon = self._canonical(engine, request.canonical_phrases)
            names = tuple(negative_names(engine.manifest.label_names))
            negs = self.encoders.negatives(self.text_model(engine), names)
            # Colour contrasts need the texts' words: a query given as an embedding goes without.
            probes = None
            if negs is not None and not request.HasField("embeddings"):
                probes = presence_probes(
                    values, q, lambda ts: self.encoders.embed(self.text_model(engine), ts)
                )
            n = len(values)
            t0 = time.perf_counter()
            between = lambda i: stop_if_gone(context, f"text {i} of {n}")  # noqa: E731
            many = engine.text_query_many(  # one pass for all texts
                q, k, thr, canon, inst_cfg, between, negs, cfg.presence(), probes
            )
            ms = (time.perf_counter() - t0) * 1e3 / max(1, len(values))
            answers = [(i, text, a, ms) for i, (text, a) in enumerate(zip(values, many, strict=True))]
        for i, text, a, ms in answers:
            rivals = names if probes is None else names + probes[i].names
            yield from responses.text_chunks(engine, i, text, a, fields, ms, cfg.chunk_bytes, rivals)

    # ------------------------------------------------------------------ render

    def _render(self, request, context, patient: bool = False) -> Iterator[pb.RenderChunk]:
        cfg = self.cfg
        cam = convert.camera(request.camera, cfg, request.HasField("camera"))
        outputs = convert.outputs(request.outputs)
        encoding = convert.encoding(request.encoding)
        if self.sharded.is_sharded(request.scene):
            # Each layer is the image's channels and opacity: (1 + C + 1) floats per pixel, all held
            # until they are composited.
            from fmgs.scene.shards import ShardManifest

            n = len(ShardManifest.read(self.cfg.models / request.scene).shards)
            need = (
                budget.render_bytes(cam.width, cam.height, outputs, False) + n * cam.width * cam.height * 24
            )
            with self.budget.reserve(need, context, "this render", patient):
                stop = lambda: stop_if_gone(context, "the render")  # noqa: E731
                yield from self.sharded.render(request, context, stop)
            return
        engine = self.repo.get(request.scene)
        png = encoding == pb.IMAGE_ENCODING_PNG
        need = budget.render_bytes(cam.width, cam.height, outputs, png, engine.num_gaussians)
        with self.budget.reserve(need, context, "this render", patient):
            yield from self._render_work(request, context, engine, cam, outputs, encoding, patient)

    def _render_work(self, request, context, engine, cam, outputs, encoding, patient):
        cfg = self.cfg
        with self.slots.compute(context, patient):
            t0 = time.perf_counter()
            q = None
            if "relevancy" in outputs:
                values = convert.texts([request.text] if request.text else [], cfg, "text")
                q = self.encoders.embed(self.text_model(engine), values)[0]
            canon = self._canonical(engine, request.canonical_phrases)
            stop = lambda: stop_if_gone(context, "the render")  # noqa: E731
            out = render_pose(engine, cam, q, outputs, canon, stop)
            ms = (time.perf_counter() - t0) * 1e3
        yield from responses.render_chunks(request.sequence, cam, out, encoding, ms, cfg.chunk_bytes)

    @rpc_stream
    def Render(self, request, context):
        yield from self._render(request, context)

    @rpc_stream
    def StreamRender(self, request_iterator, context):
        """Requests arrive as bytes (server.RAW_REQUESTS) and are decoded by the reader thread."""
        with self.slots.stream():
            latest = LatestRequest(pb.RenderRequest.FromString(b) for b in request_iterator)
            while context.is_active():
                req = latest.next(context.is_active)
                if req is None:
                    return
                yield from self._render(req, context, patient=True)

    # ------------------------------------------------------------------ points and segmentation

    @rpc
    def PointQuery(self, request, context):
        self._refuse_sharded("PointQuery", request.scene)
        values = convert.texts(request.texts, self.cfg)
        if not request.HasField("points"):
            raise InvalidArgument("points: missing")
        pts = convert.tensor(request.points, "points", (None, 3), self.cfg.max_points)
        answer_bytes = len(values) * len(pts) * 8  # relevancy and similarity, float32
        if answer_bytes > self.cfg.max_send_bytes - 4096:
            raise InvalidArgument(
                f"points: {len(values)} texts x {len(pts)} points need a {answer_bytes / 2**20:.1f} MiB "
                f"answer, over max_send_bytes ({self.cfg.max_send_bytes / 2**20:.0f} MiB); "
                "send fewer points or texts"
            )
        engine = self.repo.get(request.scene)
        if engine.field is None:
            raise FailedPrecondition(f"scene {engine.name!r} has no feature field; point queries need one")
        need = budget.point_bytes(len(pts), len(values), self.cfg.point_chunk)
        # The answer's copies (arrays, wire bytes, the message grpc serialises) are part of the estimate.
        with self.budget.reserve_until_sent(need, context, "this point query"):
            with self.slots.compute(context):
                t0 = time.perf_counter()
                q = self.encoders.embed(self.text_model(engine), values)
                canon = self._canonical(engine, request.canonical_phrases)
                if canon is None:
                    canon = self.encoders.embed(self.text_model(engine), list(engine.canonical_phrases))
                stop = lambda: stop_if_gone(context, "the point query")  # noqa: E731
                a = query_points(engine, pts, q, canon, self.cfg.point_chunk, stop)
            return pb.PointQueryResponse(
                relevancy=to_tensor(a.relevancy.numpy().astype(np.float32)),
                similarity=to_tensor(a.similarity.numpy().astype(np.float32)),
                elapsed_ms=(time.perf_counter() - t0) * 1e3,
            )

    @rpc_stream
    def Segment(self, request, context):
        self._refuse_sharded("Segment", request.scene)
        names = convert.texts(request.class_names, self.cfg, "class_names")
        cam = convert.camera(request.camera, self.cfg) if request.HasField("camera") else None
        if cam is None and not request.per_gaussian:
            raise InvalidArgument(
                "camera/per_gaussian: ask for pixel labels (a camera) or per_gaussian labels"
            )
        engine = self.repo.get(request.scene)
        w, h = (cam.width, cam.height) if cam is not None else (0, 0)
        need = budget.segment_bytes(w, h, len(names), engine.num_embedded if request.per_gaussian else 0)
        with self.budget.reserve(need, context, "this segmentation"):
            yield from self._segment(request, context, engine, names, cam)

    def _segment(self, request, context, engine, names, cam):
        with self.slots.compute(context):
            t0 = time.perf_counter()
            v = self.encoders.embed(self.text_model(engine), names)
            s = segment(engine, v, cam, request.per_gaussian)
            ms = (time.perf_counter() - t0) * 1e3
        yield from responses.segment_chunks(names, cam, s, ms, self.cfg.chunk_bytes)

    # ------------------------------------------------------------------ geometry

    @rpc_stream
    def Geometry(self, request, context):
        self._refuse_sharded("Geometry", request.scene)
        k = convert.geometry_cap(request.max_gaussians, self.cfg)
        floor = convert.min_opacity(request.min_opacity)
        engine = self.repo.get(request.scene)
        need = budget.geometry_bytes(engine.num_gaussians, min(k, engine.num_gaussians))
        with self.budget.reserve(need, context, "this geometry"):
            with self.slots.compute(context):
                t0 = time.perf_counter()
                g = engine.gaussians
                sel = select_geometry(g.opacity_logits, k, floor)
                index = torch.from_numpy(sel.index).to(g.means.device)
                cols = engine.gaussian_columns(index, ("mean", "color", "opacity", "scale"))
                ms = (time.perf_counter() - t0) * 1e3
            yield from responses.geometry_chunks(
                engine, sel.index, sel.qualified, cols, ms, self.cfg.chunk_bytes
            )
