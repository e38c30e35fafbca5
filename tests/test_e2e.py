"""End to end on loopback: a real ``wallcull serve`` subprocess, the driver and 16 simulated
render nodes (a 4 x 4 wall) over 500 frames of the power plant's orbit.

Checked exactly, for both transports (long-polling every frame number; WebSocket streams with a
driver that waits on the swap barrier, so nothing is conflated):

* every tile receives every frame's packet, in order;
* the list each node rebuilds from each packet (full, or a delta applied with
  ``protocol.apply``) equals, leaf for leaf, the in-process culler's list for the same frame:
  ``Session(scene, wall).frame(frame).visibility.leaf_lists()``;
* the swap barrier holds: every barrier answers complete (16 of 16 acknowledged), the driver never
  posts frame n + 1 before the barrier of n has answered, and no node sends its acknowledgement of
  n + 1 before the barrier of n completed (that is, before every tile had acknowledged n).

The order of events is observed in one event loop, where the nodes and the driver all run, so it
is a total order.
"""

import asyncio
import json
import secrets
from pathlib import Path

import numpy as np
import pytest

from wallcull.clients.driver import Driver
from wallcull.clients.sim import run_wall
from wallcull.clients.loadtest import running_server
from wallcull.pipeline import Session
from wallcull.scene import load
from wallcull.wall import Wall

ROOT = Path(__file__).resolve().parent.parent
WALL = json.loads((ROOT / "examples" / "wall-4x4.json").read_text())
SCENE = "powerplant"
FRAMES = 500
TOKEN = secrets.token_hex(8)


@pytest.fixture(scope="module")
def server():
    with running_server(TOKEN) as url:
        yield url


@pytest.fixture(scope="module")
def scene():
    return load(SCENE)


def expected_lists(scene, frames):
    """Per frame, the in-process culler's CSR ``(start, leaves)`` for the same frame dicts."""
    session = Session(scene, Wall.from_dict(WALL))
    return [session.frame(f).visibility.leaf_lists() for f in frames]


async def walk(url: str, mode: str, scene, frames_count: int = FRAMES):
    """Drive one wall through ``frames_count`` frames with the barrier; returns what the checks
    need."""
    events = []  # (kind, tile or None, frame) in the order the event loop saw them
    mismatches, received = [], {}

    def node_event(kind, tile, frame):
        events.append((kind, tile, frame))

    def driver_event(kind, frame, state=None):
        events.append((kind, None, frame))
        if kind == "barrier":
            barriers.append(state)

    barriers = []
    async with Driver(url, TOKEN) as driver:
        info = await driver.create_wall(SCENE, WALL)
        wid, tiles = info["id"], info["tiles"]
        frames = await driver.frames(SCENE, info["wall"], "orbit", frames_count)
        expected = expected_lists(scene, frames)

        def on_list(tile, frame, leaves):
            received.setdefault(tile, []).append(frame)
            start, want = expected[frame]
            want = want[start[tile]:start[tile + 1]]
            if not np.array_equal(leaves, want):
                mismatches.append((frame, tile, len(leaves), len(want)))

        ready = asyncio.Event()
        nodes = asyncio.create_task(run_wall(
            url, wid, "all", mode=mode, token=TOKEN, until=frames_count - 1, idle_timeout=30,
            on_list=on_list, on_event=node_event, ready=lambda clients: ready.set()))
        await asyncio.wait_for(ready.wait(), 60)
        if mode == "ws":
            assert await driver.wait_clients(wid, tiles, 30) == tiles
        log = await driver.run(wid, frames, rate=0, barrier=True, barrier_timeout=10,
                               on_event=driver_event)
        clients = await asyncio.wait_for(nodes, 60)
        final = await driver.wall_info(wid)
        await driver.conn.call("DELETE", f"/walls/{wid}", auth=True)
    return dict(tiles=tiles, frames=frames, expected=expected, events=events, log=log,
                barriers=barriers, mismatches=mismatches, received=received, clients=clients,
                final=final)


def check(result, mode):
    tiles, n = result["tiles"], len(result["frames"])
    # the comparison is not vacuous: lists change along the path, some tiles draw a lot
    sizes = np.array([[e[0][t + 1] - e[0][t] for t in range(tiles)] for e in result["expected"]])
    assert sizes.max() > 500 and len({tuple(e[1][:50]) for e in result["expected"]}) > 10

    log = result["log"]
    assert log.frame == list(range(n)), "the server numbered the frames 0..n-1"
    assert result["final"]["latest"] == n - 1

    # every tile got every frame, in order, and rebuilt exactly the culler's list
    for c in result["clients"]:
        assert c.stats.errors == [], (c.tile, c.stats.errors[:3])
        assert c.stats.frame == list(range(n)), f"tile {c.tile} missed or reordered frames"
        assert result["received"][c.tile] == list(range(n))
    assert result["mismatches"] == [], result["mismatches"][:5]
    deltas = sum(len(c.stats.full) - sum(c.stats.full) for c in result["clients"])
    assert deltas > 0.9 * tiles * n, "the packets were deltas, and the deltas were checked"
    if mode == "pull":
        assert all(c.stats.base_misses == 0 for c in result["clients"])

    # the swap barrier held
    assert len(result["barriers"]) == n
    assert all(b["complete"] and b["acked"] == tiles for b in result["barriers"])
    assert all(log.barrier_complete)
    assert ordering_violations(result["events"], n, tiles) == []
    for t in range(tiles):  # and each tile acknowledged every frame once, in order
        acks = [f for kind, tile, f in result["events"] if kind == "ack" and tile == t]
        assert acks == list(range(n))


def ordering_violations(events, n, tiles) -> list:
    """Frames posted before the previous barrier answered, and acknowledgements of k sent
    before the barrier of k - 1 completed (before every tile had acknowledged k - 1)."""
    position = {}
    for i, (kind, tile, frame) in enumerate(events):
        position.setdefault((kind, tile, frame), i)
    out = []
    for k in range(1, n):
        released = position.get(("barrier", None, k - 1), float("inf"))
        if position[("post", None, k)] < released:
            out.append(("post", k))
        out += [("ack", t, k) for t in range(tiles) if position[("ack", t, k)] < released]
    return out


@pytest.mark.parametrize("mode", ["pull", "ws"])
def test_wall_end_to_end(server, scene, mode):
    result = asyncio.run(walk(server, mode, scene))
    check(result, mode)


def test_ordering_check_catches_a_tile_running_ahead():
    """The barrier check is real: a tile acknowledging k + 1 before the barrier of k answered,
    or a frame posted before the previous barrier, are reported."""
    good = [("post", None, 0), ("ack", 0, 0), ("ack", 1, 0), ("barrier", None, 0),
            ("post", None, 1), ("ack", 1, 1), ("ack", 0, 1), ("barrier", None, 1)]
    assert ordering_violations(good, 2, 2) == []
    early_ack = [("post", None, 0), ("ack", 0, 0), ("post", None, 1), ("ack", 0, 1),
                 ("ack", 1, 0), ("barrier", None, 0), ("ack", 1, 1), ("barrier", None, 1)]
    assert ordering_violations(early_ack, 2, 2) == [("post", 1), ("ack", 0, 1)]
