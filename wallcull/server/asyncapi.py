"""The AsyncAPI document of the streams (``GET /asyncapi.json``), next to the OpenAPI one: what a
lab implements in C++, C# or JavaScript to be a render node or a tracker.

Channels: a tile's WebSocket stream (packets), a render node's (node messages), the frame
stream of a driver, the operator console's status stream (:mod:`.pages`), and the NATS
subjects (:mod:`.nats`). The message schemas are JSON Schema (2020-12) of the pydantic models
of :mod:`.messages` (and of the frame body, :class:`.models.FramePost`), strict (no key they do
not list); the tests validate what the server sends, on every channel, against them.
"""

from __future__ import annotations

import json

from pydantic.json_schema import models_json_schema

from . import messages
from .messages import MessageSchema
from .models import FramePost
from .openapi import markdown

#: The models whose schemas the document holds (what they refer to comes along).
MODELS = (messages.Packet, messages.NodeMessage, messages.Control, messages.StreamError,
          FramePost, messages.FrameAnswer, messages.FrameRefused, messages.ConsoleStatus)


def _definitions() -> dict:
    """Every schema by name: the messages' and the frame body's, from their models."""
    _, doc = models_json_schema([(m, "validation") for m in MODELS],
                                ref_template="#/$defs/{model}", schema_generator=MessageSchema)
    return doc["$defs"]


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
    "empty": {"name": "Empty", "summary": "An empty request (no payload)"},
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
    "natsAck": {"address": "{prefix}.{wid}.ack.{first}",
                "title": "NATS: a node's acknowledgements ({\"ack\": n, \"node\": name}; no "
                         "reply, and no credential: the broker's permissions guard it)",
                "parameters": _params("prefix", "wid", "first"), "messages": _ref("control")},
    "natsFull": {"address": "{prefix}.{wid}.full.{first}",
                 "title": "NATS: full lists, by request (the reply: a node message)",
                 "parameters": _params("prefix", "wid", "first"),
                 "messages": _ref("empty", "control", "nodeMessage", "streamError")},
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
    "answerFull": _op("receive", "natsFull", "empty", "control",
                      reply=("nodeMessage", "streamError")),
}


def document(version: str) -> dict:
    """The AsyncAPI 3.0 document (operations are the server's: ``send`` is what it sends)."""
    schemas = json.loads(json.dumps(_definitions()).replace('"#/$defs/',
                                                           '"#/components/schemas/'))
    return markdown({
        "asyncapi": "3.0.0",
        "info": {"title": "wallcull streams", "version": version,
                 "description": " ".join(__doc__.split("\n\n")[1].split())},
        "defaultContentType": "application/msgpack",
        "channels": CHANNELS, "operations": OPERATIONS,
        "components": {"schemas": schemas, "messages": MESSAGES},
    })
