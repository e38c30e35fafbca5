"""The oracle's exact shortcuts agree with plain clipping, and false positives are counted."""

import numpy as np
from hypothesis import given, settings, strategies as st

from wallcull.oracle import clip_triangles, false_positives, triangles_meet, visible_leaves

from .test_cull import WALL4, boxes_scene


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread=st.sampled_from([0.1, 1.0, 5.0]))
def test_shortcuts_agree_with_clipping(seed, spread):
    rng = np.random.default_rng(seed)
    # a unit cube as six planes, triangles around it
    planes = np.array([[1, 0, 0, 1], [-1, 0, 0, 1], [0, 1, 0, 1], [0, -1, 0, 1],
                       [0, 0, 1, 1], [0, 0, -1, 1]], float)
    tris = rng.normal(size=(int(rng.integers(1, 6)), 3, 3)) * spread + rng.normal(size=3) * 2
    assert triangles_meet(tris, planes) == clip_triangles(tris, planes).any()


def test_clipping_knows_a_triangle_that_crosses_without_a_vertex_inside():
    planes = np.array([[1, 0, 0, 1], [-1, 0, 0, 1], [0, 1, 0, 1], [0, -1, 0, 1],
                       [0, 0, 1, 1], [0, 0, -1, 1]], float)
    big = np.array([[[-10, -10, 0], [10, -10, 0], [0, 20, 0]]], float)  # covers the cube's middle
    assert clip_triangles(big, planes).all() and triangles_meet(big, planes)
    apart = big + [0, 0, 5]
    assert not triangles_meet(apart, planes)


def test_false_positives_counts_pairs_the_frustum_does_not_meet():
    from wallcull.wall import Wall

    wall = Wall.from_dict(WALL4)
    x0, x1, y0, y1 = wall.tile_rect(9)
    scene = boxes_scene([3 * np.array([(x0 + x1) / 2, (y0 + y1) / 2, -2.0])])
    frame = {"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}
    truth = visible_leaves(scene, WALL4, frame, 0.0)
    assert [sorted(s) for s in truth] == [[1] if t == 9 else [] for t in range(12)]
    reported = [[1] if t in (8, 9, 10) else [] for t in range(12)]
    assert false_positives(scene, WALL4, frame, reported, 1e-9) == (2, 3)
