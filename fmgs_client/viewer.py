"""``fmgs-client view``: an Open3D window to look through a served scene (optional extra ``fmgs[open3d]``).

The scene's Gaussians as points (fetched with the Geometry call), a text box (phrases separated by ";",
Enter runs TextQuery), answers recoloured by relevancy with a legend, instance boxes, each phrase's presence,
a picture panel with the server's render of the current view (RGB, relevancy, composite) kept current
through StreamRender, segmentation by class names, and exports (answer PLY, screenshot PNG, camera JSON).

Network calls run on worker threads and post their results to the GUI thread, so the window never waits
for the server; a failed call shows as one line in the status bar. The callbacks a user's typing and
clicking trigger are plain methods (``on_query``, ``on_instance_selected``, ...), which the tests call.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fmgs_client.client import FmgsClient, FmgsError
from fmgs_client.open3d_tools import export_answer, require_open3d
from fmgs_client.picture_feed import PictureFeed
from fmgs_client.types import CameraSpec, Geometry, RenderResult, SceneInfo, SegmentResult
from fmgs_client.viewer_model import (
    PICTURE_MODES,
    AnswerView,
    ViewerConfig,
    answer_view,
    box_lines,
    camera_from_gl,
    dimmed,
    framing,
    home_view,
    instance_line,
    legend,
    parse_phrases,
    picture,
    picture_size,
    robust_bounds,
    scaled,
    segment_colors,
)
from fmgs_wire.images import label_colors

PANEL_EM = 24
"""Width of the side panel in font heights."""
FOV_DEG = 60.0
OBB_COLOR = (1.0, 0.2, 0.6)


def has_display() -> bool:
    """Whether a window can open: an X or Wayland display is set (Open3D aborts the process otherwise)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class Inspector:
    """The window and what it shows. Create after ``gui.Application.instance.initialize()``."""

    def __init__(
        self,
        client: FmgsClient,
        address: str,
        scene: str | None = None,
        cfg: ViewerConfig | None = None,
        size: tuple[int, int] = (1280, 800),
        out_dir: str | Path = ".",
    ) -> None:
        o3d = require_open3d()
        self.o3d, self.gui, self.rendering = o3d, o3d.visualization.gui, o3d.visualization.rendering
        gui = self.gui
        cfg = ViewerConfig() if cfg is None else cfg
        self.client, self.address, self.cfg = client, address, cfg
        self.out_dir = Path(out_dir)
        self.app = gui.Application.instance
        self.window = self.app.create_window("FMGS inspector", *size)
        w = self.window
        em = w.theme.font_size

        self.view = gui.SceneWidget()
        self.view.scene = self.rendering.Open3DScene(w.renderer)
        self.view.scene.set_background([0.08, 0.08, 0.1, 1.0])
        self.panel = gui.ScrollableVert(0.25 * em, gui.Margins(0.5 * em, 0.5 * em, 0.5 * em, 0.5 * em))
        self.status = gui.Label("")
        w.add_child(self.view)
        w.add_child(self.panel)
        w.add_child(self.status)
        w.set_on_layout(self._layout)
        w.set_on_tick_event(self.on_tick)
        w.set_on_close(self._on_close)

        p = self.panel
        p.add_child(gui.Label("Scene"))
        self.scene_box = gui.Combobox()
        self.scene_box.set_on_selection_changed(self.on_scene_selected)
        refresh = gui.Button("Refresh")
        refresh.set_on_clicked(self.refresh_scenes)
        row = gui.Horiz(0.25 * em)
        row.add_child(self.scene_box)
        row.add_child(refresh)
        p.add_child(row)

        p.add_child(gui.Label('Query (phrases separated by ";", Enter runs)'))
        self.text = gui.TextEdit()
        self.text.placeholder_text = "red cube; blue ball"
        self.text.set_on_value_changed(self.on_query)
        p.add_child(self.text)
        self.top_k = gui.NumberEdit(gui.NumberEdit.INT)
        self.top_k.int_value = cfg.top_k
        self.top_k.set_limits(1, 1_000_000)
        self.threshold = gui.Slider(gui.Slider.DOUBLE)
        self.threshold.set_limits(0.0, 1.0)
        self.threshold.double_value = cfg.threshold
        grid = gui.VGrid(2, 0.25 * em)
        grid.add_child(gui.Label("top-k"))
        grid.add_child(self.top_k)
        grid.add_child(gui.Label("threshold"))
        grid.add_child(self.threshold)
        p.add_child(grid)

        self.legend_image = gui.ImageWidget(o3d.geometry.Image(legend(0.5, 1.0)))
        self.legend_label = gui.Label("relevancy: no answer")
        p.add_child(self.legend_image)
        p.add_child(self.legend_label)
        self.results = gui.ListView()
        self.results.set_max_visible_items(8)
        self.results.set_on_selection_changed(self.on_instance_selected)
        p.add_child(self.results)

        p.add_child(gui.Label("Picture (the server's render of this view)"))
        self.mode_box = gui.Combobox()
        for m in PICTURE_MODES:
            self.mode_box.add_item(m)
        self.mode_box.set_on_selection_changed(self.on_picture_mode)
        p.add_child(self.mode_box)
        self.picture_image = gui.ImageWidget(o3d.geometry.Image(np.zeros((8, 8, 3), np.uint8)))
        p.add_child(self.picture_image)

        p.add_child(gui.Label('Segment (class names separated by ";", Enter runs)'))
        self.classes = gui.TextEdit()
        self.classes.placeholder_text = "floor; red cube; blue ball"
        self.classes.set_on_value_changed(self.on_segment)
        p.add_child(self.classes)

        p.add_child(gui.Label(f"Export to {self.out_dir}"))
        row = gui.Horiz(0.25 * em)
        exports = (("Answer PLY", self.on_export_ply), ("Screenshot", self.on_screenshot),
                   ("Camera JSON", self.on_save_camera))  # fmt: skip
        for name, fn in exports:
            b = gui.Button(name)
            b.set_on_clicked(fn)
            row.add_child(b)
        p.add_child(row)

        self.scene: str | None = None
        self.info: SceneInfo | None = None
        self.geometry: Geometry | None = None
        self.answers: list[AnswerView] = []
        self.segmentation: SegmentResult | None = None
        self.selected = 0
        """Which phrase's answer is drawn."""
        self.drawn: dict[str, Any] = {}
        """The Open3D geometries in the view by name (scene, answer, boxes)."""
        self.mode = PICTURE_MODES[0]
        self.last_picture: tuple[CameraSpec, RenderResult] | None = None
        self.last_picture_text = ""
        """The text the last picture was rendered for ("" for colour only): after a new query the panel
        keeps the previous picture until the new text's first one arrives."""
        self.last_error = ""
        self.latency_ms: float | None = None
        self.feed: PictureFeed | None = None
        self._pending = 0
        self._view_gl: np.ndarray | None = None
        self._closed = False
        self._list_rows: list[tuple[int, int] | None] = []
        self._scene_names: list[str] = []
        self._wanted_scene = scene
        self.refresh_scenes()

    # ------------------------------------------------------------------ plumbing

    def _layout(self, ctx) -> None:
        r = self.window.content_rect
        em = self.window.theme.font_size
        bar = round(1.6 * em)
        side = min(round(PANEL_EM * em), r.width // 2)
        self.view.frame = self.gui.Rect(r.x, r.y, r.width - side, r.height - bar)
        self.panel.frame = self.gui.Rect(r.get_right() - side, r.y, side, r.height - bar)
        self.status.frame = self.gui.Rect(r.x, r.get_bottom() - bar, r.width, bar)

    def _on_close(self) -> bool:
        self._closed = True
        if self.feed is not None:
            self.feed.close()
        return True

    @property
    def idle(self) -> bool:
        """No call of the window's is waiting for the server (the picture feed aside)."""
        return self._pending == 0

    def _post(self, fn: Callable[[], None]) -> None:
        if not self._closed:
            self.app.post_to_main_thread(self.window, fn)

    def _call(self, what: str, work: Callable[[], Any], done: Callable[[Any], None]) -> None:
        """``work()`` on a worker thread; ``done(result)`` on the GUI thread, or its error in the status
        bar."""
        self._pending += 1
        self._set_status(f"{what}...")

        def run() -> None:
            t0 = time.perf_counter()
            try:
                result, err = work(), None
            except FmgsError as e:
                result, err = None, f"{what}: {e.code}: {e.details}"
            except (OSError, ValueError) as e:
                result, err = None, f"{what}: {e}"
            ms = (time.perf_counter() - t0) * 1e3

            def finish() -> None:
                self._pending -= 1
                if err is not None:
                    self.last_error = err
                    self._set_status(err)
                    return
                self.last_error = ""
                self.latency_ms = ms
                try:
                    done(result)
                except (FmgsError, OSError, ValueError) as e:
                    self.last_error = f"{what}: {e}"
                self._set_status(self.last_error or None)

            self._post(finish)

        threading.Thread(target=run, daemon=True).start()

    def _fail(self, line: str) -> None:
        """A failure as the status bar's red line (the window goes on)."""
        self.last_error = line
        self._set_status(line)

    def _set_status(self, line: str | None) -> None:
        state = self.info.state if self.info is not None else "no scene"
        parts = [self.address, f"{self.scene or '-'} ({state})"]
        if self.latency_ms is not None:
            parts.append(f"last call {self.latency_ms:.0f} ms")
        if line:
            parts.append(line)
        self.status.text = "   |   ".join(parts)
        if self.last_error and line == self.last_error:
            self.status.text_color = self.gui.Color(1.0, 0.45, 0.4)
        else:
            self.status.text_color = self.gui.Color(0.85, 0.85, 0.85)

    def _material(self, kind: str, size: float = 3.0):
        m = self.rendering.MaterialRecord()
        if kind == "line":
            m.shader, m.line_width = "unlitLine", 2.0
        else:
            m.shader, m.point_size = "defaultUnlit", size
        return m

    def _put(self, name: str, geom, material) -> None:
        s = self.view.scene
        if s.has_geometry(name):
            s.remove_geometry(name)
        if geom is not None:
            s.add_geometry(name, geom, material)
        self.drawn[name] = geom

    def _draw_scene(self, colors: np.ndarray, size: float) -> None:
        """The scene's points (the Geometry answer) in ``colors``."""
        self._put("scene", self._points(self.geometry.mean, colors), self._material("points", size))

    def _clear_answer(self) -> None:
        self._put("answer", None, None)
        self._put("boxes", None, None)

    def _points(self, pts: np.ndarray, colors: np.ndarray):
        o3d = self.o3d
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(pts, np.float64)))
        pc.colors = o3d.utility.Vector3dVector(np.clip(np.asarray(colors, np.float64), 0, 1))
        return pc

    # ------------------------------------------------------------------ scenes

    def refresh_scenes(self) -> None:
        """List the server's scenes (with their states) in the picker; open the wanted one."""
        self._call("ListScenes", self.client.list_scenes, self._scenes_listed)

    def _scenes_listed(self, scenes: list[SceneInfo]) -> None:
        self.scene_box.clear_items()
        self._scene_names = [s.name for s in scenes]
        for s in scenes:
            self.scene_box.add_item(f"{s.name} ({s.state})")
        want = self._wanted_scene or self.scene or (self._scene_names[0] if scenes else None)
        if want is None:
            self._set_status("the server has no scenes")
            return
        if want not in self._scene_names:
            self.last_error = (
                f"scene {want!r} is not on the server ({', '.join(self._scene_names) or 'none'})"
            )
            self._set_status(self.last_error)
            return
        self.scene_box.selected_index = self._scene_names.index(want)
        if want != self.scene or self.geometry is None:
            self.open_scene(want)

    def on_scene_selected(self, text: str, index: int) -> None:
        if 0 <= index < len(self._scene_names):
            self.open_scene(self._scene_names[index])

    def open_scene(self, name: str) -> None:
        """Fetch the scene's points (the Geometry call) and frame them."""
        self._wanted_scene = None
        cfg = self.cfg

        def work():
            g = self.client.geometry(name, cfg.max_points, cfg.min_opacity)
            return g, self.client.scene(name)

        self._call(f"Geometry {name}", work, lambda r: self._scene_opened(name, *r))

    def _scene_opened(self, name: str, g: Geometry, info: SceneInfo) -> None:
        self.scene, self.info, self.geometry = name, info, g
        self.answers, self.selected, self.last_picture = [], 0, None
        self.view.scene.clear_geometry()
        self.drawn.clear()
        self._draw_scene(g.color, 4.0)
        lo, hi = robust_bounds(g.mean)
        self.view.setup_camera(FOV_DEG, self.o3d.geometry.AxisAlignedBoundingBox(lo, hi), (lo + hi) / 2)
        eye, centre = home_view(lo, hi, FOV_DEG)
        self.view.look_at(centre, eye, np.array([0.0, 0.0, 1.0]))
        if name in self._scene_names:
            self.scene_box.change_item(self._scene_names.index(name), f"{name} ({info.state})")
        self.results.set_items([f"{len(g):,} of {g.num_gaussians:,} Gaussians drawn"])
        self._list_rows = [None]
        self._restart_feed()

    # ------------------------------------------------------------------ text queries

    def on_query(self, line: str) -> None:
        """Enter in the text box: TextQuery with every phrase, instances on."""
        phrases = parse_phrases(line)
        if self.scene is None or not phrases:
            self._set_status("type phrases separated by ';' once a scene is open")
            return
        scene, k, thr = self.scene, int(self.top_k.int_value), float(self.threshold.double_value)

        def work():
            return self.client.query(scene, phrases, top_k=k, threshold=thr, fields=["mean"], instances=True)

        self._call("TextQuery", work, lambda answers: self._answered(scene, answers))

    def _answered(self, scene: str, answers) -> None:
        if scene != self.scene:
            return
        self.answers = [answer_view(a) for a in answers]
        self.selected = 0
        rows, lines = [], []
        for pi, v in enumerate(self.answers):
            lines.append(v.presence_line)
            rows.append((pi, -1))
            for ii, inst in enumerate(v.answer.instances):
                lines.append(instance_line(inst))
                rows.append((pi, ii))
        self.results.set_items(lines or ["no answer"])
        self._list_rows = rows or [None]
        self._draw_answer()
        self._restart_feed()

    def _draw_answer(self) -> None:
        g = self.geometry
        if g is None:
            return
        if not self.answers:
            self._draw_scene(g.color, 3.0)
            self._clear_answer()
            self.legend_label.text = "relevancy: no answer"
            return
        v = self.answers[self.selected]
        self._draw_scene(dimmed(g.color, self.cfg.dim), 2.0)
        self._put("answer", self._points(v.points, v.colors), self._material("points", 5.0))
        pts, edges = box_lines([i.obb for i in v.answer.instances])
        if len(pts):
            ls = self.o3d.geometry.LineSet(
                self.o3d.utility.Vector3dVector(pts), self.o3d.utility.Vector2iVector(edges)
            )
            ls.colors = self.o3d.utility.Vector3dVector(np.tile(OBB_COLOR, (len(edges), 1)))
            self._put("boxes", ls, self._material("line"))
        else:
            self._put("boxes", None, None)
        self.legend_image.update_image(self.o3d.geometry.Image(legend(v.vmin, v.vmax)))
        self.legend_label.text = f"{v.answer.text!r}: relevancy {v.vmin:.3f} (left) to {v.vmax:.3f} (right)"

    def on_instance_selected(self, value: str, double_click: bool) -> None:
        """A result line chosen: show that phrase; an instance line also moves the camera to it."""
        i = self.results.selected_index
        if not 0 <= i < len(self._list_rows) or self._list_rows[i] is None:
            return
        pi, ii = self._list_rows[i]
        if pi != self.selected:
            self.selected = pi
            self._draw_answer()
            self._restart_feed()
        if ii >= 0:
            box = self.answers[pi].answer.instances[ii].obb
            view = self.view.scene.camera.get_view_matrix()
            fwd = -np.asarray(view, np.float64)[2, :3]  # OpenGL cameras look down -z
            eye, centre = framing(box, fwd, FOV_DEG)
            self.view.look_at(centre, eye, np.array([0.0, 0.0, 1.0]))

    # ------------------------------------------------------------------ segmentation

    def on_segment(self, line: str) -> None:
        names = parse_phrases(line)
        if self.scene is None or not names:
            self._set_status("type class names separated by ';' once a scene is open")
            return
        scene = self.scene
        self._call("Segment", lambda: self.client.segment(scene, names, per_gaussian=True), self._segmented)

    def _segmented(self, seg) -> None:
        g = self.geometry
        if g is None:
            return
        self.answers = []
        self._draw_scene(segment_colors(g, seg, self.cfg.dim), 3.0)
        self._clear_answer()
        lines = []
        for k, (name, (n, _)) in enumerate(zip(seg.class_names, seg.counts(), strict=True)):
            c = label_colors(np.array([k]))[0]
            lines.append(f"#{bytes(c).hex()}  {name}: {n:,} Gaussians")
        self.results.set_items(lines)
        self._list_rows = [None] * len(lines)
        self.legend_label.text = "segmentation: class colours listed below"
        self.segmentation = seg

    # ------------------------------------------------------------------ the picture panel

    def _view_camera(self) -> CameraSpec:
        """The 3D view's camera as a pinhole camera at the view's size."""
        f = self.view.frame
        cam = self.view.scene.camera
        return camera_from_gl(
            cam.get_view_matrix(), cam.get_projection_matrix(), max(f.width, 8), max(f.height, 8)
        )

    def current_camera(self) -> CameraSpec:
        """The 3D view's camera at the picture panel's size."""
        full = self._view_camera()
        return scaled(full, *picture_size(full.width, full.height, self.cfg.picture_side))

    def on_tick(self) -> bool:
        """Every frame: hand a moved camera to the picture feed (never waits)."""
        if self.feed is None or self.scene is None:
            return False
        vm = np.asarray(self.view.scene.camera.get_view_matrix(), np.float64)
        if self._view_gl is None or not np.array_equal(vm, self._view_gl):
            self._view_gl = vm
            self.feed.put(self.current_camera())
        return False

    def _text(self) -> str:
        return self.answers[self.selected].answer.text if self.answers else ""

    def _restart_feed(self) -> None:
        if self.feed is not None:
            self.feed.close()
        self.feed = None
        if self.scene is None:
            return
        self.feed = PictureFeed(
            self.client, self.scene, self._text(), self._picture_arrived, self._picture_failed
        )
        self._view_gl = None  # the next tick sends the current view

    def _picture_arrived(self, cam: CameraSpec, r: RenderResult) -> None:
        feed = self.feed

        def show() -> None:
            if self.feed is not feed or feed is None:
                return
            self.last_picture, self.last_picture_text = (cam, r), feed.text
            self.latency_ms = r.elapsed_ms
            self._show_picture()

        self._post(show)

    def _picture_failed(self, e: FmgsError) -> None:
        def show() -> None:
            self.last_error = f"picture: {e.code}: {e.details} (reconnecting)"
            self._set_status(self.last_error)

        self._post(show)

    def picture_image_array(self) -> np.ndarray | None:
        """The panel's image as shown: [H,W,3] uint8."""
        if self.last_picture is None:
            return None
        _, r = self.last_picture
        rel = r.relevancy if r.relevancy is not None else np.zeros((r.height, r.width), np.float32)
        mode = self.mode if r.relevancy is not None else "rgb"
        return picture(mode, r.rgb, rel, r.alpha)

    def _show_picture(self) -> None:
        img = self.picture_image_array()
        if img is not None:
            self.picture_image.update_image(self.o3d.geometry.Image(np.ascontiguousarray(img)))
            self.window.post_redraw()
            if self.last_error.startswith("picture:"):
                self.last_error = ""
            self._set_status(None)

    def on_picture_mode(self, text: str, index: int) -> None:
        self.mode = PICTURE_MODES[index]
        self._show_picture()

    # ------------------------------------------------------------------ exports

    def _stem(self) -> str:
        return f"{self.scene or 'scene'}-{time.strftime('%Y%m%d-%H%M%S')}"

    def on_export_ply(self) -> None:
        if not self.answers:
            self._set_status("nothing to export: run a query first")
            return
        v = self.answers[self.selected]
        try:
            paths = export_answer(v.answer, self.out_dir / f"{self._stem()}.ply")
        except (OSError, ValueError) as e:
            self._fail(f"Answer PLY: {e}")
            return
        self._set_status("wrote " + ", ".join(str(p) for p in paths))

    def on_screenshot(self, path: str | Path | None = None) -> None:
        """The 3D view as a PNG (Open3D renders it off screen)."""
        out = Path(path) if path else self.out_dir / f"{self._stem()}.png"

        def done(img) -> None:
            def saved() -> None:
                if self.o3d.io.write_image(str(out), img):
                    self._set_status(f"wrote {out}")
                else:
                    self._fail(f"Screenshot: could not write {out}")

            self._post(saved)

        self.view.scene.scene.render_to_image(done)
        self.window.post_redraw()  # the image comes with the next frame drawn

    def on_save_camera(self, path: str | Path | None = None) -> Path | None:
        """The current view as camera JSON (``fmgs-client render --camera FILE``), at the 3D view's size;
        None when it could not be written (the status bar says why)."""
        out = Path(path) if path else self.out_dir / f"{self._stem()}-camera.json"
        try:
            out.write_text(json.dumps(self._view_camera().to_dict(), indent=1))
        except OSError as e:
            self._fail(f"Camera JSON: {e}")
            return None
        self._set_status(f"wrote {out}")
        return out


def run(address: str, scene: str | None, client: FmgsClient, cfg: ViewerConfig, out_dir: Path) -> int:
    """Open the window and run until it is closed."""
    if not has_display():
        raise OSError("no display: set DISPLAY (or run under xvfb-run) to open the inspector window")
    o3d = require_open3d()
    app = o3d.visualization.gui.Application.instance
    app.initialize()
    Inspector(client, address, scene, cfg, out_dir=out_dir)
    app.run()
    return 0
