"""The HTTP and WebSocket API (FastAPI on uvicorn): routes only, grouped by resource; the work
is in :mod:`wallcull.service`.

* :mod:`.scenes`: list, upload and describe scenes, and serve their meshes;
* :mod:`.walls`: create walls, post frames, read packets, acknowledge, the swap barrier;
* :mod:`.streams`: a tile's WebSocket stream;
* :mod:`.http`, :mod:`.deps`, :mod:`.models`, :mod:`.metrics`: what the routes share.

Bodies travel as JSON or msgpack, chosen by ``Content-Type`` (requests) and ``Accept``
(responses), with one schema, the OpenAPI document's. A request that changes state needs the
server's token when one is configured (``Authorization: Bearer <token>``).
"""

from __future__ import annotations

import asyncio
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ..errors import InputError
from ..service import Conflict, Gone, NotFound, SceneStore, Walls
from . import scenes, streams, walls
from .deps import ServerState
from .http import BodyCodec, Refused, status_handler
from .metrics import Metrics

#: Bytes a request body may have (frames, walls, updates); uploads have their own limit.
MAX_BODY = 1 << 20


def create_app(scene_folder=None, token: str | None = None, max_body: int = MAX_BODY,
               max_upload: int = 64 << 20, max_walls: int = 32) -> FastAPI:
    state = ServerState(SceneStore(scene_folder, max_upload), Walls(max_walls), Metrics(), token)
    metrics = state.metrics

    @asynccontextmanager
    async def lifespan(app):
        await asyncio.to_thread(_warm_up)  # compile (or load) the culling kernels once
        yield

    app = FastAPI(title="wallcull", version="0.1.0", lifespan=lifespan,
                  description="Culling server for tiled display walls. Bodies are JSON or "
                              "msgpack (Content-Type / Accept: application/msgpack).")
    app.state.server = state
    app.add_middleware(BodyCodec, max_body=max_body, max_upload=max_upload, metrics=metrics)

    @app.exception_handler(Refused)
    async def refused(request, exc: Refused):
        metrics.errors.labels(str(exc.status)).inc()
        return JSONResponse({"detail": exc.detail}, exc.status)

    for exc_type, status in ((InputError, 422), (NotFound, 404), (Conflict, 409), (Gone, 410)):
        app.add_exception_handler(exc_type, status_handler(status, metrics))

    @app.exception_handler(RequestValidationError)
    async def invalid(request, exc: RequestValidationError):
        metrics.errors.labels("422").inc()
        detail = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        return JSONResponse({"detail": detail}, 422)

    @app.get("/health", tags=["service"])
    async def health():
        return {"status": "ok", "walls": len(state.walls.sessions),
                "scenes_loaded": sorted(state.store.cache)}

    @app.get("/metrics", tags=["service"], response_class=Response, responses={200: {
        "description": "Prometheus text format", "content": {"text/plain": {}}}})
    async def prometheus():
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    for module in (scenes, walls, streams):
        app.include_router(module.router)
    return app


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
