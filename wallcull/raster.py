"""A software rasterizer: a scene's triangles into a depth buffer with a triangle id per pixel.

What an OpenGL render node would see in one tile, without a GPU: :func:`render` draws leaves
of a scene, each mesh template placed by its leaf's world matrix (as :mod:`wallcull.overdraw`
reads them), through a tile's ``view`` and ``projection`` (SPEC section 1: OpenGL's, clip depth
in ``[-1, 1]``) into a ``width x height`` buffer, with OpenGL's rules as far as they matter here:

* clipping against the near and far planes in clip space (a triangle crossing the near plane
  is cut, never wrapped through the eye); the side planes are the viewport's bounds;
* window coordinates ``x = (x_ndc + 1) w / 2``, ``y = (y_ndc + 1) h / 2`` (``y`` up), pixel
  centres at half-integers; a pixel is covered when its centre is inside the triangle, a centre
  exactly on an edge by the top-left rule (so two triangles sharing an edge never both cover
  it, and never leave it uncovered);
* window depth ``(z_ndc + 1) / 2``, interpolated linearly in window space (it is affine there,
  so this is perspective-correct), cleared to 1 and tested LESS: of two surfaces at the same
  depth the first drawn stays; zero-area triangles draw nothing, back faces are drawn.

Arithmetic is float64 throughout, so it is the exact image up to rounding, which a GPU's
float32 and fixed-point snapping only approximate (the tests compare the two). Triangle ids
are :func:`first_ids`' numbering: leaf ``i``'s face ``f`` is ``first[i] + f``, 0 the
background; a buffer's row 0 is the top of the image, as the OpenGL renderer reads it back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .scene import Scene


@dataclass
class IdBuffer:
    """One tile's image: ``depth (h, w)`` window depth in ``[0, 1]`` (1: nothing drawn) and
    ``ids (h, w)`` the nearest triangle's id (0: nothing); row 0 is the top row."""

    depth: np.ndarray
    ids: np.ndarray


def first_ids(scene: Scene) -> np.ndarray:
    """``(n,)`` per node the id of its first triangle: leaves numbered in id order from 1,
    each leaf's faces in its template's order (an instance's triangles are its own)."""
    count = np.zeros(len(scene), np.int64)
    leaves = scene.leaves
    count[leaves] = scene.meshes.face_count[scene.mesh_of[leaves]]
    return 1 + np.cumsum(count) - count


def render(scene: Scene, leaves: np.ndarray, view: np.ndarray, projection: np.ndarray,
           width: int, height: int, first: np.ndarray | None = None) -> IdBuffer:
    """Draw ``leaves`` (in that order) through ``projection @ view`` into a new
    ``width x height`` buffer; ``first``: :func:`first_ids` of ``scene``, if at hand."""
    first = first_ids(scene) if first is None else first
    out = IdBuffer(np.ones((height, width)), np.zeros((height, width), np.int64))
    m = scene.meshes
    pv = np.asarray(projection, np.float64) @ np.asarray(view, np.float64)
    _render(pv, np.asarray(leaves, np.int64), first, scene.mesh_of, scene.world,
            m.vertex_start, m.vertices, m.face_start, m.faces, out.depth, out.ids)
    return out


# Outcodes of a clip-space point: which of the six clip planes it is outside.
_LEFT, _RIGHT, _BOTTOM, _TOP, _NEAR, _FAR = 1, 2, 4, 8, 16, 32


@njit(cache=True)
def _render(pv, leaves, first, mesh_of, world, vertex_start, vertices, face_start, faces,
            depth, ids):
    most = 0
    for leaf in leaves:
        m = mesh_of[leaf]
        most = max(most, vertex_start[m + 1] - vertex_start[m])
    clip = np.empty((most, 4))
    code = np.empty(most, np.int64)
    mvp = np.empty((4, 4))
    poly = np.empty((8, 4))  # a triangle clipped by two planes has at most 5 corners
    nxt = np.empty((8, 4))
    win = np.empty((8, 3))
    for leaf in leaves:
        m = mesh_of[leaf]
        w = world[leaf]
        for r in range(4):
            for c in range(4):
                mvp[r, c] = (pv[r, 0] * w[0, c] + pv[r, 1] * w[1, c] + pv[r, 2] * w[2, c]
                             + pv[r, 3] * w[3, c])
        v0 = vertex_start[m]
        for i in range(vertex_start[m + 1] - v0):
            x, y, z = vertices[v0 + i, 0], vertices[v0 + i, 1], vertices[v0 + i, 2]
            for r in range(4):
                clip[i, r] = mvp[r, 0] * x + mvp[r, 1] * y + mvp[r, 2] * z + mvp[r, 3]
            code[i] = _outcode(clip[i])
        base = first[leaf] - face_start[m]
        for f in range(face_start[m], face_start[m + 1]):
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            if code[a] & code[b] & code[c]:
                continue  # wholly outside one clip plane
            for k in range(4):
                poly[0, k], poly[1, k], poly[2, k] = clip[a, k], clip[b, k], clip[c, k]
            n = 3
            if (code[a] | code[b] | code[c]) & (_NEAR | _FAR):
                n = _clip(poly, n, nxt, 1.0)  # near: z + w >= 0
                n = _clip(poly, n, nxt, -1.0)  # far: w - z >= 0
            for k in range(n):  # to window coordinates (w >= near > 0 after clipping)
                inv = 1.0 / poly[k, 3]
                win[k, 0] = (poly[k, 0] * inv + 1.0) * 0.5 * depth.shape[1]
                win[k, 1] = (poly[k, 1] * inv + 1.0) * 0.5 * depth.shape[0]
                win[k, 2] = (poly[k, 2] * inv + 1.0) * 0.5
            for k in range(1, n - 1):  # a fan, as OpenGL's clipper emits it
                _triangle(win, 0, k, k + 1, base + f, depth, ids)


@njit(cache=True, inline="always")
def _outcode(p) -> int:
    x, y, z, w = p[0], p[1], p[2], p[3]
    return ((_LEFT if x < -w else 0) | (_RIGHT if x > w else 0) | (_BOTTOM if y < -w else 0)
            | (_TOP if y > w else 0) | (_NEAR if z < -w else 0) | (_FAR if z > w else 0))


@njit(cache=True)
def _clip(poly, n, nxt, sign) -> int:
    """Clip the polygon ``poly[:n]`` (clip space) to ``w + sign * z >= 0`` (Sutherland-
    Hodgman); returns the new corner count, the corners back in ``poly``."""
    m = 0
    for i in range(n):
        j = (i + 1) % n
        di = poly[i, 3] + sign * poly[i, 2]
        dj = poly[j, 3] + sign * poly[j, 2]
        if di >= 0:
            nxt[m] = poly[i]
            m += 1
        if (di >= 0) != (dj >= 0):
            s = di / (di - dj)
            for k in range(4):
                nxt[m, k] = poly[i, k] + s * (poly[j, k] - poly[i, k])
            m += 1
    poly[:m] = nxt[:m]
    return m


@njit(cache=True, inline="always")
def _edge(ax, ay, bx, by, px, py) -> float:
    """Twice the signed area of ``(a, b, p)``, computed from the lesser of ``a`` and ``b``
    whichever way the edge runs, so the two triangles sharing it get exactly opposite values."""
    if ax > bx or (ax == bx and ay > by):
        return -((ax - bx) * (py - by) - (ay - by) * (px - bx))
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


@njit(cache=True, inline="always")
def _top_left(ax, ay, bx, by) -> bool:
    """Whether edge ``a -> b`` of a counter-clockwise triangle (window ``y`` up) is a top or a
    left edge: those own the pixel centres exactly on them."""
    return by < ay or (by == ay and bx < ax)


@njit(cache=True)
def _triangle(win, i, j, k, tid, depth, ids):
    """Rasterize the window-space triangle ``win[i], win[j], win[k]`` with id ``tid``."""
    height, width = depth.shape
    x0, y0, z0 = win[i, 0], win[i, 1], win[i, 2]
    x1, y1, z1 = win[j, 0], win[j, 1], win[j, 2]
    x2, y2, z2 = win[k, 0], win[k, 1], win[k, 2]
    area = _edge(x0, y0, x1, y1, x2, y2)
    if area == 0.0 or not math.isfinite(area):
        return
    if area < 0.0:  # counter-clockwise from here on (back faces are drawn too)
        x1, y1, z1, x2, y2, z2 = x2, y2, z2, x1, y1, z1
        area = -area
    lo_x = max(math.ceil(min(x0, x1, x2) - 0.5), 0.0)
    hi_x = min(math.floor(max(x0, x1, x2) - 0.5), width - 1.0)
    lo_y = max(math.ceil(min(y0, y1, y2) - 0.5), 0.0)
    hi_y = min(math.floor(max(y0, y1, y2) - 0.5), height - 1.0)
    if lo_x > hi_x or lo_y > hi_y:
        return
    # depth as a plane over window space: z0 + dzdx (x - x0) + dzdy (y - y0)
    dzdx = ((z1 - z0) * (y2 - y0) - (z2 - z0) * (y1 - y0)) / area
    dzdy = ((z2 - z0) * (x1 - x0) - (z1 - z0) * (x2 - x0)) / area
    tl0 = _top_left(x1, y1, x2, y2)
    tl1 = _top_left(x2, y2, x0, y0)
    tl2 = _top_left(x0, y0, x1, y1)
    for py in range(int(lo_y), int(hi_y) + 1):
        cy = py + 0.5
        row = height - 1 - py
        # The row's span between the edges, widened by a pixel each side: a long thin
        # triangle costs its pixels, not its box; the exact tests below decide each pixel.
        left, right = lo_x, hi_x
        left, right = _span(x1, y1, x2, y2, cy, left, right)
        left, right = _span(x2, y2, x0, y0, cy, left, right)
        left, right = _span(x0, y0, x1, y1, cy, left, right)
        for px in range(int(left), int(right) + 1):
            cx = px + 0.5
            z = z0 + dzdx * (cx - x0) + dzdy * (cy - y0)
            if not z < depth[row, px]:
                continue
            e0 = _edge(x1, y1, x2, y2, cx, cy)
            if e0 < 0.0 or (e0 == 0.0 and not tl0):
                continue
            e1 = _edge(x2, y2, x0, y0, cx, cy)
            if e1 < 0.0 or (e1 == 0.0 and not tl1):
                continue
            e2 = _edge(x0, y0, x1, y1, cx, cy)
            if e2 < 0.0 or (e2 == 0.0 and not tl2):
                continue
            depth[row, px] = z
            ids[row, px] = tid


@njit(cache=True, inline="always")
def _span(ax, ay, bx, by, cy, left, right):
    """``(left, right)`` pixel columns narrowed to where row ``cy`` is on the inner side of
    edge ``a -> b`` of a counter-clockwise triangle, give or take a pixel."""
    dy = by - ay
    if dy == 0.0:
        return left, right
    x = ax + (bx - ax) * (cy - ay) / dy - 0.5  # the edge crosses the row at pixel x + 0.5
    if dy > 0.0:  # inside to the left of x
        return left, min(right, math.floor(x) + 1.0)
    return max(left, math.ceil(x) - 1.0), right
