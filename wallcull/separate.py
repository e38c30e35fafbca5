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
separated on any is not in the frustum, and dropped. A unit that lies wholly between the tile's
near and far planes of a tile whose frustum is a pyramid from the eye takes a cheaper test that
is just as exact (:func:`_outline`): seen from the eye, it meets the frustum when its outline on
the image meets the tile's rectangle, so the only axes left are the planes through the eye and
each edge of its outline, worked out once per unit and frame for all the tiles it is listed in
(a 64 x 64 wall lists a cluster in about ten); half the time of the axes above on 64 x 64. (A
stereo tile's frustum, around both eyes' views, is no pyramid from one eye: it takes the axes
above.) A unit that reaches behind the near plane, as those around the camera do from inside,
has no outline from the eye; the part of it in front of the near plane has, and it is that
part that can meet the frustum (:func:`_clipped_outline`; on a 64 x 64 wall seen from inside
it finds two thirds of its pairs apart, a tenth off the cull). Conservative: the frustum's
corners come from its planes, the box's reach includes its ball, and a separation counts only
when the gap exceeds a margin relative to the coordinates. Applied the same way after every
method, so the methods still agree where they agreed.

Two shortcuts, with the same answers. ``adaptive`` tells the pass which of a tile's planes cut
each pair it lists (it tested them), so the pass does not test them again (:func:`_open`). And
on a grid, every tile's near face is a rectangle along the view's right and up directions:
the outline planes go through the eye, so a plane has the whole frustum beyond it when it has
that rectangle beyond it (the far corners lie further out on the same rays), one test a
plane rather than eight corners (:func:`_outside_rect`; its margin a little wider: on 15
frames of a 64 x 64 wall it kept 25 pairs in 513,556 that the corners would drop).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import workers
from .quad import _hull

#: A gap along an axis separates only beyond this share of the coordinates' magnitude.
MARGIN = 1e-9
#: Bounds whose sphere spans less than this share of a tile's angular size are not tested: on
#: the power plant's orbit (small parts, seen whole) that skips 85% of the tests for a third of
#: the drops; on the satellite's fly path (large clusters up close) it keeps 99% of the drops.
SMALL = 0.5
#: Pairs a thread is given at least: below, handing them over costs more than it saves.
THREAD_PAIRS = 4096
#: Rows of a clipped outline (:func:`_clipped_outline`): a box cut by a plane has at most 14
#: vertices in front of it, and their hull as many edges.
_CLIPPED = 14
#: A box's corners (bits: the sign along each axis) and its twelve edges as pairs of them.
_EDGES = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4],
                   [1, 5], [2, 6], [3, 7]], np.int64)


def drop_all(nodes, regions, count, box, planes, tile_rows, child_count, eye, small,
             scratch: list, cuts: np.ndarray | None = None, basis: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """The first ``count`` pairs ``(nodes, regions)`` but the separated ones
    (:func:`drop_separated`), in threads over chunks of pairs on a frame with many (a 64 x 64
    wall lists tens of thousands, most of them cut by two of their small tile's planes).
    ``scratch``: the tiles' corners and the units' outline planes, and per thread which it
    knows, kept between frames. The threads share the corners (12.6 MB on 256 x 256) and the
    planes: a thread reads a tile's or a unit's only after it wrote them itself, and another
    thread that writes them at the same time writes the same numbers. ``cuts``: per pair, the
    tile's planes the traversal found cutting the node (bits, see :func:`_open`), when it
    tells them; else the pass tests the planes again. ``basis``: rows ``x, y, forward`` of the
    view (unit vectors) when every tile's near face is a rectangle along ``x`` and ``y`` (a
    grid's): the outline test then takes each tile's rectangle, not its corners
    (:func:`_outside_rect`)."""
    parts = 1 if count < 2 * THREAD_PAIRS else min(workers.count(), count // THREAD_PAIRS)
    tiles = len(tile_rows)
    if not scratch:
        scratch += [np.empty((tiles, 8, 3)), np.empty((len(box), 6, 5)),
                    np.empty(len(box), np.int64), np.empty((tiles, 7)),
                    np.empty((len(box), 6, 5))]
    while len(scratch) < _SHARED + parts:
        n = len(box)
        scratch.append((np.zeros(tiles, np.uint8), np.zeros(n, np.uint8),
                        np.empty((n, _CLIPPED, 5)), np.empty(n, np.int64), np.empty(n, np.int64),
                        np.empty((n, _CLIPPED, 5))))
    corners, axes, axis_count, rects, flat = scratch[:_SHARED]
    basis = _NO_BASIS if basis is None else np.ascontiguousarray(basis, np.float64)

    def chunk(k, a, b):  # pairs [a, b) compacted in place; returns where they end
        known, known_unit, clipped, clipped_count, clipped_by, flat_clipped = scratch[_SHARED + k]
        known[:] = 0
        known_unit[:] = 0
        return a + drop_separated(nodes[a:b], regions[a:b], b - a, box, planes, tile_rows,
                                  child_count, eye, small, corners, known, axes, axis_count,
                                  known_unit, clipped, clipped_count, clipped_by,
                                  _NO_CUTS if cuts is None else cuts[a:b], basis, rects, flat,
                                  flat_clipped)

    if parts == 1:  # most frames: no thread to hand over to
        kept = chunk(0, 0, count)
        return nodes[:kept], regions[:kept]
    ranges = [(count * k // parts, count * (k + 1) // parts) for k in range(parts)]
    ends = workers.run(chunk, ranges)  # each chunk's kept pairs at its start: copied as runs
    return (np.concatenate([nodes[a:end] for (a, _), end in zip(ranges, ends)]),
            np.concatenate([regions[a:end] for (a, _), end in zip(ranges, ends)]))


@njit(cache=True, nogil=True)
def drop_separated(nodes, regions, count, box, planes, tile_rows, child_count, eye, small,
                   corners, known, axes, axis_count, known_unit, clipped, clipped_count,
                   clipped_by, cuts, basis, rects, flat, flat_clipped):
    """Keep the first ``count`` pairs ``(nodes[j], regions[j])`` but those whose node has no
    children, is not small (its sphere's radius over its distance from ``eye`` at least
    ``small``) and is found apart from the tile's frustum: by its outline when it lies between
    the near and far planes of a pyramid from ``eye``, else by :func:`_separated` when two of
    the tile's planes or more cut it, its centre outside one. Compacts the arrays in place and
    returns how many pairs are left.
    A unit the near plane cuts (and the far plane does not), in such a pyramid, is first
    tested by the outline of its part in front of the near plane (:func:`_clipped_outline`),
    and by the axes only if that finds no gap.
    Scratch: ``corners (tiles, 8, 3)`` and ``known (tiles,)``, each tile's frustum corners;
    ``axes (nodes, 6, 5)``, ``axis_count (nodes,)`` and ``known_unit (nodes,)``, each unit's
    outline planes (:func:`_outline`; ``known_unit`` bit 1); ``clipped (nodes, _CLIPPED,
    5)``, ``clipped_count`` and ``clipped_by (nodes,)``, the outline of its part in front of
    near plane ``clipped_by`` (bit 2: a pair with that plane seen; bit 4: its outline made);
    each computed when first needed. ``cuts``: see :func:`drop_all` (empty when not told).
    ``basis``: see :func:`drop_all` (empty when there is none); then ``rects (tiles, 7)``, each
    tile's near face in it (:func:`_rect`), and ``flat (nodes, 6, 5)`` and ``flat_clipped
    (nodes, _CLIPPED, 5)``, each unit's outline planes in it (:func:`_flat`), computed with
    the corners and the planes."""
    h = np.empty(3)  # scratch of _separated
    u = np.empty((3, 3))
    local = np.empty((8, 3))
    corner = np.empty((8, 4))  # scratch of _clipped_outline
    rel = np.empty((_CLIPPED, 3))
    img = np.empty((_CLIPPED, 2))
    told = cuts.shape[0] > 0  # the traversal's cuts
    grid = basis.shape[0] > 0  # tiles' near faces as rectangles
    k = 0
    for j in range(count):
        i = nodes[j]
        t = regions[j]
        keep = True
        # (one plane cutting it, as told, decides: see _undecided)
        if child_count[i] == 0 and (not told or cuts[j] & (cuts[j] - 1)) and \
                _large(box, i, eye, small):
            cut = _open(cuts[j], box, i, planes, tile_rows, t) if told else \
                _undecided(box, i, planes, tile_rows, t)
            if cut and not known[t]:
                known[t] = _frustum(planes, tile_rows, t, corners, eye)
                if known[t] == _CONE and grid:
                    _rect(corners, t, eye, basis, rects)
            if cut == _SIDES and known[t] == _CONE:  # its outline decides (see the module)
                if not known_unit[i] & 1:
                    known_unit[i] |= 1
                    axis_count[i] = _outline(box, i, eye, axes)
                    if grid:
                        _flat(axes, axis_count[i], i, eye, basis, flat)
                keep = not (_outside_rect(flat, axis_count, i, rects, t, eye, box)
                            if grid else
                            _outside(axes, axis_count, i, corners, t, eye, box))
            elif cut == _DEPTH and known[t] == _CONE and _near_only(box, i, planes, tile_rows,
                                                                    t):
                # its outline in front of the near plane, from its second pair with that
                # plane on (a unit with one, as on a CAVE's screens, is cheaper by the axes)
                near = tile_rows[t, 4]
                apart = False
                if not (known_unit[i] & 6 and clipped_by[i] == near):
                    known_unit[i] = (known_unit[i] & 1) | 2
                    clipped_by[i] = near
                else:
                    if not known_unit[i] & 4:
                        known_unit[i] |= 4
                        clipped_count[i] = _clipped_outline(box, i, eye, planes, near, clipped,
                                                            corner, rel, img)
                        if grid:
                            _flat(clipped, clipped_count[i], i, eye, basis, flat_clipped)
                    apart = clipped_count[i] > 0 and (
                        _outside_rect(flat_clipped, clipped_count, i, rects, t, eye, box)
                        if grid else
                        _outside(clipped, clipped_count, i, corners, t, eye, box))
                keep = not apart and not _separated(box, i, corners, t, h, u, local)
            elif cut and known[t] != _NONE:
                keep = not _separated(box, i, corners, t, h, u, local)
        if keep:
            nodes[k] = i
            regions[k] = t
            k += 1
    return k


@njit(cache=True, _nrt=False)
def _rect(corners, t, eye, basis, rects):
    """Into ``rects[t]``: a box around tile ``t``'s near corners seen from ``eye`` in
    ``basis`` (``x0, x1, y0, y1, f0, f1``: their offsets from the eye along its rows), and
    their largest ``|c|_1`` (the outline test's margin grows with it). Each number is written
    once, final: another thread may be reading the row (see :func:`drop_all`)."""
    largest = 0.0
    for c in range(0, 8, 2):  # the near corners
        largest = max(largest, abs(corners[t, c, 0]) + abs(corners[t, c, 1])
                      + abs(corners[t, c, 2]))
    for a in range(3):
        lo, hi = np.inf, -np.inf
        for c in range(0, 8, 2):
            d = (basis[a, 0] * (corners[t, c, 0] - eye[0]) + basis[a, 1] * (corners[t, c, 1]
                 - eye[1]) + basis[a, 2] * (corners[t, c, 2] - eye[2]))
            lo, hi = min(lo, d), max(hi, d)
        rects[t, 2 * a], rects[t, 2 * a + 1] = lo, hi
    rects[t, 6] = largest


@njit(cache=True, _nrt=False)
def _flat(axes, count, i, eye, basis, flat):
    """Into ``flat[i]``: unit ``i``'s outline planes (:func:`_outline`) in ``basis``: per
    plane its normal's components along the rows, how far the bound reaches past the plane
    through the eye (at least 0: the far corners' argument of :func:`_outside_rect` needs
    it, and more only makes the test stricter), and ``|n|_1``."""
    for q in range(count):
        for a in range(3):
            flat[i, q, a] = (axes[i, q, 0] * basis[a, 0] + axes[i, q, 1] * basis[a, 1]
                             + axes[i, q, 2] * basis[a, 2])
        through = axes[i, q, 0] * eye[0] + axes[i, q, 1] * eye[1] + axes[i, q, 2] * eye[2]
        flat[i, q, 3] = max(0.0, axes[i, q, 3] - through)
        flat[i, q, 4] = axes[i, q, 4]


@njit(cache=True, inline="always")
def _scale(eye, box, i):
    """The size of the coordinates an outline test of unit ``i`` works with, beside a corner's
    own: the eye's and the unit's centre's ``|.|_1`` and its ball; its margin grows with it."""
    return abs(eye[0]) + abs(eye[1]) + abs(eye[2]) + abs(box[i, 0]) + abs(box[i, 1]) \
        + abs(box[i, 2]) + box[i, 13]


@njit(cache=True, inline="always")
def _outside_rect(flat, axis_count, i, rects, t, eye, box) -> bool:
    """:func:`_outside` with tile ``t``'s near face as the box ``rects[t]`` (:func:`_rect`):
    every point of that box, each near corner among them, lies beyond one of the planes by
    the margin of its largest near corner, with three times the share of the eye's and the
    unit's coordinates; then its far corners, ``m`` times as far out on the same rays from the
    eye, lie beyond by ``m`` times that, more than their own margin. One test a plane, not
    eight."""
    base = _scale(eye, box, i)
    for q in range(axis_count[i]):
        gap = -flat[i, q, 3]
        for a in range(3):
            n = flat[i, q, a]
            gap += n * (rects[t, 2 * a] if n > 0 else rects[t, 2 * a + 1])
        if gap > MARGIN * flat[i, q, 4] * (rects[t, 6] + 3 * base):
            return True
    return False


@njit(cache=True, inline="always")
def _large(box, i, eye, small) -> bool:
    """Whether bound ``i`` is not small as seen from ``eye``: a small one can reach past a
    frustum's edges only a little, and is seldom worth the test."""
    d2 = (box[i, 0] - eye[0]) ** 2 + (box[i, 1] - eye[1]) ** 2 + (box[i, 2] - eye[2]) ** 2
    return box[i, 13] ** 2 >= small * small * d2


#: What :func:`_undecided` found: the planes decide (the bound meets the frustum), they leave
#: it open with the near and far planes holding it whole, or with one of those cutting it.
_DECIDED, _SIDES, _DEPTH = 0, 1, 2


@njit(cache=True, inline="always")
def _undecided(box, i, planes, rows, t) -> int:
    """Whether the planes ``rows[t]`` (left, right, top, bottom, near, far) leave it open that
    bound ``i`` (listed: outside none of them) misses the frustum, and if so whether the near
    or far plane cuts it (``_DEPTH``) or not (``_SIDES``). It meets the frustum when its
    centre is inside every plane, or when one plane alone cuts it (the others hold it whole):
    then the box's part on that plane's inner side lies in the frustum."""
    cuts = 0
    out = False
    depth = False
    for q in range(rows.shape[1]):
        s, r = _offset(box, i, planes, rows[t, q])
        out = out or s < 0
        cuts += s < r
        depth = depth or (q >= 4 and s < r)
    if not (out and cuts > 1):
        return _DECIDED
    return _DEPTH if depth else _SIDES


_NO_CUTS = np.zeros(0, np.int64)
_NO_BASIS = np.zeros((0, 3))
#: The scratch arrays all threads of :func:`drop_all` share (then one tuple per thread).
_SHARED = 5


@njit(cache=True, inline="always")
def _open(cut, box, i, planes, rows, t) -> int:
    """:func:`_undecided` from the planes ``rows[t]`` that the traversal found cutting bound
    ``i`` (bits ``cut``: left, right, top, bottom, near, far): only their centre distances
    are left to work out (a centre outside a plane puts the bound across it)."""
    cuts = 0
    out = False
    for q in range(6):
        if cut >> q & 1:
            cuts += 1
            p = rows[t, q]
            nx, ny, nz = planes[p, 0], planes[p, 1], planes[p, 2]
            out = out or nx * box[i, 0] + ny * box[i, 1] + nz * box[i, 2] + planes[p, 3] < 0
    if not (out and cuts > 1):
        return _DECIDED
    return _DEPTH if cut & 48 else _SIDES


@njit(cache=True, inline="always")
def _offset(box, i, planes, p):
    """Bound ``i``'s centre's signed distance from plane ``p``, and its reach across it."""
    nx, ny, nz = planes[p, 0], planes[p, 1], planes[p, 2]
    s = nx * box[i, 0] + ny * box[i, 1] + nz * box[i, 2] + planes[p, 3]
    r = (abs(nx * box[i, 4] + ny * box[i, 5] + nz * box[i, 6])
         + abs(nx * box[i, 7] + ny * box[i, 8] + nz * box[i, 9])
         + abs(nx * box[i, 10] + ny * box[i, 11] + nz * box[i, 12]) + box[i, 3])
    return s, r


#: What :func:`_frustum` found of a tile: a pyramid from the eye, corners of another shape
#: (a stereo tile's, around both eyes' views), no corners.
_CONE, _OTHER, _NONE = 1, 2, 3


@njit(cache=True, _nrt=False)
def _frustum(planes, rows, t, corners, eye) -> int:
    """Tile ``t``'s frustum's corners into ``corners[t]`` (:func:`_corners`), and whether its
    edges from near to far lie on rays from ``eye`` (the outline test needs its apex)."""
    if not _corners(planes, rows, t, corners):
        return _NONE
    for e in range(4):
        ax, ay, az = (corners[t, 2 * e, 0] - eye[0], corners[t, 2 * e, 1] - eye[1],
                      corners[t, 2 * e, 2] - eye[2])
        bx, by, bz = (corners[t, 2 * e + 1, 0] - eye[0], corners[t, 2 * e + 1, 1] - eye[1],
                      corners[t, 2 * e + 1, 2] - eye[2])
        cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        if not (ax * bx + ay * by + az * bz > 0.0 and cx * cx + cy * cy + cz * cz
                <= 1e-18 * (ax * ax + ay * ay + az * az) * (bx * bx + by * by + bz * bz)):
            return _OTHER
    return _CONE


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


@njit(cache=True, _nrt=False)
def _outline(box, i, eye, axes) -> int:
    """Into ``axes[i]``: a plane through ``eye`` and each edge of bound ``i``'s outline as seen
    from there (rows ``nx, ny, nz, w, s``: a normal ``n`` facing away from the box, ``w = n .
    eye`` plus the bound's reach past the plane (its ball: the box itself touches it) and ``s``
    the normal's length or more, ``|n|_1``); how many (4 when the eye faces one side of the
    box, else 6; 0 when the eye is within it or it is flat). An edge is on the outline when
    one of its two sides faces the eye and the other does not. With the eye outside a box
    that lies in front of it, the tile's frustum meets the box when no plane of its own and
    none of these has the two apart: the sides of their images on a screen, the tile's
    rectangle and the box's outline (:func:`_outside`)."""
    for a in range(3):
        if box[i, 4 + 3 * a] == 0.0 and box[i, 5 + 3 * a] == 0.0 and box[i, 6 + 3 * a] == 0.0:
            return 0
    f0, f1, f2 = _facing(box, i, eye, 0), _facing(box, i, eye, 1), _facing(box, i, eye, 2)
    n_axes = _edges_along(box, i, eye, 1, 2, 0, f1, f2, axes, 0)
    n_axes = _edges_along(box, i, eye, 2, 0, 1, f2, f0, axes, n_axes)
    n_axes = _edges_along(box, i, eye, 0, 1, 2, f0, f1, axes, n_axes)
    return max(n_axes, 0)


@njit(cache=True, inline="always")
def _edges_along(box, i, eye, a, b, c, fa, fb, axes, n_axes) -> int:
    """The rows of :func:`_outline` for the edges along axis ``c`` with one side facing the
    eye (``fa``, ``fb``: :func:`_facing` of axes ``a`` and ``b``): two, or none."""
    if fa == 0 and fb == 0:
        return n_axes  # neither side of a nor of b faces it
    if fb == 0:
        sa, sb, ta, tb = fa, -1, fa, 1
    elif fa == 0:
        sa, sb, ta, tb = -1, fb, 1, fb
    else:
        sa, sb, ta, tb = fa, -fb, -fa, fb
    n_axes = _edge_plane(box, i, eye, a, b, c, sa, sb, axes, n_axes)
    return _edge_plane(box, i, eye, a, b, c, ta, tb, axes, n_axes)


@njit(cache=True, inline="always")
def _edge_plane(box, i, eye, a, b, c, sa, sb, axes, n_axes) -> int:
    """Row ``n_axes`` of ``axes[i]`` (see :func:`_outline`): the plane through ``eye`` and the
    edge of bound ``i`` along its axis ``c`` on side ``sa`` of axis ``a`` and ``sb`` of ``b``;
    the rows then written, -1 if none could be (the eye on the edge's line)."""
    if n_axes < 0:
        return n_axes
    # a point of the edge (its middle) from the eye, and its direction
    mx = box[i, 0] + sa * box[i, 4 + 3 * a] + sb * box[i, 4 + 3 * b] - eye[0]
    my = box[i, 1] + sa * box[i, 5 + 3 * a] + sb * box[i, 5 + 3 * b] - eye[1]
    mz = box[i, 2] + sa * box[i, 6 + 3 * a] + sb * box[i, 6 + 3 * b] - eye[2]
    ex, ey, ez = box[i, 4 + 3 * c], box[i, 5 + 3 * c], box[i, 6 + 3 * c]
    nx, ny, nz = my * ez - mz * ey, mz * ex - mx * ez, mx * ey - my * ex
    # no square root: the margin and the ball scale with n's largest length, |n|_1
    size = abs(nx) + abs(ny) + abs(nz)
    if not size > 0.0:
        return -1
    cx, cy, cz = box[i, 0] - eye[0], box[i, 1] - eye[1], box[i, 2] - eye[2]
    if nx * cx + ny * cy + nz * cz > 0.0:
        nx, ny, nz = -nx, -ny, -nz  # away from the box: its centre on the other side
    # the box's reach past the plane (its support along n, from the eye: about 0)
    reach = nx * cx + ny * cy + nz * cz
    for e in range(3):
        reach += abs(nx * box[i, 4 + 3 * e] + ny * box[i, 5 + 3 * e] + nz * box[i, 6 + 3 * e])
    axes[i, n_axes, 0], axes[i, n_axes, 1], axes[i, n_axes, 2] = nx, ny, nz
    axes[i, n_axes, 3] = nx * eye[0] + ny * eye[1] + nz * eye[2] + max(reach, 0.0) \
        + box[i, 3] * size
    axes[i, n_axes, 4] = size
    return n_axes + 1


@njit(cache=True, inline="always")
def _near_only(box, i, planes, rows, t) -> bool:
    """Whether tile ``t``'s near plane cuts bound ``i`` and its far plane does not."""
    s, r = _offset(box, i, planes, rows[t, 4])
    if not s < r:
        return False
    s, r = _offset(box, i, planes, rows[t, 5])
    return not s < r


@njit(cache=True)
def _clipped_outline(box, i, eye, planes, p, out, corner, rel, img) -> int:
    """Into ``out[i]``, as :func:`_outline`'s rows: the planes through ``eye`` and each edge of
    the outline, seen from ``eye``, of the part of bound ``i`` (its box grown by its ball) in
    front of plane ``p`` (inward normal; ``eye`` behind it: a pyramid's near plane). A frustum
    from ``eye`` lies in front of its near plane, so it meets the bound only within that part,
    and only inside these planes: each is moved out to the part's farthest vertex, so that
    rounding in the outline can only make it looser. How many (0: none to be had, and the
    caller falls back to the axes: the eye not behind the plane, a box flat to nothing, a
    part flat or empty). Scratch: ``corner (8, 4)``, ``rel (_CLIPPED, 3)``, ``img (_CLIPPED,
    2)``."""
    nx, ny, nz, nd = planes[p, 0], planes[p, 1], planes[p, 2], planes[p, 3]
    length = math.sqrt(nx * nx + ny * ny + nz * nz)
    if not (length > 0.0 and nx * eye[0] + ny * eye[1] + nz * eye[2] + nd < 0.0):
        return 0
    nx, ny, nz, nd = nx / length, ny / length, nz / length, nd / length
    for c in range(8):
        for k in range(3):
            corner[c, k] = box[i, k]
    for a in range(3):
        h = math.sqrt(box[i, 4 + 3 * a] ** 2 + box[i, 5 + 3 * a] ** 2 + box[i, 6 + 3 * a] ** 2)
        if h == 0.0:
            return 0
        grow = 1.0 + box[i, 3] / h
        for c in range(8):
            sign = grow if c & (4 >> a) else -grow
            for k in range(3):
                corner[c, k] += sign * box[i, 4 + 3 * a + k]
    for c in range(8):  # column 3: the distance in front of the plane
        corner[c, 3] = nx * corner[c, 0] + ny * corner[c, 1] + nz * corner[c, 2] + nd
    # the part's vertices, from the eye: the corners in front, and where edges cross the plane
    m = 0
    for c in range(8):
        if corner[c, 3] >= 0.0:
            for k in range(3):
                rel[m, k] = corner[c, k] - eye[k]
            m += 1
    for e in range(12):
        a, b = _EDGES[e, 0], _EDGES[e, 1]
        if (corner[a, 3] >= 0.0) != (corner[b, 3] >= 0.0):
            w = corner[a, 3] / (corner[a, 3] - corner[b, 3])
            for k in range(3):
                rel[m, k] = corner[a, k] + w * (corner[b, k] - corner[a, k]) - eye[k]
            m += 1
    if m < 3:
        return 0
    # their images on a plane parallel to p at unit distance from the eye, in a basis (u, v)
    if abs(nx) < 0.9:
        ux, uy, uz = 0.0, nz, -ny
    else:
        ux, uy, uz = -nz, 0.0, nx
    ul = math.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / ul, uy / ul, uz / ul
    vx, vy, vz = ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux  # n x u
    for q in range(m):
        depth = nx * rel[q, 0] + ny * rel[q, 1] + nz * rel[q, 2]
        if not depth > 0.0:
            return 0
        img[q, 0] = (ux * rel[q, 0] + uy * rel[q, 1] + uz * rel[q, 2]) / depth
        img[q, 1] = (vx * rel[q, 0] + vy * rel[q, 1] + vz * rel[q, 2]) / depth
    hull = _hull(img[:m])
    n_hull = hull.shape[0]
    if n_hull < 3:
        return 0
    for h in range(n_hull):  # counter-clockwise: the inside on the left of each edge
        a, b = hull[h], hull[(h + 1) % n_hull]
        ax = img[a, 0] * ux + img[a, 1] * vx + nx
        ay = img[a, 0] * uy + img[a, 1] * vy + ny
        az = img[a, 0] * uz + img[a, 1] * vz + nz
        bx = img[b, 0] * ux + img[b, 1] * vx + nx
        by = img[b, 0] * uy + img[b, 1] * vy + ny
        bz = img[b, 0] * uz + img[b, 1] * vz + nz
        ox, oy, oz = by * az - bz * ay, bz * ax - bx * az, bx * ay - by * ax  # b x a: outward
        size = abs(ox) + abs(oy) + abs(oz)
        if not size > 0.0:
            return 0
        reach = 0.0  # the part's support past the plane (about 0: rounding)
        for q in range(m):
            reach = max(reach, ox * rel[q, 0] + oy * rel[q, 1] + oz * rel[q, 2])
        out[i, h, 0], out[i, h, 1], out[i, h, 2] = ox, oy, oz
        out[i, h, 3] = ox * eye[0] + oy * eye[1] + oz * eye[2] + reach
        out[i, h, 4] = size
    return n_hull


@njit(cache=True, inline="always")
def _facing(box, i, eye, a) -> int:
    """+1 (-1) when ``eye`` is past bound ``i``'s face on the + (-) side of its axis ``a``,
    else 0."""
    d = ((eye[0] - box[i, 0]) * box[i, 4 + 3 * a] + (eye[1] - box[i, 1]) * box[i, 5 + 3 * a]
         + (eye[2] - box[i, 2]) * box[i, 6 + 3 * a])  # the offset along a, times its extent
    h2 = box[i, 4 + 3 * a] ** 2 + box[i, 5 + 3 * a] ** 2 + box[i, 6 + 3 * a] ** 2
    return 1 if d > h2 else (-1 if d < -h2 else 0)


@njit(cache=True, _nrt=False)
def _outside(axes, axis_count, i, corners, t, eye, box) -> bool:
    """Whether every corner of tile ``t``'s frustum lies beyond one of unit ``i``'s outline
    planes (:func:`_outline`), by the margin of its own coordinates (the corners near the eye,
    where the planes meet, are only a near plane's distance beyond them)."""
    base = _scale(eye, box, i)
    for q in range(axis_count[i]):
        beyond = True
        for c in range(8):
            x, y, z = corners[t, c, 0], corners[t, c, 1], corners[t, c, 2]
            gap = axes[i, q, 0] * x + axes[i, q, 1] * y + axes[i, q, 2] * z - axes[i, q, 3]
            if not gap > MARGIN * axes[i, q, 4] * (abs(x) + abs(y) + abs(z) + base):
                beyond = False
                break
        if beyond:
            return True
    return False
