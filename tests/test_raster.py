"""The software rasterizer (wallcull.raster) against a real OpenGL renderer and exact geometry,
and the visible floor of ``wallcull overdraw`` built on it.

Against OpenGL (Mesa llvmpipe, headless EGL, per-triangle ids from ``gl_PrimitiveID``): every
pixel of every tile has the same triangle id in both buffers, except a pixel where the two
differ for a reason rounding explains, each checked in float64 from the triangles' own
geometry (clipped to the near and far planes, in window coordinates):

* its centre lies within ``EDGE`` pixels of the outline of one of the two triangles (llvmpipe
  snaps vertices to 1/256 pixel, and computes in float32 from float32 matrices), or
* both triangles cover its centre at window depths within ``DEPTH`` of each other (coplanar
  or crossing surfaces: a 24-bit depth buffer fed float32 coordinates orders them at random).

Where the ids agree, the depths agree within ``DEPTH`` and what the triangle's depth changes
over ``EDGE`` pixels (a snapped vertex moves it; a range fitted tightly makes that change
steep). So the sets of triangles seen agree
except for triangles whose every pixel is such an edge case. A half-pixel shift of the
projection breaks both rules (the test of the test).
"""

import json

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from wallcull import overdraw, raster
from wallcull.cli import main
from wallcull.fit import FitOptions, tile_projections, tile_views
from wallcull.paths import scene_path
from wallcull.pipeline import Session
from wallcull.scene import Scene, load
from wallcull.wall import Frame, Frusta, Wall

from .drawing import Draws
from .randscene import look_at_frame, random_scene, random_wall

EDGE = 1 / 64  # pixels
DEPTH = 1e-5  # window depth


def window_polygon(scene: Scene, first: np.ndarray, tid: int, pv: np.ndarray, width: int,
                   height: int) -> np.ndarray | None:
    """Triangle ``tid`` clipped to the near and far planes, ``(k, 3)`` window ``x, y, depth``
    (float64), or None when nothing of it is left."""
    leaves = scene.leaves
    leaf = leaves[np.searchsorted(first[leaves], tid, side="right") - 1]
    v, f = scene.leaf_mesh(leaf)
    poly = np.c_[v[f[tid - first[leaf]]], np.ones(3)] @ (pv @ scene.world[leaf]).T
    for sign in (1.0, -1.0):  # w + z >= 0, w - z >= 0
        d = poly[:, 3] + sign * poly[:, 2]
        out = []
        for i in range(len(poly)):
            j = (i + 1) % len(poly)
            if d[i] >= 0:
                out.append(poly[i])
            if (d[i] >= 0) != (d[j] >= 0):
                out.append(poly[i] + d[i] / (d[i] - d[j]) * (poly[j] - poly[i]))
        if len(out) < 3:
            return None
        poly = np.array(out)
    ndc = poly[:, :3] / poly[:, 3:]
    return np.c_[(ndc[:, 0] + 1) * width / 2, (ndc[:, 1] + 1) * height / 2, (ndc[:, 2] + 1) / 2]


def at_pixel(poly: np.ndarray | None, x: float, y: float) -> tuple[bool, float, float]:
    """``(covers the point, distance to the outline in pixels, depth there)``."""
    if poly is None:
        return False, np.inf, np.nan
    a, b = poly[:, :2], np.roll(poly[:, :2], -1, axis=0)
    ab = b - a
    e = ab[:, 0] * (y - a[:, 1]) - ab[:, 1] * (x - a[:, 0])
    t = np.clip(((x - a[:, 0]) * ab[:, 0] + (y - a[:, 1]) * ab[:, 1])
                / np.maximum((ab ** 2).sum(axis=1), 1e-300), 0, 1)
    distance = np.hypot(a[:, 0] + t * ab[:, 0] - x, a[:, 1] + t * ab[:, 1] - y).min()
    plane = np.linalg.lstsq(np.c_[poly[:, :2], np.ones(len(poly))], poly[:, 2], rcond=None)[0]
    inside = bool((e >= 0).all() or (e <= 0).all())
    return inside, float(distance), float(plane @ (x, y, 1.0))


def slope(poly: np.ndarray | None) -> float:
    """How much the window depth of a (clipped) triangle changes across a pixel, at most."""
    if poly is None:
        return 0.0
    gx, gy, _ = np.linalg.lstsq(np.c_[poly[:, :2], np.ones(len(poly))], poly[:, 2],
                                rcond=None)[0]
    return float(abs(gx) + abs(gy))


def unexplained(scene, first, soft: raster.IdBuffer, gl, pv) -> list[tuple]:
    """The pixels where the software and the OpenGL buffers disagree beyond the module's
    tolerance: ``(row, col, software id, OpenGL id, why)``."""
    height, width = soft.ids.shape
    gl_ids = gl.ids.astype(np.int64)
    same = soft.ids == gl_ids
    polygons = {}
    bad = []
    deeper = same & (soft.ids > 0) & (np.abs(soft.depth - gl.depth) > DEPTH)
    for r, c in zip(*np.nonzero(deeper)):
        tid = int(soft.ids[r, c])  # the same triangle: its depth where a snapped vertex puts it
        if tid not in polygons:
            polygons[tid] = window_polygon(scene, first, tid, pv, width, height)
        if abs(soft.depth[r, c] - gl.depth[r, c]) > DEPTH + EDGE * slope(polygons[tid]):
            bad.append((int(r), int(c), tid, tid, "depth"))
    for r, c in zip(*np.nonzero(~same)):
        x, y = c + 0.5, height - 1 - r + 0.5
        seen = []
        for tid in (int(soft.ids[r, c]), int(gl_ids[r, c])):
            if tid and tid not in polygons:
                polygons[tid] = window_polygon(scene, first, tid, pv, width, height)
            seen.append(at_pixel(polygons[tid], x, y) if tid else (False, np.inf, np.nan))
        (in_a, edge_a, z_a), (in_b, edge_b, z_b) = seen
        if min(edge_a, edge_b) <= EDGE or (in_a and in_b and abs(z_a - z_b) <= DEPTH):
            continue
        bad.append((int(r), int(c), int(soft.ids[r, c]), int(gl_ids[r, c]), "id"))
    return bad


def gl_draws(draws: Draws, leaves, first, ranges=None) -> list[tuple]:
    """The leaves' draws with per-triangle ids numbered as the software rasterizer's."""
    return [(key, model, int(first[leaf]), part) for (key, model, _, part), leaf
            in zip(draws.leaves(leaves, ranges), leaves)]


@pytest.fixture(scope="module")
def gl():
    render = pytest.importorskip("wallcull_clients.render")
    try:
        render.TileRenderer(8, 8)
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"no headless OpenGL: {exc}")
    return render


def crossing(scene, leaves, pv, sign) -> np.ndarray:
    """The ids of the listed triangles that cross the near (sign 1) or far (-1) plane."""
    first = raster.first_ids(scene)
    out = []
    for leaf in leaves:
        v, f = scene.leaf_mesh(leaf)
        clip = np.c_[v, np.ones(len(v))] @ (pv @ scene.world[leaf]).T
        d = (clip[:, 3] + sign * clip[:, 2])[f]
        out.append(first[leaf] + np.flatnonzero((d.min(axis=1) < 0) & (d.max(axis=1) > 0)))
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def test_random_scenes_rasterize_as_opengl_draws_them(gl):
    """Random scenes, walls and frames, the camera among the leaves, near and far planes that
    cut through them: per pixel as OpenGL draws them (see the module doc); triangles across
    the near and the far plane are among those drawn and seen."""
    near_seen = far_seen = compared = 0
    for seed in range(10):
        rng = np.random.default_rng(seed)
        scene = Scene.from_trimesh(random_scene(seed, leaves=int(rng.integers(4, 16)), big=0.4))
        spec = random_wall(rng)
        spec.update(near=float(rng.uniform(0.05, 1.5)), far=float(rng.uniform(2.0, 12.0)),
                    resolution=[int(rng.integers(24, 97)), int(rng.integers(16, 65))])
        wall = Wall.from_dict(spec)
        frame = Frame.from_dict(look_at_frame(rng, scene.leaf_points[0].mean(axis=0),
                                              float(rng.uniform(0.5, 8.0)), spec), wall)
        depth = "wall" if seed % 2 else "tight"
        result = Session(scene, wall, fit=FitOptions(depth=depth)).frame(frame)
        width, height = wall.resolution
        r = gl.TileRenderer(width, height)
        draws, first = Draws(scene, r), raster.first_ids(scene)
        for t in range(wall.tiles):
            view, proj = result.fits.view, result.fits.projection[t]
            leaves = result.visibility.tile_leaves(t)
            soft = raster.render(scene, leaves, view, proj, width, height, first)
            img = r.render(gl_draws(draws, leaves, first), view, proj, triangle_ids=True)
            pv = proj @ view
            assert unexplained(scene, first, soft, img, pv) == [], (seed, t)
            near_seen += int(np.isin(soft.ids, crossing(scene, leaves, pv, 1.0)).sum())
            far_seen += int(np.isin(soft.ids, crossing(scene, leaves, pv, -1.0)).sum())
            compared += int((soft.ids > 0).sum())
        r.release()
    assert compared > 5000 and near_seen > 100 and far_seen > 100, (compared, near_seen,
                                                                     far_seen)


def test_the_power_plant_rasterizes_as_opengl_draws_its_ranges(gl):
    """The bundled power plant on a 2 x 2 wall, from inside (fly) and outside (orbit): the
    software draws each tile's leaves whole, OpenGL draws them by their clusters' ranges (so
    per-triangle ids count from each range's first triangle); per pixel as the module doc
    says, and the triangles each sees are nearly all the same."""
    scene = load("powerplant", clusters=64)
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [0.6, 0.34], "gap": [0.01, 0.01],
                           "distance": 2.0, "resolution": [160, 90]})
    session = Session(scene, wall, fit=FitOptions(), fine=0.0)
    r = gl.TileRenderer(160, 90)
    draws, first = Draws(scene, r), raster.first_ids(scene)
    seen = both = 0
    for frame in scene_path(scene, wall, "fly", 9)[::4] + scene_path(scene, wall, "orbit", 4)[:1]:
        result = session.frame(frame)
        vis = result.visibility
        for t in range(wall.tiles):
            view, proj = result.fits.view, result.fits.projection[t]
            soft = raster.render(scene, vis.tile_leaves(t), view, proj, 160, 90, first)
            img = r.render(gl_draws(draws, vis.tile_leaves(t), first,
                                    dict(vis.draw_ranges().tile(t))),
                           view, proj, triangle_ids=True)
            assert unexplained(scene, first, soft, img, proj @ view) == [], t
            a, b = set(np.unique(soft.ids)) - {0}, set(np.unique(img.ids.astype(np.int64))) - {0}
            seen, both = seen + len(a | b), both + len(a & b)
    r.release()
    assert seen > 2000 and both >= 0.97 * seen, (seen, both)


def test_the_comparison_catches_a_half_pixel_shift(gl):
    """The tolerance bites: OpenGL drawing with the projection shifted half a pixel to the
    right disagrees with the software beyond it."""
    scene = load("fatehpur", clusters=None)
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [0.8, 0.45], "distance": 1.0,
                           "resolution": [96, 54]})
    frame = Frame.from_dict({"position": [60, 45, 160],
                             "orientation": [0.9848078, -0.1736482, 0, 0]}, wall)
    result = Session(scene, wall, fit=FitOptions()).frame(frame)
    view, proj = result.fits.view, result.fits.projection[0]
    leaves = result.visibility.tile_leaves(0)
    first = raster.first_ids(scene)
    soft = raster.render(scene, leaves, view, proj, 96, 54, first)
    r = gl.TileRenderer(96, 54)
    shifted = proj.copy()
    shifted[0, 2] -= 1 / 96  # x_ndc + 2 * (1/2 pixel) / 96
    draws = gl_draws(Draws(scene, r), leaves, first)
    assert unexplained(scene, first, soft, r.render(draws, view, proj, triangle_ids=True),
                       proj @ view) == []
    assert len(unexplained(scene, first, soft, r.render(draws, view, shifted,
                                                        triangle_ids=True), proj @ view)) > 20
    r.release()


def test_a_triangle_through_the_near_plane_has_exact_coverage_and_depth():
    """One tilted quad reaching from behind the eye to beyond the far plane: a pixel is drawn
    exactly where its ray meets the quad between the near and far planes (away from the cut
    lines), at the window depth of that point (perspective-correct), the quad's half
    behind the eye never wrapped onto the image."""
    import trimesh

    quad = trimesh.Trimesh([[-40, -1, 5], [40, -1, 5], [40, -3, -60], [-40, -3, -60]],
                           [[0, 1, 2], [0, 2, 3]], process=False)
    tscene = trimesh.Scene()
    tscene.add_geometry(quad, node_name="quad", geom_name="quad")
    scene = Scene.from_trimesh(tscene)
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [0.8, 0.6], "distance": 1.0,
                           "near": 0.5, "far": 30.0, "resolution": [80, 60]})
    frame = Frame.from_dict({"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}, wall)
    view = tile_views(wall, frame)
    proj = tile_projections(wall, frame, np.array([0.5]), np.array([30.0]))[0]
    soft = raster.render(scene, scene.leaves, view, proj, 80, 60)
    # each pixel's ray from the eye meets the plane y = -1 - 2 (5 - z) / 65 at z_eye
    col, row = np.meshgrid(np.arange(80) + 0.5, np.arange(60) + 0.5)
    x_ndc, y_ndc = col / 40 - 1, 1 - row / 30  # row 0 at the top
    dx, dy = x_ndc / proj[0, 0], y_ndc / proj[1, 1]  # ray direction (dx, dy, -1)
    a, b = 2 / 65, -1 - 10 / 65  # the plane: y = a z + b
    with np.errstate(divide="ignore", invalid="ignore"):
        z = b / (-dy - a)  # y = -dy z along the ray: -dy z = a z + b
    distance = -z
    hit = (distance >= 0.5) & (distance <= 30) & (np.abs(-dx * z) <= 40)
    ndc_depth = (proj[2, 2] * z + proj[2, 3]) / -z
    window = (ndc_depth + 1) / 2
    # away from the lines where the near and far planes cut the quad
    plain = ~((np.abs(distance - 0.5) < 0.01) | (np.abs(distance - 30) < 0.6))
    assert (hit & plain).sum() > 1000 and (~hit & plain).sum() > 500
    np.testing.assert_array_equal(soft.ids[plain] > 0, hit[plain])
    np.testing.assert_allclose(soft.depth[hit & plain], window[hit & plain], rtol=0, atol=1e-12)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_the_visible_floor_counts_the_buffer_within_the_frustum_floor(seed):
    """Per tile: the visible floor is the number of distinct ids in the tile's id buffer, each
    the id of a listed triangle that meets the tile's frustum (so it is at most the frustum
    floor)."""
    rng = np.random.default_rng(seed)
    scene = Scene.from_trimesh(random_scene(seed, leaves=int(rng.integers(1, 10)), big=0.5))
    spec = random_wall(rng)
    spec["resolution"] = [int(rng.integers(8, 65)), int(rng.integers(8, 65))]
    frame_spec = look_at_frame(rng, scene.leaf_points[0].mean(axis=0), float(rng.uniform(1, 20)),
                               spec)
    wall = Wall.from_dict(spec)
    frame = Frame.from_dict(frame_spec, wall)
    result = Session(scene, wall, fit=FitOptions()).frame(frame)
    frusta, vis = Frusta.build(wall, frame), result.visibility
    resolution = np.tile(spec["resolution"], (wall.tiles, 1))
    got = overdraw.visible(scene, result.fits, vis, resolution)
    floor = overdraw.floor(scene, frusta, vis)
    first = raster.first_ids(scene)
    for t in range(wall.tiles):
        ids = raster.render(scene, vis.tile_leaves(t), result.fits.view,
                            result.fits.projection[t], *spec["resolution"]).ids
        seen = np.unique(ids[ids > 0])
        assert got[t] == len(seen) <= floor[t]
        planes = frusta.planes[frusta.tile_rows[t]]
        leaves = scene.leaves
        for tid in seen:
            leaf = leaves[np.searchsorted(first[leaves], tid, side="right") - 1]
            assert leaf in vis.tile_leaves(t)
            tri = scene.leaf_triangles(leaf)[tid - first[leaf]]
            assert overdraw.triangle_meets(tri, planes), (t, tid)


def test_overdraw_reports_the_visible_floor(capsys):
    assert main(["overdraw", "scenes/CesiumMilkTruck.glb", "--wall", "examples/wall-4x4.json",
                 "--frames", "3", "--visible-resolution", "96x54", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["visible_resolution"] == "96x54"
    assert report["floor"] >= report["visible"] > 0
    assert report["floor_over_visible"] == pytest.approx(report["floor"] / report["visible"])
    for e in report["settings"]:
        assert e["over_visible"] >= report["floor_over_visible"]
    assert main(["overdraw", "scenes/CesiumMilkTruck.glb", "--frames", "1"]) == 0
    assert "visible" not in capsys.readouterr().out  # only when asked
    # a wall of screens: each tile its own view (a CAVE around the eye)
    assert main(["overdraw", "scenes/CesiumMilkTruck.glb", "--wall", "examples/wall-cave.json",
                 "--frames", "2", "--visible-resolution", "48x48", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["floor"] >= report["visible"] > 0
    # the table, into a pipe: every row whole, however many columns
    assert main(["overdraw", "scenes/CesiumMilkTruck.glb", "--frames", "1", "--occlusion",
                 "--visible-resolution", "48x27"]) == 0
    table = capsys.readouterr().out
    chosen = load("scenes/CesiumMilkTruck.glb").cluster_size
    assert f"clusters of {chosen}, occlusion" in table and "visible floor" in table
    assert "\u2026" not in table  # nothing cut short with an ellipsis


def test_overdraw_refuses_a_bad_resolution(capsys):
    assert main(["overdraw", "powerplant", "--visible-resolution", "240"]) == 2
    assert "--visible-resolution must be WIDTHxHEIGHT" in capsys.readouterr().err
