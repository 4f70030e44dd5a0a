"""Synthetic labelled scenes: files, labels, boxes, and camera conventions checked geometrically."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from PIL import Image
from plyfile import PlyData

from fmgs.data.dataset import load_dataset
from fmgs.synth import BACKGROUND, WALL_HEIGHT, WALL_RADIUS, SynthConfig, generate


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    generate(out, SynthConfig(views=8, width=64, height=48, objects=6, seed=3, points=3000))
    return out


def test_files_and_metadata(scene):
    meta = json.loads((scene / "scene.json").read_text())
    assert meta["label_names"][:2] == ["background", "floor"] and len(meta["objects"]) == 7
    assert len(meta["views"]) == 8
    ds = load_dataset(scene)
    assert len(ds) == 8 and ds.points is not None and len(ds.points) >= 3000
    img, cam = ds.image(0)
    assert img.shape == (48, 64, 3) and (cam.width, cam.height) == (64, 48)
    labels = np.stack(
        [
            np.asarray(Image.open(scene / f["label_path"]))
            for f in json.loads((scene / "transforms.json").read_text())["frames"]
        ]
    )
    assert set(np.unique(labels)) == set(range(8))  # background, floor and all six objects are seen


def test_depth_unprojects_into_the_labelled_object(scene):
    """Pixels labelled as object k, lifted with their depth and our Camera, land in k's 3D box."""
    meta = json.loads((scene / "scene.json").read_text())
    boxes = {o["label"]: (np.array(o["aabb_min"]), np.array(o["aabb_max"])) for o in meta["objects"]}
    frames = json.loads((scene / "transforms.json").read_text())["frames"]
    ds = load_dataset(scene)
    checked = 0
    for frame, f in zip(sorted(frames, key=lambda fr: fr["file_path"]), ds.frames, strict=True):
        label = np.asarray(Image.open(scene / frame["label_path"]))
        depth = np.load(scene / frame["depth_path"], allow_pickle=False)
        cam = f.camera
        K, c2w = cam.K.numpy(), cam.camtoworld.numpy()
        for lab, (lo, hi) in boxes.items():
            ys, xs = np.nonzero(label == lab)
            if not len(xs):
                continue
            z = depth[ys, xs]
            p_cam = np.stack([(xs + 0.5 - K[0, 2]) / K[0, 0] * z, (ys + 0.5 - K[1, 2]) / K[1, 1] * z, z], -1)
            p = p_cam @ c2w[:3, :3].T + c2w[:3, 3]
            inside = ((p >= lo - 1e-3) & (p <= hi + 1e-3)).all(1)
            assert inside.mean() > 0.99, (lab, inside.mean())
            checked += len(xs)
    assert checked > 1000


def test_2d_boxes_match_labels(scene):
    meta = json.loads((scene / "scene.json").read_text())
    v = meta["views"][0]
    label = np.asarray(Image.open(scene / "labels" / "0000.png"))
    for name, (x0, y0, x1, y1) in v["boxes_2d"].items():
        lab = meta["label_names"].index(name)
        ys, xs = np.nonzero(label == lab)
        assert (xs.min(), ys.min(), xs.max(), ys.max()) == (x0, y0, x1, y1)


def test_deterministic(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    cfg = SynthConfig(views=2, width=32, height=24, objects=6, seed=1, points=500)
    generate(a, cfg)
    generate(b, cfg)
    assert (a / "images/0001.png").read_bytes() == (b / "images/0001.png").read_bytes()
    assert torch.equal(
        torch.from_numpy(np.load(a / "depth/0000.npy")), torch.from_numpy(np.load(b / "depth/0000.npy"))
    )


def test_cluttered_preset_varies_with_the_seed_and_touches(tmp_path):
    from fmgs.synth import OBJECTS

    metas = []
    for seed in (1, 2):
        out = tmp_path / f"s{seed}"
        generate(
            out,
            SynthConfig(views=4, width=48, height=36, objects=10, seed=seed, points=1500, preset="cluttered"),
        )
        metas.append(json.loads((out / "scene.json").read_text()))
    names = [m["label_names"][2:] for m in metas]
    assert all(len(n) == 10 and set(n) <= {o for o, _ in OBJECTS} for n in names)
    assert names[0] != names[1]  # the seed chooses the objects
    assert any("yellow pencil" in n for n in names)
    for m in metas:
        boxes = [(np.array(o["aabb_min"]), np.array(o["aabb_max"])) for o in m["objects"] if o["label"] >= 2]
        gaps = [
            np.max(np.maximum(a0 - b1, b0 - a1)[:2])
            for i, (a0, a1) in enumerate(boxes)
            for b0, b1 in boxes[i + 1 :]
        ]
        assert min(gaps) < 0.05  # some objects touch (their boxes meet or overlap in x-y)
        thin = [o for o in m["objects"] if o["name"] == "yellow pencil"]
        for o in thin:
            ext = np.subtract(o["aabb_max"], o["aabb_min"])
            assert ext[2] <= 0.051 and max(ext[:2]) > 0.4  # 5 cm thick, lying, long
    with pytest.raises(ValueError, match="preset"):
        generate(tmp_path / "x", SynthConfig(views=1, preset="messy"))
    with pytest.raises(ValueError, match=r"objects must be in 1\.\.8"):
        generate(tmp_path / "y", SynthConfig(views=1, objects=10))


def test_grazing_rig_and_undeclared_backdrop(tmp_path):
    cfg = SynthConfig(
        views=6, width=48, height=36, objects=3, points=500, rig="grazing", declare_background=False
    )
    generate(tmp_path, cfg)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert "background" not in meta  # a trainer must find the backdrop on its own
    heights = [f["transform_matrix"][2][3] for f in meta["frames"]]
    assert sorted({round(h, 6) for h in heights}) == [0.3, 0.9, 1.6]  # every third camera on the low ring
    labels = [np.asarray(Image.open(tmp_path / f["label_path"])) for f in meta["frames"]]
    low = [lab for h, lab in zip(heights, labels, strict=True) if h < 0.5]
    # From the low ring the backdrop (label 0) fills much of the upper half of the image.
    assert all((lab[: lab.shape[0] // 2] == 0).mean() > 0.3 for lab in low)
    with pytest.raises(ValueError, match="rig"):
        generate(tmp_path / "bad", SynthConfig(views=2, width=8, height=6, rig="orbit"))


def test_walls_backdrop_is_textured_geometry_labelled_background(tmp_path):
    cfg = SynthConfig(views=6, width=48, height=36, objects=3, points=600, rig="grazing", backdrop="walls")
    generate(tmp_path / "walls", cfg)
    generate(tmp_path / "plain", replace(cfg, backdrop="constant"))
    meta = json.loads((tmp_path / "walls" / "transforms.json").read_text())
    assert meta["background"] == list(BACKGROUND)  # the sky above the wall stays declared
    sky = np.round(np.asarray(BACKGROUND) * 255).astype(int)
    for f in meta["frames"]:
        lab = np.asarray(Image.open(tmp_path / "walls" / f["label_path"]))
        plain = np.asarray(Image.open(tmp_path / "plain" / f["label_path"]))
        rgb = np.asarray(Image.open(tmp_path / "walls" / f["file_path"])).astype(int)
        assert np.array_equal(lab, plain)  # the wall is background: no label moves
        back = rgb[lab == 0]
        off_sky = np.abs(back - sky).max(1) > 8
        # Much of what lies behind the scene is now the wall, and it is not one colour.
        assert off_sky.mean() > 0.3 and back[off_sky].std(0).max() > 20
    pts = PlyData.read(str(tmp_path / "walls" / "points3D.ply"))["vertex"]
    r = np.hypot(pts["x"], pts["y"])
    on_wall = r > WALL_RADIUS - 0.01  # a 96-gon; the floor's corners reach 5.66
    assert on_wall.sum() == cfg.points // 2 and pts["z"][on_wall].max() <= WALL_HEIGHT + 1e-6
    with pytest.raises(ValueError, match="backdrop"):
        generate(tmp_path / "bad", replace(cfg, backdrop="dome"))


def test_world_preset_names_colours_textures_and_shapes(tmp_path):
    """The wider world: distinct shapes, names made of colour, texture and shape, novel pairs only when
    asked, and every object's texture visible as more than one brightness on its pixels."""
    from fmgs.synthworld import COLOURS, HELD_OUT, SHAPES, TEXTURES, world_object

    assert len(SHAPES) >= 10 and len(COLOURS) >= 10 and len(TEXTURES) - 1 >= 10  # "plain" has no name
    assert len(set(HELD_OUT)) == len(HELD_OUT) and all(c in COLOURS and s in SHAPES for c, s in HELD_OUT)
    metas = {}
    for novel in (0, 3):
        out = tmp_path / f"n{novel}"
        cfg = SynthConfig(views=4, width=96, height=72, objects=10, seed=5, points=2000, preset="world")
        generate(out, replace(cfg, novel=novel, backdrop="walls"))
        metas[novel] = json.loads((out / "scene.json").read_text())
    for novel, m in metas.items():
        objs = [o for o in m["objects"] if o["label"] >= 2]
        assert len(objs) == 10 and len({o["shape"] for o in objs}) == 10
        for o in objs:
            w = world_object(o["name"])
            assert (w.colour, w.texture, w.shape) == (o["colour_name"], o["texture"], o["shape"])
            assert o["colour"] == list(COLOURS[w.colour])
        assert sum(o["novel"] for o in objs) == novel
    # textured objects show their pattern: two brightness levels among their pixels in some view
    out = tmp_path / "n3"
    m = metas[3]
    textured = {o["label"] for o in m["objects"] if o.get("texture") not in (None, "plain")}
    seen = set()
    for f in sorted((out / "images").iterdir()):
        img = np.asarray(Image.open(f)).astype(float).sum(-1)
        lab = np.asarray(Image.open(out / "labels" / f.name))
        for t in textured:
            px = img[lab == t]
            if len(px) >= 30 and np.percentile(px, 90) > 1.3 * np.percentile(px, 10) + 10:
                seen.add(t)
    assert len(seen) >= len(textured) // 2
    with pytest.raises(ValueError, match=r"objects must be in 1\.\.15"):
        generate(tmp_path / "x", SynthConfig(views=1, objects=16, preset="world"))
    with pytest.raises(ValueError, match="novel"):
        generate(tmp_path / "y", SynthConfig(views=1, objects=2, novel=3, preset="world"))


def test_world_object_names_round_trip():
    from fmgs.synthworld import object_name, world_object

    assert object_name("red", "plain", "cube") == "red cube"
    assert world_object("red striped cube").texture == "striped"
    assert world_object("red cube").texture == "plain"
    with pytest.raises(ValueError, match="not a world object name"):
        world_object("yellow pencil case")


@pytest.mark.parametrize("down", [True, False])
def test_a_camera_looking_along_the_up_axis_gets_a_finite_pose(down):
    """Straight down (a ring of radius 0) or straight up: world +z gives no horizon, so another up is taken
    instead of writing NaN poses."""
    from fmgs.cameras import Camera
    from fmgs.synth import _look_at

    eye, target = np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, 0.25])
    if not down:
        eye, target = target, eye
    V = _look_at(eye, target)
    assert np.isfinite(V).all()
    cam = Camera(Camera.intrinsics(10, 10, 5, 5), torch.from_numpy(V), 10, 10)  # a proper rotation
    forward = cam.viewmat[2, :3].numpy()
    np.testing.assert_allclose(forward, [0.0, 0.0, -1.0 if down else 1.0], atol=1e-15)
    np.testing.assert_allclose(cam.center.numpy(), eye, atol=1e-15)
    # An ordinary camera keeps its pose: +z up gives the horizon.
    V = _look_at(np.array([4.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.25]))
    assert abs(V[0, 2]) < 1e-15 and V[1, 2] < 0  # image x level, image down is world down
