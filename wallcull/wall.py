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

from . import documents
from .errors import InputError
from .validate import MAX_TILES, RESOLVABLE, check_resolvable

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
    given_as_screens: bool = False  # SPEC 2b's form of this grid: tiles have no row and col
    #: A grid given as screens: its tiles' edges as given (x0s, x1s of the columns, y0s, y1s
    #: of the rows), so that every plane and matrix comes from the corners themselves.
    edges: tuple | None = None
    kind = "grid"

    @classmethod
    def from_dict(cls, spec: Any) -> "Wall | ScreensWall":
        """A wall from its document (SPEC section 2; a dict, or a validated
        :class:`~wallcull.documents.WallSpec`): refused in one line when it is not one.

        A spec with ``screens`` (SPEC 2b) gives a :class:`~wallcull.screens.ScreensWall`,
        unless its screens are exactly the tiles of a grid wall, listed in tile order: then
        it is that grid (``given_as_screens``), culled and fitted as the grid is, so both forms
        give identical lists and matrices."""
        doc = documents.parse(documents.Wall, spec, "wall")
        if isinstance(doc, documents.ScreensSpec):
            from .screens import ScreensWall

            screens = ScreensWall.from_spec(doc)
            return cls.from_screens(screens) or screens
        wall = cls(doc.cols, doc.rows, doc.tile_size, doc.gap, doc.distance, doc.near, doc.far,
                   doc.resolution)
        for name, edges in (("columns", wall.col_edges), ("rows", wall.row_edges)):
            # every tile must keep a width in float64 however far from the centre it lies
            if not (edges[:, 1] > edges[:, 0]).all():
                raise InputError(f"wall {name} are too narrow for their gaps: float64 cannot "
                                 "tell a tile's edges apart")
        return wall

    @classmethod
    def from_screens(cls, screens: "ScreensWall") -> "Wall | None":
        """The grid wall whose tiles are exactly ``screens``, in tile order, or None."""
        corners = screens.corners
        z = corners[..., 2]
        if not ((z == z[0, 0]).all() and z[0, 0] < 0 and len(set(map(tuple,
                                                                   screens.resolutions))) == 1):
            return None
        bl, br, tl = corners[:, 0], corners[:, 1], corners[:, 2]
        if not ((bl[:, 1] == br[:, 1]).all() and (bl[:, 0] == tl[:, 0]).all()
                and (br[:, 0] > bl[:, 0]).all() and (tl[:, 1] > bl[:, 1]).all()):
            return None  # not facing +z with rows along x and columns along y
        cols, rows = len(np.unique(bl[:, 0])), len(np.unique(tl[:, 1]))
        if cols * rows != screens.tiles or cols * rows > MAX_TILES:
            return None
        # Tile order is row-major from the top left: the corners as the grid would place them.
        order = np.lexsort((bl[:, 0], -tl[:, 1]))
        if not np.array_equal(order, np.arange(screens.tiles)):
            return None
        x0, x1 = bl[:cols, 0], br[:cols, 0]
        y0, y1 = bl[::cols, 1], tl[::cols, 1]
        if not ((bl[:, 0] == np.tile(x0, rows)).all() and (br[:, 0] == np.tile(x1, rows)).all()
                and (bl[:, 1] == np.repeat(y0, cols)).all()
                and (tl[:, 1] == np.repeat(y1, cols)).all()):
            return None
        columns, lines = _grid_axis(x0, x1), _grid_axis(-y1, -y0)
        if columns is None or lines is None:
            return None
        (w, gx), (h, gy) = columns, lines
        res = screens.resolutions[0]
        edges = tuple(tuple(map(float, e)) for e in (x0, x1, y0, y1))
        try:
            return cls(cols, rows, (w, h), (gx, gy), float(-z[0, 0]), screens.near, screens.far,
                       (int(res[0]), int(res[1])), given_as_screens=True, edges=edges)
        except (ValueError, TypeError):
            return None

    def to_dict(self) -> dict:
        if self.given_as_screens:
            return {"screens": [{"bottom_left": [x0, y0, -self.distance],
                                 "bottom_right": [x1, y0, -self.distance],
                                 "top_left": [x0, y1, -self.distance],
                                 "resolution": list(self.resolution)}
                                for x0, x1, y0, y1 in map(self.tile_rect, range(self.tiles))],
                    "near": self.near, "far": self.far}
        return {
            "cols": self.cols, "rows": self.rows, "tile_size": list(self.tile_size),
            "gap": list(self.gap), "distance": self.distance, "near": self.near,
            "far": self.far, "resolution": list(self.resolution),
        }

    def check_eye(self, eye: np.ndarray, what: str = "frame eye") -> None:
        """An eye must be strictly in front of the wall (SPEC section 3), and near enough for
        float64 to tell a tile's edges apart (:func:`check_resolvable`)."""
        if not eye[2] > -self.distance + self.near:
            raise InputError(
                f"{what} z={eye[2]:g} is not in front of the wall: it must exceed "
                f"-distance + near = {-self.distance + self.near:g}")
        size, corners, reach = self._resolution
        if size < RESOLVABLE * (math.hypot(*eye.tolist()) + reach):  # else far enough
            check_resolvable(eye, size, np.linalg.norm(corners - eye, axis=1).max(), "a tile",
                             what)

    @cached_property
    def _resolution(self) -> tuple[float, np.ndarray, float]:
        """A tile's least side, the wall's corners and their farthest from the origin."""
        (x0, x1), (y0, y1) = self.col_edges[[0, -1], [0, 1]], self.row_edges[[-1, 0], [0, 1]]
        corners = np.array([[x, y, -self.distance] for x in (x0, x1) for y in (y0, y1)])
        return min(self.tile_size), corners, float(np.linalg.norm(corners, axis=1).max())

    @property
    def tiles(self) -> int:
        return self.cols * self.rows

    @property
    def size(self) -> tuple[float, float]:
        """Total width and height ``(W, H)`` of the wall, meters."""
        if self.edges is not None:
            x0, x1, y0, y1 = self.edges
            return x1[-1] - x0[0], y1[0] - y0[-1]
        (w, h), (gx, gy) = self.tile_size, self.gap
        return self.cols * w + (self.cols - 1) * gx, self.rows * h + (self.rows - 1) * gy

    @cached_property
    def col_edges(self) -> np.ndarray:
        """``(cols, 2)``: ``x0, x1`` of each column's visible area, display space."""
        if self.edges is not None:
            return np.array(self.edges[:2]).T
        w, gx = self.tile_size[0], self.gap[0]
        x0 = -self.size[0] / 2 + np.arange(self.cols) * (w + gx)
        return np.stack([x0, x0 + w], axis=1)

    @cached_property
    def row_edges(self) -> np.ndarray:
        """``(rows, 2)``: ``y0, y1`` of each row's visible area; row 0 is the top row."""
        if self.edges is not None:
            return np.array(self.edges[2:]).T
        h, gy = self.tile_size[1], self.gap[1]
        y1 = self.size[1] / 2 - np.arange(self.rows) * (h + gy)
        return np.stack([y1 - h, y1], axis=1)

    def tile_rect(self, tile: int) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` of a tile's visible rectangle in the wall plane."""
        r, c = divmod(int(tile), self.cols)
        return (*self.col_edges[c], *self.row_edges[r])

    @cached_property
    def resolutions(self) -> np.ndarray:
        """``(tiles, 2)``: every tile's pixels (all alike on a grid)."""
        return np.tile(np.array(self.resolution, np.int64), (self.tiles, 1))

    @cached_property
    def layout(self) -> "PlaneLayout":
        return PlaneLayout(self.cols, self.rows)

    @cached_property
    def hierarchy(self) -> "FrustumHierarchy":
        return FrustumHierarchy.build(self)


def _grid_axis(lo: np.ndarray, hi: np.ndarray) -> tuple[float, float] | None:
    """``(size, gap)`` of one axis of a grid whose tiles span ``lo[i]..hi[i]`` in order, or
    None if they are not a grid's: alike in size and spacing, centred on the display origin
    (within 1e-9 of the wall's extent: corners read from a file are rounded; the tiles keep
    their own edges). Bezels that small are none: neighbours then share their split planes, as
    a grid's do, which only widens a tile by its bezel. An overlap that small stays an
    overlap unless it is rounding (a few ulps): a shared plane would cut it off the second
    tile, a wedge that widens with depth. Gaps must not change sign (bezels, or overlap)."""
    extent = float(hi[-1] - lo[0])
    scale = max(extent, abs(float(lo[0])), abs(float(hi[-1])))
    tol, rounding = 1e-9 * scale, 8 * np.finfo(float).eps * scale
    sizes, gaps = hi - lo, lo[1:] - hi[:-1]
    size = float(sizes.mean())
    if np.ptp(sizes) > tol or abs(lo[0] + hi[-1]) > tol or size <= 0:
        return None
    if not len(gaps) or ((gaps >= -rounding) & (gaps <= tol)).all():
        return size, 0.0
    if np.ptp(gaps) > tol or not ((gaps >= 0).all() or (gaps <= 0).all()):
        return None
    return size, float(gaps.mean())


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
    return matrix_quaternions(np.asarray(m, dtype=np.float64)[None])[0]


def matrix_quaternions(m: np.ndarray) -> np.ndarray:
    """:func:`matrix_quaternion` of each rotation matrix ``m (V, 3, 3)``: ``(V, 4)``. (A
    screens wall's tiles each have a view of their own: 72 of them one by one in Python took
    0.6 ms a frame.)"""
    return _quaternions(np.ascontiguousarray(m, dtype=np.float64))


@njit(cache=True)
def _quaternions(m):
    out = np.empty((m.shape[0], 4))
    q = np.empty(4)
    for v in range(m.shape[0]):
        trace = m[v, 0, 0] + m[v, 1, 1] + m[v, 2, 2]
        best, k = 1 + trace, 0
        for j in range(3):
            square = 1 + 2 * m[v, j, j] - trace
            if square > best:
                best, k = square, j + 1
        q[k] = math.sqrt(best) / 2
        s = 1 / (4 * q[k])
        a, b, c = (m[v, 2, 1] - m[v, 1, 2]) * s, (m[v, 0, 2] - m[v, 2, 0]) * s, \
            (m[v, 1, 0] - m[v, 0, 1]) * s
        xy, xz, yz = (m[v, 0, 1] + m[v, 1, 0]) * s, (m[v, 0, 2] + m[v, 2, 0]) * s, \
            (m[v, 1, 2] + m[v, 2, 1]) * s
        if k == 0:
            q[1], q[2], q[3] = a, b, c
        elif k == 1:
            q[0], q[2], q[3] = a, xy, xz
        elif k == 2:
            q[0], q[1], q[3] = b, xy, yz
        else:
            q[0], q[1], q[2] = c, xz, yz
        norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        sign = -1.0 if q[0] < 0 else 1.0  # w >= 0
        for j in range(4):
            out[v, j] = sign * (q[j] / norm)
    return out


@dataclass(frozen=True)
class Frame:
    """Where display space sits in the world for one frame, and the tracked eye (SPEC section 3),
    or two eyes for a stereo frame."""

    position: np.ndarray  # (3,) world position of the display-space origin
    orientation: np.ndarray  # (4,) unit quaternion w, x, y, z
    eye: np.ndarray  # (3,) tracked head, display space
    rotation: np.ndarray = field(repr=False)  # (3, 3) R(q)
    stereo: tuple | None = None  # (ipd, head quaternion (4,)) of a stereo frame

    @classmethod
    def from_dict(cls, spec: Any, wall) -> "Frame":
        """A frame from its document (SPEC section 3; a dict, or a validated
        :class:`~wallcull.documents.FrameSpec`) on ``wall``: refused in one line when it is
        not one, or when an eye is not in front of the wall (of every screen)."""
        doc = documents.parse(documents.FrameSpec, spec, "frame")
        stereo = None if doc.stereo is None else (doc.stereo.ipd, doc.stereo.head)
        return cls.make(doc.position, doc.orientation, doc.eye, wall, stereo)

    @classmethod
    def make(cls, position, orientation, eye, wall, stereo=None) -> "Frame":
        """A frame of valid numbers (a document's, or a camera path's): the quaternions
        normalized, every eye checked against the wall."""
        position = np.asarray(position, dtype=np.float64).reshape(3)
        q = np.asarray(orientation, dtype=np.float64).reshape(4)
        q = q / np.linalg.norm(q)
        eye = np.asarray(eye, dtype=np.float64).reshape(3)
        if stereo is not None:
            head = np.asarray(stereo[1], np.float64).reshape(4)
            stereo = (float(stereo[0]), head / np.linalg.norm(head))
        frame = cls(position, q, eye, quaternion_matrix(q), stereo)
        if stereo is None:
            wall.check_eye(eye)
        else:
            for name, e in zip(("left eye", "right eye"), frame.eyes):
                wall.check_eye(e, f"frame {name}")
        return frame

    @cached_property
    def eyes(self) -> np.ndarray:
        """``(1, 3)``, or ``(2, 3)`` left and right for a stereo frame: ``eye -+ (ipd / 2)
        R(head) e_x`` (SPEC section 3), display space."""
        if self.stereo is None:
            return self.eye[None]
        ipd, head = self.stereo
        across = quaternion_matrix(head)[:, 0] * (ipd / 2)
        return np.stack([self.eye - across, self.eye + across])

    def to_dict(self) -> dict:
        out = {"position": self.position.tolist(), "orientation": self.orientation.tolist(),
               "eye": self.eye.tolist()}
        if self.stereo is not None:
            out["stereo"] = {"ipd": self.stereo[0], "head": self.stereo[1].tolist()}
        return out

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
    """One frame's frusta: the plane table in world space and what indexes it.

    Grid walls: :class:`PlaneLayout`'s table, for one eye or (stereo) holding both eyes'
    frusta (:mod:`wallcull.stereo`). Screens walls: each tile's six planes, then the frustum
    hierarchy's split planes, then the primary bound (:mod:`wallcull.screens`); ``valid`` says
    which splits separate their screens from this eye, and a stereo frame has ``per_eye``, one
    :class:`Frusta` per eye, culled apart and merged."""

    wall: Any
    frame: Frame
    planes: np.ndarray  # (rows, 4), world space
    eye: np.ndarray | None = None  # the eye (display space) the table is for; None: frame.eye
    primary_rows: np.ndarray | None = None  # screens: the rows of the primary bound
    valid: np.ndarray | None = None  # screens: per hierarchy node, its split holds this frame
    per_eye: tuple = ()  # screens, stereo: one Frusta per eye

    def __post_init__(self):
        if self.eye is None:
            object.__setattr__(self, "eye", self.frame.eye)

    @classmethod
    def build(cls, wall, frame: Frame) -> "Frusta":
        if wall.kind == "grid":
            if frame.stereo is None:
                planes = _plane_table(wall.col_edges, wall.row_edges, frame.eye, wall.distance,
                                      wall.near, wall.far, frame.rotation, frame.position)
            else:
                from .stereo import grid_planes

                planes = _to_world(grid_planes(wall, frame.eyes), frame)
            return cls(wall, frame, planes)
        if frame.stereo is not None:
            eyes = tuple(cls.for_eye(wall, frame, e) for e in frame.eyes)
            return cls(wall, frame, eyes[0].planes, frame.eye, eyes[0].primary_rows,
                       eyes[0].valid, eyes)
        return cls.for_eye(wall, frame, frame.eye)

    @classmethod
    def for_eye(cls, wall, frame: Frame, eye: np.ndarray) -> "Frusta":
        """A screens wall's table for one eye."""
        tiles = wall.tile_planes(eye).reshape(-1, 4)
        splits, valid = wall.hierarchy.split_planes(wall, eye)
        primary = wall.primary_planes(eye)
        table = np.concatenate([tiles, splits, primary])
        rows = len(tiles) + len(splits) + np.arange(len(primary))
        return cls(wall, frame, _to_world(table, frame), eye, rows, valid)

    @property
    def primary(self) -> np.ndarray:
        """The planes of the primary bound (for a grid, the primary frustum's six)."""
        if self.wall.kind == "grid":
            return self.planes[self.wall.layout.primary_planes]
        return self.planes[self.primary_rows]

    def tile(self, tile: int) -> np.ndarray:
        """``(6, 4)`` planes of one tile frustum."""
        if self.wall.kind == "grid":
            return self.planes[self.wall.layout.tile_planes[tile]]
        return self.planes[6 * tile:6 * tile + 6]

    @property
    def tile_rows(self) -> np.ndarray:
        """``(tiles, 6)`` rows of every tile's planes: left, right, top, bottom, near, far."""
        if self.wall.kind == "grid":
            return self.wall.layout.tile_planes
        return np.arange(6 * self.wall.tiles).reshape(-1, 6)


def _to_world(planes: np.ndarray, frame: Frame) -> np.ndarray:
    """Display-space planes ``(k, 4)`` in the frame's world: under ``p' = R p + t``."""
    n = planes[:, :3] @ frame.rotation.T
    return np.concatenate([n, (planes[:, 3] - n @ frame.position)[:, None]], axis=1)


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
        # 2 tiles - 1 nodes (every split has two children), written in place: a 256 x 256
        # wall's as Python lists took 24 MB more at their peak than this table's 5 MB
        table = np.full((2 * wall.tiles - 1, 10), -1, np.int32, order="F")
        count = 0

        def add(c0, c1, r0, r1, depth) -> int:
            nonlocal count
            index, count = count, count + 1
            nc, nr = c1 - c0, r1 - r0
            if nc == 1 and nr == 1:
                table[index] = c0, c1, r0, r1, -1, -1, -1, -1, r0 * wall.cols + c0, depth
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
            table[index] = c0, c1, r0, r1, a, b, *planes, -1, depth
            return index

        add(0, wall.cols, 0, wall.rows, 0)
        return cls(*(table[:, i] for i in range(10)))  # columns of a Fortran array: contiguous

    def __len__(self) -> int:
        return len(self.tile)

    @property
    def height(self) -> int:
        return int(self.depth.max())
