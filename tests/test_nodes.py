"""Render nodes that drive several tiles: the node stream (one message per frame with all of a
node's tiles, one acknowledgement), in process (TestClient). Every list a node rebuilds is
compared with ``Session(...).frame(...)`` computed here, and every matrix it rebuilds with the
fits computed here."""

from __future__ import annotations

import asyncio
import json

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketDenialResponse

from wallcull_clients.node import NodeState
from wallcull.fit import FitOptions
from wallcull.paths import camera_path
from wallcull.pipeline import Session
from wallcull.scene import load
from wallcull.server import create_app
from wallcull.wall import Wall

TOKEN = "s3cret-t0ken"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
WALL = {"cols": 3, "rows": 2, "tile_size": [0.6, 0.34], "gap": [0.012, 0.012], "distance": 2.0}
NODES = [[0, 1, 2], [3, 5], [4]]


@pytest.fixture(scope="module")
def scene():
    return load("fatehpur")


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(None, token=TOKEN, state=None)) as c:
        yield c


@pytest.fixture
def wall(client):
    r = client.post("/walls", json={"wall": WALL, "scene": "fatehpur", "nodes": NODES},
                    headers=AUTH)
    assert r.status_code == 201, r.text
    body = r.json()
    yield body
    client.delete(f"/walls/{body['id']}", headers=AUTH)


def frames(scene, count):
    pts = scene.leaf_points[0]
    return [f.to_dict() for f in camera_path("fly", pts.min(0), pts.max(0),
                                             Wall.from_dict(WALL), count)]


def receive(ws, binary):
    raw = ws.receive_bytes() if binary else ws.receive_text().encode()
    return (msgpack.unpackb(raw) if binary else json.loads(raw)), len(raw)


@pytest.mark.parametrize("binary", [True, False])
def test_a_node_of_several_tiles_draws_every_frame_right(client, wall, scene, binary):
    wid, creds = wall["id"], wall["credentials"]
    token = creds["nodes"][0]["token"]  # tiles 0, 1, 2: implied by the credential
    reference = Session(scene, Wall.from_dict(WALL), fit=FitOptions())
    fmt = "msgpack" if binary else "json"
    node, sizes = NodeState(), {"full": [], "delta": []}
    with client.websocket_connect(f"/walls/{wid}/nodes/stream?format={fmt}&token={token}") as ws:
        for k, frame in enumerate(frames(scene, 48)[:12]):
            r = client.post(f"/walls/{wid}/frames", json={"frame": frame},
                            headers={"Authorization": f"Bearer {creds['driver']}"})
            assert r.status_code == 200, r.text
            message, size = receive(ws, binary)
            assert message["frame"] == k and [e["tile"] for e in message["tiles"]] == [0, 1, 2]
            if message["base"] is None:
                sizes["full"].append(size)
            else:  # against the same frame's full lists, made here
                whole, _ = client.app.state.server.walls.get(wid).node_message(
                    np.arange(3), k, full=True, binary=binary)
                sizes["delta"].append(size / len(whole))
            result = reference.frame(frame)
            start, leaves = result.visibility.leaf_lists()
            for tile in node.take(message):
                t = tile.tile
                assert tile.leaves.tolist() == leaves[start[t]:start[t + 1]].tolist(), (k, t)
                want = result.fits[t]
                for key in ("view", "projection"):
                    np.testing.assert_allclose(tile.matrices[key], want[key], rtol=0,
                                               atol=1e-9 * np.abs(want[key]).max())
            ws.send_bytes(msgpack.packb({"ack": k})) if binary else \
                ws.send_text(json.dumps({"ack": k}))
            barrier = client.get(f"/walls/{wid}/barrier/{k}?timeout=0").json()
            assert barrier["acked"] >= 3  # one acknowledgement took all three tiles
    assert len(sizes["full"]) == 1 and len(sizes["delta"]) == 11
    assert max(sizes["delta"]) <= 1, sizes["delta"]  # a delta never outgrows the lists


def test_a_node_asks_for_its_tiles_or_its_credential_implies_them(client, wall):
    wid, creds = wall["id"], wall["credentials"]
    token = creds["nodes"][1]["token"]  # tiles 3 and 5
    for query, status in ((f"tiles=3,4&token={token}", 403),  # 4 is another node's
                          (f"tiles=3-5&token={token}", 403),
                          (f"tiles=5&token={token}", None),
                          (f"token={token}", None),
                          (f"tiles=0-9&token={TOKEN}", 422),  # no tile 9 on a 3 x 2 wall
                          (f"tiles=2-1&token={TOKEN}", 422),
                          (f"token={TOKEN}", 422),  # the operator must say which
                          (f"tiles=1,0&token={TOKEN}", None),
                          ("tiles=0", 401)):
        url = f"/walls/{wid}/nodes/stream?{query}"
        if status is None:
            with client.websocket_connect(url):
                pass
            continue
        with pytest.raises(WebSocketDenialResponse) as exc:
            with client.websocket_connect(url):
                pass
        assert exc.value.status_code == status, (query, exc.value.content)


def test_full_lists_on_request_and_after_a_reconnection(client, wall, scene):
    wid, creds = wall["id"], wall["credentials"]
    driver = {"Authorization": f"Bearer {creds['driver']}"}
    url = f"/walls/{wid}/nodes/stream?token={creds['nodes'][0]['token']}"
    path = frames(scene, 6)
    with client.websocket_connect(url) as ws:
        for k in range(3):  # full, a delta, full again: asked for with the ack of frame 1
            client.post(f"/walls/{wid}/frames", json={"frame": path[k]}, headers=driver)
            message = msgpack.unpackb(ws.receive_bytes())
            assert (message["base"] is None) == (k != 1), k
            ws.send_bytes(msgpack.packb({"ack": k, **({"full": True} if k == 1 else {})}))
    with client.websocket_connect(url) as ws:  # a new stream holds nothing: full lists again
        message = msgpack.unpackb(ws.receive_bytes())  # the newest frame, at once
        assert message["frame"] == 2 and message["base"] is None
        assert all("visible" in e and "extent" in e and "depth" in e for e in message["tiles"])
        ws.send_bytes(msgpack.packb({"ack": 2}))
        client.post(f"/walls/{wid}/frames", json={"frame": path[3]}, headers=driver)
        message = msgpack.unpackb(ws.receive_bytes())
        assert message["frame"] == 3 and message["base"] == 2


def test_after_full_lists_no_delta_goes_against_a_frame_before_them(client, wall, scene):
    """A node that asked for full lists (it could not use a delta) got them, then deltas
    against what it had acknowledged before, until it acknowledged the full ones: unusable
    again, and the project's own nodes then asked again, for good."""
    wid, creds = wall["id"], wall["credentials"]
    driver = {"Authorization": f"Bearer {creds['driver']}"}
    path = frames(scene, 5)
    with client.websocket_connect(f"/walls/{wid}/nodes/stream?token="
                                  f"{creds['nodes'][0]['token']}") as ws:
        bases = []
        for k in range(5):
            client.post(f"/walls/{wid}/frames", json={"frame": path[k]}, headers=driver)
            bases.append(msgpack.unpackb(ws.receive_bytes())["base"])
            if k == 0:
                ws.send_bytes(msgpack.packb({"ack": 0}))
            if k == 1:  # this delta is of no use: full lists, please (no acknowledgement)
                ws.send_bytes(msgpack.packb({"full": True}))
            if k == 3:
                ws.send_bytes(msgpack.packb({"ack": 3}))
        assert bases == [None, 0, None, None, 3]


def test_two_nodes_on_the_same_tiles_each_get_deltas_against_what_they_hold(client, wall,
                                                                              scene):
    """Node A (tiles 0-2) acknowledges every frame; node B (tiles 1-2) joins late and falls
    behind, so the server stops sending to it (the window) while A moves on. B's next message
    is a delta against what B acknowledged, never against A's newer frames; and a node stuck
    in the window that asks for full lists gets them at once."""
    wid, creds = wall["id"], wall["credentials"]
    driver = {"Authorization": f"Bearer {creds['driver']}"}
    path = frames(scene, 30)
    reference = Session(scene, Wall.from_dict(WALL), fit=FitOptions())
    want = {}

    def post(k):
        r = client.post(f"/walls/{wid}/frames", json={"frame": path[k]}, headers=driver)
        assert r.status_code == 200, r.text
        start, leaves = reference.frame(path[k]).visibility.leaf_lists()
        want[k] = [leaves[start[t]:start[t + 1]].tolist() for t in range(6)]

    def take(node, ws):
        message = msgpack.unpackb(ws.receive_bytes())
        for tile in node.take(message):  # raises when the base is not held
            assert tile.leaves.tolist() == want[message["frame"]][tile.tile]
        return message

    a, b = NodeState(), NodeState()
    with client.websocket_connect(f"/walls/{wid}/nodes/stream?token="
                                  f"{creds['nodes'][0]['token']}") as ws_a:
        for k in range(10):
            post(k)
            assert take(a, ws_a)["frame"] == k
            ws_a.send_bytes(msgpack.packb({"ack": k}))
        with client.websocket_connect(f"/walls/{wid}/nodes/stream?tiles=1-2&token={TOKEN}") \
                as ws_b:
            first = take(b, ws_b)
            assert first["frame"] == 9 and first["base"] is None
            for k in range(10, 18):  # B acknowledges nothing: after 8 packets the window
                post(k)              # stops its stream (frame 17 is not sent to it)
                assert take(a, ws_a)["frame"] == k
                if k < 17:
                    ws_a.send_bytes(msgpack.packb({"ack": k}))
            assert [take(b, ws_b)["frame"] for _ in range(7)] == list(range(10, 17))
            ws_b.send_bytes(msgpack.packb({"ack": 9}))
            late = take(b, ws_b)  # the newest frame, against frame 9 (A acknowledged 16)
            assert late["base"] == 9 and late["frame"] == 17
            ws_a.send_bytes(msgpack.packb({"ack": 17}))
            for k in range(18, 30):
                post(k)
                assert take(a, ws_a)["frame"] == k
                ws_a.send_bytes(msgpack.packb({"ack": k}))
            ws_b.send_bytes(msgpack.packb({"full": True}))  # no ack: still in the window
            while True:  # what was sent before the request, then the full lists
                message = take(b, ws_b)
                if message["base"] is None:
                    break
            assert message["frame"] == 29


def test_a_cave_in_stereo_over_the_api(client, scene):
    """A wall given screen by screen, stereo frames: the node rebuilds each screen's own view
    and each eye's matrices, equal to the fits computed here; packets carry left and right."""
    from pathlib import Path

    cave = json.loads((Path(__file__).parent.parent / "examples" / "wall-cave.json").read_text())
    r = client.post("/walls", json={"wall": cave, "scene": "fatehpur"}, headers=AUTH)
    assert r.status_code == 201, r.text
    wid = r.json()["id"]
    assert r.json()["wall"]["screens"] and r.json()["tiles"] == len(cave["screens"])
    try:
        reference = Session(scene, Wall.from_dict(cave), fit=FitOptions())
        pts = scene.leaf_points[0]
        centre = (pts.min(0) + pts.max(0)) / 2
        node = NodeState()
        with client.websocket_connect(f"/walls/{wid}/nodes/stream?tiles=all&token={TOKEN}") \
                as ws:
            for k in range(3):
                frame = {"position": (centre + [k * 2.0, 1.0, 0.0]).tolist(),
                         "orientation": [1.0, 0.0, 0.0, 0.0],
                         "stereo": {"ipd": 0.064, "head": [0.9950041652780258, 0.0,
                                                           0.09983341664682815, 0.0]}}
                r = client.post(f"/walls/{wid}/frames", json={"frame": frame}, headers=AUTH)
                assert r.status_code == 200, r.text
                result = reference.frame(frame)
                start, leaves = result.visibility.leaf_lists()
                message = msgpack.unpackb(ws.receive_bytes())
                assert "view" not in message  # each screen has its own
                for tile in node.take(message):
                    t, want = tile.tile, result.fits[tile.tile]
                    assert tile.leaves.tolist() == leaves[start[t]:start[t + 1]].tolist()
                    for eye in ("left", "right"):
                        for key in ("view", "projection"):
                            np.testing.assert_allclose(
                                tile.matrices[eye][key], want[eye][key], rtol=0,
                                atol=1e-9 * np.abs(want[eye][key]).max())
                ws.send_bytes(msgpack.packb({"ack": k}))
        pkt = client.get(f"/walls/{wid}/tiles/0/packets/2", headers=AUTH).json()
        assert {"left", "right"} <= set(pkt) and "row" not in pkt
    finally:
        client.delete(f"/walls/{wid}", headers=AUTH)


# --------------------------------------------------------------------------- the frame stream


@pytest.mark.parametrize("binary", [True, False])
def test_frames_over_one_connection(client, wall, scene, binary):
    """A tracker posts frame after frame on the frame stream: each answered in order with its
    number; a refused frame gets its reason and the stream goes on; nodes see every frame."""
    wid, creds = wall["id"], wall["credentials"]
    fmt = "msgpack" if binary else "json"
    pack, unpack = (msgpack.packb, msgpack.unpackb) if binary else \
        (lambda o: json.dumps(o), json.loads)
    path = frames(scene, 4)
    node_url = f"/walls/{wid}/nodes/stream?token={creds['nodes'][0]['token']}"
    with client.websocket_connect(f"/walls/{wid}/frames/stream?format={fmt}"
                                  f"&token={creds['driver']}") as driver, \
            client.websocket_connect(node_url) as node:
        send = driver.send_bytes if binary else driver.send_text
        receive = driver.receive_bytes if binary else driver.receive_text
        answers = []
        for k, frame in enumerate(path):
            send(pack({"frame": frame}))
            answers.append(unpack(receive()))
            if k == 1:  # not a unit quaternion: refused, with its reason
                send(pack({"frame": {**frame, "orientation": [1, 1, 0, 0]}}))
                refused = unpack(receive())
                assert refused["status"] == 422 and "unit quaternion" in refused["error"]
                send(pack({"frame": frame, "bogus": 1}))
                refused = unpack(receive())
                assert refused["status"] == 422 and "bogus" in refused["error"]
        assert [a["frame"] for a in answers] == [0, 1, 2, 3]
        assert all(a["timings"]["total_ms"] > 0 for a in answers)
        seen = [msgpack.unpackb(node.receive_bytes())["frame"]]
        while seen[-1] < 3:
            seen.append(msgpack.unpackb(node.receive_bytes())["frame"])
    assert seen == sorted(seen) and seen[-1] == 3


def test_the_frame_stream_needs_the_drivers_credential(client, wall):
    wid, creds = wall["id"], wall["credentials"]
    for token, status in ((creds["nodes"][0]["token"], 403), ("nope", 401), (None, 401)):
        query = f"?token={token}" if token else ""
        with pytest.raises(WebSocketDenialResponse) as exc:
            with client.websocket_connect(f"/walls/{wid}/frames/stream{query}"):
                pass
        assert exc.value.status_code == status


# --------------------------------------------------------------------------- one NATS subject


class _Broker:
    """The NATS broker as the server's publisher sees it: every message published on the
    subject goes, in order, to every subscriber's queue (as NATS delivers it)."""

    def __init__(self):
        self.queues: dict[str, list] = {}

    async def publish(self, subject, data):
        for queue in self.queues.values():
            queue.append(data)


class _Msg:
    def __init__(self, subject, data):
        self.subject, self.data, self.reply, self.answer = subject, data, "inbox", None

    async def respond(self, data):
        self.answer = data


class _Subject:
    """The real NATS bridge (its publisher task, its ack and full handlers) on one node
    subject of a wall, with render nodes (``NodeState``) that take its messages in order."""

    def __init__(self, scene):
        from wallcull.fit import FitOptions
        from wallcull.server.metrics import Metrics
        from wallcull.server.nats import NatsBridge
        from wallcull.service import Walls

        self.walls = Walls()
        self.session = self.walls.create(scene, Wall.from_dict(WALL), "adaptive", "obb", False,
                                          64, FitOptions(), nodes=[list(range(6))])
        self.bridge = NatsBridge("nats://unused", self.walls, Metrics())
        self.bridge.nc = self.broker = _Broker()
        self.path = frames(scene, 60)
        self.nodes: dict[str, NodeState] = {}
        self.misses: list[tuple[str, int, int]] = []

    def subject(self, kind):
        return self.bridge.subject(self.session.id, kind, 0)

    async def start(self):
        self.bridge.watch(self.session)
        await asyncio.sleep(0)

    async def post(self, publish: bool = True) -> int:
        """Post the next frame; with ``publish``, let the publisher take it (else the next
        post comes first, and the publisher skips this one, as it does when frames come
        faster than it runs)."""
        number, _ = self.session.post_frame(self.path[self.session.latest + 1])
        # the publisher runs at the loop's next turns (it publishes nothing when every
        # subscriber has left the window)
        for _ in range(100 if publish else 0):
            if self.bridge.nodes[self.session.id, "0"].sent >= number:
                break
            await asyncio.sleep(0)
        return number

    async def join(self, name: str) -> int:
        """Subscribe, ask for full lists, draw them and acknowledge: the frame drawn."""
        self.broker.queues[name], self.nodes[name] = [], NodeState()
        msg = _Msg(self.subject("full"), msgpack.packb({"node": name}))
        await self.bridge._full(msg)
        return await self._draw(name, msgpack.unpackb(msg.answer))

    async def take(self, name: str) -> int | None:
        """The node takes the next message of its queue: draws it and acknowledges, skips
        it (published before its full lists), or misses its base (then joins again)."""
        message = msgpack.unpackb(self.broker.queues[name].pop(0))
        node = self.nodes[name]
        if message["frame"] <= node.frame:
            return None
        if not node.holds(message["base"]):
            self.misses.append((name, message["frame"], message["base"]))
            return await self.join(name)
        return await self._draw(name, message)

    async def _draw(self, name: str, message: dict) -> int:
        self.nodes[name].take(message)
        await self.bridge._ack(_Msg(self.subject("ack"), msgpack.packb(
            {"ack": message["frame"], "node": name})))
        return message["frame"]

    async def close(self):
        self.session.close()
        await asyncio.gather(*self.bridge.tasks.values(), return_exceptions=True)


def _on_one_subject(scene, script) -> list:
    async def run():
        subject = _Subject(scene)
        await subject.start()
        try:
            await script(subject)
        finally:
            await subject.close()
        return subject.misses

    return asyncio.run(run())


def test_a_slow_node_that_is_forgotten_and_comes_back_holds_every_base(scene):
    """The failure seen once beside four CPU hogs, step by step: node A falls more than the
    window behind, so the subject's deltas go against what B acknowledged (A, taking them in
    order, drops every frame before that base); frames then slow down, A comes back within the
    window with an acknowledgement older than that base, and the next delta went against it:
    a frame A had dropped. Every delta's base is now at least every base sent before."""
    async def script(s):
        await s.post()
        await s.join("a")
        for _ in range(3):
            await s.post()
            await s.take("a")
        assert await s.join("b") == 3
        for _ in range(9):  # A is silent; B keeps up, and A leaves the window at frame 12
            await s.post()
            await s.take("b")
        for _ in range(5):  # A catches up to frame 8 (frames 4 to 11 are against 3)
            await s.take("a")
        await s.post()  # frame 13: A is within the window again
        while s.broker.queues["a"]:
            await s.take("a")  # frame 12 is against 11 (A drops 8), then frame 13

    assert _on_one_subject(scene, script) == []


def test_a_frame_only_the_newcomer_holds_is_no_base(scene):
    """A newcomer's full lists are the newest frame when it asks; when frames come faster than
    the publisher runs, that frame may never be published on the subject, so the other nodes
    do not hold it, and a delta against it (the oldest acknowledgement) missed on them."""
    async def script(s):
        await s.post()
        await s.join("a")
        await s.post(publish=False)  # frame 1: B's full lists, skipped by the publisher
        assert await s.join("b") == 1
        await s.post()  # frame 2: full lists (B's since is 1); A draws it first
        await s.take("a")
        await s.post()  # frame 3: the oldest acknowledgement is B's, frame 1
        for name in "ab":
            while s.broker.queues[name]:
                await s.take(name)

    assert _on_one_subject(scene, script) == []


@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.sampled_from("ppsabcc"), min_size=10, max_size=90))
def test_nodes_on_one_subject_hold_every_base_whatever_the_interleaving(scene, steps):
    """Three nodes on one subject, frames posted (``p``), or posted and skipped by the
    publisher (``s``), and each node taking its next message (``a``, ``b``, ``c``; joining
    first) in any order: no node ever gets a delta against a frame it does not hold."""
    async def script(s):
        for step in steps:
            if step in "ps" and s.session.latest < len(s.path) - 2:
                await s.post(step == "p" or s.session.latest < 0)
            elif step in "abc" and s.session.latest >= 0:
                if step not in s.nodes:
                    await s.join(step)
                elif s.broker.queues[step]:
                    await s.take(step)

    assert _on_one_subject(scene, script) == []


def test_a_publish_the_broker_refuses_costs_that_frame_of_that_node_alone(scene):
    """One publish refused (a message over the broker's max_payload, a full buffer) stopped
    the wall's publisher for good, for every node; now that node misses that frame, the
    others get theirs, and the next frame is tried again."""
    from wallcull.fit import FitOptions
    from wallcull.server.metrics import Metrics
    from wallcull.server.nats import NatsBridge
    from wallcull.service import Walls

    class Refusing(_Broker):
        refuse = True

        async def publish(self, subject, data):
            if subject.endswith(".node.0") and self.refuse:
                raise ValueError("nats: maximum payload exceeded")
            self.queues.setdefault(subject, []).append(data)

    walls = Walls()
    seen = []
    walls.on_add.append(seen.append)
    session = walls.create(scene, Wall.from_dict(WALL), "adaptive", "obb", False, 64,
                           FitOptions(), nodes=[[0, 1, 2], [3, 4, 5]])
    assert seen == [session]  # a wall joining is handed to whoever publishes walls
    bridge = NatsBridge("nats://unused", walls, Metrics())
    bridge.nc = broker = Refusing()
    path = frames(scene, 4)

    async def scenario():
        bridge.watch(session)
        for k in range(4):
            if k == 2:
                broker.refuse = False
            session.post_frame(path[k])
            for _ in range(200):
                if len(broker.queues.get(bridge.subject(session.id, "node", 3), [])) > k:
                    break
                await asyncio.sleep(0)
            await bridge._ack(_Msg(bridge.subject(session.id, "ack", 3),
                                   msgpack.packb({"ack": k})))
        for _ in range(100):
            await asyncio.sleep(0)
        assert not bridge.tasks[session.id].done()
        bridge.tasks[session.id].cancel()

    asyncio.run(scenario())
    assert len(broker.queues[bridge.subject(session.id, "node", 3)]) == 4
    # refused until frame 2, then published (and, with nobody acknowledging it, no more)
    assert [msgpack.unpackb(m)["frame"] for m in
            broker.queues[bridge.subject(session.id, "node", 0)]] == [2]


def test_full_requests_neither_lift_the_window_nor_keep_a_silent_stream_open(scene):
    """A node that acknowledges nothing but asks for full lists again and again was sent a
    full message per request past the window of 8, and never closed as idle."""
    from starlette.websockets import WebSocketDisconnect

    from wallcull.limits import Limits
    from wallcull.server.streams import STREAM_WINDOW

    with TestClient(create_app(None, token=TOKEN, state=None,
                               limits=Limits(stream_idle=2.0))) as c:
        info = c.post("/walls", json={"wall": WALL, "scene": "fatehpur", "nodes": NODES},
                      headers=AUTH).json()
        wid, creds = info["id"], info["credentials"]
        driver = {"Authorization": f"Bearer {creds['driver']}"}
        received = 0
        with c.websocket_connect(f"/walls/{wid}/nodes/stream?token="
                                 f"{creds['nodes'][0]['token']}") as ws:
            for frame in frames(scene, 20):
                c.post(f"/walls/{wid}/frames", json={"frame": frame}, headers=driver)
                ws.send_bytes(msgpack.packb({"full": True}))
            with pytest.raises(WebSocketDisconnect) as closed:
                while True:
                    ws.receive_bytes()
                    received += 1
        assert received <= STREAM_WINDOW + 1 and closed.value.code == 4408, received


def test_nats_full_requests_answer_for_this_servers_walls_alone(scene):
    """Another server's wall (on one broker, one prefix) is left to that server: it was
    answered with an error, which often came first. A wall waiting for its scene is answered
    with why (it was not answered at all). And a stop with the broker away goes on (a drain
    that fails is followed by a close)."""
    from wallcull.fit import FitOptions
    from wallcull.persist import WallRow
    from wallcull.server.metrics import Metrics
    from wallcull.server.nats import NatsBridge
    from wallcull.service import Walls

    walls = Walls()
    session = walls.create(scene, Wall.from_dict(WALL), "adaptive", "obb", False, 64,
                           FitOptions(), nodes=[list(range(6))])
    walls.unavailable["0123456789ab"] = (WallRow("0123456789ab", 0.0, {}, -1, None),
                                         "its scene 'gone.glb' cannot be loaded")
    bridge = NatsBridge("nats://unused", walls, Metrics())

    class Away:
        closed = False

        async def drain(self):
            raise ConnectionError("nats: connection closed")

        async def close(self):
            self.closed = True

    async def scenario():
        bridge.nc = away = Away()
        bridge.watch(session)
        await asyncio.sleep(0)  # its publisher holds the wall's nodes
        others, waiting, ours = (_Msg(f"wallcull.{wid}.full.0", b"") for wid in (
            "fedcba987654", "0123456789ab", session.id))
        for msg in (others, waiting, ours):
            await bridge._full(msg)
        await bridge.close()
        return others.answer, msgpack.unpackb(waiting.answer), msgpack.unpackb(ours.answer), away

    others, waiting, ours, away = asyncio.run(scenario())
    assert others is None
    assert "unavailable" in waiting["error"] and "gone.glb" in waiting["error"]
    assert ours["error"] == "no frame yet"
    assert away.closed
