"""A robot's recording of a generated scene, written as a ROS 2 bag with ``rosbags``: a mobile base
driving around the scene (tf ``map -> odom -> base_link -> camera_link -> camera_optical_frame``), a
camera on a mast (raw or compressed images, CameraInfo), a registered depth camera, and optionally a tf
dropout. The generator's own poses are kept beside the bag (``truth.json``) to check what a reader
recovers, and label images under the message index (``labels/NNNNNN.png``) for label-target builds.

Between two tf samples the true pose is tf2's interpolation of them (translation linearly, rotation by
slerp, computed here with scipy's Slerp), and the images are rendered at exactly those poses.
"""

from __future__ import annotations

import io
import json
import shutil
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from fmgs.io.atomic import atomic_path
from fmgs.synth import SynthConfig, generate

OPTICAL_IN_LINK = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""REP 103: the optical frame's axes (z forward, x right, y down) in its camera link (x forward, y left,
z up); columns are the optical axes."""


@dataclass(frozen=True)
class RobotPathConfig:
    """The recording: the scene (``synth``), the path and what is published."""

    synth: SynthConfig = field(default_factory=lambda: SynthConfig(views=0))
    seconds: float = 6.0
    """Length of the drive: one full circle around the scene."""
    image_hz: float = 15.0
    tf_hz: float = 50.0
    image_offset_s: float = 0.013
    """Image stamps fall this long after a tf sample's, so every pose is interpolated."""
    radius: float = 4.0
    mast: float = 1.2
    """Camera height above the floor (metres)."""
    look_at_height: float = 0.25
    """The camera is pitched down to look at the scene centre at this height."""
    map_to_odom: tuple[float, float, float] = (0.4, -0.3, 0.2)
    """(x, y, yaw) of odom in map: the odometry's drift, corrected by localisation."""
    dropout: tuple[float, float] = (0.0, 0.0)
    """(start, length) seconds of the drive with no odom -> base_link transform."""
    transport: str = "raw"
    """"raw" (rgb8 Image), "compressed" (PNG CompressedImage) or "both" (two topics of one camera)."""
    depth: bool = True
    """A depth topic (32FC1, metres) with its own CameraInfo."""
    depth_offset: tuple[float, float, float] | None = None
    """None: the depth is registered to the colour camera (its frame, size and K). A translation (metres,
    in the colour optical frame): an unregistered depth camera there, in its own frame
    ``camera_depth_optical_frame`` at half the colour size."""
    storage: str = "mcap"
    """"mcap" or "sqlite3"."""
    blur_every: int = 0
    """Every n-th image is blurred (a 9-pixel box filter: motion blur's effect on sharpness); 0: none."""
    # Faults a reader must name (tests): a missing calibration, an encoding we do not read, a camera
    # mount left out of tf, a clock that jumps back.
    camera_info: bool = True
    encoding: str = "rgb8"
    """Raw images' encoding: "rgb8" or "bgr8" (converted); any other name is written over rgb8 bytes."""
    mount_tf: bool = True
    """Publish base_link -> camera_link; False leaves the camera's tree apart from map's."""
    clock_jump_at: int = 0
    """From this image on, stamps go back 5 s (0: never)."""


def _yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _T(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _base_in_map(cfg: RobotPathConfig, t: float) -> np.ndarray:
    """map_T_base_link at time t: on the circle, facing the centre."""
    a = 2 * np.pi * t / cfg.seconds
    p = cfg.radius * np.array([np.cos(a), np.sin(a), 0.0])
    return _T(_yaw(a + np.pi), p)


def _link_in_base(cfg: RobotPathConfig) -> np.ndarray:
    """base_link_T_camera_link: on the mast, pitched down at the scene centre."""
    pitch = np.arctan2(cfg.mast - cfg.look_at_height, cfg.radius - 0.1)
    c, s = np.cos(pitch), np.sin(pitch)
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # about y: positive pitches x down
    return _T(R, [0.1, 0.0, cfg.mast])


def _odom_in_map(cfg: RobotPathConfig) -> np.ndarray:
    x, y, a = cfg.map_to_odom
    return _T(_yaw(a), [x, y, 0.0])


def recorded_truth(cfg: RobotPathConfig) -> dict:
    """tf samples and images: stamps (ns) and, per image, map_T_optical as tf2 interpolates it."""
    from scipy.spatial.transform import Rotation, Slerp

    t0 = 1_700_000_000 * 10**9
    n_tf = int(cfg.seconds * cfg.tf_hz) + 1
    tf_t = np.arange(n_tf) / cfg.tf_hz
    m_o = _odom_in_map(cfg)
    o_b = [np.linalg.inv(m_o) @ _base_in_map(cfg, t) for t in tf_t]
    keep = ~((tf_t >= cfg.dropout[0]) & (tf_t < cfg.dropout[0] + cfg.dropout[1]))
    n_img = int((cfg.seconds - cfg.image_offset_s) * cfg.image_hz)
    img_t = np.arange(n_img) / cfg.image_hz + cfg.image_offset_s
    rots = Slerp(tf_t, Rotation.from_matrix(np.stack([T[:3, :3] for T in o_b])))
    b_opt = _link_in_base(cfg) @ _T(OPTICAL_IN_LINK, [0, 0, 0])
    poses = []
    for t in img_t:
        i = min(int(np.searchsorted(tf_t, t, side="right")) - 1, n_tf - 2)
        u = (t - tf_t[i]) / (tf_t[i + 1] - tf_t[i])
        trans = o_b[i][:3, 3] + u * (o_b[i + 1][:3, 3] - o_b[i][:3, 3])
        poses.append(m_o @ _T(rots([t]).as_matrix()[0], trans) @ b_opt)
    ns = lambda s: int(t0 + round(s * 1e9))  # noqa: E731
    return {
        "tf_stamps": [ns(t) for t in tf_t],
        "tf_kept": keep.tolist(),
        "odom_T_base": [T.tolist() for T in o_b],
        "image_stamps": [ns(t) for t in img_t],
        "map_T_optical": [T.tolist() for T in poses],
    }


def _box_blur(rgb: np.ndarray, k: int) -> np.ndarray:
    """[H,W,3] uint8 averaged over k x k windows (edges clamped)."""
    a = np.pad(rgb.astype(np.float64), ((k // 2, k // 2), (k // 2, k // 2), (0, 0)), mode="edge")
    c = np.pad(a.cumsum(0).cumsum(1), ((1, 0), (1, 0), (0, 0)))
    h, w = rgb.shape[:2]
    s = c[k : k + h, k : k + w] - c[:h, k : k + w] - c[k : k + h, :w] + c[:h, :w]
    return (s / (k * k) + 0.5).astype(np.uint8)


def write_robot_bag(out: str | Path, cfg: RobotPathConfig | None = None) -> Path:
    """Render the scene along the path and write ``out/bag`` (the recording), ``out/truth.json``,
    ``out/labels`` and ``out/scene.json``; returns the recording's path."""
    from PIL import Image
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    cfg = cfg or RobotPathConfig()
    out = Path(out)
    truth = recorded_truth(cfg)
    viewmats = np.stack([np.linalg.inv(np.array(T)) for T in truth["map_T_optical"]])
    render = out / "render"
    generate(render, replace(cfg.synth, views=len(viewmats)), viewmats)
    meta = json.loads((render / "transforms.json").read_text())
    W, H = meta["w"], meta["h"]
    dmeta, dframe, drender = meta, "camera_optical_frame", render
    if cfg.depth and cfg.depth_offset is not None:  # a second camera beside the colour one, rendered apart
        c_d = _T(np.eye(3), cfg.depth_offset)
        dviews = np.stack([np.linalg.inv(np.array(T) @ c_d) for T in truth["map_T_optical"]])
        drender, dframe = out / "render_depth", "camera_depth_optical_frame"
        generate(drender, replace(cfg.synth, views=len(dviews), width=W // 2, height=H // 2), dviews)
        dmeta = json.loads((drender / "transforms.json").read_text())

    ts = get_typestore(Stores.ROS2_HUMBLE)
    ty = ts.types
    Time, Header = ty["builtin_interfaces/msg/Time"], ty["std_msgs/msg/Header"]
    Img, CImg, Info = (
        ty["sensor_msgs/msg/Image"],
        ty["sensor_msgs/msg/CompressedImage"],
        ty["sensor_msgs/msg/CameraInfo"],
    )
    TFm, TS = ty["tf2_msgs/msg/TFMessage"], ty["geometry_msgs/msg/TransformStamped"]
    Tr, V3, Q = (
        ty["geometry_msgs/msg/Transform"],
        ty["geometry_msgs/msg/Vector3"],
        ty["geometry_msgs/msg/Quaternion"],
    )
    ROI = ty["sensor_msgs/msg/RegionOfInterest"]

    def header(ns: int, frame: str):
        return Header(Time(ns // 10**9, ns % 10**9), frame)

    def tstamped(ns: int, parent: str, child: str, T: np.ndarray):
        from scipy.spatial.transform import Rotation

        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        return TS(
            header(ns, parent),
            child,
            Tr(V3(*map(float, T[:3, 3])), Q(float(x), float(y), float(z), float(w))),
        )

    def info(ns: int, frame: str, meta: dict = meta):
        # ROS's principal point counts the top-left pixel's centre as (0, 0): ours less half a pixel.
        fx, fy, cx, cy = meta["fl_x"], meta["fl_y"], meta["cx"] - 0.5, meta["cy"] - 0.5
        H, W = meta["h"], meta["w"]
        K = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1.0])
        P = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1.0, 0])
        return Info(
            header(ns, frame),
            H,
            W,
            "plumb_bob",
            np.zeros(5),
            K,
            np.eye(3).ravel(),
            P,
            0,
            0,
            ROI(0, 0, 0, 0, False),
        )

    bag = out / "bag"
    if bag.exists():
        shutil.rmtree(bag)
    plugin = StoragePlugin.MCAP if cfg.storage == "mcap" else StoragePlugin.SQLITE3
    msgs: list[tuple[int, str, object]] = []
    opt = "camera_optical_frame"
    s0 = truth["tf_stamps"][0]
    static = [tstamped(s0, "camera_link", opt, _T(OPTICAL_IN_LINK, [0, 0, 0]))]
    if cfg.mount_tf:
        static.insert(0, tstamped(s0, "base_link", "camera_link", _link_in_base(cfg)))
    if dframe != opt:
        static.append(tstamped(s0, opt, dframe, _T(np.eye(3), cfg.depth_offset)))
    msgs.append((s0, "/tf_static", TFm(static)))
    m_o = _odom_in_map(cfg)
    for k, (s, T) in enumerate(zip(truth["tf_stamps"], truth["odom_T_base"], strict=True)):
        tfs = [tstamped(s, "map", "odom", m_o)] if k % 5 == 0 else []
        if truth["tf_kept"][k]:
            tfs.append(tstamped(s, "odom", "base_link", np.array(T)))
        if tfs:
            msgs.append((s, "/tf", TFm(tfs)))
    (out / "labels").mkdir(parents=True, exist_ok=True)
    for i, rec in enumerate(truth["image_stamps"]):
        # The recorder's clock (rec) runs on; a jumped stamp is the header's (a restarted sim clock).
        s = rec - 5 * 10**9 if cfg.clock_jump_at and i >= cfg.clock_jump_at else rec
        rgb = np.asarray(Image.open(render / "images" / f"{i:04d}.png").convert("RGB"))
        if cfg.blur_every and i % cfg.blur_every == cfg.blur_every - 1:
            rgb = _box_blur(rgb, 9)
        if cfg.transport in ("raw", "both"):
            raw = rgb[..., ::-1] if cfg.encoding == "bgr8" else rgb
            img = Img(header(s, opt), H, W, cfg.encoding, 0, 3 * W, np.ascontiguousarray(raw).ravel())
            msgs.append((rec, "/camera/color/image_raw", img))
        if cfg.transport in ("compressed", "both"):
            buf = io.BytesIO()
            Image.fromarray(rgb).save(buf, format="PNG")
            data = np.frombuffer(buf.getvalue(), np.uint8)
            img = CImg(header(s, opt), "rgb8; png compressed rgb8", data)
            msgs.append((rec, "/camera/color/image_raw/compressed", img))
        if cfg.camera_info:
            msgs.append((rec, "/camera/color/camera_info", info(s, opt)))
        if cfg.depth:
            d = np.load(drender / "depth" / f"{i:04d}.npy", allow_pickle=False).astype(np.float32)
            dh, dw = d.shape
            img = Img(header(s, dframe), dh, dw, "32FC1", 0, 4 * dw, d.view(np.uint8).ravel())
            msgs.append((rec, "/camera/depth/image_raw", img))
            msgs.append((rec, "/camera/depth/camera_info", info(s, dframe, dmeta)))
        shutil.copy(render / "labels" / f"{i:04d}.png", out / "labels" / f"{i:06d}.png")
    msgs.sort(key=lambda m: m[0])
    with Writer(bag, version=9, storage_plugin=plugin) as w:
        cons = {}
        for s, topic, msg in msgs:
            if topic not in cons:
                cons[topic] = w.add_connection(topic, msg.__msgtype__, typestore=ts)
            w.write(cons[topic], s, ts.serialize_cdr(msg, msg.__msgtype__))
    scene = json.loads((render / "scene.json").read_text())
    for v in scene["views"]:  # named as an import names its frames: by message index
        v["file_path"] = f"images/{int(Path(v['file_path']).stem):06d}.png"
    with atomic_path(out / "scene.json") as tmp:
        tmp.write_text(json.dumps(scene, indent=1))
    with atomic_path(out / "truth.json") as tmp:
        tmp.write_text(json.dumps({**truth, "config": asdict(cfg)}))
    return bag
