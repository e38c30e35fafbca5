"""Projection toolkit: exact oracles (Lengyel's matrices), round trips against the culler's tile
planes, the reversed-Z precision claim, and the oblique near plane with its refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings, strategies as st

from wallcull.projection import (
    ClipPlaneError, frustum, frustum_planes, infinite_frustum, look_at, mirrored_views,
    oblique_near, oblique_near_many, reversed_z, rigid_inverse, tile_view_projection, transform_points)
from wallcull.wall import Frame, Frusta, Wall

FAST = settings(max_examples=60, deadline=None)


def ndc(m, points):
    h = transform_points(m, np.atleast_2d(points))
    return h[:, :3] / h[:, 3:]


# --------------------------------------------------------------------------------- strategies

finite = dict(allow_nan=False, allow_infinity=False)


@st.composite
def extents(draw):
    """Off-axis view rectangles on the near plane, and near/far distances."""
    n = draw(st.floats(1e-3, 10.0, **finite))
    l = draw(st.floats(-5.0, 5.0, **finite)) * n
    w = draw(st.floats(0.01, 5.0, **finite)) * n
    b = draw(st.floats(-5.0, 5.0, **finite)) * n
    h = draw(st.floats(0.01, 5.0, **finite)) * n
    f = n * draw(st.floats(1.5, 1e4, **finite))
    return l, l + w, b, b + h, n, f


def unit_quaternion(draw):
    q = np.array([draw(st.floats(-1, 1, **finite)) for _ in range(4)])
    assume(np.linalg.norm(q) > 0.1)
    return q / np.linalg.norm(q)


@st.composite
def wall_frame(draw):
    cols, rows = draw(st.integers(1, 6)), draw(st.integers(1, 5))
    w, h = draw(st.floats(0.1, 2.0)), draw(st.floats(0.1, 2.0))
    gx = draw(st.floats(-0.5, 0.2)) * w  # negative: projector overlap
    gy = draw(st.floats(-0.5, 0.2)) * h
    near = draw(st.floats(0.01, 1.0))
    far = near * draw(st.floats(10.0, 1e5))
    distance = draw(st.floats(near + 0.1, 20.0))
    wall = Wall.from_dict({"cols": cols, "rows": rows, "tile_size": [w, h], "gap": [gx, gy],
                           "distance": distance, "near": near, "far": far})
    eye = [draw(st.floats(-3, 3)), draw(st.floats(-3, 3)),
           draw(st.floats(-distance + near + 0.05, 5.0))]
    position = [draw(st.floats(-100, 100)) for _ in range(3)]
    frame = Frame.make(position, unit_quaternion(draw), eye, wall)
    tile = draw(st.integers(0, wall.tiles - 1))
    return wall, frame, tile


# ------------------------------------------------------------------------------------ frustum


def test_frustum_is_lengyel_m_frustum():
    l, r, b, t, n, f = -1.0, 3.0, -2.0, 1.0, 0.5, 10.0
    expected = np.array([
        [2 * n / (r - l), 0, (r + l) / (r - l), 0],
        [0, 2 * n / (t - b), (t + b) / (t - b), 0],
        [0, 0, -(f + n) / (f - n), -2 * n * f / (f - n)],
        [0, 0, -1, 0]])
    np.testing.assert_array_equal(frustum(l, r, b, t, n, f), expected)


@FAST
@given(extents())
def test_frustum_maps_its_corners_to_the_ndc_cube_corners(e):
    l, r, b, t, n, f = e
    m = frustum(*e)
    s = f / n
    near = [[l, b, -n], [r, b, -n], [r, t, -n], [l, t, -n]]
    far = [[x * s, y * s, -f] for x, y, _ in near]
    cube = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)
    np.testing.assert_allclose(ndc(m, near), np.c_[cube, -np.ones(4)], rtol=0, atol=1e-12)
    np.testing.assert_allclose(ndc(m, far), np.c_[cube, np.ones(4)], rtol=0, atol=1e-9)


def test_frustum_rejects_empty_extents():
    with pytest.raises(ValueError):
        frustum(1, 1, 0, 1, 0.1, 10)
    with pytest.raises(ValueError):
        frustum(0, 1, 0, 1, 0.0, 10)
    with pytest.raises(ValueError):
        frustum(0, 1, 0, 1, 1.0, 1.0)


@FAST
@given(extents())
def test_infinite_frustum_is_the_limit_and_epsilon_moves_infinity(e):
    l, r, b, t, n, _ = e
    m = infinite_frustum(l, r, b, t, n)
    far = frustum(l, r, b, t, n, n * 1e12)
    np.testing.assert_allclose(m, far, rtol=1e-9, atol=1e-9 * n)
    np.testing.assert_allclose(ndc(m, [[l, b, -n]])[0], [-1, -1, -1], atol=1e-12)
    direction = np.array([l, t, -n, 0.0])  # a point at infinity inside the frustum
    clip = m @ direction
    assert clip[2] / clip[3] == pytest.approx(1.0, abs=1e-15)
    eps = 2.4e-7
    me = infinite_frustum(l, r, b, t, n, epsilon=eps)
    clip = me @ direction
    assert clip[2] / clip[3] == pytest.approx(1.0 - eps, abs=1e-15)
    assert ndc(me, [[r, t, -n]])[0, 2] == pytest.approx(-1.0, abs=1e-12)


# ---------------------------------------------------------------------------------- reversed Z


@FAST
@given(extents())
def test_reversed_z_maps_near_to_one_and_far_to_zero(e):
    l, r, b, t, n, f = e
    m = reversed_z(*e)
    np.testing.assert_allclose(m[[0, 1, 3]], frustum(*e)[[0, 1, 3]])
    depth = ndc(m, [[l, b, -n], [0, 0, -f], [0, 0, -math.sqrt(n * f)]])[:, 2]
    np.testing.assert_allclose(depth[:2], [1.0, 0.0], atol=1e-12)
    assert 0 < depth[2] < 1
    mi = reversed_z(l, r, b, t, n)  # infinite far: depth = n / distance
    d = np.array([n, 2 * n, 1e3 * n, 1e9 * n])
    np.testing.assert_allclose(ndc(mi, np.c_[0 * d, 0 * d, -d])[:, 2], n / d, rtol=1e-15)


def _stored_depth_float32(m, distance, zero_to_one):
    """What a GPU stores: clip = M p in float32, divide in float32, window depth in float32."""
    m32 = m.astype(np.float32)
    p = np.stack([np.zeros_like(distance), np.zeros_like(distance), -distance,
                  np.ones_like(distance)]).astype(np.float32)
    clip = m32 @ p
    z = clip[2] / clip[3]
    return z if zero_to_one else np.float32(0.5) * z + np.float32(0.5)


def test_reversed_z_float32_precision_claim():
    """Reversed-Z with [0, 1] depth keeps ~float32 relative precision in distance from near to
    far; the OpenGL [-1, 1] mapping loses it with distance (error ~ eps * distance / near)."""
    n, f = 0.1, 1e5
    distance = np.geomspace(n, 0.99 * f, 20_000)
    conventional = frustum(-n, n, -n, n, n, f)
    reversed_finite = reversed_z(-n, n, -n, n, n, f)
    reversed_infinite = reversed_z(-n, n, -n, n, n)

    # invert the stored depth exactly (float64) to the distance it encodes
    w = _stored_depth_float32(conventional, distance, False).astype(np.float64)
    z_ndc = 2 * w - 1
    d_conv = 2 * n * f / ((f + n) - z_ndc * (f - n))
    z = _stored_depth_float32(reversed_finite, distance, True).astype(np.float64)
    d_rev = n * f / (z * (f - n) + n)
    zi = _stored_depth_float32(reversed_infinite, distance, True).astype(np.float64)
    d_inf = n / zi

    err = {name: np.abs(d / distance - 1) for name, d in
           (("conventional", d_conv), ("reversed", d_rev), ("infinite", d_inf))}
    far = distance > 1e3
    assert err["infinite"].max() < 1e-6  # a few float32 ulps everywhere
    assert err["reversed"].max() < 1e-6
    assert err["conventional"][far].max() > 1e-2  # >10,000x worse at the far end
    # distances 1e-5 apart (relative) stay ordered and distinct with reversed-Z at every range
    d2 = distance * (1 + 1e-5)
    assert (_stored_depth_float32(reversed_infinite, d2, True)
            < _stored_depth_float32(reversed_infinite, distance, True)).all()
    collapsed = (_stored_depth_float32(conventional, d2, False)
                 == _stored_depth_float32(conventional, distance, False))
    assert collapsed[far].mean() > 0.5


def test_reversed_z_planes_are_the_frustums_planes():
    e = (-0.3, 0.5, -0.2, 0.25, 0.1, 50.0)
    np.testing.assert_allclose(frustum_planes(reversed_z(*e), reversed_z=True),
                               frustum_planes(frustum(*e)), atol=1e-12)
    planes = frustum_planes(reversed_z(*e[:5]), reversed_z=True)
    np.testing.assert_array_equal(planes[5], [0, 0, 0, 1])


# ------------------------------------------------------------------------------- view matrices


@FAST
@given(st.lists(st.floats(-50, 50, **finite), min_size=6, max_size=6))
def test_look_at_is_rigid_and_puts_the_target_on_minus_z(v):
    eye, target = np.array(v[:3]), np.array(v[3:])
    dist = np.linalg.norm(target - eye)
    assume(dist > 1e-3)
    assume(np.linalg.norm(np.cross((target - eye) / dist, [0, 1, 0])) > 1e-6)
    m = look_at(eye, target)
    r = m[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
    scale = 1 + abs(eye).max() + dist
    np.testing.assert_allclose(transform_points(m, [eye])[0, :3], 0, atol=1e-12 * scale)
    np.testing.assert_allclose(transform_points(m, [target])[0, :3], [0, 0, -dist],
                               atol=1e-12 * (1 + abs(eye).max() + dist))
    np.testing.assert_allclose(rigid_inverse(m), np.linalg.inv(m), atol=1e-11 * scale)


def test_look_at_refuses_degenerate_input():
    with pytest.raises(ValueError):
        look_at([0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError):
        look_at([0, 0, 0], [0, 5, 0], up=[0, 1, 0])


@FAST
@given(wall_frame())
def test_tile_view_projection_maps_the_tile_rectangle_to_the_ndc_square(wf):
    wall, frame, tile = wf
    view, proj = tile_view_projection(wall, frame, tile)
    x0, x1, y0, y1 = wall.tile_rect(tile)
    z = -wall.distance
    corners_display = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
    corners = frame.to_world(corners_display)
    got = ndc(proj @ view, corners)
    scale = 1 + np.abs(frame.position).max() / min(wall.tile_size)
    np.testing.assert_allclose(got[:, :2], [[-1, -1], [1, -1], [1, 1], [-1, 1]],
                               rtol=0, atol=1e-12 * scale)
    r = view[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-13)
    # any point on the near / far plane, in display space z = eye_z - near / - far
    ex, ey, ez = frame.eye
    on_planes = frame.to_world(np.array([[ex + 0.01, ey - 0.02, ez - wall.near],
                                         [ex + 3.0, ey + 1.0, ez - wall.far]]))
    depth = ndc(proj @ view, on_planes)[:, 2]
    np.testing.assert_allclose(depth, [-1.0, 1.0], atol=1e-9 * scale)


@FAST
@given(wall_frame())
def test_frustum_planes_round_trip_to_the_culler_tile_planes(wf):
    """Lengyel Table 5.2 on projection @ view gives the culler's planes (L, R, T, B, near, far
    in wall.py; left, right, bottom, top, near, far here)."""
    wall, frame, tile = wf
    view, proj = tile_view_projection(wall, frame, tile)
    mine = frustum_planes(proj @ view)
    culler = Frusta.build(wall, frame).planes[wall.layout.tile_planes[tile]][[0, 1, 3, 2, 4, 5]]
    np.testing.assert_allclose(np.linalg.norm(mine[:, :3], axis=1), 1.0, atol=1e-12)
    scale = 1 + np.abs(frame.position).max()
    np.testing.assert_allclose(mine[:, :3], culler[:, :3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(mine[:, 3], culler[:, 3], rtol=1e-9, atol=1e-9 * scale)


@FAST
@given(wall_frame())
def test_infinite_far_plane_is_the_plane_at_infinity(wf):
    wall, frame, tile = wf
    view, proj = tile_view_projection(wall, frame, tile)
    inf = proj.copy()
    inf[2, 2], inf[2, 3] = -1.0, -2.0 * wall.near
    planes = frustum_planes(inf @ view)
    np.testing.assert_array_equal(planes[5], [0, 0, 0, 1])
    np.testing.assert_allclose(planes[:5], frustum_planes(proj @ view)[:5], atol=1e-9,
                               rtol=1e-9)


def test_infinite_far_plane_with_epsilon_lies_behind_the_eye():
    n, eps = 0.1, 2.4e-7
    planes = frustum_planes(infinite_frustum(-n, n, -n, n, n, epsilon=eps))
    far = planes[5]
    np.testing.assert_allclose(far[:3], [0, 0, -1], atol=1e-12)
    assert -far[3] / far[2] == pytest.approx((2 - eps) * n / eps, rel=1e-6)  # z of the plane
    in_front = np.array([[0, 0, -1e9, 1.0], [1e3, -1e3, -0.2, 1.0]])
    assert (in_front @ far > 0).all()


def test_frustum_planes_refuses_a_degenerate_matrix():
    with pytest.raises(ValueError):
        frustum_planes(np.zeros((4, 4)))
    m = frustum(-1, 1, -1, 1, 1, 10)
    m[0] = -m[3]  # left = M4 + M1 = 0
    with pytest.raises(ValueError):
        frustum_planes(m)


# ---------------------------------------------------------------------------- oblique near


def lengyel_listing_5_1(m, c):
    """A direct port of Listing 5.1 (column-major indices as in the book)."""
    matrix = m.T.reshape(16).copy()  # column-major
    sgn = lambda x: float(np.sign(x))  # noqa: E731
    q = np.array([(sgn(c[0]) + matrix[8]) / matrix[0], (sgn(c[1]) + matrix[9]) / matrix[5],
                  -1.0, (1.0 + matrix[10]) / matrix[14]])
    cc = c * (2.0 / (c @ q))
    matrix[2], matrix[6], matrix[10], matrix[14] = cc[0], cc[1], cc[2] + 1.0, cc[3]
    return matrix.reshape(4, 4).T


@st.composite
def oblique_cases(draw):
    e = draw(extents())
    infinite = draw(st.booleans())
    m = infinite_frustum(*e[:5]) if infinite else frustum(*e)
    l, r, b, t, n, f = e
    # a plane through a point inside the frustum, camera on its negative side
    deepest = 0.8 * f / n if not infinite else 50.0
    assume(deepest > 1.25)  # room for a point past the near plane
    s = draw(st.floats(1.2, deepest))
    u, v = draw(st.floats(0.05, 0.95)), draw(st.floats(0.05, 0.95))
    point = np.array([(l + u * (r - l)) * s, (b + v * (t - b)) * s, -n * s])
    normal = np.array([draw(st.floats(-1, 1)), draw(st.floats(-1, 1)), -1.0])
    normal /= np.linalg.norm(normal)
    c = np.append(normal, -normal @ point)
    assume(c[3] < -1e-3 * n)
    return m, c, e, infinite


@settings(max_examples=100, deadline=None)
@given(oblique_cases(), st.integers(0, 2**31 - 1))
def test_oblique_near_plane(case, seed):
    m, c, (l, r, b, t, n, f), infinite = case
    out = oblique_near(m, c)
    np.testing.assert_array_equal(out[[0, 1, 3]], m[[0, 1, 3]])  # rows 1, 2, 4 untouched
    rng = np.random.default_rng(seed)
    # points on the clip plane map to depth -1
    basis = np.linalg.svd(c[None, :3])[2][1:]
    on = -c[3] * c[:3] / (c[:3] @ c[:3]) + rng.normal(size=(20, 2)) @ basis * n
    on = on[on[:, 2] < -1e-3 * n]
    if len(on):
        np.testing.assert_allclose(ndc(out, on)[:, 2], -1.0, atol=1e-7)
    # sample the original frustum: NDC cube -> eye space
    far_ndc = 1.0 - 1e-9 if not infinite else 1.0 - 1e-3
    cube = np.c_[rng.uniform(-1, 1, (400, 2)), rng.uniform(-1, far_ndc, 400), np.ones(400)]
    eye = cube @ np.linalg.inv(m).T
    eye = eye[:, :3] / eye[:, 3:]
    side = eye @ c[:3] + c[3]
    new = ndc(out, eye)
    np.testing.assert_allclose(new[:, :2], ndc(m, eye)[:, :2], atol=1e-9)
    kept = side > 1e-9 * np.linalg.norm(eye, axis=1)
    assert (new[kept, 2] >= -1 - 1e-9).all()
    assert (new[kept, 2] <= 1 + 1e-7).all()  # never clipped where the plane does not clip
    cut = side < -1e-9 * np.linalg.norm(eye, axis=1)
    assert (new[cut, 2] < -1).all()  # the far side of the clip plane is clipped
    # the new far plane contains the corner Q of eq. (5.64)
    c_clip = np.linalg.solve(m.T, c)
    q = np.linalg.solve(m, [np.sign(c_clip[0]), np.sign(c_clip[1]), 1, 1])
    far_plane = out[3] - out[2]
    assert abs(far_plane @ q) <= 1e-9 * np.abs(far_plane).max() * np.abs(q).max()


@FAST
@given(extents(), st.booleans(), st.floats(-1, 1), st.floats(-1, 1), st.floats(0.2, 5.0))
def test_oblique_near_matches_listing_5_1(e, infinite, cx, cy, dist):
    """Off-axis and infinite too: for any glFrustum-form matrix C'x = Cx / m00, so Lengyel's
    shortcut sgn(C') = sgn(C) is exact and the listing is the oracle."""
    m = infinite_frustum(*e[:5]) if infinite else frustum(*e)
    c = np.array([cx, cy, -1.0, 0.0])
    c /= np.linalg.norm(c[:3])
    c[3] = -dist * e[4]
    cq = _listing_cq(m, c)
    assume(abs(cq) > 1e-6)  # the plane (nearly) through the far corner: u = 2 / C.Q blows up
    expected = lengyel_listing_5_1(m, c)
    if cq < 0:
        with pytest.raises(ClipPlaneError):
            oblique_near(m, c)
        return
    np.testing.assert_allclose(oblique_near(m, c), expected, rtol=1e-10, atol=1e-12)


def _listing_cq(m, c):
    """C . Q of Listing 5.1, relative to |C| |Q|."""
    q = np.array([(np.sign(c[0]) + m[0, 2]) / m[0, 0], (np.sign(c[1]) + m[1, 2]) / m[1, 1],
                  -1.0, (1.0 + m[2, 2]) / m[2, 3]])
    return c @ q / np.linalg.norm(c) / np.linalg.norm(q)


@pytest.mark.parametrize("distance, reason", [
    (0.0, "through_camera"), (-1e-9, "through_camera"), (1e-9, "through_camera"),
    (0.5, "camera_visible")])
def test_oblique_near_refuses_planes_through_or_behind_the_camera(distance, reason):
    m = frustum(-0.1, 0.1, -0.1, 0.1, 0.1, 100.0)
    c = np.array([0.0, 0.6, -0.8, distance])  # unit normal: C_w is the camera's distance
    with pytest.raises(ClipPlaneError) as err:
        oblique_near(m, c)
    assert err.value.reason == reason


def test_oblique_near_refuses_a_plane_that_clips_everything():
    m = frustum(-0.1, 0.1, -0.1, 0.1, 0.1, 100.0)
    with pytest.raises(ClipPlaneError) as err:
        oblique_near(m, [0.0, 0.0, 1.0, -1.0])  # keeps only z >= 1, behind the camera
    assert err.value.reason == "clips_everything"


def test_oblique_near_tolerance_is_relative_to_near():
    m = frustum(-1e-4, 1e-4, -1e-4, 1e-4, 1e-4, 1.0)  # a tiny scene: near = 1e-4
    out = oblique_near(m, [0.0, 0.0, -1.0, -1e-9])  # 1e-5 x near: accepted
    assert np.isfinite(out).all()
    with pytest.raises(ClipPlaneError):
        oblique_near(m, [0.0, 0.0, -1.0, -1e-11])


def test_mirrored_views_is_the_reflected_view_and_the_oblique_projection():
    """The compiled mirror matrices against the same made in numpy, with a general inverse:
    random cameras (each its own view, or one view for all) and a random mirror, some seen
    from behind or edge-on (refused there, as :func:`oblique_near_many` refuses)."""
    rng = np.random.default_rng(7)
    seen = set()
    for trial in range(20):
        k = 12
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        plane = np.append(normal, rng.uniform(-2, 2))
        reflection = np.eye(4)
        reflection[:3, :3] -= 2 * np.outer(normal, normal)
        reflection[:3, 3] = -2 * plane[3] * normal
        eyes = rng.uniform(-4, 4, size=(k, 3))
        views = np.array([look_at(e, e + rng.normal(size=3)) for e in eyes])
        if trial % 2:
            views = views[0]  # one view shared by every tile, as a grid's
        projections = np.array([frustum(-a, b, -c, d, rng.uniform(0.05, 0.5), 100.0)
                                for a, b, c, d in rng.uniform(0.1, 1.0, size=(k, 4))])
        view, oblique, reason = mirrored_views(views, projections, reflection, plane)
        assert view.shape == views.shape
        np.testing.assert_allclose(view, views @ reflection, rtol=0, atol=1e-12)
        clip = np.swapaxes(np.linalg.inv(views), -1, -2) @ (-plane)
        expected, why = oblique_near_many(projections, clip)
        assert (reason == why).all()
        seen |= set(reason.tolist())
        scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
        assert (np.abs(oblique - expected) <= 1e-9 * scale).all()
    assert 0 in seen and len(seen) > 1  # matrices made, and refused
    for wrong in (1.0, np.nan):
        bad = projections.copy()
        bad[3, 3, 3] = wrong
        with pytest.raises(ValueError, match="row 4"):
            mirrored_views(views, bad, reflection, plane)
