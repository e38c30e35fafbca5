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


@njit(cache=True)
def _outer_line(points, ix, iy, line) -> bool:
    """For 4 points ``(4, 2)``, the line (``a x + b y + c >= 0`` inside, ``(a, b)`` unit)
    through two of them with all four inside and ``(a, b) . (ix, iy) > 0``, the tightest such
    (least total distance of the points): the supporting line of their hull on the outward
    side, into ``line (3,)``. False when there is none (degenerate frusta)."""
    scale = 0.0
    for i in range(4):
        scale = max(scale, abs(points[i, 0]), abs(points[i, 1]))
    score = np.inf
    for i in range(4):
        for j in range(i + 1, 4):
            px, py = points[i, 0], points[i, 1]
            nx, ny = -(points[j, 1] - py), points[j, 0] - px
            length = math.sqrt(nx * nx + ny * ny)
            if not length > 1e-12 * max(scale, 1e-300):
                continue
            nx, ny = nx / length, ny / length
            if nx * ix + ny * iy < 0:
                nx, ny = -nx, -ny
            c = -(nx * px + ny * py)
            total, lowest = 0.0, np.inf
            for q in range(4):
                dist = nx * points[q, 0] + ny * points[q, 1] + c
                total += dist
                lowest = min(lowest, dist)
            if lowest >= -1e-12 * scale and total < score:
                score = total
                line[0], line[1], line[2] = nx, ny, c
    if not score < np.inf:
        return False
    # every point inside, exactly: push the line out by what rounding left outside
    lowest = 0.0
    for q in range(4):
        lowest = min(lowest, line[0] * points[q, 0] + line[1] * points[q, 1] + line[2])
    line[2] -= lowest
    return True


@njit(cache=True)
def _edge_lines(edges, axes, inward, eyes, depth, near, far):
    """For each tile edge, at ``edges[k]`` along display axis ``axes[k]`` in the wall plane
    ``z = -depth``, the line (in the cross-section: that axis' coordinate, z) bounding both
    eyes' boundary faces through it on the ``inward[k]`` side: through the outermost of the
    four points where each eye's face meets its near and far planes. ``(k, 3)``, and whether
    every edge had one."""
    lines = np.zeros((edges.shape[0], 3))
    points = np.empty((4, 2))
    found = True
    for k in range(edges.shape[0]):
        axis = axes[k]
        for i in range(2):
            e, ez = eyes[i, axis], eyes[i, 2]
            reach = ez + depth  # eye to wall along -z
            for j in range(2):
                dist = near if j == 0 else far
                points[2 * i + j, 0] = e + (edges[k] - e) * dist / reach
                points[2 * i + j, 1] = ez - dist
        found &= _outer_line(points, inward[k], 0.0, lines[k])
    return lines, found


def grid_planes(wall, eyes: np.ndarray) -> np.ndarray:
    """The plane table of a grid wall seen by ``eyes (2, 3)`` (display space, the layout of
    :class:`~wallcull.wall.PlaneLayout`): each plane holds both eyes' frusta on its inside."""
    lay = wall.layout
    cols, rows = np.arange(wall.cols), np.arange(wall.rows)
    # the tiles' L, R, T and B edges: where, along which axis, facing which way, which rows
    edges = np.concatenate([wall.col_edges[:, 0], wall.col_edges[:, 1], wall.row_edges[:, 1],
                            wall.row_edges[:, 0]])
    axes = np.repeat([0, 0, 1, 1], [wall.cols, wall.cols, wall.rows, wall.rows])
    inward = np.repeat([1.0, -1.0, -1.0, 1.0], [wall.cols, wall.cols, wall.rows, wall.rows])
    rows_of = np.concatenate([lay.L(cols), lay.R(cols), lay.T(rows), lay.B(rows)])
    lines, found = _edge_lines(edges, axes, inward, np.asarray(eyes, np.float64),
                               float(wall.distance), float(wall.near), float(wall.far))
    if not found:
        raise ValueError("no supporting line: the eyes' frusta are degenerate")
    out = np.zeros((lay.count, 4))
    out[rows_of, axes] = lines[:, 0]
    out[rows_of, 2] = lines[:, 1]
    out[rows_of, 3] = lines[:, 2]
    out[lay.near] = (0.0, 0.0, -1.0, eyes[:, 2].max() - wall.near)  # z <= nearest eye - near
    out[lay.far] = (0.0, 0.0, 1.0, wall.far - eyes[:, 2].min())  # z >= farthest eye - far
    return out
