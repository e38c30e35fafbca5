"""Fitted frusta: what each tile's render node needs to draw exactly its part, and no more.

Per tile and frame:

* ``view``: world to eye space, eye space being display space moved to the tracked eye. It is
  the same for every tile of a frame.
* ``projection``: the off-axis frustum through the tile's rectangle (SPEC sections 1-3).
  ``near`` and ``far`` are fitted to the bounds of what the tile shows, never cutting them, and
  clamped to the wall's. A 24-bit depth buffer is then spent where the geometry is. Optionally it
  uses reversed-Z: depth in [0, 1], near at 1 (the client uses glClipControl ZERO_TO_ONE,
  clears depth to 0 and tests GREATER).
* ``shadows`` (only if the scene declares shadow-casting lights): per light, a Low-Ilie frustum
  from the light, fitted around the tile's visible set (:mod:`wallcull.lowilie`). Its near
  plane is pulled in to the nearest caster: the least depth of the casters' triangles clipped
  to the frustum, where nearer than :data:`NEAR_ENOUGH` of its far distance. It comes with the
  shadow casters culled against it.
  A light that the tile's visible set surrounds gets a cube map instead: six 90 degree faces,
  whose near plane is pulled in to the nearest caster's triangles where they come nearer than
  a ten-thousandth of its far distance. No map's near plane comes nearer than a millionth of
  its far distance (:data:`NEAR_FLOOR`).
* ``mirrors`` (only if the scene declares mirrors): per mirror the eye can see, the reflected
  view (det -1: the client flips its front faces), the tile's projection with Lengyel's oblique
  near plane at the mirror, and the leaves culled against the reflected frustum (bounded by the
  mirror's outline when it has one).

Every tile of a frame is fitted at once: one pass over all lights and tiles, split among
threads, each part one compiled call that fits its tiles' Low-Ilie frusta, culls their casters
(the object hierarchy against each caster region) and pulls their near planes in
(:func:`shadow_sets`); and per mirror the wall's own cull of the reflected frusta, run beside
the lights' pass. The results stay arrays
(:class:`Fits`, :class:`ShadowSet`, :class:`MirrorSet`) that read as per-tile dicts. Lists are
leaf ids, as in packets. A scene without lights or mirrors never reaches the code for them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import NamedTuple

import numpy as np
from numba import njit

from . import lowilie, workers
from . import settings as cfg
from .cull import (Culler, Visibility, _Buffers, _along, _farthest, _masked,
                   depth_ranges as node_depths, packed, stack_depth)
from .projection import THROUGH_CAMERA, as_reversed_z, look_at, mirrored_views, view_matrix
from .scene import SceneState
from .wall import Frame, Frusta, matrix_quaternions

#: A fitted depth range keeps this much of the depth buffer free beyond its bounds at both
#: ends (in window depth, [0, 1], the same in either convention: reversed-Z's is one minus the
#: standard one): a surface lying on the nearest or the farthest listed bound stays inside
#: the range after a node's float32 matrices and its depth buffer have rounded it. A relative
#: margin of the distances does not do that: at the far end a standard projection's depth
#: changes by ``n / f`` of what it changes by at the near end, and a reversed-Z one puts the
#: farthest bound at depth ``~ n / f * margin``, which a 24-bit buffer rounds to its clear value.
DEPTH_SLACK = 2.0 ** -10

#: A fitted range spans at least this fraction of its far distance: a flat surface seen
#: head-on has a range of nearly no width, whose projection's depth row (``~ f / (f - n)``)
#: turns float32's rounding of a node's matrices into whole metres, clipping the surface.
MIN_DEPTH_SPAN = 2.0 ** -6


@dataclass(frozen=True)
class FitOptions:
    depth: str = "tight"  # "tight": fitted to the visible bounds; "wall": the wall's near/far
    reversed_z: bool = False
    shadow_fit: str = "refined"  # lowilie.EFFORTS: "sphere", "greedy" or "refined"

    def __post_init__(self):
        if self.depth not in ("tight", "wall"):
            raise ValueError(f"depth must be 'tight' or 'wall', got {self.depth!r}")
        if self.shadow_fit not in lowilie.EFFORTS:
            raise ValueError(f"shadow_fit must be one of {', '.join(lowilie.EFFORTS)}, "
                             f"got {self.shadow_fit!r}")


def tile_views(wall, frame: Frame, eye: np.ndarray | None = None) -> np.ndarray:
    """World to each tile's eye space: ``(4, 4)``, the same for every tile of a grid (display
    space's axes at the eye); ``(tiles, 4, 4)`` for screens, whose eye spaces are aligned to
    their screens (x along the bottom edge, y up the left edge, z toward the viewer)."""
    view = view_matrix(frame, eye)
    if wall.kind == "grid":
        return view
    axes = np.zeros((wall.tiles, 4, 4))
    axes[:, :3, :3] = wall.basis
    axes[:, 3, 3] = 1.0
    return axes @ view


def tile_projections(wall, frame: Frame, near: np.ndarray, far: np.ndarray,
                     reversed_z: bool = False, eye: np.ndarray | None = None) -> np.ndarray:
    """``(tiles, 4, 4)`` off-axis projections through each tile rectangle, seen from the
    frame's eye (or ``eye``, display space), with per-tile near and far distances: Lengyel's
    frustum matrix, vectorized; reversed-Z maps near to 1, far to 0. A far distance of ``inf``
    gives the infinite projection. For screens, the rectangle in each tile's own eye space
    (the generalized perspective projection)."""
    eye = frame.eye if eye is None else np.asarray(eye, np.float64)
    near, far = (np.ascontiguousarray(np.broadcast_to(d, wall.tiles), np.float64)
                 for d in (near, far))
    out = np.empty((wall.tiles, 4, 4))
    if wall.kind == "grid":
        _grid_projections(wall.col_edges, wall.row_edges, wall.cols, float(eye[0]),
                          float(eye[1]), wall.distance + float(eye[2]), near, far, reversed_z,
                          out)
        return out
    rel = wall.corners - eye  # bl, br, tl from the eye
    u, v, n = wall.basis[:, 0], wall.basis[:, 1], wall.basis[:, 2]
    rect = np.stack([(rel[:, 0] * u).sum(axis=1), (rel[:, 1] * u).sum(axis=1),
                     (rel[:, 0] * v).sum(axis=1), (rel[:, 2] * v).sum(axis=1),
                     -(rel[:, 0] * n).sum(axis=1)], axis=1)
    _screen_projections(rect, near, far, reversed_z, out)
    return out


@njit(cache=True)
def _grid_projections(col_edges, row_edges, cols, ex, ey, depth, near, far, reversed_z, out):
    """:func:`_off_axis` for each tile of a grid, from the eye at ``ex, ey`` (display space),
    ``depth`` before the wall."""
    for t in range(out.shape[0]):
        r, c = t // cols, t % cols
        _off_axis(out[t], col_edges[c, 0] - ex, col_edges[c, 1] - ex, row_edges[r, 0] - ey,
                  row_edges[r, 1] - ey, depth, near[t], far[t], reversed_z)


@njit(cache=True)
def _screen_projections(rect, near, far, reversed_z, out):
    """:func:`_off_axis` for each screen: ``rect[t]`` = x0, x1, y0, y1, depth in its eye
    space."""
    for t in range(out.shape[0]):
        _off_axis(out[t], rect[t, 0], rect[t, 1], rect[t, 2], rect[t, 3], rect[t, 4], near[t],
                  far[t], reversed_z)


@njit(cache=True, inline="always")
def _off_axis(m, x0, x1, y0, y1, depth, n, f, reversed_z):
    """``m``: the projection through ``[x0, x1] x [y0, y1]`` at ``depth`` (from the eye), with
    near and far distances ``n``, ``f``."""
    m[:, :] = 0.0
    # 2n/(r-l) with l = x0 n / depth: the near distance cancels out of the x and y rows
    m[0, 0] = 2 * depth / (x1 - x0)
    m[0, 2] = (x1 + x0) / (x1 - x0)
    m[1, 1] = 2 * depth / (y1 - y0)
    m[1, 2] = (y1 + y0) / (y1 - y0)
    m[3, 2] = -1.0
    if not math.isfinite(f):  # an infinite far plane takes the limit (Lengyel eq. 5.53)
        m[2, 2], m[2, 3] = (0.0, n) if reversed_z else (-1.0, -2 * n)
    elif reversed_z:
        m[2, 2], m[2, 3] = n / (f - n), n * f / (f - n)
    else:
        m[2, 2], m[2, 3] = -(f + n) / (f - n), -2 * f * n / (f - n)


def depth_ranges(state: SceneState, wall, frame: Frame, visibility: Visibility,
                 eye: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile ``(near, far)``: the eye-space depths the tile's listed bounds span (from the
    frame's eye, or ``eye``), rounded outward to float32 and clamped to the wall's. A tile that
    shows nothing keeps the wall's range."""
    eye = frame.eye if eye is None else np.asarray(eye, np.float64)
    if wall.kind == "grid":
        forward = (-frame.rotation[:, 2])[None]  # the view direction in the world
    else:
        forward = -wall.basis[:, 2] @ frame.rotation.T  # each screen's, into the world
    lo, hi = node_depths(state, visibility.start, visibility.nodes, forward,
                         frame.to_world(eye)[None], (np.nan, np.nan))
    near, far = np.empty(wall.tiles), np.empty(wall.tiles)
    _tight(lo, hi, float(wall.near), float(wall.far), near, far)
    return near, far


@njit(cache=True)
def _tight(lo, hi, wall_near, wall_far, near, far):
    """Each tile's depth range from the depths ``lo``, ``hi`` its bounds span (NaN: none):
    ``near`` and ``far`` such that depths ``lo`` and ``hi`` lie :data:`DEPTH_SLACK` inside
    the depth buffer's ends and the range spans :data:`MIN_DEPTH_SPAN` of ``far``, rounded
    outward to float32 and clamped to the wall's ``[wall_near, wall_far]`` (the wall's for a
    tile that shows nothing). In window depth ``z(d) = f (d - n) / ((f - n) d)``:
    ``n = lo (1 - s)`` gives ``z(lo) >= s`` for every ``f``; ``f = n hi (1 - s) / (n - s hi)``
    gives ``z(hi) = 1 - s``, and a larger ``f`` keeps both. When ``hi >= n / s`` no far plane
    does: the wall's then."""
    s = DEPTH_SLACK
    for t in range(lo.shape[0]):
        n, f = wall_near, wall_far
        if math.isfinite(lo[t]):
            n = min(max(outward(lo[t] * (1 - s), -1.0), wall_near), wall_far)
            if n > s * hi[t]:  # False for an infinite hi: the wall's far
                f = max(n * hi[t] * (1 - s) / (n - s * hi[t]), n / (1 - MIN_DEPTH_SPAN))
                f = min(max(outward(f, 1.0), wall_near), wall_far)
            if f <= n:
                f = outward(n * (1 + 1e-9) + 1e-300, 1.0)
        near[t], far[t] = n, f


@njit(cache=True)
def outward(value: float, direction: float) -> float:
    """``value`` rounded to float32 toward ``direction`` (-1: down, 1: up): a tight depth
    range stays conservative, and a node message carries each bound exactly in 5 bytes (a
    depth buffer resolves no finer). Beyond float32's range: infinite, still outward."""
    rounded = np.float64(np.float32(value))
    if rounded < value if direction > 0 else rounded > value:
        rounded = np.float64(np.nextafter(np.float32(rounded), np.float32(direction * np.inf)))
    return rounded


def _csr_rows(start: np.ndarray, items: np.ndarray, t: int) -> list[int]:
    return items[start[t]:start[t + 1]].tolist()


# --------------------------------------------------------------------------- shadows

NONE, FRUSTUM, CUBE = 0, 1, 2

#: OpenGL cube-map face order: +x, -x, +y, -y, +z, -z, with the usual up vectors.
_CUBE_LOOKS = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))
_CUBE_UPS = ((0, -1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1), (0, -1, 0), (0, -1, 0))


@dataclass
class ShadowSet:
    """One light's shadow frusta for every tile of a frame. Tile ``t`` has a Low-Ilie frustum
    (``kind[t] == FRUSTUM``: ``view[t]``, ``projection[t]``), a cube map (``CUBE``: the six
    ``cube_views`` and ``projection[t]``) or nothing (``NONE``: it shows nothing the light
    reaches); its casters are the leaves ``casters[casters_start[t]:casters_start[t + 1]]``."""

    light: cfg.Light
    kind: np.ndarray  # (T,) NONE, FRUSTUM or CUBE
    view: np.ndarray  # (T, 4, 4)
    projection: np.ndarray  # (T, 4, 4)
    near: np.ndarray  # (T,)
    far: np.ndarray  # (T,)
    coverage: np.ndarray  # (T,)
    casters_start: np.ndarray  # (T + 1,)
    casters: np.ndarray  # leaf ids
    cube_views: np.ndarray | None  # (6, 4, 4) when a tile has a cube map

    def entry(self, t: int) -> dict | None:
        """Tile ``t``'s record, JSON-ready, or None."""
        kind = self.kind[t]
        if kind == NONE:
            return None
        out = {"light": self.light.name}
        if kind == CUBE:
            out.update(cube=True, views=self.cube_views.tolist())
        else:
            out["view"] = self.view[t].tolist()
        out.update(projection=self.projection[t].tolist(), near=float(self.near[t]),
                   far=float(self.far[t]))
        if kind == FRUSTUM:
            out["coverage"] = float(self.coverage[t])
        out["casters"] = _csr_rows(self.casters_start, self.casters, t)
        return out


def shadow_sets(state: SceneState, lights: Sequence[cfg.Light], visibility: Visibility,
                effort: str = "refined") -> list[ShadowSet]:
    """Each light's frustum for every tile: fitted around the bounds of what the tile shows
    (the shadow receivers), with the casters that can shade them. Casters anywhere between the
    light and the receivers shade them: they are culled against the frustum's side and far
    planes (not its near plane), and the near plane is then pulled in to the nearest caster.
    A tile whose receivers no single frustum from the light holds (the light is among them)
    gets a cube map, with the casters in the cube around the light, its near plane pulled in
    to the nearest of their triangles.

    Each tile's shadow is independent of the others', so it is one pass over every light's
    tiles, split among threads once (:mod:`wallcull.workers`, by receivers): in each part one
    compiled call fits the tiles' frusta, culls their casters and pulls their near planes in
    (:func:`_shadow_part`). Only the parts' caster lists are joined afterwards."""
    if not lights:
        return []
    efforts = lowilie.effort_code(effort)
    count, tiles = len(lights), len(visibility.start) - 1
    b, scene, box = state.bounds, state.scene, packed(state)
    leaf_start, leaf_count = scene.leaf_range
    start, nodes = visibility.start, visibility.nodes
    status = np.zeros((count, tiles), np.int64)
    kind, casters = np.zeros((count, tiles), np.int64), np.zeros((count, tiles), np.int64)
    view, projection = np.zeros((count, tiles, 4, 4)), np.zeros((count, tiles, 4, 4))
    near, far, coverage = (np.zeros((count, tiles)) for _ in range(3))
    # every light's tiles one after the other, split by their receivers
    total = start[-1] - start[0]
    work = np.append((start[:-1] - start[0] + total * np.arange(count)[:, None]).ravel(),
                     total * count)
    stack = stack_depth(state)
    faces = _faces(state)
    ranges = workers.chunks(count * tiles, work, per_thread=workers.SPLIT)
    pool = state.__dict__.setdefault("_shadow_buffers", [])  # kept: outputs grow once
    pool.extend(_Buffers() for _ in range(len(ranges) - len(pool)))

    def part(k, a, z):  # tiles [a, z) of the lights' sequence
        buf, leaves, used = pool[k], [], 0  # each light's leaves after the one's before
        for j in range(a // tiles, (z - 1) // tiles + 1):
            lo, hi = max(a - j * tiles, 0), min(z - j * tiles, tiles)
            light = lights[j]
            spot = light.kind == "spot"
            while True:
                got = _shadow_part(
                    np.asarray(light.position, np.float64), float(light.resolution[0]),
                    float(light.resolution[1]), efforts, spot,
                    np.asarray(light.direction if spot else (0.0, 0.0, 0.0), np.float64),
                    math.cos(math.radians(light.angle)) if spot else 1.0,
                    b.center, b.axes, b.half, b.radius, start[lo:hi + 1], nodes, box,
                    scene.child_start, scene.leaf_child_count, scene.children, leaf_start,
                    leaf_count, scene.leaves, scene.cluster_leaf, faces, view[j, lo:hi],
                    projection[j, lo:hi], near[j, lo:hi], far[j, lo:hi], coverage[j, lo:hi],
                    status[j, lo:hi], kind[j, lo:hi], casters[j, lo:hi],
                    buf.get("stack_n", stack), buf.get("stack_m", stack),
                    buf.get("stack_b", stack, np.float64), buf.get("listed_n", len(box)),
                    buf.get("listed_b", len(box), np.float64),
                    buf.get("out_n", CASTERS)[used:])
                if got is not None:
                    break
                # the casters overflowed: again, with room (the lights' before keep theirs)
                buf.arrays["out_n"], used = np.empty(2 * len(buf.arrays["out_n"]),
                                                       np.int64), 0
            leaves.append(got)
            used += len(got)
        return leaves

    parts = workers.run(part, ranges)
    # (a copy: the parts' leaves lie in buffers that the next frame writes again)
    leaves = np.concatenate([a for p in parts for a in p]) if parts else np.zeros(0, np.int64)
    edges = np.concatenate([[0], np.cumsum(casters.ravel())])
    out = []
    for j, light in enumerate(lights):
        first = edges[j * tiles:(j + 1) * tiles + 1]
        cube_views = _cube_views(tuple(light.position)) if (kind[j] == CUBE).any() else None
        out.append(ShadowSet(light, kind[j], view[j], projection[j], near[j], far[j],
                             coverage[j], first - first[0], leaves[first[0]:first[-1]],
                             cube_views))
    return out


def _faces(state: SceneState) -> tuple:
    """The state's hierarchy with its clusters, and its triangles, as
    :func:`_nearest_below` reads them."""
    scene, m = state.scene, state.scene.meshes
    return (scene.child_count, scene.cluster_leaf, *scene.cluster_faces, scene.mesh_of,
            state.world, m.vertex_start, m.vertices, m.face_start, m.faces)


#: A cube map's near distance, as a fraction of its far distance, unless a caster lies nearer
#: (each face's near plane bounds a point's largest coordinate from the light, so the
#: casters' least Chebyshev distance from it: :func:`_nearest_below`).
CUBE_NEAR = 1e-4

#: No shadow map's near plane is pulled in nearer the light than this fraction of its far
#: distance: a caster nearer than that (5 cm from a light whose map reaches 50 km), or one
#: whose bounds reach behind a frustum's light, is clipped where it lies before it. A map's
#: window depth at distance ``d`` is about ``1 - near (far - d) / (far d)``, and a caster is
#: kept only where that lies a step of the depth buffer below the cleared 1 (``2 ** -24``: a
#: 24-bit buffer, and a float32 one just below 1). At this floor that holds out to 94% of the
#: far distance; at a floor four times nearer, to 80%; at ``2 ** -24``, to half. What a depth
#: buffer holds is a ratio of the near to the far distance: a floor that is not a fraction of
#: the far distance drops the far casters of some map (``tests/test_fit_render.py``).
NEAR_FLOOR = 1e-6

#: A shadow frustum's near plane is pulled in to its nearest caster's triangles clipped to it,
#: but only as far as needed: once every listed node's bound lies beyond this fraction of the
#: far distance, the least bound is its near plane and no node is opened. A map whose near
#: plane is a 1,024th of its far distance resolves its far end in a 24-bit buffer to 6e-5 of
#: it (at the floor, to 6%); the opening that would bring it nearer costs more than it buys.
NEAR_ENOUGH = 2.0 ** -10

#: Caster leaves a part of :func:`shadow_sets` has room for at first: doubled while they
#: overflow, and kept from frame to frame.
CASTERS = 4096

#: A fit's status (:mod:`wallcull.lowilie`) to the kind of shadow it gives: ``OK`` a frustum,
#: ``EMPTY`` and ``UNLIT`` none, any other (no single frustum holds the receivers) a cube map.
_KIND_OF_STATUS = np.full(lowilie.BAD_DEPTH + 1, CUBE, np.int64)
_KIND_OF_STATUS[[lowilie.OK, lowilie.EMPTY, lowilie.UNLIT]] = FRUSTUM, NONE, NONE


@njit(cache=True, nogil=True)
def _shadow_part(light, width, height, effort, spot, spot_dir, spot_cos, center, axes, half,
                 radius, start, nodes, box, child_start, child_count, children, leaf_start,
                 leaf_count, leaves, cluster_leaf, faces, view, projection, near, far, coverage,
                 status, kind, casters, stack_n, stack_m, stack_b, listed_n, listed_b, out):
    """One light's shadows for a run of tiles (receivers ``nodes[start[t]:start[t + 1]]``),
    written into its rows of the frame's arrays: the Low-Ilie fits, a cube map where none
    holds the receivers, the caster culls (:func:`_cull_casters`), each map's near plane
    pulled in to its nearest caster (:func:`_pull_near`), and ``casters[t]``, how many leaves
    each tile's casters are. Returns those leaves, tile after tile (sorted in each): the start
    of ``out``, or None when they did not fit in it (nothing is then complete)."""
    n = start.shape[0] - 1
    lowilie._fit_boxes(light, center, axes, half, radius, start, nodes, width, height, effort,
                       spot, spot_dir, spot_cos, view, projection, near, far, coverage, status)
    shaded = 0
    for t in range(n):
        kind[t] = _KIND_OF_STATUS[status[t]]
        shaded += kind[t] != NONE
    lit = np.empty(shaded, np.int64)
    shaded = 0
    for t in range(n):
        if kind[t] != NONE:
            lit[shaded] = t
            shaded += 1
        if kind[t] == CUBE:  # the light among the receivers: a cube map
            far[t] = _farthest(start[t:t + 2], nodes, box, light)[0] * (1 + 1e-6)
            near[t] = far[t] * CUBE_NEAR  # pulled in to the nearest caster (_pull_near)
            projection[t] = 0.0
            projection[t, 0, 0] = projection[t, 1, 1] = 1.0
            projection[t, 3, 2] = -1.0
    # each tile's caster region: the fitted frustum's side and far planes (rows of
    # projection @ view, Gribb-Hartmann), or the cube around the light
    pv = np.zeros((shaded, 4, 4))
    forward = np.empty((shaded, 3))
    for k in range(shaded):
        t = lit[k]
        for r in range(4):  # (no BLAS here: numba's would be SciPy's, which is an extra)
            for c in range(4):
                total = 0.0
                for m in range(4):
                    total += projection[t, r, m] * view[t, m, c]
                pv[k, r, c] = total
        for a in range(3):
            forward[k, a] = -view[t, 2, a]
    planes, regions, sizes = _caster_regions(pv, kind, lit, far, light)
    lo = np.full(shaded, np.nan)  # each region's nearest caster (none: NaN)
    first = np.zeros(shaded + 1, np.int64)
    cubes = np.empty(shaded, np.bool_)
    for k in range(shaded):
        cubes[k] = kind[lit[k]] == CUBE
        if cubes[k]:  # casters this far out leave its near plane as it is
            lo[k] = 2 * near[lit[k]]
        else:  # nodes bounded beyond this are not opened
            lo[k] = far[lit[k]] * NEAR_ENOUGH
    near_work = (*_region_shapes(planes, regions, sizes, forward, cubes, light), stack_b,
                 listed_n, listed_b, np.empty((2, _POLYGON, 3)))
    if _cull_casters(child_start, child_count, children, box, planes, regions, sizes, forward,
                     cubes, faces, near_work, light, leaf_start, leaf_count, leaves,
                     cluster_leaf, stack_n, stack_m, out, lo, first) < 0:
        return None
    _pull_near(lo, kind, lit, near, far, projection)
    casters[:] = 0
    for k in range(shaded):
        casters[lit[k]] = first[k + 1] - first[k]
    return out[:first[shaded]]


@njit(cache=True, nogil=True)
def _cull_casters(child_start, child_count, children, box, planes, regions, sizes, forward,
                  cubes, faces, near_work, origin, leaf_start, leaf_count, leaves, cluster_leaf,
                  stack_n, stack_m, out, nearest, first):
    """The caster regions of :func:`_caster_regions` (region ``q``: the planes
    ``regions[q, :sizes[q]]``) culled as the ``oh`` kernel culls them (:func:`wallcull.cull._oh`:
    the same tests, in the same order), each listed node's leaves written out as it is
    listed, as :func:`wallcull.cull._expand` writes them from the kernel's pairs: region ``q``'s
    leaves are ``out[first[q]:first[q + 1]]``. ``nearest[q]`` gets how near the light
    ``origin`` its casters' triangles come, opened through ``faces`` (the scene's hierarchy
    with its clusters and its meshes) only where a node's bound comes nearer than the nearest
    so far (:func:`_nearest_below`). For a frustum's region, the least depth along
    ``forward[q]`` of the listed nodes' triangles clipped to the region (NaN when none lies
    in it, or when it lists nothing): its listed nodes are opened once the region is culled,
    the nearest bound first (:func:`_open_nearest`), while their bounds come nearer than the
    ``nearest[q]`` given (none given, NaN: to the least depth itself); past it, the least
    bound. For a cube map's region (``cubes[q]``), a
    lower bound of the least Chebyshev distance from ``origin`` (a point's largest distance
    along one of the world's axes: what a face's near plane bounds) of the listed leaves'
    triangles, where below the ``nearest[q]`` given (and that otherwise): each listed node is
    opened as it is listed, where its box comes nearer. ``near_work``: the regions' shapes
    (:func:`_region_shapes`) and the buffers the opening uses. Returns the leaves written, or
    -1 when ``out`` cannot hold them."""
    rel, corners, spread, stack_b, listed_n, listed_b, poly = near_work
    w = 0
    cap = out.shape[0]
    for q in range(sizes.shape[0]):
        size, ids = sizes[q], regions[q]
        fx, fy, fz = forward[q, 0], forward[q, 1], forward[q, 2]
        cube = cubes[q]
        least = nearest[q] if cube else np.inf
        enough = np.inf if cube or not nearest[q] > 0 else nearest[q]
        last = -1  # the cluster's leaf written last (a leaf's clusters come one after another)
        listed = 0
        stack_n[0] = 0
        stack_m[0] = (np.int64(1) << size) - 1
        sp = 1
        while sp > 0:
            sp -= 1
            i = stack_n[sp]
            outside, m, _ = _masked(box, i, planes, ids, size, stack_m[sp])
            if outside:
                continue
            if m == 0 or child_count[i] == 0:
                c = cluster_leaf[i]
                if c < 0:
                    if w + leaf_count[i] > cap:
                        return -1
                    for j in range(leaf_start[i], leaf_start[i] + leaf_count[i]):
                        out[w] = leaves[j]
                        w += 1
                elif c != last:
                    if w == cap:
                        return -1
                    out[w] = c
                    w += 1
                    last = c
                if cube:
                    bound = _chebyshev(box, i, origin)
                    if bound < least:  # (seldom: open it)
                        least = _nearest_below(box, child_start, children, faces, i, bound,
                                               least, origin, q, True, fx, fy, fz, rel, ids,
                                               size, corners, spread, stack_n, stack_b, sp,
                                               poly)
                else:  # opened once the region is culled, the nearest first
                    depth, r = _along(box, i, fx, fy, fz, origin[0], origin[1], origin[2])
                    listed_n[listed], listed_b[listed] = -1 - i, depth - r  # (not refined)
                listed += 1
                continue
            for c in range(child_start[i] + child_count[i] - 1, child_start[i] - 1, -1):
                stack_n[sp] = children[c]
                stack_m[sp] = m
                sp += 1
        if listed and not cube:
            least = _open_nearest(box, child_start, children, faces, listed, least, enough,
                                  origin, q, fx, fy, fz, rel, ids, size, corners, spread,
                                  listed_n, listed_b, stack_n, stack_b, poly)
            nearest[q] = least if least < np.inf else np.nan
        elif listed:
            nearest[q] = least
        first[q + 1] = w
    return w


@njit(cache=True, _nrt=False)
def _open_nearest(box, child_start, children, faces, count, least, enough, origin, q, fx, fy,
                  fz, rel, ids, size, corners, spread, listed_n, listed_b, stack, bounds, poly):
    """The least of ``least`` and the depths within frustum region ``q`` of the triangles
    under the listed nodes ``listed_n[:count]``, each opened (:func:`_nearest_below`) the
    nearest bound first, and only while its bound comes nearer than the least so far and
    than ``enough`` (past that, the least bound is returned: near enough). A
    node's bound is its depth less its reach (``listed_b``, the node's id given as
    ``-1 - id``) until it is the nearest, then the tighter :func:`_region_floor`: a heap
    (the lists are reordered)."""
    for j in range(count // 2 - 1, -1, -1):
        _sift_down(listed_n, listed_b, j, count)
    while count > 0 and listed_b[0] < least:
        if not listed_b[0] < enough:  # near enough: the least bound
            return listed_b[0]
        i, bound = listed_n[0], listed_b[0]
        if i < 0:  # bounded by its depth alone so far
            i = -1 - i
            listed_n[0] = i
            listed_b[0] = max(bound, _region_floor(box, i, origin, fx, fy, fz, corners, q,
                                                   spread[q]))
            _sift_down(listed_n, listed_b, 0, count)
            continue
        count -= 1
        listed_n[0], listed_b[0] = listed_n[count], listed_b[count]
        _sift_down(listed_n, listed_b, 0, count)
        least = _nearest_below(box, child_start, children, faces, i, bound, least, origin, q,
                               False, fx, fy, fz, rel, ids, size, corners, spread, stack, bounds,
                               0, poly)
    return least


@njit(cache=True, inline="always")
def _sift_down(ids, keys, j, count):
    """Entry ``j`` of the binary min-heap ``keys[:count]`` (with ``ids``) sifted down."""
    while True:
        k = 2 * j + 1
        if k >= count:
            return
        if k + 1 < count and keys[k + 1] < keys[k]:
            k += 1
        if not keys[k] < keys[j]:
            return
        ids[j], ids[k] = ids[k], ids[j]
        keys[j], keys[k] = keys[k], keys[j]
        j = k


@njit(cache=True, inline="always")
def _chebyshev(box, i, origin):
    """A lower bound of the least Chebyshev distance from ``origin`` of bound ``i``: that of
    its box along the world's axes (not positive when that box holds ``origin``)."""
    out = -np.inf
    for a in range(3):
        depth, r = _along(box, i, 1.0 if a == 0 else 0.0, 1.0 if a == 1 else 0.0,
                          1.0 if a == 2 else 0.0, origin[0], origin[1], origin[2])
        out = max(out, abs(depth) - r)
    return out


@njit(cache=True, inline="always")
def _region_floor(box, i, origin, fx, fy, fz, corners, q, spread):
    """A lower bound of the depth along unit ``(fx, fy, fz)`` from ``origin`` (the light) of
    the part of bound ``i`` within frustum region ``q``, whose side planes meet at ``origin``
    along the corner rays ``corners[q]`` (each of depth 1; ``spread``: their largest length,
    not positive when they are not to be trusted). Its depth less its reach along the axis;
    and, where more, along each of its box's axes ``u`` (a separating axis): the part of the
    region nearer than depth ``d`` lies within the pyramid from ``origin`` through the
    corners at depth ``d``, whose span along ``u`` grows from the light's as ``d`` times
    the corners' least and largest; a box wholly past one end of it along ``u`` meets it only
    from the depth where that end reaches the box (never: infinite). Beside a frustum, a tall
    box whose reach along the axis comes up to the light's plane (or behind it) has its part
    within the region far below the light, where the region has grown to meet it."""
    ox, oy, oz = origin[0], origin[1], origin[2]
    depth, r = _along(box, i, fx, fy, fz, ox, oy, oz)
    out = depth - r
    if not spread > 0:
        return out
    tiny = 1e-12 * spread
    for a in range(3):
        ex, ey, ez = box[i, 4 + 3 * a], box[i, 5 + 3 * a], box[i, 6 + 3 * a]
        length = math.sqrt(ex * ex + ey * ey + ez * ez)
        if not length > 0:
            continue
        ux, uy, uz = ex / length, ey / length, ez / length
        c, r = _along(box, i, ux, uy, uz, ox, oy, oz)
        if -r <= c <= r:  # the box spans the light along u
            continue
        top, bottom = -np.inf, np.inf
        for k in range(4):
            s = ux * corners[q, k, 0] + uy * corners[q, k, 1] + uz * corners[q, k, 2]
            top, bottom = max(top, s), min(bottom, s)
        if c > r:  # the box lies wholly on u's side of the light
            if top > tiny:
                out = max(out, (c - r) / top)
            elif top < -tiny:
                return np.inf
        else:
            if bottom < -tiny:
                out = max(out, (c + r) / bottom)
            elif bottom > tiny:
                return np.inf
    return out


@njit(cache=True, _nrt=False)
def _nearest_below(box, child_start, children, faces, i, bound, least, origin, q, cube, fx, fy,
                   fz, rel, ids, size, corners, spread, stack, bounds, base, poly):
    """How near ``origin`` (the light) the triangles under node ``i`` (its bound ``bound``)
    come, where nearer than ``least`` (``least`` otherwise): in a frustum's region ``q``, the
    least depth along its axis ``(fx, fy, fz)`` of their parts within the region
    (:func:`_clipped_below`, the region's planes ``rel[ids[:size]]`` taken from the light); in
    a cube map's (``cube``), a
    lower bound of their least Chebyshev distance (:func:`_triangle_chebyshev`). Its subtree
    is opened depth-first, through the leaves' clusters (``faces``: the scene's
    ``child_count``, ``cluster_leaf``, ``cluster_faces``, ``mesh_of``, the state's ``world``
    and the mesh table's arrays), only where a node's bound comes nearer than the least so
    far (:func:`_chebyshev`; in a frustum's region its depth less its reach, then, as it is
    taken, :func:`_region_floor`), the nearest child first, on ``stack`` and ``bounds`` above
    ``base`` (a traversal that went on into ``i`` would reach as deep); the triangles of a
    node without children are taken one by one (in a frustum's region only those with a
    corner nearer than the least so far are placed in the world and clipped). A box that
    holds the light (a lamp's housing, a room around it) says nothing of how near its
    surfaces come."""
    child_count, cluster_leaf, first, count, mesh_of, world, vertex_start, vertices, \
        face_start, tris = faces
    ox, oy, oz = origin[0], origin[1], origin[2]
    stack[base], bounds[base] = i, bound
    sp = base + 1
    while sp > base:
        sp -= 1
        j = stack[sp]
        if not bounds[sp] < least:
            continue
        if not cube and j != i and not _region_floor(box, j, origin, fx, fy, fz, corners, q,
                                                     spread[q]) < least:
            continue  # (its depth brought it here: within the region it lies farther)
        if child_count[j] > 0:
            top = sp
            for c in range(child_start[j], child_start[j] + child_count[j]):
                k = children[c]
                if cube:
                    b = _chebyshev(box, k, origin)
                else:
                    depth, r = _along(box, k, fx, fy, fz, ox, oy, oz)
                    b = depth - r
                if b < least:
                    stack[sp], bounds[sp] = k, b
                    sp += 1
            if sp - top > 1:  # the nearest on top
                best = top
                for s in range(top + 1, sp):
                    if bounds[s] < bounds[best]:
                        best = s
                s = sp - 1
                stack[best], stack[s] = stack[s], stack[best]
                bounds[best], bounds[s] = bounds[s], bounds[best]
            continue
        leaf = cluster_leaf[j] if cluster_leaf[j] >= 0 else j
        mesh = mesh_of[leaf]
        if mesh < 0:
            continue
        m = world[leaf]
        v0 = vertex_start[mesh]
        # a vertex's depth along the region's axis: g . v + g0 (the axis into the mesh)
        gx = fx * m[0, 0] + fy * m[1, 0] + fz * m[2, 0]
        gy = fx * m[0, 1] + fy * m[1, 1] + fz * m[2, 1]
        gz = fx * m[0, 2] + fy * m[1, 2] + fz * m[2, 2]
        g0 = fx * (m[0, 3] - ox) + fy * (m[1, 3] - oy) + fz * (m[2, 3] - oz)
        for f in range(face_start[mesh] + first[j], face_start[mesh] + first[j] + count[j]):
            a, b, c = v0 + tris[f, 0], v0 + tris[f, 1], v0 + tris[f, 2]
            if not cube and not min(
                    gx * vertices[a, 0] + gy * vertices[a, 1] + gz * vertices[a, 2],
                    gx * vertices[b, 0] + gy * vertices[b, 1] + gz * vertices[b, 2],
                    gx * vertices[c, 0] + gy * vertices[c, 1] + gz * vertices[c, 2]) + g0 < least:
                continue  # no corner nearer than the least so far
            ax, ay, az = (_moved(m, 0, vertices, a) - ox, _moved(m, 1, vertices, a) - oy,
                          _moved(m, 2, vertices, a) - oz)
            bx, by, bz = (_moved(m, 0, vertices, b) - ox, _moved(m, 1, vertices, b) - oy,
                          _moved(m, 2, vertices, b) - oz)
            cx, cy, cz = (_moved(m, 0, vertices, c) - ox, _moved(m, 1, vertices, c) - oy,
                          _moved(m, 2, vertices, c) - oz)
            if cube:
                least = min(least, _triangle_chebyshev(ax, ay, az, bx, by, bz, cx, cy, cz))
            else:
                least = _clipped_below(ax, ay, az, bx, by, bz, cx, cy, cz, fx, fy, fz, rel,
                                       ids, size, least, poly)
    return least


#: Room for a triangle clipped by a region's planes (3 corners and one more per plane, five;
#: rounding can add a few, and a polygon that would outgrow this is taken whole).
_POLYGON = 16


@njit(cache=True, _nrt=False)
def _clipped_below(ax, ay, az, bx, by, bz, cx, cy, cz, fx, fy, fz, planes, ids, size, least,
                   poly):
    """The least of ``least`` and the least depth along ``(fx, fy, fz)`` of the part of the
    triangle ``a, b, c`` within the planes ``planes[ids[:size]]`` (the triangle, the planes and
    the depth all taken from the light): its least corner's when all its corners lie within
    them, none when all lie outside one plane, and otherwise that of the polygon left by
    clipping it (Sutherland-Hodgman) against the planes it crosses, in ``poly (2, k, 3)``.
    A corner on a plane lies within it. A triangle whose least corner lies no nearer than
    ``least`` is left at once: its clipped part lies no nearer."""
    low = min(fx * ax + fy * ay + fz * az, fx * bx + fy * by + fz * bz,
              fx * cx + fy * cy + fz * cz)
    if not low < least:
        return least
    cut = 0
    for p in range(size):
        nx, ny, nz, d = planes[ids[p], 0], planes[ids[p], 1], planes[ids[p], 2], \
            planes[ids[p], 3]
        sa = nx * ax + ny * ay + nz * az + d
        sb = nx * bx + ny * by + nz * bz + d
        sc = nx * cx + ny * cy + nz * cz + d
        if sa < 0 and sb < 0 and sc < 0:
            return least
        if sa < 0 or sb < 0 or sc < 0:
            cut |= 1 << p
    if cut == 0:
        return low
    poly[0, 0, 0], poly[0, 0, 1], poly[0, 0, 2] = ax, ay, az
    poly[0, 1, 0], poly[0, 1, 1], poly[0, 1, 2] = bx, by, bz
    poly[0, 2, 0], poly[0, 2, 1], poly[0, 2, 2] = cx, cy, cz
    n, src, room = 3, 0, poly.shape[1]
    for p in range(size):
        if not cut & (1 << p):
            continue  # all the polygon lies within it (it lies within the triangle)
        nx, ny, nz, d = planes[ids[p], 0], planes[ids[p], 1], planes[ids[p], 2], \
            planes[ids[p], 3]
        dst = 1 - src
        k = 0
        s1 = nx * poly[src, 0, 0] + ny * poly[src, 0, 1] + nz * poly[src, 0, 2] + d
        for v in range(n):
            s0 = s1
            u = v + 1 if v + 1 < n else 0
            s1 = nx * poly[src, u, 0] + ny * poly[src, u, 1] + nz * poly[src, u, 2] + d
            if k + 2 > room:  # (rounding only) the polygon before this plane, whole
                dst = src
                k = n
                break
            if s0 >= 0:
                for e in range(3):
                    poly[dst, k, e] = poly[src, v, e]
                k += 1
            if (s0 >= 0) != (s1 >= 0):
                t = s0 / (s0 - s1)
                for e in range(3):
                    poly[dst, k, e] = poly[src, v, e] + t * (poly[src, u, e] - poly[src, v, e])
                k += 1
        n, src = k, dst
        if n == 0:
            return least
    for v in range(n):
        least = min(least, fx * poly[src, v, 0] + fy * poly[src, v, 1] + fz * poly[src, v, 2])
    return least


@njit(cache=True, inline="always")
def _moved(m, a, vertices, v):
    """Coordinate ``a`` of vertex ``v`` placed by the affine ``m (4, 4)``."""
    return m[a, 0] * vertices[v, 0] + m[a, 1] * vertices[v, 1] + m[a, 2] * vertices[v, 2] \
        + m[a, 3]


@njit(cache=True, inline="always")
def _triangle_chebyshev(ax, ay, az, bx, by, bz, cx, cy, cz):
    """The least Chebyshev distance from the origin of the triangle ``a, b, c``: the half-width
    of the smallest cube around the origin that meets it, by the separating axis theorem
    (Akenine-Moller's triangle-box test): the triangle lies beyond a cube of half-width ``h``
    along an axis ``d`` when its span along ``d`` starts past ``h |d|_1``; of the 13 axes
    (the world's, the triangle's normal, each edge across each of the world's), the one that
    keeps it out the longest. Each axis alone gives a lower bound, however its rounding turns
    it (an axis of no length is left out: a triangle of no area keeps its edges' axes)."""
    out = max(min(ax, bx, cx), -max(ax, bx, cx), min(ay, by, cy), -max(ay, by, cy),
              min(az, bz, cz), -max(az, bz, cz))
    ux, uy, uz, vx, vy, vz = bx - ax, by - ay, bz - az, cx - ax, cy - ay, cz - az
    out = max(out, _apart(uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx,
                          ax, ay, az, bx, by, bz, cx, cy, cz))
    for k in range(3):
        if k == 0:
            ex, ey, ez = ux, uy, uz
        elif k == 1:
            ex, ey, ez = cx - bx, cy - by, cz - bz
        else:
            ex, ey, ez = vx, vy, vz
        out = max(out, _apart(0.0, -ez, ey, ax, ay, az, bx, by, bz, cx, cy, cz),
                  _apart(ez, 0.0, -ex, ax, ay, az, bx, by, bz, cx, cy, cz),
                  _apart(-ey, ex, 0.0, ax, ay, az, bx, by, bz, cx, cy, cz))
    return out


@njit(cache=True, inline="always")
def _apart(dx, dy, dz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """How far the triangle ``a, b, c`` lies from the origin along ``d``, over ``|d|_1``: the
    half-width of the cube around the origin that it clears along ``d`` (-inf for a ``d`` of
    no length)."""
    length = abs(dx) + abs(dy) + abs(dz)
    if not length > 0:
        return -np.inf
    pa, pb, pc = dx * ax + dy * ay + dz * az, dx * bx + dy * by + dz * bz, \
        dx * cx + dy * cy + dz * cz
    return max(min(pa, pb, pc), -max(pa, pb, pc)) / length


@njit(cache=True)
def _caster_regions(pv, kind, shaded, far, light):
    """The caster regions of the ``shaded`` tiles, as the ``oh`` kernel takes them: six plane
    rows each (inward unit normals; a frustum uses its first five, its side and far planes from
    ``pv``, the rows of projection @ view; a cube map all six, the cube of half-width ``far``
    around the light)."""
    n = shaded.shape[0]
    planes = np.zeros((6 * n, 4))
    regions = np.arange(6 * n).reshape(n, 6)
    sizes = np.empty(n, np.int64)
    for k in range(n):
        t = shaded[k]
        rows = planes[6 * k:6 * k + 6]
        if kind[t] == CUBE:
            sizes[k] = 6
            for a in range(3):
                rows[2 * a, a], rows[2 * a + 1, a] = 1.0, -1.0
                rows[2 * a, 3], rows[2 * a + 1, 3] = far[t] - light[a], far[t] + light[a]
            continue
        sizes[k] = 5
        for j in range(4):
            rows[0, j], rows[1, j] = pv[k, 3, j] + pv[k, 0, j], pv[k, 3, j] - pv[k, 0, j]
            rows[2, j], rows[3, j] = pv[k, 3, j] + pv[k, 1, j], pv[k, 3, j] - pv[k, 1, j]
            rows[4, j] = pv[k, 3, j] - pv[k, 2, j]
        for p in range(5):
            norm = max(math.sqrt(rows[p, 0] * rows[p, 0] + rows[p, 1] * rows[p, 1]
                                 + rows[p, 2] * rows[p, 2]), 1e-300)
            for j in range(4):
                rows[p, j] /= norm
    return planes, regions, sizes


@njit(cache=True)
def _region_shapes(planes, regions, sizes, forward, cubes, light):
    """What the near planes' search (:func:`_nearest_below`) needs of the caster regions:
    ``rel``, the planes taken from ``light`` (the same normals, each offset by its value at
    the light: a point's distance is then that of its offset from the light), and per
    frustum region ``q``, ``corners[q]``, its four corner rays (where its side planes meet,
    in turn: left and bottom, bottom and right, right and top, top and left), each scaled to
    depth 1 along ``forward[q]``, and ``spread[q]``, their largest length. A cube map's
    region, or one whose rays come out edge-on or outside its other side planes (a frustum
    of nearly 180 degrees), gets no rays (``spread`` 0): its nodes are bounded by their
    depth alone."""
    rel = planes.copy()
    for p in range(planes.shape[0]):
        rel[p, 3] += planes[p, 0] * light[0] + planes[p, 1] * light[1] + planes[p, 2] * light[2]
    n = sizes.shape[0]
    corners = np.zeros((n, 4, 3))
    spread = np.zeros(n)
    for q in range(n):
        if cubes[q]:
            continue
        ids = regions[q]
        good, longest = True, 0.0
        for k in range(4):
            a, b = ids[_CORNER_SIDES[k, 0]], ids[_CORNER_SIDES[k, 1]]
            cx = planes[a, 1] * planes[b, 2] - planes[a, 2] * planes[b, 1]
            cy = planes[a, 2] * planes[b, 0] - planes[a, 0] * planes[b, 2]
            cz = planes[a, 0] * planes[b, 1] - planes[a, 1] * planes[b, 0]
            length = math.sqrt(cx * cx + cy * cy + cz * cz)
            depth = cx * forward[q, 0] + cy * forward[q, 1] + cz * forward[q, 2]
            if not abs(depth) > 1e-9 * length:
                good = False
                break
            cx, cy, cz = cx / depth, cy / depth, cz / depth
            longest = max(longest, length / abs(depth))
            corners[q, k, 0], corners[q, k, 1], corners[q, k, 2] = cx, cy, cz
            for p in range(4):  # within the other side planes
                if planes[ids[p], 0] * cx + planes[ids[p], 1] * cy + planes[ids[p], 2] * cz \
                        < -1e-9 * length / abs(depth):
                    good = False
        if good:
            spread[q] = longest
    return rel, corners, spread


#: The side planes (rows of :func:`_caster_regions`: left, right, bottom, top) that meet in
#: each corner ray of a frustum's region, around it.
_CORNER_SIDES = np.array([[0, 2], [2, 1], [1, 3], [3, 0]])


@njit(cache=True)
def _pull_near(lo, kind, shaded, near, far, projection):
    """Each shadow frustum's near plane pulled in to ``lo``, the nearest of its casters (half
    its far distance without any); a cube map's (``far`` * :data:`CUBE_NEAR` until then) to
    the Chebyshev distance of its nearest caster, when that is nearer; neither below
    :data:`NEAR_FLOOR` of the far distance. Then every shaded tile's depth rows from its near
    and far."""
    for k in range(shaded.shape[0]):
        t = shaded[k]
        f = far[t]
        if kind[t] == FRUSTUM:
            nearest = f * 0.5 if math.isnan(lo[k]) else lo[k]
            near[t] = max(nearest * (1 - 1e-6), f * NEAR_FLOOR)
        else:  # a cube map (lo: twice its near distance when no caster comes nearer)
            near[t] = min(near[t], max(lo[k] * (1 - 1e-6), f * NEAR_FLOOR))
        n = near[t]
        projection[t, 2, 2] = -(f + n) / (f - n)
        projection[t, 2, 3] = -2 * f * n / (f - n)


@lru_cache(maxsize=64)
def _cube_views(position: tuple) -> np.ndarray:
    """The six 90 degree face views of a cube map at ``position`` (a light's: cached)."""
    at = np.array(position)
    return np.array([look_at(at, at + np.array(d, float), u) for d, u in zip(_CUBE_LOOKS,
                                                                                 _CUBE_UPS)])


# --------------------------------------------------------------------------- mirrors


def _tile_view(view: np.ndarray, t: int) -> np.ndarray:
    """Tile ``t``'s view from a shared ``(4, 4)`` or per-tile ``(T, 4, 4)`` array."""
    return view if view.ndim == 2 else view[t]


@dataclass
class MirrorSet:
    """One mirror as every tile of a frame sees it: the reflected view (shared on a grid, each
    tile's on a screens wall), each tile's projection with the oblique near plane, and the
    leaves culled against each tile's reflected frustum. Tiles with ``shown[t]`` false see
    nothing in it."""

    mirror: cfg.Mirror
    view: np.ndarray  # (4, 4) or (T, 4, 4), det -1
    shown: np.ndarray  # (T,) bool
    projection: np.ndarray  # (T, 4, 4)
    visible_start: np.ndarray  # (T + 1,)
    visible: np.ndarray  # leaf ids

    @cached_property
    def view_rows(self) -> list:
        return self.view.tolist()

    def entry(self, t: int) -> dict | None:
        if not self.shown[t]:
            return None
        view = self.view_rows if self.view.ndim == 2 else self.view[t].tolist()
        return {"mirror": self.mirror.name, "view": view,
                "projection": self.projection[t].tolist(), "front_face": "cw",
                "visible": _csr_rows(self.visible_start, self.visible, t)}


@dataclass
class MirrorSight:
    """A mirror as one frame's eyes see it: what every tile's reflected view shares."""

    mirror: cfg.Mirror
    outline: np.ndarray  # (k, 4) world planes: in front of the mirror, within its outline

    @classmethod
    def of(cls, mirror: cfg.Mirror, frame: Frame, near: float) -> "MirrorSight | None":
        """None when no eye can see the mirror's reflective side: none lies farther in front
        of its plane than :data:`wallcull.projection.THROUGH_CAMERA` times ``near`` (the
        mirror pass's near distance, the wall's), which its oblique near plane needs."""
        eyes = frame.to_world(frame.eyes)
        plane = mirror.plane
        sees = eyes @ plane[:3] + plane[3] > THROUGH_CAMERA * near
        if not sees.any():
            return None
        outline = [plane[None]]
        if mirror.polygon is not None:
            # the pyramid through the outline from each reflected eye that sees the mirror
            # (a stereo frame's eye behind its plane sees nothing in it)
            outline.append(_pyramid([mirror.reflection @ np.append(e, 1.0) for e in eyes[sees]],
                                    mirror.polygon))
        return cls(mirror, np.concatenate(outline))

    def matrices(self, views: np.ndarray, projections: np.ndarray, reversed_z: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(views, projections, ok)``: each tile's reflected view (det -1), its projection
        (``[-1, 1]`` ones given) with the mirror as oblique near plane (in the tile's eye
        space), reversed-Z with ``reversed_z``, and whether it has one (the mirror is behind
        the tile's camera, or edge-on: it shows nothing)."""
        view, oblique, refused = mirrored_views(views, projections, self.mirror.reflection,
                                                self.mirror.plane)
        return view, as_reversed_z(oblique) if reversed_z else oblique, refused == 0

    def seen(self, culler: Culler, frusta: Frusta) -> tuple[np.ndarray, np.ndarray]:
        """The leaves every tile sees in the mirror, CSR ``(start, leaves)``."""
        # Seen in the mirror, in world space: the tile frusta reflected, in front of the
        # mirror, within the pyramid from the reflected eye through the outline. The reflected
        # table keeps the wall's layout, so the wall's own culling (frustum hierarchy
        # included) does it, with the mirror's planes bounding every tile.
        return culler.cull_reflected(frusta, self.mirror.reflection, self.outline).leaf_lists()

    def tiles(self, seen: tuple[np.ndarray, np.ndarray], views: np.ndarray,
              projections: np.ndarray, reversed_z: bool = False,
              eyes_see: np.ndarray | None = None) -> MirrorSet:
        """The reflected view of every tile (its frustum's planes and projection), showing
        the leaves it has ``seen`` (:meth:`seen`): where the tile's camera sees the mirror,
        or, in a stereo frame, where either eye does (``eyes_see``; the centre's projection
        then stays the tile's, and each eye's record has its own)."""
        start, leaves = seen
        view, oblique, ok = self.matrices(views, projections, reversed_z)
        shown = (np.diff(start) > 0) & (ok if eyes_see is None else ok | eyes_see)
        counts = np.where(shown, np.diff(start), 0)
        keep = np.repeat(shown, np.diff(start))
        return MirrorSet(self.mirror, view, shown, oblique,
                         np.concatenate([[0], np.cumsum(counts)]), leaves[keep])


def _pyramid(apexes: list[np.ndarray], polygon: np.ndarray) -> np.ndarray:
    """Planes through each edge of a convex polygon, facing its inside, that hold what the
    polygon shows seen from any of ``apexes`` (points on its far side: the reflected eyes),
    the longest edges' first (a view holds 63 planes: those past them are left out).

    Each plane through an edge and an apex bounds a wedge past the polygon's plane; the
    planes of one edge share its line, so of two such wedges one holds the other: the plane
    kept for the edge is the one whose inside holds the others' (the union of the pyramids
    past the polygon lies within the planes kept)."""
    center = polygon.mean(axis=0)
    edges = np.roll(polygon, -1, axis=0) - polygon
    longest = np.argsort(-np.linalg.norm(edges, axis=1), kind="stable")
    polygon, edges = polygon[longest], edges[longest]
    kept = None
    for apex in apexes:
        apex = np.asarray(apex, dtype=float)[:3]
        normals = np.cross(polygon - apex, edges)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        d = -np.einsum("ij,ij->i", normals, polygon)
        flip = normals @ center + d < 0
        normals[flip] *= -1
        d[flip] *= -1
        planes = np.concatenate([normals, d[:, None]], axis=1)
        if kept is not None:  # a point of this plane past the polygon, beyond each edge's middle
            past = 2 * (polygon + edges / 2) - apex
            holds = np.einsum("ij,ij->i", kept[:, :3], past) + kept[:, 3] >= 0
            planes = np.where(holds[:, None], kept, planes)
        kept = planes
    return kept


# --------------------------------------------------------------------------- a frame


@dataclass
class EyeFits:
    """One eye's matrices for every tile of a stereo frame: the ``left`` or ``right`` record
    (SPEC section 3); ``mirrors`` holds, per mirror set of the frame, this eye's reflected
    views, oblique projections and which tiles have them."""

    view: np.ndarray  # (4, 4) or (T, 4, 4)
    projection: np.ndarray  # (T, 4, 4)
    near: np.ndarray
    far: np.ndarray
    mirrors: list = field(default_factory=list)  # [(views, projections, shown)]

    def entry(self, t: int, mirror_sets: list) -> dict:
        out = {"view": _tile_view(self.view, t).tolist(),
               "projection": self.projection[t].tolist(), "near": float(self.near[t]),
               "far": float(self.far[t])}
        seen = [{"mirror": m.mirror.name, "view": _tile_view(v, t).tolist(),
                 "projection": p[t].tolist()}
                for m, (v, p, shown) in zip(mirror_sets, self.mirrors) if m.shown[t] and shown[t]]
        if seen:
            out["mirrors"] = seen
        return out


@dataclass
class Fits(Sequence):
    """One frame's fitted frusta: arrays, read as a sequence of per-tile JSON-ready dicts
    (``fits[t]``: ``view``, ``projection``, ``near``, ``far``, any ``shadows``/``mirrors``, and
    ``left``/``right`` for a stereo frame). Kept as arrays, a 64 x 64 wall's frame takes half a
    megabyte, not ten."""

    view: np.ndarray  # (4, 4), shared by every tile of a grid; (tiles, 4, 4) for screens
    projection: np.ndarray  # (tiles, 4, 4)
    near: np.ndarray  # (tiles,)
    far: np.ndarray  # (tiles,)
    shadows: list[ShadowSet] = field(default_factory=list)
    mirrors: list[MirrorSet] = field(default_factory=list)
    eyes: list[EyeFits] = field(default_factory=list)  # left, right: a stereo frame
    reversed_z: bool = False  # the projections map near to 1 and far to 0 (FitOptions)

    def __len__(self) -> int:
        return len(self.projection)

    def __getitem__(self, tile: int) -> dict:
        if not 0 <= tile < len(self):
            raise IndexError(tile)
        view = self.view_rows if self.view.ndim == 2 else self.view[tile].tolist()
        out = {"view": view, "projection": self.projection[tile].tolist(),
               "near": float(self.near[tile]), "far": float(self.far[tile])}
        for key, sets in (("shadows", self.shadows), ("mirrors", self.mirrors)):
            entries = [e for e in (s.entry(tile) for s in sets) if e is not None]
            if entries:
                out[key] = entries
        for key, eye in zip(("left", "right"), self.eyes):
            out[key] = eye.entry(tile, self.mirrors)
        return out

    @cached_property
    def view_rows(self) -> list:
        return self.view.tolist()

    @cached_property
    def compact(self) -> "Compact":
        """The fits as a node message carries them (:mod:`wallcull.protocol`)."""
        views = self.view.reshape(-1, 4, 4)
        eyes = len(self.eyes)
        e_views = np.array([e.view.reshape(-1, 4, 4) for e in self.eyes]).reshape(-1, 4, 4)
        q, t = rigid_parts(views)
        e_q, e_t = rigid_parts(e_views)
        e_projection = np.array([e.projection for e in self.eyes]).reshape(eyes, len(self), 4, 4)
        e_depth = np.array([np.stack([e.near, e.far], axis=1) for e in self.eyes])
        return Compact(q, t, _tangents(self.projection), np.stack([self.near, self.far], axis=1),
                       e_q.reshape(eyes, len(views), 4), e_t.reshape(eyes, len(views), 3),
                       _tangents(e_projection), e_depth.reshape(eyes, len(self), 2))


class Compact(NamedTuple):
    """A frame's views as rotations (unit quaternions ``(w, x, y, z)``) and translations, one
    shared (grid) or one per tile (screens), and each tile's frustum as its extent (tangents
    ``l/n, r/n, b/n, t/n``) and depth range; the same per eye of a stereo frame (``e_*``, eye
    first)."""

    rotation: np.ndarray  # (V, 4)
    translation: np.ndarray  # (V, 3)
    tangents: np.ndarray  # (T, 4)
    depth: np.ndarray  # (T, 2)
    e_rotation: np.ndarray  # (E, V, 4)
    e_translation: np.ndarray  # (E, V, 3)
    e_tangents: np.ndarray  # (E, T, 4)
    e_depth: np.ndarray  # (E, T, 2)

    def changed(self, other: "Compact") -> np.ndarray:
        """``(T, 2)``: the tiles whose extent (column 0) or depth range (column 1), or an
        eye's, differs from ``other``'s."""
        out = np.zeros((len(self.tangents), 2), np.bool_)
        if self.e_tangents.shape != other.e_tangents.shape:
            out[:] = True
            return out
        _differ(self.tangents[None], other.tangents[None], out[:, 0])
        _differ(self.depth[None], other.depth[None], out[:, 1])
        _differ(self.e_tangents, other.e_tangents, out[:, 0])
        _differ(self.e_depth, other.e_depth, out[:, 1])
        return out


@njit(cache=True)
def _differ(a, b, out):
    """``out[t] |=`` whether rows ``a[:, t]`` and ``b[:, t]`` (``(E, T, k)``) differ anywhere
    (compiled: on a 64 x 64 wall, numpy's reductions over rows of four took 0.2 ms a frame)."""
    for e in range(a.shape[0]):
        for t in range(a.shape[1]):
            for k in range(a.shape[2]):
                if a[e, t, k] != b[e, t, k]:
                    out[t] = True


def rigid_parts(views: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(V, 4)`` rotation quaternions ``(w, x, y, z)`` and ``(V, 3)`` translations of rigid
    view matrices ``(V, 4, 4)``."""
    return matrix_quaternions(views[:, :3, :3]), np.ascontiguousarray(views[:, :3, 3])


def _tangents(projection: np.ndarray) -> np.ndarray:
    """``(..., 4)``: ``l/n, r/n, b/n, t/n`` of off-axis projections, whatever their depth
    (:func:`wallcull.projection.frustum_extents` at ``n = 1``, compiled)."""
    m = np.ascontiguousarray(projection, np.float64)
    out = np.empty(m.shape[:-2] + (4,))
    _tangents_of(m.reshape(-1, 4, 4), out.reshape(-1, 4))
    return out


@njit(cache=True)
def _tangents_of(m, out):
    for k in range(m.shape[0]):
        out[k, 0] = (m[k, 0, 2] - 1) / m[k, 0, 0]
        out[k, 1] = (m[k, 0, 2] + 1) / m[k, 0, 0]
        out[k, 2] = (m[k, 1, 2] - 1) / m[k, 1, 1]
        out[k, 3] = (m[k, 1, 2] + 1) / m[k, 1, 1]


def fit_frame(wall, frame: Frame, visibility: Visibility | None = None,
              state: SceneState | None = None, scene_settings: cfg.Settings | None = None,
              options: FitOptions = FitOptions(), frusta: Frusta | None = None,
              culler: Culler | None = None) -> Fits:
    """One frame's fitted frusta (see the module docstring). ``culler`` (the frame's own, or
    one for ``state`` and ``wall``) culls what mirrors show."""
    tight = options.depth == "tight" and visibility is not None

    def for_eye(eye):
        if tight:
            near, far = depth_ranges(state, wall, frame, visibility, eye)
        else:
            near, far = np.full(wall.tiles, wall.near), np.full(wall.tiles, wall.far)
        return (tile_views(wall, frame, eye),
                tile_projections(wall, frame, near, far, options.reversed_z, eye), near, far)

    declared = not (scene_settings is None or scene_settings.empty or visibility is None)
    sights = [MirrorSight.of(m, frame, wall.near) for m in scene_settings.mirrors] \
        if declared else []
    sights = [s for s in sights if s is not None]  # None: no eye sees the reflective side
    out = Fits(*for_eye(frame.eye), reversed_z=options.reversed_z)
    if frame.stereo is not None:
        out.eyes = [EyeFits(*for_eye(e)) for e in frame.eyes]
    made = list  # no mirror seen: nothing to wait for
    if sights:
        # What the mirrors show is culled, and their matrices made, beside the rest: on two
        # cores, while a shadow pass waits for its threads, the other core does the mirrors.
        frusta = frusta or Frusta.build(wall, frame)
        culler = culler or Culler(state, wall)

        def mirrored():
            # What a mirror shows lies beyond it, past what the tile shows directly: its
            # projection is the tile's with the wall's depth range, the mirror its near plane
            # (made on the [-1, 1] matrix, then reversed-Z if asked for).
            ranged = [out.projection] + [eye.projection for eye in out.eyes]
            if tight or options.reversed_z:
                near, far = np.full(wall.tiles, wall.near), np.full(wall.tiles, wall.far)
                ranged = [tile_projections(wall, frame, near, far, False, e)
                          for e in [frame.eye, *([] if frame.stereo is None else frame.eyes)]]
            reverse, sets = options.reversed_z, []
            for s in sights:
                per_eye = [s.matrices(eye.view, p, reverse) for eye, p in zip(out.eyes, ranged[1:])]
                # a stereo tile shows a mirror either eye sees (the plane between the eyes)
                either = np.logical_or.reduce([ok for *_, ok in per_eye]) if per_eye else None
                sets.append((s.tiles(s.seen(culler, frusta), out.view, ranged[0], reverse,
                                     either), per_eye))
            return sets

        made = workers.aside(mirrored)
    try:
        if declared:
            out.shadows = shadow_sets(state, scene_settings.lights, visibility,
                                      options.shadow_fit)
    finally:  # the mirrors' culls use the culler's buffers: never left running after a frame
        mirrors = made()
    for mirror, per_eye in mirrors:
        out.mirrors.append(mirror)
        for eye, matrices in zip(out.eyes, per_eye):
            eye.mirrors.append(matrices)
    return out
