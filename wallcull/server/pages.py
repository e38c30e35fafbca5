"""The browser pages: the walls' index, a render node's tile client, the operator console, and
the API's own interactive documents.

* ``GET /``: the walls the server holds, each with links to its console and view pages (and
  the first few node credentials' tiles), and links to the API's documents.
* ``GET /walls/{wid}/view?tiles=3,4``: the page a render PC opens full-screen, one browser
  window per output. It draws its tiles in one WebGL2 canvas (``static/view.js``), a grid's
  tiles as on the wall when they fill a rectangle, else side by side: the node stream in JSON,
  lists and matrices rebuilt as :mod:`wallcull_clients.node` does, meshes fetched once (again
  when a restarted server culls a replaced scene file), one acknowledgement per frame drawn.
  It draws each tile's primary view (both eyes in stereo), not the shadow maps or mirror
  passes of the messages' ``shadows`` and ``mirrors``, as the Python clients; a render node of
  its own draws those from their frusta and lists.
* ``GET /walls/{wid}/console``: the wall drawn to scale (front view of a flat wall, top view
  of screens around the viewer), each tile's list size, latency and state, live
  (``static/console.js``), from ``WS /walls/{wid}/console/stream``.
* ``GET /static/{name}``: the pages' scripts and style (package data, no build step).
* ``GET /docs``: Swagger UI on the OpenAPI document, its script and style served from the
  installed package ``fastapi-offline`` (no CDN: it works on a lab network with no way out).

The pages are open (like ``GET /walls/{wid}``); what they open is not: with a server token,
the view page needs a node credential (``?token=``), which it passes on to its stream. A page's
refusal is a page too (an unknown wall, a bad query), with the same status.
"""

from __future__ import annotations

import asyncio
import html
import json
import time
from pathlib import Path as FilePath
from typing import Annotated

import fastapi_offline
import numpy as np
from fastapi import APIRouter, Path, Query, Request, WebSocket
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse
from starlette.websockets import WebSocketDisconnect, WebSocketState

from ..errors import InputError
from ..service import LAG, LAG_FRAMES, LIVE, NotFound, Unavailable
from ..validate import parse_tiles, tiles_text
from ..workers import background
from .access import bearer
from .deps import ServerState, State
from .http import Budget, Refused, encode_in_pieces
from .models import WAITS, WallId, refusals, worded
from .streams import GONE, count, deny, room

router = APIRouter(tags=["pages"])

STATIC = FilePath(__file__).resolve().parent / "static"
#: Swagger UI's script and style, as the package fastapi-offline ships them.
DOCS_ASSETS = FilePath(fastapi_offline.__file__).resolve().parent / "static"
#: Seconds between two looks at a wall's state, for the console streams; a status unchanged
#: is sent again only after ``CONSOLE_QUIET`` seconds.
CONSOLE_PERIOD, CONSOLE_QUIET = 0.25, 2.0
#: Console streams opened with a credential of their wall (the operator's token, a node's or
#: the driver's) open at once, on the whole server; those without one have their own cap,
#: ``limits.consoles``, and never take these.
MAX_CONSOLES = 32
#: The index links the view pages of a wall's first node credentials, at most this many and
#: of at most this many tiles in all (a 256 x 256 wall has 65,536 of them: 3.9 MB of links,
#: made on the event loop at every ``GET /``); the console links every tile's page.
INDEX_NODES, INDEX_TILES = 8, 1024
#: Seconds a page refused for a wall waiting for its scene (503) waits before it loads again.
REFRESH = 5
#: A tile list's form (``0-3``, ``0,1,8,9``, ``all``); tiles out of the wall are a 404.
TILES = worded(r"^ *(all|\d{1,6}(-\d{1,6})?( *, *\d{1,6}(-\d{1,6})?)*) *$",
               "tiles are 'all' or tile numbers and ranges, such as '0-3,8'")
ASSET = worded(r"^[a-z][a-z.-]{0,40}\.(js|css)$", "the docs' assets are .js and .css files")
STATIC_NAME = worded(r"^[a-z][a-z0-9_-]{0,40}\.(js|css)$",
                     "the pages' files are .js and .css files")
SIZE = worded(r"^[1-9]\d{0,3}x[1-9]\d{0,3}$", "a size is WIDTHxHEIGHT in pixels, such as 1920x1080")


def _html_or_refusals(*codes: int | str) -> dict:
    """OpenAPI ``responses`` of a page: an HTML page, its refusals too."""
    out = {200: {"description": "An HTML page", "content": {"text/html": {
        "schema": {"type": "string"}}}}}
    for code, response in refusals(*codes).items():
        response.pop("model", None)
        if code != 503:  # a page refused for now says when to load it again
            response.pop("headers", None)
        out[code] = {**response, "content": {"text/html": {"schema": {"type": "string"}}}}
    return out


def page(endpoint):
    """Marks a route as a page: its refusals are pages (:func:`is_page`)."""
    endpoint.wallcull_page = True
    return endpoint


def is_page(request: Request) -> bool:
    """Whether ``request`` reached a page (whose refusals are pages, not JSON; the gate's
    refusals look at the route's endpoint the same way)."""
    return getattr(request.scope.get("endpoint"), "wallcull_page", False)


def _page(title: str, body: str, root: str, script: str | None = None,
          config: dict | None = None, status: int = 200, kind: str = "index",
          head: str = "") -> HTMLResponse:
    if script is not None:
        # JSON inside <script>: "<", ">" and "&" escaped, so no value can close the element
        data = json.dumps(config).replace("<", "\\u003c").replace(">", "\\u003e") \
            .replace("&", "\\u0026")
        head += (f'<script type="application/json" id="wallcull-config">{data}</script>\n'
                f'<script type="module" src="{root}/static/{script}"></script>\n')
        kind = script.split(".")[0]
    return HTMLResponse(f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1"><link rel="icon" href="data:,">
<title>{html.escape(title)}</title>
<link rel="stylesheet" href="{root}/static/pages.css">
{head}</head><body class="{kind}">{body}</body></html>
""", status, headers={"Cache-Control": "no-store"})


def error_page(request: Request, status: int, detail: str) -> HTMLResponse:
    """A refusal, as a page: the status, what is wrong, and the way back to the walls; a 503
    (a wall waiting for its scene) loads itself again every ``REFRESH`` seconds."""
    root = _root(request)
    reason = html.escape(_REASONS.get(status, "Refused"))
    again = f'<meta http-equiv="refresh" content="{REFRESH}">\n' if status == 503 else ""
    page = _page(f"{status} {reason}: wallcull", f'<main><h1>{status} {reason}</h1>'
                 f'<p class="detail">{html.escape(detail)}</p>'
                 + (f"<p>Trying again every {REFRESH} s.</p>" if again else "") +
                 f'<p><a href="{root}/">the walls of this server</a></p></main>', root,
                 status=status, kind="index error", head=again)
    if again:
        page.headers["Retry-After"] = str(REFRESH)
    return page


#: A page's ``?token=``: a credential it passes on to its streams and links.
Token = Annotated[str | None, Query(max_length=512)]

_REASONS = {404: "Not Found", 422: "Invalid request", 429: "Too Many Requests",
            503: "Service Unavailable"}


def _missing(request: Request, exc: Exception) -> HTMLResponse:
    """The page of a wall (or tiles) that is not there: 503 while its scene is away (it
    comes back with it), else 404; counted with the API's refusals."""
    status = 503 if isinstance(exc, Unavailable) else 404
    request.app.state.server.metrics.errors.labels(str(status)).inc()
    return error_page(request, status, str(exc))


def _root(request: Request) -> str:
    """The path the app is served under (uvicorn's ``--root-path``), for the pages' links."""
    return html.escape(request.scope.get("root_path", "").rstrip("/"))


@router.get("/", response_class=HTMLResponse, operation_id="indexPage",
            responses=_html_or_refusals())
@page
async def index_page(request: Request, state: State):
    """The walls this server holds, each with links to its console and to its view pages (all
    tiles, and the first few node credentials' tiles: ``INDEX_NODES``), the walls waiting for
    their scene with the reason, and links to the API's documents."""
    root = _root(request)
    rows = []
    for wid, session in state.walls.sessions.items():
        wall = session.wall
        shape = f"{wall.cols} x {wall.rows}" if wall.kind == "grid" else f"{wall.tiles} screens"
        shown, named, issued = [], 0, session.issued
        for tiles in [] if issued is None else issued.nodes(INDEX_NODES):
            named += len(tiles)
            if named > INDEX_TILES:
                break
            shown.append(tiles)
        views = " ".join(f'<a href="{root}/walls/{wid}/view?tiles={tiles_text(tiles)}">'
                         f"tiles {tiles_text(tiles)}</a>" for tiles in shown)
        more = (0 if issued is None else issued.node_count) - len(shown)
        if more:
            views += (f' <span class="more">and {more} more node(s): their tiles in '
                      f'<a href="{root}/walls/{wid}">the wall\'s nodes</a>, each tile\'s page '
                      "on the console</span>")
        rows.append(f'<tr id="wall-{wid}"><td><code>{wid}</code></td>'
                    f"<td>{html.escape(session.scene.name)}</td><td>{shape}</td>"
                    f"<td>{session.session.method}</td>"
                    f"<td>{session.newest if session.newest >= 0 else 'none yet'}</td>"
                    f'<td><a class="console" href="{root}/walls/{wid}/console">console</a></td>'
                    f'<td><a class="view" href="{root}/walls/{wid}/view">all tiles</a> '
                    f"{views}</td></tr>")
    for wid, (_, reason) in list(state.walls.unavailable.items()):
        rows.append(f'<tr id="wall-{wid}" class="unavailable"><td><code>{wid}</code></td>'
                    f'<td colspan="6">unavailable: {html.escape(reason)}</td></tr>')
    walls = ('<table id="walls"><thead><tr><th>wall</th><th>scene</th><th>tiles</th>'
             "<th>method</th><th>frame</th><th>console</th><th>view (a render node's page)"
             f"</th></tr></thead><tbody>{''.join(rows)}</tbody></table>" if rows else
             '<p id="walls">No walls yet. A driver creates one (<code>POST /walls</code>, '
             f'see <a href="{root}/docs">the API</a>).</p>')
    token = ("<p>This server has a token: a view page needs its node's credential, "
             "<code>?token=...</code>, issued when the wall was created.</p>"
             if not state.open else "")
    return _page("wallcull", f"""<main><h1>wallcull</h1>
<p>A culling server for tiled display walls: {len(rows)} wall(s).</p>{walls}{token}
<h2>The API</h2><ul>
<li><a href="{root}/docs">/docs</a>: the HTTP API, interactive (Swagger UI), from
<a href="{root}/openapi.json">/openapi.json</a></li>
<li><a href="{root}/asyncapi.json">/asyncapi.json</a>: the streams (WebSocket and NATS)</li>
<li><a href="{root}/scenes">/scenes</a>, <a href="{root}/walls">/walls</a>,
<a href="{root}/health">/health</a>, <a href="{root}/metrics">/metrics</a></li></ul></main>""",
                 root)


@router.get("/walls/{wid}/view", response_class=HTMLResponse, operation_id="viewPage",
            responses=_html_or_refusals(404, WAITS))
@page
async def view_page(request: Request, state: State, wid: WallId,
                    tiles: Annotated[str | None, Query(pattern=TILES, max_length=4000)] = None,
                    token: Token = None,
                    ids: bool = False,
                    size: Annotated[str | None, Query(pattern=SIZE)] = None):
    """A render node's page: open it full-screen on each render PC, one window per output.
    It draws ``tiles`` (default: those of the node credential ``token``, else every tile),
    a grid's as on the wall when they fill a rectangle, else side by side, each at ``size``
    pixels (``WxH``; default: its own resolution, all scaled by one factor to as large as the
    window holds), a stereo frame's eyes side by side in each tile (half width each); the
    primary views only, not the shadow and mirror passes. ``ids=true`` also
    draws every leaf's draw id (leaf id + 1, 0 for background) into an integer target that
    ``window.wallcull.readIds(tile)`` reads back."""
    try:
        session = state.walls.get(wid)
        count = session.wall.tiles
        chosen = None if tiles is None else parse_tiles(tiles, count)
    except (NotFound, InputError, Unavailable) as exc:
        return _missing(request, exc)
    if chosen is None:
        grant = state.walls.grant(token) if token else None
        chosen = sorted(grant.tiles) if grant is not None and grant.wall == wid else \
            list(range(count))
    root = _root(request)
    config = {"root": root, "wall": wid, "tiles": chosen, "spec": tiles_text(chosen),
              "token": token, "ids": ids,
              "size": [int(v) for v in size.split("x")] if size else None}
    return _page(f"wallcull {wid}: tiles {tiles_text(chosen)}",
                 '<canvas id="wall"></canvas><div id="status">connecting</div>', root,
                 "view.js", config)


@router.get("/walls/{wid}/console", response_class=HTMLResponse, operation_id="consolePage",
            responses=_html_or_refusals(404, WAITS))
@page
async def console_page(request: Request, state: State, wid: WallId,
                       token: Token = None):
    """The operator's console: the wall to scale as it stands in the room, each tile's list
    size, frame latency and state (a legend says which colour is which), updated a few times
    a second (``WS /walls/{wid}/console/stream``); each tile links to its view page, which
    gets ``token`` (the operator's, or a credential of the wall) with the link."""
    try:
        state.walls.get(wid)
    except (NotFound, Unavailable) as exc:
        return _missing(request, exc)
    root = _root(request)
    legend = "".join(f'<li class="{name}"><span class="swatch"></span>{name}: {text}</li>'
                     for name, text in LEGEND)
    return _page(f"wallcull console {wid}",
                 '<header><h1>wall <code></code></h1><p id="summary">connecting</p>'
                 f'<a href="{root}/">all walls</a></header>'
                 '<main><svg id="plan" xmlns="http://www.w3.org/2000/svg"></svg>'
                 f'<div id="side"><ul id="legend">{legend}</ul>'
                 '<table id="tiles"><thead><tr><th>tile</th><th>list</th><th>acked</th>'
                 '<th>latency</th><th>streams</th><th>state</th></tr></thead>'
                 '<tbody></tbody></table></div></main>', root, "console.js",
                 {"root": root, "wall": wid, "token": token})


#: The console's tile states (``WallSession.status``), and what each means.
LEGEND = (("offline", f"no stream, no acknowledgement for {LIVE:g} s, the newest frame "
                      "not drawn"),
          ("waiting", "no frame posted yet"),
          ("drawing", "the newest frame is not yet acknowledged"),
          ("acked", "has drawn the newest frame (streaming or not)"),
          ("lagging", f"more than {LAG_FRAMES} frames or {LAG:g} s behind"))


@router.get("/docs", include_in_schema=False)
async def swagger_ui(request: Request):
    root = _root(request)
    return get_swagger_ui_html(openapi_url=f"{root}/openapi.json", title="wallcull: the API",
                               swagger_js_url=f"{root}/docs/assets/swagger-ui-bundle.js",
                               swagger_css_url=f"{root}/docs/assets/swagger-ui.css",
                               swagger_favicon_url="data:,")


@router.get("/docs/assets/{name}", include_in_schema=False)
async def docs_asset(name: Annotated[str, Path(pattern=ASSET)]):
    return _file(DOCS_ASSETS / name, "public, max-age=86400")  # a release's, unchanging


@router.get("/static/{name}", include_in_schema=False)
async def static(name: Annotated[str, Path(pattern=STATIC_NAME)]):
    return _file(STATIC / name, "no-cache")


def _file(path: FilePath, cache: str) -> FileResponse:
    if not path.is_file():
        raise NotFound(f"no file {path.name!r}")
    return FileResponse(path, headers={"Cache-Control": cache})


@router.websocket("/walls/{wid}/console/stream")
async def console_stream(ws: WebSocket, wid: str):
    """The console's status of a wall (JSON, see ``WallSession.status``) whenever it changes,
    looked at every ``CONSOLE_PERIOD`` seconds; closed with code 4404 when the wall is
    deleted. Open, like ``GET /walls/{wid}`` (it carries no pose), but counted against the
    caps of streams (the server's, the wall's: 429). A console opened without a credential of
    the wall (``?token=``: the operator's or one of the wall's) counts against
    ``limits.consoles`` (429), never against the ``MAX_CONSOLES`` of those opened with one (so
    that anonymous consoles cannot lock the operator out), and shares with every other such
    console ``limits.open_bytes`` a second: on a 256 x 256 wall it is sent a status (2 MB)
    less often."""
    state: ServerState = ws.app.state.server
    token = ws.query_params.get("token") or bearer(ws.headers.get("authorization"))
    try:
        session = state.walls.get(wid)
        grant = state.walls.grant(token) if token else None
        trusted = token is not None and (state.is_operator(token) or
                                         (grant is not None and grant.wall == wid))
        cap = MAX_CONSOLES if trusted else state.limits.consoles
        if state.consoles[trusted] >= cap:
            raise Refused(429, f"the server already has {cap} consoles open "
                               f"{'with' if trusted else 'without'} a credential")
        room(state, session, NO_TILES)
    except (NotFound, Refused, Unavailable) as exc:
        return await deny(ws, state, exc)
    await ws.accept()
    state.consoles[trusted] += 1
    count(state, session, NO_TILES, +1)

    pace = Budget(state.limits.messages)

    async def left():  # a console sends nothing: its receive ends when it goes
        while (await ws.receive())["type"] != "websocket.disconnect":
            await pace.spend()  # (what it does send is read no faster than a stream's)

    waits = [asyncio.ensure_future(left()), asyncio.ensure_future(session.gone.wait())]
    try:
        sent, sent_at = None, 0.0
        while not any(w.done() for w in waits):
            if (await _status(session))[1] != sent or \
                    time.monotonic() - sent_at > CONSOLE_QUIET:
                if not trusted:  # its turn waited for holding no status: the newest is sent
                    await state.open_budget.spend(len((await _status(session))[0]))
                text, sent = await _status(session)
                await ws.send_text(text)
                # no status held between sends: 32 consoles, each holding the one it sent
                # last (2 MB at 256 x 256, a new one every CONSOLE_PERIOD), held 128 MB
                del text
                sent_at = time.monotonic()
            await asyncio.wait(waits, timeout=CONSOLE_PERIOD,
                               return_when=asyncio.FIRST_COMPLETED)
        if session.closed and ws.application_state == WebSocketState.CONNECTED:
            await ws.close(code=GONE, reason="the wall was deleted")
    except (WebSocketDisconnect, RuntimeError, OSError):
        pass  # the console went away
    finally:
        state.consoles[trusted] -= 1
        count(state, session, NO_TILES, -1)
        for w in waits:
            w.cancel()


NO_TILES = np.zeros(0, np.int64)


async def _status(session) -> tuple[str, int]:
    """A wall's console status as JSON, and a hash of it without its time (to see whether it
    changed): computed at most once per ``CONSOLE_PERIOD`` for all of the wall's consoles,
    in a worker thread (a 256 x 256 wall's is 2 MB)."""
    cached = session.__dict__.get("_console")
    if cached is None or time.monotonic() - cached[0] >= CONSOLE_PERIOD:
        async with session.__dict__.setdefault("_console_lock", asyncio.Lock()):
            cached = session.__dict__.get("_console")
            if cached is None or time.monotonic() - cached[0] >= CONSOLE_PERIOD:
                cached = session.__dict__["_console"] = (
                    time.monotonic(), *await background(_status_texts, session))
    return cached[1], cached[2]


def _status_texts(session) -> tuple[str, int]:
    """The status as JSON, and a hash of it without its time; encoded a piece at a time, so
    that the worker thread lets the event loop run between pieces."""
    status = session.status()
    now = status.pop("time")
    same = encode_in_pieces(status, binary=False)
    return (same[:-1] + f',"time":{json.dumps(now)}}}'.encode()).decode(), hash(same)
