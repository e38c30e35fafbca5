"""Fitted frusta: what each tile's render node needs to draw exactly its part.

Every tile gets its view and off-axis projection (SPEC sections 1-3). The view is the same for
all tiles of a frame, eye space being display space moved to the tracked eye; only the
projections differ.
"""

from __future__ import annotations

import numpy as np

from .projection import rigid_inverse
from .wall import Frame, Wall


def tile_projections(wall: Wall, frame: Frame, near: np.ndarray, far: np.ndarray) -> np.ndarray:
    """``(tiles, 4, 4)`` off-axis projections through each tile rectangle, with per-tile near
    and far distances (Lengyel's frustum matrix, vectorized)."""
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
    out[:, 2, 2] = -(far + near) / (far - near)
    out[:, 2, 3] = -2 * far * near / (far - near)
    out[:, 3, 2] = -1.0
    return out


def view_matrix(frame: Frame) -> np.ndarray:
    """World to eye space: display axes, origin at the tracked eye."""
    eye_to_world = np.eye(4)
    eye_to_world[:3, :3] = frame.rotation
    eye_to_world[:3, 3] = frame.to_world(frame.eye)
    return rigid_inverse(eye_to_world)


def fit_frame(wall: Wall, frame: Frame) -> list[dict]:
    """Per tile, the JSON-ready fitted frusta: ``view`` and ``projection``, row by row."""
    near = np.full(wall.tiles, wall.near)
    far = np.full(wall.tiles, wall.far)
    view = view_matrix(frame).tolist()
    return [{"view": view, "projection": p} for p in tile_projections(wall, frame, near, far).tolist()]
