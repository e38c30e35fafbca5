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

from .projection import frustum, look_at
from .quad import bounding_quad, quad_area, refine_quad

__all__ = ["FitError", "FrustumFit", "fit_frustum", "float32_error", "bench_fit",
           "MAX_HALF_ANGLE_DEG", "SPHERE_PAD"]

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


# ----------------------------------------------------------------------------- small helpers


def _column_bounds(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column-wise min and max of ``(m, k)``; numpy's axis-0 reductions of narrow arrays are
    ~20x slower than per-column ones."""
    lo = np.array([a[:, j].min() for j in range(a.shape[1])])
    hi = np.array([a[:, j].max() for j in range(a.shape[1])])
    return lo, hi


def _up_for(axis: np.ndarray) -> np.ndarray:
    """World +y, unless the view axis is within ~8 degrees of it; then world -z."""
    return np.array([0.0, 1.0, 0.0]) if abs(axis[1]) < 0.99 else np.array([0.0, 0.0, -1.0])


def _depth_range(center_depth: float, radius: float, depths: np.ndarray) -> tuple[float, float]:
    """Eq. (17) with the near clamp: ``n = max(c - r, NEAR_FRACTION * min depth)``,
    ``f = c + r``."""
    near = max(center_depth - radius, NEAR_FRACTION * float(depths.min()))
    return near, center_depth + radius


def _normalizer(p: np.ndarray) -> np.ndarray:
    """Hartley's similarity ``(3, 3)`` for 4 points ``(4, 2)``: centroid to the origin, mean
    distance sqrt(2). (Plain floats: numpy's per-call overhead dominates at this size.)"""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = p.tolist()
    cx, cy = 0.25 * (x0 + x1 + x2 + x3), 0.25 * (y0 + y1 + y2 + y3)
    mean = 0.25 * (math.hypot(x0 - cx, y0 - cy) + math.hypot(x1 - cx, y1 - cy)
                   + math.hypot(x2 - cx, y2 - cy) + math.hypot(x3 - cx, y3 - cy))
    s = math.sqrt(2.0) / mean
    return np.array([[s, 0.0, -s * cx], [0.0, s, -s * cy], [0.0, 0.0, 1.0]])


def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """3x3 ``H`` with ``dst ~ H src`` for 4 point pairs ``(4, 2)``: the DLT (the null vector of
    the 8x9 system, by SVD) on Hartley-normalized points, then denormalized."""
    ts, td = _normalizer(src), _normalizer(dst)
    s = src * ts[0, 0] + ts[:2, 2]
    d = dst * td[0, 0] + td[:2, 2]
    a = np.zeros((8, 9))
    a[0::2, 0:2] = s
    a[0::2, 2] = 1.0
    a[1::2, 3:5] = s
    a[1::2, 5] = 1.0
    a[0::2, 6:8] = -d[:, :1] * s
    a[0::2, 8] = -d[:, 0]
    a[1::2, 6:8] = -d[:, 1:] * s
    a[1::2, 8] = -d[:, 1]
    h = np.linalg.svd(a)[2][-1].reshape(3, 3)
    return np.linalg.solve(td, h @ ts)  # H = Td^-1 Hn Ts


def _mapped_area(h: np.ndarray, u: np.ndarray, v: np.ndarray) -> float:
    """Area of the polygon with vertices ``(u, v)`` (each ``(m,)``) mapped by homography ``h``."""
    w = h[2, 0] * u + h[2, 1] * v + h[2, 2]
    x = (h[0, 0] * u + h[0, 1] * v + h[0, 2]) / w
    y = (h[1, 0] * u + h[1, 1] * v + h[1, 2]) / w
    return abs(0.5 * float(x[:-1] @ y[1:] - x[1:] @ y[:-1] + x[-1] * y[0] - x[0] * y[-1]))


def _assign_corners(quad: np.ndarray, width: float, height: float) -> np.ndarray:
    """Viewport corner ``(4, 2)`` for each quad corner: the longest edge and its opposite go to
    the viewport's longer sides, in CCW order (orientation preserved), choosing of the two such
    assignments the one that turns the image least."""
    edges = quad[[1, 2, 3, 0]] - quad
    i = int(np.argmax((edges * edges).sum(axis=1)))
    if width >= height:  # bottom side runs +x from corner 0, top side runs -x from corner 2
        start = 0 if edges[i, 0] >= 0 else 2
    else:  # right side runs +y from corner 1, left side runs -y from corner 3
        start = 1 if edges[i, 1] >= 0 else 3
    return _CORNERS[(start - i + np.arange(4)) % 4]


def _rq(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``p = k @ r`` with ``k`` upper triangular and ``r`` orthonormal, via Householder QR (the
    rows of ``r`` are orthonormal to rounding whatever the conditioning of ``k``)."""
    q, u = np.linalg.qr(p[::-1].T)
    k = u.T[::-1, ::-1]
    r = q.T[::-1]
    return k, r


# ------------------------------------------------------------------------------------ the fit


def fit_frustum(eye, points, width: int, height: int, near: float | None = None,
                far: float | None = None, refine: bool = True) -> FrustumFit:
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

    ``refine=True`` computes both the greedy and the refined quad and keeps the one whose fitted
    frustum covers more of the viewport: the refined quad is never larger, but a smaller quad
    does not guarantee a larger image (the paper's section 6; the warp is not uniform).
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise ValueError("fit_frustum needs at least one point")
    if not (np.isfinite(eye).all() and np.isfinite(pts).all()):
        raise ValueError("eye and points must be finite")
    if not (width > 0 and height > 0):
        raise ValueError(f"viewport must have a positive size, got {width} x {height}")
    rel = pts - eye  # eye-relative: keeps full precision far from the origin
    lo, hi = _column_bounds(rel)
    center = 0.5 * (lo + hi)
    dist_c = float(np.linalg.norm(center))
    radius = float(np.sqrt(((rel - center) ** 2).sum(axis=1).max())) * (1.0 + SPHERE_PAD)
    depth_radius = max(radius, DEPTH_PAD * dist_c)
    max_half = math.radians(MAX_HALF_ANGLE_DEG)

    # 1. the sample frustum
    if dist_c > radius and radius / dist_c <= math.sin(max_half):
        sample, axis = "sphere", center / dist_c
        half = max(math.asin(radius / dist_c), MIN_HALF_ANGLE)
    else:
        sample = "cone"
        lengths = np.sqrt((rel ** 2).sum(axis=1))
        if not lengths.min() > 1e-12 * (radius + dist_c):
            raise FitError("a point coincides with the eye: no frustum from there contains it")
        units = rel / lengths[:, None]
        axis = units.mean(axis=0)
        norm = float(np.linalg.norm(axis))
        cos_half = float((units @ axis).min()) / norm if norm > 0 else -1.0
        if not cos_half >= math.cos(max_half):
            raise FitError(
                "the points surround the eye (the eye is inside their bounding sphere and they "
                f"span more than a {2 * MAX_HALF_ANGLE_DEG:g} degree cone): no single "
                "perspective frustum from there contains them")
        axis = axis / norm
        half = max(math.acos(min(cos_half, 1.0)), MIN_HALF_ANGLE)
    sample_view = look_at(eye, eye + axis, _up_for(axis))
    rot_s = sample_view[:3, :3]
    eye_s = rel @ rot_s.T  # sample eye space
    depth_s = -eye_s[:, 2]
    n_s, f_s = _depth_range(float(axis @ center), depth_radius, depth_s)
    aspect = width / height
    t = math.tan(half)
    tx, ty = t * max(aspect, 1.0), t * max(1.0 / aspect, 1.0)  # shorter side touches the sphere
    sample_projection = frustum(-tx * n_s, tx * n_s, -ty * n_s, ty * n_s, n_s, f_s)

    # 2. the sample image in isotropic tangent-plane coordinates (x / -z, y / -z)
    img = eye_s[:, :2] / depth_s[:, None]
    hull_idx, greedy = bounding_quad(img, refine=False)
    hull = img[hull_idx]
    scale = np.array([tx, ty])
    sample_coverage = abs(quad_area(hull)) / (tx * ty) / 4.0 if len(hull) >= 3 else 0.0

    degenerate = None
    candidates = [(greedy, False)]
    diameter = float(np.sqrt(((hull - hull[0]) ** 2).sum(axis=1).max())) if len(hull) > 1 else 0.0
    if len(hull) < 3 or abs(quad_area(hull)) <= FLAT * diameter ** 2:
        if diameter <= 1e-12 * t:
            degenerate = "point"
            candidates = [(_CORNERS * scale, False)]
        else:
            degenerate = "segment"
            candidates = [(_segment_rectangle(hull, aspect), False)]
    elif refine and len(hull) >= 5:
        refined = refine_quad(hull, greedy)
        if quad_area(refined) < quad_area(greedy):
            candidates.append((refined, True))

    # 3. correspondences and the projective map, per candidate quad; keep the best coverage
    best = None
    u, v = hull[:, 0].copy(), hull[:, 1].copy()
    for quad, is_refined in candidates:
        target = _assign_corners(quad, width, height)
        h = _homography(quad, target)
        coverage = _mapped_area(h, u, v) / 4.0 if len(hull) >= 3 else 0.0
        if best is None or coverage > best[0]:
            best = (coverage, quad, target, h, is_refined)
    coverage, quad, target, h, is_refined = best

    # 4. P: world direction -> homogeneous NDC; the sample eye has (u, v, 1) ~ (x, y, -z)
    p = h @ (np.diag([1.0, 1.0, -1.0]) @ rot_s)
    w = quad @ h[2, :2] + h[2, 2]
    if not (np.all(w > 0) or np.all(w < 0)):
        raise RuntimeError("fit_frustum: the quad's corners straddle the horizon of the warp")
    if w[0] < 0:
        p = -p
    k, r = _rq(p)
    signs = np.sign(np.diag(k)) * np.array([1.0, 1.0, -1.0])  # want k00 > 0, k11 > 0, k22 < 0
    k, r = k * signs, signs[:, None] * r
    if np.linalg.det(r) < 0:
        raise RuntimeError("fit_frustum: the corner assignment mirrored the image")
    k = k / -k[2, 2]

    # 5. the matrices
    view = np.eye(4)
    view[:3, :3] = r
    view[:3, 3] = -r @ eye
    depths = -(rel @ r[2])
    if near is None or far is None:
        near_f, far_f = _depth_range(-float(r[2] @ center), depth_radius, depths)
        near = near_f if near is None else float(near)
        far = far_f if far is None else float(far)
    if not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    projection = np.zeros((4, 4))
    projection[0, :3] = k[0]
    projection[1, 1:3] = k[1, 1:]
    projection[2, 2] = -(far + near) / (far - near)
    projection[2, 3] = -2.0 * far * near / (far - near)
    projection[3, 2] = -1.0

    # the corner rays (sample eye (u, v, -1) -> world), scaled to the points' mean sample depth
    rays = (quad @ rot_s[:2] - rot_s[2]) * float(depth_s.mean())
    return FrustumFit(view, projection, quad / scale, float(coverage), sample_view,
                      sample_projection, float(sample_coverage), float(near), float(far),
                      eye, rays, target.copy(), sample, degenerate, is_refined)


def _segment_rectangle(hull: np.ndarray, aspect: float) -> np.ndarray:
    """CCW rectangle ``(4, 2)`` around a (nearly) collinear point set: its long axis along the
    principal direction, padded by 1e-6 of its length; its width the larger of the points'
    spread across and ``length / max(aspect, 1 / aspect)``."""
    c = hull.mean(axis=0)
    _, _, vt = np.linalg.svd(hull - c)
    u, v = vt[0], np.array([-vt[0, 1], vt[0, 0]])
    t, s = (hull - c) @ u, (hull - c) @ v
    length = float(t.max() - t.min()) * (1 + 2e-6)
    width = max(float(s.max() - s.min()) * (1 + 2e-6), length / max(aspect, 1.0 / aspect))
    mid = c + u * 0.5 * (t.max() + t.min()) + v * 0.5 * (s.max() + s.min())
    hu, hv = 0.5 * length * u, 0.5 * width * v
    return np.array([mid - hu - hv, mid + hu - hv, mid + hu + hv, mid - hu + hv])


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
