"""What a render node draws: the exact floor kernel against the oracle's clipping, and the
counts of ``wallcull overdraw`` in their order (no culling >= leaves >= clusters >= floor)."""

import json

import numpy as np
from hypothesis import given, settings, strategies as st

from wallcull import oracle, overdraw
from wallcull.cli import main
from wallcull.cull import cull
from wallcull.scene import Scene, SceneState
from wallcull.wall import Frame, Frusta, Wall

from .randscene import look_at_frame, random_scene, random_wall


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread=st.sampled_from([0.5, 2.0, 8.0]),
       degenerate=st.sampled_from(["none", "point", "segment"]))
def test_a_triangle_meets_a_frustum_as_the_oracle_clips_it(seed, spread, degenerate):
    rng = np.random.default_rng(seed)
    wall = random_wall(rng)
    planes = oracle.tile_planes_display(wall, [0, 0, 0], int(rng.integers(oracle.tiles_of(wall))))
    tris = rng.normal(size=(64, 3, 3)) * spread + [0, 0, -wall["distance"] * 2]
    if degenerate == "point":
        tris[:, 1:] = tris[:, :1]
    elif degenerate == "segment":
        tris[:, 2] = (tris[:, 0] + tris[:, 1]) / 2
    want = oracle.clip_triangles(tris, planes)
    got = np.array([overdraw.triangle_meets(t, planes) for t in tris])
    np.testing.assert_array_equal(got, want)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_the_floor_counts_the_triangles_the_oracle_sees(seed):
    """Per tile, over the leaves the culler lists, the triangles that meet the tile frustum."""
    rng = np.random.default_rng(seed)
    scene = Scene.from_trimesh(random_scene(seed, leaves=int(rng.integers(1, 10)), big=0.5),
                               clusters=32)
    wall_spec = random_wall(rng)
    frame_spec = look_at_frame(rng, scene.leaf_points[0].mean(axis=0), float(rng.uniform(2, 20)),
                               wall_spec)
    wall = Wall.from_dict(wall_spec)
    frusta = Frusta.build(wall, Frame.from_dict(frame_spec, wall))
    vis = cull(SceneState(scene), frusta)
    got = overdraw.floor(scene, frusta, vis)
    for t in range(wall.tiles):
        planes = oracle.tile_frusta(wall_spec, frame_spec, t)[0]
        want = sum(int(oracle.clip_triangles(oracle.leaf_triangles_display(scene, frame_spec, leaf),
                                             planes).sum())
                   for leaf in scene.leaves)  # every leaf: the lists lose none of it
        assert got[t] == want, t
        assert vis.triangles()[t] >= got[t]


def test_overdraw_command_orders_its_counts(capsys):
    assert main(["overdraw", "scenes/CesiumMilkTruck.glb", "--wall", "examples/wall-4x4.json",
                 "--frames", "6", "--sizes", "32,256", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    by = {e["clusters"]: e for e in report["settings"] if not e["occlusion"]}
    assert set(by) == {"off", 32, 256}
    assert report["none"] == 16 * report["triangles"] == 16 * 3624
    assert report["none"] >= by["off"]["triangles"] >= by[256]["triangles"] \
        >= by[32]["triangles"] >= report["floor"] > 0
    assert by[32]["draw_calls"] >= by["off"]["draw_calls"]
    assert by["off"]["over_floor"] > 2 * by[32]["over_floor"]  # the truck is one mesh or so


def test_overdraw_names_the_size_auto_chose_once(capsys):
    """``auto`` is reported as the cluster size it chose (it was "clusters of auto"), and
    asking for that size beside it measures it once."""
    from wallcull.scene import load

    chosen = load("scenes/CesiumMilkTruck.glb").cluster_size
    assert main(["overdraw", "scenes/CesiumMilkTruck.glb", "--wall", "examples/wall-4x4.json",
                 "--frames", "2", "--sizes", f"auto,{chosen}", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert [e["clusters"] for e in report["settings"]] == ["off", chosen]


def test_overdraw_refuses_bad_sizes(capsys):
    assert main(["overdraw", "powerplant", "--sizes", "8"]) == 2
    assert "between 32 and 4096" in capsys.readouterr().err
