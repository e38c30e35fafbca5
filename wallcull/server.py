"""The HTTP and WebSocket API (FastAPI on uvicorn): routes only; the work is in
:mod:`wallcull.service`.

Bodies travel as JSON or msgpack, chosen by ``Content-Type`` (requests) and ``Accept``
(responses), with one schema, the OpenAPI document's. A request that changes state needs the
server's token when one is configured (``Authorization: Bearer <token>``).
"""

from __future__ import annotations

import asyncio
import base64
import json
import secrets
from contextlib import asynccontextmanager
from typing import Annotated, Any, Literal, Optional

from fastapi import Depends, FastAPI, Header, Path, Query, Request, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from prometheus_client import (CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge,
                               Histogram, generate_latest)
from pydantic import BaseModel, ConfigDict, Field, FiniteFloat
from starlette.websockets import WebSocketDisconnect, WebSocketState

from . import protocol
from .bounds import KINDS
from .cull import METHODS
from .errors import InputError
from .fit import FitOptions
from .service import Conflict, Gone, NotFound, SceneStore, Walls, describe, mesh_blob
from .wall import MAX_TILES, Wall

MAX_BODY = 1 << 20  # bytes: frames, walls, updates
STREAM_WINDOW = 8  # packets a stream may have sent and not yet seen acknowledged
MAX_WAIT = 10.0  # seconds a request may wait for a frame or the barrier

Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]


class WallSpec(BaseModel):
    """A wall (SPEC section 2)."""

    model_config = ConfigDict(extra="forbid")
    cols: int = Field(ge=1, le=MAX_TILES)
    rows: int = Field(ge=1, le=MAX_TILES)
    tile_size: tuple[FiniteFloat, FiniteFloat]
    gap: tuple[FiniteFloat, FiniteFloat] = (0.0, 0.0)
    distance: FiniteFloat
    near: FiniteFloat = 0.1
    far: FiniteFloat = 1000.0
    resolution: tuple[Annotated[int, Field(ge=1, le=1 << 16)],
                      Annotated[int, Field(ge=1, le=1 << 16)]] = (1920, 1080)


class FrameSpec(BaseModel):
    """A frame (SPEC section 3)."""

    model_config = ConfigDict(extra="forbid")
    position: Vec3
    orientation: tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat]
    eye: Vec3 = (0.0, 0.0, 0.0)


class NodeUpdate(BaseModel):
    """A node's new local transform: ``matrix`` (4x4, row by row), or position, orientation
    (unit quaternion w, x, y, z) and an optional scale."""

    model_config = ConfigDict(extra="forbid")
    matrix: Optional[list[list[FiniteFloat]]] = None
    position: Optional[Vec3] = None
    orientation: Optional[tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat]] = None
    scale: Optional[Vec3] = None

    def value(self) -> Any:
        if self.matrix is not None:
            return self.matrix
        if self.position is None or self.orientation is None:
            raise InputError("a node update needs a matrix, or a position and an orientation")
        out = {"position": self.position, "orientation": self.orientation}
        if self.scale is not None:
            out["scale"] = self.scale
        return out


class WallCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    wall: WallSpec
    scene: str = Field(min_length=1, max_length=128)
    method: Literal[METHODS] = "adaptive"  # type: ignore[valid-type]
    bounds: Literal[KINDS] = "obb"  # type: ignore[valid-type]
    pseudo_groups: bool = False
    history: int = Field(default=64, ge=2, le=4096)
    depth: Literal["tight", "wall"] = "tight"
    reversed_z: bool = False


class FramePost(BaseModel):
    model_config = ConfigDict(extra="forbid")
    frame: FrameSpec
    updates: dict[str, NodeUpdate] = Field(default_factory=dict, max_length=100_000)
    number: Optional[int] = Field(default=None, ge=0, le=2**53)
    refit: Optional[Literal["obb", "aabb"]] = None
    packets: bool = False
    full: bool = False


class Ack(BaseModel):
    model_config = ConfigDict(extra="forbid")
    frame: int = Field(ge=0, le=2**53)


class FrameAnswer(BaseModel):
    frame: int
    timings: dict[str, float]
    packets: Optional[list[dict]] = None


class Packet(BaseModel):
    """See :mod:`wallcull.protocol`."""

    model_config = ConfigDict(extra="allow")
    frame: int
    tile: int
    time: float
    base: Optional[int]
    count: int
    visible: Optional[list[int]] = None
    added: Optional[list[int]] = None
    removed: Optional[list[int]] = None
    view: list[list[float]]
    projection: list[list[float]]


class Barrier(BaseModel):
    frame: int
    acked: int
    tiles: int
    complete: bool


class Detail(BaseModel):
    """Every refusal: a status and one line saying what is wrong."""

    detail: str


_REFUSALS = {304: "Not modified: the ETag matches", 400: "Malformed msgpack body",
             401: "Missing or wrong token", 404: "No such scene, wall, tile, node or frame",
             409: "Conflicts with the server's state", 410: "The frame left the history",
             413: "Body too large", 422: "Invalid input"}


def refusals(*codes: int) -> dict:
    """OpenAPI ``responses`` for the refusals a route may answer (all with a ``detail``)."""
    return {c: {"description": _REFUSALS[c]} if c == 304 else
            {"model": Detail, "description": _REFUSALS[c]} for c in (*codes, 422)}


# --------------------------------------------------------------------------- plumbing


def reply(request: Request, payload: Any, status: int = 200, headers=None) -> Response:
    """``payload`` as msgpack when the client accepts it, else JSON (bytes as base64)."""
    if protocol.wants_msgpack(request.headers.get("accept")):
        return Response(protocol.encode(payload, True), status, headers,
                        media_type=protocol.MSGPACK)
    return Response(json.dumps(payload, default=_b64, separators=(",", ":")), status, headers,
                    media_type=protocol.JSON)


def _b64(value):
    if isinstance(value, (bytes, bytearray)):
        return base64.b64encode(value).decode()
    raise TypeError(f"cannot encode {type(value).__name__}")


class BodyCodec:
    """ASGI middleware: caps request bodies, and turns msgpack bodies into JSON so that one
    set of typed models validates both."""

    def __init__(self, app, max_body: int, max_upload: int, metrics: "Metrics | None" = None):
        self.app, self.max_body, self.max_upload = app, max_body, max_upload
        self.metrics = metrics

    async def _refuse(self, send, status: int, detail: str):
        if self.metrics is not None:
            self.metrics.errors.labels(str(status)).inc()
        await _error(send, status, detail)

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS"):
            return await self.app(scope, receive, send)
        upload = scope["path"] == "/scenes"
        limit = self.max_upload if upload else self.max_body
        headers = dict(scope["headers"])
        declared = headers.get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > limit):
            return await self._refuse(send, 413, f"request body over {limit} bytes")
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > limit:
                return await self._refuse(send, 413, f"request body over {limit} bytes")
            chunks.append(chunk)
            if not message.get("more_body"):
                break
        body = b"".join(chunks)
        ctype = headers.get(b"content-type", b"").split(b";")[0].strip().decode("latin-1").lower()
        if ctype in (protocol.MSGPACK, "application/x-msgpack") and not upload:
            try:
                body = json.dumps(protocol.decode(body, True), allow_nan=True).encode()
            except InputError as exc:
                return await self._refuse(send, 400, str(exc))
            except (TypeError, ValueError):
                return await self._refuse(send, 400, "msgpack body holds values JSON cannot carry")
            scope = dict(scope)
            scope["headers"] = [(k, v) for k, v in scope["headers"]
                                if k not in (b"content-type", b"content-length")] + [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode())]
        sent = False

        async def replay():
            nonlocal sent
            if sent:
                return await receive()
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}

        await self.app(scope, replay, send)


async def _error(send, status: int, detail: str):
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})


class Metrics:
    def __init__(self):
        self.registry = CollectorRegistry()
        r = self.registry
        self.frames = Counter("wallcull_frames", "Frames culled", registry=r)
        self.stage = Histogram("wallcull_stage_seconds", "Time per pipeline stage", ["stage"],
                               buckets=(1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2,
                                        5e-2, 0.1, 0.25, 1.0), registry=r)
        self.packets = Counter("wallcull_packets", "Packets sent", ["kind", "transport"],
                               registry=r)
        self.bytes = Counter("wallcull_packet_bytes", "Packet bytes sent", ["kind", "transport"],
                             registry=r)
        self.clients = Gauge("wallcull_clients_connected", "Streaming render nodes", registry=r)
        self._bound: dict = {}
        self.errors = Counter("wallcull_errors", "Requests refused", ["status"], registry=r)

    def packet(self, pkt: dict, size: int, transport: str):
        key = ("full" if pkt["base"] is None else "delta", transport)
        bound = self._bound.get(key)
        if bound is None:  # labels() costs a lock and a dict lookup: bind each pair once
            bound = self._bound[key] = (self.packets.labels(*key), self.bytes.labels(*key))
        bound[0].inc()
        bound[1].inc(size)


# --------------------------------------------------------------------------- the app


def create_app(scene_folder=None, token: str | None = None, max_body: int = MAX_BODY,
               max_upload: int = 64 << 20, max_walls: int = 32) -> FastAPI:
    store = SceneStore(scene_folder, max_upload)
    walls = Walls(max_walls)
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app):
        await asyncio.to_thread(_warm_up)  # compile (or load) the culling kernels once
        yield

    app = FastAPI(title="wallcull", version="0.1.0", lifespan=lifespan,
                  description="Culling server for tiled display walls. Bodies are JSON or "
                              "msgpack (Content-Type / Accept: application/msgpack).")
    app.state.store, app.state.walls, app.state.metrics = store, walls, metrics
    app.add_middleware(BodyCodec, max_body=max_body, max_upload=max_upload, metrics=metrics)

    def authorized(value: str | None) -> bool:
        return token is None or (value is not None and secrets.compare_digest(
            value.encode(), token.encode()))

    def require_token(authorization: Annotated[Optional[str], Header()] = None):
        # the scheme is case-insensitive (RFC 9110, 11.1); the token is not
        given = authorization[7:] if authorization and authorization[:7].lower() == "bearer " \
            else None
        if not authorized(given):
            raise _Refused(401, "this request needs the server's token (Authorization: Bearer)")

    Token = [Depends(require_token)]

    @app.exception_handler(_Refused)
    async def refused(request, exc: _Refused):
        metrics.errors.labels(str(exc.status)).inc()
        return JSONResponse({"detail": exc.detail}, exc.status)

    for exc_type, status in ((InputError, 422), (NotFound, 404), (Conflict, 409), (Gone, 410)):
        app.add_exception_handler(exc_type, _handler(status, metrics))

    @app.exception_handler(RequestValidationError)
    async def invalid(request, exc: RequestValidationError):
        metrics.errors.labels("422").inc()
        detail = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        return JSONResponse({"detail": detail}, 422)

    # -------------------------------------------------------------- health and metrics

    @app.get("/health")
    async def health():
        return {"status": "ok", "walls": len(walls.sessions),
                "scenes_loaded": sorted(store.cache)}

    @app.get("/metrics", response_class=Response, responses={200: {
        "description": "Prometheus text format", "content": {"text/plain": {}}}})
    async def prometheus():
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    # -------------------------------------------------------------- scenes

    @app.get("/scenes")
    async def list_scenes(request: Request):
        return reply(request, {"scenes": store.names()})

    @app.post("/scenes", dependencies=Token, status_code=201,
              responses=refusals(401, 409, 413), openapi_extra={
        "requestBody": {"required": True, "content": {
            "model/gltf-binary": {"schema": {"type": "string", "format": "binary"}}}}})
    async def upload_scene(request: Request,
                           name: Annotated[str, Query(min_length=1, max_length=128)],
                           replace: bool = False):
        """Upload a GLB into the scene folder (or memory, without one)."""
        scene = await store.upload(name, await request.body(), replace)
        return reply(request, describe(scene, nodes=False), 201)

    @app.get("/scenes/{name}", responses=refusals(404))
    async def scene_info(request: Request, name: str, nodes: bool = False):
        """A scene's stats, bounds and settings; ``nodes=true`` adds every node: name, parent,
        leaf flag, mesh key and rest world transform (row by row, flattened)."""
        return reply(request, describe(await store.get(name), nodes))

    @app.get("/scenes/{name}/meshes/{key}", responses=refusals(304, 404))
    async def mesh(request: Request, name: str, key: str):
        """A mesh as typed arrays (little-endian float32 vertices, uint32 faces); cache it by
        its ETag."""
        return _mesh_reply(request, mesh_blob(await store.get(name), key))

    @app.get("/scenes/{name}/nodes/{node}/mesh", responses=refusals(304, 404))
    async def node_mesh(request: Request, name: str, node: int):
        """The mesh of a leaf node, in the node's local coordinates (see ``nodes=true``)."""
        scene = await store.get(name)
        if not 0 <= node < len(scene) or scene.geometry[node] is None:
            raise NotFound(f"node {node} of scene {name!r} carries no mesh")
        return _mesh_reply(request, mesh_blob(scene, scene.geometry[node]))

    # -------------------------------------------------------------- walls

    @app.post("/walls", dependencies=Token, status_code=201,
              responses=refusals(400, 401, 404, 409, 413))
    async def create_wall(request: Request, body: WallCreate):
        wall = Wall.from_dict(body.wall.model_dump())
        scene = await store.get(body.scene)
        session = walls.create(scene, wall, body.method, body.bounds, body.pseudo_groups,
                               body.history, FitOptions(body.depth, body.reversed_z))
        return reply(request, session.info(), 201)

    @app.get("/walls")
    async def list_walls(request: Request):
        return reply(request, {"walls": [w.info() for w in walls.sessions.values()]})

    @app.get("/walls/{wid}", responses=refusals(404))
    async def wall_info(request: Request, wid: str):
        return reply(request, walls.get(wid).info())

    @app.delete("/walls/{wid}", dependencies=Token, status_code=204,
                responses=refusals(400, 401, 404, 413))
    async def delete_wall(wid: str):
        walls.get(wid).close()
        walls.delete(wid)
        return Response(status_code=204)

    @app.post("/walls/{wid}/frames", dependencies=Token, response_model=FrameAnswer,
              responses=refusals(400, 401, 404, 409, 413))
    async def post_frame(request: Request, wid: str, body: FramePost):
        """Cull (and fit) a frame; answer its number and, with ``packets``, every tile's packet."""
        session = walls.get(wid)
        updates = {name: u.value() for name, u in body.updates.items()}
        number, timings = await session.post_frame_async(body.frame.model_dump(), updates,
                                                         body.number, body.refit)
        metrics.frames.inc()
        for stage in ("cull_ms", "fit_ms", "total_ms"):
            metrics.stage.labels(stage[:-3]).observe(timings[stage] / 1e3)
        out: dict[str, Any] = {"frame": number, "timings": timings}
        if body.packets:
            out["packets"] = [session.packet(t, number, body.full) for t in range(session.wall.tiles)]
        return reply(request, out)

    @app.get("/walls/{wid}/tiles/{tile}/packets/{frame}", response_model=Packet,
             responses=refusals(404, 410))
    async def get_packet(request: Request, wid: str, tile: int,
                         frame: Annotated[str, Path(pattern=r"^(latest|\d{1,15})$")],
                         full: bool = False,
                         wait: Annotated[float, Query(ge=0, le=MAX_WAIT)] = 1.0):
        """Tile ``tile``'s packet of frame ``frame`` (a number or ``latest``): a delta against
        the frame the tile last acknowledged, or a full list. Waits up to ``wait`` seconds for a
        frame that is not ready yet. A node that lost its lists asks with ``full=true`` and
        acknowledges that frame before asking for deltas again."""
        session = walls.get(wid)
        session.check_tile(tile)
        if frame == "latest":
            if session.latest < 0 and not await session.wait_frame(0, wait):
                raise NotFound("no frame yet")
            number = session.latest
        else:
            number = int(frame)
            if not await session.wait_frame(number, wait):
                raise NotFound(f"frame {number} is not ready (latest {session.latest})")
        pkt = session.packet(tile, number, full)
        response = reply(request, pkt)
        metrics.packet(pkt, len(response.body), "http")
        return response

    @app.post("/walls/{wid}/tiles/{tile}/ack", dependencies=Token, status_code=204,
              responses=refusals(400, 401, 404, 409, 413))
    async def ack(wid: str, tile: int, body: Ack):
        """The tile has drawn frame ``frame`` (the swap barrier counts these)."""
        walls.get(wid).ack(tile, body.frame)
        return Response(status_code=204)

    @app.get("/walls/{wid}/barrier/{frame}", response_model=Barrier,
             responses=refusals(404))
    async def barrier(request: Request, wid: str, frame: Annotated[int, Path(ge=0, le=2**53)],
                      timeout: Annotated[float, Query(ge=0, le=MAX_WAIT)] = 1.0):
        """Wait until every tile has acknowledged ``frame``, or ``timeout`` seconds."""
        return reply(request, await walls.get(wid).barrier(frame, timeout))

    @app.websocket("/walls/{wid}/tiles/{tile}/stream")
    async def stream(ws: WebSocket, wid: str, tile: int, format: str = "msgpack",
                     token_param: Annotated[Optional[str], Query(alias="token")] = None):
        """Push every new frame's packet (conflated: a slow node gets the newest). The node
        sends ``{"ack": n}`` after drawing frame n (needs the token when one is set) and
        ``{"full": true}`` to get a full list next. The first packet is full, and deltas are
        only against frames acknowledged since: a node that reconnects starts afresh. The
        stream closes with code 4404 when the wall is deleted."""
        try:
            session = walls.get(wid)
            session.check_tile(tile)
        except NotFound:
            await ws.close(code=4404)
            return
        binary = format != "json"
        can_ack = authorized(token_param)
        await ws.accept()
        session.subscribers += 1
        metrics.clients.inc()
        state = {"full": True}

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
                pkt = session.packet(tile, number, state.pop("full", False), since)
                since = number if since < 0 else since
                data = protocol.encode(pkt, binary)
                if binary:
                    await ws.send_bytes(data)
                else:
                    await ws.send_text(data.decode())
                metrics.packet(pkt, len(data), "ws")
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
                        state["full"] = True
                    if "ack" in msg:
                        if not can_ack:
                            raise _Refused(401, "acknowledgements need the server's token")
                        if not isinstance(msg["ack"], int) or isinstance(msg["ack"], bool):
                            raise InputError("ack must be a frame number")
                        session.ack(tile, msg["ack"])
                except (InputError, Conflict, NotFound, _Refused) as exc:
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

    return app


class _Refused(Exception):
    def __init__(self, status: int, detail: str):
        self.status, self.detail = status, detail


def _handler(status: int, metrics: Metrics):
    async def handle(request, exc):
        metrics.errors.labels(str(status)).inc()
        return JSONResponse({"detail": str(exc)}, status)
    return handle


def _mesh_reply(request: Request, blob) -> Response:
    headers = {"ETag": blob.etag, "Cache-Control": "public, max-age=31536000, immutable"}
    if request.headers.get("if-none-match") == blob.etag:
        return Response(status_code=304, headers=headers)
    return reply(request, blob.body, headers=headers)


def _warm_up() -> None:
    """Cull one frame of a tiny scene so that the kernels are compiled before the first client."""
    import numpy as np
    import trimesh

    from .pipeline import Session
    from .scene import Scene

    scene = trimesh.Scene()
    for k in range(3):
        m = np.eye(4)
        m[:3, 3] = [k, 0, -5]
        scene.add_geometry(trimesh.creation.box(), node_name=f"b{k}", transform=m)
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [1, 1], "distance": 1})
    frame = {"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}
    for method in METHODS:
        for pseudo in (False, True):
            Session(Scene.from_trimesh(scene), wall, method, pseudo_groups=pseudo).frame(frame)


def make_app_from_env() -> FastAPI:
    """For ``uvicorn wallcull.server:make_app_from_env --factory`` (Docker and friends)."""
    import os

    return create_app(os.environ.get("WALLCULL_SCENES") or None,
                      os.environ.get("WALLCULL_TOKEN") or None)


def serve(host: str = "127.0.0.1", port: int = 8000, scenes=None, token=None,
          log_level: str = "info") -> None:
    import uvicorn

    uvicorn.run(create_app(scenes, token), host=host, port=port, log_level=log_level,
                access_log=False, ws_max_size=1 << 20)
