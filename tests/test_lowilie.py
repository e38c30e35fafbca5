"""The Low-Ilie frustum: round trips (corners to the viewport corners, every point inside the
NDC cube), a rigid view, coverage against the symmetric frustum, and the degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from wallcull.lowilie import (
    MAX_HALF_ANGLE_DEG, NEAR_FRACTION, FitError, fit_frustum, float32_error)
from wallcull.projection import transform_points
from wallcull.quad import quad_area

CORNERS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])


def project(fit, points, eye):
    """NDC ``(m, 3)`` and clip w of world points, computed eye-relative (the test must not lose
    the digits the fit keeps when the scene is far from the origin)."""
    e = (np.atleast_2d(points) - eye) @ fit.view[:3, :3].T
    clip = e @ fit.projection[:, :3].T + fit.projection[:, 3]
    return clip[:, :3] / clip[:, 3:], clip[:, 3]


def check_fit(fit, points, eye, tol=1e-9):
    """The properties every fit must have."""
    r = fit.view[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), rtol=0, atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(fit.view[3], [0, 0, 0, 1])
    np.testing.assert_allclose(fit.view[:3, 3], -r @ eye, rtol=0, atol=1e-15 * (1 + abs(eye).max()))
    p = fit.projection
    assert p[0, 0] > 0 and p[1, 1] > 0 and p[1, 0] == 0 and p[2, :2].tolist() == [0, 0]
    np.testing.assert_array_equal(p[3], [0, 0, -1, 0])
    assert 0 < fit.near < fit.far
    # the four corner rays land on the viewport corners, in CCW order
    np.testing.assert_array_equal(fit.eye, eye)
    got, w = project(fit, fit.corner_rays, 0.0)
    assert (w > 0).all()
    np.testing.assert_allclose(got[:, :2], fit.corner_ndc, rtol=0, atol=tol)
    assert {tuple(c) for c in fit.corner_ndc} == {tuple(c) for c in CORNERS}
    assert quad_area(fit.corner_ndc) == 4.0
    # every point inside the NDC cube, in front of the eye
    ndc, w = project(fit, points, eye)
    assert (w > 0).all()
    assert np.abs(ndc).max() <= 1 + tol
    assert 0.0 <= fit.coverage <= 1 + tol


def sample_rays_to_world(fit, eye):
    """Independent round trip: unproject the quad (sample NDC) through the sample matrices."""
    inv = np.linalg.inv(fit.sample_projection @ fit.sample_view)
    clip = np.c_[fit.quad, np.zeros(4), np.ones(4)] @ inv.T
    return clip[:, :3] / clip[:, 3:]


# --------------------------------------------------------------------------------- objects


def box(size, rotation, center, n=8, rng=None):
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    pts = corners if rng is None else rng.uniform(-1, 1, (n, 3))
    return (pts * size) @ rotation.T + center


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


@st.composite
def scenes(draw):
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    kind = draw(st.sampled_from(["box", "cloud", "slab", "ring"]))
    size = rng.uniform(0.1, 3.0, 3)
    rot = random_rotation(rng)
    if kind == "box":
        pts = box(size, rot, 0)
    elif kind == "cloud":
        pts = rng.normal(size=(int(rng.integers(5, 300)), 3)) * size @ rot.T
    elif kind == "slab":  # a wall-like object (paper Fig. 1)
        pts = box(size * [1, 1, 0.02], rot, 0, n=200, rng=rng)
    else:
        t = rng.uniform(0, 2 * np.pi, int(rng.integers(5, 500)))
        pts = np.c_[np.cos(t), np.sin(t), 0 * t] * size @ rot.T
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    distance = np.linalg.norm(pts, axis=1).max() * rng.uniform(1.2, 30.0)
    eye = direction * distance + rng.normal(size=3) * 0.1
    origin = rng.uniform(-100, 100, 3)
    width, height = draw(st.sampled_from([(1920, 1080), (1080, 1920), (1024, 1024), (800, 600)]))
    return eye + origin, pts + origin, width, height, kind


# ------------------------------------------------------------------------------- properties


@settings(max_examples=60, deadline=None)
@given(scenes(), st.booleans())
def test_fit_round_trips(scene, refine):
    eye, pts, width, height, _ = scene
    fit = fit_frustum(eye, pts, width, height, refine=refine)
    check_fit(fit, pts, eye)
    # the quad's corner rays, recovered through the sample matrices, land on the corners too
    rays = sample_rays_to_world(fit, eye)
    np.testing.assert_allclose(project(fit, rays, eye)[0][:, :2], fit.corner_ndc, atol=1e-9)
    # the longest quad edge went to a long side of the viewport
    quad_px = fit.quad * [width, height]
    edges = np.roll(quad_px, -1, axis=0) - quad_px
    i = int(np.argmax(np.linalg.norm(edges, axis=1)))
    side = fit.corner_ndc[(i + 1) % 4] - fit.corner_ndc[i]
    assert (side[1] == 0) == (width >= height)
    assert side @ edges[i] >= 0  # of the two ways to do that, the one that turns it less
    # points of the sample image
    ndc_s = transform_points(fit.sample_projection @ fit.sample_view, pts)
    assert np.abs(ndc_s[:, :3] / ndc_s[:, 3:]).max() <= 1 + 1e-9


def test_coverage_beats_the_symmetric_frustum_on_typical_objects():
    rng = np.random.default_rng(5)
    rows = []
    for kind in ("box", "slab", "cloud", "ring"):
        for _ in range(10):
            size = rng.uniform(0.2, 3.0, 3)
            rot = random_rotation(rng)
            if kind == "box":
                pts = box(size, rot, 0)
            elif kind == "slab":
                pts = box(size * [1, 1, 0.05], rot, 0, n=300, rng=rng)
            elif kind == "cloud":
                pts = rng.normal(size=(300, 3)) * size @ rot.T
            else:
                t = rng.uniform(0, 2 * np.pi, 300)
                pts = np.c_[np.cos(t), np.sin(t), 0 * t] * size @ rot.T
            d = rng.normal(size=3)
            eye = d / np.linalg.norm(d) * np.linalg.norm(pts, axis=1).max() * rng.uniform(1.5, 8)
            fit = fit_frustum(eye, pts, 1920, 1080)
            check_fit(fit, pts, eye)
            rows.append((kind, fit.sample_coverage, fit.coverage))
    print("\ncoverage: kind, symmetric (median), fitted (median), fitted / symmetric (min)")
    for kind in ("box", "slab", "cloud", "ring"):
        s = np.array([r[1] for r in rows if r[0] == kind])
        f = np.array([r[2] for r in rows if r[0] == kind])
        print(f"  {kind:6s} {np.median(s):.3f} {np.median(f):.3f} {np.min(f / s):.2f}")
        assert (f >= s).all()


def test_the_view_is_rigid_where_the_papers_decomposition_is_not():
    """The composite 3x3 camera of a fit has skew: the paper's eq. (14) applied to it returns
    first and second rows that are not orthogonal, while the fit's view is orthonormal."""
    rng = np.random.default_rng(2)
    skews = []
    for _ in range(20):
        pts = box(rng.uniform(0.2, 2.0, 3), random_rotation(rng), 0)
        eye = rng.normal(size=3) * 6
        fit = fit_frustum(eye, pts, 1920, 1080)
        k = fit.projection[[0, 1, 3]][:, :3]  # rows x, y, w of the clip coordinates
        q = k @ fit.view[:3, :3]  # the 3x3 camera: world direction -> homogeneous NDC
        q = q / np.linalg.norm(q[2])  # eq. (12)
        cx, cy = q[0] @ q[2], q[1] @ q[2]  # eq. (14)
        r1 = q[0] - cx * q[2]
        r2 = q[1] - cy * q[2]
        skews.append(abs(r1 @ r2) / np.linalg.norm(r1) / np.linalg.norm(r2))
        check_fit(fit, pts, eye)
    assert max(skews) > 1e-3  # the paper's "rotation" would be visibly non-orthonormal


# ------------------------------------------------------------------------- degenerate inputs


def test_single_point_and_coincident_points():
    eye = np.array([0.5, -1.0, 2.0])
    for pts in ([[1.0, 2.0, -5.0]], [[1.0, 2.0, -5.0]] * 5):
        pts = np.array(pts)
        fit = fit_frustum(eye, pts, 1920, 1080)
        assert fit.degenerate == "point"
        check_fit(fit, pts, eye)
        np.testing.assert_allclose(fit.view, fit.sample_view, atol=1e-12)
        ndc, _ = project(fit, pts, eye)
        np.testing.assert_allclose(ndc[:, :2], 0, atol=1e-9)  # centred
        assert fit.coverage == 0.0


def test_points_on_one_ray_from_the_eye():
    """Distinct points whose image is one point: the sample frustum, which holds them all."""
    eye = np.array([1.0, 1.0, 1.0])
    pts = eye + np.outer([1.0, 2.5, 5.0], [0.2, -0.3, -1.0])
    fit = fit_frustum(eye, pts, 1920, 1080)
    assert fit.degenerate == "point"
    check_fit(fit, pts, eye)
    depths = -(pts - eye) @ fit.view[2, :3]
    assert fit.near <= depths.min() and fit.far >= depths.max()


@pytest.mark.parametrize("aspect", [(1920, 1080), (1080, 1920)])
def test_collinear_points_fill_the_long_centre_line(aspect):
    eye = np.array([0.0, 0.0, 0.0])
    pts = np.linspace([1.0, -1.0, -4.0], [3.0, 2.0, -6.0], 17)
    fit = fit_frustum(eye, pts, *aspect)
    assert fit.degenerate == "segment"
    check_fit(fit, pts, eye)
    ndc, _ = project(fit, pts, eye)
    long_axis = 0 if aspect[0] >= aspect[1] else 1
    np.testing.assert_allclose(ndc[:, 1 - long_axis], 0.0, atol=1e-9)
    assert np.ptp(ndc[:, long_axis]) == pytest.approx(2.0, rel=1e-5)


def test_coplanar_points_seen_edge_on():
    """A square plate in a plane through the eye: its image is a segment."""
    rng = np.random.default_rng(4)
    eye = np.array([0.0, 1.0, 0.0])
    pts = np.c_[rng.uniform(-1, 1, 50), np.ones(50), rng.uniform(-6, -3, 50)]  # plane y = 1
    fit = fit_frustum(eye, pts, 1280, 720)
    assert fit.degenerate == "segment"
    check_fit(fit, pts, eye)


def test_three_points_give_half_the_viewport():
    """A triangle's image: the paper's parallelogram maps (affinely) onto the viewport, so the
    triangle covers exactly half of it."""
    eye = np.array([0.0, 0.0, 0.0])
    pts = np.array([[-1.0, -0.5, -5.0], [2.0, 0.0, -6.0], [0.0, 1.5, -4.0]])
    fit = fit_frustum(eye, pts, 1920, 1080)
    check_fit(fit, pts, eye)
    assert fit.degenerate is None and not fit.refined
    assert fit.coverage == pytest.approx(0.5, abs=1e-9)
    ndc, _ = project(fit, pts, eye)
    on_corner = [np.abs(np.abs(v[:2]) - 1).max() < 1e-9 for v in ndc]
    assert all(on_corner)  # three of the parallelogram's corners are the triangle's


def test_four_points_fill_the_viewport():
    eye = np.array([0.2, 0.1, 3.0])
    pts = np.array([[-1.0, -0.7, 0.0], [1.3, -0.5, -0.4], [0.9, 0.8, 0.2], [-1.1, 0.6, -0.3]])
    fit = fit_frustum(eye, pts, 1920, 1080)
    check_fit(fit, pts, eye)
    assert fit.coverage == pytest.approx(1.0, abs=1e-9)
    ndc, _ = project(fit, pts, eye)
    np.testing.assert_allclose(np.abs(ndc[:, :2]), 1.0, atol=1e-9)


def test_distant_scene_keeps_its_digits_and_float32_does_not():
    """Eye and points 1e7 from the origin (exactly representable offsets): the fit equals the
    one at the origin, rotated views and projections alike; the float32 matrices lose the
    correspondences (translation 1e7 in float32), the reason to render camera-relative."""
    rng = np.random.default_rng(9)
    pts = np.round(box(rng.uniform(0.5, 2, 3), random_rotation(rng), 0, n=100, rng=rng) * 64) / 64
    eye = np.array([0.25, 0.5, 8.0])
    near_origin = fit_frustum(eye, pts, 1920, 1080)
    offset = np.array([1e7, -3e7, 2e7])
    far_away = fit_frustum(eye + offset, pts + offset, 1920, 1080)
    check_fit(far_away, pts + offset, eye + offset)
    np.testing.assert_allclose(far_away.projection, near_origin.projection, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(far_away.view[:3, :3], near_origin.view[:3, :3], atol=1e-14)
    err_near, err_far = float32_error(near_origin), float32_error(far_away)
    print(f"\nfloat32 NDC error on the corners: origin {err_near:.2e}, 1e7 away {err_far:.2e}")
    assert err_near < 1e-5
    assert err_far > 1e-3


def test_object_far_from_the_eye():
    rng = np.random.default_rng(12)
    pts = box(np.array([2.0, 1.0, 0.5]), random_rotation(rng), 0, n=200, rng=rng)
    for distance in (1e3, 1e5, 1e7):
        eye = np.array([0.3, 0.2, distance])
        fit = fit_frustum(eye, pts, 1920, 1080)
        check_fit(fit, pts, eye)
        assert fit.coverage >= fit.sample_coverage


def test_eye_inside_the_bounding_sphere_uses_a_cone():
    """A light inside the bounding sphere of what it lights (a bowl seen from its inside)."""
    rng = np.random.default_rng(1)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    bowl = u[u[:, 2] < -0.5] * rng.uniform(1.0, 3.0, (int((u[:, 2] < -0.5).sum()), 1))
    eye = np.zeros(3)
    centre = 0.5 * (bowl.min(axis=0) + bowl.max(axis=0))
    assert np.linalg.norm(bowl - centre, axis=1).max() > np.linalg.norm(centre)  # eye inside
    fit = fit_frustum(eye, bowl, 1024, 1024)
    assert fit.sample == "cone"
    check_fit(fit, bowl, eye)
    depths = -(bowl - eye) @ fit.view[2, :3]
    assert fit.near == pytest.approx(NEAR_FRACTION * depths.min(), rel=1e-12)  # the clamp


def test_points_surrounding_the_eye_are_refused():
    rng = np.random.default_rng(1)
    u = rng.normal(size=(200, 3))
    with pytest.raises(FitError, match="surround"):
        fit_frustum([0, 0, 0], u, 640, 480)
    # a cone just too wide for MAX_HALF_ANGLE_DEG around -z
    a = np.radians(MAX_HALF_ANGLE_DEG + 2)
    t = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    rim = np.c_[np.sin(a) * np.cos(t), np.sin(a) * np.sin(t), -np.cos(a) * np.ones_like(t)]
    with pytest.raises(FitError):
        fit_frustum([0, 0, 0], np.r_[rim, rim * 2], 640, 480)
    with pytest.raises(FitError, match="coincides"):
        fit_frustum([0, 0, 0], [[0, 0, 0], [1, 0, -3], [0, 1, -3], [-1, 0, -3]], 640, 480)


def test_near_clamp_and_given_depth_range():
    eye = np.array([0.0, 0.0, 0.0])
    pts = box(np.array([1.0, 1.0, 1.0]), np.eye(3), np.array([0.0, 0.0, -1.9]))  # eye 0.9 out
    fit = fit_frustum(eye, pts, 800, 600)
    check_fit(fit, pts, eye)
    depths = -pts @ fit.view[2, :3]
    centre = -np.array([0.0, 0.0, -1.9]) @ fit.view[2, :3]
    radius = np.sqrt(3) * (1 + 1e-6)
    expected = max(centre - radius, NEAR_FRACTION * depths.min())
    assert fit.near == pytest.approx(expected, rel=1e-9)
    assert 0 < fit.near <= depths.min()
    given_fit = fit_frustum(eye, pts, 800, 600, near=0.05, far=50.0)
    assert (given_fit.near, given_fit.far) == (0.05, 50.0)
    with pytest.raises(ValueError):
        fit_frustum(eye, pts, 800, 600, near=2.0, far=1.0)


def test_refine_keeps_the_better_coverage():
    rng = np.random.default_rng(21)
    for _ in range(20):
        pts = rng.normal(size=(300, 3)) * rng.uniform(0.2, 2, 3) @ random_rotation(rng).T
        eye = rng.normal(size=3)
        eye *= 8 / np.linalg.norm(eye)
        a = fit_frustum(eye, pts, 1920, 1080, refine=False)
        b = fit_frustum(eye, pts, 1920, 1080, refine=True)
        assert b.coverage >= a.coverage - 1e-12
        assert quad_area(b.quad) <= quad_area(a.quad) * (1 + 1e-12)


def test_float32_error_is_small_for_ordinary_scenes():
    rng = np.random.default_rng(8)
    pts = rng.normal(size=(100, 3)) + [0, 0, -6]
    fit = fit_frustum([0.1, 0.2, 0.3], pts, 1920, 1080)
    assert float32_error(fit) < 1e-5


def test_bad_input():
    with pytest.raises(ValueError):
        fit_frustum([0, 0, 0], np.zeros((0, 3)), 10, 10)
    with pytest.raises(ValueError):
        fit_frustum([0, 0, 0], [[0, 0, np.nan]], 10, 10)
    with pytest.raises(ValueError):
        fit_frustum([0, 0, 0], [[0, 0, -1]], 0, 10)


# ------------------------------------------------------------------- many fits at once


@st.composite
def box_sets(draw):
    """Random oriented boxes (some flat, some points) around a centre, and a light outside
    or inside their spread."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 60))
    center = rng.normal(size=(n, 3)) * rng.uniform(0.5, 5.0)
    axes = np.stack([random_rotation(rng) for _ in range(n)])
    half = rng.uniform(0, 1, (n, 3)) * (rng.random((n, 3)) > 0.1)  # some flat, some points
    radius = rng.uniform(0, 0.2, n) * (rng.random(n) > 0.5)
    light = rng.normal(size=3)
    light *= rng.uniform(0.0 if draw(st.booleans()) else 8.0, 30.0) / np.linalg.norm(light)
    offset = rng.uniform(-1e3, 1e3, 3)
    return center + offset, axes, half, radius, light + offset


def check_holds(view, projection, corners, light):
    """A rigid view, and every corner in front of the light and inside the frustum's sides."""
    r = view[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    ndc = ((corners - light) @ r.T) @ projection[:3, :3].T + projection[:3, 3]
    w = -((corners - light) @ r.T)[:, 2]
    assert (w > 0).all()
    assert np.abs(ndc[:, :2] / w[:, None]).max() <= 1 + 1e-9


@settings(max_examples=60, deadline=None)
@given(box_sets(), st.sampled_from(["sphere", "greedy", "refined"]))
def test_fits_of_boxes_are_the_fits_of_their_corners(boxes, effort):
    """fit_boxes works per box (support functions, a filter of boxes whose image lies inside
    the hull); the result is the fit of all the corners, or, where the light is inside the
    boxes' sphere (a cone sample, whose axis it takes from the boxes' centres), a fit with the
    same guarantees."""
    from wallcull.bounds import Bounds
    from wallcull.lowilie import OK, SURROUNDS, fit_boxes

    center, axes, half, radius, light = boxes
    bounds = Bounds("obb", center, axes, half, radius)
    n = len(center)
    start = np.array([0, n, n, n // 2 + n])  # all, none, the first half again
    nodes = np.concatenate([np.arange(n), np.arange(n // 2)])
    out = fit_boxes(light, bounds, start, nodes, 1920, 1080, effort)
    assert out["status"][1] == 1  # EMPTY
    for q, chosen in ((0, np.arange(n)), (2, np.arange(n // 2))):
        if not len(chosen):
            continue
        corners = bounds.take(chosen).world_corners().reshape(-1, 3)
        try:
            ref = fit_frustum(light, corners, 1920, 1080, effort=effort)
        except FitError as exc:
            if out["status"][q] == OK:
                # the same cone sampling the other way round: the boxes' axis (their
                # centres) holds them in a cone where the corners' own axis does not; the
                # frustum found must still hold every corner
                assert "surround" in str(exc)
                check_holds(out["view"][q], out["projection"][q], corners, light)
            continue
        if out["status"][q] == SURROUNDS:
            # inside the boxes' sphere each fit samples a cone around its own axis (the
            # corners' fit from its points, fit_boxes from the boxes' centres, rounded boxes
            # grown by their radius): where one finds it within MAX_HALF_ANGLE and the other
            # not, that light gets a cube map instead, as conservative
            assert ref.sample == "cone", ref.sample
            continue
        assert out["status"][q] == OK
        view, projection = out["view"][q], out["projection"][q]
        check_holds(view, projection, corners, light)
        if ref.sample == "sphere":  # the same fit, up to the rounding of the corners
            scale = 1.0 + np.abs(light).max()  # the corners are eye-relative in one, not both
            np.testing.assert_allclose(view[:3, :3], ref.view[:3, :3], rtol=0, atol=1e-9)
            np.testing.assert_allclose(view[:3, 3], ref.view[:3, 3], rtol=0, atol=1e-9 * scale)
            # each row's rounding is relative to its largest entry (a skew of 1e-9 beside a
            # focal length of 243 is a rounding of 5e-12)
            row = np.abs(ref.projection).max(axis=1, keepdims=True)
            np.testing.assert_array_less(np.abs(projection - ref.projection),
                                         1e-9 * np.abs(ref.projection) + 1e-9 + 1e-11 * row)
            assert out["coverage"][q] == pytest.approx(ref.coverage, abs=1e-12)


@pytest.mark.parametrize("offset", [0.0, 1e4])
def test_a_box_centred_on_the_light_beside_others_surrounds_it(offset):
    """A light at the exact centre of a receiver's box (a bulb in its lamp housing, a ball
    around it, a light on a flat sheet at the sheet's centre), with another receiver beside
    it: its corners lie all around the light, so no frustum holds them and the set gets a
    cube map (``SURROUNDS``). The cone sample divided by the box's distance from the light,
    zero: ZeroDivisionError in every frame. A point at the light coincides with it."""
    from wallcull.bounds import Bounds
    from wallcull.lowilie import COINCIDES, SURROUNDS, fit_boxes

    light = np.array([0.0, 0.5, -5.0]) + offset
    rows = [(light, [0.5, 0.5, 0.5], 0.0),  # the lamp housing
            (light, [0.0, 0.0, 0.0], 0.2),  # a ball around the bulb
            (light, [1.0, 1.5, 0.0], 0.0),  # a flat sheet, the light on it
            (light, [0.0, 0.0, 0.0], 0.0),  # a point at the light
            (light + [0.0, -1.5, -1.0], [4.0, 0.05, 4.0], 0.0)]  # the floor
    bounds = Bounds("obb", np.array([c for c, _, _ in rows], float),
                    np.tile(np.eye(3), (len(rows), 1, 1)), np.array([h for _, h, _ in rows]),
                    np.array([r for _, _, r in rows]))
    start = np.array([0, 2, 4, 6, 8])
    nodes = np.array([0, 4, 1, 4, 2, 4, 3, 4])
    for effort in ("sphere", "greedy", "refined"):
        out = fit_boxes(light, bounds, start, nodes, 1024, 1024, effort)
        assert out["status"].tolist() == [SURROUNDS, SURROUNDS, SURROUNDS, COINCIDES]


def test_fit_boxes_splits_among_threads_without_changing_a_bit(monkeypatch):
    from wallcull.bounds import Bounds
    from wallcull.lowilie import fit_boxes

    rng = np.random.default_rng(3)
    n = 400
    bounds = Bounds("obb", rng.normal(size=(n, 3)) * 10, np.tile(np.eye(3), (n, 1, 1)),
                    rng.uniform(0, 1, (n, 3)), np.zeros(n))
    start = np.sort(np.r_[0, rng.integers(0, n, 63), n])
    light = np.array([0.0, 60.0, 0.0])
    results = []
    for threads in ("1", "2", "5"):
        monkeypatch.setenv("WALLCULL_THREADS", threads)
        results.append(fit_boxes(light, bounds, start, np.arange(n), 2048, 2048))
    for other in results[1:]:
        for key in results[0]:
            np.testing.assert_array_equal(results[0][key], other[key])


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0, 12))
def test_rq_round_trip(seed, decades):
    """``_rq`` (written out: numba's ``np.linalg`` needs SciPy) splits ``k @ r`` back into an
    upper triangular ``k`` and orthonormal rows, however ill-conditioned ``k`` is."""
    from wallcull.lowilie import _rq

    rng = np.random.default_rng(seed)
    k = np.triu(rng.normal(size=(3, 3)))
    k[np.diag_indices(3)] = np.abs(k.diagonal()) * 10.0 ** (-decades * np.arange(3) / 2) + 1e-300
    r = random_rotation(rng) * rng.choice([-1.0, 1.0], size=(3, 1))
    p = k @ r
    k2, r2 = _rq(p)
    np.testing.assert_allclose(r2 @ r2.T, np.eye(3), atol=4e-16 * 8)
    assert np.all(np.tril(k2, -1) == 0)
    np.testing.assert_allclose(k2 @ r2, p, rtol=0, atol=1e-14 * np.abs(p).max())
