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

import numpy as np


def _outer_lines(points: np.ndarray, inward: np.ndarray) -> np.ndarray:
    """For sets of 4 points ``(k, 4, 2)``, the line ``(k, 3)`` (``a x + b y + c >= 0`` inside,
    ``(a, b)`` unit) through two of them with all four inside and ``(a, b) . inward > 0``,
    the tightest such (least total distance of the points); the supporting line of their
    hull on the outward side."""
    k = len(points)
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    best = np.zeros((k, 3))
    score = np.full(k, np.inf)
    scale = np.abs(points).max(axis=(1, 2))
    for i, j in pairs:
        p, q = points[:, i], points[:, j]
        d = q - p
        normal = np.stack([-d[:, 1], d[:, 0]], axis=1)
        length = np.linalg.norm(normal, axis=1)
        ok = length > 1e-12 * np.maximum(scale, 1e-300)
        normal = normal / np.where(ok, length, 1)[:, None]
        flip = (normal * inward).sum(axis=1) < 0
        normal[flip] *= -1
        c = -(normal * p).sum(axis=1)
        dist = (points * normal[:, None]).sum(axis=2) + c[:, None]
        ok &= dist.min(axis=1) >= -1e-12 * scale
        total = dist.sum(axis=1)
        better = ok & (total < score)
        best[better] = np.c_[normal, c][better]
        score[better] = total[better]
    if not np.isfinite(score).all():
        raise ValueError("no supporting line: the eyes' frusta are degenerate")
    # every point inside, exactly: push the line out by what rounding left outside
    dist = (points * best[:, None, :2]).sum(axis=2) + best[:, None, 2]
    best[:, 2] -= np.minimum(dist.min(axis=1), 0)
    return best


def _boundary_points(edge: np.ndarray, eyes: np.ndarray, depth: float, near: float,
                     far: float, axis: int) -> np.ndarray:
    """``(k, 4, 2)``: where each eye's boundary face through the edge lines at ``edge``
    (coordinates along display ``axis``, in the wall plane ``z = -depth``) meets its near and
    far planes, in the cross-section (``axis`` coordinate, z)."""
    out = []
    for eye in eyes:
        e, ez = eye[axis], eye[2]
        reach = ez + depth  # eye to wall along -z
        for dist in (near, far):
            out.append(np.stack([e + (edge - e) * dist / reach,
                                 np.full(len(edge), ez - dist)], axis=1))
    return np.stack(out, axis=1)


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
        points = _boundary_points(edges, eyes, wall.distance, wall.near, wall.far, axis)
        lines = _outer_lines(points, np.array([inward, 0.0]))
        out[rows, axis] = lines[:, 0]
        out[rows, 2] = lines[:, 1]
        out[rows, 3] = lines[:, 2]
    out[lay.near] = (0.0, 0.0, -1.0, eyes[:, 2].max() - wall.near)  # z <= nearest eye - near
    out[lay.far] = (0.0, 0.0, 1.0, wall.far - eyes[:, 2].min())  # z >= farthest eye - far
    return out
