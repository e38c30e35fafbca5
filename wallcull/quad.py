"""Bounding quadrilaterals of convex polygons (Low & Ilie, section 3, and beyond).

A polygon is an ``(n, 2)`` float64 array of vertices in counter-clockwise (CCW) order. Every
function here returns CCW vertices; quadrilaterals have shape ``(4, 2)``.

* :func:`convex_hull_2d` / :func:`hull_indices`: Andrew's monotone chain;
* :func:`greedy_quad`: the paper's greedy edge removal, O(n log n) with a heap;
* :func:`refine_quad`: beyond the paper, a local optimization of a bounding quad (each side
  rotated and pivoted along the hull to its best position given its neighbours);
* :func:`best_quad_exhaustive`: the reference: the smallest quad with three sides flush with
  hull edges and the fourth at its optimum, O(n^4);
* :func:`bounding_quad`: hull -> greedy -> refine, what :mod:`wallcull.lowilie` calls;
* :func:`quad_area`, :func:`contains`, :func:`ratio_report` (``python -m wallcull.quad``).

Why numba, and why not Qhull: the greedy removal and the refinement are sequential loops over
hull vertices. For a 1,000-vertex hull the greedy removal with ``heapq`` in pure Python takes
3.4 ms, and ``scipy.spatial.ConvexHull`` (Qhull) 0.64 ms when all 1,000 points are on the hull
(measured), against a budget of 1 ms for a whole Low-Ilie fit; numpy cannot vectorize either
loop. The compiled kernels take 30 us (hull), 95 us (greedy) and 30 us (refine) there (see
:func:`bench_quad`). They are pure functions of arrays, cached on disk (``cache=True``). The
monotone chain also gives degenerate input a defined answer where Qhull raises; the tests check
it against Qhull on everything Qhull accepts.

Sides of bounding quads are kept as *supporting lines* of the hull (a point on the line and a
direction): the quad is the intersection of four half-planes that each contain the hull, so it
contains the hull by construction, whatever the rounding in the corner computations.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "hull_indices",
    "convex_hull_2d",
    "quad_area",
    "contains",
    "greedy_quad",
    "refine_quad",
    "best_quad_exhaustive",
    "bounding_quad",
    "ratio_report",
    "bench_quad",
]

#: :func:`hull_indices` may leave out points that lie within this fraction of the input's
#: diameter from the hull it returns (near-duplicates, near-collinear middle points), so that
#: hull edges are never shorter than that and turns never vanishingly small.
COLLINEAR = 1e-12

#: The directions whose extreme points make the octagon of the Akl-Toussaint filter: the
#: minima of x, x + y, y, y - x, -x, ... in turn, which are the octagon's vertices in CCW
#: order from the leftmost.
OCTANTS = np.array([[1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [-1.0, 1.0], [-1.0, 0.0],
                    [-1.0, -1.0], [0.0, -1.0], [1.0, -1.0]])

#: Two lines whose directions' cross product is at most this fraction of the product of their
#: lengths are treated as parallel: they do not intersect (no division by ~0).
PARALLEL = 1e-12


# -------------------------------------------------------------------------------- convex hull


@njit(cache=True)
def _monotone_chain(pts, order, eps):
    """Andrew's monotone chain over ``pts[order]`` (sorted by x, then y); CCW indices.

    A point within ``eps`` of the last hull vertex is skipped, and a middle vertex within
    ``eps`` of the segment past it is popped when the chain runs forward through it: a
    near-zero turn can also be a near-180-degree spike, whose tip is extreme and stays.
    """
    n = order.shape[0]
    out = np.empty(2 * n + 1, dtype=np.int64)
    k = 0
    rightmost = 0
    eps2 = eps * eps
    for step in range(2):  # 0: lower chain left to right, 1: upper chain right to left
        start = k + 1
        for jj in range(n):
            if step == 1 and jj == 0:
                continue  # the rightmost point ends the lower chain already
            j = order[jj] if step == 0 else order[n - 1 - jj]
            px, py = pts[j, 0], pts[j, 1]
            if k > 0:
                ex, ey = px - pts[out[k - 1], 0], py - pts[out[k - 1], 1]
                if ex * ex + ey * ey <= eps2:
                    continue
            while k >= (2 if step == 0 else start):
                ox, oy = pts[out[k - 2], 0], pts[out[k - 2], 1]
                ax, ay = pts[out[k - 1], 0] - ox, pts[out[k - 1], 1] - oy
                bx, by = px - ox, py - oy
                turn = ax * by - ay * bx
                if turn > 0.0:
                    forward = ax * (bx - ax) + ay * (by - ay) > 0.0
                    if not forward or turn * turn > eps2 * (bx * bx + by * by):
                        break
                k -= 1
            out[k] = j
            k += 1
        if step == 0:
            rightmost = k - 1
    return _drop_flat_vertices(pts, out[:max(k - 1, 1)], eps, rightmost)


@njit(cache=True)
def _drop_flat_vertices(pts, idx, eps, rightmost):
    """Remove hull vertices within ``eps`` of the chord of their neighbours (with the hull
    running forward through them). The chain's popping did this everywhere except at its two
    ends, the leftmost and rightmost points; a removal puts the neighbours up for review."""
    m = idx.shape[0]
    if m < 3:
        return idx
    prv = np.empty(m, dtype=np.int64)
    nxt = np.empty(m, dtype=np.int64)
    for i in range(m):
        prv[i] = i - 1 if i > 0 else m - 1
        nxt[i] = i + 1 if i + 1 < m else 0
    alive = np.ones(m, dtype=np.bool_)
    todo = np.empty(2 * m + 2, dtype=np.int64)
    todo[0], todo[1] = 0, min(rightmost, m - 1)
    top, count = 2, m
    while top > 0 and count >= 3:
        top -= 1
        i = todo[top]
        if not alive[i]:
            continue
        a, b, c = idx[prv[i]], idx[i], idx[nxt[i]]
        abx, aby = pts[b, 0] - pts[a, 0], pts[b, 1] - pts[a, 1]
        acx, acy = pts[c, 0] - pts[a, 0], pts[c, 1] - pts[a, 1]
        off = abs(acx * aby - acy * abx)  # |ac| x distance of b from the chord
        forward = abx * (acx - abx) + aby * (acy - aby) > 0.0
        if forward and off <= eps * math.hypot(acx, acy):
            alive[i] = False
            count -= 1
            nxt[prv[i]], prv[nxt[i]] = nxt[i], prv[i]
            todo[top], todo[top + 1] = prv[i], nxt[i]
            top += 2
    if count == m:
        return idx
    out = np.empty(count, dtype=np.int64)
    i = 0
    while not alive[i]:
        i += 1
    for t in range(count):
        out[t] = idx[i]
        i = nxt[i]
    return out


def hull_indices(points) -> np.ndarray:
    """Indices of the convex hull vertices of ``points`` ``(m, 2)``, CCW, starting at the
    lowest-x (then lowest-y) point. Collinear and repeated points on the hull are dropped, and
    so are points within ``COLLINEAR`` x diameter of the returned hull (see :data:`COLLINEAR`).

    Degenerate input: all points equal -> one index; all points on a line -> the two extreme
    points (two indices, lowest x/y first). Never raises for finite input with ``m >= 1``.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2 or len(points) == 0:
        raise ValueError(f"need points of shape (m, 2) with m >= 1, got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points must be finite")
    return _hull(points)


@njit(cache=True)
def _hull(points):
    """:func:`hull_indices`, compiled (for callers that are compiled too)."""
    keep, eps = _candidates(points)
    idx = _monotone_chain(points, _by_x_then_y(points, keep), eps)
    if idx.shape[0] == 2 and points[idx[0], 0] == points[idx[1], 0] \
            and points[idx[0], 1] == points[idx[1], 1]:
        idx = idx[:1]
    return idx


@njit(cache=True)
def _by_x_then_y(points, keep):
    """``keep`` (increasing indices) ordered by x, then y, then index: what two stable sorts
    (by y, then by x) give, for half their time. One sort by x, then each run of equal x put in
    order by y and index: by insertion where it is short (a few repeated points, the rule), by
    two sorts where it is long (a column of aligned boxes)."""
    x = points[:, 0]
    order = keep[np.argsort(x[keep])]
    n = order.shape[0]
    i = 0
    while i < n:
        j = i + 1
        while j < n and x[order[j]] == x[order[i]]:
            j += 1
        if j - i > 16:
            run = np.sort(order[i:j])
            order[i:j] = run[np.argsort(points[run, 1], kind="mergesort")]
            i = j
            continue
        for a in range(i + 1, j):  # insertion sort of the run [i, j)
            v = order[a]
            b = a - 1
            while b >= i and (points[order[b], 1] > points[v, 1]
                              or (points[order[b], 1] == points[v, 1] and order[b] > v)):
                order[b + 1] = order[b]
                b -= 1
            order[b + 1] = v
        i = j
    return order


@njit(cache=True)
def extremes(points):
    """For each ``k``, the index of the first of ``points`` ``(m, 2)`` with the least
    ``OCTANTS[k] . p``: the least x, x + y, y and y - x, then the greatest (zeros when
    ``m == 0``)."""
    e0 = e1 = e2 = e3 = e4 = e5 = e6 = e7 = 0
    lx, ls, ly, ld = np.inf, np.inf, np.inf, np.inf
    gx, gs, gy, gd = -np.inf, -np.inf, -np.inf, -np.inf
    for i in range(points.shape[0]):
        px, py = points[i, 0], points[i, 1]
        s, d = px + py, py - px
        if px < lx:
            lx, e0 = px, i
        if s < ls:
            ls, e1 = s, i
        if py < ly:
            ly, e2 = py, i
        if d < ld:
            ld, e3 = d, i
        if px > gx:
            gx, e4 = px, i
        if s > gs:
            gs, e5 = s, i
        if py > gy:
            gy, e6 = py, i
        if d > gd:
            gd, e7 = d, i
    return np.array([e0, e1, e2, e3, e4, e5, e6, e7])


@njit(cache=True)
def octagon(points, ext):
    """Edges ``(8, 3)`` (inward unit normal, offset) of the polygon of ``points[ext]``, the
    points extreme in x, x + y, y, y - x, ... (:func:`extremes`; counter-clockwise); zero rows
    for edges of no length."""
    edges = np.zeros((8, 3))
    for k in range(8):
        a, b = ext[k], ext[(k + 1) % 8]
        ex, ey = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1]
        length = math.hypot(ex, ey)
        if length > 0.0:
            edges[k, 0], edges[k, 1] = -ey / length, ex / length
            edges[k, 2] = edges[k, 0] * points[a, 0] + edges[k, 1] * points[a, 1]
    return edges


@njit(cache=True)
def _candidates(points):
    """Indices of the points that can be hull vertices, and ``eps``, :data:`COLLINEAR` times
    the diameter of their bounding box. Akl-Toussaint: a point farther than ``2 eps`` inside
    the octagon of the extreme points in x, y, x + y and x - y is not one, and is dropped
    before the sort. The octagon's vertices are input points, so the hull and the chain's
    collinearity decisions (within ``eps``) are the same as over all points."""
    m = points.shape[0]
    if m == 0:
        return np.arange(0), 0.0
    ext = extremes(points)  # the octagon's vertices
    lx, ly = points[ext[0], 0], points[ext[2], 1]
    gx, gy = points[ext[4], 0], points[ext[6], 1]
    eps = COLLINEAR * math.hypot(gx - lx, gy - ly)
    if m <= 16:
        return np.arange(m), eps
    edges = octagon(points, ext)
    nx, ny, off = edges[:, 0], edges[:, 1], np.full(8, -np.inf)
    for k in range(8):  # each edge's offset moved in by 2 eps
        if nx[k] != 0.0 or ny[k] != 0.0:
            off[k] = edges[k, 2] + 2 * eps
    if not np.isfinite(off).any():  # all points coincide: no inside to drop
        return np.arange(m), eps
    out = np.empty(m, np.int64)
    n = 0
    for i in range(m):
        px, py = points[i, 0], points[i, 1]
        for k in range(8):
            if nx[k] * px + ny[k] * py <= off[k]:  # not well inside: a candidate
                out[n] = i
                n += 1
                break
    return out[:n], eps


def convex_hull_2d(points) -> np.ndarray:
    """Convex hull vertices ``(k, 2)``, CCW (see :func:`hull_indices` for degenerate input:
    ``k == 1`` for coincident points, ``k == 2`` for collinear ones)."""
    points = np.asarray(points, dtype=np.float64)
    return points[hull_indices(points)]


# ---------------------------------------------------------------------------- small predicates


def quad_area(poly) -> float:
    """Signed area of a polygon ``(n, 2)`` (shoelace), positive when CCW."""
    return float(_polygon_area(np.ascontiguousarray(poly, dtype=np.float64).reshape(-1, 2)))


def _diameter(points: np.ndarray) -> float:
    """Diagonal of the bounding box of ``(n, 2)`` points (column-wise: ``max(axis=0)`` on an
    (n, 2) array is ~20x slower in numpy)."""
    x, y = points[:, 0], points[:, 1]
    return math.hypot(x.max() - x.min(), y.max() - y.min())


def contains(poly, points, tol: float = 1e-9) -> np.ndarray:
    """Which ``points`` ``(m, 2)`` lie in the convex CCW polygon ``poly`` ``(n, 2)``, ``(m,)`` bool.

    ``tol`` is relative to the diameter of ``poly`` and ``points`` together: a point within
    ``tol * diameter`` of the polygon counts as inside. Zero-length edges are ignored; a polygon
    of zero area (a point or a segment, as :func:`greedy_quad` returns for degenerate hulls)
    contains the points within that distance of it.
    """
    poly = np.asarray(poly, dtype=np.float64)
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    slack = tol * _diameter(np.concatenate([poly, points]))
    edges = np.roll(poly, -1, axis=0) - poly
    length = np.linalg.norm(edges, axis=1)
    keep = length > 0
    if not keep.any():  # a single point
        return np.linalg.norm(points - poly[0], axis=1) <= slack
    edges, starts, length = edges[keep], poly[keep], length[keep]
    px, py = points[:, 0:1], points[:, 1:2]  # (m, 1) against (k,) edges
    dist = (edges[:, 0] * (py - starts[:, 1]) - edges[:, 1] * (px - starts[:, 0])) / length
    inside = (dist >= -slack).all(axis=1)
    if abs(quad_area(poly)) <= slack * length.max():  # a segment: also bound its ends
        t = (edges[:, 0] * (px - starts[:, 0]) + edges[:, 1] * (py - starts[:, 1])) / length
        inside &= ((t >= -slack) & (t <= length + slack)).any(axis=1)
    return inside


# ------------------------------------------------------------------------------ greedy removal


@njit(cache=True, inline="always")
def _before(key, a, b):
    """Heap order: smaller key first, ties by smaller edge index (deterministic)."""
    ka, kb = key[a], key[b]
    return ka < kb or (ka == kb and a < b)


# A 4-ary heap: half the depth of a binary one, and the four children of a slot are adjacent in
# memory; measured 1.5x faster than a binary heap for the greedy removal at n = 1000.


@njit(cache=True)
def _sift_up(heap, pos, key, i):
    x = heap[i]
    while i > 0:
        parent = (i - 1) >> 2
        y = heap[parent]
        if not _before(key, x, y):
            break
        heap[i] = y
        pos[y] = i
        i = parent
    heap[i] = x
    pos[x] = i


@njit(cache=True)
def _sift_down(heap, pos, key, i, size):
    x = heap[i]
    while True:
        first = 4 * i + 1
        if first >= size:
            break
        best = first
        for c in range(first + 1, min(first + 4, size)):
            if _before(key, heap[c], heap[best]):
                best = c
        y = heap[best]
        if not _before(key, y, x):
            break
        heap[i] = y
        pos[y] = i
        i = best
    heap[i] = x
    pos[x] = i


@njit(cache=True)
def _removal_cost(ax, ay, bx, by, d1x, d1y, l1, d3x, d3y, l3):
    """Area added by removing the edge ``a -> b`` whose neighbours have directions d1 (before)
    and d3 (after), of lengths l1 and l3: the triangle between the edge and the neighbours'
    meeting point. ``inf`` when the neighbours do not meet beyond the edge (interior angles
    summing to <= 180 deg, or parallel within ``PARALLEL``): such an edge cannot be removed."""
    den = d1x * d3y - d1y * d3x
    if not den > PARALLEL * l1 * l3:
        return np.inf
    ex, ey = bx - ax, by - ay
    n1 = max(d1x * ey - d1y * ex, 0.0)  # cross(d1, e) >= 0 on a convex polygon, up to rounding
    n2 = max(ex * d3y - ey * d3x, 0.0)  # cross(e, d3)
    return 0.5 * n1 * n2 / den


@njit(cache=True)
def _greedy_kernel(hull):
    """Greedy edge removal on a CCW strictly convex hull with n >= 5 vertices; (4, 2) corners.

    Edge i runs from vertex i to i+1 and keeps its supporting line (hull[i], d[i]) throughout;
    what changes is its start corner (sx[i], sy[i]), where it meets its current predecessor.
    The heap is indexed (``pos[i]`` is edge i's slot), so a neighbour's new cost is sifted in
    place: n - 4 pops and 2 (n - 4) sifts, O(n log n). (Lazy deletion with version stamps does
    the same job with a heap three times larger; measured 3x slower at n = 1000.)
    """
    n = hull.shape[0]
    hx = hull[:, 0].copy()
    hy = hull[:, 1].copy()
    dx = np.empty(n)
    dy = np.empty(n)
    dl = np.empty(n)
    for i in range(n):
        j = i + 1 if i + 1 < n else 0
        dx[i] = hx[j] - hx[i]
        dy[i] = hy[j] - hy[i]
        dl[i] = math.sqrt(dx[i] * dx[i] + dy[i] * dy[i])
    sx = hx.copy()
    sy = hy.copy()
    prv = np.empty(n, dtype=np.int64)
    nxt = np.empty(n, dtype=np.int64)
    for i in range(n):
        prv[i] = i - 1 if i > 0 else n - 1
        nxt[i] = i + 1 if i + 1 < n else 0
    key = np.empty(n)
    for i in range(n):
        p, q = prv[i], nxt[i]
        key[i] = _removal_cost(sx[i], sy[i], sx[q], sy[q], dx[p], dy[p], dl[p],
                               dx[q], dy[q], dl[q])
    heap = np.arange(n)
    pos = np.arange(n)
    for i in range((n - 2) // 4, -1, -1):
        _sift_down(heap, pos, key, i, n)
    size = n
    while size > 4:
        i = heap[0]
        if key[i] == np.inf:  # impossible for a convex polygon with >= 5 sides (appendix)
            raise RuntimeError("greedy_quad: no removable edge; is the hull convex and CCW?")
        size -= 1
        heap[0] = heap[size]
        pos[heap[0]] = 0
        _sift_down(heap, pos, key, 0, size)
        p, q = prv[i], nxt[i]
        # The new corner from the original lines, not from corners computed earlier: no drift.
        den = dx[p] * dy[q] - dy[p] * dx[q]
        s = ((hx[q] - hx[p]) * dy[q] - (hy[q] - hy[p]) * dx[q]) / den
        sx[q] = hx[p] + s * dx[p]
        sy[q] = hy[p] + s * dy[p]
        nxt[p] = q
        prv[q] = p
        for e in (p, q):
            a, b = prv[e], nxt[e]
            old = key[e]
            key[e] = _removal_cost(sx[e], sy[e], sx[b], sy[b], dx[a], dy[a], dl[a],
                                   dx[b], dy[b], dl[b])
            if key[e] < old:
                _sift_up(heap, pos, key, pos[e])
            else:
                _sift_down(heap, pos, key, pos[e], size)
    out = np.empty((4, 2))
    e = heap[0]
    for k in range(4):
        out[k, 0] = sx[e]
        out[k, 1] = sy[e]
        e = nxt[e]
    return out


@njit(cache=True)
def _degenerate_quad(hull):
    """Zero-area (4, 2) 'quad' of a 1- or 2-vertex hull: ``[a, a, a, a]`` or ``[a, b, b, a]``."""
    out = np.empty((4, 2))
    b = hull.shape[0] - 1
    for k, i in enumerate((0, b, b, 0)):
        out[k, 0], out[k, 1] = hull[i, 0], hull[i, 1]
    return out


@njit(cache=True)
def _triangle_parallelogram(tri):
    """The paper's answer for a triangle: the parallelogram with the longest edge as diagonal
    and three corners on the triangle's; twice the triangle's area."""
    i, longest = 0, -1.0
    for k in range(3):
        j = (k + 1) % 3
        length = math.hypot(tri[j, 0] - tri[k, 0], tri[j, 1] - tri[k, 1])
        if length > longest:
            i, longest = k, length
    a, b, c = tri[i], tri[(i + 1) % 3], tri[(i + 2) % 3]
    out = np.empty((4, 2))
    out[0], out[2], out[3] = a, b, c
    out[1] = a + b - c  # the fourth corner mirrors c across the diagonal
    return out


@njit(cache=True)
def _greedy(hull):
    """:func:`greedy_quad`, compiled."""
    n = hull.shape[0]
    if n <= 2:
        return _degenerate_quad(hull)
    if n == 3:
        return _triangle_parallelogram(hull)
    if n == 4:
        return hull.copy()
    return _greedy_kernel(hull)


def _as_hull(hull) -> np.ndarray:
    hull = np.ascontiguousarray(hull, dtype=np.float64)
    if hull.ndim != 2 or hull.shape[1] != 2 or len(hull) == 0:
        raise ValueError(f"need a hull of shape (n, 2) with n >= 1, got {hull.shape}")
    return hull


def greedy_quad(hull) -> np.ndarray:
    """Low & Ilie's bounding quadrilateral of a convex polygon, ``(4, 2)`` CCW.

    ``hull``: ``(n, 2)`` CCW strictly convex, as :func:`convex_hull_2d` returns. For ``n >= 5``
    repeatedly remove the edge whose removal adds the least area, among the edges whose two
    interior angles sum to more than 180 degrees (the neighbours' extensions meet beyond it);
    the neighbours are extended to their meeting point. An indexed heap makes it O(n log n):
    after a removal only the two neighbours' costs change and are sifted in place. An edge whose
    neighbours are parallel within :data:`PARALLEL` gets cost ``inf`` (never a division by ~0),
    and one whose neighbours are nearly parallel gets a huge finite cost, so it goes last.

    ``n == 4``: the hull itself. ``n == 3``: the paper's parallelogram (longest edge as its
    diagonal, area twice the triangle's). ``n <= 2`` (coincident or collinear points): a
    zero-area quad ``[a, a, a, a]`` or ``[a, b, b, a]``, which :func:`contains` accepts.
    """
    return _greedy(_as_hull(hull))


# ------------------------------------------------------------------------- side optimization
#
# A quad is four lines in CCW order, ``pt[k]`` a point on line k and ``dr[k]`` its direction;
# corner k is where line k-1 meets line k. While one side j moves, the other three are fixed and
# ``ctx`` caches them: the previous line (p, dp), the next line (q, dq), the two fixed corners
# C = next ^ opposite and D = opposite ^ previous, and cross(dp, dq).


@njit(cache=True, inline="always")
def _cross(ax, ay, bx, by):
    return ax * by - ay * bx


@njit(cache=True)
def _turns(ax, ay, bx, by):
    """True when direction b is a left turn of less than 180 degrees from a (not ~parallel)."""
    c = ax * by - ay * bx
    return c > PARALLEL * math.sqrt((ax * ax + ay * ay) * (bx * bx + by * by))


@njit(cache=True)
def _meet(px, py, dx, dy, qx, qy, ex, ey):
    """Intersection of lines (p, d) and (q, e); the caller makes sure they are not parallel."""
    s = _cross(qx - px, qy - py, ex, ey) / _cross(dx, dy, ex, ey)
    return px + s * dx, py + s * dy


@njit(cache=True)
def _side_context(pt, dr, j):
    jp, jn, jo = (j + 3) % 4, (j + 1) % 4, (j + 2) % 4
    ctx = np.empty(13)
    ctx[0], ctx[1], ctx[2], ctx[3] = pt[jp, 0], pt[jp, 1], dr[jp, 0], dr[jp, 1]
    ctx[4], ctx[5], ctx[6], ctx[7] = pt[jn, 0], pt[jn, 1], dr[jn, 0], dr[jn, 1]
    ctx[8], ctx[9] = _meet(pt[jn, 0], pt[jn, 1], dr[jn, 0], dr[jn, 1],
                           pt[jo, 0], pt[jo, 1], dr[jo, 0], dr[jo, 1])
    ctx[10], ctx[11] = _meet(pt[jo, 0], pt[jo, 1], dr[jo, 0], dr[jo, 1],
                             pt[jp, 0], pt[jp, 1], dr[jp, 0], dr[jp, 1])
    ctx[12] = _cross(dr[jp, 0], dr[jp, 1], dr[jn, 0], dr[jn, 1])
    return ctx


@njit(cache=True)
def _line_area(ctx, vx, vy, dx, dy):
    """Quad area with side j on the line (v, d); ``inf`` if the quad would not be bounded and
    convex (a turn of >= 180 degrees, or ~0, between consecutive sides)."""
    px, py, dpx, dpy = ctx[0], ctx[1], ctx[2], ctx[3]
    qx, qy, dqx, dqy = ctx[4], ctx[5], ctx[6], ctx[7]
    if not (_turns(dpx, dpy, dx, dy) and _turns(dx, dy, dqx, dqy)):
        return np.inf
    ax, ay = _meet(px, py, dpx, dpy, vx, vy, dx, dy)
    bx, by = _meet(vx, vy, dx, dy, qx, qy, dqx, dqy)
    cx, cy, ex, ey = ctx[8], ctx[9], ctx[10], ctx[11]
    return 0.5 * (_cross(ax, ay, bx, by) + _cross(bx, by, cx, cy)
                  + _cross(cx, cy, ex, ey) + _cross(ex, ey, ax, ay))


@njit(cache=True)
def _midpoint_direction(ctx, hull, edge, k):
    """Direction of the line through hull vertex k that has k at the midpoint of side j, or
    (0, 0) if there is none or it does not support the hull at k."""
    den = ctx[12]
    dpx, dpy, dqx, dqy = ctx[2], ctx[3], ctx[6], ctx[7]
    if abs(den) <= PARALLEL * math.sqrt((dpx * dpx + dpy * dpy) * (dqx * dqx + dqy * dqy)):
        return 0.0, 0.0  # parallel neighbours: area is monotone in the angle, an end wins
    vx, vy = hull[k, 0], hull[k, 1]
    # A = p + s dp on the previous line, B = 2 v - A on the next line
    s = _cross(2 * vx - ctx[0] - ctx[4], 2 * vy - ctx[1] - ctx[5], dqx, dqy) / den
    dx, dy = vx - (ctx[0] + s * dpx), vy - (ctx[1] + s * dpy)
    n = hull.shape[0]
    km = k - 1 if k > 0 else n - 1
    if (_cross(edge[km, 0], edge[km, 1], dx, dy) < 0.0
            or _cross(dx, dy, edge[k, 0], edge[k, 1]) < 0.0):
        return 0.0, 0.0  # outside vertex k's cone of supporting directions
    return dx, dy


@njit(cache=True)
def _midpoint_area(ctx, hull, edge, k):
    dx, dy = _midpoint_direction(ctx, hull, edge, k)
    if dx == 0.0 and dy == 0.0:
        return np.inf, dx, dy
    return _line_area(ctx, hull[k, 0], hull[k, 1], dx, dy), dx, dy


@njit(cache=True)
def _best_side_scan(hull, edge, pt, dr, j, out):
    """Exact best line for side j over *all* supporting lines of the hull, others fixed.

    On the lines through one vertex the area has a single critical point, where the vertex is
    the side's midpoint (the classical condition for a locally minimal circumscribed polygon);
    between vertices the line is flush with a hull edge. So the minimum is among those two
    candidate families, O(n). Writes (point, direction) into ``out``; returns the area.
    """
    ctx = _side_context(pt, dr, j)
    best = np.inf
    for k in range(hull.shape[0]):
        area = _line_area(ctx, hull[k, 0], hull[k, 1], edge[k, 0], edge[k, 1])
        if area < best:
            best = area
            out[0], out[1], out[2], out[3] = hull[k, 0], hull[k, 1], edge[k, 0], edge[k, 1]
        area, dx, dy = _midpoint_area(ctx, hull, edge, k)
        if area < best:
            best = area
            out[0], out[1], out[2], out[3] = hull[k, 0], hull[k, 1], dx, dy
    return best


@njit(cache=True)
def _walk_side(hull, edge, pt, dr, j, k0, current, out):
    """Local best line for side j: rotate it about its contact vertex k0 and pivot along the
    hull, both ways, while the area keeps falling (the family of supporting lines is visited in
    angular order: flush with edge k-1, through vertex k, flush with edge k, ...; in each
    vertex's cone the midpoint line is tried too). Writes (point, direction) into ``out``;
    returns (area, new contact vertex). O(steps) instead of :func:`_best_side_scan`'s O(n).
    """
    n = hull.shape[0]
    ctx = _side_context(pt, dr, j)
    best, best_k = current, k0
    for step_dir in (1, -1):
        k = k0
        last = current
        for step in range(n):
            area, dx, dy = _midpoint_area(ctx, hull, edge, k)
            if area < best:
                best, best_k = area, k
                out[0], out[1], out[2], out[3] = hull[k, 0], hull[k, 1], dx, dy
            e = k if step_dir == 1 else (k - 1 if k > 0 else n - 1)  # the far end of k's cone
            area = _line_area(ctx, hull[e, 0], hull[e, 1], edge[e, 0], edge[e, 1])
            if area < best:
                best, best_k = area, e
                out[0], out[1], out[2], out[3] = hull[e, 0], hull[e, 1], edge[e, 0], edge[e, 1]
            if area == np.inf or (step > 0 and area > last):
                break
            last = min(last, area)
            k = (k + step_dir) % n
    return best, best_k


@njit(cache=True)
def _refine_kernel(hull, pt, dr, contact, max_steps):
    """Move sides to their local optimum until none improves by 1e-12 relative.

    A side's best line depends only on its two neighbours (the opposite side adds a constant to
    the area), so a side is revisited only when a neighbour moved. Returns the number of moves.
    """
    n = hull.shape[0]
    edge = np.empty((n, 2))
    for i in range(n):
        k = i + 1 if i + 1 < n else 0
        edge[i, 0], edge[i, 1] = hull[k, 0] - hull[i, 0], hull[k, 1] - hull[i, 1]
    out = np.empty(4)
    corners = np.empty((4, 2))
    current = _quad_area_lines(pt, dr, corners)
    dirty = np.ones(4, dtype=np.bool_)
    moves = 0
    j = 0
    idle = 0
    while idle < 4 and moves < max_steps:
        if dirty[j]:
            dirty[j] = False
            area, k = _walk_side(hull, edge, pt, dr, j, contact[j], current, out)
            if area < current * (1.0 - 1e-12):
                pt[j, 0], pt[j, 1], dr[j, 0], dr[j, 1] = out[0], out[1], out[2], out[3]
                contact[j] = k
                current = area
                dirty[(j + 1) % 4] = True
                dirty[(j + 3) % 4] = True
                moves += 1
                idle = 0
            else:
                idle += 1
        else:
            idle += 1
        j = (j + 1) % 4
    return moves


@njit(cache=True)
def _exhaustive_kernel(hull):
    """Smallest quad with three sides flush with hull edges and the fourth optimal (O(n^4))."""
    n = hull.shape[0]
    edge = np.empty((n, 2))
    for i in range(n):
        k = i + 1 if i + 1 < n else 0
        edge[i, 0], edge[i, 1] = hull[k, 0] - hull[i, 0], hull[k, 1] - hull[i, 1]
    pt = np.empty((4, 2))
    dr = np.empty((4, 2))
    best_pt = np.empty((4, 2))
    best_dr = np.empty((4, 2))
    out = np.empty(4)
    best = np.inf
    flush = np.empty(3, dtype=np.int64)
    for a in range(n):
        for b in range(a + 1, n):
            for c in range(b + 1, n):
                for rot in range(3):  # which gap between the flush sides holds the free side
                    flush[0], flush[1], flush[2] = a, b, c
                    e1, e2, e3 = flush[rot], flush[(rot + 1) % 3], flush[(rot + 2) % 3]
                    # sides in CCW order: e1, free, e2, e3
                    if not (_turns(edge[e2, 0], edge[e2, 1], edge[e3, 0], edge[e3, 1])
                            and _turns(edge[e3, 0], edge[e3, 1], edge[e1, 0], edge[e1, 1])):
                        continue
                    for s, e in ((0, e1), (2, e2), (3, e3)):
                        pt[s, 0], pt[s, 1] = hull[e, 0], hull[e, 1]
                        dr[s, 0], dr[s, 1] = edge[e, 0], edge[e, 1]
                    area = _best_side_scan(hull, edge, pt, dr, 1, out)
                    if area < best:
                        best = area
                        pt[1, 0], pt[1, 1], dr[1, 0], dr[1, 1] = out[0], out[1], out[2], out[3]
                        best_pt[:, :] = pt
                        best_dr[:, :] = dr
    return best_pt, best_dr, best


@njit(cache=True)
def _quad_area_lines(pt, dr, corners):
    """Corners (written into ``corners``) and area of the quad bounded by 4 lines."""
    for k in range(4):
        km = k - 1 if k > 0 else 3
        corners[k, 0], corners[k, 1] = _meet(pt[km, 0], pt[km, 1], dr[km, 0], dr[km, 1],
                                             pt[k, 0], pt[k, 1], dr[k, 0], dr[k, 1])
    area = 0.0
    for k in range(4):
        kn = k + 1 if k < 3 else 0
        area += _cross(corners[k, 0], corners[k, 1], corners[kn, 0], corners[kn, 1])
    return 0.5 * area


def _corners(pt, dr) -> np.ndarray:
    corners = np.empty((4, 2))
    _quad_area_lines(pt, dr, corners)
    return corners


def refine_quad(hull, quad, max_steps: int = 10_000) -> np.ndarray:
    """Shrink a bounding quad of a convex polygon to a local minimum of area, ``(4, 2)`` CCW.

    Goes beyond the paper, whose greedy quad is not optimal. First every side is slid inward,
    parallel to itself, until it touches the hull (becomes a supporting line). Then each side in
    turn is rotated about its contact vertex, pivoting from vertex to vertex along the hull, to
    the local minimum of the quad's area with the other three sides fixed; in each vertex's cone
    of supporting directions the one candidate besides the flush ends is the line that has the
    vertex at its midpoint (in a locally minimal circumscribed polygon every side's midpoint
    touches the polygon). A side is revisited when a neighbour moves (its optimum depends on its
    neighbours only), until no side gains 1e-12 relative, or ``max_steps`` moves.

    Every side stays a supporting line of the hull, so the result contains the hull (up to the
    rounding of the corners, ~1e-15 of the hull's size), and no move increases the area, so it
    is never larger than ``quad``. ``quad`` must contain the hull (``ValueError`` otherwise).

    A 4-vertex hull is its own optimum and is returned. Returned unchanged: triangles (the
    infimum is the triangle itself, a degenerate quad that no frustum can map to a rectangle,
    so the paper's parallelogram is kept on purpose) and zero-area quads.
    """
    out, outside = _refine(_as_hull(hull), np.ascontiguousarray(quad, np.float64).reshape(4, 2),
                           max_steps)
    if outside:
        raise ValueError("refine_quad: the quad does not contain the hull")
    return out


@njit(cache=True)
def _polygon_area(poly):
    """Signed shoelace area of ``(n, 2)``, compiled (see :func:`quad_area`)."""
    n = poly.shape[0]
    area = 0.0
    for k in range(n):
        j = k + 1 if k + 1 < n else 0
        area += poly[k, 0] * poly[j, 1] - poly[j, 0] * poly[k, 1]
    return 0.5 * area


@njit(cache=True)
def _refine(hull, quad, max_steps):
    """:func:`refine_quad`, compiled: ``(quad, outside)``, ``outside`` when ``quad`` does not
    contain the hull (then the quad comes back unchanged)."""
    if hull.shape[0] < 4 or not _polygon_area(quad) > 0:
        return quad.copy(), False
    dr = np.empty((4, 2))
    for k in range(4):
        j = (k + 1) % 4
        dr[k, 0], dr[k, 1] = quad[j, 0] - quad[k, 0], quad[j, 1] - quad[k, 1]
    convex, outside, contact = _slide_sides(hull, quad, dr)
    if not convex:
        return quad.copy(), False  # not strictly convex (a side of zero length): no refining
    if outside > 1e-9:
        return quad.copy(), True
    if hull.shape[0] == 4:
        return hull.copy(), False  # the optimum
    pt = np.empty((4, 2))
    for k in range(4):
        pt[k, 0], pt[k, 1] = hull[contact[k], 0], hull[contact[k], 1]
    _refine_kernel(hull, pt, dr, contact, max_steps)
    out = np.empty((4, 2))
    _quad_area_lines(pt, dr, out)
    if not _polygon_area(out) <= _polygon_area(quad):  # rounding at the very last ulp
        return quad.copy(), False
    return out, False


@njit(cache=True)
def _slide_sides(hull, quad, dr):
    """For each side of ``quad`` (directions ``dr``): the hull vertex nearest to it, where the
    side slid inward parallel to itself first touches the hull. Also: whether the quad is
    strictly convex, and how far (relative to the hull's size) the hull sticks out of it."""
    n = hull.shape[0]
    convex = True
    for k in range(4):
        km = k - 1 if k > 0 else 3
        if not _turns(dr[km, 0], dr[km, 1], dr[k, 0], dr[k, 1]):
            convex = False
    contact = np.zeros(4, dtype=np.int64)
    worst = np.inf
    for k in range(4):
        length = math.sqrt(dr[k, 0] ** 2 + dr[k, 1] ** 2)
        best = np.inf
        for i in range(n):
            dist = _cross(dr[k, 0], dr[k, 1], hull[i, 0] - quad[k, 0], hull[i, 1] - quad[k, 1])
            if dist < best:
                best, contact[k] = dist, i
        worst = min(worst, best / length)
    lox, hix, loy, hiy = hull[0, 0], hull[0, 0], hull[0, 1], hull[0, 1]
    for i in range(n):
        lox, hix = min(lox, hull[i, 0]), max(hix, hull[i, 0])
        loy, hiy = min(loy, hull[i, 1]), max(hiy, hull[i, 1])
    size = math.sqrt((hix - lox) ** 2 + (hiy - loy) ** 2)
    return convex, -worst / size if size > 0 else 0.0, contact


def best_quad_exhaustive(hull) -> np.ndarray:
    """Reference minimum-area bounding quad of a convex polygon by exhaustive search, ``(4, 2)``.

    Searching only quads whose four sides are flush with hull edges is *not* enough: in a
    minimum-area circumscribed polygon a side may touch the hull at a single vertex, which is
    then its midpoint. What is known (Aggarwal, Chang & Yap 1985; see also S. Har-Peled's note
    "Min area convex polygon with k sides") is that a side whose neighbours meet beyond it can
    be made flush without growing the quad, and that at most one side of the other kind exists
    when k = 4. So this enumerates every triple of hull edges as three flush sides, and puts
    the fourth side, in each of the three gaps, at its exact optimum (flush or midpoint-touching,
    as :func:`refine_quad` does). O(n^4): meant for n up to ~30-50, as a benchmark reference.

    Hulls of fewer than 5 vertices: as :func:`greedy_quad`.
    """
    hull = _as_hull(hull)
    if len(hull) < 5:
        return greedy_quad(hull)
    pt, dr, area = _exhaustive_kernel(hull)
    if not np.isfinite(area):
        raise RuntimeError("best_quad_exhaustive: no valid quad; is the hull convex and CCW?")
    return _corners(pt, dr)


def bounding_quad(points, refine: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``(hull_index, quad)``: hull indices of ``points`` ``(m, 2)`` and a bounding quad.

    The quad is :func:`greedy_quad` of the hull, then :func:`refine_quad` if ``refine``.
    """
    idx = hull_indices(points)
    hull = np.asarray(points, dtype=np.float64)[idx]
    quad = greedy_quad(hull)
    if refine:
        quad = refine_quad(hull, quad)
    return idx, quad


# ---------------------------------------------------------------------------------- reporting


def random_hull(rng: np.random.Generator, n_points: int) -> np.ndarray:
    kind = rng.integers(3)
    if kind == 0:  # points in a disk, stretched and rotated
        p = rng.normal(size=(n_points, 2))
        p /= np.linalg.norm(p, axis=1, keepdims=True)
        p *= np.sqrt(rng.random((n_points, 1)))
    elif kind == 1:  # Gaussian blob
        p = rng.normal(size=(n_points, 2))
    else:  # points on an ellipse arc plus clutter
        t = rng.random(n_points) * 2 * np.pi
        p = np.c_[np.cos(t), np.sin(t)] * (1 + 0.2 * rng.random((n_points, 1)))
    a = rng.normal(size=(2, 2))
    return convex_hull_2d(p @ a.T)


def ratio_report(n_hulls: int = 300, seed: int = 0, max_vertices: int = 30) -> dict:
    """Area ratios greedy/best and refined/best over random hulls: median, p90, max.

    Hulls come from random point sets (disk, Gaussian, noisy ellipse, under random linear maps)
    with 5 to ``max_vertices`` hull vertices; ``best`` is :func:`best_quad_exhaustive`.
    """
    rng = np.random.default_rng(seed)
    greedy, refined, sizes = [], [], []
    while len(greedy) < n_hulls:
        hull = random_hull(rng, int(rng.integers(8, 200)))
        if not 5 <= len(hull) <= max_vertices:
            continue
        g = greedy_quad(hull)
        r = refine_quad(hull, g)
        b = best_quad_exhaustive(hull)
        best = quad_area(b)
        greedy.append(quad_area(g) / best)
        refined.append(quad_area(r) / best)
        sizes.append(len(hull))

    def stats(x):
        x = np.asarray(x)
        return {"median": float(np.median(x)), "p90": float(np.percentile(x, 90)),
                "max": float(x.max()), "min": float(x.min())}

    return {"n_hulls": n_hulls, "seed": seed, "hull_vertices": stats(sizes),
            "greedy_over_best": stats(greedy), "refined_over_best": stats(refined)}


def bench_quad(n_vertices: int = 1000, repeat: int = 200) -> dict:
    """Median milliseconds of the hull, greedy and refine steps on points on an ellipse."""
    import time

    t = np.linspace(0.0, 2 * np.pi, n_vertices, endpoint=False)
    points = np.c_[2.0 * np.cos(t), np.sin(t)] @ np.array([[1.0, 0.3], [-0.2, 1.0]])
    hull = convex_hull_2d(points)
    quad = greedy_quad(hull)
    refine_quad(hull, quad)  # compile
    out = {}
    for name, fn in (("hull", lambda: hull_indices(points)), ("greedy", lambda: greedy_quad(hull)),
                     ("refine", lambda: refine_quad(hull, quad)),
                     ("bounding_quad", lambda: bounding_quad(points))):
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        out[name] = 1e3 * float(np.median(times))
    out["hull_vertices"] = len(hull)
    return out


if __name__ == "__main__":  # python -m wallcull.quad
    import json

    print(json.dumps(ratio_report(), indent=2))
    print(json.dumps(bench_quad(), indent=2))
