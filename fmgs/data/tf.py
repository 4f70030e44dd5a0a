"""A recording's tf tree: static and dynamic transforms composed along the tree and interpolated at a
stamp as tf2 does (translation linearly, rotation by slerp), with the gaps and ends tf2 refuses.

Conventions are ROS's: a transform on edge parent -> child maps child coordinates into the parent's
(x_parent = R x_child + t); quaternions are (x, y, z, w); stamps are integer nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fmgs.errors import ValidationError

CLOCK_JUMP_S = 1.0
"""A stamp this much earlier than the one recorded before it on the same edge or topic is a clock jump
(a restarted simulation, a looped playback), not jitter."""


GAP_PERIODS = 3.0
"""A moving transform's samples around a stamp further apart than max_gap_s and than this many of its
median interval are a dropout."""


def stamp_text(ns: int) -> str:
    """A message time as ROS prints it: seconds and nanoseconds."""
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """[3,3] rotation of a quaternion (x, y, z, w) of any non-zero norm."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(x, y, z, w) of a rotation matrix [3,3], w >= 0."""
    m = np.asarray(R, np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q if q[3] >= 0 else -q


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Unit quaternion a fraction ``u`` of the way from q0 to q1 along the shorter arc."""
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 1 - 1e-12:  # nearly equal: the arc is a line to double precision
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    a = np.arccos(min(d, 1.0))
    return (np.sin((1 - u) * a) * q0 + np.sin(u * a) * q1) / np.sin(a)


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def invert(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return rigid(R.T, -R.T @ t)


@dataclass
class _Edge:
    parent: str
    static: bool
    stamps: list[int] = field(default_factory=list)
    quats: list[np.ndarray] = field(default_factory=list)
    trans: list[np.ndarray] = field(default_factory=list)


class NotAPose(ValidationError):
    """A transform sample with a NaN or infinite value or a zero quaternion: tf2 drops such a sample with
    a warning, and so does the import (``TfTree.skipped`` counts them)."""


class TfTree:
    """Transforms as a recording's /tf and /tf_static hold them; ``lookup`` answers tf2's
    lookupTransform(target, source, stamp)."""

    def __init__(self, max_gap_s: float = 0.2) -> None:
        self.max_gap_ns = int(max_gap_s * 1e9)
        self._edges: dict[str, _Edge] = {}
        self._arrays: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, float]] = {}
        self.skipped = 0
        """Samples refused as not a pose (NotAPose) by the reader that filled the tree."""

    def add(self, parent: str, child: str, stamp_ns: int, quat, trans, static: bool, topic: str = "/tf"):
        """One transform parent -> child. A child has one parent (tf2's rule); a static edge keeps its
        latest value; a dynamic edge's stamps must not jump back by CLOCK_JUMP_S or more; a sample that is
        not a pose raises NotAPose (the tree is unchanged)."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        q, v = np.asarray(quat, float), np.asarray(trans, float)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v)) and np.linalg.norm(q) > 1e-6):
            raise NotAPose(
                topic,
                f"{parent} -> {child} at {stamp_text(int(stamp_ns))}: quaternion {q.tolist()} with "
                f"translation {v.tolist()} is not a pose (NaN, infinite or a zero quaternion)",
            )
        e = self._edges.get(child)
        if e is None:
            e = self._edges[child] = _Edge(parent, static)
        elif e.parent != parent:
            raise ValidationError(
                topic, f"frame {child!r} has two parents, {e.parent!r} and {parent!r} (tf allows one)"
            )
        if static:
            e.static, e.stamps, e.quats, e.trans = True, [0], [q], [v]
            return
        if e.static:  # a frame published both ways: the dynamic samples win, as in tf2's cache
            e.static, e.stamps, e.quats, e.trans = False, [], [], []
        if e.stamps and stamp_ns < e.stamps[-1] - CLOCK_JUMP_S * 1e9:
            raise ValidationError(
                topic,
                f"{parent} -> {child}: a stamp goes back {(e.stamps[-1] - stamp_ns) / 1e9:.1f} s "
                "(clock jump: a restarted simulation or a looped playback); record once, or cut the "
                "recording before the jump",
            )
        e.stamps.append(int(stamp_ns))
        e.quats.append(q)
        e.trans.append(v)
        self._arrays.pop(child, None)

    @property
    def frames(self) -> set[str]:
        return set(self._edges) | {e.parent for e in self._edges.values()}

    def _chain(self, frame: str) -> list[str]:
        """frame, its parent, ... up to its tree's root."""
        out = [frame]
        while out[-1] in self._edges:
            out.append(self._edges[out[-1]].parent)
            if len(out) > len(self._edges) + 1:
                raise ValidationError("/tf", f"the frames above {frame!r} form a loop")
        return out

    def tree_of(self, frame: str) -> list[str]:
        """Every frame in the tree that holds ``frame``, sorted."""
        root = self._chain(frame)[-1]
        return sorted(f for f in self.frames if self._chain(f)[-1] == root)

    def check_connected(self, target: str, source: str) -> None:
        """ValidationError naming the two trees when no chain of transforms joins the frames."""
        for f in (target, source):
            if f not in self.frames:
                raise ValidationError(
                    "tf",
                    f"frame {f!r} is not in the recording's tf (frames: {', '.join(sorted(self.frames))})",
                )
        if self._chain(target)[-1] != self._chain(source)[-1]:
            raise ValidationError(
                "tf",
                f"frames {target!r} and {source!r} are not connected: {target!r} is in the tree "
                f"{{{', '.join(self.tree_of(target))}}}, {source!r} in {{{', '.join(self.tree_of(source))}}}",
            )

    def _edge_at(self, child: str, stamp_ns: int) -> tuple[np.ndarray | None, str]:
        """parent_T_child [4,4] at the stamp, or (None, why): "outside" the edge's samples, or a "gap"."""
        e = self._edges[child]
        if e.static:
            return rigid(quat_to_matrix(e.quats[0]), e.trans[0]), ""
        arr = self._arrays.get(child)
        if arr is None:
            order = np.argsort(np.asarray(e.stamps), kind="stable")
            st = np.asarray(e.stamps)[order]
            # A transform published slowly (localisation's map -> odom at 1 Hz) is not in a dropout
            # between its usual samples: the bound is GAP_PERIODS of its median interval when larger.
            usual = float(np.median(np.diff(st))) if len(st) > 1 else 0.0
            bound = max(self.max_gap_ns, GAP_PERIODS * usual)
            arr = (st, np.asarray(e.quats)[order], np.asarray(e.trans)[order], bound)
            self._arrays[child] = arr
        st, qs, ts, bound = arr
        i = int(np.searchsorted(st, stamp_ns, side="right")) - 1
        if i >= 0 and st[i] == stamp_ns:
            return rigid(quat_to_matrix(qs[i]), ts[i]), ""
        if i < 0 or i + 1 >= len(st):
            return None, "outside"
        if st[i + 1] - st[i] > bound:
            return None, "gap"
        u = (stamp_ns - st[i]) / (st[i + 1] - st[i])
        q = slerp(qs[i], qs[i + 1], u)
        return rigid(quat_to_matrix(q), ts[i] + u * (ts[i + 1] - ts[i])), ""

    def lookup(self, target: str, source: str, stamp_ns: int) -> tuple[np.ndarray | None, str]:
        """target_T_source [4,4] at the stamp (x_target = T x_source), or (None, why) with why "outside"
        (the stamp is before or after a moving edge's samples) or "gap" (its samples around the stamp
        are further apart than max_gap_s and GAP_PERIODS of its usual interval). check_connected first."""
        up_s, up_t = self._chain(source), self._chain(target)
        common = next(f for f in up_s if f in set(up_t))
        T_s, why = self._up_to(up_s[: up_s.index(common)], stamp_ns)  # common_T_source
        if T_s is None:
            return None, why
        T_t, why = self._up_to(up_t[: up_t.index(common)], stamp_ns)  # common_T_target
        if T_t is None:
            return None, why
        return invert(T_t) @ T_s, ""

    def _up_to(self, chain: list[str], stamp_ns: int) -> tuple[np.ndarray | None, str]:
        """top_T_first [4,4] along ``chain`` (a frame and its ancestors below ``top``), or (None, why)."""
        T_all = np.eye(4)
        for f in chain:
            T, why = self._edge_at(f, stamp_ns)
            if T is None:
                return None, why
            T_all = T @ T_all
        return T_all, ""
