"""End to end on loopback: a real ``wallcull serve`` subprocess, the driver and simulated
render nodes of a 4 x 4 wall over the power plant's orbit (500 frames; 200 for nodes of four
tiles).

Checked exactly, for every transport (long-polling every frame number; WebSocket streams of one
tile each; node streams of four tiles; node messages through a real NATS broker), with a
driver that waits on the swap barrier, so nothing is conflated:

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
import time
from pathlib import Path

import numpy as np
import pytest

from wallcull_clients import broker
from wallcull_clients.driver import Driver
from wallcull_clients.sim import run_wall
from wallcull_clients.loadtest import Server, running_server
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
def nats_server():
    """A real nats-server, and a wallcull server publishing there: ``(url, broker url)``."""
    if broker.find() is None:
        pytest.skip("no nats-server (Debian package nats-server; .ci/run installs it)")
    with broker.Broker() as nats, running_server(TOKEN, args=["--nats", nats.url]) as url:
        yield url, nats.url


@pytest.fixture(scope="module")
def scene():
    return load(SCENE)


def expected_lists(scene, frames):
    """Per frame, the in-process culler's CSR ``(start, leaves)`` for the same frame dicts."""
    session = Session(scene, Wall.from_dict(WALL))
    return [session.frame(f).visibility.leaf_lists() for f in frames]


async def walk(url: str, mode: str, scene, frames_count: int = FRAMES,
               tiles_per_node: int = 1, nats: str | None = None):
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
        groups = [list(range(k, k + tiles_per_node)) for k in range(0, 16, tiles_per_node)]
        info = await driver.create_wall(SCENE, WALL,
                                        nodes=groups if tiles_per_node > 1 else None)
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
            on_list=on_list, on_event=node_event, ready=lambda clients: ready.set(),
            tiles_per_node=tiles_per_node, nats=nats))
        await asyncio.wait_for(ready.wait(), 60)
        if mode == "ws" and nats is None:
            assert await driver.wait_clients(wid, len(groups), 30) == len(groups)
        await driver.stream_frames(wid)
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
    stats = [s for c in result["clients"]
             for s in getattr(c, "tile_stats", {c.tile: c.stats}).values()]
    assert sorted(s.tile for s in stats) == list(range(tiles))
    for s in stats:
        assert s.errors == [], (s.tile, s.errors[:3])
        assert s.frame == list(range(n)), f"tile {s.tile} missed or reordered frames"
        assert result["received"][s.tile] == list(range(n))
    assert result["mismatches"] == [], result["mismatches"][:5]
    deltas = sum(len(s.full) - sum(s.full) for s in stats)
    # (a node's tile whose delta would be no shorter than its list gets the list)
    assert deltas > (0.9 if mode == "pull" or len(stats) == len(result["clients"]) else 0.5) \
        * tiles * n, "the packets were deltas, and the deltas were checked"
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


def test_nodes_of_four_tiles_end_to_end(server, scene):
    result = asyncio.run(walk(server, "ws", scene, 200, tiles_per_node=4))
    assert len(result["clients"]) == 4
    check(result, "ws")


def test_nodes_over_nats_end_to_end(nats_server, scene):
    """The same checks with the node messages and acknowledgements through a NATS broker."""
    url, nats = nats_server
    result = asyncio.run(walk(url, "ws", scene, 200, tiles_per_node=4, nats=nats))
    assert len(result["clients"]) == 4
    check(result, "ws")


def test_two_nodes_on_the_same_subject_over_nats(nats_server, scene):
    """Two render nodes take the same NATS subject (a node of all 16 tiles): the first draws
    slower than frames come at 60 Hz, the second joins later and keeps up. Each message is one
    both can use (deltas against what both acknowledged, full lists until the newcomer has
    acknowledged), so neither ever misses a base, and both rebuild every frame's lists
    exactly."""
    url, nats = nats_server
    count = 120

    async def scenario():
        async with Driver(url, TOKEN) as driver:
            info = await driver.create_wall(SCENE, WALL, nodes=[list(range(16))])
            wid = info["id"]
            frames = await driver.frames(SCENE, info["wall"], "orbit", count)
            expected = expected_lists(scene, frames)
            mismatches, seen = [], {0: asyncio.Event()}

            def checker(tile, frame, leaves):
                start, want = expected[frame]
                if not np.array_equal(leaves, want[start[tile]:start[tile + 1]]):
                    mismatches.append((frame, tile))
                if frame >= 20:
                    seen[0].set()

            def nodes(draw_time, ready=None):
                return asyncio.create_task(run_wall(
                    url, wid, "all", token=TOKEN, until=count - 1, idle_timeout=30,
                    on_list=checker, nats=nats, draw_time=draw_time,
                    ready=lambda clients: ready.set() if ready else None))

            subscribed = asyncio.Event()
            first = nodes(0.02, subscribed)  # behind, more and more
            await asyncio.wait_for(subscribed.wait(), 60)
            await driver.stream_frames(wid)
            posting = asyncio.create_task(driver.run(wid, frames, rate=60))
            await asyncio.wait_for(seen[0].wait(), 60)
            second = nodes(0.0)  # joins while the first is still drawing older frames
            clients = [c for group in await asyncio.gather(first, second) for c in group]
            await posting
            await driver.call("DELETE", f"/walls/{wid}", auth=True)
            return clients, mismatches

    clients, mismatches = asyncio.run(scenario())
    assert len(clients) == 2 and mismatches == []
    for client in clients:
        stats = client.tile_stats[0]
        assert stats.errors == [] and client.stats.base_misses == 0
        assert stats.frame[-1] == count - 1 and len(stats.frame) > 20
        # deltas, all of them used (a tile with an empty list gets it, no longer than a delta)
        entries = [full for s in client.tile_stats.values()
                   for full, n in zip(s.full, s.leaves) if n > 0]
        assert sum(not full for full in entries) > 0.5 * len(entries)


def test_ordering_check_catches_a_tile_running_ahead():
    """The barrier check is real: a tile acknowledging k + 1 before the barrier of k answered,
    or a frame posted before the previous barrier, are reported."""
    good = [("post", None, 0), ("ack", 0, 0), ("ack", 1, 0), ("barrier", None, 0),
            ("post", None, 1), ("ack", 1, 1), ("ack", 0, 1), ("barrier", None, 1)]
    assert ordering_violations(good, 2, 2) == []
    early_ack = [("post", None, 0), ("ack", 0, 0), ("post", None, 1), ("ack", 0, 1),
                 ("ack", 1, 0), ("barrier", None, 0), ("ack", 1, 1), ("barrier", None, 1)]
    assert ordering_violations(early_ack, 2, 2) == [("post", 1), ("ack", 0, 1)]


async def _acked(driver, wid: str, number: int, tiles: int, deadline: float = 120.0) -> int:
    """How many tiles the barrier counts as having drawn frame ``number``, read until it is
    ``tiles`` (a node's, where the wall has more: the barrier itself never completes)."""
    end = time.monotonic() + deadline
    while True:
        acked = (await driver.barrier(wid, number, 0.05))["acked"]
        if acked >= tiles or time.monotonic() > end:
            return acked


def test_a_node_that_joins_late_over_nats_asks_for_full_lists(nats_server, scene):
    """Raw NATS, as a lab's own client would speak it: subscribe, request full lists, draw,
    acknowledge; the next message is a delta against that frame; a node that stops
    acknowledging is published nothing more after the window, and comes back when it
    acknowledges what it was sent."""
    import jsonschema
    import msgpack
    import nats as nats_py

    from wallcull.server.asyncapi import schema
    from wallcull.server.nats import WINDOW

    url, broker_url = nats_server

    async def scenario():
        async with Driver(url, TOKEN) as driver:
            info = await driver.create_wall(SCENE, WALL, nodes=[[0, 1, 2, 3]])
            wid = info["id"]
            assert info["nodes"][0] == [0, 1, 2, 3]
            frames = await driver.frames(SCENE, info["wall"], "orbit", 30)
            await driver.stream_frames(wid)
            for frame in frames[:5]:
                await driver.post(wid, frame)
            nc = await nats_py.connect(broker_url)
            sub = await nc.subscribe(f"wallcull.{wid}.node.0")
            full = msgpack.unpackb((await nc.request(f"wallcull.{wid}.full.0", b"",
                                                     timeout=60)).data)
            assert full["frame"] == 4 and full["base"] is None
            jsonschema.validate(full, schema("NodeMessage"))  # the AsyncAPI document's
            assert [e["tile"] for e in full["tiles"]] == [0, 1, 2, 3]
            session = Session(scene, Wall.from_dict(WALL))
            start, leaves = session.frame(frames[4]).visibility.leaf_lists()
            assert full["tiles"][2]["visible"] == leaves[start[2]:start[3]].tolist()
            await nc.publish(f"wallcull.{wid}.ack.0", msgpack.packb({"ack": 4}))
            await nc.flush()
            # the barrier counts the node's four tiles once the acknowledgement is in
            assert await _acked(driver, wid, 4, 4) == 4
            await driver.post(wid, frames[5])
            delta = msgpack.unpackb((await sub.next_msg(timeout=60)).data)
            assert delta["frame"] == 5 and delta["base"] == 4
            jsonschema.validate(delta, schema("NodeMessage"))
            for frame in frames[6:6 + 2 * WINDOW]:  # no more acknowledgements
                await driver.post(wid, frame)
            got = []  # what the window lets through, however slowly it comes ...
            while len(got) < WINDOW - 1:
                got.append(msgpack.unpackb((await sub.next_msg(timeout=60)).data)["frame"])
            with pytest.raises(nats_py.errors.TimeoutError):  # ... then silence
                await sub.next_msg(timeout=0.5)
            assert got == list(range(6, 5 + WINDOW))  # it stopped acknowledging
            # late acknowledgements of what it was sent bring it back (its window counts the
            # frames it was sent, not the frames posted meanwhile)
            await nc.publish(f"wallcull.{wid}.ack.0", msgpack.packb({"ack": got[-1]}))
            await nc.flush()
            assert await _acked(driver, wid, got[-1], 4) == 4  # taken in
            await driver.post(wid, frames[6 + 2 * WINDOW])
            back = msgpack.unpackb((await sub.next_msg(timeout=60)).data)
            assert back["frame"] == 6 + 2 * WINDOW and back["base"] == got[-1]
            await nc.drain()
            await driver.call("DELETE", f"/walls/{wid}", auth=True)

    asyncio.run(scenario())


def test_a_brokers_password_is_never_shown():
    """A broker URL's user, password or token never reaches what the server shows: ``/health``
    (which needs no credential) while the broker is away, and the server's log."""
    import httpx

    from wallcull.credentials import shown

    assert shown("nats://u:pw@h:4222,nats://tok@g:4222,nats://h") == \
        "nats://***@h:4222,nats://***@g:4222,nats://h"
    if broker.find() is None:
        pytest.skip("no nats-server (Debian package nats-server; .ci/run installs it)")
    secret = "s3cret-pw"
    away = broker.Broker(user="wall", password=secret).start()

    async def scenario():
        async with Server(TOKEN, log_level="info", args=["--nats", away.url]) as server, \
                httpx.AsyncClient() as http:
            away.stop()
            deadline = time.monotonic() + 60
            while not (problems := (await http.get(f"{server.url}/health")).json()["problems"]):
                assert time.monotonic() < deadline, "health never said the broker is away"
                await asyncio.sleep(0.1)
            assert "***@127.0.0.1" in " ".join(problems), problems
            assert secret not in (await http.get(f"{server.url}/health")).text
            return server.output()

    try:
        log = asyncio.run(scenario())
    finally:
        away.stop()
    assert "NATS" in log and "went away" in log and secret not in log, log


def test_nodes_over_nats_ride_out_a_broker_restart(scene):
    """The broker away for a while, then back on its address. What the server published
    meanwhile reached no one, and it stopped publishing for good once no acknowledgement came
    for a window of frames, while health said all was well. Now health says the broker is
    away, and once it is back every node gets frames again, in full first."""
    import httpx

    if broker.find() is None:
        pytest.skip("no nats-server (Debian package nats-server; .ci/run installs it)")
    first = broker.Broker().start()
    try:
        with running_server(TOKEN, args=["--nats", first.url]) as url:
            async def scenario():
                async with Driver(url, TOKEN) as driver, httpx.AsyncClient() as http:
                    info = await driver.create_wall(SCENE, WALL, nodes=[list(range(8)),
                                                                       list(range(8, 16))])
                    wid = info["id"]
                    frames = await driver.frames(SCENE, info["wall"], "orbit", 40)
                    nodes = asyncio.create_task(run_wall(
                        url, wid, "all", token=TOKEN, until=39, tiles_per_node=8,
                        nats=first.url, reconnect_for=120))
                    for frame in frames[:10]:
                        await driver.post(wid, frame)
                        await asyncio.sleep(0.05)
                    first.stop()
                    deadline = time.monotonic() + 60
                    while "NATS" not in " ".join((await http.get(f"{url}/health")).json()
                                                 ["problems"]):
                        assert time.monotonic() < deadline, "health never said so"
                        await asyncio.sleep(0.1)
                    for frame in frames[10:20]:  # culled and served; published to no one
                        await driver.post(wid, frame)
                    again = broker.Broker(first.port).start()
                    try:
                        while (await http.get(f"{url}/health")).json()["status"] != "ok":
                            assert time.monotonic() < deadline + 60, "never back"
                            await asyncio.sleep(0.1)
                        for frame in frames[20:]:
                            await driver.post(wid, frame)
                            await asyncio.sleep(0.05)
                        clients = await asyncio.wait_for(nodes, 120)
                    finally:
                        again.stop()
                return clients

            clients = asyncio.run(scenario())
            for c in clients:
                for s in c.tile_stats.values():
                    assert s.errors == [] and s.frame[-1] == 39, (s.tile, s.frame[-5:])
    finally:
        first.stop()
