"""The OpenGL tile renderer against analytic projections (real Mesa/EGL rendering, no mocks)."""

import numpy as np
import pytest

from wallcull_clients import render

try:
    render.reversed_z_available()  # creates the shared EGL context
except Exception as exc:  # no EGL / no GPU driver on this machine: nothing here can run
    pytest.skip(f"no headless OpenGL (EGL) context: {exc}", allow_module_level=True)

from wallcull_clients.render import Image, TileRenderer

W, H = 96, 64


def perspective(fovy, aspect, near, far):
    """The textbook symmetric gluPerspective matrix (clip depth in [-1, 1])."""
    f = 1.0 / np.tan(fovy / 2)
    return np.array([[f / aspect, 0, 0, 0],
                     [0, f, 0, 0],
                     [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
                     [0, 0, -1, 0]])


def reversed_perspective(fovy, aspect, near, far):
    """Symmetric perspective with clip depth 1 at the near plane and 0 at the far plane."""
    m = perspective(fovy, aspect, near, far)
    m[2, 2], m[2, 3] = near / (far - near), far * near / (far - near)
    return m


def translation(x, y, z):
    m = np.eye(4)
    m[:3, 3] = x, y, z
    return m


def rotation(axis, angle):
    (x, y, z), c, s = np.asarray(axis) / np.linalg.norm(axis), np.cos(angle), np.sin(angle)
    m = np.eye(4)
    m[:3, :3] = [[c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
                 [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
                 [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)]]
    return m


def cube():
    """Unit cube centred on the origin, outward faces counter-clockwise."""
    v = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)])
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return v, np.array(f)


def quad(size=1.0):
    """Square of side ``size`` in the z = 0 plane, facing +z."""
    s = size / 2
    return np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]]), np.array([[0, 1, 2], [0, 2, 3]])


def to_pixels(points, mvp, w=W, h=H):
    """Project (n, 3) points to (n, 2) image coordinates: x right, y DOWN, pixel centres at +.5."""
    p = np.c_[points, np.ones(len(points))] @ mvp.T
    ndc = p[:, :3] / p[:, 3:]
    return np.c_[(ndc[:, 0] + 1) / 2 * w, (1 - ndc[:, 1]) / 2 * h]


def pixel_centres(w=W, h=H):
    """(h, w, 2) image coordinates of the pixel centres, row 0 at the top."""
    x, y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    return np.stack([x, y], axis=-1)


def cross2(a, b):
    """z of the cross product of 2-vectors (broadcasting over leading axes)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def convex_hull(points):
    """Andrew's monotone chain; (k, 2) vertices, counter-clockwise in y-down image coordinates."""
    pts = sorted(map(tuple, points))

    def half(seq):
        out = []
        for p in seq:
            while len(out) >= 2 and cross2(np.subtract(out[-1], out[-2]), np.subtract(p, out[-2])) <= 0:
                out.pop()
            out.append(p)
        return out[:-1]

    return np.array(half(pts) + half(pts[::-1]))


def signed_distance_to_hull(hull, xy):
    """Min signed distance (pixels, > 0 inside) of points ``xy (..., 2)`` to the hull's edges."""
    d = np.full(xy.shape[:-1], np.inf)
    for a, b in zip(hull, np.roll(hull, -1, axis=0)):
        e = b - a
        d = np.minimum(d, cross2(e, xy - a) / np.linalg.norm(e))
    return d


@pytest.fixture(scope="module")
def renderer():
    r = TileRenderer(W, H)
    r.upload("cube", *cube())
    r.upload("quad", *quad())
    yield r
    r.release()


PROJ = perspective(np.radians(50), W / H, 0.1, 100.0)


def test_cube_covers_exactly_its_analytic_projection(renderer):
    model = translation(0.3, -0.2, -4) @ rotation([1, 2, 0.5], 0.7)
    view = rotation([0, 1, 0], 0.05)  # camera turned slightly: the view matrix is honoured too
    image = renderer.render([("cube", model, 1)], view, PROJ)
    hull = convex_hull(to_pixels(cube()[0], PROJ @ view @ model))
    inside = signed_distance_to_hull(hull, pixel_centres()) > 0

    covered = image.ids == 1
    assert set(np.unique(image.ids)) == {0, 1}
    rows, cols = np.nonzero(covered)
    lo, hi = hull.min(0), hull.max(0)  # the covered box is the pixel centres inside the hull's box
    assert abs(cols.min() - np.ceil(lo[0] - 0.5)) <= 1 and abs(cols.max() - np.floor(hi[0] - 0.5)) <= 1
    assert abs(rows.min() - np.ceil(lo[1] - 0.5)) <= 1 and abs(rows.max() - np.floor(hi[1] - 0.5)) <= 1
    # Stronger: the covered set is exactly the centres inside the silhouette, up to centres lying
    # within a hundredth of a pixel of an edge (rasterisation tie rules and float rounding).
    wrong = covered != inside
    assert not np.any(wrong & (np.abs(signed_distance_to_hull(hull, pixel_centres())) > 0.01))
    assert covered.sum() > 200


def test_nearer_object_wins_and_depth_is_analytic(renderer):
    near_model = translation(0.2, 0.1, -2.0)
    normal = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    tilt = rotation(np.cross([0, 0, 1], normal), np.arccos(normal[2]))
    far_model = translation(0, 0, -3.0) @ tilt @ np.diag([8.0, 8.0, 1.0, 1.0])  # fills the view
    # The near quad is drawn first: only the depth test, not the draw order, can hide the far one.
    image = renderer.render([("quad", near_model, 7), ("quad", far_model, 3)], np.eye(4), PROJ)
    assert set(np.unique(image.ids)) == {3, 7}
    near_box = to_pixels(quad()[0], PROJ @ near_model)
    cy, cx = np.round(near_box.mean(0)[::-1]).astype(int)
    assert image.ids[cy, cx] == 7 and image.ids[0, 0] == 3

    # Eye-space depth of the tilted plane n.p = n.(0, 0, -3) along each pixel-centre ray.
    ndc = pixel_centres() / [W, H] * [2, -2] + [-1, 1]
    rays = np.dstack([ndc[..., 0] / PROJ[0, 0], ndc[..., 1] / PROJ[1, 1], -np.ones((H, W))])
    z_eye = -(normal @ [0, 0, -3.0]) / (rays @ normal)
    expected = ((PROJ[2, 2] * z_eye + PROJ[2, 3]) / -z_eye + 1) / 2
    far_pixels = image.ids == 3
    assert np.abs(image.depth - expected)[far_pixels].max() < 1e-5
    z_near = ((PROJ[2, 2] * -2.0 + PROJ[2, 3]) / 2.0 + 1) / 2
    assert np.abs(image.depth[image.ids == 7] - z_near).max() < 1e-5
    # Depth test LESS: of two coincident surfaces the first drawn stays.
    tie = renderer.render([("quad", near_model, 7), ("quad", near_model, 8)], np.eye(4), PROJ)
    assert set(np.unique(tie.ids)) == {0, 7}


def test_reversed_z_keeps_coverage_and_reverses_depth(renderer):
    if not render.reversed_z_available():
        with pytest.raises(NotImplementedError):
            renderer.render([], np.eye(4), PROJ, reversed_z=True)
        pytest.skip("no glClipControl in this context")
    draws = [("quad", translation(0.2, 0.1, -2.0), 7), ("cube", translation(0, 0, -3.0), 3)]
    rproj = reversed_perspective(np.radians(50), W / H, 0.1, 100.0)
    normal = renderer.render(draws, np.eye(4), PROJ)
    reversed_ = renderer.render(draws, np.eye(4), rproj, reversed_z=True)
    assert np.array_equal(normal.ids, reversed_.ids)  # the nearer still wins, with GREATER
    assert np.all(reversed_.depth[reversed_.ids == 0] == 0)  # cleared to 0
    expected = rproj[2, 3] / 2.0 - rproj[2, 2]  # window depth = clip depth in [0, 1] at z = -2
    assert np.abs(reversed_.depth[reversed_.ids == 7] - expected).max() < 1e-5
    # The shared context is back to [-1, 1] for the next frame.
    assert np.array_equal(renderer.render(draws, np.eye(4), PROJ).depth, normal.depth)


def test_row_zero_is_the_top(renderer, tmp_path):
    image = renderer.render([("cube", translation(1.0, 0.8, -5), 2)], np.eye(4), PROJ)
    rows, cols = np.nonzero(image.ids)
    assert rows.max() < H // 2 and cols.min() > W // 2  # above and right of the view axis
    assert np.all(image.color[image.ids == 0] == [26, 26, 26, 255])  # background
    assert np.all(image.color[image.ids == 2][:, :3].max(1) > 40)  # shaded, not black
    image.save_png(tmp_path / "tile.png")
    from PIL import Image as PILImage

    assert np.array_equal(np.asarray(PILImage.open(tmp_path / "tile.png")), image.color)


@pytest.mark.parametrize("tilt", [0.0, 1.0])
def test_headlight_lambert_shading(renderer, tilt):
    model = translation(0, 0, -3) @ rotation([1, 0, 0], tilt)
    image = renderer.render([("quad", model, 6)], np.eye(4), PROJ)
    assert image.ids[H // 2, W // 2] == 6
    # On the view axis the light direction is +z: shade = 0.25 + 0.75 cos(tilt).
    expected = np.array(render.draw_color(6)) * 255 * (0.25 + 0.75 * np.cos(tilt))
    assert np.abs(image.color[H // 2, W // 2, :3] - expected).max() <= 2


def test_model_matrix_is_honoured(renderer):
    models = {4: translation(-1.2, 0.3, -5), 5: translation(1.0, -0.4, -5)}
    image = renderer.render([("quad", m, i) for i, m in models.items()], np.eye(4), PROJ)
    assert set(np.unique(image.ids)) == {0, 4, 5}
    sizes = [np.sum(image.ids == i) for i in models]
    assert abs(sizes[0] - sizes[1]) <= 0.1 * sizes[0]  # same mesh, same depth: same size
    for i, m in models.items():  # each blob is centred where its own model matrix puts it
        rows, cols = np.nonzero(image.ids == i)
        centre = to_pixels(np.zeros((1, 3)), PROJ @ m)[0]
        assert np.allclose([cols.mean() + 0.5, rows.mean() + 0.5], centre, atol=0.5)


def test_draw_ranges_draw_exactly_their_triangles(renderer):
    """A mesh drawn by ranges of its triangles (a leaf shown in part) gives the pixels of a mesh
    made of those triangles alone; ranges outside the mesh are refused."""
    v, f = cube()
    model = translation(0.1, 0.2, -4) @ rotation([1, 2, 0.5], 0.7)
    for ranges in ([[0, 12]], [[0, 2], [6, 4]], [[3, 1]], [[11, 1], [0, 0]], []):
        keep = np.concatenate([np.arange(a, a + b) for a, b in ranges] or [np.zeros(0, int)])
        if len(keep):
            renderer.upload("part", v, f[keep])
        want = renderer.render([("part", model, 2)] if len(keep) else [], np.eye(4), PROJ)
        got = renderer.render([("cube", model, 2, ranges)], np.eye(4), PROJ)
        np.testing.assert_array_equal(got.ids, want.ids)
        np.testing.assert_array_equal(got.color, want.color)
    assert (want.ids == 0).all() and (renderer.render([("cube", model, 2, [[3, 1]])], np.eye(4),
                                                      PROJ).ids == 2).any()
    renderer.evict("part")
    with pytest.raises(ValueError):
        renderer.render([("cube", model, 2, [[10, 3]])], np.eye(4), PROJ)


@pytest.mark.parametrize("plane", [(-1.0, 0.0, 0.0, 0.3), (0.6, -0.8, 0.0, 0.17)])
def test_clip_plane_removes_exactly_one_side(renderer, plane):
    model = translation(0, 0, -2) @ np.diag([2.0, 2.0, 1.0, 1.0])  # quad x, y in [-1, 1] at z = -2
    full = renderer.render([("quad", model, 1)], np.eye(4), PROJ).ids == 1
    clipped = renderer.render([("quad", model, 1)], np.eye(4), PROJ, clip_plane=plane).ids == 1
    # World (x, y) on the quad under each pixel centre, and its signed distance to the plane.
    ndc = pixel_centres() / [W, H] * [2, -2] + [-1, 1]
    x, y = 2 * ndc[..., 0] / PROJ[0, 0], 2 * ndc[..., 1] / PROJ[1, 1]
    side = plane[0] * x + plane[1] * y + plane[3]
    assert 0.25 < clipped.sum() / full.sum() < 0.75
    assert not np.any(clipped & ~full)
    wrong = clipped != (full & (side >= 0))
    pixel_world = 2 / (PROJ[1, 1] * H / 2)  # world size of one pixel on the quad
    assert not np.any(wrong & (np.abs(side) > 0.01 * pixel_world))


def test_camera_relative_far_from_origin():
    """A scene 1e7 from the origin renders the same ids as at the origin.

    Observed: the geometry never degrades, with or without ``camera_relative``, because
    ``projection @ view @ model`` is multiplied in float64 and its translation is small; what does
    degrade without it is the world-space clip distance (float32 positions and plane offsets of 1e7,
    ulp 1), which ``camera_relative`` makes eye-relative. Vertices baked at 1e7 are fine too,
    because uploads are re-centred before the float32 conversion.
    """
    r = TileRenderer(W, H)
    r.upload("cube", *cube())
    offset = np.array([1e7 + 0.37, -1e7 + 0.61, 1.3e7 + 0.13])
    view = rotation([0.3, 1, 0.2], 0.05) @ translation(-0.5, -0.2, 0.3)  # eye at (0.5, 0.2, -0.3)
    models = [translation(-0.4, 0.1, -4) @ rotation([1, 1, 0], 0.5), translation(0.6, -0.3, -4.6)]
    plane = np.array([0.7, 0.1, 0.2, 0.4])

    def scene(shift, **kw):
        shifted = plane - [0, 0, 0, plane[:3] @ shift]  # the same plane, moved with the scene
        v = view @ translation(*-shift)
        draws = [("cube", translation(*shift) @ m, i + 1) for i, m in enumerate(models)]
        return r.render(draws, v, PROJ, **kw).ids, r.render(draws, v, PROJ, clip_plane=shifted, **kw).ids

    ids, clipped = scene(np.zeros(3))
    assert 0 < np.sum(clipped > 0) < np.sum(ids > 0)
    far_ids, far_clipped = scene(offset, camera_relative=True)
    assert np.array_equal(far_ids, ids) and np.array_equal(far_clipped, clipped)
    plain_ids, plain_clipped = scene(offset)
    assert np.array_equal(plain_ids, ids)  # float64 product: geometry intact
    # float32 world-space clipping at 1e7 (ulp 1) moves the cut by ~0.3 units, ~3 pixels here.
    assert np.sum(plain_clipped != clipped) > 0.1 * np.sum(clipped > 0)

    # Vertices baked 1e7 away from the origin, identity model matrix.
    baked = [(f"baked{i}", i + 1) for i in range(len(models))]
    for (key, _), m in zip(baked, models):
        r.upload(key, (np.c_[cube()[0], np.ones(8)] @ (translation(*offset) @ m).T)[:, :3], cube()[1])
    draws = [(key, np.eye(4), i) for key, i in baked]
    assert np.array_equal(r.render(draws, view @ translation(*-offset), PROJ).ids, ids)

    # The scene is a real float32 stress test: float32 matrices multiplied on the GPU (simulated
    # by rounding each before the product) lose it.
    f32 = lambda m: m.astype(np.float32).astype(np.float64)  # noqa: E731
    draws = [("cube", f32(translation(*offset) @ m), i + 1) for i, m in enumerate(models)]
    assert np.sum(r.render(draws, f32(view @ translation(*-offset)), PROJ).ids != ids) > 0.1 * np.sum(ids > 0)
    r.release()


def test_mirrored_view_needs_clockwise_front_faces(renderer):
    model = translation(0, 0, -4) @ rotation([1, 1, 0], 0.6)
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])  # a reflection flips the winding on screen

    def brightness(image):
        return image.color[image.ids > 0][:, :3].astype(float).mean()

    plain = renderer.render([("cube", model, 1)], np.eye(4), PROJ)
    wrong = renderer.render([("cube", model, 1)], mirror, PROJ)
    right = renderer.render([("cube", model, 1)], mirror, PROJ, front_face_cw=True)
    assert np.sum(right.ids != plain.ids[:, ::-1]) <= 0.05 * np.sum(plain.ids > 0)
    assert abs(brightness(right) - brightness(plain)) < 2
    assert brightness(wrong) < 0.6 * brightness(right)  # seen as back faces: darker


def test_several_renderers_share_one_context():
    a, b = TileRenderer(40, 30), TileRenderer(24, 24)
    ms = TileRenderer(40, 30, samples=4)
    a.upload("m", *cube())
    b.upload("m", *quad())
    ms.upload("m", *cube())
    model, proj = translation(0, 0, -3), perspective(np.radians(60), 40 / 30, 0.1, 10)
    first = a.render([("m", model, 1)], np.eye(4), proj)
    other = b.render([("m", model, 2)], np.eye(4), perspective(np.radians(60), 1, 0.1, 10))
    again = a.render([("m", model, 1)], np.eye(4), proj)
    assert first.ids.shape == (30, 40) and other.ids.shape == (24, 24)
    assert np.array_equal(first.ids, again.ids) and np.array_equal(first.color, again.color)
    assert set(np.unique(other.ids)) == {0, 2}
    multi = ms.render([("m", model, 1)], np.eye(4), proj)
    assert set(np.unique(multi.ids)) <= {0, 1}  # integer ids resolve to one sample, never blended
    assert np.sum(multi.ids != first.ids) <= 0.1 * np.sum(first.ids > 0)
    b.evict("m")
    assert a.cached_bytes > 0  # caches are per renderer
    for r in (a, b, ms):
        r.release()


def test_upload_evict_bookkeeping():
    r = TileRenderer(8, 8)
    v, f = cube()
    assert r.cached_bytes == 0
    r.upload("a", v, f)
    assert r.cached_bytes == 8 * 3 * 4 + 12 * 3 * 4
    r.upload("a", *quad())  # replaces, does not add
    assert r.cached_bytes == 4 * 3 * 4 + 2 * 3 * 4
    r.upload(("tuple", 1), v, f)
    assert r.cached_bytes == 4 * 3 * 4 + 2 * 3 * 4 + 8 * 3 * 4 + 12 * 3 * 4
    r.evict("a")
    r.evict("never uploaded")
    assert r.cached_bytes == 8 * 3 * 4 + 12 * 3 * 4
    with pytest.raises(KeyError):
        r.render([("a", np.eye(4), 1)], np.eye(4), PROJ)
    with pytest.raises(ValueError):
        r.render([(("tuple", 1), np.eye(4), 0)], np.eye(4), PROJ)  # 0 is the background id
    with pytest.raises(ValueError):
        r.upload("bad", v, f + 8)
    r.evict(("tuple", 1))
    assert r.cached_bytes == 0
    assert isinstance(r.render([], np.eye(4), PROJ), Image)
    r.release()


def test_a_mesh_of_no_triangles_draws_nothing(renderer):
    """A mesh of vertices and no faces (a glTF primitive of points) is cached and draws
    nothing, whole, by no range or by triangle ids; its upload raised (a GL buffer cannot be
    empty), and took down the render nodes and the picture tool that fetched it."""
    points = np.random.default_rng(0).random((20, 3)) - 0.5
    r = TileRenderer(W, H)
    r.upload("cube", *cube())
    before = r.cached_bytes
    r.upload("points", points, np.zeros((0, 3), np.int64))
    assert r.cached_bytes == before
    model = translation(0, 0, -4)
    alone = r.render([("cube", model, 1)], np.eye(4), PROJ)
    for extra in (("points", model, 2), ("points", model, 2, []), ("points", model, 2, None)):
        image = r.render([("cube", model, 1), extra], np.eye(4), PROJ)
        np.testing.assert_array_equal(image.ids, alone.ids)
        np.testing.assert_array_equal(image.color, alone.color)
    image = r.render([("points", model, 5)], np.eye(4), PROJ, triangle_ids=True)
    assert not image.ids.any()
    with pytest.raises(ValueError):
        r.render([("points", model, 2, [[0, 1]])], np.eye(4), PROJ)  # no triangle to draw
    r.upload("points", *quad())  # replaced by a mesh of triangles, and back
    r.upload("points", points, np.zeros((0, 3), np.int64))
    r.evict("points")
    assert r.cached_bytes == before
    r.release()


def test_a_leaf_of_points_the_server_lists_is_drawn_as_nothing(tmp_path, monkeypatch):
    """A glTF of a point primitive beside a box: the server lists the points' leaf (it is
    bounded and in view), and a tile drawn from its list equals the whole scene drawn."""
    import trimesh

    from wallcull.fit import FitOptions
    from wallcull.pipeline import Session
    from wallcull.scene import load
    from wallcull.wall import Wall

    from .drawing import Draws

    monkeypatch.setenv("WALLCULL_CACHE", str(tmp_path / "cache"))
    s = trimesh.Scene()
    cloud = np.random.default_rng(0).random((20, 3)) - [0.5, 0.5, 0]
    s.add_geometry(trimesh.PointCloud(cloud), node_name="points", geom_name="points")
    s.add_geometry(trimesh.creation.box(extents=[1, 1, 1]), node_name="box", geom_name="box")
    path = tmp_path / "points.glb"
    path.write_bytes(s.export(file_type="glb"))
    scene = load(str(path))
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [1.6, 0.9], "distance": 1.0,
                           "resolution": [64, 36]})
    result = Session(scene, wall, fit=FitOptions()).frame(
        {"position": [0, 0, 4], "orientation": [1, 0, 0, 0]})
    assert sorted(result.visibility.names(0, leaves=True)) == ["box", "points"]
    r = TileRenderer(64, 36)
    draws = Draws(scene, r)
    view, proj = (np.asarray(result.fits[0][k]) for k in ("view", "projection"))
    culled = r.render(draws.tile(result.visibility, 0), view, proj).ids
    np.testing.assert_array_equal(culled, r.render(draws.everything(), view, proj).ids)
    assert (culled == scene.index["box"] + 1).sum() > 100
    r.release()


@pytest.mark.parametrize("mirrored", [False, True])
def test_a_single_sided_mesh_shows_its_front_faces_alone(mirrored):
    """A mesh uploaded ``single_sided`` has its back faces culled, as glTF asks where a
    material is not ``doubleSided``: a quad facing the eye is drawn, turned away it is not;
    under a mirroring model matrix its front is its clockwise side (glTF's rule), and a
    mirrored view (``front_face_cw``) turns it back. A quad uploaded as it was shows both."""
    r = TileRenderer(W, H)
    r.upload("one", *quad(), single_sided=True)
    r.upload("both", *quad())
    mirror = np.diag([1.0, 1.0, -1.0, 1.0]) if mirrored else np.eye(4)  # (its front to -z)
    for turned in (False, True):
        model = translation(0, 0, -3) @ (rotation([0, 1, 0], np.pi) if turned else np.eye(4))
        model = model @ mirror
        facing = turned == mirrored  # its front towards the eye
        one = r.render([("one", model, 1)], np.eye(4), PROJ).ids
        assert (one == 1).sum() > 100 if facing else not one.any()
        both = r.render([("both", model, 1)], np.eye(4), PROJ).ids
        assert (both == 1).sum() > 100
        # a mirrored view (its winding flipped on the image, front_face_cw) sees the same
        flip = np.diag([-1.0, 1.0, 1.0, 1.0])
        seen = r.render([("one", model, 1)], flip, PROJ, front_face_cw=True).ids
        np.testing.assert_array_equal(seen, one[:, ::-1])
    r.release()
