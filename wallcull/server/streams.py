"""The WebSocket streams: a tile's (every new frame's packet pushed, acknowledgements back)
and a render node's (one message per frame with all of its tiles, one acknowledgement)."""

from __future__ import annotations

import asyncio
import json
import time
from collections import deque

import numpy as np
from fastapi import APIRouter, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.websockets import WebSocketDisconnect, WebSocketState

from .. import protocol
from ..credentials import DRIVER, NODE
from ..errors import InputError
from ..persist import StateWriteFailed
from ..service import Conflict, NotFound, Unavailable, WallSession
from ..validate import parse_tiles
from .access import bearer, needs
from .deps import ServerState
from .http import Budget, Refused, decode_body, decode_message, refusal_detail
from .messages import control
from .models import FramePost
from .walls import take_frame

#: Packets a stream may have sent and not yet seen acknowledged on it.
STREAM_WINDOW = 8
#: Close codes: the wall was deleted; the stream waited too long for an acknowledgement.
GONE, IDLE = 4404, 4408
#: A stream's ``?format=``: msgpack (binary messages) or JSON (text).
FORMATS = ("msgpack", "json")

router = APIRouter(tags=["streams"])


@router.websocket("/walls/{wid}/tiles/{tile}/stream")
@needs(NODE)
async def stream(ws: WebSocket, wid: str, tile: int, format: str = "msgpack"):
    """Push every new frame's packet of one tile (conflated: a slow node gets the newest). The
    node sends ``{"ack": n}`` after drawing frame n and ``{"full": true}`` to get a full list
    next. The first packet is full, and deltas are only against frames acknowledged since: a
    node that reconnects starts afresh.

    With a server token, opening a stream needs the tile's node credential (``?token=`` or
    ``Authorization: Bearer``). A stream that has sent ``STREAM_WINDOW`` packets it has not
    seen acknowledged *on itself* is sent nothing more until an acknowledgement comes, and is
    closed (code 4408) after ``limits.stream_idle`` seconds of that: an idle socket costs no
    work per frame and frees its place. Streams are capped per tile, per wall and in all
    (HTTP 429 at the handshake). The stream closes with code 4404 when the wall is deleted."""
    def tiles_of(session: WallSession) -> np.ndarray:
        session.check_tile(tile)
        return np.array([tile])

    await _open(ws, wid, tiles_of, node=False, format=format)


@router.websocket("/walls/{wid}/nodes/stream")
@needs(NODE)
async def node_stream(ws: WebSocket, wid: str, tiles: str | None = None,
                      format: str = "msgpack"):
    """Push every new frame to a render node as one message with all of its tiles (a node
    message, see the AsyncAPI document), and take one ``{"ack": n}`` for all of them; as the
    tile stream otherwise (``{"full": true}``, conflation, the window, the close codes).
    ``tiles`` (``0-3`` or ``0,1,8,9``) defaults to the tiles of the node's credential."""
    def tiles_of(session: WallSession) -> np.ndarray:
        if tiles is not None:
            try:
                return session.check_tiles(parse_tiles(tiles, session.wall.tiles))
            except InputError as exc:
                raise Refused(422, str(exc)) from None
        token = _token(ws)
        grant = ws.app.state.server.walls.grant(token) if token else None
        if grant is None or not grant.tiles:  # none, or the driver's
            raise Refused(422, "say which tiles: ?tiles=0-3 (only a node's own credential "
                               "implies them)")
        return session.check_tiles(sorted(grant.tiles))

    await _open(ws, wid, tiles_of, node=True, format=format)


@router.websocket("/walls/{wid}/frames/stream")
@needs(DRIVER)
async def frame_stream(ws: WebSocket, wid: str, format: str = "msgpack"):
    """Post frames over one connection, as a tracker does 60 to 120 times a second: each
    message is a ``POST /walls/{wid}/frames`` body, each answer that request's (``{"frame",
    "timings"}``), in order; a refused frame is answered ``{"error": detail, "status": code}``
    and the stream goes on. Needs the wall's driver credential (or the operator's token)."""
    state: ServerState = ws.app.state.server
    try:
        binary = _binary(format)
        session = state.walls.get(wid)
    except (NotFound, Unavailable, Refused) as exc:
        return await deny(ws, state, exc)
    await ws.accept()
    try:
        while True:  # one message at a time: each is answered before the next
            message = await _unless_deleted(session, ws.receive())
            if message is None:
                break
            if message["type"] == "websocket.disconnect":
                return
            raw = message.get("bytes")
            try:
                body = decode_body(FramePost, raw, protocol.MSGPACK) if raw is not None else \
                    decode_body(FramePost, message.get("text", "").encode(), protocol.JSON)
                answer = await take_frame(state, session, body)
            except RequestValidationError as exc:
                answer = {"error": refusal_detail(exc), "status": 422}
            except Refused as exc:
                answer = {"error": exc.detail, "status": exc.status}
            except StateWriteFailed as exc:
                answer = {"error": str(exc), "status": exc.status}
            except (InputError, Conflict, NotFound) as exc:
                status = 422 if isinstance(exc, InputError) else \
                    409 if isinstance(exc, Conflict) else 404
                answer = {"error": str(exc), "status": status}
            if "error" in answer:
                state.metrics.errors.labels(str(answer["status"])).inc()
            data = protocol.encode(answer, binary)
            await (ws.send_bytes(data) if binary else ws.send_text(data.decode()))
    except WebSocketDisconnect:
        return
    if ws.application_state == WebSocketState.CONNECTED:
        await ws.close(code=GONE, reason="the wall was deleted")


def _binary(format: str) -> bool:
    """Whether a stream's ``?format=`` sends binary (msgpack) messages; 422 for neither."""
    if format not in FORMATS:
        raise Refused(422, f"format must be {' or '.join(FORMATS)}, got {format!r}")
    return format == "msgpack"


async def _unless_deleted(session: WallSession, aw):
    """What ``aw`` gives, or None once the wall is deleted (``aw`` is then cancelled)."""
    task = asyncio.ensure_future(aw)
    gone = asyncio.ensure_future(session.gone.wait())
    try:
        await asyncio.wait((task, gone), return_when=asyncio.FIRST_COMPLETED)
    finally:
        for waiting in (task, gone):
            if not waiting.done():
                waiting.cancel()
    return None if session.closed or task.cancelled() else task.result()


async def deny(ws: WebSocket, state: ServerState, exc: Exception) -> None:
    """Refuse a stream's handshake: 404 (no such wall), 503 (the wall waits for its scene:
    retry) or a :class:`Refused`'s status."""
    status = exc.status if isinstance(exc, Refused) else 503 if isinstance(exc, Unavailable) \
        else 404
    state.metrics.errors.labels(str(status)).inc()
    headers = {"Retry-After": "5"} if status == 503 else None
    await ws.send_denial_response(JSONResponse({"detail": getattr(exc, "detail", str(exc))},
                                               status, headers))


def writer(ws: WebSocket, binary: bool):
    """``write(data)`` for an accepted stream's messages (msgpack bytes, or JSON text given as
    UTF-8 bytes): straight to the server's own ``send`` when :class:`~wallcull.server.App`
    kept it, else through Starlette's. The middlewares only pass a stream's messages on; their
    wrappers cost a few percent of the server's CPU on 8x8 at 60 Hz, on every write."""
    raw = ws.scope.get("wallcull.send")
    if raw is None:
        return ws.send_bytes if binary else (lambda data: ws.send_text(data.decode()))
    if binary:
        return lambda data: raw({"type": "websocket.send", "bytes": data})
    return lambda data: raw({"type": "websocket.send", "text": data.decode()})


def _token(ws: WebSocket) -> str | None:
    return ws.query_params.get("token") or bearer(ws.headers.get("authorization"))


async def _open(ws: WebSocket, wid: str, tiles_of, node: bool, format: str) -> None:
    """Admit a stream (its format, its wall, its tiles, room for it), run it, close it with
    its reason."""
    state: ServerState = ws.app.state.server
    try:
        binary = _binary(format)
        session = state.walls.get(wid)
        tiles = tiles_of(session)
        room(state, session, tiles)
    except (NotFound, Refused, Unavailable) as exc:
        return await deny(ws, state, exc)
    await ws.accept()
    count(state, session, tiles, +1)
    try:
        reason = await _serve(ws, state, session, tiles, node, binary)
    finally:
        count(state, session, tiles, -1)
    code = GONE if session.closed else IDLE if reason == "idle" else None
    if code is not None and ws.application_state == WebSocketState.CONNECTED \
            and ws.client_state == WebSocketState.CONNECTED:
        try:
            await ws.close(code=code, reason="the wall was deleted" if code == GONE else
                           "no acknowledgement came: reconnect to resume")
        except (RuntimeError, WebSocketDisconnect, OSError):
            pass  # the node left at the same moment


def room(state: ServerState, session: WallSession, tiles: np.ndarray) -> None:
    """Refuse (429) a stream that would pass the caps: the server's, the wall's, a tile's
    (consoles, which hold no tile, count against the first two)."""
    limits = state.limits
    busiest = max((session.streams[t] for t in tiles.tolist()), default=0)
    on_wall = session.subscribers + session.consoles
    for open_, cap, where in ((state.streams, limits.streams, "the server"),
                              (on_wall, limits.streams_per_wall, f"wall {session.id}"),
                              (busiest, limits.streams_per_tile, "a tile")):
        if open_ >= cap:
            raise Refused(429, f"{where} already has {cap} streams open")


def count(state: ServerState, session: WallSession, tiles: np.ndarray, step: int) -> None:
    """Count a stream opening (+1) or closing (-1) against the caps of :func:`room`."""
    state.streams += step
    session.active = time.monotonic()
    if not len(tiles):  # a console
        session.consoles += step
        return
    session.subscribers += step
    for t in tiles.tolist():
        session.streams[t] += step
    state.metrics.clients.inc(step)


async def _serve(ws: WebSocket, state: ServerState, session: WallSession, tiles: np.ndarray,
                 node: bool, binary: bool) -> str:
    """Run the stream (a tile's packets, or a node's messages) until the node leaves, the wall
    goes, or the stream idles; why. One write per frame."""
    tile = int(tiles[0])
    acks = tiles if node else tile
    metrics, idle = state.metrics, state.limits.stream_idle
    wants = {"full": True}
    acked = [-1]  # the newest frame acknowledged on this stream
    sent: deque = deque(maxlen=STREAM_WINDOW)  # the numbers of its last packets
    ack_came = asyncio.Event()
    #: the newest full lists asked for and sent: the node holds no frame from before them
    since = [-1]

    def may_go() -> bool:
        """A node that could not use a delta acknowledges nothing until it has full lists:
        its request lets one full message past the window, not one per request."""
        return bool(wants.get("full")) and acked[0] >= since[0]

    async def acknowledged(number: int) -> bool:
        """Wait until this stream has acknowledged ``number`` (or may have full lists past
        the window); False: nothing acknowledged for ``idle`` seconds."""
        clock = asyncio.get_running_loop().time
        deadline, heard = clock() + idle, acked[0]
        while acked[0] < number and not may_go() and not session.closed:
            ack_came.clear()
            if acked[0] > heard:  # an acknowledgement came (a full request is none)
                deadline, heard = clock() + idle, acked[0]
            left = deadline - clock()
            try:
                await _unless_deleted(session, asyncio.wait_for(ack_came.wait(), max(left, 0)))
            except asyncio.TimeoutError:
                return False
        return True

    write = writer(ws, binary)

    async def sender():
        last = -1
        while True:
            number = await session.next_frame(last)
            if len(sent) == STREAM_WINDOW and acked[0] < sent[0]:
                # At most STREAM_WINDOW packets unacknowledged; a node that falls behind then
                # gets the newest frame (conflation) instead of a queue of stale ones in
                # socket buffers (uvicorn's send only blocks past 64 KiB).
                if not await acknowledged(sent[0]):
                    return "idle"
                number = session.latest
            full = wants.pop("full", False)
            # deltas against what this stream acknowledged, not what the tiles did: another
            # node on the same tiles may be ahead of this one (or behind it)
            if node:  # its tiles' entries, encoded once per frame for every node
                data, delta = session.node_message(tiles, number, full, since[0], binary,
                                                   held=acked[0])
            elif binary:  # encoded once per frame for every tile (wallcull.encode)
                data, delta = session.packet_bytes(tile, number, full, since[0],
                                                   held=acked[0])
            else:
                pkt = session.packet(tile, number, full, since[0], held=acked[0])
                data, delta = protocol.encode(pkt, False), pkt["base"] is not None
            await write(data)
            sent.append(number)
            if full:  # asked for (the first, or a node that dropped what it held): from
                since[0] = number  # here on, no delta against a frame before
            metrics.packet(delta, len(data), "ws")
            last = number

    pace = Budget(state.limits.messages)

    async def receiver():
        while True:
            await pace.spend()
            message = await ws.receive()
            if message["type"] == "websocket.disconnect":
                return "left"
            try:
                number, full, _ = control(decode_message(
                    message.get("bytes"), message.get("text"), state.limits.message_bytes))
                if full:
                    wants["full"] = True
                    ack_came.set()
                if number is not None:
                    session.ack(acks, number)
                    if number > acked[0]:
                        acked[0] = number
                        ack_came.set()
            except (InputError, Conflict, NotFound) as exc:
                metrics.errors.labels("ws").inc()
                error = {"error": str(exc)}
                await (ws.send_bytes(protocol.encode(error, True)) if binary
                       else ws.send_text(json.dumps(error)))

    tasks = [asyncio.create_task(sender()), asyncio.create_task(receiver())]
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finished = next(iter(done))
        return finished.result() if not finished.cancelled() and \
            finished.exception() is None else "left"
    finally:
        for task in tasks:
            task.cancel()
        for task in tasks:
            try:
                await task
            except (asyncio.CancelledError, WebSocketDisconnect, RuntimeError, OSError,
                    NotFound):
                pass  # the node went away (uvicorn: ClientDisconnected), or the wall went
