"""Drive the inspector window through its edge cases against the in-process fake service, under a display.

    xvfb-run -a python -m tests.helpers.drive_viewer_edges OUT_DIR

A scene of zero drawn Gaussians, a query whose answers have zero rows, a server sending NaN, and exports
into a folder that cannot be written (OUT_DIR/not-a-folder is a file). Writes OUT_DIR/edges.json with what
the window showed at each step; tests/client/test_viewer.py asserts on it. Open3D's application starts
once per process, hence the separate process.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.tensors import to_tensor
from tests.helpers import client_fakes
from tests.helpers.client_fakes import text_chunks


class EdgeFmgs(client_fakes.FakeFmgs):
    """The fake with a Geometry call: the scene "demo" draws no Gaussians; "nan" answers carry NaN."""

    def Geometry(self, request, context):
        self._check(context, request.scene)
        c = pb.GeometryChunk(start=0, total=0, num_gaussians=1000, qualified=0, bounds=[-1, -1, 0, 1, 1, 1])
        c.last = True
        for n, shape, dt in [("index", (0,), np.int64), ("mean", (0, 3), np.float32),
                             ("color", (0, 3), np.float32), ("opacity", (0,), np.float32),
                             ("scale", (0, 3), np.float32)]:  # fmt: skip
            getattr(c, n).CopyFrom(to_tensor(np.zeros(shape, dt)))
        yield c

    def TextQuery(self, request, context):
        self._check(context, request.scene)
        for i, t in enumerate(request.texts):
            k = 3 if t == "nan" else 0
            rel = np.full(k, np.nan if t == "nan" else 0.7, np.float32)
            cols = {"index": np.arange(k, dtype=np.int64), "relevancy": rel,
                    "mean": np.zeros((k, 3), np.float32), "instance": np.zeros(k, np.int32)}  # fmt: skip
            yield from text_chunks(i, t, cols)


def main() -> int:
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    blocked = out / "not-a-folder"
    blocked.write_text("a file where the exports would go\n")

    import open3d as o3d

    from fmgs_client.client import FmgsClient
    from fmgs_client.viewer import Inspector

    client_fakes.FakeFmgs = EdgeFmgs  # serve_fake builds the servicer by this name
    rec: dict = {}
    with client_fakes.serve_fake() as (_, address):
        app = o3d.visualization.gui.Application.instance
        app.initialize()
        client = FmgsClient(address, timeout=10)
        insp = Inspector(client, address, "demo", size=(800, 600), out_dir=blocked / "exports")

        def pump(until, what: str, limit: float = 60.0) -> None:
            t0 = time.monotonic()
            while not until():
                app.run_one_tick()
                if time.monotonic() - t0 > limit:
                    raise SystemExit(f"timed out waiting for {what}; status: {insp.status.text}")
            for _ in range(5):
                app.run_one_tick()

        def step(name: str, **more) -> None:
            rec[name] = {"status": insp.status.text, "error": insp.last_error, **more}

        pump(lambda: insp.geometry is not None and insp.idle, "the scene")
        pump(lambda: insp.last_picture is not None, "the picture")
        step("scene", drawn=len(insp.drawn["scene"].points), picture=list(insp.picture_image_array().shape))

        insp.on_query(";;")
        step("separators_only")

        insp.on_query("red cube; blue ball")
        pump(lambda: insp.idle and bool(insp.answers), "the empty answers")
        step("empty_answers", rows=[len(v.answer) for v in insp.answers], legend=insp.legend_label.text)

        errors = {}
        for name, fn in [("ply", insp.on_export_ply), ("camera", insp.on_save_camera)]:
            try:
                fn()
            except BaseException as e:  # what a button's callback would let escape into Open3D
                errors[name] = repr(e)
            step(f"export_{name}", raised=errors.get(name))
        insp.on_screenshot()
        pump(lambda: "Screenshot" in insp.last_error or "wrote" in insp.status.text, "the screenshot")
        step("export_screenshot")

        insp.on_query("nan")
        pump(lambda: insp.idle, "the NaN answer")
        step("nan_answer", answers=len(insp.answers), legend=insp.legend_label.text)

        insp.feed.close()
        client.close()
    (out / "edges.json").write_text(json.dumps(rec, indent=1))
    sys.stdout.flush()
    os._exit(0)  # Open3D's and gRPC's teardown can hang at interpreter exit; everything is written


if __name__ == "__main__":
    try:
        main()
    except BaseException as e:  # report, then leave without the teardown that can hang
        print(f"drive_viewer_edges failed: {e!r}", flush=True)
        os._exit(1)
