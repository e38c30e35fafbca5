"""The Low-Ilie frustum: a view and projection that make a point set fill the viewport.

Low & Ilie, *View Frustum Optimization To Maximize Object's Image Area* (seeds 000, 003, 004):

1. a *sample* frustum: symmetric, around the points' bounding sphere, from the given eye;
2. project the points, take their 2D convex hull and a tight bounding quadrilateral
   (:mod:`wallcull.quad`: the paper's greedy removal, then our refinement);
3. map the quad's corners to the viewport's corners: the longest quad edge and its opposite to
   the viewport's longer sides. The four corner rays and the four viewport corners determine a
   3x3 projective map ``P`` (world directions -> homogeneous NDC), solved by SVD with Hartley
   normalization;
4. decompose ``P`` into an OpenGL view and projection matrix.

**Beyond the paper: a rigid view.** Four correspondences fix 8 degrees of freedom; a zero-skew
camera has 7 (3 rotation, focal x and y, principal point x and y), so the paper's
decomposition (eq. 12-14) returns a "rotation" whose first two rows are not orthogonal, and a
client that lights in eye space with that view matrix gets wrong normals. Here ``P = K R`` is
an RQ decomposition: ``R`` orthonormal with det +1 (the view), ``K`` upper triangular with a
skew entry, which goes into the projection matrix as a term in ``y`` on row 1::

    projection = [[k00, k01, k02, 0], [0, k11, k12, 0], [0, 0, A, B], [0, 0, -1, 0]]

with ``k00, k11 > 0`` and ``A, B`` the usual depth terms, so ``projection @ view`` maps the
four corner rays exactly onto NDC ``(+-1, +-1)`` and the view stays rigid. Signs: the eye looks
down ``-z``; ``K``'s last row is ``(0, 0, -1)``, so ``w_clip = -z_eye > 0`` exactly for points in
front; ``P``'s overall sign is chosen so that the corners have ``w > 0``, and the viewport
corners are assigned in the quad's CCW order, which makes ``det R = +1`` (checked).

Conventions (SPEC section 1): OpenGL, column vectors, clip depth in ``[-1, 1]``, matrices
``m[row, col]``. Geometry is computed eye-relative in float64 (the eye is subtracted first), so
points 1e7 away from the origin lose nothing.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from numba import njit

from . import workers
from .projection import dot, frustum, look_at, matmul
from .quad import COLLINEAR, _greedy, _hull, _polygon_area, _refine, extremes, octagon

__all__ = ["FitError", "FrustumFit", "fit_frustum", "float32_error", "bench_fit",
           "MAX_HALF_ANGLE_DEG", "SPHERE_PAD", "EFFORTS", "effort_code", "fit_boxes"]

#: The widest sample frustum, half-angle in degrees. Beyond it (or when no cone around the
#: points' mean direction holds them all) :func:`fit_frustum` raises :class:`FitError`.
MAX_HALF_ANGLE_DEG = 80.0

#: The bounding sphere's radius is grown by this fraction, so that rounding never puts a point
#: outside the sample frustum or the depth range.
SPHERE_PAD = 1e-6

#: For the depth range (eq. 17) the sphere's radius is at least this fraction of its distance
#: from the eye: one point, or a tiny distant object, still gets a usable depth range.
DEPTH_PAD = 1e-6

#: The narrowest sample frustum, half-angle in radians (a single point gets this one).
#: Narrower frusta lose float64 digits in the round trips and all float32 ones.
MIN_HALF_ANGLE = 1e-4

#: Near-plane clamp: the near distance is never less than this fraction of the nearest point's
#: depth (see :func:`fit_frustum`).
NEAR_FRACTION = 0.5

#: A sample-image hull whose area is below this fraction of its diameter squared is treated as
#: a segment (its points are collinear up to rounding).
FLAT = 1e-9

_CORNERS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])  # CCW from bottom-left


class FitError(ValueError):
    """No perspective frustum from this eye contains the points (they surround the eye, or a
    point coincides with it)."""


@dataclass(frozen=True)
class FrustumFit:
    """The result of :func:`fit_frustum`. All matrices ``(4, 4)`` float64, OpenGL conventions."""

    view: np.ndarray  # rigid world -> eye (orthonormal rotation, det +1)
    projection: np.ndarray  # skewed off-axis perspective, clip depth [-1, 1]
    quad: np.ndarray  # (4, 2) bounding quad in the sample image, sample NDC, CCW
    coverage: float  # fraction of the viewport covered by the points' projected hull
    sample_view: np.ndarray  # the symmetric bounding-sphere frustum's view
    sample_projection: np.ndarray  # ... and projection (aspect width / height)
    sample_coverage: float  # the same fraction for the sample frustum
    near: float
    far: float
    eye: np.ndarray  # (3,) the viewpoint, world space
    corner_rays: np.ndarray  # (4, 3) world directions of the quad corners' rays from the eye
    corner_ndc: np.ndarray  # (4, 2) the viewport corners they map to
    sample: str  # "sphere" (eye outside the bounding sphere) or "cone" (eye inside)
    degenerate: str | None  # None, "segment" (collinear image) or "point" (one image point)
    refined: bool  # True when the refined quad (not the greedy one) was used

    @property
    def corners(self) -> np.ndarray:
        """``(4, 3)`` world points on the corner rays (at the points' mean depth in the sample
        frame). Far from the origin they carry the rounding of world coordinates;
        ``corner_rays`` do not."""
        return self.eye + self.corner_rays


# ------------------------------------------------------------------------- the compiled fit
#
# One fit is a few dozen small steps; as numpy calls they cost ~0.4 ms, compiled ~10-20 us, so
# every tile of a wall can have one per light each frame. :func:`_fit_core` is the whole of
# :func:`fit_frustum` below the argument checks; :func:`fit_boxes` runs it for many point sets
# (a wall's tiles) in one call.

#: Fitting effort (``--shadow-fit``): the symmetric bounding-sphere frustum only, the paper's
#: greedy quad, or the greedy quad refined (the better of the two by coverage).
EFFORTS = ("sphere", "greedy", "refined")

# statuses of _fit_core
OK, EMPTY, UNLIT, SURROUNDS, COINCIDES, HORIZON, MIRRORED, BAD_DEPTH = range(8)

# info[] slots of _fit_core
_NEAR, _FAR, _COVERAGE, _SAMPLE_COVERAGE, _TX, _TY, _NS, _FS, _SAMPLE, _DEGENERATE, \
    _REFINED, _MEAN_DEPTH = range(12)
INFO_SIZE = 12


@njit(cache=True)
def _look(axis):
    """Rows ``side, up, -axis`` of :func:`look_at` toward ``axis`` (unit), up world +y unless
    ``axis`` is within ~8 degrees of it, then world -z."""
    ux, uy, uz = (0.0, 1.0, 0.0) if abs(axis[1]) < 0.99 else (0.0, 0.0, -1.0)
    sx = axis[1] * uz - axis[2] * uy
    sy = axis[2] * ux - axis[0] * uz
    sz = axis[0] * uy - axis[1] * ux
    norm = math.sqrt(sx * sx + sy * sy + sz * sz)
    sx, sy, sz = sx / norm, sy / norm, sz / norm
    rot = np.empty((3, 3))
    rot[0, 0], rot[0, 1], rot[0, 2] = sx, sy, sz
    rot[1, 0] = sy * axis[2] - sz * axis[1]
    rot[1, 1] = sz * axis[0] - sx * axis[2]
    rot[1, 2] = sx * axis[1] - sy * axis[0]
    rot[2, 0], rot[2, 1], rot[2, 2] = -axis[0], -axis[1], -axis[2]
    return rot


@njit(cache=True)
def _assign_corners(quad, width, height):
    """Viewport corner ``(4, 2)`` for each quad corner: the longest edge and its opposite go to
    the viewport's longer sides, in CCW order (orientation preserved), choosing of the two such
    assignments the one that turns the image least."""
    i, longest = 0, -1.0
    for k in range(4):
        j = (k + 1) % 4
        ex, ey = quad[j, 0] - quad[k, 0], quad[j, 1] - quad[k, 1]
        if ex * ex + ey * ey > longest:
            i, longest = k, ex * ex + ey * ey
    j = (i + 1) % 4
    ex, ey = quad[j, 0] - quad[i, 0], quad[j, 1] - quad[i, 1]
    if width >= height:  # bottom side runs +x from corner 0, top side runs -x from corner 2
        start = 0 if ex >= 0 else 2
    else:  # right side runs +y from corner 1, left side runs -y from corner 3
        start = 1 if ey >= 0 else 3
    out = np.empty((4, 2))
    for k in range(4):
        out[k] = _CORNERS[(start - i + k) % 4]
    return out


@njit(cache=True)
def _from_square(q):
    """The projective map of the unit square's corners (0,0), (1,0), (1,1), (0,1) onto the
    four points ``q`` (Heckbert's closed form), ``(3, 3)``."""
    x0, y0, x1, y1, x2, y2, x3, y3 = (q[0, 0], q[0, 1], q[1, 0], q[1, 1], q[2, 0], q[2, 1],
                                      q[3, 0], q[3, 1])
    sx, sy = x0 - x1 + x2 - x3, y0 - y1 + y2 - y3
    h = np.empty((3, 3))
    if sx == 0.0 and sy == 0.0:  # a parallelogram: affine
        g = hh = 0.0
    else:
        dx1, dx2, dy1, dy2 = x1 - x2, x3 - x2, y1 - y2, y3 - y2
        den = dx1 * dy2 - dx2 * dy1
        g = (sx * dy2 - dx2 * sy) / den
        hh = (dx1 * sy - sx * dy1) / den
    h[0, 0], h[0, 1], h[0, 2] = x1 - x0 + g * x1, x3 - x0 + hh * x3, x0
    h[1, 0], h[1, 1], h[1, 2] = y1 - y0 + g * y1, y3 - y0 + hh * y3, y0
    h[2, 0], h[2, 1], h[2, 2] = g, hh, 1.0
    return h


@njit(cache=True)
def _adjugate(m):
    """The adjugate of a 3x3 matrix: its inverse up to scale, which is all a homography needs."""
    a = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            r0, r1 = (j + 1) % 3, (j + 2) % 3
            c0, c1 = (i + 1) % 3, (i + 2) % 3
            a[i, j] = m[r0, c0] * m[r1, c1] - m[r0, c1] * m[r1, c0]
    return a


@njit(cache=True)
def _homography(src, dst):
    """3x3 ``H`` with ``dst ~ H src`` for 4 point pairs ``(4, 2)``: through the unit square in
    closed form, ``H = S_dst adj(S_src)``, with ``src`` first moved to its centroid and scaled
    to a mean distance of sqrt(2) (Hartley's normalization), so that small or distant quads keep
    their digits."""
    cx = 0.25 * (src[0, 0] + src[1, 0] + src[2, 0] + src[3, 0])
    cy = 0.25 * (src[0, 1] + src[1, 1] + src[2, 1] + src[3, 1])
    mean = 0.0
    for k in range(4):
        mean += 0.25 * math.hypot(src[k, 0] - cx, src[k, 1] - cy)
    scale = math.sqrt(2.0) / mean
    norm = np.empty((4, 2))
    for k in range(4):
        norm[k, 0], norm[k, 1] = (src[k, 0] - cx) * scale, (src[k, 1] - cy) * scale
    t = np.array([[scale, 0.0, -scale * cx], [0.0, scale, -scale * cy], [0.0, 0.0, 1.0]])
    return matmul(matmul(_from_square(dst), _adjugate(_from_square(norm))), t)


@njit(cache=True)
def _mapped_area(h, poly):
    """Area of the polygon ``(m, 2)`` mapped by homography ``h``."""
    m = poly.shape[0]
    x, y = np.empty(m), np.empty(m)
    for k in range(m):
        u, v = poly[k, 0], poly[k, 1]
        w = h[2, 0] * u + h[2, 1] * v + h[2, 2]
        x[k] = (h[0, 0] * u + h[0, 1] * v + h[0, 2]) / w
        y[k] = (h[1, 0] * u + h[1, 1] * v + h[1, 2]) / w
    area = 0.0
    for k in range(m):
        j = k + 1 if k + 1 < m else 0
        area += x[k] * y[j] - x[j] * y[k]
    return abs(0.5 * area)


@njit(cache=True)
def _segment_rectangle(hull, aspect):
    """CCW rectangle ``(4, 2)`` around a (nearly) collinear point set: its long axis along the
    principal direction, padded by 1e-6 of its length; its width the larger of the points'
    spread across and ``length / max(aspect, 1 / aspect)``."""
    n = hull.shape[0]
    cx, cy = 0.0, 0.0
    for k in range(n):
        cx += hull[k, 0] / n
        cy += hull[k, 1] / n
    a = b = c = 0.0
    for k in range(n):
        dx, dy = hull[k, 0] - cx, hull[k, 1] - cy
        a += dx * dx
        b += dx * dy
        c += dy * dy
    theta = 0.5 * math.atan2(2 * b, a - c)  # the principal axis of the scatter
    ux, uy = math.cos(theta), math.sin(theta)
    vx, vy = -uy, ux
    tlo = slo = np.inf
    thi = shi = -np.inf
    for k in range(n):
        dx, dy = hull[k, 0] - cx, hull[k, 1] - cy
        t, s_ = dx * ux + dy * uy, dx * vx + dy * vy
        tlo, thi, slo, shi = min(tlo, t), max(thi, t), min(slo, s_), max(shi, s_)
    length = (thi - tlo) * (1 + 2e-6)
    width = max((shi - slo) * (1 + 2e-6), length / max(aspect, 1.0 / aspect))
    mx = cx + ux * 0.5 * (thi + tlo) + vx * 0.5 * (shi + slo)
    my = cy + uy * 0.5 * (thi + tlo) + vy * 0.5 * (shi + slo)
    hux, huy, hvx, hvy = 0.5 * length * ux, 0.5 * length * uy, 0.5 * width * vx, 0.5 * width * vy
    out = np.empty((4, 2))
    out[0, 0], out[0, 1] = mx - hux - hvx, my - huy - hvy
    out[1, 0], out[1, 1] = mx + hux - hvx, my + huy - hvy
    out[2, 0], out[2, 1] = mx + hux + hvx, my + huy + hvy
    out[3, 0], out[3, 1] = mx - hux + hvx, my - huy + hvy
    return out


@njit(cache=True)
def _rq(p):
    """``p = k @ r`` (3 x 3) with ``k`` upper triangular and ``r`` a rotation or a reflection,
    by Gram-Schmidt over ``p``'s rows from the last, each row's part orthogonal to those below
    taken twice (once more recovers the digits the first loses when ``p`` is ill-conditioned),
    and ``r``'s first row the cross product of the other two: its rows are orthonormal to
    rounding whatever the conditioning of ``k``. (Not ``np.linalg.qr``: it needs SciPy.)"""
    r = np.zeros((3, 3))
    for i in (2, 1):
        row = p[i].copy()
        for _ in range(2):
            for j in range(i + 1, 3):
                row -= dot(row, r[j]) * r[j]
        length = math.sqrt(dot(row, row))
        if length > 0:
            r[i] = row / length
        else:  # a degenerate p: any unit vector orthogonal to the rows below
            axis = np.zeros(3)
            axis[np.argmin(np.abs(r[2]))] = 1.0
            axis -= dot(axis, r[2]) * r[2]
            r[i] = axis / math.sqrt(dot(axis, axis))
    r[0, 0] = r[1, 1] * r[2, 2] - r[1, 2] * r[2, 1]
    r[0, 1] = r[1, 2] * r[2, 0] - r[1, 0] * r[2, 2]
    r[0, 2] = r[1, 0] * r[2, 1] - r[1, 1] * r[2, 0]
    k = np.zeros((3, 3))
    for i in range(3):
        for j in range(i, 3):
            k[i, j] = dot(p[i], r[j])
    return k, r


@njit(cache=True)
def _box_images(rel, g, u, disc, rot_s, axis, points):
    """The sample images of the corners that can be on the hull of all boxes' corners, ``(k,
    2)``. The boxes with the most extreme image centres in 8 directions give an octagon of
    real corner images, inside the hull; a box whose image disc lies farther inside it than the
    hull's collinearity tolerance cannot add a hull vertex and is skipped."""
    n = u.shape[0]
    pick = extremes(u)
    out = np.empty((points, 2))
    corner = np.empty((8, 3))
    k = 0
    for j in range(8):  # the extreme boxes' corners: real points inside the hull
        i = pick[j]
        if disc[i] < 0:  # already taken
            continue
        for q in range(_corners_of(rel, g, i, corner, 0)):
            _image(corner, q, rot_s, axis, out, k)
            k += 1
        disc[i] = -1.0
    inner = octagon(out[:k], extremes(out[:k]))
    lox, hix, loy, hiy = np.inf, -np.inf, np.inf, -np.inf
    for i in range(n):
        lox, hix = min(lox, u[i, 0] - disc[i]), max(hix, u[i, 0] + disc[i])
        loy, hiy = min(loy, u[i, 1] - disc[i]), max(hiy, u[i, 1] + disc[i])
    margin = 2 * COLLINEAR * math.hypot(hix - lox, hiy - loy) if np.isfinite(hix) else np.inf
    for i in range(n):
        if disc[i] < 0:
            continue
        if disc[i] < np.inf and _well_inside(inner, u[i, 0], u[i, 1], disc[i] + margin):
            continue
        for q in range(_corners_of(rel, g, i, corner, 0)):
            _image(corner, q, rot_s, axis, out, k)
            k += 1
    return out[:k]


@njit(cache=True, inline="always")
def _image(p, q, rot_s, axis, out, k):
    """The sample image of eye-relative point ``p[q]`` into ``out[k]``."""
    x, y, z = p[q, 0], p[q, 1], p[q, 2]
    depth = axis[0] * x + axis[1] * y + axis[2] * z
    out[k, 0] = (rot_s[0, 0] * x + rot_s[0, 1] * y + rot_s[0, 2] * z) / depth
    out[k, 1] = (rot_s[1, 0] * x + rot_s[1, 1] * y + rot_s[1, 2] * z) / depth


# The per-box helpers below allocate nothing and are compiled without reference counting
# (``_nrt=False``; their callers hold the arrays): counting each call's array arguments in and
# out, atomically, cost 7% of the fits.
@njit(cache=True, _nrt=False)
def _well_inside(edges, x, y, margin):
    """Whether the disc of radius ``margin`` at (x, y) lies inside the octagon ``edges`` (a
    degenerate octagon, of fewer than three edges, holds nothing)."""
    count = 0
    for k in range(8):
        if edges[k, 0] == 0.0 and edges[k, 1] == 0.0:
            continue
        count += 1
        if edges[k, 0] * x + edges[k, 1] * y - edges[k, 2] <= margin:
            return False
    return count >= 3


@njit(cache=True, _nrt=False)
def _support(g, i, nx, ny, nz):
    """Half-width of box ``i`` (rows of ``g[i]``: its half-extent vectors) along ``n``."""
    return (abs(nx * g[i, 0, 0] + ny * g[i, 0, 1] + nz * g[i, 0, 2])
            + abs(nx * g[i, 1, 0] + ny * g[i, 1, 1] + nz * g[i, 1, 2])
            + abs(nx * g[i, 2, 0] + ny * g[i, 2, 1] + nz * g[i, 2, 2]))


@njit(cache=True, _nrt=False)
def _corners_of(rel, g, i, out, k):
    """Write box ``i``'s corners (eye-relative) into ``out[k:]``; returns the new ``k`` (one
    point for a box of no extent)."""
    if g[i, 0, 0] == 0.0 and g[i, 0, 1] == 0.0 and g[i, 0, 2] == 0.0 and g[i, 1, 0] == 0.0 \
            and g[i, 1, 1] == 0.0 and g[i, 1, 2] == 0.0 and g[i, 2, 0] == 0.0 \
            and g[i, 2, 1] == 0.0 and g[i, 2, 2] == 0.0:
        out[k, 0], out[k, 1], out[k, 2] = rel[i, 0], rel[i, 1], rel[i, 2]
        return k + 1
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            for sz in (-1.0, 1.0):
                for b in range(3):
                    out[k, b] = rel[i, b] + sx * g[i, 0, b] + sy * g[i, 1, b] + sz * g[i, 2, b]
                k += 1
    return k


@njit(cache=True)
def _fit_core(eye, centers, g, width, height, near_in, far_in, effort, view, projection,
              quad_out, target_out, rays_out, axis_out, info):
    """The Low-Ilie fit of :func:`fit_frustum` around the corners of boxes ``centers (n, 3)``,
    ``g (n, 3, 3)`` (each box's three half-extent vectors, orthogonal; all zero for a point),
    from ``eye``: writes the view and projection ``(4, 4)``, the quad and its viewport corners
    ``(4, 2)``, the corner rays ``(4, 3)``, the sample axis and ``info`` (the ``_NEAR`` ...
    slots); returns a status (``OK`` or why not). ``near_in``/``far_in``: NaN to fit them.
    ``effort``: 0 sphere, 1 greedy, 2 refined.

    The result is the fit of all the corners, but most of the work is per box: extents and
    depths come from each box's support function, and a box whose image lies well inside the
    hull of a few extreme boxes' corners never has its corners projected."""
    n = centers.shape[0]
    rel = np.empty((n, 3))
    reach = np.empty(n)  # distance from a box's centre to its corners
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    points = 0
    for i in range(n):
        for j in range(3):
            rel[i, j] = centers[i, j] - eye[j]  # eye-relative: full precision far away
            e = abs(g[i, 0, j]) + abs(g[i, 1, j]) + abs(g[i, 2, j])
            lo[j] = min(lo[j], rel[i, j] - e)
            hi[j] = max(hi[j], rel[i, j] + e)
        r2 = 0.0
        for a in range(3):
            r2 += g[i, a, 0] ** 2 + g[i, a, 1] ** 2 + g[i, a, 2] ** 2
        reach[i] = math.sqrt(r2)
        points += 1 if reach[i] == 0.0 else 8
    center = 0.5 * (lo + hi)
    dist_c = math.sqrt(center[0] ** 2 + center[1] ** 2 + center[2] ** 2)
    corner = np.empty((8, 3))
    # The farthest corner from the centre, exactly. A box's farthest corner from a point lies
    # between sqrt(d^2 + reach^2) and d + reach (d: the distance to the box's centre; its
    # corners are symmetric about it), so only boxes whose upper bound beats every lower
    # bound are opened.
    away = np.empty(n)
    r2 = 0.0
    for i in range(n):
        d2 = ((rel[i, 0] - center[0]) ** 2 + (rel[i, 1] - center[1]) ** 2
              + (rel[i, 2] - center[2]) ** 2)
        away[i] = math.sqrt(d2) + reach[i]
        r2 = max(r2, d2 + reach[i] ** 2)
    for i in range(n):
        if away[i] ** 2 <= r2:
            continue
        for q in range(_corners_of(rel, g, i, corner, 0)):
            r2 = max(r2, (corner[q, 0] - center[0]) ** 2 + (corner[q, 1] - center[1]) ** 2
                     + (corner[q, 2] - center[2]) ** 2)
    radius = math.sqrt(r2) * (1.0 + SPHERE_PAD)
    depth_radius = max(radius, DEPTH_PAD * dist_c)
    max_half = math.radians(MAX_HALF_ANGLE_DEG)

    # 1. the sample frustum
    axis = np.empty(3)
    if dist_c > radius and radius / dist_c <= math.sin(max_half):
        info[_SAMPLE] = 0.0  # sphere
        axis[:] = center / dist_c
        half = max(math.asin(radius / dist_c), MIN_HALF_ANGLE)
    else:
        info[_SAMPLE] = 1.0  # cone: the eye is inside the bounding sphere
        # The axis: the mean unit direction to the boxes' centres (their corners, for points).
        ax = ay = az = 0.0
        shortest = np.inf
        for i in range(n):
            length = math.sqrt(rel[i, 0] ** 2 + rel[i, 1] ** 2 + rel[i, 2] ** 2)
            shortest = min(shortest, length - reach[i])
            if length > 0:
                weight = (1.0 if reach[i] == 0.0 else 8.0) / points
                ax += rel[i, 0] / length * weight
                ay += rel[i, 1] / length * weight
                az += rel[i, 2] / length * weight
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        if shortest <= 1e-12 * (radius + dist_c):  # a box reaches the eye: check its corners
            for i in range(n):
                length = math.sqrt(rel[i, 0] ** 2 + rel[i, 1] ** 2 + rel[i, 2] ** 2)
                if length - reach[i] > 1e-12 * (radius + dist_c):
                    continue
                for q in range(_corners_of(rel, g, i, corner, 0)):
                    if not math.sqrt(corner[q, 0] ** 2 + corner[q, 1] ** 2 + corner[q, 2] ** 2) \
                            > 1e-12 * (radius + dist_c):
                        return COINCIDES
        if not norm > 0:
            return SURROUNDS
        ax, ay, az = ax / norm, ay / norm, az / norm
        # The widest corner, exactly. A box's corners lie within asin(reach / length) of its
        # centre's direction, so the cosine of their angle to the axis is at least
        # cos(angle + spread): only boxes whose bound is below the widest so far are opened,
        # the box with the lowest bound first.
        bound = np.empty(n)
        lowest = 0
        for i in range(n):
            length = math.sqrt(rel[i, 0] ** 2 + rel[i, 1] ** 2 + rel[i, 2] ** 2)
            if not length > reach[i]:  # the eye within the box's sphere (at its centre: 0)
                bound[i] = -1.0
            else:
                cos_a = max(-1.0, min(1.0, (rel[i, 0] * ax + rel[i, 1] * ay + rel[i, 2] * az)
                                      / length))
                sin_a, sin_s = math.sqrt(1 - cos_a * cos_a), reach[i] / length
                cos_s = math.sqrt(max(0.0, 1 - sin_s * sin_s))
                if sin_s >= 1.0 or sin_a * cos_s + cos_a * sin_s < 0:  # a + s past 180 degrees
                    bound[i] = -1.0
                else:  # cos(a + s) = cos a cos s - sin a sin s
                    bound[i] = cos_a * cos_s - sin_a * sin_s
            if bound[i] < bound[lowest]:
                lowest = i
        cos_half = np.inf
        for j in range(-1, n):
            i = lowest if j < 0 else j
            if bound[i] >= cos_half or (j == lowest):
                continue
            for q in range(_corners_of(rel, g, i, corner, 0)):
                length = math.sqrt(corner[q, 0] ** 2 + corner[q, 1] ** 2 + corner[q, 2] ** 2)
                if not length > 0:  # (a corner at the eye returned COINCIDES above)
                    return COINCIDES
                cos_half = min(cos_half, (corner[q, 0] * ax + corner[q, 1] * ay
                                          + corner[q, 2] * az) / length)
        if not cos_half >= math.cos(max_half):
            return SURROUNDS
        axis[0], axis[1], axis[2] = ax, ay, az
        half = max(math.acos(min(cos_half, 1.0)), MIN_HALF_ANGLE)
    axis_out[:] = axis
    rot_s = _look(axis)
    # the boxes seen from the eye: the depth of each centre, its image, and a disc around the
    # image that holds the box's image (|d image| <= reach sqrt(1 + |u|^2) / (depth - reach))
    u = np.empty((n, 2))
    disc = np.empty(n)
    shallowest = np.inf
    mean_depth = 0.0
    for i in range(n):
        x, y, z = rel[i, 0], rel[i, 1], rel[i, 2]
        depth = axis[0] * x + axis[1] * y + axis[2] * z
        if not depth > 0:  # every corner lies within 80 degrees of the axis: only by rounding
            return SURROUNDS
        shallowest = min(shallowest, depth - _support(g, i, axis[0], axis[1], axis[2]))
        mean_depth += depth * (1 if reach[i] == 0.0 else 8) / points
        u[i, 0] = (rot_s[0, 0] * x + rot_s[0, 1] * y + rot_s[0, 2] * z) / depth
        u[i, 1] = (rot_s[1, 0] * x + rot_s[1, 1] * y + rot_s[1, 2] * z) / depth
        disc[i] = reach[i] * math.sqrt(1 + u[i, 0] ** 2 + u[i, 1] ** 2) / (depth - reach[i]) \
            if depth > reach[i] else np.inf
    img = _box_images(rel, g, u, disc, rot_s, axis, points)
    center_depth = axis[0] * center[0] + axis[1] * center[1] + axis[2] * center[2]
    n_s = max(center_depth - depth_radius, NEAR_FRACTION * shallowest)
    f_s = center_depth + depth_radius
    aspect = width / height
    t = math.tan(half)
    tx, ty = t * max(aspect, 1.0), t * max(1.0 / aspect, 1.0)  # shorter side touches the sphere
    info[_TX], info[_TY], info[_NS], info[_FS] = tx, ty, n_s, f_s
    info[_MEAN_DEPTH] = mean_depth

    # 2. the sample image: hull and quads
    hull = img[_hull(img)]
    nh = hull.shape[0]
    hull_area = abs(_polygon_area(hull)) if nh >= 3 else 0.0
    info[_SAMPLE_COVERAGE] = hull_area / (tx * ty) / 4.0
    diameter = 0.0
    for k in range(nh):
        diameter = max(diameter, math.hypot(hull[k, 0] - hull[0, 0], hull[k, 1] - hull[0, 1]))
    info[_DEGENERATE] = 0.0
    info[_REFINED] = 0.0
    corners = np.empty((4, 2))
    for k in range(4):
        corners[k, 0], corners[k, 1] = _CORNERS[k, 0] * tx, _CORNERS[k, 1] * ty
    if effort == 0 or nh < 3 or hull_area <= FLAT * diameter ** 2:
        if effort == 0:
            quad = corners
        elif diameter <= 1e-12 * t:
            info[_DEGENERATE] = 2.0  # point
            quad = corners
        else:
            info[_DEGENERATE] = 1.0  # segment
            quad = _segment_rectangle(hull, aspect)
        target = _assign_corners(quad, width, height) if effort else _CORNERS.copy()
        h = _homography(quad, target)
        coverage = _mapped_area(h, hull) / 4.0 if nh >= 3 else 0.0
    else:
        quad = _greedy(hull)
        target = _assign_corners(quad, width, height)
        h = _homography(quad, target)
        coverage = _mapped_area(h, hull) / 4.0
        if effort == 2 and nh >= 5:
            refined, _ = _refine(hull, quad, 10_000)
            if _polygon_area(refined) < _polygon_area(quad):
                r_target = _assign_corners(refined, width, height)
                r_h = _homography(refined, r_target)
                r_coverage = _mapped_area(r_h, hull) / 4.0
                if r_coverage > coverage:
                    quad, target, h, coverage = refined, r_target, r_h, r_coverage
                    info[_REFINED] = 1.0
    info[_COVERAGE] = coverage

    # 3. P: world direction -> homogeneous NDC; the sample eye has (u, v, 1) ~ (x, y, -z)
    flip = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            flip[i, j] = rot_s[i, j] * (-1.0 if i == 2 else 1.0)
    p = matmul(h, flip)
    w0 = quad[0, 0] * h[2, 0] + quad[0, 1] * h[2, 1] + h[2, 2]
    for k in range(4):
        w = quad[k, 0] * h[2, 0] + quad[k, 1] * h[2, 1] + h[2, 2]
        if not (w * w0 > 0):
            return HORIZON  # the quad's corners straddle the horizon of the warp
    if w0 < 0:
        p = -p
    k_, r = _rq(p)
    for j in range(3):  # want k00 > 0, k11 > 0, k22 < 0
        sign = (1.0 if k_[j, j] >= 0 else -1.0) * (-1.0 if j == 2 else 1.0)
        for i in range(3):
            k_[i, j] *= sign
            r[j, i] *= sign
    det = (r[0, 0] * (r[1, 1] * r[2, 2] - r[1, 2] * r[2, 1])
           - r[0, 1] * (r[1, 0] * r[2, 2] - r[1, 2] * r[2, 0])
           + r[0, 2] * (r[1, 0] * r[2, 1] - r[1, 1] * r[2, 0]))
    if det < 0:
        return MIRRORED  # the corner assignment mirrored the image
    k_ /= -k_[2, 2]
    if effort == 0:  # the sample frustum itself
        r = rot_s

    # 4. the matrices
    view[:, :] = 0.0
    view[3, 3] = 1.0
    view[:3, :3] = r
    for i in range(3):
        view[i, 3] = -(r[i, 0] * eye[0] + r[i, 1] * eye[1] + r[i, 2] * eye[2])
    shallowest = np.inf
    for i in range(n):
        shallowest = min(shallowest, -(r[2, 0] * rel[i, 0] + r[2, 1] * rel[i, 1]
                                       + r[2, 2] * rel[i, 2]) - _support(g, i, r[2, 0],
                                                                          r[2, 1], r[2, 2]))
    center_depth = -(r[2, 0] * center[0] + r[2, 1] * center[1] + r[2, 2] * center[2])
    near = max(center_depth - depth_radius, NEAR_FRACTION * shallowest)
    far = center_depth + depth_radius
    if not math.isnan(near_in):
        near = near_in
    if not math.isnan(far_in):
        far = far_in
    if not 0 < near < far:
        return BAD_DEPTH
    info[_NEAR], info[_FAR] = near, far
    projection[:, :] = 0.0
    if effort == 0:
        projection[0, 0], projection[1, 1] = 1.0 / tx, 1.0 / ty
    else:
        projection[0, 0], projection[0, 1], projection[0, 2] = k_[0, 0], k_[0, 1], k_[0, 2]
        projection[1, 1], projection[1, 2] = k_[1, 1], k_[1, 2]
    projection[2, 2] = -(far + near) / (far - near)
    projection[2, 3] = -2.0 * far * near / (far - near)
    projection[3, 2] = -1.0
    # the corner rays (sample eye (u, v, -1) -> world), scaled to the points' mean sample depth
    for k in range(4):
        for j in range(3):
            rays_out[k, j] = (quad[k, 0] * rot_s[0, j] + quad[k, 1] * rot_s[1, j]
                              - rot_s[2, j]) * mean_depth
        quad_out[k, 0], quad_out[k, 1] = quad[k, 0] / tx, quad[k, 1] / ty
        target_out[k, 0], target_out[k, 1] = target[k, 0], target[k, 1]
    return OK


@njit(cache=True, inline="always")
def _meets_cone(apex, axis, cos, center, radius):
    """Whether the sphere (``center``, ``radius``) meets the cone from ``apex`` around the unit
    ``axis`` with half-angle ``acos(cos)`` (below 90 degrees): Eberly's test, the sphere grown
    by a millionth so that rounding keeps it conservative. A box whose corners all lie outside
    the cone and whose centre lies behind the apex can still cross the cone (a floor passing
    under a spot light)."""
    sin = math.sqrt(max(1.0 - cos * cos, 0.0))
    r = radius * (1 + 1e-6) + 1e-12 * (abs(center[0] - apex[0]) + abs(center[1] - apex[1])
                                        + abs(center[2] - apex[2]))
    step = r / sin  # the cone's apex moved back along the axis: the sphere's centre in it
    dx = center[0] - apex[0] + step * axis[0]
    dy = center[1] - apex[1] + step * axis[1]
    dz = center[2] - apex[2] + step * axis[2]
    e = dx * axis[0] + dy * axis[1] + dz * axis[2]
    if not (e > 0 and e * e >= (dx * dx + dy * dy + dz * dz) * cos * cos):
        return False
    dx, dy, dz = center[0] - apex[0], center[1] - apex[1], center[2] - apex[2]
    e = -(dx * axis[0] + dy * axis[1] + dz * axis[2])
    dd = dx * dx + dy * dy + dz * dz
    if e > 0 and e * e >= dd * sin * sin:  # behind the apex, outside the cone's mirror image
        return dd <= r * r
    return True


@njit(cache=True, nogil=True)
def _fit_boxes(eye, center, axes, half, radius, start, nodes, width, height, effort, spot,
               spot_dir, spot_cos, views, projections, near, far, coverage, status):
    """:func:`_fit_core` for many sets of boxes at once: set ``q`` is the boxes enclosing the
    rounded boxes ``nodes[start[q]:start[q + 1]]`` (a tile's receivers). With ``spot``, a set
    none of whose boxes' spheres reaches into the cone (``spot_dir``, ``spot_cos``) is
    ``UNLIT``."""
    most = 0
    for q in range(start.shape[0] - 1):
        most = max(most, start[q + 1] - start[q])
    c = np.empty((most, 3))
    g = np.empty((most, 3, 3))
    quad, target, rays, axis = np.empty((4, 2)), np.empty((4, 2)), np.empty((4, 3)), np.empty(3)
    info = np.zeros(INFO_SIZE)
    for q in range(start.shape[0] - 1):
        count = start[q + 1] - start[q]
        if count == 0:
            status[q] = EMPTY
            continue
        lit = not spot
        for j in range(count):
            i = nodes[start[q] + j]
            for a in range(3):
                c[j, a] = center[i, a]
                for b in range(3):
                    g[j, a, b] = axes[i, a, b] * (half[i, a] + radius[i])
            if not lit:
                lit = _meets_cone(eye, spot_dir, spot_cos, center[i],
                                  math.sqrt((half[i, 0] + radius[i]) ** 2
                                            + (half[i, 1] + radius[i]) ** 2
                                            + (half[i, 2] + radius[i]) ** 2))
        if not lit:
            status[q] = UNLIT  # no receiver reaches into the spot light's cone
            continue
        status[q] = _fit_core(eye, c[:count], g[:count], width, height, np.nan, np.nan, effort,
                              views[q], projections[q], quad, target, rays, axis, info)
        near[q], far[q], coverage[q] = info[_NEAR], info[_FAR], info[_COVERAGE]


def effort_code(effort: str) -> int:
    """The compiled fits' code of a fitting effort (:data:`EFFORTS`: 0 sphere, 1 greedy, 2
    refined); ValueError for any other word."""
    if effort not in EFFORTS:
        raise ValueError(f"effort must be one of {', '.join(EFFORTS)}, got {effort!r}")
    return EFFORTS.index(effort)


def fit_boxes(eye, bounds, start: np.ndarray, nodes: np.ndarray, width: int, height: int,
              effort: str = "refined", spot: tuple | None = None) -> dict:
    """Low-Ilie fits from ``eye`` around many sets of bounds at once (a wall's tiles, each
    around the bounds of what it shows), split among threads by their sizes: set ``q`` is
    ``bounds`` rows ``nodes[start[q]:start[q + 1]]``, fitted around the corners of the boxes
    that enclose them. ``spot``: ``(direction, cos_angle)`` of a spot light, whose sets wholly
    behind it are ``UNLIT``. Returns arrays: ``status (Q,)`` (``OK``, ``EMPTY``, ``UNLIT``, or
    why no single frustum fits), ``view``, ``projection (Q, 4, 4)``, ``near``, ``far``,
    ``coverage (Q,)``. (A frame's shadows fit their tiles in :func:`wallcull.fit.shadow_sets`,
    each part culling its casters in the same compiled call.)"""
    code = effort_code(effort)
    eye = np.asarray(eye, np.float64).reshape(3)
    count = len(start) - 1
    out = {"status": np.zeros(count, np.int64), "view": np.zeros((count, 4, 4)),
           "projection": np.zeros((count, 4, 4)), "near": np.zeros(count),
           "far": np.zeros(count), "coverage": np.zeros(count)}
    direction, cos_angle = spot if spot is not None else (np.zeros(3), 1.0)

    def chunk(k, a, b):  # sets [a, b): views of the arrays
        _fit_boxes(eye, bounds.center, bounds.axes, bounds.half, bounds.radius,
                   start[a:b + 1], nodes, float(width), float(height), code, spot is not None,
                   np.asarray(direction, np.float64), float(cos_angle),
                   *(out[key][a:b] for key in ("view", "projection", "near", "far", "coverage",
                                               "status")))

    workers.run(chunk, workers.chunks(count, start, per_thread=workers.SPLIT))
    return out


_STATUS_ERRORS = {
    SURROUNDS: (FitError, "the points surround the eye (the eye is inside their bounding sphere "
                          f"and they span more than a {2 * MAX_HALF_ANGLE_DEG:g} degree cone): no "
                          "single perspective frustum from there contains them"),
    COINCIDES: (FitError, "a point coincides with the eye: no frustum from there contains it"),
    HORIZON: (RuntimeError, "fit_frustum: the quad's corners straddle the horizon of the warp"),
    MIRRORED: (RuntimeError, "fit_frustum: the corner assignment mirrored the image"),
}


# ------------------------------------------------------------------------------------ the fit


def fit_frustum(eye, points, width: int, height: int, near: float | None = None,
                far: float | None = None, refine: bool = True,
                effort: str | None = None) -> FrustumFit:
    """Fit a view and projection from ``eye`` ``(3,)`` to ``points`` ``(m, 3)`` (world space)
    for a ``width`` x ``height`` viewport (pixels; only the aspect matters).

    **Sample frustum.** With the eye outside the bounding sphere (centre: the points' bounding
    box centre; radius grown by :data:`SPHERE_PAD`) and the sphere's half-angle at most
    :data:`MAX_HALF_ANGLE_DEG`: the symmetric frustum around the sphere, its shorter side
    touching it, but never narrower than :data:`MIN_HALF_ANGLE` (``sample == "sphere"``).
    Otherwise, e.g. a light inside the bounding sphere of the object it shadows (``sample ==
    "cone"``): the symmetric frustum around the mean of the unit directions to the points, as
    wide as the widest of them. If that is wider than :data:`MAX_HALF_ANGLE_DEG` (the points
    surround the eye: no single frustum sees them all), or a point coincides with the eye,
    :class:`FitError` is raised.

    **Near and far** (``near``/``far`` not given): eq. (17), the bounding sphere's depth range
    in the fitted eye space (the sphere's radius at least :data:`DEPTH_PAD` times its
    distance, so one point still has a range), with the near distance clamped to at least
    ``NEAR_FRACTION * (depth of the nearest point)``: eq. (17) goes to zero or below when the
    eye is near or inside the sphere, which would wreck or invert the depth buffer; the clamp
    keeps ``0 < near <= nearest point``. Given values are used as they are (points outside
    them are clipped: the caller's choice). Depth is along the fitted view's ``-z``, which for
    an oblique fit can be far from the direction of the object.

    **Degenerate images.** Points whose image is a segment (collinear points, a plane seen
    edge-on) get a rectangle around the segment instead of a hull quad: the segment along the
    viewport's long centre line, the rectangle's width set by the viewport's aspect (so the map
    is a similarity) or by the points' spread, whichever is larger (``degenerate ==
    "segment"``; the coverage is ~0, as the image has no area). One point, or coincident
    points: the fit is the sample frustum itself, :data:`MIN_HALF_ANGLE` wide around the
    point (``degenerate == "point"``). Hulls of 3 points
    use the paper's parallelogram, hulls of 4 points themselves (coverage 1).

    **Effort** (:data:`EFFORTS`): ``"refined"`` (the default; ``refine=False`` means
    ``"greedy"``) computes both the greedy and the refined quad and keeps the one whose fitted
    frustum covers more of the viewport: the refined quad is never larger, but a smaller quad
    does not guarantee a larger image (the paper's section 6; the warp is not uniform).
    ``"greedy"`` keeps the paper's quad; ``"sphere"`` returns the sample frustum itself.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise ValueError("fit_frustum needs at least one point")
    if not (np.isfinite(eye).all() and np.isfinite(pts).all()):
        raise ValueError("eye and points must be finite")
    if not (width > 0 and height > 0):
        raise ValueError(f"viewport must have a positive size, got {width} x {height}")
    effort = effort or ("refined" if refine else "greedy")
    code = effort_code(effort)
    view, projection = np.empty((4, 4)), np.empty((4, 4))
    quad, target, rays, axis = np.empty((4, 2)), np.empty((4, 2)), np.empty((4, 3)), np.empty(3)
    info = np.zeros(INFO_SIZE)
    status = _fit_core(eye, pts, np.zeros((len(pts), 3, 3)), float(width), float(height),
                       np.nan if near is None else float(near),
                       np.nan if far is None else float(far), code, view,
                       projection, quad, target, rays, axis, info)
    if status in _STATUS_ERRORS:
        kind, message = _STATUS_ERRORS[status]
        raise kind(message)
    if status == BAD_DEPTH:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    tx, ty, n_s, f_s = info[_TX], info[_TY], info[_NS], info[_FS]
    sample_view = look_at(eye, eye + axis, _up_for(axis))
    sample_projection = frustum(-tx * n_s, tx * n_s, -ty * n_s, ty * n_s, n_s, f_s)
    return FrustumFit(view, projection, quad, float(info[_COVERAGE]), sample_view,
                      sample_projection, float(info[_SAMPLE_COVERAGE]), float(info[_NEAR]),
                      float(info[_FAR]), eye, rays, target,
                      "cone" if info[_SAMPLE] else "sphere",
                      (None, "segment", "point")[int(info[_DEGENERATE])], bool(info[_REFINED]))


def _up_for(axis: np.ndarray) -> np.ndarray:
    """World +y, unless the view axis is within ~8 degrees of it; then world -z."""
    return np.array([0.0, 1.0, 0.0]) if abs(axis[1]) < 0.99 else np.array([0.0, 0.0, -1.0])


# ------------------------------------------------------------------------------ diagnostics


def float32_error(fit: FrustumFit) -> float:
    """Largest NDC error on the four corner correspondences when ``view`` and ``projection``
    are cast to float32 and applied in float32, as a GPU does. The float64 error is ~1e-15;
    the float32 one grows with the view's translation (the eye's distance from the origin):
    render camera-relative (translate the scene by -eye on the CPU) when it matters."""
    v32 = fit.view.astype(np.float32)
    p32 = fit.projection.astype(np.float32)
    c32 = np.c_[fit.corners, np.ones(4)].astype(np.float32)
    clip = (c32 @ v32.T) @ p32.T
    ndc = clip[:, :2] / clip[:, 3:]
    return float(np.abs(ndc.astype(np.float64) - fit.corner_ndc).max())


def bench_fit(n_points: int = 1000, repeat: int = 200, refine: bool = True) -> float:
    """Median milliseconds of :func:`fit_frustum` for ``n_points`` that all lie on the image
    hull (a tilted ring seen from outside), so the quad step sees ``n_points`` hull vertices."""
    t = np.linspace(0.0, 2 * np.pi, n_points, endpoint=False)
    ring = np.c_[np.cos(t), 0.6 * np.sin(t), 0.3 * np.sin(t)]
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, 0.8, -0.6], [0.0, 0.6, 0.8]])
    points = ring @ tilt.T + np.array([0.5, 0.2, -5.0])
    eye = np.array([0.0, 0.0, 0.0])
    fit_frustum(eye, points, 1920, 1080, refine=refine)  # compile the quad kernels
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fit_frustum(eye, points, 1920, 1080, refine=refine)
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


if __name__ == "__main__":  # python -m wallcull.lowilie
    print(f"fit of 1000 hull points: {bench_fit():.3f} ms median "
          f"(greedy only: {bench_fit(refine=False):.3f} ms)")
