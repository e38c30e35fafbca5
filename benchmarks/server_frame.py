"""The server's own work per frame of a wall, in one process, without the network: computing
the frame (cull, lists, fits, every tile's node-message entry), publishing it, every node's
message (a delta against the frame before) and every node's acknowledgement, as
``wallcull.service.WallSession`` does them for the streams. What ``wallcull loadtest``
measures beyond this is the WebSocket (or NATS) stack around the same calls.

    python benchmarks/server_frame.py [WALL.json] [TILES_PER_NODE] [FRAMES]
"""

from __future__ import annotations

import json
import time

import numpy as np

from wallcull.paths import scene_path
from wallcull.scene import load, parse_clusters
from wallcull.service import Walls
from wallcull.wall import Wall
from _cli import count, run, wall_file  # beside this file


def wall_session(wall_file: str, per_node: int, clusters: str = "auto"):
    """A wall of the power plant (its leaves cut into ``clusters``: a size, ``auto`` or
    ``off``) whose nodes drive ``per_node`` consecutive tiles each: the session, and its
    frames, the orbit's 600 frames a loop (the load test's at 60 frames/s)."""
    with open(wall_file) as f:
        wall = Wall.from_dict(json.load(f))
    scene = load("powerplant", clusters=parse_clusters(clusters))
    nodes = [list(range(k, min(k + per_node, wall.tiles))) for k in range(0, wall.tiles, per_node)]
    session = Walls().create(scene, wall, "adaptive", "obb", False, 64, nodes=nodes)
    return session, [f.to_dict() for f in scene_path(scene, wall, "orbit", 600)]


def main(wall_file: str = "examples/wall-8x8.json", per_node: int = 4,
         count: int = 300) -> None:
    session, frames = wall_session(wall_file, per_node)
    wall = session.wall
    tiles = [np.asarray(t) for t in session.nodes]
    stages = {"compute": [], "publish": [], "messages": [], "acks": []}
    for number, frame in enumerate(frames[:count]):
        t0 = time.perf_counter()
        record, _ = session.compute_frame(frame)
        t1 = time.perf_counter()
        session.publish(record)
        t2 = time.perf_counter()
        for node in tiles:
            session.node_message(node, number, held=number - 1)
        t3 = time.perf_counter()
        for node in tiles:
            session.ack(node, number)
        t4 = time.perf_counter()
        for key, value in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            stages[key].append(value * 1e3)
    median = {key: float(np.median(values[30:])) for key, values in stages.items()}
    total = sum(median.values())
    print(f"{wall_file}, {len(tiles)} nodes of {per_node}: "
          + ", ".join(f"{k} {v:.3f}" for k, v in median.items())
          + f" ms (medians); {total:.3f} ms a frame, {1e3 * total / wall.tiles:.1f} us a "
            "tile-frame")


if __name__ == "__main__":
    run(main, __doc__, ("wall", "examples/wall-8x8.json", wall_file, "the wall file"),
        ("per_node", 4, count(1), "tiles a node draws"),
        ("frames", 300, count(31, 600), "frames of the orbit (the first 30 are left out)"))
