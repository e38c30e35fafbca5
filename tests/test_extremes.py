"""Numerical stability at the extremes (issue: fitted frusta). Each test names its case and
states what the code returns; the README's "Extremes" section lists the same. Matrix-level
cases (hulls of 3 and 4 points, collinear and coincident points, nearly parallel hull edges, the
eye or a light inside the bounding sphere, reversed-Z float32 precision) are in
test_quad.py, test_lowilie.py and test_projection.py."""

import re

import numpy as np
import pytest
import trimesh

from wallcull.cull import METHODS, cull
from wallcull.errors import InputError
from wallcull.fit import FitOptions, tile_projections
from wallcull.projection import view_matrix
from wallcull.lowilie import fit_frustum
from wallcull.oracle import visible_leaves
from wallcull.pipeline import Session
from wallcull.projection import frustum_planes
from wallcull.scene import Scene, SceneState
from wallcull.wall import Frame, Frusta, Wall

from .randscene import look_at_frame, random_scene


def homog(m, p):
    q = np.c_[p, np.ones(len(p))] @ np.asarray(m).T
    return q[:, :3] / q[:, 3:]


def boxes(centers, sizes):
    s = trimesh.Scene()
    for i, (c, e) in enumerate(zip(centers, sizes)):
        m = np.eye(4)
        m[:3, 3] = c
        s.add_geometry(trimesh.creation.box(extents=[e] * 3), node_name=f"b{i}", geom_name=f"g{i}",
                       transform=m)
    return Scene.from_trimesh(s, hierarchy="file")


def conservative(scene, wall_spec, frame_spec, tol):
    wall = Wall.from_dict(wall_spec)
    frusta = Frusta.build(wall, Frame.from_dict(frame_spec, wall))
    truth = visible_leaves(scene, wall_spec, frame_spec, tol)
    for kind in ("obb", "aabb", "sphere"):
        for method in METHODS:
            vis = cull(SceneState(scene, kind), frusta, method)
            for t in range(wall.tiles):
                assert truth[t] <= set(vis.tile_leaves(t).tolist()), (kind, method, t)
    return truth


def corners_round_trip(wall, frame, projections, rtol):
    """Each tile's rectangle on the wall maps to the NDC square's corners."""
    view = view_matrix(frame)
    for t in range(wall.tiles):
        x0, x1, y0, y1 = wall.tile_rect(t)
        corners = frame.to_world(np.array([[x0, y0, -wall.distance], [x1, y0, -wall.distance],
                                           [x1, y1, -wall.distance], [x0, y1, -wall.distance]]))
        ndc = homog(projections[t] @ view, corners)[:, :2]
        np.testing.assert_allclose(ndc, [[-1, -1], [1, -1], [1, 1], [-1, 1]], atol=rtol)


def test_near_1e_6_far_1e9():
    """Culling stays exact at both ends (objects at 1e-5 and 1e8 found, one beyond 1e9 not);
    the projection is finite and round-trips; float32 depth with the standard matrix cannot
    tell 1e3 from 1.001e3 apart, reversed-Z can."""
    spec = {"cols": 2, "rows": 2, "tile_size": [1, 1], "distance": 1.0, "near": 1e-6,
            "far": 1e9}
    scene = boxes([[0.1e-5, 0.1e-5, -1e-5], [1e7, 1e7, -1e8], [0, 0, -2e9]], [1e-6, 1e6, 1e6])
    frame = {"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}
    truth = conservative(scene, spec, frame, 1e-7 * 1e9)
    assert scene.index["b1"] in set().union(*truth)
    # The contract's tolerance here is 1e-7 of a 2e9 scene, 200 units: the oracle need not see
    # a 1e-6 box 1e-5 away; the culler must and does.
    vis = cull(SceneState(scene), Frusta.build(Wall.from_dict(spec),
                                               Frame.from_dict(frame, Wall.from_dict(spec))))
    found = np.concatenate([vis.tile_leaves(t) for t in range(4)])
    assert scene.index["b0"] in found and scene.index["b2"] not in found
    wall = Wall.from_dict(spec)
    f = Frame.from_dict(frame, wall)
    proj = tile_projections(wall, f, np.full(4, 1e-6), np.full(4, 1e9))
    assert np.isfinite(proj).all()
    corners_round_trip(wall, f, proj, 1e-9)
    points = np.c_[[[0, 0, -1e3], [0, 0, -1.001e3]], np.ones(2)].astype(np.float32)

    def depth32(m):  # what a float32 GPU computes
        clip = points @ m.astype(np.float32).T
        return clip[:, 2] / clip[:, 3]

    standard = depth32(proj[0])
    rev = tile_projections(wall, f, np.full(4, 1e-6), np.full(4, 1e9), reversed_z=True)[0]
    reversed_depth = depth32(rev)
    assert standard[0] == standard[1]  # 24 bits, or even float32, cannot separate them
    assert reversed_depth[0] > reversed_depth[1]


def test_infinite_far_plane():
    """An infinite far distance gives Lengyel's limit matrix (rows 3 = (0, 0, -1, -2n)): finite,
    the near plane still maps to -1, and the extracted far plane is the plane at infinity."""
    wall = Wall.from_dict({"cols": 3, "rows": 1, "tile_size": [1, 1], "distance": 2.0})
    frame = Frame.from_dict({"position": [1, 2, 3], "orientation": [1, 0, 0, 0]}, wall)
    proj = tile_projections(wall, frame, np.full(3, 0.1), np.full(3, np.inf))
    assert np.isfinite(proj).all()
    np.testing.assert_allclose(proj[:, 2, 2:], [[-1, -0.2]] * 3)
    corners_round_trip(wall, frame, proj, 1e-12)
    planes = frustum_planes(proj[1] @ view_matrix(frame))
    np.testing.assert_allclose(planes[5], [0, 0, 0, 1])
    far_point = frame.to_world(np.array([[0, 0, -1e12]]))
    assert -1 < homog(proj[1] @ view_matrix(frame), far_point)[0, 2] < 1


def test_only_the_matrices_take_an_infinite_far_plane():
    """A wall document with an infinite far distance is refused in one line, as every infinity
    is: the infinite projection comes from the matrix functions alone, and the concepts page,
    wherever it gives a far distance of infinity, says a wall's must be finite (it said a far
    distance of infinity gave the infinite projection, and a wall made with one was
    refused)."""
    from pathlib import Path

    with pytest.raises(InputError, match="wall far must be finite"):
        Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [1, 1], "distance": 1.0,
                        "far": float("inf")})
    page = (Path(__file__).resolve().parent.parent / "docs" / "concepts.md").read_text()
    items = re.split(r"\n(?=- |\| |\n)", page)  # list items, table rows, paragraphs
    infinite = [i for i in items if re.search(r"far distance of infinity|infinite far", i)]
    assert infinite
    for item in infinite:
        assert "must be finite" in item, item


def test_scene_offset_by_1e7():
    """A scene and camera 1e7 from the origin cull conservatively, and their fitted matrices,
    evaluated in float64, map geometry to the same NDC as the same scene at the origin within
    1e-6 (the view removes the offset before anything is projected)."""
    offset = np.array([1e7, -2e7, 3e7])
    spec = {"cols": 3, "rows": 2, "tile_size": [0.6, 0.34], "gap": [0.01, 0.01], "distance": 1.0}
    results = []
    for shift in (np.zeros(3), offset):
        scene = Scene.from_trimesh(random_scene(4, leaves=20, offset=shift))
        center = scene.leaf_points[0].mean(0)
        frame = {"position": (center + [0, 0, 25]).tolist(), "orientation": [1, 0, 0, 0],
                 "eye": [0.1, -0.05, 0.2]}
        conservative(scene, spec, frame, 1e-7 * max(30, np.linalg.norm(frame["position"])))
        wall = Wall.from_dict(spec)
        res = Session(scene, wall, fit=FitOptions()).frame(frame)
        pts = scene.leaf_points[0]
        tile = int(np.argmax(np.diff(res.visibility.start)))  # the busiest tile (same in both)
        m = np.asarray(res.fits[tile]["projection"]) @ np.asarray(res.fits[tile]["view"])
        results.append(homog(m, pts))
    # compare what the tile shows (points near the eye plane project far outside, where any
    # rounding is magnified without bound)
    shown = (np.abs(results[0]) <= 1).all(axis=1)
    assert shown.sum() > 10
    np.testing.assert_allclose(results[0][shown], results[1][shown], atol=1e-6)


def test_tile_1mm_wide():
    """A tile 1 mm wide: the planes stay unit and exact; an object straight ahead is found in
    the middle tile only; the projection round-trips to 1e-9."""
    spec = {"cols": 3, "rows": 3, "tile_size": [1e-3, 1e-3], "distance": 2.0}
    scene = boxes([[0, 0, -50]], [1e-4])
    frame = {"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}
    truth = conservative(scene, spec, frame, 1e-7 * 50)
    assert [len(s) for s in truth] == [0, 0, 0, 0, 1, 0, 0, 0, 0]
    wall = Wall.from_dict(spec)
    f = Frame.from_dict(frame, wall)
    corners_round_trip(wall, f, tile_projections(wall, f, np.full(9, 0.1), np.full(9, 1e3)), 1e-9)


def test_1x64_wall():
    """One row of 64 tiles: the frustum hierarchy is 6 column splits deep, every method is
    conservative, and a scene spanning the row shows up in every tile."""
    spec = {"cols": 64, "rows": 1, "tile_size": [0.1, 0.5], "gap": [0.002, 0], "distance": 1.0}
    wall = Wall.from_dict(spec)
    assert wall.hierarchy.height == 6
    scene = Scene.from_trimesh(random_scene(9, leaves=30))
    frame = look_at_frame(np.random.default_rng(1), scene.leaf_points[0].mean(0), 10.0, spec)
    conservative(scene, spec, frame, 1e-6)
    wide = boxes([[0, 0, -10]], [400.0])
    truth = conservative(wide, spec, {"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}, 1e-6)
    assert all(truth)


def test_field_of_view_near_180_degrees():
    """A wall 2 km wide 1 mm from the eye (half-angle 89.99994 degrees): planes stay valid,
    culling stays conservative (objects beside the eye are found, behind it not), and the
    projection maps the tile corners to within 1e-6 of the NDC square."""
    spec = {"cols": 2, "rows": 2, "tile_size": [1000, 1000], "distance": 1e-3, "near": 1e-4}
    scene = boxes([[50, 0.5, -1], [-50, 2, -0.5], [0, 0, 5]], [0.5, 0.5, 0.5])
    frame = {"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}
    truth = conservative(scene, spec, frame, 1e-7 * 60)
    seen = set().union(*truth)
    assert seen == {scene.index["b0"], scene.index["b1"]}
    wall = Wall.from_dict(spec)
    f = Frame.from_dict(frame, wall)
    corners_round_trip(wall, f, tile_projections(wall, f, np.full(4, 1e-4), np.full(4, 1e3)),
                       1e-6)


@pytest.mark.parametrize("shape", ["point", "segment", "flat"])
def test_degenerate_receivers_get_a_valid_shadow_frustum(shape):
    """A light over a receiver that is one point, a segment or a flat quad seen edge-on: the
    fit returns finite matrices with a rigid view, and the receiver lies inside."""
    pts = {"point": np.array([[0.0, 0.0, 0.0]] * 3),
           "segment": np.array([[-1.0, 0, 0], [1.0, 0, 0], [0.2, 0, 0]]),
           "flat": np.array([[-1.0, 0, -1], [1.0, 0, -1], [1.0, 0, 1], [-1.0, 0, 1]])}[shape]
    light = np.array([0.0, 0.0, 10.0]) if shape == "flat" else np.array([0.3, 5.0, 0.2])
    fit = fit_frustum(light, pts, 512, 512)
    m = fit.projection @ fit.view
    assert np.isfinite(m).all()
    np.testing.assert_allclose(fit.view[:3, :3] @ fit.view[:3, :3].T, np.eye(3), atol=1e-12)
    assert (np.abs(homog(m, pts)) <= 1 + 1e-9).all()


def test_float32_matrices_on_the_client():
    """What a client computing in float32 gets: at the origin, tile corners land within 1e-6 of
    the NDC square; 1e7 away, multiplying float32 world coordinates by a float32 view loses
    whole units (the renderer's camera_relative mode subtracts the eye in float64 first)."""
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [0.6, 0.34], "distance": 2.0})
    for position, tol, ok in (([0, 0, 0], 1e-6, True), ([1e7, 1e7, 1e7], 1e-6, False)):
        frame = Frame.from_dict({"position": position, "orientation": [1, 0, 0, 0]}, wall)
        proj = tile_projections(wall, frame, np.full(4, 0.1), np.full(4, 1e3))
        view = view_matrix(frame).astype(np.float32)
        x0, x1, y0, y1 = wall.tile_rect(0)
        world = frame.to_world(np.array([[x0, y0, -2.0], [x1, y1, -2.0]])).astype(np.float32)
        clip = np.c_[world, np.ones(2, np.float32)] @ (proj[0].astype(np.float32) @ view).T
        ndc = clip[:, :2] / clip[:, 3:]
        err = np.abs(ndc - [[-1, -1], [1, 1]]).max()
        assert (err < tol) == ok, err


def triangles(points) -> Scene:
    """A scene of one-triangle leaves, each ``(3, 3)`` world points."""
    s = trimesh.Scene()
    for i, t in enumerate(np.asarray(points, float)):
        m = np.eye(4)
        m[:3, 3] = t.mean(axis=0)
        s.add_geometry(trimesh.Trimesh(t - m[:3, 3], [[0, 1, 2]], process=False),
                       node_name=f"t{i}", geom_name=f"g{i}", transform=m)
    return Scene.from_trimesh(s, hierarchy="file")


def screen(bl, br, tl) -> dict:
    return {"bottom_left": list(map(float, bl)), "bottom_right": list(map(float, br)),
            "top_left": list(map(float, tl)), "resolution": [100, 100]}


NO_MOVE = {"position": [0.0, 0.0, 0.0], "orientation": [1.0, 0.0, 0.0, 0.0]}


def test_a_screen_a_hair_over_its_split_plane_loses_nothing_far_beyond():
    """Two screens that a plane through the eye and the first one's edge tells apart, but for
    the second's corners, 3 nm over it. Taken as holding, the plane left a wedge of the second
    screen's frustum untested, 1.5e-9 rad wide: tiny triangles 4 km out were missed. A split
    holds only within rounding."""
    eye, edge = np.array([-2.0, 0.0, 2.0]), np.array([0.0, 0.0, -2.0])
    ray = (edge - eye) / np.linalg.norm(edge - eye)
    over = np.array([ray[2], 0.0, -ray[0]])  # across the ray, toward the first screen (x < 0)
    over = -over if over[0] > 0 else over
    corner = edge + ray + 3e-9 * over
    spec = {"screens": [screen([-1, -1, -2], [0, -1, -2], [-1, 1, -2]),
                        screen(corner + [0, -1, 0], corner + [1, -1, 0], corner + [0, 1, 0])],
            "near": 0.1, "far": 1e4}
    t = 1000.0
    scene = triangles([centre + np.array([[-e, -e, 0], [e, -e, 0], [0, e, 0]])
                       for s in np.linspace(-3, 3, 13)
                       for centre, e in [(corner + t * (corner - eye) + s * 3e-9 * (1 + t) * over,
                                          3e-10 * (1 + t))]])
    frame = {**NO_MOVE, "eye": eye.tolist()}
    extent = np.ptp(scene.leaf_points[0], axis=0).max()
    truth = conservative(scene, spec, frame, 1e-7 * extent)
    assert len(truth[1]) >= 5  # the second screen sees the wedge's triangles


def test_screens_overlapping_by_a_hair_keep_the_overlap_far_beyond():
    """Neighbouring screens that overlap by 1e-10 m were taken as a seamless grid: the shared
    plane cut the overlap off the second, a strip 2.5 mm wide 1e8 m out. A tiny overlap stays
    an overlap; a tiny bezel is still none (sharing the plane only widens a tile)."""
    spec = {"screens": [screen([-1, -1, -2], [5e-11, -1, -2], [-1, 1, -2]),
                        screen([-5e-11, -1, -2], [1, -1, -2], [-5e-11, 1, -2])],
            "near": 0.1, "far": 1e9}
    wall = Wall.from_dict(spec)
    assert wall.kind == "grid" and wall.gap[0] < 0
    z = -1e8
    scene = triangles([[[-1.5e-3, -1e-3, z], [-1.0e-3, -1e-3, z], [-1.2e-3, 1e-3, z]]])
    truth = conservative(scene, spec, NO_MOVE, 1e-7 * 2e-3)
    assert truth == [{scene.leaves[0]}, {scene.leaves[0]}]
    bezel = {**spec, "screens": [screen([-1, -1, -2], [-5e-11, -1, -2], [-1, 1, -2]),
                                 screen([5e-11, -1, -2], [1, -1, -2], [5e-11, 1, -2])]}
    assert Wall.from_dict(bezel).gap[0] == 0.0


@pytest.mark.parametrize("wall", [
    {"cols": 2, "rows": 2, "tile_size": [1e-9, 1e-9], "distance": 1.0},
    {"screens": [screen([0, 0, -2], [3e-9, 0, -2], [0, 3e-9, -2])]},
], ids=["grid", "screens"])
def test_a_tile_too_small_to_place_from_the_eye_is_refused_not_divided_by(wall):
    """A nanometre tile seen from 1e8 m aside: its edges are the same float64 from the eye
    (the projection divided by zero). Refused in one line, naming the tile; from half a metre
    the same tile is projected to finite matrices."""
    with pytest.raises(InputError, match="too far for float64 to tell its edges apart"):
        Frame.from_dict({**NO_MOVE, "eye": [1e8, 0.0, 0.0]}, Wall.from_dict(wall))
    w = Wall.from_dict(wall)
    frame = Frame.from_dict({**NO_MOVE, "eye": [0.0, 0.0, 0.5]}, w)
    near, far = np.full(w.tiles, w.near), np.full(w.tiles, w.far)
    assert np.isfinite(tile_projections(w, frame, near, far)).all()


def test_a_degenerate_screen_says_what_its_edges_need():
    with pytest.raises(InputError, match=r"longer than 1e-9 of .* \(2 m\), got 1e-09 x 1e-09 m"):
        Wall.from_dict({"screens": [screen([0, 0, -2], [1e-9, 0, -2], [0, 1e-9, -2])]})
