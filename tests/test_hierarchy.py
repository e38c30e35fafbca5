"""The vectorized, instance-aware build gives the hierarchy the per-node loops gave
(tests/oldscene.py), node for node, with bounds as tight and as conservative; the tree helpers
agree with plain loops; and K tiled copies are the scene a trimesh load of K copies gives."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from wallcull import hierarchy as H
from wallcull.scene import CLUSTERS, Scene, Source
from wallcull.bundled import build

from .oldscene import old_arrays, old_leaf_bounds
from .randscene import random_scene

STRUCTURE = ("parent", "child_start", "child_count", "children", "is_leaf", "synthetic")


def check_same_as_before(tm, hierarchy="auto", branching=8):
    old = old_arrays(tm, hierarchy, branching)
    new = Scene.from_trimesh(tm, hierarchy=hierarchy, branching=branching, clusters=None)
    assert list(new.names) == old["names"]
    for key in STRUCTURE:
        np.testing.assert_array_equal(getattr(new, key), old[key], err_msg=key)
    assert new.geometry == old["geometry"]
    assert list(new.meshes) == list(old["meshes"])
    for k, (v, f) in old["meshes"].items():
        np.testing.assert_array_equal(new.meshes[k][0], v)
        np.testing.assert_array_equal(new.meshes[k][1], f)
    np.testing.assert_array_equal(new.local, old["local"])
    np.testing.assert_allclose(new.world, old["world"], rtol=0,
                               atol=1e-13 * max(1.0, np.abs(old["world"]).max()))
    # Leaf OBBs: each encloses its leaf's points as fitted before; where the points' spread
    # along the box axes is distinct it is the old box (the axes within a repeated eigenvalue
    # are free, and the old fit picked them by rounding)
    ob = old_leaf_bounds(old, "obb")
    nb = new.bounds("obb").take(new.leaves)
    points, starts = new.leaf_points
    for k in range(len(new.leaves)):
        assert nb.contains(k, points[starts[k]:starts[k + 1]]).all()
    same = (np.abs(np.einsum("nkj,nkj->nk", nb.axes, ob.axes)) > 1 - 1e-9).all(axis=1)
    scale = np.abs(ob.center).max(axis=1) + ob.half.max(axis=1)
    np.testing.assert_allclose(nb.half[same], ob.half[same], rtol=0,
                               atol=1e-12 * scale[same].max(initial=1))
    return new, same


@pytest.mark.parametrize("name", ["fatehpur", "powerplant"])
def test_bundled_scenes_build_as_before(name):
    new, same = check_same_as_before(build(name))
    assert same.mean() > 0.3  # many leaves have distinct spreads: the comparison bites


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), flat=st.booleans(), self_geometry=st.booleans(),
       hierarchy=st.sampled_from(["auto", "file"]), branching=st.integers(2, 6))
def test_random_scenes_build_as_before(seed, flat, self_geometry, hierarchy, branching):
    rng = np.random.default_rng(seed)
    tm = random_scene(seed, leaves=int(rng.integers(1, 80)), flat=flat,
                      self_geometry=self_geometry)
    check_same_as_before(tm, hierarchy, branching)


def random_tree(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.array([-1] + [int(rng.integers(0, i)) for i in range(1, n)])


def loop_depth_and_size(parent):
    depth = np.zeros(len(parent), dtype=int)
    for i in range(1, len(parent)):
        depth[i] = depth[parent[i]] + 1
    size = np.ones(len(parent), dtype=int)
    for i in range(len(parent) - 1, 0, -1):
        size[parent[i]] += size[i]
    return depth, size


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 300))
def test_tree_helpers_agree_with_loops(seed, n):
    parent = random_tree(seed, n)
    depth, size = loop_depth_and_size(parent)
    np.testing.assert_array_equal(H.depths(parent), depth)
    by_level = H.levels(depth)
    assert all((depth[level] == d).all() for d, level in enumerate(by_level))
    np.testing.assert_array_equal(H.subtree_sizes(parent, by_level), size)
    # preorder with random sibling ranks: a stack walk visiting children by rank
    rank = np.random.default_rng(seed).permutation(n)
    kids = {i: sorted(np.flatnonzero(parent == i), key=lambda k: rank[k]) for i in range(n)}
    order, stack = [], [0]
    while stack:
        i = stack.pop()
        order.append(i)
        stack.extend(reversed(kids[i]))
    np.testing.assert_array_equal(H.preorder(parent, rank), order)


@pytest.mark.parametrize("name", ["fatehpur*3", "powerplant*2"])
def test_tiled_copies_are_the_scene_trimesh_builds(name):
    """``NAME*K`` tiled as arrays (what load does) against the K copies put in a trimesh
    scene graph and read back: the same scene, array for array and bound for bound."""
    tiled = Source.of(name).build("auto", 8, CLUSTERS)
    full = Scene.from_trimesh(build(name), name=name)
    assert list(tiled.names) == list(full.names)
    for key in (*STRUCTURE, "mesh_of", "cluster_of", "local", "world"):
        np.testing.assert_array_equal(getattr(tiled, key), getattr(full, key), err_msg=key)
    assert list(tiled.meshes) == list(full.meshes)
    for kind in ("obb", "aabb"):
        a, b = tiled.bounds(kind), full.bounds(kind)
        for field in ("center", "axes", "half", "radius"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


@pytest.mark.slow
def test_forty_tiled_plants_are_the_scene_trimesh_builds():
    """Enough copies for the automatic hierarchy to group the plants (40 > 4 x 8)."""
    tiled = Source.of("powerplant*40").build("auto", 8, CLUSTERS)
    full = Scene.from_trimesh(build("powerplant*40"), name="powerplant*40")
    assert tiled.synthetic.any()
    assert list(tiled.names) == list(full.names)
    for key in (*STRUCTURE, "mesh_of", "cluster_of", "local", "world"):
        np.testing.assert_array_equal(getattr(tiled, key), getattr(full, key), err_msg=key)
    np.testing.assert_array_equal(tiled.bounds().half, full.bounds().half)


def test_tiled_scenes_are_copies_side_by_side():
    one = Source.of("powerplant").build("auto", 8, CLUSTERS)
    four = Source.of("powerplant*4").build("auto", 8, CLUSTERS)
    assert len(four.leaves) == 4 * len(one.leaves)
    assert four.stats["triangles"] == 4 * one.stats["triangles"]
    roots = [four.names[i] for i in four.children[:four.child_count[0]]]
    assert roots == ["powerplant0", "powerplant1", "powerplant2", "powerplant3"]
    assert four.names[four.leaves[0]] == one.names[one.leaves[0]].replace("powerplant", "powerplant0", 1)
    size = np.ptp(one.box, axis=0)
    span = np.ptp(four.box, axis=0)
    assert span[0] > 1.9 * size[0] and span[2] > 1.9 * size[2]  # a 2 x 2 grid in x and z
    assert span[1] == pytest.approx(size[1])  # all on the ground


@pytest.mark.parametrize("bad", ["powerplant*0", "powerplant*257", "powerplant*x", "castle*3"])
def test_bad_tiled_names_are_clear_errors(bad):
    from wallcull.errors import InputError

    with pytest.raises(InputError):
        Source.of(bad)


def check_sampled_leaves_conservative(spec: str, frames: int, leaves: int, seed: int = 0):
    """Every method lists every sampled leaf that the exact oracle sees in a tile, on frames
    of the fly path (inside the scene, so that tiles see some leaves and not others)."""
    from wallcull import oracle
    from wallcull.cull import METHODS
    from wallcull.paths import scene_path
    from wallcull.pipeline import Session
    from wallcull.scene import load, prepare
    from wallcull.wall import Wall

    prepare(spec)
    scene = load(spec)
    assert scene.prepared is not None
    wall = Wall.from_dict({"cols": 4, "rows": 3, "tile_size": [0.6, 0.34], "gap": [0.01, 0.01],
                           "distance": 2.0, "near": 0.1, "far": 1000.0})
    rng = np.random.default_rng(seed)
    sample = rng.choice(scene.leaves, leaves, replace=False)
    path = scene_path(scene, wall, "fly", 40)
    seen = 0
    for frame in [path[k] for k in rng.choice(len(path), frames, replace=False)]:
        fd = frame.to_dict()
        tol = 1e-7 * max(float(np.ptp(scene.box, axis=0).max()), float(np.linalg.norm(frame.position)))
        frusta = [oracle.tile_frusta(wall.to_dict(), fd, t, tol) for t in range(wall.tiles)]
        truth = [{int(l) for l in sample
                  if oracle.meets(oracle.leaf_triangles_display(scene, fd, l), frusta[t])}
                 for t in range(wall.tiles)]
        seen += sum(map(len, truth))
        for method in METHODS:
            vis = Session(scene, wall, method).frame(frame).visibility
            for t in range(wall.tiles):
                assert truth[t] <= set(vis.tile_leaves(t).tolist()), (method, t)
    assert seen > 0


def test_a_tiled_scene_is_culled_conservatively():
    check_sampled_leaves_conservative("powerplant*4", frames=2, leaves=150)


@pytest.mark.slow
def test_a_large_tiled_scene_is_culled_conservatively():
    check_sampled_leaves_conservative("powerplant*40", frames=6, leaves=600)
