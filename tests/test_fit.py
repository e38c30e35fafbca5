"""Fitted frusta: round trips and properties, against independent computations."""

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings as hsettings, strategies as st

from wallcull import fit as fitmod
from wallcull.fit import FitOptions, tile_projections
from wallcull.projection import view_matrix
from wallcull.oracle import clip_triangles, tile_frusta
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
    to leaves (``cull._expand``) and their depths taken (``cull._depth_ranges``), give: the
    same leaves in the same order, the same nearest depths to the bit, NaN for a region that
    lists nothing; and -1 when its output cannot hold them. A cube map's region gets instead
    a lower bound of its casters' least Chebyshev distance from the light, between their
    leaves' boxes' and their vertices'."""
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
    for k in range(count):  # region 0 looks away from the scene: it lists nothing
        target = box[rng.integers(len(box)), :3] + rng.normal(size=3) if k \
            else 2 * light - box[0, :3]
        w, h = rng.uniform(0.05, 1.5, 2) if k else (0.1, 0.1)
        pv[k] = frustum(-w, w, -h, h, 0.1, far[k]) @ look_at(light, target)
    lit = np.arange(count)
    planes, regions, sizes = fitmod._caster_regions(pv, kind, lit, far, light)
    forward = rng.normal(size=(count, 3))
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
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
    out, nearest, starts = np.empty(1 << 16, np.int64), np.where(cubes, np.inf, np.nan), \
        np.zeros(count + 1, np.int64)
    written = fitmod._cull_casters(*tree, box, planes, regions, sizes, forward, cubes, faces,
                                   light, *lists, np.empty(stack, np.int64),
                                   np.empty(stack, np.int64), out, nearest, starts)
    assert written == len(leaves) > 0
    assert np.array_equal(out[:written], leaves) and np.array_equal(starts, first)
    assert np.array_equal(nearest[~cubes], lo[~cubes], equal_nan=True)
    assert np.isnan(nearest[0]) and not np.isnan(nearest).all()  # none behind the light
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
                                light, *lists, np.empty(stack, np.int64),
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
