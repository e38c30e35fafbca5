"""Routes of the walls: create and delete, post frames, read packets, acknowledge, the barrier."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import Response

from .. import settings as cfg
from ..fit import FitOptions
from ..service import NotFound
from ..wall import Wall
from .deps import TOKEN, State
from .http import reply
from .models import Ack, Barrier, FrameAnswer, FramePost, Packet, WallCreate, refusals

#: Seconds a request may wait for a frame or the barrier.
MAX_WAIT = 10.0

router = APIRouter(tags=["walls"])


@router.post("/walls", dependencies=TOKEN, status_code=201,
             responses=refusals(400, 401, 404, 409, 413))
async def create_wall(request: Request, state: State, body: WallCreate):
    wall = Wall.from_dict(body.wall.model_dump())
    if body.settings is not None:
        cfg.parse(body.settings)  # refused here, with its reason, not at the first frame
    scene = await state.store.get(body.scene)
    session = state.walls.create(scene, wall, body.method, body.bounds, body.pseudo_groups,
                                 body.history,
                                 FitOptions(body.depth, body.reversed_z, body.shadow_fit),
                                 body.settings)
    return reply(request, session.info(), 201)


@router.get("/walls")
async def list_walls(request: Request, state: State):
    return reply(request, {"walls": [w.info() for w in state.walls.sessions.values()]})


@router.get("/walls/{wid}", responses=refusals(404))
async def wall_info(request: Request, state: State, wid: str):
    return reply(request, state.walls.get(wid).info())


@router.delete("/walls/{wid}", dependencies=TOKEN, status_code=204,
               responses=refusals(400, 401, 404, 413))
async def delete_wall(state: State, wid: str):
    state.walls.get(wid).close()
    state.walls.delete(wid)
    return Response(status_code=204)


@router.post("/walls/{wid}/frames", dependencies=TOKEN, response_model=FrameAnswer,
             responses=refusals(400, 401, 404, 409, 413))
async def post_frame(request: Request, state: State, wid: str, body: FramePost):
    """Cull (and fit) a frame; answer its number and, with ``packets``, every tile's packet."""
    session = state.walls.get(wid)
    updates = {name: u.value() for name, u in body.updates.items()}
    number, timings = await session.post_frame_async(body.frame.model_dump(), updates,
                                                     body.number, body.refit)
    metrics = state.metrics
    metrics.frames.inc()
    for stage in ("cull_ms", "fit_ms", "total_ms"):
        metrics.stage.labels(stage[:-3]).observe(timings[stage] / 1e3)
    out: dict[str, Any] = {"frame": number, "timings": timings}
    if body.packets:
        out["packets"] = [session.packet(t, number, body.full) for t in range(session.wall.tiles)]
    return reply(request, out)


@router.get("/walls/{wid}/tiles/{tile}/packets/{frame}", response_model=Packet,
            responses=refusals(404, 410))
async def get_packet(request: Request, state: State, wid: str, tile: int,
                     frame: Annotated[str, Path(pattern=r"^(latest|\d{1,15})$")],
                     full: bool = False,
                     wait: Annotated[float, Query(ge=0, le=MAX_WAIT)] = 1.0):
    """Tile ``tile``'s packet of frame ``frame`` (a number or ``latest``): a delta against
    the frame the tile last acknowledged, or a full list. Waits up to ``wait`` seconds for a
    frame that is not ready yet. A node that lost its lists asks with ``full=true`` and
    acknowledges that frame before asking for deltas again."""
    session = state.walls.get(wid)
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
    state.metrics.packet(pkt["base"] is not None, len(response.body), "http")
    return response


@router.post("/walls/{wid}/tiles/{tile}/ack", dependencies=TOKEN, status_code=204,
             responses=refusals(400, 401, 404, 409, 413))
async def ack(state: State, wid: str, tile: int, body: Ack):
    """The tile has drawn frame ``frame`` (the swap barrier counts these)."""
    state.walls.get(wid).ack(tile, body.frame)
    return Response(status_code=204)


@router.get("/walls/{wid}/barrier/{frame}", response_model=Barrier, responses=refusals(404))
async def barrier(request: Request, state: State, wid: str,
                  frame: Annotated[int, Path(ge=0, le=2**53)],
                  timeout: Annotated[float, Query(ge=0, le=MAX_WAIT)] = 1.0):
    """Wait until every tile has acknowledged ``frame``, or ``timeout`` seconds."""
    return reply(request, await state.walls.get(wid).barrier(frame, timeout))
