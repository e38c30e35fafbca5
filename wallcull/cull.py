"""The traversals of paper section 4.2: naive, OH without FH, FH without OH, adaptive OH+FH.

All four start from the same first-level cull against the primary frustum (:func:`_primary`),
which yields *roots*: internal nodes wholly inside the primary frustum, and leaves that meet it.
Then:

* ``naive``    every leaf under the roots against every tile frustum, O(n m);
* ``oh``       the object hierarchy culled to each tile in turn, with plane masking;
* ``fh``       each leaf pushed down the frustum hierarchy, O(n log m);
* ``adaptive`` Algorithm 2, adaptive in the paper's sense: at every frustum node it decides
  which hierarchy to descend. A pair (object node, frustum node) whose object lies on one side
  of the frustum node's split moves down the FH intact. One the split cuts either unfolds into
  its children now (the object is large for this frustum node: it would reach many of its
  tiles) or moves down *both* sides whole (it is small: it will reach few tiles), carrying a
  mask of the tile planes it is cut by. At a tile such an object is tested against the planes
  in its mask only and then unfolded against that tile alone, as ``oh`` does with plane
  masking: a node known inside a plane is never tested against it again below.
  ``pseudo_groups=True`` runs the paper's Algorithm 2 as written (a cut object always unfolds)
  with its pseudo-groups: the unfolded children that fall on one side are regrouped under a
  fresh axis-aligned box and move down together.

Every test is the rounded-box test of :mod:`wallcull.bounds` on a packed record per node
(:func:`pack`): a bound is outside a plane when ``n . c + d < -r``. Every method is
conservative, and an internal node is reported to a tile only when its bound lies inside all
the planes that tile is tested against, so a reported node never stands for leaves the same
test would have rejected. For the same bounds:

* ``naive`` and ``oh`` report the same leaves: those whose bound is outside none of the tile's
  six planes;
* ``fh`` (and ``adaptive`` with pseudo-groups) report the leaves outside none of the primary
  planes and the split planes on the tile's path down the FH; ``adaptive`` reports leaves
  between the two (a leaf reached through an object unfolded at a tile is tested against the
  tile's own planes) when it unfolds clusters to the finest (``fine=0``); by default it lists
  a leaf's small clusters whole (:data:`FINE`), and then may report a few leaves more;
* ``fh``'s set is contained in ``naive``'s. The split planes above a tile are planes through
  the eye whose half-spaces contain the tile frustum, so they are valid culling planes; in
  front of the eye they add nothing to the tile's own planes, but a bound that straddles the
  eye's plane can pass each of the tile's planes one at a time and still be rejected by one of
  them.

**Bezels.** With a gap between tiles (``gap > 0``) a frustum node's children are bounded by two
planes, and for a bound wholly in front of the eye, inside the first means outside the second
(the half-spaces meet only behind the eye). The FH methods then skip the second test. With
``gap == 0`` the two planes are one, negated exactly; with overlap (``gap < 0``) both are tested.

The kernels are compiled with numba: the recursion of the paper is a loop over an explicit
stack of node ids, over flat arrays, with no Python object per node. Stacks and outputs are
allocated by the caller (:class:`Culler` keeps them from frame to frame): a stack's depth is
bounded by the two hierarchies' heights times the largest branching factor, and an output that
fills up makes the kernel return ``-1``, the caller double it and run again. Nothing is
allocated, grown or reference-counted inside a traversal loop.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from . import workers
from .bounds import Bounds
from .errors import InputError
from .scene import Scene, SceneState
from .separate import SMALL, drop_all
from .wall import Frusta

METHODS = ("naive", "oh", "fh", "adaptive")

#: Width of a packed node record (float64): centre (3), ball radius, the three half-extent
#: vectors ``axes[k] * half[k]`` (9), the radius of a sphere around the whole bound, padding.
#: 128 bytes: two cache lines.
RECORD = 16
_R_BALL, _R_AXES, _R_SPHERE = 3, 4, 13

#: ``adaptive`` unfolds a cut object when it would reach more tiles than this many times the
#: levels of frustum hierarchy below the split (see :func:`_adaptive`). Measured on the bench
#: scenes and walls (``wallcull bench``): 2 keeps its box-plane tests below ``oh``'s
#: on all of them; the count is flat between 1 and 4.
UNFOLD_RATIO = 1.0

#: On a screens wall ``adaptive`` unfolds a cut object only at frustum nodes over at least this
#: many screens. Its splits tell nothing of the screens' own planes, so an object unfolded above
#: a screen reaches it with all six planes still to test, where ``oh`` would have masked them:
#: on a CAVE (5 screens) unfolding cost 40% more tests than ``oh``, on CAVE2 (72) it saves half.
SCREENS_UNFOLD_TILES = 8
#: ... and only objects that would reach more screens than this many times the levels below:
#: on CAVE2, 4 takes 6% fewer tests than 1 (``UNFOLD_RATIO``), 12% less time; 0.25 to 8 all
#: stay within 10% of each other.
SCREENS_UNFOLD_RATIO = 4.0

#: ``adaptive`` stops unfolding a leaf's clusters (:mod:`wallcull.clusters`) at those whose
#: sphere spans less than this share of a tile's angular size: they are listed whole, their
#: triangles one range. Finer clusters than that save few triangles and cost tests and list
#: entries. On 8 x 8 at the default cluster sizes, 0.125 against 0 (always the finest): the
#: satellite's orbit 1.36x the floor against 1.30x, for 3% fewer draw calls; 0.25 gave 1.51x
#: there, and the power plant's orbit 1.25x against 0.125's 1.21x, for no measurable
#: difference in cull time (``docs/clusters.md``).
FINE = 0.125

#: ``adaptive`` runs in threads, over parts of the frustum hierarchy, after a frame that took at
#: least this many box-plane tests (about a millisecond; below it a thread costs more than it
#: saves).
PARALLEL_TESTS = 100_000
#: ... its hierarchy cut into this many subtrees a thread, dealt out to the threads each frame
#: by what their tiles listed the frame before (:class:`_Split`).
SUBTREES = 4

_OUT, _CUTS, _FULL = 0, 1, 2

# Columns of the frustum-hierarchy table (int64).
_FIRST, _SECOND, _PA, _PB, _TILE, _MODE, _SIDE_A, _SIDE_B = range(8)
# How a node's children are told apart: one plane, negated for the second (no gap); two planes
# whose insides meet only behind the eye (bezels); two planes that may overlap (projectors, or
# the two eyes of a stereo frame); each child by its own tile's six planes, or by none (screens
# that no plane through the eye separates, see wallcull.screens); not at all (a split of a
# screens wall that does not hold from this frame's eye).
_SHARED, _DISJOINT, _OVERLAP, _BOUNDS, _PASS = range(5)

# Bits of an object's mask in ``adaptive``: the side planes of its frustum node's region
# (L, R, T, B; near and far for screens, whose tiles do not share them), "unknown" in bits 0-5
# (not tested: inherited from a parent unfolded above) and "cut" in bits 8-13 (tested, cut);
# bit 16: the object may reach behind the eye.
_UNKNOWN = 63
_CUT = 8
_BEHIND = 1 << 16


def pack(bounds: Bounds) -> np.ndarray:
    """``(n, RECORD)`` float64 records of the bounds: what every kernel reads. The half-extent
    vectors are premultiplied, so a plane test is three dot products and a sum."""
    n = len(bounds)
    out = np.zeros((n, RECORD))
    out[:, :3] = bounds.center
    out[:, _R_BALL] = bounds.radius
    out[:, _R_AXES:_R_AXES + 9] = (bounds.axes * bounds.half[:, :, None]).reshape(n, 9)
    out[:, _R_SPHERE] = np.sqrt((bounds.half ** 2).sum(axis=1)) + bounds.radius
    return out


# --------------------------------------------------------------------------- kernels


@njit(cache=True, inline="always")
def _sr(box, i, planes, p):
    """``(s, r)`` of bound ``i`` against plane ``p``: outside when ``s < -r``, inside if ``s >= r``."""
    nx, ny, nz, d = planes[p, 0], planes[p, 1], planes[p, 2], planes[p, 3]
    s = nx * box[i, 0] + ny * box[i, 1] + nz * box[i, 2] + d
    r = (abs(nx * box[i, 4] + ny * box[i, 5] + nz * box[i, 6])
         + abs(nx * box[i, 7] + ny * box[i, 8] + nz * box[i, 9])
         + abs(nx * box[i, 10] + ny * box[i, 11] + nz * box[i, 12]) + box[i, 3])
    return s, r


@njit(cache=True, inline="always")
def _masked(box, i, planes, ids, size, m):
    """Bound ``i`` against the planes ``ids[p]`` whose bit ``p`` (``p < size``) mask ``m``
    holds: ``(outside, m, tests)``, outside some plane, or ``m`` less the planes it lies wholly
    inside (plane masking), and the tests made."""
    tests = 0
    for p in range(size):
        if m & (1 << p):
            s, r = _sr(box, i, planes, ids[p])
            tests += 1
            if s < -r:
                return True, m, tests
            if s >= r:
                m &= ~(1 << p)
    return False, m, tests


@njit(cache=True, inline="always")
def _along(box, i, fx, fy, fz, ox, oy, oz):
    """``(c, r)``: bound ``i``'s centre's depth along unit ``(fx, fy, fz)`` from ``(ox, oy,
    oz)``, and how far the bound reaches either side of it along that direction."""
    c = (box[i, 0] - ox) * fx + (box[i, 1] - oy) * fy + (box[i, 2] - oz) * fz
    r = (abs(fx * box[i, 4] + fy * box[i, 5] + fz * box[i, 6])
         + abs(fx * box[i, 7] + fy * box[i, 8] + fz * box[i, 9])
         + abs(fx * box[i, 10] + fy * box[i, 11] + fz * box[i, 12]) + box[i, 3])
    return c, r


@njit(cache=True, inline="always")
def _state(s, r):
    if s < -r:
        return _OUT
    if s >= r:
        return _FULL
    return _CUTS


@njit(cache=True, inline="always")
def _region(box, o, planes, tile_planes, tile):
    """State of bound ``o`` against tile ``tile``'s planes (-1: no bound, inside), the tests
    taken, and the planes that cut it (bits; -1 when there is no bound)."""
    if tile < 0:
        return _FULL, 0, -1
    cut = 0
    for p in range(tile_planes.shape[1]):
        s, r = _sr(box, o, planes, tile_planes[tile, p])
        if s < -r:
            return _OUT, p + 1, 0
        if s < r:
            cut |= 1 << p
    return _CUTS if cut else _FULL, tile_planes.shape[1], cut


@njit(cache=True, inline="always")
def _split(box, o, planes, fh, f, behind):
    """States of bound ``o`` against frustum node ``f``'s two children split by planes, and the
    tests taken: one when the planes are one (no gap), or when the bound, wholly in front of the
    eye, is inside the first plane of a bezel split (then it is outside the second)."""
    mode = fh[f, _MODE]
    s, r = _sr(box, o, planes, fh[f, _PA])
    sa = _state(s, r)
    if mode == _SHARED:
        return sa, _state(-s, r), 1
    if mode == _DISJOINT and sa == _FULL and not behind:
        return sa, _OUT, 1
    s, r = _sr(box, o, planes, fh[f, _PB])
    return sa, _state(s, r), 2


@njit(cache=True, inline="always")
def _split_any(box, o, planes, fh, f, behind, tile_planes):
    """:func:`_split` for every mode: also children told apart by their own tiles' planes, or
    not at all (screens walls); then also the planes of its own tile that cut each child's
    part (bits), or -1 where a child has no tile of its own."""
    mode = fh[f, _MODE]
    if mode == _PASS:
        return _FULL, _FULL, 0, -1, -1
    if mode == _BOUNDS:
        sa, na, ca = _region(box, o, planes, tile_planes, fh[f, _PA])
        sb, nb, cb = _region(box, o, planes, tile_planes, fh[f, _PB])
        return sa, sb, na + nb, ca, cb
    sa, sb, nt = _split(box, o, planes, fh, f, behind)
    return sa, sb, nt, -1, -1


@njit(cache=True)
def _primary(child_start, child_count, children, box, planes, plane_ids, roots, masks,
             stack_n, stack_m):
    """Cull the root's children to one convex region: ``(count, tests)``, writing ``roots``
    and ``masks``.

    The region is the intersection of the planes ``plane_ids`` (at most 63). ``roots`` are the
    nodes wholly inside it and the leaves that meet it; ``masks`` holds, per root, the planes it
    is not yet known to be inside (bit ``p`` for ``plane_ids[p]``). Planes a node is inside of
    are dropped for its children (plane masking).
    """
    count = plane_ids.shape[0]
    n = 0
    tests = 0
    sp = 0
    for k in range(child_start[0] + child_count[0] - 1, child_start[0] - 1, -1):
        stack_n[sp] = children[k]
        stack_m[sp] = (1 << count) - 1
        sp += 1
    while sp > 0:
        sp -= 1
        i = stack_n[sp]
        outside, m, made = _masked(box, i, planes, plane_ids, count, stack_m[sp])
        tests += made
        if outside:
            continue
        if m == 0 or child_count[i] == 0:
            roots[n] = i
            masks[n] = m
            n += 1
            continue
        for j in range(child_start[i] + child_count[i] - 1, child_start[i] - 1, -1):
            stack_n[sp] = children[j]
            stack_m[sp] = m
            sp += 1
    return n, tests


@njit(cache=True)
def _naive(roots, masks, leaves, leaf_start, leaf_count, box, planes, tile_planes, force,
           inherit, out_n, out_t):
    k = 0
    tests = 0
    cap = out_n.shape[0]
    for j in range(roots.shape[0]):
        root = roots[j]
        for li in range(leaf_start[root], leaf_start[root] + leaf_count[root]):
            leaf = leaves[li]
            for t in range(tile_planes.shape[0]):
                # A tile tests its inner side planes; its border planes and near/far are the
                # primary's, which the root may already be known to be inside.
                m = force[t] | (masks[j] & inherit[t])
                visible = True
                for p in range(6):
                    if m & (1 << p):
                        s, r = _sr(box, leaf, planes, tile_planes[t, p])
                        tests += 1
                        if s < -r:
                            visible = False
                            break
                if visible:
                    if k == cap:
                        return -1, tests
                    out_n[k] = leaf
                    out_t[k] = t
                    k += 1
    return k, tests


@njit(cache=True, nogil=True)
def _oh(roots, masks, child_start, child_count, children, box, planes, region_planes,
        region_size, force, inherit, stack_n, stack_m, out_n, out_t):
    """The object hierarchy culled to each convex region in turn, with plane masking: region
    ``q`` is the intersection of planes ``region_planes[q, :region_size[q]]``; root ``j``
    starts with mask ``force[q] | (masks[j] & inherit[q])``. Used for the tiles (``oh``) and for
    any set of regions (shadow casters, mirror views: :func:`cull_regions`)."""
    k = 0
    tests = 0
    cap = out_n.shape[0]
    for q in range(region_planes.shape[0]):
        sp = 0
        for j in range(roots.shape[0] - 1, -1, -1):
            stack_n[sp] = roots[j]
            stack_m[sp] = force[q] | (masks[j] & inherit[q])
            sp += 1
        size = region_size[q]
        ids = region_planes[q]
        while sp > 0:
            sp -= 1
            i = stack_n[sp]
            outside, m, made = _masked(box, i, planes, ids, size, stack_m[sp])
            tests += made
            if outside:
                continue
            if m == 0 or child_count[i] == 0:
                if k == cap:
                    return -1, tests
                out_n[k] = i
                out_t[k] = q
                k += 1
                continue
            for c in range(child_start[i] + child_count[i] - 1, child_start[i] - 1, -1):
                stack_n[sp] = children[c]
                stack_m[sp] = m
                sp += 1
    return k, tests


@njit(cache=True)
def _fh(roots, masks, leaves, leaf_start, leaf_count, box, planes, fh, near_bit, regions, stack,
        out_n, out_t):
    """``regions``: each tile's six planes on a screens wall, ``None`` on a grid (a version
    compiled for each, as for :func:`_adaptive`)."""
    k = 0
    tests = 0
    cap = out_n.shape[0]
    for j in range(roots.shape[0]):
        root = roots[j]
        behind = (masks[j] & near_bit) != 0
        for li in range(leaf_start[root], leaf_start[root] + leaf_count[root]):
            leaf = leaves[li]
            stack[0] = 0
            sp = 1
            while sp > 0:
                sp -= 1
                f = stack[sp]
                tile = fh[f, _TILE]
                if tile >= 0:
                    if regions is not None:  # screens: the splits above are not its planes
                        state, nt, _ = _region(box, leaf, planes, regions, tile)
                        tests += nt
                        if state == _OUT:
                            continue
                    if k == cap:
                        return -1, tests
                    out_n[k] = leaf
                    out_t[k] = tile
                    k += 1
                    continue
                if regions is None:
                    sa, sb, nt = _split(box, leaf, planes, fh, f, behind)
                else:
                    sa, sb, nt, _, _ = _split_any(box, leaf, planes, fh, f, behind, regions)
                tests += nt
                if sb != _OUT:
                    stack[sp] = fh[f, _SECOND]
                    sp += 1
                if sa != _OUT:
                    stack[sp] = fh[f, _FIRST]
                    sp += 1
    return k, tests


@njit(cache=True, nogil=True)
def _adaptive(roots, masks, child_start, child_count, children, box, planes, fh, fh_unfold,
              tile_planes, view, pitch_x, pitch_y, near_bit, unknown_at_root, regions, parts,
              fine, allowed, so, sf, sm, ts, tm, out_n, out_t, out_c):
    """Algorithm 2 with an adaptive choice of hierarchy and plane masking (module docstring).

    A stack entry is (object ``so``, frustum node ``sf``, mask ``sm``). At an internal frustum
    node the object is tested against the planes bounding the two children. If neither cuts it,
    it moves down intact to each child it fills (and the side plane the split gives that child
    is known inside: its bits clear). If one cuts it, a leaf goes down each side it reaches,
    its "cut" bit set for the plane that cut it. An internal node unfolds into its children,
    tested at the same frustum node, when it would reach more than ``fh_unfold[f]`` tiles
    (estimated from the angle its bounding sphere spans, ``view`` giving its depth, against the
    tiles' angular pitch); otherwise it goes down both sides whole like a leaf. At a tile, an
    object is tested against its "unknown" planes; with no plane left cut it is inside the
    tile and is listed; a cut leaf is listed; a cut internal node is culled to this tile alone,
    over the planes it is cut by (``oh`` with plane masking, on stack ``ts``/``tm``).

    ``tile_planes`` holds each tile's side planes: four for a grid (the primary frustum holds
    near and far), six for screens, whose objects start with all six unknown
    (``unknown_at_root``). ``view``: the plane ``view[:4]`` whose distance is an object's depth,
    or zeros there and the eye at ``view[4:7]`` for its distance from the eye (screens).
    ``regions``: ``tile_planes`` when the frustum hierarchy has ``BOUNDS`` and ``PASS`` nodes
    (screens walls), ``None`` for a grid. numba compiles a version for each, so a grid's hot
    loop has no branch it never takes (with it, 5x slower on 8x8).

    ``allowed`` (one flag per frustum node): the part of the frustum hierarchy this call
    covers. Parts whose tiles are disjoint run in threads at once (:class:`Culler`), each
    listing exactly the pairs, in the same order, that one call over everything lists for its
    tiles.

    ``out_c`` gets, per pair, the tile's planes (left, right, top, bottom, near, far: bits) it
    found cutting the node, for the separating pass (:mod:`wallcull.separate`): on a grid,
    the wall's outer sides and the near and far planes as the first-level cull found them
    (``masks``: only nodes without children can be cut by them there), the others from the
    node's own tests. A plane a node's ancestor lay inside is not among them, even where the
    node's own bound reaches across it.
    """
    sides = 4 if regions is None else 6
    k = 0
    tests = 0
    cap = out_n.shape[0]
    sp = 0
    for j in range(roots.shape[0] - 1, -1, -1):
        so[sp] = roots[j]
        sf[sp] = 0
        sm[sp] = unknown_at_root | (_BEHIND if masks[j] & near_bit else 0)
        if near_bit:  # a grid: the first-level planes cutting it are its border tiles' sides,
            sm[sp] |= (masks[j] & _UNKNOWN) << _CUT  # and every tile's near and far
        sp += 1
    while sp > 0:
        sp -= 1
        o = so[sp]
        f = sf[sp]
        m = sm[sp]
        while True:  # follow the object down while it goes one way: no stack traffic
            tile = fh[f, _TILE]
            if tile >= 0:
                break
            if regions is None:  # decided when compiled (see the docstring)
                sa, sb, nt = _split(box, o, planes, fh, f, (m & _BEHIND) != 0)
                ca = cb = -1
            else:
                sa, sb, nt, ca, cb = _split_any(box, o, planes, fh, f, (m & _BEHIND) != 0,
                                                regions)
            tests += nt
            bit_a = fh[f, _SIDE_A]
            bit_b = fh[f, _SIDE_B]
            # the split gives each child a new side plane: forget what was known of the old one
            ma = (m & ~(bit_a | (bit_a << _CUT))) | ((bit_a << _CUT) if sa == _CUTS else 0)
            mb = (m & ~(bit_b | (bit_b << _CUT))) | ((bit_b << _CUT) if sb == _CUTS else 0)
            if ca >= 0:  # a tile's six planes tested here: nothing is left unknown
                ma = (m & _BEHIND) | (ca << _CUT)
            if cb >= 0:
                mb = (m & _BEHIND) | (cb << _CUT)
            if (sa == _CUTS or sb == _CUTS) and child_count[o] > 0:
                angle = _angle(box, o, view, regions)
                reach = (2 * angle / pitch_x + 1) * (2 * angle / pitch_y + 1)
                if reach > fh_unfold[f] and not (parts[o] and angle < fine):
                    # large for this frustum node: unfold here
                    cm = (m & _UNKNOWN) | ((m >> _CUT) & _UNKNOWN)
                    for c in range(child_start[o] + child_count[o] - 1, child_start[o] - 1,
                                   -1):
                        so[sp] = children[c]
                        sf[sp] = f
                        sm[sp] = cm
                        sp += 1
                    tile = -2
                    break
            # Down every side it reaches, whole: intact where it is inside, cut where it is
            # cut (the plane's "cut" bit set), both sides or neither in an overlap or a gap.
            if not allowed[fh[f, _FIRST]]:  # another thread's part
                sa = _OUT
            if not allowed[fh[f, _SECOND]]:
                sb = _OUT
            if sa != _OUT:
                if sb != _OUT:
                    so[sp] = o
                    sf[sp] = fh[f, _SECOND]
                    sm[sp] = mb
                    sp += 1
                f = fh[f, _FIRST]
                m = ma
            elif sb != _OUT:
                f = fh[f, _SECOND]
                m = mb
            else:
                tile = -2
                break
        if tile < 0:
            continue
        unknown = m & _UNKNOWN
        cut = (m >> _CUT) & _UNKNOWN
        if unknown:
            outside = False
            for p in range(sides):
                if unknown & (1 << p):
                    s, r = _sr(box, o, planes, tile_planes[tile, p])
                    tests += 1
                    if s < -r:
                        outside = True
                        break
                    if s < r:
                        cut |= 1 << p
            if outside:
                continue
        if cut == 0 or child_count[o] == 0 or (parts[o] and _angle(box, o, view, regions)
                                                < fine):
            if k == cap:
                return -1, tests
            out_n[k] = o
            out_t[k] = tile
            out_c[k] = cut
            k += 1
            continue
        tp = 0  # cull o's subtree to this tile, over the planes o is cut by
        for c in range(child_start[o] + child_count[o] - 1, child_start[o] - 1, -1):
            ts[tp] = children[c]
            tm[tp] = cut
            tp += 1
        while tp > 0:
            tp -= 1
            i = ts[tp]
            mm = tm[tp]
            outside = False
            for p in range(sides):  # four for a grid, six for screens
                if mm & (1 << p):
                    s, r = _sr(box, i, planes, tile_planes[tile, p])
                    tests += 1
                    if s < -r:
                        outside = True
                        break
                    if s >= r:
                        mm &= ~(1 << p)
            if outside:
                continue
            if mm == 0 or child_count[i] == 0 or (parts[i] and _angle(box, i, view, regions)
                                                  < fine):
                if k == cap:
                    return -1, tests
                out_n[k] = i
                out_t[k] = tile
                out_c[k] = mm
                k += 1
                continue
            for c in range(child_start[i] + child_count[i] - 1, child_start[i] - 1, -1):
                ts[tp] = children[c]
                tm[tp] = mm
                tp += 1
    return k, tests


@njit(cache=True, inline="always")
def _angle(box, o, view, regions):
    """The angle bound ``o``'s sphere spans from the eye (radians, about), its depth along
    ``view`` (grids) or its distance from the eye (screens, ``regions`` given)."""
    if regions is not None:  # screens all around: distance
        depth = math.sqrt((box[o, 0] - view[4]) ** 2 + (box[o, 1] - view[5]) ** 2
                          + (box[o, 2] - view[6]) ** 2)
    else:
        depth = view[0] * box[o, 0] + view[1] * box[o, 1] + view[2] * box[o, 2] + view[3]
    return box[o, _R_SPHERE] / depth if depth > 0 else np.inf


@njit(cache=True, inline="always")
def _box_sr(pool, g, planes, p):
    """``(s, r)`` of an axis-aligned box ``pool[g] = (centre, half extents)`` against plane ``p``."""
    nx, ny, nz, d = planes[p, 0], planes[p, 1], planes[p, 2], planes[p, 3]
    s = nx * pool[g, 0] + ny * pool[g, 1] + nz * pool[g, 2] + d
    r = abs(nx) * pool[g, 3] + abs(ny) * pool[g, 4] + abs(nz) * pool[g, 5]
    return s, r


@njit(cache=True)
def _grow(a):
    out = np.empty((2 * a.shape[0],) + a.shape[1:], a.dtype)
    out[:a.shape[0]] = a
    return out


@njit(cache=True)
def _group(members, count, box, pool_box, pool_start, pool_members, n_pg, n_pm):
    """Append a pseudo-group of ``members[:count]`` to the pool, with its axis-aligned box.

    ``pool_box[g]`` holds the centre and half extents (6 numbers); group ``g``'s members are
    ``pool_members[pool_start[g]:pool_start[g + 1]]``. Returns the (possibly grown) pool arrays
    and the new counts.
    """
    if n_pg + 1 >= pool_box.shape[0]:
        pool_box = _grow(pool_box)
    if n_pg + 2 >= pool_start.shape[0]:
        pool_start = _grow(pool_start)
    while n_pm + count > pool_members.shape[0]:
        pool_members = _grow(pool_members)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for q in range(count):
        i = members[q]
        pool_members[n_pm + q] = i
        for j in range(3):
            e = (abs(box[i, 4 + j]) + abs(box[i, 7 + j]) + abs(box[i, 10 + j]) + box[i, 3])
            lo[j] = min(lo[j], box[i, j] - e)
            hi[j] = max(hi[j], box[i, j] + e)
    for j in range(3):
        mid = (lo[j] + hi[j]) / 2
        pool_box[n_pg, j] = mid
        # rounded up so that the box still holds its members after rounding
        pool_box[n_pg, 3 + j] = (hi[j] - lo[j]) / 2 * (1 + 4e-16) + 4e-16 * abs(mid)
    pool_start[n_pg] = n_pm
    pool_start[n_pg + 1] = n_pm + count
    return pool_box, pool_start, pool_members, n_pg + 1, n_pm + count


@njit(cache=True)
def _pseudo(roots, masks, child_start, child_count, children, box, planes, fh, near_bit,
            tile_planes):
    """The paper's Algorithm 2 as written, with pseudo-groups (section 4.2).

    A cut object always unfolds; its members are classified at once and the ones wholly on one
    side of the split are regrouped under a fresh axis-aligned box that moves down as one
    object. The roots of the first-level cull enter the frustum hierarchy as one such group,
    so a flat scene (one parent, thousands of leaves) benefits too. Object ids ``>= n`` name
    groups. The pool of groups grows as needed (this variant is measured, not the default).
    """
    n = box.shape[0]
    out_n = np.empty(1024, np.int64)
    out_t = np.empty(1024, np.int64)
    so = np.empty(1024, np.int64)
    sf = np.empty(1024, np.int64)
    sb_ = np.empty(1024, np.uint8)  # 1: may reach behind the eye
    pool_box = np.empty((64, 6))
    pool_start = np.zeros(66, np.int64)
    pool_members = np.empty(256, np.int64)
    n_pg = 0
    n_pm = 0
    firsts = np.empty(64, np.int64)
    seconds = np.empty(64, np.int64)
    k = 0
    tests = 0
    sp = 0
    behind_roots = False
    for j in range(roots.shape[0]):
        behind_roots |= (masks[j] & near_bit) != 0
    if roots.shape[0] > 1:
        pool_box, pool_start, pool_members, n_pg, n_pm = _group(
            roots, roots.shape[0], box, pool_box, pool_start, pool_members, n_pg, n_pm)
        so[0] = n
        sf[0] = 0
        sb_[0] = behind_roots
        sp = 1
    elif roots.shape[0] == 1:
        so[0] = roots[0]
        sf[0] = 0
        sb_[0] = behind_roots
        sp = 1
    while sp > 0:
        sp -= 1
        o = so[sp]
        f = sf[sp]
        behind = sb_[sp] != 0
        if o < n:
            m0, m_count = child_start[o], child_count[o]
        else:
            m0, m_count = pool_start[o - n], pool_start[o - n + 1] - pool_start[o - n]
        tile = fh[f, _TILE]
        if tile >= 0:  # a frustum leaf: mark the object (or the group's members) visible
            count = 1 if o < n else m_count
            while k + count > out_n.shape[0]:
                out_n = _grow(out_n)
                out_t = _grow(out_t)
            for q in range(count):
                out_n[k] = o if o < n else pool_members[m0 + q]
                out_t[k] = tile
                k += 1
            continue
        if o < n:
            sa, sb, nt = _split(box, o, planes, fh, f, behind)
        else:
            s, r = _box_sr(pool_box, o - n, planes, fh[f, _PA])
            sa, nt = _state(s, r), 1
            if fh[f, _MODE] == _SHARED:
                sb = _state(-s, r)
            elif fh[f, _MODE] == _DISJOINT and sa == _FULL and not behind:
                sb = _OUT
            else:
                s, r = _box_sr(pool_box, o - n, planes, fh[f, _PB])
                sb, nt = _state(s, r), 2
        tests += nt
        first = fh[f, _FIRST]
        second = fh[f, _SECOND]
        while sp + 2 * m_count + 2 > so.shape[0]:
            so = _grow(so)
            sf = _grow(sf)
            sb_ = _grow(sb_)
        if sa != _CUTS and sb != _CUTS:  # intact to each side it fills
            if sb == _FULL:
                so[sp], sf[sp], sb_[sp] = o, second, behind
                sp += 1
            if sa == _FULL:
                so[sp], sf[sp], sb_[sp] = o, first, behind
                sp += 1
            continue
        if o < n and child_count[o] == 0:
            if sb != _OUT:
                so[sp], sf[sp], sb_[sp] = o, second, behind
                sp += 1
            if sa != _OUT:
                so[sp], sf[sp], sb_[sp] = o, first, behind
                sp += 1
            continue
        # Cut: classify the members here; the ones wholly on one side are regrouped.
        if firsts.shape[0] < m_count:
            firsts = np.empty(2 * m_count, np.int64)
            seconds = np.empty(2 * m_count, np.int64)
        n_first = 0
        n_second = 0
        for q in range(m0, m0 + m_count):
            i = children[q] if o < n else pool_members[q]
            ma, mb, nt = _split(box, i, planes, fh, f, behind)
            tests += nt
            if ma == _FULL and mb == _OUT:
                firsts[n_first] = i
                n_first += 1
            elif mb == _FULL and ma == _OUT:
                seconds[n_second] = i
                n_second += 1
            elif ma != _CUTS and mb != _CUTS:  # in both children (projector overlap) or neither
                if mb == _FULL:
                    so[sp], sf[sp], sb_[sp] = i, second, behind
                    sp += 1
                if ma == _FULL:
                    so[sp], sf[sp], sb_[sp] = i, first, behind
                    sp += 1
            elif child_count[i] == 0:
                if mb != _OUT:
                    so[sp], sf[sp], sb_[sp] = i, second, behind
                    sp += 1
                if ma != _OUT:
                    so[sp], sf[sp], sb_[sp] = i, first, behind
                    sp += 1
            else:  # cut: unfold it here
                while sp + child_count[i] + 2 * m_count + 2 > so.shape[0]:
                    so = _grow(so)
                    sf = _grow(sf)
                    sb_ = _grow(sb_)
                for qq in range(child_start[i], child_start[i] + child_count[i]):
                    so[sp], sf[sp], sb_[sp] = children[qq], f, behind
                    sp += 1
        for side in range(2):
            members = firsts if side == 0 else seconds
            count = n_first if side == 0 else n_second
            target = first if side == 0 else second
            if count == 1:
                so[sp], sf[sp], sb_[sp] = members[0], target, behind
                sp += 1
            elif count > 1:
                pool_box, pool_start, pool_members, n_pg, n_pm = _group(
                    members, count, box, pool_box, pool_start, pool_members, n_pg, n_pm)
                so[sp], sf[sp], sb_[sp] = n + n_pg - 1, target, behind
                sp += 1
    return out_n[:k], out_t[:k], tests


@njit(cache=True)
def _by_region(nodes, regions, m):
    """Counting sort of (node, region) pairs into CSR ``(start (m + 1,), nodes)``, each
    region's nodes in increasing id (preorder) order. The traversals' stacks already emit each
    region's nodes in preorder (children are pushed in reverse and a node's pairs are done before
    its next sibling's); only pseudo-groups mix them, and only those regions get sorted."""
    start = np.zeros(m + 1, np.int64)
    for t in regions:
        start[t + 1] += 1
    for t in range(m):
        start[t + 1] += start[t]
    fill = start[:-1].copy()
    out = np.empty(nodes.shape[0], np.int64)
    for j in range(nodes.shape[0]):
        t = regions[j]
        out[fill[t]] = nodes[j]
        fill[t] += 1
    for t in range(m):
        for j in range(start[t] + 1, start[t + 1]):
            if out[j] < out[j - 1]:
                out[start[t]:start[t + 1]].sort()
                break
    return start, out


@njit(cache=True)
def _expand(start, nodes, leaf_start, leaf_count, leaves, cluster_leaf):
    """Every region's leaves in CSR form, from its nodes (each a whole subtree, or a cluster,
    which stands for its leaf: ``cluster_leaf``, -1 for other nodes). The nodes of a region are
    disjoint subtrees in preorder, so their leaf runs come out sorted, and a leaf's clusters
    are consecutive, so each leaf comes once."""
    m = start.shape[0] - 1
    out_start = np.zeros(m + 1, np.int64)
    for t in range(m):
        total = 0
        last = -1
        for j in range(start[t], start[t + 1]):
            i = nodes[j]
            c = cluster_leaf[i]
            if c < 0:
                total += leaf_count[i]
            elif c != last:
                total += 1
                last = c
        out_start[t + 1] = out_start[t] + total
    out = np.empty(out_start[m], np.int64)
    w = 0
    for t in range(m):
        last = -1
        for j in range(start[t], start[t + 1]):
            i = nodes[j]
            c = cluster_leaf[i]
            if c < 0:
                for q in range(leaf_start[i], leaf_start[i] + leaf_count[i]):
                    out[w] = leaves[q]
                    w += 1
            elif c != last:
                out[w] = c
                w += 1
                last = c
    return out_start, out


@njit(cache=True)
def _draw_ranges(start, nodes, cluster_leaf, first, count):
    """Every region's leaves shown in part, and their triangle ranges.

    A run of consecutive listed clusters of one leaf (clusters or groups of them: each stands
    for the triangles ``[first, first + count)`` of the leaf's mesh) that does not cover all of
    its triangles (a leaf whose clusters all are is drawn whole) gives the ranges of those
    clusters, merged where they touch. Returns CSR arrays ``(part_start (m + 1,),
    part_leaf (P,), range_start (P + 1,), ranges (R, 2))``: region ``t``'s partial leaves are
    ``part_leaf[part_start[t]:part_start[t + 1]]``, leaf ``p``'s ranges (first triangle, count)
    ``ranges[range_start[p]:range_start[p + 1]]``."""
    m = start.shape[0] - 1
    n = nodes.shape[0]
    part_start = np.zeros(m + 1, np.int64)
    part_leaf = np.empty(n, np.int64)
    range_start = np.zeros(n + 1, np.int64)
    ranges = np.empty((n, 2), np.int64)
    p = 0
    r = 0
    for t in range(m):
        j = start[t]
        while j < start[t + 1]:
            leaf = cluster_leaf[nodes[j]]
            if leaf < 0:
                j += 1
                continue
            k = j
            shown = 0
            while k < start[t + 1] and cluster_leaf[nodes[k]] == leaf:
                shown += count[nodes[k]]
                k += 1
            if shown < count[leaf]:
                part_leaf[p] = leaf
                for q in range(j, k):
                    i = nodes[q]
                    if q > j and ranges[r - 1, 0] + ranges[r - 1, 1] == first[i]:
                        ranges[r - 1, 1] += count[i]
                    else:
                        ranges[r, 0] = first[i]
                        ranges[r, 1] = count[i]
                        r += 1
                p += 1
                range_start[p] = r
            j = k
        part_start[t + 1] = p
    return part_start, part_leaf[:p], range_start[:p + 1], ranges[:r]


@njit(cache=True)
def _depth_ranges(start, nodes, box, forward, origin, lo_default, hi_default):
    """Per region, the smallest and largest depth along unit ``forward[q]`` from ``origin[q]``
    reached by its nodes' bounds (``lo_default``/``hi_default`` for an empty region); one row
    of ``forward`` (or ``origin``) serves every region, or one row each."""
    m = start.shape[0] - 1
    lo = np.full(m, lo_default)
    hi = np.full(m, hi_default)
    for t in range(m):
        if start[t + 1] == start[t]:
            continue
        q = t if forward.shape[0] > 1 else 0
        o = t if origin.shape[0] > 1 else 0
        fx, fy, fz = forward[q, 0], forward[q, 1], forward[q, 2]
        ox, oy, oz = origin[o, 0], origin[o, 1], origin[o, 2]
        a = np.inf
        b = -np.inf
        for j in range(start[t], start[t + 1]):
            c, r = _along(box, nodes[j], fx, fy, fz, ox, oy, oz)
            a = min(a, c - r)
            b = max(b, c + r)
        lo[t] = a
        hi[t] = b
    return lo, hi


@njit(cache=True)
def _farthest(start, nodes, box, origin):
    """Per region, an upper bound on the distance from ``origin`` to its nodes' bounds (the
    distance to a centre plus the radius of the sphere around the bound); 0 for none. (A
    cube-map shadow's far plane: :func:`wallcull.fit.shadow_sets`.)"""
    m = start.shape[0] - 1
    out = np.zeros(m)
    for t in range(m):
        for j in range(start[t], start[t + 1]):
            i = nodes[j]
            d = math.sqrt((box[i, 0] - origin[0]) ** 2 + (box[i, 1] - origin[1]) ** 2
                          + (box[i, 2] - origin[2]) ** 2) + box[i, _R_SPHERE]
            out[t] = max(out[t], d)
    return out


# --------------------------------------------------------------------------- public API


@dataclass
class DrawRanges:
    """Per tile, the leaves it shows only in part and, for each, the ranges of its mesh's
    triangles to draw (``(first, count)``, sorted, disjoint, not touching): CSR arrays as
    :func:`_draw_ranges` returns them. Every other leaf of a tile's list is drawn whole."""

    part_start: np.ndarray  # (m + 1,)
    part_leaf: np.ndarray  # (P,) leaf ids, sorted within a tile
    range_start: np.ndarray  # (P + 1,)
    ranges: np.ndarray  # (R, 2) int64: first triangle, triangles

    def tile(self, tile: int) -> list[tuple[int, np.ndarray]]:
        """Tile ``tile``'s partial leaves as ``(leaf, ranges (k, 2))`` pairs."""
        rs = self.range_start
        return [(int(self.part_leaf[p]), self.ranges[rs[p]:rs[p + 1]])
                for p in range(self.part_start[tile], self.part_start[tile + 1])]


@dataclass
class Visibility:
    """Per-tile lists of scene nodes, in CSR form: tile ``t`` sees ``nodes[start[t]:start[t+1]]``,
    in increasing id order. A listed internal node stands for its whole subtree (SPEC section
    4); a tile's nodes are disjoint subtrees. A listed cluster stands for part of its leaf:
    :meth:`leaf_lists` names the leaf, :meth:`draw_ranges` says which triangles."""

    scene: Scene
    start: np.ndarray
    nodes: np.ndarray
    stats: dict = field(default_factory=dict)

    @property
    def tiles(self) -> int:
        return len(self.start) - 1

    def tile_nodes(self, tile: int) -> np.ndarray:
        return self.nodes[self.start[tile]:self.start[tile + 1]]

    def tile_leaves(self, tile: int) -> np.ndarray:
        """Sorted leaf ids the tile must draw."""
        start, leaves = self.leaf_lists()
        return leaves[start[tile]:start[tile + 1]]

    def leaf_lists(self) -> tuple[np.ndarray, np.ndarray]:
        """Every tile's sorted leaf ids at once, in CSR form ``(start (m + 1,), leaves)``;
        computed once (compiled: the nodes' leaf runs, concatenated)."""
        cached = self.__dict__.get("_leaf_lists")
        if cached is None:
            cached = self.__dict__["_leaf_lists"] = leaf_lists(self.scene, self.start, self.nodes)
        return cached

    def draw_ranges(self) -> DrawRanges:
        """Every tile's partial leaves and their triangle ranges; computed once."""
        cached = self.__dict__.get("_draw_ranges")
        if cached is None:
            scene = self.scene
            cached = self.__dict__["_draw_ranges"] = DrawRanges(*_draw_ranges(
                self.start, self.nodes, scene.cluster_leaf, *scene.cluster_faces))
        return cached

    def triangles(self) -> np.ndarray:
        """``(m,)`` triangles each tile draws: its leaves', less what their ranges leave out."""
        start, leaves = self.leaf_lists()
        d = self.draw_ranges()
        faces = self.scene.cluster_faces[1]
        shown = _sums(d.range_start, d.ranges[:, 1])  # per partial leaf
        return _sums(start, faces[leaves]) - _sums(d.part_start, faces[d.part_leaf] - shown)

    def draw_calls(self) -> np.ndarray:
        """``(m,)`` draw calls each tile makes: one per whole leaf, one per range."""
        start, _ = self.leaf_lists()
        d = self.draw_ranges()
        return np.diff(start) + _sums(d.part_start, np.diff(d.range_start) - 1)

    def names(self, tile: int, leaves: bool = False) -> list[str]:
        """Node names for a tile; synthetic groups are replaced by the file nodes they hold."""
        names = self.scene.names
        if leaves:
            return [names[i] for i in self.tile_leaves(tile)]
        nodes = self.tile_nodes(tile)
        leaf = self.scene.cluster_leaf[nodes]
        if (leaf >= 0).any():  # a cluster: its leaf, named once
            nodes = np.unique(np.where(leaf >= 0, leaf, nodes))
        if self.scene.synthetic[nodes].any():
            cover = self.scene.real_cover
            nodes = np.concatenate([cover[i] for i in nodes])
        return [names[i] for i in np.sort(nodes)]


def _sums(start: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Sums of CSR segments: ``values[start[k]:start[k + 1]]`` for each ``k``."""
    total = np.r_[0, np.cumsum(values, dtype=np.int64)]
    return total[start[1:]] - total[start[:-1]]


class _Buffers:
    """Stacks and outputs the kernels write into, kept from frame to frame."""

    def __init__(self):
        self.arrays: dict[str, np.ndarray] = {}

    def get(self, name: str, size: int, dtype=np.int64) -> np.ndarray:
        a = self.arrays.get(name)
        if a is None or len(a) < size:
            a = self.arrays[name] = np.empty(max(size, 1024), dtype)
        return a

    def run(self, kernel, *args, cuts: bool = False):
        """Call ``kernel(*args, out_n, out_t)`` (``cuts``: and ``out_c``), doubling the outputs
        until they hold it all: ``(nodes, regions, tests)`` (``cuts``: ``(nodes, regions,
        cuts, tests)``)."""
        names = ("out_n", "out_t", "out_c") if cuts else ("out_n", "out_t")
        while True:
            outs = [self.get(name, 4096) for name in names]
            k, tests = kernel(*args, *outs)
            if k >= 0:
                return (*(out[:k] for out in outs), tests)
            for name, out in zip(names, outs):
                self.arrays[name] = np.empty(2 * len(out), np.int64)


def packed(state: SceneState) -> np.ndarray:
    """The state's bounds as packed records. While the state shares its scene's arrays (nothing
    moved), these are the scene's records, packed once for every state of the scene (every
    wall); a state that moved packs its own, copied from the scene's once, then re-packs only
    the rows each move changed (:meth:`SceneState.changed_rows`)."""
    cache = state.__dict__.get("_packed")  # (version, records, whether the state's own)
    if cache is not None and cache[0] == state.version:
        return cache[1]
    if state.shared:
        state.changed_rows()
        out, own = _scene_packed(state.scene, state.kind), False
    else:
        rows = state.changed_rows()
        if cache is not None and cache[2]:
            out = cache[1]
        else:  # the first pack since the state's first move
            rest = state.scene.__dict__.get("_packed", {}).get(state.kind)
            out = None if rest is None else rest.copy()
        if out is None or rows is None:
            out = pack(state.bounds)
        elif len(rows):
            out[rows] = pack(state.bounds.take(rows))
        own = True
    state.__dict__["_packed"] = (state.version, out, own)
    return out


_PACKING = threading.Lock()


def _scene_packed(scene, kind: str) -> np.ndarray:
    """The packed records of a scene's rest bounds of ``kind``, packed once per scene."""
    cache = scene.__dict__.setdefault("_packed", {})
    out = cache.get(kind)
    if out is None:
        with _PACKING:
            out = cache.get(kind)
            if out is None:
                out = cache[kind] = pack(scene.bounds(kind))
    return out


def _fh_table(wall) -> tuple[np.ndarray, np.ndarray]:
    """The frustum hierarchy as one int64 table (columns ``_FIRST`` ... ``_SIDE_B``) and, per
    node, the tile count above which ``adaptive`` unfolds a cut object there."""
    fh = wall.hierarchy
    n = len(fh)
    table = np.zeros((n, 8), np.int64)
    table[:, _FIRST], table[:, _SECOND] = fh.first, fh.second
    table[:, _PA], table[:, _PB], table[:, _TILE] = fh.plane_a, fh.plane_b, fh.tile
    inner = fh.tile < 0
    x_split = np.zeros(n, bool)
    x_split[inner] = fh.c0[fh.first[inner]] != fh.c0[fh.second[inner]]
    gap = np.where(x_split, wall.gap[0], wall.gap[1])
    table[:, _MODE] = np.where(gap == 0, _SHARED, np.where(gap > 0, _DISJOINT, _OVERLAP))
    # the side plane each child gets from the split: the first child's R (or B), the second's
    # L (or T); bits 0-3 are L, R, T, B
    table[:, _SIDE_A] = np.where(x_split, 2, 8)
    table[:, _SIDE_B] = np.where(x_split, 1, 4)
    tiles = (fh.c1 - fh.c0) * (fh.r1 - fh.r0)
    return table, UNFOLD_RATIO * np.log2(np.maximum(tiles, 1))


class Culler:
    """Culls one scene state to one wall, frame after frame, by one method.

    The wall's static tables (frustum hierarchy, per-tile plane indices) are built once, and so
    are the kernels' stacks and outputs; each call to :meth:`cull` takes the frame's planes
    (:class:`~wallcull.wall.Frusta`) and runs the traversal. Grid walls and screens walls
    share the kernels: a screens tile has six planes of its own (near and far included), and
    the splits of its frustum hierarchy are checked each frame. A stereo frame is culled once
    against planes that hold both eyes' frusta on a grid (:mod:`wallcull.stereo`), and eye by
    eye, merged, on screens. ``fine``: ``adaptive`` lists a leaf's clusters whole once they
    span less than this share of a tile's angular size (:data:`FINE`; 0: the finest clusters,
    where the methods' lists relate as the module docstring says).
    """

    def __init__(self, state: SceneState, wall, method: str = "adaptive",
                 pseudo_groups: bool = False, fine: float = FINE):
        if method not in METHODS:
            raise InputError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
        if pseudo_groups and wall.kind != "grid":
            raise InputError("pseudo-groups need a grid wall")
        self.state = state
        self.wall = wall
        self.method = method
        self.pseudo_groups = pseudo_groups
        self.fine = fine
        scene = state.scene
        self._tree = (scene.child_start, scene.child_count, scene.children)
        self._leaf_tree = (scene.child_start, scene.leaf_child_count, scene.children)
        tiles = wall.tiles
        if wall.kind == "grid":
            lay = wall.layout
            self._tile_planes = np.ascontiguousarray(lay.tile_planes, dtype=np.int64)
            self._tile_sides = np.ascontiguousarray(self._tile_planes[:, :4])
            self._primary_planes = lay.primary_planes.astype(np.int64)
            r, col = np.divmod(np.arange(tiles), wall.cols)
            border = ((col == 0) * 1 | (col == wall.cols - 1) * 2 | (r == 0) * 4
                      | (r == wall.rows - 1) * 8)
            self._inherit = (border | 48).astype(np.int64)
            self._force = (15 & ~border).astype(np.int64)
            self._fh, self._unfold = _fh_table(wall)
            self._fh_stereo = None  # made by the first stereo frame (8 MB on 256 x 256)
            self._near_bit = 1 << 4  # the primary planes are L, R, T, B, near, far
            self._unknown_at_root = 0
        else:
            self._tile_planes = np.arange(6 * tiles, dtype=np.int64).reshape(tiles, 6)
            self._tile_sides = self._tile_planes
            self._inherit = np.zeros(tiles, np.int64)
            self._force = np.full(tiles, 63, np.int64)
            self._fh, self._unfold = _screen_fh_table(wall)
            self._near_bit = 0
            self._unknown_at_root = _UNKNOWN
        self._size = np.full(tiles, 6, np.int64)
        # the nodes that stand for part of one leaf's triangles: its clusters, and the leaf
        self._parts_of_leaves = ((scene.cluster_of >= 0)
                                 | (scene.is_leaf & (scene.child_count > 0))).astype(np.uint8)
        self._separate: list = []  # scratch of drop_all
        self._units = (scene.units, *scene.unit_range)
        self._leaf_units = (scene.leaves, *scene.leaf_range)
        height = int(scene.depth.max()) + wall.hierarchy.height + 2
        self._depth_bound = height * max(int(scene.child_count.max()), 2)
        self._everywhere = np.ones(len(self._fh), np.uint8)
        self._split = _Split(self._fh, workers.count())
        self._buffers = [_Buffers() for _ in range(max(1, self._split.threads))]
        self._last_tests = 0
        self._last_pairs = None  # each tile's pairs in the last frame (balances the threads)

    def _run_adaptive(self, args, stack):
        """``adaptive`` over the whole frustum hierarchy, or, when the last frame took at least
        ``PARALLEL_TESTS`` tests, over its parts in threads at once (their tiles are disjoint,
        so the pairs are those of one call, each tile's in the same order)."""
        parts = self._split.parts(self._last_pairs) if self._last_tests >= PARALLEL_TESTS \
            else []

        def task(k, *_):
            buf = self._buffers[k]
            return buf.run(_adaptive, *args, parts[k] if parts else self._everywhere,
                           buf.get("stack_n", stack), buf.get("stack_m", stack),
                           buf.get("stack_o", stack), buf.get("tile_n", stack),
                           buf.get("tile_m", stack), cuts=True)

        if not parts:
            return task(0)
        done = workers.run(task, [(k, k + 1) for k in range(len(parts))])
        return (*(np.concatenate([d[j] for d in done]) for j in range(3)),
                sum(d[3] for d in done))

    def cull(self, frusta: Frusta) -> Visibility:
        """The frame's per-tile node lists."""
        t0 = time.perf_counter()
        vis = self._each_eye(frusta, None, None)
        vis.stats["cull_ms"] = (time.perf_counter() - t0) * 1e3
        return vis

    def cull_reflected(self, frusta: Frusta, reflection: np.ndarray,
                       extra: np.ndarray) -> Visibility:
        """Per-tile node lists of a mirror's view: the frame's frusta reflected by
        ``reflection (4, 4)`` (their layout and hierarchy stay the wall's), bounded besides by
        ``extra`` planes ``(k, 4)`` (the mirror's plane and outline) that every tile shares.
        The lists stop at leaves, never their clusters: a mirror's list is leaves, each drawn
        whole, and its clusters would only cost time (a leaf none of whose clusters the tile
        sees may be listed, as a caster is)."""
        return self._each_eye(frusta, reflection, extra)

    def _each_eye(self, frusta: Frusta, reflection, extra) -> Visibility:
        if not frusta.per_eye:
            return self._traverse(frusta, reflection, extra)
        lists = [self._traverse(f, reflection, extra) for f in frusta.per_eye]
        return merge(lists)

    def _traverse(self, frusta: Frusta, reflection, extra) -> Visibility:
        frame, wall = frusta.frame, self.wall
        # a mirror's view down to leaves (see cull_reflected), the frame's own to clusters
        tree, units = (self._leaf_tree, self._leaf_units) if reflection is not None else \
            (self._tree, self._units)
        planes = frusta.planes
        forward = -frame.rotation[:, 2]  # the view direction
        eye = frame.to_world(frusta.eye)
        if reflection is not None:
            planes = planes @ reflection  # a plane P of reflected points: P . (R p) = (P R) . p
            forward = reflection[:3, :3] @ forward
            eye = reflection[:3, :3] @ eye + reflection[:3, 3]
        box = packed(self.state)
        fh = self._fh
        if wall.kind == "grid":
            primary = self._primary_planes
            if frame.stereo is not None:
                if self._fh_stereo is None:  # two eyes: the planes of a split differ
                    self._fh_stereo = self._fh.copy()
                    self._fh_stereo[self._fh[:, _TILE] < 0, _MODE] = _OVERLAP
                fh = self._fh_stereo
            elif wall.gap[0] == 0.0 or wall.gap[1] == 0.0:
                # Equal and opposite split planes: one test decides both sides. Use the exact
                # negation so that rounding cannot make the two disagree.
                planes = _shared_planes(planes, wall)
            view = np.array([*forward, -float(forward @ eye), 0.0, 0.0, 0.0])  # depth
            depth = wall.distance + frusta.eye[2]
            (w, h), (gx, gy) = wall.tile_size, wall.gap
            pitch = ((w + gx) / depth, (h + gy) / depth)
            tile_angle = min(w, h) / depth
        else:
            primary = frusta.primary_rows.astype(np.int64)
            fh = fh.copy()  # a split that does not hold from this eye culls nothing
            fh[(fh[:, _MODE] == _SHARED) & ~frusta.valid, _MODE] = _PASS
            view = np.array([0.0, 0.0, 0.0, 0.0, *eye])  # all around the eye: distance
            pitch = wall.pitch
            tile_angle = min(pitch)
        if extra is not None and len(extra):
            # bounding planes beyond the 63 a view holds are left out, the last first: fewer
            # planes bound a larger region, so the lists only grow (a mirror's outline: its
            # plane, then its pyramid's, longest edges first)
            extra = extra[:max(63 - len(primary), 0)]
            primary = np.concatenate([primary, len(planes) + np.arange(len(extra))])
            planes = np.concatenate([planes, extra])
        if len(primary) > 63:
            raise InputError(f"at most 63 planes bound a view, got {len(primary)}")
        buf = self._buffers[0]
        n = len(box)
        stack = self._depth_bound + n  # the roots are at most all nodes
        t0 = time.perf_counter()
        stack_n, stack_m = buf.get("stack_n", stack), buf.get("stack_m", stack)
        roots, masks = buf.get("roots", n), buf.get("masks", n)
        count, primary_tests = _primary(*tree, box, planes, primary, roots, masks,
                                        stack_n, stack_m)
        roots, masks = roots[:count], masks[:count]
        regions = None if wall.kind == "grid" else self._tile_planes
        cuts = None  # the planes that cut each pair, where the traversal tells them
        if self.method == "naive":
            nodes, tiles, tests = buf.run(_naive, roots, masks, *units, box, planes,
                                          self._tile_planes, self._force, self._inherit)
        elif self.method == "oh":
            nodes, tiles, tests = buf.run(_oh, roots, masks, *tree, box, planes,
                                          self._tile_planes, self._size, self._force,
                                          self._inherit, stack_n, stack_m)
        elif self.method == "fh":
            nodes, tiles, tests = buf.run(_fh, roots, masks, *units, box, planes, fh,
                                          self._near_bit, regions, stack_n)
        elif self.pseudo_groups:
            nodes, tiles, tests = _pseudo(roots, masks, *tree, box, planes, fh,
                                          self._near_bit, self._tile_sides)
        else:
            nodes, tiles, cuts, tests = self._run_adaptive(
                (roots, masks, *tree, box, planes, fh, self._unfold, self._tile_sides,
                 view, pitch[0], pitch[1], self._near_bit, self._unknown_at_root, regions,
                 self._parts_of_leaves, self.fine * tile_angle),
                stack)
        self._last_tests = tests
        listed = len(nodes)
        t1 = time.perf_counter()
        # a grid's tiles' near faces are rectangles along the view's x and y
        basis = frame.rotation.T if wall.kind == "grid" and reflection is None else None
        nodes, tiles = drop_all(nodes, tiles, listed, box, planes, self._tile_planes,
                                tree[1], eye, SMALL * tile_angle, self._separate, cuts, basis)
        kept = len(nodes)
        t2 = time.perf_counter()
        start, ordered = _by_region(nodes, tiles, wall.tiles)
        if reflection is None:  # how the frame's next cull deals its threads
            self._last_pairs = np.diff(start)
        t3 = time.perf_counter()
        return Visibility(self.state.scene, start, ordered, {
            "method": self.method, "roots": int(count), "primary_tests": int(primary_tests),
            "tests": int(tests), "pairs": kept, "separated": listed - kept,
            # where a frame's cull goes: the two traversals, the separating axes, the sort
            "traverse_ms": (t1 - t0) * 1e3, "separate_ms": (t2 - t1) * 1e3,
            "sort_ms": (t3 - t2) * 1e3})


def leaf_lists(scene: Scene, start: np.ndarray, nodes: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Per region, the sorted leaf ids its nodes (CSR ``start``, ``nodes``) stand for."""
    leaf_start, leaf_count = scene.leaf_range
    return _expand(start, nodes, leaf_start, leaf_count, scene.leaves, scene.cluster_leaf)


def merge(lists: list[Visibility]) -> Visibility:
    """The union of per-tile lists (each eye's of a stereo frame): a node also under a node
    listed for the same tile is dropped, so every tile's nodes stay disjoint subtrees."""
    first = lists[0]
    start, nodes = first.start, first.nodes
    for other in lists[1:]:
        start, nodes = _merge_lists(start, nodes, other.start, other.nodes, first.scene.size)
    stats = {key: sum(v.stats[key] for v in lists)
             for key in ("roots", "primary_tests", "tests", "separated", "traverse_ms",
                         "separate_ms", "sort_ms")}
    return Visibility(first.scene, start, nodes, {"method": first.stats["method"], **stats,
                                                  "pairs": len(nodes), "eyes": len(lists)})


@njit(cache=True)
def _merge_lists(start_a, nodes_a, start_b, nodes_b, size):
    tiles = start_a.shape[0] - 1
    out = np.empty(nodes_a.shape[0] + nodes_b.shape[0], np.int64)
    out_start = np.zeros(tiles + 1, np.int64)
    k = 0
    for t in range(tiles):
        i, j = start_a[t], start_b[t]
        cover = -1  # the end of the subtree of the last node kept
        while i < start_a[t + 1] or j < start_b[t + 1]:
            if j >= start_b[t + 1] or (i < start_a[t + 1] and nodes_a[i] <= nodes_b[j]):
                node = nodes_a[i]
                i += 1
            else:
                node = nodes_b[j]
                j += 1
            if node < cover:
                continue  # in (or equal to) a node kept already
            out[k] = node
            k += 1
            cover = node + size[node]
        out_start[t + 1] = k
    return out_start, out[:k]


class _Split:
    """The frustum hierarchy cut into subtrees of disjoint tiles, dealt out to threads for
    ``adaptive`` (:meth:`parts`). The hierarchy is cut level by level until it has
    :data:`SUBTREES` subtrees a thread; each frame deals them out afresh, the heaviest first to
    the lightest thread, weighed by the pairs their tiles listed the frame before (what a
    part costs follows what its tiles show, which a split by tile count does not know: on
    64 x 64 one thread's half took a fifth longer than the other's). Nothing for one thread."""

    def __init__(self, table: np.ndarray, threads: int):
        self.threads = threads
        self.flags = np.zeros((0, len(table)), np.uint8)
        self.of_tile = np.zeros(0, np.int64)
        self._parts: dict = {}
        n = len(table)
        if threads < 2 or n < 3:
            return
        first, second, tile = table[:, _FIRST], table[:, _SECOND], table[:, _TILE]
        inner = tile < 0
        parent = np.full(n, -1)
        parent[first[inner]] = np.flatnonzero(inner)
        parent[second[inner]] = np.flatnonzero(inner)
        frontier = [0]
        while len(frontier) < threads * SUBTREES and any(inner[f] for f in frontier):
            frontier = [c for f in frontier for c in ((first[f], second[f]) if inner[f] else (f,))]
        self.flags = np.zeros((len(frontier), n), np.uint8)  # per subtree: it, its ancestors
        self.of_tile = np.zeros(int(tile.max()) + 1, np.int64)
        for k, f in enumerate(frontier):
            a = parent[f]
            while a >= 0:
                self.flags[k, a] = 1
                a = parent[a]
            todo = [f]
            while todo:
                g = todo.pop()
                self.flags[k, g] = 1
                if inner[g]:
                    todo += [first[g], second[g]]
                else:
                    self.of_tile[tile[g]] = k

    def parts(self, pairs: np.ndarray | None) -> list[np.ndarray]:
        """Each thread's flags per frustum node, from the pairs each tile listed the frame
        before (None: as many as it has tiles)."""
        count = len(self.flags)
        if count < 2:
            return []
        weight = np.bincount(self.of_tile, None if pairs is None else pairs, count).tolist()
        groups = range(min(self.threads, count))
        load, deal = [0.0] * len(groups), [0] * count
        for k in sorted(range(count), key=lambda k: -weight[k]):
            deal[k] = g = min(groups, key=load.__getitem__)
            load[g] += weight[k] + 1  # + 1: a subtree is work even when empty
        key = tuple(deal)
        parts = self._parts.get(key)
        if parts is None:
            if len(self._parts) > 256:  # a walkthrough deals few ways; keep those
                self._parts.clear()
            dealt = np.array(deal)
            parts = self._parts[key] = [np.bitwise_or.reduce(self.flags[dealt == g], axis=0)
                                        for g in groups]
        return parts


def _screen_fh_table(wall) -> tuple[np.ndarray, np.ndarray]:
    """The frustum-hierarchy table of a screens wall (see :func:`_fh_table`): a split node's
    plane is row ``6 T + node`` of the frame's table (:class:`~wallcull.wall.Frusta`), its
    second child outside it; a ``BOUNDS`` node names the tile bounding each child."""
    from .screens import BOUNDS, SPLIT

    h = wall.hierarchy
    n = len(h)
    table = np.zeros((n, 8), np.int64)
    table[:, _FIRST], table[:, _SECOND], table[:, _TILE] = h.first, h.second, h.tile
    split, bounds = h.mode == SPLIT, h.mode == BOUNDS
    table[split, _PA] = 6 * wall.tiles + np.flatnonzero(split)
    table[split, _MODE] = _SHARED
    table[bounds, _PA] = h.own[h.first[bounds]]
    table[bounds, _PB] = h.own[h.second[bounds]]
    table[bounds, _MODE] = _BOUNDS
    counts = np.array([len(m) for m in h.members])
    unfold = SCREENS_UNFOLD_RATIO * np.log2(np.maximum(counts, 1))
    return table, np.where(counts >= SCREENS_UNFOLD_TILES, unfold, np.inf)


def _shared_planes(planes: np.ndarray, wall) -> np.ndarray:
    """Where a gap is 0, make each ``L[c+1]`` exactly ``-R[c]`` (or ``T[r+1]`` exactly ``-B[r]``)."""
    lay = wall.layout
    planes = planes.copy()
    if wall.gap[0] == 0.0:
        c = np.arange(1, wall.cols)
        planes[lay.L(c)] = -planes[lay.R(c - 1)]
    if wall.gap[1] == 0.0:
        r = np.arange(1, wall.rows)
        planes[lay.T(r)] = -planes[lay.B(r - 1)]
    return planes


@dataclass
class Regions:
    """The nodes of a scene in each of several convex regions, CSR: region ``q`` holds
    ``nodes[start[q]:start[q+1]]`` (increasing ids; internal nodes stand for their subtrees)."""

    scene: Scene
    start: np.ndarray
    nodes: np.ndarray
    tests: int = 0

    def region(self, q: int) -> np.ndarray:
        return self.nodes[self.start[q]:self.start[q + 1]]

    def leaf_lists(self) -> tuple[np.ndarray, np.ndarray]:
        """Every region's sorted leaf ids, CSR."""
        return leaf_lists(self.scene, self.start, self.nodes)


def stack_depth(state: SceneState) -> int:
    """The deepest a depth-first traversal of the scene's hierarchy gets (its stack's size;
    kept on ``state``)."""
    depth = state.__dict__.get("_stack_depth")
    if depth is None:
        scene = state.scene
        depth = state.__dict__["_stack_depth"] = \
            (int(scene.depth.max()) + 2) * int(scene.child_count.max()) + 1
    return depth


def cull_regions(state: SceneState, planes: np.ndarray, region_planes: np.ndarray,
                 region_size: np.ndarray | None = None, work: np.ndarray | None = None
                 ) -> Regions:
    """Cull the scene to many convex regions at once, each the intersection of some of
    ``planes (P, 4)`` (inward unit normals): region ``q`` uses rows
    ``region_planes[q, :region_size[q]]`` (at most 63). Nodes wholly inside a region stand for
    their subtrees, as in a tile list. The object hierarchy is culled to each region in turn
    with plane masking (the ``oh`` kernel), down to leaves (not their clusters): the shadow
    casters of every tile.
    The regions are split among threads (:mod:`wallcull.workers`), by ``work`` (cumulative,
    ``(R + 1,)``: an estimate of each region's cost) when given."""
    planes = np.ascontiguousarray(planes, dtype=np.float64)
    region_planes = np.ascontiguousarray(region_planes, dtype=np.int64)
    count = len(region_planes)
    if region_size is None:
        region_size = np.full(count, region_planes.shape[1] if count else 0, np.int64)
    region_size = np.ascontiguousarray(region_size, dtype=np.int64)
    if count and not (0 < region_size.min() and region_size.max() <= 63):
        raise InputError("a region needs 1 to 63 planes")
    scene = state.scene
    box = packed(state)
    force = (np.int64(1) << region_size) - 1
    stack = stack_depth(state)
    root = np.zeros(1, np.int64)
    ranges = workers.chunks(count, work, per_thread=workers.SPLIT)
    pool = state.__dict__.setdefault("_region_buffers", [])  # kept: outputs grow once
    pool.extend(_Buffers() for _ in range(len(ranges) - len(pool)))
    inherit = np.zeros(count, np.int64)

    def chunk(k, a, b):  # regions [a, b), on buffers of their own
        buf = pool[k]
        return buf.run(
            _oh, root, root, scene.child_start, scene.leaf_child_count, scene.children, box,
            planes, region_planes[a:b], region_size[a:b], force[a:b], inherit[a:b],
            buf.get("stack_n", stack), buf.get("stack_m", stack))

    parts = workers.run(chunk, ranges)
    # The kernel lists region after region, each in preorder (see :func:`_by_region`): the
    # pairs are already in CSR order.
    ordered = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
    start = np.zeros(count + 1, np.int64)
    for (a, b), (_, which, _) in zip(ranges, parts):
        start[a + 1:b + 1] = np.bincount(which, minlength=b - a)
    np.cumsum(start, out=start)
    return Regions(scene, start, ordered, int(sum(p[2] for p in parts)))


def cull_region(state: SceneState, planes: np.ndarray) -> np.ndarray:
    """Nodes of the scene that meet the convex region ``planes (k, 4)`` (inward unit normals,
    ``k <= 63``): internal nodes wholly inside stand for their subtrees, as in a tile list."""
    planes = np.ascontiguousarray(planes, dtype=np.float64)
    if not 0 < len(planes) <= 63:
        raise InputError(f"a region needs 1 to 63 planes, got {len(planes)}")
    return cull_regions(state, planes, np.arange(len(planes))[None]).nodes


def depth_ranges(state: SceneState, start: np.ndarray, nodes: np.ndarray, forward: np.ndarray,
                 origin: np.ndarray, empty: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Per region of a CSR node list, the depth range ``(lo, hi)`` along unit ``forward[q]``
    from ``origin[q]`` (``(R, 3)`` each, or ``(1, 3)`` for all) that its nodes' bounds span;
    ``empty`` for a region with no node. Compiled, next to the traversal: a wall's tight depth
    ranges (the shadow pass calls the kernel itself, for each tile's nearest caster)."""
    return _depth_ranges(start, nodes, packed(state),
                         np.ascontiguousarray(forward, np.float64).reshape(-1, 3),
                         np.ascontiguousarray(origin, np.float64).reshape(-1, 3),
                         float(empty[0]), float(empty[1]))


def cull(state: SceneState, frusta: Frusta, method: str = "adaptive",
         pseudo_groups: bool = False, fine: float = FINE) -> Visibility:
    """One-shot cull; build a :class:`Culler` to cull many frames."""
    return Culler(state, frusta.wall, method, pseudo_groups, fine).cull(frusta)
