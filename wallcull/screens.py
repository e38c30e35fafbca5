"""Walls given screen by screen (SPEC section 2b): CAVEs, curved and angled walls.

A screen is a rectangle in display space given by three corners, ``bottom_left``,
``bottom_right`` and ``top_left``; it is seen from the side its normal ``u x v`` points to
(``u``, ``v``: the unit directions of its bottom and left edges). Its tile frustum is bounded by
the four planes through the eye and its edges and by a near and a far plane parallel to it, at
distances ``near`` and ``far`` from the eye.

**The plane table of a frame** (world space, unit normals inward, as for grid walls): tile ``t``
owns rows ``6 t .. 6 t + 5``: its left, right, top, bottom, near and far planes. After them come
the split planes of the frustum hierarchy (one per split node) and the primary bound: six
planes of a box around the eye that holds every tile frustum, and, when every screen lies in
an open half-space through the eye, the planes through the eye and the edges of the screens'
spherical convex hull (at most :data:`MAX_CONE` of them).

**The frustum hierarchy** (the paper's general case, section 4.2). A group of screens is split
in two by a plane through the eye and one of its screens' edges wherever such a plane separates
the group: every corner of one part on one side, every corner of the other on the other (the
tile frusta, cones from the eye over their screens, then lie on their sides). Among the
separating planes the most even split is taken. Where none separates the group (the floor of a
CAVE from its walls; screens all around the eye), the group is cut in two along the widest
spread of the screens' directions, and each part is bounded by its own planes: a single screen
by its tile planes, a group by none (an object goes on down it). The hierarchy is built once,
for the nominal eye (display space origin); each frame the split planes are rebuilt through the
tracked eye and checked: a split that no longer separates its groups culls nothing that frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numba import njit

from .documents import ScreensSpec, parse
from .errors import InputError
from .validate import RESOLVABLE, check_resolvable

#: Most planes of the cone bounding all screens (the primary bound keeps at most 63 planes).
MAX_CONE = 48

# Modes of a node of the frustum hierarchy (columns of the table, see wallcull.cull).
SPLIT, BOUNDS, PASS = 0, 3, 4


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of arrays of 3-vectors (last axis), without its generic overhead: a frame
    builds its planes from a few hundred of them."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


@dataclass(frozen=True, eq=False)
class ScreensWall:
    """A wall given as a list of screens (SPEC section 2b). Build it with
    :meth:`wallcull.wall.Wall.from_dict`, which keeps a grid given as screens a grid."""

    corners: np.ndarray  # (T, 3, 3): bottom_left, bottom_right, top_left
    resolutions: np.ndarray  # (T, 2) pixels
    near: float
    far: float
    kind: str = field(default="screens", init=False)

    @classmethod
    def from_spec(cls, spec: ScreensSpec) -> "ScreensWall":
        """The wall of a validated document (its screens are rectangles)."""
        corners = [(s.bottom_left, s.bottom_right, s.top_left) for s in spec.screens]
        return cls(np.array(corners, np.float64),
                   np.array([s.resolution for s in spec.screens], np.int64), spec.near, spec.far)

    @classmethod
    def from_dict(cls, spec) -> "ScreensWall":
        """A screens wall as given, even one whose screens are a grid's tiles (which
        :meth:`wallcull.wall.Wall.from_dict` makes that grid)."""
        return cls.from_spec(parse(ScreensSpec, spec, "wall"))

    def to_dict(self) -> dict:
        return {"screens": [{"bottom_left": c[0].tolist(), "bottom_right": c[1].tolist(),
                             "top_left": c[2].tolist(), "resolution": r.tolist()}
                            for c, r in zip(self.corners, self.resolutions)],
                "near": self.near, "far": self.far}

    # ----------------------------------------------------------------- geometry

    @property
    def tiles(self) -> int:
        return len(self.corners)

    @cached_property
    def basis(self) -> np.ndarray:
        """``(T, 3, 3)``: each screen's unit ``u`` (along its bottom edge), ``v`` (up its left
        edge) and normal ``n = u x v`` (toward the seen side), as rows: world-to-screen axes."""
        u = self.corners[:, 1] - self.corners[:, 0]
        v = self.corners[:, 2] - self.corners[:, 0]
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        v -= (v * u).sum(axis=1, keepdims=True) * u  # exactly perpendicular, for the matrices
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        return np.stack([u, v, np.cross(u, v)], axis=1)

    @cached_property
    def size(self) -> np.ndarray:
        """``(T, 2)``: width and height of each screen, meters."""
        return np.stack([np.linalg.norm(self.corners[:, 1] - self.corners[:, 0], axis=1),
                         np.linalg.norm(self.corners[:, 2] - self.corners[:, 0], axis=1)], axis=1)

    @cached_property
    def quads(self) -> np.ndarray:
        """``(T, 4, 3)``: each screen's corners, bottom left, bottom right, top right, top
        left (CCW seen from the front)."""
        bl, br, tl = self.corners[:, 0], self.corners[:, 1], self.corners[:, 2]
        return np.stack([bl, br, br + tl - bl, tl], axis=1)

    def check_eye(self, eye: np.ndarray, what: str = "frame eye") -> None:
        """An eye must be on the seen side of every screen, farther than ``near`` from its
        plane (SPEC section 2b)."""
        n = self.basis[:, 2]
        distance = ((eye - self.corners[:, 0]) * n).sum(axis=1)
        bad = np.flatnonzero(~(distance > self.near))
        if len(bad):
            t = int(bad[0])
            raise InputError(f"{what} {np.round(eye, 9).tolist()} is {distance[t]:.6g} m in front "
                             f"of screen {t}: it must be on its seen side, farther than near = "
                             f"{self.near:g}")
        least, reach = self._resolution
        if least < RESOLVABLE * (math.hypot(*eye.tolist()) + reach):  # else far enough
            reach = np.linalg.norm(self.quads - eye, axis=2).max(axis=1)
            t = int(np.argmin(self.size.min(axis=1) / reach))
            check_resolvable(eye, float(self.size[t].min()), float(reach[t]), f"screen {t},",
                             what)

    @cached_property
    def _resolution(self) -> tuple[float, float]:
        """The least side of any screen, and the farthest corner from the origin."""
        return float(self.size.min()), float(np.linalg.norm(self.quads, axis=2).max())

    @cached_property
    def pitch(self) -> tuple[float, float]:
        """The screens' typical angular size (width, height over their distance) from the
        nominal eye: what the adaptive traversal weighs an object's angular size against."""
        distance = np.maximum(-(self.corners[:, 0] * self.basis[:, 2]).sum(axis=1), 1e-9)
        return (float(np.median(self.size[:, 0] / distance)),
                float(np.median(self.size[:, 1] / distance)))

    @cached_property
    def hierarchy(self) -> "ScreenHierarchy":
        return ScreenHierarchy.build(self)

    # ----------------------------------------------------------------- planes

    def tile_planes(self, eye: np.ndarray) -> np.ndarray:
        """``(T, 6, 4)``: each tile frustum's planes in display space, seen from ``eye``:
        left, right, top, bottom (through the eye and the edges, facing the screen's inside),
        near and far (parallel to the screen)."""
        return _tile_planes(self.quads, np.ascontiguousarray(self.basis[:, 2]),
                            np.asarray(eye, np.float64), float(self.near), float(self.far))

    def reach(self, eye: np.ndarray) -> float:
        """How far from ``eye`` any tile frustum reaches: its far cap's farthest corner."""
        return _reach(self.quads, np.ascontiguousarray(self.basis[:, 2]),
                      np.asarray(eye, np.float64), float(self.far))

    def primary_planes(self, eye: np.ndarray) -> np.ndarray:
        """``(k, 4)`` display-space planes bounding every tile frustum: a box around the eye,
        and the cone through the screens' spherical hull when they fit in a half-space."""
        r = self.reach(eye) * (1 + 1e-9)
        box = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                       float)
        planes = [np.concatenate([box, (r - box @ eye)[:, None]], axis=1)]
        cone = hull_cone(self.quads.reshape(-1, 3) - eye)
        if cone is not None and len(cone) <= MAX_CONE:
            planes.append(np.concatenate([cone, np.zeros((len(cone), 1))], axis=1))
            planes[-1][:, 3] = -(cone @ eye)
        return np.concatenate(planes)


# left: tl -> bl, right: br -> tr, top: tr -> tl, bottom: bl -> br (corners of a quad)
_EDGE_START, _EDGE_END = (3, 1, 2, 0), (0, 2, 3, 1)


@njit(cache=True)
def _tile_planes(quads, normals, eye, near, far):
    """:meth:`ScreensWall.tile_planes`, compiled. A side's normal is the cross product of its
    edge with the ray from the eye to the edge's start, which faces the screen's inside (the
    quad is CCW seen from the eye)."""
    out = np.empty((quads.shape[0], 6, 4))
    for t in range(quads.shape[0]):
        for p in range(4):
            s, e = _EDGE_START[p], _EDGE_END[p]
            ax, ay, az = (quads[t, e, 0] - quads[t, s, 0], quads[t, e, 1] - quads[t, s, 1],
                          quads[t, e, 2] - quads[t, s, 2])
            bx, by, bz = (quads[t, s, 0] - eye[0], quads[t, s, 1] - eye[1],
                          quads[t, s, 2] - eye[2])
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            length = math.sqrt(nx * nx + ny * ny + nz * nz)
            nx, ny, nz = nx / length, ny / length, nz / length
            out[t, p, 0], out[t, p, 1], out[t, p, 2] = nx, ny, nz
            out[t, p, 3] = -(nx * eye[0] + ny * eye[1] + nz * eye[2])
        n_eye = normals[t, 0] * eye[0] + normals[t, 1] * eye[1] + normals[t, 2] * eye[2]
        for k in range(3):
            out[t, 4, k], out[t, 5, k] = -normals[t, k], normals[t, k]
        out[t, 4, 3], out[t, 5, 3] = n_eye - near, far - n_eye
    return out


@njit(cache=True)
def _reach(quads, normals, eye, far):
    """:meth:`ScreensWall.reach`, compiled."""
    lowest = np.inf
    for t in range(quads.shape[0]):
        for c in range(4):
            rx, ry, rz = quads[t, c, 0] - eye[0], quads[t, c, 1] - eye[1], quads[t, c, 2] - eye[2]
            cos = -(rx * normals[t, 0] + ry * normals[t, 1] + rz * normals[t, 2]) \
                / math.sqrt(rx * rx + ry * ry + rz * rz)
            lowest = min(lowest, cos)
    return far / lowest


def hull_cone(directions: np.ndarray) -> np.ndarray | None:
    """Inward unit normals ``(k, 3)`` of the planes through the origin and the edges of the
    convex cone over ``directions (m, 3)``, or None when they do not all lie in an open
    half-space (they surround the origin). Found as the 2D hull of their gnomonic projection on
    the plane across their mean direction."""
    from .quad import hull_indices

    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    axis = d.mean(axis=0)
    norm = np.linalg.norm(axis)
    if not norm > 1e-6:
        return None
    axis /= norm
    depth = d @ axis
    if not depth.min() > 1e-6:
        return None
    a = cross(axis, np.array([1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0]))
    a /= np.linalg.norm(a)
    b = cross(axis, a)
    image = np.stack([d @ a, d @ b], axis=1) / depth[:, None]
    hull = hull_indices(image)
    if len(hull) < 3:
        return None
    rays = d[hull]
    normals = cross(rays, np.roll(rays, -1, axis=0))  # CCW hull: the inside is on the left
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    if (normals @ axis < 0).all():
        normals = -normals
    # conservative: every direction on or inside every plane (rounding pushed outward)
    slack = np.minimum(d @ normals.T, 0).min(axis=0)
    if slack.min() < -1e-9:
        return None
    return normals


@dataclass(frozen=True)
class ScreenHierarchy:
    """The frustum hierarchy of a screens wall (module docstring), as flat arrays.

    Node 0 is the root. Internal nodes have ``first``/``second`` children and ``tile == -1``;
    a ``SPLIT`` node's first child lies inside the plane through the eye and its edge
    ``(edge_a, edge_b)`` (display space), its second outside; a ``BOUNDS`` node's children are
    bounded by their own planes (``own[c]``: the tile whose six planes bound child ``c``, or -1
    for none).
    """

    first: np.ndarray
    second: np.ndarray
    tile: np.ndarray
    mode: np.ndarray
    edge_a: np.ndarray  # (nodes, 3)
    edge_b: np.ndarray  # (nodes, 3)
    own: np.ndarray  # (nodes,) tile bounding this node as a child of a BOUNDS node, or -1
    members: list  # tiles under each node
    depth: np.ndarray

    def __len__(self) -> int:
        return len(self.tile)

    @property
    def height(self) -> int:
        return int(self.depth.max())

    @classmethod
    def build(cls, wall: ScreensWall, eye: np.ndarray | None = None) -> "ScreenHierarchy":
        eye = np.zeros(3) if eye is None else np.asarray(eye, float)
        quads = wall.quads
        scale = float(np.abs(quads - eye).max())
        rows: list[list] = []

        def add(group: np.ndarray, depth: int) -> int:
            index = len(rows)
            rows.append([-1, -1, -1, PASS, np.zeros(3), np.zeros(3), -1, group, depth])
            if len(group) == 1:
                rows[index][2] = int(group[0])
                rows[index][6] = int(group[0])
                return index
            split = _best_split(quads, group, eye, scale)
            if split is not None:
                inside, outside, a, b = split
                rows[index][3], rows[index][4], rows[index][5] = SPLIT, a, b
            else:
                inside, outside = _halves(quads, group, eye)
                rows[index][3] = BOUNDS
            first = add(inside, depth + 1)
            second = add(outside, depth + 1)
            rows[index][0], rows[index][1] = first, second
            return index

        add(np.arange(wall.tiles), 0)
        col = list(zip(*rows))
        return cls(np.array(col[0], np.int64), np.array(col[1], np.int64),
                   np.array(col[2], np.int64), np.array(col[3], np.int64),
                   np.array(col[4]), np.array(col[5]), np.array(col[6], np.int64),
                   list(col[7]), np.array(col[8], np.int64))

    @cached_property
    def _corners(self) -> tuple[np.ndarray, ...]:
        """``(split nodes, first start, first corners, second start, second corners)``: for
        each split node, the corners of its first child's screens and of its second's, in CSR
        form (corner ``4 t + k`` of tile ``t``)."""
        splits = np.flatnonzero(self.mode == SPLIT)

        def csr(children):
            rows = [(4 * self.members[c][:, None] + np.arange(4)).ravel() for c in children]
            start = np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int64)
            return start, (np.concatenate(rows) if rows else np.zeros(0)).astype(np.int64)

        return (splits, *csr(self.first[splits]), *csr(self.second[splits]))

    def split_planes(self, wall: ScreensWall, eye: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(planes (nodes, 4), valid (nodes,))``: each split node's plane through ``eye``
        and its edge, facing its first child, and whether it still separates its children's
        screens from this eye (False for other nodes)."""
        a, b = self.edge_a - eye, self.edge_b - eye
        normal = cross(a, b)
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        split = (self.mode == SPLIT) & (length[:, 0] > 0)
        normal = np.where(length > 0, normal / np.where(length > 0, length, 1), 0.0)
        planes = np.concatenate([normal, -(normal @ eye)[:, None]], axis=1)
        quads = wall.quads.reshape(-1, 3)  # corner 4 t + k of tile t
        tol = SLACK * float(np.abs(quads - eye).max())
        nodes, *corners = self._corners
        side = _separates(quads, planes, nodes, *corners, tol)
        side[~split[nodes]] = 0
        turned = nodes[side < 0]
        planes[turned] = -planes[turned]
        valid = np.zeros(len(self), bool)
        valid[nodes[side != 0]] = True
        return planes, valid


@njit(cache=True)
def _separates(quads, planes, nodes, first_start, first, second_start, second, tol):
    """For each split node, +1 when its plane has its first child's screens' corners on its
    inside and its second's on its outside (within ``tol``), -1 when the other way round, 0
    when it separates them neither way."""
    out = np.zeros(nodes.shape[0], np.int64)
    for j in range(nodes.shape[0]):
        k = nodes[j]
        nx, ny, nz, d = planes[k, 0], planes[k, 1], planes[k, 2], planes[k, 3]
        a_lo, a_hi, b_lo, b_hi = np.inf, -np.inf, np.inf, -np.inf
        for i in range(first_start[j], first_start[j + 1]):
            c = first[i]
            v = quads[c, 0] * nx + quads[c, 1] * ny + quads[c, 2] * nz + d
            a_lo, a_hi = min(a_lo, v), max(a_hi, v)
        for i in range(second_start[j], second_start[j + 1]):
            c = second[i]
            v = quads[c, 0] * nx + quads[c, 1] * ny + quads[c, 2] * nz + d
            b_lo, b_hi = min(b_lo, v), max(b_hi, v)
        if a_lo >= -tol and b_hi <= tol:
            out[j] = 1
        elif b_lo >= -tol and a_hi <= tol:
            out[j] = -1
    return out


#: How far, relative to the screens' distance from the eye, a screen's corner may lie on the
#: wrong side of a split and the split still hold: rounding, no more. A split shares one plane
#: between its two sides, so a corner over it by ``s`` leaves a wedge of that screen's frustum
#: untested, ``s / distance`` wide at every depth beyond (with 1e-9, a centimetre 10,000 km
#: out: a miss). Corners that far over make the split not hold from that eye: it culls
#: nothing there (conservative, and slower only on such frames).
SLACK = 1e-13


def _best_split(quads: np.ndarray, group: np.ndarray, eye: np.ndarray, scale: float):
    """The most even split of ``group`` by a plane through ``eye`` and one of its screens'
    edges: ``(inside, outside, edge point a, edge point b)``, or None."""
    tol = SLACK * scale
    corners = quads[group] - eye  # (g, 4, 3)
    edges = np.stack([corners, np.roll(corners, -1, axis=1)], axis=2).reshape(-1, 2, 3)
    normal = np.cross(edges[:, 0], edges[:, 1])
    length = np.linalg.norm(normal, axis=1)
    keep = length > 1e-12 * scale * scale
    edges, normal = edges[keep], normal[keep] / length[keep, None]
    side = (corners.reshape(-1, 3) @ normal.T).T.reshape(len(normal), len(group), 4)
    plus = (side >= -tol).all(axis=2)
    minus = (side <= tol).all(axis=2)
    separated = (plus | minus).all(axis=1) & plus.any(axis=1) & minus.any(axis=1) \
        & ~(plus & minus).all(axis=1)
    best, best_score = None, None
    for e in np.flatnonzero(separated):
        inside = plus[e] & ~minus[e]
        on = plus[e] & minus[e]  # screens in the plane itself (seen edge-on): either side
        first = group[inside | on]
        second = group[~(inside | on)]
        if not len(first) or not len(second):
            continue
        score = abs(len(first) - len(second))
        if best_score is None or score < best_score:
            best_score = score
            best = (first, second, edges[e, 0] + eye, edges[e, 1] + eye)
    return best


def _halves(quads: np.ndarray, group: np.ndarray, eye: np.ndarray):
    """``group`` cut in two along the widest spread of its screens' directions from ``eye``."""
    d = quads[group].mean(axis=1) - eye
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centered = d - d.mean(axis=0)
    axis = np.linalg.svd(centered, full_matrices=False)[2][0] if len(group) > 1 else d[0]
    order = group[np.argsort(d @ axis, kind="stable")]
    half = (len(order) + 1) // 2
    return order[:half], order[half:]
