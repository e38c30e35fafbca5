"""Occlusion culling: a tile draws nothing that is hidden behind something else.

After the frustum cull, a frame's largest nearby clusters (or what was visible last frame) are
rasterized as *occluders* into small depth buffers, one per image plane: every tile of a planar
grid shares the eye and the wall's plane, so one buffer serves the whole wall; each screen of a
screens wall has its own; a stereo frame has one per eye. Then each tile's listed nodes are
tested against the buffer over the tile's part of it, top down: a node hidden over every texel
its projection touches is dropped; one that is not, but might be in part, is replaced by its
children, and so on down to clusters; one that cannot be is kept whole.

Conservative on both sides, so that dropping never removes a pixel:

* an occluder triangle writes only the texels it covers *wholly* (all four corners inside its
  edges, by a margin), and writes there its *farthest* depth over the texel (depth's reciprocal
  is affine on the image plane, so the farthest is at a corner); a texel keeps the nearest such
  depth: everything beyond it, over the whole texel, is hidden. Triangles that reach behind the
  near plane do not occlude;
* a node's bound is projected whole (its box's eight corners, grown by its ball): the texels
  of its rectangle within the tile, and its nearest depth. It is hidden when that depth lies
  beyond the buffer's farthest over the rectangle (read from a max pyramid of the buffer, at the
  level where the rectangle spans two texels), by a relative margin that keeps a 24-bit depth
  buffer's rounding from letting it through. A bound reaching behind the near plane is never
  hidden. In stereo a node must be hidden from both eyes.

Occluders come from the frame's own lists (``choice="size"``: the units, clusters or whole
leaves, that span the largest angles, within a budget of triangles) or from what the tiles
showed last frame (``"last"``), and never from nodes the scene's settings mark transparent
(``{"occlusion": {"exclude": [node names]}}``, their subtrees with them). What mirrors and
lights see is culled apart (:mod:`wallcull.fit`) and never occlusion-culled.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from numba import njit

from .cull import Visibility
from .errors import InputError
from .scene import SceneState
from .wall import Frame

CHOICES = ("size", "last")
#: ``on``: every frame; ``auto``: the frames whose camera is inside the scene's box (grown by a
#: tenth), where most of what a tile's frustum holds lies behind something (docs/occlusion.md).
MODES = ("on", "auto")
#: The occlusion setting's words, ``off`` among them (no occlusion culling).
SETTINGS = ("off", *MODES)

#: Nodes are hidden only this far (relative) beyond the occluders' depth.
DEPTH_MARGIN = 1e-3
#: Texel corners count inside an occluder's edge only by this share of the texel.
EDGE_MARGIN = 1e-6
#: The most texels on a side of one buffer.
MAX_TEXELS = 1024


@dataclass(frozen=True)
class OcclusionOptions:
    """``mode``: every frame (``on``) or frames from inside the scene (``auto``); ``budget``:
    occluder triangles per frame; ``texels``: buffer texels across one tile's (one screen's)
    width; ``choice``: occluders by ``size`` this frame, or what was visible ``last`` frame."""

    mode: str = "on"
    budget: int = 20_000
    texels: int = 32
    choice: str = "size"

    @classmethod
    def parse(cls, setting: str) -> "OcclusionOptions | None":
        """The options of an occlusion setting (``off``, ``on``, ``auto``); None for off."""
        if setting not in SETTINGS:
            raise InputError(f"occlusion must be {', '.join(SETTINGS)}, got {setting!r}")
        return None if setting == "off" else cls(mode=setting)

    def __post_init__(self):
        if self.mode not in MODES:
            raise InputError(f"occlusion mode must be {' or '.join(MODES)}, got {self.mode!r}")
        if self.choice not in CHOICES:
            raise InputError(f"occluders must be chosen by {' or '.join(CHOICES)}, "
                             f"got {self.choice!r}")
        if not 0 <= self.budget <= 10_000_000 or not 2 <= self.texels <= 512:
            raise InputError("occlusion budget must be 0 to 10 million triangles and texels "
                             "2 to 512 per tile")


@dataclass
class Views:
    """The image planes of one frame: view ``v`` maps world points to its own coordinates by
    ``affine[v] (3, 4)`` (looking down -z, depth -z) and covers the rectangle ``rect[v]`` =
    ``(x0, x1, y0, y1)`` of ``x / depth``, ``y / depth`` with ``size[v] = (W, H)`` texels. Tile
    ``t`` seen by eye ``e`` lies in view ``tile_view[e, t]``, texels ``tile_texels[e, t]`` =
    ``(i0, i1, j0, j1)`` (half-open)."""

    affine: np.ndarray  # (V, 3, 4)
    rect: np.ndarray  # (V, 4)
    size: np.ndarray  # (V, 2) int64
    tile_view: np.ndarray  # (E, T) int64
    tile_texels: np.ndarray  # (E, T, 4) int64

    @classmethod
    def of(cls, wall, frame: Frame, texels: int) -> "Views":
        to_display = np.concatenate([frame.rotation.T, -(frame.rotation.T @ frame.position)[:, None]],
                                    axis=1)  # world -> display: R^T (p - t)
        eyes = frame.eyes
        affine, rect, size, tile_view, tile_texels = [], [], [], [], []
        for eye in eyes:
            views, boxes = [], []
            if wall.kind == "grid":
                depth = eye[2] + wall.distance
                a = to_display.copy()
                a[:, 3] -= eye
                x0, x1 = wall.col_edges[0, 0], wall.col_edges[-1, 1]
                y0, y1 = wall.row_edges[-1, 0], wall.row_edges[0, 1]
                r = (np.array([x0, x1, y0, y1]) - eye[[0, 0, 1, 1]]) / depth
                w = min(MAX_TEXELS, texels * wall.cols)
                h = min(MAX_TEXELS, max(1, round(w * (r[3] - r[2]) / (r[1] - r[0]))))
                views.append((a, r, (w, h)))
                for t in range(wall.tiles):
                    tx0, tx1, ty0, ty1 = (np.array(wall.tile_rect(t)) - eye[[0, 0, 1, 1]]) / depth
                    boxes.append((0, (tx0, tx1, ty0, ty1)))
            else:
                for t in range(wall.tiles):
                    basis = wall.basis[t]
                    a = basis @ to_display
                    a[:, 3] -= basis @ eye
                    quad = (wall.quads[t] - eye) @ basis.T  # the screen in view coordinates
                    xy = quad[:, :2] / -quad[:, 2:3]
                    r = np.array([xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max()])
                    w = texels
                    h = min(MAX_TEXELS, max(1, round(w * wall.size[t, 1] / wall.size[t, 0])))
                    views.append((a, r, (w, h)))
                    boxes.append((t, tuple(r)))
            base = len(affine)
            for a, r, s in views:
                affine.append(a)
                rect.append(r)
                size.append(s)
            tv, tt = [], []
            for v, (tx0, tx1, ty0, ty1) in boxes:
                r, (w, h) = rect[base + v], size[base + v]
                sx, sy = w / (r[1] - r[0]), h / (r[3] - r[2])
                tv.append(base + v)
                tt.append((max(0, math.floor((tx0 - r[0]) * sx)), min(w, math.ceil((tx1 - r[0]) * sx)),
                           max(0, math.floor((ty0 - r[2]) * sy)), min(h, math.ceil((ty1 - r[2]) * sy))))
            tile_view.append(tv)
            tile_texels.append(tt)
        return cls(np.array(affine), np.array(rect), np.array(size, np.int64),
                   np.array(tile_view, np.int64), np.array(tile_texels, np.int64))


class Occluder:
    """Occlusion-culls one scene state's frames on one wall (see the module docstring); keeps
    its buffers, and what was visible last frame, from frame to frame."""

    def __init__(self, state: SceneState, wall, options: OcclusionOptions = OcclusionOptions()):
        self.state, self.wall, self.options = state, wall, options
        scene = state.scene
        self._occluding = _occluding(scene)
        self._last: np.ndarray | None = None
        self._stamp = np.zeros(len(scene), np.int64)  # frame stamps of nodes seen
        self._frame = 0

    def wanted(self, frame: Frame) -> bool:
        """Whether this frame is occlusion-culled (``auto``: its camera is inside the scene)."""
        if self.options.mode == "on":
            return True
        lo, hi = self.state.scene.box
        grow = 0.1 * (hi - lo)
        eye = frame.eye_world
        return bool(((lo - grow <= eye) & (eye <= hi + grow)).all())

    def occlude(self, vis: Visibility, frame: Frame) -> Visibility:
        """``vis`` (the frame's frustum-culled lists) without what the occluders hide."""
        t0 = time.perf_counter()
        state, scene, o = self.state, self.state.scene, self.options
        from .cull import packed

        box = packed(state)
        views = Views.of(self.wall, frame, o.texels)
        near = self.wall.near
        self._frame += 1
        if o.choice == "last" and self._last is not None:
            seeds = self._last
        else:
            seeds = np.unique(vis.nodes)
        units, angle = _pick(seeds, box, scene.child_start, scene.child_count, scene.children,
                             self._occluding, views.affine, near, self._stamp, self._frame)
        first, count = scene.cluster_faces
        # the most image for the triangles first: a wall's two triangles before a pipe's forty
        units = units[np.argsort(-angle ** 2 / np.maximum(count[units], 1), kind="stable")]
        owner = np.where(scene.cluster_leaf[units] >= 0, scene.cluster_leaf[units], units)
        take = np.cumsum(count[units]) <= o.budget
        units, owner = units[take], owner[take]
        m = scene.meshes
        offsets, total = _levels(views.size)
        izlo = np.zeros(total)  # per texel 1 / the depth beyond which all is hidden; 0: none
        order = np.argsort(_depths(units, box, views.affine))  # nearest first: masks fill
        _rasterize(units[order], owner[order], first, count, scene.mesh_of, state.world,
                   m.vertex_start, m.vertices, m.face_start, m.faces, m.face_neighbors,
                   views.affine, views.rect,
                   views.size, near, izlo, offsets, np.zeros(total, np.uint64),
                   np.full(total, np.inf))
        izhi = izlo.copy()
        _pyramids(izlo, izhi, views.size, offsets)
        start, nodes, hidden = _prune(vis.start, vis.nodes, box, scene.child_start,
                                      scene.child_count, scene.children, views.affine,
                                      views.rect, views.size, views.tile_view, views.tile_texels,
                                      near, izlo, izhi, offsets)
        out = Visibility(vis.scene, start, nodes, {
            **vis.stats, "pairs": len(nodes), "occluded": int(hidden),
            "occluder_units": len(units), "occluder_triangles": int(count[units].sum()),
            "occlude_ms": (time.perf_counter() - t0) * 1e3})
        self._last = np.unique(nodes)
        return out


def _occluding(scene) -> np.ndarray:
    """``(n,)`` uint8: 1 where a node may occlude; 0 under the nodes the settings exclude."""
    names = (scene.settings.get("occlusion") or {}).get("exclude", [])
    flag = np.ones(len(scene), np.uint8)
    for name in names:
        node = scene.index.get(name)
        if node is None:
            raise InputError(f"occlusion exclude names no node {name!r}")
        flag[node:node + scene.size[node]] = 0
    return flag


def _levels(size: np.ndarray) -> tuple[np.ndarray, int]:
    """Offsets ``(V, L)`` of each view's pyramid levels in one flat array, and its length;
    level ``l`` of a ``W x H`` view is ``ceil(W / 2^l) x ceil(H / 2^l)``, row-major."""
    levels = int(math.ceil(math.log2(max(int(size.max()), 1)))) + 1
    offsets = np.zeros((len(size), levels), np.int64)
    at = 0
    for v, (w, h) in enumerate(size):
        for l in range(levels):
            offsets[v, l] = at
            at += (-(-int(w) >> l) if l else int(w)) * (-(-int(h) >> l) if l else int(h))
    return offsets, at


@njit(cache=True, inline="always")
def _to_view(a, x, y, z):
    return (a[0, 0] * x + a[0, 1] * y + a[0, 2] * z + a[0, 3],
            a[1, 0] * x + a[1, 1] * y + a[1, 2] * z + a[1, 3],
            a[2, 0] * x + a[2, 1] * y + a[2, 2] * z + a[2, 3])


@njit(cache=True)
def _angle(box, i, affine, near):
    """The largest angle node ``i``'s sphere spans in any view (radians, about); 0 when it
    reaches behind the near plane of every view."""
    best = 0.0
    for v in range(affine.shape[0]):
        _, _, z = _to_view(affine[v], box[i, 0], box[i, 1], box[i, 2])
        d = -z - box[i, 13]
        if d > near:
            best = max(best, box[i, 13] / d)
    return best


@njit(cache=True)
def _depths(units, box, affine):
    """Each unit's centre's smallest depth over the views."""
    out = np.empty(units.shape[0])
    for q in range(units.shape[0]):
        i = units[q]
        d = np.inf
        for v in range(affine.shape[0]):
            _, _, z = _to_view(affine[v], box[i, 0], box[i, 1], box[i, 2])
            d = min(d, -z)
        out[q] = d
    return out


@njit(cache=True)
def _pick(seeds, box, child_start, child_count, children, occluding, affine, near, stamp, frame):
    """The childless nodes under ``seeds`` that may occlude, and the angle each spans. Only
    nodes spanning at least a 500th of a radian are opened (what is smaller hides little)."""
    stack = np.empty(seeds.shape[0] + 64, np.int64)
    found = np.empty(seeds.shape[0] * 4 + 64, np.int64)
    angle = np.empty(found.shape[0])
    k = 0
    for s in range(seeds.shape[0]):
        sp = 0
        stack[sp] = seeds[s]
        sp += 1
        while sp > 0:
            sp -= 1
            i = stack[sp]
            if stamp[i] == frame or not occluding[i]:
                continue
            stamp[i] = frame
            a = _angle(box, i, affine, near)
            if a < 0.002:
                continue
            if child_count[i] == 0:
                if k == found.shape[0]:
                    found = np.concatenate((found, np.empty(found.shape[0], np.int64)))
                    angle = np.concatenate((angle, np.empty(angle.shape[0])))
                found[k] = i
                angle[k] = a
                k += 1
                continue
            while sp + child_count[i] > stack.shape[0]:
                stack = np.concatenate((stack, np.empty(stack.shape[0], np.int64)))
            for c in range(child_start[i], child_start[i] + child_count[i]):
                stack[sp] = children[c]
                sp += 1
    return found[:k], angle[:k]


@njit(cache=True)
def _rasterize(units, owner, first, count, mesh_of, world, vertex_start, vertices, face_start,
               faces, neighbors, affine, rect, size, near, iz, offsets, mask, iz_work):
    """Write every triangle of ``units`` (leaf ``owner[u]``'s faces ``first[u]:first[u] +
    count[u]``, nearest units first) into level 0 of each view (see :func:`_raster_triangle`),
    with the far vertex of each edge's neighbour face (``neighbors``: per face of the table,
    the face across each edge, -1 for none). Blocks of ``BLOCK`` x ``BLOCK`` texels keep a
    lower bound of what their texels hold, brought up to date after each unit: a triangle
    nearer nowhere than what its blocks already hold is skipped (nearest units first, most of
    what lies behind them is)."""
    tri = np.empty((3, 3))
    far = np.empty((3, 3))
    scratch = np.empty((16, SUB))
    spans = np.empty((2, SUB + 6), np.int64)
    views = affine.shape[0]
    bw = np.empty(views, np.int64)
    bh = np.empty(views, np.int64)
    b_at = np.zeros(views + 1, np.int64)
    for v in range(views):
        bw[v], bh[v] = -(-size[v, 0] // BLOCK), -(-size[v, 1] // BLOCK)
        b_at[v + 1] = b_at[v] + bw[v] * bh[v]
    low = np.zeros(b_at[views])  # per block: no texel holds less
    dirty = np.zeros(b_at[views], np.uint8)
    for q in range(units.shape[0]):
        u = units[q]
        leaf = owner[q]
        m = mesh_of[leaf]
        w = world[leaf]
        v0 = vertex_start[m]
        f0 = face_start[m] + first[u]
        for f in range(f0, f0 + count[u]):
            for c in range(3):
                _place(w, vertices[v0 + faces[f, c]], tri[c])
            for e in range(3):  # the neighbour's vertex off the shared edge (a, b)
                g = neighbors[f, e]
                far[e, 0] = np.nan
                if g >= 0:
                    a_, b_ = faces[f, e], faces[f, (e + 1) % 3]
                    for c in range(3):
                        x = faces[g, c]
                        if x != a_ and x != b_:
                            _place(w, vertices[v0 + x], far[e])
            for v in range(views):
                _raster_triangle(tri, far, affine[v], rect[v], size[v, 0], size[v, 1], near,
                                 iz, mask, iz_work, offsets[v, 0], scratch, spans,
                                 low[b_at[v]:b_at[v + 1]], dirty[b_at[v]:b_at[v + 1]], bw[v])
        for v in range(views):  # the blocks this unit wrote: their bound again
            for b in range(b_at[v + 1] - b_at[v]):
                if dirty[b_at[v] + b]:
                    dirty[b_at[v] + b] = 0
                    J, I = b // bw[v], b % bw[v]
                    lo = np.inf
                    for j in range(J * BLOCK, min((J + 1) * BLOCK, size[v, 1])):
                        for i in range(I * BLOCK, min((I + 1) * BLOCK, size[v, 0])):
                            lo = min(lo, iz[offsets[v, 0] + j * size[v, 0] + i])
                    low[b_at[v] + b] = lo


@njit(cache=True, inline="always")
def _place(w, p, out):
    for r in range(3):
        out[r] = w[r, 0] * p[0] + w[r, 1] * p[1] + w[r, 2] * p[2] + w[r, 3]


#: Sub-samples across a texel each way: a texel's coverage is a 64-bit mask of 8 x 8 cells.
SUB = 8
#: Texels across a block whose least value :func:`_rasterize` keeps.
BLOCK = 8
_FULL = np.uint64(0xFFFFFFFFFFFFFFFF)


@njit(cache=True, inline="always")
def _project(a, p, rect, sx, sy, near, out, k):
    """Point ``p`` (world) to cells of the view: ``out[0:3, k]`` = x, y, 1 / depth; False when
    it lies behind the near plane."""
    x, y, z = _to_view(a, p[0], p[1], p[2])
    d = -z
    if not d > near:
        return False
    out[0, k] = (x / d - rect[0]) * sx
    out[1, k] = (y / d - rect[2]) * sy
    out[2, k] = 1.0 / d
    return True


@njit(cache=True, inline="always")
def _side(px, py, i, j, k):
    """Twice the signed area of points ``i, j, k`` (cells)."""
    return (px[j] - px[i]) * (py[k] - py[i]) - (px[k] - px[i]) * (py[j] - py[i])


@njit(cache=True)
def _raster_triangle(tri, far, a, rect, w, h, near, buf, mask, iz_work, at, scratch, spans,
                     low, dirty, bw):
    """One occluder triangle into one view's texels, conservatively (the module docstring).

    Coverage: the cells (8 x 8 a texel) wholly inside the triangle, by a margin, and across an
    edge shared with a neighbour face (``far[e]``: its vertex off edge ``e``, NaN for none)
    that lies on the other side of it on the image, inside the neighbour too: a cell is then
    inside the triangle's other edges and the neighbour's, so each of its parts is in one of
    the two, and a surface of many triangles covers whole the texels its triangles share.
    Depths are kept as reciprocals (``1 / depth``: affine on the image plane, no division per
    texel), the smallest over the cell's corners and the planes of the faces used (the
    farthest the surface can be there). ``buf`` per texel: the largest, over what covers it
    whole, of those. Texel rows by texel rows, each of its eight cell rows by the span of cells
    covered; a texel covered whole takes the farthest depth over it at once, a texel covered in
    part gets the cells' bits in its coverage mask and the farthest depth over them in its
    working depth. Once the mask is full (several triangles covering the texel together),
    everything beyond the working depth is hidden there: the texel takes it, and the mask
    starts again."""
    sx = SUB * w / (rect[1] - rect[0])  # cells
    sy = SUB * h / (rect[3] - rect[2])
    pts = scratch[0:3]  # x, y, 1/d of the triangle (0-2) and the neighbours' far vertices (3-5)
    for c in range(3):
        if not _project(a, tri[c], rect, sx, sy, near, pts, c):
            return  # reaches behind the near plane: no occluder
    px, py, iz = pts[0], pts[1], pts[2]
    # nowhere nearer than what every texel its box touches holds already (``low``: a lower
    # bound per block): it can change nothing
    i0 = max(0, int(min(px[0], px[1], px[2]) // SUB) // BLOCK)
    i1 = min(bw - 1, int(max(px[0], px[1], px[2]) // SUB) // BLOCK)
    j0 = max(0, int(min(py[0], py[1], py[2]) // SUB) // BLOCK)
    j1 = min(low.shape[0] // bw - 1, int(max(py[0], py[1], py[2]) // SUB) // BLOCK)
    if i0 <= i1 and j0 <= j1:
        held = np.inf
        for J in range(j0, j1 + 1):
            for I in range(i0, i1 + 1):
                held = min(held, low[J * bw + I])
        if max(iz[0], iz[1], iz[2]) <= held:
            return
    area = _side(px, py, 0, 1, 2)
    if not abs(area) > 1e-9:
        return
    sign = 1.0 if area > 0 else -1.0
    # half-planes, inside when A x + B y + C >= margin, and the planes of 1/depth in use
    hp = scratch[3:7]  # A, B, C, margin
    planes = scratch[7:10]  # ga, gb, gc
    nh = 0
    npl = 0
    y_lo, y_hi = min(py[0], py[1], py[2]), max(py[0], py[1], py[2])  # of the faces in use
    for e in range(4):
        if e == 3:  # the triangle's own plane of 1/depth
            i, j, k = 0, 1, 2
        else:
            i, j, k = e, (e + 1) % 3, 3 + e  # the neighbour across edge e: (i, j, far)
            shared = not np.isnan(far[e, 0]) and _project(a, far[e], rect, sx, sy, near, pts, k)
            if shared:
                s2 = _side(px, py, i, j, k)
                shared = s2 * area < 0 and abs(s2) > 1e-9  # across the edge on the image
            if not shared:  # the edge bounds the coverage
                nh = _half_plane(hp, nh, px, py, i, j, sign)
                continue
            s_n = 1.0 if s2 > 0 else -1.0
            y_lo, y_hi = min(y_lo, py[k]), max(y_hi, py[k])
            nh = _half_plane(hp, nh, px, py, j, k, s_n)
            nh = _half_plane(hp, nh, px, py, k, i, s_n)
        det = _side(px, py, i, j, k)
        planes[0, npl] = ((iz[j] - iz[i]) * (py[k] - py[i]) - (iz[k] - iz[i]) * (py[j] - py[i])) / det
        planes[1, npl] = ((px[j] - px[i]) * (iz[k] - iz[i]) - (px[k] - px[i]) * (iz[j] - iz[i])) / det
        planes[2, npl] = iz[i] - planes[0, npl] * px[i] - planes[1, npl] * py[i]
        npl += 1
    # each half-plane as a bound on x, linear in y: x >= (or <=) p + q y; or on y alone
    bp, bq, kind = scratch[10], scratch[11], spans[0]
    for c in range(nh):
        A, B, C, margin = hp[0, c], hp[1, c], hp[2, c], hp[3, c]
        if A != 0:
            bp[c] = (margin - C) / A
            bq[c] = -B / A
            kind[c] = 1 if A > 0 else 2
        elif B != 0:  # B y + C >= margin
            bp[c] = B
            bq[c] = (margin - C) / B
            kind[c] = 0
        else:  # no line: everywhere (3) or nowhere
            bp[c], bq[c] = 1.0, np.inf
            kind[c] = 3 if C >= margin else 0
    cells_w, cells_h = SUB * w, SUB * h
    r0 = max(0, int(math.floor(y_lo)))
    r1 = min(cells_h, int(math.ceil(y_hi)))
    lo, hi = spans[0, 6:], spans[1, :SUB]
    slope, offset = scratch[12], scratch[13]
    for J in range(r0 // SUB, -(-r1 // SUB)):
        inner_lo, inner_hi = cells_w, -1
        outer_lo, outer_hi = cells_w, -1
        for k in range(SUB):
            y0 = float(J * SUB + k)
            xl, xr = 0.0, float(cells_w)
            for c in range(nh):
                if kind[c] == 1:
                    xl = max(xl, bp[c] + bq[c] * y0 + max(bq[c], 0.0))
                elif kind[c] == 2:
                    xr = min(xr, bp[c] + bq[c] * y0 + min(bq[c], 0.0))
                elif not ((y0 >= bq[c] and y0 + 1 >= bq[c]) if bp[c] > 0
                          else (y0 <= bq[c] and y0 + 1 <= bq[c])):
                    xr = -1.0  # the row lies outside
            c0 = int(math.ceil(xl))
            c1 = int(math.floor(xr)) - 1  # the last cell whose right side is within
            lo[k], hi[k] = c0, c1
            if c0 <= c1:
                outer_lo = min(outer_lo, c0)
                outer_hi = max(outer_hi, c1)
            inner_lo = max(inner_lo, c0) if k else c0
            inner_hi = min(inner_hi, c1) if k else c1
        if outer_lo > outer_hi:
            continue
        # the texels covered whole: one run, each the farthest of the planes over it, which
        # along the run is affine in I (slope 8 ga, and the rest fixed for the row)
        Ia, Ib = -(-inner_lo // SUB), (inner_hi + 1) // SUB - 1
        if Ia <= Ib:
            y0, y1 = J * SUB, J * SUB + SUB
            for p_ in range(npl):
                ga, gb = planes[0, p_], planes[1, p_]
                slope[p_] = ga * SUB
                offset[p_] = min(0.0, ga * SUB) + min(gb * y0, gb * y1) + planes[2, p_]
            row = at + J * w
            wrote = False
            for I in range(Ia, Ib + 1):
                far_iz = slope[0] * I + offset[0]
                for p_ in range(1, npl):
                    far_iz = min(far_iz, slope[p_] * I + offset[p_])
                if far_iz > buf[row + I]:
                    buf[row + I] = far_iz
                    wrote = True
            if wrote:
                for b in range(Ia // BLOCK, Ib // BLOCK + 1):
                    dirty[(J // BLOCK) * bw + b] = 1
        for I in range(outer_lo // SUB, outer_hi // SUB + 1):
            if Ia <= I <= Ib:
                continue
            k_at = at + J * w + I
            x0, x1 = I * SUB, I * SUB + SUB
            bits = np.uint64(0)
            low_iz = np.inf
            for k in range(SUB):
                c0, c1 = max(lo[k], x0), min(hi[k], x1 - 1)
                if c0 > c1:
                    continue
                run = (np.uint64(1) << np.uint64(c1 - c0 + 1)) - np.uint64(1)
                bits |= run << np.uint64(k * SUB + c0 - x0)
                yk = J * SUB + k
                low_iz = min(low_iz, _lowest(planes, npl, c0, c1 + 1, yk, yk + 1))
            if bits == 0 or not low_iz > 0:
                continue
            mask[k_at] |= bits
            iz_work[k_at] = min(iz_work[k_at], low_iz)
            if mask[k_at] == _FULL:
                if iz_work[k_at] > buf[k_at]:
                    buf[k_at] = iz_work[k_at]
                    dirty[(J // BLOCK) * bw + I // BLOCK] = 1
                mask[k_at] = np.uint64(0)
                iz_work[k_at] = np.inf


@njit(cache=True, inline="always")
def _half_plane(hp, n, px, py, i, j, sign):
    """Add the half-plane on the ``sign`` side of the line from point ``i`` to ``j``, inside
    by a margin of a millionth of a cell's size: ``sign (ex (y - ay) - ey (x - ax)) >= m``."""
    ax, ay = px[i], py[i]
    ex, ey = px[j] - ax, py[j] - ay
    hp[0, n] = -sign * ey
    hp[1, n] = sign * ex
    hp[2, n] = sign * (ey * ax - ex * ay)
    hp[3, n] = EDGE_MARGIN * SUB * (abs(ex) + abs(ey))
    return n + 1


@njit(cache=True, inline="always")
def _lowest(planes, n, x0, x1, y0, y1):
    """The smallest value of ``n`` planes of 1/depth over the rectangle ``[x0, x1] x [y0,
    y1]`` (cells): at a corner, plane by plane."""
    out = np.inf
    for p in range(n):
        ga, gb, gc = planes[0, p], planes[1, p], planes[2, p]
        out = min(out, min(ga * x0, ga * x1) + min(gb * y0, gb * y1) + gc)
    return out


@njit(cache=True)
def _pyramids(lo_, hi_, size, offsets):
    """Levels 1 and up of each view: the smallest (``lo_``) and largest (``hi_``) of the level
    below's 2 x 2 texels (a border texel of fewer)."""
    for v in range(size.shape[0]):
        w, h = size[v, 0], size[v, 1]
        for l in range(1, offsets.shape[1]):
            cw, ch = -(-w // 2), -(-h // 2)
            src, dst = offsets[v, l - 1], offsets[v, l]
            for j in range(ch):
                for i in range(cw):
                    hi = -np.inf
                    lo = np.inf
                    for dj in range(2):
                        for di in range(2):
                            y, x = 2 * j + dj, 2 * i + di
                            if y < h and x < w:
                                lo = min(lo, lo_[src + y * w + x])
                                hi = max(hi, hi_[src + y * w + x])
                    lo_[dst + j * cw + i] = lo
                    hi_[dst + j * cw + i] = hi
            w, h = cw, ch


@njit(cache=True)
def _extreme(buf, offsets, v, w0, h0, i0, i1, j0, j1, largest):
    """The largest (or smallest) value of level 0's texels ``[i0, i1) x [j0, j1)``, read at the
    level where they span at most two texels each way (which covers them, and maybe more)."""
    l = 0
    w, h = w0, h0
    while ((i1 - 1) >> l) - (i0 >> l) > 1 or ((j1 - 1) >> l) - (j0 >> l) > 1:
        l += 1
        w, h = -(-w // 2), -(-h // 2)
    out = -np.inf if largest else np.inf
    at = offsets[v, l]
    for j in range(j0 >> l, ((j1 - 1) >> l) + 1):
        for i in range(i0 >> l, ((i1 - 1) >> l) + 1):
            x = buf[at + j * w + i]
            out = max(out, x) if largest else min(out, x)
    return out


@njit(cache=True)
def _judge(box, i, affine, rect, size, tile_view, tile_texels, t, near, izlo, izhi, offsets,
           half, child_count_i, hull):
    """0: node ``i`` is hidden in tile ``t`` (from every eye); 1: it is not, and no part of it
    can be; 2: a part of it might be. ``half (6, 3)`` is scratch."""
    ball = box[i, 3]
    for k in range(3):  # the half-extent vectors, grown by the ball (a box around the bound)
        hx, hy, hz = box[i, 4 + 3 * k], box[i, 5 + 3 * k], box[i, 6 + 3 * k]
        n = math.sqrt(hx * hx + hy * hy + hz * hz)
        if n > 0:
            g = 1.0 + ball / n
            half[k, 0], half[k, 1], half[k, 2] = hx * g, hy * g, hz * g
        else:  # no extent along this axis: the ball along the world's
            half[k, 0] = half[k, 1] = half[k, 2] = 0.0
            half[k, k] = ball
    hidden = True
    partly = False
    for e in range(tile_view.shape[0]):
        v = tile_view[e, t]
        a = affine[v]
        cx, cy, cz = _to_view(a, box[i, 0], box[i, 1], box[i, 2])
        # the eight corners in view coordinates: the centre plus the signed half vectors
        hv = half[3:]
        for k in range(3):
            for r in range(3):
                hv[k, r] = a[r, 0] * half[k, 0] + a[r, 1] * half[k, 1] + a[r, 2] * half[k, 2]
        lo_x = lo_y = np.inf
        hi_x = hi_y = -np.inf
        d_near = np.inf
        d_far = 0.0
        for c in range(8):
            s0 = 1.0 if c & 1 else -1.0
            s1 = 1.0 if c & 2 else -1.0
            s2 = 1.0 if c & 4 else -1.0
            x = cx + s0 * hv[0, 0] + s1 * hv[1, 0] + s2 * hv[2, 0]
            y = cy + s0 * hv[0, 1] + s1 * hv[1, 1] + s2 * hv[2, 1]
            d = -(cz + s0 * hv[0, 2] + s1 * hv[1, 2] + s2 * hv[2, 2])
            if not d > near:
                return 2  # it reaches the eye: never hidden; its children may be
            d_near = min(d_near, d)
            d_far = max(d_far, d)
            lo_x = min(lo_x, x / d)
            hi_x = max(hi_x, x / d)
            lo_y = min(lo_y, y / d)
            hi_y = max(hi_y, y / d)
        w, h = size[v, 0], size[v, 1]
        sx = w / (rect[v, 1] - rect[v, 0])
        sy = h / (rect[v, 3] - rect[v, 2])
        i0 = max(tile_texels[e, t, 0], int(math.floor((lo_x - rect[v, 0]) * sx)))
        i1 = min(tile_texels[e, t, 1], int(math.ceil((hi_x - rect[v, 0]) * sx)))
        j0 = max(tile_texels[e, t, 2], int(math.floor((lo_y - rect[v, 2]) * sy)))
        j1 = min(tile_texels[e, t, 3], int(math.ceil((hi_y - rect[v, 2]) * sy)))
        if i1 <= i0 or j1 <= j0:
            continue  # nothing of it in this tile from this eye
        # hidden beyond 1 / iz: over every texel (the smallest iz), or over some (the largest)
        if not d_near * _extreme(izlo, offsets, v, w, h, i0, i1, j0, j1, False) \
                > 1 + DEPTH_MARGIN:
            partly = partly or d_far * _extreme(izhi, offsets, v, w, h, i0, i1, j0, j1, True) \
                > 1 + DEPTH_MARGIN
            # a node that cannot be opened: over the texels its outline touches, not its box
            if not (child_count_i == 0 and partly
                    and _outline_hidden(hull, cx, cy, cz, hv, rect[v], w, h, i0, i1, j0, j1,
                                        d_near, izlo, offsets[v, 0])):
                hidden = False
    if hidden:
        return 0
    return 2 if partly else 1


@njit(cache=True)
def _outline_hidden(hull, cx, cy, cz, hv, rect, w, h, i0, i1, j0, j1, d_near, izlo, at):
    """Whether every texel of ``[i0, i1) x [j0, j1)`` that the outline of the box (centre
    ``c``, half vectors ``hv``, view coordinates) touches holds occluders nearer than
    ``d_near``. The outline: the convex hull of the eight corners on the image (gift
    wrapping), in texel coordinates; a texel is left out only when all four of its corners lie
    outside one of its edges (then the two are apart)."""
    sx = w / (rect[1] - rect[0])
    sy = h / (rect[3] - rect[2])
    for c in range(8):
        s0 = 1.0 if c & 1 else -1.0
        s1 = 1.0 if c & 2 else -1.0
        s2 = 1.0 if c & 4 else -1.0
        d = -(cz + s0 * hv[0, 2] + s1 * hv[1, 2] + s2 * hv[2, 2])
        hull[0, c] = ((cx + s0 * hv[0, 0] + s1 * hv[1, 0] + s2 * hv[2, 0]) / d - rect[0]) * sx
        hull[1, c] = ((cy + s0 * hv[0, 1] + s1 * hv[1, 1] + s2 * hv[2, 1]) / d - rect[2]) * sy
    # gift wrapping: the hull's corners in counter-clockwise order, into hull[2] (indices)
    start = 0
    for c in range(1, 8):
        if hull[0, c] < hull[0, start] or (hull[0, c] == hull[0, start]
                                            and hull[1, c] < hull[1, start]):
            start = c
    n = 0
    p = start
    while True:
        hull[2, n] = p
        n += 1
        q = (p + 1) % 8
        for r in range(8):
            cross = ((hull[0, q] - hull[0, p]) * (hull[1, r] - hull[1, p])
                     - (hull[1, q] - hull[1, p]) * (hull[0, r] - hull[0, p]))
            if cross < 0:
                q = r
        p = q
        if p == start or n == 8:
            break
    for j in range(j0, j1):
        for i in range(i0, i1):
            touched = True
            for e in range(n):
                a = int(hull[2, e])
                b = int(hull[2, (e + 1) % n])
                ex, ey = hull[0, b] - hull[0, a], hull[1, b] - hull[1, a]
                out = True
                for cy_ in range(2):
                    for cx_ in range(2):
                        if ex * (j + cy_ - hull[1, a]) - ey * (i + cx_ - hull[0, a]) >= 0:
                            out = False
                if out:
                    touched = False
                    break
            if touched and not d_near * izlo[at + j * w + i] > 1 + DEPTH_MARGIN:
                return False
    return True


@njit(cache=True)
def _prune(start, nodes, box, child_start, child_count, children, affine, rect, size,
           tile_view, tile_texels, near, izlo, izhi, offsets):
    """Each tile's nodes without the hidden ones, partly hidden ones replaced by their children
    (recursively): CSR ``(start, nodes)`` in preorder, and how many nodes were dropped."""
    tiles = start.shape[0] - 1
    out = np.empty(nodes.shape[0] + 1024, np.int64)
    out_start = np.zeros(tiles + 1, np.int64)
    stack = np.empty(1024, np.int64)
    half = np.empty((6, 3))
    hull = np.empty((3, 9))
    k = 0
    hidden = 0
    for t in range(tiles):
        sp = 0
        for j in range(start[t + 1] - 1, start[t] - 1, -1):
            if sp == stack.shape[0]:
                stack = np.concatenate((stack, np.empty(stack.shape[0], np.int64)))
            stack[sp] = nodes[j]
            sp += 1
        while sp > 0:
            sp -= 1
            i = stack[sp]
            state = _judge(box, i, affine, rect, size, tile_view, tile_texels, t, near, izlo,
                           izhi, offsets, half, child_count[i], hull)
            if state == 0:
                hidden += 1
                continue
            if state == 2 and child_count[i] > 0:
                while sp + child_count[i] > stack.shape[0]:
                    stack = np.concatenate((stack, np.empty(stack.shape[0], np.int64)))
                for c in range(child_start[i] + child_count[i] - 1, child_start[i] - 1, -1):
                    stack[sp] = children[c]
                    sp += 1
                continue
            if k == out.shape[0]:
                out = np.concatenate((out, np.empty(out.shape[0], np.int64)))
            out[k] = i
            k += 1
        out_start[t + 1] = k
    return out_start, out[:k], hidden
