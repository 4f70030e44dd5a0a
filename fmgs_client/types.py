"""What the client hands back: frozen dataclasses holding numpy arrays (no protobuf objects leak out).

Array-holding classes use ``eq=False`` (identity comparison): ``==`` on numpy arrays is elementwise, so
the generated field-by-field ``__eq__`` would raise instead of answering.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

_STATE_PREFIX = "SCENE_STATE_"


def require_finite(values: Any, what: str) -> np.ndarray:
    """``values`` as an array; ValueError naming ``what`` when a float among them is NaN or infinite
    (a malformed answer: nothing downstream should draw or write such a number)."""
    a = np.asarray(values)
    if a.dtype.kind in "fc":
        bad = a.size - int(np.count_nonzero(np.isfinite(a)))
        if bad:
            raise ValueError(f"{what}: {bad} of {a.size} values are NaN or infinite")
    return a


@dataclass(frozen=True, eq=False)
class SceneInfo:
    """A scene in the server's repository and, when loaded, what it holds."""

    name: str
    """Scene name (its folder in the repository)."""
    state: str
    """``"unloaded"``, ``"loading"``, ``"ready"``, ``"failed"`` (or ``"unspecified"``)."""
    reason: str
    """Why the scene is failed (empty otherwise)."""
    encoder_id: str
    """The text encoder the scene's embeddings live in."""
    embedding_dim: int
    """Size D of the embeddings."""
    num_gaussians: int
    """All Gaussians of the scene (as in its PLY)."""
    num_embedded: int
    """Gaussians that carry embeddings (the ones text queries rank)."""
    sh_degree: int
    """Spherical-harmonics degree of the colours."""
    has_field: bool
    """Whether point queries work (the package holds the feature field)."""
    canonical_phrases: tuple[str, ...]
    """The relevancy's canonical phrases."""
    label_names: tuple[str, ...]
    """Object names the scene was trained with (label-supervised scenes), else empty."""
    resident_bytes: int
    """Bytes the loaded scene holds in memory (0 when not loaded)."""
    version: str
    """Changes whenever the scene's files change."""
    bounds: np.ndarray | None
    """[2,3] float64 axis-aligned bounds of the means (row 0 min, row 1 max); None when not reported."""
    frame_id: str = ""
    """The frame every position is in, in metres (a robot's fixed frame, e.g. "map", for a scene built
    from its recording); "" when the scene's frame is its own."""

    @property
    def center(self) -> np.ndarray | None:
        """[3] centre of the bounds, or None."""
        return None if self.bounds is None else self.bounds.mean(0)

    @classmethod
    def from_proto(cls, m: pb.SceneInfo) -> SceneInfo:
        """Convert a wire ``SceneInfo``; ValueError when ``bounds`` is neither empty nor 6 numbers."""
        name = pb.SceneState.Name(m.state) if m.state in pb.SceneState.values() else str(m.state)
        state = name.removeprefix(_STATE_PREFIX).lower()
        if len(m.bounds) not in (0, 6):
            raise ValueError(f"SceneInfo.bounds: expected 6 numbers, got {len(m.bounds)}")
        bounds = require_finite(np.asarray(m.bounds, np.float64), "SceneInfo.bounds")
        bounds = bounds.reshape(2, 3) if len(m.bounds) else None
        return cls(
            name=m.name,
            state=state,
            reason=m.reason,
            encoder_id=m.encoder_id,
            embedding_dim=int(m.embedding_dim),
            num_gaussians=int(m.num_gaussians),
            num_embedded=int(m.num_embedded),
            sh_degree=int(m.sh_degree),
            has_field=bool(m.has_field),
            canonical_phrases=tuple(m.canonical_phrases),
            label_names=tuple(m.label_names),
            resident_bytes=int(m.resident_bytes),
            version=m.version,
            bounds=bounds,
            frame_id=m.frame_id,
        )


@dataclass(frozen=True, eq=False)
class Box:
    """An oriented box in world coordinates."""

    center: np.ndarray
    """[3] float64 centre."""
    extent: np.ndarray
    """[3] float64 full side lengths along the box axes."""
    rotation: np.ndarray
    """[3,3] float64 rotation whose columns are the box axes in world coordinates."""

    def corners(self) -> np.ndarray:
        """[8,3] corners; corner i has sign (-1)**bit for bits x=1, y=2, z=4 of i."""
        signs = np.array([[(1 if i & b else -1) for b in (1, 2, 4)] for i in range(8)], np.float64)
        return self.center + (signs * (self.extent / 2)) @ self.rotation.T

    @classmethod
    def from_proto(cls, m: pb.Box, what: str = "box") -> Box:
        """Convert a wire ``Box``; an empty rotation means axis-aligned (identity)."""
        if len(m.center) != 3 or len(m.extent) != 3 or len(m.rotation) not in (0, 9):
            raise ValueError(
                f"{what}: expected 3 centre, 3 extent and 9 (or 0) rotation numbers, got "
                f"{len(m.center)}, {len(m.extent)}, {len(m.rotation)}"
            )
        require_finite(np.asarray([*m.center, *m.extent, *m.rotation], np.float64), what)
        rot = np.asarray(m.rotation, np.float64).reshape(3, 3) if len(m.rotation) else np.eye(3)
        return cls(np.asarray(m.center, np.float64), np.asarray(m.extent, np.float64), rot)


@dataclass(frozen=True, eq=False)
class Instance:
    """One object instance: a cluster of relevant Gaussians."""

    id: int
    """Instance id (the value in ``TextAnswer.instance``)."""
    centroid: np.ndarray
    """[3] float64 relevancy- and opacity-weighted centroid of the members' means."""
    aabb: Box
    """Axis-aligned bounding box of the members."""
    obb: Box
    """Oriented bounding box of the members."""
    score: float
    """Mean relevancy of the members."""
    num_members: int
    """How many Gaussians belong to the instance."""

    @classmethod
    def from_proto(cls, m: pb.Instance) -> Instance:
        """Convert a wire ``Instance``."""
        if len(m.centroid) != 3:
            raise ValueError(f"Instance {m.id}.centroid: expected 3 numbers, got {len(m.centroid)}")
        require_finite(np.asarray(m.score, np.float64), f"Instance {m.id}.score")
        return cls(
            id=int(m.id),
            centroid=require_finite(np.asarray(m.centroid, np.float64), f"Instance {m.id}.centroid"),
            aabb=Box.from_proto(m.aabb, f"Instance {m.id}.aabb"),
            obb=Box.from_proto(m.obb, f"Instance {m.id}.obb"),
            score=float(m.score),
            num_members=int(m.num_members),
        )


@dataclass(frozen=True)
class Presence:
    """Is the queried thing in the scene? (server-side: fmgs.query.presence)"""

    score: float
    """In [0,1]: sigmoid(10 * margin)."""
    found: bool
    """False is the "not found" answer: the mean embedding of the query's best Gaussians (10 by default)
    fits some name the query does not mean (``rival``) better than the query (server rule "each": the
    quorum-th best Gaussian does)."""
    margin: float
    """mean f.q - max mean f.n over those Gaussians (rule "each": the quorum-th best f.q - max f.n)."""
    rival: str
    """The name that decided the margin (what the scene has there instead)."""

    @classmethod
    def from_proto(cls, m: pb.Presence) -> Presence:
        """Convert a wire ``Presence``; a score outside [0,1] or a non-finite margin is refused."""
        if not (0.0 <= m.score <= 1.0) or not math.isfinite(m.margin):
            raise ValueError(f"presence: score {m.score} must lie in [0,1] and margin {m.margin} be finite")
        return cls(float(m.score), bool(m.found), float(m.margin), str(m.rival))


@dataclass(frozen=True, eq=False)
class TextAnswer:
    """The answer to one text: K Gaussians, most relevant first, and optional per-Gaussian arrays.

    The optional arrays are None unless their field was asked for (``query(fields=...)``).
    """

    text: str
    """The text this answers."""
    index: np.ndarray
    """[K] int64 Gaussian indices into the scene (all Gaussians, as in its PLY)."""
    relevancy: np.ndarray
    """[K] float32 relevancy in (0,1), descending."""
    similarity: np.ndarray | None = None
    """[K] float32 cosine similarity of the embedding with the query."""
    mean: np.ndarray | None = None
    """[K,3] float32 means."""
    opacity: np.ndarray | None = None
    """[K] float32 opacity in [0,1]."""
    scale: np.ndarray | None = None
    """[K,3] float32 activated scales (scene units)."""
    rotation: np.ndarray | None = None
    """[K,4] float32 unit quaternions, wxyz."""
    color: np.ndarray | None = None
    """[K,3] float32 base colour in [0,1]."""
    instance: np.ndarray | None = None
    """[K] int32 instance id of each Gaussian, -1 for none."""
    instances: tuple[Instance, ...] = ()
    """Object instances, best first (when asked for)."""
    elapsed_ms: float = 0.0
    """Server-side time spent on this text, milliseconds."""
    rescored: int = 0
    """Gaussians the server scored exactly to certify that this is the exact top-k (0 from servers that
    do not report it)."""
    presence: Presence | None = None
    """Whether the queried thing is in the scene (None when the server does not say: older servers, or
    its text encoder is not available there)."""

    @property
    def found(self) -> bool | None:
        """``presence.found``, or None when the server did not say."""
        return None if self.presence is None else self.presence.found

    def __len__(self) -> int:
        return len(self.index)


@dataclass(frozen=True, eq=False)
class CameraSpec:
    """A pinhole camera: OpenCV axes (x right, y down, z forward), pixel centres at (j + 0.5, i + 0.5)."""

    viewmat: np.ndarray
    """[4,4] float64 world-to-camera rigid transform."""
    fx: float
    """Focal length along x, pixels."""
    fy: float
    """Focal length along y, pixels."""
    cx: float
    """Principal point x, pixels."""
    cy: float
    """Principal point y, pixels."""
    width: int
    """Image width W, pixels."""
    height: int
    """Image height H, pixels."""
    near: float = 0.0
    """Near plane (0: the server's default, 0.01 scene units)."""

    def __post_init__(self) -> None:
        vm = np.asarray(self.viewmat, np.float64)
        if vm.shape != (4, 4) or not np.all(np.isfinite(vm)):
            raise ValueError(f"CameraSpec.viewmat: expected a finite [4,4] matrix, got shape {vm.shape}")
        object.__setattr__(self, "viewmat", vm)

    @classmethod
    def look_at(
        cls,
        eye: Sequence[float],
        target: Sequence[float],
        up: Sequence[float] = (0.0, 0.0, 1.0),
        width: int = 640,
        height: int = 480,
        fov_deg: float = 60.0,
    ) -> CameraSpec:
        """A camera at ``eye`` looking at ``target`` with ``up`` pointing up in the image.

        ``fov_deg`` is the horizontal field of view; pixels are square and the principal point is the
        image centre (W/2, H/2), so ``target`` projects onto the middle of the image. When ``up`` is
        (nearly) parallel to the viewing direction another world axis stands in for it.
        """
        eye = np.asarray(eye, np.float64)
        fwd = np.asarray(target, np.float64) - eye
        n = np.linalg.norm(fwd)
        if not np.isfinite(n) or n == 0:
            raise ValueError("look_at: eye and target must be distinct finite points")
        fwd = fwd / n
        up_v = np.asarray(up, np.float64)
        if up_v.shape != (3,) or not np.all(np.isfinite(up_v)):
            raise ValueError(f"look_at: up must be 3 finite numbers, got {up_v.tolist()}")
        right = np.cross(fwd, up_v)
        if np.linalg.norm(right) < 1e-9 * max(1.0, np.linalg.norm(up_v)):
            # Looking straight along up: any perpendicular axis will do; pick the least aligned one.
            alt = np.eye(3)[np.argmin(np.abs(fwd))]
            right = np.cross(fwd, alt)
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)  # OpenCV y points down the image
        R = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
        vm = np.eye(4)
        vm[:3, :3] = R
        vm[:3, 3] = -R @ eye
        if not 0 < fov_deg < 180 or width < 1 or height < 1:
            raise ValueError(
                f"look_at: need 0 < fov_deg < 180 and a positive size, got {fov_deg}, {width}x{height}"
            )
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
        return cls(vm, f, f, width / 2, height / 2, int(width), int(height))

    @property
    def K(self) -> np.ndarray:
        """[3,3] intrinsics."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def eye(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates [N,2] (x, y; pixel centres at +0.5) and depth [N] of world points [N,3]."""
        p = np.asarray(points, np.float64) @ self.viewmat[:3, :3].T + self.viewmat[:3, 3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy], -1)
        return uv, z

    def to_proto(self) -> pb.Camera:
        """The wire ``Camera`` (viewmat row-major)."""
        return pb.Camera(
            viewmat=[float(v) for v in self.viewmat.reshape(-1)],
            fx=float(self.fx),
            fy=float(self.fy),
            cx=float(self.cx),
            cy=float(self.cy),
            width=int(self.width),
            height=int(self.height),
            near=float(self.near),
        )

    def to_dict(self) -> dict:
        """JSON-ready: ``viewmat`` (4 rows of 4, world-to-camera, OpenCV axes), intrinsics in pixels,
        ``width``, ``height``, ``near`` (what ``fmgs-client render --camera FILE`` reads)."""
        return {
            "viewmat": self.viewmat.tolist(),
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "width": int(self.width),
            "height": int(self.height),
            "near": float(self.near),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CameraSpec:
        """The inverse of :meth:`to_dict`; ValueError naming what is missing or wrong."""
        if not isinstance(d, Mapping):
            raise ValueError(f"camera: expected a JSON object, got {type(d).__name__}")
        missing = [k for k in ("viewmat", "fx", "fy", "cx", "cy", "width", "height") if k not in d]
        if missing:
            raise ValueError(f"camera: missing {', '.join(missing)}")
        try:
            vm = np.asarray(d["viewmat"], np.float64).reshape(4, 4)
            nums = [float(d[k]) for k in ("fx", "fy", "cx", "cy")]
            w, h = int(d["width"]), int(d["height"])
            near = float(d.get("near", 0.0))
        except (TypeError, ValueError) as e:
            raise ValueError(f"camera: {e}") from None
        if not all(math.isfinite(v) for v in nums) or nums[0] <= 0 or nums[1] <= 0 or w < 1 or h < 1:
            raise ValueError("camera: fx, fy must be positive and finite, width and height at least 1")
        return cls(vm, *nums, w, h, near)

    @classmethod
    def from_proto(cls, m: pb.Camera) -> CameraSpec:
        """Convert a wire ``Camera``."""
        if len(m.viewmat) != 16:
            raise ValueError(f"Camera.viewmat: expected 16 numbers, got {len(m.viewmat)}")
        return cls(
            np.asarray(m.viewmat, np.float64).reshape(4, 4), m.fx, m.fy, m.cx, m.cy, m.width, m.height, m.near
        )


@dataclass(frozen=True)
class Pixel:
    """One pixel of an image and its value."""

    x: int
    """Column."""
    y: int
    """Row."""
    value: float
    """The image's value there."""


@dataclass(frozen=True, eq=False)
class RenderResult:
    """One rendered view. Images are decoded to arrays for both encodings (PNG ones are quantised)."""

    sequence: int
    """The request's sequence number (pose streams: the index of the camera in the input)."""
    width: int
    """W, pixels."""
    height: int
    """H, pixels."""
    relevancy: np.ndarray | None
    """[H,W] float32 relevancy, or None when not asked for."""
    rgb: np.ndarray | None = None
    """[H,W,3] float32 colour in [0,1]."""
    depth: np.ndarray | None = None
    """[H,W] float32 expected depth, 0 where empty."""
    alpha: np.ndarray | None = None
    """[H,W] float32 accumulated opacity of the embedded Gaussians."""
    argmax: Pixel | None = None
    """The most relevant pixel, when relevancy was rendered."""
    png: Mapping[str, bytes] = field(default_factory=dict)
    """PNG encoding only: the server's PNG bytes by output name (``"relevancy"``, ``"rgb"``, ...)."""
    elapsed_ms: float = 0.0
    """Server-side render time, milliseconds."""


@dataclass(frozen=True, eq=False)
class PointResult:
    """Relevancy of arbitrary 3D points for each text (through the feature field)."""

    relevancy: np.ndarray
    """[T,P] float32 relevancy of every point for every text."""
    similarity: np.ndarray
    """[T,P] float32 cosine similarity."""
    elapsed_ms: float = 0.0
    """Server-side time, milliseconds."""


@dataclass(frozen=True, eq=False)
class SegmentResult:
    """Open-vocabulary segmentation: each pixel / Gaussian labelled with its best class name."""

    class_names: tuple[str, ...]
    """The classes; labels index into this."""
    pixel_labels: np.ndarray | None
    """[H,W] int32 class per pixel, -1 where nothing is rendered; None without a camera."""
    gaussian_index: np.ndarray | None
    """[k] int64 Gaussian indices; None unless per-Gaussian labels were asked for."""
    gaussian_labels: np.ndarray | None
    """[k] int32 class of each of those Gaussians."""
    elapsed_ms: float = 0.0
    """Server-side time, milliseconds."""

    def counts(self) -> list[tuple[int, int]]:
        """(Gaussians, pixels) labelled with each class, in class order (0 where not asked for)."""

        def count(labels: np.ndarray | None, k: int) -> int:
            return int((labels == k).sum()) if labels is not None else 0

        return [
            (count(self.gaussian_labels, k), count(self.pixel_labels, k))
            for k in range(len(self.class_names))
        ]


@dataclass(frozen=True, eq=False)
class Geometry:
    """A scene's Gaussians as points (all of them, or a uniform sample of those opaque enough)."""

    index: np.ndarray
    """[k] int64 Gaussian indices into the scene, increasing."""
    mean: np.ndarray
    """[k,3] float32 means."""
    color: np.ndarray
    """[k,3] float32 base colour in [0,1] (SH degree 0)."""
    opacity: np.ndarray
    """[k] float32 opacity in [0,1]."""
    scale: np.ndarray
    """[k,3] float32 scales (activated, scene units)."""
    num_gaussians: int
    """Gaussians in the scene."""
    qualified: int
    """Gaussians at or above the opacity floor asked for (k is at most this)."""
    bounds: np.ndarray
    """[6] float64 bounds of all the scene's means: min x, y, z, max x, y, z."""
    elapsed_ms: float = 0.0
    """Server-side time, milliseconds."""

    def __len__(self) -> int:
        return len(self.index)
