"""Draw lists for the OpenGL tile renderer from a culled frame: each listed leaf's mesh, placed
at its leaf, whole or by the tile's draw ranges (as a render node draws a packet)."""

from __future__ import annotations

import numpy as np


class Draws:
    """Uploads each mesh once to ``renderer``; draw ids are leaf id + 1. ``single_sided``: the
    keys of the meshes whose back faces the renderer culls (as a glTF renderer does where a
    material is not ``doubleSided``); the others show both faces."""

    def __init__(self, scene, renderer, single_sided=()):
        self.scene, self.renderer, self.uploaded = scene, renderer, set()
        self.single_sided = set(single_sided)

    def leaves(self, leaves, ranges: dict | None = None) -> list[tuple]:
        ranges = ranges or {}
        out = []
        for leaf in leaves:
            key = self.scene.geometry[leaf]
            if key not in self.uploaded:
                self.renderer.upload(key, *self.scene.meshes[key],
                                     single_sided=key in self.single_sided)
                self.uploaded.add(key)
            out.append((key, self.scene.world[leaf], int(leaf) + 1, ranges.get(int(leaf))))
        return out

    def everything(self) -> list[tuple]:
        return self.leaves(self.scene.leaves)

    def tile(self, vis, tile: int) -> list[tuple]:
        """What tile ``tile`` draws: its leaves, those shown in part by their ranges."""
        return self.leaves(vis.tile_leaves(tile), dict(vis.draw_ranges().tile(tile)))


def partial_leaves(vis) -> int:
    """How many (tile, leaf) pairs a frame draws by ranges: the test must exercise some."""
    return int(len(vis.draw_ranges().part_leaf))


def ids_equal(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_array_equal(a, b)
