"""Culling for two eyes at once (SPEC sections 3 and 5): a leaf either eye sees in a tile is
listed.

For a grid wall the two eyes' frusta of a tile share its rectangle, and each boundary of the
tile (the line of one of its edges) bounds the two frusta by two planes that pivot about that
line: before the screen one eye's wedge reaches farther out, beyond it the other's. Neither
plane holds both frusta, but a plane through the outermost of the four segments where the eyes'
boundary faces meet their near and far planes does: the two frusta lie between their near and
far planes, so each face lies between its two segments, and all four segments are parallel to
the edge. :func:`grid_planes` builds the frame's plane table from such planes, laid out as for
one eye (:class:`~wallcull.wall.PlaneLayout`), so the wall's frustum hierarchy culls for both
eyes in one pass; the two planes of a split are no longer one plane negated, so both are tested.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


def _outer_lines(points: np.ndarray, inward: np.ndarray) -> np.ndarray:
    """For sets of 4 points ``(k, 4, 2)``, the line ``(k, 3)`` (``a x + b y + c >= 0`` inside,
    ``(a, b)`` unit) through two of them with all four inside and ``(a, b) . inward > 0``,
    the tightest such (least total distance of the points); the supporting line of their
    hull on the outward side."""
    best, found = _outer_kernel(np.ascontiguousarray(points, np.float64),
                                np.asarray(inward, np.float64))
    if not found:
        raise ValueError("no supporting line: the eyes' frusta are degenerate")
    return best


@njit(cache=True)
def _outer_kernel(points, inward):
    k = points.shape[0]
    best = np.zeros((k, 3))
    found = True
    for m in range(k):
        scale = 0.0
        for i in range(4):
            scale = max(scale, abs(points[m, i, 0]), abs(points[m, i, 1]))
        score = np.inf
        for i in range(4):
            for j in range(i + 1, 4):
                px, py = points[m, i, 0], points[m, i, 1]
                nx, ny = -(points[m, j, 1] - py), points[m, j, 0] - px
                length = math.sqrt(nx * nx + ny * ny)
                if not length > 1e-12 * max(scale, 1e-300):
                    continue
                nx, ny = nx / length, ny / length
                if nx * inward[0] + ny * inward[1] < 0:
                    nx, ny = -nx, -ny
                c = -(nx * px + ny * py)
                total, lowest = 0.0, np.inf
                for q in range(4):
                    dist = nx * points[m, q, 0] + ny * points[m, q, 1] + c
                    total += dist
                    lowest = min(lowest, dist)
                if lowest >= -1e-12 * scale and total < score:
                    score = total
                    best[m, 0], best[m, 1], best[m, 2] = nx, ny, c
        if not score < np.inf:
            found = False
            continue
        # every point inside, exactly: push the line out by what rounding left outside
        lowest = 0.0
        for q in range(4):
            lowest = min(lowest, best[m, 0] * points[m, q, 0] + best[m, 1] * points[m, q, 1]
                         + best[m, 2])
        best[m, 2] -= lowest
    return best, found


@njit(cache=True)
def _boundary_points(edge: np.ndarray, eyes: np.ndarray, depth: float, near: float,
                     far: float, axis: int) -> np.ndarray:
    """``(k, 4, 2)``: where each eye's boundary face through the edge lines at ``edge``
    (coordinates along display ``axis``, in the wall plane ``z = -depth``) meets its near and
    far planes, in the cross-section (``axis`` coordinate, z)."""
    out = np.empty((edge.shape[0], 4, 2))
    for k in range(edge.shape[0]):
        for i in range(2):
            e, ez = eyes[i, axis], eyes[i, 2]
            reach = ez + depth  # eye to wall along -z
            for j in range(2):
                dist = near if j == 0 else far
                out[k, 2 * i + j, 0] = e + (edge[k] - e) * dist / reach
                out[k, 2 * i + j, 1] = ez - dist
    return out


def grid_planes(wall, eyes: np.ndarray) -> np.ndarray:
    """The plane table of a grid wall seen by ``eyes (2, 3)`` (display space, the layout of
    :class:`~wallcull.wall.PlaneLayout`): each plane holds both eyes' frusta on its inside."""
    lay = wall.layout
    out = np.zeros((lay.count, 4))
    x0, x1 = wall.col_edges[:, 0], wall.col_edges[:, 1]
    y0, y1 = wall.row_edges[:, 0], wall.row_edges[:, 1]
    for edges, axis, inward, rows in ((x0, 0, +1.0, lay.L(np.arange(wall.cols))),
                                      (x1, 0, -1.0, lay.R(np.arange(wall.cols))),
                                      (y1, 1, -1.0, lay.T(np.arange(wall.rows))),
                                      (y0, 1, +1.0, lay.B(np.arange(wall.rows)))):
        points = _boundary_points(np.ascontiguousarray(edges), np.asarray(eyes, np.float64),
                                  float(wall.distance), float(wall.near), float(wall.far), axis)
        lines = _outer_lines(points, np.array([inward, 0.0]))
        out[rows, axis] = lines[:, 0]
        out[rows, 2] = lines[:, 1]
        out[rows, 3] = lines[:, 2]
    out[lay.near] = (0.0, 0.0, -1.0, eyes[:, 2].max() - wall.near)  # z <= nearest eye - near
    out[lay.far] = (0.0, 0.0, 1.0, wall.far - eyes[:, 2].min())  # z >= farthest eye - far
    return out
