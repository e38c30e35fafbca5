"""Occlusion culling: a tile draws nothing that is hidden behind something else.

After the frustum cull, a frame's best occluders are rasterized into small depth buffers, one
per image plane: every tile of a planar grid shares the eye and the wall's plane, so one buffer
serves the whole wall; on a screens wall the screens in one plane share one (a column of a
curved wall's panels), and a screen in no other's plane has its own; a stereo frame has one
per eye. Then each tile's listed nodes are tested against the buffer over the tile's part of it,
top down: a node hidden over every texel its projection touches is dropped; one that is not,
but might be in part, is replaced by its children, and so on down to clusters; one that cannot
be is kept whole.

Conservative on both sides, so that dropping never removes a pixel:

* occluders claim only what they cover *wholly*. A leaf's chosen faces that face the eye form
  *patches*, faces joined across the edges they share (when the two lie either side of the
  edge on the image); the patch's other edges, and the near plane's cuts through its faces,
  are its *outline*. Texels are split into ``SUB x SUB`` cells, a row of cells bits of a
  word: a cell whose centre a face of the patch covers and that no edge of the outline
  touches (by a margin) lies wholly inside the patch, and a texel all of whose cells are
  claimed so is claimed whole; cells claimed by several patches gather in a mask until they
  fill the texel. A texel claimed keeps the nearest of the *farthest* depths of what claimed
  it (depth's reciprocal is affine on each face, so the farthest is at a corner of the face's
  part in the texel): everything beyond it, over the whole texel, is hidden. Faces before the
  near plane are cut off; a closed mesh's back faces are skipped where its box lies clear of
  the eye and the near plane (its front faces hide them; from inside it they are what is
  seen), and a single-sided glTF mesh's always (a render node may cull them, and show what
  lies behind them: ``MeshTable.single_sided``);
  two faces across a side that make a convex quadrilateral are drawn as one polygon (a
  wall's, a pipe's sides), each keeping its own depths;
* a node's bound is projected whole (its box's eight corners, grown by its ball): the texels
  of its rectangle within the tile, and its nearest depth. It is hidden when that depth lies
  beyond the buffer's farthest over the rectangle (read from a max pyramid of the buffer, at the
  level where the rectangle spans two texels), or else over every texel its box's outline
  touches, at the box's own depth there (blocks of texels first, from the min pyramid), by a
  margin that keeps a 24-bit depth buffer's rounding from letting it through (relative, plus
  a few of the buffer's steps at the wall's near plane, for far depths). A bound
  reaching behind the near plane is never hidden. In stereo a node must be hidden from both
  eyes.

Occluders are the units (clusters, or whole leaves) under the frame's lists whose box covers
the most image per triangle, weighted by the share of the box their faces fill (a wall before
a pipe, a floor before a grating), within a budget of triangles (the default of
:data:`CHOICES`), and never nodes whose material may show what lies behind them (glass,
alpha-tested leaves: ``MeshTable.see_through``), nor those the scene's settings name
(``{"occlusion": {"exclude": [node names]}}``, their subtrees with them). They are
rasterized nearest leaf first, so that a patch that cannot bring any texel of its image
nearer is skipped whole, and in threads, each drawing every patch into its own run of rows.
What mirrors and lights see is culled apart (:mod:`wallcull.fit`) and never
occlusion-culled.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from . import workers
from .cull import Visibility, packed
from .errors import InputError
from .scene import SceneState
from .validate import MAX_OCCLUDER_TRIANGLES, MAX_TEXELS, MIN_TEXELS
from .wall import Frame

#: ``on``: every frame; ``auto``: the frames whose camera is inside the scene's box as its nodes
#: lie (grown by a tenth), where most of what a tile's frustum holds lies behind something
#: (docs/occlusion.md).
MODES = ("on", "auto")
#: The occlusion setting's words, ``off`` among them (no occlusion culling).
SETTINGS = ("off", *MODES)

#: Nodes are hidden only this far (relative) beyond the occluders' depth ...
DEPTH_MARGIN = 1e-3
#: ... and this much more in 1 / depth, times 1 / the wall's near: four steps of a 24-bit
#: depth buffer, whose step in 1 / depth is 2^-24 / near (with any far plane, standard or
#: reversed), beyond the relative margin at depths over about 4,000 times the near plane's.
DEPTH_STEPS = 4 * 2.0**-24
#: The most texels on a side of one buffer.
MAX_TEXELS = 1024
#: Occluder triangles, and listed nodes to test, a thread is given at least: handing less
#: to a thread, and merging what it drew, costs more than it saves.
RASTER_CHUNK = 4096
TEST_CHUNK = 512
#: How a frame's occluders are chosen within the budget: ``image``, the units under the frame's
#: lists that cover the most image per triangle; ``area``, the most image (the largest nearby
#: first); ``visible``, as ``image`` but under what the frame before showed (its occlusion-culled
#: lists: temporal coherence). Measured by ``wallcull experiment occluders``.
CHOICES = ("image", "area", "visible")
#: The parts of a frame's occlusion, each timed (``occlude_parts_ms`` in the culled lists'
#: stats, ms): choosing the occluders, setting their patches up, drawing them, the pyramids
#: over the buffers, and the test of the tiles' lists.
PARTS = ("choose", "setup", "draw", "pyramids", "test")


@dataclass(frozen=True)
class OcclusionOptions:
    """``mode``: every frame (``on``) or frames from inside the scene (``auto``); ``budget``:
    occluder triangles per frame; ``texels``: buffer texels across one tile's (one screen's)
    width (a scene's settings may set both: :class:`~wallcull.pipeline.Session`);
    ``choice``: how occluders are chosen (:data:`CHOICES`)."""

    mode: str = "on"
    budget: int = 20_000
    texels: int = 32
    choice: str = "image"

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
            raise InputError(f"occluder choice must be {', '.join(CHOICES)}, got {self.choice!r}")
        if not 0 <= self.budget <= MAX_OCCLUDER_TRIANGLES or \
                not MIN_TEXELS <= self.texels <= MAX_TEXELS:
            raise InputError(f"occlusion budget must be 0 to {MAX_OCCLUDER_TRIANGLES:,} "
                             f"triangles and texels {MIN_TEXELS} to {MAX_TEXELS} per tile")


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
    def of(cls, wall, frame: Frame, texels: int, layout: "Layout | None" = None) -> "Views":
        """The frame's views; ``layout``: :func:`_layout` of the frame's eyes, when kept."""
        basis, shift, rect, size, tile_view, tile_texels = layout or _layout(wall, frame.eyes,
                                                                             texels)
        to_display = np.concatenate([frame.rotation.T, -(frame.rotation.T @ frame.position)[:, None]],
                                    axis=1)  # world -> display: R^T (p - t)
        affine = basis @ to_display
        affine[:, :, 3] -= shift
        return cls(affine, rect, size, tile_view, tile_texels)


#: What a frame's views take from its eyes and the wall alone (:func:`_layout`).
Layout = tuple


def _screen_planes(wall) -> np.ndarray:
    """Per screen of a screens wall, the group of screens in its plane (numbered from 0, in
    the order of their first screens): one view, one buffer, serves them all, and an
    occluder seen across several is set up and drawn once."""
    n = wall.basis[:, 2]
    offset = (wall.corners[:, 0] * n).sum(axis=1)
    scale = max(float(np.abs(wall.corners).max()), 1e-300)
    group = np.full(wall.tiles, -1, np.int64)
    count = 0
    for t in range(wall.tiles):
        if group[t] >= 0:
            continue
        same = (np.abs(n - n[t]).max(axis=1) <= 1e-9) & \
            (np.abs(offset - offset[t]) <= 1e-9 * scale) & (group < 0)
        group[same] = count
        count += 1
    return group


def _layout(wall, eyes: np.ndarray, texels: int) -> Layout:
    """The views' parts that depend only on the wall and the eyes, kept while the eyes stay:
    per view, display space to its own axes (``basis (V, 3, 3)``, then less ``shift (V, 3)``,
    the eye in them), its rectangle and size; per eye and tile, its view and texels (see
    :class:`Views`)."""
    basis, shift, rect, size, tile_view, tile_texels = [], [], [], [], [], []
    for eye in eyes:
        if wall.kind == "grid":  # one view: the wall's plane, seen from the eye
            depth = eye[2] + wall.distance
            x0, x1 = wall.col_edges[0, 0], wall.col_edges[-1, 1]
            y0, y1 = wall.row_edges[-1, 0], wall.row_edges[0, 1]
            r = (np.array([x0, x1, y0, y1]) - eye[[0, 0, 1, 1]]) / depth
            w = min(MAX_TEXELS, texels * wall.cols)
            h = min(MAX_TEXELS, max(1, round(w * (r[3] - r[2]) / (r[1] - r[0]))))
            views = [(np.eye(3), eye, r, (w, h))]
            row, col = np.divmod(np.arange(wall.tiles), wall.cols)
            boxes = (np.c_[wall.col_edges[col], wall.row_edges[row]]
                     - eye[[0, 0, 1, 1]]) / depth
            view = np.zeros(wall.tiles, np.int64)
        else:  # a view per plane of screens (a column of a curved wall's panels shares one)
            views, boxes = [], np.zeros((wall.tiles, 4))
            view = _screen_planes(wall)
            for g in range(view.max() + 1):
                group = np.flatnonzero(view == g)
                b = wall.basis[group[0]]
                for t in group:
                    quad = (wall.quads[t] - eye) @ b.T  # the screen in view coordinates
                    xy = quad[:, :2] / -quad[:, 2:3]
                    boxes[t] = xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max()
                r = np.array([boxes[group, 0].min(), boxes[group, 1].max(),
                              boxes[group, 2].min(), boxes[group, 3].max()])
                across = texels / (boxes[group[0], 1] - boxes[group[0], 0])  # its first's
                w = min(MAX_TEXELS, max(1, round(across * (r[1] - r[0]))))
                h = min(MAX_TEXELS, max(1, round(across * (r[3] - r[2]))))
                views.append((b, b @ eye, r, (w, h)))
        base = len(rect)
        for b, e, r, wh in views:
            basis.append(b)
            shift.append(e)
            rect.append(r)
            size.append(wh)
        r, wh = np.array(rect[base:])[view], np.array(size[base:])[view]
        scale = wh / (r[:, [1, 3]] - r[:, [0, 2]])  # texels per unit, across and up
        lo = np.floor((boxes[:, [0, 2]] - r[:, [0, 2]]) * scale).astype(np.int64)
        hi = np.ceil((boxes[:, [1, 3]] - r[:, [0, 2]]) * scale).astype(np.int64)
        tile_view.append(base + view)
        tile_texels.append(np.c_[np.maximum(lo[:, 0], 0), np.minimum(hi[:, 0], wh[:, 0]),
                                 np.maximum(lo[:, 1], 0), np.minimum(hi[:, 1], wh[:, 1])])
    return (np.array(basis), np.array(shift), np.array(rect), np.array(size, np.int64),
            np.array(tile_view, np.int64), np.array(tile_texels, np.int64))


class Occluder:
    """Occlusion-culls one scene state's frames on one wall (see the module docstring); keeps
    its buffers and scratch from frame to frame. ``exclude``: the names of nodes that never
    occlude, their subtrees with them (the settings' ``occlusion.exclude``)."""

    def __init__(self, state: SceneState, wall, options: OcclusionOptions = OcclusionOptions(),
                 exclude: Sequence[str] = ()):
        self.state, self.wall, self.options = state, wall, options
        scene = state.scene
        self._outward = _outward(scene.meshes)
        self._single = scene.meshes.single_sided.astype(np.bool_)  # per mesh (see _setup)
        # per node: the share of its box its faces fill (see _solid); 0: it never occludes
        self._solid = _solid(scene, packed(state), self._outward) * _occluding(scene, exclude)
        self._stamp = np.zeros(len(scene), np.int64)  # frame stamps of nodes seen
        self._frame = 0
        self._scratch: list = []  # per thread: _setup's (see _scratch)
        self._canvas = _canvas()  # _setup's patches, _draw's cells (see _raster)
        self._buffers: list = []  # per thread: _prune's slot and records
        # the eyes and texels, their views' layout and its pyramids' levels (see _levels)
        self._layout: tuple = (None, None, None)
        self._depth: tuple = (np.zeros(0), np.zeros(0))  # the buffers, kept between frames
        self._shown: tuple | None = None  # choice "visible": the frame before's lists (CSR)
        self._parts: dict = {}  # the last frame's time per part (see PARTS), ms

    def wanted(self, frame: Frame) -> bool:
        """Whether this frame is occlusion-culled (``auto``: its camera is inside the scene's
        box as the frame's updates left it, :meth:`SceneState.box`). A frame that is not
        leaves choice ``visible`` no frame before to choose from."""
        if self.options.mode == "on":
            return True
        lo, hi = self.state.box()
        grow = 0.1 * (hi - lo)
        eye = frame.eye_world
        inside = bool(((lo - grow <= eye) & (eye <= hi + grow)).all())
        if not inside:
            self._shown = None
        return inside

    def occlude(self, vis: Visibility, frame: Frame) -> Visibility:
        """``vis`` (the frame's frustum-culled lists) without what the occluders hide."""
        t0 = time.perf_counter()
        scene = self.state.scene
        d = self.depth(vis, frame)
        views = d.views
        eyes = views.tile_view.shape[0]
        t_test = time.perf_counter()
        # tiles in threads, of equal lists
        ranges = workers.chunks(vis.tiles, vis.start, min_work=TEST_CHUNK)
        while len(self._buffers) < len(ranges):
            self._buffers.append([np.zeros((len(scene), 3), np.int64), None])
        stamp = self._frame

        def chunk(k, a, b):
            buf = self._buffers[k]
            if buf[1] is None or buf[1].shape[1] != eyes:
                buf[1] = np.empty((1024, eyes, _R_SIZE))
            lo, hi = vis.start[a], vis.start[b]
            start, nodes, hidden, buf[1] = _prune(
                vis.start[a:b + 1] - lo, vis.nodes[lo:hi], a, d.box, scene.child_start,
                scene.child_count, scene.children, views.affine, views.rect, views.size,
                views.tile_view, views.tile_texels, self.wall.near, d.izlo, d.izhi, d.offsets,
                buf[0], stamp, buf[1])
            return start, nodes, hidden

        parts = workers.run(chunk, ranges)
        base = np.cumsum([0] + [len(p[1]) for p in parts])
        start = np.concatenate([[0]] + [p[0][1:] + b for p, b in zip(parts, base)])
        nodes = np.concatenate([p[1] for p in parts])
        hidden = sum(p[2] for p in parts)
        if self.options.choice == "visible":
            self._shown = (start, nodes)
        t1 = time.perf_counter()
        self._parts["test"] = (t1 - t_test) * 1e3
        out = Visibility(vis.scene, start, nodes, {
            **vis.stats, "pairs": len(nodes), "occluded": int(hidden),
            "occluder_units": len(d.units),
            "occluder_triangles": int(scene.cluster_faces[1][d.units].sum()),
            "occlude_ms": (t1 - t0) * 1e3, "occlude_parts_ms": dict(self._parts)})
        return out

    def depth(self, vis: Visibility, frame: Frame) -> "Depth":
        """The frame's occluders (chosen from ``vis``) rasterized."""
        box = packed(self.state)
        key = (frame.eyes.tobytes(), self.options.texels)
        if self._layout[0] != key:
            layout = _layout(self.wall, frame.eyes, self.options.texels)
            self._layout = (key, layout, _levels(layout[3]))
        views = Views.of(self.wall, frame, self.options.texels, self._layout[1])
        t0 = time.perf_counter()
        units = self.choose(vis, views, box)
        self._parts["choose"] = (time.perf_counter() - t0) * 1e3
        return self.rasterize(units, views, box, self._layout[2])

    def choose(self, vis: Visibility, views: Views, box: np.ndarray) -> np.ndarray:
        """The units (clusters, or leaves) to rasterize as occluders this frame, within the
        budget, the most image (per triangle) first (see :func:`_pick`, :data:`CHOICES`)."""
        scene = self.state.scene
        self._frame += 1
        choice = self.options.choice
        start, seeds = (vis.start, vis.nodes) if choice != "visible" or self._shown is None \
            else self._shown
        return _pick(start, seeds, views.tile_view, box, scene.child_start, scene.child_count,
                     scene.children, self._solid, views.affine, self.wall.near, self._stamp,
                     self._frame, scene.cluster_faces[1], self.options.budget,
                     choice != "area")

    def rasterize(self, units: np.ndarray, views: Views, box: np.ndarray, levels: tuple
                  ) -> "Depth":
        """``units`` rasterized into ``views``' buffers, and their pyramids (``levels``:
        :func:`_levels` of the views' sizes)."""
        state, scene = self.state, self.state.scene
        first, count = scene.cluster_faces
        owner = np.where(scene.cluster_leaf[units] >= 0, scene.cluster_leaf[units], units)
        m = scene.meshes
        offsets, total, spans = levels
        if len(self._depth[0]) != total:
            self._depth = (np.zeros(total), np.zeros(total))
        izlo, izhi = self._depth
        for a, b in spans:  # per texel 1 / the depth beyond which all is hidden; 0: none
            izlo[a:b] = 0.0  # (level 0: the pyramids write over the rest)
        # a leaf's units together (its patches), the nearest leaves first (they make most
        # farther patches skippable, and their cells gather first where they cover in part)
        order = np.lexsort((owner, _depths(owner, box, views.affine)))
        threads = max(1, min(workers.count(), int(count[units].sum()) // RASTER_CHUNK))
        while len(self._scratch) < threads:
            self._scratch.append(_scratch(len(m.faces), len(m.vertices)))
        if len(self._canvas["work"]) != total:  # the cells gathered per texel (see _draw)
            self._canvas = _canvas(total)
        self._parts["setup"], self._parts["draw"] = _raster(
            units[order], owner[order], first, count, scene.mesh_of, state.world, box, m,
            self._outward, self._single, views.affine, views.rect, views.size, self.wall.near, izlo,
            offsets[:, 0], spans, self._scratch, self._canvas, threads)
        t0 = time.perf_counter()
        for a, b in spans:
            izhi[a:b] = izlo[a:b]
        _pyramids(izlo, izhi, views.size, offsets)
        self._parts["pyramids"] = (time.perf_counter() - t0) * 1e3
        return Depth(views, box, units, offsets, izlo, izhi)


@dataclass
class Depth:
    """A frame's occluders rasterized: per view, level 0 of ``izlo`` (from ``offsets[v, 0]``,
    row-major) holds per texel the reciprocal of the depth beyond which everything is hidden
    (0: nothing is); its levels above, the least of the level below (``izhi``: the largest).
    The buffers are the occluder's, drawn over by its next frame."""

    views: Views
    box: np.ndarray
    units: np.ndarray
    offsets: np.ndarray
    izlo: np.ndarray
    izhi: np.ndarray


def _canvas(texels: int = 0) -> dict:
    """:func:`_raster`'s arrays, kept from frame to frame: the patches (grown when a frame's
    occluders need more room), the cells gathered per texel of the buffers, and how the
    threads share the drawing."""
    return {"polys": np.empty((0, 4, 3)), "info": np.empty((0, 4), np.int64),
            "patches": np.empty((0, 3), np.int64), "boxes": np.empty((0, 5)),
            "work": np.zeros(texels, np.uint16), "low": np.empty(texels),
            "balance": workers.Balance()}


def _scratch(faces: int, vertices: int) -> tuple:
    """:func:`_setup`'s scratch for a mesh table of ``faces`` and ``vertices``: kept from frame
    to frame, its marks compared with stamps that only grow, so that a frame neither allocates
    nor clears it."""
    return np.zeros((2, faces), np.int64), np.zeros((2, vertices), np.int64), np.zeros(1, np.int64)


def _leaf_of(scene) -> np.ndarray:
    """Per node, the leaf whose mesh it draws: a cluster's leaf, else the node itself."""
    return np.where(scene.cluster_leaf >= 0, scene.cluster_leaf, np.arange(len(scene)))


def _occluding(scene, exclude: Sequence[str]) -> np.ndarray:
    """``(n,)`` uint8: 1 where a node may occlude; 0 under the nodes named in ``exclude``, and
    where its mesh's material may show what lies behind it (``MeshTable.see_through``)."""
    flag = np.ones(len(scene), np.uint8)
    template = scene.mesh_of[_leaf_of(scene)]
    if len(scene.meshes.see_through):  # (a scene of no mesh: nothing to see through)
        flag[(template >= 0) & scene.meshes.see_through[np.maximum(template, 0)]] = 0
    for name in exclude:
        node = scene.index.get(name)
        if node is None:
            raise InputError(f"occlusion exclude names no node {name!r}")
        flag[node:node + scene.size[node]] = 0
    return flag


def _solid(scene, box: np.ndarray, outward: np.ndarray) -> np.ndarray:
    """Per node: about the share of its box its faces fill, from 0 to 1 (0 for nodes without
    faces): their area over the box's, twice for an open mesh (seen from one side only, a
    closed one from two). A solid box fills its box, a cylinder about 0.8 of it, a grating of
    bars a third or less: the image it covers is its box's times this."""
    m = scene.meshes
    f = np.asarray(m.faces, np.int64)
    mesh = np.repeat(np.arange(len(m)), np.diff(m.face_start))
    p = np.asarray(m.vertices)[f + m.vertex_start[mesh][:, None]]
    area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1) / 2
    cum = np.concatenate([[0.0], np.cumsum(area)])
    first, count = scene.cluster_faces
    leaf = _leaf_of(scene)
    template = scene.mesh_of[leaf]
    out = np.zeros(len(scene))
    has = (template >= 0) & (count > 0)
    at = m.face_start[template[has]] + first[has]
    faces = cum[at + count[has]] - cum[at]  # in the template's units
    scale = np.abs(np.linalg.det(scene.world[leaf[has]][:, :3, :3])) ** (2 / 3)
    halves = np.linalg.norm(box[has, 4:13].reshape(-1, 3, 3), axis=2) + box[has, 3:4]
    surface = 8 * (halves[:, 0] * halves[:, 1] + halves[:, 1] * halves[:, 2]
                   + halves[:, 2] * halves[:, 0])
    sides = np.where(outward[template[has]] != 0, 1.0, 2.0)
    out[has] = np.minimum(1.0, sides * faces * scale / np.maximum(surface, 1e-300))
    return out


def _outward(meshes) -> np.ndarray:
    """Per mesh of the table: +1 (-1) when it is closed (every edge between two faces) and its
    faces wind counter-clockwise (clockwise) seen from outside (a positive (negative) volume);
    0 when it is not closed."""
    f = np.asarray(meshes.faces, np.int64)
    mesh = np.repeat(np.arange(len(meshes)), np.diff(meshes.face_start))
    p = np.asarray(meshes.vertices)[f + meshes.vertex_start[mesh][:, None]]
    volume = np.bincount(mesh, np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])),
                         len(meshes))
    size = np.zeros(len(meshes))
    np.maximum.at(size, mesh, np.abs(p).max(axis=(1, 2)))
    open_ = np.bincount(mesh, (meshes.face_neighbors < 0).any(axis=1), len(meshes)) > 0
    return np.where(open_ | (np.abs(volume) <= 1e-9 * size ** 3), 0,
                    np.sign(volume)).astype(np.int64)


def _levels(size: np.ndarray) -> tuple[np.ndarray, int, list]:
    """Offsets ``(V, L)`` of each view's pyramid levels in one flat array, its length, and
    each view's level 0 as ``(start, stop)``; level ``l`` of a ``W x H`` view is ``ceil(W /
    2^l) x ceil(H / 2^l)``, row-major."""
    levels = int(math.ceil(math.log2(max(int(size.max()), 1)))) + 1
    offsets = np.zeros((len(size), levels), np.int64)
    at = 0
    for v, (w, h) in enumerate(size):
        for l in range(levels):
            offsets[v, l] = at
            at += (-(-int(w) >> l) if l else int(w)) * (-(-int(h) >> l) if l else int(h))
    level0 = [(int(o), int(o) + int(w) * int(h)) for o, (w, h) in zip(offsets[:, 0], size)]
    return offsets, at, level0


@njit(cache=True, inline="always")
def _to_view(a, x, y, z):
    return (a[0, 0] * x + a[0, 1] * y + a[0, 2] * z + a[0, 3],
            a[1, 0] * x + a[1, 1] * y + a[1, 2] * z + a[1, 3],
            a[2, 0] * x + a[2, 1] * y + a[2, 2] * z + a[2, 3])


@njit(cache=True, inline="always")
def _angle(box, i, affine, views, near):
    """The largest angle node ``i``'s sphere spans in any of ``views`` (radians, about); one
    radian when it reaches through the near plane (its part beyond is cut out and occludes), 0
    when it lies wholly before it in every one."""
    best = 0.0
    for v in views:
        _, _, z = _to_view(affine[v], box[i, 0], box[i, 1], box[i, 2])
        d = -z - box[i, 13]
        if d > near:
            best = max(best, box[i, 13] / d)
        elif d + 2 * box[i, 13] > near:
            best = max(best, 1.0)
    return best


@njit(cache=True, inline="always")
def _image(box, i, affine, views, near):
    """About the solid angle node ``i``'s box covers in any of ``views``: each face's area
    times its slant to the eye, over the squared distance; one when it reaches through the
    near plane."""
    best = 0.0
    for v in views:
        a = affine[v]
        cx, cy, cz = _to_view(a, box[i, 0], box[i, 1], box[i, 2])
        dist = math.sqrt(cx * cx + cy * cy + cz * cz)
        d = -cz - box[i, 13]
        if not d > near:
            if d + 2 * box[i, 13] > near:
                best = max(best, 1.0)
            continue
        area = 0.0
        for k in range(3):  # the faces across h_k: area 4 |h_k+1| |h_k+2|, slanted
            p, q = 4 + 3 * ((k + 1) % 3), 4 + 3 * ((k + 2) % 3)
            nx = box[i, p + 1] * box[i, q + 2] - box[i, p + 2] * box[i, q + 1]
            ny = box[i, p + 2] * box[i, q] - box[i, p] * box[i, q + 2]
            nz = box[i, p] * box[i, q + 1] - box[i, p + 1] * box[i, q]
            m = math.sqrt(nx * nx + ny * ny + nz * nz)
            if m > 0:  # the normal in view coordinates, toward the centre
                vx = a[0, 0] * nx + a[0, 1] * ny + a[0, 2] * nz
                vy = a[1, 0] * nx + a[1, 1] * ny + a[1, 2] * nz
                vz = a[2, 0] * nx + a[2, 1] * ny + a[2, 2] * nz
                area += 4 * (m + box[i, 3] * (_length(box, i, (k + 1) % 3) + _length(box, i, (k + 2) % 3))) \
                    * abs(vx * cx + vy * cy + vz * cz) / (m * dist)
        best = max(best, area / (d * d))
    return best


@njit(cache=True, inline="always")
def _length(box, i, k):
    return math.sqrt(box[i, 4 + 3 * k] ** 2 + box[i, 5 + 3 * k] ** 2 + box[i, 6 + 3 * k] ** 2)


@njit(cache=True)
def _depths(units, box, affine):
    """Each node's nearest depth (its centre's, less its sphere's radius) over the views."""
    out = np.empty(units.shape[0])
    for q in range(units.shape[0]):
        i = units[q]
        d = np.inf
        for v in range(affine.shape[0]):
            _, _, z = _to_view(affine[v], box[i, 0], box[i, 1], box[i, 2])
            d = min(d, -z - box[i, 13])
        out[q] = d
    return out


@njit(cache=True)
def _pick(start, seeds, tile_view, box, child_start, child_count, children, solid, affine,
          near, stamp, frame, count, budget, per_triangle):
    """The units to rasterize: the childless nodes under ``seeds`` (each tile's, CSR
    ``start``) that may occlude (``stamp`` marks those seen this ``frame``), the best first
    within ``budget`` triangles. A unit's worth: the image its box covers (:func:`_image`),
    in the views of the tile it is found under (``tile_view[:, t]``: on a grid every tile's;
    a screen's own, where a node off to its side would seem larger than it is), times the
    share of the box its faces fill (``solid``; 0 where it must not occlude), per triangle
    when ``per_triangle``: a wall's two triangles before a pipe's forty, and a floor before a
    grating. Only nodes spanning at least a 500th of a radian are opened (what is smaller
    hides little). The order is by worth within a factor of 1.02 (buckets of its logarithm:
    linear time)."""
    stack = np.empty(64, np.int64)
    found = np.empty(seeds.shape[0] + 64, np.int64)
    worth = np.empty(found.shape[0])
    k = 0
    for tile in range(start.shape[0] - 1):
        views = tile_view[:, tile]
        for s in range(start[tile], start[tile + 1]):
            sp = 0
            stack[sp] = seeds[s]
            sp += 1
            while sp > 0:
                sp -= 1
                i = stack[sp]
                if stamp[i] == frame or not solid[i] > 0:
                    continue
                stamp[i] = frame
                if _angle(box, i, affine, views, near) < 0.002:
                    continue
                if child_count[i] == 0:
                    if k == found.shape[0]:
                        found = np.concatenate((found, np.empty(found.shape[0], np.int64)))
                        worth = np.concatenate((worth, np.empty(worth.shape[0])))
                    found[k] = i
                    worth[k] = solid[i] * _image(box, i, affine, views, near)
                    if per_triangle:
                        worth[k] /= max(count[i], 1)
                    k += 1
                    continue
                while sp + child_count[i] > stack.shape[0]:
                    stack = np.concatenate((stack, np.empty(stack.shape[0], np.int64)))
                for c in range(child_start[i], child_start[i] + child_count[i]):
                    stack[sp] = children[c]
                    sp += 1
    # buckets of log worth, the best first
    buckets = 1024
    top = -np.inf
    for q in range(k):
        if worth[q] > 0:
            top = max(top, math.log(worth[q]))
    bucket = np.empty(k, np.int64)
    load = np.zeros(buckets + 1, np.int64)
    for q in range(k):
        b = buckets
        if worth[q] > 0:
            b = min(buckets - 1, int((top - math.log(worth[q])) * 50.0))
        bucket[q] = b
        load[b] += count[found[q]]
    cut, total = 0, 0
    while cut < buckets and total + load[cut] <= budget:
        total += load[cut]
        cut += 1
    out = np.empty(k, np.int64)
    n = 0
    for q in range(k):  # the buckets before the cut, and the cut's first units that fit
        b = bucket[q]
        if b < cut or (b == cut and cut < buckets and total + count[found[q]] <= budget):
            if b == cut:
                total += count[found[q]]
            out[n] = found[q]
            n += 1
    return out[:n]


def _raster(units, owner, first, count, mesh_of, world, box, meshes, outward, single, affine,
            rect, size, near, buf, at, spans, scratch, canvas, threads):
    """Write the occluders ``units`` (leaf ``owner[u]``'s faces ``first[u]:first[u] +
    count[u]`` of the mesh table ``meshes``; a leaf's units next to each other, the nearest
    leaves first) into level 0 of each view's buffer ``buf`` (view ``v``'s texels from
    ``at[v]``, row-major; ``spans``: each view's level 0 as ``(start, stop)``),
    conservatively: their patches set up (:func:`_setup`) and drawn (:func:`_draw`). In
    ``threads`` threads: each sets up a run of whole leaves (of about equal triangles), and
    then draws every patch, in order, into its own run of rows (:func:`_bands`), so that the
    buffer is the one a single thread draws. ``outward``: see :func:`_outward`; ``single``:
    per mesh, whether it is single-sided (see :func:`_setup`); ``scratch``:
    per thread, see :func:`_scratch`; ``canvas``: see :func:`_canvas` (grown here). Returns
    how long the set-up and the drawing took (ms)."""
    t0 = time.perf_counter()
    cuts, before = _runs(units, owner, count, threads) if threads > 1 else \
        (np.array([0, len(units)]), np.array([0, count[units].sum()]))
    views = len(affine)
    room = int(before[-1]) * views  # polygons and patches: at most a face each per view
    if len(canvas["boxes"]) < room:
        for name, shape, dtype in (("polys", (4, 3), np.float64), ("info", (4,), np.int64),
                                   ("patches", (3,), np.int64), ("boxes", (5,), np.float64)):
            canvas[name] = np.empty((2 * room, *shape), dtype)
    polys, info, patches, boxes = (canvas[k] for k in ("polys", "info", "patches", "boxes"))

    def setup(k, a, b):  # units [a, b): their polygons and patches from their first face's
        start = int(before[k]) * views
        return start, *_setup(units[a:b], owner[a:b], first, count, mesh_of, world, box,
                              meshes.vertex_start, meshes.vertices, meshes.face_start,
                              meshes.faces, meshes.face_neighbors, outward, single, affine, rect,
                              size, near, *scratch[k], polys, info, patches, boxes, start)

    cuts = cuts.tolist()
    runs = workers.run(setup, list(zip(cuts[:-1], cuts[1:])))
    which = np.arange(runs[0][0], runs[0][2]) if threads == 1 else \
        np.concatenate([np.arange(start, end) for start, _, end in runs])
    work, low = canvas["work"], canvas["low"]
    for a, b in spans:  # (only level 0 is drawn and read)
        work[a:b] = 0
    t1 = time.perf_counter()
    if threads == 1:
        _draw(polys, info, patches, boxes, which, size, buf, at, work, low, 0, size[:, 1].sum())
        return (t1 - t0) * 1e3, (time.perf_counter() - t1) * 1e3
    # each thread's share of the rows' work as estimated, corrected by how long the threads
    # took the frame before (the estimate cannot know which rows nearer patches leave)
    balance = canvas["balance"]
    bounds = _bands(polys, info, patches, which, size, balance.of(threads))
    took = [0.0] * threads

    def draw(k, *_):
        t = time.perf_counter()
        _draw(polys, info, patches, boxes, which, size, buf, at, work, low, bounds[k],
              bounds[k + 1])
        took[k] = time.perf_counter() - t

    workers.run(draw, [(k, k + 1) for k in range(threads)])
    balance.took(took)
    return (t1 - t0) * 1e3, (time.perf_counter() - t1) * 1e3


@njit(cache=True)
def _runs(units, owner, count, parts):
    """``units`` (a leaf's next to each other) split into at most ``parts`` runs of whole
    leaves, of about equal triangles (``count[u]``): where each run starts (and the last
    ends), and the triangles before each."""
    total = 0
    for u in units:
        total += count[u]
    cuts = np.zeros(parts + 1, np.int64)
    before = np.zeros(parts + 1, np.int64)
    k, done = 1, 0
    for q in range(units.shape[0]):
        if k < parts and q > 0 and owner[q] != owner[q - 1] and done * parts >= total * k:
            cuts[k], before[k] = q, done
            k += 1
        done += count[units[q]]
    cuts[k], before[k] = units.shape[0], total
    return cuts[:k + 1], before[:k + 1]


@njit(cache=True)
def _bands(polys, info, patches, which, size, shares):
    """Where threads split the drawing of patches ``which`` (see :func:`_setup`): thread
    ``k`` draws rows ``[bounds[k], bounds[k + 1])`` of the views' rows counted one view after
    the other, ``shares[k]`` of the work (the rows the polygons span, each one more for its
    set-up)."""
    parts = shares.shape[0]
    views = size.shape[0]
    first = np.zeros(views + 1, np.int64)
    for v in range(views):
        first[v + 1] = first[v] + size[v, 1]
    step = np.zeros(first[views] + 1)  # per row, the change of the polygons spanning it
    for q in which:
        v = patches[q, 2]
        h = size[v, 1]
        for p in range(patches[q, 0], patches[q, 1]):
            lo, hi = np.inf, -np.inf
            for c in range(info[p, 0]):
                lo, hi = min(lo, polys[p, c, 1]), max(hi, polys[p, c, 1])
            a = first[v] + min(max(int(math.floor(max(lo, -1.0))), 0), h - 1)
            b = first[v] + min(max(int(math.floor(min(hi, h + 1.0))), 0), h - 1)
            step[a] += 2.0  # its set-up, and its first row
            step[a + 1] -= 1.0
            step[b + 1] -= 1.0
    bounds = np.empty(parts + 1, np.int64)
    bounds[0], bounds[parts] = 0, first[views]
    total = 0.0
    spanning = 0.0
    for j in range(first[views]):
        spanning += step[j]
        total += spanning
    k, done, spanning, goal = 1, 0.0, 0.0, total * shares[0]
    for j in range(first[views]):
        spanning += step[j]
        done += spanning
        while k < parts and done >= goal:
            bounds[k] = j + 1
            goal += total * shares[k]
            k += 1
    while k < parts:
        bounds[k] = first[views]
        k += 1
    return bounds


@njit(cache=True, inline="always")
def _in_view(box, i, a, rect, size, cut):
    """Whether node ``i``'s sphere reaches into the view of ``a`` (its rectangle ``rect``
    grown by two texels each way, beyond depth ``cut``)."""
    x, y, z = _to_view(a, box[i, 0], box[i, 1], box[i, 2])
    radius = box[i, 13]
    if -z + radius < cut:
        return False
    gx = 2.0 * (rect[1] - rect[0]) / size[0]
    gy = 2.0 * (rect[3] - rect[2]) / size[1]
    for k, sign in ((0, 1.0), (1, -1.0)):  # x >= x0 depth, x <= x1 depth; the same for y
        r = rect[k] - sign * gx
        if sign * (x + r * z) < -radius * math.sqrt(1.0 + r * r):
            return False
        r = rect[2 + k] - sign * gy
        if sign * (y + r * z) < -radius * math.sqrt(1.0 + r * r):
            return False
    return True


@njit(cache=True, inline="always")
def _clear_of_near(box, i, a, rect, cut):
    """Whether node ``i``'s box (packed: centre, ball, half-extent axes) lies farther from the
    eye of the view ``a`` than any point of its near rectangle (at depth ``cut``, across the
    tangents ``rect``): the eye is outside it and the near plane cuts nothing of it in view."""
    cx, cy, cz = _to_view(a, box[i, 0], box[i, 1], box[i, 2])
    gap = 0.0
    for k in range(4, 13, 3):  # the axes, each premultiplied by its half extent, in the view
        ax = a[0, 0] * box[i, k] + a[0, 1] * box[i, k + 1] + a[0, 2] * box[i, k + 2]
        ay = a[1, 0] * box[i, k] + a[1, 1] * box[i, k + 1] + a[1, 2] * box[i, k + 2]
        az = a[2, 0] * box[i, k] + a[2, 1] * box[i, k + 1] + a[2, 2] * box[i, k + 2]
        half = math.sqrt(ax * ax + ay * ay + az * az)
        if half > 0:
            out = abs(cx * ax + cy * ay + cz * az) / half - half  # the eye beyond this slab
            if out > 0:
                gap += out * out
    tx = max(abs(rect[0]), abs(rect[1]))
    ty = max(abs(rect[2]), abs(rect[3]))
    reach = cut * math.sqrt(1.0 + tx * tx + ty * ty) * (1 + 1e-9)
    return math.sqrt(gap) - box[i, 3] > reach


@njit(cache=True, nogil=True)
def _setup(units, owner, first, count, mesh_of, world, box, vertex_start, vertices, face_start,
           faces, neighbors, outward, single, affine, rect, size, near, face_marks, vertex_marks,
           stamps, polys, info, patches, boxes, start):
    """The *patches* of the occluders ``units`` in each view (see :func:`_raster`): a leaf's
    chosen faces that face the same way, joined across edges whose two faces lie on either
    side of the edge as seen from the eye. Every other edge of a patch (of one face only,
    between two faces folding over each other on the image, to a face not chosen or facing the
    other way) is part of its *outline*, and so are the cuts of the near plane through its
    faces (what lies nearer is never drawn: it does not occlude). ``neighbors``: per face of
    the mesh table, the face across each edge, -1 for none; ``outward``: per mesh, +1 (-1)
    when it is closed and its faces wind counter-clockwise (clockwise) seen from outside, 0
    when it is not closed: a closed mesh's back faces lie behind its front faces and are
    skipped where its box lies clear of the eye and the near plane (from inside it, or with
    the near plane through it, they are what is seen); ``single``: per mesh, whether it is a
    glTF mesh whose material is not ``doubleSided``, whose back faces are always skipped (a
    render node may cull them: from inside such a closed mesh wound outward nothing is
    drawn). Front faces wind counter-clockwise, clockwise under a mirroring placement (glTF's
    rule). The rest: scratch kept between frames (see :func:`_scratch`), marked with the
    ``stamps`` of leaves (updated).

    Writes from row ``start`` on (room for every face in every view) the patches' polygons
    ``polys (P, 4, 3)`` (each face's part beyond the near plane, or two whole faces across a
    side that make a convex quadrilateral: x, y in texels and 1 / depth per corner), per
    polygon ``info (P, 4)`` its corners, the sign of its area, which of its sides are outline
    (bits) and whether it is two faces (1 / depth affine on corners 0, 1, 2 and on 0, 2, 3;
    else on all), and per patch ``patches (Q, 3)`` its polygons' range and its view, and
    ``boxes (Q, 5)`` its image's box (x0, x1, y0, y1) and its most 1 / depth, all in the
    order they are to be drawn; returns where the polygons and the patches end. A leaf whose
    sphere (``box``, its packed bound) lies beyond a view's near plane or sides is not set up
    in that view (it could claim nothing there): a screens wall has a view per plane of
    screens, and a leaf is in a few of them."""
    views = affine.shape[0]
    mark, slot_of = face_marks[0], face_marks[1]  # per face: the last leaf, its slot there
    vmark, vslot = vertex_marks[0], vertex_marks[1]  # per vertex: the same
    stamp = stamps[0]
    np_ = nq = start
    cap = 64
    vlist = np.empty(3 * cap, np.int64)  # per vertex slot: the vertex
    vview = np.empty((3 * cap, 3))  # ... its view coordinates
    vimage = np.empty((3 * cap, 3))  # ... x, y (texels), 1 / depth; depth: its depth
    vdepth = np.empty(3 * cap)
    corner = np.empty((cap, 3), np.int64)  # per face slot: its vertices' slots
    poly = np.empty((cap, 4, 3))  # its part beyond the near plane: x, y (texels), 1 / depth
    label = np.empty((cap, 4), np.int64)  # the edge of the face each side lies on, 3: near
    sides = np.empty(cap, np.int64)  # how many corners
    facing = np.empty(cap, np.int64)  # +1: counter-clockwise on the image, -1, 0: skipped
    face_of = np.empty(cap, np.int64)
    inner = np.empty(cap, np.int64)  # which of its edges lie inside its patch (bits)
    done = np.empty(cap, np.bool_)
    paired = np.empty(cap, np.bool_)  # drawn as a polygon already, with another or alone
    queue = np.empty(cap, np.int64)
    quad = np.empty((4, 3))
    m_ = np.empty((3, 4))
    q = 0
    cut = near * (1 + NEAR_MARGIN)
    while q < units.shape[0]:
        leaf = owner[q]
        q1 = q
        n = 0
        while q1 < units.shape[0] and owner[q1] == leaf:
            n += count[units[q1]]
            q1 += 1
        if n > cap:
            cap = 2 * n
            vlist = np.empty(3 * cap, np.int64)
            vview = np.empty((3 * cap, 3))
            vimage = np.empty((3 * cap, 3))
            vdepth = np.empty(3 * cap)
            corner = np.empty((cap, 3), np.int64)
            poly = np.empty((cap, 4, 3))
            label = np.empty((cap, 4), np.int64)
            sides = np.empty(cap, np.int64)
            facing = np.empty(cap, np.int64)
            face_of = np.empty(cap, np.int64)
            inner = np.empty(cap, np.int64)
            done = np.empty(cap, np.bool_)
            paired = np.empty(cap, np.bool_)
            queue = np.empty(cap, np.int64)
        stamp += 1
        m = mesh_of[leaf]
        w = world[leaf]
        v0 = vertex_start[m]
        n = 0
        nv = 0
        for r in range(q, q1):
            f0 = face_start[m] + first[units[r]]
            for f in range(f0, f0 + count[units[r]]):
                mark[f] = stamp
                slot_of[f] = n
                face_of[n] = f
                for c in range(3):
                    x = v0 + faces[f, c]
                    if vmark[x] != stamp:
                        vmark[x] = stamp
                        vslot[x] = nv
                        vlist[nv] = x
                        nv += 1
                    corner[n, c] = vslot[x]
                n += 1
        # the front of a closed mesh: its winding outward, mirrored by a mirroring placement
        det = (w[0, 0] * (w[1, 1] * w[2, 2] - w[1, 2] * w[2, 1])
               - w[0, 1] * (w[1, 0] * w[2, 2] - w[1, 2] * w[2, 0])
               + w[0, 2] * (w[1, 0] * w[2, 1] - w[1, 1] * w[2, 0]))
        front = outward[m] * (1 if det > 0 else -1)
        # a single-sided mesh's front: counter-clockwise, mirrored by a mirroring placement
        sided = (1 if det > 0 else -1) if single[m] else 0
        for v in range(views):
            a = affine[v]
            if not _in_view(box, leaf, a, rect[v], size[v], cut):
                continue
            # From outside a closed mesh its front faces hide its back faces; from inside it,
            # or where the near plane cuts it, its back faces are what is seen.
            skip = front if front != 0 and _clear_of_near(box, leaf, a, rect[v], cut) else 0
            for r in range(3):  # world -> view, for this leaf
                for c in range(4):
                    m_[r, c] = a[r, 0] * w[0, c] + a[r, 1] * w[1, c] + a[r, 2] * w[2, c] \
                        + (a[r, 3] if c == 3 else 0.0)
            sx = size[v, 0] / (rect[v, 1] - rect[v, 0])
            sy = size[v, 1] / (rect[v, 3] - rect[v, 2])
            for x in range(nv):  # the vertices, once each
                p = vertices[vlist[x]]
                px = m_[0, 0] * p[0] + m_[0, 1] * p[1] + m_[0, 2] * p[2] + m_[0, 3]
                py = m_[1, 0] * p[0] + m_[1, 1] * p[1] + m_[1, 2] * p[2] + m_[1, 3]
                pz = m_[2, 0] * p[0] + m_[2, 1] * p[1] + m_[2, 2] * p[2] + m_[2, 3]
                vview[x, 0], vview[x, 1], vview[x, 2] = px, py, pz
                d = -pz
                vdepth[x] = d
                if d > cut:
                    vimage[x, 0] = (px / d - rect[v, 0]) * sx
                    vimage[x, 1] = (py / d - rect[v, 2]) * sy
                    vimage[x, 2] = 1.0 / d
            for s in range(n):
                facing[s] = 0
                c0, c1, c2 = corner[s, 0], corner[s, 1], corner[s, 2]
                # counter-clockwise seen from the eye (the origin): a negative triple product
                t3 = _triple(vview[c0], vview[c1], vview[c2])
                if skip != 0 and (t3 < 0) != (skip > 0):
                    continue  # a back face of a closed mesh seen from outside
                if sided != 0 and (t3 < 0) != (sided > 0):
                    continue  # a back face of a single-sided mesh: a render node may cull it
                if vdepth[c0] > cut and vdepth[c1] > cut and vdepth[c2] > cut:
                    for c in range(3):
                        x = corner[s, c]
                        poly[s, c, 0], poly[s, c, 1], poly[s, c, 2] = \
                            vimage[x, 0], vimage[x, 1], vimage[x, 2]
                        label[s, c] = c
                    sides[s] = 3
                else:
                    if _reaches(vview, corner[s], CUT_REACH * near):
                        continue
                    sides[s] = _clip_near(vview, corner[s], poly[s], label[s], cut, rect[v],
                                          sx, sy)
                    if sides[s] == 0:
                        continue
                area = _cross(poly[s, 0], poly[s, 1], poly[s, 2])
                if abs(area) > AREA_MIN and t3 * area < 0:
                    facing[s] = 1 if area > 0 else -1
            for s in range(n):  # which edges lie inside the outline (bits)
                inner[s] = 0
                if facing[s] != 0:
                    f = face_of[s]
                    for e in range(3):
                        g = neighbors[f, e]
                        if g >= 0 and mark[g] == stamp and facing[slot_of[g]] == facing[s] \
                                and _across(f, e, g, s, slot_of[g], faces, corner, vview):
                            inner[s] |= 1 << e
                done[s] = facing[s] == 0
            for s0 in range(n):  # each patch: the faces reached across inner edges
                if done[s0]:
                    continue
                done[s0] = True
                queue[0] = s0
                size_ = 1
                r = 0
                while r < size_:
                    s = queue[r]
                    r += 1
                    for e in range(3):
                        if inner[s] >> e & 1:
                            t = slot_of[neighbors[face_of[s], e]]
                            if not done[t]:
                                done[t] = True
                                queue[size_] = t
                                size_ += 1
                patches[nq, 0] = np_
                x0 = y0 = np.inf
                x1 = y1 = nearest = -np.inf
                for r in range(size_):
                    paired[queue[r]] = False
                for r in range(size_):
                    s = queue[r]
                    if paired[s]:
                        continue
                    paired[s] = True
                    ns = sides[s]
                    outline = 0
                    for e in range(ns):
                        lab = label[s, e]
                        if lab == 3 or not inner[s] >> lab & 1:
                            outline |= 1 << e
                    polys[np_, :ns] = poly[s, :ns]
                    split = 0
                    for e in range(3 if ns == 3 else 0):
                        # with the whole face across an inner side, if they make a convex
                        # quadrilateral (a wall's, a pipe's side): one polygon, two planes
                        t = slot_of[neighbors[face_of[s], e]] if inner[s] >> e & 1 else s
                        if paired[t] or sides[t] != 3:
                            continue
                        e1, e2 = (e + 1) % 3, (e + 2) % 3
                        for c in range(3):  # t's corners c, c + 1: s's e + 1, e
                            if corner[t, c] == corner[s, e1] and \
                                    corner[t, (c + 1) % 3] == corner[s, e]:
                                quad[0], quad[1] = poly[s, e], poly[t, (c + 2) % 3]
                                quad[2], quad[3] = poly[s, e1], poly[s, e2]
                                if _convex(quad, facing[s]):
                                    polys[np_] = quad
                                    outline = ((1 - (inner[t] >> (c + 1) % 3 & 1))
                                               | (1 - (inner[t] >> (c + 2) % 3 & 1)) << 1
                                               | (1 - (inner[s] >> e1 & 1)) << 2
                                               | (1 - (inner[s] >> e2 & 1)) << 3)
                                    paired[t] = True
                                    ns, split = 4, 1
                        if split:
                            break
                    for e in range(ns):
                        x0, x1 = min(x0, polys[np_, e, 0]), max(x1, polys[np_, e, 0])
                        y0, y1 = min(y0, polys[np_, e, 1]), max(y1, polys[np_, e, 1])
                        nearest = max(nearest, polys[np_, e, 2])
                    info[np_, 0], info[np_, 1], info[np_, 2], info[np_, 3] = \
                        ns, facing[s], outline, split
                    np_ += 1
                patches[nq, 1], patches[nq, 2] = np_, v
                boxes[nq, 0], boxes[nq, 1], boxes[nq, 2] = x0, x1, y0
                boxes[nq, 3], boxes[nq, 4] = y1, nearest
                nq += 1
        q = q1
    stamps[0] = stamp
    return np_, nq


#: Cells across a texel each way: a texel's cells are bits of a mask, a row of a patch's
#: cells bits of 64-bit words (``_PER_WORD`` texels a word).
SUB = 4
_PER_WORD = 64 // SUB
_FULL = np.uint64((1 << SUB * SUB) - 1)
_ONES = np.uint64(0xFFFFFFFFFFFFFFFF)
_ROW = np.uint64((1 << SUB) - 1)
#: Twice the least area (texels) of an occluder triangle on the image.
AREA_MIN = 1e-9
#: Occluders are cut this far (relative) beyond the near plane.
NEAR_MARGIN = 1e-4
#: A face the near plane cuts occludes nothing when a corner lies this many times the near
#: distance away (along any axis of the view): a render node clips it in float32, off by
#: about its corners' distance times 6e-8, which then passes the near plane (a 200 km ground
#: through a 1 mm near plane was drawn nowhere, and what it hid showed).
CUT_REACH = 1e5
#: The far vertex of a neighbour face counts as across an edge only this far (relative).
SIDE_MARGIN = 1e-9
#: Texels and cells count as touched by a line within this distance (texels): rounding
#: never claims one an outline crosses.
TOUCH = 1e-6


@njit(cache=True, nogil=True)
def _draw(polys, info, patches, boxes, which, size, buf, at, work, work_low, row_lo, row_hi):
    """Draw patches ``which`` (see :func:`_setup`) into each view's buffer ``buf``, in order, in
    rows ``[row_lo, row_hi)`` of the views' rows counted one view after the other (other
    threads draw the rest at the same time, see :func:`_bands`); ``work`` and ``work_low``
    (of ``buf``'s size, zero where drawn) gather cells claimed in part, and their least 1 /
    depth, until they fill a texel.

    A patch claims a texel whole when every one of its ``SUB x SUB`` cells is claimed: the
    cell's centre lies in one of the patch's faces, and no edge of the patch's outline touches
    the cell. Such a cell lies wholly inside the patch (the outline holds every edge of its
    border: an edge inside it has the patch on both sides, and so does a vertex all of whose
    edges are inside, its faces winding around it), and so does the texel. A texel claimed
    whole hides everything behind the patch's farthest depth over it (1 / depth is affine on
    each face: its least over the face's part in the texel is at a corner of that part's
    box): ``buf`` keeps the nearest such depth (its reciprocal). Cells claimed in part gather
    in ``work`` with the farthest depth of the patches that claimed them, until they fill the
    texel. A patch that is nowhere nearer than the buffer over its box, or whose box holds no
    whole cell, is skipped (it could claim nothing: its depth would be no nearer)."""
    first = np.zeros(size.shape[0], np.int64)  # each view's first row, counted through all
    for v in range(1, size.shape[0]):
        first[v] = first[v - 1] + size[v - 1, 1]
    rows = cols = 16
    cover = np.empty((SUB * rows, cols // _PER_WORD + 1), np.uint64)  # cells faces' centres cover
    edge = np.empty((SUB * rows, cols // _PER_WORD + 1), np.uint64)  # cells the outline touches
    low = np.empty((rows, cols))  # the patch's least 1 / depth per texel
    live = np.empty((rows, 2), np.int64)  # per row, the texels where it may claim
    ed = np.empty((14, 4))
    for q in which:
        v = patches[q, 2]
        w, h = size[v, 0], size[v, 1]
        x0, x1, y0, y1, nearest = boxes[q, 0], boxes[q, 1], boxes[q, 2], boxes[q, 3], boxes[q, 4]
        # no whole cell in its box within the view (a vertex near the eye's plane may
        # project far beyond)
        cx0, cx1 = max(x0, -1.0), min(x1, w + 1.0)
        cy0, cy1 = max(y0, -1.0), min(y1, h + 1.0)
        if math.ceil(cx0 * SUB) + 1 > math.floor(cx1 * SUB) or \
                math.ceil(cy0 * SUB) + 1 > math.floor(cy1 * SUB):
            continue
        r0, r1 = max(0, int(math.floor(cy0 - TOUCH))), min(h - 1, int(math.floor(cy1 + TOUCH)))
        c0, c1 = max(0, int(math.floor(cx0 - TOUCH))), min(w - 1, int(math.floor(cx1 + TOUCH)))
        if r0 > r1 or c0 > c1:
            continue
        # per row, the texels between the first and the last where it may be nearer than
        # the buffer (elsewhere it claims nothing, and nothing there is drawn)
        if r1 - r0 + 1 > live.shape[0]:
            live = np.empty((2 * (r1 - r0 + 1), 2), np.int64)
        first_row, last_row = r1 + 1, r0 - 1
        for j in range(r0, r1 + 1):
            row = at[v] + j * w
            a, b = c0, c1
            if not row_lo <= first[v] + j < row_hi:  # another thread's row
                a = c1 + 1
            while a <= c1 and not buf[row + a] < nearest:
                a += 1
            while b > a and not buf[row + b] < nearest:
                b -= 1
            live[j - r0, 0], live[j - r0, 1] = a, b
            if a <= b:
                first_row, last_row = min(first_row, j), j
        if first_row > last_row:
            continue
        live_ = live[first_row - r0:]
        r0, r1 = first_row, last_row
        nr, nc = r1 - r0 + 1, c1 - c0 + 1
        words = nc // _PER_WORD + 1
        if nr > rows or nc > cols:
            rows, cols = max(rows, nr), max(cols, nc)
            cover = np.empty((SUB * rows, cols // _PER_WORD + 1), np.uint64)
            edge = np.empty((SUB * rows, cols // _PER_WORD + 1), np.uint64)
            low = np.empty((rows, cols))
        cover[:SUB * nr, :words] = 0
        edge[:SUB * nr, :words] = 0
        low[:nr, :nc] = np.inf
        for p in range(patches[q, 0], patches[q, 1]):
            _cover(polys[p], info[p, 0], info[p, 1], info[p, 3], r0, r1, c0, live_, cover, low,
                   ed)
        for p in range(patches[q, 0], patches[q, 1]):
            ns, outline = info[p, 0], info[p, 2]
            for e in range(ns):
                if outline >> e & 1:
                    e1 = e + 1 if e + 1 < ns else 0
                    _edge(polys[p, e, 0], polys[p, e, 1], polys[p, e1, 0], polys[p, e1, 1], r0,
                          r1, c0, live_, edge)
        _claim(cover, edge, low, r0, nr, c0, live_, at[v] + c0, w, buf, work, work_low)


@njit(cache=True, inline="always")
def _bits(row, lo, hi):
    """Set bits ``lo`` to ``hi`` (inclusive) of the words ``row``."""
    a, b = lo >> 6, hi >> 6
    if a == b:
        row[a] |= (_ONES >> np.uint64(63 - (hi - lo))) << np.uint64(lo & 63)
        return
    row[a] |= _ONES << np.uint64(lo & 63)
    for k in range(a + 1, b):
        row[k] = _ONES
    row[b] |= _ONES >> np.uint64(63 - (hi & 63))


@njit(cache=True, inline="always")
def _cover(p, ns, side, split, r0, r1, c0, live, cover, low, ed):
    """Convex polygon ``p[:ns]`` (x, y texels, 1 / depth per corner; ``side``: the sign of its
    area; ``split``: two faces, see :func:`_setup`) into its patch's texels of rows ``[r0,
    r1]`` (``cover``'s and ``low``'s first, from column ``c0``), within each row's ``live``
    columns: every texel it touches (or nearly) takes the least 1 / depth of the polygon over
    the texel into ``low``, and the cells whose centres lie inside it are set in ``cover``.
    ``ed (14, 4)``: scratch."""
    y_lo, y_hi = np.inf, -np.inf
    for c in range(ns):
        y_lo, y_hi = min(y_lo, p[c, 1]), max(y_hi, p[c, 1])
    j0 = max(r0, int(math.floor(y_lo - TOUCH)))
    j1 = min(r1, int(math.floor(y_hi + TOUCH)))
    while j0 <= j1 and live[j0 - r0, 0] > live[j0 - r0, 1]:
        j0 += 1
    while j1 >= j0 and live[j1 - r0, 0] > live[j1 - r0, 1]:
        j1 -= 1
    if j0 > j1:
        return  # no row of it may claim
    # 1 / depth as a plane over the image: ga x + gb y + gc (affine: exact for a perspective);
    # two faces: each one's plane, the least of the two a bound over both
    ga, gb, gc = _plane(p[0], p[1], p[2])
    ga2, gb2, gc2 = _plane(p[0], p[2], p[3]) if split else (ga, gb, gc)
    least = np.inf
    for c in range(ns):
        least = min(least, p[c, 2])
    # each side: inside where side (ex (y - ay) - ey (x - ax)) >= 0 (a centre on an edge the
    # outline holds is in a cell the outline touches, by a margin: rounding claims nothing
    # there, and one on an inner edge is in both faces); as a bound on x, x >= q y + o (the
    # left sides, ``ed[0:2, :nl]``) or x <= q y + o (the right ones, ``ed[2:4, :nr]``), or
    # on y alone (the level ones, where q y + o >= 0: ``ed[4:6, :nv]``); and each side from
    # its lower end up, for the rows' extent: x, y, the other end's y and x, dx / dy
    # (``ed[6:11]``); and per cell row of a texel row, its y and x bounds (``ed[11:14]``)
    nl = nr = nv = 0
    ys, xls, xrs = ed[11], ed[12], ed[13]
    for e in range(ns):
        e1 = e + 1 if e + 1 < ns else 0
        ax, ay = p[e, 0], p[e, 1]
        ex, ey = p[e1, 0] - ax, p[e1, 1] - ay
        A = -side * ey
        B = side * ex
        C = side * (ey * ax - ex * ay)
        if A > 0:
            ed[0, nl], ed[1, nl] = -B / A, -C / A
            nl += 1
        elif A < 0:
            ed[2, nr], ed[3, nr] = -B / A, -C / A
            nr += 1
        else:
            ed[4, nv], ed[5, nv] = B, C
            nv += 1
        if ey >= 0:
            ed[6, e], ed[7, e], ed[8, e], ed[9, e] = ax, ay, p[e1, 1], p[e1, 0]
        else:
            ed[6, e], ed[7, e], ed[8, e], ed[9, e] = p[e1, 0], p[e1, 1], ay, ax
        ed[10, e] = ex / ey if ey != 0 else 0.0
    for J in range(j0, j1 + 1):
        r = J - r0
        g0, g1 = live[r, 0], live[r, 1]
        if g0 > g1:
            continue
        y0, y1 = max(J - TOUCH, y_lo), min(J + 1 + TOUCH, y_hi)  # the polygon's rows in it
        lo, hi = np.inf, -np.inf
        for e in range(ns):
            ax, ay, by = ed[6, e], ed[7, e], ed[8, e]
            if by < y0 or ay > y1:
                continue
            if by > ay:
                x0 = ax + ed[10, e] * (max(y0, ay) - ay)
                x1 = ax + ed[10, e] * (min(y1, by) - ay)
            else:
                x0, x1 = ax, ed[9, e]
            lo, hi = min(lo, x0, x1), max(hi, x0, x1)
        if not lo <= hi:
            continue
        i0 = max(g0, int(math.floor(max(lo, g0 - 1.0) - TOUCH)))
        i1 = min(g1, int(math.floor(min(hi, g1 + 1.0) + TOUCH)))
        if i0 > i1:
            continue
        # the least over the polygon's part in each texel, within its box there
        _least(low[r], i0, i1, c0, lo, hi, least, ga, min(gb * y0, gb * y1) + gc)
        if split:
            _least(low[r], i0, i1, c0, lo, hi, least, ga2, min(gb2 * y0, gb2 * y1) + gc2)
        # the cells whose centres on each of the texel row's cell rows lie inside (the
        # SUB cell rows side by side: the same sums, row by row)
        for k in range(SUB):
            ys[k] = J + (k + 0.5) / SUB
            xls[k], xrs[k] = -1e9, 1e9
        for e in range(nl):
            for k in range(SUB):
                xls[k] = max(xls[k], ed[0, e] * ys[k] + ed[1, e])
        for e in range(nr):
            for k in range(SUB):
                xrs[k] = min(xrs[k], ed[2, e] * ys[k] + ed[3, e])
        for e in range(nv):
            for k in range(SUB):
                if ed[4, e] * ys[k] + ed[5, e] < 0:
                    xrs[k] = -2e9
        for k in range(SUB):
            xl, xr = xls[k], xrs[k]
            if xl <= xr:
                a = max(int(math.ceil(xl * SUB - 0.5)), SUB * i0)
                b = min(int(math.floor(xr * SUB - 0.5)), SUB * i1 + SUB - 1)
                if a <= b:
                    _bits(cover[SUB * r + k], a - SUB * c0, b - SUB * c0)


@njit(cache=True, inline="always")
def _plane(a, b, c):
    """The plane through ``a, b, c`` (x, y, 1 / depth): ``ga, gb, gc`` with 1 / depth = ga x +
    gb y + gc."""
    area = _cross(a, b, c)
    ga = ((b[2] - a[2]) * (c[1] - a[1]) - (c[2] - a[2]) * (b[1] - a[1])) / area
    gb = ((b[0] - a[0]) * (c[2] - a[2]) - (c[0] - a[0]) * (b[2] - a[2])) / area
    return ga, gb, a[2] - ga * a[0] - gb * a[1]


@njit(cache=True, inline="always")
def _least(out, i0, i1, c0, lo, hi, least, ga, gy):
    """Lower ``out[i - c0]`` for texels ``i0`` to ``i1`` of a row to the least of plane ``ga x
    + gy`` over ``[max(i, lo), min(i + 1, hi)]``, and no less than ``least``."""
    if ga >= 0:
        for i in range(i0, i1 + 1):
            out[i - c0] = min(out[i - c0], max(least, ga * max(i, lo) + gy))
    else:
        for i in range(i0, i1 + 1):
            out[i - c0] = min(out[i - c0], max(least, ga * min(i + 1, hi) + gy))


@njit(cache=True, inline="always")
def _edge(ax, ay, bx, by, r0, r1, c0, live, edge):
    """Set in ``edge`` the cells of rows ``[r0, r1]`` (its first, from column ``c0``), within
    each row's ``live`` columns, that segment ``a b`` (texel coordinates) touches, or
    nearly."""
    if ay > by:
        ax, ay, bx, by = bx, by, ax, ay
    dy = by - ay
    slope = (bx - ax) / dy if dy > 0 else 0.0
    for J in range(max(r0, int(math.floor(max(ay - TOUCH, r0 - 1.0)))),
                   min(r1, int(math.floor(min(by + TOUCH, r1 + 1.0)))) + 1):
        g0, g1 = live[J - r0, 0], live[J - r0, 1]
        if g0 > g1:
            continue
        for k in range(SUB):  # the cell rows of this texel row
            y0 = J + k / SUB
            if y0 > by + TOUCH or y0 + 1.0 / SUB < ay - TOUCH:
                continue
            lo, hi = _along(ax, ay, bx, by, slope, y0 - TOUCH, y0 + 1.0 / SUB + TOUCH)
            a = max(SUB * g0, int(math.floor((max(lo, g0 - 1.0) - TOUCH) * SUB)))
            b = min(SUB * g1 + SUB - 1, int(math.floor((min(hi, g1 + 1.0) + TOUCH) * SUB)))
            if a <= b:
                _bits(edge[SUB * (J - r0) + k], a - SUB * c0, b - SUB * c0)


@njit(cache=True, inline="always")
def _claim(cover, edge, low, r0, nr, c0, live, at, w, buf, work, work_low):
    """A patch's claims (see :func:`_draw`) from its cells (``cover`` and not ``edge``) and
    depths ``low`` over its ``nr`` rows from ``r0`` (from column ``c0``), within each row's
    ``live`` columns; ``at``: the buffer's index of texel ``(c0, 0)``."""
    for r in range(nr):
        row = at + (r0 + r) * w
        g0, g1 = live[r, 0] - c0, live[r, 1] - c0
        if g0 > g1:
            continue
        for word in range(g0 // _PER_WORD, g1 // _PER_WORD + 1):
            any_ = np.uint64(0)
            every = _ONES
            for k in range(SUB):
                cells = cover[SUB * r + k, word] & ~edge[SUB * r + k, word]
                any_ |= cells
                every &= cells
            if any_ == 0:
                continue
            first = _PER_WORD * word
            if every == _ONES:  # every cell of the word's texels: each claimed whole
                for i in range(max(g0, first), min(first + _PER_WORD, g1 + 1)):
                    if low[r, i] > buf[row + i]:
                        buf[row + i] = low[r, i]
                continue
            for n in range(max(0, g0 - first), min(_PER_WORD, g1 + 1 - first)):
                shift = np.uint64(SUB * n)
                if any_ >> shift & _ROW == 0:
                    continue  # nothing
                i = first + n
                t = row + i
                z = low[r, i]
                if not z > buf[t]:
                    continue  # nothing nearer
                if every >> shift & _ROW == _ROW:  # every cell
                    buf[t] = z
                    continue
                claimed = np.uint64(0)
                for k in range(SUB):
                    claimed |= ((cover[SUB * r + k, word] & ~edge[SUB * r + k, word]) >> shift
                                & _ROW) << np.uint64(SUB * k)
                work_low[t] = min(work_low[t], z) if work[t] else z
                work[t] |= claimed
                if work[t] == _FULL:
                    if work_low[t] > buf[t]:
                        buf[t] = work_low[t]
                    work[t] = 0


@njit(cache=True, inline="always")
def _cross(a, b, c):
    """Twice the signed area of ``a, b, c`` on the image (their x, y)."""
    return (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1])


@njit(cache=True, inline="always")
def _convex(q, side):
    """Whether quadrilateral ``q`` (x, y) turns the way of ``side`` (+1: counter-clockwise) at
    each corner, by a margin."""
    for k in range(4):
        if not side * _cross(q[k - 1], q[k], q[(k + 1) % 4]) > AREA_MIN:
            return False
    return True


@njit(cache=True, inline="always")
def _triple(a, b, c):
    """``a . (b x c)``."""
    return (a[0] * (b[1] * c[2] - b[2] * c[1]) + a[1] * (b[2] * c[0] - b[0] * c[2])
            + a[2] * (b[0] * c[1] - b[1] * c[0]))


@njit(cache=True, inline="always")
def _across(f, e, g, s, t, faces, corner, vview):
    """Whether face ``g`` (slot ``t``) lies on the other side of edge ``e`` of face ``f``
    (slot ``s``) than ``f`` does, as seen from the eye: either side of the plane through the
    eye and the edge, by a margin (so the two lie either side of the edge on the image)."""
    a_, b_ = faces[f, e], faces[f, (e + 1) % 3]
    for c in range(3):
        x = faces[g, c]
        if x != a_ and x != b_:
            p = vview[corner[s, e]]
            q = vview[corner[s, (e + 1) % 3]]
            far = vview[corner[t, c]]
            own = _triple(p, q, vview[corner[s, (e + 2) % 3]])
            other = _triple(p, q, far)
            scale = ((abs(p[0]) + abs(p[1]) + abs(p[2])) * (abs(q[0]) + abs(q[1]) + abs(q[2]))
                     * (abs(far[0]) + abs(far[1]) + abs(far[2])))
            return own * other < 0 and abs(other) > SIDE_MARGIN * scale
    return False


@njit(cache=True, inline="always")
def _reaches(vview, corners, reach):
    """Whether a corner of a face lies ``reach`` or farther along an axis of the view."""
    for c in range(3):
        p = vview[corners[c]]
        if max(abs(p[0]), abs(p[1]), abs(p[2])) >= reach:
            return True
    return False


@njit(cache=True, inline="always")
def _clip_near(vview, corners, out, label, cut, rect, sx, sy):
    """The part of the triangle of vertices ``vview[corners]`` (view coordinates) at depths
    beyond ``cut``, projected into ``out`` (x, y in texels, 1 / depth per corner, in order),
    each side's edge of the triangle in ``label`` (``e``: from corner ``e`` to ``e + 1``; 3:
    along the cut). Returns how many corners (0, 3 or 4)."""
    k = 0
    for e in range(3):
        p, q = vview[corners[e]], vview[corners[(e + 1) % 3]]
        dp, dq = -p[2], -q[2]
        if dp > cut:
            _put(out, k, p[0], p[1], dp, rect, sx, sy)
            label[k] = e
            k += 1
            if not dq > cut:  # leaves: the next side runs along the cut
                t = (dp - cut) / (dp - dq)
                _put(out, k, p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]), cut, rect,
                     sx, sy)
                label[k] = 3
                k += 1
        elif dq > cut:  # enters: the next side runs along edge e
            t = (cut - dp) / (dq - dp)
            _put(out, k, p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]), cut, rect, sx, sy)
            label[k] = e
            k += 1
    return k


@njit(cache=True, inline="always")
def _put(out, k, x, y, d, rect, sx, sy):
    out[k, 0] = (x / d - rect[0]) * sx
    out[k, 1] = (y / d - rect[2]) * sy
    out[k, 2] = 1.0 / d


@njit(cache=True, inline="always")
def _along(ax, ay, bx, by, slope, y0, y1):
    """The x extent of segment ``a b`` (``ay <= by``; ``slope``: dx / dy, or 0 when level)
    within the rows ``y0`` to ``y1``."""
    if by > ay:
        x0 = ax + slope * (min(max(y0, ay), by) - ay)
        x1 = ax + slope * (min(max(y1, ay), by) - ay)
        return min(x0, x1), max(x0, x1)
    return min(ax, bx), max(ax, bx)


@njit(cache=True)
def _pyramids(lo_, hi_, size, offsets):
    """Levels 1 and up of each view: the smallest (``lo_``) and largest (``hi_``) of the level
    below's 2 x 2 texels (a border texel of fewer)."""
    for v in range(size.shape[0]):
        w, h = size[v, 0], size[v, 1]
        for l in range(1, offsets.shape[1]):
            cw, ch = -(-w // 2), -(-h // 2)
            src, dst = offsets[v, l - 1], offsets[v, l]
            for j in range(h // 2):  # whole 2 x 2 blocks
                a, b = src + 2 * j * w, dst + j * cw
                for i in range(w // 2):
                    lo_[b + i] = min(min(lo_[a + 2 * i], lo_[a + 2 * i + 1]),
                                     min(lo_[a + w + 2 * i], lo_[a + w + 2 * i + 1]))
                    hi_[b + i] = max(max(hi_[a + 2 * i], hi_[a + 2 * i + 1]),
                                     max(hi_[a + w + 2 * i], hi_[a + w + 2 * i + 1]))
            if w % 2:  # a last column of fewer
                for j in range(ch):
                    _reduce(lo_, hi_, src, dst, w, h, cw, cw - 1, j)
            if h % 2:  # a last row
                for i in range(cw):
                    _reduce(lo_, hi_, src, dst, w, h, cw, i, ch - 1)
            w, h = cw, ch


@njit(cache=True, inline="always")
def _reduce(lo_, hi_, src, dst, w, h, cw, i, j):
    """Texel ``(i, j)`` of a level from the texels of the level below it covers (a border
    texel covers fewer than four)."""
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


@njit(cache=True, inline="always")
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


#: The texel test reads blocks of 2^BLOCK x 2^BLOCK texels first (pyramid level BLOCK).
BLOCK = 2
#: What a node's projection says of it over a whole view (:func:`_project`): hidden wherever
#: it is; not hidden anywhere, nor any part of it; reaching the eye (never hidden, its
#: children may be); or to be tested tile by tile.
_HIDDEN, _CLEAR, _NEAR, _TEST = 0, 1, 2, 3
#: A node's record per eye (:func:`_project`): its rectangle (texels, unclipped), nearest and
#: farthest depth, centre and half vectors (view coordinates); once a texel test needs them,
#: the planes of its front faces (ready 1) and its outline's corners (ready 2, texels); room
#: for the outline's working (its corners in order of x, and its chains).
_R_RECT, _R_NEAR, _R_FAR, _R_CENTRE, _R_HALF, _R_READY, _R_HULL, _R_ORDER, _R_CORNERS, \
    _R_FACES, _R_PLANES, _R_WORK, _R_SIZE = 0, 4, 5, 6, 9, 18, 19, 35, 43, 44, 45, 54, 78


@njit(cache=True, nogil=True)
def _prune(start, nodes, first_tile, box, child_start, child_count, children, affine, rect,
           size, tile_view, tile_texels, near, izlo, izhi, offsets, slot, stamp, rec):
    """Each tile's nodes (CSR ``(start, nodes)``, the first tile ``first_tile``) without the
    hidden ones, partly hidden ones replaced by their children (recursively): CSR ``(start,
    nodes)`` in preorder, how many nodes were dropped, and the records. A node is projected
    once per frame and view (``slot (nodes, 3)``: the frame's ``stamp``, its record in
    ``rec`` and its first eye's view; both kept between frames, ``rec`` grown when full)."""
    tiles = start.shape[0] - 1
    eyes = tile_view.shape[0]
    out = np.empty(nodes.shape[0] + 1024, np.int64)
    out_start = np.zeros(tiles + 1, np.int64)
    stack = np.empty(1024, np.int64)
    cap = rec.shape[0]
    verdict = np.empty(cap, np.int64)
    half = np.empty((3, 3))
    step = DEPTH_STEPS / near
    seen = 0
    k = 0
    hidden = 0
    for tile in range(tiles):
        t = first_tile + tile
        sp = 0
        for j in range(start[tile + 1] - 1, start[tile] - 1, -1):
            if sp == stack.shape[0]:
                stack = np.concatenate((stack, np.empty(stack.shape[0], np.int64)))
            stack[sp] = nodes[j]
            sp += 1
        while sp > 0:
            sp -= 1
            i = stack[sp]
            if child_count[i] == 0 and _centre_shows(box, i, affine, rect, size, tile_view,
                                                      tile_texels, t, near, step, izlo,
                                                      offsets):
                state = _CLEAR
            elif slot[i, 0] != stamp or slot[i, 2] != tile_view[0, t]:
                if seen == cap:
                    cap *= 2
                    rec2 = np.empty((cap, eyes, _R_SIZE))
                    rec2[:seen] = rec[:seen]
                    rec = rec2
                    verdict = np.concatenate((verdict, np.empty(seen, np.int64)))
                slot[i, 0], slot[i, 1], slot[i, 2] = stamp, seen, tile_view[0, t]
                verdict[seen] = _project(box, i, affine, rect, size, near, step, izlo, izhi,
                                         offsets, tile_view[:, t], rec[seen], half)
                seen += 1
                state = verdict[slot[i, 1]]
            else:
                state = verdict[slot[i, 1]]
            if state == _TEST:
                state = _judge(rec[slot[i, 1]], rect, size, tile_view, tile_texels, t, step,
                               izlo, izhi, offsets)
            if state == _HIDDEN:
                hidden += 1
                continue
            if state != _CLEAR and child_count[i] > 0:
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
        out_start[tile + 1] = k
    return out_start, out[:k], hidden, rec


@njit(cache=True, inline="always")
def _centre_shows(box, i, affine, rect, size, tile_view, tile_texels, t, near, step, izlo,
                  offsets):
    """Whether node ``i``'s centre lies in tile ``t`` (a texel of it) from some eye, with
    nothing nearer there in the buffer: then neither it nor any part of it can be hidden
    there, and projecting it is not needed."""
    for e in range(tile_view.shape[0]):
        v = tile_view[e, t]
        x, y, z = _to_view(affine[v], box[i, 0], box[i, 1], box[i, 2])
        d = -z
        if not d > near:
            continue
        w = size[v, 0]
        fi = (x / d - rect[v, 0]) * w / (rect[v, 1] - rect[v, 0])
        fj = (y / d - rect[v, 2]) * size[v, 1] / (rect[v, 3] - rect[v, 2])
        if tile_texels[e, t, 0] <= fi < tile_texels[e, t, 1] and \
                tile_texels[e, t, 2] <= fj < tile_texels[e, t, 3]:
            if not _behind(d, izlo[offsets[v, 0] + int(fj) * w + int(fi)], step):
                return True
    return False


@njit(cache=True, inline="always")
def _project(box, i, affine, rect, size, near, step, izlo, izhi, offsets, views, rec, half):
    """Node ``i``'s bound in each eye's view (``views[e]``), into ``rec[e]`` (see
    ``_R_...``), and what that says of it over the whole view (``_HIDDEN`` ...). Its bound:
    its box grown by its ball (the half vectors lengthened by the ball)."""
    ball = box[i, 3]
    for k in range(3):
        hx, hy, hz = box[i, 4 + 3 * k], box[i, 5 + 3 * k], box[i, 6 + 3 * k]
        n = math.sqrt(hx * hx + hy * hy + hz * hz)
        if n > 0:
            g = 1.0 + ball / n
            half[k, 0], half[k, 1], half[k, 2] = hx * g, hy * g, hz * g
        else:  # no extent along this axis: the ball along the world's
            half[k, 0] = half[k, 1] = half[k, 2] = 0.0
            half[k, k] = ball
    hidden = clear = True
    for e in range(views.shape[0]):
        v = views[e]
        a = affine[v]
        re = rec[e]
        cx, cy, cz = _to_view(a, box[i, 0], box[i, 1], box[i, 2])
        re[_R_CENTRE], re[_R_CENTRE + 1], re[_R_CENTRE + 2] = cx, cy, cz
        for k in range(3):
            for r in range(3):
                re[_R_HALF + 3 * k + r] = a[r, 0] * half[k, 0] + a[r, 1] * half[k, 1] \
                    + a[r, 2] * half[k, 2]
        lo_x = lo_y = np.inf
        hi_x = hi_y = -np.inf
        d_near = np.inf
        d_far = 0.0
        for c in range(8):
            x, y, d = _corner(re, c)
            if not d > near:
                return _NEAR
            d_near = min(d_near, d)
            d_far = max(d_far, d)
            lo_x, hi_x = min(lo_x, x / d), max(hi_x, x / d)
            lo_y, hi_y = min(lo_y, y / d), max(hi_y, y / d)
        w, h = size[v, 0], size[v, 1]
        sx = w / (rect[v, 1] - rect[v, 0])
        sy = h / (rect[v, 3] - rect[v, 2])
        re[_R_RECT] = (lo_x - rect[v, 0]) * sx
        re[_R_RECT + 1] = (hi_x - rect[v, 0]) * sx
        re[_R_RECT + 2] = (lo_y - rect[v, 2]) * sy
        re[_R_RECT + 3] = (hi_y - rect[v, 2]) * sy
        re[_R_NEAR], re[_R_FAR] = d_near, d_far
        re[_R_READY] = 0.0
        i0, i1, j0, j1 = _clip(re, 0, w, 0, h)
        if i1 <= i0 or j1 <= j0:
            continue  # not in this view
        if not _behind(d_near, _extreme(izlo, offsets, v, w, h, i0, i1, j0, j1, False), step):
            hidden = False
        if _behind(d_far, _extreme(izhi, offsets, v, w, h, i0, i1, j0, j1, True), step):
            clear = False
    if hidden:
        return _HIDDEN
    return _CLEAR if clear else _TEST


@njit(cache=True, inline="always")
def _hides(iz, bound, step):
    """Whether an occluder at ``1 / iz`` hides what lies at ``1 / bound`` or beyond, by the
    margins (``DEPTH_MARGIN``, and ``step``: ``DEPTH_STEPS`` over the wall's near)."""
    return iz > (1 + DEPTH_MARGIN) * bound + step


@njit(cache=True, inline="always")
def _behind(d, iz, step):
    """:func:`_hides` for what lies at depth ``d`` (> 0) or beyond."""
    return d * iz > 1 + DEPTH_MARGIN + d * step


@njit(cache=True, inline="always")
def _corner(re, c):
    """Corner ``c`` of a node's box: view x, y and depth."""
    s0 = 1.0 if c & 1 else -1.0
    s1 = 1.0 if c & 2 else -1.0
    s2 = 1.0 if c & 4 else -1.0
    h = _R_HALF
    x = re[_R_CENTRE] + s0 * re[h] + s1 * re[h + 3] + s2 * re[h + 6]
    y = re[_R_CENTRE + 1] + s0 * re[h + 1] + s1 * re[h + 4] + s2 * re[h + 7]
    d = -(re[_R_CENTRE + 2] + s0 * re[h + 2] + s1 * re[h + 5] + s2 * re[h + 8])
    return x, y, d


@njit(cache=True, inline="always")
def _clip(re, i0, i1, j0, j1):
    """A node's rectangle's texels within ``[i0, i1) x [j0, j1)``."""
    return (max(i0, int(math.floor(re[_R_RECT]))), min(i1, int(math.ceil(re[_R_RECT + 1]))),
            max(j0, int(math.floor(re[_R_RECT + 2]))), min(j1, int(math.ceil(re[_R_RECT + 3]))))


@njit(cache=True, inline="always")
def _judge(rec, rect, size, tile_view, tile_texels, t, step, izlo, izhi, offsets):
    """``_HIDDEN``: the node of record ``rec`` (see :func:`_project`) is hidden in tile ``t``
    from every eye; ``_CLEAR``: it is not, and no part of it can be; else ``_TEST``: a part of
    it might be."""
    hidden = True
    partly = False
    for e in range(tile_view.shape[0]):
        v = tile_view[e, t]
        re = rec[e]
        w, h = size[v, 0], size[v, 1]
        i0, i1, j0, j1 = _clip(re, tile_texels[e, t, 0], tile_texels[e, t, 1],
                               tile_texels[e, t, 2], tile_texels[e, t, 3])
        if i1 <= i0 or j1 <= j0:
            continue  # nothing of it in this tile from this eye
        # hidden beyond 1 / iz: over every texel (the smallest iz), or over some (the largest);
        # as over the whole view (:func:`_project`) when all of it lies in this tile
        if (i0, i1, j0, j1) != _clip(re, 0, w, 0, h):
            if _behind(re[_R_NEAR], _extreme(izlo, offsets, v, w, h, i0, i1, j0, j1, False),
                       step):
                continue
            if not _behind(re[_R_FAR], _extreme(izhi, offsets, v, w, h, i0, i1, j0, j1, True),
                           step):
                hidden = False  # nowhere hidden
                continue
        partly = True
        # texel by texel: those its outline touches, at its nearest depth there
        if hidden and not _texels_hidden(re, rect[v], w, h, i0, i1, j0, j1, step, izlo,
                                         offsets[v]):
            hidden = False
    if hidden:
        return _HIDDEN
    return _TEST if partly else _CLEAR


@njit(cache=True, inline="always")
def _outline_of(re, rect, w, h):
    """A node's outline on the image, into its record: the convex hull of its box's eight
    corners (Andrew's monotone chain), counter-clockwise, in texel coordinates. A flat box
    (a wall's, a floor's, any planar mesh's) has corners in pairs a rounding apart, along
    which a cross product's sign is noise: gift wrapping then walked to wrong corners and the
    outline left most of the box out (whole walls judged hidden behind nothing). Here a near
    twin is popped as not turning left, and its twin, as far out, stays. Should rounding still
    give an outline of more than eight corners, it is one point, which rules nothing out."""
    sx = w / (rect[1] - rect[0])
    sy = h / (rect[3] - rect[2])
    hull = _R_HULL
    for c in range(8):
        x, y, d = _corner(re, c)
        re[hull + 2 * c] = (x / d - rect[0]) * sx
        re[hull + 2 * c + 1] = (y / d - rect[2]) * sy
    order, chain = _R_WORK, _R_WORK + 8  # the corners by x, then y; the chains (16 at most)
    for c in range(8):
        m = c
        while m > 0:
            o = int(re[order + m - 1])
            if re[hull + 2 * o] < re[hull + 2 * c] or (
                    re[hull + 2 * o] == re[hull + 2 * c]
                    and re[hull + 2 * o + 1] <= re[hull + 2 * c + 1]):
                break
            re[order + m] = o
            m -= 1
        re[order + m] = c
    n = 0
    for upper in range(2):  # the lower chain left to right, then the upper right to left
        first = n
        for q in range(8):
            k = int(re[order + 7 - q]) if upper else int(re[order + q])
            kx, ky = re[hull + 2 * k], re[hull + 2 * k + 1]
            while n >= first + 2:
                o, a = int(re[chain + n - 2]), int(re[chain + n - 1])
                ox, oy = re[hull + 2 * o], re[hull + 2 * o + 1]
                if (re[hull + 2 * a] - ox) * (ky - oy) - (re[hull + 2 * a + 1] - oy) * (kx - ox) \
                        > 0:
                    break
                n -= 1
            re[chain + n] = k
            n += 1
        n -= 1  # each chain's last corner is the other's first
    if not 1 <= n <= 8:
        n = 1
    for e in range(n):
        re[_R_ORDER + e] = re[chain + e]
    re[_R_CORNERS] = n
    re[_R_READY] = 2.0


@njit(cache=True, inline="always")
def _planes_of(re, rect, w, h):
    """The planes of a node's box's faces toward the eye, into its record: per face, 1 / depth
    on its plane as ``a x + b y + c`` over texel coordinates."""
    sx = w / (rect[1] - rect[0])
    sy = h / (rect[3] - rect[2])
    cx, cy, cz = re[_R_CENTRE], re[_R_CENTRE + 1], re[_R_CENTRE + 2]
    faces = 0
    for k in range(3):
        a, b = _R_HALF + 3 * ((k + 1) % 3), _R_HALF + 3 * ((k + 2) % 3)
        nx = re[a + 1] * re[b + 2] - re[a + 2] * re[b + 1]
        ny = re[a + 2] * re[b] - re[a] * re[b + 2]
        nz = re[a] * re[b + 1] - re[a + 1] * re[b]
        hk = _R_HALF + 3 * k
        dot = nx * re[hk] + ny * re[hk + 1] + nz * re[hk + 2]
        if dot < 0:
            nx, ny, nz, dot = -nx, -ny, -nz, -dot
        central = nx * cx + ny * cy + nz * cz
        for sign in (1.0, -1.0):  # the face at c + sign h_k, its outward normal sign n
            q = sign * central + dot
            if dot > 0 and q < 0:
                at = _R_PLANES + 3 * faces
                re[at] = sign * nx / (sx * q)
                re[at + 1] = sign * ny / (sy * q)
                re[at + 2] = sign * (nx * rect[0] + ny * rect[2] - nz) / q
                faces += 1
    re[_R_FACES] = faces
    re[_R_READY] = 1.0


@njit(cache=True, inline="always")
def _bound(re, i, j, s):
    """The most 1 / depth a node's box has over the ``s x s`` texels from ``(i, j)``: a ray
    entering the box crosses the plane of every face that faces the eye, so the box lies no
    nearer there than the farthest of those planes over the texels (1 / depth is affine on
    the image: at a corner), nor nearer than its nearest corner; at most 0 where none of it
    is."""
    bound = 1.0 / re[_R_NEAR]
    for f in range(int(re[_R_FACES])):
        ga, gb = re[_R_PLANES + 3 * f], re[_R_PLANES + 3 * f + 1]
        bound = min(bound, ga * i + max(ga, 0.0) * s + gb * j + max(gb, 0.0) * s
                    + re[_R_PLANES + 3 * f + 2])
    return bound


@njit(cache=True, inline="always")
def _texels_hidden(re, rect, w, h, i0, i1, j0, j1, step, izlo, offsets):
    """Whether the node of record ``re`` lies behind ``izlo`` over every texel of ``[i0, i1) x
    [j0, j1)`` that its outline touches, at its depth there (:func:`_bound`). The texel of its
    centre first (its outline always touches it); then blocks of texels, read at a level of
    the pyramid (its least over the block), and texel by texel only in those where that does
    not settle it and that its outline reaches; a block or a texel is out of its outline when
    all four of its corners lie outside one of the outline's edges."""
    if re[_R_READY] == 0.0:
        _planes_of(re, rect, w, h)
    at = offsets[0]
    sx = w / (rect[1] - rect[0])
    sy = h / (rect[3] - rect[2])
    d = -re[_R_CENTRE + 2]
    ic = int(math.floor((re[_R_CENTRE] / d - rect[0]) * sx))
    jc = int(math.floor((re[_R_CENTRE + 1] / d - rect[2]) * sy))
    if i0 <= ic < i1 and j0 <= jc < j1:
        bound = _bound(re, ic, jc, 1)
        if bound > 0 and not _hides(izlo[at + jc * w + ic], bound, step):
            return False
    l = min(BLOCK, offsets.shape[0] - 1)
    s = 1 << l
    wl = -(-w // s)
    for J in range(j0 >> l, ((j1 - 1) >> l) + 1):
        for I in range(i0 >> l, ((i1 - 1) >> l) + 1):
            if _hides(izlo[offsets[l] + J * wl + I], _bound(re, I * s, J * s, s), step):
                continue  # hidden over the whole block
            if re[_R_READY] == 1.0:
                _outline_of(re, rect, w, h)
            xa, xb, ya, yb = max(i0, I * s), min(i1, I * s + s), max(j0, J * s), min(j1, J * s + s)
            if _beyond(re, xa, ya, xb, yb):
                continue  # the block is out of its outline
            for j in range(ya, yb):
                for i in range(xa, xb):
                    if _touches(re, i, j, izlo[at + j * w + i], step):
                        return False
    return True


@njit(cache=True, inline="always")
def _touches(re, i, j, iz, step):
    """Whether the node of record ``re`` (its outline ready) may show in texel ``(i, j)``
    before ``1 / iz``: some of it is there, nearer, and its outline touches the texel."""
    bound = _bound(re, i, j, 1)
    if not bound > 0 or _hides(iz, bound, step):
        return False  # hidden there, or none of it there
    return not _beyond(re, i, j, i + 1.0, j + 1.0)


@njit(cache=True, inline="always")
def _beyond(re, x0, y0, x1, y1):
    """Whether the rectangle ``[x0, x1] x [y0, y1]`` (texel coordinates) lies wholly outside
    an edge of the outline of the node of record ``re`` (ready): its corner most inside is
    outside."""
    n = int(re[_R_CORNERS])
    hull = _R_HULL
    for e in range(n):
        a = int(re[_R_ORDER + e])
        b = int(re[_R_ORDER + (e + 1) % n])
        ax, ay = re[hull + 2 * a], re[hull + 2 * a + 1]
        ex, ey = re[hull + 2 * b] - ax, re[hull + 2 * b + 1] - ay
        if ex * ((y1 if ex > 0 else y0) - ay) - ey * ((x1 if ey < 0 else x0) - ax) < 0:
            return True
    return False
