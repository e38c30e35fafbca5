"""What a render node draws: triangles per frame, summed over a wall's tiles, against the floor.

``wallcull overdraw`` walks a camera path and, for every frame, counts the triangles the tiles
draw four ways:

* **none**: no culling, every tile draws the whole scene;
* **leaves**: each tile draws every triangle of every leaf in its list (clusters off);
* **clusters** (one count per cluster size): each tile draws its whole leaves and the triangle
  ranges of its partial leaves (:mod:`wallcull.clusters`), and, when asked, the same with
  occlusion culling (:mod:`wallcull.occlude`);
* **floor**: the triangles not wholly outside the tile's frustum, clipped exactly: what any
  frustum culling must draw at least;
* **visible** (when asked, it costs): the triangles with at least one pixel in the tile's id
  buffer, drawn by the software rasterizer of :mod:`wallcull.raster` with the tile's fitted
  view and projection at a reduced resolution: what even an exact occlusion culling must draw.

It also counts draw calls (a whole leaf is one, a partial leaf one per range) and times the
cull. The floor is counted by one compiled kernel (:func:`_floor`) over the triangles the
leaf-level lists draw, a superset of it because the culler is conservative (the tests hold
it to the exact oracle of :mod:`wallcull.oracle`, and this kernel to the oracle's clipping).
The visible floor rasterizes the same leaf-level lists: every triangle a tile may show, and
every triangle that may hide one, is among them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from . import raster
from .cull import Visibility
from .fit import FitOptions, Fits
from .occlude import OcclusionOptions
from .pipeline import Session
from .scene import Scene
from .wall import Frame, Frusta, Wall


@dataclass
class Counts:
    """One cluster setting's numbers over a path: per frame, summed over the tiles."""

    triangles: list[int] = field(default_factory=list)
    calls: list[int] = field(default_factory=list)
    cull_ms: list[float] = field(default_factory=list)
    occlude_ms: list[float] = field(default_factory=list)

    def add(self, vis: Visibility, timings: dict) -> None:
        self.triangles.append(int(vis.triangles().sum()))
        self.calls.append(int(vis.draw_calls().sum()))
        self.cull_ms.append(timings["cull_ms"])
        self.occlude_ms.append(timings.get("occlude_ms", 0.0))


@dataclass
class Report:
    """A path's overdraw: ``settings`` maps ``(cluster size, occlusion)`` (size None: the
    leaf-level lists) to its :class:`Counts`; ``floor``, ``visible`` (when measured, at
    ``resolution``: each tile's ``(width, height)``) and ``none`` are per frame."""

    scene: str
    triangles: int
    tiles: int
    frames: int
    floor: list[int] = field(default_factory=list)
    settings: dict = field(default_factory=dict)
    visible: list[int] | None = None
    resolution: np.ndarray | None = None

    @property
    def none(self) -> int:
        return self.triangles * self.tiles

    def summary(self) -> dict:
        """Means per frame; ratios to the floor (and the visible floor, when measured) of
        sums over the path (a frame that sees nothing weighs nothing)."""
        floor = float(np.sum(self.floor))
        over = _ratio(floor)
        out = {"scene": self.scene, "triangles": self.triangles, "tiles": self.tiles,
               "frames": self.frames, "floor": floor / self.frames, "none": self.none,
               "none_over_floor": over(self.none * self.frames), "settings": []}
        if self.visible is not None:
            visible = float(np.sum(self.visible))
            over_visible = _ratio(visible)
            out.update(visible=visible / self.frames,
                       visible_resolution=_resolution_text(self.resolution),
                       none_over_visible=over_visible(self.none * self.frames),
                       floor_over_visible=over_visible(floor))
        for (size, occluded), c in self.settings.items():
            entry = {"clusters": "off" if size is None else size, "occlusion": occluded,
                     "triangles": float(np.mean(c.triangles)),
                     "over_floor": over(np.sum(c.triangles)),
                     "draw_calls": float(np.mean(c.calls)),
                     "cull_ms_median": float(np.median(c.cull_ms))}
            if occluded:
                entry["occlude_ms_median"] = float(np.median(c.occlude_ms))
            if self.visible is not None:
                entry["over_visible"] = over_visible(np.sum(c.triangles))
            out["settings"].append(entry)
        return out


def _ratio(denominator: float):
    return (lambda total: total / denominator) if denominator else (lambda total: float("nan"))


def _resolution_text(resolution: np.ndarray) -> str:
    """``240x135``, or the distinct sizes of a wall whose tiles differ, comma-separated."""
    sizes = dict.fromkeys(f"{w}x{h}" for w, h in resolution.tolist())
    return ",".join(sizes)


def measure(scenes: dict, wall: Wall, frames: list[Frame], method: str = "adaptive",
            bounds: str = "obb", progress=None, occlusion: bool = False,
            resolution: np.ndarray | None = None) -> Report:
    """Walk ``frames`` with each of ``scenes`` (cluster size -> the scene loaded with it; None
    must be among them: the leaf-level lists, which the floors are counted over), each also
    with occlusion culling on every frame when ``occlusion``. With ``resolution`` (``(tiles,
    2)`` pixels), the visible floor too."""
    base: Scene = scenes[None]
    tiles = wall.tiles
    keys = [(size, occluded) for size in scenes for occluded in (False, True)[:1 + occlusion]]
    report = Report(base.name, int(base.stats["triangles"]), tiles, len(frames),
                    settings={key: Counts() for key in keys})
    sessions = {(size, occluded): Session(scenes[size], wall, method, bounds,
                                          occlusion=OcclusionOptions() if occluded else None)
                for size, occluded in keys}
    if resolution is not None:  # the leaf-level session also fits: the tiles' matrices
        sessions[None, False].fit_options = FitOptions()
        report.visible, report.resolution = [], resolution
        first = raster.first_ids(base)
    for s in sessions.values():
        s.frame(frames[0])  # compiles the kernels before anything is timed
    for frame in frames:
        results = {key: session.frame(frame) for key, session in sessions.items()}
        for key, result in results.items():
            report.settings[key].add(result.visibility, result.timings)
        plain = results[None, False]
        report.floor.append(int(floor(base, plain.frusta, plain.visibility).sum()))
        if resolution is not None:
            report.visible.append(int(visible(base, plain.fits, plain.visibility, resolution,
                                              first).sum()))
        if progress is not None:
            progress()
    return report


def floor(scene: Scene, frusta: Frusta, vis: Visibility) -> np.ndarray:
    """``(tiles,)`` triangles of the leaves ``vis`` lists that are not wholly outside each
    tile's frustum (whole leaves: the candidates must include every triangle that is in)."""
    start, leaves = vis.leaf_lists()
    m = scene.meshes
    return _floor(frusta.tile_rows, frusta.planes, start, leaves, scene.mesh_of, scene.world,
                  m.vertex_start, m.vertices, m.face_start, m.faces)


@njit(cache=True)
def _floor(tile_rows, planes, start, leaves, mesh_of, world, vertex_start, vertices, face_start,
           faces):
    tiles = tile_rows.shape[0]
    out = np.zeros(tiles, np.int64)
    p = np.empty((6, 4))
    tri = np.empty((3, 3))
    for t in range(tiles):
        for k in range(6):
            p[k] = planes[tile_rows[t, k]]
        for j in range(start[t], start[t + 1]):
            leaf = leaves[j]
            m = mesh_of[leaf]
            w = world[leaf]
            v0 = vertex_start[m]
            for f in range(face_start[m], face_start[m + 1]):
                for c in range(3):
                    v = vertices[v0 + faces[f, c]]
                    for r in range(3):
                        tri[c, r] = w[r, 0] * v[0] + w[r, 1] * v[1] + w[r, 2] * v[2] + w[r, 3]
                if triangle_meets(tri, p):
                    out[t] += 1
    return out


@njit(cache=True)
def triangle_meets(tri, planes) -> bool:
    """Whether triangle ``(3, 3)`` meets the convex region ``planes (k, 4)`` (``n . x + d >=
    0`` inside), exactly up to rounding: a vertex inside every plane says yes, all three outside
    one plane says no, and what is left is clipped (Sutherland-Hodgman)."""
    k = planes.shape[0]
    d = np.empty((3, k))
    for c in range(3):
        inside = True
        for q in range(k):
            d[c, q] = (planes[q, 0] * tri[c, 0] + planes[q, 1] * tri[c, 1]
                       + planes[q, 2] * tri[c, 2] + planes[q, 3])
            inside = inside and d[c, q] >= 0
        if inside:
            return True
    for q in range(k):
        if d[0, q] < 0 and d[1, q] < 0 and d[2, q] < 0:
            return False
    cap = 3 + k
    poly = np.empty((cap, 3))
    nxt = np.empty((cap, 3))
    poly[:3] = tri
    n = 3
    for q in range(k):
        a, b, c, e = planes[q, 0], planes[q, 1], planes[q, 2], planes[q, 3]
        m = 0
        for i in range(n):
            j = (i + 1) % n
            di = a * poly[i, 0] + b * poly[i, 1] + c * poly[i, 2] + e
            dj = a * poly[j, 0] + b * poly[j, 1] + c * poly[j, 2] + e
            if di >= 0:
                nxt[m] = poly[i]
                m += 1
            if (di >= 0) != (dj >= 0) and m < cap:
                s = di / (di - dj)
                for r in range(3):
                    nxt[m, r] = poly[i, r] + s * (poly[j, r] - poly[i, r])
                m += 1
        n = min(m, cap)
        if n == 0:
            return False
        poly[:n] = nxt[:n]
    return True


def visible(scene: Scene, fits: Fits, vis: Visibility, resolution: np.ndarray,
            first: np.ndarray | None = None) -> np.ndarray:
    """``(tiles,)`` distinct triangles in each tile's id buffer: the leaves ``vis`` lists,
    rasterized with the tile's fitted view and projection at ``resolution[t]`` pixels
    (``first``: :func:`wallcull.raster.first_ids` of ``scene``, if at hand)."""
    start, leaves = vis.leaf_lists()
    first = raster.first_ids(scene) if first is None else first
    out = np.zeros(len(start) - 1, np.int64)
    for t in range(len(out)):
        view = fits.view if fits.view.ndim == 2 else fits.view[t]
        ids = raster.render(scene, leaves[start[t]:start[t + 1]], view, fits.projection[t],
                            *resolution[t], first).ids
        out[t] = _distinct(ids.ravel())
    return out


@njit(cache=True)
def _distinct(ids) -> int:
    """How many different ids other than 0 (the background)."""
    s = np.sort(ids)
    n = 0
    for i in range(len(s)):
        if s[i] != 0 and (i == 0 or s[i] != s[i - 1]):
            n += 1
    return n


#: The visible floor's default resolution is each tile's divided by this.
RESOLUTION_DIVISOR = 8


def default_resolution(wall: Wall) -> np.ndarray:
    """The visible floor's default pixels per tile: each tile's resolution over
    :data:`RESOLUTION_DIVISOR`, rounded up (240 x 135 for 1920 x 1080 tiles)."""
    return -(-wall.resolutions // RESOLUTION_DIVISOR)


def run(spec: str, wall: Wall, path: str = "orbit", frames: int = 60,
        sizes=(None,), method: str = "adaptive", bounds: str = "obb",
        hierarchy: str = "auto", branching: int = 8, progress=None,
        occlusion: bool = False, resolution: np.ndarray | None = None) -> Report:
    """``wallcull overdraw``: the scene ``spec`` loaded with each cluster size of ``sizes``
    (None, clusters off, always among them), walked along ``path``; the visible floor too
    with ``resolution`` (``(tiles, 2)`` pixels)."""
    from .paths import scene_path
    from .scene import load

    loaded = [load(spec, hierarchy, branching, clusters=size)
              for size in dict.fromkeys((None, *sizes))]
    # by the size each scene has: "auto" is reported as the size it chose, once
    scenes = {scene.cluster_size: scene for scene in loaded}
    return measure(scenes, wall, scene_path(scenes[None], wall, path, frames), method, bounds,
                   progress, occlusion, resolution)
