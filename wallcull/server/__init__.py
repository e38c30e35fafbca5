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
import sys
import time
from pathlib import Path
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
from .. import warm
from . import heap, redact
from ..workers import background, count as kernel_threads
from ..persist import StateWriteFailed
from ..service import Conflict, Gone, NotFound, SceneStore, Unavailable, Walls, settled
from . import asyncapi, openapi, pages, scenes, streams, walls
from .deps import ServerState
from .gate import Gate
from .http import Refused, refusal_detail, status_handler
from .metrics import Metrics
from .nats import NatsBridge, check_prefix

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
               nats_prefix: str = "wallcull", wall_ttl: float | None = None) -> FastAPI:
    """The app. ``state``: a folder where walls persist (None: they live in memory only), and
    where uploads go when there is no ``scene_folder``. ``origins``: browser origins allowed
    to call the API and open streams (``"*"``: any). ``nats``: a NATS broker's URL, to publish
    node messages there too (:mod:`.nats`). ``wall_ttl``: delete a wall once it has had no
    frame and no stream for that many seconds (None: never). ``max_body``, ``max_upload`` and
    ``max_walls`` override ``limits``."""
    limits = limits or Limits()
    overrides = {"body": max_body, "upload": max_upload, "walls": max_walls}
    limits = replace(limits, **{k: v for k, v in overrides.items() if v is not None})
    if scene_folder is not None and not Path(scene_folder).is_dir():
        raise InputError(f"the scene folder {scene_folder} is not a folder"
                         if Path(scene_folder).exists() else
                         f"the scene folder {scene_folder} does not exist")
    folder = StateFolder(state) if state is not None else None
    if scene_folder is None and folder is not None:
        scene_folder = folder.scenes
    walls_ = Walls(limits.walls, folder)
    try:
        walls_.check_specs()  # a start with walls it cannot read is refused, in one line
    except InputError:
        folder.close()
        raise
    store = SceneStore(scene_folder, limits, in_use=walls_.scene_names)
    server = ServerState(store, walls_, Metrics(), token, limits, tuple(origins))
    metrics = server.metrics
    if nats:
        optional("nats", "nats", "--nats")  # refused now, not when the server starts
        server.bridge = NatsBridge(nats, walls_, metrics, check_prefix(nats_prefix))

    @asynccontextmanager
    async def lifespan(app):
        # the kernels (compiled once and cached: wallcull.warm) load in a worker thread while
        # the walls of the state folder come back and the server answers: a frame that needs
        # a kernel before it is loaded waits for it (numba's lock), and health answers within
        # seconds of a restart
        kernels = asyncio.ensure_future(background(warm.everything))
        kernels.add_done_callback(lambda done: _kernels_loaded(server, done))
        chores = [kernels]
        restored = await walls_.restore(store)
        if restored:
            log.info("restored %d wall(s): %s", len(restored), ", ".join(restored))
        await asyncio.to_thread(settled)
        if server.bridge is not None:
            await server.bridge.start()
        chores.append(asyncio.ensure_future(_keep(server, wall_ttl)))
        yield
        for chore in chores:
            chore.cancel()
        if server.bridge is not None:
            await server.bridge.close()
        if folder is not None:
            walls_.settle()
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

    @app.exception_handler(Unavailable)
    async def unavailable(request, exc: Unavailable):
        metrics.errors.labels("503").inc()
        return JSONResponse({"detail": str(exc)}, 503, {"Retry-After": str(RETRY_PERIOD)})

    @app.exception_handler(StateWriteFailed)
    async def unwritten(request, exc: StateWriteFailed):
        metrics.errors.labels(str(exc.status)).inc()
        return JSONResponse({"detail": str(exc)}, exc.status, {"Retry-After": "10"})

    @app.exception_handler(RequestValidationError)
    async def invalid(request, exc: RequestValidationError):
        metrics.errors.labels("422").inc()
        if pages.is_page(request):
            return pages.error_page(request, 422, refusal_detail(exc))
        return JSONResponse({"detail": refusal_detail(exc)}, 422)

    @app.get("/health", tags=["service"], operation_id="health")
    async def health():
        """``ok``, or ``degraded`` with the ``problems`` an operator should fix (the state
        folder cannot be written; the NATS broker is away; walls wait for their scenes).
        Frames are served either way, so the answer is 200. ``kernels``: ``loading`` for a
        second or two after a start (frames wait for them meanwhile), then ``ready``."""
        problems = []
        failure = folder.failure if folder is not None else None
        if failure:
            problems.append(failure)
        if server.bridge is not None and server.bridge.problem:
            problems.append(server.bridge.problem)
        for wid, (_, why) in server.walls.unavailable.items():
            problems.append(f"wall {wid} is unavailable: {why}")
        metrics.state_failing.set(failure is not None)
        metrics.unavailable.set(len(server.walls.unavailable))
        return {"status": "degraded" if problems else "ok",
                "kernels": "ready" if server.kernels_ready else "loading",
                "walls": len(server.walls.sessions),
                "walls_unavailable": sorted(server.walls.unavailable),
                "scenes_loaded": sorted(server.store.cache), "problems": problems[:20]}

    @app.get("/asyncapi.json", tags=["service"], operation_id="asyncapi")
    async def streams_document():
        """The AsyncAPI document of the streams: WebSocket and NATS messages."""
        return asyncapi.document(app.version)

    @app.get("/metrics", tags=["service"], response_class=Response, operation_id="metrics",
             responses={200: {"description": "Prometheus text format",
                              "content": {"text/plain": {}}}})
    async def prometheus():
        metrics.state_failing.set(folder is not None and folder.failure is not None)
        metrics.unavailable.set(len(server.walls.unavailable))
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    for module in (scenes, walls, streams, pages):
        app.include_router(module.router)
    return app


def _document(app: FastAPI, secured: bool) -> dict:
    app.openapi_schema = openapi.document(app, secured)
    return app.openapi_schema


def _kernels_loaded(server: ServerState, done: asyncio.Future) -> None:
    server.kernels_ready = True
    if not done.cancelled() and done.exception() is not None:  # frames compile them instead
        log.warning("loading the kernels ahead of frames failed: %r", done.exception())


#: Seconds between two tries at the walls waiting for their scenes, and between two looks
#: for walls idle longer than ``--wall-ttl``.
RETRY_PERIOD = 5


async def _keep(server: ServerState, wall_ttl: float | None) -> None:
    """Chores while the server runs: bring back walls whose scenes came back, delete walls
    idle longer than ``wall_ttl`` seconds (no frame posted, no stream open), and remove the
    spooled bodies of uploads that will never end (:meth:`SceneStore.sweep`)."""
    period = RETRY_PERIOD if not wall_ttl else min(RETRY_PERIOD, max(wall_ttl / 4, 0.1))
    unwritten = None  # the state folder's last failure a chore met (said once)
    sweep = 0.0  # when to look for uploads' spools next (once a minute is soon enough)
    while True:
        await asyncio.sleep(period)
        try:
            if server.walls.state is not None:
                server.walls.state.check()  # moved or deleted under the server: health says
            if time.monotonic() >= sweep:
                sweep = time.monotonic() + 60
                swept = await background(server.store.sweep)
                if swept:
                    log.info("removed the spooled bodies of uploads that ended with no "
                             "answer: %s", ", ".join(swept))
            if server.walls.unavailable:
                restored = await server.walls.retry(server.store)
                if restored:
                    log.info("wall(s) back with their scenes: %s", ", ".join(restored))
            if wall_ttl:
                for wid in server.walls.idle(wall_ttl):
                    try:
                        server.walls.delete(wid)
                    except StateWriteFailed as exc:  # health says why; tried again later
                        if str(exc) != unwritten:
                            log.warning("an idle wall is kept: %s", exc)
                        unwritten = str(exc)
                        continue
                    server.metrics.expired.inc()
                    log.info("wall %s deleted: idle for over %g s (--wall-ttl)", wid, wall_ttl)
        except Exception:  # noqa: BLE001 - a chore that fails now is tried again later
            log.exception("a background chore failed; trying again in %g s", period)


def settings_from_env(environ=os.environ) -> dict:
    """``create_app`` keywords from the environment: ``WALLCULL_SCENES``, ``WALLCULL_TOKEN``,
    ``WALLCULL_STATE`` (a folder; ``none`` keeps walls in memory only; default
    :func:`wallcull.persist.default_folder`), ``WALLCULL_LIMITS`` (``NAME=VALUE,...``),
    ``WALLCULL_CORS_ORIGINS`` (comma-separated), ``WALLCULL_NATS``,
    ``WALLCULL_NATS_PREFIX`` and ``WALLCULL_WALL_TTL`` (seconds); ``WALLCULL_THREADS`` is
    checked (:func:`wallcull.workers.count`), and ``WALLCULL_CACHE`` must be a folder if it
    exists."""
    state = environ.get("WALLCULL_STATE") or str(default_folder())
    kernel_threads(environ)  # WALLCULL_THREADS, named at start rather than in every frame
    cache = environ.get("WALLCULL_CACHE")
    if cache and Path(cache).exists() and not Path(cache).is_dir():
        raise InputError(f"WALLCULL_CACHE {cache} is not a folder: the prepared scenes go "
                         "there")
    token = environ.get("WALLCULL_TOKEN")
    if token is not None and not token.strip():
        raise InputError("WALLCULL_TOKEN is set but empty: unset it for a server anyone may "
                         "use")
    try:
        limits = Limits().with_text(environ.get("WALLCULL_LIMITS", ""))
    except InputError as exc:
        raise InputError(f"WALLCULL_LIMITS: {exc}") from None
    return {"scene_folder": environ.get("WALLCULL_SCENES") or None,
            "token": token,
            "state": None if state.lower() == "none" else state,
            "limits": limits,
            "origins": tuple(o.strip() for o in environ.get("WALLCULL_CORS_ORIGINS", "").split(",")
                             if o.strip()),
            "nats": environ.get("WALLCULL_NATS") or None,
            "nats_prefix": check_prefix(environ.get("WALLCULL_NATS_PREFIX") or "wallcull"),
            "wall_ttl": seconds_setting(environ.get("WALLCULL_WALL_TTL"), "WALLCULL_WALL_TTL")}


def seconds_setting(text: str | None, what: str) -> float | None:
    """A positive number of seconds, or None for nothing (or ``0``, ``off``)."""
    if not text or text.strip().lower() in ("0", "off", "none"):
        return None
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{what} must be a number of seconds, got {text!r}") from None
    if not 0 < value < float("inf"):
        raise InputError(f"{what} must be a positive number of seconds, got {text!r}")
    return value


def make_app_from_env() -> FastAPI:
    """For ``uvicorn wallcull.server:make_app_from_env --factory`` (Docker and friends)."""
    heap.tune()
    redact.install()  # no credential in uvicorn's logs, the access log included
    return create_app(**settings_from_env())


def uvicorn_options(app: FastAPI, tls=None) -> dict:
    """What :func:`serve` runs uvicorn with besides the address and the logs: the protocols
    of :mod:`.guard` (connections capped, header deadlines, refusals that are no errors; with
    ``tls``, an ``ssl.SSLContext``, TLS served by the guard, each handshake counted and on
    the header's deadline) and the largest WebSocket message."""
    from .guard import Refusals, protocol

    limits = app.state.server.limits
    return {"http": protocol(limits, tls), "ws": Refusals,
            "ws_max_size": max(limits.body, limits.message_bytes)}


def serve(host: str = "127.0.0.1", port: int = 8000, log_level: str = "info",
          tls: tuple[str, str | None] | None = None, **settings) -> None:
    """Run the server (``settings``: :func:`create_app` keywords) with
    :func:`uvicorn_options`; over TLS with ``tls``, ``(certificate, key)`` files (PEM; the key
    None when the certificate's file holds it)."""
    import ssl

    import uvicorn
    from uvicorn.main import STARTUP_FAILURE

    heap.tune()
    redact.install()
    app = create_app(**settings)
    context = None
    if tls is not None:  # served by the guard's protocol, not by uvicorn (:mod:`.guard`)
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        context.load_cert_chain(*tls)

    class Server(uvicorn.Server):
        def _log_started_message(self, listeners) -> None:
            self.config.ssl = context  # "running on https://..." when it does
            try:
                super()._log_started_message(listeners)
            finally:
                self.config.ssl = None

    config = uvicorn.Config(app, host=host, port=port, log_level=log_level, access_log=False,
                            **uvicorn_options(app, context))
    server = Server(config)
    try:
        server.run()
    except KeyboardInterrupt:
        pass
    if not server.started:  # as uvicorn.run: the port was taken, the app failed to start
        sys.exit(STARTUP_FAILURE)
