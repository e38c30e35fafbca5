"""The browser pages: a render node's tile client and the operator console.

* ``GET /walls/{wid}/view?tiles=3,4``: the page a render PC opens full-screen, one browser
  window per output. It draws its tiles side by side in one WebGL2 canvas (``static/view.js``):
  the node stream in JSON, lists and matrices rebuilt as :mod:`wallcull_clients.node` does,
  meshes fetched once, one acknowledgement per frame drawn.
* ``GET /walls/{wid}/console``: the wall drawn to scale (front view of a flat wall, top view
  of screens around the viewer), each tile's list size, latency and state, live
  (``static/console.js``), from ``WS /walls/{wid}/console/stream``.
* ``GET /static/{name}``: the pages' scripts and style (package data, no build step).

The pages are open (like ``GET /walls/{wid}``); what they open is not: with a server token,
the view page needs a node credential (``?token=``), which it passes on to its stream.
"""

from __future__ import annotations

import asyncio
import html
import json
import time
from pathlib import Path as FilePath
from typing import Annotated

from fastapi import APIRouter, Path, Query, Request, WebSocket
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse
from starlette.websockets import WebSocketDisconnect, WebSocketState

from ..errors import InputError
from ..service import NotFound
from ..validate import parse_tiles, tiles_text
from .deps import ServerState, State
from .models import WALL_ID, refusals
from .streams import GONE

router = APIRouter(tags=["pages"])

STATIC = FilePath(__file__).resolve().parent / "static"
#: Seconds between two looks at a wall's state, for the console streams; a status unchanged
#: is sent again only after ``CONSOLE_QUIET`` seconds.
CONSOLE_PERIOD, CONSOLE_QUIET = 0.25, 2.0
#: Console streams open at once, on the whole server.
MAX_CONSOLES = 32
#: A tile list's form (``0-3``, ``0,1,8,9``, ``all``); tiles out of the wall are a 404.
TILES = r"^ *(all|\d{1,6}(-\d{1,6})?( *, *\d{1,6}(-\d{1,6})?)*) *$"

WallId = Annotated[str, Path(pattern=WALL_ID)]


def _html_or_refusals(*codes: int) -> dict:
    """OpenAPI ``responses`` of a page: HTML, or a refusal in JSON (said so: a route whose
    response class is HTML would otherwise document its refusals as HTML)."""
    out = {200: {"description": "An HTML page", "content": {"text/html": {
        "schema": {"type": "string"}}}}}
    for code, response in refusals(*codes).items():
        response.pop("model", None)
        out[code] = {**response, "content": {"application/json": {
            "schema": {"$ref": "#/components/schemas/Detail"}}}}
    return out


def _page(title: str, script: str, config: dict, body: str) -> HTMLResponse:
    # JSON inside <script>: "<", ">" and "&" escaped, so no value can close the element
    data = json.dumps(config).replace("<", "\\u003c").replace(">", "\\u003e") \
        .replace("&", "\\u0026")
    return HTMLResponse(f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1"><link rel="icon" href="data:,">
<title>{html.escape(title)}</title>
<link rel="stylesheet" href="{config['root']}/static/pages.css">
<script type="application/json" id="wallcull-config">{data}</script>
<script type="module" src="{config['root']}/static/{script}"></script>
</head><body class="{script.split('.')[0]}">{body}</body></html>
""", headers={"Cache-Control": "no-store"})


def _root(request: Request) -> str:
    """The path the app is served under (uvicorn's ``--root-path``), for the pages' links."""
    return html.escape(request.scope.get("root_path", "").rstrip("/"))


@router.get("/walls/{wid}/view", response_class=HTMLResponse, operation_id="viewPage",
            responses=_html_or_refusals(404))
async def view_page(request: Request, state: State, wid: WallId,
                    tiles: Annotated[str | None, Query(pattern=TILES, max_length=4000)] = None,
                    token: Annotated[str | None, Query(max_length=512)] = None,
                    ids: bool = False,
                    size: Annotated[str | None, Query(pattern=r"^[1-9]\d{0,3}x[1-9]\d{0,3}$")
                                    ] = None):
    """A render node's page: open it full-screen on each render PC, one window per output.
    It draws ``tiles`` (default: those of the node credential ``token``, else every tile)
    side by side, each at ``size`` pixels (``WxH``; default: as large as the window holds),
    a stereo frame's eyes side by side in each tile (half width each). ``ids=true`` also
    draws every leaf's draw id (leaf id + 1, 0 for background) into an integer target that
    ``window.wallcull.readIds(tile)`` reads back."""
    session = state.walls.get(wid)
    count = session.wall.tiles
    if tiles is not None:
        try:
            chosen = parse_tiles(tiles, count)
        except InputError as exc:
            raise NotFound(str(exc)) from None
    else:
        grant = state.walls.grant(token) if token else None
        chosen = sorted(grant.tiles) if grant is not None and grant.wall == wid else \
            list(range(count))
    config = {"root": _root(request), "wall": wid, "tiles": chosen, "spec": tiles_text(chosen),
              "token": token, "ids": ids,
              "size": [int(v) for v in size.split("x")] if size else None}
    return _page(f"wallcull {wid}: tiles {tiles or 'all'}", "view.js", config,
                 '<canvas id="wall"></canvas><div id="status">connecting</div>')


@router.get("/walls/{wid}/console", response_class=HTMLResponse, operation_id="consolePage",
            responses=_html_or_refusals(404))
async def console_page(request: Request, state: State, wid: WallId):
    """The operator's console: the wall to scale as it stands in the room, each tile's list
    size, frame latency and state, updated a few times a second
    (``WS /walls/{wid}/console/stream``)."""
    state.walls.get(wid)
    config = {"root": _root(request), "wall": wid}
    return _page(f"wallcull console {wid}", "console.js", config,
                 '<header><h1>wall <code></code></h1><p id="summary">connecting</p></header>'
                 '<main><svg id="plan" xmlns="http://www.w3.org/2000/svg"></svg>'
                 '<table id="tiles"><thead><tr><th>tile</th><th>list</th><th>acked</th>'
                 '<th>latency</th><th>streams</th><th>state</th></tr></thead>'
                 '<tbody></tbody></table></main>')


@router.get("/static/{name}", include_in_schema=False)
async def static(name: Annotated[str, Path(pattern=r"^[a-z][a-z0-9_-]{0,40}\.(js|css)$")]):
    path = STATIC / name
    if not path.is_file():
        raise NotFound(f"no file {name!r}")
    return FileResponse(path, headers={"Cache-Control": "no-cache"})


@router.websocket("/walls/{wid}/console/stream")
async def console_stream(ws: WebSocket, wid: str):
    """The console's status of a wall (JSON, see ``WallSession.status``) whenever it changes,
    looked at every ``CONSOLE_PERIOD`` seconds; closed with code 4404 when the wall is
    deleted. Open, like ``GET /walls/{wid}`` (it carries no pose)."""
    state: ServerState = ws.app.state.server
    try:
        session = state.walls.get(wid)
    except NotFound as exc:
        await ws.send_denial_response(JSONResponse({"detail": str(exc)}, 404))
        return
    if state.consoles >= MAX_CONSOLES:
        await ws.send_denial_response(JSONResponse(
            {"detail": f"the server already has {MAX_CONSOLES} consoles open"}, 429))
        return
    await ws.accept()
    state.consoles += 1

    async def left():  # a console sends nothing: its receive ends when it goes
        while (await ws.receive())["type"] != "websocket.disconnect":
            pass

    waits = [asyncio.ensure_future(left()), asyncio.ensure_future(session.gone.wait())]
    try:
        sent, sent_at = None, 0.0
        while not any(w.done() for w in waits):
            status = session.status()
            same = {k: v for k, v in status.items() if k != "time"}
            if same != sent or time.monotonic() - sent_at > CONSOLE_QUIET:
                await ws.send_text(json.dumps(status, separators=(",", ":")))
                sent, sent_at = same, time.monotonic()
            await asyncio.wait(waits, timeout=CONSOLE_PERIOD,
                               return_when=asyncio.FIRST_COMPLETED)
        if session.closed and ws.application_state == WebSocketState.CONNECTED:
            await ws.close(code=GONE, reason="the wall was deleted")
    except (WebSocketDisconnect, RuntimeError, OSError):
        pass  # the console went away
    finally:
        state.consoles -= 1
        for w in waits:
            w.cancel()
