"""The AsyncAPI document of the streams (``GET /asyncapi.json``), next to the OpenAPI one: what a
lab implements in C++, C# or JavaScript to be a render node or a tracker.

Channels: a tile's WebSocket stream (packets), a render node's (node messages), the frame
stream of a driver, the operator console's status stream (:mod:`.pages`), and the NATS
subjects (:mod:`.nats`). The message schemas are JSON Schema
(2020-12) of :mod:`wallcull.protocol`'s packets and node messages, strict (no key they do not
list); the tests validate what the server sends, on every channel, against them.
"""

from __future__ import annotations

import json
from typing import Any

from .models import FramePost

NUMBER = {"type": "number"}
INT = {"type": "integer", "minimum": 0}
IDS = {"type": "array", "items": INT, "description": "leaf ids (scene.leaves), sorted"}
MAT4 = {"type": "array", "minItems": 4, "maxItems": 4,
        "items": {"type": "array", "minItems": 4, "maxItems": 4, "items": NUMBER},
        "description": "a 4 x 4 matrix, row by row (SPEC section 1)"}


def _strict(properties: dict, required=(), description: str = "") -> dict:
    out = {"type": "object", "properties": properties, "required": list(required),
           "additionalProperties": False}
    if description:
        out["description"] = description
    return out


def _vector(n: int) -> dict:
    return {"type": "array", "minItems": n, "maxItems": n, "items": NUMBER}


SCHEMAS: dict[str, Any] = {
    "Transforms": _strict({"ids": IDS, "matrices": {"type": "array", "items": _vector(16)}},
                          ("ids", "matrices"),
                          "world transforms of moved leaves the node may lack (row by row)"),
    "Shadow": _strict({"light": {"type": "string"}, "view": MAT4, "cube": {"const": True},
                       "views": {"type": "array", "minItems": 6, "maxItems": 6, "items": MAT4},
                       "projection": MAT4, "near": NUMBER, "far": NUMBER, "coverage": NUMBER,
                       "casters": IDS},
                      ("light", "projection", "near", "far", "casters"),
                      "a light's shadow frustum for the tile (Low-Ilie), or a cube map"),
    "Mirror": _strict({"mirror": {"type": "string"}, "view": MAT4, "projection": MAT4,
                       "front_face": {"const": "cw"}, "visible": IDS},
                      ("mirror", "view", "projection", "front_face", "visible"),
                      "a mirror the tile shows: reflected view, oblique near plane"),
    "EyeMirror": _strict({"mirror": {"type": "string"}, "view": MAT4, "projection": MAT4},
                         ("mirror", "view", "projection")),
    "Rigid": _strict({"rotation": _vector(4), "translation": _vector(3)},
                     ("rotation", "translation"),
                     "a view: the rotation of the unit quaternion [w, x, y, z], then the "
                     "translation"),
}
SCHEMAS["Eye"] = _strict({"view": MAT4, "projection": MAT4, "near": NUMBER, "far": NUMBER,
                          "mirrors": {"type": "array", "items": {"$ref": "#/$defs/EyeMirror"}}},
                         ("view", "projection", "near", "far"), "one eye of a stereo frame")
_LISTS = {"visible": IDS, "added": IDS, "removed": IDS, "count": INT}
SCHEMAS["Packet"] = _strict(
    {"frame": INT, "tile": INT, "time": NUMBER, "base": {"type": ["integer", "null"]},
     **_LISTS, "transforms": {"$ref": "#/$defs/Transforms"}, "view": MAT4,
     "projection": MAT4, "near": NUMBER, "far": NUMBER,
     "shadows": {"type": "array", "items": {"$ref": "#/$defs/Shadow"}},
     "mirrors": {"type": "array", "items": {"$ref": "#/$defs/Mirror"}},
     "left": {"$ref": "#/$defs/Eye"}, "right": {"$ref": "#/$defs/Eye"}},
    ("frame", "tile", "time", "base", "count", "view", "projection", "near", "far"),
    "one tile's frame (wallcull.protocol): its full list when base is null, else the delta "
    "against frame base")
_FRUSTUM = {"extent": _vector(4), "depth": _vector(2)}
SCHEMAS["TileEye"] = _strict(
    {"view": {"$ref": "#/$defs/Rigid"}, **_FRUSTUM,
     "mirrors": {"type": "array", "items": {"$ref": "#/$defs/EyeMirror"}}}, (),
    "one eye of a tile; extent and depth as the tile's")
SCHEMAS["TileEntry"] = _strict(
    {"tile": INT, **_LISTS, "view": {"$ref": "#/$defs/Rigid"}, **_FRUSTUM,
     "shadows": {"type": "array", "items": {"$ref": "#/$defs/Shadow"}},
     "mirrors": {"type": "array", "items": {"$ref": "#/$defs/Mirror"}},
     "left": {"$ref": "#/$defs/TileEye"}, "right": {"$ref": "#/$defs/TileEye"}},
    ("tile", "count"),
    "one tile of a node message: its list (visible), or the delta's non-empty parts; its "
    "frustum's extent [l/n, r/n, b/n, t/n] and depth [n, f] when they changed since the base "
    "(a node keeps them by frame); its own view on a wall of screens")
SCHEMAS["NodeMessage"] = _strict(
    {"frame": INT, "time": NUMBER, "base": {"type": ["integer", "null"]},
     "reversed_z": {"const": True}, "view": {"$ref": "#/$defs/Rigid"},
     "left": _strict({"view": {"$ref": "#/$defs/Rigid"}}, ("view",)),
     "right": _strict({"view": {"$ref": "#/$defs/Rigid"}}, ("view",)),
     "transforms": {"$ref": "#/$defs/Transforms"},
     "tiles": {"type": "array", "items": {"$ref": "#/$defs/TileEntry"}}},
    ("frame", "time", "base", "tiles"),
    "one frame for a render node of several tiles (wallcull.protocol; the matrices: "
    "wallcull_clients.frusta)")
SCHEMAS["Control"] = {**_strict({"ack": INT, "full": {"type": "boolean"}}, (),
                                "from a node: it has drawn frame ack; full: send full lists "
                                "next"), "minProperties": 1}
SCHEMAS["StreamError"] = _strict({"error": {"type": "string"}}, ("error",))
SCHEMAS["FrameAnswer"] = _strict(
    {"frame": INT, "timings": {"type": "object", "additionalProperties": NUMBER},
     "packets": {"type": "array", "items": {"$ref": "#/$defs/Packet"}}},
    ("frame", "timings"))
SCHEMAS["FrameRefused"] = _strict({"error": {"type": "string"}, "status": INT},
                                  ("error", "status"))
SCHEMAS["Empty"] = {"description": "an empty request"}
_COLUMN = "per tile, in tile order: "
SCHEMAS["ConsoleStatus"] = _strict(
    {"wall": {"type": "string"}, "frame": {"type": "integer", "minimum": -1},
     "time": NUMBER, "posted": {"type": ["number", "null"]},
     "count": {"type": "array", "items": INT, "description": _COLUMN + "list size"},
     "ack": {"type": "array", "items": {"type": "integer", "minimum": -1},
             "description": _COLUMN + "the newest frame acknowledged (-1: none)"},
     "latency_ms": {"type": "array", "items": {"type": ["number", "null"]},
                    "description": _COLUMN + "from that frame's post to its ack, ms"},
     "streams": {"type": "array", "items": INT, "description": _COLUMN + "streams open"},
     "state": {"type": "array", "items": {"enum": ["offline", "waiting", "drawing", "acked",
                                                   "lagging"]},
               "description": _COLUMN + "offline, waiting (no frame yet), drawing, acked "
                                        "(has drawn the newest frame) or lagging"}},
    ("wall", "frame", "time", "posted", "count", "ack", "latency_ms", "streams", "state"),
    "a wall's state for the operator console (JSON), whenever it changes; frame: the "
    "newest (-1: none yet), posted: its server time, time: now (s since the epoch)")


def _definitions() -> dict:
    """Every schema by name: the messages', and the frame body's (from its model)."""
    doc = FramePost.model_json_schema(ref_template="#/$defs/{model}")
    return {**SCHEMAS, **doc.pop("$defs", {}), "FramePost": doc}


def schema(name: str) -> dict:
    """Message ``name``'s JSON Schema, standalone (what it refers to in ``$defs``)."""
    defs = _definitions()
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **defs[name],
            "$defs": defs}


def _message(name: str, summary: str) -> dict:
    return {"name": name, "summary": summary, "contentType": "application/msgpack",
            "payload": {"$ref": f"#/components/schemas/{name}"}}


MESSAGES = {
    "packet": _message("Packet", "A tile's packet of a frame"),
    "nodeMessage": _message("NodeMessage", "A frame for a node's tiles"),
    "control": _message("Control", "An acknowledgement, or a request for full lists"),
    "streamError": _message("StreamError", "A message the server could not take"),
    "framePost": _message("FramePost", "A frame (and node updates) to cull"),
    "frameAnswer": _message("FrameAnswer", "The frame's number and timings"),
    "frameRefused": _message("FrameRefused", "Why a frame was refused"),
    "empty": _message("Empty", "An empty request"),
    "consoleStatus": {**_message("ConsoleStatus", "A wall's state, for the console"),
                      "contentType": "application/json"},
}


def _params(*names: str) -> dict:
    text = {"wid": "the wall's id", "tile": "a tile id", "prefix": "--nats-prefix (wallcull)",
            "first": "the first tile of the node (one of the wall's nodes)"}
    return {n: {"description": text[n]} for n in names}


def _ref(*names: str) -> dict:
    return {n: {"$ref": f"#/components/messages/{n}"} for n in names}


CHANNELS = {
    "tileStream": {"address": "/walls/{wid}/tiles/{tile}/stream",
                   "title": "A tile's stream (WebSocket; ?format=msgpack|json&token=)",
                   "parameters": _params("wid", "tile"),
                   "messages": _ref("packet", "control", "streamError"),
                   "bindings": {"ws": {"method": "GET"}}},
    "nodeStream": {"address": "/walls/{wid}/nodes/stream",
                   "title": "A render node's stream (WebSocket; ?tiles=0-3&format=&token=)",
                   "parameters": _params("wid"),
                   "messages": _ref("nodeMessage", "control", "streamError"),
                   "bindings": {"ws": {"method": "GET"}}},
    "frameStream": {"address": "/walls/{wid}/frames/stream",
                    "title": "A driver's frames (WebSocket; ?format=&token=)",
                    "parameters": _params("wid"),
                    "messages": _ref("framePost", "frameAnswer", "frameRefused"),
                    "bindings": {"ws": {"method": "GET"}}},
    "consoleStream": {"address": "/walls/{wid}/console/stream",
                      "title": "The operator console's status of a wall (WebSocket, JSON; "
                               "open, like GET /walls/{wid})",
                      "parameters": _params("wid"), "messages": _ref("consoleStatus"),
                      "bindings": {"ws": {"method": "GET"}}},
    "natsNode": {"address": "{prefix}.{wid}.node.{first}", "title": "NATS: a node's messages",
                 "parameters": _params("prefix", "wid", "first"),
                 "messages": _ref("nodeMessage")},
    "natsAck": {"address": "{prefix}.{wid}.ack.{first}", "title": "NATS: a node's acks",
                "parameters": _params("prefix", "wid", "first"), "messages": _ref("control")},
    "natsFull": {"address": "{prefix}.{wid}.full.{first}",
                 "title": "NATS: full lists, by request (the reply: a node message)",
                 "parameters": _params("prefix", "wid", "first"),
                 "messages": _ref("empty", "nodeMessage", "streamError")},
}


def _op(action: str, channel: str, *messages: str, reply: tuple = ()) -> dict:
    out = {"action": action, "channel": {"$ref": f"#/channels/{channel}"},
           "messages": [{"$ref": f"#/channels/{channel}/messages/{m}"} for m in messages]}
    if reply:
        out["reply"] = {"channel": {"$ref": f"#/channels/{channel}"},
                        "messages": [{"$ref": f"#/channels/{channel}/messages/{m}"}
                                     for m in reply]}
    return out


OPERATIONS = {
    "receivePackets": _op("send", "tileStream", "packet", "streamError"),
    "tileControl": _op("receive", "tileStream", "control"),
    "receiveNodeMessages": _op("send", "nodeStream", "nodeMessage", "streamError"),
    "nodeControl": _op("receive", "nodeStream", "control"),
    "postFrames": _op("receive", "frameStream", "framePost",
                      reply=("frameAnswer", "frameRefused")),
    "consoleStatus": _op("send", "consoleStream", "consoleStatus"),
    "publishNodeMessages": _op("send", "natsNode", "nodeMessage"),
    "takeAcks": _op("receive", "natsAck", "control"),
    "answerFull": _op("receive", "natsFull", "empty", reply=("nodeMessage", "streamError")),
}


def document(version: str) -> dict:
    """The AsyncAPI 3.0 document (operations are the server's: ``send`` is what it sends)."""
    schemas = json.loads(json.dumps(_definitions()).replace('"#/$defs/',
                                                           '"#/components/schemas/'))
    return {
        "asyncapi": "3.0.0",
        "info": {"title": "wallcull streams", "version": version,
                 "description": " ".join(__doc__.split("\n\n")[1].split())},
        "defaultContentType": "application/msgpack",
        "channels": CHANNELS, "operations": OPERATIONS,
        "components": {"schemas": schemas, "messages": MESSAGES},
    }
