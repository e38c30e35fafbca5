"""Bounds enclose what they bound, always: random and degenerate point sets, at any scale."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from wallcull import bounds as bnd

SHAPES = ["random", "coplanar", "collinear", "point", "repeated", "cube", "grid"]


def point_set(shape: str, n: int, seed: int, size: float, offset: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if shape == "random":
        p = rng.normal(size=(n, 3)) * rng.uniform(0.01, 1, 3)
    elif shape == "coplanar":
        p = np.c_[rng.normal(size=(n, 2)), np.zeros(n)]
    elif shape == "collinear":
        p = np.outer(rng.normal(size=n), rng.normal(size=3))
    elif shape == "point":
        p = np.zeros((1, 3))
    elif shape == "repeated":
        p = np.repeat(rng.normal(size=(2, 3)), n, axis=0)
    elif shape == "cube":  # repeated eigenvalues
        p = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    else:
        g = np.linspace(-1, 1, 4)
        p = np.stack(np.meshgrid(g, g, g), -1).reshape(-1, 3)
    rot = Rotation.random(random_state=seed).as_matrix()
    return (p @ rot.T) * size + offset * rng.choice([-1, 1], 3)


point_sets = st.builds(
    point_set, shape=st.sampled_from(SHAPES), n=st.integers(1, 60), seed=st.integers(0, 2**31),
    size=st.sampled_from([1e-6, 1e-3, 1.0, 1e3, 1e6]), offset=st.sampled_from([0.0, 1.0, 1e7]))


def segments(sets):
    starts = np.zeros(len(sets) + 1, dtype=np.int64)
    np.cumsum([len(s) for s in sets], out=starts[1:])
    return np.concatenate(sets), starts


@settings(max_examples=150, deadline=None)
@given(sets=st.lists(point_sets, min_size=1, max_size=5),
       kind=st.sampled_from(["obb", "aabb", "sphere", "obb-hull"]))
def test_leaf_bounds_enclose_their_points(sets, kind):
    points, starts = segments(sets)
    b = bnd.LEAF_FITTERS[kind](points, starts)
    assert np.isfinite(b.center).all() and np.isfinite(b.half).all()
    assert (b.half >= 0).all() and (b.radius >= 0).all()
    np.testing.assert_allclose(b.axes @ np.swapaxes(b.axes, 1, 2), np.broadcast_to(np.eye(3), b.axes.shape), atol=1e-12)
    for i, s in enumerate(sets):
        assert b.contains(i, s).all(), f"{kind} misses points of set {i}"


@settings(max_examples=80, deadline=None)
@given(sets=st.lists(point_sets, min_size=2, max_size=6),
       kind=st.sampled_from(["obb", "aabb", "sphere"]), parents=st.integers(1, 3))
def test_internal_bounds_enclose_their_children(sets, kind, parents):
    points, starts = segments(sets)
    children = bnd.LEAF_FITTERS[kind](points, starts)
    # split the children into `parents` consecutive groups
    cuts = np.unique(np.linspace(0, len(sets), parents + 1).astype(int))
    group_starts = cuts.astype(np.int64)
    parent = bnd.enclose(children, group_starts, bnd.enclosing_mode(kind))
    for g in range(len(group_starts) - 1):
        for child in range(group_starts[g], group_starts[g + 1]):
            s = sets[child]
            assert parent.contains(g, s).all()
            # the whole child bound, not only its points
            if kind == "sphere":
                reach = np.linalg.norm(children.center[child] - parent.center[g])
                assert reach + children.radius[child] <= parent.radius[g]
            else:
                assert parent.contains(g, children.take([child]).world_corners()[0]).all()


def test_obb_of_a_rotated_box_is_tight():
    rot = Rotation.from_euler("xyz", [30, 40, 50], degrees=True).as_matrix()
    corners = np.array([[x, y, z] for x in (-3, 3) for y in (-1, 1) for z in (-0.5, 0.5)], float)
    pts = corners @ rot.T + [5, 6, 7]
    obb = bnd.pca_boxes(pts, np.array([0, len(pts)]))
    aabb = bnd.aabb_boxes(pts, np.array([0, len(pts)]))
    assert np.prod(obb.half[0]) == pytest.approx(3 * 1 * 0.5, rel=1e-9)
    assert np.prod(aabb.half[0]) > 5 * np.prod(obb.half[0])
    np.testing.assert_allclose(obb.center[0], [5, 6, 7], atol=1e-12)


def test_axes_are_right_handed():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3)) * [5, 2, 1]
    b = bnd.pca_boxes(pts, np.array([0, 100, 200, 500]))
    assert np.allclose(np.linalg.det(b.axes), 1)


def test_rigid_motion_moves_an_obb_exactly():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(200, 3)) * [4, 1, 0.2]
    starts = np.array([0, 200])
    rot = Rotation.random(random_state=3).as_matrix()
    t = np.array([1e3, -2, 5])
    moved = bnd.transform(bnd.pca_boxes(pts, starts), rot[None], t[None])
    refit = bnd.pca_boxes(pts @ rot.T + t, starts)
    np.testing.assert_allclose(moved.center, refit.center, atol=1e-9)
    np.testing.assert_allclose(moved.half, refit.half, rtol=1e-9)
    assert moved.contains(0, pts @ rot.T + t).all()
    aa = bnd.axis_aligned(moved)
    assert aa.contains(0, pts @ rot.T + t).all()
    assert np.prod(aa.half) > np.prod(moved.half)


def test_extent_is_the_support_function():
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(50, 3))
    b = bnd.pca_boxes(pts, np.array([0, 50]))
    for _ in range(20):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        corners = b.corners()[0]
        reach = np.abs((corners - b.center[0]) @ n).max()
        assert b.extent(n[None])[0] == pytest.approx(reach, rel=1e-12)


def test_min_volume_obb_is_no_larger_than_pca():
    rng = np.random.default_rng(5)
    sets = [rng.normal(size=(80, 3)) * rng.uniform(0.2, 3, 3) @ Rotation.random(random_state=k).as_matrix()
            for k in range(5)]
    points, starts = segments(sets)
    pca = bnd.pca_boxes(points, starts)
    best = bnd.min_volume_boxes(points, starts)
    for i, s in enumerate(sets):
        assert best.contains(i, s).all()
    assert (np.prod(best.half, 1) <= np.prod(pca.half, 1) * (1 + 1e-6)).all()


def test_parent_of_one_square_child_is_the_childs_box():
    """A child box with two equal sides gives its corners' covariance a repeated eigenvalue;
    the parent must still get the child's own box, not one turned within that eigenspace."""
    rot = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    for half in ([2.0, 2.0, 0.5], [1.0, 1.0, 1.0], [3.0, 1.0, 1.0]):
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
        child = bnd.pca_boxes(corners @ rot.T + [4, 5, 6], np.array([0, 8]))
        parent = bnd.enclose(child, np.array([0, 1]), "obb")
        np.testing.assert_allclose(np.prod(parent.half), np.prod(child.half), rtol=1e-9)
