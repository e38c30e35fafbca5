"""Over NATS, is one publish a frame cheaper than one a node? A wall's real node messages
(the power plant's orbit, deltas against the frame before, as ``server_frame.py`` makes them)
are published through a ``nats-server`` on loopback at 60 frames/s to a process holding one
connection per node, either

* ``per node``: each node's message on its own subject (what the server does), or
* ``per frame``: all of them in one message on one subject every node reads, behind a table of
  offsets from which a node takes its own part,

and each node decodes its own message. Reported per frame: the CPU of the publisher (its
publishes, and the joining of the parts for ``per frame``), of the broker and of the nodes,
and the bytes into and out of the broker.

    python benchmarks/nats_fanout.py [WALL.json] [TILES_PER_NODE] [FRAMES]
"""

from __future__ import annotations

import asyncio
import json
import os
import struct
import subprocess
import sys
import time

import msgpack
import nats
from _cli import count, run, wall_file  # beside this file
from server_frame import wall_session
from wallcull_clients.broker import Broker

RATE = 60.0
MODES = ("per node", "per frame")


def messages(wall_file: str, per_node: int, count: int) -> list[list[bytes]]:
    """Per frame, every node's message (a delta against the frame before)."""
    session, frames = wall_session(wall_file, per_node)
    out = []
    for number, frame in enumerate(frames[:count]):
        record, _ = session.compute_frame(frame)
        session.publish(record)
        out.append([session.node_message(t, number, held=number - 1)[0] for t in session.nodes])
        for t in session.nodes:
            session.ack(t, number)
    return out


def cpu_of(pid: int) -> float:
    """Seconds of CPU process ``pid`` has used (user and system)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def publish(url: str, mode: str, frames: list[list[bytes]], broker_pid: int) -> dict:
    nodes = len(frames[0])
    nc = await nats.connect(url)
    ready = await nc.subscribe("bench.ready")
    child = subprocess.Popen([sys.executable, __file__, "--nodes", url, mode, str(nodes)],
                             stdout=subprocess.PIPE)
    await ready.next_msg(timeout=60)
    broker0, own0, t0 = cpu_of(broker_pid), time.process_time(), time.perf_counter()
    sent = 0
    for k, parts in enumerate(frames):
        if mode == "per node":
            for n, part in enumerate(parts):
                await nc.publish(f"bench.node.{n}", part)
                sent += len(part)
        else:
            offsets, at = [], 0
            for part in parts:
                offsets.append(at)
                at += len(part)
            offsets.append(at)
            data = struct.pack(f"<{nodes + 1}I", *offsets) + b"".join(parts)
            await nc.publish("bench.frame", data)
            sent += len(data)
        await asyncio.sleep(max(0.0, t0 + (k + 1) / RATE - time.perf_counter()))
    await nc.flush()
    own = time.process_time() - own0
    answer = await nc.request("bench.done", b"", timeout=60)
    broker = cpu_of(broker_pid) - broker0
    child.wait(30)
    await nc.close()
    got = json.loads(answer.data)
    n = len(frames)
    return {"publisher_ms": 1e3 * own / n, "broker_ms": 1e3 * broker / n,
            "nodes_ms": 1e3 * got["cpu_s"] / n, "bytes_in": sent / n,
            "bytes_out": got["bytes"] / n, "decoded": got["decoded"]}


async def nodes_process(url: str, mode: str, nodes: int) -> None:
    """The nodes: one connection each, decoding its own message of every frame."""
    conns = [await nats.connect(url) for _ in range(nodes)]
    counts = {"bytes": 0, "decoded": 0}
    head = struct.calcsize(f"<{nodes + 1}I")

    def handler(n):
        async def on_message(msg):
            data = msg.data
            counts["bytes"] += len(data)
            if mode == "per frame":
                at = struct.unpack_from("<2I", data, 4 * n)
                data = data[head + at[0]:head + at[1]]
            msgpack.unpackb(data)
            counts["decoded"] += 1
        return on_message

    for n, nc in enumerate(conns):
        subject = f"bench.node.{n}" if mode == "per node" else "bench.frame"
        await nc.subscribe(subject, cb=handler(n))
    for nc in conns:
        await nc.flush()
    done = asyncio.Event()
    cpu0 = time.process_time()

    async def on_done(msg):
        await conns[0].flush()
        await msg.respond(json.dumps({**counts, "cpu_s": time.process_time() - cpu0}).encode())
        done.set()

    await conns[0].subscribe("bench.done", cb=on_done)
    await conns[0].flush()
    await conns[0].publish("bench.ready", b"")
    await done.wait()
    for nc in conns:
        await nc.close()


def main(wall_file: str = "examples/wall-8x8.json", per_node: int = 4, count: int = 600) -> None:
    frames = messages(wall_file, per_node, count)
    with Broker() as broker:
        results = {}
        for mode in MODES:  # in turns, twice each
            for _ in range(2):
                results.setdefault(mode, []).append(
                    asyncio.run(publish(broker.url, mode, frames, broker.proc.pid)))
    print(f"{wall_file}, {len(frames[0])} nodes of {per_node}, {count} frames at {RATE:g}/s; "
          "CPU ms a frame and bytes a frame (two runs each):")
    for mode, runs in results.items():
        for r in runs:
            print(f"  {mode:9}: publisher {r['publisher_ms']:.3f}, broker {r['broker_ms']:.3f}, "
                  f"nodes {r['nodes_ms']:.3f} ms; into the broker {r['bytes_in']:,.0f} B, out "
                  f"{r['bytes_out']:,.0f} B; {r['decoded']} messages decoded")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--nodes"]:
        asyncio.run(nodes_process(sys.argv[2], sys.argv[3], int(sys.argv[4])))
    else:
        run(main, __doc__, ("wall", "examples/wall-8x8.json", wall_file, "the wall file"),
            ("per_node", 4, count(1), "tiles a node draws"),
            ("frames", 600, count(1, 600), "frames of the orbit"))
