"""One wall, one scene, frame after frame: the pipeline of DESIGN.md.

``scene ──load──▶ SceneState ── wall + frame ──▶ Frusta ──cull──▶ Visibility ──▶ leaf lists
──fit──▶ Fits``; :mod:`wallcull.encode` turns the last two into packets.

The command line, the benchmark and the server all drive a :class:`Session`, so a number the
benchmark measures is the number the server delivers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Mapping

import numpy as np

from . import settings as cfg
from .cull import FINE, Culler, Visibility
from .fit import FitOptions, Fits, fit_frame
from .occlude import Occluder, OcclusionOptions
from .scene import Scene, SceneState
from .wall import Frame, Frusta, Wall


@dataclass
class FrameResult:
    frame: Frame
    frusta: Frusta
    visibility: Visibility
    timings: dict = field(default_factory=dict)  # ms per stage: cull, leaves, fit
    fits: Fits | None = None  # when the session fits

    @property
    def leaves(self) -> tuple[np.ndarray, np.ndarray]:
        """Every tile's sorted leaf ids, CSR ``(start, leaves)``: what packets carry."""
        return self.visibility.leaf_lists()

    @property
    def parts(self) -> tuple:
        """Every tile's leaves drawn in part and their draw ranges, CSR ``(part_start,
        part_leaf, range_start, ranges)``: what packets carry beside the lists."""
        d = self.visibility.draw_ranges()
        return d.part_start, d.part_leaf, d.range_start, d.ranges


class Session:
    """A scene culled to a wall with one method and one bound type; with ``fit`` options, each
    frame also gets its fitted frusta (:mod:`wallcull.fit`)."""

    def __init__(self, scene: Scene, wall: Wall, method: str = "adaptive", bounds: str = "obb",
                 pseudo_groups: bool = False, fit: FitOptions | None = None,
                 settings: Mapping[str, Any] | None = None, fine: float = FINE,
                 occlusion: OcclusionOptions | None = None):
        self.scene = scene
        self.wall = wall
        self.state = SceneState(scene, bounds)
        self.culler = Culler(self.state, wall, method, pseudo_groups, fine)
        # what the scene asks for (lights, mirrors, what occludes): its own, or ``settings``
        # for this wall
        self.raw_settings = dict(scene.settings if settings is None else settings)
        self.settings = cfg.parse(self.raw_settings)
        self.occluder = None if occlusion is None else Occluder(
            self.state, wall, replace(occlusion, **self.settings.occlusion),
            self.settings.exclude)
        self.occlusion = "off" if occlusion is None else occlusion.mode  # the setting's word
        self.fit_options = fit

    @property
    def method(self) -> str:
        return self.culler.method

    def frame(self, frame: Frame | Mapping[str, Any]) -> FrameResult:
        """Cull one frame (a :class:`Frame` or a SPEC section 3 frame dict)."""
        if not isinstance(frame, Frame):
            frame = Frame.from_dict(frame, self.wall)
        t0 = time.perf_counter()
        frusta = Frusta.build(self.wall, frame)
        visibility = self.culler.cull(frusta)
        t1 = time.perf_counter()
        timings = {"cull_ms": (t1 - t0) * 1e3}
        if self.occluder is not None and self.occluder.wanted(frame):
            visibility = self.occluder.occlude(visibility, frame)
            t1 = time.perf_counter()
            timings["occlude_ms"] = visibility.stats["occlude_ms"]
        visibility.leaf_lists()  # compiled, next to the traversal; cached on the visibility
        t2 = time.perf_counter()
        result = FrameResult(frame, frusta, visibility, {**timings,
                                                         "leaves_ms": (t2 - t1) * 1e3})
        if self.fit_options is not None:
            result.fits = fit_frame(self.wall, frame, visibility, self.state, self.settings,
                                    self.fit_options, frusta, self.culler)
            result.timings["fit_ms"] = (time.perf_counter() - t2) * 1e3
        return result

    def move(self, updates: Mapping[str, Any], refit: str | None = None) -> np.ndarray:
        """Apply dynamic node updates before the next frame (see :meth:`SceneState.move`)."""
        return self.state.move(updates, refit)


def tile_records(result: FrameResult, leaves: bool = False) -> list[dict]:
    """SPEC section 6 ``tiles`` entries for one frame, with the fitted frusta when there are
    some (their lists of leaf ids given as leaf names). ``ranges`` maps each leaf the tile
    shows only in part to the ranges of its mesh's triangles to draw, ``[first, count]``; the
    tile draws every other leaf whole."""
    wall, vis = result.frusta.wall, result.visibility
    names = vis.scene.names
    ranges = vis.draw_ranges()
    out = []
    grid = wall.kind == "grid" and not wall.given_as_screens  # screens have no row and col
    for t in range(wall.tiles):
        record = {"id": t, **({"row": t // wall.cols, "col": t % wall.cols} if grid else {}),
                  "visible": vis.names(t, leaves=leaves),
                  "ranges": {names[leaf]: r.tolist() for leaf, r in ranges.tile(t)}}
        if result.fits is not None:
            fits = dict(result.fits[t])
            for key, field_name in (("shadows", "casters"), ("mirrors", "visible")):
                if key in fits:
                    fits[key] = [{**e, field_name: [names[i] for i in e[field_name]]}
                                 for e in fits[key]]
            record.update(fits)
        out.append(record)
    return out
