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
  plane is pulled in to the nearest caster. It comes with the shadow casters culled against it.
  A light that the tile's visible set surrounds gets a cube map instead: six 90 degree faces.
* ``mirrors`` (only if the scene declares mirrors): per mirror the eye can see, the reflected
  view (det -1: the client flips its front faces), the tile's projection with Lengyel's oblique
  near plane at the mirror, and the leaves culled against the reflected frustum (bounded by the
  mirror's outline when it has one).

Lists are leaf ids, as in packets. A scene without lights or mirrors never reaches the code
for them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from . import settings as cfg
from .cull import Visibility, cull_region
from .lowilie import FitError, fit_frustum
from .projection import (ClipPlaneError, frustum_planes, look_at, oblique_near, rigid_inverse,
                         view_matrix)
from .scene import SceneState
from .wall import Frame, Frusta, Wall

#: Depth ranges are widened by this fraction of their far distance, so that rounding in the
#: client's float32 matrices never clips a surface lying exactly on a fitted plane.
DEPTH_MARGIN = 1e-6


@dataclass(frozen=True)
class FitOptions:
    depth: str = "tight"  # "tight": fitted to the visible bounds; "wall": the wall's near/far
    reversed_z: bool = False
    refine: bool = True  # refine Low-Ilie quadrilaterals beyond the paper's greedy ones

    def __post_init__(self):
        if self.depth not in ("tight", "wall"):
            raise ValueError(f"depth must be 'tight' or 'wall', got {self.depth!r}")


def tile_projections(wall: Wall, frame: Frame, near: np.ndarray, far: np.ndarray,
                     reversed_z: bool = False) -> np.ndarray:
    """``(tiles, 4, 4)`` off-axis projections through each tile rectangle with per-tile near
    and far distances: Lengyel's frustum matrix, vectorized; reversed-Z maps near to 1, far to
    0. A far distance of ``inf`` gives the infinite projection."""
    ex, ey, ez = frame.eye
    depth = wall.distance + ez
    r, c = np.divmod(np.arange(wall.tiles), wall.cols)
    x0, x1 = wall.col_edges[c, 0] - ex, wall.col_edges[c, 1] - ex
    y0, y1 = wall.row_edges[r, 0] - ey, wall.row_edges[r, 1] - ey
    # 2n/(r-l) with l = x0 n / depth: the near distance cancels out of the x and y rows.
    out = np.zeros((wall.tiles, 4, 4))
    out[:, 0, 0] = 2 * depth / (x1 - x0)
    out[:, 0, 2] = (x1 + x0) / (x1 - x0)
    out[:, 1, 1] = 2 * depth / (y1 - y0)
    out[:, 1, 2] = (y1 + y0) / (y1 - y0)
    out[:, 3, 2] = -1.0
    near, far = np.broadcast_to(near, wall.tiles), np.broadcast_to(far, wall.tiles)
    finite = np.isfinite(far)  # an infinite far plane takes the limit (Lengyel eq. 5.53)
    f, n = np.where(finite, far, 2.0), near
    if reversed_z:
        out[:, 2, 2] = np.where(finite, n / (f - n), 0.0)
        out[:, 2, 3] = np.where(finite, n * f / (f - n), n)
    else:
        out[:, 2, 2] = np.where(finite, -(f + n) / (f - n), -1.0)
        out[:, 2, 3] = np.where(finite, -2 * f * n / (f - n), -2 * n)
    return out


def depth_ranges(state: SceneState, wall: Wall, frame: Frame,
                 visibility: Visibility) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile ``(near, far)``: the eye-space depths the tile's listed bounds span, clamped to
    the wall's. A tile that shows nothing keeps the wall's range."""
    b = state.bounds
    forward = -frame.rotation[:, 2]  # the view direction in the world
    nodes = visibility.nodes
    rel = b.center[nodes] - frame.to_world(frame.eye)
    center = rel @ forward
    reach = b.reach(nodes, forward)
    near = np.full(wall.tiles, wall.near)
    far = np.full(wall.tiles, wall.far)
    counts = np.diff(visibility.start)
    full = counts > 0
    if full.any():
        starts = visibility.start[:-1][full]
        lo = np.minimum.reduceat(center - reach, starts)
        hi = np.maximum.reduceat(center + reach, starts)
        margin = DEPTH_MARGIN * np.abs(hi) + np.finfo(float).eps * np.abs(center).max()
        near[full] = np.clip(lo - margin, wall.near, wall.far)
        far[full] = np.clip(hi + margin, wall.near, wall.far)
        far = np.maximum(far, near * (1 + 1e-9) + 1e-300)  # a flat range still has two planes
    return near, far


@dataclass
class Fits(Sequence):
    """One frame's fitted frusta: arrays, read as a sequence of per-tile JSON-ready dicts
    (``fits[t]``: ``view``, ``projection``, ``near``, ``far`` and any ``shadows``/``mirrors``).
    Kept as arrays, a 64 x 64 wall's frame takes half a megabyte, not ten."""

    view: np.ndarray  # (4, 4), shared by every tile
    projection: np.ndarray  # (tiles, 4, 4)
    near: np.ndarray  # (tiles,)
    far: np.ndarray  # (tiles,)
    extras: dict = field(default_factory=dict)  # tile -> {"shadows": [...], "mirrors": [...]}

    def __len__(self) -> int:
        return len(self.projection)

    def __getitem__(self, tile: int) -> dict:
        if not 0 <= tile < len(self):
            raise IndexError(tile)
        return {"view": self.view_rows, "projection": self.projection[tile].tolist(),
                "near": float(self.near[tile]), "far": float(self.far[tile]),
                **self.extras.get(tile, {})}

    @cached_property
    def view_rows(self) -> list:
        return self.view.tolist()


def fit_frame(wall: Wall, frame: Frame, visibility: Visibility | None = None,
              state: SceneState | None = None, scene_settings: cfg.Settings | None = None,
              options: FitOptions = FitOptions()) -> Fits:
    """One frame's fitted frusta (see the module docstring)."""
    view = view_matrix(frame)
    if options.depth == "tight" and visibility is not None:
        near, far = depth_ranges(state, wall, frame, visibility)
    else:
        near, far = np.full(wall.tiles, wall.near), np.full(wall.tiles, wall.far)
    projections = tile_projections(wall, frame, near, far, options.reversed_z)
    out = Fits(view, projections, near, far)
    if scene_settings is None or scene_settings.empty or visibility is None:
        return out  # nothing declared: nothing computed, nothing sent
    for light in scene_settings.lights:
        for t in range(wall.tiles):
            shadow = shadow_frustum(state, light, visibility.tile_nodes(t), options)
            if shadow is not None:
                out.extras.setdefault(t, {}).setdefault("shadows", []).append(shadow)
    frusta = Frusta.build(wall, frame) if scene_settings.mirrors else None
    for mirror in scene_settings.mirrors:
        seen_from = MirrorSight.of(mirror, frame, view)
        if seen_from is None:
            continue  # the eye is behind the mirror (or on it): no tile sees anything in it
        for t in range(wall.tiles):
            seen = seen_from.tile(state, frusta.tile(t), projections[t])
            if seen is not None:
                out.extras.setdefault(t, {}).setdefault("mirrors", []).append(seen)
    return out


# --------------------------------------------------------------------------- shadows


def _leaves(state: SceneState, nodes: np.ndarray) -> list[int]:
    return np.unique(state.scene.subtree_leaves(nodes)).tolist()


def shadow_frustum(state: SceneState, light: cfg.Light, receivers: np.ndarray,
                   options: FitOptions) -> dict | None:
    """The light's frustum for one tile: fitted around the bounds of what the tile shows (the
    shadow receivers), with the casters that can shade them. None when the tile shows nothing
    the light reaches."""
    if not len(receivers):
        return None
    corners = state.bounds.take(receivers).world_corners().reshape(-1, 3)
    if light.kind == "spot" and not cfg.spot_contains(light, corners).any() and \
            not ((state.bounds.center[receivers] - light.position) @ light.direction > 0).any():
        return None  # every receiver lies behind the spot light: nothing there is lit
    width, height = light.resolution
    try:
        fit = fit_frustum(light.position, corners, width, height, refine=options.refine)
    except FitError:
        return cube_shadow(state, light, corners)
    view, projection = fit.view, fit.projection.copy()
    # Casters anywhere between the light and the receivers shade them: keep the side planes
    # and the far plane, drop the near one, then pull the near plane in to the nearest caster.
    planes = frustum_planes(projection @ view)[[0, 1, 2, 3, 5]]
    casters = cull_region(state, planes)
    near = _nearest_depth(state, casters, view, fit.far)
    far = fit.far
    projection[2, 2] = -(far + near) / (far - near)
    projection[2, 3] = -2 * far * near / (far - near)
    return {"light": light.name, "view": view.tolist(), "projection": projection.tolist(),
            "near": near, "far": far, "coverage": float(fit.coverage),
            "casters": _leaves(state, casters)}


def _nearest_depth(state: SceneState, nodes: np.ndarray, view: np.ndarray, far: float) -> float:
    """The smallest eye-space depth of the nodes' bounds, kept a sliver above zero."""
    b = state.bounds
    forward = -view[2, :3]
    depth = (b.center[nodes] @ forward + (-view[2, 3]))
    reach = b.reach(nodes, forward)
    nearest = float((depth - reach).min()) if len(nodes) else far * 0.5
    return max(nearest * (1 - 1e-6), far * 1e-6)


def cube_shadow(state: SceneState, light: cfg.Light, corners: np.ndarray) -> dict:
    """The six 90-degree faces of a cube map around a light its receivers surround."""
    far = float(np.linalg.norm(corners - light.position, axis=1).max()) * (1 + 1e-6)
    near = far * 1e-4
    projection = np.zeros((4, 4))
    projection[0, 0] = projection[1, 1] = 1.0
    projection[2, 2] = -(far + near) / (far - near)
    projection[2, 3] = -2 * far * near / (far - near)
    projection[3, 2] = -1.0
    # OpenGL cube-map face order: +x, -x, +y, -y, +z, -z, with the usual up vectors
    looks = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))
    ups = ((0, -1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1), (0, -1, 0), (0, -1, 0))
    faces = [look_at(light.position, light.position + np.array(d, float), u).tolist()
             for d, u in zip(looks, ups)]
    lo, hi = light.position - far, light.position + far
    box = np.array([[1, 0, 0, -lo[0]], [-1, 0, 0, hi[0]], [0, 1, 0, -lo[1]],
                    [0, -1, 0, hi[1]], [0, 0, 1, -lo[2]], [0, 0, -1, hi[2]]], dtype=float)
    return {"light": light.name, "cube": True, "views": faces, "projection": projection.tolist(),
            "near": near, "far": far, "casters": _leaves(state, cull_region(state, box))}


# --------------------------------------------------------------------------- mirrors


@dataclass
class MirrorSight:
    """A mirror as one frame's eye sees it: what every tile's reflected view shares."""

    mirror: cfg.Mirror
    view: np.ndarray  # the reflected view, world -> eye, det -1
    clip: np.ndarray  # the mirror plane in eye space, keeping what lies beyond it
    outline: np.ndarray  # (k, 4) world planes: in front of the mirror, within its outline

    @classmethod
    def of(cls, mirror: cfg.Mirror, frame: Frame, view: np.ndarray) -> "MirrorSight | None":
        """None when the eye cannot see the mirror's reflective side."""
        eye = frame.to_world(frame.eye)
        plane = mirror.plane
        if plane[:3] @ eye + plane[3] <= 1e-9 * max(float(np.abs(eye).max()), 1.0):
            return None
        refl = mirror.reflection
        outline = [plane[None]]
        if mirror.polygon is not None:
            outline.append(_pyramid(refl @ np.append(eye, 1.0), mirror.polygon))
        clip = rigid_inverse(view).T @ (-plane)
        return cls(mirror, view @ refl, clip, np.concatenate(outline))

    def tile(self, state: SceneState, tile_planes: np.ndarray,
             projection: np.ndarray) -> dict | None:
        """The reflected view of one tile (its frustum's planes and projection), or None when
        the tile sees nothing in the mirror."""
        # Seen in the mirror, in world space: the tile frustum reflected (a plane P applied to
        # reflected points, P . (R p), is the plane P R), in front of the mirror, within the
        # pyramid from the reflected eye through the outline.
        region = np.concatenate([tile_planes @ self.mirror.reflection, self.outline])
        nodes = cull_region(state, region)
        if not len(nodes):
            return None
        try:
            oblique = oblique_near(projection, self.clip)
        except ClipPlaneError:
            return None
        return {"mirror": self.mirror.name, "view": self.view.tolist(),
                "projection": oblique.tolist(), "front_face": "cw",
                "visible": _leaves(state, nodes)}


def _pyramid(apex: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Planes through ``apex`` and each edge of a convex polygon, facing its inside."""
    apex = apex[:3]
    center = polygon.mean(axis=0)
    edges = np.roll(polygon, -1, axis=0) - polygon
    normals = np.cross(polygon - apex, edges)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    d = -np.einsum("ij,ij->i", normals, polygon)
    flip = normals @ center + d < 0
    normals[flip] *= -1
    d[flip] *= -1
    return np.concatenate([normals, d[:, None]], axis=1)
