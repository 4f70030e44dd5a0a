"""Faults of real recordings that fmgs.data.rosbag must name, not pass on as NaN poses, wrong points or a
traceback: tiny hand-written recordings (a camera moving along x in map, tf at 50 Hz, 32x24 images)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fmgs.data.rosbag import RecordingConfig, import_recording, is_recording
from fmgs.errors import ValidationError

T0 = 1_700_000_000 * 10**9
W, H = 32, 24
OPTICAL = (-0.5, 0.5, -0.5, 0.5)
"""base -> cam: REP 103's optical axes in a body frame, as (x, y, z, w)."""


def _types(ros1: bool = False):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:  # noetic's store has no tf2_msgs
        ts.register(
            get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
        )
    return ts


def _messages(ts, n=10, ros1=False, quat=None, k=None, image=None, depth=None, depth_info=None):
    """(recorded ns, topic, message) of a camera moving 0.2 m per image along map's x; ``quat(k)`` the
    k-th map -> base rotation, ``k`` CameraInfo's K, ``image(i, stamp)`` and ``depth(i, stamp)`` replace
    the i-th image or add a depth image (``depth_info`` its CameraInfo size)."""
    ty = ts.types
    Time, Header = ty["builtin_interfaces/msg/Time"], ty["std_msgs/msg/Header"]
    TFm, TS, Tr = (
        ty["tf2_msgs/msg/TFMessage"],
        ty["geometry_msgs/msg/TransformStamped"],
        ty["geometry_msgs/msg/Transform"],
    )
    V3, Q = ty["geometry_msgs/msg/Vector3"], ty["geometry_msgs/msg/Quaternion"]
    Img, Info, ROI = (
        ty["sensor_msgs/msg/Image"],
        ty["sensor_msgs/msg/CameraInfo"],
        ty["sensor_msgs/msg/RegionOfInterest"],
    )

    def hdr(ns, frame):
        t = Time(ns // 10**9, ns % 10**9)
        return Header(0, t, frame) if ros1 else Header(t, frame)

    def tf(ns, parent, child, t, q):
        return TS(hdr(ns, parent), child, Tr(V3(*map(float, t)), Q(*map(float, q))))

    def info(ns, frame, w, h):
        K = np.array([30.0, 0, w / 2 - 0.5, 0, 30.0, h / 2 - 0.5, 0, 0, 1]) if k is None else np.asarray(k)
        return Info(
            hdr(ns, frame),
            h,
            w,
            "plumb_bob",
            np.zeros(5),
            K,
            np.eye(3).ravel(),
            np.zeros(12),
            0,
            0,
            ROI(0, 0, 0, 0, False),
        )

    out = [(T0, "/tf_static", TFm([tf(T0, "base", "cam", (0, 0, 0), OPTICAL)]))]
    for j in range(int((n / 10 + 0.2) * 50) + 1):
        s = T0 + j * 20_000_000
        q = quat(j) if quat else (0, 0, 0, 1)
        out.append((s, "/tf", TFm([tf(s, "map", "base", (2.0 * j / 50, 0, 0), q)])))
    for i in range(n):
        s = T0 + int((i / 10 + 0.05) * 1e9)
        a = np.random.default_rng(i).integers(0, 255, (H, W, 3), dtype=np.uint8)
        img = Img(hdr(s, "cam"), H, W, "rgb8", 0, 3 * W, a.ravel())
        out.append((s, "/cam/image_raw", image(i, s, img) if image else img))
        out.append((s, "/cam/camera_info", info(s, "cam", W, H)))
        if depth:
            frame, d = depth(i, s)
            dh, dw = d.shape
            out.append(
                (
                    s,
                    "/depth/image_raw",
                    Img(hdr(s, frame), dh, dw, "32FC1", 0, 4 * dw, d.view(np.uint8).ravel()),
                )
            )
            if depth_info:
                out.append((s, "/depth/camera_info", info(s, frame, *depth_info)))
    return sorted(out, key=lambda m: m[0])


def _write(path: Path, ros1: bool = False, edit=None, **kw) -> Path:
    ts = _types(ros1)
    msgs = _messages(ts, ros1=ros1, **kw)
    msgs = edit(msgs) if edit else msgs
    if ros1:
        from rosbags.rosbag1 import Writer

        path = path.with_suffix(".bag")
        ser = ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        ser = ts.serialize_cdr
    with Writer(path) if ros1 else Writer(path, version=9) as w:
        cons = {}
        for s, topic, msg in msgs:
            if topic not in cons:
                cons[topic] = w.add_connection(topic, msg.__msgtype__, typestore=ts)
            w.write(cons[topic], s, ser(msg, msg.__msgtype__))
    return path


def _fails(bag, tmp_path: Path, cfg: RecordingConfig | None = None) -> str:
    with pytest.raises(ValidationError) as e:
        import_recording(bag, tmp_path / "ds", cfg or RecordingConfig(blur_ratio=0))
    assert not (tmp_path / "ds").exists() and not (tmp_path / "ds.partial").exists()  # nothing half-written
    return str(e.value)


def test_a_tiny_recording_imports_posed(tmp_path):
    res = import_recording(_write(tmp_path / "ok"), tmp_path / "ds", RecordingConfig(blur_ratio=0))
    assert res.posed and res.kept == 10
    meta = json.loads((tmp_path / "ds" / "transforms.json").read_text())
    xs = [f["transform_matrix"][0][3] for f in meta["frames"]]
    assert np.allclose(np.diff(xs), 0.2)


@pytest.mark.parametrize("q", [(float("nan"), 0, 0, 1), (0, 0, 0, 0), (0, 0, float("inf"), 1)])
def test_a_transform_that_is_no_rotation_is_skipped_as_tf2_does(tmp_path, q, caplog):
    """Before: the NaN pose was kept, written into transforms.json as NaN, and every later frame dropped
    as "still" (NaN compares false). Now the sample is skipped and counted, with a warning naming it, and
    the poses come from the samples around it."""
    bag = _write(tmp_path / "bag", quat=lambda j: q if j == 3 else (0, 0, 0, 1))
    with caplog.at_level("WARNING"):
        res = import_recording(bag, tmp_path / "ds", RecordingConfig(blur_ratio=0))
    assert res.posed and res.kept == 10 and res.tf_skipped == 1, res
    assert "1 tf samples skipped" in res.line()
    said = caplog.text
    assert "/tf" in said and "map -> base" in said and "1700000000.060000000" in said and "quaternion" in said
    meta = json.loads((tmp_path / "ds" / "transforms.json").read_text())
    xs = [f["transform_matrix"][0][3] for f in meta["frames"]]
    assert np.all(np.isfinite(np.array([f["transform_matrix"] for f in meta["frames"]])))
    assert np.allclose(np.diff(xs), 0.2)


def test_camera_info_with_nan_calibration_is_refused(tmp_path):
    bag = _write(tmp_path / "bag", k=[float("nan"), 0, 16, 0, 30, 12, 0, 0, 1])
    msg = _fails(bag, tmp_path)
    assert "/cam/camera_info" in msg and "K" in msg


def test_a_ros1_bag_reads_its_upper_case_calibration(tmp_path):
    bag = _write(tmp_path / "run", ros1=True)
    assert is_recording(bag)
    res = import_recording(bag, tmp_path / "ds", RecordingConfig(blur_ratio=0))
    assert res.posed and res.kept == 10
    assert json.loads((tmp_path / "ds" / "transforms.json").read_text())["fl_x"] == 30.0


def test_a_topic_that_holds_no_images_is_named(tmp_path):
    bag = _write(tmp_path / "bag")
    msg = _fails(bag, tmp_path, RecordingConfig(image_topic="/cam/camera_info"))
    assert "--image-topic" in msg and "/cam/camera_info" in msg and "sensor_msgs/msg/CameraInfo" in msg
    msg = _fails(bag, tmp_path, RecordingConfig(depth_topic="/cam/camera_info"))
    assert "--depth-topic" in msg and "/cam/camera_info" in msg and "sensor_msgs/msg/CameraInfo" in msg


def test_an_image_in_a_frame_tf_does_not_join_is_named_with_its_time(tmp_path):
    def other(i, s, img):
        if i == 6:
            img.header.frame_id = "cam_old"
        return img

    msg = _fails(_write(tmp_path / "bag", image=other), tmp_path)
    assert "/cam/image_raw" in msg and "'cam_old'" in msg and "1700000000.650000000" in msg


def test_depth_in_a_frame_tf_does_not_join_is_named(tmp_path):
    bag = _write(tmp_path / "bag", depth=lambda i, s: ("dcam", np.full((H, W), 2.0, np.float32)))
    msg = _fails(bag, tmp_path)
    assert "/depth/image_raw" in msg and "'dcam'" in msg and "--depth-topic none" in msg


def test_depth_of_another_size_than_its_calibration_is_refused(tmp_path):
    # Before: back-projected with a calibration of another size, the points were silently wrong.
    half = np.full((H // 2, W // 2), 2.0, np.float32)
    bag = _write(tmp_path / "noinfo", depth=lambda i, s: ("cam", half))  # no CameraInfo: the colour one's
    msg = _fails(bag, tmp_path)
    assert "/depth/image_raw" in msg and "16x12" in msg and "32x24" in msg
    bag = _write(tmp_path / "info", depth=lambda i, s: ("cam", half), depth_info=(W, H))
    msg = _fails(bag, tmp_path)
    assert "/depth/image_raw" in msg and "16x12" in msg and "/depth/camera_info" in msg
    bag = _write(tmp_path / "ok", depth=lambda i, s: ("cam", half), depth_info=(W // 2, H // 2))
    res = import_recording(bag, tmp_path / "ds", RecordingConfig(blur_ratio=0))
    assert res.depth_points > 0


def test_a_folder_whose_recorder_stopped_before_metadata_is_read(tmp_path):
    """A recorder killed (power lost, SIGKILL) leaves its storage file without metadata.yaml."""
    bag = _write(tmp_path / "run")
    (bag / "metadata.yaml").unlink()
    assert is_recording(bag) and not is_recording(tmp_path)
    res = import_recording(bag, tmp_path / "ds", RecordingConfig(blur_ratio=0))
    assert res.posed and res.kept == 10
    f = next(bag.glob("*.db3"))  # rosbags' Writer writes sqlite3 unless told otherwise
    f.rename(bag / "run_1.db3")
    _write(tmp_path / "more")
    next((tmp_path / "more").glob("*.db3")).rename(bag / "run_0.db3")
    (tmp_path / "two").mkdir()
    msg = _fails(bag, tmp_path / "two")
    assert "metadata.yaml" in msg and "ros2 bag reindex" in msg


def test_a_corrupt_compressed_image_is_named_with_its_time(tmp_path):
    from rosbags.typesys import Stores, get_typestore

    CImg = get_typestore(Stores.ROS2_HUMBLE).types["sensor_msgs/msg/CompressedImage"]

    def jpeg(i, s, img):
        return CImg(img.header, "jpeg", np.frombuffer(b"\xff\xd8\xff\xe0 cut short", np.uint8))

    bag = _write(tmp_path / "bag", image=jpeg)
    msg = _fails(bag, tmp_path)
    assert "/cam/image_raw" in msg and "1700000000.050000000" in msg


def test_a_recording_sent_to_sfm_says_what_its_tf_lacks(tmp_path):
    def namespaced(msgs):
        for _s, topic, msg in msgs:
            for tr in msg.transforms if topic.startswith("/tf") else []:
                tr.header.frame_id, tr.child_frame_id = "r1/" + tr.header.frame_id, "r1/" + tr.child_frame_id
        return msgs

    def r1(i, s, img):
        img.header.frame_id = "r1/cam"
        return img

    bag = _write(tmp_path / "ns", edit=namespaced, image=r1)
    res = import_recording(bag, tmp_path / "ns_ds", RecordingConfig(blur_ratio=0))
    assert not res.posed and "no frame map or odom in tf (r1/base, r1/cam, r1/map)" in res.line()
    assert "--fixed-frame" in res.line()
    fixed = RecordingConfig(blur_ratio=0, fixed_frame="/r1/map")  # tf's names lose their leading slash
    res = import_recording(bag, tmp_path / "fixed", fixed)
    assert res.posed and res.kept == 10 and res.fixed_frame == "r1/map"

    def image_frame(i, s, img):
        img.header.frame_id = "camera_optical_frame"  # its mount published nowhere (no /tf_static recorded)
        return img

    res = import_recording(_write(tmp_path / "m", image=image_frame), tmp_path / "m_ds")
    assert (
        not res.posed
        and "the camera's frame 'camera_optical_frame' is not in tf (base, cam, map)" in res.line()
    )
