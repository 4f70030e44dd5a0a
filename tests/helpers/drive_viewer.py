"""Drive the inspector window as a user would, under a display (xvfb-run), and record what it shows.

    xvfb-run -a python -m tests.helpers.drive_viewer ADDRESS SCENE OUT_DIR [--shots]
    xvfb-run -a python -m tests.helpers.drive_viewer serve:MODELS SCENE OUT_DIR   # its own server

With ``serve:MODELS`` it serves MODELS itself, and at the end stops that server and starts it again on the
same port, recording what the window says meanwhile and that it recovers.

Opens ``fmgs_client.viewer.Inspector`` on the scene, pumps Open3D's event loop, then calls the same
callbacks typing and clicking trigger: Enter in the query box ("red cube"), a picture mode, a result
line (an instance), class names in the segment box. Writes OUT_DIR/viewer.json with what was drawn and
the server's own answers to the same requests, a capture of the whole X display per step (PIL's
ImageGrab), and, with --shots, the screenshots the docs show. The test (tests/client/test_viewer.py)
asserts on them; Open3D's application can be initialised once per process, hence the separate process.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("address")
    ap.add_argument("scene")
    ap.add_argument("out", type=Path)
    ap.add_argument("--shots", action="store_true", help="also save docs screenshots of each mode")
    ap.add_argument("--query", default="red cube")
    ap.add_argument("--classes", default="floor; red cube; blue ball; green cylinder; yellow cone")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)

    import open3d as o3d
    from PIL import ImageGrab

    from fmgs_client.client import FmgsClient
    from fmgs_client.viewer import Inspector
    from fmgs_client.viewer_model import PICTURE_MODES, ViewerConfig, box_lines

    t_start = time.monotonic()
    srv, make_server = None, None
    if a.address.startswith("serve:"):
        from fmgs_server.config import ServerConfig
        from fmgs_server.server import start_server

        models = Path(a.address.split(":", 1)[1])

        def make_server(port: int = 0):
            return start_server(ServerConfig(models=models, port=port, reload_check_s=0.0))

        srv = make_server()
        a.address = srv.address
    app = o3d.visualization.gui.Application.instance
    app.initialize()
    client = FmgsClient(a.address, timeout=60)
    cfg = ViewerConfig()
    insp = Inspector(client, a.address, a.scene, cfg, size=(1280, 800), out_dir=a.out)
    rec: dict = {"steps": []}

    def pump(until, what: str, limit: float = 120.0) -> None:
        t0 = time.monotonic()
        while not until():
            app.run_one_tick()
            if time.monotonic() - t0 > limit:
                raise SystemExit(f"timed out waiting for {what}; status: {insp.status.text}")
        for _ in range(5):  # let the window draw what just changed
            app.run_one_tick()

    def grab(name: str) -> None:
        for _ in range(10):
            app.run_one_tick()
            time.sleep(0.02)
        ImageGrab.grab(xdisplay=os.environ["DISPLAY"]).save(a.out / f"{name}.png")
        rec["steps"].append(name)

    def picture_ready(text: str):
        def ok() -> bool:
            lp = insp.last_picture
            return (
                insp.feed is not None
                and insp.feed.text == text
                and lp is not None
                and insp.last_picture_text == text
                and np.array_equal(lp[0].viewmat, insp.current_camera().viewmat)
            )

        return ok

    # 1. The scene opens: its points.
    pump(lambda: insp.geometry is not None and insp.idle, "the scene's geometry")
    pump(picture_ready(""), "the colour picture")
    g = client.geometry(a.scene, cfg.max_points, cfg.min_opacity)
    pts = np.asarray(insp.drawn["scene"].points)
    rec["scene"] = {
        "drawn": len(pts),
        "drawn_bounds": pts.min(0).tolist() + pts.max(0).tolist() if len(pts) else [],
        "geometry": len(g),
        "geometry_bounds": g.mean.min(0).tolist() + g.mean.max(0).tolist() if len(g) else [],
        "drawn_equals_geometry": bool(np.allclose(pts, g.mean, atol=1e-6)),
        "num_gaussians": g.num_gaussians,
        "status": insp.status.text,
    }
    grab("1-scene")

    # 2. Typing a phrase and Enter.
    insp.text.text_value = a.query
    insp.on_query(a.query)
    pump(lambda: insp.idle and bool(insp.answers), "the text query")
    [direct] = client.query(
        a.scene, [a.query], top_k=cfg.top_k, threshold=cfg.threshold, fields=["mean"], instances=True
    )
    v = insp.answers[0]
    ans = insp.drawn["answer"]
    colors, apts = np.asarray(ans.colors), np.asarray(ans.points)
    from fmgs_wire.images import colorize

    top = colorize(np.array([1.0]))[0] / 255.0
    boxes = insp.drawn.get("boxes")
    want_pts, _ = box_lines([i.obb for i in direct.instances])
    rec["query"] = {
        "text": a.query,
        "index_equal": bool(np.array_equal(v.answer.index, direct.index)),
        "relevancy_equal": bool(np.array_equal(v.answer.relevancy, direct.relevancy)),
        "points_equal_means": bool(np.allclose(apts, direct.mean, atol=1e-6)),
        "top_colour": colors[0].tolist(),
        "map_high_end": top.tolist(),
        "top_is_high_end": bool(np.allclose(colors[0], top, atol=1 / 255)),
        "dimmed_scene": bool(np.all(np.asarray(insp.drawn["scene"].colors) <= 0.5 + 0.3 * 0.5 + 1e-6)),
        "instances": len(direct.instances),
        "box_points": 0 if boxes is None else len(boxes.points),
        "boxes_equal_instances": boxes is not None
        and bool(np.allclose(np.asarray(boxes.points), want_pts, atol=1e-9)),
        "presence_line": v.presence_line,
        "list": insp._list_rows and [str(r) for r in insp._list_rows],
        "legend": insp.legend_label.text,
    }
    pump(picture_ready(a.query), "the relevancy picture")
    cam, shown = insp.last_picture
    r = client.render(a.scene, cam, a.query, outputs=("relevancy", "rgb", "alpha"))
    rec["picture"] = {
        "camera": cam.to_dict(),
        "relevancy_equal": bool(np.array_equal(shown.relevancy, r.relevancy)),
        "shown_has_relevancy": shown.relevancy is not None,  # not a colour-only picture of the old feed
        "rgb_equal": bool(np.array_equal(shown.rgb, r.rgb)),
        "alpha_equal": bool(np.array_equal(shown.alpha, r.alpha)),
        "size": [r.width, r.height],
    }
    grab("2-query-composite")
    if a.shots:
        for i, mode in enumerate(PICTURE_MODES):
            insp.mode_box.selected_index = i
            insp.on_picture_mode(mode, i)
            img = insp.picture_image_array()
            rec.setdefault("modes", {})[mode] = hashlib.sha256(img.tobytes()).hexdigest()
            grab(f"2-query-{mode}")
        insp.mode_box.selected_index = 0
        insp.on_picture_mode(PICTURE_MODES[0], 0)

    # 3. Choosing an instance moves the camera to it.
    before = np.asarray(insp.view.scene.camera.get_view_matrix()).copy()
    rows = [i for i, row in enumerate(insp._list_rows) if row is not None and row[1] >= 0]
    rec["instance"] = {"rows": len(rows)}
    if rows:
        insp.results.selected_index = rows[0]
        insp.on_instance_selected("", False)
        pump(lambda: True, "the camera move")
        after = np.asarray(insp.view.scene.camera.get_view_matrix())
        eye = -after[:3, :3].T @ after[:3, 3]
        c = direct.instances[0].obb.center
        rec["instance"].update(
            moved=bool(not np.allclose(before, after)),
            eye_to_instance=float(np.linalg.norm(eye - c)),
            looks_at_instance=bool(np.dot(-after[2, :3], (c - eye) / np.linalg.norm(c - eye)) > 0.999),
        )
        pump(picture_ready(a.query), "the picture of the instance")
        grab("3-instance")

    # 4. Exports.
    cam_path = insp.on_save_camera(a.out / "camera.json")
    insp.on_export_ply()
    insp.on_screenshot(a.out / "view.png")
    pump(lambda: (a.out / "view.png").is_file(), "the screenshot")
    rec["exports"] = {"camera": str(cam_path), "ply": sorted(p.name for p in a.out.glob("*.ply"))}

    # 5. Segmentation.
    insp.classes.text_value = a.classes
    insp.on_segment(a.classes)
    pump(lambda: insp.idle and insp.segmentation is not None, "the segmentation")
    seg = insp.segmentation
    rec["segment"] = {"classes": list(seg.class_names), "labelled": len(seg.gaussian_labels)}
    grab("4-segment")

    # 6. An error is a line in the status bar, and the window goes on.
    insp.on_query("")
    insp.open_scene("no-such-scene")
    pump(lambda: insp.idle, "the failed call")
    rec["error"] = {"status": insp.status.text, "last_error": insp.last_error}
    insp.open_scene(a.scene)
    pump(lambda: insp.idle and insp.scene == a.scene, "the scene again")
    rec["error"]["recovered"] = insp.last_error == ""

    # 7. The server goes away and comes back: a readable line meanwhile, then the window works again.
    if srv is not None:
        port = int(a.address.rsplit(":", 1)[1])
        srv.stop(0)
        insp.refresh_scenes()
        pump(lambda: insp.idle, "the call to a stopped server")
        rec["restart"] = {"status_down": insp.status.text, "error_down": insp.last_error}
        srv = make_server(port)
        insp.refresh_scenes()
        pump(lambda: insp.idle, "the server again")
        centre = np.asarray(insp.view.scene.bounding_box.get_center())
        insp.view.look_at(centre, centre + np.array([3.0, -3.0, 3.0]), np.array([0.0, 0.0, 1.0]))  # moved
        pump(picture_ready(insp._text()), "a picture after the restart")
        rec["restart"].update(error_up=insp.last_error, picture_after=True)
        srv.stop(0)

    rec["seconds"] = time.monotonic() - t_start
    (a.out / "viewer.json").write_text(json.dumps(rec, indent=1))
    if insp.feed is not None:
        insp.feed.close()
    client.close()
    sys.stdout.flush()
    os._exit(0)  # Open3D's and gRPC's teardown can hang at interpreter exit; everything is written


if __name__ == "__main__":
    try:
        main()
    except BaseException as e:  # report, then leave without the teardown that can hang
        print(f"drive_viewer failed: {e!r}", flush=True)
        os._exit(1)
