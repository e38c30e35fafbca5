"""The culling step alone, frame after frame with nothing between them (warm caches), beside
``wallcull bench``, which runs every stage of a frame between its culls as the server does.
Per method: the median and p99 of a frame's cull, where it goes (the first-level cull and the
traversal, the separating-axis pass, the per-tile sort; the rest is the planes and Python
around them) and the traversal's time per box-plane test.

    python benchmarks/cull_alone.py [SCENE] [WALL.json] [FRAMES]
"""

from __future__ import annotations

import json
import time

import numpy as np

from wallcull.cull import Culler
from wallcull.paths import scene_path
from wallcull.scene import SceneState, load
from wallcull.wall import Frusta, Wall
from _cli import count, run, wall_file  # beside this file

STAGES = ("traverse_ms", "separate_ms", "sort_ms")


def main(scene_name: str = "powerplant", wall_file: str = "examples/wall-8x8.json",
         count: int = 200) -> None:
    scene = load(scene_name)
    with open(wall_file) as f:
        wall = Wall.from_dict(json.load(f))
    frames = scene_path(scene, wall, "orbit", count)
    state = SceneState(scene)
    for method in ("adaptive", "oh", "fh"):
        culler = Culler(state, wall, method)
        times, stats = [], []
        for frame in frames[:3] + frames:  # the first three compile
            t0 = time.perf_counter()
            vis = culler.cull(Frusta.build(wall, frame))
            times.append(time.perf_counter() - t0)
            stats.append(vis.stats)
        times, stats = times[3:], stats[3:]
        stage = {k: np.median([s[k] for s in stats]) for k in STAGES}
        tests = np.median([s["tests"] + s["primary_tests"] for s in stats])
        print(f"{method:>8}: median {1e3 * np.median(times):.3f} ms, "
              f"p99 {1e3 * np.percentile(times, 99):.3f} ms; traversal "
              f"{stage['traverse_ms']:.3f} ms for {tests:.0f} tests "
              f"({1e6 * stage['traverse_ms'] / tests:.1f} ns a test), separating axes "
              f"{stage['separate_ms']:.3f} ms, sort {stage['sort_ms']:.3f} ms")


if __name__ == "__main__":
    run(main, __doc__, ("scene", "powerplant", str, "a scene name or file"),
        ("wall", "examples/wall-8x8.json", wall_file, "the wall file"),
        ("frames", 200, count(3), "frames of the orbit (three more first, compiling)"))
