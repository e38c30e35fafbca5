"""Separating axes (wallcull.separate): a box found apart from a tile's frustum never meets it,
checked exactly (its faces clipped against the frustum, the frustum's corners against the box),
and the test finds separations the plane test misses; so too the test by a box's outline seen
from the eye, which finds every separation there is for a box between the near and far
planes."""

import numpy as np
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from wallcull import oracle
from wallcull.cull import RECORD
from wallcull.separate import _CLIPPED, _CONE, _DEPTH, _OTHER, _SIDES, _clipped_outline
from wallcull.separate import _corners as _corners_into, _frustum, _near_only, _outline
from wallcull.separate import _flat, _outside, _outside_rect, _rect, _undecided
from wallcull.separate import _separated as _separated_into

from .randscene import random_wall


def _corners(planes, rows, corners) -> bool:
    """The frustum's corners into ``corners (8, 3)`` (the kernel's table of one tile)."""
    table = np.empty((1, 8, 3))
    ok = _corners_into(planes, rows[None], 0, table)
    corners[:] = table[0]
    return ok


def _separated(box, i, corners) -> bool:
    return _separated_into(box, i, corners[None], 0, np.empty(3), np.empty((3, 3)),
                           np.empty((8, 3)))


def _apart_by_outline(box, eye, corners) -> bool:
    """The outline test of one unit and one tile (the kernel's tables of one each)."""
    axes = np.empty((1, 6, 5))
    count = np.array([_outline(box, 0, np.asarray(eye, float), axes)])
    return _outside(axes, count, 0, corners[None], 0, np.asarray(eye, float), box)


def _outside_the_rect(axes, count, box, eye, corners) -> bool:
    """Outline planes ``axes`` against the tile's near face as a rectangle of display space (a
    grid tile's, as the traversal's frame hands it to the pass)."""
    flat, rects = np.empty(axes.shape), np.empty((1, 7))
    _flat(axes, count[0], 0, eye, np.eye(3), flat)
    _rect(corners[None], 0, eye, np.eye(3), rects)
    return _outside_rect(flat, count, 0, rects, 0, eye, box)


def _apart_by_outline_rect(box, eye, corners) -> bool:
    """The outline test against the tile's near face as a rectangle."""
    eye = np.asarray(eye, float)
    axes = np.empty((1, 6, 5))
    count = np.array([_outline(box, 0, eye, axes)])
    return _outside_the_rect(axes, count, box, eye, corners)


def _apart_by_clipped_outline(box, eye, planes, corners, rect=False) -> bool:
    """The test by the outline of the box's part in front of the near plane (row 4); against
    the near face as a rectangle of display space with ``rect``."""
    eye = np.asarray(eye, float)
    axes = np.empty((1, _CLIPPED, 5))
    count = np.array([_clipped_outline(
        box, 0, eye, planes, 4, axes, np.empty((8, 4)), np.empty((_CLIPPED, 3)),
        np.empty((_CLIPPED, 2)))])
    if not rect:
        return bool(count[0]) and _outside(axes, count, 0, corners[None], 0, eye, box)
    return bool(count[0]) and _outside_the_rect(axes, count, box, eye, corners)


#: the oracle's planes (bottom, right, top, left, near, far) as the culler orders them
LRTB = [3, 1, 2, 0, 4, 5]
_SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
_FACES = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]


def record(center, axes, half):
    """A packed bound (wallcull.cull.pack's layout) of an oriented box."""
    r = np.zeros((1, RECORD))
    r[0, :3] = center
    r[0, 4:13] = (axes * half[:, None]).reshape(9)
    r[0, 13] = np.linalg.norm(half)
    return r


def box_meets(center, axes, half, planes, corners) -> bool:
    """Exactly: a face of the box meets the frustum, or the frustum lies inside the box."""
    pts = center + (_SIGNS * half) @ axes
    tris = np.array([[pts[a], pts[b], pts[c]] for f in _FACES for a, b, c in
                     ((f[0], f[1], f[2]), (f[0], f[2], f[3]))])
    if oracle.triangles_meet(tris, planes):
        return True
    local = (corners - center) @ axes.T
    return bool((np.abs(local) <= half).all(axis=1).any())


def near_corner_case(seed):
    """A tile frustum and a box near its edges: around a corner or an edge point, of any size
    and turn."""
    rng = np.random.default_rng(seed)
    wall = random_wall(rng)
    tile = int(rng.integers(oracle.tiles_of(wall)))
    eye = rng.normal(size=3) * 0.05
    planes = oracle.tile_planes_display(wall, eye, tile)[LRTB]
    corners = np.empty((8, 3))
    assert _corners(planes, np.arange(6), corners)
    # a box near the frustum's edges: around a corner or an edge point, of any size and turn
    k = rng.integers(8)
    anchor = corners[k] * rng.uniform(0.05, 1.0) if k % 2 else corners[k]
    center = anchor + rng.normal(size=3) * rng.uniform(0.01, 3.0)
    axes = Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()
    half = rng.uniform(0.01, 2.0, 3)
    return planes, corners, center, axes, half, eye


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_a_separated_box_never_meets_the_frustum(seed):
    planes, corners, center, axes, half, _ = near_corner_case(seed)
    if _separated(record(center, axes, half), 0, corners):
        assert not box_meets(center, axes, half, planes, corners)


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_a_box_apart_by_its_outline_never_meets_the_frustum(seed):
    """The planes through the eye and the edges of the box's outline: any of them with every
    corner of the frustum beyond it has the two apart, wherever the box is (even behind the
    eye, or around it)."""
    planes, corners, center, axes, half, eye = near_corner_case(seed)
    if _apart_by_outline(record(center, axes, half), eye, corners):
        assert not box_meets(center, axes, half, planes, corners)


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_a_box_apart_by_its_outline_from_the_tiles_rectangle_is_apart_from_its_corners(seed):
    """The outline test against the tile's near face taken whole, as a rectangle: a box it
    finds apart every corner of the frustum finds apart too (the far corners lie further out
    on the rays from the eye through the near ones), and so does the exact test."""
    planes, corners, center, axes, half, eye = near_corner_case(seed)
    box = record(center, axes, half)
    if _apart_by_outline_rect(box, eye, corners):
        assert _apart_by_outline(box, eye, corners)
        assert not box_meets(center, axes, half, planes, corners)


def test_the_outline_finds_every_separation_between_near_and_far():
    """A box wholly between the near and far planes that the tile's planes leave open (outside
    none of them, cut by two or more) and that is apart from the frustum is found apart by its
    outline: on a screen, the box's image and the tile's rectangle are two convex polygons,
    and two that do not meet are apart along a side of one of them (the margin relative to the
    coordinates aside)."""
    apart = found = by_rect = 0
    for seed in range(8000):
        planes, corners, center, axes, half, eye = near_corner_case(seed)
        box = record(center, axes, half)
        pts = center + (_SIGNS * half) @ axes
        dist = pts @ planes[:, :3].T + planes[:, 3]
        if _undecided(box, 0, planes, np.arange(6)[None], 0) != _SIDES \
                or (dist < 0).all(axis=0).any():
            continue
        if not box_meets(center, axes, half, planes, corners):
            apart += 1
            found += _apart_by_outline(box, eye, corners)
            by_rect += _apart_by_outline_rect(box, eye, corners)
        else:
            assert not _apart_by_outline(box, eye, corners)
            assert not _apart_by_outline_rect(box, eye, corners)
    # against the rectangle, with a margin a little wider: all but a near touch in a thousand
    assert found == apart and apart > 100 and by_rect >= apart - apart // 1000


def _cut_by_near(seed):
    """A case of :func:`near_corner_case` whose box the near plane cuts and the far plane
    does not, outside no plane (as the traversal lists it), else None."""
    planes, corners, center, axes, half, eye = near_corner_case(seed)
    box = record(center, axes, half)
    rows = np.arange(6)[None]
    pts = center + (_SIGNS * half) @ axes
    if _undecided(box, 0, planes, rows, 0) != _DEPTH or not _near_only(box, 0, planes, rows, 0) \
            or ((pts @ planes[:, :3].T + planes[:, 3]) < 0).all(axis=0).any():
        return None
    return planes, corners, center, axes, half, eye, box


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_a_box_apart_by_the_outline_of_its_part_in_front_never_meets_the_frustum(seed):
    """A box that reaches behind the near plane: the planes through the eye and the outline of
    its part in front of that plane; any with every corner of the frustum beyond it has the two
    apart."""
    planes, corners, center, axes, half, eye = near_corner_case(seed)
    box = record(center, axes, half)
    if _apart_by_clipped_outline(box, eye, planes, corners):
        assert not box_meets(center, axes, half, planes, corners)
    if _apart_by_clipped_outline(box, eye, planes, corners, rect=True):  # a grid's tile
        assert _apart_by_clipped_outline(box, eye, planes, corners)


def test_the_outline_of_the_part_in_front_finds_the_separations():
    """Of the boxes the near plane cuts that are apart from the frustum, the outline of their
    part in front of it finds all but a few (the axes then find them), and never one that meets
    the frustum."""
    apart = found = by_rect = meet = 0
    for seed in range(6000):
        case = _cut_by_near(seed)
        if case is None:
            continue
        planes, corners, center, axes, half, eye, box = case
        if box_meets(center, axes, half, planes, corners):
            meet += 1
            assert not _apart_by_clipped_outline(box, eye, planes, corners)
            assert not _apart_by_clipped_outline(box, eye, planes, corners, rect=True)
        else:
            apart += 1
            found += _apart_by_clipped_outline(box, eye, planes, corners)
            by_rect += _apart_by_clipped_outline(box, eye, planes, corners, rect=True)
    assert apart > 200 and meet > 200 and found >= 0.99 * apart
    assert by_rect >= found - found // 1000


def test_the_cases_above_are_not_vacuous():
    """Among such boxes, many meet the frustum and many are found apart from it."""
    found = meet = 0
    for seed in range(300):
        planes, corners, center, axes, half, _ = near_corner_case(seed)
        found += _separated(record(center, axes, half), 0, corners)
        meet += box_meets(center, axes, half, planes, corners)
    assert found > 30 and meet > 30


def test_the_outline_is_used_only_where_the_frustum_is_a_pyramid_from_the_eye():
    """The outline's planes pass through the eye: they decide only for a tile whose frustum's
    edges are rays from that eye (a stereo tile's frustum, around both eyes' views, is not)."""
    for seed in range(50):
        planes, corners, _, _, _, eye = near_corner_case(seed)
        table = np.empty((1, 8, 3))
        assert _frustum(planes, np.arange(6)[None], 0, table, eye) == _CONE
        moved = eye + np.random.default_rng(seed).normal(size=3) * 0.03
        assert _frustum(planes, np.arange(6)[None], 0, table, moved) == _OTHER


def test_it_finds_what_the_plane_test_misses():
    """A long box past a frustum's corner: outside no single plane, yet apart from the frustum."""
    wall = {"cols": 1, "rows": 1, "tile_size": [1.0, 1.0], "distance": 1.0, "near": 0.1,
            "far": 10.0}
    planes = oracle.tile_planes_display(wall, [0, 0, 0], 0)[LRTB]
    corners = np.empty((8, 3))
    assert _corners(planes, np.arange(6), corners)
    # a thin rod across the frustum's top-right edge, beyond it
    axes = Rotation.from_euler("z", 45, degrees=True).as_matrix().T
    center = np.array([2.2, 2.2, -3.0])
    half = np.array([0.05, 3.0, 0.05])
    box = record(center, axes, half)
    pts = center + (_SIGNS * half) @ axes
    dist = pts @ planes[:, :3].T + planes[:, 3]
    assert not (dist < 0).all(axis=0).any()  # no plane has it wholly outside
    assert not box_meets(center, axes, half, planes, corners)
    assert _separated(box, 0, corners)


def test_threads_drop_the_same_pairs(monkeypatch):
    """The pass runs over chunks of pairs in threads on big frames: the same lists, tile for
    tile, for any number of threads; and it does drop pairs there."""
    import json
    from pathlib import Path

    import wallcull.separate as S
    from wallcull.cull import Culler
    from wallcull.paths import scene_path
    from wallcull.scene import SceneState, load
    from wallcull.wall import Frusta, Wall

    powerplant = load("powerplant")

    wall = Wall.from_dict(json.loads((Path(__file__).parents[1] / "examples" / "wall-8x8.json")
                                     .read_text()))
    state = SceneState(powerplant)
    frames = [Frusta.build(wall, f) for f in scene_path(powerplant, wall, "orbit", 4)]
    monkeypatch.setenv("WALLCULL_THREADS", "1")
    expect = [Culler(state, wall).cull(f) for f in frames]
    assert sum(e.stats["separated"] for e in expect) > 0
    monkeypatch.setattr(S, "THREAD_PAIRS", 16)
    for threads in ("2", "3", "5"):
        monkeypatch.setenv("WALLCULL_THREADS", threads)
        culler = Culler(state, wall)
        for frusta, e in zip(frames, expect):
            got = culler.cull(frusta)
            assert np.array_equal(got.start, e.start) and np.array_equal(got.nodes, e.nodes)
            assert got.stats["separated"] == e.stats["separated"]
