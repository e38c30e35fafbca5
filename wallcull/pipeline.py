"""One wall, one scene, frame after frame: the pipeline of DESIGN.md.

``scene ──load──▶ SceneState ── wall + frame ──▶ Frusta ──cull──▶ Visibility``

The command line, the benchmark and the server all drive a :class:`Session`, so a number the
benchmark measures is the number the server delivers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from .cull import Culler, Visibility
from .scene import Scene, SceneState
from .wall import Frame, Frusta, Wall


@dataclass
class FrameResult:
    frame: Frame
    frusta: Frusta
    visibility: Visibility
    timings: dict = field(default_factory=dict)  # ms per stage


class Session:
    """A scene culled to a wall with one method and one bound type."""

    def __init__(self, scene: Scene, wall: Wall, method: str = "adaptive", bounds: str = "obb",
                 pseudo_groups: bool = False):
        self.scene = scene
        self.wall = wall
        self.state = SceneState(scene, bounds)
        self.culler = Culler(self.state, wall, method, pseudo_groups)

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
        cull_ms = (time.perf_counter() - t0) * 1e3
        return FrameResult(frame, frusta, visibility, {"cull_ms": cull_ms})

    def move(self, updates: Mapping[str, Any], refit: str | None = None) -> np.ndarray:
        """Apply dynamic node updates before the next frame (see :meth:`SceneState.move`)."""
        return self.state.move(updates, refit)


def tile_records(result: FrameResult, leaves: bool = False) -> list[dict]:
    """SPEC section 6 ``tiles`` entries for one frame."""
    wall, vis = result.frusta.wall, result.visibility
    return [{"id": t, "row": t // wall.cols, "col": t % wall.cols,
             "visible": vis.names(t, leaves=leaves)} for t in range(wall.tiles)]
