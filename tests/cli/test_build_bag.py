"""End to end from a robot's recording: a ROS 2 bag of a generated scene (fmgs.synthbag) -> fmgs build
-> a package whose answers are in the recording's map frame, in metres."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fmgs.cli import main
from fmgs.synth import SynthConfig
from fmgs.synthbag import RobotPathConfig, write_robot_bag

pytestmark = pytest.mark.slow  # a 3DGS and a field trained from the recording

SCENE = SynthConfig(views=0, width=80, height=60, objects=4, seed=5, supersample=1)
PATH = RobotPathConfig(synth=SCENE, seconds=5.0, dropout=(2.0, 0.5), transport="compressed", blur_every=9)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bagbuild")
    bag = write_robot_bag(tmp, PATH)
    args = [
        "build", str(bag), "--name", "robot", "--models", str(tmp / "models"),
        "--targets", "labels", "--labels", str(tmp / "labels"), "--names", str(tmp / "scene.json"),
        "--gs-steps", "300", "--grad-threshold", "0.005", "--field-steps", "300", "--feature-scale", "0.5",
        "--device", "cpu", "--recording-max-depth-points", "4000",
    ]  # fmt: skip
    assert main(args) == 0
    return tmp, args


def test_build_from_a_bag_answers_in_the_map_frame(built, capsys):
    from fmgs.features.text import load_text_encoder
    from fmgs.query.engine import SceneEngine
    from fmgs.query.instances import InstanceConfig
    from fmgs.scene.manifest import Manifest

    tmp, _ = built
    m = Manifest.read(tmp / "models" / "robot")
    assert m.frame_id == "map" and m.extra["frame"]["units"] == "m"
    rec = m.extra["recording"]
    assert rec["image_topic"] == "/camera/color/image_raw/compressed" and rec["posed"]
    assert rec["dropped"]["tf_gap"] > 0 and rec["dropped"]["blurred"] > 0
    assert rec["read"] == rec["kept"] + sum(rec["dropped"].values())
    geometry = json.loads((tmp / "models" / ".work" / "robot" / "geometry.json").read_text())
    assert geometry["recording"] == rec
    assert main(["info", str(tmp / "models" / "robot")]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["frame"] == "map" and shown["build"]["recording"]["kept"] == rec["kept"]
    engine = SceneEngine.open(tmp / "models" / "robot")
    enc = load_text_encoder(engine.manifest.encoder_id)
    objects = json.loads((tmp / "scene.json").read_text())["objects"][1:]  # not the floor
    for o in objects:
        q = enc.encode_text([o["name"]])[0]
        r = engine.text_query(q, top_k=10)
        means = engine.gaussians.means[r.index].detach().numpy()
        lo, hi = np.array(o["aabb_min"]) - 0.1, np.array(o["aabb_max"]) + 0.1
        inside = np.all((means >= lo) & (means <= hi), axis=1)
        # In map coordinates: the first answer and most of the top 10 lie in the object's box (measured:
        # 10 of 10 for each of the 4 objects); in odom's frame they would be about 0.5 m away.
        assert inside[0] and inside.sum() >= 7, (o["name"], inside)
        best = engine.text_query(q, top_k=100, instances=InstanceConfig()).instances[0]  # the 3D box served
        assert np.all((best.centroid >= lo) & (best.centroid <= hi)), (o["name"], best.centroid)


def test_the_terminal_says_what_the_recording_gave_and_a_rebuild_reuses_it(built, capsys):
    _, args = built
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "[1/5] poses: /camera/color/image_raw/compressed: read " in out
    assert "poses from tf in frame 'map'" in out and "points from /camera/depth/image_raw" in out
    assert "reading the recording" not in out  # the import was complete: reused
