"""A scene tree under construction, and the transforms that place template meshes in it.

Generators describe a scene as groups (internal nodes: a name and a local transform) and leaves
(a name, a local transform and a template name). :class:`Tree` keeps them in plain lists in the
order they were made, which is the order the scene graph receives them, so the same calls always
give the same graph. Names are paths (``"plant/unit2/boiler/buckstay07"``): unique by
construction, readable, and stable across builds.

Group transforms are rigid (rotation and translation); leaves may also scale non-uniformly to fit
a unit template to a part. Keeping scale on leaves only means every node's matrix decomposes as
translation x rotation x scale, as glTF requires, and no shear ever reaches a child.

All matrix helpers return float64 ``(4, 4)`` arrays, or ``(n, 4, 4)`` for vectorised forms.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from . import meshes

if TYPE_CHECKING:  # imported where used: names and layouts load without trimesh
    import trimesh

ArrayLike = np.ndarray | Sequence[float]


# ---------------------------------------------------------------------------------------------
# transforms


def trs(t: ArrayLike = (0.0, 0.0, 0.0), r: np.ndarray | None = None, s: ArrayLike | float = 1.0) -> np.ndarray:
    """Translation @ rotation @ scale as one 4x4: a template scaled by ``s``, turned by the 3x3
    ``r``, then moved to ``t``."""
    m = np.eye(4)
    m[:3, :3] = (np.eye(3) if r is None else r) * np.broadcast_to(np.asarray(s, dtype=np.float64), 3)
    m[:3, 3] = t
    return m


def rot_z(angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about z (yaw, the usual way parts are turned)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_x(angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about x."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about y."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


#: z-up (how the generators think) to glTF's y-up: (x, y, z) -> (x, z, -y).
Z_UP_TO_Y_UP = trs(r=rot_x(-np.pi / 2))


def frames(directions: np.ndarray) -> np.ndarray:
    """Rotations ``(n, 3, 3)`` whose z column is each unit direction ``(n, 3)``.

    The x column is horizontal (``up x d``) and y = z x x, so a member built with its depth on
    local y (an I-beam's web) stands upright; vertical directions fall back to world x for x.
    """
    d = np.asarray(directions, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    hint = np.where(np.abs(d[:, 2:3]) > 0.999, [[0.0, 1.0, 0.0]], [[0.0, 0.0, 1.0]])
    x = np.cross(hint, d)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(d, x)
    return np.stack([x, y, d], -1)


def members(p0: np.ndarray, p1: np.ndarray, section: ArrayLike, roll: ArrayLike | float = 0.0) -> np.ndarray:
    """Transforms ``(n, 4, 4)`` that stretch a unit prism (z in [-0.5, 0.5]) between ``p0`` and
    ``p1`` ``(n, 3)``, scaled to ``section`` (its x and y size, ``(2,)`` or ``(n, 2)``) and
    rolled about its own axis by ``roll`` radians. Pipes, beams, braces, rails."""
    p0 = np.atleast_2d(np.asarray(p0, dtype=np.float64))
    p1 = np.atleast_2d(np.asarray(p1, dtype=np.float64))
    d = p1 - p0
    length = np.linalg.norm(d, axis=-1)
    r = frames(d)
    roll = np.broadcast_to(np.asarray(roll, dtype=np.float64), length.shape)
    if np.any(roll):
        c, s = np.cos(roll), np.sin(roll)
        x, y = r[..., 0].copy(), r[..., 1].copy()
        r[..., 0] = c[:, None] * x + s[:, None] * y
        r[..., 1] = -s[:, None] * x + c[:, None] * y
    section = np.broadcast_to(np.asarray(section, dtype=np.float64), (len(length), 2))
    m = np.zeros((len(length), 4, 4))
    m[:, :3, :3] = r * np.concatenate([section, length[:, None]], -1)[:, None, :]
    m[:, :3, 3] = 0.5 * (p0 + p1)
    m[:, 3, 3] = 1.0
    return m


def placements(t: np.ndarray, yaw: ArrayLike | float = 0.0, s: ArrayLike = 1.0) -> np.ndarray:
    """Transforms ``(n, 4, 4)``: scale by ``s`` (scalar, ``(3,)`` or ``(n, 3)``), turn by ``yaw``
    about z, move to ``t`` ``(n, 3)``. The common way to scatter equipment and architecture."""
    t = np.atleast_2d(np.asarray(t, dtype=np.float64))
    n = len(t)
    yaw = np.broadcast_to(np.asarray(yaw, dtype=np.float64), (n,))
    s = np.asarray(s, dtype=np.float64)
    s = np.broadcast_to(s if s.ndim else np.full(3, s), (n, 3)) if s.ndim < 2 else s
    c, si = np.cos(yaw), np.sin(yaw)
    m = np.zeros((n, 4, 4))
    m[:, 0, 0], m[:, 0, 1] = c * s[:, 0], -si * s[:, 1]
    m[:, 1, 0], m[:, 1, 1] = si * s[:, 0], c * s[:, 1]
    m[:, 2, 2] = s[:, 2]
    m[:, :3, 3] = t
    m[:, 3, 3] = 1.0
    return m


def polyline_pipe(points: np.ndarray, radius: float, bend: float = 1.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split a pipe route into straight runs and bends of ``bend * radius``.

    ``points`` ``(k, 3)`` are the corners of the route. Returns the straight segments' end points
    ``(k-1, 3)`` each (trimmed by the bends' tangent lengths), and the bends' placements
    ``(k-2, 4, 4)`` for an :func:`meshes.elbow` template of the turn angle at each corner, plus
    the turn angles in degrees ``(k-2,)``.
    """
    p = np.asarray(points, dtype=np.float64)
    d = np.diff(p, axis=0)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d_in, d_out = d[:-1], d[1:]
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", d_in, d_out), -1.0, 1.0))
    tangent = bend * radius * np.tan(angle / 2)
    start = p[:-1].copy()
    end = p[1:].copy()
    start[1:] += d_out * tangent[:, None]
    end[:-1] -= d_in * tangent[:, None]
    # bend frame: z along the incoming pipe, x toward the outgoing one
    x = d_out - d_in * np.einsum("ij,ij->i", d_in, d_out)[:, None]
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(d_in, x)
    m = np.zeros((len(angle), 4, 4))
    m[:, :3, :3] = np.stack([x, y, d_in], -1) * radius
    m[:, :3, 3] = p[1:-1] - d_in * tangent[:, None]
    m[:, 3, 3] = 1.0
    return np.stack([start, end], 1), m, np.degrees(angle)


# ---------------------------------------------------------------------------------------------
# the tree


class Tree:
    """Groups and leaves in creation order, emitted as a :class:`trimesh.Scene`.

    ``root`` becomes the single child of the scene's base frame ``"world"``; its transform turns
    the generators' z-up into glTF's y-up.
    """

    def __init__(self, root: str, matrix: np.ndarray = Z_UP_TO_Y_UP):
        self.root = root
        self.names: list[str] = [root]
        self.parents: list[str] = ["world"]
        self.matrices: list[np.ndarray] = [np.asarray(matrix, dtype=np.float64)]
        self.geometry: list[str | None] = [None]
        self._known: set[str] = {root}

    def _add(self, parent: str, name: str, matrix: np.ndarray, geometry: str | None) -> str:
        full = f"{parent}/{name}"
        if full in self._known:
            raise ValueError(f"duplicate node name {full!r}")
        if parent not in self._known:
            raise ValueError(f"unknown parent {parent!r}")
        self._known.add(full)
        self.names.append(full)
        self.parents.append(parent)
        self.matrices.append(matrix)
        self.geometry.append(geometry)
        return full

    def group(self, parent: str, name: str, matrix: np.ndarray | None = None) -> str:
        """Add an internal node; returns its full name (the parent for its children)."""
        return self._add(parent, name, np.eye(4) if matrix is None else np.asarray(matrix, dtype=np.float64), None)

    def leaf(self, parent: str, name: str, geometry: str, matrix: np.ndarray) -> str:
        """Add a geometry node placing the template ``geometry`` (a :data:`meshes.TEMPLATES` key)."""
        if geometry not in meshes.TEMPLATES:
            raise KeyError(geometry)
        return self._add(parent, name, np.asarray(matrix, dtype=np.float64), geometry)

    def leaves(self, parent: str, stem: str, geometry: str | Sequence[str], matrices: np.ndarray,
               start: int = 0, width: int = 2) -> list[str]:
        """Add ``len(matrices)`` numbered leaves ``stem00, stem01, ...`` under ``parent``."""
        geoms = [geometry] * len(matrices) if isinstance(geometry, str) else list(geometry)
        return [self.leaf(parent, f"{stem}{start + i:0{width}d}", g, m)
                for i, (g, m) in enumerate(zip(geoms, matrices))]

    def counts(self) -> tuple[int, int]:
        """(internal, leaf) node counts so far; the base frame is not counted."""
        leaves = sum(g is not None for g in self.geometry)
        return len(self.names) - leaves, leaves

    def scene(self, copies: Sequence[tuple[str, np.ndarray]] | None = None) -> trimesh.Scene:
        """The finished scene: each used template once in ``scene.geometry`` (named after it),
        every node in creation order under ``"world"``. With ``copies``, ``(root name, root
        matrix)`` pairs, the tree is emitted once per pair, each copy's names starting with its
        own root name instead of ``self.root``."""
        import trimesh  # only here: the bundled scenes' names and layouts load without it

        scene = trimesh.Scene()
        used = dict.fromkeys(g for g in self.geometry if g is not None)  # ordered, no set order
        for name in used:
            scene.geometry[name] = meshes.template(name)
        graph = scene.graph
        cut = len(self.root)
        for root, top in copies or [(self.root, self.matrices[0])]:
            rows = zip(self.names, self.parents, self.matrices, self.geometry)
            for k, (name, parent, matrix, geom) in enumerate(rows):
                name = root + name[cut:]
                parent = parent if k == 0 else root + parent[cut:]
                matrix = top if k == 0 else matrix
                if geom is None:
                    graph.update(frame_from=parent, frame_to=name, matrix=matrix)
                else:
                    graph.update(frame_from=parent, frame_to=name, matrix=matrix, geometry=geom)
        return scene
