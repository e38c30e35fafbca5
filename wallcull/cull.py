"""The traversals of paper section 4.2: naive, OH without FH, FH without OH, adaptive OH+FH.

All four start from the same first-level cull against the primary frustum (:func:`_primary`),
which yields *roots*: internal nodes wholly inside the primary frustum, and leaves that meet it.
Then:

* ``naive``    every leaf under the roots against every tile frustum, O(n m);
* ``oh``       the object hierarchy culled to each tile in turn, O(m log n);
* ``fh``       each leaf pushed down the frustum hierarchy, O(n log m);
* ``adaptive`` Algorithm 2 with the decision of the text: a pair (object node, frustum node)
  whose object lies on one side of the frustum node's split moves down the FH intact; one the
  split cuts unfolds into the object's children (a cut leaf goes down both sides). Optional
  *pseudo-groups*: when a node unfolds, the children that fall on the same side are regrouped
  under a fresh axis-aligned box and move down together.

Every test is the rounded-box test of :mod:`wallcull.bounds`: a bound is outside a plane when
``n . c + d < -r``. Every method is conservative, and an internal node is reported to a tile
only when its bound lies inside all the planes that tile is tested against, so a reported node
never stands for leaves the same test would have rejected. For the same bounds:

* ``naive`` and ``oh`` report the same leaves: those whose bound is outside none of the tile's
  six planes;
* ``fh`` and ``adaptive`` (with or without pseudo-groups) report the same leaves: those outside
  none of the primary planes and the split planes on the tile's path down the FH;
* the second set is contained in the first. The split planes above a tile are planes through the
  eye whose half-spaces contain the tile frustum, so they are valid culling planes; in front of
  the eye they add nothing to the tile's own planes, but a bound that straddles the eye's plane
  can pass each of the tile's planes one at a time and still be rejected by one of them.

The methods differ in how many tests they take, and how many internal nodes stand for leaves.

The kernels are compiled with numba: the recursion of the paper is a loop over an explicit
stack of node ids, over the structure-of-arrays hierarchy, with no Python object per node.
Each kernel writes out its own plane-masked test, stack pushes and output appends. Helpers for
them, inlined or not, made the kernels 15-20% slower (numba passes the grown arrays back as
tuples), so the repetition is deliberate.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from .errors import InputError
from .scene import Scene, SceneState
from .wall import Frusta

METHODS = ("naive", "oh", "fh", "adaptive")

_ALL6 = 63  # the six planes of a frustum as a bit mask: L, R, T, B, near, far


# --------------------------------------------------------------------------- kernels


@njit(cache=True, inline="always")
def _classify(c, a, h, rad, i, planes, p):
    """``(s, r)`` of bound ``i`` against plane ``p``: outside when ``s < -r``, inside if ``s >= r``."""
    nx, ny, nz, d = planes[p, 0], planes[p, 1], planes[p, 2], planes[p, 3]
    s = nx * c[i, 0] + ny * c[i, 1] + nz * c[i, 2] + d
    r = (abs(nx * a[i, 0, 0] + ny * a[i, 0, 1] + nz * a[i, 0, 2]) * h[i, 0]
         + abs(nx * a[i, 1, 0] + ny * a[i, 1, 1] + nz * a[i, 1, 2]) * h[i, 1]
         + abs(nx * a[i, 2, 0] + ny * a[i, 2, 1] + nz * a[i, 2, 2]) * h[i, 2] + rad[i])
    return s, r


@njit(cache=True)
def _grow(a):
    out = np.empty(2 * a.shape[0], a.dtype)
    out[:a.shape[0]] = a
    return out


@njit(cache=True)
def _primary(child_start, child_count, children, is_leaf, c, a, h, rad, planes, plane_ids):
    """Cull the root's children to one convex region: ``(roots, masks, tests)``.

    The region is the intersection of the planes ``plane_ids`` (at most 63). ``roots`` are the
    nodes wholly inside it and the leaves that meet it; ``masks`` holds, per root, the planes it
    is not yet known to be inside (bit ``p`` for ``plane_ids[p]``). Planes a node is inside of
    are dropped for its children (plane masking).
    """
    roots = np.empty(256, np.int64)
    masks = np.empty(256, np.int64)
    stack_n = np.empty(256, np.int64)
    stack_m = np.empty(256, np.int64)
    count = plane_ids.shape[0]
    n = 0
    tests = 0
    for k in range(child_start[0], child_start[0] + child_count[0]):
        sp = 1
        stack_n[0] = children[k]
        stack_m[0] = (1 << count) - 1
        while sp > 0:
            sp -= 1
            i = stack_n[sp]
            m = stack_m[sp]
            outside = False
            for p in range(count):
                if m & (1 << p):
                    s, r = _classify(c, a, h, rad, i, planes, plane_ids[p])
                    tests += 1
                    if s < -r:
                        outside = True
                        break
                    if s >= r:
                        m &= ~(1 << p)
            if outside:
                continue
            if m == 0 or is_leaf[i]:
                if n == roots.shape[0]:
                    roots = _grow(roots)
                    masks = _grow(masks)
                roots[n] = i
                masks[n] = m
                n += 1
                continue
            k0 = child_start[i]
            while sp + child_count[i] > stack_n.shape[0]:
                stack_n = _grow(stack_n)
                stack_m = _grow(stack_m)
            for j in range(k0 + child_count[i] - 1, k0 - 1, -1):
                stack_n[sp] = children[j]
                stack_m[sp] = m
                sp += 1
    return roots[:n], masks[:n], tests


@njit(cache=True)
def _tile_mask(root_mask, force, inherit):
    # A tile must test its inner side planes; its border planes and near/far are the primary's,
    # which the root may already be known to be inside.
    return force | (root_mask & inherit)


@njit(cache=True)
def _naive(roots, masks, leaves, leaf_start, leaf_count, c, a, h, rad, planes, tile_planes,
           force, inherit):
    out_n = np.empty(1024, np.int64)
    out_t = np.empty(1024, np.int64)
    k = 0
    tests = 0
    for j in range(roots.shape[0]):
        root = roots[j]
        for li in range(leaf_start[root], leaf_start[root] + leaf_count[root]):
            leaf = leaves[li]
            for t in range(tile_planes.shape[0]):
                m = _tile_mask(masks[j], force[t], inherit[t])
                visible = True
                for p in range(6):
                    if m & (1 << p):
                        s, r = _classify(c, a, h, rad, leaf, planes, tile_planes[t, p])
                        tests += 1
                        if s < -r:
                            visible = False
                            break
                if visible:
                    if k == out_n.shape[0]:
                        out_n = _grow(out_n)
                        out_t = _grow(out_t)
                    out_n[k] = leaf
                    out_t[k] = t
                    k += 1
    return out_n[:k], out_t[:k], tests


@njit(cache=True)
def _oh(roots, masks, child_start, child_count, children, is_leaf, c, a, h, rad, planes,
        tile_planes, force, inherit):
    out_n = np.empty(1024, np.int64)
    out_t = np.empty(1024, np.int64)
    stack_n = np.empty(256, np.int64)
    stack_m = np.empty(256, np.int64)
    k = 0
    tests = 0
    for t in range(tile_planes.shape[0]):
        while roots.shape[0] > stack_n.shape[0]:
            stack_n = _grow(stack_n)
            stack_m = _grow(stack_m)
        sp = 0
        for j in range(roots.shape[0] - 1, -1, -1):
            stack_n[sp] = roots[j]
            stack_m[sp] = _tile_mask(masks[j], force[t], inherit[t])
            sp += 1
        while sp > 0:
            sp -= 1
            i = stack_n[sp]
            m = stack_m[sp]
            outside = False
            for p in range(6):
                if m & (1 << p):
                    s, r = _classify(c, a, h, rad, i, planes, tile_planes[t, p])
                    tests += 1
                    if s < -r:
                        outside = True
                        break
                    if s >= r:
                        m &= ~(1 << p)
            if outside:
                continue
            if m == 0 or is_leaf[i]:
                if k == out_n.shape[0]:
                    out_n = _grow(out_n)
                    out_t = _grow(out_t)
                out_n[k] = i
                out_t[k] = t
                k += 1
                continue
            k0 = child_start[i]
            while sp + child_count[i] > stack_n.shape[0]:
                stack_n = _grow(stack_n)
                stack_m = _grow(stack_m)
            for q in range(k0 + child_count[i] - 1, k0 - 1, -1):
                stack_n[sp] = children[q]
                stack_m[sp] = m
                sp += 1
    return out_n[:k], out_t[:k], tests


@njit(cache=True, inline="always")
def _box_sr(box, g, planes, p):
    """``(s, r)`` of an axis-aligned box ``box[g] = (centre, half extents)`` against plane ``p``."""
    nx, ny, nz, d = planes[p, 0], planes[p, 1], planes[p, 2], planes[p, 3]
    s = nx * box[g, 0] + ny * box[g, 1] + nz * box[g, 2] + d
    r = abs(nx) * box[g, 3] + abs(ny) * box[g, 4] + abs(nz) * box[g, 5]
    return s, r


_OUT, _CUT, _FULL = 0, 1, 2


@njit(cache=True, inline="always")
def _state(s, r):
    if s < -r:
        return _OUT
    if s >= r:
        return _FULL
    return _CUT


@njit(cache=True, inline="always")
def _states(c, a, h, rad, i, planes, pa, pb, shared_split):
    """States of bound ``i`` against a split's two planes: ``(state_a, state_b, tests)``."""
    s, r = _classify(c, a, h, rad, i, planes, pa)
    if shared_split:
        return _state(s, r), _state(-s, r), 1
    sa = _state(s, r)
    s, r = _classify(c, a, h, rad, i, planes, pb)
    return sa, _state(s, r), 2


@njit(cache=True)
def _fh(roots, leaves, leaf_start, leaf_count, c, a, h, rad, planes, fh_first, fh_second,
        fh_plane_a, fh_plane_b, fh_tile, shared_split):
    out_n = np.empty(1024, np.int64)
    out_t = np.empty(1024, np.int64)
    stack = np.empty(256, np.int64)
    k = 0
    tests = 0
    for j in range(roots.shape[0]):
        root = roots[j]
        for li in range(leaf_start[root], leaf_start[root] + leaf_count[root]):
            leaf = leaves[li]
            stack[0] = 0
            sp = 1
            while sp > 0:
                sp -= 1
                f = stack[sp]
                if fh_tile[f] >= 0:
                    if k == out_n.shape[0]:
                        out_n = _grow(out_n)
                        out_t = _grow(out_t)
                    out_n[k] = leaf
                    out_t[k] = fh_tile[f]
                    k += 1
                    continue
                sa, sb, nt = _states(c, a, h, rad, leaf, planes, fh_plane_a[f], fh_plane_b[f],
                                     shared_split)
                tests += nt
                if sp + 2 > stack.shape[0]:
                    stack = _grow(stack)
                if sb != _OUT:
                    stack[sp] = fh_second[f]
                    sp += 1
                if sa != _OUT:
                    stack[sp] = fh_first[f]
                    sp += 1
    return out_n[:k], out_t[:k], tests


@njit(cache=True)
def _adaptive(roots, child_start, child_count, children, is_leaf, c, a, h, rad, planes,
              fh_first, fh_second, fh_plane_a, fh_plane_b, fh_tile, shared_split):
    """Algorithm 2 over an explicit stack of (object node, frustum node) pairs.

    At an internal frustum node the object is tested against the planes bounding the two
    children (one plane, negated, when there is no gap). Against each it is out, cut or full.
    If neither plane cuts it, it moves down intact to each child it fills; if one does, a leaf
    goes down to each child it is not out of, and an internal node unfolds into its children,
    which are tested at the same frustum node. So an internal node reaches a tile only when its
    bound lies wholly inside the tile frustum.
    """
    out_n = np.empty(1024, np.int64)
    out_t = np.empty(1024, np.int64)
    so = np.empty(1024, np.int64)  # stack: object node
    sf = np.empty(1024, np.int64)  # stack: frustum node
    k = 0
    tests = 0
    sp = 0
    while roots.shape[0] > so.shape[0]:
        so = _grow(so)
        sf = _grow(sf)
    for j in range(roots.shape[0] - 1, -1, -1):
        so[sp] = roots[j]
        sf[sp] = 0
        sp += 1
    while sp > 0:
        sp -= 1
        o = so[sp]
        f = sf[sp]
        tile = fh_tile[f]
        if tile >= 0:  # Alg. 2 lines 1-3: a frustum leaf; mark visible
            if k == out_n.shape[0]:
                out_n = _grow(out_n)
                out_t = _grow(out_t)
            out_n[k] = o
            out_t[k] = tile
            k += 1
            continue
        sa, sb, nt = _states(c, a, h, rad, o, planes, fh_plane_a[f], fh_plane_b[f],
                             shared_split)
        tests += nt
        first = fh_first[f]
        second = fh_second[f]
        if sp + 2 > so.shape[0]:
            so = _grow(so)
            sf = _grow(sf)
        if sa != _CUT and sb != _CUT:  # on one side (or in both, or in a gap): intact
            if sb == _FULL:
                so[sp] = o
                sf[sp] = second
                sp += 1
            if sa == _FULL:
                so[sp] = o
                sf[sp] = first
                sp += 1
            continue
        if is_leaf[o]:  # a cut leaf goes down every side it reaches
            if sb != _OUT:
                so[sp] = o
                sf[sp] = second
                sp += 1
            if sa != _OUT:
                so[sp] = o
                sf[sp] = first
                sp += 1
            continue
        m0 = child_start[o]  # cut: unfold into the children, tested at this frustum node
        m_count = child_count[o]
        while sp + m_count > so.shape[0]:
            so = _grow(so)
            sf = _grow(sf)
        for q in range(m0 + m_count - 1, m0 - 1, -1):
            so[sp] = children[q]
            sf[sp] = f
            sp += 1
    return out_n[:k], out_t[:k], tests


@njit(cache=True)
def _group(members, count, c, a, h, rad, pool_box, pool_start, pool_members, n_pg, n_pm):
    """Append a pseudo-group of ``members[:count]`` to the pool, with its axis-aligned box.

    ``pool_box[g]`` holds the centre and half extents (6 numbers). Returns the (possibly grown)
    pool arrays and the new counts.
    """
    if n_pg + 1 >= pool_start.shape[0]:
        pool_box = _grow2(pool_box)
        pool_start = _grow(pool_start)
    while n_pm + count > pool_members.shape[0]:
        pool_members = _grow(pool_members)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for q in range(count):
        i = members[q]
        pool_members[n_pm + q] = i
        for j in range(3):
            e = (abs(a[i, 0, j]) * h[i, 0] + abs(a[i, 1, j]) * h[i, 1]
                 + abs(a[i, 2, j]) * h[i, 2] + rad[i])
            lo[j] = min(lo[j], c[i, j] - e)
            hi[j] = max(hi[j], c[i, j] + e)
    for j in range(3):
        mid = (lo[j] + hi[j]) / 2
        pool_box[n_pg, j] = mid
        # rounded up so that the box still holds its members after rounding
        pool_box[n_pg, 3 + j] = (hi[j] - lo[j]) / 2 * (1 + 4e-16) + 4e-16 * abs(mid)
    pool_start[n_pg] = n_pm
    pool_start[n_pg + 1] = n_pm + count
    return pool_box, pool_start, pool_members, n_pg + 1, n_pm + count


@njit(cache=True)
def _adaptive_pseudo(roots, child_start, child_count, children, is_leaf, c, a, h, rad, planes,
                     fh_first, fh_second, fh_plane_a, fh_plane_b, fh_tile, shared_split):
    """:func:`_adaptive` with pseudo-groups (paper section 4.2).

    When an object unfolds, its members are classified at once and the ones wholly on one side
    of the split are regrouped under a fresh axis-aligned box that moves down as one object.
    The roots of the first-level cull enter the frustum hierarchy as one such group, so a flat
    scene (one parent, thousands of leaves) benefits too. Object ids ``>= n`` name groups;
    group ``g`` holds ``pool_members[pool_start[g]:pool_start[g + 1]]``, all scene nodes.
    """
    n = c.shape[0]
    out_n = np.empty(1024, np.int64)
    out_t = np.empty(1024, np.int64)
    so = np.empty(1024, np.int64)  # stack: object
    sf = np.empty(1024, np.int64)  # stack: frustum node
    pool_box = np.empty((64, 6))
    pool_start = np.zeros(65, np.int64)
    pool_members = np.empty(256, np.int64)
    n_pg = 0
    n_pm = 0
    firsts = np.empty(64, np.int64)  # members of an unfolding object wholly on each side
    seconds = np.empty(64, np.int64)
    k = 0
    tests = 0
    sp = 0
    if roots.shape[0] > 1:
        pool_box, pool_start, pool_members, n_pg, n_pm = _group(
            roots, roots.shape[0], c, a, h, rad, pool_box, pool_start, pool_members, n_pg, n_pm)
        so[0] = n
        sf[0] = 0
        sp = 1
    elif roots.shape[0] == 1:
        so[0] = roots[0]
        sf[0] = 0
        sp = 1
    while sp > 0:
        sp -= 1
        o = so[sp]
        f = sf[sp]
        if o < n:
            m0, m_count = child_start[o], child_count[o]
        else:
            m0, m_count = pool_start[o - n], pool_start[o - n + 1] - pool_start[o - n]
        tile = fh_tile[f]
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
            s, r = _classify(c, a, h, rad, o, planes, fh_plane_a[f])
        else:
            s, r = _box_sr(pool_box, o - n, planes, fh_plane_a[f])
        sa = _state(s, r)
        if shared_split:
            sb = _state(-s, r)
            tests += 1
        else:
            if o < n:
                s, r = _classify(c, a, h, rad, o, planes, fh_plane_b[f])
            else:
                s, r = _box_sr(pool_box, o - n, planes, fh_plane_b[f])
            sb = _state(s, r)
            tests += 2
        first = fh_first[f]
        second = fh_second[f]
        while sp + 2 * m_count + 2 > so.shape[0]:
            so = _grow(so)
            sf = _grow(sf)
        if sa != _CUT and sb != _CUT:  # intact to each side it fills
            if sb == _FULL:
                so[sp] = o
                sf[sp] = second
                sp += 1
            if sa == _FULL:
                so[sp] = o
                sf[sp] = first
                sp += 1
            continue
        if o < n and is_leaf[o]:
            if sb != _OUT:
                so[sp] = o
                sf[sp] = second
                sp += 1
            if sa != _OUT:
                so[sp] = o
                sf[sp] = first
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
            ma, mb, nt = _states(c, a, h, rad, i, planes, fh_plane_a[f], fh_plane_b[f],
                                 shared_split)
            tests += nt
            if ma == _FULL and mb == _OUT:
                firsts[n_first] = i
                n_first += 1
            elif mb == _FULL and ma == _OUT:
                seconds[n_second] = i
                n_second += 1
            elif ma != _CUT and mb != _CUT:  # in both children (projector overlap) or neither
                if mb == _FULL:
                    so[sp] = i
                    sf[sp] = second
                    sp += 1
                if ma == _FULL:
                    so[sp] = i
                    sf[sp] = first
                    sp += 1
            elif is_leaf[i]:
                if mb != _OUT:
                    so[sp] = i
                    sf[sp] = second
                    sp += 1
                if ma != _OUT:
                    so[sp] = i
                    sf[sp] = first
                    sp += 1
            else:  # cut: unfold it here
                while sp + child_count[i] + 2 * m_count > so.shape[0]:
                    so = _grow(so)
                    sf = _grow(sf)
                for qq in range(child_start[i], child_start[i] + child_count[i]):
                    so[sp] = children[qq]
                    sf[sp] = f
                    sp += 1
        for side in range(2):
            members = firsts if side == 0 else seconds
            count = n_first if side == 0 else n_second
            target = first if side == 0 else second
            if count == 1:
                so[sp] = members[0]
                sf[sp] = target
                sp += 1
            elif count > 1:
                pool_box, pool_start, pool_members, n_pg, n_pm = _group(
                    members, count, c, a, h, rad, pool_box, pool_start, pool_members, n_pg, n_pm)
                so[sp] = n + n_pg - 1
                sf[sp] = target
                sp += 1
    return out_n[:k], out_t[:k], tests


@njit(cache=True)
def _grow2(a):
    out = np.empty((2 * a.shape[0], a.shape[1]), a.dtype)
    out[:a.shape[0]] = a
    return out


@njit(cache=True)
def _by_tile(nodes, tiles, m):
    """Counting sort of (node, tile) pairs into per-tile CSR ``(start (m + 1,), nodes)``."""
    start = np.zeros(m + 1, np.int64)
    for t in tiles:
        start[t + 1] += 1
    for t in range(m):
        start[t + 1] += start[t]
    fill = start[:-1].copy()
    out = np.empty(nodes.shape[0], np.int64)
    for j in range(nodes.shape[0]):
        t = tiles[j]
        out[fill[t]] = nodes[j]
        fill[t] += 1
    return start, out


# --------------------------------------------------------------------------- public API


@dataclass
class Visibility:
    """Per-tile lists of scene nodes, in CSR form: tile ``t`` sees ``nodes[start[t]:start[t+1]]``.

    A listed internal node stands for its whole subtree (SPEC section 4).
    """

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
        return np.unique(self.scene.subtree_leaves(self.tile_nodes(tile)))

    def leaf_lists(self) -> tuple[np.ndarray, np.ndarray]:
        """Every tile's sorted leaf ids at once, in CSR form ``(start (m + 1,), leaves)``."""
        scene = self.scene
        tiles = np.repeat(np.arange(self.tiles), np.diff(self.start))
        leaf_start, leaf_count = scene.leaf_range
        count = leaf_count[self.nodes]
        offsets = np.repeat(leaf_start[self.nodes] - np.cumsum(count) + count, count)
        leaves = scene.leaves[np.arange(int(count.sum())) + offsets]
        key = np.unique(np.repeat(tiles, count) * len(scene) + leaves)
        tile_of, leaves = np.divmod(key, len(scene))
        return np.searchsorted(tile_of, np.arange(self.tiles + 1)), leaves

    def names(self, tile: int, leaves: bool = False) -> list[str]:
        """Node names for a tile; synthetic groups are replaced by the file nodes they hold."""
        names = self.scene.names
        if leaves:
            return [names[i] for i in self.tile_leaves(tile)]
        nodes = self.tile_nodes(tile)
        if self.scene.synthetic[nodes].any():
            cover = self.scene.real_cover
            nodes = np.concatenate([cover[i] for i in nodes])
        return [names[i] for i in np.sort(nodes)]


class Culler:
    """Culls one scene state to one wall, frame after frame, by one method.

    The wall's static tables (frustum hierarchy, per-tile plane indices) are built once; each
    call to :meth:`cull` builds the frame's planes and runs the traversal.
    """

    def __init__(self, state: SceneState, wall, method: str = "adaptive",
                 pseudo_groups: bool = False):
        if method not in METHODS:
            raise InputError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
        self.state = state
        self.wall = wall
        self.method = method
        self.pseudo_groups = pseudo_groups
        scene = state.scene
        self._tree = (scene.child_start, scene.child_count, scene.children,
                      scene.is_leaf.astype(np.uint8))
        lay = wall.layout
        self._tile_planes = lay.tile_planes.astype(np.int64)
        self._primary_planes = lay.primary_planes.astype(np.int64)
        r, col = np.divmod(np.arange(wall.tiles), wall.cols)
        border = ((col == 0) * 1 | (col == wall.cols - 1) * 2 | (r == 0) * 4
                  | (r == wall.rows - 1) * 8)
        self._inherit = (border | 48).astype(np.int64)
        self._force = (15 & ~border).astype(np.int64)
        fh = wall.hierarchy
        self._fh = (fh.first, fh.second, fh.plane_a, fh.plane_b, fh.tile)
        self._shared_split = wall.gap == (0.0, 0.0)
        leaf_start, leaf_count = scene.leaf_range
        self._leaves = (scene.leaves, leaf_start, leaf_count)

    def cull(self, frusta: Frusta) -> Visibility:
        t0 = time.perf_counter()
        b = self.state.bounds
        geo = (b.center, b.axes, b.half, b.radius)
        planes = frusta.planes
        if self._shared_split:
            # Equal and opposite split planes: one test decides both sides. Use the exact
            # negation so that rounding cannot make the two disagree.
            planes = _shared_planes(planes, self.wall)
        roots, masks, primary_tests = _primary(*self._tree, *geo, planes, self._primary_planes)
        if self.method == "naive":
            nodes, tiles, tests = _naive(roots, masks, *self._leaves, *geo, planes,
                                         self._tile_planes, self._force, self._inherit)
        elif self.method == "oh":
            nodes, tiles, tests = _oh(roots, masks, *self._tree, *geo, planes,
                                      self._tile_planes, self._force, self._inherit)
        elif self.method == "fh":
            nodes, tiles, tests = _fh(roots, *self._leaves, *geo, planes, *self._fh,
                                      self._shared_split)
        else:
            kernel = _adaptive_pseudo if self.pseudo_groups else _adaptive
            nodes, tiles, tests = kernel(roots, *self._tree, *geo, planes, *self._fh,
                                         self._shared_split)
        start, ordered = _by_tile(nodes, tiles, self.wall.tiles)
        elapsed = time.perf_counter() - t0
        return Visibility(self.state.scene, start, ordered, {
            "method": self.method, "roots": len(roots), "primary_tests": int(primary_tests),
            "tests": int(tests), "pairs": len(nodes), "cull_ms": elapsed * 1e3,
        })


def _shared_planes(planes: np.ndarray, wall) -> np.ndarray:
    """With no gap, make each ``L[c+1]`` exactly ``-R[c]`` and ``T[r+1]`` exactly ``-B[r]``."""
    lay = wall.layout
    planes = planes.copy()
    c = np.arange(1, wall.cols)
    planes[lay.L(c)] = -planes[lay.R(c - 1)]
    r = np.arange(1, wall.rows)
    planes[lay.T(r)] = -planes[lay.B(r - 1)]
    return planes


def cull_region(state: SceneState, planes: np.ndarray) -> np.ndarray:
    """Nodes of the scene that meet the convex region ``planes (k, 4)`` (inward unit normals,
    ``k <= 63``): internal nodes wholly inside stand for their subtrees, as in a tile list.
    Used for shadow casters and mirror views."""
    planes = np.ascontiguousarray(planes, dtype=np.float64)
    if not 0 < len(planes) <= 63:
        raise InputError(f"a region needs 1 to 63 planes, got {len(planes)}")
    scene, b = state.scene, state.bounds
    roots, _, _ = _primary(scene.child_start, scene.child_count, scene.children,
                           scene.is_leaf.astype(np.uint8), b.center, b.axes, b.half, b.radius,
                           planes, np.arange(len(planes), dtype=np.int64))
    return roots


def cull(state: SceneState, frusta: Frusta, method: str = "adaptive",
         pseudo_groups: bool = False) -> Visibility:
    """One-shot cull; build a :class:`Culler` to cull many frames."""
    return Culler(state, frusta.wall, method, pseudo_groups).cull(frusta)
