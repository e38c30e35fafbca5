"""Separating axes: the last word on a cluster that a tile's planes cut.

A bound is culled when it lies outside one of a frustum's planes. That test is conservative but
not exact: a box near a frustum's edge or corner can reach past every plane's outer side only
in places the frustum does not reach, and then it is listed though it does not meet the
frustum. Small boxes rarely do this; the clusters of a mesh close to the camera, as wide as
several tiles, often do (measured on the fly path through the satellite: two clusters in five
that a tile listed had no triangle in its frustum).

So every culled frame ends with one compiled pass (:func:`drop_separated`; on big frames in
threads over chunks of pairs, :func:`drop_all`) over the listed (unit, tile) pairs, units being
the nodes without children (clusters, and leaves not cut into clusters): a unit that the tile's
planes cut is tested against the tile's frustum by the separating axis theorem, on the axes the
plane test leaves out: the box's three axes and the cross products of its edges with the
frustum's edges. Two convex bodies that do not meet are separated along one of them, so a unit
separated on any is not in the frustum, and dropped. Conservative: the frustum's corners come
from its planes, the box's reach includes its ball, and a separation counts only when the gap
exceeds a margin relative to the coordinates. Applied the same way after every method, so the
methods still agree where they agreed.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import workers

#: A gap along an axis separates only beyond this share of the coordinates' magnitude.
MARGIN = 1e-9
#: Bounds whose sphere spans less than this share of a tile's angular size are not tested: on
#: the power plant's orbit (small parts, seen whole) that skips 85% of the tests for a third of
#: the drops; on the satellite's fly path (large clusters up close) it keeps 99% of the drops.
SMALL = 0.5
#: Pairs a thread is given at least: below, handing them over costs more than it saves.
THREAD_PAIRS = 4096


def drop_all(nodes, regions, count, box, planes, tile_rows, child_count, eye, small,
             scratch: list) -> tuple[np.ndarray, np.ndarray]:
    """The first ``count`` pairs ``(nodes, regions)`` but the separated ones
    (:func:`drop_separated`), in threads over chunks of pairs on a frame with many (a 64 x 64
    wall lists tens of thousands, most of them cut by two of their small tile's planes).
    ``scratch``: the tiles' corners, and per thread which it knows, kept between frames. The
    threads share the corners (12.6 MB on 256 x 256): a thread reads a tile's only after it
    wrote them itself, and another thread that writes them at the same time writes the same
    numbers."""
    parts = 1 if count < 2 * THREAD_PAIRS else min(workers.count(), count // THREAD_PAIRS)
    tiles = len(tile_rows)
    if not scratch:
        scratch.append(np.empty((tiles, 8, 3)))
    while len(scratch) < parts + 1:
        scratch.append(np.zeros(tiles, np.uint8))
    corners = scratch[0]

    def chunk(k, a, b):  # pairs [a, b) compacted in place; returns where they end
        known = scratch[1 + k]
        known[:] = 0
        return a + drop_separated(nodes[a:b], regions[a:b], b - a, box, planes, tile_rows,
                                  child_count, eye, small, corners, known)

    if parts == 1:  # most frames: no thread to hand over to
        kept = chunk(0, 0, count)
        return nodes[:kept], regions[:kept]
    ranges = [(count * k // parts, count * (k + 1) // parts) for k in range(parts)]
    ends = workers.run(chunk, ranges)
    keep = np.concatenate([np.arange(a, end) for (a, _), end in zip(ranges, ends)])
    return nodes[keep], regions[keep]


@njit(cache=True, nogil=True)
def drop_separated(nodes, regions, count, box, planes, tile_rows, child_count, eye, small,
                   corners, known):
    """Keep the first ``count`` pairs ``(nodes[j], regions[j])`` but those whose node has no
    children, is cut by two of its tile's planes or more, its centre outside one, is not small
    (its sphere's
    radius over its distance from ``eye`` at least ``small``) and is separated from the tile's
    frustum; compacts the arrays in place and returns how many pairs are left.
    ``corners (tiles, 8, 3)`` and ``known (tiles,)`` are scratch: each tile's frustum corners,
    computed when first needed."""
    h = np.empty(3)  # scratch of _separated
    u = np.empty((3, 3))
    local = np.empty((8, 3))
    k = 0
    for j in range(count):
        i = nodes[j]
        t = regions[j]
        keep = True
        if child_count[i] == 0 and _large(box, i, eye, small) \
                and _undecided(box, i, planes, tile_rows, t):
            if not known[t]:
                known[t] = 1 if _corners(planes, tile_rows, t, corners) else 2
            if known[t] == 1 and _separated(box, i, corners, t, h, u, local):
                keep = False
        if keep:
            nodes[k] = i
            regions[k] = t
            k += 1
    return k


@njit(cache=True, inline="always")
def _large(box, i, eye, small) -> bool:
    """Whether bound ``i`` is not small as seen from ``eye``: a small one can reach past a
    frustum's edges only a little, and is seldom worth the test."""
    d2 = (box[i, 0] - eye[0]) ** 2 + (box[i, 1] - eye[1]) ** 2 + (box[i, 2] - eye[2]) ** 2
    return box[i, 13] ** 2 >= small * small * d2


@njit(cache=True, inline="always")
def _undecided(box, i, planes, rows, t) -> bool:
    """Whether the planes ``rows[t]`` leave it open that bound ``i`` (listed: outside none of
    them) misses the frustum. It meets it when its centre is inside every plane, or when one
    plane alone cuts it (the others hold it whole): then the box's part on that plane's inner
    side lies in the frustum."""
    cuts = 0
    out = False
    for q in range(rows.shape[1]):
        p = rows[t, q]
        nx, ny, nz = planes[p, 0], planes[p, 1], planes[p, 2]
        s = nx * box[i, 0] + ny * box[i, 1] + nz * box[i, 2] + planes[p, 3]
        r = (abs(nx * box[i, 4] + ny * box[i, 5] + nz * box[i, 6])
             + abs(nx * box[i, 7] + ny * box[i, 8] + nz * box[i, 9])
             + abs(nx * box[i, 10] + ny * box[i, 11] + nz * box[i, 12]) + box[i, 3])
        out = out or s < 0
        cuts += s < r
    return out and cuts > 1


@njit(cache=True, _nrt=False)
def _corners(planes, rows, t, out) -> bool:
    """Into ``out[t]``: the eight corners of the frustum bounded by ``rows[t]`` (left, right,
    top, bottom, near, far), corner ``4 a + 2 b + c`` on side ``a`` (left, right), ``b`` (top,
    bottom) and ``c`` (near, far). False when three of the planes do not meet in one point.
    (Tiles' rows and corners are passed as arrays and an index, never as views: a view's
    reference count is an atomic operation, which was a fifth of a 64 x 64 wall's cull.)"""
    for a in range(2):
        for b in range(2):
            for c in range(2):
                p, q, r = rows[t, a], rows[t, 2 + b], rows[t, 4 + c]
                # the point on all three planes n . x + d = 0 (Cramer's rule)
                qx = planes[q, 1] * planes[r, 2] - planes[q, 2] * planes[r, 1]
                qy = planes[q, 2] * planes[r, 0] - planes[q, 0] * planes[r, 2]
                qz = planes[q, 0] * planes[r, 1] - planes[q, 1] * planes[r, 0]
                det = planes[p, 0] * qx + planes[p, 1] * qy + planes[p, 2] * qz
                if not abs(det) > 1e-12 or not math.isfinite(det):
                    return False
                rx = planes[r, 1] * planes[p, 2] - planes[r, 2] * planes[p, 1]
                ry = planes[r, 2] * planes[p, 0] - planes[r, 0] * planes[p, 2]
                rz = planes[r, 0] * planes[p, 1] - planes[r, 1] * planes[p, 0]
                px = planes[p, 1] * planes[q, 2] - planes[p, 2] * planes[q, 1]
                py = planes[p, 2] * planes[q, 0] - planes[p, 0] * planes[q, 2]
                pz = planes[p, 0] * planes[q, 1] - planes[p, 1] * planes[q, 0]
                dp, dq, dr = planes[p, 3], planes[q, 3], planes[r, 3]
                k = 4 * a + 2 * b + c
                out[t, k, 0] = -(dp * qx + dq * rx + dr * px) / det
                out[t, k, 1] = -(dp * qy + dq * ry + dr * py) / det
                out[t, k, 2] = -(dp * qz + dq * rz + dr * pz) / det
    return True


@njit(cache=True, _nrt=False)
def _separated(box, i, corners, t, h, u, local) -> bool:
    """Whether bound ``i`` and the frustum of ``corners[t]`` lie apart along one of the box's axes
    or the cross product of one with a frustum edge (the frustum's face normals are the planes
    already tested). Worked in the box's frame: the corners' coordinates along its axes once,
    then each axis is a few products. The edges: the four from near to far, and two of the near
    face's (the other two are parallel to them on a tile's frustum; on any other, fewer axes
    only find fewer separations). First, though, an edge from near to far that passes inside
    the box shrunk by the margin shows that the two meet (no axis can then find a gap beyond
    the margin, so the answer is the same, sooner): most boxes tested do meet the frustum,
    and on 64 x 64 this skips the axes for most of them. ``h``, ``u``, ``local``: scratch."""
    for a in range(3):
        h[a] = math.sqrt(box[i, 4 + 3 * a] ** 2 + box[i, 5 + 3 * a] ** 2 + box[i, 6 + 3 * a] ** 2)
        if h[a] == 0.0:
            return False  # a sphere, or a box flat to nothing: not worth it
        for k in range(3):
            u[a, k] = box[i, 4 + 3 * a + k] / h[a]
    ball = box[i, 3]
    scale = abs(box[i, 0]) + abs(box[i, 1]) + abs(box[i, 2]) + box[i, 13]
    for c in range(8):
        scale = max(scale, abs(corners[t, c, 0]) + abs(corners[t, c, 1]) + abs(corners[t, c, 2]))
        for a in range(3):
            local[c, a] = ((corners[t, c, 0] - box[i, 0]) * u[a, 0]
                           + (corners[t, c, 1] - box[i, 1]) * u[a, 1]
                           + (corners[t, c, 2] - box[i, 2]) * u[a, 2])
    gap = MARGIN * scale
    for e in range(4):  # most boxes tested meet the frustum: show it, and skip the axes
        if _crosses(local, 2 * e, 2 * e + 1, h, gap):
            return False
    for a in range(3):  # the box's own axes
        lo = np.inf
        hi = -np.inf
        for c in range(8):
            lo = min(lo, local[c, a])
            hi = max(hi, local[c, a])
        if lo > h[a] + ball + gap or hi < -h[a] - ball - gap:
            return True
    for e in range(6):
        if e < 4:
            p, q = 2 * e, 2 * e + 1  # corners (side, side, near) and (side, side, far)
        else:
            p, q = 0, 2 if e == 4 else 4  # two edges of the near face at corner 0
        ex = local[q, 0] - local[p, 0]
        ey = local[q, 1] - local[p, 1]
        ez = local[q, 2] - local[p, 2]
        for a in range(3):
            # n = edge x axis a, in the box's frame: two of its components, the third zero
            if a == 0:
                n1, n2, b1, b2 = ez, -ey, 1, 2
            elif a == 1:
                n1, n2, b1, b2 = -ez, ex, 0, 2
            else:
                n1, n2, b1, b2 = ey, -ex, 0, 1
            norm = math.sqrt(n1 * n1 + n2 * n2)
            if norm == 0.0:
                continue
            reach = h[b1] * abs(n1) + h[b2] * abs(n2) + (ball + gap) * norm
            lo = np.inf
            hi = -np.inf
            for c in range(8):
                v = local[c, b1] * n1 + local[c, b2] * n2
                lo = min(lo, v)
                hi = max(hi, v)
            if lo > reach or hi < -reach:
                return True
    return False


@njit(cache=True, inline="always")
def _crosses(local, p, q, h, gap) -> bool:
    """Whether the segment from corner ``p`` to corner ``q`` (``local``: the box's frame)
    passes inside the box of half extents ``h - gap`` (the slab test)."""
    t0 = 0.0
    t1 = 1.0
    for a in range(3):
        half = h[a] - gap
        if not half > 0.0:
            return False
        start = local[p, a]
        step = local[q, a] - start
        if step == 0.0:
            if abs(start) >= half:
                return False
            continue
        enter = (-half - start) / step
        leave = (half - start) / step
        if enter > leave:
            enter, leave = leave, enter
        t0 = max(t0, enter)
        t1 = min(t1, leave)
        if not t0 < t1:
            return False
    return True
