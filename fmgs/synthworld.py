"""The generator's wider world (``fmgs synth --preset world``): objects named by colour, surface texture
and shape, some colour-shape pairs held out.

Every object is one of SHAPES, painted one of COLOURS, with one of TEXTURES (a solid 3D pattern, or
"plain"); its name is "<colour> <texture> <shape>" ("red striped cube"), or "<colour> <shape>" when plain.
HELD_OUT lists colour-shape pairs that no scene places unless asked to (``SynthConfig.novel``): stand-ins
trained on ordinary world scenes never see them, so a scene that places them measures names the
stand-ins never saw, the small analogue of open vocabulary.

Pure numpy: the meshes come from fmgs.synth, which calls ``sample_objects`` and ``texture_shade``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from fmgs.errors import ValidationError

COLOURS: dict[str, tuple[float, float, float]] = {
    "red": (0.85, 0.12, 0.1),
    "orange": (0.95, 0.5, 0.1),
    "yellow": (0.95, 0.85, 0.15),
    "green": (0.15, 0.65, 0.2),
    "blue": (0.12, 0.25, 0.85),
    "cyan": (0.1, 0.8, 0.85),
    "purple": (0.55, 0.18, 0.72),
    "pink": (0.95, 0.45, 0.7),
    "white": (0.93, 0.93, 0.91),
    "black": (0.08, 0.08, 0.09),
    "grey": (0.5, 0.5, 0.52),
    "brown": (0.45, 0.26, 0.1),
}
"""Colour words (each the plain word of a group in fmgs.query.colours) and their linear RGB albedo."""

SHAPES: tuple[str, ...] = (
    "cube", "ball", "cylinder", "cone", "donut", "pyramid", "ring", "box",
    "pencil", "book", "plate", "mug", "egg", "arrow", "diamond",
)  # fmt: skip
"""Shape words; fmgs.synth builds each one's mesh (SHAPE_MAKERS there)."""

TEXTURES: tuple[str, ...] = (
    "plain", "striped", "checkered", "dotted", "wavy", "speckled",
    "marbled", "zigzag", "plaid", "grid", "ringed",
)  # fmt: skip
"""Surface patterns; "plain" is left out of the name."""

SYNONYMS: dict[str, str] = {
    "cube": "block",
    "ball": "sphere",
    "cylinder": "tube",
    "cone": "traffic cone",
    "donut": "doughnut",
    "pyramid": "triangle",
    "ring": "hoop",
    "box": "crate",
    "pencil": "pen",
    "book": "notebook",
    "plate": "dish",
    "mug": "cup",
    "egg": "oval",
    "arrow": "pointer",
    "diamond": "gem",
}
"""A paraphrase of each shape word (fixed before any measurement)."""

HELD_OUT: tuple[tuple[str, str], ...] = (
    ("green", "cube"), ("white", "ball"), ("orange", "cylinder"), ("purple", "cone"),
    ("blue", "pyramid"), ("black", "ring"), ("yellow", "box"), ("pink", "pencil"),
    ("cyan", "plate"), ("grey", "mug"), ("red", "egg"), ("brown", "arrow"),
)  # fmt: skip
"""Colour-shape pairs placed only when a scene asks for novel objects (fixed before any measurement):
12 pairs, no colour twice, every shape but three."""


class WorldObject(NamedTuple):
    """One placed object's identity."""

    name: str
    colour: str
    texture: str
    shape: str

    @property
    def novel(self) -> bool:
        """Its colour-shape pair is held out (HELD_OUT)."""
        return (self.colour, self.shape) in HELD_OUT


def object_name(colour: str, texture: str, shape: str) -> str:
    """ "red striped cube"; "red cube" for a plain one."""
    return f"{colour} {shape}" if texture == "plain" else f"{colour} {texture} {shape}"


def sample_objects(rng: np.random.Generator, n: int, novel: int = 0) -> list[WorldObject]:
    """``n`` objects of distinct shapes, ``novel`` of them with a held-out colour-shape pair (the others
    never have one); colours and textures drawn at random."""
    if not 1 <= n <= len(SHAPES):
        raise ValidationError("synth", f"objects must be in 1..{len(SHAPES)} for preset 'world', got {n}")
    if not 0 <= novel <= n:
        raise ValidationError("synth", f"novel must be in 0..{n}, got {novel}")
    held = list(HELD_OUT)
    picks = [held[i] for i in rng.choice(len(held), novel, replace=False)] if novel else []
    shapes = [s for _, s in picks]
    rest = [s for s in SHAPES if s not in shapes]
    shapes += [rest[i] for i in rng.choice(len(rest), n - novel, replace=False)]
    colours = [c for c, _ in picks]
    names = list(COLOURS)
    for s in shapes[novel:]:
        allowed = [c for c in names if (c, s) not in HELD_OUT]
        colours.append(allowed[int(rng.integers(len(allowed)))])
    out = []
    for c, s in zip(colours, shapes, strict=True):
        t = TEXTURES[int(rng.integers(len(TEXTURES)))]
        out.append(WorldObject(object_name(c, t, s), c, t, s))
    return out


def texture_shade(texture: str, p: np.ndarray) -> np.ndarray:
    """[...] brightness factor in [0.3, 1] of ``texture`` at surface points p [...,3] given relative to
    the object's centre (scene units; patterns a few pixels wide at the generator's usual scale)."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    dark = 0.4
    if texture == "plain":
        return np.ones_like(x)
    if texture == "striped":  # horizontal bands
        return np.where(np.sin(2 * np.pi * z / 0.14) > 0, 1.0, dark)
    if texture == "checkered":
        return np.where(np.floor(p / 0.08).astype(np.int64).sum(-1) % 2 == 0, 1.0, dark)
    if texture == "dotted":  # dark dots on a lattice
        q = (p / 0.1) % 1.0 - 0.5
        return np.where(np.linalg.norm(q, axis=-1) < 0.3, dark, 1.0)
    if texture == "wavy":
        bent = z + 0.05 * np.sin(2 * np.pi * (x + y) / 0.25)
        return np.where(np.sin(2 * np.pi * bent / 0.12) > 0, 1.0, dark)
    if texture == "speckled":  # hashed cells of random brightness
        c = np.floor(p / 0.035).astype(np.int64)
        h = (c[..., 0] * 73856093) ^ (c[..., 1] * 19349663) ^ (c[..., 2] * 83492791)
        return 0.45 + 0.55 * ((h % 1009) / 1008.0)
    if texture == "marbled":  # veins: a sine of a turbulent coordinate
        t = x + y + 0.3 * np.sin(7 * z) + 0.2 * np.sin(11 * x + 5 * y)
        return 0.55 + 0.45 * np.abs(np.sin(2 * np.pi * t / 0.2)) ** 0.3
    if texture == "zigzag":  # bands that bend back and forth along x+y
        tri = np.abs(((x + y) / 0.12) % 2.0 - 1.0) * 0.08
        return np.where(np.sin(2 * np.pi * (z + tri) / 0.14) > 0, 1.0, dark)
    if texture == "plaid":  # crossed bands, darker where they cross
        a = np.where(np.sin(2 * np.pi * x / 0.16) > 0.3, 0.7, 1.0)
        b = np.where(np.sin(2 * np.pi * y / 0.16) > 0.3, 0.7, 1.0)
        c = np.where(np.sin(2 * np.pi * z / 0.16) > 0.3, 0.8, 1.0)
        return a * b * c
    if texture == "grid":  # thin dark lines on a lattice
        f = (p / 0.1) % 1.0
        return np.where((f < 0.22).any(-1), dark, 1.0)
    if texture == "ringed":  # rings around the object's vertical axis
        return np.where(np.sin(2 * np.pi * np.hypot(x, y) / 0.1) > 0, 1.0, dark)
    raise ValueError(f"texture must be one of {TEXTURES}, got {texture!r}")


def world_object(name: str) -> WorldObject:
    """The colour, texture and shape a world name is made of (the inverse of ``object_name``)."""
    words = name.split()
    if len(words) == 2 and words[0] in COLOURS and words[1] in SHAPES:
        return WorldObject(name, words[0], "plain", words[1])
    if len(words) == 3 and words[0] in COLOURS and words[1] in TEXTURES and words[2] in SHAPES:
        return WorldObject(name, *words)
    raise ValueError(f"{name!r} is not a world object name (<colour> [<texture>] <shape>)")
