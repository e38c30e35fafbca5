"""Routes of the walls: create and delete, post frames, read packets, acknowledge, the barrier."""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import Response

from .. import settings as cfg
from ..credentials import DRIVER, NODE, OPERATOR
from ..errors import InputError
from ..fit import FitOptions
from ..service import NotFound, warm_meshes
from ..validate import MAX_FRAME
from ..wall import Wall
from ..workers import background
from .access import needs
from .deps import State
from .guard import long_poll
from .http import body_of, reply, reply_large
from .messages import FrameAnswer, Packet
from .models import (CROWDED, UNWRITABLE, WAITS, Ack, Barrier, FramePost, WallCreate, WallCreated,
                     WallId, WallInfo, WallList, refusals, worded)
from .openapi import FRAME_LINKS, WALL_LINKS

#: Seconds a request may wait for a frame or the barrier.
MAX_WAIT = 10.0
#: A request's ``wait`` or ``timeout``: seconds, finite.
Wait = Annotated[float, Query(ge=0, le=MAX_WAIT, allow_inf_nan=False)]
#: Updates converted on the event loop at most; more go to a worker thread.
INLINE_UPDATES = 2000
#: Tiles of a wall whose answers are encoded off the event loop; and the most tiles a frame's
#: answer may carry every packet of (``packets=true``: 1.9 s on the loop at 256 x 256).
LARGE_WALL = MAX_PACKETS = 1024

router = APIRouter(tags=["walls"])

TileId = Annotated[int, Path(ge=0, lt=1 << 16)]
#: A packet's frame: a number, or the newest.
FRAME = worded(r"^(latest|\d{1,16})$", "a frame is 'latest' or a frame number")


@router.post("/walls", status_code=201, operation_id="createWall", response_model=WallCreated,
             responses={**refusals(400, 401, 403, 404, 408, 409, 413, 415, UNWRITABLE),
                        201: {"description": "The wall, with its credentials (shown once)",
                              "links": WALL_LINKS}})
@needs(OPERATOR)
async def create_wall(request: Request, state: State,
                      body: Annotated[WallCreate, body_of(WallCreate)]):
    """A wall culling a scene. The answer carries the wall's credentials, shown this once:
    the driver's (posting frames) and one per node (its tiles' packets, streams and
    acknowledgements)."""
    wall = Wall.from_dict(body.wall)  # a grid, or screens (SPEC 2b)
    settings = None if body.settings is None else body.settings.model_dump(exclude_unset=True, exclude_none=True)
    if settings is not None:
        cfg.parse(settings)  # refused here, with its reason, not at the first frame
    with state.walls.reservation(body.scene):  # a place for it, before any work
        scene = await state.store.get(body.scene)
        await state.store.bounds(scene, body.bounds)  # in a child process, with a time budget
        fit = FitOptions(body.depth, body.reversed_z, body.shadow_fit)
        # a 256 x 256 wall takes seconds to make: a worker thread, the loop keeps serving
        session, grants = await background(
            state.walls.build, scene, wall, body.method, body.bounds, body.pseudo_groups,
            body.history, fit, body.nodes, settings, body.occlusion)
        state.walls.register(session, grants)  # (and published on NATS, if there is one)
    # the nodes' first mesh requests find them encoded (a thread: the loop keeps serving)
    warming = asyncio.ensure_future(background(warm_meshes, scene))
    state.warming.add(warming)
    warming.add_done_callback(state.warming.discard)
    issued, session.credentials = session.credentials, None  # shown once
    # in pieces whatever the wall's size: the nodes' credentials are made as they are encoded
    return await reply_large(request, lambda: {**session.info(), "credentials": issued}, 201)


async def _reply(request: Request, session, build, status: int = 200):
    """A wall's answer: encoded off the event loop for a large wall (its node lists, and
    its credentials when it is created, are megabytes at 256 x 256)."""
    if session.wall.tiles <= LARGE_WALL:
        return reply(request, build(), status)
    return await reply_large(request, build, status)


@router.get("/walls", operation_id="listWalls", response_model=WallList)
async def list_walls(request: Request, state: State):
    walls = list(state.walls.sessions.values())
    if sum(w.wall.tiles for w in walls) <= LARGE_WALL:
        return reply(request, {"walls": [w.info() for w in walls]})
    return await reply_large(request, lambda: {"walls": [w.info() for w in walls]})


@router.get("/walls/{wid}", operation_id="getWall", response_model=WallInfo,
            responses=refusals(404, WAITS))
async def wall_info(request: Request, state: State, wid: WallId):
    session = state.walls.get(wid)
    return await _reply(request, session, session.info)


@router.delete("/walls/{wid}", status_code=204, operation_id="deleteWall",
               responses=refusals(401, 403, 404, UNWRITABLE))
@needs(OPERATOR)
async def delete_wall(state: State, wid: WallId):
    if wid in state.walls.sessions and state.walls.state is not None:
        # on disk first (a 256 x 256 wall's 65,536 credentials: a worker thread), so that a
        # failed write leaves the wall whole
        await background(state.walls.state.remove_wall, wid)
        if wid in state.walls.sessions:
            state.walls.forget(wid)
    else:
        state.walls.delete(wid)
    state.store.evict()  # its scene may be one no wall uses now
    return Response(status_code=204)


@router.post("/walls/{wid}/frames", operation_id="postFrame", response_model=FrameAnswer,
             responses={**refusals(400, 401, 403, 404, 408, 409, 413, 415, WAITS,
                                   UNWRITABLE),
                        200: {"description": "The frame's number and timings",
                              "links": FRAME_LINKS}})
@needs(DRIVER)
async def post_frame(request: Request, state: State, wid: WallId,
                     body: Annotated[FramePost, body_of(FramePost)]):
    """Cull (and fit) a frame; answer its number and, with ``packets``, every tile's packet.
    (A tracker posting frame after frame keeps one connection instead: the frame stream.)"""
    return reply(request, await take_frame(state, state.walls.get(wid), body))


async def take_frame(state, session, body: FramePost) -> dict[str, Any]:
    """A posted frame, culled, fitted and published: its answer (the HTTP route's and the
    frame stream's)."""
    def moves():
        return {name: u.value(name) for name, u in body.updates.items()}

    check_packets(session, body)
    updates = moves() if len(body.updates) <= INLINE_UPDATES else await asyncio.to_thread(moves)
    number, timings = await session.post_frame_async(body.frame.model_dump(exclude_none=True),
                                                     updates, body.number, body.refit)
    metrics = state.metrics
    metrics.frames.inc()
    for stage in ("cull_ms", "fit_ms", "encode_ms", "total_ms"):
        metrics.stage.labels(stage[:-3]).observe(timings[stage] / 1e3)
    out: dict[str, Any] = {"frame": number, "timings": timings}
    if body.packets:
        out["packets"] = [session.packet(t, number, body.full) for t in range(session.wall.tiles)]
    return out


def check_packets(session, body: FramePost) -> None:
    """Refuse, before any work, a frame that asks for every packet of a wall too large to
    answer that way."""
    if body.packets and session.wall.tiles > MAX_PACKETS:
        raise InputError(f"packets=true answers every tile's packet at once, for walls of at "
                         f"most {MAX_PACKETS} tiles; this one has {session.wall.tiles}: read "
                         "each tile's packet, or open streams")


@router.get("/walls/{wid}/tiles/{tile}/packets/{frame}", operation_id="getPacket",
            response_model=Packet, responses=refusals(401, 403, 404, 410, WAITS, CROWDED))
@needs(NODE)
async def get_packet(request: Request, state: State, wid: WallId, tile: TileId,
                     frame: Annotated[str, Path(pattern=FRAME)],
                     full: bool = False,
                     wait: Wait = 1.0):
    """Tile ``tile``'s packet of frame ``frame`` (a number or ``latest``): a delta against
    the frame the tile last acknowledged, or a full list. Waits up to ``wait`` seconds for a
    frame that is not ready yet. A node that lost its lists asks with ``full=true`` and
    acknowledges that frame before asking for deltas again. Packets carry the tracked head's
    pose: with a server token, reading one needs the tile's node credential."""
    session = state.walls.get(wid)
    session.check_tile(tile)
    if frame == "latest":
        if session.latest < 0 and not await long_poll(request.scope,
                                                      session.wait_frame(0, wait)):
            raise NotFound("no frame yet")
        number = session.latest
    else:
        number = int(frame)
        if number > MAX_FRAME:
            raise InputError(f"frame numbers end at {MAX_FRAME}, got {number}")
        if not await long_poll(request.scope, session.wait_frame(number, wait)):
            raise NotFound(f"frame {number} is not ready (latest {session.newest})")
    pkt = session.packet(tile, number, full)
    response = reply(request, pkt)
    state.metrics.packet(pkt["base"] is not None, len(response.body), "http")
    return response


@router.post("/walls/{wid}/tiles/{tile}/ack", status_code=204, operation_id="acknowledge",
             responses=refusals(400, 401, 403, 404, 408, 409, 413, 415, WAITS))
@needs(NODE)
async def ack(state: State, wid: WallId, tile: TileId, body: Annotated[Ack, body_of(Ack)]):
    """The tile has drawn frame ``frame`` (the swap barrier counts these). With a server
    token, only the tile's node credential (or the operator) may say so."""
    state.walls.get(wid).ack(tile, body.frame)
    return Response(status_code=204)


@router.get("/walls/{wid}/barrier/{frame}", operation_id="barrier", response_model=Barrier,
            responses=refusals(404, WAITS, CROWDED))
async def barrier(request: Request, state: State, wid: WallId,
                  frame: Annotated[int, Path(ge=0, le=MAX_FRAME)],
                  timeout: Wait = 1.0):
    """Wait until every tile has acknowledged ``frame``, or ``timeout`` seconds."""
    session = state.walls.get(wid)
    return reply(request, await long_poll(request.scope, session.barrier(frame, timeout)))
