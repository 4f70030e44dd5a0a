"""A robot's ROS 2 (or ROS 1) recording as a posed dataset in the recording's fixed frame, read with
``rosbags`` (no ROS install).

``import_recording`` picks the camera topic and its CameraInfo, takes each image's pose from tf (the
fixed frame, ``map`` else ``odom``, to the image's ``frame_id``; fmgs.data.tf), keeps keyframes by motion
and sharpness up to a cap, back-projects a matching depth topic into sparse points, and writes a
transforms.json dataset (fmgs.data.transforms) whose coordinates are the fixed frame's, in metres.
Without usable tf it writes the keyframes alone, for structure from motion.

Conventions handled here: the optical frame of REP 103 (z forward, x right, y down) is our camera's
(OpenCV axes); CameraInfo's principal point counts the top-left pixel's centre as (0, 0), ours as
(0.5, 0.5).
"""

from __future__ import annotations

import io
import json
import logging
import shutil
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from fmgs.data.rosbag_config import RecordingConfig
from fmgs.data.tf import CLOCK_JUMP_S, NotAPose, TfTree, stamp_text
from fmgs.errors import ValidationError
from fmgs.io.atomic import atomic_path
from fmgs.io.points import write_point_ply

log = logging.getLogger(__name__)

RECORDING_SUFFIXES = (".mcap", ".db3", ".bag")
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
"""16UC1/mono16 depth is in millimetres, 32FC1 in metres (REP 118)."""
FIXED_FRAMES = ("map", "odom")
DEPTH_MATCH_S = 0.02
"""A depth image pairs with the colour image nearest in stamp, at most this far."""
IMPORT_RECORD = "recording.json"
"""What an import read, kept and dropped, written last in the dataset folder (its completion mark)."""


def _storage_files(folder: Path) -> list[Path]:
    return sorted(q for q in folder.iterdir() if q.is_file() and q.suffix in (".mcap", ".db3"))


def is_recording(path: str | Path) -> bool:
    """A rosbag2 folder (metadata.yaml, or .mcap/.db3 files left without it by a recorder that was
    stopped before writing it), or one .mcap, .db3 or ROS 1 .bag file."""
    p = Path(path)
    return (p.is_dir() and ((p / "metadata.yaml").is_file() or bool(_storage_files(p)))) or (
        p.is_file() and p.suffix in RECORDING_SUFFIXES
    )


@contextmanager
def open_recording(path: str | Path) -> Iterator:
    """rosbags' AnyReader over the recording; a truncated, unindexed or unreadable one is a
    ValidationError naming the file and the repair."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    p = Path(path)
    if not p.exists():
        raise ValidationError(str(p), "no such recording")
    if p.is_dir() and not (p / "metadata.yaml").is_file():  # a recorder stopped before writing it
        files = _storage_files(p)
        if len(files) != 1:
            raise ValidationError(
                str(p),
                f"has no metadata.yaml and {len(files)} storage files ({', '.join(f.name for f in files)}); "
                "`ros2 bag reindex` writes it, or pass one file",
            )
        p = files[0]
    try:
        reader = AnyReader([p], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as e:  # rosbags raises its own errors and struct/yaml errors on damaged files
        raise ValidationError(
            str(p),
            f"cannot read the recording ({type(e).__name__}: {e}); a recording cut short loses its index: "
            "`ros2 bag reindex` repairs a rosbag2 folder, `mcap recover` an .mcap file",
        ) from e
    try:
        yield reader
    finally:
        reader.close()


def _stamp(msg, fallback_ns: int) -> int:
    s = msg.header.stamp
    ns = int(s.sec) * 1_000_000_000 + int(s.nanosec)
    return ns if ns > 0 else fallback_ns


@dataclass
class TopicInfo:
    topic: str
    msgtype: str
    count: int


@dataclass
class RecordingInfo:
    """What a recording holds (``fmgs bag-info``)."""

    path: str
    topics: list[TopicInfo]
    duration_s: float
    tf_frames: list[str]
    colour_topics: list[str]
    depth_topics: list[str]

    def lines(self) -> list[str]:
        out = [f"{self.path}: {self.duration_s:.1f} s, {len(self.topics)} topics"]
        out += [f"  {t.topic:<48} {t.msgtype:<34} {t.count:>7}" for t in self.topics]
        out.append(f"colour cameras: {', '.join(self.colour_topics) or 'none'}")
        out.append(f"depth: {', '.join(self.depth_topics) or 'none'}")
        out.append(f"tf frames: {', '.join(self.tf_frames) or 'none'}")
        return out


def _is_depth_topic(reader, con) -> bool:
    """Depth by its encoding (the first message), or compressedDepth transport."""
    if con.msgtype == "sensor_msgs/msg/CompressedImage":
        return con.topic.endswith("compressedDepth")
    for c, _t, raw in _messages(reader, [con]):
        return reader.deserialize(raw, c.msgtype).encoding in DEPTH_ENCODINGS
    return False


def _camera_topics(reader) -> tuple[list[str], list[str]]:
    """(colour topics, depth topics); a raw topic's own /compressed twin is not listed twice."""
    colour, depth = [], []
    for con in reader.connections:
        if con.msgtype not in IMAGE_TYPES or con.msgcount == 0:
            continue
        (depth if _is_depth_topic(reader, con) else colour).append(con.topic)
    colour = sorted(set(colour))
    colour = [t for t in colour if not (t.endswith("/compressed") and t[: -len("/compressed")] in colour)]
    return colour, sorted(set(depth))


def recording_info(path: str | Path) -> RecordingInfo:
    with open_recording(path) as r:
        topics = [TopicInfo(c.topic, c.msgtype, c.msgcount) for c in r.connections]
        colour, depth = _camera_topics(r)
        tree = _load_tf(r, TfTree())
        dur = (r.end_time - r.start_time) / 1e9 if r.message_count else 0.0
    return RecordingInfo(
        str(path), sorted(topics, key=lambda t: t.topic), dur, sorted(tree.frames), colour, depth
    )


def _messages(reader, cons: list) -> Iterator:
    """(connection, timestamp, bytes) of these connections only (rosbags reads every topic for [])."""
    return reader.messages(connections=cons) if cons else iter(())


def _load_tf(reader, tree: TfTree) -> TfTree:
    """The recording's /tf and /tf_static in ``tree``; samples that are not a pose are skipped and
    counted (``tree.skipped``), with one warning naming the first, as tf2 drops them."""
    first = ""
    for con, t, raw in _messages(reader, [c for c in reader.connections if c.msgtype == TF_TYPE]):
        msg = reader.deserialize(raw, con.msgtype)
        static = con.topic.endswith("tf_static")
        for tr in msg.transforms:
            q, v = tr.transform.rotation, tr.transform.translation
            try:
                tree.add(
                    tr.header.frame_id, tr.child_frame_id, _stamp(tr, t), (q.x, q.y, q.z, q.w),
                    (v.x, v.y, v.z), static, con.topic,
                )  # fmt: skip
            except NotAPose as e:
                tree.skipped += 1
                first = first or str(e)
    if tree.skipped:
        log.warning(
            "skipped %d tf samples that are not poses, as tf2 does (the first: %s)", tree.skipped, first
        )
    return tree


# ---------------------------------------------------------------------------------------------- images


def _at(msg) -> str:
    """The message's header stamp as ' at TIME', or '' where it has none."""
    ns = _stamp(msg, 0)
    return f" at {stamp_text(ns)}" if ns else ""


def decode_colour(msg, msgtype: str, topic: str) -> np.ndarray:
    """[H,W,3] uint8 RGB of an Image or CompressedImage message."""
    from PIL import Image

    if msgtype == "sensor_msgs/msg/CompressedImage":
        try:
            return np.asarray(Image.open(io.BytesIO(bytes(msg.data))).convert("RGB"))
        except Exception as e:
            raise ValidationError(
                topic, f"cannot decode the compressed image{_at(msg)} ({msg.format!r}: {e})"
            ) from e
    enc = msg.encoding
    if enc not in COLOUR_ENCODINGS:
        raise ValidationError(
            topic,
            f"unsupported image encoding {enc!r}; colour images must be one of {', '.join(COLOUR_ENCODINGS)}",
        )
    ch = {"mono8": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}[enc]
    a = _rows(msg, ch, np.uint8, topic)
    if enc == "mono8":
        return np.repeat(a, 3, axis=2)
    rgb = a[..., :3]
    return np.ascontiguousarray(rgb[..., ::-1] if enc.startswith("bgr") else rgb)


def decode_depth(msg, msgtype: str, topic: str) -> np.ndarray:
    """[H,W] float64 depth in metres (0 where unknown) of a depth Image."""
    if msgtype != "sensor_msgs/msg/Image" or msg.encoding not in DEPTH_ENCODINGS:
        what = msg.format if msgtype.endswith("CompressedImage") else msg.encoding
        raise ValidationError(
            topic,
            f"unsupported depth {what!r}; depth must be a raw Image in {', '.join(DEPTH_ENCODINGS)} "
            "(--depth-topic none builds without it)",
        )
    if msg.encoding == "32FC1":
        d = _rows(msg, 1, np.float32, topic)[..., 0].astype(np.float64)
    else:
        d = _rows(msg, 1, np.uint16, topic)[..., 0].astype(np.float64) / 1000.0
    return np.where(np.isfinite(d) & (d > 0), d, 0.0)


def _rows(msg, ch: int, dtype, topic: str) -> np.ndarray:
    """[H,W,ch] of a raw Image's bytes, honouring its row step and byte order."""
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * ch * dt.itemsize
    data = np.asarray(msg.data, np.uint8)
    if step < row or len(data) < h * step:
        raise ValidationError(
            topic, f"image{_at(msg)} of {w}x{h} {msg.encoding} has {len(data)} bytes, step {step}"
        )
    a = data[: h * step].reshape(h, step)[:, :row]
    return np.ascontiguousarray(a).view(dt).reshape(h, w, ch).astype(dtype)


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (higher: sharper)."""
    g = rgb.astype(np.float64).mean(axis=2)
    lap = g[1:-1, :-2] + g[1:-1, 2:] + g[:-2, 1:-1] + g[2:, 1:-1] - 4 * g[1:-1, 1:-1]
    return float(lap.var()) if lap.size else 0.0


# ---------------------------------------------------------------------------------------------- cameras


@dataclass(frozen=True)
class Lens:
    """A CameraInfo in our conventions: transforms.json keys (principal point with pixel centres at +0.5)."""

    width: int
    height: int
    keys: dict

    @property
    def K(self) -> np.ndarray:
        k = self.keys
        return np.array([[k["fl_x"], 0, k["cx"]], [0, k["fl_y"], k["cy"]], [0, 0, 1.0]])


def lens_from_info(info, topic: str) -> Lens:
    """transforms.json camera keys of a CameraInfo: K shifted by half a pixel (ROS counts the top-left
    pixel's centre as (0, 0), we as (0.5, 0.5)); plumb_bob and rational_polynomial (k4-k6 zero) as OPENCV,
    equidistant as OPENCV_FISHEYE."""
    ros1 = not hasattr(info, "k")  # ROS 1's CameraInfo names its arrays K and D
    K = np.asarray(info.K if ros1 else info.k, np.float64).reshape(3, 3)
    d = [float(x) for x in (info.D if ros1 else info.d)]
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or info.width <= 0 or info.height <= 0:
        raise ValidationError(
            topic, f"CameraInfo has no usable K or size (K={K.tolist()}, {info.width}x{info.height})"
        )
    if not np.all(np.isfinite(d)):
        raise ValidationError(topic, f"CameraInfo's distortion D={d} is not finite")
    keys = {
        "w": int(info.width), "h": int(info.height), "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
        "cx": float(K[0, 2]) + 0.5, "cy": float(K[1, 2]) + 0.5,
    }  # fmt: skip
    model = info.distortion_model
    if not any(d):
        keys["camera_model"] = "PINHOLE"
    elif model in ("plumb_bob", "rational_polynomial"):
        d = d + [0.0] * (8 - len(d))
        if any(d[5:8]):
            raise ValidationError(
                topic, f"{model} distortion with k4-k6 {d[5:8]} is not supported (OPENCV: k1 k2 p1 p2 k3)"
            )
        keys.update(camera_model="OPENCV", k1=d[0], k2=d[1], p1=d[2], p2=d[3], k3=d[4])
    elif model == "equidistant":
        d = d + [0.0] * (4 - len(d))
        keys.update(camera_model="OPENCV_FISHEYE", k1=d[0], k2=d[1], k3=d[2], k4=d[3])
    else:
        raise ValidationError(
            topic, f"unsupported distortion model {model!r} (plumb_bob, rational_polynomial, equidistant)"
        )
    return Lens(int(info.width), int(info.height), keys)


def _info_topic_for(image_topic: str) -> str:
    base = image_topic
    for suffix in ("/compressed", "/compressedDepth"):
        if base.endswith(suffix):
            base = base[: -len(suffix)]
    return base.rsplit("/", 1)[0] + "/camera_info"


def _first_info(reader, topic: str):
    cons = [c for c in reader.connections if c.topic == topic and c.msgtype == INFO_TYPE]
    for con, _t, raw in _messages(reader, cons):
        return reader.deserialize(raw, con.msgtype)
    return None


# ---------------------------------------------------------------------------------------------- import


@dataclass
class ImportResult:
    """What ``import_recording`` wrote and why frames were dropped."""

    dataset: str
    """The folder written: transforms.json (posed) or images/ alone (for SfM)."""
    posed: bool
    """True: poses from tf in ``fixed_frame``; False: no usable tf, the frames go to SfM."""
    image_topic: str
    camera_frame: str
    fixed_frame: str
    read: int
    kept: int
    dropped: dict[str, int] = field(default_factory=dict)
    """Reasons: no_tf (before or after the transforms), tf_gap, still (moved too little), blurred, cap."""
    depth_topic: str = ""
    depth_points: int = 0
    camera_info_topic: str = ""
    unposed_why: str = ""
    """Why the frames go to SfM (not posed): what the recording's tf lacks."""
    tf_skipped: int = 0
    """tf samples skipped as not a pose (NaN, infinite, a zero quaternion), as tf2 skips them."""

    def line(self) -> str:
        why = ", ".join(f"{k} {v}" for k, v in sorted(self.dropped.items()) if v) or "none"
        where = f"poses from tf in frame {self.fixed_frame!r}" if self.posed else "no usable tf: poses by SfM"
        if not self.posed and self.unposed_why:
            where += f" ({self.unposed_why})"
        pts = f"; {self.depth_points:,} points from {self.depth_topic}" if self.depth_topic else ""
        bad = f"; {self.tf_skipped} tf samples skipped (not poses)" if self.tf_skipped else ""
        return f"{self.image_topic}: read {self.read}, kept {self.kept} (dropped: {why}); {where}{pts}{bad}"


def _pick(topic: str, have: list[str], what: str, flag: str, all_topics: list[str]) -> str:
    if topic:
        if topic not in all_topics:
            raise ValidationError(
                flag, f"no topic {topic!r} in the recording; {what} topics: {', '.join(have) or 'none'}"
            )
        return topic
    if len(have) == 1:
        return have[0]
    if not have:
        raise ValidationError(
            flag, f"the recording has no {what} topic (image topics are sensor_msgs Image or CompressedImage)"
        )
    raise ValidationError(
        flag, f"the recording has {len(have)} {what} topics ({', '.join(have)}); choose one with {flag}"
    )


def _require_images(reader, topic: str, flag: str) -> None:
    """ValidationError naming a chosen topic that holds something other than images."""
    other = sorted({c.msgtype for c in reader.connections if c.topic == topic} - set(IMAGE_TYPES))
    if other:
        raise ValidationError(
            flag, f"{topic} holds {', '.join(other)}, not images (sensor_msgs Image or CompressedImage)"
        )


def _check_frame(tree: TfTree, fixed: str, frame: str, topic: str, what: str, stamp_ns: int, hint: str = ""):
    """ValidationError naming the message (topic, time, frame) whose frame tf does not join to ``fixed``."""
    try:
        tree.check_connected(fixed, frame)
    except ValidationError as e:
        raise ValidationError(
            topic, f"{what} at {stamp_text(stamp_ns)} is in frame {frame!r}: {e.reason}{hint}"
        ) from e


def _moved(T: np.ndarray, last: np.ndarray, cfg: RecordingConfig) -> bool:
    d = np.linalg.norm(T[:3, 3] - last[:3, 3])
    c = np.clip((np.trace(last[:3, :3].T @ T[:3, :3]) - 1) / 2, -1.0, 1.0)
    return d >= cfg.min_translation or np.degrees(np.arccos(c)) >= cfg.min_rotation_deg


def _even(idx: list[int], n: int) -> list[int]:
    if len(idx) <= n:
        return idx
    return [idx[i] for i in np.round(np.linspace(0, len(idx) - 1, n)).astype(int)]


def source_fingerprint(path: str | Path) -> str:
    """Size and modification time of the recording's files: an import is redone when they change."""
    p = Path(path)
    files = sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else [p]
    return ";".join(f"{q.name}:{q.stat().st_size}:{q.stat().st_mtime_ns}" for q in files)


def completed_import(out: str | Path, cfg: RecordingConfig, fingerprint: str) -> ImportResult | None:
    """The result of an earlier import into ``out`` with the same settings of the same files, else None."""
    try:
        rec = json.loads((Path(out) / IMPORT_RECORD).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if rec.get("config") != asdict(cfg) or rec.get("fingerprint") != fingerprint:
        return None
    return ImportResult(**rec["result"])


def import_recording(
    path: str | Path, out: str | Path, cfg: RecordingConfig | None = None, fingerprint: str = ""
) -> ImportResult:
    """Write the recording's keyframes as a dataset in ``out`` (replaced; written aside and renamed
    once complete); see the module docstring. ``fingerprint`` (source_fingerprint) is recorded for
    completed_import."""
    cfg = cfg or RecordingConfig()
    final = Path(out)
    part = final.with_name(final.name + ".partial")  # renamed once complete: nothing half-written
    if part.exists():
        shutil.rmtree(part)
    try:
        res = _import(path, part, final, cfg, fingerprint)
    except BaseException:
        shutil.rmtree(part, ignore_errors=True)
        raise
    if final.exists():
        shutil.rmtree(final)
    part.rename(final)
    return res


def _import(path, out: Path, final: Path, cfg: RecordingConfig, fingerprint: str) -> ImportResult:
    from PIL import Image

    with open_recording(path) as r:
        names = sorted({c.topic for c in r.connections})
        colour, depth_topics = _camera_topics(r)
        topic = _pick(cfg.image_topic, colour, "colour camera", "--image-topic", names)
        _require_images(r, topic, "--image-topic")
        info_topic = cfg.camera_info_topic or _info_topic_for(topic)
        info = _first_info(r, info_topic)
        if info is None:
            infos = sorted({c.topic for c in r.connections if c.msgtype == INFO_TYPE})
            raise ValidationError(
                "--camera-info-topic",
                f"no CameraInfo for {topic} on {info_topic}; CameraInfo topics: {', '.join(infos) or 'none'} "
                "(a camera without its calibration cannot be posed)",
            )
        lens = lens_from_info(info, info_topic)
        depth_topic = "" if cfg.depth_topic == "none" else cfg.depth_topic
        if cfg.depth_topic == "" and len(depth_topics) == 1:
            depth_topic = depth_topics[0]
        elif depth_topic and depth_topic not in names:
            raise ValidationError(
                "--depth-topic",
                f"no topic {depth_topic!r}; depth topics: {', '.join(depth_topics) or 'none'}",
            )
        if depth_topic:
            _require_images(r, depth_topic, "--depth-topic")

        # Image stamps and frames first (messages are read again for the kept ones only).
        cons = [c for c in r.connections if c.topic == topic]
        msgtype = cons[0].msgtype
        stamps, frame_ids, last = [], [], None
        for con, t, raw in _messages(r, cons):
            msg = r.deserialize(raw, con.msgtype)
            s = _stamp(msg, t)
            if last is not None and s < last - CLOCK_JUMP_S * 1e9:
                raise ValidationError(
                    topic,
                    f"image stamps go back {(last - s) / 1e9:.1f} s (clock jump: a restarted simulation or a "
                    "looped playback); record once, or cut the recording before the jump",
                )
            last = s
            stamps.append(s)
            frame_ids.append(msg.header.frame_id.lstrip("/"))
        if not stamps:
            raise ValidationError(topic, "holds no images")
        tree = _load_tf(r, TfTree(cfg.max_tf_gap_s))
        cam_frame = frame_ids[0]
        fixed = cfg.fixed_frame.lstrip("/") or next((f for f in FIXED_FRAMES if f in tree.frames), "")
        dropped: Counter[str] = Counter()
        posed = bool(fixed) and cam_frame in tree.frames
        if cfg.fixed_frame and not posed:
            tree.check_connected(fixed, cam_frame)  # names what is missing
        if posed:  # every frame the images name, the first time each appears
            for f in dict.fromkeys(frame_ids):
                _check_frame(tree, fixed, f, topic, "the image", stamps[frame_ids.index(f)])
        poses: list[np.ndarray | None] = []
        for s, f in zip(stamps, frame_ids, strict=True):
            if not posed:
                poses.append(None)
                continue
            T, why = tree.lookup(fixed, f, s)
            if T is None:
                dropped["no_tf" if why == "outside" else "tf_gap"] += 1
            poses.append(T)
        if posed and not any(p is not None for p in poses):
            raise ValidationError(
                "tf", f"no image of {topic} has a pose: every stamp lies outside or in a gap of the tf from "
                f"{fixed!r} to {cam_frame!r}",
            )  # fmt: skip

        # Keyframes by motion (posed), then sharpness, then the cap.
        cand, last_T = [], None
        for i, T in enumerate(poses):
            if posed and T is None:
                continue
            if posed and last_T is not None and not _moved(T, last_T, cfg):
                dropped["still"] += 1
                continue
            cand.append(i)
            if posed:
                last_T = T
        (out / "images").mkdir(parents=True)
        sharp: dict[int, float] = {}
        want = set(cand)
        for k, (con, _t, raw) in enumerate(_messages(r, cons)):
            if k not in want:
                continue
            rgb = decode_colour(r.deserialize(raw, con.msgtype), msgtype, topic)
            if rgb.shape[:2] != (lens.height, lens.width):
                raise ValidationError(
                    topic,
                    f"images are {rgb.shape[1]}x{rgb.shape[0]}, CameraInfo says {lens.width}x{lens.height}",
                )
            sharp[k] = sharpness(rgb)
            Image.fromarray(rgb).save(out / "images" / f"{k:06d}.png")
        kept = list(cand)
        if cfg.blur_ratio > 0 and len(kept) > 2:
            vals = np.array([sharp[k] for k in kept])
            keep = []
            for j, k in enumerate(kept):
                near = vals[max(0, j - 5) : j + 6]
                if sharp[k] >= cfg.blur_ratio * float(np.median(near)):
                    keep.append(k)
                else:
                    dropped["blurred"] += 1
            kept = keep
        capped = _even(kept, cfg.max_frames)
        dropped["cap"] += len(kept) - len(capped)
        for k in set(cand) - set(capped):
            (out / "images" / f"{k:06d}.png").unlink()
        kept = capped

        res = ImportResult(
            str(final), posed, topic, cam_frame, fixed if posed else "", len(stamps), len(kept),
            {k: v for k, v in dropped.items() if v}, camera_info_topic=info_topic, tf_skipped=tree.skipped,
        )  # fmt: skip
        if not posed:
            frames = ", ".join(sorted(tree.frames))
            if not tree.frames:
                res.unposed_why = "the recording has no tf"
            elif not fixed:
                res.unposed_why = f"no frame map or odom in tf ({frames}); name one with --fixed-frame"
            else:
                res.unposed_why = f"the camera's frame {cam_frame!r} is not in tf ({frames})"
        if posed:
            meta = {**lens.keys, "frames": []}
            for k in kept:
                c2w = poses[k] @ np.diag([1.0, -1.0, -1.0, 1.0])  # optical (OpenCV) axes to OpenGL's
                meta["frames"].append(
                    {
                        "file_path": f"images/{k:06d}.png",
                        "transform_matrix": c2w.tolist(),
                        "stamp_ns": stamps[k],
                    }
                )
            if depth_topic:
                pts, cols = _depth_points(r, depth_topic, tree, fixed, kept, stamps, poses, out, lens, cfg)
                if len(pts):
                    write_point_ply(out / "points3D.ply", pts, cols)
                    meta["ply_file_path"] = "points3D.ply"
                res.depth_topic, res.depth_points = depth_topic, len(pts)
            meta["fmgs_frame"] = {"id": fixed, "units": "m", "camera_frame": cam_frame}
            with atomic_path(out / "transforms.json") as tmp:
                tmp.write_text(json.dumps(meta, indent=1))
    with atomic_path(out / IMPORT_RECORD) as tmp:
        record = {"result": asdict(res), "config": asdict(cfg), "fingerprint": fingerprint}
        tmp.write_text(json.dumps(record, indent=1))
    return res


def _depth_points(r, topic, tree, fixed, kept, stamps, poses, out: Path, lens: Lens, cfg: RecordingConfig):
    """Sparse points [P,3] in the fixed frame with colours [P,3] uint8 from the depth images nearest the
    kept frames' stamps (within DEPTH_MATCH_S): each back-projected with its own CameraInfo and posed by
    tf at its own stamp (registered depth shares the colour camera's frame; unregistered has its own),
    coloured by projecting into the colour image (pixels it does not see are grey)."""
    from PIL import Image

    from fmgs.data.distortion import OpenCVDistortion

    cons = [c for c in r.connections if c.topic == topic]
    info = _first_info(r, _info_topic_for(topic))
    dstamps = []
    for con, t, raw in _messages(r, cons):
        dstamps.append(_stamp(r.deserialize(raw, con.msgtype), t))
    dstamps_a = np.asarray(dstamps, np.int64)
    pair = {}
    for k in kept:
        if not len(dstamps_a):
            break
        j = int(np.argmin(np.abs(dstamps_a - stamps[k])))
        if abs(int(dstamps_a[j]) - stamps[k]) <= DEPTH_MATCH_S * 1e9:
            pair[j] = k
    if not pair:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    dlens = lens if info is None else lens_from_info(info, _info_topic_for(topic))
    per = max(1, cfg.max_depth_points // len(pair))
    stride = max(1, int(np.ceil(np.sqrt(dlens.width * dlens.height / per))))
    dist = OpenCVDistortion(*(lens.keys.get(k, 0.0) for k in ("k1", "k2", "p1", "p2")))
    pts_all, cols_all = [], []
    for j, (con, _t, raw) in enumerate(_messages(r, cons)):
        if j not in pair:
            continue
        k = pair[j]
        msg = r.deserialize(raw, con.msgtype)
        d = decode_depth(msg, con.msgtype, topic)
        if d.shape != (dlens.height, dlens.width):
            whose = f"its CameraInfo ({_info_topic_for(topic)})" if info is not None else (
                f"with no CameraInfo on {_info_topic_for(topic)}, the colour camera's"
            )  # fmt: skip
            raise ValidationError(
                topic,
                f"depth images are {d.shape[1]}x{d.shape[0]}; {whose} is {dlens.width}x{dlens.height}",
            )
        d = d[::stride, ::stride]
        vs, us = np.nonzero(d > 0)
        z = d[vs, us]
        K = dlens.K  # our convention: pixel (u, v)'s centre is at (u + 0.5, v + 0.5)
        x = ((us * stride + 0.5) - K[0, 2]) / K[0, 0] * z
        y = ((vs * stride + 0.5) - K[1, 2]) / K[1, 1] * z
        p_cam = np.stack([x, y, z], 1)
        frame = msg.header.frame_id.lstrip("/")
        hint = "; --depth-topic none builds without depth"
        _check_frame(tree, fixed, frame, topic, "the depth image", dstamps[j], hint)
        T, _ = tree.lookup(fixed, frame, dstamps[j])
        if T is None:
            continue
        pw = p_cam @ T[:3, :3].T + T[:3, 3]
        # Colour: project into the kept colour frame.
        Vc = np.linalg.inv(poses[k])
        pc = pw @ Vc[:3, :3].T + Vc[:3, 3]
        rgb = np.asarray(Image.open(out / "images" / f"{k:06d}.png").convert("RGB"))
        cols = np.full((len(pw), 3), 128, np.uint8)
        front = pc[:, 2] > 1e-9
        xn, yn = pc[front, 0] / pc[front, 2], pc[front, 1] / pc[front, 2]
        if lens.keys.get("camera_model") == "OPENCV":
            xn, yn = dist.distort(xn, yn)
        Kc = lens.K
        u = np.floor(Kc[0, 0] * xn + Kc[0, 2]).astype(np.int64)
        v = np.floor(Kc[1, 1] * yn + Kc[1, 2]).astype(np.int64)
        ok = (u >= 0) & (u < lens.width) & (v >= 0) & (v < lens.height)
        idx = np.flatnonzero(front)[ok]
        cols[idx] = rgb[v[ok], u[ok]]
        pts_all.append(pw)
        cols_all.append(cols)
    if not pts_all:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return np.concatenate(pts_all), np.concatenate(cols_all)
