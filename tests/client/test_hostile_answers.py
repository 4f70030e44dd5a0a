"""Answers a hostile or buggy server could send: NaN or infinity in any number, requested render outputs
left out. The client refuses them as malformed (DATA_LOSS) naming what is wrong, so nothing shows or
writes NaN (the inspector's legend, its picture, a PLY export)."""

from __future__ import annotations

import numpy as np
import pytest

from fmgs_client.client import (
    FmgsClient,
    FmgsError,
    assemble_geometry,
    assemble_render,
    assemble_segment,
    assemble_text_answers,
    point_result,
)
from fmgs_client.ply import write_ply
from fmgs_client.types import CameraSpec, SceneInfo
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.tensors import to_tensor
from tests.helpers.client_fakes import (
    FakeFmgs,
    answer_cols,
    answer_with_instances,
    pb_box,
    render_chunks,
    serve_fake,
    text_chunks,
)

BAD = (np.nan, np.inf, -np.inf)


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("name", ["relevancy", "similarity", "mean"])
def test_text_answer_with_non_finite_rows_is_refused(name, bad):
    cols = answer_cols(np.random.default_rng(0), 5)
    cols[name] = cols[name].copy()
    cols[name].reshape(-1)[3] = bad
    with pytest.raises(ValueError, match=rf"text\[0\]\.{name}: 1 of \d+ values are NaN or infinite"):
        assemble_text_answers(text_chunks(0, "cup", cols), ["cup"], ["mean"])


def _instance(**over):
    box = pb_box([0, 0, 0], [1, 1, 1])
    m = dict(id=0, centroid=[0, 0, 0], aabb=box, obb=box, score=0.5, num_members=3)
    m.update(over)
    return pb.Instance(**m)


@pytest.mark.parametrize(
    ("inst", "what"),
    [
        (_instance(centroid=[0, np.nan, 0]), "centroid"),
        (_instance(score=np.nan), "score"),
        (_instance(obb=pb_box([0, 0, np.inf], [1, 1, 1])), "obb"),
        (_instance(aabb=pb_box([0, 0, 0], [1, np.nan, 1])), "aabb"),
        (_instance(obb=pb_box([0, 0, 0], [1, 1, 1], np.full((3, 3), np.nan))), "obb"),
    ],
)
def test_instance_with_non_finite_numbers_is_refused(inst, what):
    cols = answer_cols(np.random.default_rng(0), 5, with_fields=False)
    with pytest.raises(ValueError, match=rf"Instance 0\.{what}.*NaN or infinite"):
        assemble_text_answers(text_chunks(0, "cup", cols, [inst]), ["cup"])


@pytest.mark.parametrize("name", ["relevancy", "rgb", "depth", "alpha"])
def test_render_with_non_finite_pixels_is_refused(name):
    images = {
        "relevancy": np.full((4, 5), 0.6, np.float32),
        "rgb": np.full((4, 5, 3), 0.2, np.float32),
        "depth": np.ones((4, 5), np.float32),
        "alpha": np.ones((4, 5), np.float32),
    }
    images[name].reshape(-1)[7] = np.nan
    with pytest.raises(ValueError, match=rf"render\[0\]\.{name}: 1 of \d+ values are NaN or infinite"):
        assemble_render(render_chunks(0, images, 2))


def test_render_numbers_beside_the_images_must_be_finite():
    images = {"relevancy": np.full((4, 5), 0.6, np.float32)}
    with pytest.raises(ValueError, match=r"render\[0\]\.argmax.*NaN or infinite"):
        assemble_render(render_chunks(0, images, 2, argmax=(1, 1, float("nan"))))
    chunks = render_chunks(0, images, 2)
    chunks[0].elapsed_ms = float("inf")
    with pytest.raises(ValueError, match=r"render\[0\]\.elapsed_ms.*NaN or infinite"):
        assemble_render(chunks)


def _geometry_chunk(mean: np.ndarray, bounds=(-1, -1, 0, 1, 1, 0.5)) -> pb.GeometryChunk:
    n = len(mean)
    c = pb.GeometryChunk(start=0, total=n, num_gaussians=n, qualified=n, bounds=list(bounds), last=True)
    c.index.CopyFrom(to_tensor(np.arange(n, dtype=np.int64)))
    c.mean.CopyFrom(to_tensor(mean.astype(np.float32)))
    c.color.CopyFrom(to_tensor(np.full((n, 3), 0.5, np.float32)))
    c.opacity.CopyFrom(to_tensor(np.ones(n, np.float32)))
    c.scale.CopyFrom(to_tensor(np.ones((n, 3), np.float32)))
    return c


def test_geometry_with_non_finite_numbers_is_refused():
    mean = np.zeros((6, 3), np.float32)
    assert len(assemble_geometry([_geometry_chunk(mean)])) == 6
    assert len(assemble_geometry([_geometry_chunk(mean[:0])])) == 0  # no Gaussians drawn
    mean[2, 1] = np.inf
    with pytest.raises(ValueError, match=r"geometry\.mean: 1 of 18 values are NaN or infinite"):
        assemble_geometry([_geometry_chunk(mean)])
    with pytest.raises(ValueError, match=r"geometry\.bounds.*NaN or infinite"):
        assemble_geometry([_geometry_chunk(mean[:0], (0, 0, 0, np.nan, 1, 1))])


def test_scene_bounds_and_point_results_must_be_finite():
    with pytest.raises(ValueError, match=r"SceneInfo\.bounds.*NaN or infinite"):
        SceneInfo.from_proto(pb.SceneInfo(name="s", bounds=[0, 0, 0, 1, np.nan, 1]))
    rel = np.array([[0.5, np.nan]], np.float32)
    resp = pb.PointQueryResponse(relevancy=to_tensor(rel), similarity=to_tensor(np.zeros_like(rel)))
    with pytest.raises(ValueError, match=r"points\.relevancy: 1 of 2 values are NaN or infinite"):
        point_result(resp, 1, 2)


def test_segment_of_zero_gaussians():
    c = pb.SegmentChunk(class_names=["a", "b"], last=True)
    c.gaussian_index.CopyFrom(to_tensor(np.zeros(0, np.int64)))
    c.gaussian_labels.CopyFrom(to_tensor(np.zeros(0, np.int32)))
    seg = assemble_segment([c])
    assert len(seg.gaussian_index) == 0 and seg.counts() == [(0, 0), (0, 0)]


class _NanServer(FakeFmgs):
    """Sends NaN in its renders' relevancy, and leaves out the colour render when asked for it."""

    def _render(self, request):
        cam = request.camera
        rel = np.full((cam.height, cam.width), 0.7, np.float32)
        if request.text == "nan":
            rel[0, 0] = np.nan
        return render_chunks(request.sequence, {"relevancy": rel}, 3)


def test_client_refuses_nan_and_missing_outputs_from_the_server(monkeypatch):
    monkeypatch.setattr("tests.helpers.client_fakes.FakeFmgs", _NanServer)
    with serve_fake() as (_, address), FmgsClient(address, timeout=10) as c:
        cam = CameraSpec.look_at((0, -3, 1), (0, 0, 0), width=6, height=4)
        assert c.render("demo", cam, "ok").relevancy.shape == (4, 6)
        with pytest.raises(FmgsError) as e:
            c.render("demo", cam, "nan")
        assert e.value.code == "DATA_LOSS" and "render[0].relevancy: 1 of 24 values" in e.value.details
        with pytest.raises(FmgsError) as e:
            c.render("demo", cam, "ok", outputs=("relevancy", "rgb"))
        assert e.value.code == "DATA_LOSS" and "render[0]: no rgb" in e.value.details
        with pytest.raises(FmgsError) as e:
            list(c.stream("demo", [cam, cam], "ok", outputs=("rgb", "alpha")))
        assert e.value.code == "DATA_LOSS" and "render[0]: no rgb, alpha" in e.value.details
        with pytest.raises(FmgsError) as e:
            list(c.stream("demo", [cam], "nan"))
        assert e.value.code == "DATA_LOSS" and "render[0].relevancy" in e.value.details


@pytest.mark.parametrize("bad", BAD)
def test_write_ply_refuses_non_finite_numbers(tmp_path, bad):
    pts = np.zeros((3, 3), np.float32)
    pts[1, 2] = bad
    with pytest.raises(ValueError, match=r"write_ply: points: 1 of 9 values are NaN or infinite"):
        write_ply(tmp_path / "p.ply", pts)
    rel = np.array([0.5, bad, 0.7], np.float32)
    with pytest.raises(ValueError, match=r"write_ply: property 'relevancy': 1 of 3 values are NaN"):
        write_ply(tmp_path / "p.ply", np.zeros((3, 3)), scalars={"relevancy": rel})
    assert not (tmp_path / "p.ply").exists()


@pytest.mark.parametrize(
    ("size", "up", "match"),
    [
        ((0, 600), (0, 0, 1), "width and height must be at least 1, got 0x600"),
        ((800, 0), (0, 0, 1), "width and height must be at least 1, got 800x0"),
        ((800, 600), (0, 0, 0), r"up must be 3 finite numbers, not all zero, got \[0.0, 0.0, 0.0\]"),
    ],
)
def test_view_camera_names_a_bad_size_or_up(size, up, match):
    from fmgs_client import open3d_tools as ot

    with pytest.raises(ValueError, match=match):
        ot.view_camera(answer_with_instances(), *size, up=up)


def test_screenshot_of_size_zero_is_refused_by_name(tmp_path):
    from fmgs_client import open3d_tools as ot

    with pytest.raises(ValueError, match="width and height must be at least 1, got 0x1"):
        ot.screenshot(answer_with_instances(), tmp_path / "s.png", 0, 1, method="numpy")
    assert not (tmp_path / "s.png").exists()
