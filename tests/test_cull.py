"""Every method, with every bound type, is conservative against the exact oracle; the methods
agree leaf for leaf; and known answers come out right."""

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings, strategies as st

from wallcull.cull import FINE, METHODS, Culler, cull
from wallcull.scene import Scene, SceneState
from wallcull.wall import Frame, Frusta, Wall

from wallcull.oracle import visible_leaves, visible_units
from .randscene import look_at_frame, random_scene, random_wall

BOUNDS = ("obb", "aabb", "sphere")


def leaf_sets(vis):
    return [set(vis.tile_leaves(t).tolist()) for t in range(vis.tiles)]


def drawn_triangles(vis, tile: int) -> dict[int, set[int]]:
    """What a tile draws: leaf id -> the triangles of its mesh (its list, less what its
    ranges leave out)."""
    count = vis.scene.cluster_faces[1]
    out = {int(leaf): set(range(count[leaf])) for leaf in vis.tile_leaves(tile)}
    for leaf, ranges in vis.draw_ranges().tile(tile):
        out[leaf] = set().union(*(range(a, a + b) for a, b in ranges))
    return out


def check_units(scene: Scene, vis, units: list[set[int]], what: str):
    """Every cluster (or whole leaf) the oracle sees in a tile is drawn there, all of it."""
    first, count = scene.cluster_faces
    for t, seen in enumerate(units):
        drawn = drawn_triangles(vis, t)
        for unit in seen:
            leaf = scene.cluster_leaf[unit] if scene.cluster_of[unit] >= 0 else unit
            tris = set(range(first[unit], first[unit] + count[unit]))
            assert tris <= drawn.get(int(leaf), set()), \
                f"{what} misses cluster {unit} of {scene.names[leaf]} in tile {t}"


def check_against_oracle(scene: Scene, wall_spec: dict, frame_spec: dict):
    """Run every method and bound type; return the oracle's sets (for callers' sanity)."""
    wall = Wall.from_dict(wall_spec)
    frame = Frame.from_dict(frame_spec, wall)
    frusta = Frusta.build(wall, frame)
    extent = np.ptp(scene.leaf_points[0], axis=0).max()
    tol = 1e-7 * max(extent, np.linalg.norm(frame.position))
    truth = visible_leaves(scene, wall_spec, frame_spec, tol)
    units = visible_units(scene, wall_spec, frame_spec, tol) if len(scene.clusters) else None
    for kind in BOUNDS:
        state = SceneState(scene, kind)
        got = {}
        for method in [*METHODS, "pseudo", "coarse"]:
            # "coarse": adaptive as the product runs it, listing small clusters whole; the
            # others unfold clusters to the finest, where their lists relate as documented
            vis = cull(state, frusta, "adaptive" if method in ("pseudo", "coarse") else method,
                       pseudo_groups=method == "pseudo", fine=FINE if method == "coarse" else 0)
            got[method] = leaf_sets(vis)
            for t in range(wall.tiles):
                missed = truth[t] - got[method][t]
                assert not missed, (f"{method} ({kind}) misses leaves "
                                    f"{sorted(scene.names[i] for i in missed)} in tile {t}")
            if units is not None:
                check_units(scene, vis, units, f"{method} ({kind})")
        # Same bounds, same tests: the per-tile methods agree, the FH methods agree; the split
        # planes above a tile can only remove leaves, and adaptive, which tests objects it
        # unfolds at a tile against that tile's own planes, lies between (see wallcull.cull).
        assert got["oh"] == got["naive"], kind
        assert got["fh"] == got["pseudo"], kind
        assert all(a <= b <= c for a, b, c in zip(got["fh"], got["adaptive"], got["naive"])), kind
    return truth


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), flat=st.booleans(),
       hierarchy=st.sampled_from(["auto", "file"]))
def test_no_method_misses_a_leaf_the_oracle_sees(seed, flat, hierarchy):
    rng = np.random.default_rng(seed)
    tscene = random_scene(seed, leaves=int(rng.integers(1, 40)), flat=flat)
    scene = Scene.from_trimesh(tscene, hierarchy=hierarchy, branching=int(rng.integers(2, 6)))
    wall = random_wall(rng)
    center = scene.leaf_points[0].mean(axis=0)
    frame = look_at_frame(rng, center, float(rng.uniform(2, 25)), wall)
    check_against_oracle(scene, wall, frame)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), hierarchy=st.sampled_from(["auto", "file"]),
       size=st.sampled_from([32, 48, 100]), far=st.booleans())
def test_no_method_misses_a_cluster_the_oracle_sees(seed, hierarchy, size, far):
    """Leaves of many triangles cut into clusters (and trees of clusters): every cluster with
    a triangle in a tile frustum is drawn there, by every method and bound type; near the
    origin and 1e7 away."""
    rng = np.random.default_rng(seed)
    offset = np.array([1e7, -3e6, 2e7]) if far else np.zeros(3)
    tscene = random_scene(seed, leaves=int(rng.integers(1, 12)), offset=offset, big=0.6)
    scene = Scene.from_trimesh(tscene, hierarchy=hierarchy, branching=int(rng.integers(2, 6)),
                               clusters=size)
    wall = random_wall(rng)
    center = scene.leaf_points[0].mean(axis=0)
    frame = look_at_frame(rng, center, float(rng.uniform(2, 25)), wall)
    check_against_oracle(scene, wall, frame)


def test_random_clustered_cases_are_not_vacuous():
    """The clustered scenes above have clusters, and tiles that see some but not all of them."""
    parts = 0
    for seed in range(12):
        rng = np.random.default_rng(seed)
        scene = Scene.from_trimesh(random_scene(seed, leaves=int(rng.integers(1, 12)), big=0.6),
                                   clusters=32)
        assert len(scene.clusters)
        wall = random_wall(rng)
        frame = look_at_frame(rng, scene.leaf_points[0].mean(axis=0), float(rng.uniform(2, 25)),
                              wall)
        vis = cull(SceneState(scene), Frusta.build(Wall.from_dict(wall),
                                                   Frame.from_dict(frame, Wall.from_dict(wall))))
        parts += len(vis.draw_ranges().part_leaf)
    assert parts >= 6


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1))
def test_conservative_far_from_the_origin(seed):
    """Scene and camera offset by 1e7: the tolerance grows with |position| (SPEC section 5)."""
    rng = np.random.default_rng(seed)
    offset = np.array([1e7, -3e6, 2e7])
    scene = Scene.from_trimesh(random_scene(seed, leaves=15, offset=offset))
    wall = random_wall(rng)
    center = scene.leaf_points[0].mean(axis=0)
    frame = look_at_frame(rng, center, float(rng.uniform(3, 20)), wall)
    check_against_oracle(scene, wall, frame)


def test_random_cases_are_not_vacuous():
    """The generators above put leaves in view often enough for the property to bite."""
    seen = 0
    for seed in range(12):
        rng = np.random.default_rng(seed)
        scene = Scene.from_trimesh(random_scene(seed, leaves=int(rng.integers(1, 40))))
        wall = random_wall(rng)
        frame = look_at_frame(rng, scene.leaf_points[0].mean(axis=0), float(rng.uniform(2, 25)), wall)
        truth = visible_leaves(scene, wall, frame, 0.0)
        seen += sum(len(s) > 0 for s in truth) > 1
    assert seen >= 6


# ---------------------------------------------------------------- known answers


def boxes_scene(centers, size=0.05) -> Scene:
    s = trimesh.Scene()
    for i, c in enumerate(centers):
        m = np.eye(4)
        m[:3, 3] = c
        s.add_geometry(trimesh.creation.box(extents=[size] * 3), node_name=f"box{i}",
                       geom_name=f"g{i}", transform=m)
    return Scene.from_trimesh(s, hierarchy="file")


WALL4 = {"cols": 4, "rows": 3, "tile_size": [0.6, 0.4], "gap": [0.02, 0.02], "distance": 2.0}


@pytest.mark.parametrize("kind", BOUNDS)
@pytest.mark.parametrize("method", METHODS)
def test_object_inside_one_tile_lands_there_alone(kind, method):
    wall = Wall.from_dict(WALL4)
    frame = Frame.from_dict({"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}, wall)
    # the centre of tile (row 2, col 1), pushed 3x further than the wall
    x0, x1, y0, y1 = wall.tile_rect(2 * 4 + 1)
    target = 3 * np.array([(x0 + x1) / 2, (y0 + y1) / 2, -2.0])
    scene = boxes_scene([target])
    vis = cull(SceneState(scene, kind), Frusta.build(wall, frame), method)
    assert [vis.names(t) for t in range(wall.tiles)] == \
        [["box0"] if t == 9 else [] for t in range(wall.tiles)]


@pytest.mark.parametrize("kind", BOUNDS)
@pytest.mark.parametrize("method", METHODS)
def test_object_spanning_the_wall_lands_in_every_tile(kind, method):
    wall = Wall.from_dict(WALL4)
    frame = Frame.from_dict({"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}, wall)
    scene = boxes_scene([[0, 0, -20.0]], size=40.0)
    vis = cull(SceneState(scene, kind), Frusta.build(wall, frame), method)
    assert all(vis.names(t, leaves=True) == ["box0"] for t in range(wall.tiles))


@pytest.mark.parametrize("method", METHODS)
def test_object_behind_a_bezel_is_in_no_tile_and_in_an_overlap_in_both(method):
    for gap, expected in [(0.2, [[], []]), (-0.2, [["box0"], ["box0"]])]:
        wall = Wall.from_dict({"cols": 2, "rows": 1, "tile_size": [1.0, 1.0], "gap": [gap, 0],
                               "distance": 1.0})
        frame = Frame.from_dict({"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}, wall)
        scene = boxes_scene([[0, 0, -5.0]], size=0.1)  # 0.02 wide on the wall, at x = 0
        vis = cull(SceneState(scene, "obb"), Frusta.build(wall, frame), method)
        assert [vis.names(t) for t in range(2)] == expected


def test_internal_nodes_stand_for_whole_subtrees_only_when_inside():
    tscene = random_scene(7, leaves=30)
    scene = Scene.from_trimesh(tscene)
    wall = Wall.from_dict({**WALL4, "gap": [0.0, 0.0]})
    frame = Frame.from_dict({"position": [0, 0, 40], "orientation": [1, 0, 0, 0]}, wall)
    frusta = Frusta.build(wall, frame)
    vis = cull(SceneState(scene, "obb"), frusta, "adaptive")
    b = scene.bounds("obb")
    internal = 0
    for t in range(wall.tiles):
        planes = frusta.tile(t)
        for node in vis.tile_nodes(t):
            if not scene.is_leaf[node]:
                internal += 1
                s = planes[:, :3] @ b.center[node] + planes[:, 3]
                r = b.take([node] * 6).extent(planes[:, :3])
                assert (s >= r).all()
    assert internal > 0


def test_leaves_option_lists_leaf_names_and_hides_synthetic_groups():
    tscene = random_scene(3, leaves=60, flat=True)
    scene = Scene.from_trimesh(tscene, hierarchy="auto", branching=4)
    assert scene.synthetic.any()
    wall = Wall.from_dict({"cols": 1, "rows": 1, "tile_size": [1, 1], "distance": 0.5})
    frame = Frame.from_dict({"position": [0, 0, 60], "orientation": [1, 0, 0, 0]}, wall)
    vis = cull(SceneState(scene), Frusta.build(wall, frame), "adaptive")
    names = vis.names(0)
    leaves = vis.names(0, leaves=True)
    assert all("#g" not in n for n in names)
    assert set(names) <= set(scene.index)
    assert len(leaves) == len(set(leaves)) > 10
    assert all(scene.is_leaf[scene.index[n]] for n in leaves)


def test_pseudo_groups_change_tests_not_answers():
    tscene = random_scene(11, leaves=300, flat=True)
    scene = Scene.from_trimesh(tscene, hierarchy="file")
    wall = Wall.from_dict({**WALL4, "cols": 8, "rows": 8, "gap": [0.0, 0.0]})
    frame = Frame.from_dict({"position": [0, 0, 30], "orientation": [1, 0, 0, 0]}, wall)
    frusta = Frusta.build(wall, frame)
    state = SceneState(scene)
    plain = Culler(state, wall, "adaptive").cull(frusta)
    grouped = Culler(state, wall, "adaptive", pseudo_groups=True).cull(frusta)
    assert leaf_sets(plain) == leaf_sets(grouped)
    assert grouped.stats["tests"] != plain.stats["tests"]


# ---------------------------------------------------------------- the kernels' machinery


def test_threads_take_the_next_part_until_none_is_left(monkeypatch):
    """``workers.run`` gives every part once, results in order; a thread the system keeps
    busy elsewhere takes fewer parts (here none: the pool's one thread is held until every
    part is done, so the calling thread must take them all). Before, the parts were dealt to
    the threads up front, and this waited on the held thread."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from wallcull import workers

    monkeypatch.setattr(workers, "count", lambda: 2)
    pool = ThreadPoolExecutor(1)
    monkeypatch.setattr(workers, "_pool", pool)
    monkeypatch.setattr(workers, "_pool_size", 1)
    assert workers.run(lambda k, a, b: (k, a, b), [(0, 3), (3, 5), (5, 9)]) == \
        [(0, 0, 3), (1, 3, 5), (2, 5, 9)]
    done, release, ran = threading.Event(), threading.Event(), []
    held = pool.submit(release.wait, 60)  # the pool's only thread, held

    def part(k, a, b):
        ran.append((k, threading.current_thread().name))
        if len(ran) == 6:
            release.set()
        return k

    assert workers.run(part, [(k, k + 1) for k in range(6)]) == list(range(6))
    assert held.result() is True  # released by the last part, not by its timeout
    assert sorted(k for k, _ in ran) == list(range(6))
    assert {name for _, name in ran} == {threading.current_thread().name}
    pool.shutdown()


@pytest.fixture(scope="module")
def powerplant():
    from wallcull.scene import load

    return load("powerplant")


def _frames(scene, wall, count=3):
    from wallcull.paths import scene_path

    return [Frusta.build(wall, f) for f in scene_path(scene, wall, "orbit", count)]


@pytest.mark.parametrize("method", [*METHODS, "pseudo"])
def test_tile_lists_are_sorted_disjoint_subtrees(powerplant, method):
    """What the leaf expansion relies on: each tile's nodes in increasing id, no node inside
    another's subtree, so their leaf runs concatenate into sorted unique leaves."""
    wall = Wall.from_dict({**WALL4, "cols": 8, "rows": 8})
    state = SceneState(powerplant)
    culler = Culler(state, wall, "adaptive" if method == "pseudo" else method,
                    pseudo_groups=method == "pseudo")
    size, of_cluster = powerplant.size, powerplant.cluster_leaf
    first, count = powerplant.cluster_faces
    for frusta in _frames(powerplant, wall):
        vis = culler.cull(frusta)
        start, leaves = vis.leaf_lists()
        ranges = vis.draw_ranges()
        partial = 0
        for t in range(wall.tiles):
            nodes = vis.tile_nodes(t)
            assert (nodes[1:] >= (nodes + size[nodes])[:-1]).all()  # sorted, disjoint subtrees
            cluster = of_cluster[nodes] >= 0
            expect = np.union1d(powerplant.subtree_leaves(nodes[~cluster]), of_cluster[nodes[cluster]])
            assert np.array_equal(leaves[start[t]:start[t + 1]], expect)
            # a leaf reached through some of its clusters: their triangles, merged into ranges
            shown = {}
            for node in nodes[cluster]:
                shown.setdefault(int(of_cluster[node]), set()).update(
                    range(first[node], first[node] + count[node]))
            want = {leaf: tris for leaf, tris in shown.items() if len(tris) < count[leaf]}
            got = {leaf: set().union(*(range(a, a + b) for a, b in r)) for leaf, r in ranges.tile(t)}
            assert got == want
            for leaf, r in ranges.tile(t):
                assert (r[1:, 0] > r[:-1].sum(axis=1)).all()  # sorted, apart: merged
            partial += len(want)
        assert partial > 0  # the frames do cut leaves


def test_outputs_that_fill_up_are_doubled_not_truncated(powerplant):
    """The kernels write into buffers kept from frame to frame; one that fills up is doubled
    and the frame culled again (8 x 8: more pairs than the first buffer holds)."""
    wall = Wall.from_dict({**WALL4, "cols": 8, "rows": 8})
    frusta = _frames(powerplant, wall, 1)[0]
    state = SceneState(powerplant)
    fresh = Culler(state, wall).cull(frusta)
    assert fresh.stats["pairs"] > 4096  # the first buffer's size
    warm = Culler(state, wall)
    warm._buffers[0].arrays["out_n"] = np.zeros(8, np.int64)
    warm._buffers[0].arrays["out_t"] = np.zeros(8, np.int64)
    again = warm.cull(frusta)
    assert np.array_equal(fresh.start, again.start) and np.array_equal(fresh.nodes, again.nodes)


def test_pseudo_groups_on_a_large_wall(powerplant):
    """Hundreds of pseudo-groups in one frame: the pool grows (it once overran its box table)."""
    wall = Wall.from_dict({**WALL4, "cols": 64, "rows": 64, "tile_size": [0.1, 0.1]})
    state = SceneState(powerplant)
    frusta = _frames(powerplant, wall, 1)[0]
    grouped = leaf_sets(Culler(state, wall, "adaptive", pseudo_groups=True).cull(frusta))
    assert grouped == leaf_sets(Culler(state, wall, "fh").cull(frusta))


@pytest.mark.parametrize("wall_name", ["4x4", "8x8", "64x64", "angled", "cave2"])
def test_adaptive_takes_no_more_tests_than_oh_on_the_bundled_scenes(wall_name):
    """Plane masking and the choice of hierarchy (wallcull.cull): counted, not timed."""
    import json
    from pathlib import Path

    from wallcull.paths import scene_path
    from wallcull.scene import load

    spec = json.loads((Path(__file__).parent.parent / "examples" / f"wall-{wall_name}.json")
                      .read_text())
    wall = Wall.from_dict(spec)
    for name in ("powerplant", "fatehpur"):
        scene = load(name)
        state = SceneState(scene)
        for path in ("orbit", "fly"):
            frames = [Frusta.build(wall, f) for f in scene_path(scene, wall, path, 4)]
            count = {m: sum(Culler(state, wall, m).cull(f).stats["tests"] for f in frames)
                     for m in ("oh", "adaptive")}
            assert count["adaptive"] <= count["oh"], (name, path, count)


def test_regions_hold_the_leaves_whose_bounds_meet_them():
    """cull_regions (the ``oh`` kernel over any convex regions) against a brute-force test of
    every leaf's bound, computed with the bounds' own support function."""
    from wallcull.cull import cull_region, cull_regions

    scene = Scene.from_trimesh(random_scene(5, leaves=80), hierarchy="auto", branching=3)
    state = SceneState(scene)
    b = state.bounds
    rng = np.random.default_rng(5)
    center = b.center[0]
    planes = rng.normal(size=(12, 4))
    planes[:, :3] /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    planes[:, 3] = -planes[:, :3] @ center + rng.uniform(0, 3, 12)  # through the scene
    region_planes = np.array([[0, 1, 2, -1], [3, 4, 5, 6], [7, 8, 9, 10], [11, -1, -1, -1]])
    sizes = np.array([3, 4, 4, 1])
    regions = cull_regions(state, planes, region_planes, sizes)
    start, leaves = regions.leaf_lists()
    leaf = scene.leaves
    for q in range(4):
        rows = planes[region_planes[q, :sizes[q]]]
        s = rows[:, :3] @ b.center[leaf].T + rows[:, 3:4]
        r = np.stack([b.take(leaf).extent(np.tile(n, (len(leaf), 1))) for n in rows[:, :3]])
        expect = leaf[(s >= -r).all(axis=0)]
        assert np.array_equal(leaves[start[q]:start[q + 1]], expect), q
        assert np.array_equal(np.unique(scene.subtree_leaves(
            cull_region(state, rows))), expect)
    assert 0 < len(leaves) < 4 * len(leaf)  # not vacuous


def test_regions_split_among_threads_give_the_same_lists(powerplant, monkeypatch):
    from wallcull.cull import cull_regions

    state = SceneState(powerplant)
    rng = np.random.default_rng(1)
    center = state.bounds.center[0]
    planes = rng.normal(size=(120, 4))
    planes[:, :3] /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    planes[:, 3] = -planes[:, :3] @ center + rng.uniform(-10, 30, 120)
    region_planes = np.arange(120).reshape(40, 3)
    got = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("WALLCULL_THREADS", threads)
        r = cull_regions(state, planes, region_planes, work=np.arange(41) ** 2)
        got.append((r.start, r.nodes, r.tests))
    for start, nodes, tests in got[1:]:
        assert np.array_equal(start, got[0][0]) and np.array_equal(nodes, got[0][1])
        assert tests == got[0][2]
    assert len(got[0][1]) > 40


@pytest.mark.parametrize("wall_name", ["wall-8x8.json", "wall-cave.json", "wall-angled.json"])
def test_adaptive_in_threads_lists_what_one_pass_lists(powerplant, monkeypatch, wall_name):
    """Big frames run ``adaptive`` over parts of the frustum hierarchy in threads: the same
    pairs, each tile's in the same order, for any number of parts."""
    import json
    from pathlib import Path

    import wallcull.cull as C
    from wallcull.paths import scene_path

    wall = Wall.from_dict(json.loads((Path(__file__).parents[1] / "examples" / wall_name)
                                     .read_text()))
    state = SceneState(powerplant)
    frames = [Frusta.build(wall, f) for f in scene_path(powerplant, wall, "orbit", 4)]
    one = Culler(state, wall)
    expect = [one.cull(f) for f in frames]
    monkeypatch.setattr(C, "PARALLEL_TESTS", 0)
    for threads in ("2", "3", "5"):
        monkeypatch.setenv("WALLCULL_THREADS", threads)
        culler = Culler(state, wall)
        leaves = culler._fh[:, C._TILE] >= 0
        for frusta, e in zip(frames, expect):
            culler.cull(frusta)  # the first frame decides: threads from the next one
            parts = culler._split.parts(culler._last_pairs)  # as the next cull deals them
            assert len(parts) == min(int(threads), wall.tiles)
            assert (np.sum(parts, axis=0)[leaves] == 1).all()  # each tile in exactly one
            got = culler.cull(frusta)
            assert np.array_equal(got.start, e.start) and np.array_equal(got.nodes, e.nodes)


@pytest.mark.parametrize("wall_name, path, stereo", [
    ("wall-8x8.json", "fly", None), ("wall-8x8.json", "orbit", 0.064),
    ("wall-cave.json", "fly", None), ("wall-angled.json", "fly", None)])
def test_the_separating_pass_told_the_cuts_drops_what_it_drops_testing_them(
        powerplant, monkeypatch, wall_name, path, stereo):
    """``adaptive`` tells the separating pass which of a tile's planes cut each listed node,
    so that the pass need not test them again: never a plane that does not cut the node; and
    a grid's frame, so that its outline test takes each tile's near face as a rectangle. The
    pass then keeps the pairs it keeps when it tests the planes and corners itself."""
    import json
    from pathlib import Path

    from wallcull import cull as C, separate
    from wallcull.paths import scene_path

    wall = Wall.from_dict(json.loads((Path(__file__).parents[1] / "examples" / wall_name)
                                     .read_text()))
    real = separate.drop_all
    seen = {"pairs": 0, "two_cuts": 0, "depth": 0, "dropped": 0}

    def both(nodes, regions, count, box, planes, rows, child_count, eye, small, scratch,
             cuts=None, basis=None):
        assert cuts is not None and len(cuts) >= count
        for j in np.flatnonzero(child_count[nodes[:count]] == 0):
            i, t = nodes[j], regions[j]
            actual = sum(1 << q for q in range(rows.shape[1])
                         if np.subtract(*separate._offset(box, i, planes, rows[t, q])) < 0)
            assert cuts[j] & ~actual == 0, (i, t, bin(cuts[j]), bin(actual))
            seen["two_cuts"] += bin(cuts[j]).count("1") > 1
            seen["depth"] += bin(cuts[j]).count("1") > 1 and cuts[j] & 48 != 0
        seen["pairs"] += count
        told = real(nodes.copy(), regions.copy(), count, box, planes, rows, child_count, eye,
                    small, [], cuts, basis)
        tested = real(nodes.copy(), regions.copy(), count, box, planes, rows, child_count,
                      eye, small, [])
        assert all(np.array_equal(a, b) for a, b in zip(told, tested))
        seen["dropped"] += count - len(told[0])
        return told

    monkeypatch.setattr(C, "drop_all", both)
    culler = Culler(SceneState(powerplant), wall)
    for f in scene_path(powerplant, wall, path, 6):
        if stereo:
            f = Frame.make(f.position, f.orientation, f.eye, wall, (stereo, (1.0, 0, 0, 0)))
        culler.cull(Frusta.build(wall, f))
    assert seen["pairs"] > 1000 and seen["two_cuts"] > 50 and seen["dropped"] > 0, seen


def test_walls_share_the_scenes_packed_records_until_they_move():
    """The packed records every kernel reads come from the scene while a state shares its
    arrays: a second wall on a scene costs no second copy (335 MB at a million nodes). A state
    that moves copies them once, and the scene's and the other walls' stay as they were."""
    from wallcull.cull import pack, packed

    scene = Scene.from_trimesh(random_scene(6, leaves=30))
    a, b = SceneState(scene), SceneState(scene)
    rest = packed(a)
    assert packed(b) is rest
    assert packed(SceneState(scene)) is rest
    assert packed(SceneState(scene, "aabb")) is not rest  # another kind, other records
    m = scene.local[scene.index["leaf4"]].copy()
    m[:3, 3] += 1.0
    a.move({"leaf4": m})
    moved = packed(a)
    assert not np.shares_memory(moved, rest) and packed(b) is rest
    np.testing.assert_array_equal(moved, pack(a.bounds))
    np.testing.assert_array_equal(rest, pack(scene.bounds("obb")))
    assert not np.array_equal(moved, rest)


def test_moves_repack_only_the_rows_they_change(monkeypatch):
    """A move re-packs the records of the rows it changed into the state's kept records (the
    moved subtrees and their refit ancestors), not all of them: at a million nodes re-packing
    every record took culling from 15 to 220 ms a frame. They stay equal to a full pack."""
    from wallcull import cull as C
    from wallcull.scene import load

    from .test_scene import _reach

    scene = load("fatehpur")
    state = SceneState(scene)
    C.packed(state)
    real, sizes = C.pack, []
    monkeypatch.setattr(C, "pack", lambda b: sizes.append(len(b)) or real(b))
    kept = None
    for k, i in enumerate((50, 200, 350, 420)):
        leaf = int(scene.leaves[i])
        m = scene.local[leaf].copy()
        m[:3, 3] += [0.3, 0.0, -0.2]
        rows = np.union1d(*_reach(scene, leaf))
        state.move({scene.names[leaf]: m}, "aabb" if k % 2 else None)
        sizes.clear()
        out = C.packed(state)
        assert sizes == [len(rows)] and len(rows) < len(scene) // 10, (sizes, len(rows))
        np.testing.assert_array_equal(out, real(state.bounds))
        assert kept is None or out is kept  # re-packed in place
        kept = out
