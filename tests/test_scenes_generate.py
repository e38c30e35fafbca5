"""The bundled scene generators: deterministic, shaped like the paper's models, well-formed trees.

Targets are the paper's section 5 (Fatehpur Sikri: 288 internal + 482 leaves, branching 2.67;
UNC power plant: 1,118 internal + 3,919 leaves, branching 4.5) and the project brief (about
1.6 M and 1 M triangles). Builds are cached per module: nothing here mutates a scene.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from wallcull import bundled
from wallcull.bundled import meshes
from wallcull.bundled.generate import digest, tree_stats
from wallcull.bundled.tree import members, placements, polyline_pipe

TARGETS = {
    #              internal, leaves, branching, triangles (lo, hi), half extent x/z, max height
    "fatehpur": (288, 482, 2.67, (1_200_000, 2_000_000), 160.0, 55.0),
    "powerplant": (1118, 3919, 4.5, (900_000, 1_200_000), 45.0, 62.0),
}


@pytest.fixture(scope="module")
def built():
    """name -> scene built with seed 0, shared by the read-only tests below."""
    return {name: bundled.build(name) for name in bundled.BUNDLED}


def world_transforms(scene: trimesh.Scene) -> dict[str, np.ndarray]:
    return {n: scene.graph.get(n)[0] for n in scene.graph.nodes if n != scene.graph.base_frame}


# ---------------------------------------------------------------------------------------------
# the public API


def test_bundled_names_and_descriptions():
    assert {"fatehpur", "powerplant"} <= set(bundled.BUNDLED)
    assert all(isinstance(d, str) and d and "\n" not in d for d in bundled.BUNDLED.values())


def test_unknown_name_raises_key_error():
    with pytest.raises(KeyError):
        bundled.build("taj_mahal")
    with pytest.raises(KeyError):
        bundled.settings("taj_mahal")


def test_bundled_settings_are_valid_and_fresh_copies():
    from wallcull.settings import parse

    assert parse(bundled.settings("powerplant")).empty  # asks for nothing
    fatehpur = parse(bundled.settings("fatehpur"))
    assert [l.name for l in fatehpur.lights] == ["sun"]
    assert [m.name for m in fatehpur.mirrors] == ["anup_talao"]
    bundled.settings("fatehpur")["lights"].clear()
    assert bundled.settings("fatehpur")["lights"]  # callers cannot change the registry


# ---------------------------------------------------------------------------------------------
# determinism


@pytest.mark.parametrize("name", ["fatehpur", "powerplant"])
def test_same_seed_same_scene(built, name):
    again = bundled.build(name)
    a, b = built[name], again
    assert list(a.graph.transforms.edge_data) == list(b.graph.transforms.edge_data)
    ta, tb = world_transforms(a), world_transforms(b)
    assert all(np.array_equal(ta[n], tb[n]) for n in ta)
    assert {k: g.identifier_hash for k, g in a.geometry.items()} == {k: g.identifier_hash for k, g in b.geometry.items()}
    assert digest(a) == digest(b)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_other_seed_other_scene_same_shape(built, seed):
    for name, (internal, leaves, branching, (tri_lo, tri_hi), *_rest) in TARGETS.items():
        other = bundled.build(name, seed=seed)
        assert digest(other) != digest(built[name])
        s = tree_stats(other)
        assert abs(s["internal"] - internal) <= 0.1 * internal, s
        assert abs(s["leaves"] - leaves) <= 0.1 * leaves, s
        assert abs(s["branching"] - branching) <= 0.15 * branching, s
        assert tri_lo <= s["triangles"] <= tri_hi, s


def test_digest_independent_of_python_hash_seed(built):
    """No set order or ``hash()`` leaks into the scene: another interpreter, another hash seed."""
    code = "from wallcull import bundled; from wallcull.bundled.generate import digest; print(digest(bundled.build('fatehpur')))"
    env = dict(os.environ, PYTHONHASHSEED="12345")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == digest(built["fatehpur"])


# ---------------------------------------------------------------------------------------------
# shape: the paper's counts


@pytest.mark.parametrize("name", ["fatehpur", "powerplant"])
def test_counts_match_the_paper(built, name):
    internal, leaves, branching, (tri_lo, tri_hi), *_ = TARGETS[name]
    s = tree_stats(built[name])
    assert abs(s["internal"] - internal) <= 0.10 * internal, s
    assert abs(s["leaves"] - leaves) <= 0.10 * leaves, s
    assert abs(s["branching"] - branching) <= 0.15 * branching, s
    assert tri_lo <= s["triangles"] <= tri_hi, s
    assert 5 <= s["depth"] <= 8, s


def test_tree_stats_on_a_tiny_scene():
    scene = trimesh.Scene()
    scene.geometry["box"] = meshes.template("box")
    scene.graph.update(frame_from="world", frame_to="root")
    scene.graph.update(frame_from="root", frame_to="a", geometry="box")
    scene.graph.update(frame_from="root", frame_to="g")
    scene.graph.update(frame_from="g", frame_to="b", geometry="box")
    assert tree_stats(scene) == {"nodes": 4, "internal": 2, "leaves": 2, "branching": 1.5, "depth": 3, "triangles": 24}


# ---------------------------------------------------------------------------------------------
# a well-formed tree


@pytest.mark.parametrize("name", ["fatehpur", "powerplant"])
def test_tree_is_well_formed(built, name):
    scene = built[name]
    graph = scene.graph
    children = graph.transforms.children
    parents = graph.transforms.parents
    base = graph.base_frame
    nodes = [n for n in graph.nodes if n != base]
    leaves = set(graph.nodes_geometry)
    # one root under the base frame, named after the scene
    assert list(children[base]) == [name]
    # every leaf carries a known geometry and has no children; every group has children
    for n in nodes:
        if n in leaves:
            assert graph.get(n)[1] in scene.geometry
            assert not children.get(n)
        else:
            assert children.get(n), n
    # every node reaches the base frame, and its name is its parent's path plus one readable part
    for n in nodes:
        p, hops = n, 0
        while p != base:
            p = parents[p]
            hops += 1
            assert hops < 20
        if n != name:
            assert n.startswith(parents[n] + "/") and re.fullmatch(r"[a-z0-9_]+", n[len(parents[n]) + 1:]), n
    assert len(set(nodes)) == len(nodes)


@pytest.mark.parametrize("name", ["fatehpur", "powerplant"])
def test_transforms_decompose_as_glTF_wants(built, name):
    """Groups are rigid; leaves are translation x rotation x scale (orthogonal columns)."""
    edges = built[name].graph.transforms.edge_data
    for (_, child), edge in edges.items():
        m = edge["matrix"]
        assert np.array_equal(m[3], [0, 0, 0, 1])
        gram = m[:3, :3].T @ m[:3, :3]
        assert np.allclose(gram, np.diag(np.diag(gram)), atol=1e-9 * gram.max()), child
        assert np.linalg.det(m[:3, :3]) > 0, child
        if "geometry" not in edge:
            assert np.allclose(gram, np.eye(3), atol=1e-9), child


@pytest.mark.parametrize("name", ["fatehpur", "powerplant"])
def test_extents_are_bounded_and_y_up(built, name):
    *_, half, height = TARGETS[name]
    lo, hi = built[name].bounds
    assert -half <= lo[0] and hi[0] <= half and -half <= lo[2] and hi[2] <= half
    assert -2.0 <= lo[1] <= 0.5 and 0.8 * height <= hi[1] <= height  # ground near y = 0, y is up


@pytest.mark.parametrize("name", ["fatehpur", "powerplant"])
def test_geometry_is_instanced(built, name):
    scene = built[name]
    assert len(scene.geometry) <= 40
    assert len(scene.graph.nodes_geometry) > 10 * len(scene.geometry)


def test_powerplant_has_many_parts_off_the_axes(built):
    """Oriented boxes must have something to win: diagonal braces, 45-degree and turned pipes,
    rotated equipment, the tilted conveyor."""
    scene = built["powerplant"]
    off = 0
    for n in scene.graph.nodes_geometry:
        r = scene.graph.get(n)[0][:3, :3]
        r = r / np.linalg.norm(r, axis=0)
        off += np.abs(r).max(axis=0).min() < 0.99
    assert off >= 0.2 * len(scene.graph.nodes_geometry)


# ---------------------------------------------------------------------------------------------
# templates and placement helpers


@pytest.mark.parametrize("name", sorted(meshes.TEMPLATES))
def test_templates_are_clean_solids(name):
    mesh = meshes.template(name)
    assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
    assert np.all(np.isfinite(mesh.vertices))
    assert mesh.is_winding_consistent
    if not name.startswith("elbow"):  # bends are open tubes; everything else is closed
        assert mesh.is_watertight
    assert mesh.volume > 0  # wound outward
    assert np.all(np.abs(mesh.vertices) <= 5.0)


def test_templates_are_bit_identical_on_every_call():
    a, b = meshes.template("onion_dome"), meshes.template("onion_dome")
    assert a.vertices is not b.vertices
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)


def test_pipe_bends_meet_the_straight_pipes():
    """A bend placed by polyline_pipe starts where one straight ends and ends where the next
    starts, for 90 and 45 degree corners."""
    pts = np.array([[0, 0, 0], [5, 0, 0], [5, 4, 0], [8, 7, 0], [8, 7, 6.0]])
    ends, bends, angles = polyline_pipe(pts, radius=0.2)
    assert np.allclose(angles, [90, 45, 90])
    for k, (m, a) in enumerate(zip(bends, np.radians(angles))):
        start = m @ [0, 0, 0, 1]
        stop = m @ [1.5 * (1 - np.cos(a)), 0, 1.5 * np.sin(a), 1]
        assert np.allclose(start[:3], ends[k, 1]) and np.allclose(stop[:3], ends[k + 1, 0])


def test_members_stretch_a_unit_prism_between_points():
    p0, p1 = np.array([[1.0, 2, 3], [0, 0, 0]]), np.array([[4.0, 6, 3], [0, 0, 5]])
    m = members(p0, p1, (0.2, 0.4))
    assert np.allclose(m[:, :3, :3] @ [0, 0, -0.5] + m[:, :3, 3], p0)
    assert np.allclose(m[:, :3, :3] @ [0, 0, 0.5] + m[:, :3, 3], p1)
    assert np.allclose(np.linalg.norm(m[:, :3, :3], axis=1), [[0.2, 0.4, 5.0], [0.2, 0.4, 5.0]])
    assert np.allclose(m[0, :3, 1] / 0.4, [0, 0, 1])  # a horizontal beam's depth stands upright


def test_placements_scale_turn_move():
    m = placements([[1.0, 2, 3]], np.pi / 2, (2.0, 3.0, 4.0))[0]
    assert np.allclose(m @ [1, 0, 0, 1], [1, 4, 3, 1])
    assert np.allclose(m @ [0, 1, 0, 1], [-2, 2, 3, 1])
    assert np.allclose(m @ [0, 0, 1, 1], [1, 2, 7, 1])


# ---------------------------------------------------------------------------------------------
# files and speed


def test_glb_round_trip_keeps_the_tree(built):
    scene = built["fatehpur"]
    data = scene.export(file_type="glb")
    back = trimesh.load(trimesh.util.wrap_as_stream(data), file_type="glb")
    assert set(back.graph.nodes_geometry) == set(scene.graph.nodes_geometry)
    assert tree_stats(back) == tree_stats(scene)
    before, after = world_transforms(scene), world_transforms(back)
    assert set(before) == set(after)
    assert all(np.allclose(before[n], after[n], atol=1e-6) for n in before)
