"""The adaptive traversal as a numpy frontier, the project's first design, measured against
the compiled kernel that replaced it.

Each step classifies every (object node, frustum node) pair of the frontier against its
frustum node's split planes at once; pairs on one side move down the frustum hierarchy, cut
pairs unfold the object into its children, pairs at a frustum leaf are emitted. This is the
paper's Algorithm 2 as written, so its leaf lists are checked to hold ``fh``'s, the same split
planes deciding, where ``fh`` goes on to test each pair against its tile's own planes and the
separating axes (:mod:`wallcull.separate`), dropping some; the times are printed beside the
compiled ``adaptive`` kernel's.

    python benchmarks/numpy_frontier.py [SCENE] [WALL.json] [FRAMES]
"""

from __future__ import annotations

import json
import time

import numpy as np

from wallcull.errors import InputError
from wallcull.cull import Culler, _primary, _shared_planes, packed
from wallcull.paths import camera_path
from wallcull.scene import SceneState, load
from wallcull.wall import Frusta, Wall
from _cli import count, run, wall_file  # beside this file

OUT, CUT, FULL = 0, 1, 2
NEAR_BIT = 1 << 4  # a grid's primary planes: left, right, top, bottom, near, far


def states(s, r):
    return np.where(s < -r, OUT, np.where(s >= r, FULL, CUT))


def adaptive_frontier(scene, b, planes, fh, roots, behind, shared):
    """``behind``: per root, whether the near plane cuts it (then a bezel split's two planes
    are both tested: the shortcut below holds only in front of the eye); its descendants
    inherit it."""
    c, axes, half, rad = b.center, b.axes, b.half, b.radius
    o = roots
    f = np.zeros(len(roots), dtype=np.int64)
    nodes, tiles = [], []
    while len(o):
        tile = fh.tile[f]
        done = tile >= 0
        nodes.append(o[done])
        tiles.append(tile[done])
        o, f, behind = o[~done], f[~done], behind[~done]
        if not len(o):
            break

        def test(plane_ids):
            p = planes[plane_ids]
            s = np.einsum("kj,kj->k", c[o], p[:, :3]) + p[:, 3]
            r = (np.abs(np.einsum("kij,kj->ki", axes[o], p[:, :3])) * half[o]).sum(1) + rad[o]
            return s, r

        s, r = test(fh.plane_a[f])
        sa = states(s, r)
        sb = states(-s, r) if shared else states(*test(fh.plane_b[f]))
        if not shared:  # in front of the eye, inside one bezel plane is outside the other
            sb = np.where((sa == FULL) & ~behind, OUT, sb)
        cut = (sa == CUT) | (sb == CUT)
        leaf = scene.is_leaf[o] | (scene.child_count[o] == 0)  # a cluster has no children
        to_second = (~cut & (sb == FULL)) | (cut & leaf & (sb != OUT))
        to_first = (~cut & (sa == FULL)) | (cut & leaf & (sa != OUT))
        unfold = cut & ~leaf
        parents, pf = o[unfold], f[unfold]
        counts = scene.child_count[parents]
        offsets = np.repeat(scene.child_start[parents] - np.cumsum(counts) + counts, counts)
        kids = scene.children[np.arange(counts.sum()) + offsets]
        o = np.concatenate([o[to_first], o[to_second], kids])
        behind = np.concatenate([behind[to_first], behind[to_second],
                                 np.repeat(behind[unfold], counts)])
        f = np.concatenate([fh.first[f[to_first]], fh.second[f[to_second]],
                            np.repeat(pf, counts)])
    return np.concatenate(nodes), np.concatenate(tiles)


def main(scene_name="powerplant", wall_path="examples/wall-4x4.json", frames=100):
    wall = Wall.from_dict(json.load(open(wall_path)))
    if wall.kind != "grid":
        raise InputError(f"{wall_path} is a wall of screens: the numpy frontier culls grids")
    scene = load(scene_name)
    state = SceneState(scene, "obb")
    culler = Culler(state, wall, "adaptive")
    reference = Culler(state, wall, "fh")
    path = camera_path("orbit", scene.box[0], scene.box[1], wall, frames)
    shared = wall.gap == (0.0, 0.0)
    b = state.bounds
    box, n = packed(state), len(scene)
    numpy_ms, kernel_ms = [], []
    extra = 0  # leaf-tile pairs fh's tests at the tiles drop from the frontier's
    for frame in path:
        t0 = time.perf_counter()
        frusta = Frusta.build(wall, frame)
        planes = _shared_planes(frusta.planes, wall) if shared else frusta.planes
        roots, masks = np.empty(n, np.int64), np.empty(n, np.int64)
        stack = np.empty(2 * n, np.int64), np.empty(2 * n, np.int64)
        count, _ = _primary(*culler._tree, box, planes, culler._primary_planes, roots, masks,
                            *stack)
        nodes, tiles = adaptive_frontier(scene, b, planes, wall.hierarchy, roots[:count],
                                         (masks[:count] & NEAR_BIT) != 0, shared)
        numpy_ms.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        culler.cull(Frusta.build(wall, frame))
        kernel_ms.append((time.perf_counter() - t0) * 1e3)
        vis = reference.cull(frusta)
        # a listed cluster (or group of them) stands for its leaf
        nodes = np.where(scene.cluster_leaf[nodes] >= 0, scene.cluster_leaf[nodes], nodes)
        for t in range(wall.tiles):
            got = np.unique(scene.subtree_leaves(nodes[tiles == t]))
            lost = vis.tile_leaves(t)[~np.isin(vis.tile_leaves(t), got)]
            assert not len(lost), f"the frontier lost leaves {lost[:5]} of fh's in tile {t}"
            extra += len(got) - len(vis.tile_leaves(t))
    print(f"{scene_name}, {wall.cols} x {wall.rows}, {frames} frames of the orbit path: "
          f"numpy frontier median {np.median(numpy_ms[3:]):.3f} ms, "
          f"numba adaptive kernel median {np.median(kernel_ms[3:]):.3f} ms (the frontier's "
          f"leaf lists hold fh's, and {extra / len(path):.0f} pairs a frame more, which fh's "
          "tests at the tiles drop)")


if __name__ == "__main__":
    run(main, __doc__, ("scene", "powerplant", str, "a scene name or file"),
        ("wall", "examples/wall-4x4.json", wall_file, "the wall file"),
        ("frames", 100, count(4), "frames of the path (the first 3 are left out)"))
