"""Fitted frusta verified through a real OpenGL renderer (Mesa llvmpipe, headless EGL)."""

import numpy as np
import pytest
import trimesh

from wallcull.cull import FINE
from wallcull.fit import FitOptions, tile_projections
from wallcull.projection import view_matrix
from wallcull.lowilie import fit_frustum
from wallcull.pipeline import Session
from wallcull.scene import Scene, load
from wallcull.wall import Frame, Wall

from .drawing import Draws, partial_leaves

render = pytest.importorskip("wallcull_clients.render")
try:
    render.TileRenderer(8, 8)
except Exception as exc:  # noqa: BLE001
    pytest.skip(f"no headless OpenGL: {exc}", allow_module_level=True)


def draws_for(scene: Scene, leaves, renderer):
    """Upload the leaves' meshes once; draw ids are leaf id + 1."""
    return renderer.draws.leaves(leaves)


def renderer_for(w, h, scene=None):
    r = render.TileRenderer(w, h)
    r.draws = Draws(scene, r)
    return r


@pytest.mark.parametrize("clusters,fine", [(256, FINE), (48, FINE), (48, 0.0)])
def test_culled_list_renders_exactly_like_the_whole_scene(clusters, fine):
    """Every tile of a 2 x 2 wall over fatehpur: drawing only the tile's culled list, the
    leaves it shows in part by their clusters' draw ranges, gives the same pixels as drawing
    every leaf, and the tight depth range clips nothing the wall's range would show. Clusters
    of two sizes, small ones listed whole as the product does (``fine``) or not."""
    scene = load("fatehpur", clusters=clusters)
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [0.8, 0.45], "gap": [0.02, 0.02],
                           "distance": 1.0, "resolution": [160, 90]})
    frame = Frame.from_dict({"position": [60, 45, 160], "eye": [0.1, 0.05, 0.2],
                             "orientation": [0.9848078, -0.1736482, 0, 0]}, wall)
    result = Session(scene, wall, fit=FitOptions(), fine=fine).frame(frame)
    assert partial_leaves(result.visibility) > (20 if fine == 0 else 5)
    r = renderer_for(*wall.resolution, scene=scene)
    everything = r.draws.everything()
    wide = tile_projections(wall, frame, np.full(4, wall.near), np.full(4, wall.far))
    drawn = 0
    for t in range(wall.tiles):
        view, proj = np.asarray(result.fits[t]["view"]), np.asarray(result.fits[t]["projection"])
        culled = r.draws.tile(result.visibility, t)
        full_img = r.render(everything, view, proj)
        culled_img = r.render(culled, view, proj)
        np.testing.assert_array_equal(culled_img.ids, full_img.ids)
        np.testing.assert_array_equal(culled_img.color, full_img.color)
        wall_img = r.render(everything, view, wide[t])
        np.testing.assert_array_equal(culled_img.ids > 0, wall_img.ids > 0)
        drawn += int((full_img.ids > 0).sum())
    assert drawn > 1000  # the view is not empty


def _lost_to_the_range(scene, wall, frame, fit):
    """Pixels each tile's fitted list and frusta lose against the whole scene drawn with the
    wall's depth range (a different range than the fitted one: what the fit may not clip)."""
    result = Session(scene, wall, fit=fit).frame(frame)
    r = renderer_for(*wall.resolution, scene=scene)
    everything = r.draws.everything()
    wide = tile_projections(wall, frame, np.full(wall.tiles, wall.near),
                            np.full(wall.tiles, wall.far), fit.reversed_z)
    lost = shown = 0
    for t in range(wall.tiles):
        view = np.asarray(result.fits[t]["view"])
        proj = np.asarray(result.fits[t]["projection"])
        culled = r.render(r.draws.tile(result.visibility, t), view, proj,
                          reversed_z=fit.reversed_z).ids
        whole = r.render(everything, view, wide[t], reversed_z=fit.reversed_z).ids
        lost += int(((whole > 0) & (culled == 0)).sum())
        shown += int((whole > 0).sum())
    return lost, shown


@pytest.mark.parametrize("reversed_z", [False, True])
@pytest.mark.parametrize("room,eye_z", [((8, 4, 12), 1.0), ((4, 3, 5), 0.0), ((20, 6, 60), 0.0)])
def test_the_fitted_depth_range_keeps_a_wall_seen_face_on_at_its_far_end(room, eye_z,
                                                                          reversed_z):
    """From inside a box room looking straight at its back wall, the wall is the farthest
    listed bound and lies face-on at it: the fitted far plane must leave it inside the depth
    range after float32 rounding and a 24-bit depth buffer (a margin of a millionth of the far
    distance lost the whole wall, in either depth convention)."""
    if reversed_z and not render.reversed_z_available():
        pytest.skip("this OpenGL has no glClipControl for reversed-Z")
    box = trimesh.creation.box(extents=room)
    box.apply_translation([0, 0, -room[2] / 2 + 2])
    s = trimesh.Scene()
    s.add_geometry(box, node_name="room", geom_name="room")
    scene = Scene.from_trimesh(s, hierarchy="file")
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [0.8, 0.45], "distance": 1.0,
                           "resolution": [160, 90]})
    frame = Frame.from_dict({"position": [0, 0, eye_z], "orientation": [1, 0, 0, 0]}, wall)
    lost, shown = _lost_to_the_range(scene, wall, frame, FitOptions(reversed_z=reversed_z))
    assert shown == 4 * 160 * 90
    assert lost == 0


@pytest.mark.parametrize("yaw", [19, 54, 68])
def test_a_flat_facade_seen_head_on_keeps_its_pixels(yaw):
    """A facade 2 km long of one quad, turned by ``yaw`` and seen head-on from 10 m, 50 m from
    one end: its depth range has nearly no width, and a projection fitted that narrowly made
    float32's rounding of the matrices clip the facade from every tile (at these yaws). The
    range spans at least a sixty-fourth of its far distance."""
    a = np.radians(yaw)
    facade = trimesh.Trimesh([[0, 0, 0], [2000, 0, 0], [2000, 30, 0], [0, 30, 0]],
                             [[0, 1, 2], [0, 2, 3]], process=False)
    facade.apply_transform(trimesh.transformations.rotation_matrix(a, [0, 1, 0]))
    s = trimesh.Scene()
    s.add_geometry(facade, node_name="facade", geom_name="facade")
    scene = Scene.from_trimesh(s, hierarchy="file")
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [0.8, 0.45], "distance": 1.0,
                           "resolution": [160, 90]})
    along, normal = np.array([np.cos(a), 0, -np.sin(a)]), np.array([np.sin(a), 0, np.cos(a)])
    eye = 50 * along + [0, 5, 0] + 10 * normal
    frame = Frame.from_dict({"position": eye.tolist(),  # looking down -normal
                             "orientation": [np.cos(a / 2), 0, np.sin(a / 2), 0]}, wall)
    result = Session(scene, wall, fit=FitOptions()).frame(frame)
    assert result.fits[0]["far"] - result.fits[0]["near"] < 1.0  # it is seen head-on
    lost, shown = _lost_to_the_range(scene, wall, frame, FitOptions())
    assert shown == 4 * 160 * 90
    assert lost == 0


def test_stereo_eyes_render_exactly_like_the_whole_scene():
    """A stereo frame on a 2 x 2 wall, eyes far apart: each eye's image of each tile, drawn
    from the tile's one list (what either eye sees) and its ranges, equals that eye's image of
    the whole scene."""
    scene = load("fatehpur", clusters=48)
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [0.8, 0.45], "gap": [0.0, 0.0],
                           "distance": 1.0, "resolution": [120, 68]})
    frame = Frame.from_dict({"position": [40, 20, 60], "eye": [0.0, 0.05, 0.3],
                             "orientation": [0.9848078, -0.1736482, 0, 0],
                             "stereo": {"ipd": 0.3}}, wall)
    result = Session(scene, wall, fit=FitOptions(), fine=0.0).frame(frame)
    assert partial_leaves(result.visibility) > 10
    r = renderer_for(*wall.resolution, scene=scene)
    everything = r.draws.everything()
    drawn = 0
    for t in range(wall.tiles):
        culled = r.draws.tile(result.visibility, t)
        for eye in ("left", "right"):
            view = np.asarray(result.fits[t][eye]["view"])
            proj = np.asarray(result.fits[t][eye]["projection"])
            full_img = r.render(everything, view, proj)
            np.testing.assert_array_equal(r.render(culled, view, proj).ids, full_img.ids)
            drawn += int((full_img.ids > 0).sum())
    assert drawn > 1000


def test_seamless_tiles_stitch_into_the_whole_wall():
    """A 3 x 2 seamless wall: the tiles' images side by side equal one image of the whole wall
    at the combined resolution, except for pixels whose centre a triangle edge passes through
    (the two renders' matrices round differently there). Tolerance: at most 0.3% of pixels, and
    each such pixel borders a different id in the whole-wall image."""
    scene = load("powerplant")
    cols, rows, w_px, h_px = 3, 2, 96, 64
    wall = Wall.from_dict({"cols": cols, "rows": rows, "tile_size": [0.6, 0.4], "gap": [0, 0],
                           "distance": 1.0, "resolution": [w_px, h_px]})
    frame = Frame.from_dict({"position": [0, 30, 90], "orientation": [0.9914449, -0.1305262, 0, 0]},
                            wall)
    result = Session(scene, wall, fit=FitOptions(depth="wall")).frame(frame)
    r = renderer_for(w_px, h_px, scene)
    stitched = np.zeros((rows * h_px, cols * w_px), dtype=np.uint32)
    for t in range(wall.tiles):
        row, col = divmod(t, cols)
        img = r.render(r.draws.tile(result.visibility, t),
                       np.asarray(result.fits[t]["view"]), np.asarray(result.fits[t]["projection"]))
        stitched[row * h_px:(row + 1) * h_px, col * w_px:(col + 1) * w_px] = img.ids
    whole = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": list(wall.size), "distance": 1.0})
    big = renderer_for(cols * w_px, rows * h_px, scene)
    proj = tile_projections(whole, Frame.from_dict(
        {"position": [0, 30, 90], "orientation": [0.9914449, -0.1305262, 0, 0]}, whole),
        np.array([wall.near]), np.array([wall.far]))[0]
    ref = big.render(draws_for(scene, scene.leaves, big), view_matrix(frame), proj).ids
    differ = stitched != ref
    assert (ref > 0).mean() > 0.2
    assert differ.mean() <= 0.003, f"{differ.sum()} pixels differ"
    edge = np.zeros_like(differ)
    pad = np.pad(ref, 1, mode="edge")
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        edge |= pad[dy:dy + ref.shape[0], dx:dx + ref.shape[1]] != ref
    assert not (differ & ~edge).any()


def test_mirror_view_clips_what_lies_behind_the_mirror():
    s = trimesh.Scene()
    for name, at in (("above", [0, 1.5, -6]), ("below", [0.5, -1.5, -6]),
                     ("straddle", [-2.5, 0, -7])):
        m = np.eye(4)
        m[:3, 3] = at
        s.add_geometry(trimesh.creation.box(extents=[1.5, 1.5, 1.5]), node_name=name,
                       geom_name=name, transform=m)
    scene = Scene.from_trimesh(s, hierarchy="file",
                               settings={"mirrors": [{"name": "floor", "point": [0, 0, 0],
                                                      "normal": [0, 1, 0]}]})
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [2.0, 1.2], "distance": 1.0,
                           "resolution": [200, 120]})
    frame = Frame.from_dict({"position": [0, 3, 2], "orientation": [0.9659258, -0.2588190, 0, 0]},
                            wall)
    result = Session(scene, wall, fit=FitOptions(depth="wall")).frame(frame)
    (entry,) = result.fits[0]["mirrors"]
    r = renderer_for(200, 120, scene)
    draws = draws_for(scene, scene.leaves, r)
    view, proj = np.asarray(entry["view"]), np.asarray(entry["projection"])
    img = r.render(draws, view, proj, front_face_cw=True)
    ids = {scene.names[i - 1] for i in np.unique(img.ids) if i}
    assert "above" in ids and "straddle" in ids and "below" not in ids
    # The same through a user clip plane (gl_ClipDistance) on the unmodified projection:
    plain = np.asarray(result.fits[0]["projection"])
    # The clip distance is taken on model (world) positions, before the view reflects them:
    # keep what lies in front of the mirror, which the reflection puts beyond it.
    refl_plane = np.array([0.0, 1.0, 0.0, 0.0])
    clipped = r.render(draws, view, plain, clip_plane=refl_plane, front_face_cw=True)
    assert ((clipped.ids > 0) != (img.ids > 0)).mean() < 0.002
    assert {i for i in np.unique(img.ids)} == {i for i in np.unique(clipped.ids)}
    # and the mirror's list holds exactly what is drawn there
    assert set(entry["visible"]) >= {i - 1 for i in np.unique(img.ids) if i}


@pytest.mark.parametrize("housing", [False, True])
def test_a_cube_maps_faces_keep_a_caster_right_by_the_light(housing):
    """A lamp 3 m over a 1 km ground, seen with the ground all around it (a cube map, its far
    plane 710 m out), with a caster 4 cm from the bulb: a flat shade under it, or an open
    housing around it (its box holds the bulb). Each face drawn with the fitted matrices
    shows the casters as the same face with a near plane at 0.1 mm does, pixel for pixel.
    The cube map's near plane stayed at a ten-thousandth of its far distance (7 cm), and
    clipped the caster from every face: its shadow was lost."""
    from wallcull.projection import frustum

    s = trimesh.Scene()
    ground = trimesh.creation.box(extents=[1000, 0.2, 1000])
    ground.apply_translation([0, -0.1, -10])
    s.add_geometry(ground, node_name="ground", geom_name="ground")
    if housing:  # a cube of half-width 4 cm around the bulb, open below
        cup = trimesh.creation.box(extents=[0.08, 0.08, 0.08])
        cup.update_faces(cup.face_normals[:, 1] > -0.5)
        cup.apply_translation([0, 3, -10])
    else:  # a shade, its top 4 cm under the bulb
        cup = trimesh.creation.box(extents=[0.3, 0.02, 0.3])
        cup.apply_translation([0, 2.95, -10])
    s.add_geometry(cup, node_name="cup", geom_name="cup")
    scene = Scene.from_trimesh(s, hierarchy="file",
                               settings={"lights": [{"name": "lamp", "position": [0, 3, -10]}]})
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [1.6, 0.9], "distance": 1.0,
                           "far": 1e5, "resolution": [160, 90]})
    frame = Frame.from_dict({"position": [0, 1.7, -6],
                             "orientation": [0.9659258, -0.2588190, 0, 0]}, wall)
    result = Session(scene, wall, fit=FitOptions()).frame(frame)
    (shadow,) = result.fits[0]["shadows"]
    assert shadow["cube"] and shadow["far"] > 700
    assert set(shadow["casters"]) == {scene.index["ground"], scene.index["cup"]}
    r = renderer_for(64, 64, scene)
    casters = r.draws.leaves(shadow["casters"])
    near = 1e-4
    reference = frustum(-near, near, -near, near, near, shadow["far"])
    cup_pixels = 0
    for view in shadow["views"]:
        got = r.render(casters, np.asarray(view), np.asarray(shadow["projection"])).ids
        ref = r.render(casters, np.asarray(view), reference).ids
        np.testing.assert_array_equal(got, ref)
        cup_pixels += int((ref == scene.index["cup"] + 1).sum())
    assert cup_pixels >= (5 * 64 * 64 if housing else 1000)  # the housing: five whole faces


def test_a_shadow_frustums_near_plane_keeps_every_caster_pixel():
    """A lamp 20 m over a ground patch a tile sees from above (a Low-Ilie frustum), a crate
    8 m under the lamp within it, and a pole beside the patch reaching 5.5 m over the lamp, only
    its foot within the frustum (clear of the patch: no two faces share a depth). The shadow
    map drawn with the fitted matrices (its near plane pulled in to the crate, not to the
    floor where the pole's bound put it) shows the casters
    as the same map with a near plane at 0.1 mm does, pixel for pixel: the crate, the pole's
    foot and the patch around them."""
    s = trimesh.Scene()
    for name, extents, at in (("patch", [6, 0.1, 6], [0, -0.05, -10]),
                              ("crate", [1, 1, 1], [0, 12, -4]),
                              ("pole", [0.2, 25, 2], [2.5, 13, -10])):
        m = trimesh.creation.box(extents=extents)
        m.apply_translation(at)
        s.add_geometry(m, node_name=name, geom_name=name)
    scene = Scene.from_trimesh(s, hierarchy="file",
                               settings={"lights": [{"name": "lamp", "position": [0, 20, 0]}]})
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [0.4, 0.4], "distance": 1.0,
                           "resolution": [64, 64]})
    frame = Frame.from_dict({"position": [0, 6, -10],
                             "orientation": [0.7071068, -0.7071068, 0, 0]}, wall)
    result = Session(scene, wall, fit=FitOptions()).frame(frame)
    (shadow,) = result.fits[0]["shadows"]
    far, near = shadow["far"], shadow["near"]
    assert not shadow.get("cube") and near > 1e3 * far * 1e-6
    r = renderer_for(128, 128, scene)
    view, projection = np.asarray(shadow["view"]), np.asarray(shadow["projection"])
    reference = projection.copy()
    n = 1e-4
    reference[2, 2:] = -(far + n) / (far - n), -2 * far * n / (far - n)
    casters = r.draws.leaves(shadow["casters"])
    got = r.render(casters, view, projection).ids
    ref = r.render(casters, view, reference).ids
    np.testing.assert_array_equal(got, ref)
    for name in ("crate", "pole", "patch"):
        assert (ref == scene.index[name] + 1).sum() > 20, name


def test_a_shadow_maps_near_floor_keeps_far_casters_in_a_24_bit_map():
    """Why a shadow map's near plane stops at a millionth of its far distance (``fit.NEAR_FLOOR``)
    though a caster lies nearer the light. A lamp lights a wall 50 km away (the map's far
    plane, 52.8 km with the fit's margin) past a 400 m slab at 45 km; a 2 mm fitting hangs
    3 mm before the bulb, off to the side. At the floor (5.3 cm) the fitting is clipped, but
    the slab lies three steps of the 24-bit depth buffer before the far plane: every pixel of
    it is in the map, in front of the wall. With the near plane pulled in to the fitting,
    2 mm, the map keeps the fitting and loses the slab: its depth rounds to the cleared 1.
    (A map's window depth at distance ``d`` is ``1 - near (far - d) / (far d)``, about.)"""
    f = 50000.0
    s = trimesh.Scene()
    wall_mesh = trimesh.Trimesh([[-2000, -1990, -f], [2000, -1990, -f], [2000, 2010, -f],
                                 [-2000, 2010, -f]], [[0, 1, 2], [0, 2, 3]], process=False)
    slab = trimesh.creation.box(extents=[400, 400, 10])
    slab.apply_translation([0, 10, -0.9 * f])
    fitting = trimesh.creation.box(extents=[0.002, 0.002, 0.002])
    fitting.apply_translation([0.0005, 10.0005, -0.003])
    for name, mesh in (("wall", wall_mesh), ("slab", slab), ("fitting", fitting)):
        s.add_geometry(mesh, node_name=name, geom_name=name)
    scene = Scene.from_trimesh(s, hierarchy="file",
                               settings={"lights": [{"name": "lamp", "position": [0, 10, 0]}]})
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [1.6, 0.9], "distance": 1.0,
                           "far": 1e6, "resolution": [160, 90]})
    frame = Frame.from_dict({"position": [0, 10, 1000 - f], "orientation": [1, 0, 0, 0]}, wall)
    result = Session(scene, wall, fit=FitOptions()).frame(frame)
    (shadow,) = result.fits[0]["shadows"]
    far, near = shadow["far"], shadow["near"]
    assert near == pytest.approx(far * 1e-6, rel=1e-12)  # the fitting lies nearer
    assert {scene.names[i] for i in shadow["casters"]} == {"wall", "slab", "fitting"}
    r = renderer_for(128, 128, scene)
    view, projection = np.asarray(shadow["view"]), np.asarray(shadow["projection"])

    def near_at(n):
        out = projection.copy()
        out[2, 2:] = -(far + n) / (far - n), -2 * far * n / (far - n)
        return out

    slab_id, fitting_id = scene.index["slab"] + 1, scene.index["fitting"] + 1
    footprint = r.render(r.draws.leaves([slab_id - 1]), view, near_at(0.5 * f)).ids > 0
    assert footprint.sum() > 100
    for proj, kept in ((projection, True), (near_at(0.002), False)):
        shown = r.render(r.draws.leaves(shadow["casters"]), view, proj).ids
        assert (shown == fitting_id).any() != kept
        if kept:  # the slab's whole footprint, in front of the wall
            np.testing.assert_array_equal(shown == slab_id, footprint)
        else:
            assert not (shown == slab_id).any()


@pytest.mark.parametrize("seed", range(3))
def test_low_ilie_frustum_clips_no_pixel_and_covers_more(seed, capsys):
    rng = np.random.default_rng(seed)
    mesh = trimesh.creation.box(extents=rng.uniform(0.5, 6, 3))
    mesh.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    mesh.apply_translation([0, 0, -20])
    eye = rng.normal(size=3) * 4
    w, h = 128, 96
    fit = fit_frustum(eye, mesh.vertices, w, h)
    r = renderer_for(w, h)
    r.upload("m", mesh.vertices, mesh.faces)
    draw = [("m", np.eye(4), 1)]
    img = r.render(draw, fit.view, fit.projection)
    zoom = np.diag([0.5, 0.5, 1.0, 1.0])  # the same view, twice as wide: what lies beyond
    wide = r.render(draw, fit.view, zoom @ fit.projection)
    ys, xs = np.nonzero(wide.ids)
    assert xs.min() >= w // 4 - 1 and xs.max() <= 3 * w // 4 and \
        ys.min() >= h // 4 - 1 and ys.max() <= 3 * h // 4, "part of the object lies outside"
    sample = r.render(draw, fit.sample_view, fit.sample_projection)
    covered, sample_covered = (img.ids > 0).mean(), (sample.ids > 0).mean()
    with capsys.disabled():
        print(f"\nLow-Ilie coverage {covered:.3f} against {sample_covered:.3f} (symmetric)")
    assert covered >= sample_covered and covered > 0.5


@pytest.mark.parametrize("glass, reversed_z", [(False, False), (True, False), (True, True),
                                               (False, True)])
def test_a_mirror_shows_what_lies_beyond_the_tiles_own_depth_range(glass, reversed_z):
    """A wall mirror 4 m ahead, facing the viewer, who sees a small box 2.5 m ahead (and, with
    ``glass``, the mirror's own surface just behind its plane): what the mirror shows lies 5 to
    14 m away, beyond the tile's fitted far plane. The mirror's pass keeps every pixel of the
    reflection drawn with the wall's range and a clip plane at the mirror; it lost them all
    when its projection kept the tile's own far plane, and without the glass (the far plane
    before the mirror) the tile had no mirror pass at all. With reversed-Z the oblique near
    plane was made on the reversed matrix, by the [-1, 1] formula, and no tile ever had a
    mirror pass."""
    from wallcull import settings as cfg

    s = trimesh.Scene()
    boxes = {"near_box": ([0.4, 0.4, 0.4], [0.5, 0.0, -2.5]),
             "behind": ([1.5, 1.5, 1.5], [-0.3, 0.0, 6.0])}
    if glass:
        boxes["glass"] = ([3, 3, 0.01], [0, 0, -4.006])
    for name, (extents, at) in boxes.items():
        m = trimesh.creation.box(extents=extents)
        m.apply_translation(at)
        s.add_geometry(m, node_name=name, geom_name=name)
    settings = {"mirrors": [{"name": "wallmirror", "point": [0, 0, -4], "normal": [0, 0, 1]}]}
    scene = Scene.from_trimesh(s, hierarchy="file", settings=settings)
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [1.6, 0.9], "distance": 1.0,
                           "resolution": [160, 90]})
    frame = Frame.from_dict({"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}, wall)
    result = Session(scene, wall, fit=FitOptions(reversed_z=reversed_z)).frame(frame)
    assert result.fits[0]["far"] < 5  # the tile's own range ends before the reflection
    (entry,) = result.fits[0]["mirrors"]
    r = renderer_for(160, 90, scene)
    mirror = cfg.parse(settings).mirrors[0]
    wide = tile_projections(wall, frame, np.array([wall.near]), np.array([wall.far]))[0]
    reflected = np.asarray(result.fits.view) @ mirror.reflection
    ref = r.render(r.draws.everything(), reflected, wide, clip_plane=list(mirror.plane),
                   front_face_cw=True).ids
    img = r.render(r.draws.leaves(entry["visible"]), np.asarray(entry["view"]),
                   np.asarray(entry["projection"]), front_face_cw=True,
                   reversed_z=reversed_z).ids
    assert {scene.names[i - 1] for i in np.unique(ref) if i} == {"near_box", "behind"}
    assert int((ref > 0).sum()) > 100
    assert int(((ref > 0) & (img == 0)).sum()) == 0
    assert set(np.unique(img)) <= set(np.unique(ref))  # the glass, behind the mirror: clipped
