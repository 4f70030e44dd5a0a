"""Synthetic labelled scenes rendered by an independent renderer (Open3D ray casting, CPU, no display).

A ground plane with named, procedurally textured primitives, seen from cameras on a ring: RGB,
z-depth and per-pixel label maps, written as a transforms.json dataset (OpenGL camera-to-world, the
instant-ngp/nerfstudio layout) plus ``scene.json`` with object names, ground-truth 3D boxes and
per-view 2D boxes, and ``points3D.ply`` (surface samples with their colours) for initialisation.

Shading is diffuse (albedo x (ambient + Lambert)), so the images are view-consistent.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from fmgs.data.distortion import OpenCVDistortion
from fmgs.errors import ValidationError
from fmgs.io.atomic import atomic_path
from fmgs.io.points import write_point_ply
from fmgs.synthworld import COLOURS, sample_objects, texture_shade, world_object

# name, base colour (linear RGB in [0,1]); label ids: 0 background, 1 floor, 2.. objects in this order
OBJECTS = (
    ("red cube", (0.85, 0.15, 0.12)),
    ("blue ball", (0.15, 0.35, 0.9)),
    ("green cylinder", (0.15, 0.7, 0.25)),
    ("yellow cone", (0.95, 0.85, 0.15)),
    ("purple donut", (0.6, 0.2, 0.75)),
    ("orange pyramid", (0.95, 0.5, 0.1)),
    ("white ring", (0.92, 0.92, 0.9)),
    ("cyan box", (0.1, 0.8, 0.85)),
    # Harder ones (preset "cluttered"): thin, small, flat, and names that share words with others.
    ("yellow pencil", (0.93, 0.72, 0.12)),
    ("pink marble", (0.92, 0.35, 0.62)),
    ("blue book", (0.18, 0.25, 0.62)),
    ("white plate", (0.95, 0.95, 0.93)),
    ("red mug", (0.75, 0.1, 0.12)),
)
RIGS = ("ring", "grazing")
"""ring: every camera on one ring, alternating between two heights. grazing: three rings of equal share
(the two heights and a low one just above the floor, looking across it: the backdrop fills the upper part
of those images, as outdoor captures with sky and turntables on a backdrop do)."""
GRAZING_HEIGHT = 0.3
"""Camera height of the grazing ring (scene units; the objects stand on the floor at z = 0)."""
BACKDROPS = ("constant", "walls")
"""constant: every ray that misses the scene sees BACKGROUND. walls: a textured round wall (WALL_RADIUS,
WALL_HEIGHT) encloses the floor, as a room or a street does, with BACKGROUND above it; its pixels are
labelled background (0) and its surface is sampled into points3D.ply, as structure from motion would."""
WALL_RADIUS = 6.0
WALL_HEIGHT = 2.5
PRESETS = ("basic", "cluttered", "world")
"""basic: the first ``objects`` of OBJECTS, spread apart on a checkered floor. cluttered: a seeded
choice of ``objects`` from all of OBJECTS, about half placed touching another, on a striped floor.
world: ``objects`` of distinct shapes from the wider world (fmgs.synthworld: 15 shapes, 12 colours,
11 surface textures, named "<colour> <texture> <shape>"), sizes from small to large, about a third
touching another, on a striped floor; ``novel`` of them with a held-out colour-shape pair."""
FLOOR_COLOUR = (0.55, 0.5, 0.45)
BACKGROUND = (0.8, 0.85, 0.95)
LIGHT = np.array([0.4, 0.5, 0.77]) / np.linalg.norm([0.4, 0.5, 0.77])  # world +z is up


@dataclass(frozen=True)
class SynthConfig:
    """What to generate."""

    views: int = 32
    """Number of cameras (placed by ``rig``)."""
    width: int = 128
    """Image width in pixels."""
    height: int = 96
    """Image height in pixels."""
    objects: int = 6
    """Number of objects (at most len(OBJECTS))."""
    seed: int = 0
    """Seeds object placement and sizes."""
    fov_deg: float = 55.0
    """Horizontal field of view."""
    ring_radius: float = 4.0
    """Distance of the cameras from the scene centre (horizontal)."""
    points: int = 20_000
    """Surface samples written to points3D.ply for initialisation."""
    supersample: int = 3
    """RGB is the mean of supersample x supersample rays per pixel (anti-aliased, consistent across
    views); labels and depth come from the ray through the pixel centre. Must be odd."""
    checker: float = 0.15
    """Edge of the 3D checkerboard cells of the procedural texture (scene units)."""
    distortion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    """OpenCV lens distortion (k1, k2, p1, p2) the images are rendered with (rays through the distorted
    pixels); written as transforms.json keys with camera_model OPENCV when non-zero."""
    preset: str = "basic"
    """Scene kind (PRESETS): "basic" or "cluttered" (thin, small and touching objects, more classes)."""
    rig: str = "ring"
    """Camera placement (RIGS): "ring" (two heights) or "grazing" (adds a low ring that sees the backdrop)."""
    backdrop: str = "constant"
    """What lies behind the scene (BACKDROPS): "constant" (one colour) or "walls" (textured surroundings)."""
    declare_background: bool = True
    """Write the constant backdrop colour into transforms.json ("background"); False leaves it undeclared,
    as most captures do, so a trainer must cope with it on its own."""
    novel: int = 0
    """Preset "world": how many objects take a held-out colour-shape pair (fmgs.synthworld.HELD_OUT);
    the others never do."""


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[4,4] world-to-camera (OpenCV: x right, y down, z forward), world +z up; a camera looking straight
    up or down (no horizon to level) takes world +y as up instead."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return V


def _camera_position(cfg: SynthConfig, v: int) -> tuple[np.ndarray, np.ndarray]:
    """Eye and look-at target of camera v: on the ring, two heights for parallax; the grazing rig puts
    every third camera on a low ring looking across the floor (its own angles, so it sees new sides)."""
    ang = 2 * np.pi * v / cfg.views
    if cfg.rig == "grazing" and v % 3 == 2:
        eye = np.array([cfg.ring_radius * np.cos(ang), cfg.ring_radius * np.sin(ang), GRAZING_HEIGHT])
        return eye, np.array([0.0, 0.0, GRAZING_HEIGHT])
    elev = 0.9 if v % 2 == 0 else 1.6
    eye = np.array([cfg.ring_radius * np.cos(ang), cfg.ring_radius * np.sin(ang), elev])
    return eye, np.array([0.0, 0.0, 0.25])


def _shape_makers():
    """Shape word -> function of the size s making its open3d mesh (built along +z, centred later)."""
    import open3d as o3d

    g = o3d.geometry.TriangleMesh

    def diamond(s):
        m = g.create_octahedron(s / 2)
        m.scale(1.0, center=(0, 0, 0))
        v = np.asarray(m.vertices) * np.array([0.8, 0.8, 1.2])  # taller than wide: a gem, not a die
        m.vertices = o3d.utility.Vector3dVector(v)
        return m

    def egg(s):
        m = g.create_sphere(s / 2, resolution=20)
        v = np.asarray(m.vertices) * np.array([0.75, 0.75, 1.0])
        v[:, 2] *= np.where(v[:, 2] > 0, 1.15, 0.9)  # a narrower top
        m.vertices = o3d.utility.Vector3dVector(v)
        return m

    return {
        "cube": lambda s: g.create_box(s, s, s),
        "ball": lambda s: g.create_sphere(s / 2, resolution=24),
        "cylinder": lambda s: g.create_cylinder(s / 3, s, resolution=24),
        "cone": lambda s: g.create_cone(s / 2.5, s, resolution=24),
        "donut": lambda s: g.create_torus(s / 2.6, s / 7, radial_resolution=24, tubular_resolution=12),
        "pyramid": lambda s: g.create_cone(s / 2, s * 0.8, resolution=4),
        "ring": lambda s: g.create_torus(s / 2.2, s / 12, radial_resolution=24, tubular_resolution=8),
        "box": lambda s: g.create_box(s * 1.2, s * 0.5, s * 0.4),
        "pencil": lambda s: _lying(g.create_cylinder(0.025, s * 1.3, resolution=12)),
        "marble": lambda s: g.create_sphere(s * 0.2, resolution=16),
        "book": lambda s: g.create_box(s * 0.9, s * 0.65, 0.09),
        "plate": lambda s: g.create_cylinder(s * 0.55, 0.03, resolution=32),
        "mug": lambda s: _mug(g, s),
        "egg": egg,
        "arrow": lambda s: _lying(g.create_arrow(s * 0.06, s * 0.13, s * 0.75, s * 0.3, resolution=12)),
        "diamond": diamond,
    }


def _meshes(cfg: SynthConfig):
    """(name, colour, open3d TriangleMesh, texture) for the floor and each object, placed without
    overlap; the texture is None outside the world preset (the classic checker)."""
    import open3d as o3d

    if cfg.preset not in PRESETS:
        raise ValueError(f"preset must be one of {PRESETS}, got {cfg.preset!r}")
    if cfg.preset == "world":
        return _world_meshes(cfg)
    limit = len(OBJECTS) if cfg.preset == "cluttered" else 8
    if not 1 <= cfg.objects <= limit:
        raise ValidationError(
            "synth", f"objects must be in 1..{limit} for preset {cfg.preset!r}, got {cfg.objects}"
        )
    rng = np.random.default_rng(cfg.seed)
    g = o3d.geometry.TriangleMesh
    makers = _shape_makers()  # each classic object's last word is its shape
    floor = g.create_box(8.0, 8.0, 0.02)
    floor.translate((-4.0, -4.0, -0.02))
    out = [("floor", FLOOR_COLOUR, floor, None)]
    placed: list[tuple[float, float, float]] = []
    if cfg.preset == "basic":
        chosen = list(OBJECTS[: cfg.objects])
    else:
        chosen = [OBJECTS[i] for i in sorted(rng.choice(len(OBJECTS), cfg.objects, replace=False))]
    for name, colour in chosen:
        size = float(rng.uniform(0.45, 0.7))
        mesh = makers[name.split()[-1]](size)
        out.append((name, colour, _put(mesh, rng, placed, cfg.preset == "cluttered" and 0.5), None))
    return out


def _put(mesh, rng, placed: list[tuple[float, float, float]], touch_p: float | bool, extent: float = 1.6):
    """Turn ``mesh`` about z at random, place it on the floor apart from ``placed`` (touching a placed
    one with probability ``touch_p``; ``extent``: _place's), record its footprint in ``placed``; returns
    the mesh."""
    mesh.translate(-mesh.get_axis_aligned_bounding_box().get_center())
    R = mesh.get_rotation_matrix_from_xyz((0.0, 0.0, float(rng.uniform(0, 2 * np.pi))))
    mesh.rotate(R, center=(0, 0, 0))
    r = mesh.get_axis_aligned_bounding_box().get_half_extent()[:2].max()
    touch = bool(touch_p) and bool(placed) and rng.uniform() < touch_p
    x, y = _place(rng, placed, r, touch, extent)
    placed.append((x, y, r))
    zmin = mesh.get_axis_aligned_bounding_box().min_bound[2]
    mesh.translate((x, y, -zmin))  # rest on the floor
    mesh.compute_triangle_normals()
    return mesh


WORLD_SIZES = (0.45, 1.15)
"""Range of the world preset's size factor s (a cube's edge): small objects beside large ones, large
enough at 128x96 from the default ring that their texture shows (stripes 3-5 pixels apart)."""
WORLD_EXTENT = 2.1
"""The world preset places objects within this distance of the centre in x and y (the classic presets:
1.6), so that larger objects fit."""


def _world_meshes(cfg: SynthConfig):
    """The world preset's floor and objects (fmgs.synthworld.sample_objects), smallest placed last."""
    import open3d as o3d

    rng = np.random.default_rng(cfg.seed)
    objs = sample_objects(rng, cfg.objects, cfg.novel)
    sizes = rng.uniform(*WORLD_SIZES, len(objs))
    makers = _shape_makers()
    floor = o3d.geometry.TriangleMesh.create_box(8.0, 8.0, 0.02)
    floor.translate((-4.0, -4.0, -0.02))
    out = [("floor", FLOOR_COLOUR, floor, "floor")]
    placed: list[tuple[float, float, float]] = []
    order = np.argsort(-sizes, kind="stable")  # large ones first: rejection sampling then fits the rest
    meshes = {}
    for i in order:
        o = objs[i]
        meshes[i] = _put(makers[o.shape](float(sizes[i])), rng, placed, 0.35, WORLD_EXTENT)
    for i, o in enumerate(objs):
        out.append((o.name, COLOURS[o.colour], meshes[i], o.texture))
    return out


def _wall():
    """An open (capless) round wall of WALL_RADIUS and WALL_HEIGHT standing on z = 0."""
    import open3d as o3d

    n = 96
    a = 2 * np.pi * np.arange(n) / n
    ring = np.stack([WALL_RADIUS * np.cos(a), WALL_RADIUS * np.sin(a), np.zeros(n)], 1)
    top = ring + np.array([0.0, 0.0, WALL_HEIGHT])
    i = np.arange(n)
    j = (i + 1) % n
    tris = np.concatenate([np.stack([i, j, n + i], 1), np.stack([j, n + j, n + i], 1)])
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.concatenate([ring, top])), o3d.utility.Vector3iVector(tris)
    )
    mesh.compute_triangle_normals()
    return mesh


def _wall_albedo(points: np.ndarray, cell: float) -> np.ndarray:
    """The wall's texture: hues that drift around it, horizontal courses and a checker, so that no one
    colour (a learned background) can explain it."""
    a = np.arctan2(points[..., 1], points[..., 0])
    hue = 0.5 + 0.3 * np.stack([np.sin(3 * a), np.sin(3 * a + 2.1), np.sin(3 * a + 4.2)], -1)
    courses = np.where(np.sin(points[..., 2] * 2 * np.pi / 0.5) > 0, 1.0, 0.75)
    cells = np.floor(points / (3 * cell)).astype(np.int64).sum(-1) % 2
    return hue * (courses * np.where(cells == 0, 1.0, 0.8))[..., None]


def _lying(mesh):
    """A mesh built along +z laid down along +x."""
    mesh.rotate(mesh.get_rotation_matrix_from_xyz((0.0, np.pi / 2, 0.0)), center=(0, 0, 0))
    return mesh


def _mug(g, s: float):
    """A cylinder with a ring handle on its side."""
    body = g.create_cylinder(s * 0.22, s * 0.45, resolution=24)
    handle = g.create_torus(s * 0.1, s * 0.025, radial_resolution=16, tubular_resolution=8)
    handle.rotate(handle.get_rotation_matrix_from_xyz((np.pi / 2, 0.0, 0.0)), center=(0, 0, 0))
    handle.translate((s * 0.3, 0.0, 0.0))
    return body + handle


def _place(
    rng, placed: list[tuple[float, float, float]], r: float, touch: bool, extent: float = 1.6
) -> tuple[float, float]:
    """(x, y) for an object of footprint radius r: apart from every placed one by 0.1, within ``extent``
    of the centre in x and y, or, when ``touch``, with its footprint circle touching a random placed
    one's (within extent + 0.2) and apart from the others."""
    for _ in range(1000):  # rejection sampling: no two objects overlap
        if touch:
            px, py, pr = placed[int(rng.integers(len(placed)))]
            a = rng.uniform(0, 2 * np.pi)
            x, y = px + (r + pr + 0.005) * np.cos(a), py + (r + pr + 0.005) * np.sin(a)
            if abs(x) > extent + 0.2 or abs(y) > extent + 0.2:
                continue
        else:
            x, y = rng.uniform(-extent, extent, 2)
        gap = 0.0 if touch else 0.1
        if all(math.hypot(x - qx, y - qy) > r + qr + gap for qx, qy, qr in placed):
            return float(x), float(y)
    raise RuntimeError("could not place the objects without overlap")


def _albedo(
    label: np.ndarray, points: np.ndarray, colours: np.ndarray, cell: float, striped_floor: bool = False
) -> np.ndarray:
    """Procedural texture: each surface's colour modulated by a 3D checkerboard of ``cell``-sized cells;
    with ``striped_floor`` the floor (label 1) also gets wood-like stripes across x."""
    cells = np.floor(points / cell).astype(np.int64).sum(-1) % 2
    shade = np.where(cells == 0, 1.0, 0.7)
    if striped_floor:
        stripes = 0.75 + 0.25 * np.sin(points[..., 0] * 2 * np.pi / (0.6 * cell) + 3 * np.sin(points[..., 1]))
        shade = np.where(label == 1, shade * stripes, shade)
    return colours[label] * shade[..., None]


def _shade(albedo: np.ndarray, normals: np.ndarray) -> np.ndarray:
    lam = np.abs(normals @ LIGHT)  # two-sided: thin shells look the same from both sides
    return np.clip(albedo * (0.35 + 0.65 * lam)[..., None], 0.0, 1.0)


def check_sizes(cfg: SynthConfig, views: bool = True) -> None:
    """ValidationError naming the first of the image size, the view count (``views``: the rig places the
    cameras) or the point count that no dataset can have."""
    for name, value, low in (("width", cfg.width, 1), ("height", cfg.height, 1), ("points", cfg.points, 0)):
        if value < low:
            raise ValidationError("synth", f"{name} must be at least {low}, got {value}")
    if views and cfg.views < 1:
        raise ValidationError("synth", f"views must be at least 1, got {cfg.views}")


def generate(out: str | Path, cfg: SynthConfig = SynthConfig(), viewmats: np.ndarray | None = None) -> Path:
    """Render the scene into ``out`` (created); returns the path of its transforms.json.

    ``viewmats`` [V,4,4] world-to-camera (OpenCV axes) replace the rig's cameras (a robot's path,
    fmgs.synthbag); ``cfg.views`` is then ignored."""
    import open3d as o3d
    from PIL import Image

    out = Path(out)
    check_sizes(cfg, views=viewmats is None)
    if out.exists() and not out.is_dir():
        raise ValidationError(str(out), "is a file, not a folder for the dataset")
    if cfg.backdrop not in BACKDROPS:
        raise ValueError(f"backdrop must be one of {BACKDROPS}, got {cfg.backdrop!r}")
    items = _meshes(cfg)  # checks the object counts before any folder is made
    for sub in ("images", "labels", "depth"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    scene = o3d.t.geometry.RaycastingScene()
    geom_label = {}
    for label, (_, _, mesh, _) in enumerate(items, start=1):
        gid = scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        geom_label[gid] = label
    wall = _wall() if cfg.backdrop == "walls" else None
    wall_gid = None
    if wall is not None:
        wall_gid = scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(wall))
        geom_label[wall_gid] = 0  # surroundings, not a class
    names = ["background"] + [n for n, _, _, _ in items]
    colours = np.array([BACKGROUND] + [c for _, c, _, _ in items])
    albedo_of = _albedo_for(items, colours, cfg)
    lut = np.zeros(max(geom_label) + 2, dtype=np.int64)
    for gid, label in geom_label.items():
        lut[gid] = label

    W, H, S = cfg.width, cfg.height, cfg.supersample
    if S < 1 or S % 2 == 0:
        raise ValueError(f"supersample must be odd and positive, got {S}")
    if cfg.rig not in RIGS:
        raise ValueError(f"rig must be one of {RIGS}, got {cfg.rig!r}")
    fx = 0.5 * W / math.tan(math.radians(cfg.fov_deg) / 2)
    K = np.array([[fx, 0, W / 2], [0, fx, H / 2], [0, 0, 1.0]])
    # S x S sub-pixel samples per pixel; the middle one is the pixel centre (j + 0.5, i + 0.5).
    js, is_ = np.meshgrid((np.arange(W * S) + 0.5) / S, (np.arange(H * S) + 0.5) / S)
    lens = OpenCVDistortion(*cfg.distortion)
    x, y = lens.undistort((js - K[0, 2]) / fx, (is_ - K[1, 2]) / fx)  # the ray each pixel sees
    d_cam = np.stack([x, y, np.ones_like(js)], -1)  # z = 1
    mid = S // 2

    frames, views = [], []
    for v in range(cfg.views if viewmats is None else len(viewmats)):
        if viewmats is None:
            eye, target = _camera_position(cfg, v)
            V = _look_at(eye, target)
        else:
            V = np.asarray(viewmats[v], np.float64)
            eye = -V[:3, :3].T @ V[:3, 3]
        R = V[:3, :3]
        dirs = d_cam @ R  # world directions (R^T d), keeping the camera z component = 1
        rays = np.concatenate([np.broadcast_to(eye, dirs.shape), dirs], -1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))
        t = hit["t_hit"].numpy().astype(np.float64)
        miss = ~np.isfinite(t)
        gid = hit["geometry_ids"].numpy().astype(np.int64)
        label = np.where(miss, 0, lut[np.where(miss, 0, gid)])
        depth = np.where(miss, 0.0, t)  # z-depth, because the camera-frame ray has z = 1
        pts = eye + dirs * np.where(miss, 0.0, t)[..., None]
        normals = hit["primitive_normals"].numpy().astype(np.float64)
        albedo = albedo_of(label, pts)
        if wall_gid is not None:
            on_wall = ~miss & (gid == wall_gid)
            albedo[on_wall] = _wall_albedo(pts[on_wall], cfg.checker)
        rgb = _shade(albedo, normals)
        rgb[miss] = BACKGROUND
        rgb = rgb.reshape(H, S, W, S, 3).mean((1, 3))  # box filter down to the image
        label = label[mid::S, mid::S]
        depth = depth[mid::S, mid::S]
        name = f"{v:04d}.png"
        Image.fromarray((rgb * 255 + 0.5).astype(np.uint8)).save(out / "images" / name)
        Image.fromarray(label.astype(np.uint8)).save(out / "labels" / name)
        np.save(out / "depth" / f"{v:04d}.npy", depth.astype(np.float32), allow_pickle=False)
        c2w_gl = np.linalg.inv(V) @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append(
            {
                "file_path": f"images/{name}",
                "label_path": f"labels/{name}",
                "depth_path": f"depth/{v:04d}.npy",
                "transform_matrix": c2w_gl.tolist(),
            }
        )
        boxes = {}
        for lab in range(2, len(names)):
            ys, xs = np.nonzero(label == lab)
            if len(xs) >= 4:  # visible: pixel box, inclusive, in pixel indices
                boxes[names[lab]] = [int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())]
        views.append({"file_path": f"images/{name}", "boxes_2d": boxes})

    pts, cols = _surface_points(items, albedo_of, cfg)
    if wall is not None:
        wp, wn = _sample_surface(wall, cfg.points // 2, np.random.default_rng(cfg.seed + 1))
        wc = (_shade(_wall_albedo(wp, cfg.checker), wn) * 255 + 0.5).astype(np.uint8)
        pts, cols = np.concatenate([pts, wp]), np.concatenate([cols, wc])
    write_point_ply(out / "points3D.ply", pts, cols)
    meta = {
        "w": W,
        "h": H,
        "fl_x": fx,
        "fl_y": fx,
        "cx": W / 2,
        "cy": H / 2,
        "camera_model": "PINHOLE" if lens.is_zero else "OPENCV",
        **({} if lens.is_zero else dict(zip(("k1", "k2", "p1", "p2"), cfg.distortion, strict=True))),
        "ply_file_path": "points3D.ply",
        **({"background": list(BACKGROUND)} if cfg.declare_background else {}),
        "frames": frames,
    }
    objects = []
    for label, (name, colour, mesh, _) in enumerate(items, start=1):
        bb = mesh.get_axis_aligned_bounding_box()
        o = {
            "label": label,
            "name": name,
            "colour": list(colour),
            "aabb_min": bb.min_bound.tolist(),
            "aabb_max": bb.max_bound.tolist(),
        }
        if cfg.preset == "world" and label >= 2:
            w = world_object(name)
            o.update(colour_name=w.colour, texture=w.texture, shape=w.shape, novel=w.novel)
        objects.append(o)
    scene_meta = {
        "generator": "fmgs.synth",
        "config": asdict(cfg),
        "label_names": names,
        "objects": objects,
        "views": views,
    }
    with atomic_path(out / "scene.json") as tmp:
        tmp.write_text(json.dumps(scene_meta, indent=1))
    with atomic_path(out / "transforms.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=1))
    return out / "transforms.json"


def _albedo_for(items, colours: np.ndarray, cfg: SynthConfig):
    """The scene's albedo as a function of (label [...], surface points [...,3]) -> [...,3]: the classic
    checker (and striped floor) of _albedo, or the world's named textures about each object's centre."""
    striped = cfg.preset in ("cluttered", "world")
    if cfg.preset != "world":
        return lambda label, pts: _albedo(label, pts, colours, cfg.checker, striped)

    centres = [np.zeros(3)] + [m.get_axis_aligned_bounding_box().get_center() for _, _, m, _ in items]

    def albedo(label: np.ndarray, pts: np.ndarray) -> np.ndarray:
        out = _albedo(label, pts, colours, cfg.checker, striped)  # floor and background
        for lab, (_, _, _, texture) in enumerate(items, start=1):
            if lab < 2:
                continue
            on = label == lab
            if on.any():
                out[on] = colours[lab] * texture_shade(texture, pts[on] - centres[lab])[..., None]
        return out

    return albedo


def _surface_points(items, albedo_of, cfg: SynthConfig) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform samples on every surface, coloured like the renderer colours them."""
    rng = np.random.default_rng(cfg.seed)
    pts, cols = [], []
    areas = np.array([m.get_surface_area() for _, _, m, _ in items])
    counts = np.maximum(50, (cfg.points * areas / areas.sum()).astype(int))
    for label, ((_, _, mesh, _), n) in enumerate(zip(items, counts, strict=True), start=1):
        p, nrm = _sample_surface(mesh, int(n), rng)
        lab = np.full(len(p), label)
        pts.append(p)
        cols.append(_shade(albedo_of(lab, p), nrm))
    return np.concatenate(pts), (np.concatenate(cols) * 255 + 0.5).astype(np.uint8)


def _sample_surface(mesh, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """n area-uniform points [n,3] on a triangle mesh and their face normals [n,3]."""
    v = np.asarray(mesh.vertices)
    tri = np.asarray(mesh.triangles)
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1)
    pick = rng.choice(len(tri), size=n, p=area / area.sum())
    u, w = rng.uniform(size=(2, n))
    flip = u + w > 1  # fold the square onto the triangle: uniform barycentric coordinates
    u, w = np.where(flip, 1 - u, u), np.where(flip, 1 - w, w)
    p = a[pick] + u[:, None] * (b - a)[pick] + w[:, None] * (c - a)[pick]
    return p, cross[pick] / np.maximum(area[pick], 1e-300)[:, None]
