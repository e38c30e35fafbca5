"""Leaves as instances: a template's box moved by an instance's transform encloses the
instance's points under any affine map, equals the refit where the map keeps it a box, and the
points come out a bounded chunk at a time, each instance exactly once."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from wallcull import bounds as bnd
from wallcull.instances import (BATCH, MeshTable, fit_points, instance_extremes,
                                instance_points, leaf_bounds, moved_boxes)

from .test_bounds import SHAPES, point_set

MOTIONS = ["rigid", "uniform", "reflect", "along-axes", "shear", "singular-ish"]


def transform(motion: str, seed: int, template: np.ndarray, offset: float) -> np.ndarray:
    """A ``(4, 4)`` affine map of kind ``motion`` (``along-axes``: a non-uniform scale along the
    template's own box axes, which keeps the box a box)."""
    rng = np.random.default_rng(seed)
    rot = Rotation.random(random_state=seed).as_matrix()
    a = rot
    if motion == "uniform":
        a = rot * rng.uniform(1e-3, 1e3)
    elif motion == "reflect":
        a = rot @ np.diag([1.0, 1.0, -1.0]) * rng.uniform(0.1, 10)
    elif motion == "along-axes":
        q = bnd.pca_boxes(template, np.array([0, len(template)])).axes[0]
        a = rot @ q.T @ np.diag(rng.uniform(0.1, 10, 3)) @ q
    elif motion == "shear":
        a = rot @ (np.eye(3) + np.triu(rng.normal(size=(3, 3)), 1)) * rng.uniform(0.1, 10, 3)
    elif motion == "singular-ish":
        a = rot @ np.diag([1.0, 1.0, 1e-9])
    m = np.eye(4)
    m[:3, :3] = a
    m[:3, 3] = rng.normal(size=3) * max(offset, 1.0)
    return m


def table(sets) -> MeshTable:
    return MeshTable.from_meshes({f"t{i}": (s, np.zeros((0, 3), dtype=np.int64))
                                  for i, s in enumerate(sets)})


templates = st.builds(
    point_set, shape=st.sampled_from(SHAPES), n=st.integers(1, 40), seed=st.integers(0, 2**31),
    size=st.sampled_from([1e-3, 1.0, 1e3]), offset=st.sampled_from([0.0, 1.0, 1e7]))


@settings(max_examples=200, deadline=None)
@given(template=templates, motion=st.sampled_from(MOTIONS), seed=st.integers(0, 2**31),
       offset=st.sampled_from([0.0, 1e3, 1e7]))
def test_moved_box_encloses_the_instance_points(template, motion, seed, offset):
    m = transform(motion, seed, template, offset)
    box = moved_boxes(table([template]), np.array([0]), m[None])
    points = template @ m[:3, :3].T + m[:3, 3]
    assert np.isfinite(box.center).all() and (box.half >= 0).all()
    np.testing.assert_allclose(box.axes[0] @ box.axes[0].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(box.axes[0]) > 0
    assert box.contains(0, points).all(), motion


def same_box(a: bnd.Bounds, i: int, b: bnd.Bounds, j: int, rtol: float) -> bool:
    """Box ``i`` of ``a`` is box ``j`` of ``b``, up to the sign of each axis (eigenvectors
    have no sign)."""
    dots = np.abs((a.axes[i] * b.axes[j]).sum(axis=1))
    scale = np.abs(b.center[j]).max() + b.half[j].max()
    return (np.allclose(dots, 1, atol=1e-9) and np.allclose(a.center[i], b.center[j],
                                                            rtol=0, atol=rtol * scale)
            and np.allclose(a.half[i], b.half[j], rtol=0, atol=rtol * scale))


@pytest.mark.parametrize("motion", ["rigid", "uniform", "reflect", "along-axes", "shear"])
def test_moved_box_is_the_refit_where_the_map_keeps_it_a_box(motion):
    """Distinct eigenvalues (points spread differently along three axes): the eigenvector box
    of the moved points is the moved box, as paper section 5 uses for rigid motion; a shear is
    fitted again, so it equals the refit too."""
    rng = np.random.default_rng(0)
    template = rng.normal(size=(300, 3)) * [5.0, 2.0, 0.5] @ Rotation.random(random_state=1).as_matrix()
    mats = np.array([transform(motion, s, template, 1e3) for s in range(20)])
    moved = moved_boxes(table([template]), np.zeros(20, dtype=np.int64), mats)
    for k, m in enumerate(mats):
        points = template @ m[:3, :3].T + m[:3, 3]
        refit = bnd.pca_boxes(points, np.array([0, len(points)]))
        assert same_box(moved, k, refit, 0, 1e-9), (motion, k)


def test_other_bound_types_are_fitted_to_the_points():
    rng = np.random.default_rng(2)
    sets = [rng.normal(size=(int(rng.integers(1, 50)), 3)) for _ in range(6)]
    meshes = table(sets)
    mesh_of = rng.integers(0, 6, 40)
    world = np.array([transform(str(rng.choice(MOTIONS)), s, sets[0], 10.0) for s in range(40)])
    points = [sets[m] @ w[:3, :3].T + w[:3, 3] for m, w in zip(mesh_of, world)]
    starts = np.cumsum([0] + [len(p) for p in points])
    for kind in ("aabb", "sphere", "obb-hull"):
        ref = bnd.LEAF_FITTERS[kind](np.concatenate(points), starts)
        got = leaf_bounds(kind, meshes, mesh_of, world)
        np.testing.assert_allclose(got.center, ref.center, atol=1e-12)
        np.testing.assert_allclose(got.half, ref.half, atol=1e-12)
        np.testing.assert_allclose(got.radius, ref.radius, atol=1e-12)


@pytest.mark.parametrize("budget", [1, 7, 100, 1 << 21])
def test_instance_points_come_once_each_in_bounded_chunks(budget):
    """Templates placed often (a matrix product per chunk) and rarely (gathered) alike."""
    rng = np.random.default_rng(3)
    sets = [rng.normal(size=(int(rng.integers(1, 9)), 3)) for _ in range(5)]
    meshes = table(sets)
    mesh_of = np.concatenate([np.zeros(3 * BATCH, dtype=np.int64), rng.integers(1, 5, 30)])
    rng.shuffle(mesh_of)
    world = np.array([transform("shear", s, sets[0], 5.0) for s in range(len(mesh_of))])
    seen = np.zeros(len(mesh_of), dtype=int)
    for rows, points, starts in instance_points(meshes, mesh_of, world, budget):
        assert len(points) <= max(budget, 8) and starts[-1] == len(points)
        for k, r in enumerate(rows):
            seen[r] += 1
            want = sets[mesh_of[r]] @ world[r, :3, :3].T + world[r, :3, 3]
            np.testing.assert_allclose(points[starts[k]:starts[k + 1]], want, rtol=1e-14,
                                       atol=1e-14)
    assert (seen == 1).all()
    lo, hi = instance_extremes(meshes, mesh_of, world)
    for r in range(len(mesh_of)):
        want = sets[mesh_of[r]] @ world[r, :3, :3].T + world[r, :3, 3]
        np.testing.assert_allclose(lo[r], want.min(0), atol=1e-13)
        np.testing.assert_allclose(hi[r], want.max(0), atol=1e-13)


def test_sheared_instances_alone_are_fitted_from_points(monkeypatch):
    """Rigid and scaled instances never touch their points; only sheared ones do."""
    from wallcull import instances

    rng = np.random.default_rng(4)
    template = rng.normal(size=(50, 3)) * [3, 2, 1]
    motions = ["rigid", "uniform", "along-axes", "shear", "rigid", "shear"]
    world = np.array([transform(m, s, template, 1.0) for s, m in enumerate(motions)])
    asked = []
    real = instances.fit_points
    monkeypatch.setattr(instances, "fit_points",
                        lambda kind, meshes, mesh_of, w: asked.append(len(mesh_of))
                        or real(kind, meshes, mesh_of, w))
    moved_boxes(table([template]), np.zeros(len(motions), dtype=np.int64), world)
    assert asked == [2]


def test_mesh_table_is_a_mapping_of_float64_and_int64_copies():
    v = np.arange(12, dtype=np.float32).reshape(4, 3)
    f = np.array([[0, 1, 2], [1, 2, 3]], dtype=np.int32)
    t = MeshTable(["a", "b"], np.array([0, 1, 4]), v, np.array([0, 0, 2]), f)
    assert list(t) == ["a", "b"] and len(t) == 2 and "b" in t and "c" not in t
    vb, fb = t["b"]
    assert vb.dtype == np.float64 and fb.dtype == np.int64
    np.testing.assert_array_equal(vb, v[1:])
    vb[:] = -1  # a copy: the table is untouched
    assert t["b"][0][0, 0] == 3
    assert t.face_count.tolist() == [0, 2] and t.vertex_count.tolist() == [1, 3]
    with pytest.raises(KeyError):
        t["c"]
    sub = t.subset(np.array([1]))
    assert list(sub) == ["b"] and np.array_equal(sub["b"][1], f)


def test_fit_points_is_exactly_the_fitter_on_each_instance():
    rng = np.random.default_rng(5)
    template = rng.normal(size=(30, 3))
    world = np.array([transform("shear", s, template, 1.0) for s in range(3)])
    got = fit_points("obb", table([template]), np.zeros(3, dtype=np.int64), world)
    for k, m in enumerate(world):
        ref = bnd.pca_boxes(template @ m[:3, :3].T + m[:3, 3], np.array([0, 30]))
        assert same_box(got, k, ref, 0, 1e-12)
