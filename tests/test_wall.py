"""The wall, frames, tile frusta and the frustum hierarchy against SPEC sections 2-3."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from wallcull.errors import InputError
from wallcull.wall import (Frame, Frusta, Wall, display_planes, matrix_quaternion,
                           matrix_quaternions, quaternion_matrix)

from wallcull.oracle import tile_planes_display

SPEC_WALL = {"cols": 4, "rows": 4, "tile_size": [0.60, 0.34], "gap": [0.012, 0.012],
             "distance": 2.0, "near": 0.1, "far": 1000.0, "resolution": [1920, 1080]}


def wall_of(cols, rows, gap=(0.0, 0.0), **kw):
    return Wall.from_dict({**SPEC_WALL, "cols": cols, "rows": rows, "gap": list(gap), **kw})


def test_tile_rectangles_follow_the_spec_formulae():
    wall = Wall.from_dict(SPEC_WALL)
    W = 4 * 0.60 + 3 * 0.012
    H = 4 * 0.34 + 3 * 0.012
    assert wall.size == pytest.approx((W, H))
    # tile (row 1, col 2) has id 1*4 + 2 = 6
    x0, x1, y0, y1 = wall.tile_rect(6)
    assert x0 == pytest.approx(-W / 2 + 2 * 0.612)
    assert x1 == pytest.approx(x0 + 0.60)
    assert y1 == pytest.approx(H / 2 - 1 * 0.352)
    assert y0 == pytest.approx(y1 - 0.34)
    # row 0 is the top, col 0 the left
    assert wall.tile_rect(0)[3] == pytest.approx(H / 2)
    assert wall.tile_rect(0)[0] == pytest.approx(-W / 2)
    assert wall.tile_rect(15)[1] == pytest.approx(W / 2)
    assert wall.tile_rect(15)[2] == pytest.approx(-H / 2)


@pytest.mark.parametrize("cols,rows", [(1, 1), (3, 5), (1, 8), (7, 1), (64, 64), (5, 3)])
@pytest.mark.parametrize("gap", [(0.0, 0.0), (0.05, 0.02), (-0.1, -0.05)])
def test_frustum_hierarchy_bisects_down_to_every_tile_once(cols, rows, gap):
    wall = wall_of(cols, rows, gap)
    fh = wall.hierarchy
    leaves = fh.tile[fh.tile >= 0]
    assert sorted(leaves.tolist()) == list(range(cols * rows))
    assert len(fh) == 2 * cols * rows - 1
    lay = wall.layout
    for i in np.flatnonzero(fh.tile < 0):
        a, b = fh.first[i], fh.second[i]
        nc, nr = fh.c1[i] - fh.c0[i], fh.r1[i] - fh.r0[i]
        if nc >= nr:  # larger dimension first, columns on a tie; first half takes the extra
            k = fh.c0[i] + (nc + 1) // 2
            assert (fh.c0[a], fh.c1[a], fh.c0[b], fh.c1[b]) == (fh.c0[i], k, k, fh.c1[i])
            assert (fh.plane_a[i], fh.plane_b[i]) == (lay.R(k - 1), lay.L(k))
        else:
            k = fh.r0[i] + (nr + 1) // 2
            assert (fh.r0[a], fh.r1[a], fh.r0[b], fh.r1[b]) == (fh.r0[i], k, k, fh.r1[i])
            assert (fh.plane_a[i], fh.plane_b[i]) == (lay.B(k - 1), lay.T(k))
    assert fh.height == int(np.ceil(np.log2(cols))) + int(np.ceil(np.log2(rows)))


@settings(max_examples=60, deadline=None)
@given(cols=st.integers(1, 9), rows=st.integers(1, 9),
       gx=st.floats(-0.2, 0.3), gy=st.floats(-0.1, 0.3),
       ex=st.floats(-3, 3), ey=st.floats(-3, 3), ez=st.floats(-1.85, 5))
def test_tile_planes_match_first_principles(cols, rows, gx, gy, ex, ey, ez):
    spec = {**SPEC_WALL, "cols": cols, "rows": rows, "gap": [gx, gy]}
    wall = Wall.from_dict(spec)
    eye = np.array([ex, ey, ez])
    table = display_planes(wall, eye)
    for tile in range(wall.tiles):
        ours = table[wall.layout.tile_planes[tile]]  # L, R, T, B, near, far
        ref = tile_planes_display(spec, eye, tile)  # bottom, right, top, left, near, far
        ref = ref[[3, 1, 2, 0, 4, 5]]
        np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=1e-12)


def test_bezel_and_overlap_split_planes_differ():
    eye = np.zeros(3)
    for gap, sign in [((0.1, 0.1), 1), ((-0.1, -0.1), -1)]:
        wall = wall_of(2, 1, gap)
        p = display_planes(wall, eye)
        lay = wall.layout
        R0, L1 = p[lay.R(0)], p[lay.L(1)]
        # a point straight behind the middle of the gap (or overlap), on the wall
        mid = np.array([0.0, 0.0, -wall.distance])
        in0, in1 = R0[:3] @ mid + R0[3] >= 0, L1[:3] @ mid + L1[3] >= 0
        assert (in0, in1) == ((False, False) if sign > 0 else (True, True))


def test_frame_places_display_space_in_the_world():
    wall = Wall.from_dict(SPEC_WALL)
    # 90 degrees about y: display -z (the view direction) becomes world -x
    q = [np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0]
    frame = Frame.from_dict({"position": [10, 0, 0], "orientation": q}, wall)
    np.testing.assert_allclose(frame.to_world(np.array([0, 0, -1.0])), [9, 0, 0], atol=1e-12)
    frusta = Frusta.build(wall, frame)
    ahead = np.array([5.0, 0, 0, 1])  # in front of the camera, centre of the wall
    primary = frusta.primary
    assert (primary @ ahead >= 0).all()
    behind = np.array([15.0, 0, 0, 1])
    assert (primary @ behind < 0).any()


@pytest.mark.parametrize("frame,message", [
    ({"position": [0, 0, 0], "orientation": [1, 0, 0, 0.01]}, "unit quaternion"),
    ({"position": [0, 0, 0], "orientation": [1, 0, 0, 0], "eye": [0, 0, -1.95]}, "in front"),
    ({"position": [0, 0], "orientation": [1, 0, 0, 0]}, "3 numbers"),
    ({"position": [0, 0, float("nan")], "orientation": [1, 0, 0, 0]}, "finite"),
    ({"orientation": [1, 0, 0, 0]}, "missing"),
    ({"position": [0, 0, 0], "orientation": [1, 0, 0, 0], "eyes": [0, 0, 0]}, "unknown"),
    ({"position": [1e16, 0, 0], "orientation": [1, 0, 0, 0]}, r"position\[0\] must be at most"),
    ({"position": [0, 0, 0], "orientation": [1, 0, 0, 0], "eye": [0, 0, 1e10]},
     r"eye\[2\] must be at most"),
])
def test_bad_frames_are_rejected_with_a_clear_message(frame, message):
    with pytest.raises(InputError, match=message):
        Frame.from_dict(frame, Wall.from_dict(SPEC_WALL))


def test_quaternion_within_tolerance_is_accepted_and_normalized():
    wall = Wall.from_dict(SPEC_WALL)
    frame = Frame.from_dict({"position": [0, 0, 0], "orientation": [1 + 5e-7, 0, 0, 0]}, wall)
    assert np.linalg.norm(frame.orientation) == pytest.approx(1, abs=1e-15)


@pytest.mark.parametrize("patch,message", [
    ({"cols": 0}, "at least 1"),
    ({"rows": -2}, "at least 1"),
    ({"cols": 1000, "rows": 1000}, "at most"),
    ({"cols": 2.5}, "whole number"),
    ({"tile_size": [0.6]}, "2 numbers"),
    ({"tile_size": [0.6, -1]}, r"tile_size\[1\] must be at least 1e-09, got -1"),
    ({"gap": [-0.7, 0]}, "overlaps a whole tile"),
    ({"near": 5, "far": 1}, "near < far"),
    ({"distance": 0}, "distance must be at least 1e-09, got 0"),
    ({"colls": 3}, "unknown"),
    ({"resolution": [1920]}, "resolution"),
    ({"tile_size": [1e-12, 0.3]}, "at least 1e-09"),
    ({"distance": 1e12}, "at most 1e"),
    ({"cols": 64, "tile_size": [1e-9, 0.3], "gap": [1e9, 0]}, "cannot tell"),
])
def test_bad_walls_are_rejected_with_a_clear_message(patch, message):
    with pytest.raises(InputError, match=message):
        Wall.from_dict({**SPEC_WALL, **patch})


def test_wall_defaults():
    wall = Wall.from_dict({"cols": 2, "rows": 1, "tile_size": [1, 1], "distance": 1})
    assert (wall.gap, wall.near, wall.far, wall.resolution) == ((0, 0), 0.1, 1000.0, (1920, 1080))
    assert Wall.from_dict(wall.to_dict()) == wall


def test_matrix_quaternions_round_trip_with_w_not_negative():
    """Random rotations and the half turns (``w = 0``: Shepperd's other branches), one by one
    and all at once: each quaternion is of unit length, has ``w >= 0`` and gives the matrix
    back."""
    rng = np.random.default_rng(7)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    turns = [np.diag(d) for d in ([1.0, -1, -1], [-1.0, 1, -1], [-1.0, -1, 1])]
    m = np.array([*(quaternion_matrix(p) for p in q), np.eye(3), *turns])
    batch = matrix_quaternions(m)
    for k, rotation in enumerate(m):
        one = matrix_quaternion(rotation)
        assert np.array_equal(one, batch[k])
        assert one[0] >= 0 and abs(np.linalg.norm(one) - 1) < 1e-15
        assert np.abs(quaternion_matrix(one) - rotation).max() < 1e-14
    assert np.allclose(np.abs(batch[:500]), np.abs(q), atol=1e-14)  # the same up to sign
