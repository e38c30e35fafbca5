"""Stereo on a grid: one pass against planes that hold both eyes' frusta (what wallcull does,
:mod:`wallcull.stereo`) against culling each eye alone and merging the lists, side by side on
the same frames.

    python benchmarks/stereo_passes.py [SCENE] [WALL.json] [FRAMES]
"""

from __future__ import annotations

import json
import time

import numpy as np

from wallcull.cull import Culler, merge
from wallcull.paths import scene_path
from wallcull.scene import SceneState, load
from wallcull.wall import Frame, Frusta, Wall
from _cli import count, run, wall_file  # beside this file

IPD = 0.064


def main(scene_name: str = "powerplant", wall_file: str = "examples/wall-8x8.json",
         count: int = 200) -> None:
    scene = load(scene_name)
    with open(wall_file) as f:
        wall = Wall.from_dict(json.load(f))
    culler = Culler(SceneState(scene), wall)
    frames = [Frame.make(f.position, f.orientation, f.eye, wall, (IPD, (1.0, 0.0, 0.0, 0.0)))
              for f in scene_path(scene, wall, "orbit", count)]
    times = {"one pass": [], "eye by eye": []}
    tests = {"one pass": [], "eye by eye": []}
    for frame in frames[:3] + frames:  # the first three compile
        t0 = time.perf_counter()
        both = culler.cull(Frusta.build(wall, frame))
        t1 = time.perf_counter()
        each = [culler.cull(Frusta.build(wall, Frame.make(frame.position, frame.orientation, e,
                                                          wall))) for e in frame.eyes]
        merge(each)
        t2 = time.perf_counter()
        times["one pass"].append(t1 - t0)
        times["eye by eye"].append(t2 - t1)
        tests["one pass"].append(both.stats["tests"])
        tests["eye by eye"].append(sum(v.stats["tests"] for v in each))
    for name in times:
        print(f"{name:>10}: median {1e3 * np.median(times[name][3:]):.3f} ms, "
              f"{np.mean(tests[name][3:]):,.0f} box-plane tests per frame")


if __name__ == "__main__":
    run(main, __doc__, ("scene", "powerplant", str, "a scene name or file"),
        ("wall", "examples/wall-8x8.json", wall_file, "the wall file"),
        ("frames", 200, count(4), "frames of the orbit (the first 3 are left out)"))
