"""Projection and view matrices (Lengyel, *Mathematics for 3D Game Programming*, ch. 5).

Conventions (SPEC section 1): OpenGL, right-handed, the camera looks down its local ``-z``,
column vectors (``p_clip = M @ p``), clip-space depth in ``[-1, 1]``. Every matrix is a float64
``(4, 4)`` numpy array indexed ``m[row, col]``, which is also the wire order (row by row).

A plane is a row ``(nx, ny, nz, d)``; a homogeneous point ``p`` lies on its positive side when
``plane @ p >= 0``. Frustum planes have unit normals pointing *into* the frustum, the same
convention as :mod:`wallcull.wall`.

The functions:

* :func:`frustum`, :func:`infinite_frustum`: Lengyel's ``M_frustum`` and eq. (5.53);
* :func:`reversed_z`: reversed-Z with ``[0, 1]`` depth (near -> 1, far or infinity -> 0);
  :func:`as_reversed_z` turns any ``[-1, 1]`` matrix (an oblique one) into one;
* :func:`look_at`, :func:`rigid_inverse`, :func:`tile_view_projection`: view matrices;
* :func:`frustum_planes`: the six planes of any projection-view matrix (Gribb-Hartmann);
* :func:`frustum_extents`: ``l, r, b, t, n, f`` back from off-axis projections (the wire's
  compact form);
* :func:`oblique_near`: Lengyel's oblique near plane, eq. (5.68) / Listing 5.1, generalized.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "ClipPlaneError",
    "frustum",
    "infinite_frustum",
    "reversed_z",
    "as_reversed_z",
    "look_at",
    "rigid_inverse",
    "tile_view_projection",
    "frustum_planes",
    "frustum_extents",
    "oblique_near",
    "oblique_near_many",
    "mirrored_views",
    "transform_points",
]


#: An oblique near plane is refused when the camera lies within this fraction of the
#: projection's near distance of it (``through_camera``): the depth buffer would resolve no
#: better than with a near plane that near. A mirror is seen only by an eye farther than this
#: in front of it (:meth:`wallcull.fit.MirrorSight.of`, with the wall's near distance).
THROUGH_CAMERA = 1e-6


class ClipPlaneError(ValueError):
    """:func:`oblique_near` cannot use the plane: see ``reason``.

    ``reason`` is one of

    * ``"through_camera"``: the camera lies on the plane (within the tolerance);
    * ``"camera_visible"``: the camera is on the visible (positive) side of the plane;
    * ``"clips_everything"``: the whole view frustum is on the clipped side.

    In all three cases no perspective matrix with an unmodified fourth row can have that plane as
    its near plane, and in all three the reflection (or whatever the plane bounds) shows nothing:
    a mirror seen edge-on or from behind, or out of view. Callers skip that render pass.
    """

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


# --------------------------------------------------------------------------- perspective matrices


def _check_extent(l, r, b, t, n) -> None:
    if not (r != l and t != b and n > 0):
        raise ValueError(f"need l != r, b != t and n > 0, got l={l}, r={r}, b={b}, t={t}, n={n}")


def frustum(l: float, r: float, b: float, t: float, n: float, f: float) -> np.ndarray:
    """Off-axis perspective projection, ``(4, 4)`` (Lengyel ``M_frustum``, ``glFrustum``).

    ``l, r, b, t`` bound the view rectangle on the near plane ``z = -n``; ``0 < n < f`` are the
    distances of the near and far planes. Eye-space ``z = -n`` maps to NDC depth -1, ``z = -f``
    to +1.
    """
    _check_extent(l, r, b, t, n)
    if not f > n:
        raise ValueError(f"need far > near, got n={n}, f={f}")
    m = np.zeros((4, 4))
    m[0, 0] = 2.0 * n / (r - l)
    m[0, 2] = (r + l) / (r - l)
    m[1, 1] = 2.0 * n / (t - b)
    m[1, 2] = (t + b) / (t - b)
    m[2, 2] = -(f + n) / (f - n)
    m[2, 3] = -2.0 * n * f / (f - n)
    m[3, 2] = -1.0
    return m


def infinite_frustum(l: float, r: float, b: float, t: float, n: float,
                     epsilon: float = 0.0) -> np.ndarray:
    """Off-axis perspective projection with the far plane at infinity, ``(4, 4)``.

    ``epsilon = 0`` is Lengyel eq. (5.53), the limit of :func:`frustum` as ``f -> inf``: a point
    at infinity lands exactly on NDC depth +1, where rounding in the hardware clips it half the
    time. ``epsilon > 0`` is Lengyel's fix (row 3 = ``(0, 0, epsilon - 1, (epsilon - 2) n)``):
    infinity lands on ``1 - epsilon`` and the near plane stays at -1. Use ``epsilon`` of a few
    float32 ulps of 1, e.g. ``2.4e-7``, when rendering shadow volumes closed at infinity.
    """
    _check_extent(l, r, b, t, n)
    if not 0.0 <= epsilon < 1.0:
        raise ValueError(f"need 0 <= epsilon < 1, got {epsilon}")
    m = frustum(l, r, b, t, n, 2.0 * n)  # rows 1, 2 and 4 do not depend on f
    m[2, 2] = epsilon - 1.0
    m[2, 3] = (epsilon - 2.0) * n
    return m


def reversed_z(l: float, r: float, b: float, t: float, n: float,
               f: float = math.inf) -> np.ndarray:
    """Reversed-Z off-axis projection with ``[0, 1]`` clip depth, ``(4, 4)``.

    NDC depth is ``z_ndc = z_clip / w_clip`` with ``z = -n -> 1`` and ``z = -f -> 0`` (``f`` may
    be ``math.inf``: row 3 becomes ``(0, 0, 0, n)`` and ``z_ndc = n / distance``). Rows 1, 2
    and 4 are those of :func:`frustum`.

    This is *not* an OpenGL ``[-1, 1]`` matrix: the client must call
    ``glClipControl(GL_LOWER_LEFT, GL_ZERO_TO_ONE)`` (GL 4.5 / ARB_clip_control), clear depth to
    0, use ``glDepthFunc(GL_GREATER)`` and a floating-point depth buffer
    (``GL_DEPTH_COMPONENT32F``).
    Why [0, 1] and not [-1, 1]: the float32 depth value is then proportional to ``n / distance``,
    so its relative precision (2^-24) becomes relative precision in distance, uniform from near to
    infinity; the ``[-1, 1]`` mapping ``w = 0.5 z_ndc + 0.5`` adds 0.5 and throws those bits away.
    The precision claim is checked numerically in the tests.

    Use ``frustum_planes(m, reversed_z=True)`` to read its planes.
    """
    _check_extent(l, r, b, t, n)
    if not f > n:
        raise ValueError(f"need far > near, got n={n}, f={f}")
    m = frustum(l, r, b, t, n, 2.0 * n)
    if math.isinf(f):
        m[2, 2], m[2, 3] = 0.0, n
    else:
        # z_ndc = (A z + B) / -z with A = n / (f - n), B = n f / (f - n): 1 at -n, 0 at -f.
        m[2, 2], m[2, 3] = n / (f - n), n * f / (f - n)
    return m


def as_reversed_z(projections: np.ndarray) -> np.ndarray:
    """``[-1, 1]`` projections (``(..., 4, 4)``, oblique ones included) as reversed-Z ones with
    ``[0, 1]`` clip depth: NDC depth ``z`` becomes ``(1 - z) / 2`` (row 3 becomes half of row
    4 minus row 3), so near (or the oblique plane) lands on 1 and far on 0, and what was
    clipped is clipped."""
    out = np.array(projections, np.float64)
    out[..., 2, :] = 0.5 * (out[..., 3, :] - out[..., 2, :])
    return out


def frustum_extents(projections: np.ndarray, near: np.ndarray, far: np.ndarray) -> np.ndarray:
    """``(..., 6)``: ``l, r, b, t, n, f`` of off-axis projections ``(..., 4, 4)`` (any of
    :func:`frustum`, :func:`infinite_frustum`, :func:`reversed_z`) with near and far distances
    ``near``, ``far``: the rectangle on the near plane that the x and y rows map to [-1, 1]
    (``m00 = 2n / (r - l)``, ``m02 = (r + l) / (r - l)``, and the same for y)."""
    m = np.asarray(projections, np.float64)
    n = np.asarray(near, np.float64)
    out = np.empty(m.shape[:-2] + (6,))
    out[..., 0] = n * (m[..., 0, 2] - 1) / m[..., 0, 0]
    out[..., 1] = n * (m[..., 0, 2] + 1) / m[..., 0, 0]
    out[..., 2] = n * (m[..., 1, 2] - 1) / m[..., 1, 1]
    out[..., 3] = n * (m[..., 1, 2] + 1) / m[..., 1, 1]
    out[..., 4] = n
    out[..., 5] = far
    return out


# --------------------------------------------------------------------------------- view matrices


def rigid_inverse(m: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform ``[R | t]`` (``R`` orthonormal), ``(4, 4)``: ``[R^T | -R^T t]``.

    Exact up to rounding where ``np.linalg.inv`` would spend conditioning; the caller is trusted
    that ``R`` is orthonormal (not checked).
    """
    m = np.asarray(m, dtype=np.float64)
    out = np.eye(4)
    rt = m[:3, :3].T
    out[:3, :3] = rt
    out[:3, 3] = -rt @ m[:3, 3]
    return out


def _cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (``np.cross`` costs ~10 us of call overhead)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World -> eye view matrix, ``(4, 4)`` (``gluLookAt``): the eye at ``eye`` looks down its
    ``-z`` toward ``target`` with ``+y`` as close to ``up`` as possible. Rigid (det +1).

    Raises ``ValueError`` when ``target == eye`` or ``up`` is parallel to the view direction.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    forward = np.asarray(target, dtype=np.float64).reshape(3) - eye
    up = np.asarray(up, dtype=np.float64).reshape(3)
    norm_f = np.linalg.norm(forward)
    if not norm_f > 0:
        raise ValueError("look_at: target coincides with eye")
    forward = forward / norm_f
    side = _cross3(forward, up)
    norm_s = np.linalg.norm(side)
    if not norm_s > 1e-12 * np.linalg.norm(up):
        raise ValueError("look_at: up is parallel to the view direction")
    side = side / norm_s
    true_up = _cross3(side, forward)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = side, true_up, -forward
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def transform_points(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a ``(4, 4)`` matrix to points ``(n, 3)``: homogeneous ``(n, 4)``, not divided."""
    points = np.asarray(points, dtype=np.float64)
    return points @ m[:, :3].T + m[:, 3]


def tile_view_projection(wall, frame, tile: int, near: float | None = None,
                         far: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(view, projection)`` that render one tile of the wall for the frame's tracked eye.

    The view maps world to eye space whose axes are display space's (x right, y up, z toward the
    viewer) and whose origin is the tracked eye: ``view = inverse([R(q) | R(q) eye + t])``. The
    projection is the off-axis :func:`frustum` through the tile rectangle as seen from the eye:
    the rectangle lies at eye-space ``z = -(distance + eye_z)`` and is scaled onto the near plane,
    ``l = (x0 - ex) n / (distance + ez)`` and so on. ``near``/``far`` default to the wall's, as
    distances from the eye along ``-z`` (SPEC section 2), so the planes of ``projection @ view``
    are the culler's tile planes (see :func:`frustum_planes`).
    """
    near = wall.near if near is None else float(near)
    far = wall.far if far is None else float(far)
    ex, ey, ez = frame.eye
    depth = wall.distance + ez
    x0, x1, y0, y1 = wall.tile_rect(tile)
    scale = near / depth
    projection = frustum((x0 - ex) * scale, (x1 - ex) * scale,
                         (y0 - ey) * scale, (y1 - ey) * scale, near, far)
    return view_matrix(frame), projection


def view_matrix(frame, eye=None) -> np.ndarray:
    """World to eye space for a frame: display space's axes, origin at the tracked eye (or at
    ``eye``, display space: one eye of a stereo frame), ``inverse([R(q) | R(q) eye + t])``.
    The same for every tile of a grid wall."""
    eye_to_world = np.eye(4)
    eye_to_world[:3, :3] = frame.rotation
    eye_to_world[:3, 3] = frame.to_world(frame.eye if eye is None else np.asarray(eye))
    return rigid_inverse(eye_to_world)


# ---------------------------------------------------------------------------------------- planes

#: Row combinations of Gribb-Hartmann / Lengyel Table 5.2, as (sign, row) added to row 4.
_PLANE_ROWS = ((+1, 0), (-1, 0), (+1, 1), (-1, 1), (+1, 2), (-1, 2))


def frustum_planes(m: np.ndarray, reversed_z: bool = False) -> np.ndarray:
    """The six frustum planes of a projection (or projection @ view) matrix, ``(6, 4)``.

    Order: left, right, bottom, top, near, far. Rows ``(nx, ny, nz, d)`` with unit normals
    pointing into the frustum, in the space ``m`` maps from (eye space for a projection, world
    space for ``projection @ view``). Clip space is ``-w <= x, y, z <= w`` (Lengyel Table 5.2:
    left = ``M4 + M1``, right = ``M4 - M1``, ..., near = ``M4 + M3``, far = ``M4 - M3``). With
    ``reversed_z=True`` the depth range is :func:`reversed_z`'s ``0 <= z <= w``: near is
    ``M4 - M3``, far is ``M3``.

    **Far at infinity.** For an infinite projection the far combination has a zero normal:
    ``(0, 0, 0, c)`` with ``c > 0``, the plane at infinity, which every finite point satisfies.
    It is returned as ``(0, 0, 0, 1)``: a plane test against it always passes, so a culler that
    loops over six planes needs no special case. A normal counts as zero when its length is
    within 64 ulps of the rows it was computed from (for a finite far plane that is
    ``far / near > ~1e14``, beyond which the plane is not determined in float64 anyway). A zero
    normal with ``c <= 0`` (nothing inside) or for any other plane means ``m`` is not a
    perspective or orthographic projection and raises ``ValueError``. With Lengyel's
    ``epsilon > 0`` (:func:`infinite_frustum`) the far row is a genuine plane, ``z = (2 - eps)
    n / eps`` in eye space, *behind* the eye, which every point in front of the eye satisfies;
    it is returned as such.
    """
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"need a (4, 4) matrix, got shape {m.shape}")
    rows = [m[3] + s * m[k] for s, k in _PLANE_ROWS]
    scales = [np.abs(m[3, :3]).sum() + np.abs(m[k, :3]).sum() for _, k in _PLANE_ROWS]
    if reversed_z:
        rows[4], rows[5] = m[3] - m[2], m[2].copy()
        scales[4] = np.abs(m[3, :3]).sum() + np.abs(m[2, :3]).sum()
        scales[5] = np.abs(m[2, :3]).sum()
    planes = np.array(rows)
    norms = np.linalg.norm(planes[:, :3], axis=1)
    zero = norms <= 64 * np.finfo(np.float64).eps * np.asarray(scales)
    for i in np.flatnonzero(zero):
        if i != 5 or not planes[i, 3] > 0:
            raise ValueError(f"degenerate frustum: plane {i} of the matrix has no normal")
        planes[i] = (0.0, 0.0, 0.0, 1.0)
        norms[i] = 1.0
    return planes / norms[:, None]


# -------------------------------------------------------------------------- oblique near plane


def oblique_near(projection: np.ndarray, clip_plane, rtol: float = THROUGH_CAMERA) -> np.ndarray:
    """Replace the near plane of a perspective projection by an eye-space plane (Lengyel 5.6).

    ``projection``: any ``[-1, 1]`` perspective matrix whose fourth row is ``(0, 0, -1, 0)``,
    off-axis and infinite ones included (a reversed-Z matrix is not supported). ``clip_plane``:
    ``(a, b, c, d)`` in eye space; what is drawn is its positive side ``a x + b y + c z + d >= 0``
    (for a mirror: the half-space behind the mirror surface, as seen by the reflected camera).
    The camera must be on the negative side, ``d < 0`` (Lengyel's ``C_w < 0``).

    Returns a new matrix whose rows 1, 2 and 4 are the input's and whose row 3 is
    ``u C - M4`` (eq. 5.67) with ``u = 2 / (C . Q)`` and ``Q = M^-1 (sgn C'x, sgn C'y, 1, 1)``,
    ``C' = M^-T C`` (eq. 5.64-5.66), which is eq. (5.68) and Listing 5.1 for any matrix of
    :func:`frustum`'s form, off-axis or infinite (there ``C'x = Cx / m00``, so Lengyel's shortcut
    ``sgn C' = sgn C`` is exact; the tests use the listing as the oracle). Then: points on the plane
    map to NDC depth -1, points on its negative side to depth < -1 (clipped), and the new far
    plane passes through the frustum corner ``Q``, so no point of the original frustum on the
    positive side of the plane is clipped by it. For an infinite projection ``Q`` is a direction
    (``Q_w = 0``) and the new far plane is parallel to that frustum edge (Lengyel Exercise 7).

    Raises :class:`ClipPlaneError` when the plane cannot be a near plane:

    * the camera is within ``rtol * near`` of the plane (``near``: distance from the camera to
      the projection's own near plane, the only length scale a projection knows;
      :data:`THROUGH_CAMERA` by default). A plane through the camera would make rows 3 and 4
      proportional at the eye, and one just beside it leaves the depth buffer no precision; a
      mirror seen from that close shows nothing.
    * the camera is on the positive side: the plane would have to clip the camera's own
      neighbourhood while keeping what is behind it, which a perspective matrix cannot do.
    * ``C . Q <= 0``: the plane clips the whole frustum.

    Raising rather than returning the unmodified matrix because the unmodified matrix draws the
    geometry the plane was meant to remove (the mirror artefacts of Lengyel Fig. 5.20); skipping
    the pass is the right answer in every one of these cases, and only the caller can skip it.
    """
    m = np.asarray(projection, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError("oblique_near needs a perspective projection with row 4 = (0, 0, -1, 0)")
    out, reason = oblique_near_many(m[None], clip_plane, rtol)
    if reason[0]:
        raise ClipPlaneError(*_CLIP_REFUSALS[int(reason[0])])
    return out[0]


#: Why :func:`oblique_near_many` refused a matrix (its ``reason`` codes 1-3).
_CLIP_REFUSALS = {
    1: ("through_camera", "the clip plane passes too close to the camera"),
    2: ("camera_visible", "the camera is on the visible (positive) side of the clip plane"),
    3: ("clips_everything", "the clip plane clips the whole view frustum"),
}


def oblique_near_many(projections: np.ndarray, clip_plane, rtol: float = THROUGH_CAMERA
                      ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`oblique_near` for many projections ``(k, 4, 4)`` and one eye-space plane ``(4,)``
    (a mirror seen by every tile of a grid wall) or one each ``(k, 4)`` (each tile's own eye
    space): ``(matrices (k, 4, 4), reason (k,))``, ``reason`` 0 where the matrix was made, else
    1 (through the camera), 2 (camera on the visible side) or 3 (clips everything), as
    :class:`ClipPlaneError`'s reasons; those rows are left as they were."""
    m = np.asarray(projections, dtype=np.float64)
    if m.ndim != 3 or m.shape[1:] != (4, 4) or not _perspective(m):
        raise ValueError("oblique_near needs a perspective projection with row 4 = (0, 0, -1, 0)")
    c = np.asarray(clip_plane, np.float64)  # checked before it is repeated for every matrix
    if not (np.isfinite(c).all() and (np.linalg.norm(c[..., :3], axis=-1) > 0).all()):
        raise ValueError(f"clip plane {c.reshape(-1, 4)[:1].tolist()} has no normal")
    c = np.ascontiguousarray(np.broadcast_to(c, (len(m), 4)))
    out = m.copy()
    reason = np.zeros(len(m), np.int64)
    _oblique(m, c, rtol, out, reason)
    return out, reason


def mirrored_views(views: np.ndarray, projections: np.ndarray, reflection: np.ndarray,
                   plane: np.ndarray, rtol: float = THROUGH_CAMERA
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What each of many cameras (rigid ``views``, ``(k, 4, 4)`` or one ``(4, 4)`` for all;
    ``projections (k, 4, 4)``) needs to draw the reflection in a mirror (``reflection (4,
    4)`` through the world ``plane (4,)``, reflective side positive): ``(views @ reflection,
    the projections with the mirror as oblique near plane, reason)``, ``reason`` as
    :func:`oblique_near_many`'s (the mirror's plane in each camera's eye space from the view's
    rigid inverse). One compiled pass that releases the interpreter: a mirror's matrices are
    made beside a frame's shadow passes."""
    views = np.asarray(views, np.float64)
    projections = np.ascontiguousarray(projections, np.float64)
    flat = np.ascontiguousarray(views.reshape(-1, 4, 4))
    if projections.ndim != 3 or projections.shape[1:] != (4, 4) \
            or len(flat) not in (1, len(projections)):
        raise ValueError(f"mirrored_views needs (k, 4, 4) projections and as many views or "
                         f"one, got {views.shape} and {projections.shape}")
    out_views = np.empty_like(flat)
    oblique = projections.copy()
    reason = np.zeros(len(projections), np.int64)
    if not _mirrored(flat, projections, np.ascontiguousarray(reflection, np.float64),
                     np.ascontiguousarray(plane, np.float64), rtol, out_views, oblique, reason):
        raise ValueError("oblique_near needs a perspective projection with row 4 = (0, 0, -1, 0)")
    return out_views.reshape(views.shape), oblique, reason


@njit(cache=True, nogil=True)
def _perspective(projections) -> bool:
    """Whether every matrix of ``projections (k, 4, 4)`` has the fourth row ``(0, 0, -1, 0)``
    (within 1e-12; not NaN) that :func:`oblique_near` needs."""
    for t in range(projections.shape[0]):
        m = projections[t]
        if not (abs(m[3, 0]) <= 1e-12 and abs(m[3, 1]) <= 1e-12 and abs(m[3, 2] + 1.0) <= 1e-12
                and abs(m[3, 3]) <= 1e-12):
            return False
    return True


@njit(cache=True, nogil=True)
def _mirrored(views, projections, reflection, plane, rtol, out_views, oblique, reason):
    """The body of :func:`mirrored_views` (``views (1 or k, 4, 4)``); False if a projection's
    fourth row is not ``(0, 0, -1, 0)``."""
    if not _perspective(projections):
        return False
    k = projections.shape[0]
    for t in range(views.shape[0]):
        v = views[t]
        for i in range(4):
            for j in range(4):
                out_views[t, i, j] = (v[i, 0] * reflection[0, j] + v[i, 1] * reflection[1, j]
                                      + v[i, 2] * reflection[2, j] + v[i, 3] * reflection[3, j])
    clip = np.empty((k, 4))
    for t in range(k):
        v = views[t if views.shape[0] > 1 else 0]
        # the eye-space plane: -plane . view^-1, with view^-1 = [R^T | -R^T t]
        for j in range(3):
            clip[t, j] = -(v[j, 0] * plane[0] + v[j, 1] * plane[1] + v[j, 2] * plane[2])
        clip[t, 3] = -plane[3] - (v[0, 3] * clip[t, 0] + v[1, 3] * clip[t, 1]
                                  + v[2, 3] * clip[t, 2])
    _oblique(projections, clip, rtol, oblique, reason)
    return True


# Small products inside compiled kernels are written out: numba's ``@``, ``np.dot`` and
# ``np.linalg`` call SciPy's BLAS and LAPACK, which the base install does not have (a kernel
# that used them would stop the process, not raise).
@njit(cache=True)
def matmul(a, b):
    """``a @ b`` for 2-D arrays, in a compiled kernel."""
    out = np.zeros((a.shape[0], b.shape[1]))
    for i in range(a.shape[0]):
        for k in range(a.shape[1]):
            x = a[i, k]
            for j in range(b.shape[1]):
                out[i, j] += x * b[k, j]
    return out


@njit(cache=True)
def matvec(a, v):
    """``a @ v`` for a 2-D ``a`` and a 1-D ``v``, in a compiled kernel."""
    out = np.zeros(a.shape[0])
    for i in range(a.shape[0]):
        for k in range(a.shape[1]):
            out[i] += a[i, k] * v[k]
    return out


@njit(cache=True)
def dot(u, v):
    """``u @ v`` for 1-D arrays, in a compiled kernel."""
    total = 0.0
    for k in range(u.shape[0]):
        total += u[k] * v[k]
    return total


@njit(cache=True)
def _inverse4(m):
    """Inverse of a 4x4 matrix by cofactors (no pivoting needed for projections: they are
    well conditioned in the sense that matters here, and LAPACK's call overhead is 50x the
    arithmetic)."""
    inv = np.empty((4, 4))
    a = m.ravel()
    s0 = a[0] * a[5] - a[4] * a[1]
    s1 = a[0] * a[6] - a[4] * a[2]
    s2 = a[0] * a[7] - a[4] * a[3]
    s3 = a[1] * a[6] - a[5] * a[2]
    s4 = a[1] * a[7] - a[5] * a[3]
    s5 = a[2] * a[7] - a[6] * a[3]
    c5 = a[10] * a[15] - a[14] * a[11]
    c4 = a[9] * a[15] - a[13] * a[11]
    c3 = a[9] * a[14] - a[13] * a[10]
    c2 = a[8] * a[15] - a[12] * a[11]
    c1 = a[8] * a[14] - a[12] * a[10]
    c0 = a[8] * a[13] - a[12] * a[9]
    det = s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0
    d = 1.0 / det
    inv[0, 0] = (a[5] * c5 - a[6] * c4 + a[7] * c3) * d
    inv[0, 1] = (-a[1] * c5 + a[2] * c4 - a[3] * c3) * d
    inv[0, 2] = (a[13] * s5 - a[14] * s4 + a[15] * s3) * d
    inv[0, 3] = (-a[9] * s5 + a[10] * s4 - a[11] * s3) * d
    inv[1, 0] = (-a[4] * c5 + a[6] * c2 - a[7] * c1) * d
    inv[1, 1] = (a[0] * c5 - a[2] * c2 + a[3] * c1) * d
    inv[1, 2] = (-a[12] * s5 + a[14] * s2 - a[15] * s1) * d
    inv[1, 3] = (a[8] * s5 - a[10] * s2 + a[11] * s1) * d
    inv[2, 0] = (a[4] * c4 - a[5] * c2 + a[7] * c0) * d
    inv[2, 1] = (-a[0] * c4 + a[1] * c2 - a[3] * c0) * d
    inv[2, 2] = (a[12] * s4 - a[13] * s2 + a[15] * s0) * d
    inv[2, 3] = (-a[8] * s4 + a[9] * s2 - a[11] * s0) * d
    inv[3, 0] = (-a[4] * c3 + a[5] * c1 - a[6] * c0) * d
    inv[3, 1] = (a[0] * c3 - a[1] * c1 + a[2] * c0) * d
    inv[3, 2] = (-a[12] * s3 + a[13] * s1 - a[14] * s0) * d
    inv[3, 3] = (a[8] * s3 - a[9] * s1 + a[10] * s0) * d
    return inv


@njit(cache=True)
def _oblique(m, c, rtol, out, reason):
    """The body of :func:`oblique_near_many`: row 3 of ``out[k]`` replaced, or ``reason[k]``
    set (1 through the camera, 2 camera visible, 3 clips everything)."""
    corner = np.empty(4)
    for k in range(m.shape[0]):
        normal = math.sqrt(c[k, 0] ** 2 + c[k, 1] ** 2 + c[k, 2] ** 2)
        distance = c[k, 3] / normal  # signed distance of the camera (eye space origin)
        near_plane = m[k, 3] + m[k, 2]
        near = abs(near_plane[3]) / math.sqrt(near_plane[0] ** 2 + near_plane[1] ** 2
                                                 + near_plane[2] ** 2)
        if abs(distance) <= rtol * near:
            reason[k] = 1
            continue
        if distance > 0:
            reason[k] = 2
            continue
        inv = _inverse4(m[k])
        c_clip = matvec(inv.T, c[k])  # C' = M^-T C
        corner[0] = 1.0 if c_clip[0] > 0 else (-1.0 if c_clip[0] < 0 else 0.0)
        corner[1] = 1.0 if c_clip[1] > 0 else (-1.0 if c_clip[1] < 0 else 0.0)
        corner[2] = corner[3] = 1.0
        q = matvec(inv, corner)  # Q = M^-1 (sgn C'x, sgn C'y, 1, 1)
        cq = dot(c[k], q)
        if not cq > 0:
            reason[k] = 3
            continue
        scale = 2.0 * dot(m[k, 3], q) / cq
        for j in range(4):
            out[k, 2, j] = scale * c[k, j] - m[k, 3, j]
