"""The object hierarchy: loading real files, the flat-array invariants, the automatic spatial
hierarchy, and dynamic moves that refit only what moved."""

from pathlib import Path

import numpy as np
import pytest
import trimesh

from wallcull.errors import InputError
from wallcull.oracle import visible_leaves
from wallcull.cull import METHODS, cull
from wallcull.scene import Scene, SceneState, load, load_sizes, load_trimesh, spatial_groups
from wallcull.wall import Frame, Frusta, Wall

from .randscene import look_at_frame, random_scene, random_wall

# The third-party scenes the project ships (scenes/README.md: sources and licences).
SCENES = Path(__file__).resolve().parents[1] / "scenes"


def check_invariants(scene: Scene):
    n = len(scene)
    assert scene.parent[0] == -1 and (scene.parent[1:] < np.arange(1, n)).all()  # preorder
    descendants = _descendants(scene)
    for i in range(n):
        kids = scene.children[scene.child_start[i]:scene.child_start[i] + scene.child_count[i]]
        assert (scene.parent[kids] == i).all()
        assert set(range(i + 1, i + scene.size[i])) == descendants[i]
    # Below a leaf lies its cluster tree alone: groups whose triangles are their children's,
    # over clusters (no children) that cut the mesh's triangles into consecutive runs, in order.
    clusters = scene.cluster_of >= 0
    assert not (clusters & scene.is_leaf).any()
    first, count = scene.cluster_faces
    for leaf in scene.leaves:
        below = np.arange(leaf + 1, leaf + scene.size[leaf])
        assert clusters[below].all() and (scene.cluster_leaf[below] == leaf).all()
        for node in (leaf, *below):
            kids = scene.children[scene.child_start[node]:scene.child_start[node] + scene.child_count[node]]
            if len(kids):
                assert len(kids) <= max(int(scene.hierarchy.partition(":")[2] or 8), 2)
                assert first[kids[0]] == first[node]
                assert (first[kids[1:]] == (first + count)[kids[:-1]]).all()
                assert (first + count)[kids[-1]] == (first + count)[node]
        units = below[scene.child_count[below] == 0]
        if len(units):
            assert count[units].max() <= scene.cluster_size
            assert count[leaf] == len(scene.leaf_mesh(leaf)[1])
    assert (scene.cluster_leaf[~clusters] == -1).all()
    assert all(scene.geometry[i] is not None for i in scene.leaves)
    start, count = scene.leaf_range
    leaves = set(scene.leaves.tolist())
    for i in range(n):
        under = scene.leaves[start[i]:start[i] + count[i]]
        mine = {j for j in descendants[i] | {i} if j in leaves}  # i itself when a leaf
        assert set(under.tolist()) <= mine and len(under) == len(mine)


def _descendants(scene) -> list[set]:
    """Per node, the nodes below it, found by walking up from each node along ``parent``
    alone (not ``size``, ``children`` or the order, which the checks test)."""
    below = [set() for _ in range(len(scene))]
    for j in range(len(scene)):
        p = scene.parent[j]
        while p >= 0:
            below[p].add(j)
            p = scene.parent[p]
    return below


@pytest.mark.parametrize("name,leaves", [("CesiumMilkTruck.glb", 5), ("TestScene.gltf", 9),
                                         ("FM1_satellite.3DXML", 62)])
def test_real_scenes_load_and_follow_the_file_tree(name, leaves):
    scene = load(str(SCENES / name))
    check_invariants(scene)
    assert len(scene.leaves) == leaves
    tm = load_trimesh(SCENES / name)
    assert len(tm.graph.nodes_geometry) == leaves


def test_names_are_stable_across_loads():
    """trimesh names the extra primitives of a glTF mesh at random; ours do not change."""
    a = load(str(SCENES / "CesiumMilkTruck.glb")).names
    b = load(str(SCENES / "CesiumMilkTruck.glb")).names
    assert a == b
    assert "0:Cesium_Milk_Truck_1" in a


def test_flat_obj_gets_a_spatial_hierarchy_that_can_be_switched_off():
    flat = load(str(SCENES / "sportsCar.zip"), hierarchy="file")
    assert flat.stats["internal"] == 0 and len(flat.leaves) == 1075
    auto = load(str(SCENES / "sportsCar.zip"), hierarchy="auto", branching=8)
    check_invariants(auto)
    assert auto.synthetic.sum() > 50 and (auto.child_count[~auto.is_leaf] <= 8).all()
    assert sorted(auto.names[i] for i in auto.leaves) == sorted(flat.names[i] for i in flat.leaves)


def test_node_with_geometry_and_children_is_a_leaf_for_its_own_geometry():
    scene = Scene.from_trimesh(random_scene(5, leaves=10))
    node = scene.index["g_self"]
    assert not scene.is_leaf[node]
    first = scene.children[scene.child_start[node]]
    assert scene.is_leaf[first] and scene.names[first] == "g_self"
    assert scene.geometry[first] == "selfmesh"


def test_empty_subtrees_are_dropped():
    s = trimesh.Scene()
    s.graph.update(frame_from="world", frame_to="empty_group", matrix=np.eye(4))
    s.add_geometry(trimesh.creation.box(), node_name="box", geom_name="box")
    scene = Scene.from_trimesh(s)
    assert "empty_group" not in scene.index and "box" in scene.index


def test_spatial_groups_are_compact_and_bounded():
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.normal(size=(100, 3)) + c for c in ([0, 0, 0], [50, 0, 0])])
    groups = spatial_groups(pts, 4)
    assert len(groups) <= 4

    def flat(g):
        return [g] if isinstance(g, np.ndarray) else [x for h in g for x in flat(h)]

    leaves = flat(groups)
    assert all(len(g) <= 4 for g in leaves)
    assert sorted(np.concatenate(leaves).tolist()) == list(range(200))
    # the two clusters are never mixed at the top
    assert all(len({int(i >= 100) for i in np.concatenate(flat(g))}) == 1 for g in groups)


def test_several_cluster_sizes_from_one_read_are_the_scenes_load_builds():
    """``load_sizes`` reads the file once and builds every size from it: each scene is the
    one ``load`` builds alone (so the build leaves what it reads as it was)."""
    spec = str(SCENES / "CesiumMilkTruck.glb")
    sizes = (None, 32, 256)
    many = load_sizes(spec, sizes)
    for size in sizes:
        one, other = load(spec, clusters=size, cache="off"), many[size]
        assert list(one.names) == list(other.names) and one.settings == other.settings
        assert one.cluster_size == other.cluster_size
        for name in ("parent", "child_start", "children", "cluster_of", "cluster_leaf"):
            assert np.array_equal(getattr(one, name), getattr(other, name)), name
        for name in ("vertices", "faces", "face_start"):
            assert np.array_equal(getattr(one.meshes, name), getattr(other.meshes, name)), name
    assert len(many[32]) > len(many[256]) > len(many[None])  # the sizes did differ


@pytest.mark.parametrize("bad", ["nonexistent_scene_name", "/no/such/file.glb"])
def test_unknown_scenes_are_clear_errors(bad):
    with pytest.raises(InputError):
        load(bad)


def test_unreadable_file_is_a_clear_error(tmp_path):
    f = tmp_path / "broken.glb"
    f.write_bytes(b"glTF not really")
    with pytest.raises(InputError, match="cannot read scene"):
        load(str(f))


def test_a_zip_bomb_is_refused_before_it_is_inflated(tmp_path, monkeypatch, capsys):
    """A member that inflates past a hundred times its packed size (and past the free
    allowance) is refused from the zip's directory, in one line on the command line; the
    scene zips in the repository pass."""
    import zipfile

    from wallcull import cli
    from wallcull import scene as S

    monkeypatch.setattr(S, "INFLATE_FREE", 1 << 20)
    bomb = tmp_path / "bomb.zip"
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("model.obj", bytes(8 << 20))  # 8 MiB of zeros: about 1,000 times
    inflated = []
    monkeypatch.setattr(zipfile.ZipFile, "read", lambda self, name, pwd=None:
                        inflated.append(name) or b"")
    with pytest.raises(InputError, match="model.obj.*inflates .* times.*zip bomb"):
        load(str(bomb))
    assert cli.main(["cull", str(bomb), "--wall", "examples/wall-4x4.json",
                     "--frame", "examples/frame.json"]) == 2
    err = capsys.readouterr().err.strip()
    assert "zip bomb" in err and len(err.splitlines()) == 1, err
    assert inflated == []
    monkeypatch.undo()
    for packed in SCENES.glob("*.zip"):
        S.check_archive(packed)


# ------------------------------------------------------------------ dynamic scenes


def random_moves(scene, rng, count):
    nodes = rng.choice(np.arange(1, len(scene)), size=count, replace=False)
    updates = {}
    for n in nodes:
        if scene.synthetic[n] or scene.names[n] in updates:
            continue
        m = scene.local[scene.index[scene.names[n]]].copy()
        from scipy.spatial.transform import Rotation

        r = Rotation.from_rotvec(rng.normal(size=3) * 0.5).as_matrix()
        m[:3, :3] = r @ m[:3, :3]
        m[:3, 3] += rng.normal(size=3)
        updates[scene.names[n]] = m
    return updates


@pytest.mark.parametrize("refit", ["obb", "aabb"])
@pytest.mark.parametrize("seed", range(6))
def test_moved_scene_stays_conservative(seed, refit):
    rng = np.random.default_rng(seed)
    scene = Scene.from_trimesh(random_scene(seed, leaves=25))
    state = SceneState(scene, "obb")
    wall_spec = random_wall(rng)
    wall = Wall.from_dict(wall_spec)
    for step in range(3):
        updates = random_moves(scene, rng, 4)
        # rigid local transforms under possibly scaled parents: the world motion may not be
        # rigid; move() must handle both
        state.move({k: v for k, v in updates.items()}, refit)
        frame = look_at_frame(rng, state.bounds.center[0], 15.0, wall_spec)
        truth = visible_leaves(scene, wall_spec, frame, 1e-7 * 50, world=state.world)
        for method in METHODS:
            vis = cull(state, Frusta.build(wall, Frame.from_dict(frame, wall)), method)
            for t in range(wall.tiles):
                assert truth[t] <= set(vis.tile_leaves(t).tolist()), (method, step, t)


def test_only_moved_nodes_and_their_ancestors_change():
    scene = load("fatehpur")
    state = SceneState(scene, "obb")
    before = state.bounds.copy()
    leaf = scene.leaves[100]
    m = scene.local[leaf].copy()
    m[:3, 3] += [1.0, 0, 0]
    up = state.move_nodes(np.array([leaf]), m[None])
    ancestors = []
    p = scene.parent[leaf]
    while p >= 0:
        ancestors.append(p)
        p = scene.parent[p]
    assert sorted(up.tolist()) == sorted(ancestors)
    changed = np.flatnonzero((state.bounds.center != before.center).any(1)
                             | (state.bounds.half != before.half).any(1))
    below = set(range(leaf, leaf + scene.size[leaf]))  # the leaf and its clusters
    assert len(below) > 1
    assert set(changed.tolist()) <= set(ancestors) | below
    assert below <= set(changed.tolist())
    shift = scene.world[scene.parent[leaf]][:3, :3] @ [1.0, 0, 0]
    np.testing.assert_allclose(state.bounds.center[sorted(below)],
                               before.center[sorted(below)] + shift)
    np.testing.assert_allclose(state.bounds.center[leaf], before.center[leaf]
                               + scene.world[scene.parent[leaf]][:3, :3] @ [1.0, 0, 0])


def test_aabb_refit_makes_moved_nodes_axis_aligned_and_is_looser():
    scene = load("fatehpur")
    leaves = scene.leaves[::5]
    local = scene.local[leaves].copy()
    local[:, :3, 3] += 0.5
    vols = {}
    for refit in ("obb", "aabb"):
        state = SceneState(scene, "obb")
        state.move_nodes(leaves, local, refit)
        if refit == "aabb":
            assert np.allclose(state.bounds.axes[leaves], np.eye(3))
        vols[refit] = np.prod(state.bounds.half[leaves], axis=1).sum()
    assert vols["aabb"] > vols["obb"]


def test_bad_updates_are_rejected():
    scene = Scene.from_trimesh(random_scene(1, leaves=5))
    state = SceneState(scene)
    with pytest.raises(InputError, match="unknown node"):
        state.move({"nope": np.eye(4)})
    with pytest.raises(InputError, match="singular"):
        state.move({"leaf0": np.diag([0.0, 1, 1, 1])})
    with pytest.raises(InputError, match="affine"):
        state.move({"leaf0": np.ones((4, 4))})
    state.move({"leaf0": np.diag([2.0, 1, 1, 1])})  # scaling is a legitimate update
    with pytest.raises(InputError, match="unit quaternion"):
        state.move({"leaf0": {"position": [0, 0, 0], "orientation": [2, 0, 0, 0]}})
    state.move({"leaf0": {"position": [1, 2, 3], "orientation": [1, 0, 0, 0]}})
    assert np.allclose(state.local[scene.index["leaf0"]][:3, 3], [1, 2, 3])


@pytest.mark.parametrize("refit", ["obb", "aabb"])
def test_repeated_moves_do_not_grow_the_bounds(refit):
    """Moving the same nodes frame after frame ends with the same bounds as moving them once
    from rest to the final pose: no box of a box of a box."""
    from wallcull.bench import Motion

    scene = load("fatehpur")
    motion = Motion(scene, 0.3, seed=1)
    groups = scene.levels[3][~scene.is_leaf[scene.levels[3]]][:5]  # some internal nodes too
    nodes = np.concatenate([motion.nodes, groups])
    group_local = scene.local[groups].copy()
    walked = SceneState(scene, "obb")
    for k in range(40):
        local = np.concatenate([motion.at(k), group_local])
        group_local[:, :3, 3] += 0.01  # the groups drift a little each frame
        walked.move_nodes(nodes, local, refit)
    once = SceneState(scene, "obb")
    once.move_nodes(nodes, local, refit)
    vol = lambda b: np.prod(b.half + b.radius[:, None], axis=1)
    np.testing.assert_allclose(vol(walked.bounds), vol(once.bounds), rtol=1e-6)
    np.testing.assert_allclose(walked.bounds.center, once.bounds.center, atol=1e-6)


def poison_refits(monkeypatch):
    """Every refit from now on comes out non-finite; the real ``bounds.enclose`` back."""
    from wallcull import bounds as bnd

    real = bnd.enclose

    def poisoned(*args, **kw):
        out = real(*args, **kw)
        out.center[:] = np.nan
        return out

    monkeypatch.setattr(bnd, "enclose", poisoned)
    return real


def test_a_move_that_fails_changes_nothing(monkeypatch):
    """All or nothing: if a refit turns out non-finite, the scene state is as before."""
    scene = Scene.from_trimesh(random_scene(2, leaves=12))
    state = SceneState(scene)
    before = [a.copy() for a in (state.local, state.world, state.bounds.center, state.exact.center)]
    poison_refits(monkeypatch)
    m = scene.local[scene.index["leaf3"]].copy()
    m[:3, 3] += 1.0
    with pytest.raises(InputError, match="overflow"):
        state.move({"leaf3": m})
    after = (state.local, state.world, state.bounds.center, state.exact.center)
    for a, b in zip(before, after):
        np.testing.assert_array_equal(a, b)


def _reach(scene, leaf):
    """``(sub, up)`` of a move of one leaf: its subtree (itself and its clusters) and its
    ancestors."""
    up, p = [], scene.parent[leaf]
    while p >= 0:
        up.append(p)
        p = scene.parent[p]
    return np.arange(leaf, leaf + scene.size[leaf]), np.array(sorted(up), dtype=np.int64)


class _Watched(np.ndarray):
    """An array that notes the length of every whole copy made of it."""
    copies: list = []

    def copy(self, *args, **kw):
        _Watched.copies.append(len(self))
        return super().copy(*args, **kw)


def test_a_move_backs_up_and_checks_only_the_rows_it_changes(monkeypatch):
    """A move copies and checks the rows it changes (the moved subtrees and the refit
    ancestors), not every row of the scene: at a million nodes that cost 0.8 s a move, even of
    one leaf. The moves still land as unchecked ones do."""
    from wallcull import bounds as bnd

    scene = load("fatehpur")
    state, plain = SceneState(scene), SceneState(scene)
    leaves = [int(i) for i in scene.leaves[[100, 300, 450]]]
    m = scene.local[leaves[0]].copy()
    m[:3, 3] += 1.0
    state.move({scene.names[leaves[0]]: m})  # the first move copies the scene's arrays
    plain.move_nodes(np.array([leaves[0]]), m[None])
    state.local, state.world = state.local.view(_Watched), state.world.view(_Watched)
    copied, checked = [], []
    real_copy, real_det = bnd.Bounds.copy, np.linalg.det
    monkeypatch.setattr(bnd.Bounds, "copy", lambda b: copied.append(len(b)) or real_copy(b))
    monkeypatch.setattr(np.linalg, "det", lambda a: checked.append(len(a)) or real_det(a))
    _Watched.copies = []
    for leaf in leaves[1:]:
        m = scene.local[leaf].copy()
        m[:3, 3] += [0.0, 0.5, 0.0]
        sub, up = _reach(scene, leaf)
        assert 0 < len(sub) + len(up) < len(scene) // 10
        state.move({scene.names[leaf]: m})
        plain.move_nodes(np.array([leaf]), m[None])
        assert checked and max(checked) <= len(sub), (checked, len(sub))
        checked.clear()
    assert not copied and not _Watched.copies, (copied, _Watched.copies)
    np.testing.assert_array_equal(np.asarray(state.world), plain.world)
    for a, b in ((state.bounds, plain.bounds), (state.exact, plain.exact)):
        np.testing.assert_array_equal(a.center, b.center)
        np.testing.assert_array_equal(a.half, b.half)


def test_a_refused_move_after_others_restores_its_rows_and_their_records(monkeypatch):
    """All or nothing on the row-wise path: once the state owns its arrays, a refused move
    puts back exactly the rows it changed, and the packed records the culler reads follow."""
    from wallcull import bounds as bnd
    from wallcull.cull import pack, packed

    scene = Scene.from_trimesh(random_scene(2, leaves=30))
    state = SceneState(scene)
    m = scene.local[scene.index["leaf5"]].copy()
    m[:3, 3] += 1.0
    state.move({"leaf5": m})
    packed(state)
    arrays = lambda: [np.array(a) for a in (state.local, state.world, state.bounds.center,
                                             state.bounds.half, state.bounds.radius,
                                             state.exact.center, state.exact.half)]
    before, records = arrays(), packed(state).copy()
    real = poison_refits(monkeypatch)
    m = scene.local[scene.index["leaf3"]].copy()
    m[:3, 3] += 2.0
    with pytest.raises(InputError, match="overflow"):
        state.move({"leaf3": m})
    for a, b in zip(before, arrays()):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(packed(state), records)
    monkeypatch.setattr(bnd, "enclose", real)
    state.move({"leaf3": m})  # and the state still moves
    np.testing.assert_array_equal(packed(state), pack(state.bounds))


def test_updates_out_of_range_are_refused():
    state = SceneState(Scene.from_trimesh(random_scene(1, leaves=5)))
    for bad in ({"position": [0, 0, 0], "orientation": [1, 0, 0, 0], "scale": [1e-12, 1, 1]},
                {"position": [1e16, 0, 0], "orientation": [1, 0, 0, 0]}):
        with pytest.raises(InputError, match="out of range"):
            state.move({"leaf0": bad})


def test_a_state_shares_its_scenes_arrays_until_something_moves():
    """Walls that never move a node cost no copy of the scene (1.3 GB at a million nodes with
    their clusters); the first move copies, and the scene itself never changes."""
    scene = Scene.from_trimesh(random_scene(4, leaves=20))
    rest = {k: getattr(scene, k).copy() for k in ("local", "world")}
    rest_bounds = scene.bounds("obb").copy()
    states = [SceneState(scene, "obb") for _ in range(2)]
    for state in states:
        assert state.world is scene.world and state.local is scene.local
        assert state.bounds is scene.bounds("obb") and state.exact is state.bounds
    m = scene.local[scene.index["leaf3"]].copy()
    m[:3, 3] += 1.0
    states[0].move({"leaf3": m}, "aabb")
    assert not np.shares_memory(states[0].world, scene.world)
    assert not np.shares_memory(states[0].bounds.center, scene.bounds("obb").center)
    assert not np.shares_memory(states[0].exact.center, states[0].bounds.center)
    assert states[1].world is scene.world  # the other wall still shares
    for k, a in rest.items():
        np.testing.assert_array_equal(getattr(scene, k), a)
    np.testing.assert_array_equal(scene.bounds("obb").center, rest_bounds.center)
    np.testing.assert_array_equal(scene.bounds("obb").half, rest_bounds.half)
    assert not np.array_equal(states[0].world, scene.world)


@pytest.mark.parametrize("seed", range(4))
def test_a_states_box_follows_its_moves(seed):
    """A state's box is its scene's box at rest, holds every vertex as its nodes now lie
    after random moves (turns under scaled parents among them), is the box of the moved
    vertices exactly after a translation of leaves placed without a turn, and is the rest box
    again once the moved nodes are put back."""
    rng = np.random.default_rng(seed)
    scene = Scene.from_trimesh(random_scene(seed, leaves=25))
    state = SceneState(scene, "obb")
    np.testing.assert_array_equal(state.box(), scene.box)
    rest = {n: scene.local[scene.index[n]].copy() for n in scene.names[1:]
            if not scene.synthetic[scene.index[n]]}
    for _ in range(3):
        updates = random_moves(scene, rng, 4)
        state.move(updates)
        points = np.concatenate([scene.leaf_vertices(int(leaf), state.world[leaf])
                                 for leaf in scene.leaves])
        lo, hi = state.box()
        assert (points >= lo - 1e-9 * np.abs(lo).max()).all()
        assert (points <= hi + 1e-9 * np.abs(hi).max()).all()
    state.move({n: m for n, m in rest.items()})
    np.testing.assert_array_equal(state.box(), scene.box)
    s = trimesh.Scene()  # leaves without a turn, moved by 1000 m: their box moves with them
    for k in range(3):
        m = np.eye(4)
        m[:3, 3] = [3 * k, k, -k]
        s.add_geometry(trimesh.creation.icosphere(1, radius=0.5 + k), node_name=f"s{k}",
                       geom_name=f"s{k}", transform=m)
    scene = Scene.from_trimesh(s, hierarchy="file", clusters=None)
    state = SceneState(scene)
    m = scene.local[scene.index["s2"]].copy()
    m[:3, 3] += [1000, 0, 0]
    state.move({"s2": m})
    points = np.concatenate([scene.leaf_vertices(int(leaf), state.world[leaf])
                             for leaf in scene.leaves])
    np.testing.assert_allclose(state.box(), [points.min(axis=0), points.max(axis=0)])
