"""The inspector's pieces that need no window: colours, composite, cameras, segmentation, the pose feed."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from fmgs_client.client import FmgsError
from fmgs_client.picture_feed import PictureFeed
from fmgs_client.types import Box, CameraSpec, Geometry, Presence, RenderResult, SegmentResult, TextAnswer
from fmgs_client.viewer_model import (
    GL_TO_CV,
    ViewerConfig,
    answer_view,
    box_lines,
    camera_from_gl,
    composite,
    framing,
    legend,
    parse_phrases,
    picture,
    picture_size,
    robust_bounds,
    scaled,
    segment_colors,
)
from fmgs_wire.images import colorize, label_colors


def _answer(rel, presence=None):
    rel = np.asarray(rel, np.float32)
    mean = np.arange(3 * len(rel), dtype=np.float32).reshape(-1, 3)
    return TextAnswer(text="red cube", index=np.arange(len(rel)), relevancy=rel, mean=mean, presence=presence)


def test_parse_phrases():
    assert parse_phrases(" red cube ; blue ball;; ") == ["red cube", "blue ball"]
    assert parse_phrases(";;") == []


def test_answer_view_puts_the_most_relevant_at_the_maps_high_end():
    v = answer_view(_answer([0.9, 0.7, 0.55, 0.3]))
    assert v.vmin == 0.5 and v.vmax == pytest.approx(0.9)
    assert np.allclose(v.colors[0], colorize(np.array([1.0]))[0] / 255)
    assert np.allclose(v.colors[3], colorize(np.array([0.0]))[0] / 255)  # below 0.5: the low end
    flat = answer_view(_answer([0.8, 0.8]))
    assert np.allclose(flat.colors, colorize(np.array([1.0]))[0] / 255)
    assert np.isfinite(answer_view(_answer([])).colors).all()
    with pytest.raises(ValueError, match="mean"):
        answer_view(TextAnswer(text="x", index=np.arange(1), relevancy=np.ones(1, np.float32)))


def test_presence_lines():
    found = answer_view(_answer([0.9], Presence(0.9, True, 0.3, "")))
    assert found.presence_line == "red cube: found (0.90)"
    absent = answer_view(_answer([0.9], Presence(0.2, False, -0.1, "blue ball")))
    assert absent.presence_line == "red cube: NOT FOUND: the scene has 'blue ball' there (0.20)"


def test_legend_and_boxes():
    bar = legend(0.5, 1.0, 64, 4)
    assert bar.shape == (4, 64, 3) and bar.dtype == np.uint8
    assert np.array_equal(bar[0, -1], colorize(np.array([1.0]))[0])
    b = Box(np.zeros(3), np.array([2.0, 2, 2]), np.eye(3))
    pts, edges = box_lines([b, b])
    assert pts.shape == (16, 3) and edges.shape == (24, 2) and edges.max() == 15
    lengths = np.linalg.norm(pts[edges[:, 0]] - pts[edges[:, 1]], axis=1)
    assert np.allclose(lengths, 2.0)  # every edge of the cube is a side, not a diagonal


def test_composite_and_modes():
    rgb = np.full((2, 3, 3), 0.25, np.float32)
    rel = np.array([[0.2, 0.5, 0.9], [0.49, 0.7, 0.9]], np.float32)
    alpha = np.array([[1, 1, 1], [1, 1, 0.0]], np.float32)
    c = composite(rgb, rel, alpha)
    assert np.array_equal(c[0, 0], [64, 64, 64]) and np.array_equal(c[1, 0], [64, 64, 64])
    assert np.array_equal(c[0, 2], colorize(np.array([1.0]))[0])  # the highest: the map's top
    assert np.array_equal(c[1, 2], [64, 64, 64])  # nothing drawn there
    assert np.array_equal(c[0, 1], colorize(np.array([0.0]))[0])
    assert np.array_equal(picture("rgb", rgb, rel, alpha), np.full((2, 3, 3), 64))
    r = picture("relevancy", rgb, rel, alpha)
    assert np.array_equal(r[1, 2], [0, 0, 0]) and np.array_equal(r[0, 2], colorize(np.array([0.9]))[0])
    with pytest.raises(ValueError):
        picture("depth", rgb, rel, alpha)
    assert composite(rgb, np.full((2, 3), np.nan, np.float32)).shape == (2, 3, 3)


def test_camera_from_gl_is_the_same_view():
    cam = CameraSpec.look_at([3.0, -2.0, 1.5], [0.1, 0.2, 0.0], (0, 0, 1), 400, 300, 60.0)
    view_gl = GL_TO_CV @ cam.viewmat
    f_ndc_x, f_ndc_y = 2 * cam.fx / 400, 2 * cam.fy / 300
    proj = np.diag([f_ndc_x, f_ndc_y, -1.0, 0.0])
    proj[3, 2] = -1.0
    back = camera_from_gl(view_gl.astype(np.float32), proj, 400, 300)
    assert np.allclose(back.viewmat, cam.viewmat, atol=1e-6) and back.viewmat[3].tolist() == [0, 0, 0, 1]
    assert np.allclose([back.fx, back.fy, back.cx, back.cy], [cam.fx, cam.fy, cam.cx, cam.cy])
    pts = np.random.default_rng(0).normal(size=(20, 3))
    assert np.allclose(back.project(pts)[0], cam.project(pts)[0], atol=1e-3)
    small = scaled(back, *picture_size(400, 300, 320))
    assert (small.width, small.height) == (320, 240)
    assert np.allclose(small.project(pts)[0], cam.project(pts)[0] * 0.8, atol=1e-3)


def test_camera_json_round_trip_and_errors():
    cam = CameraSpec.look_at([1.0, 2, 3], [0.0, 0, 0], width=64, height=48)
    back = CameraSpec.from_dict(cam.to_dict())
    assert np.array_equal(back.viewmat, cam.viewmat) and (back.fx, back.width) == (cam.fx, 64)
    with pytest.raises(ValueError, match="missing fx"):
        CameraSpec.from_dict({k: v for k, v in cam.to_dict().items() if k != "fx"})
    with pytest.raises(ValueError, match="positive"):
        CameraSpec.from_dict({**cam.to_dict(), "fy": -1})
    with pytest.raises(ValueError):
        CameraSpec.from_dict({**cam.to_dict(), "viewmat": [1, 2, 3]})
    with pytest.raises(ValueError, match="JSON object"):
        CameraSpec.from_dict([1, 2])


def test_framing_and_bounds():
    box = Box(np.array([1.0, 1, 0]), np.array([0.5, 0.5, 0.5]), np.eye(3))
    eye, centre = framing(box, np.array([0.0, 1.0, -1.0]), 60.0)
    assert np.allclose(centre, box.center) and eye[1] < 1 and eye[2] > 0
    pts = np.concatenate([np.random.default_rng(1).uniform(-1, 1, (1000, 3)), [[100.0, 100, 100]]])
    lo, hi = robust_bounds(pts)
    assert (hi < 2).all() and (lo > -2).all()


def test_segment_colours_map_labels_onto_the_drawn_points():
    g = Geometry(
        index=np.array([0, 2, 5, 7]), mean=np.zeros((4, 3), np.float32), color=np.ones((4, 3), np.float32),
        opacity=np.ones(4, np.float32), scale=np.ones((4, 3), np.float32), num_gaussians=8, qualified=4,
        bounds=np.zeros(6),
    )  # fmt: skip
    seg = SegmentResult(("a", "b"), None, np.array([7, 0, 3]), np.array([1, 0, 1], np.int32))
    c = segment_colors(g, seg, keep=0.5)
    assert np.allclose(c[0], label_colors(np.array([0]))[0] / 255)
    assert np.allclose(c[3], label_colors(np.array([1]))[0] / 255)
    assert np.allclose(c[1], 0.75) and np.allclose(c[2], 0.75)  # not embedded: dimmed


def test_config_limits():
    with pytest.raises(ValueError):
        ViewerConfig(max_points=0)
    with pytest.raises(ValueError):
        ViewerConfig(min_opacity=1.0)


class _SlowClient:
    """stream(): answers each pose after a pause, recording which poses were sent."""

    def __init__(self, fail_first: bool = False) -> None:
        self.sent: list[CameraSpec] = []
        self.fail_first = fail_first

    def stream(self, scene, cameras, text, outputs):
        for seq, cam in enumerate(cameras):
            self.sent.append(cam)
            if self.fail_first:
                self.fail_first = False
                raise FmgsError("UNAVAILABLE", "server went away")
            time.sleep(0.1)
            yield RenderResult(seq, cam.width, cam.height, None)


def _cams(n):
    return [CameraSpec.look_at([float(i) + 1, 1.0, 1.0], [0.0, 0, 0], width=8, height=8) for i in range(n)]


def test_picture_feed_newest_pose_wins_and_never_blocks():
    client, got, done = _SlowClient(), [], threading.Event()
    cams = _cams(20)

    def on_result(cam, r):
        got.append(cam)
        if cam is cams[-1]:
            done.set()

    feed = PictureFeed(client, "s", "t", on_result, lambda e: None)
    in_put = 0.0  # time spent inside put (not in the sleeps between, which a loaded machine stretches)
    for c in cams:  # a user orbiting: poses far faster than renders
        t0 = time.monotonic()
        feed.put(c)
        in_put += time.monotonic() - t0
        time.sleep(0.01)
    assert in_put < 1.0  # put never waits for the server (20 renders of 0.1 s would take 2 s)
    assert done.wait(5.0)
    feed.close()
    assert got[-1] is cams[-1] and len(client.sent) < len(cams)  # skipped, not queued
    assert all(a is b for a, b in zip(got, client.sent, strict=False))


def test_picture_feed_reconnects_with_the_last_pose():
    client, got, errors = _SlowClient(fail_first=True), [], []
    feed = PictureFeed(client, "s", "", lambda c, r: got.append(c), errors.append)
    cam = _cams(1)[0]
    feed.put(cam)
    t0 = time.monotonic()
    while not got and time.monotonic() - t0 < 5:
        time.sleep(0.05)
    feed.close()
    assert [e.code for e in errors] == ["UNAVAILABLE"] and got == [cam] and feed.outputs == ("rgb", "alpha")


def test_picture_feed_delivers_nothing_once_closed():
    """A restarted feed (a new text) must not show the old feed's picture: close() waits for a delivery
    already under way, and none starts after it."""
    client, got = _SlowClient(), []
    entered, release = threading.Event(), threading.Event()

    def on_result(cam, r):
        got.append(cam)
        entered.set()
        release.wait(5.0)

    feed = PictureFeed(client, "s", "t", on_result, lambda e: None)
    cams = _cams(3)
    feed.put(cams[0])
    assert entered.wait(5.0)
    feed.put(cams[1])  # its answer comes after close()
    closer = threading.Thread(target=feed.close)
    closer.start()
    closer.join(0.3)
    assert closer.is_alive()  # close() waits for the callback in progress
    release.set()
    closer.join(5.0)
    assert not closer.is_alive()
    time.sleep(0.3)  # the pose sent before close() is answered after it: not delivered
    assert got == [cams[0]]
