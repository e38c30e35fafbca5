"""The AsyncAPI document (``/asyncapi.json``) against what the server actually sends: every
packet, node message, control and frame answer captured here on real streams (grids, walls of
screens, stereo frames, lights and mirrors, moved nodes, refusals) validates against its
message's JSON Schema, strictly; and the document names every stream the app serves."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import msgpack
import pytest
from fastapi.testclient import TestClient
from starlette.routing import WebSocketRoute

from wallcull.paths import camera_path
from wallcull.scene import load
from wallcull.server import create_app
from wallcull.server.access import leaf_routes
from wallcull.server.asyncapi import schema
from wallcull.wall import Wall

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "t0ken"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SETTINGS = json.loads((ROOT / "scenes" / "powerplant-lights.json").read_text())


def valid(name: str, message) -> None:
    jsonschema.validate(message, schema(name), cls=jsonschema.Draft202012Validator)


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(None, token=TOKEN, state=None)) as c:
        yield c


def test_the_document_names_every_stream_and_resolves(client):
    doc = client.get("/asyncapi.json").json()
    assert doc["asyncapi"].startswith("3.")
    served = {r.path for r in leaf_routes(client.app.router.routes)
              if isinstance(r, WebSocketRoute) or type(r).__name__ == "APIWebSocketRoute"}
    documented = {c["address"] for c in doc["channels"].values() if c["address"].startswith("/")}
    assert served and served == documented
    text = json.dumps(doc)
    for ref in {part.split('"')[0] for part in text.split('"$ref": "#/')[1:]}:
        node = doc
        for key in ref.split("/"):
            node = node[key]  # every reference resolves
    for name in doc["components"]["schemas"]:
        jsonschema.Draft202012Validator.check_schema(schema(name))


def frames(scene, wall, count=6):
    pts = scene.leaf_points[0]
    return [f.to_dict() for f in camera_path("orbit", pts.min(0), pts.max(0),
                                             Wall.from_dict(wall), 40)[:count]]


@pytest.mark.parametrize("wall_file, stereo", [("wall-4x4.json", False),
                                               ("wall-4x4.json", True),
                                               ("wall-cave.json", True)])
def test_what_the_streams_send_matches_the_document(client, wall_file, stereo):
    wall = json.loads((ROOT / "examples" / wall_file).read_text())
    r = client.post("/walls", json={"wall": wall, "scene": "powerplant", "settings": SETTINGS,
                                    "nodes": [[0, 1, 2]]}, headers=AUTH)
    assert r.status_code == 201, r.text
    wid, tiles = r.json()["id"], r.json()["tiles"]
    scene = load("powerplant")
    session = client.app.state.server.walls.get(wid)
    seen = {"Packet": 0, "NodeMessage": 0, "delta": 0, "left": 0, "shadows": 0, "mirrors": 0,
            "transforms": 0}
    q = f"token={TOKEN}"
    with client.websocket_connect(f"/walls/{wid}/frames/stream?{q}") as driver, \
            client.websocket_connect(f"/walls/{wid}/tiles/0/stream?{q}") as tile, \
            client.websocket_connect(f"/walls/{wid}/nodes/stream?tiles=0-2&{q}") as node:
        for k, frame in enumerate(frames(scene, wall)):
            if stereo:
                frame["stereo"] = {"ipd": 0.064}
            body = {"frame": frame}
            if k == 3:  # a leaf the node shows moves (to where it was): its transform is sent
                shown = session.history.get(2)
                leaf = next(int(shown.tile(t)[0]) for t in range(3) if len(shown.tile(t)))
                body["updates"] = {scene.names[leaf]: {"matrix": scene.local[leaf].tolist()}}
            driver.send_bytes(msgpack.packb(body))
            answer = msgpack.unpackb(driver.receive_bytes())
            valid("FrameAnswer", answer)
            pkt = msgpack.unpackb(tile.receive_bytes())
            msg = msgpack.unpackb(node.receive_bytes())
            valid("Packet", pkt)
            valid("NodeMessage", msg)
            seen["Packet"] += 1
            seen["NodeMessage"] += 1
            seen["delta"] += msg["base"] is not None
            seen["left"] += "left" in msg["tiles"][0]
            seen["shadows"] += any("shadows" in e for e in msg["tiles"])
            seen["mirrors"] += any("mirrors" in e for e in msg["tiles"])
            seen["transforms"] += "transforms" in msg or "transforms" in pkt
            for ws in (tile, node):
                control = {"ack": answer["frame"]}
                valid("Control", control)
                ws.send_bytes(msgpack.packb(control))
        driver.send_bytes(msgpack.packb({"frame": {"position": [0, 0, 0],
                                                   "orientation": [2, 0, 0, 0]}}))
        valid("FrameRefused", msgpack.unpackb(driver.receive_bytes()))
        node.send_bytes(msgpack.packb({"ack": "soon"}))
        valid("StreamError", msgpack.unpackb(node.receive_bytes()))
    client.delete(f"/walls/{wid}", headers=AUTH)
    assert seen["delta"] and seen["shadows"] and seen["transforms"], seen
    assert bool(seen["left"]) == stereo
