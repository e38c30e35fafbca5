"""The wall, the frame, the tile frusta and the frustum hierarchy (SPEC sections 1-3).

Display space: meters, x right, y up, z toward the viewer; the wall lies in ``z = -distance``.
A frame places display space in the world: ``p_world = R(q) p_display + t``.

Every frustum plane is stored as a row ``(nx, ny, nz, d)`` with a unit normal pointing *into* the
frustum: a point ``p`` is inside when ``n . p + d >= 0``. Tile frusta and the frustum hierarchy
share one table of planes per frame, laid out by :class:`PlaneLayout`:

* ``L[c]``, ``R[c]``: the planes through the eye and the left / right edge of column ``c``;
* ``T[r]``, ``B[r]``: the planes through the eye and the top / bottom edge of row ``r``;
* ``NEAR``, ``FAR``: ``z = eye_z - near`` and ``z = eye_z - far``, parallel to the wall.

Tile ``(r, c)`` is bounded by ``L[c], R[c], T[r], B[r], NEAR, FAR``; the primary frustum by the
outer ones. With bezels (``gap > 0``) ``R[c]`` and ``L[c+1]`` differ and a point seen through the
bezel lies in neither tile; with projector overlap (``gap < 0``) it lies in both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Mapping

import numpy as np
from numba import njit

from .errors import InputError

#: The largest wall accepted (tiles). 64 x 64 is the largest wall the project is built for;
#: the limit leaves room above it while refusing requests that could only exhaust memory.
MAX_TILES = 1 << 16

#: Relative tolerance on the norm of a frame's quaternion (SPEC section 3).
QUATERNION_TOLERANCE = 1e-6

#: The ranges float64 geometry stays meaningful in (beyond them the matrices sent to clients
#: would overflow or lose every digit): lengths of the wall, m; and world coordinates.
MIN_LENGTH, MAX_LENGTH = 1e-9, 1e9
MAX_COORDINATE = 1e15

WALL_DEFAULTS = {"gap": (0.0, 0.0), "near": 0.1, "far": 1000.0, "resolution": (1920, 1080)}
WALL_KEYS = {"cols", "rows", "tile_size", "gap", "distance", "near", "far", "resolution"}


def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{what} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise InputError(f"{what} must be finite, got {value!r}")
    return value


def _vector(value: Any, n: int, what: str) -> tuple[float, ...]:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise InputError(f"{what} must be a list of {n} numbers, got {value!r}")
    return tuple(_number(v, f"{what}[{i}]") for i, v in enumerate(value))


def _count(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            raise InputError(f"{what} must be a whole number, got {value!r}")
    if value < 1:
        raise InputError(f"{what} must be at least 1, got {value}")
    return value


@dataclass(frozen=True)
class Wall:
    """An N x M wall of tiles (SPEC section 2). Build it with :meth:`from_dict`."""

    cols: int
    rows: int
    tile_size: tuple[float, float]
    gap: tuple[float, float]
    distance: float
    near: float
    far: float
    resolution: tuple[int, int]

    @classmethod
    def from_dict(cls, spec: Mapping[str, Any]) -> "Wall":
        """Validate a wall spec (SPEC section 2); missing optional keys take ``WALL_DEFAULTS``."""
        if not isinstance(spec, Mapping):
            raise InputError(f"a wall must be a JSON object, got {type(spec).__name__}")
        unknown = set(spec) - WALL_KEYS
        if unknown:
            raise InputError(f"unknown wall key(s): {', '.join(sorted(map(str, unknown)))}")
        for key in ("cols", "rows", "tile_size", "distance"):
            if key not in spec:
                raise InputError(f"wall is missing {key!r}")
        spec = {**WALL_DEFAULTS, **spec}
        cols, rows = _count(spec["cols"], "wall cols"), _count(spec["rows"], "wall rows")
        if cols * rows > MAX_TILES:
            raise InputError(f"wall has {cols * rows} tiles; at most {MAX_TILES} are supported")
        w, h = _vector(spec["tile_size"], 2, "wall tile_size")
        if w <= 0 or h <= 0:
            raise InputError(f"wall tile_size must be positive, got {[w, h]}")
        gx, gy = _vector(spec["gap"], 2, "wall gap")
        if gx <= -w or gy <= -h:
            raise InputError(f"wall gap {[gx, gy]} overlaps a whole tile; it must exceed -tile_size")
        distance = _number(spec["distance"], "wall distance")
        near = _number(spec["near"], "wall near")
        far = _number(spec["far"], "wall far")
        if distance <= 0:
            raise InputError(f"wall distance must be positive, got {distance}")
        if not 0 < near < far:
            raise InputError(f"wall needs 0 < near < far, got near={near}, far={far}")
        for what, value in (("tile_size", w), ("tile_size", h), ("distance", distance)):
            if not MIN_LENGTH <= value <= MAX_LENGTH:
                raise InputError(f"wall {what} must be between {MIN_LENGTH:g} and "
                                 f"{MAX_LENGTH:g} m, got {value:g}")
        if max(abs(gx), abs(gy)) > MAX_LENGTH or far > MAX_COORDINATE:
            raise InputError(f"wall gap must be within {MAX_LENGTH:g} m and far within "
                             f"{MAX_COORDINATE:g} m")
        res = spec["resolution"]
        if not isinstance(res, (list, tuple)) or len(res) != 2:
            raise InputError(f"wall resolution must be [width, height] in pixels, got {res!r}")
        resolution = (_count(res[0], "wall resolution[0]"), _count(res[1], "wall resolution[1]"))
        wall = cls(cols, rows, (w, h), (gx, gy), distance, near, far, resolution)
        for name, edges in (("columns", wall.col_edges), ("rows", wall.row_edges)):
            # every tile must keep a width in float64 however far from the centre it lies
            if not (edges[:, 1] > edges[:, 0]).all():
                raise InputError(f"wall {name} are too narrow for their gaps: float64 cannot "
                                 "tell a tile's edges apart")
        return wall

    def to_dict(self) -> dict:
        return {
            "cols": self.cols, "rows": self.rows, "tile_size": list(self.tile_size),
            "gap": list(self.gap), "distance": self.distance, "near": self.near,
            "far": self.far, "resolution": list(self.resolution),
        }

    @property
    def tiles(self) -> int:
        return self.cols * self.rows

    @property
    def size(self) -> tuple[float, float]:
        """Total width and height ``(W, H)`` of the wall, meters."""
        (w, h), (gx, gy) = self.tile_size, self.gap
        return self.cols * w + (self.cols - 1) * gx, self.rows * h + (self.rows - 1) * gy

    @cached_property
    def col_edges(self) -> np.ndarray:
        """``(cols, 2)``: ``x0, x1`` of each column's visible area, display space."""
        w, gx = self.tile_size[0], self.gap[0]
        x0 = -self.size[0] / 2 + np.arange(self.cols) * (w + gx)
        return np.stack([x0, x0 + w], axis=1)

    @cached_property
    def row_edges(self) -> np.ndarray:
        """``(rows, 2)``: ``y0, y1`` of each row's visible area; row 0 is the top row."""
        h, gy = self.tile_size[1], self.gap[1]
        y1 = self.size[1] / 2 - np.arange(self.rows) * (h + gy)
        return np.stack([y1 - h, y1], axis=1)

    def tile_rect(self, tile: int) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` of a tile's visible rectangle in the wall plane."""
        r, c = divmod(int(tile), self.cols)
        return (*self.col_edges[c], *self.row_edges[r])

    @cached_property
    def layout(self) -> "PlaneLayout":
        return PlaneLayout(self.cols, self.rows)

    @cached_property
    def hierarchy(self) -> "FrustumHierarchy":
        return FrustumHierarchy.build(self)


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(w, x, y, z)``."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_quaternion(m: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix, with ``w >= 0`` (Shepperd's
    method: the largest of the four squared components is taken first, for stability)."""
    m = np.asarray(m, dtype=np.float64)
    trace = np.trace(m)
    squares = np.array([1 + trace, 1 + 2 * m[0, 0] - trace, 1 + 2 * m[1, 1] - trace,
                        1 + 2 * m[2, 2] - trace])
    k = int(np.argmax(squares))
    q = np.empty(4)
    q[k] = np.sqrt(squares[k]) / 2
    s = 1 / (4 * q[k])
    if k == 0:
        q[1:] = (m[2, 1] - m[1, 2]) * s, (m[0, 2] - m[2, 0]) * s, (m[1, 0] - m[0, 1]) * s
    elif k == 1:
        q[[0, 2, 3]] = (m[2, 1] - m[1, 2]) * s, (m[0, 1] + m[1, 0]) * s, (m[0, 2] + m[2, 0]) * s
    elif k == 2:
        q[[0, 1, 3]] = (m[0, 2] - m[2, 0]) * s, (m[0, 1] + m[1, 0]) * s, (m[1, 2] + m[2, 1]) * s
    else:
        q[[0, 1, 2]] = (m[1, 0] - m[0, 1]) * s, (m[0, 2] + m[2, 0]) * s, (m[1, 2] + m[2, 1]) * s
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


@dataclass(frozen=True)
class Frame:
    """Where display space sits in the world for one frame, and the tracked eye (SPEC section 3)."""

    position: np.ndarray  # (3,) world position of the display-space origin
    orientation: np.ndarray  # (4,) unit quaternion w, x, y, z
    eye: np.ndarray  # (3,) tracked head, display space
    rotation: np.ndarray = field(repr=False)  # (3, 3) R(q)

    @classmethod
    def from_dict(cls, spec: Mapping[str, Any], wall: Wall) -> "Frame":
        """Validate a frame against its wall: unit quaternion, eye strictly in front of the wall."""
        if not isinstance(spec, Mapping):
            raise InputError(f"a frame must be a JSON object, got {type(spec).__name__}")
        unknown = set(spec) - {"position", "orientation", "eye"}
        if unknown:
            raise InputError(f"unknown frame key(s): {', '.join(sorted(map(str, unknown)))}")
        for key in ("position", "orientation"):
            if key not in spec:
                raise InputError(f"frame is missing {key!r}")
        position = np.array(_vector(spec["position"], 3, "frame position"))
        q = np.array(_vector(spec["orientation"], 4, "frame orientation"))
        eye = np.array(_vector(spec.get("eye", (0.0, 0.0, 0.0)), 3, "frame eye"))
        return cls.make(position, q, eye, wall)

    @classmethod
    def make(cls, position, orientation, eye, wall: Wall) -> "Frame":
        position = np.asarray(position, dtype=np.float64).reshape(3)
        q = np.asarray(orientation, dtype=np.float64).reshape(4)
        eye = np.asarray(eye, dtype=np.float64).reshape(3)
        if not (np.isfinite(position).all() and np.isfinite(q).all() and np.isfinite(eye).all()):
            raise InputError("frame position, orientation and eye must be finite")
        if np.abs(position).max() > MAX_COORDINATE:
            raise InputError(f"frame position must be within {MAX_COORDINATE:g} of the origin")
        if np.abs(eye).max() > MAX_LENGTH:
            raise InputError(f"frame eye must be within {MAX_LENGTH:g} m of the display origin")
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > QUATERNION_TOLERANCE:
            raise InputError(
                f"frame orientation {q.tolist()} is not a unit quaternion (norm {norm:.9g})")
        if not eye[2] > -wall.distance + wall.near:
            raise InputError(
                f"frame eye z={eye[2]:g} is not in front of the wall: it must exceed "
                f"-distance + near = {-wall.distance + wall.near:g}")
        q = q / norm
        return cls(position, q, eye, quaternion_matrix(q))

    def to_dict(self) -> dict:
        return {"position": self.position.tolist(), "orientation": self.orientation.tolist(),
                "eye": self.eye.tolist()}

    def to_world(self, p: np.ndarray) -> np.ndarray:
        """Display-space points ``(..., 3)`` to world space."""
        return p @ self.rotation.T + self.position

    @property
    def eye_world(self) -> np.ndarray:
        return self.to_world(self.eye)


@dataclass(frozen=True)
class PlaneLayout:
    """Indices into a frame's plane table (see the module docstring)."""

    cols: int
    rows: int

    def L(self, c):  # noqa: N802 - the names are the planes'
        return c

    def R(self, c):  # noqa: N802
        return self.cols + c

    def T(self, r):  # noqa: N802
        return 2 * self.cols + r

    def B(self, r):  # noqa: N802
        return 2 * self.cols + self.rows + r

    @property
    def near(self) -> int:
        return 2 * (self.cols + self.rows)

    @property
    def far(self) -> int:
        return self.near + 1

    @property
    def count(self) -> int:
        return self.near + 2

    @cached_property
    def tile_planes(self) -> np.ndarray:
        """``(tiles, 6)`` plane indices of each tile frustum: L, R, T, B, near, far."""
        r, c = np.divmod(np.arange(self.cols * self.rows), self.cols)
        n = np.full_like(r, self.near)
        return np.stack([self.L(c), self.R(c), self.T(r), self.B(r), n, n + 1], axis=1)

    @cached_property
    def primary_planes(self) -> np.ndarray:
        """``(6,)`` plane indices of the primary frustum."""
        return np.array([self.L(0), self.R(self.cols - 1), self.T(0), self.B(self.rows - 1),
                         self.near, self.far])


def display_planes(wall: Wall, eye: np.ndarray) -> np.ndarray:
    """The frame's plane table in display space, ``(PlaneLayout.count, 4)``, unit normals inward."""
    return _plane_table(wall.col_edges, wall.row_edges, np.asarray(eye, dtype=np.float64),
                        wall.distance, wall.near, wall.far, np.eye(3), np.zeros(3))


@njit(cache=True)
def _plane_table(col_edges, row_edges, eye, distance, near, far, rotation, translation):
    """The plane table of a frame (see the module docstring), moved by ``p' = R p + t``: per
    frame a few dozen planes, so one compiled loop rather than dozens of small numpy calls."""
    cols, rows = col_edges.shape[0], row_edges.shape[0]
    ex, ey, ez = eye[0], eye[1], eye[2]
    depth = distance + ez  # eye to wall plane, > near > 0 for a valid frame
    out = np.empty((2 * (cols + rows) + 2, 4))
    k = 0
    for side in range(4):  # L[c], R[c], T[r], B[r]
        for j in range(cols if side < 2 else rows):
            if side == 0:  # inside is to the right of x0
                nx, ny, nz = depth, 0.0, col_edges[j, 0] - ex
            elif side == 1:  # inside is to the left of x1
                nx, ny, nz = -depth, 0.0, -(col_edges[j, 1] - ex)
            elif side == 2:  # inside is below y1
                nx, ny, nz = 0.0, -depth, -(row_edges[j, 1] - ey)
            else:  # inside is above y0
                nx, ny, nz = 0.0, depth, row_edges[j, 0] - ey
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            out[k, 0], out[k, 1], out[k, 2] = nx / norm, ny / norm, nz / norm
            out[k, 3] = -(out[k, 0] * ex + out[k, 1] * ey + out[k, 2] * ez)
            k += 1
    out[k, 0], out[k, 1], out[k, 2], out[k, 3] = 0.0, 0.0, -1.0, ez - near  # near
    out[k + 1, 0], out[k + 1, 1], out[k + 1, 2], out[k + 1, 3] = 0.0, 0.0, 1.0, far - ez  # far
    for k in range(out.shape[0]):  # n' = R n, d' = d - n' . t
        x = rotation[0, 0] * out[k, 0] + rotation[0, 1] * out[k, 1] + rotation[0, 2] * out[k, 2]
        y = rotation[1, 0] * out[k, 0] + rotation[1, 1] * out[k, 1] + rotation[1, 2] * out[k, 2]
        z = rotation[2, 0] * out[k, 0] + rotation[2, 1] * out[k, 1] + rotation[2, 2] * out[k, 2]
        out[k, 0], out[k, 1], out[k, 2] = x, y, z
        out[k, 3] -= x * translation[0] + y * translation[1] + z * translation[2]
    return out


@dataclass(frozen=True)
class Frusta:
    """One frame's frusta: the plane table in world space and what indexes it."""

    wall: Wall
    frame: Frame
    planes: np.ndarray  # (PlaneLayout.count, 4), world space

    @classmethod
    def build(cls, wall: Wall, frame: Frame) -> "Frusta":
        planes = _plane_table(wall.col_edges, wall.row_edges, frame.eye, wall.distance,
                              wall.near, wall.far, frame.rotation, frame.position)
        return cls(wall, frame, planes)

    @property
    def primary(self) -> np.ndarray:
        """``(6, 4)`` planes of the primary frustum."""
        return self.planes[self.wall.layout.primary_planes]

    def tile(self, tile: int) -> np.ndarray:
        """``(6, 4)`` planes of one tile frustum."""
        return self.planes[self.wall.layout.tile_planes[tile]]


@dataclass(frozen=True)
class FrustumHierarchy:
    """The bisection hierarchy of tile frusta (paper section 3, Fig. 1), as flat arrays.

    Node 0 is the root (all tiles, the primary frustum). An internal node covers the half-open
    tile rectangle ``[c0, c1) x [r0, r1)`` and splits it across its larger dimension in tile
    count (columns on a tie), the first half taking the extra tile of an odd count. Its first
    child (left or top) is bounded by plane ``plane_a``, its second (right or bottom) by
    ``plane_b``: the two edge planes of the split, equal and opposite when ``gap == 0``.
    Leaves carry their tile id; internal nodes carry ``tile == -1``.
    """

    c0: np.ndarray
    c1: np.ndarray
    r0: np.ndarray
    r1: np.ndarray
    first: np.ndarray  # child index, -1 at leaves
    second: np.ndarray
    plane_a: np.ndarray  # plane bounding the first child, -1 at leaves
    plane_b: np.ndarray  # plane bounding the second child
    tile: np.ndarray  # tile id at leaves, -1 inside
    depth: np.ndarray

    @classmethod
    def build(cls, wall: Wall) -> "FrustumHierarchy":
        lay = wall.layout
        rows_out: list[list[int]] = []

        def add(c0, c1, r0, r1, depth) -> int:
            index = len(rows_out)
            rows_out.append([c0, c1, r0, r1, -1, -1, -1, -1, -1, depth])
            nc, nr = c1 - c0, r1 - r0
            if nc == 1 and nr == 1:
                rows_out[index][8] = r0 * wall.cols + c0
                return index
            if nc >= nr:
                k = c0 + (nc + 1) // 2
                a = add(c0, k, r0, r1, depth + 1)
                b = add(k, c1, r0, r1, depth + 1)
                planes = lay.R(k - 1), lay.L(k)
            else:
                k = r0 + (nr + 1) // 2
                a = add(c0, c1, r0, k, depth + 1)
                b = add(c0, c1, k, r1, depth + 1)
                planes = lay.B(k - 1), lay.T(k)
            rows_out[index][4:8] = [a, b, *planes]
            return index

        add(0, wall.cols, 0, wall.rows, 0)
        table = np.array(rows_out, dtype=np.int64)
        return cls(*(np.ascontiguousarray(table[:, i]) for i in range(10)))

    def __len__(self) -> int:
        return len(self.tile)

    @property
    def height(self) -> int:
        return int(self.depth.max())
