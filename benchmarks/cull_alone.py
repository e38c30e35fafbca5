"""The culling step alone, frame after frame with nothing between them (warm caches), beside
``wallcull bench``, which runs every stage of a frame between its culls as the server does.

    python benchmarks/cull_alone.py [SCENE] [WALL.json] [FRAMES]
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from wallcull.cull import Culler
from wallcull.paths import scene_path
from wallcull.scene import SceneState, load
from wallcull.wall import Frusta, Wall


def main(scene_name: str = "powerplant", wall_file: str = "examples/wall-8x8.json",
         count: int = 200) -> None:
    scene = load(scene_name)
    with open(wall_file) as f:
        wall = Wall.from_dict(json.load(f))
    frames = scene_path(scene, wall, "orbit", count)
    state = SceneState(scene)
    for method in ("adaptive", "oh", "fh"):
        culler = Culler(state, wall, method)
        times = []
        for frame in frames[:3] + frames:  # the first three compile
            t0 = time.perf_counter()
            culler.cull(Frusta.build(wall, frame))
            times.append(time.perf_counter() - t0)
        print(f"{method:>8}: median {1e3 * np.median(times[3:]):.3f} ms, "
              f"p99 {1e3 * np.percentile(times[3:], 99):.3f} ms")


if __name__ == "__main__":
    main(*(sys.argv[1:3]), *(int(a) for a in sys.argv[3:4]))
