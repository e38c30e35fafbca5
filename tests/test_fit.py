"""Fitted frusta: round trips and properties, against independent computations."""

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings as hsettings, strategies as st

from wallcull import fit as fitmod
from wallcull.fit import FitOptions, tile_projections
from wallcull.projection import view_matrix
from wallcull.oracle import clip_triangles, clipped_depths, tile_frusta
from wallcull.pipeline import Session
from wallcull.projection import frustum_planes, tile_view_projection
from wallcull.scene import Scene
from wallcull.settings import parse
from wallcull.wall import Frame, Frusta, Wall

from .randscene import look_at_frame, random_scene, random_wall


def homog(m, p):
    q = np.c_[p, np.ones(len(p))] @ np.asarray(m).T
    return q[:, :3] / q[:, 3:]


@hsettings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), reversed_z=st.booleans())
def test_tight_depth_never_cuts_what_a_tile_shows(seed, reversed_z):
    """Every vertex of a listed leaf that lies in the tile's frustum (wall near/far) also lies
    between the fitted near and far planes, and the range is never wider than the wall's."""
    rng = np.random.default_rng(seed)
    scene = Scene.from_trimesh(random_scene(seed, leaves=20))
    wall_spec = random_wall(rng)
    wall = Wall.from_dict(wall_spec)
    frame = Frame.from_dict(look_at_frame(rng, scene.leaf_points[0].mean(0), 10.0, wall_spec), wall)
    session = Session(scene, wall, fit=FitOptions(reversed_z=reversed_z))
    result = session.frame(frame)
    eye = frame.to_world(frame.eye)
    forward = -frame.rotation[:, 2]
    for t, tile in enumerate(result.fits):
        assert wall.near <= tile["near"] < tile["far"] <= wall.far
        planes = Frusta.build(wall, frame).tile(t)
        for leaf in result.visibility.tile_leaves(t):
            v = scene.leaf_vertices(leaf)
            inside = (v @ planes[:, :3].T + planes[:, 3] >= 0).all(axis=1)
            depth = (v[inside] - eye) @ forward
            assert (depth >= tile["near"]).all() and (depth <= tile["far"]).all()
        # and the matrix uses them: the near and far planes round-trip
        m = np.asarray(tile["projection"]) @ np.asarray(tile["view"])
        planes6 = frustum_planes(m, reversed_z=reversed_z)
        p_near = eye + forward * tile["near"]
        p_far = eye + forward * tile["far"]
        assert abs(planes6[4, :3] @ p_near + planes6[4, 3]) < 1e-6 * tile["far"]
        assert abs(planes6[5, :3] @ p_far + planes6[5, 3]) < 1e-6 * tile["far"]


@hsettings(max_examples=300, deadline=None)
@given(value=st.floats(allow_nan=False, allow_infinity=False, width=64),
       direction=st.sampled_from([-1.0, 1.0]))
def test_depths_round_outward_to_the_nearest_float32(value, direction):
    """A depth bound is a float32 on the outer side of the exact one, and the nearest such."""
    rounded = fitmod.outward(value, direction)
    assert rounded == value or (rounded - value) * direction > 0
    if np.isfinite(rounded):
        as32 = np.float32(rounded)
        assert float(as32) == rounded
        if rounded != value:  # the next float32 back lies beyond the exact value
            with np.errstate(over="ignore"):  # past float32's largest: infinite
                back = float(np.nextafter(as32, np.float32(-direction * np.inf)))
            assert (back - value) * direction < 0
    else:  # beyond float32's range
        assert abs(value) > float(np.finfo(np.float32).max)


def test_projections_match_the_toolkit_and_the_culler():
    wall = Wall.from_dict({"cols": 5, "rows": 3, "tile_size": [0.6, 0.34], "gap": [0.02, -0.05],
                           "distance": 2.0})
    q = np.array([0.9, 0.1, 0.3, 0.2])
    frame = Frame.make([1e3, 2, 3], q / np.linalg.norm(q), [0.2, -0.1, 0.5], wall)
    near, far = np.full(wall.tiles, wall.near), np.full(wall.tiles, wall.far)
    ours = tile_projections(wall, frame, near, far)
    view = view_matrix(frame)
    frusta = Frusta.build(wall, frame)
    for t in range(wall.tiles):
        v, p = tile_view_projection(wall, frame, t)
        np.testing.assert_allclose(view, v, atol=1e-12)
        np.testing.assert_allclose(ours[t], p, rtol=1e-12, atol=1e-15)
        planes = frustum_planes(ours[t] @ view)  # left, right, bottom, top, near, far
        np.testing.assert_allclose(planes[[0, 1, 3, 2, 4, 5]], frusta.tile(t), atol=1e-9)


def test_reversed_z_maps_near_to_one_and_far_to_zero():
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [1, 1], "distance": 1.0,
                           "near": 0.5, "far": 80.0})
    frame = Frame.make([0, 0, 0], [1, 0, 0, 0], [0, 0, 0], wall)
    p = tile_projections(wall, frame, np.full(4, 0.5), np.full(4, 80.0), reversed_z=True)[0]
    ndc = homog(p, np.array([[-0.1, -0.1, -0.5], [-10, -10, -80.0]]))
    np.testing.assert_allclose(ndc[:, 2], [1.0, 0.0], atol=1e-12)


# ------------------------------------------------------------------ shadows and mirrors


def lit_scene():
    """A ground slab, a pillar standing on it, a box floating above, a sphere to the side."""
    s = trimesh.Scene()
    def add(name, mesh, at):
        m = np.eye(4)
        m[:3, 3] = at
        s.add_geometry(mesh, node_name=name, geom_name=name, transform=m)
    add("ground", trimesh.creation.box(extents=[40, 0.5, 40]), [0, -0.25, 0])
    add("pillar", trimesh.creation.box(extents=[1, 6, 1]), [2, 3, -3])
    add("floater", trimesh.creation.box(extents=[2, 2, 2]), [-4, 8, -2])
    add("ball", trimesh.creation.icosphere(subdivisions=2, radius=1.5), [6, 1.5, 4])
    # out of the camera's view, close to the light, shading ground the camera sees
    add("cloud", trimesh.creation.box(extents=[3, 1, 3]), [8, 21, 3])
    return Scene.from_trimesh(s, hierarchy="file")


def boxes(spec: dict) -> trimesh.Scene:
    """A scene of boxes, ``name: (extents, centre)``, each its own node and mesh."""
    s = trimesh.Scene()
    for name, (extents, at) in spec.items():
        m = trimesh.creation.box(extents=extents)
        m.apply_translation(at)
        s.add_geometry(m, node_name=name, geom_name=name)
    return s


WALL = {"cols": 3, "rows": 2, "tile_size": [0.6, 0.34], "gap": [0.01, 0.01], "distance": 1.0}
FRAME = {"position": [0, 12, 30], "orientation": [0.9762960, -0.2164396, 0, 0]}


def fitted(scene, raw_settings, frame=FRAME):
    scene.settings = raw_settings
    wall = Wall.from_dict(WALL)
    session = Session(scene, wall, fit=FitOptions())
    return session, session.frame(frame)


def test_nothing_declared_nothing_computed(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("fitting code ran for a scene that declares nothing")
    monkeypatch.setattr(fitmod, "shadow_sets", boom)
    monkeypatch.setattr(fitmod.MirrorSight, "of", boom)
    _, result = fitted(lit_scene(), {})
    assert all(set(t) == {"view", "projection", "near", "far"} for t in result.fits)


def test_shadow_frustum_holds_every_receiver_and_every_occluder():
    scene = lit_scene()
    light = [12.0, 25.0, 8.0]
    session, result = fitted(scene, {"lights": [{"name": "sun", "position": light}]})
    names = scene.names
    rng = np.random.default_rng(0)
    checked = 0
    for t, tile in enumerate(result.fits):
        shown = result.visibility.tile_leaves(t)
        if not len(shown):
            assert "shadows" not in tile
            continue
        (shadow,) = tile["shadows"]
        m = np.asarray(shadow["projection"]) @ np.asarray(shadow["view"])
        assert np.linalg.det(np.asarray(shadow["view"])[:3, :3]) == pytest.approx(1, abs=1e-9)
        casters = set(shadow["casters"])
        for leaf in shown:  # no receiver is clipped by the light's frustum
            ndc = homog(m, scene.leaf_vertices(leaf))
            assert (np.abs(ndc) <= 1 + 1e-9).all(), names[leaf]
        # Every leaf a light ray to a receiver point crosses must be a caster.
        samples = np.concatenate([scene.leaf_vertices(l) for l in shown])
        samples = samples[rng.choice(len(samples), min(200, len(samples)), replace=False)]
        for leaf in scene.leaves:
            tris = scene.leaf_triangles(leaf)
            for p in samples:
                if _segment_hits(light, p, tris):
                    assert leaf in casters, (names[leaf], t)
                    checked += 1
                    break
        # casters lie within the depth range (nothing between light and near plane is lost)
        for leaf in casters:
            z = homog(m, scene.leaf_vertices(leaf))[:, 2]
            assert z.min() >= -1 - 1e-9
    assert checked > 0  # the test saw occluders
    cloud = scene.index["cloud"]
    assert not any(cloud in result.visibility.tile_leaves(t) for t in range(6))
    assert any(cloud in t["shadows"][0]["casters"] for t in result.fits if "shadows" in t)


def _segment_hits(a, b, tris, eps=1e-9):
    """Whether segment a-b crosses any triangle (Moller-Trumbore, vectorized), excluding the
    endpoint b itself (a receiver does not shade its own sample point)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = b - a
    v0, v1, v2 = tris[:, 0], tris[:, 1], tris[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > eps
    inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
    s = a - v0
    u = np.einsum("ij,ij->i", s, h) * inv
    q = np.cross(s, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    return bool((ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6) & (t < 1 - 1e-6)).any())


def test_light_surrounded_by_what_a_tile_shows_gets_a_cube_map():
    scene = lit_scene()
    session, result = fitted(scene, {"lights": [{"name": "lamp", "position": [0, 0.5, 0]}]},
                             frame={"position": [0, 30, 0.01],
                                    "orientation": [0.7071068, -0.7071068, 0, 0]})
    cubes = [s for t in result.fits for s in t.get("shadows", []) if s.get("cube")]
    assert cubes, "the lamp on the ground under the camera needs a cube map"
    for cube in cubes:
        assert len(cube["views"]) == 6
        dirs = [-np.asarray(v)[2, :3] for v in cube["views"]]
        np.testing.assert_allclose(np.abs(np.sum(dirs, axis=0)), 0, atol=1e-12)
        assert scene.index["ground"] in cube["casters"]


def test_a_light_at_the_centre_of_a_receivers_box_gets_a_cube_map():
    """A bulb at the exact centre of its lamp housing's box, a floor under it, both in view:
    the housing's corners lie all around the light, so the tile gets a cube map listing both.
    The frustum fit divided by the housing's distance from the light, zero: every frame of
    such a scene failed (ZeroDivisionError)."""
    s = boxes({"housing": ([1, 1, 1], [0, 0.5, -5]), "floor": ([8, 0.1, 8], [0, -1, -6])})
    scene = Scene.from_trimesh(s, hierarchy="file",
                               settings={"lights": [{"name": "bulb", "position": [0, 0.5, -5]}]})
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [1.6, 0.9], "distance": 1.0,
                           "resolution": [64, 36]})
    frame = {"position": [0, 2, 2], "orientation": [0.9848078, -0.1736482, 0, 0]}
    result = Session(scene, wall, fit=FitOptions()).frame(frame)
    assert sorted(result.visibility.names(0)) == ["floor", "housing"]
    (shadow,) = result.fits[0]["shadows"]
    assert shadow["cube"] and 0 < shadow["near"] < shadow["far"]
    assert np.isfinite(np.asarray(shadow["projection"])).all()
    assert set(shadow["casters"]) == {scene.index["housing"], scene.index["floor"]}


def test_spot_light_behind_everything_casts_nothing():
    scene = lit_scene()
    _, result = fitted(scene, {"lights": [{"name": "spot", "type": "spot", "position": [0, 50, 0],
                                           "direction": [0, 1, 0], "angle": 20}]})
    assert not any("shadows" in t for t in result.fits)


def test_a_spot_lights_a_floor_passing_under_it_though_no_corner_is_in_its_cone():
    """A spot at the origin along +x (30 degrees) over a floor running from behind it to 5 m
    ahead: no corner of the floor's box lies in the cone and its centre lies behind the light,
    but the cone lights the floor from 1.7 m on, and a box hanging there shades it. A tile that
    sees only that floor gets the spot's shadow with the box among its casters (it got none:
    its receivers were judged unlit)."""
    s = trimesh.Scene()
    s.add_geometry(trimesh.Trimesh([[-20, -1, -10], [5, -1, -10], [5, -1, 10], [-20, -1, 10]],
                                   [[0, 2, 1], [0, 3, 2]], process=False),
                   node_name="floor", geom_name="floor")
    hanging = trimesh.creation.box(extents=[0.3, 0.3, 0.3])
    hanging.apply_translation([3.0, -0.5, 0.0])
    s.add_geometry(hanging, node_name="hanging", geom_name="hanging")
    scene = Scene.from_trimesh(s, hierarchy="file", clusters=None)  # the floor one box
    scene.settings = {"lights": [{"name": "spot", "type": "spot", "position": [0, 0, 0],
                                  "direction": [1, 0, 0], "angle": 30}]}
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [0.8, 0.6], "distance": 1.0,
                           "resolution": [120, 90]})
    frame = {"position": [4.5, -0.2, 0.0],  # looking straight down at the shaded floor
             "orientation": [np.cos(-np.pi / 4), np.sin(-np.pi / 4), 0, 0]}
    result = Session(scene, wall, fit=FitOptions()).frame(frame)
    assert result.visibility.names(0) == ["floor"]
    (shadow,) = result.fits[0]["shadows"]
    assert scene.index["hanging"] in shadow["casters"]


@given(st.integers(0, 2**32 - 1))
@hsettings(max_examples=200, deadline=None)
def test_a_sphere_meeting_a_cone_is_never_judged_apart(seed):
    """``lowilie._meets_cone`` against sampled points: a sphere with any point in the cone
    (its centre, points on its surface and inside it) meets it."""
    from wallcull.lowilie import _meets_cone

    rng = np.random.default_rng(seed)
    apex = rng.normal(size=3) * 5
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    cos = np.cos(np.radians(rng.uniform(1, 89)))
    center = apex + rng.normal(size=3) * rng.choice([0.5, 5, 50])
    radius = rng.choice([0.01, 1, 10, 100]) * rng.uniform()
    points = rng.normal(size=(4000, 3))
    points *= (radius * rng.uniform(size=(4000, 1)) ** (1 / 3)
               / np.linalg.norm(points, axis=1, keepdims=True))
    rel = np.vstack([center, center + points]) - apex
    inside = rel @ axis >= np.linalg.norm(rel, axis=1) * cos
    if inside.any():
        assert _meets_cone(apex, axis, cos, center, radius)


MIRROR = {"name": "pond", "point": [0, 0.01, 0], "normal": [0, 1, 0],
          "polygon": [[-10, 0.01, -10], [10, 0.01, -10], [10, 0.01, 10], [-10, 0.01, 10]]}


ROUND = {**MIRROR, "polygon": [[10 * np.cos(a), 0.01, 10 * np.sin(a)]
                               for a in np.linspace(0, 2 * np.pi, 300, endpoint=False)]}


@pytest.mark.parametrize("spec", [MIRROR, ROUND], ids=["square", "round"])
def test_mirror_lists_everything_seen_in_it(spec):
    """Oracle: reflect every leaf's triangles through the mirror, clip them against the tile
    frustum, the far side of the mirror and the pyramid through its outline; whatever survives
    must be in the tile's mirror list. A round mirror of 300 points (its pyramid past the 63
    planes a view holds) was refused in every frame that saw it; the planes past them are now
    left out."""
    scene = lit_scene()
    _, result = fitted(scene, {"mirrors": [spec]})
    mirror = parse({"mirrors": [spec]}).mirrors[0]
    refl = mirror.reflection
    eye = np.array(FRAME["position"])
    from wallcull.fit import _pyramid
    outline = _pyramid([eye], mirror.polygon)  # seen from the real eye
    beyond = -mirror.plane
    seen_any = 0
    for t, tile in enumerate(result.fits):
        (planes,) = tile_frusta(WALL, FRAME, t, 1e-7 * 50)
        # to world, for the clipping: the oracle's planes are in display space
        from wallcull.oracle import to_display
        listed = set()
        for entry in tile.get("mirrors", []):
            assert entry["front_face"] == "cw"
            assert np.linalg.det(np.asarray(entry["view"])[:3, :3]) == pytest.approx(-1)
            listed |= set(entry["visible"])
        for leaf in scene.leaves:
            tris = scene.leaf_triangles(leaf).reshape(-1, 3)
            mirrored = (tris @ refl[:3, :3].T + refl[:3, 3])
            keep = np.concatenate([outline, beyond[None]])
            world_clip = clip_triangles(mirrored.reshape(-1, 3, 3), keep)
            disp = to_display(FRAME, mirrored).reshape(-1, 3, 3)
            if (world_clip & clip_triangles(disp, planes)).any():
                assert leaf in listed, (scene.names[leaf], t)
                seen_any += 1
    assert seen_any > 0


def _seen_through(eye, polygon):
    """The oracle's pyramid: planes through ``eye`` and each edge of the convex ``polygon``,
    facing its inside (no plane is left out)."""
    centre = polygon.mean(axis=0)
    planes = []
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0)):
        n = np.cross(a - eye, b - a)
        n /= np.linalg.norm(n)
        plane = np.append(n, -n @ a)
        planes.append(plane if plane[:3] @ centre + plane[3] >= 0 else -plane)
    return np.array(planes)


def test_a_stereo_mirror_lists_what_either_eye_sees_through_its_outline():
    """Oracle: for each eye, each leaf's triangles reflected through the mirror and clipped
    against that eye's tile frustum, the far side of the mirror and the pyramid from that eye
    through the mirror's outline: whatever survives must be in the tile's mirror list. A
    stereo frame's mirror lists were culled by the mirror's plane alone; with the outline they
    are shorter, here by more than half."""
    from wallcull.oracle import _rotation, eyes_of, to_display

    s = trimesh.Scene()
    for i in range(-7, 8):
        for k in range(-7, 8):
            m = np.eye(4)
            m[:3, 3] = [2.0 * i, 0.8 + 0.3 * ((i * k) % 5), 2.0 * k]
            s.add_geometry(trimesh.creation.box(extents=[0.5, 0.5, 0.5]), node_name=f"b{i}_{k}",
                           geom_name="box", transform=m)
    scene = Scene.from_trimesh(s, hierarchy="file")
    pond = {"name": "pond", "point": [0, 0.01, 0], "normal": [0, 1, 0],
            "polygon": [[-3, 0.01, -4], [4, 0.01, -3], [3, 0.01, 4], [-4, 0.01, 2]]}
    wall = {"cols": 3, "rows": 2, "tile_size": [0.6, 0.4], "gap": [0.01, 0.01],
            "distance": 1.0}
    frame = {"position": [0, 9, 16], "orientation": [0.9396926, -0.3420201, 0, 0],
             "stereo": {"ipd": 1.0}}  # the widest the server takes: eyes far apart

    def listed(spec):
        scene.settings = {"mirrors": [spec]}
        result = Session(scene, Wall.from_dict(wall), fit=FitOptions()).frame(frame)
        return [set().union(*(e["visible"] for e in result.fits[t].get("mirrors", [])))
                for t in range(6)]

    lists = listed(pond)
    mirror = parse({"mirrors": [pond]}).mirrors[0]
    refl, polygon = mirror.reflection, mirror.polygon
    rot, position = _rotation(frame["orientation"]), np.array(frame["position"])
    tris = [scene.leaf_triangles(leaf).reshape(-1, 3, 3) for leaf in scene.leaves]
    owner = np.repeat(scene.leaves, [len(x) for x in tris])
    images = to_display(frame, np.concatenate(tris).reshape(-1, 3) @ refl[:3, :3].T
                        + refl[:3, 3]).reshape(-1, 3, 3)
    seen = 0
    for t in range(6):
        for eye, planes in zip(eyes_of(frame), tile_frusta(wall, frame, t, 1e-9)):
            world = np.concatenate([_seen_through(rot.apply(eye) + position, polygon),
                                    -mirror.plane[None]])  # the images lie behind the mirror
            # to display space: n . (R x + t) + d
            moved = np.column_stack([rot.inv().apply(world[:, :3]), world[:, :3] @ position
                                     + world[:, 3]])
            survive = clip_triangles(images, np.vstack([planes, moved]))
            for leaf in set(owner[survive].tolist()):
                assert leaf in lists[t], (scene.names[leaf], t)
                seen += 1
    assert seen > 20
    by_plane = listed({k: v for k, v in pond.items() if k != "polygon"})
    assert all(a <= b for a, b in zip(lists, by_plane))
    assert 2 * sum(map(len, lists)) < sum(map(len, by_plane))


def test_mirror_oblique_near_plane_is_the_mirror():
    scene = lit_scene()
    _, result = fitted(scene, {"mirrors": [MIRROR]})
    entries = [e for t in result.fits for e in t.get("mirrors", [])]
    assert entries
    for e in entries:
        m = np.asarray(e["projection"]) @ np.asarray(e["view"])
        # points on the mirror plane map to the near plane (NDC z = -1) ...
        on = np.array([[x, 0.01, z] for x in (-3.0, 0.0, 4.0) for z in (-5.0, 1.0)])
        assert np.allclose(homog(m, on)[:, 2], -1, atol=1e-6)
        # ... and points behind the mirror land in front of it after reflection: clipped
        under = np.array([[0.0, -2.0, 0.0], [3.0, -0.5, -2.0]])
        assert (homog(m, under)[:, 2] < -1).all()


@pytest.mark.parametrize("stereo", [None, 0.064])
def test_threads_change_no_bit_of_a_frames_fits(monkeypatch, stereo):
    """The shadow passes split among threads and the mirrors culled beside them give every
    tile the same fits, bit for bit, as one thread doing it all in turn."""
    frame = {**FRAME, **({"stereo": {"ipd": stereo}} if stereo else {})}
    lit = {"lights": [{"name": "sun", "position": [12.0, 25.0, 8.0]},
                      {"name": "lamp", "position": [0, 0.5, 0]}],
           "mirrors": [MIRROR, {"name": "wall", "point": [0, 0, -15], "normal": [0, 0, 1]}]}
    results = []
    for threads in ("1", "2"):
        monkeypatch.setenv("WALLCULL_THREADS", threads)
        _, result = fitted(lit_scene(), lit, frame)
        results.append([result.fits[t] for t in range(len(result.fits))])
    assert any("mirrors" in t and "shadows" in t for t in results[0])
    assert results[0] == results[1]


def test_lights_fitted_together_as_each_alone(monkeypatch):
    """All lights' fits and caster culls run as one pass each (split among threads across the
    lights' boundaries): every tile gets, bit for bit, what each light fitted alone gives."""
    monkeypatch.setenv("WALLCULL_THREADS", "2")
    scene = Scene.from_trimesh(random_scene(7, leaves=120))
    wall = Wall.from_dict({"cols": 4, "rows": 3, "tile_size": [0.5, 0.4], "distance": 1.0,
                           "far": 200.0})
    centre = scene.leaf_points[0].mean(0)
    frame = Frame.make(centre + [0, 4, 30], [1, 0, 0, 0], [0, 0, 0], wall)
    lights = [{"name": "sun", "position": (centre + [40, 60, 30]).tolist(),
               "resolution": [1024, 512]},
              {"name": "lamp", "position": centre.tolist()},  # among the receivers: cube maps
              {"name": "spot", "type": "spot", "position": (centre + [-15, 20, 10]).tolist(),
               "direction": [0.5, -1.0, -0.3], "angle": 25}]

    def shadows(declared):
        session = Session(scene, wall, fit=FitOptions(), settings={"lights": declared})
        fits = session.frame(frame).fits
        return [{s["light"]: s for s in fits[t].get("shadows", [])} for t in range(wall.tiles)]

    together = shadows(lights)
    for light in lights:
        alone = shadows([light])
        for t in range(wall.tiles):
            assert together[t].get(light["name"]) == alone[t].get(light["name"])
    kinds = {"cube" if s.get("cube") else "frustum" for tile in together for s in tile.values()}
    assert kinds == {"cube", "frustum"}
    casters = [{tuple(s["casters"]) for s in tile.values()} for tile in together]
    assert any(len(c) == 3 for c in casters)  # each light's own casters


def test_casters_that_overflow_their_room_are_culled_again(monkeypatch):
    """A part of the shadow pass whose casters do not fit in its output runs again with twice
    the room, until they do: the same fits as with room enough from the start."""
    from wallcull.cull import _Buffers

    lit = {"lights": [{"name": "sun", "position": [12.0, 25.0, 8.0]},
                      {"name": "lamp", "position": [0, 0.5, 0]}]}
    _, roomy = fitted(lit_scene(), lit)
    monkeypatch.setattr(fitmod, "CASTERS", 1)
    monkeypatch.setenv("WALLCULL_THREADS", "1")  # one part: the buffers seeded below
    scene = lit_scene()
    scene.settings = lit
    wall = Wall.from_dict(WALL)
    session = Session(scene, wall, fit=FitOptions())
    tight = _Buffers()
    tight.arrays.update(out_n=np.empty(1, np.int64), out_t=np.empty(1, np.int64))
    session.state.__dict__["_shadow_buffers"] = [tight]
    result = session.frame(FRAME)
    assert len(tight.arrays["out_n"]) > 1  # it did overflow, and grew
    fits = [result.fits[t] for t in range(wall.tiles)]
    assert fits == [roomy.fits[t] for t in range(wall.tiles)]
    assert sum(len(s["casters"]) for tile in fits for s in tile.get("shadows", [])) > 0


def test_eye_behind_mirror_sees_nothing_in_it():
    scene = lit_scene()
    below = {"position": [0, -5, 30], "orientation": [1, 0, 0, 0]}
    _, result = fitted(scene, {"mirrors": [MIRROR]}, frame=below)
    assert not any("mirrors" in t for t in result.fits)


def test_an_eye_sees_a_mirror_by_one_rule_however_near_it_stands():
    """An eye just before an unbounded side mirror, which fills the right half of the view,
    the wall's near distance 0.1: farther than a millionth of it (1e-7 m) the tiles looking at
    the mirror show it; nearer, none does (an oblique near plane that near the eye leaves the
    depth buffer nothing to resolve) and the mirror is not culled for at all. Between 3e-9 m
    and 1e-7 m the mirror was culled for every tile, its lists made, and then every tile's
    oblique near plane refused: the frame carried a mirror no tile showed."""
    s = trimesh.Scene()
    for name, (extents, at) in {"floor": ([12, 0.2, 12], [0, -1.1, -6]),
                                "cube": ([1, 1, 1], [0.5, 0, -5]),
                                "side": ([1, 1, 1], [-4, 0.5, -2])}.items():
        m = trimesh.creation.box(extents=extents)
        m.apply_translation(at)
        s.add_geometry(m, node_name=name, geom_name=name)
    scene = Scene.from_trimesh(s, hierarchy="file", settings={
        "mirrors": [{"name": "m", "point": [3, 0, 0], "normal": [-1, 0, 0]}]})
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [0.8, 0.45], "distance": 1.0,
                           "near": 0.1, "far": 1000})
    session = Session(scene, wall, fit=FitOptions())
    for away in (3e-9, 3e-8, 9e-8, 1.1e-7, 3e-7, 1e-6):
        fits = session.frame({"position": [3 - away, 0.5, 0], "orientation": [1, 0, 0, 0]}).fits
        showing = [t for t in range(wall.tiles) if "mirrors" in fits[t]]
        assert showing == ([1, 3] if away > 1e-7 else []), away  # the right-hand tiles
        assert len(fits.mirrors) == (away > 1e-7), away


def test_a_mirror_between_the_eyes_is_seen_by_the_eye_before_it():
    """A mirror whose plane passes between a stereo frame's eyes (the centre eye 4 mm behind
    it) shows the right eye a reflection: that eye's record carries the mirror, with its own
    oblique near plane at the mirror, and the tile the leaves seen in it (seen nearly edge-on,
    the mirror shows a thin sliver beside its plane, out to the box). No record did, the
    tile's showing being decided by the centre eye alone."""
    s = boxes({"reflected": ([1.0, 1.0, 1.0], [0.6, 0.0, -20.0]),
               "floor": ([6, 0.1, 10], [0, -1.0, -5])})
    settings = {"mirrors": [{"name": "side", "point": [0.004, 0, -3], "normal": [1, 0, 0],
                             "polygon": [[0.004, -1, -1.5], [0.004, -1, -8], [0.004, 1, -8],
                                         [0.004, 1, -1.5]]}]}
    scene = Scene.from_trimesh(s, hierarchy="file", settings=settings)
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [1.6, 0.9], "distance": 1.0})
    frame = Frame.from_dict({"position": [0, 0, 0], "orientation": [1, 0, 0, 0],
                             "stereo": {"ipd": 0.064}}, wall)
    record = Session(scene, wall, fit=FitOptions(depth="wall")).frame(frame).fits[0]
    assert "mirrors" not in record["left"]
    (right,) = record["right"]["mirrors"]
    (entry,) = record["mirrors"]
    assert right["mirror"] == entry["mirror"] == "side"
    assert scene.names.index("reflected") in entry["visible"]
    # the right eye's oblique near plane is the mirror: its points land on NDC depth -1
    on_mirror = np.array([[0.004, 0.3, -3.0], [0.004, -0.5, -6.0]])  # world = display here
    eye_space = homog(np.asarray(right["view"]), on_mirror)  # the reflection fixes the plane
    np.testing.assert_allclose(homog(np.asarray(right["projection"]), eye_space)[:, 2], -1,
                               atol=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_caster_cull_lists_what_the_oh_kernel_its_leaves_and_depths_give(seed):
    """The shadow pass's caster cull (``fit._cull_casters``: each region's leaves and nearest
    caster worked out as each node is listed) gives what the ``oh`` kernel's pairs, expanded
    to leaves (``cull._expand``), give: the same leaves in the same order, and -1 when its
    output cannot hold them. A frustum's region gets the least depth along its axis of its
    listed leaves' triangles clipped to it (``oracle.clipped_depths``), at or past the least
    its listed bounds reach (``cull._depth_ranges``), NaN for a region that lists nothing.
    A cube map's region gets instead a lower bound of its casters' least Chebyshev distance
    from the light, between their leaves' boxes' and their vertices'."""
    from wallcull.cull import _depth_ranges, _expand, _oh, packed, stack_depth
    from wallcull.projection import frustum, look_at

    rng = np.random.default_rng(seed)
    scene = Scene.from_trimesh(random_scene(seed, leaves=40, big=0.3), hierarchy="file")
    state = Session(scene, Wall.from_dict(WALL)).state
    box = packed(state)
    reach = box[0, 3] + np.linalg.norm(box[0, 4:13].reshape(3, 3), axis=1).sum()
    away = rng.normal(size=3)
    light = box[0, :3] + away / np.linalg.norm(away) * (2 * reach + 1)  # outside the scene
    count = 9
    kind = np.full(count, fitmod.FRUSTUM)
    kind[rng.integers(1, count)] = fitmod.CUBE  # the cube around the light
    pv, far = np.zeros((count, 4, 4)), rng.uniform(1, 4 * reach + 2, count)
    forward = rng.normal(size=(count, 3))  # (a cube map's: any)
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    for k in range(count):  # region 0 looks away from the scene: it lists nothing
        target = box[rng.integers(len(box)), :3] + rng.normal(size=3) if k \
            else 2 * light - box[0, :3]
        w, h = rng.uniform(0.05, 1.5, 2) if k else (0.1, 0.1)
        view = look_at(light, target)
        pv[k] = frustum(-w, w, -h, h, 0.1, far[k]) @ view
        if kind[k] == fitmod.FRUSTUM:
            forward[k] = -view[2, :3]
    lit = np.arange(count)
    planes, regions, sizes = fitmod._caster_regions(pv, kind, lit, far, light)
    stack = stack_depth(state)
    leaf_start, leaf_count = scene.leaf_range
    tree = (scene.child_start, scene.leaf_child_count, scene.children)
    lists = (leaf_start, leaf_count, scene.leaves, scene.cluster_leaf)

    root = np.zeros(1, np.int64)
    out_n, out_t = np.empty(1 << 16, np.int64), np.empty(1 << 16, np.int64)
    pairs, _ = _oh(root, root, *tree, box, planes, regions, sizes, (np.int64(1) << sizes) - 1,
                   np.zeros(count, np.int64), np.empty(stack, np.int64),
                   np.empty(stack, np.int64), out_n, out_t)
    culled = np.concatenate([[0], np.cumsum(np.bincount(out_t[:pairs], minlength=count))])
    first, leaves = _expand(culled, out_n[:pairs], *lists)
    lo, _ = _depth_ranges(culled, out_n[:pairs], box, forward, light[None], np.nan, np.nan)

    cubes = kind == fitmod.CUBE
    faces = fitmod._faces(state)
    work = (*fitmod._region_shapes(planes, regions, sizes, forward, cubes, light),
            np.empty(stack), np.empty(len(box), np.int64), np.empty(len(box)),
            np.empty((2, fitmod._POLYGON, 3)))
    out, nearest, starts = np.empty(1 << 16, np.int64), np.where(cubes, np.inf, np.nan), \
        np.zeros(count + 1, np.int64)
    written = fitmod._cull_casters(*tree, box, planes, regions, sizes, forward, cubes, faces,
                                   work, light, *lists, np.empty(stack, np.int64),
                                   np.empty(stack, np.int64), out, nearest, starts)
    assert written == len(leaves) > 0
    assert np.array_equal(out[:written], leaves) and np.array_equal(starts, first)
    assert np.isnan(nearest[0]) and np.isnan(lo[0])  # none behind the light
    for q in np.flatnonzero(~cubes):
        listed = leaves[first[q]:first[q + 1]]
        tris = np.concatenate([np.zeros((0, 3, 3))]
                              + [scene.leaf_triangles(leaf) for leaf in listed])
        least = clipped_depths(tris, planes[regions[q, :sizes[q]]], forward[q], light).min() \
            if len(tris) else np.inf
        if least == np.inf:
            assert np.isnan(nearest[q])
        else:
            assert lo[q] <= nearest[q] == pytest.approx(least, rel=1e-12, abs=1e-12)
    assert not np.isnan(nearest[~cubes]).all()
    (q,) = np.flatnonzero(cubes)
    listed = leaves[first[q]:first[q + 1]]
    if len(listed):
        boxes = (np.abs(box[listed, :3] - light)
                 - np.abs(box[listed, 4:13].reshape(-1, 3, 3)).sum(axis=1)
                 - box[listed, 3:4]).max(axis=1).min()
        points = min(np.abs(scene.leaf_vertices(leaf) - light).max(axis=1).min()
                     for leaf in listed)
        assert boxes <= nearest[q] <= points + 1e-12 * np.abs(light).max()
    else:
        assert nearest[q] == np.inf
    assert fitmod._cull_casters(*tree, box, planes, regions, sizes, forward, cubes, faces,
                                work, light, *lists, np.empty(stack, np.int64),
                                np.empty(stack, np.int64), out[:written - 1], nearest,
                                starts) == -1


@pytest.mark.parametrize("seed", range(3))
def test_a_triangles_chebyshev_distance_is_its_samples_least(seed):
    """``fit._triangle_chebyshev`` (how near a cube map's near plane may come to a caster's
    triangle: a face's near plane bounds a point's largest coordinate from the light) against
    dense samples of each triangle: never above their least largest coordinate, and below it
    by no more than the samples' spacing; the same for triangles with coincident or collinear
    corners (no division by zero), and for a triangle in a plane of the world's axes that
    faces the light, the plane's distance."""
    rng = np.random.default_rng(seed)
    g = np.linspace(0, 1, 121)
    u, v = np.meshgrid(g, g)
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    for k in range(300):
        scale = 10.0 ** rng.uniform(-3, 3)
        t = rng.normal(size=(3, 3)) * scale + rng.normal(size=3) * scale * rng.uniform(0, 3)
        if k % 10 == 1:
            t[1] = t[0]  # coincident corners
        elif k % 10 == 2:
            t[2] = t[0] + 0.3 * (t[1] - t[0])  # collinear
        elif k % 10 == 3:  # in a plane x = const
            t[:, 0] = t[0, 0]
        samples = t[0] + u[:, None] * (t[1] - t[0]) + v[:, None] * (t[2] - t[0])
        least = np.abs(samples).max(axis=1).min()
        step = np.abs(t - t[0]).max() / 120 * 2  # the samples' spacing, at most
        got = fitmod._triangle_chebyshev(*t.ravel())
        assert least - step <= max(got, 0.0) <= least * (1 + 1e-12), (k, got, least)
        if k % 10 == 3 and (np.abs(samples[:, 1:]).max(axis=1) <= abs(t[0, 0])).any():
            assert got == pytest.approx(abs(t[0, 0]), rel=1e-12)  # facing the light


def _frustum_regions(rng, light, count, far=50.0):
    """``count`` random frustum caster regions from ``light`` (off-axis, some skewed, as a
    Low-Ilie projection is): ``(planes, regions, sizes, forward, rel, corners, spread)``."""
    from wallcull.projection import frustum, look_at

    pv, forward = np.zeros((count, 4, 4)), np.zeros((count, 3))
    for k in range(count):
        view = look_at(light, light + rng.normal(size=3), rng.normal(size=3))
        w, h = rng.uniform(0.05, 2.5, 2)
        x, y = rng.uniform(-1, 1, 2) * (w, h)
        proj = frustum(x - w, x + w, y - h, y + h, 0.1, far)
        if k % 2:
            proj[0, 1] = rng.normal() * 0.5  # skew
        pv[k] = proj @ view
        forward[k] = -view[2, :3]
    kind, lit = np.full(count, fitmod.FRUSTUM), np.arange(count)
    planes, regions, sizes = fitmod._caster_regions(pv, kind, lit, np.full(count, far), light)
    shapes = fitmod._region_shapes(planes, regions, sizes, forward, np.zeros(count, bool),
                                   light)
    return (planes, regions, sizes, forward, *shapes)


@pytest.mark.parametrize("seed", range(3))
def test_a_triangles_clipped_depth_is_its_clipped_polygons_least(seed):
    """``fit._clipped_below`` (how near a frustum's near plane may come to a caster's
    triangle) against the least depth of the triangle clipped to the region by numpy
    (``oracle.clipped_depths``, Sutherland-Hodgman) and against dense samples of it: random
    triangles around the light, wholly within a region, crossing its side or far planes,
    reaching behind the light's plane outside the frustum, or wholly outside one plane. Equal
    to the clipped polygon's least depth to rounding, never above the least of the samples
    within the region, the least given when that is nearer, and nothing for a triangle that
    keeps no part."""
    rng = np.random.default_rng(seed)
    light = rng.normal(size=3) * 100
    planes, regions, sizes, forward, rel, corners, spread = _frustum_regions(rng, light, 6)
    assert (spread > 0).all()
    poly = np.empty((2, fitmod._POLYGON, 3))
    g = np.linspace(0, 1, 81)
    u, v = np.meshgrid(g, g)
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    seen = {"inside": 0, "cut": 0, "none": 0, "behind": 0}
    for k in range(600):
        q = k % 6
        ids = regions[q, :sizes[q]]
        scale = 10.0 ** rng.uniform(-1, 1.5)
        if k % 4 == 0:  # within the region: corners along random rays inside it
            w = rng.dirichlet(np.ones(4), size=3)
            t = light + (w @ corners[q]) * rng.uniform(0.1, 40, (3, 1))
        elif k % 4 == 1:  # across the light's plane, beside the frustum
            side = np.cross(forward[q], rng.normal(size=3))
            t = light + side / np.linalg.norm(side) * rng.uniform(1, 3) * scale \
                + np.outer([-1, 0.5, 2], forward[q]) * scale + rng.normal(size=(3, 3)) * scale
        else:
            t = light + forward[q] * rng.uniform(-5, 60) + rng.normal(size=(3, 3)) * scale
        ref = clipped_depths(t[None], planes[ids], forward[q], light)[0]
        got = fitmod._clipped_below(*(t - light).ravel(), *forward[q], rel, regions[q],
                                    sizes[q], np.inf, poly)
        dist = t @ planes[ids, :3].T + planes[ids, 3]
        if not np.isfinite(ref):
            assert got == np.inf, (k, got)
            seen["none"] += 1
            continue
        span = np.abs(t - light).max() + 1
        assert got == pytest.approx(ref, abs=1e-12 * span), (k, got, ref)
        seen["inside" if (dist >= 0).all() else "cut"] += 1
        seen["behind"] += bool(((t - light) @ forward[q] < 0).any())
        samples = t[0] + u[:, None] * (t[1] - t[0]) + v[:, None] * (t[2] - t[0])
        within = (samples @ planes[ids, :3].T + planes[ids, 3] >= 0).all(axis=1)
        if within.any():
            assert got <= ((samples[within] - light) @ forward[q]).min() + 1e-12 * span
        assert fitmod._clipped_below(*(t - light).ravel(), *forward[q], rel, regions[q],
                                     sizes[q], got - 1, poly) == got - 1
        assert fitmod._clipped_below(*(t - light).ravel(), *forward[q], rel, regions[q],
                                     sizes[q], got + 1, poly) == got
    assert min(seen.values()) >= 20, seen


def _packed_boxes(rng, count, around, scale):
    """``count`` random bound records (``cull.pack``'s layout: centre, ball, three half-axis
    vectors, sphere) of oriented boxes near ``around``, some swept by a ball, some flat."""
    from scipy.spatial.transform import Rotation

    box = np.zeros((count, 14))
    box[:, :3] = around + rng.normal(size=(count, 3)) * scale
    half = rng.uniform(0.01, 1, (count, 3)) * scale * rng.uniform(0.1, 3, (count, 1))
    half[::7, 2] = 0  # flat
    axes = Rotation.random(count, random_state=rng).as_matrix().transpose(0, 2, 1) \
        * half[:, :, None]
    axes[::3] = np.eye(3) * half[::3, :, None]  # along the world's axes
    box[:, 4:13] = axes.reshape(count, 9)
    box[1::4, 3] = rng.uniform(0, 0.3, len(box[1::4])) * scale
    box[:, 13] = np.linalg.norm(half, axis=1) + box[:, 3]
    return box, axes


@pytest.mark.parametrize("seed", range(3))
def test_a_boxs_depth_floor_in_a_region_is_below_its_points_there(seed):
    """``fit._region_floor`` (a node is opened for its triangles only where it comes below
    the nearest so far) never lies above the depth of a point of the box within the region
    (dense samples of each random box, swept or flat, within a random frustum region), and
    for a tall slab beside a frustum, reaching past the light's plane, it comes far above the
    box's depth less its reach (which is below zero): its part within the region lies where
    the region has grown to meet it."""
    rng = np.random.default_rng(seed)
    light = rng.normal(size=3) * 50
    planes, regions, sizes, forward, rel, corners, spread = _frustum_regions(rng, light, 6)
    box, axes = _packed_boxes(rng, 400, light, 8.0)
    unit = rng.uniform(-1, 1, (4000, 3))
    ball = rng.normal(size=(4000, 3))
    ball *= (rng.uniform(0, 1, (4000, 1)) ** (1 / 3)) / np.linalg.norm(ball, axis=1)[:, None]
    met = 0
    for i in range(len(box)):
        points = box[i, :3] + unit @ axes[i] + ball * box[i, 3]
        for q in range(6):
            ids = regions[q, :sizes[q]]
            floor = fitmod._region_floor(box, i, light, *forward[q], corners, q, spread[q])
            depth, r = fitmod._along(box, i, *forward[q], *light)
            assert floor >= depth - r
            within = (points @ planes[ids, :3].T + planes[ids, 3] >= 0).all(axis=1)
            if within.any():
                met += 1
                least = ((points[within] - light) @ forward[q]).min()
                assert floor <= least + 1e-9 * (1 + abs(least)), (i, q, floor, least)
    assert met > 100
    # a wide thin slab beside region 0, from behind the light's plane to 30 deep, meeting the
    # region only about 20 deep: the floor is within a hundredth of its points' there
    q, f = 0, forward[0]
    side = corners[0, 0] - f  # toward the left and bottom corner (at right angles to f)
    reach = np.linalg.norm(side)
    side /= reach
    slab = np.zeros((1, 14))
    slab[0, :3] = light + f * 12 + side * reach * 20
    slab[0, 4:7], slab[0, 7:10], slab[0, 10:13] = f * 18, side * 0.01, np.cross(f, side) * 50
    floor = fitmod._region_floor(slab, 0, light, *f, corners, q, spread[q])
    depth, r = fitmod._along(slab, 0, *f, *light)
    shape = np.eye(4)
    shape[:3, :3], shape[:3, 3] = slab[0, 4:13].reshape(3, 3).T * 2, slab[0, :3]
    tris = trimesh.creation.box(extents=[1, 1, 1], transform=shape).triangles
    least = clipped_depths(tris, planes[regions[q, :sizes[q]]], f, light).min()
    assert depth - r < 0 < 0.99 * least <= floor <= least * (1 + 1e-12)


def test_a_frustums_near_plane_comes_to_its_nearest_casters_part_within_it():
    """A lamp 20 m over a ground patch that a tile sees from above (a Low-Ilie frustum), a
    crate hanging 8 m under the lamp within that frustum, and a tall thin pole beside the
    patch, reaching 5 m over the lamp: only the foot of the pole lies within the frustum, 17 m
    under the lamp. The frustum's near plane comes just under the crate's nearest corner (a
    millionth nearer), not to the floor (a millionth of its far distance): the pole's bound
    reaches behind the lamp's plane, and the near plane came from the casters' bounds. No
    caster's triangle keeps a part within the frustum nearer than its near plane."""
    s = boxes({"patch": ([6, 0.1, 6], [0, -0.05, -10]), "crate": ([1, 1, 1], [0, 12, -4]),
               "pole": ([0.2, 25, 2], [2.5, 13, -10])})
    lamp = np.array([0.0, 20.0, 0.0])
    scene = Scene.from_trimesh(s, hierarchy="file",
                               settings={"lights": [{"name": "lamp", "position": list(lamp)}]})
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [0.4, 0.4], "distance": 1.0,
                           "resolution": [64, 64]})
    frame = {"position": [0, 6, -10], "orientation": [0.7071068, -0.7071068, 0, 0]}
    result = Session(scene, wall, fit=FitOptions()).frame(frame)
    assert result.visibility.names(0) == ["patch"]
    (shadow,) = result.fits[0]["shadows"]
    assert not shadow.get("cube")
    assert {scene.names[i] for i in shadow["casters"]} == {"patch", "crate", "pole"}
    view, projection = np.asarray(shadow["view"]), np.asarray(shadow["projection"])
    pv = projection @ view
    planes = np.array([pv[3] + pv[0], pv[3] - pv[0], pv[3] + pv[1], pv[3] - pv[1],
                       pv[3] - pv[2]])
    forward = -view[2, :3]
    crate = scene.leaf_vertices(scene.index["crate"])
    assert (crate @ planes[:, :3].T + planes[:, 3] > 0).all()  # wholly within the frustum
    nearest = ((crate - lamp) @ forward).min()
    near, far = shadow["near"], shadow["far"]
    assert near == pytest.approx(nearest * (1 - 1e-6), rel=1e-12)
    assert near > 1000 * far * fitmod.NEAR_FLOOR
    for leaf in shadow["casters"]:
        least = clipped_depths(scene.leaf_triangles(leaf), planes, forward, lamp).min()
        assert near <= least, scene.names[leaf]
    pole = clipped_depths(scene.leaf_triangles(scene.index["pole"]), planes, forward, lamp)
    assert 15 < pole.min() < np.inf


@pytest.mark.parametrize("lights", ["powerplant-lights.json", "powerplant-lights3.json"])
def test_frustums_near_planes_come_to_their_casters_clipped_triangles(lights):
    """Over frames of the power plant (orbit and fly, its example lamp and its three lights),
    every Low-Ilie frustum's near plane lies no farther than the least depth of its casters'
    triangles clipped to the frustum (``oracle.clipped_depths``, numpy). Where that least
    depth is under :data:`~wallcull.fit.NEAR_ENOUGH` of the far distance, the near plane is
    it, a millionth nearer (at the floor, a millionth of the far distance, only where the
    least depth lies under it); otherwise it lies at least that fraction out (a bound of the
    casters', nearer than their triangles, or half the far distance where no caster keeps a
    part within it). Its near plane came from its casters' bounds, which reach the light's
    plane (or behind it) for half the frusta: at the floor."""
    import json
    from pathlib import Path

    from wallcull.paths import scene_path
    from wallcull.scene import load

    root = Path(__file__).resolve().parent.parent
    scene = load("powerplant", settings=json.loads((root / "scenes" / lights).read_text()))
    wall = Wall.from_dict(json.loads((root / "examples" / "wall-4x4.json").read_text()))
    tris = [scene.leaf_triangles(int(leaf)) for leaf in scene.leaves]
    at = np.zeros(len(scene), np.int64)
    at[scene.leaves] = np.arange(len(scene.leaves))
    ends = np.cumsum([len(t) for t in tris])
    starts = ends - [len(t) for t in tris]
    tris = np.concatenate(tris)
    frusta = 0
    for path in ("orbit", "fly"):
        session = Session(scene, wall, fit=FitOptions())
        frames = scene_path(scene, wall, path, 40)
        for frame in (frames[7], frames[29]):
            for shadow in session.frame(frame).fits.shadows:
                light = np.asarray(shadow.light.position, float)
                for t in np.flatnonzero(shadow.kind == fitmod.FRUSTUM):
                    view, pv = shadow.view[t], shadow.projection[t] @ shadow.view[t]
                    planes = np.array([pv[3] + pv[0], pv[3] - pv[0], pv[3] + pv[1],
                                       pv[3] - pv[1], pv[3] - pv[2]])
                    forward = -view[2, :3]
                    near, far = shadow.near[t], shadow.far[t]
                    enough = far * fitmod.NEAR_ENOUGH
                    leaves = at[shadow.casters[shadow.casters_start[t]:
                                               shadow.casters_start[t + 1]]]
                    own = tris[np.concatenate([np.arange(starts[k], ends[k]) for k in leaves])]
                    # only a triangle with a corner nearer than this can matter: the least
                    # depth is exact below it (or at least it)
                    reach = max(near / (1 - 1e-6), enough) * (1 + 1e-9)
                    close = ((own - light) @ forward).min(axis=1) < reach
                    least = clipped_depths(own[close], planes, forward, light).min() \
                        if close.any() else np.inf
                    frusta += 1
                    assert near <= least, (path, shadow.light.name, t)
                    if least < enough:  # to the nearest caster
                        if least * (1 - 1e-6) > far * fitmod.NEAR_FLOOR * (1 + 1e-12):
                            assert near == pytest.approx(least * (1 - 1e-6), rel=1e-9)
                        else:
                            assert near == pytest.approx(far * fitmod.NEAR_FLOOR, rel=1e-9)
                    else:  # near enough
                        assert near >= enough * (1 - 1e-6) * (1 - 1e-12), (path, t)
    assert frusta > 20
