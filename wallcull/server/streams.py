"""The WebSocket stream of a tile: every new frame's packet pushed, acknowledgements back."""

from __future__ import annotations

import asyncio
import json
from typing import Annotated, Optional

from fastapi import APIRouter, Query, WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from .. import protocol
from ..errors import InputError
from ..service import Conflict, NotFound
from .deps import ServerState
from .http import Refused
from .walls import MAX_WAIT

#: Packets a stream may have sent and not yet seen acknowledged.
STREAM_WINDOW = 8

router = APIRouter(tags=["streams"])


@router.websocket("/walls/{wid}/tiles/{tile}/stream")
async def stream(ws: WebSocket, wid: str, tile: int, format: str = "msgpack",
                 token_param: Annotated[Optional[str], Query(alias="token")] = None):
    """Push every new frame's packet (conflated: a slow node gets the newest). The node
    sends ``{"ack": n}`` after drawing frame n (needs the token when one is set) and
    ``{"full": true}`` to get a full list next. The first packet is full, and deltas are
    only against frames acknowledged since: a node that reconnects starts afresh. The
    stream closes with code 4404 when the wall is deleted."""
    state: ServerState = ws.app.state.server
    metrics = state.metrics
    try:
        session = state.walls.get(wid)
        session.check_tile(tile)
    except NotFound:
        await ws.close(code=4404)
        return
    binary = format != "json"
    can_ack = state.authorized(token_param)
    await ws.accept()
    session.subscribers += 1
    metrics.clients.inc()
    wants = {"full": True}

    async def sender():
        last = since = -1
        while True:
            number = await session.next_frame(last)
            if can_ack and since >= 0 and session.acks[tile] >= since:
                # Flow control, for nodes that acknowledge: at most STREAM_WINDOW packets
                # unacknowledged. A node that falls behind then gets the newest frame
                # (conflation) instead of a queue of stale ones in socket buffers:
                # uvicorn's send only blocks past the transport's 64 KiB high-water mark.
                await session.wait_acked(tile, last - STREAM_WINDOW + 1, MAX_WAIT)
                number = session.latest
            full = wants.pop("full", False)
            if binary:  # encoded once per frame for every tile (wallcull.encode)
                data, delta = session.packet_bytes(tile, number, full, since)
                await ws.send_bytes(data)
            else:
                pkt = session.packet(tile, number, full, since)
                data, delta = protocol.encode(pkt, False), pkt["base"] is not None
                await ws.send_text(data.decode())
            since = number if since < 0 else since
            metrics.packet(delta, len(data), "ws")
            last = number

    async def receiver():
        while True:
            message = await ws.receive()
            if message["type"] == "websocket.disconnect":
                return
            raw = message.get("bytes")
            try:
                msg = protocol.decode(raw, True) if raw is not None else \
                    protocol.decode(message.get("text", "").encode(), False)
                if not isinstance(msg, dict):
                    raise InputError("a message must be an object")
                if msg.get("full"):
                    wants["full"] = True
                if "ack" in msg:
                    if not can_ack:
                        raise Refused(401, "acknowledgements need the server's token")
                    if not isinstance(msg["ack"], int) or isinstance(msg["ack"], bool):
                        raise InputError("ack must be a frame number")
                    session.ack(tile, msg["ack"])
            except (InputError, Conflict, NotFound, Refused) as exc:
                metrics.errors.labels("ws").inc()
                error = {"error": getattr(exc, "detail", str(exc))}
                await (ws.send_bytes(protocol.encode(error, True)) if binary
                       else ws.send_text(json.dumps(error)))

    tasks = [asyncio.create_task(sender()), asyncio.create_task(receiver())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        for task in tasks:
            try:
                await task
            except (asyncio.CancelledError, WebSocketDisconnect, RuntimeError, NotFound):
                pass  # the node went away, or the wall was deleted
        session.subscribers -= 1
        metrics.clients.dec()
    if session.closed and ws.application_state == WebSocketState.CONNECTED \
            and ws.client_state == WebSocketState.CONNECTED:
        try:
            await ws.close(code=4404, reason="the wall was deleted")
        except (RuntimeError, WebSocketDisconnect, OSError):
            pass  # the node left at the same moment
