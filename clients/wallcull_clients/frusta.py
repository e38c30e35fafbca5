"""A render node's matrices from node messages (:mod:`wallcull.protocol`): the exact 4x4 view
and projection of each of its tiles, and of each eye of a stereo frame.

A node message sends what a frame's tiles share once (a grid's view) and each tile's
projection as its frustum's *extent* ``[l/n, r/n, b/n, t/n]`` (the sides of the tile's
rectangle as tangents in its eye space, where the camera looks down ``-z``) and *depth*
``[n, f]`` (the near and far distances; ``f`` may be ``inf``). A delta carries a tile's extent
and depth only when they changed since the base frame, so a node keeps them by frame, as it
keeps its lists (:class:`Frusta`).

With ``l = n * extent[0]`` and so on, the projection is OpenGL's ``glFrustum`` matrix (clip
depth -1 at the near plane, +1 at the far one), or with ``reversed_z`` the ``[0, 1]`` matrix
that maps the near plane to 1 and the far one (or infinity) to 0::

    [2n/(r-l)   0         (r+l)/(r-l)   0 ]
    [0          2n/(t-b)  (t+b)/(t-b)   0 ]
    [0          0         A             B ]      A, B = -(f+n)/(f-n), -2fn/(f-n)
    [0          0         -1            0 ]      reversed: n/(f-n), fn/(f-n)

A view ``{"rotation": [w, x, y, z], "translation": [x, y, z]}`` is the 4x4 rigid matrix with
the rotation of the unit quaternion and that translation.

This module is what a lab's own client does in C++, C# or JavaScript; it needs numpy only.
"""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np

EYES = ("left", "right")


def projection(extent, depth, reversed_z: bool = False) -> np.ndarray:
    """The ``(4, 4)`` projection of an extent and a depth range (module docstring)."""
    n, f = float(depth[0]), float(depth[1])
    l, r, b, t = (float(v) * n for v in extent)
    m = np.zeros((4, 4))
    m[0, 0], m[0, 2] = 2 * n / (r - l), (r + l) / (r - l)
    m[1, 1], m[1, 2] = 2 * n / (t - b), (t + b) / (t - b)
    m[3, 2] = -1.0
    if reversed_z:
        m[2, 2], m[2, 3] = (0.0, n) if math.isinf(f) else (n / (f - n), f * n / (f - n))
    else:
        m[2, 2], m[2, 3] = (-1.0, -2 * n) if math.isinf(f) else \
            (-(f + n) / (f - n), -2 * f * n / (f - n))
    return m


#: Projections a :class:`Frusta` keeps built (a 256 x 256 wall's node of 64 tiles in stereo
#: needs 128 a frame).
PROJECTIONS_KEPT = 4096


def view(rigid: dict) -> np.ndarray:
    """The ``(4, 4)`` matrix of a rigid view (module docstring)."""
    w, x, y, z = (float(v) for v in rigid["rotation"])
    tx, ty, tz = (float(v) for v in rigid["translation"])
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y), tx],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x), ty],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y), tz],
                     [0.0, 0.0, 0.0, 1.0]])


class Frusta:
    """A node's tiles' frusta, message after message: :meth:`take` returns every tile's
    matrices and keeps their extents and depth ranges by frame for the deltas to come. It
    keeps the frames a delta may still be based on: from the newest base seen on (as for the
    lists), at most ``keep``."""

    def __init__(self, keep: int = 256):
        self.keep = keep
        self.held: OrderedDict[int, dict] = OrderedDict()  # frame -> {(tile, eye, key): value}
        # (extent, depth, reversed_z) -> its projection, read-only: most tiles keep theirs
        # from one frame to the next (a delta leaves them out), so each is built once
        self._projections: dict[tuple, np.ndarray] = {}

    def take(self, message: dict) -> dict[int, dict]:
        """``{tile: {"view", "projection", "near", "far", "left"?, "right"?}}`` of a node
        message: its entries' tiles, and the base's tiles a delta left out (they keep the
        base's extent and depth). Raises KeyError when a delta leaves out what only a base not
        held had."""
        base = message.get("base")
        held = self.held.get(base, {}) if base is not None else {}
        reversed_z = bool(message.get("reversed_z", False))
        now, out = {}, {}
        # a tile the delta left out: as an entry of nothing but its tile
        entries = {tile: {} for tile, eye, key in held if eye is None}
        entries.update((entry["tile"], entry) for entry in message["tiles"])
        shared = {}  # eye -> the matrix of the message's shared view: built once for all tiles
        for tile in sorted(entries):
            entry = entries[tile]
            record = self._eye(tile, None, entry, message, held, now, shared, reversed_z, base)
            for eye in EYES:
                if eye in entry:
                    record[eye] = self._eye(tile, eye, entry[eye], message, held, now, shared,
                                            reversed_z, base)
            out[tile] = record
        self.held[message["frame"]] = now
        if base is not None:
            while self.held and next(iter(self.held)) < base:
                self.held.popitem(last=False)
        while len(self.held) > self.keep:
            self.held.popitem(last=False)
        return out

    def _eye(self, tile, eye, part, message, held, now, shared, reversed_z, base) -> dict:
        """One tile's (one eye's) matrices from its ``part`` of the message, the rest from
        ``held``; its extent and depth go into ``now``."""
        values = []
        for key in ("extent", "depth"):
            value = part.get(key)
            if value is None:
                value = held.get((tile, eye, key))
                if value is None:
                    raise KeyError(f"tile {tile}: the delta's {key} is that of frame {base}, "
                                   "which is not held")
            now[tile, eye, key] = value
            values.append(value)
        extent, depth = values
        if "view" in part:
            matrix = view(part["view"])
        else:
            matrix = shared.get(eye)
            if matrix is None:
                rigid = message.get("view") if eye is None else \
                    message.get(eye, {}).get("view")
                matrix = shared[eye] = view(rigid)
        return {"view": matrix, "projection": self._projection(extent, depth, reversed_z),
                "near": float(depth[0]), "far": float(depth[1])}

    def _projection(self, extent, depth, reversed_z: bool) -> np.ndarray:
        """:func:`projection`, built once for the same numbers (read-only)."""
        key = (*extent, *depth, reversed_z)
        found = self._projections.get(key)
        if found is None:
            if len(self._projections) >= PROJECTIONS_KEPT:
                self._projections.clear()
            found = self._projections[key] = projection(extent, depth, reversed_z)
            found.flags.writeable = False
        return found
