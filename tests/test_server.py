"""The HTTP and WebSocket API (wallcull.server), in process (TestClient) and on a real uvicorn
server: codecs and negotiation, bad input, tokens, scene names, uploads, long walkthroughs
with simulated render nodes, dynamic updates, the swap barrier, caching, history, limits,
deletion and metrics.

Every list a simulated node holds is compared with ``Session(...).frame(...)`` computed here,
in this process, for the same frame.
"""

from __future__ import annotations

import base64
import json
import logging
import pathlib
import math
import os
import re
import socket
import struct
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from types import SimpleNamespace

import httpx
import msgpack
import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from starlette.testclient import WebSocketDenialResponse
from starlette.websockets import WebSocketDisconnect

from wallcull_clients.hostile import glb as glb_build
from wallcull.paths import camera_path
from wallcull.pipeline import Session
from wallcull.scene import Scene, load
from wallcull.server import create_app, uvicorn_options
from wallcull.server.messages import ConsoleStatus
from wallcull.service import LIVE
from wallcull.wall import Wall

from .test_protocol import Holder

TOKEN = "s3cret-t0ken"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
MP = "application/msgpack"
WALL = {"cols": 3, "rows": 2, "tile_size": [0.6, 0.34], "gap": [0.012, 0.012], "distance": 2.0}
FRAME = {"position": [0.0, 20.0, 300.0], "orientation": [1.0, 0.0, 0.0, 0.0]}
MAX_BODY = 64 << 10
MAX_UPLOAD = 256 << 10


# --------------------------------------------------------------------------- scenes and GLBs


def boxes_glb(names=("left", "right"), spread=3.0) -> bytes:
    """A small GLB: one unit box per name, side by side 10 m in front of the origin."""
    s = trimesh.Scene()
    for k, name in enumerate(names):
        m = np.eye(4)
        m[:3, 3] = [spread * (k - (len(names) - 1) / 2), 0, -10]
        s.add_geometry(trimesh.creation.box(extents=[1, 1, 1]), node_name=name, geom_name=name,
                       transform=m)
    return s.export(file_type="glb")


def glb_parts(data: bytes) -> tuple[dict, bytes]:
    (length,) = struct.unpack("<I", data[12:16])
    doc = json.loads(data[20:20 + length])
    rest = data[20 + length:]
    return doc, rest[8:8 + struct.unpack("<I", rest[:4])[0]] if rest else b""


def glb_from_bytes(data: bytes, name: str) -> Scene:
    import io

    return Scene.from_trimesh(trimesh.load(io.BytesIO(data), file_type="glb"), name=name)


@pytest.fixture(scope="module")
def fatehpur() -> Scene:
    """The bundled scene, loaded here: the reference the server is held to."""
    return load("fatehpur")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """A scene folder with one scene, a symlink pointing out of it, a subfolder and a text
    file; beside it, outside, a secret scene and a secret text."""
    root = tmp_path_factory.mktemp("server")
    scenes, outside = root / "scenes", root / "outside"
    scenes.mkdir()
    outside.mkdir()
    (scenes / "two.glb").write_bytes(boxes_glb())
    (outside / "secret.glb").write_bytes(boxes_glb(("secret_a", "secret_b", "secret_c")))
    (outside / "secret.txt").write_text("TOP SECRET")
    os.symlink(outside / "secret.glb", scenes / "escape.glb")
    os.symlink(outside / "secret.txt", scenes / "escape.txt")
    (scenes / "sub").mkdir()
    (scenes / "sub" / "two.glb").write_bytes(boxes_glb())
    (scenes / "notes.txt").write_text("not a scene")
    return SimpleNamespace(root=root, scenes=scenes, outside=outside)


@pytest.fixture(scope="module")
def client(folder):
    app = create_app(folder.scenes, token=TOKEN, max_body=MAX_BODY, max_upload=MAX_UPLOAD)
    with TestClient(app) as c:
        yield c


def new_wall(client, scene="fatehpur", wall=WALL, **extra) -> str:
    r = client.post("/walls", json={"wall": wall, "scene": scene, **extra}, headers=AUTH)
    assert r.status_code == 201, r.text
    return r.json()["id"]


@pytest.fixture
def wid(client):
    wid = new_wall(client)
    yield wid
    client.delete(f"/walls/{wid}", headers=AUTH)


def post_frame(client, wid, frame=FRAME, **extra) -> dict:
    r = client.post(f"/walls/{wid}/frames", json={"frame": frame, **extra}, headers=AUTH)
    assert r.status_code == 200, r.text
    return r.json()


def reference(scene: Scene, wall: dict, frame, updates=None, session=None):
    """Per-tile leaf lists of a frame, computed in this process."""
    session = session or Session(scene, Wall.from_dict(wall))
    if updates:
        session.move(updates)
    start, leaves = session.frame(frame).visibility.leaf_lists()
    return [leaves[start[t]:start[t + 1]] for t in range(len(start) - 1)]


def fly(scene: Scene, wall: dict, frames: int) -> list[dict]:
    pts = scene.leaf_points[0]
    return [f.to_dict() for f in camera_path("fly", pts.min(0), pts.max(0), Wall.from_dict(wall),
                                             frames)]


def metrics(client) -> dict:
    """``{(name, labels...): value}`` of every sample on /metrics."""
    out = {}
    for family in text_string_to_metric_families(client.get("/metrics").text):
        for s in family.samples:
            out[(s.name, *sorted(s.labels.items()))] = s.value
    return out


def metric(m: dict, name: str, **labels) -> float:
    return m.get((name, *sorted((k, str(v)) for k, v in labels.items())), 0.0)


# --------------------------------------------------------------------------- render nodes


class HttpNode:
    """A render node that pulls packets over HTTP (JSON or msgpack) and acknowledges them."""

    def __init__(self, client, wid, tile, binary=False):
        self.client, self.wid, self.tile, self.binary = client, wid, tile, binary
        self.node = Holder()
        self.sizes = {"full": 0, "delta": 0}

    def fetch(self, number, full=False) -> dict:
        headers = {**AUTH, "Accept": MP if self.binary else "application/json"}
        r = self.client.get(f"/walls/{self.wid}/tiles/{self.tile}/packets/{number}",
                            params={"full": str(full).lower(), "wait": 0}, headers=headers)
        assert r.status_code == 200, r.text
        assert r.headers["content-type"] == (MP if self.binary else "application/json")
        pkt = msgpack.unpackb(r.content) if self.binary else r.json()
        assert (pkt["frame"], pkt["tile"]) == (number, self.tile)
        if full:
            assert pkt["base"] is None
        self.sizes["full" if pkt["base"] is None else "delta"] += len(r.content)
        self.node.take(pkt)
        return pkt

    def ack(self, number):
        r = self.client.post(f"/walls/{self.wid}/tiles/{self.tile}/ack", json={"frame": number},
                             headers=AUTH)
        assert r.status_code == 204, r.text


class WsNode:
    """A render node on the WebSocket stream (TestClient), msgpack or JSON."""

    def __init__(self, client, wid, tile, binary=True, token=TOKEN):
        fmt = "msgpack" if binary else "json"
        query = f"?format={fmt}" + (f"&token={token}" if token else "")
        self.cm = client.websocket_connect(f"/walls/{wid}/tiles/{tile}/stream{query}")
        self.ws = self.cm.__enter__()
        self.binary, self.tile = binary, tile
        self.node = Holder()
        self.received = []
        self.sizes = {"full": 0, "delta": 0}

    def message(self) -> dict:
        raw = self.ws.receive_bytes() if self.binary else self.ws.receive_text().encode()
        msg = msgpack.unpackb(raw) if self.binary else json.loads(raw)
        if "base" in msg:
            self.sizes["full" if msg["base"] is None else "delta"] += len(raw)
        return msg

    def until(self, number, check) -> None:
        """Take packets until frame ``number``'s, checking each."""
        while True:
            pkt = self.message()
            assert "error" not in pkt, pkt
            assert pkt["tile"] == self.tile
            self.node.take(pkt)
            self.received.append(pkt)
            check(pkt["frame"], self.tile, self.node.current)
            if pkt["frame"] >= number:
                return

    def send(self, msg: dict) -> None:
        if self.binary:
            self.ws.send_bytes(msgpack.packb(msg))
        else:
            self.ws.send_text(json.dumps(msg))

    def close(self) -> None:
        self.cm.__exit__(None, None, None)


# --------------------------------------------------------------------------- codecs


@pytest.mark.parametrize("binary", [False, True])
def test_answers_in_pieces_leave_nothing_for_the_garbage_collector(binary):
    """An answer encoded in pieces is freed as soon as it is dropped: no reference cycle
    keeps its pieces (a 256 x 256 wall's console status, four a second, grew the server by
    megabytes a second until the collector's next full pass)."""
    import gc

    from wallcull.server.http import encode_in_pieces

    answer = {"rows": np.arange(3 * 5000.0).reshape(-1, 3), "nested": {"more": list(range(9000))},
              "latency": np.array([1.5, np.nan] * 3000)}
    gc.collect()
    gc.disable()
    try:
        body = encode_in_pieces(answer, binary)
        found = gc.collect()
    finally:
        gc.enable()
    assert found == 0
    decoded = msgpack.unpackb(body) if binary else json.loads(body)
    assert decoded["rows"] == answer["rows"].tolist()
    assert decoded["latency"][:4] == [1.5, None, 1.5, None]


def test_the_heap_is_set_unless_the_environment_chose():
    """glibc's arenas and mapping threshold (wallcull.server.heap), and none of it when the
    environment names its own."""
    import subprocess
    import sys

    code = "from wallcull.server import heap; print(heap.tune())"
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout
    assert out.strip() == "{'arenas': 2, 'mmap_threshold': 1048576}"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "MALLOC_ARENA_MAX": "4"},
                         capture_output=True, text=True, check=True).stdout
    assert out.strip() == "{}"


def test_json_and_msgpack_requests_and_responses(client, fatehpur):
    body = msgpack.packb({"wall": WALL, "scene": "fatehpur", "history": 16})
    r = client.post("/walls", content=body, headers={**AUTH, "Content-Type": MP, "Accept": MP})
    assert r.status_code == 201 and r.headers["content-type"] == MP
    info = msgpack.unpackb(r.content)
    wid = info["id"]
    assert info["tiles"] == 6 and info["history"] == 16 and info["latest"] == -1
    try:
        # msgpack body with a charset parameter and odd case; q-values pick msgpack
        r = client.post(f"/walls/{wid}/frames", content=msgpack.packb({"frame": FRAME}),
                        headers={**AUTH, "Content-Type": "Application/MsgPack; charset=binary",
                                 "Accept": "application/json;q=0.9, application/msgpack"})
        assert r.status_code == 200 and r.headers["content-type"] == MP
        assert msgpack.unpackb(r.content)["frame"] == 0
        # JSON body; msgpack with a lower q than JSON gives JSON
        r = client.post(f"/walls/{wid}/frames", json={"frame": FRAME},
                        headers={**AUTH, "Accept": "application/msgpack;q=0.1, application/json"})
        assert r.headers["content-type"] == "application/json" and r.json()["frame"] == 1
        want = reference(fatehpur, WALL, FRAME)
        for accept, decode in (("application/msgpack;q=0", json.loads), ("*/*", json.loads),
                               (None, json.loads), (MP, msgpack.unpackb),
                               ("application/x-msgpack", msgpack.unpackb)):
            r = client.get(f"/walls/{wid}/tiles/4/packets/1",
                           headers={**AUTH, "Accept": accept} if accept else AUTH)
            pkt = decode(r.content)
            assert pkt["visible"] == want[4].tolist() and pkt["count"] == len(want[4])
            assert len(pkt["view"]) == 4 and len(pkt["projection"][0]) == 4
        # errors are JSON with a detail, whatever the client accepts
        r = client.get(f"/walls/{wid}/tiles/99/packets/1", headers={**AUTH, "Accept": MP})
        assert r.status_code == 404 and "no tile 99" in r.json()["detail"]
    finally:
        client.delete(f"/walls/{wid}", headers=AUTH)


# --------------------------------------------------------------------------- bad input

HUGE = 1.7e308
Q45 = [math.cos(math.pi / 8), 0.0, math.sin(math.pi / 8), 0.0]


def _json(obj):
    return {"content": json.dumps(obj).encode(), "headers": {"Content-Type": "application/json"}}


def _raw(data: bytes, ctype="application/json"):
    return {"content": data, "headers": {"Content-Type": ctype}}


def _mp(obj):
    return {"content": msgpack.packb(obj), "headers": {"Content-Type": MP}}


BAD = [  # (id, method, path, request kwargs, status, detail pattern)
    ("malformed-json", "POST", "/walls/{wid}/frames", _raw(b'{"frame": {"position": [0,'), 422,
     "JSON decode error"),
    ("malformed-msgpack", "POST", "/walls/{wid}/frames", _raw(b"\xc1\x92", MP), 400,
     "malformed msgpack"),
    ("truncated-msgpack", "POST", "/walls/{wid}/frames", _raw(msgpack.packb({"frame": FRAME})[:-3],
                                                             MP), 400, "malformed msgpack"),
    ("msgpack-bytes", "POST", "/walls/{wid}/frames", _mp({"frame": b"\x00\x01"}), 400,
     "JSON cannot carry"),
    ("msgpack-int-keys", "POST", "/walls/{wid}/frames", _raw(b"\x81\x01\x02", MP), 400,
     "malformed msgpack"),
    ("deep-json", "POST", "/walls/{wid}/frames", _raw(b"[" * 60_000), 4, ""),
    ("not-an-object", "POST", "/walls/{wid}/frames", _json([1, 2, 3]), 422, "body"),
    ("wrong-type", "POST", "/walls/{wid}/frames",
     _json({"frame": {"position": "here", "orientation": [1, 0, 0, 0]}}), 422, "frame.position"),
    ("short-vector", "POST", "/walls/{wid}/frames",
     _json({"frame": {"position": [0, 0], "orientation": [1, 0, 0, 0]}}), 422, "frame.position"),
    ("missing-field", "POST", "/walls/{wid}/frames",
     _json({"frame": {"orientation": [1, 0, 0, 0]}}), 422, "position: Field required"),
    ("extra-field", "POST", "/walls/{wid}/frames", _json({"frame": FRAME, "bogus": 1}), 422,
     "bogus"),
    ("nan-json", "POST", "/walls/{wid}/frames",
     _raw(b'{"frame": {"position": [NaN, 0, 0], "orientation": [1, 0, 0, 0]}}'), 422, "finite"),
    ("infinity-json", "POST", "/walls/{wid}/frames",
     _raw(b'{"frame": {"position": [0, 0, 0], "orientation": [Infinity, 0, 0, 0]}}'), 422,
     "finite"),
    ("overflow-json", "POST", "/walls/{wid}/frames",
     _raw(b'{"frame": {"position": [1e999, 0, 0], "orientation": [1, 0, 0, 0]}}'), 422, "finite"),
    ("nan-msgpack", "POST", "/walls/{wid}/frames",
     _mp({"frame": {"position": [0, 0, 0], "orientation": [1, 0, 0, 0], "eye": [0, math.nan, 0]}}),
     422, "finite"),
    ("inf-msgpack", "POST", "/walls/{wid}/frames",
     _mp({"frame": {"position": [-math.inf, 0, 0], "orientation": [1, 0, 0, 0]}}), 422, "finite"),
    ("non-unit-quaternion", "POST", "/walls/{wid}/frames",
     _json({"frame": {"position": [0, 0, 0], "orientation": [1, 1, 0, 0]}}), 422,
     "not a unit quaternion"),
    ("zero-quaternion", "POST", "/walls/{wid}/frames",
     _json({"frame": {"position": [0, 0, 0], "orientation": [0, 0, 0, 0]}}), 422,
     "not a unit quaternion"),
    ("eye-behind-wall", "POST", "/walls/{wid}/frames",
     _json({"frame": {**FRAME, "eye": [0, 0, -5]}}), 422, "not in front of the wall"),
    ("eye-on-near-plane", "POST", "/walls/{wid}/frames",
     _json({"frame": {**FRAME, "eye": [0, 0, -1.9]}}), 422, "not in front of the wall"),
    ("position-overflows", "POST", "/walls/{wid}/frames",
     _json({"frame": {"position": [HUGE, HUGE, HUGE], "orientation": Q45}}), 422,
     "less than or equal"),
    ("eye-overflows", "POST", "/walls/{wid}/frames",
     _json({"frame": {**FRAME, "eye": [0, 0, HUGE]}}), 422, "less than or equal"),
    ("number-negative", "POST", "/walls/{wid}/frames", _json({"frame": FRAME, "number": -1}), 422,
     "number"),
    ("number-too-big", "POST", "/walls/{wid}/frames", _json({"frame": FRAME, "number": 2**60}),
     422, "number"),
    ("unknown-node", "POST", "/walls/{wid}/frames",
     _json({"frame": FRAME, "updates": {"no/such/node": {"position": [0, 0, 0],
                                                         "orientation": [1, 0, 0, 0]}}}),
     422, "unknown node"),
    ("update-half", "POST", "/walls/{wid}/frames",
     _json({"frame": FRAME, "updates": {"x": {"position": [0, 0, 0]}}}), 422, "needs a matrix"),
    ("update-non-unit", "POST", "/walls/{wid}/frames",
     _json({"frame": FRAME, "updates": {"{node}": {"position": [0, 0, 0],
                                                   "orientation": [0.5, 0.5, 0.5, 0.6]}}}),
     422, "not a unit quaternion"),
    ("update-matrix-and-pose", "POST", "/walls/{wid}/frames",
     _json({"frame": FRAME, "updates": {"{node}": {"matrix": [[1, 0, 0, 0], [0, 1, 0, 0],
                                                              [0, 0, 1, 0], [0, 0, 0, 1]],
                                                   "position": [5, 0, 0]}}}),
     422, "send one or the other"),
    ("update-half-named", "POST", "/walls/{wid}/frames",
     _json({"frame": FRAME, "updates": {"x": {"orientation": [1, 0, 0, 0]}}}), 422,
     "update of 'x' needs a matrix"),
    ("update-huge-scale", "POST", "/walls/{wid}/frames",
     _json({"frame": FRAME, "updates": {"{node}": {"matrix": [[1e200, 0, 0, 0], [0, 1e200, 0, 0],
                                                              [0, 0, 1e200, 0], [0, 0, 0, 1]]}}}),
     422, "out of range"),
    ("update-singular", "POST", "/walls/{wid}/frames",
     _json({"frame": FRAME, "updates": {"{node}": {"matrix": [[0] * 4] * 3 + [[0, 0, 0, 1]]}}}),
     422, "singular"),
    ("update-not-affine", "POST", "/walls/{wid}/frames",
     _json({"frame": FRAME, "updates": {"{node}": {"matrix": [[1, 0, 0, 0]] * 4}}}), 422,
     "matrix.3"),
    ("update-nan-matrix", "POST", "/walls/{wid}/frames",
     _raw(json.dumps({"frame": FRAME, "updates": {"{node}": {"matrix": [[1, 0, 0, 0]] * 4}}}
                     ).replace("[1, 0, 0, 0]", "[NaN, 0, 0, 0]", 1).encode()), 422, "finite"),
    ("refit-bogus", "POST", "/walls/{wid}/frames", _json({"frame": FRAME, "refit": "sphere"}), 422,
     "refit"),
    ("oversized-body", "POST", "/walls/{wid}/frames",
     _json({"frame": FRAME, "pad": "x" * MAX_BODY}), 413, "over"),
    ("oversized-chunked", "POST", "/walls/{wid}/frames",
     {"content": iter([b'{"frame": '] + [b" " * 8192] * 10), "headers": AUTH}, 413, "over"),
    ("unknown-wall", "POST", "/walls/000000000000/frames", _json({"frame": FRAME}), 404,
     "no wall '000000000000'"),
    ("unknown-wall-get", "GET", "/walls/000000000000", {}, 404, "no wall"),
    ("malformed-wall-id", "GET", "/walls/nope", {}, 422, "wid"),
    ("unknown-tile", "GET", "/walls/{wid}/tiles/6/packets/latest", {}, 404, "no tile 6"),
    ("negative-tile", "GET", "/walls/{wid}/tiles/-1/packets/latest", {}, 422, "tile"),
    ("frame-not-ready", "GET", "/walls/{wid}/tiles/0/packets/12345?wait=0", {}, 404,
     "not ready"),
    ("frame-not-a-number", "GET", "/walls/{wid}/tiles/0/packets/1e3", {}, 422, "frame"),
    ("frame-past-the-last", "GET", "/walls/{wid}/tiles/0/packets/9999999999999999", {}, 422,
     "frame numbers end at 9007199254740992"),
    ("wait-too-long", "GET", "/walls/{wid}/tiles/0/packets/latest?wait=11", {}, 422, "wait"),
    ("wait-nan", "GET", "/walls/{wid}/tiles/0/packets/latest?wait=nan", {}, 422,
     "wait: Input should be a finite number"),
    ("timeout-inf", "GET", "/walls/{wid}/barrier/0?timeout=inf", {}, 422,
     "timeout: Input should be a finite number"),
    ("ack-negative", "POST", "/walls/{wid}/tiles/0/ack", _json({"frame": -1}), 422, "frame"),
    ("ack-future", "POST", "/walls/{wid}/tiles/0/ack", _json({"frame": 999}), 409,
     "cannot acknowledge frame 999"),
    ("ack-unknown-tile", "POST", "/walls/{wid}/tiles/7/ack", _json({"frame": 0}), 404, "no tile"),
    ("ack-not-int", "POST", "/walls/{wid}/tiles/0/ack", _json({"frame": "zero"}), 422, "frame"),
    ("barrier-negative", "GET", "/walls/{wid}/barrier/-1", {}, 422, "frame"),
    ("barrier-timeout", "GET", "/walls/{wid}/barrier/0?timeout=-1", {}, 422, "timeout"),
    ("zero-tiles", "POST", "/walls", _json({"wall": {**WALL, "cols": 0}, "scene": "fatehpur"}),
     422, "cols"),
    ("million-tiles", "POST", "/walls",
     _json({"wall": {**WALL, "cols": 1000, "rows": 1000}, "scene": "fatehpur"}), 422,
     "less than or equal to 256"),
    ("negative-tile-size", "POST", "/walls",
     _json({"wall": {**WALL, "tile_size": [-0.6, 0.34]}, "scene": "fatehpur"}), 422,
     "greater than or equal"),
    ("near-beyond-far", "POST", "/walls",
     _json({"wall": {**WALL, "near": 10, "far": 1}, "scene": "fatehpur"}), 422, "near < far"),
    ("wall-overflows", "POST", "/walls",
     _json({"wall": {**WALL, "tile_size": [1e307, 1e307], "cols": 64}, "scene": "fatehpur"}),
     422, "less than or equal"),
    ("tiles-too-small", "POST", "/walls",
     _json({"wall": {**WALL, "tile_size": [1e-300, 1e-300], "gap": [1.0, 1.0]},
            "scene": "fatehpur"}), 422, "greater than or equal"),
    ("tiles-lost-in-their-gaps", "POST", "/walls",
     _json({"wall": {**WALL, "cols": 64, "tile_size": [1e-9, 0.3], "gap": [1e9, 0.0]},
            "scene": "fatehpur"}), 422, "cannot tell"),
    ("wall-nan", "POST", "/walls",
     _raw(json.dumps({"wall": WALL, "scene": "fatehpur"}).replace("2.0", "NaN").encode()), 422,
     "finite"),
    ("wall-extra-key", "POST", "/walls", _json({"wall": {**WALL, "depth": 3}, "scene": "fatehpur"}),
     422, "depth"),
    ("unknown-scene", "POST", "/walls", _json({"wall": WALL, "scene": "atlantis"}), 404,
     "no scene 'atlantis'"),
    ("unknown-method", "POST", "/walls", _json({"wall": WALL, "scene": "fatehpur", "method": "x"}),
     422, "method"),
    ("history-too-short", "POST", "/walls",
     _json({"wall": WALL, "scene": "fatehpur", "history": 1}), 422, "history"),
]


@pytest.mark.parametrize("method,path,kwargs,status,detail", [b[1:] for b in BAD],
                         ids=[b[0] for b in BAD])
def test_bad_input_gets_a_clear_4xx_and_the_server_keeps_serving(client, wid, fatehpur, method,
                                                                 path, kwargs, status, detail):
    node = next(fatehpur.names[i] for i in fatehpur.leaves)
    post_frame(client, wid)
    kwargs = dict(kwargs)
    if isinstance(kwargs.get("content"), bytes):
        kwargs["content"] = kwargs["content"].replace(b"{node}", node.encode())
    headers = {**AUTH, **kwargs.pop("headers", {})}
    r = client.request(method, path.format(wid=wid), headers=headers, **kwargs)
    if status == 4:  # any clear 4xx
        assert 400 <= r.status_code < 500, r.text
    else:
        assert r.status_code == status, r.text
    assert r.headers["content-type"] == "application/json"
    assert detail in r.json()["detail"] and len(r.json()["detail"]) < 2000
    # ...and the server keeps serving: the next good frame culls and packs as it should
    number = post_frame(client, wid)["frame"]
    assert number == 1
    pkt = client.get(f"/walls/{wid}/tiles/4/packets/{number}", headers=AUTH).json()
    assert pkt["visible"] == reference(fatehpur, WALL, FRAME)[4].tolist()
    assert client.get("/health").json()["status"] == "ok"


def test_a_wall_shows_every_option_it_was_made_with_and_is_made_again_from_them(client):
    """Revoking a leaked credential is deleting its wall and making it again from what
    ``GET /walls/{wid}`` shows (deployment.md): the depth range and reversed Z were left
    out, and a wall made again from it sent its nodes other projections."""
    from wallcull.server.models import WallCreate, WallInfo

    assert set(WallCreate.model_fields) <= set(WallInfo.model_fields)
    options = {"method": "oh", "bounds": "aabb", "pseudo_groups": True, "history": 8,
               "depth": "wall", "reversed_z": True, "shadow_fit": "greedy",
               "occlusion": "auto", "nodes": [[0, 1], [2], [3], [4, 5]]}
    first = client.get(f"/walls/{new_wall(client, **options)}").json()
    made = new_wall(client, **{k: first[k] for k in WallCreate.model_fields})
    again = client.get(f"/walls/{made}").json()
    mine = {"id", "latest", "subscribers"}
    assert {k: v for k, v in again.items() if k not in mine} == \
        {k: v for k, v in first.items() if k not in mine}
    assert {k: first[k] for k in options} == options


def test_frames_in_order_with_numbers(client, wid):
    assert post_frame(client, wid, number=5)["frame"] == 5
    for number in (5, 3, 0):
        r = client.post(f"/walls/{wid}/frames", json={"frame": FRAME, "number": number},
                        headers=AUTH)
        assert r.status_code == 409 and f"frame {number} is out of order" in r.json()["detail"]
    assert post_frame(client, wid)["frame"] == 6
    assert post_frame(client, wid, number=2**40)["frame"] == 2**40
    # frames that were skipped do not exist; frames that were posted do
    r = client.get(f"/walls/{wid}/tiles/0/packets/100?wait=0", headers=AUTH)
    assert r.status_code == 404 and "skipped" in r.json()["detail"]
    assert client.get(f"/walls/{wid}/tiles/0/packets/6", headers=AUTH).status_code == 200
    assert client.get(f"/walls/{wid}").json()["latest"] == 2**40
    # the last frame number every route takes; after it, a wall takes no frame
    last = 2**53
    assert post_frame(client, wid, number=last)["frame"] == last
    assert client.get(f"/walls/{wid}/tiles/0/packets/{last}", headers=AUTH).status_code == 200
    r = client.post(f"/walls/{wid}/tiles/0/ack", json={"frame": last}, headers=AUTH)
    assert r.status_code == 204, r.text
    assert client.get(f"/walls/{wid}/barrier/{last}?timeout=0").status_code == 200
    r = client.post(f"/walls/{wid}/frames", json={"frame": FRAME}, headers=AUTH)
    assert r.status_code == 409 and "used every frame number" in r.json()["detail"], r.text
    assert client.get(f"/walls/{wid}").json()["latest"] == last


def test_console_status_columns(client, wid, fatehpur):
    """The console's status: each column one value per tile, a latency not known as null."""
    number = post_frame(client, wid)["frame"]
    r = client.post(f"/walls/{wid}/tiles/2/ack", json={"frame": number}, headers=AUTH)
    assert r.status_code == 204, r.text
    with client.websocket_connect(f"/walls/{wid}/console/stream?token={TOKEN}") as ws:
        status = json.loads(ws.receive_text())
    ConsoleStatus.model_validate(status)  # the AsyncAPI document's schema
    tiles = Wall.from_dict(WALL).tiles
    lists = reference(fatehpur, WALL, FRAME)
    assert status["frame"] == number
    assert status["count"] == [len(v) for v in lists]
    assert status["ack"] == [number if t == 2 else -1 for t in range(tiles)]
    assert status["streams"] == [0] * tiles
    assert status["latency_ms"][2] >= 0
    assert status["latency_ms"][:2] + status["latency_ms"][3:] == [None] * (tiles - 1)
    assert status["state"][2] == "acked"
    assert set(status["state"][:2] + status["state"][3:]) == {"offline"}


def test_a_tile_that_drew_the_newest_frame_stays_acked_without_a_stream(client, wid):
    """A node that pulls over HTTP and acknowledges, then hears of no new frame for longer than
    ``LIVE``: its tile has drawn the newest frame, as the barrier says (it was "offline", and
    the console said 0 tiles had drawn it)."""
    number = post_frame(client, wid)["frame"]
    assert client.post(f"/walls/{wid}/tiles/2/ack", json={"frame": number},
                       headers=AUTH).status_code == 204
    session = client.app.state.server.walls.sessions[wid]
    later = session.status(now=time.time() + 10 * LIVE)  # long after the ack, no stream
    assert later["state"][2] == "acked" and later["state"][0] == "offline"
    assert client.get(f"/walls/{wid}/barrier/{number}?timeout=0").json()["acked"] == 1


def test_an_older_acknowledgement_keeps_a_newer_ones_time(client, wid):
    """A second node on the same tiles acknowledges an older frame: tile 0, which drew the
    newer one, keeps that frame and its time (its latency went from ms to seconds)."""
    first = post_frame(client, wid)["frame"]
    second = post_frame(client, wid)["frame"]
    session = client.app.state.server.walls.sessions[wid]
    assert client.post(f"/walls/{wid}/tiles/0/ack", json={"frame": second},
                       headers=AUTH).status_code == 204
    at = session.acked_at[0]
    with client.websocket_connect(f"/walls/{wid}/nodes/stream?tiles=0-1&format=json"
                                  f"&token={TOKEN}") as ws:
        ws.receive_text()  # its first message
        ws.send_text(json.dumps({"ack": first}))
        with client.websocket_connect(f"/walls/{wid}/console/stream?token={TOKEN}") as console:
            status = json.loads(console.receive_text())
            while status["ack"][1] != first:  # the stream's ack, taken
                status = json.loads(console.receive_text())
    assert status["ack"][:2] == [second, first]
    assert session.acked_at[0] == at


def test_consoles_without_a_credential_never_lock_out_one_with_it(client, wid):
    """Anonymous consoles fill their own cap (429) and no more: the operator's console, and
    one with a node's credential, still open (32 anonymous sockets locked out every console,
    the operator's too)."""
    with ExitStack() as held:
        for k in range(40):
            try:
                held.enter_context(client.websocket_connect(f"/walls/{wid}/console/stream"))
            except WebSocketDenialResponse as refused:
                assert refused.status_code == 429
                detail = refused.json()["detail"]
                break
        else:
            pytest.fail("40 consoles without a credential were all let in")
        with client.websocket_connect(f"/walls/{wid}/console/stream?token={TOKEN}") as ws:
            assert json.loads(ws.receive_text())["wall"] == wid
        assert k == client.app.state.server.limits.consoles and "without a credential" in detail
        info = client.post("/walls", json={"wall": WALL, "scene": "fatehpur"},
                           headers=AUTH).json()
        try:
            node = info["credentials"]["nodes"][0]["token"]
            with client.websocket_connect(f"/walls/{info['id']}/console/stream",
                                          headers={"Authorization": f"Bearer {node}"}) as ws:
                assert json.loads(ws.receive_text())["wall"] == info["id"]
        finally:
            client.delete(f"/walls/{info['id']}", headers=AUTH)


def test_pages_refused_are_counted_as_refusals(client):
    """A page's 404 counts in ``wallcull_errors_total`` as the API's does."""
    before = metric(metrics(client), "wallcull_errors_total", status=404)
    for page in ("console", "view"):
        assert client.get(f"/walls/000000000000/{page}").status_code == 404
    assert metric(metrics(client), "wallcull_errors_total", status=404) == before + 2


def test_a_refused_frame_applies_none_of_its_updates(client, wid, fatehpur):
    """Updates travel with the frame: when the frame is refused, nothing moves."""
    leaf = fatehpur.names[int(fatehpur.leaves[0])]
    away = {leaf: {"position": [1e5, 0, 0], "orientation": [1, 0, 0, 0]}}
    for frame in ({**FRAME, "eye": [0, 0, -3]}, {**FRAME, "orientation": [0.5, 0.5, 0.5, 0.6]}):
        r = client.post(f"/walls/{wid}/frames", json={"frame": frame, "updates": away},
                        headers=AUTH)
        assert r.status_code == 422
    post_frame(client, wid)
    want = reference(fatehpur, WALL, FRAME)
    for t in range(6):
        pkt = client.get(f"/walls/{wid}/tiles/{t}/packets/0", headers=AUTH).json()
        assert pkt["visible"] == want[t].tolist() and "transforms" not in pkt


def test_updates_that_collapse_or_overflow_change_nothing(client, wid, fatehpur):
    """Scales that are fine alone but collapse to 0 or overflow once composed down a chain
    of nested nodes: refused, and the scene stays as it was, so later updates still work."""
    leaf = int(fatehpur.leaves[100])
    chain = [leaf]
    while fatehpur.parent[chain[-1]] > 0:
        chain.append(int(fatehpur.parent[chain[-1]]))
    chain = chain[::-1][:5]
    assert len(chain) == 5

    def scaled(scale):
        return {fatehpur.names[i]: {"position": [0.0, 0.0, 0.0], "orientation": [1, 0, 0, 0],
                                    "scale": [scale] * 3} for i in chain}

    for scale in (1e-100, 1e100, 1e-100):
        r = client.post(f"/walls/{wid}/frames", json={"frame": FRAME, "updates": scaled(scale)},
                        headers=AUTH)
        assert r.status_code == 422 and "update" in r.json()["detail"], r.text
    good = scaled(0.5)
    post_frame(client, wid, updates=good)
    session = Session(fatehpur, Wall.from_dict(WALL))
    want = reference(fatehpur, WALL, FRAME, good, session=session)
    moved = set(fatehpur.subtree_leaves(np.array([chain[0]])).tolist())
    for t in range(6):
        node = Holder()
        node.take(client.get(f"/walls/{wid}/tiles/{t}/packets/0", headers=AUTH).json())
        np.testing.assert_array_equal(node.current, want[t])
        node.check_transforms({k: session.state.world[k] for k in moved})


# --------------------------------------------------------------------------- walkthroughs


def test_long_walkthrough_with_http_and_websocket_nodes(client, fatehpur):
    """300 frames of the fly path on a 3 x 2 wall. Tile 0 pulls every frame over JSON and
    acknowledges it; tile 1 (msgpack) joins late, skips frames, acknowledges some, restarts and
    asks for full lists; tile 2 streams msgpack, acknowledges, reconnects mid-walk and asks for
    a full list; tile 3 streams JSON from frame 60 and acknowledges late; tile 5 acknowledges
    three frames late, so its base is older than the last frame it received."""
    frames = fly(fatehpur, WALL, 300)
    session = Session(fatehpur, Wall.from_dict(WALL))
    wid = new_wall(client, history=32)
    truth = {}

    def check(number, tile, held):
        np.testing.assert_array_equal(held, truth[number][tile], err_msg=f"frame {number}")

    rng = np.random.default_rng(7)
    t0, t1, t5 = HttpNode(client, wid, 0), HttpNode(client, wid, 1, binary=True), \
        HttpNode(client, wid, 5)
    t2 = WsNode(client, wid, 2)
    t3 = None
    try:
        for n, frame in enumerate(frames):
            truth[n] = reference(fatehpur, WALL, frame, session=session)
            assert post_frame(client, wid, frame)["frame"] == n
            t0.fetch(n)
            check(n, 0, t0.node.current)
            t0.ack(n)
            if n >= 40 and (n == 150 or rng.random() < 0.4):
                if n == 150:
                    t1.node.reset()  # restarts: asks for a full list and acknowledges it
                    t1.fetch(n, full=True)
                    t1.ack(n)
                else:
                    t1.fetch(n, full=rng.random() < 0.05)
                    if rng.random() < 0.5:
                        t1.ack(n)
                check(n, 1, t1.node.current)
            if n == 100:  # reconnect: a new connection, and a node that starts afresh
                t2.close()
                t2 = WsNode(client, wid, 2)
            t2.until(n, check)
            if n == 180:
                t2.send({"full": True})
            t2.send({"ack": n})
            if n == 60:
                t3 = WsNode(client, wid, 3, binary=False)
            if t3 is not None:
                t3.until(n, check)
                if n % 4 == 0:  # late; the first is for a frame from before it joined
                    t3.send({"ack": n - 2})
            t5.fetch(n)
            check(n, 5, t5.node.current)
            if n >= 3:
                t5.ack(n - 3)
    finally:
        t2.close()
        if t3 is not None:
            t3.close()
        client.delete(f"/walls/{wid}", headers=AUTH)
    # the walk is not trivial: lists change, and deltas carry them
    sizes = [sum(map(len, truth[n])) for n in truth]
    assert max(sizes) > 50 and len(set(sizes)) > 20
    assert t0.node.full == 1 and t0.node.deltas == 299
    assert t1.node.full >= 2 and t1.node.deltas > 20
    assert t5.node.full == 4 and t5.node.deltas == 296  # frames 0-3 come before any ack lands
    assert t2.node.deltas > 100 and 2 <= t2.node.full <= 4
    assert any(p["base"] is None for p in t2.received if p["frame"] > 180)
    assert t3.node.deltas > 100
    assert t0.sizes["delta"] / t0.node.deltas < t0.sizes["full"]  # deltas are smaller


def by_id(nodes: dict) -> dict:
    """A node table (``?nodes=true``) indexed by node id: its rows leave the clusters out,
    which here have no name, parent -1, ``synthetic`` set and a zero transform."""
    n, ids = nodes["count"], nodes["id"]
    out = {"id": ids, "name": [None] * n, "mesh": [None] * n, "parent": [-1] * n,
           "leaf": [False] * n, "synthetic": [True] * n, "world": [[0.0] * 16] * n}
    for key in ("name", "mesh", "parent", "leaf", "synthetic", "world"):
        for row, i in enumerate(ids):
            out[key][i] = nodes[key][row]
    return out


def test_dynamic_updates_change_lists_and_carry_transforms(client, fatehpur):
    """Frames that move nodes (position/orientation and matrices, some refit as AABBs): lists
    equal an in-process session moved the same way, and every node holds, for each leaf in
    its list, the world transform of that frame."""
    info = by_id(client.get("/scenes/fatehpur", params={"nodes": "true"}).json()["nodes"])
    names, parent = info["name"], np.array(info["parent"])
    world_rest = np.array(info["world"]).reshape(-1, 4, 4)
    assert world_rest.shape == fatehpur.world.shape
    np.testing.assert_array_equal(world_rest[info["id"]], fatehpur.world[info["id"]])
    start, count = fatehpur.leaf_range
    # three internal nodes with many leaves, below the top level, and one leaf
    internal = [i for i in range(1, len(names)) if not info["leaf"][i]
                and not info["synthetic"][i] and parent[i] > 0 and count[i] >= 4]
    movers = sorted(internal, key=lambda i: -count[i])[:3] + [int(fatehpur.leaves[7])]
    local = {i: np.linalg.inv(world_rest[parent[i]]) @ world_rest[i] for i in movers}
    frames = fly(fatehpur, WALL, 60)
    moving = Session(fatehpur, Wall.from_dict(WALL))
    still = Session(fatehpur, Wall.from_dict(WALL))
    wid = new_wall(client)
    nodes = [HttpNode(client, wid, 0), HttpNode(client, wid, 1, binary=True)]
    ws = WsNode(client, wid, 2)
    posed: set[int] = set()
    differs = 0
    try:
        for n, frame in enumerate(frames):
            updates, refit = {}, None  # as sent, and as Session.move takes them
            moves = {}
            if n % 5 != 4:
                i = movers[n % len(movers)]
                a = 0.2 * n
                q = [math.cos(a / 2), 0.0, math.sin(a / 2), 0.0]
                offset = 15.0 * np.array([math.sin(a), 0.3, math.cos(a)])
                if n % 3 == 0:
                    m = local[i].copy()
                    m[:3, 3] += offset
                    updates[names[i]] = {"matrix": m.tolist()}
                    moves[names[i]] = m.tolist()
                else:
                    updates[names[i]] = {"position": (local[i][:3, 3] + offset).tolist(),
                                         "orientation": q}
                    moves[names[i]] = updates[names[i]]
                refit = "aabb" if n % 7 == 0 else None
                posed.update(fatehpur.subtree_leaves(np.array([i])).tolist())
            body = {"frame": frame, "updates": updates, "packets": n % 10 == 0,
                    "full": n % 20 == 0}
            if refit:
                body["refit"] = refit
            r = client.post(f"/walls/{wid}/frames", json=body, headers=AUTH)
            assert r.status_code == 200, r.text
            moving.move(moves, refit)
            want = reference(fatehpur, WALL, frame, session=moving)
            differs += any(not np.array_equal(a, b) for a, b in
                           zip(want, reference(fatehpur, WALL, frame, session=still)))
            world = {leaf: moving.state.world[leaf] for leaf in posed}

            def check(number, tile, held):
                assert number == n
                np.testing.assert_array_equal(held, want[tile])

            if body["packets"]:
                pkts = r.json()["packets"]
                assert [p["tile"] for p in pkts] == list(range(6))
                for p in pkts:
                    assert p["frame"] == n
                    if body["full"] or p["tile"] >= 3:  # asked for, or never acknowledged
                        assert p["base"] is None
                    if p["base"] is None:
                        assert p["visible"] == want[p["tile"]].tolist()
            for k, node in enumerate(nodes):
                node.fetch(n, full=(k == 1 and n % 9 == 0))
                check(n, node.tile, node.node.current)
                node.node.check_transforms(world)
                if (n + k) % 2 == 0:
                    node.ack(n)
            ws.until(n, check)
            ws.node.check_transforms(world)
            ws.send({"ack": n})
    finally:
        ws.close()
        client.delete(f"/walls/{wid}", headers=AUTH)
    assert differs > 5, "the updates should change what tiles see"
    assert any(len(node.node.transforms) > 10 for node in nodes)


# --------------------------------------------------------------------------- tokens


STATE_CHANGING = [
    ("upload", "POST", "/scenes?name=tok.glb", lambda wid: {"content": boxes_glb()}),
    ("wall", "POST", "/walls", lambda wid: {"json": {"wall": WALL, "scene": "fatehpur"}}),
    ("delete", "DELETE", "/walls/{wid}", lambda wid: {}),
    ("frame", "POST", "/walls/{wid}/frames", lambda wid: {"json": {"frame": FRAME}}),
    ("ack", "POST", "/walls/{wid}/tiles/0/ack", lambda wid: {"json": {"frame": 0}}),
]
BAD_AUTH = {"none": {}, "wrong": {"Authorization": "Bearer nope"},
            "prefix": {"Authorization": f"Bearer {TOKEN}x"},
            "no-scheme": {"Authorization": TOKEN}, "basic": {"Authorization": f"Basic {TOKEN}"},
            "empty": {"Authorization": "Bearer "}}


@pytest.mark.parametrize("auth", list(BAD_AUTH), ids=list(BAD_AUTH))
@pytest.mark.parametrize("route", STATE_CHANGING, ids=[r[0] for r in STATE_CHANGING])
def test_state_changing_routes_need_the_token(client, wid, route, auth, folder):
    _, method, path, kwargs = route
    post_frame(client, wid)
    before = client.get(f"/walls/{wid}").json(), client.get("/walls").json(), \
        client.get("/scenes").json(), client.get(f"/walls/{wid}/barrier/0?timeout=0").json()
    m0 = metrics(client)
    r = client.request(method, path.format(wid=wid), headers=BAD_AUTH[auth], **kwargs(wid))
    assert r.status_code == 401 and "token" in r.json()["detail"]
    assert metric(metrics(client), "wallcull_errors_total", status=401) == \
        metric(m0, "wallcull_errors_total", status=401) + 1
    after = client.get(f"/walls/{wid}").json(), client.get("/walls").json(), \
        client.get("/scenes").json(), client.get(f"/walls/{wid}/barrier/0?timeout=0").json()
    assert after == before
    assert not (folder.scenes / "tok.glb").exists()
    # the scheme is case-insensitive; the token is not
    r = client.request(method, path.format(wid=wid),
                       headers={"Authorization": f"bearer {TOKEN}"}, **kwargs(wid))
    assert r.status_code in (200, 201, 204), r.text
    if path == "/walls":
        client.delete(f"/walls/{r.json()['id']}", headers=AUTH)
    (folder.scenes / "tok.glb").unlink(missing_ok=True)
    client.app.state.server.store.cache.pop("tok.glb", None)


def test_reads_are_open_but_packets_need_a_credential(client, wid):
    post_frame(client, wid)
    for path in ("/health", "/metrics", "/scenes", "/scenes/two.glb", "/walls",
                 f"/walls/{wid}", f"/walls/{wid}/barrier/0?timeout=0", "/openapi.json"):
        assert client.get(path).status_code == 200, path
    # packets carry the tracked head's pose
    for path in (f"/walls/{wid}/tiles/0/packets/latest", f"/walls/{wid}/tiles/0/packets/0"):
        r = client.get(path)
        assert r.status_code == 401 and "token" in r.json()["detail"]
        assert client.get(path, headers=AUTH).status_code == 200


def test_websocket_streams_need_a_node_credential(client, wid):
    post_frame(client, wid)
    for token, status in ((None, 401), ("nope", 401)):
        with pytest.raises(WebSocketDenialResponse) as denied:
            WsNode(client, wid, 0, token=token)
        assert denied.value.status_code == status and "token" in denied.value.json()["detail"]
    assert client.get(f"/walls/{wid}/barrier/0?timeout=0").json()["acked"] == 0
    node = WsNode(client, wid, 0)
    try:
        node.message()
        node.send({"ack": 0})
        _wait_for(lambda: client.get(f"/walls/{wid}/barrier/0?timeout=0").json()["acked"] == 1,
                  "the acknowledgement to land")
        # bad messages get an error and the stream goes on
        for bad in ({"ack": "zero"}, {"ack": 99}, [1, 2], {"ack": True}):
            node.send(bad)
            assert "error" in node.message()
        # ...and so do messages the AsyncAPI document's Control does not describe
        for bad, why in (({}, "an object of"), ({"bogus": 1}, "unknown key 'bogus'"),
                         ({"ack": 0, "bogus": 1}, "unknown key 'bogus'"),
                         ({"ack": -1}, "ack must be a frame number"),
                         ({"ack": None}, "ack must be a frame number"),
                         ({"ack": 2**53 + 1}, "ack must be a frame number"),
                         ({"full": "yes"}, "full must be true or false")):
            node.send(bad)
            node.ws.send_bytes(b"\xc1")  # then one every version refuses, so none waits
            assert why in node.message()["error"], bad
            assert "malformed msgpack" in node.message()["error"]
        node.ws.send_text("[" * 200_000)  # deeper than any parser's recursion: too long too
        assert "at most 65536 bytes" in node.message()["error"]
        node.ws.send_text("[" * 20_000)  # within the size, beyond any parser's recursion
        assert "malformed JSON" in node.message()["error"]
        node.ws.send_text("[" * 40 + "]" * 40)  # parses, but deeper than bodies may be
        assert "deeper than 32" in node.message()["error"]
        node.ws.send_bytes(b"\xc1")
        assert "malformed msgpack" in node.message()["error"]
        post_frame(client, wid)
        pkt = node.message()
        assert pkt["frame"] == 1 and pkt["base"] == 0
    finally:
        node.close()


# --------------------------------------------------------------------------- scene names

TRAVERSALS = ["..", "%2e%2e", "..%2fescape.glb", "%2e%2e%2foutside%2fsecret.glb",
              "..%2f..%2f..%2fetc%2fpasswd", "%2fetc%2fpasswd", ".hidden.glb",
              "..%5coutside%5csecret.glb", "escape.glb", "escape.txt", "sub%2ftwo.glb", "sub",
              "notes.txt", "two.glb%00.txt", "%252e%252e%252fsecret.glb", "~root"]


@pytest.mark.parametrize("name", TRAVERSALS)
def test_scene_names_stay_inside_the_folder(client, name, folder):
    for path in (f"/scenes/{name}", f"/scenes/{name}?nodes=true", f"/scenes/{name}/meshes/left",
                 f"/scenes/{name}/nodes/1/mesh"):
        r = client.get(path)
        assert b"secret" not in r.content.replace(b"secret.glb", b"").lower()
        if r.request.url.path == "/":  # the client resolved "/scenes/.." itself: the index
            continue
        assert r.status_code in (404, 422), (path, r.status_code, r.text)
    plain = name.replace("%2f", "/").replace("%2F", "/").replace("%2e", ".")
    for scene in (plain, "../outside/secret.glb", str(folder.outside / "secret.glb"),
                  str(folder.scenes / "two.glb")):
        r = client.post("/walls", json={"wall": WALL, "scene": scene}, headers=AUTH)
        assert r.status_code in (404, 422), (scene, r.text)


def test_listing_shows_only_scenes_inside_the_folder(client):
    listed = {s["name"]: s for s in client.get("/scenes").json()["scenes"]}
    assert {"fatehpur", "powerplant", "two.glb"} <= set(listed)
    assert "escape.glb" not in listed and "notes.txt" not in listed and "sub" not in listed
    assert listed["two.glb"]["source"] == "folder"


def test_a_symlink_in_the_folder_is_replaced_not_followed(tmp_path):
    scenes, outside = tmp_path / "scenes", tmp_path / "outside"
    scenes.mkdir()
    outside.mkdir()
    secret = boxes_glb(("secret",))
    (outside / "secret.glb").write_bytes(secret)
    os.symlink(outside / "secret.glb", scenes / "escape.glb")
    with TestClient(create_app(scenes, token=TOKEN)) as c:
        r = c.post("/scenes?name=escape.glb", content=boxes_glb(), headers=AUTH)
        assert r.status_code == 409
        r = c.post("/scenes?name=escape.glb&replace=true", content=boxes_glb(), headers=AUTH)
        assert r.status_code == 201
        assert (outside / "secret.glb").read_bytes() == secret
        assert not (scenes / "escape.glb").is_symlink()
        assert (scenes / "escape.glb").read_bytes() == boxes_glb()
        assert c.get("/scenes/escape.glb").json()["stats"]["leaves"] == 2


# --------------------------------------------------------------------------- uploads


def _bad_glbs():
    good = boxes_glb()
    doc, binary = glb_parts(good)
    nan = bytearray(binary)
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    off = doc["bufferViews"][acc["bufferView"]].get("byteOffset", 0) + acc.get("byteOffset", 0)
    nan[off:off + 12 * acc["count"]] = np.full(3 * acc["count"], np.nan, "<f4").tobytes()
    return [
        ("not-glb", b"solid cube\nendsolid cube\n", "binary glTF"),
        ("json-gltf", json.dumps(doc).encode(), "binary glTF"),
        ("empty", b"", "binary glTF"),
        ("magic-only", b"glTF", "cannot read"),
        ("truncated", good[: len(good) // 2], "cannot read"),
        ("bad-version", b"glTF" + struct.pack("<II", 7, 12), "cannot read"),
        ("bad-json", glb_build(doc, binary).replace(b'"asset"', b'"asset\x00', 1), "cannot"),
        ("external-uri", glb_build({**doc, "buffers": [{"uri": "/etc/passwd",
                                                        "byteLength": 64}]}, b""), "cannot"),
        ("relative-uri", glb_build({**doc, "buffers": [{"uri": "../outside/secret.glb",
                                                        "byteLength": 64}]}, b""), "cannot"),
        ("no-geometry", glb_build({"asset": {"version": "2.0"}, "scenes": [{"nodes": [0]}],
                                   "nodes": [{"name": "empty"}]}, b""), "no geometry"),
        ("nan-vertices", glb_build(doc, bytes(nan)), "vertex that is not finite"),
        ("node-cycle", glb_build({**doc, "nodes": [{"name": "a", "children": [1], "mesh": 0},
                                                   {"name": "b", "children": [0], "mesh": 1}],
                                  "scenes": [{"nodes": [0]}]}, binary), "cycle"),
        ("bad-mesh-index", glb_build({**doc, "nodes": [{"name": "a", "mesh": 9}],
                                      "scenes": [{"nodes": [0]}]}, binary), "mesh"),
        ("overflowing-matrix", glb_build({**doc, "nodes": [{"name": "a", "mesh": 0,
                                                            "matrix": [1e300] * 16}],
                                          "scenes": [{"nodes": [0]}]}, binary), "bad.glb"),
        ("huge-matrix", glb_build({**doc, "nodes": [{"name": "a", "mesh": 0, "matrix":
                                                     [1e200, 0, 0, 0, 0, 1e200, 0, 0, 0, 0,
                                                      1e200, 0, 0, 0, 0, 1]}],
                                   "scenes": [{"nodes": [0]}]}, binary), "bound"),
    ]


BAD_GLBS = _bad_glbs()


@pytest.mark.parametrize("data,detail", [b[1:] for b in BAD_GLBS], ids=[b[0] for b in BAD_GLBS])
def test_uploads_parse_only_good_glb(client, folder, data, detail):
    r = client.post("/scenes?name=bad", content=data,
                    headers={**AUTH, "Content-Type": "model/gltf-binary"})
    assert r.status_code == 422 and detail in r.json()["detail"], r.text
    assert sorted(p.name for p in folder.scenes.iterdir()) == \
        ["escape.glb", "escape.txt", "notes.txt", "sub", "two.glb"]
    assert client.get("/scenes/bad.glb").status_code == 404
    assert client.get("/health").status_code == 200


def test_uploads_are_size_limited(client, folder):
    big = b"glTF" + b"\0" * MAX_UPLOAD
    r = client.post("/scenes?name=big", content=big, headers=AUTH)
    assert r.status_code == 413 and "over" in r.json()["detail"]
    chunks = iter([b"glTF"] + [b"\0" * 4096] * (MAX_UPLOAD // 4096 + 1))
    r = client.post("/scenes?name=big", content=chunks, headers=AUTH)  # no Content-Length
    assert r.status_code == 413
    r = client.post("/scenes?name=big", content=b"x",
                    headers={**AUTH, "Content-Length": str(10 * MAX_UPLOAD)})
    assert r.status_code == 413
    assert not (folder.scenes / "big.glb").exists()
    # frames have their own, smaller limit; uploads do not count against it
    data = boxes_glb([f"b{k}" for k in range(300)], spread=1.5)
    assert MAX_BODY < len(data) < MAX_UPLOAD
    r = client.post("/scenes?name=many", content=data, headers=AUTH)
    assert r.status_code == 201 and r.json()["stats"]["leaves"] == 300
    (folder.scenes / "many.glb").unlink()


@pytest.mark.parametrize("name", ["../evil", "/etc/evil", "a/b", ".hidden", "x" * 200, "a b",
                                  "fatehpur\x00", "%2e%2e"])
def test_upload_names_are_plain_file_names(client, folder, name):
    r = client.post("/scenes", params={"name": name}, content=boxes_glb(), headers=AUTH)
    assert r.status_code == 422, r.text
    assert sorted(p.name for p in folder.scenes.iterdir()) == \
        ["escape.glb", "escape.txt", "notes.txt", "sub", "two.glb"]
    assert not any(p.suffix == ".glb" for p in folder.root.iterdir())


def test_a_good_upload_is_stored_and_usable(client, folder):
    data = boxes_glb(("a", "b", "c"), spread=2.0)
    r = client.post("/scenes?name=three", content=data,
                    headers={**AUTH, "Content-Type": "model/gltf-binary"})
    assert r.status_code == 201, r.text
    assert r.json()["name"] == "three.glb" and r.json()["stats"]["leaves"] == 3
    try:
        assert (folder.scenes / "three.glb").read_bytes() == data
        assert not [p for p in folder.scenes.iterdir() if p.name.endswith(".tmp")]
        assert "three.glb" in {s["name"] for s in client.get("/scenes").json()["scenes"]}
        r = client.post("/scenes?name=three.glb", content=data, headers=AUTH)
        assert r.status_code == 409 and "replace" in r.json()["detail"]
        assert client.post("/scenes?name=three.glb&replace=true", content=data,
                           headers=AUTH).status_code == 201
        wall = {"cols": 3, "rows": 1, "tile_size": [0.6, 0.34], "distance": 2.0}
        wid = new_wall(client, "three.glb", wall)
        frame = {"position": [0.0, 0.0, 0.0], "orientation": [1.0, 0.0, 0.0, 0.0]}
        pkts = post_frame(client, wid, frame, packets=True)["packets"]
        want = reference(glb_from_bytes(data, "three"), wall, frame)
        assert [p["visible"] for p in pkts] == [w.tolist() for w in want]
        assert sum(map(len, want)) >= 3
        client.delete(f"/walls/{wid}", headers=AUTH)
    finally:
        (folder.scenes / "three.glb").unlink()


def test_uploads_without_a_folder_stay_in_memory(tmp_path):
    with TestClient(create_app(None, token=TOKEN)) as c:
        assert c.post("/scenes?name=mem", content=boxes_glb(), headers=AUTH).status_code == 201
        assert {"name": "mem.glb", "source": "upload"} in c.get("/scenes").json()["scenes"]
        assert c.get("/scenes/mem.glb").status_code == 200
        r = c.get("/scenes/other.glb")
        assert r.status_code == 404 and "no scene folder" in r.json()["detail"]


def test_uploads_held_in_memory_stay_within_the_scene_cache():
    """Uploads a server keeps in memory are never evicted (nothing could load them again):
    they used to grow past the scene cache with every new name. Within it they are taken,
    beyond it refused, and a replacement counts instead of what it replaces."""
    import tempfile

    from wallcull.limits import Limits
    from wallcull.service import footprint
    from wallcull.uploads import parse_glb

    one = boxes_glb()
    with tempfile.NamedTemporaryFile(suffix=".glb") as f:
        f.write(one)
        f.flush()
        size = footprint(parse_glb(f.name, "a.glb", Limits()))
    with TestClient(create_app(None, token=TOKEN,
                               limits=Limits(scene_cache=int(2.5 * size)))) as c:
        for name in ("a", "b"):
            assert c.post(f"/scenes?name={name}", content=one, headers=AUTH).status_code == 201
        r = c.post("/scenes?name=c", content=one, headers=AUTH)
        assert r.status_code == 409 and "in memory only" in r.json()["detail"], r.text
        assert c.post("/scenes?name=b&replace=true", content=one,
                      headers=AUTH).status_code == 201


# --------------------------------------------------------------------------- barrier, caching


def test_swap_barrier(client):
    wid = new_wall(client, wall={**WALL, "cols": 2, "rows": 1})
    try:
        post_frame(client, wid)
        post_frame(client, wid)

        def barrier(frame):
            r = client.get(f"/walls/{wid}/barrier/{frame}?timeout=0")
            assert r.status_code == 200
            return r.json()

        assert barrier(0) == {"frame": 0, "acked": 0, "tiles": 2, "complete": False}
        client.post(f"/walls/{wid}/tiles/0/ack", json={"frame": 0}, headers=AUTH)
        assert barrier(0)["acked"] == 1 and not barrier(0)["complete"]
        client.post(f"/walls/{wid}/tiles/1/ack", json={"frame": 1}, headers=AUTH)
        assert barrier(0)["complete"] and barrier(1)["acked"] == 1
        client.post(f"/walls/{wid}/tiles/1/ack", json={"frame": 0}, headers=AUTH)  # no going back
        assert barrier(1)["acked"] == 1 and barrier(0)["complete"]
        client.post(f"/walls/{wid}/tiles/0/ack", json={"frame": 1}, headers=AUTH)
        assert barrier(1)["complete"] and barrier(2) == {"frame": 2, "acked": 0, "tiles": 2,
                                                         "complete": False}
        r = client.get(f"/walls/{wid}/barrier/1?timeout=5", headers={"Accept": MP})
        assert msgpack.unpackb(r.content)["complete"] is True  # complete: no waiting
    finally:
        client.delete(f"/walls/{wid}", headers=AUTH)


def test_the_index_links_a_few_nodes_of_each_wall_not_every_one(client, monkeypatch):
    """``GET /`` is open: it links the view pages of a wall's first node credentials only
    (at most ``INDEX_NODES``, of ``INDEX_TILES`` tiles in all), and says how many more there
    are, so that its size does not grow with the walls' (a 256 x 256 wall's 65,536 links were
    3.9 MB, made on the event loop at every request)."""
    from wallcull.server import pages

    monkeypatch.setattr(pages, "INDEX_TILES", 40, raising=False)
    grid = {**WALL, "cols": 16, "rows": 16}
    one = new_wall(client, wall=grid)  # a node per tile: 256
    rows = new_wall(client, wall=grid, nodes=[list(range(16 * k, 16 * k + 16))
                                              for k in range(16)])
    try:
        page = client.get("/").text
        row = page.split(f'id="wall-{one}"')[1].split("</tr>")[0]
        assert row.count("/view?tiles=") == 8  # INDEX_NODES
        assert f'/walls/{one}/view?tiles=7"' in row and "?tiles=8\"" not in row
        assert f"and {256 - 8} more node(s)" in row and f'href="/walls/{one}"' in row
        row = page.split(f'id="wall-{rows}"')[1].split("</tr>")[0]
        assert row.count("/view?tiles=") == 2 and "?tiles=16-31" in row  # 32 of 40 tiles
        assert "and 14 more node(s)" in row
    finally:
        for wid in (one, rows):
            client.delete(f"/walls/{wid}", headers=AUTH)


def assert_documented(client, r) -> None:
    """``r`` is an answer the OpenAPI document declares for its request's operation: its
    status, its content type and its ``Retry-After``."""
    doc = client.app.openapi()
    method, path = r.request.method.lower(), r.request.url.path
    found = [t for t, ops in doc["paths"].items()
             if method in ops and re.fullmatch(re.sub(r"\{[^}]+\}", "[^/]+", t), path)]
    assert len(found) == 1, (method, path, found)
    declared = doc["paths"][found[0]][method]["responses"].get(str(r.status_code))
    where = f"{method.upper()} {found[0]}: {r.status_code}"
    assert declared is not None, f"{where} is not in the document"
    if r.content:
        media = r.headers["content-type"].split(";")[0]
        assert media in declared.get("content", {}), f"{where} in {media} is not in the document"
    if "retry-after" in r.headers:
        assert "Retry-After" in declared.get("headers", {}), f"{where}: Retry-After undocumented"


def test_every_route_documents_what_it_answers(client, wid):
    """Each operation of the OpenAPI document declares what it answers: the 422 of an
    unknown query parameter (the gate's, on every route), and msgpack where JSON is, asked
    for by ``Accept`` or sent as a body. (The 503s and 507s: where they are provoked.)"""
    post_frame(client, wid)
    nodes = client.get("/scenes/two.glb?nodes=true").json()["nodes"]
    row = nodes["leaf"].index(True)
    real = {"wid": wid, "tile": 0, "frame": 0, "name": "two.glb", "node": nodes["id"][row],
            "key": nodes["mesh"][row]}
    doc = client.app.openapi()
    for template, ops in doc["paths"].items():
        path = template.format(**real)
        for method, op in ops.items():
            r = client.request(method, f"{path}?bogus=1", headers=AUTH)
            assert r.status_code == 422 and "bogus" in r.text, (method, path, r.text)
            assert_documented(client, r)
            body = op.get("requestBody", {}).get("content", {})
            if "application/json" in body:
                assert body.get(MP) == body["application/json"], (method, template)
            if method == "get":
                r = client.get(path, headers={**AUTH, "Accept": MP})
                assert r.status_code == 200, (path, r.text)
                assert_documented(client, r)
                if MP in op["responses"]["200"].get("content", {}):
                    assert r.headers["content-type"] == MP, path
    r = client.post(f"/walls/{wid}/frames", content=msgpack.packb({"frame": FRAME}),
                    headers={**AUTH, "Content-Type": MP, "Accept": MP})
    assert r.status_code == 200 and msgpack.unpackb(r.content)["frame"] == 1
    assert_documented(client, r)


def assert_one_etag_per_format(client, path: str) -> None:
    """JSON and msgpack answers of ``path`` (chosen by ``Accept``) vary by ``Accept`` and
    each has its own ETag: a cache never answers one format for the other, and the ETag of
    one is no 304 for the other (RFC 9110, 8.8.3: a strong ETag names one representation)."""
    plain, packed = client.get(path), client.get(path, headers={"Accept": MP})
    assert plain.headers["content-type"].startswith("application/json")
    assert packed.headers["content-type"].startswith(MP)
    for r in (plain, packed):
        assert "accept" in [v.strip().lower() for v in r.headers.get("vary", "").split(",")]
    assert plain.headers["etag"] != packed.headers["etag"]
    for accept, held, status in ((MP, plain, 200), (MP, packed, 304), ("*/*", packed, 200),
                                 ("*/*", plain, 304)):
        r = client.get(path, headers={"Accept": accept, "If-None-Match": held.headers["etag"]})
        assert r.status_code == status, (accept, held.headers["etag"])
        if status == 200:
            assert r.content == (packed if accept == MP else plain).content
        else:
            assert r.headers["etag"] == held.headers["etag"]
            assert "accept" in r.headers["vary"].lower()


def test_meshes_by_etag(client):
    nodes = client.get("/scenes/two.glb?nodes=true").json()["nodes"]
    scene = glb_from_bytes(boxes_glb(), "two")
    assert nodes["name"] == list(scene.names)
    leaf = nodes["leaf"].index(True)
    r = client.get(f"/scenes/two.glb/nodes/{leaf}/mesh")
    assert r.status_code == 200
    etag = r.headers["etag"]
    body = r.json()
    v, f = scene.meshes[nodes["mesh"][leaf]]
    assert body["vertices"]["shape"] == [len(v), 3] and body["faces"]["shape"] == [len(f), 3]
    got_v = np.frombuffer(base64.b64decode(body["vertices"]["data"]), "<f4").reshape(-1, 3)
    got_f = np.frombuffer(base64.b64decode(body["faces"]["data"]), "<u4").reshape(-1, 3)
    np.testing.assert_array_equal(got_v, v.astype("<f4"))
    np.testing.assert_array_equal(got_f, f)
    binary = msgpack.unpackb(client.get(f"/scenes/two.glb/meshes/{body['mesh']}",
                                        headers={"Accept": MP}).content)
    assert binary["vertices"]["data"] == got_v.tobytes()
    r = client.get(f"/scenes/two.glb/meshes/{body['mesh']}", headers={"If-None-Match": etag})
    assert r.status_code == 304 and r.content == b"" and r.headers["etag"] == etag
    r = client.get(f"/scenes/two.glb/meshes/{body['mesh']}", headers={"If-None-Match": '"x"'})
    assert r.status_code == 200
    for held in (f"W/{etag}", f'"x", {etag}', "*"):  # weakly, in a list, any (RFC 9110)
        r = client.get(f"/scenes/two.glb/meshes/{body['mesh']}", headers={"If-None-Match": held})
        assert r.status_code == 304, held
    assert_one_etag_per_format(client, f"/scenes/two.glb/nodes/{leaf}/mesh")
    assert client.get("/scenes/two.glb/nodes/0/mesh").status_code == 404  # the root has none
    assert client.get("/scenes/two.glb/nodes/99/mesh").status_code == 404
    assert client.get("/scenes/two.glb/meshes/nope").status_code == 404


def test_history_overflow_and_late_acks(client, fatehpur):
    wid = new_wall(client, history=3)
    try:
        for _ in range(6):
            post_frame(client, wid)
        r = client.get(f"/walls/{wid}/tiles/0/packets/1", headers=AUTH)
        assert r.status_code == 410 and "left the history (oldest 3)" in r.json()["detail"]
        assert client.get(f"/walls/{wid}/tiles/0/packets/3", headers=AUTH).status_code == 200
        client.post(f"/walls/{wid}/tiles/0/ack", json={"frame": 1}, headers=AUTH)
        pkt = client.get(f"/walls/{wid}/tiles/0/packets/5", headers=AUTH).json()
        assert pkt["base"] is None  # its acknowledged frame is gone: a full list
        client.post(f"/walls/{wid}/tiles/0/ack", json={"frame": 4}, headers=AUTH)
        pkt = client.get(f"/walls/{wid}/tiles/0/packets/latest", headers=AUTH).json()
        assert (pkt["frame"], pkt["base"], pkt["added"], pkt["removed"]) == (5, 4, [], [])
    finally:
        client.delete(f"/walls/{wid}", headers=AUTH)


def test_wall_limit(tmp_path):
    with TestClient(create_app(None, token=TOKEN, max_walls=2)) as c:
        ids = [new_wall(c, wall={**WALL, "cols": 1, "rows": 1}) for _ in range(2)]
        r = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=AUTH)
        assert r.status_code == 409 and "already holds 2 walls" in r.json()["detail"]
        assert c.delete(f"/walls/{ids[0]}", headers=AUTH).status_code == 204
        assert c.delete(f"/walls/{ids[0]}", headers=AUTH).status_code == 404
        new_wall(c)
        assert len(c.get("/walls").json()["walls"]) == 2


def test_delete_closes_streams(client):
    wid = new_wall(client)
    post_frame(client, wid)
    m0 = metrics(client)
    nodes = [WsNode(client, wid, t, binary=t % 2 == 0) for t in range(3)]
    try:
        for node in nodes:
            assert node.message()["frame"] == 0
        assert client.get(f"/walls/{wid}").json()["subscribers"] == 3
        assert metric(metrics(client), "wallcull_clients_connected") == \
            metric(m0, "wallcull_clients_connected") + 3
        assert client.delete(f"/walls/{wid}", headers=AUTH).status_code == 204
        for node in nodes:
            with pytest.raises(WebSocketDisconnect) as closed:
                node.message()
            assert closed.value.code == 4404
    finally:
        for node in nodes:
            node.close()
    _wait_for(lambda: metric(metrics(client), "wallcull_clients_connected") ==
              metric(m0, "wallcull_clients_connected"), "the clients counted out")
    assert client.get(f"/walls/{wid}").status_code == 404
    with pytest.raises(WebSocketDenialResponse) as refused:
        with client.websocket_connect(f"/walls/{wid}/tiles/0/stream?token={TOKEN}") as ws:
            ws.receive_bytes()
    assert refused.value.status_code == 404 and "no wall" in refused.value.json()["detail"]


def test_metrics_count_frames_packets_bytes_errors_and_clients(tmp_path):
    with TestClient(create_app(None, token=TOKEN, max_body=MAX_BODY)) as c:
        wid = new_wall(c)
        http = HttpNode(c, wid, 0)
        for n in range(5):
            post_frame(c, wid)
            http.fetch(n)
            http.ack(n)
        again = c.get(f"/walls/{wid}/tiles/0/packets/4?full=true", headers=AUTH)
        assert again.json()["base"] is None
        http.sizes["full"] += len(again.content)
        node = WsNode(c, wid, 1)
        node.until(4, lambda *a: None)
        node.send({"ack": 4})
        _wait_for(lambda: c.get(f"/walls/{wid}/barrier/4?timeout=0").json()["acked"] == 2,
                  "the acknowledgement to land")
        post_frame(c, wid)
        node.until(5, lambda *a: None)
        m = metrics(c)
        assert metric(m, "wallcull_frames_total") == 6
        assert metric(m, "wallcull_packets_total", kind="full", transport="http") == 2
        assert metric(m, "wallcull_packets_total", kind="delta", transport="http") == 4
        assert metric(m, "wallcull_packet_bytes_total", kind="full", transport="http") == \
            http.sizes["full"]
        assert metric(m, "wallcull_packet_bytes_total", kind="delta", transport="http") == \
            http.sizes["delta"]
        ws_full = sum(p["base"] is None for p in node.received)
        assert metric(m, "wallcull_packets_total", kind="full", transport="ws") == ws_full >= 1
        assert metric(m, "wallcull_packets_total", kind="delta", transport="ws") == \
            len(node.received) - ws_full
        assert metric(m, "wallcull_packet_bytes_total", kind="full", transport="ws") == \
            node.sizes["full"]
        assert metric(m, "wallcull_packet_bytes_total", kind="delta", transport="ws") == \
            node.sizes["delta"]
        assert metric(m, "wallcull_clients_connected") == 1
        node.close()
        _wait_for(lambda: metric(metrics(c), "wallcull_clients_connected") == 0,
                  "the client counted out")
        for status, request in ((401, dict(method="POST", url="/walls", json={})),
                                (422, dict(method="POST", url=f"/walls/{wid}/frames",
                                           json={"frame": {}}, headers=AUTH)),
                                (404, dict(method="GET", url="/walls/000000000000")),
                                (409, dict(method="POST", url=f"/walls/{wid}/frames",
                                           json={"frame": FRAME, "number": 0}, headers=AUTH)),
                                (413, dict(method="POST", url=f"/walls/{wid}/frames",
                                           content=b" " * (MAX_BODY + 1), headers=AUTH)),
                                (400, dict(method="POST", url=f"/walls/{wid}/frames",
                                           content=b"\xc1", headers={**AUTH,
                                                                     "Content-Type": MP}))):
            before = metric(metrics(c), "wallcull_errors_total", status=status)
            assert c.request(**request).status_code == status
            assert metric(metrics(c), "wallcull_errors_total", status=status) == before + 1
        assert metric(metrics(c), "wallcull_frames_total") == 6


# --------------------------------------------------------------------------- a real server


@pytest.fixture(scope="module")
def live():
    """wallcull on uvicorn, on a free loopback port, in a thread of this process."""
    import uvicorn

    app = create_app(None, token=TOKEN)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on",
                                           **uvicorn_options(app)))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.02)
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", trust_env=False, timeout=30) as http:
        yield SimpleNamespace(http=http, ws=f"ws://127.0.0.1:{port}", app=app)
    server.should_exit = True
    thread.join(30)
    sock.close()


def _connect(live, wid, tile, sock=None, token=TOKEN, fmt="msgpack"):
    from websockets.sync.client import connect

    return connect(f"{live.ws}/walls/{wid}/tiles/{tile}/stream?format={fmt}&token={token}",
                   sock=sock, proxy=None, open_timeout=30, close_timeout=5, compression=None)


def _until(ws, number, node: Holder, check, fmt="msgpack"):
    while True:
        raw = ws.recv(timeout=30)
        pkt = msgpack.unpackb(raw) if fmt == "msgpack" else json.loads(raw)
        assert "error" not in pkt, pkt
        node.take(pkt)
        check(pkt["frame"], pkt["tile"], node.current)
        if pkt["frame"] >= number:
            return pkt


def _live_wall(live, **extra):
    r = live.http.post("/walls", json={"wall": WALL, "scene": "fatehpur", **extra}, headers=AUTH)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _gauge(live) -> float:
    return metric(metrics(live.http), "wallcull_clients_connected")


def _wait_for(predicate, what):
    deadline = time.monotonic() + 30
    while not predicate():
        assert time.monotonic() < deadline, f"never {what}"
        time.sleep(0.02)


def test_live_stream_survives_a_node_that_vanishes_mid_stream(live, fatehpur):
    frames = fly(fatehpur, WALL, 40)
    session = Session(fatehpur, Wall.from_dict(WALL))
    wid = _live_wall(live)
    truth = {}
    stack = ExitStack()

    def check(number, tile, held):
        np.testing.assert_array_equal(held, truth[number][tile])

    def post(n):
        truth[n] = reference(fatehpur, WALL, frames[n], session=session)
        r = live.http.post(f"/walls/{wid}/frames", json={"frame": frames[n]}, headers=AUTH)
        assert r.status_code == 200 and r.json()["frame"] == n

    base = _gauge(live)
    raw = socket.create_connection(("127.0.0.1", int(live.ws.rsplit(":", 1)[1])))
    gone, kept = Holder(), Holder()
    try:
        steady = stack.enter_context(_connect(live, wid, 1, fmt="json"))
        with _connect(live, wid, 0, sock=raw) as vanishing:
            for n in range(20):
                post(n)
                _until(vanishing, n, gone, check)
                _until(steady, n, kept, check, fmt="json")
                vanishing.send(msgpack.packb({"ack": n}))
                steady.send(json.dumps({"ack": n}))
            _wait_for(lambda: _gauge(live) == base + 2, "two clients")
            raw.shutdown(socket.SHUT_RDWR)  # no close frame: the node just disappears
            raw.close()
        for n in range(20, 40):
            post(n)
            _until(steady, n, kept, check, fmt="json")
            steady.send(json.dumps({"ack": n}))
        _wait_for(lambda: _gauge(live) == base + 1, "the vanished client to be counted out")
        assert live.http.get("/health").json()["status"] == "ok"
        assert live.http.get(f"/walls/{wid}").json()["subscribers"] == 1
        # the same tile again: a new connection starts from a full list of the newest frame
        with _connect(live, wid, 0) as again:
            pkt = _until(again, 39, Holder(), check)
            assert pkt["base"] is None and pkt["frame"] == 39
        assert kept.full == 1 and kept.deltas > 30
    finally:
        stack.close()
        live.http.delete(f"/walls/{wid}", headers=AUTH)
    _wait_for(lambda: _gauge(live) == base, "every client counted out")


def test_live_barrier_waits_for_every_tile(live):
    wid = _live_wall(live, wall={**WALL, "cols": 2, "rows": 1})
    try:
        live.http.post(f"/walls/{wid}/frames", json={"frame": FRAME}, headers=AUTH)
        with ThreadPoolExecutor(2) as pool:
            waiting = pool.submit(live.http.get, f"/walls/{wid}/barrier/0?timeout=10")
            for tile in (0, 1):
                live.http.post(f"/walls/{wid}/tiles/{tile}/ack", json={"frame": 0},
                               headers=AUTH)
            r = waiting.result(30)
        assert r.json() == {"frame": 0, "acked": 2, "tiles": 2, "complete": True}
    finally:
        live.http.delete(f"/walls/{wid}", headers=AUTH)


def test_live_delete_wakes_every_waiter(live):
    """Deleting a wall answers a long poll and a barrier wait at once, and closes its
    streams with code 4404."""
    from websockets.exceptions import ConnectionClosed

    wid = _live_wall(live)
    live.http.post(f"/walls/{wid}/frames", json={"frame": FRAME}, headers=AUTH)
    with _connect(live, wid, 2) as ws, ThreadPoolExecutor(2) as pool:
        assert msgpack.unpackb(ws.recv(timeout=30))["frame"] == 0
        packet = pool.submit(live.http.get, f"/walls/{wid}/tiles/0/packets/1?wait=10",
                             headers=AUTH)
        barrier = pool.submit(live.http.get, f"/walls/{wid}/barrier/0?timeout=10")
        time.sleep(0.3)  # let both requests reach the server and wait there
        assert live.http.delete(f"/walls/{wid}", headers=AUTH).status_code == 204
        for future in (packet, barrier):  # woken, not left to spin until their timeouts
            r = future.result(30)
            assert r.status_code == 404, r.text
            assert "deleted" in r.json()["detail"] or "no wall" in r.json()["detail"]
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=30)
        assert closed.value.rcvd.code == 4404
    assert live.http.get("/health").json()["walls"] == 0


def test_live_delete_closes_the_driver_stream_at_once(live):
    """The driver's frame stream closes with 4404 when its wall is deleted, as the others do,
    without another frame to cull on a wall that is gone."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    wid = _live_wall(live)
    with connect(f"{live.ws}/walls/{wid}/frames/stream?token={TOKEN}", proxy=None,
                 open_timeout=30, close_timeout=5, compression=None) as ws:
        ws.send(msgpack.packb({"frame": FRAME}))
        assert msgpack.unpackb(ws.recv(timeout=30))["frame"] == 0
        assert live.http.delete(f"/walls/{wid}", headers=AUTH).status_code == 204
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=30)
        assert closed.value.rcvd.code == 4404


def test_live_the_window_counts_packets_not_frame_numbers(live):
    """A stream opened on a wall far into its frames is sent 8 packets before it must
    acknowledge one; then it is sent the newest frame, not the ones it missed."""
    wid = _live_wall(live, wall={**WALL, "cols": 1, "rows": 1})
    try:
        for n in range(40):
            live.http.post(f"/walls/{wid}/frames", json={"frame": FRAME}, headers=AUTH)
        with _connect(live, wid, 0) as ws:
            got = [msgpack.unpackb(ws.recv(timeout=30))["frame"]]
            for n in range(40, 49):
                live.http.post(f"/walls/{wid}/frames", json={"frame": FRAME}, headers=AUTH)
            got += [msgpack.unpackb(ws.recv(timeout=30))["frame"] for _ in range(7)]
            assert got == list(range(39, 47))  # 8 packets, none acknowledged
            ws.send(msgpack.packb({"ack": 39}))
            # frames 47 and 48 were posted while the window was full: the newest comes next
            assert msgpack.unpackb(ws.recv(timeout=30))["frame"] == 48
    finally:
        live.http.delete(f"/walls/{wid}", headers=AUTH)


def test_live_refused_handshakes_are_answers_not_errors(live):
    """A refused stream gets its status and reason, and the server logs no error for it
    (uvicorn's own WebSocket protocol logged each as a failed application)."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    wid = _live_wall(live)
    errors = []
    handler = logging.Handler(logging.ERROR)
    handler.emit = errors.append
    logger = logging.getLogger("uvicorn.error")
    logger.addHandler(handler)
    try:
        for path, status, why in (
                ("/walls/000000000000/tiles/0/stream", 404, "no wall"),
                (f"/walls/{wid}/tiles/0/stream?format=xml", 422, "format must be"),
                (f"/walls/{wid}/nodes/stream?format=xml", 422, "format must be"),
                (f"/walls/{wid}/frames/stream?format=xml", 422, "format must be"),
                (f"/walls/{wid}/nodes/stream", 422, "say which tiles")):
            sep = "&" if "?" in path else "?"
            with pytest.raises(InvalidStatus) as refused:
                connect(f"{live.ws}{path}{sep}token={TOKEN}", proxy=None, open_timeout=30)
            assert refused.value.response.status_code == status, path
            assert why in json.loads(refused.value.response.body)["detail"], path
        assert live.http.get("/health").json()["status"] == "ok"
    finally:
        logger.removeHandler(handler)
        live.http.delete(f"/walls/{wid}", headers=AUTH)
    assert not errors, [r.getMessage() for r in errors]


def test_a_node_stream_naming_no_tiles_is_told_to_on_a_server_without_token():
    with TestClient(create_app(None)) as c:
        wid = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}).json()["id"]
        for query in ("", "?format=json", "?token="):
            with pytest.raises(WebSocketDenialResponse) as refused:
                with c.websocket_connect(f"/walls/{wid}/nodes/stream{query}"):
                    pass
            assert refused.value.status_code == 422
            assert "say which tiles" in refused.value.json()["detail"]


def test_history_times_tiles_is_capped(client):
    big = {**WALL, "cols": 64, "rows": 64, "tile_size": [0.05, 0.03], "gap": [0.0, 0.0]}
    r = client.post("/walls", json={"wall": big, "scene": "fatehpur", "history": 1024},
                    headers=AUTH)
    assert r.status_code == 422 and "at most 256 frames" in r.json()["detail"]
    r = client.post("/walls", json={"wall": big, "scene": "fatehpur", "history": 256},
                    headers=AUTH)
    assert r.status_code == 201
    client.delete(f"/walls/{r.json()['id']}", headers=AUTH)


def test_the_server_keeps_answering_while_a_frame_is_culled(monkeypatch):
    """A frame is computed in a worker thread: requests that arrive meanwhile are answered
    before it finishes (checked by order of completion, not by timing)."""
    import asyncio
    import threading

    import httpx

    from wallcull import service

    started, release = threading.Event(), threading.Event()
    real = service.WallSession.compute_frame

    def slow(self, *args, **kwargs):
        started.set()
        release.wait(5)  # held until the test has been answered meanwhile
        return real(self, *args, **kwargs)

    monkeypatch.setattr(service.WallSession, "compute_frame", slow)
    app = create_app(token=TOKEN)

    async def scenario():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as c:
            wid = (await c.post("/walls", json={"wall": WALL, "scene": "fatehpur"},
                                headers=AUTH)).json()["id"]
            order = []

            async def post():
                r = await c.post(f"/walls/{wid}/frames", json={"frame": FRAME}, headers=AUTH)
                order.append(("frame", r.status_code))

            task = asyncio.create_task(post())
            while not started.is_set():
                await asyncio.sleep(0.01)
            r = await c.get("/health")
            order.append(("health", r.status_code))
            release.set()
            await task
            return order

    assert asyncio.run(scenario()) == [("health", 200), ("frame", 200)]


def test_a_wall_can_cull_what_occluders_hide(client):
    """``occlusion`` on POST /walls: inside the power plant, "on" lists fewer leaves than "off"
    in no tile more; "auto" culls like "on" from inside the scene; bad values are refused."""
    frame = {"position": [30.0, 12.0, 20.0], "orientation": [0.9238795, 0.0, 0.3826834, 0.0]}
    walls = {mode: new_wall(client, "powerplant", occlusion=mode) for mode in ("off", "on", "auto")}
    lists = {}
    for mode, wid in walls.items():
        assert client.get(f"/walls/{wid}").json()["occlusion"] == mode
        packets = post_frame(client, wid, frame, packets=True)["packets"]
        lists[mode] = [set(p["visible"]) for p in sorted(packets, key=lambda p: p["tile"])]
    assert all(on <= off for on, off in zip(lists["on"], lists["off"]))
    assert sum(map(len, lists["on"])) < sum(map(len, lists["off"]))
    assert lists["auto"] == lists["on"]
    r = client.post("/walls", json={"wall": WALL, "scene": "powerplant", "occlusion": "yes"},
                    headers=AUTH)
    assert r.status_code == 422, r.text
    for wid in walls.values():
        client.delete(f"/walls/{wid}", headers=AUTH)


def test_a_wall_can_declare_its_own_lights_and_mirrors(client):
    """``settings`` on POST /walls replaces the scene's own (the power plant declares none),
    ``shadow_fit`` picks the fitting effort; bad settings are refused before any frame."""
    lights = json.loads((pathlib.Path(__file__).parent.parent / "scenes" /
                         "powerplant-lights.json").read_text())
    frame = {"position": [0.0, 60.0, 160.0], "orientation": [0.9659258, -0.2588190, 0.0, 0.0]}
    plain, lit = new_wall(client, "powerplant"), new_wall(client, "powerplant", settings=lights,
                                                           shadow_fit="greedy")
    info = client.get(f"/walls/{lit}").json()
    assert info["settings"] == lights and info["shadow_fit"] == "greedy"
    packets = {}
    for wid in (plain, lit):
        packets[wid] = post_frame(client, wid, frame, packets=True)["packets"]
    assert not any("shadows" in p or "mirrors" in p for p in packets[plain])
    shaded = [p for p in packets[lit] if "shadows" in p]
    assert shaded and all(s["light"] == "roof_lamp" for p in shaded for s in p["shadows"])
    assert any("mirrors" in p for p in packets[lit])
    for bad in ({"lights": [{"name": "x"}]}, {"mirrors": [{"normal": [0, 0, 0]}]}, {"sun": 1},
                {"occlusion": {"budget": -1}}, {"occlusion": {"exclude": "roof"}}):
        r = client.post("/walls", json={"wall": WALL, "scene": "powerplant", "settings": bad},
                        headers=AUTH)
        assert r.status_code == 422, (bad, r.text)
    for wid in (plain, lit):
        client.delete(f"/walls/{wid}", headers=AUTH)


def test_a_wall_can_say_what_never_occludes(client):
    """``settings.occlusion`` on POST /walls: the nodes that never occlude and the occluder
    budget, used by a wall with occlusion on; a name the scene lacks is refused."""
    frame = {"position": [0.0, 5.0, 0.0], "orientation": [1.0, 0.0, 0.0, 0.0]}
    wids = {}
    for name, settings in (("plain", {}), ("none", {"occlusion": {"budget": 0}})):
        wids[name] = new_wall(client, "powerplant", settings=settings, occlusion="on")
    counts = {name: sum(len(p["visible"]) for p in post_frame(client, wid, frame,
                                                             packets=True)["packets"])
              for name, wid in wids.items()}
    assert counts["none"] > counts["plain"]  # no occluder: nothing hidden
    r = client.post("/walls", json={"wall": WALL, "scene": "powerplant", "occlusion": "on",
                                    "settings": {"occlusion": {"exclude": ["no such node"]}}},
                    headers=AUTH)
    assert r.status_code == 422 and "no such node" in r.text, r.text
    for wid in wids.values():
        client.delete(f"/walls/{wid}", headers=AUTH)


def test_a_scene_a_wall_is_being_made_on_is_not_replaced(client, folder):
    """Replaced while a wall was being made on it (the scene loaded and bounded, the wall
    built: seconds), a scene was culled as the old file while the server served the new one:
    the nodes asked for meshes of ids the new scene has not."""
    old, new = boxes_glb(("a", "b")), boxes_glb(("c",))
    assert client.post("/scenes?name=making.glb", content=old, headers=AUTH).status_code == 201
    try:
        with client.app.state.server.walls.reservation("making.glb"):
            r = client.post("/scenes?name=making.glb&replace=true", content=new, headers=AUTH)
            assert r.status_code == 409 and "one being made" in r.json()["detail"], r.text
        assert (folder.scenes / "making.glb").read_bytes() == old
        r = client.post("/scenes?name=making.glb&replace=true", content=new, headers=AUTH)
        assert r.status_code == 201, r.text
    finally:
        (folder.scenes / "making.glb").unlink()


def test_an_upload_killed_with_its_server_leaves_no_spool_behind(folder):
    """A server killed while receiving an upload left its spooled body in the scene folder,
    forever. Spools older than any upload could still be written and parsed are removed;
    a spool of an upload in progress is not."""
    import time

    from wallcull.service import SceneStore

    store = SceneStore(folder.scenes)
    stale, fresh = (folder.scenes / ".upload.stale.tmp", folder.scenes / ".upload.fresh.tmp")
    for path in (stale, fresh):
        path.write_bytes(b"half a body")
    old = time.time() - (store.limits.body_seconds + store.limits.parse_seconds + 61)
    os.utime(stale, (old, old))
    try:
        assert store.sweep() == [".upload.stale.tmp"]
        assert not stale.exists() and fresh.exists()
        assert (folder.scenes / "two.glb").exists()
    finally:
        for path in (stale, fresh):
            path.unlink(missing_ok=True)


def test_an_upload_cannot_take_the_place_of_a_folder(client, folder):
    (folder.scenes / "dir.glb").mkdir()
    try:
        r = client.post("/scenes?name=dir.glb&replace=true", content=boxes_glb(), headers=AUTH)
        assert r.status_code == 409 and "not a file" in r.json()["detail"], r.text
        assert (folder.scenes / "dir.glb").is_dir()
    finally:
        (folder.scenes / "dir.glb").rmdir()


def test_a_frame_culled_as_its_wall_is_deleted_is_neither_published_nor_answered():
    """A frame in the worker thread when its wall was deleted was answered 200, with a
    number, after the DELETE's 204: it is a 404 now, and the wall publishes nothing more."""
    import asyncio
    import threading

    from wallcull.service import NotFound, Walls
    from wallcull.wall import Wall

    walls = Walls()
    session = walls.create(load("fatehpur"), Wall.from_dict(WALL), "adaptive", "obb", False, 8)
    culling, go_on = threading.Event(), threading.Event()
    compute = session.compute_frame

    def slow(*args):
        culling.set()
        go_on.wait(60)
        return compute(*args)

    session.compute_frame = slow

    async def race():
        posted = asyncio.ensure_future(session.post_frame_async(
            {"position": [0.0, 20.0, 300.0], "orientation": [1.0, 0.0, 0.0, 0.0]}))
        await asyncio.to_thread(culling.wait, 60)
        walls.delete(session.id)
        go_on.set()
        with pytest.raises(NotFound, match="deleted"):
            await posted

    asyncio.run(race())
    assert session.latest == -1


def test_a_replacing_upload_waits_for_a_load_of_the_old_file(folder, tmp_path, monkeypatch):
    """A load of a scene file that ended after an upload replaced the file cached the old
    scene over the new one: walls made then culled the old geometry. The upload now takes
    the name's lock, as a load does, and waits for it."""
    import asyncio
    import threading

    import wallcull.service as service
    from wallcull.service import SceneStore

    name, old, new = "racing.glb", boxes_glb(("a", "b")), boxes_glb(("c",))
    (folder.scenes / name).write_bytes(old)
    spool = tmp_path / "new.glb"
    spool.write_bytes(new)
    parsed = threading.Event()
    parse = service.parse_sandboxed
    monkeypatch.setattr(service, "parse_sandboxed",
                        lambda *a: (parse(*a), parsed.set())[0])
    store = SceneStore(folder.scenes)

    async def race():
        lock = store._locks.setdefault(name, asyncio.Lock())
        await lock.acquire()  # a load of the old file, in progress
        upload = asyncio.ensure_future(store.upload(name, spool))
        await asyncio.to_thread(parsed.wait, 120)
        await asyncio.sleep(0.2)
        assert (folder.scenes / name).read_bytes() == old and not upload.done()
        store.cache[name] = glb_from_bytes(old, name)  # what the load caches as it ends
        lock.release()
        return await upload

    try:
        scene = asyncio.run(race())
        assert store.cache[name] is scene and scene.stats["leaves"] == 1
        assert (folder.scenes / name).read_bytes() == new
    finally:
        (folder.scenes / name).unlink()


# --------------------------------------------------------------------------- big scenes, small


def balls_glb() -> bytes:
    """Two spheres of 1,280 triangles (each cut into clusters) with a box between them: the
    first sphere's clusters take ids before the box's and the second sphere's."""
    s = trimesh.Scene()
    for k, name in enumerate(("a_ball", "b_box", "c_ball")):
        m = np.eye(4)
        m[:3, 3] = [3.0 * (k - 1), 0, -10]
        mesh = trimesh.creation.box(extents=[1, 1, 1]) if "box" in name else \
            trimesh.creation.icosphere(subdivisions=3)
        s.add_geometry(mesh, node_name=name, geom_name=name, transform=m)
    return s.export(file_type="glb")


def test_the_node_table_leaves_clusters_out_and_keeps_the_ids(tmp_path):
    """``?nodes=true`` has no cluster rows (``#c0``, ...: 60% of a big scene's rows), and
    each row names its node id: a leaf after some clusters keeps the id frames and the node
    mesh route use, and the simulated nodes read the table by id."""
    from wallcull_clients.sim import SceneInfo

    (tmp_path / "balls.glb").write_bytes(balls_glb())
    scene = load(str(tmp_path / "balls.glb"))
    clusters = set(scene.clusters.tolist())
    kept = [i for i in range(len(scene)) if i not in clusters]
    assert clusters and max(kept) > min(clusters)  # rows after clusters: ids that must hold
    with TestClient(create_app(tmp_path, token=TOKEN)) as c:
        body = c.get("/scenes/balls.glb?nodes=true").json()
    nodes = body["nodes"]
    assert not any(n.startswith("#c") for n in nodes["name"])
    assert nodes["count"] == len(scene) and nodes["id"] == kept
    assert nodes["name"] == [scene.names[i] for i in kept]
    assert nodes["mesh"] == [scene.geometry[i] for i in kept]
    np.testing.assert_array_equal(np.reshape(nodes["world"], (-1, 4, 4)), scene.world[kept])
    info = SceneInfo.from_description(body)
    assert sorted(info.leaves.tolist()) == scene.leaves.tolist()
    last = max(scene.leaves.tolist())  # the second sphere, after the first one's clusters
    assert info.keys[info.mesh_of[last]] == scene.geometry[last]
    np.testing.assert_array_equal(info.world[last], scene.world[last])


def test_the_node_table_is_encoded_once_and_revalidated_by_its_etag(tmp_path, monkeypatch):
    """A second ``?nodes=true`` is the bytes kept from the first (no new encoding), with the
    same ``ETag``; ``If-None-Match`` with it is a 304 without a body; msgpack has its own."""
    from wallcull.server import scenes as routes

    built = []
    real = routes.describe
    monkeypatch.setattr(routes, "describe",
                        lambda scene, nodes=True, arrays=False: (
                            built.append(nodes), real(scene, nodes, arrays))[1])
    (tmp_path / "two.glb").write_bytes(boxes_glb())
    with TestClient(create_app(tmp_path, token=TOKEN)) as c:
        first = c.get("/scenes/two.glb?nodes=true")
        second = c.get("/scenes/two.glb?nodes=true")
        assert first.status_code == second.status_code == 200
        assert built.count(True) == 1 and second.content == first.content
        etag = first.headers["etag"]
        assert second.headers["etag"] == etag
        held = c.get("/scenes/two.glb?nodes=true", headers={"If-None-Match": etag})
        assert held.status_code == 304 and held.content == b""
        packed = c.get("/scenes/two.glb?nodes=true", headers={"Accept": MP})
        assert packed.headers["etag"] != etag
        assert msgpack.unpackb(packed.content)["nodes"] == first.json()["nodes"]
        assert_one_etag_per_format(c, "/scenes/two.glb?nodes=true")
        assert built.count(True) == 2


def test_node_tables_being_encoded_leave_the_background_pool_free(tmp_path, monkeypatch):
    """Node tables of four scenes asked for at once, their encodings held: a wall is still
    created meanwhile (they used to take all four threads of the background pool, and a wall
    waited 76 s behind four big scenes' tables)."""
    import asyncio

    from wallcull.server import deps, scenes as routes

    started, release = threading.Semaphore(0), threading.Event()
    begun = []
    real = routes.describe

    def held(scene, nodes=True, arrays=False):
        if nodes:
            begun.append(scene.name)
            started.release()
            release.wait(120)
        return real(scene, nodes, arrays)

    monkeypatch.setattr(routes, "describe", held)
    names = [f"s{k}.glb" for k in range(4)]
    for name in names + ["wall.glb"]:
        (tmp_path / name).write_bytes(boxes_glb())
    app = create_app(tmp_path, token=TOKEN)
    at_once = min(4, getattr(deps, "NODE_ENCODES", 4))  # 4 before there was a bound

    async def scenario():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test",
                                     timeout=180) as c:
            for name in names + ["wall.glb"]:  # loaded first: only the tables are held
                assert (await c.get(f"/scenes/{name}")).status_code == 200
            tables = [asyncio.ensure_future(c.get(f"/scenes/{n}?nodes=true")) for n in names]
            for _ in range(at_once):
                assert await asyncio.to_thread(started.acquire, True, 120)
            try:
                made = await asyncio.wait_for(c.post("/walls", json={
                    "wall": WALL, "scene": "wall.glb"}, headers=AUTH), 60)
            finally:
                release.set()
            answers = await asyncio.gather(*tables)
            return made, answers

    made, answers = asyncio.run(scenario())
    assert made.status_code == 201, made.text
    assert [r.status_code for r in answers] == [200] * 4 and sorted(begun) == names


def test_a_scene_that_failed_to_prepare_is_refused_at_once_until_it_changes(tmp_path,
                                                                          monkeypatch):
    """A folder scene too big for ``parse_memory`` is refused with what to do (prepare it
    ahead, or raise the limit); asked again, for a wall too, it is refused at once without a
    new child process, until the file changes or a file is prepared into the cache folder."""
    from wallcull import sandbox
    from wallcull.errors import InputError

    children = []

    def too_big(target, args, *, seconds, memory, what):
        children.append(args)
        raise InputError(f"{what} needs more than {memory:,} bytes of memory")

    monkeypatch.setattr(sandbox, "run", too_big)
    monkeypatch.setenv("WALLCULL_CACHE", str(tmp_path / "cache"))
    (tmp_path / "cache").mkdir()
    path = tmp_path / "huge.glb"
    path.write_bytes(boxes_glb())
    with TestClient(create_app(tmp_path, token=TOKEN)) as c:
        first = c.get("/scenes/huge.glb")
        assert first.status_code == 422 and len(children) == 1
        detail = first.json()["detail"]
        assert "wallcull prepare" in detail and "parse_memory" in detail, detail
        again = c.get("/scenes/huge.glb?nodes=true")
        wall = c.post("/walls", json={"wall": WALL, "scene": "huge.glb"}, headers=AUTH)
        assert again.status_code == wall.status_code == 422
        assert again.json()["detail"] == wall.json()["detail"] == detail
        assert len(children) == 1
        stat = path.stat()
        os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10 ** 9))  # the file changed
        assert c.get("/scenes/huge.glb").status_code == 422 and len(children) == 2
        assert c.get("/scenes/huge.glb").status_code == 422 and len(children) == 2
        (tmp_path / "cache" / "ahead.wcprep").write_bytes(b"")  # `wallcull prepare` ran
        assert c.get("/scenes/huge.glb").status_code == 422 and len(children) == 3


def test_a_full_scene_cache_is_507_and_an_unwritable_one_503(tmp_path, monkeypatch, caplog):
    """A folder scene whose prepared file the cache folder cannot take is the server's disk
    problem, as for uploads: 507 when it is full, 503 when it cannot be written, for a wall
    too, logged once (it used to be a 422, the client's error)."""
    import errno
    import pickle

    from wallcull import prepared, sandbox

    (tmp_path / "scenes").mkdir()
    (tmp_path / "scenes" / "full.glb").write_bytes(boxes_glb())
    (tmp_path / "scenes" / "ro.glb").write_bytes(boxes_glb(("x", "y", "z")))

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as patch:  # a full disk, in this process
        patch.setattr(sandbox, "run", lambda target, args, **limits: target(*args))
        patch.setattr(prepared, "write", full)
        with TestClient(create_app(tmp_path / "scenes", token=TOKEN)) as c, \
                caplog.at_level(logging.ERROR, "wallcull"):
            r = c.get("/scenes/full.glb")
            assert r.status_code == 507, r.text
            assert "No space left on device" in r.json()["detail"]
            assert_documented(c, r)
            r = c.post("/walls", json={"wall": WALL, "scene": "full.glb"}, headers=AUTH)
            assert r.status_code == 507, r.text
            assert_documented(c, r)
            r = c.get("/scenes/full.glb/meshes/left")
            assert r.status_code == 507, r.text
            assert_documented(c, r)
        told = [rec for rec in caplog.records if "cache folder cannot be written" in
                rec.getMessage()]
        assert len(told) == 1
    # a cache folder that cannot be made, in the real child process
    (tmp_path / "plain").write_text("a file, not a folder")
    monkeypatch.setenv("WALLCULL_CACHE", str(tmp_path / "plain" / "cache"))
    with TestClient(create_app(tmp_path / "scenes", token=TOKEN)) as c:
        r = c.get("/scenes/ro.glb")
        assert r.status_code == 503, r.text
        assert_documented(c, r)
        r = c.post("/walls", json={"wall": WALL, "scene": "ro.glb"}, headers=AUTH)
        assert r.status_code == 503, r.text
        assert_documented(c, r)
    from wallcull.errors import WriteFailed  # what the child hands back, errno and all

    assert pickle.loads(pickle.dumps(WriteFailed("full", errno.ENOSPC))).errno == errno.ENOSPC
