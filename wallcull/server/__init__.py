"""The HTTP and WebSocket API (FastAPI on uvicorn): routes only, grouped by resource; the work
is in :mod:`wallcull.service`.

* :mod:`.scenes`: list, upload and describe scenes, and serve their meshes;
* :mod:`.walls`: create walls, post frames, read packets, acknowledge, the swap barrier;
* :mod:`.streams`: the WebSocket streams: a tile's, a render node's, a driver's frames;
* :mod:`.nats`: the same node messages published on a NATS broker, acks taken back;
* :mod:`.asyncapi`: the streams' messages, as an AsyncAPI document (``/asyncapi.json``);
* :mod:`.pages`: the browser pages: a render node's tile client (WebGL2) and the operator
  console, with the console's status stream;
* :mod:`.gate`: what every request passes first: ``OPTIONS``, origins, tokens, body limits;
* :mod:`.access`, :mod:`.http`, :mod:`.deps`, :mod:`.models`, :mod:`.openapi`,
  :mod:`.metrics`: what the routes share.

Bodies travel as JSON or msgpack, chosen by ``Content-Type`` (requests) and ``Accept``
(responses), with one schema, the OpenAPI document's. With a token (``--token``), routes need
the operator's token or a credential issued with a wall (:mod:`.access`); with a state folder,
walls survive a restart (:mod:`wallcull.persist`).
"""

from __future__ import annotations

import asyncio
import logging
import os
from contextlib import asynccontextmanager
from dataclasses import replace

from fastapi import FastAPI
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ..errors import InputError, optional
from ..limits import Limits
from ..persist import StateFolder, default_folder
from ..service import Conflict, Gone, NotFound, SceneStore, Walls, settled
from . import asyncapi, openapi, pages, scenes, streams, walls
from .deps import ServerState
from .gate import Gate
from .http import Refused, refusal_detail, status_handler
from .metrics import Metrics
from .nats import NatsBridge

#: Bytes a request body may have (frames, walls, updates); uploads have their own limit.
MAX_BODY = Limits.body

log = logging.getLogger("wallcull")


class App(FastAPI):
    """FastAPI, with each WebSocket's own ``send`` kept in its scope (``wallcull.send``): a
    stream's writes, one per frame, go straight to the server's protocol instead of through
    every middleware's wrapper of ``send`` (:func:`.streams.writer`)."""

    async def __call__(self, scope, receive, send):
        if scope["type"] == "websocket":
            scope["wallcull.send"] = send
        await super().__call__(scope, receive, send)


def create_app(scene_folder=None, token: str | None = None, max_body: int | None = None,
               max_upload: int | None = None, max_walls: int | None = None, *,
               limits: Limits | None = None, state=None, origins=(), nats: str | None = None,
               nats_prefix: str = "wallcull") -> FastAPI:
    """The app. ``state``: a folder where walls persist (None: they live in memory only), and
    where uploads go when there is no ``scene_folder``. ``origins``: browser origins allowed
    to call the API and open streams (``"*"``: any). ``nats``: a NATS broker's URL, to publish
    node messages there too (:mod:`.nats`). ``max_body``, ``max_upload`` and ``max_walls``
    override ``limits``."""
    limits = limits or Limits()
    overrides = {"body": max_body, "upload": max_upload, "walls": max_walls}
    limits = replace(limits, **{k: v for k, v in overrides.items() if v is not None})
    folder = StateFolder(state) if state is not None else None
    if scene_folder is None and folder is not None:
        scene_folder = folder.scenes
    walls_ = Walls(limits.walls, folder)
    store = SceneStore(scene_folder, limits, in_use=walls_.scene_names)
    server = ServerState(store, walls_, Metrics(), token, limits, tuple(origins))
    metrics = server.metrics
    if nats:
        optional("nats", "nats", "--nats")  # refused now, not when the server starts
        server.bridge = NatsBridge(nats, walls_, metrics, nats_prefix)

    @asynccontextmanager
    async def lifespan(app):
        # compile (or load) the culling kernels once, while the walls of the state folder
        # come back (their scenes load in another thread): clients wait for both
        _, restored = await asyncio.gather(asyncio.to_thread(_warm_up), walls_.restore(store))
        if restored:
            log.info("restored %d wall(s): %s", len(restored), ", ".join(restored))
        await asyncio.to_thread(settled)
        if server.bridge is not None:
            await server.bridge.start()
        yield
        if server.bridge is not None:
            await server.bridge.close()
        if folder is not None:
            folder.close()

    app = App(title="wallcull", version="0.1.0", lifespan=lifespan, docs_url=None,
              redoc_url=None,  # Swagger UI from the package, not a CDN (:mod:`.pages`)
              description="Culling server for tiled display walls. Bodies are JSON or "
                          "msgpack (Content-Type / Accept: application/msgpack).")
    app.state.server = server
    app.add_middleware(Gate, state=server)
    app.add_middleware(CORSMiddleware, allow_origins=list(origins), allow_credentials=False,
                       allow_methods=["GET", "POST", "DELETE"], expose_headers=["ETag"],
                       allow_headers=["Authorization", "Content-Type", "Accept",
                                      "If-None-Match"], max_age=600)
    app.openapi = lambda: app.openapi_schema or _document(app, not server.open)

    @app.exception_handler(Refused)
    async def refused(request, exc: Refused):
        metrics.errors.labels(str(exc.status)).inc()
        return JSONResponse({"detail": exc.detail}, exc.status, exc.headers)

    for exc_type, status in ((InputError, 422), (NotFound, 404), (Conflict, 409), (Gone, 410)):
        app.add_exception_handler(exc_type, status_handler(status, metrics))

    @app.exception_handler(RequestValidationError)
    async def invalid(request, exc: RequestValidationError):
        metrics.errors.labels("422").inc()
        if pages.is_page(request):
            return pages.error_page(request, 422, refusal_detail(exc))
        return JSONResponse({"detail": refusal_detail(exc)}, 422)

    @app.get("/health", tags=["service"], operation_id="health")
    async def health():
        return {"status": "ok", "walls": len(server.walls.sessions),
                "scenes_loaded": sorted(server.store.cache)}

    @app.get("/asyncapi.json", tags=["service"], operation_id="asyncapi")
    async def streams_document():
        """The AsyncAPI document of the streams: WebSocket and NATS messages."""
        return asyncapi.document(app.version)

    @app.get("/metrics", tags=["service"], response_class=Response, operation_id="metrics",
             responses={200: {"description": "Prometheus text format",
                              "content": {"text/plain": {}}}})
    async def prometheus():
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    for module in (scenes, walls, streams, pages):
        app.include_router(module.router)
    return app


def _document(app: FastAPI, secured: bool) -> dict:
    app.openapi_schema = openapi.document(app, secured)
    return app.openapi_schema


def _warm_up() -> None:
    """Cull one frame of a tiny scene so that the kernels are compiled before the first client."""
    import numpy as np
    import trimesh

    from ..cull import METHODS
    from ..pipeline import Session
    from ..scene import Scene
    from ..wall import Wall

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


def settings_from_env(environ=os.environ) -> dict:
    """``create_app`` keywords from the environment: ``WALLCULL_SCENES``, ``WALLCULL_TOKEN``,
    ``WALLCULL_STATE`` (a folder; ``none`` keeps walls in memory only; default
    :func:`wallcull.persist.default_folder`), ``WALLCULL_LIMITS`` (``NAME=VALUE,...``),
    ``WALLCULL_CORS_ORIGINS`` (comma-separated), ``WALLCULL_NATS`` and
    ``WALLCULL_NATS_PREFIX``."""
    state = environ.get("WALLCULL_STATE") or str(default_folder())
    return {"scene_folder": environ.get("WALLCULL_SCENES") or None,
            "token": environ.get("WALLCULL_TOKEN") or None,
            "state": None if state.lower() == "none" else state,
            "limits": Limits().with_text(environ.get("WALLCULL_LIMITS", "")),
            "origins": tuple(o.strip() for o in environ.get("WALLCULL_CORS_ORIGINS", "").split(",")
                             if o.strip()),
            "nats": environ.get("WALLCULL_NATS") or None,
            "nats_prefix": environ.get("WALLCULL_NATS_PREFIX") or "wallcull"}


def make_app_from_env() -> FastAPI:
    """For ``uvicorn wallcull.server:make_app_from_env --factory`` (Docker and friends)."""
    return create_app(**settings_from_env())


def serve(host: str = "127.0.0.1", port: int = 8000, log_level: str = "info", **settings) -> None:
    """Run the server (``settings``: :func:`create_app` keywords)."""
    import uvicorn

    uvicorn.run(create_app(**settings), host=host, port=port, log_level=log_level,
                access_log=False, ws_max_size=1 << 20)
