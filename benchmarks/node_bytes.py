"""What a frame's node messages are made of, as the server sends them to every node of a wall:
bytes per frame with full lists and as deltas against the frame before, and the delta's bytes
by key (the shared head, each tile entry's parts).

    python benchmarks/node_bytes.py [WALL.json] [TILES_PER_NODE] [FRAMES] [CLUSTERS]

The power plant's orbit, 600 frames a loop (the load test's path at 60 frames/s), frames 30
on; every node of ``TILES_PER_NODE`` consecutive tiles; the scene's leaves cut into clusters
(``auto``, the default, a size, or ``off``: leaves whole, what packets were before draw
ranges).
"""

from __future__ import annotations

from collections import Counter

import msgpack
import numpy as np
from server_frame import wall_session  # beside this file

from wallcull import encode
from _cli import count, run, wall_file  # beside this file


def main(wall_file: str = "examples/wall-16x16.json", per_node: int = 4,
         count: int = 150, clusters: str = "auto") -> None:
    session, frames = wall_session(wall_file, per_node, clusters)
    frames = frames[:count]
    full = delta = 0
    parts = Counter()
    for number, frame in enumerate(frames):
        session.post_frame(frame)
        if number < 30:
            continue
        for tiles in session.nodes:
            tiles = np.asarray(tiles)
            full += len(encode.node_message(session.history, number, tiles, None))
            raw = encode.node_message(session.history, number, tiles, number - 1)
            delta += len(raw)
            message = msgpack.unpackb(raw)
            for key, value in message.items():
                if key != "tiles":
                    parts["head: " + key] += len(msgpack.packb(key)) + len(msgpack.packb(value))
            parts["head: map, tiles key and array"] += len(msgpack.packb({"tiles": []}))
            for entry in message["tiles"]:
                parts["entry: map"] += 1
                for key, value in entry.items():
                    parts["entry: " + key] += len(msgpack.packb(key)) + len(msgpack.packb(value))
    n = len(frames) - 30
    print(f"{wall_file}, clusters {clusters}, {len(session.nodes)} nodes of {per_node}: "
          f"full {full / n:,.0f} B/frame, "
          f"delta {delta / n:,.0f} B/frame, {full / delta:.2f}x")
    for key, value in parts.most_common():
        print(f"  {key:32} {value / n:8,.0f} B/frame")


if __name__ == "__main__":
    run(main, __doc__, ("wall", "examples/wall-16x16.json", wall_file, "the wall file"),
        ("per_node", 4, count(1), "tiles a node draws"),
        ("frames", 150, count(31), "frames of the orbit (the first 30 are left out)"),
        ("clusters", "auto", str, "cluster size, auto or off"))
