"""Occlusion culling (wallcull.occlude): the rasterizer never claims a texel it does not cover
wholly, nearer than it says (checked against exact ray casts); a tile drawn from its
occlusion-culled list is pixel-identical to the tile drawn from the whole scene (a real
renderer, on grids, CAVE screens and stereo); and hidden things are dropped."""

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings, strategies as st

from wallcull import occlude
from wallcull.cull import cull
from wallcull.fit import FitOptions
from wallcull.occlude import Occluder, OcclusionOptions, _raster_triangle
from wallcull.pipeline import Session
from wallcull.scene import Scene, SceneState, load
from wallcull.wall import Frame, Frusta, Wall

from .drawing import Draws


def _ray_depths(tris: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Per view ray through ``xy (k, 2)`` (tangents; the view looks down -z), the nearest
    depth at which one of ``tris (m, 3, 3)`` (view coordinates) is hit, inf if none (exact
    Moller-Trumbore, all rays against all triangles at once, up to rounding)."""
    d = np.c_[xy, -np.ones(len(xy))][:, None, :]  # (k, 1, 3)
    a, b, c = tris[None, :, 0], tris[None, :, 1], tris[None, :, 2]
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = (e1 * p).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -a
        u = (s * p).sum(-1) / det
        q = np.cross(s, e1)
        v = (d * q).sum(-1) / det
        t = (e2 * q).sum(-1) / det
    eps = 1e-9  # a ray through a shared vertex or edge hits by rounding on neither side
    hit = (np.abs(det) > 1e-15) & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (t > 0)
    return np.where(hit, t, np.inf).min(axis=1)  # d has unit z: t is the depth


def raster(tris: np.ndarray, faces=None, w=24, h=16, rect=(-0.6, 0.6, -0.4, 0.4)):
    """Rasterize triangles (view coordinates) as occluders; with ``faces`` (indices into the
    triangles' points as one mesh), each edge shared by two faces lets coverage cross it."""
    rect = np.asarray(rect, float)
    buf, mask, work = np.zeros(w * h), np.zeros(w * h, np.uint64), np.full(w * h, np.inf)
    scratch, spans = np.empty((16, occlude.SUB)), np.empty((2, occlude.SUB + 6), np.int64)
    if faces is None:
        faces = np.arange(3 * len(tris)).reshape(-1, 3)
        points = tris.reshape(-1, 3)
    else:
        points = tris
    from wallcull.instances import MeshTable

    table = MeshTable.from_meshes({"m": (points, faces)})
    nb = table.face_neighbors
    for f, face in enumerate(faces):
        far = np.full((3, 3), np.nan)
        for e in range(3):
            g = nb[f, e]
            if g >= 0:
                (x,) = [v for v in faces[g] if v not in (face[e], face[(e + 1) % 3])]
                far[e] = points[x]
        bw, bh = -(-w // occlude.BLOCK), -(-h // occlude.BLOCK)
        _raster_triangle(points[face], far, np.eye(3, 4), rect, w, h, 0.05, buf, mask, work, 0,
                         scratch, spans, np.zeros(bw * bh), np.zeros(bw * bh, np.uint8), bw)
    return buf, rect


def check_claims(buf, rect, tris, w=24, h=16, rng=None):
    """Every texel given a depth z is covered, at each sample (its corners, its centre and
    random points), by an occluder no farther than z (exact ray casts); returns how many
    texels were claimed."""
    rng = rng or np.random.default_rng(0)
    j, i = np.divmod(np.flatnonzero(buf > 0), w)
    if not len(i):
        return 0
    samples = np.r_[[[0, 0], [1, 0], [0, 1], [1, 1], [0.5, 0.5]], rng.random((6, 2))]
    dx, dy = (rect[1] - rect[0]) / w, (rect[3] - rect[2]) / h
    x = rect[0] + (i[:, None] + samples[None, :, 0]) * dx
    y = rect[2] + (j[:, None] + samples[None, :, 1]) * dy
    depth = _ray_depths(tris, np.c_[x.ravel(), y.ravel()]).reshape(x.shape)
    limit = 1 / buf[j * w + i]
    bad = depth > limit[:, None] * (1 + 1e-9)
    assert not bad.any(), (i[bad.any(1)], j[bad.any(1)], depth[bad], limit[bad.any(1)])
    return len(i)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(1, 12))
def test_the_rasterizer_claims_only_what_it_covers_and_no_nearer(seed, count):
    rng = np.random.default_rng(seed)
    tris = rng.normal(size=(count, 3, 3)) * [0.8, 0.8, 1.5]
    tris[:, :, 2] -= rng.uniform(2, 6, size=(count, 1))  # in front, at various depths
    buf, rect = raster(tris)
    check_claims(buf, rect, tris, rng=rng)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 7), fold=st.floats(0, 1.5))
def test_a_mesh_covers_across_its_shared_edges_and_no_more(seed, n, fold):
    """A patch of triangles sharing edges: a grid of points jittered on the image, at depths
    that bend it (and may fold it over itself on the image): coverage crosses the shared
    edges, never past what the mesh covers."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(-1, 1, n + 1), np.linspace(-0.8, 0.8, n + 1))
    xy = np.stack([u, v], -1).reshape(-1, 2) + rng.normal(size=((n + 1) ** 2, 2)) * fold / n
    depth = 3 + rng.uniform(-1, 1, size=len(xy)) * fold
    points = np.c_[xy * depth[:, None], -depth]  # view coordinates
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.c_[a, b, c], np.c_[a, c, d]])
    buf, rect = raster(points, faces)
    claimed = check_claims(buf, rect, points[faces], rng=rng)
    if fold == 0:
        assert claimed > 0.5 * buf.size  # a flat patch covers most texels, across its edges


def test_the_rasterizer_is_not_vacuous():
    """A big near quad covers most texels, each at its farthest depth over the texel; as two
    triangles sharing an edge, the texels along the diagonal too."""
    quad = np.array([[-2, -2, -2.0], [2, -2, -2.0], [2, 2, -3.0], [-2, 2, -3.0]])
    buf, rect = raster(quad, np.array([[0, 1, 2], [0, 2, 3]]), 16, 16, (-0.5, 0.5, -0.5, 0.5))
    assert (buf > 0).all()
    depth = 1 / buf.reshape(16, 16)
    assert (np.diff(depth, axis=0) > 0).all()  # farther up the quad
    apart, _ = raster(quad[[0, 1, 2, 0, 2, 3]].reshape(2, 3, 3), None, 16, 16,
                      (-0.5, 0.5, -0.5, 0.5))
    assert (apart > 0).sum() < 0.9 * 256  # the same triangles unjoined miss the diagonal


def boxes_behind_a_wall() -> Scene:
    """A wall in front of a row of small boxes, and one box beside the wall, in view."""
    s = trimesh.Scene()
    m = np.eye(4)
    m[:3, 3] = [0, 0, -10]
    s.add_geometry(trimesh.creation.box(extents=[8, 8, 0.2]), node_name="wall", geom_name="w",
                   transform=m)
    for k, x in enumerate(np.linspace(-2.5, 2.5, 6)):
        m = np.eye(4)
        m[:3, 3] = [x, 0.5 * k - 1, -20]
        s.add_geometry(trimesh.creation.icosphere(2, radius=0.4), node_name=f"hidden{k}",
                       geom_name=f"h{k}", transform=m)
    m = np.eye(4)
    m[:3, 3] = [12, 0, -20]  # past the wall's edge (its tangent 0.4, this one's 0.6)
    s.add_geometry(trimesh.creation.icosphere(2, radius=0.4), node_name="beside",
                   geom_name="b", transform=m)
    return Scene.from_trimesh(s, hierarchy="file", clusters=32)


WALL = {"cols": 3, "rows": 2, "tile_size": [0.6, 0.4], "gap": [0.01, 0.01], "distance": 1.0,
        "resolution": [96, 64]}


def test_what_a_wall_hides_is_dropped():
    scene = boxes_behind_a_wall()
    wall = Wall.from_dict(WALL)
    frame = Frame.from_dict({"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}, wall)
    state = SceneState(scene)
    vis = cull(state, Frusta.build(wall, frame))
    out = Occluder(state, wall).occlude(vis, frame)
    names = lambda v: {n for t in range(wall.tiles) for n in v.names(t, leaves=True)}  # noqa
    assert {f"hidden{k}" for k in range(6)} <= names(vis)
    assert names(out) == {"wall", "beside"}
    assert out.stats["occluded"] > 0 and out.stats["occluder_triangles"] > 0


def render_or_skip(w, h):
    render = pytest.importorskip("wallcull_clients.render")
    try:
        return render.TileRenderer(w, h)
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"no headless OpenGL: {exc}")


def check_pixels(scene, wall_spec, frame_spec, eyes=(None,)):
    """Every tile (and eye) drawn from its occlusion-culled list and ranges equals the whole
    scene drawn; returns how many (tile, node) pairs occlusion dropped."""
    wall = Wall.from_dict(wall_spec)
    result = Session(scene, wall, fit=FitOptions(), occlusion=OcclusionOptions()).frame(
        Frame.from_dict(frame_spec, wall))
    res = wall.resolutions[0]
    r = render_or_skip(int(res[0]), int(res[1]))
    draws = Draws(scene, r)
    everything = draws.everything()
    for t in range(wall.tiles):
        culled = draws.tile(result.visibility, t)
        for eye in eyes:
            fit = result.fits[t] if eye is None else result.fits[t][eye]
            view, proj = np.asarray(fit["view"]), np.asarray(fit["projection"])
            np.testing.assert_array_equal(r.render(culled, view, proj).ids,
                                          r.render(everything, view, proj).ids)
    r.release()
    return result.visibility.stats["occluded"]


def test_a_grid_drawn_from_occlusion_culled_lists_loses_no_pixel():
    assert check_pixels(boxes_behind_a_wall(), WALL,
                        {"position": [0.3, 0.2, 0], "orientation": [1, 0, 0, 0]}) > 0


@pytest.mark.parametrize("name,frame", [
    ("powerplant", {"position": [30, 12, 20], "orientation": [0.9238795, 0, 0.3826834, 0]}),
    ("fatehpur", {"position": [40, 8, 60], "orientation": [1, 0, 0, 0]})])
def test_real_scenes_lose_no_pixel_inside(name, frame):
    """Inside the bundled scenes, where most of a tile's frustum is hidden."""
    wall = {**WALL, "cols": 2, "rows": 2, "resolution": [120, 80]}
    assert check_pixels(load(name), wall, frame) > 10


def test_stereo_keeps_what_either_eye_sees():
    frame = {"position": [0.3, 0.2, 0], "orientation": [1, 0, 0, 0], "stereo": {"ipd": 0.6}}
    assert check_pixels(boxes_behind_a_wall(), WALL, frame, eyes=("left", "right")) > 0


def test_cave_screens_lose_no_pixel():
    import json
    from pathlib import Path

    cave = json.loads((Path(__file__).parents[1] / "examples" / "wall-cave.json").read_text())
    cave = {**cave, "screens": [{**s, "resolution": [64, 64]} for s in cave["screens"]]}
    frame = {"position": [30, 10, 20], "orientation": [1, 0, 0, 0], "eye": [0.2, 0.1, -0.1]}
    assert check_pixels(load("powerplant"), cave, frame) > 0
