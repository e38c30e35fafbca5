"""The gate: ASGI middleware every request passes before a route sees it (behind CORS).

In this order, each step refusing with a status and a ``detail``, the way an attacker's
request costs least:

1. ``OPTIONS`` is answered here (204, ``Allow``), and a method the path does not take gets 405
   with ``Allow``; ``HEAD`` is the ``GET`` of the same path without its body (RFC 9110);
2. a WebSocket whose ``Origin`` is not allowed (``--cors-origin``; same-origin always is) is
   denied 403 before the handshake completes;
3. the caller's token is checked against the route's role (:mod:`.access`): 401 or 403,
   **before a byte of the body is read**; then a query parameter the route does not declare
   is refused (422), as an unknown key of a body is, and so is one given twice;
4. a body is capped (``Content-Length`` first, then as it arrives: 413) and must keep arriving
   (``limits.body_idle`` seconds between chunks, ``limits.body_seconds`` in all: 408).
   Uploads at once are capped by their route, once their name is known to be free (503).

The route reads the body itself, through the capped ``receive``; nothing is buffered here.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections import Counter
from urllib.parse import parse_qs, parse_qsl, urlsplit

from starlette.requests import Request
from starlette.routing import Match

from .access import bearer, check, leaf_routes, query_names, role_of
from .deps import ServerState
from .http import Refused
from .pages import error_page

BODY_METHODS = ("POST", "PUT", "PATCH", "DELETE")


class Gate:
    def __init__(self, app, state: ServerState):
        self.app, self.state = app, state

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        if scope["type"] == "http" and scope["method"] == "HEAD":
            scope, send = {**scope, "method": "GET"}, _without_body(send)
        try:
            admitted = self._admit(scope, receive)
        except Refused as exc:
            self.state.metrics.errors.labels(str(exc.status)).inc()
            route = _route(scope)[0]
            if scope["type"] == "http" and route is not None and \
                    getattr(route.endpoint, "wallcull_page", False):  # a page's refusal: a page
                page = error_page(Request(scope), exc.status, exc.detail)
                page.headers.update(exc.headers or {})
                return await page(scope, receive, send)
            return await refuse(scope, receive, send, exc)
        if isinstance(admitted, set):  # OPTIONS, answered here with the path's methods
            await send({"type": "http.response.start", "status": 204,
                        "headers": [(b"allow", _allow(admitted).encode())]})
            return await send({"type": "http.response.body", "body": b""})
        try:
            await self.app(scope, admitted, send)
        except Exception:
            # a bug, answered 500 by the server: counted, so that a soak sees every one
            self.state.metrics.errors.labels("500").inc()
            raise

    def _admit(self, scope, receive):
        """The ``receive`` of a request that may go on to its route, the path's
        methods for an ``OPTIONS`` to answer here; raises :class:`Refused` for the others."""
        route, params, methods = _route(scope)
        headers = _headers(scope)
        if scope["type"] == "websocket":
            if route is None:
                return receive  # the router refuses it
            origin = headers.get("origin")
            if origin is not None and not origin_allowed(origin, headers.get("host"),
                                                         self.state.origins):
                raise Refused(403, f"origin {origin!r} is not allowed (--cors-origin)")
            query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
            token = stream_token(query.get("token", []), headers.get("authorization"))
            if "tiles" in query:  # a node's stream: the tiles its credential must hold
                params = {**params, "tiles": query["tiles"][0]}
        else:
            if scope["method"] == "OPTIONS":
                if not methods:
                    raise Refused(404, "Not Found")
                return methods
            if route is None:
                if methods:
                    raise Refused(405, f"{scope['method']} is not a method of this path",
                                  {"Allow": _allow(methods)})
                return receive  # the router's 404
            token = bearer(headers.get("authorization"))
        check(self.state, role_of(route.endpoint), token, params)
        query = scope.get("query_string", b"")
        if query:  # the schema lists every parameter a route takes: no others, like bodies
            keys = Counter(k for k, _ in parse_qsl(query.decode("latin-1"),
                                                   keep_blank_values=True))
            unknown = set(keys) - query_names(route)
            if unknown:
                raise Refused(422, f"unknown query parameter(s): {', '.join(sorted(unknown))}")
            twice = sorted(k for k, n in keys.items() if n > 1)
            if twice:  # each takes one value: never whichever of two a parser keeps
                raise Refused(422, f"query parameter(s) given more than once: "
                                   f"{', '.join(twice)}")
        if scope["type"] == "websocket" or scope["method"] not in BODY_METHODS:
            return receive
        upload = getattr(route.endpoint, "wallcull_upload", False)
        limits = self.state.limits
        limit = limits.upload if upload else limits.body
        declared = headers.get("content-length")
        if declared is not None and (not (declared.isascii() and declared.isdigit())
                                     or int(declared) > limit):
            raise Refused(413, f"request body over {limit} bytes")
        return _capped(receive, limit, limits)


def stream_token(query: list[str], authorization: str | None) -> str | None:
    """The one credential a WebSocket handshake carries (``?token=`` or ``Authorization:
    Bearer``; a browser can only send the first). Two that disagree, an ``Authorization``
    that is not a bearer token, or ``token`` given twice are refused (401): a request is
    judged by one credential, never by whichever of two a check happens to read."""
    header = bearer(authorization) if authorization is not None else None
    if authorization is not None and header is None:
        raise Refused(401, "the Authorization header must be 'Bearer <token>'")
    if len(set(query)) > 1:
        raise Refused(401, "the query gives more than one token")
    if query and header is not None and query[0] != header:
        raise Refused(401, "the ?token= and the Authorization header carry different "
                           "credentials: send one")
    return query[0] if query else header


def _route(scope):
    """The route a request reaches, its path parameters, and the methods its path takes."""
    methods: set[str] = set()
    app = scope["app"]
    routes = app.__dict__.get("wallcull_routes")
    if routes is None:  # the routes are all in place by the first request
        routes = app.wallcull_routes = leaf_routes(app.router.routes)
    for route in routes:
        match, child = route.matches(scope)
        if match == Match.FULL:
            return route, child.get("path_params", {}), methods
        if match == Match.PARTIAL and getattr(route, "methods", None):
            methods |= route.methods
    return None, {}, methods


def _headers(scope) -> dict[str, str]:
    return {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"]}


def _allow(methods) -> str:
    """An ``Allow`` header: the path's methods, with ``HEAD`` where it takes ``GET`` and the
    ``OPTIONS`` the gate answers."""
    return ", ".join(sorted({*methods, "OPTIONS", *(("HEAD",) if "GET" in methods else ())}))


def _without_body(send):
    """``send`` for a ``HEAD``: the ``GET``'s status and headers (its ``Content-Length``
    included), no body."""
    async def headless(message):
        if message["type"] == "http.response.body":
            message = {**message, "body": b""}
        await send(message)

    return headless


def origin_allowed(origin: str, host: str | None, allowed) -> bool:
    """Whether a browser page from ``origin`` may open a stream: listed, ``*`` listed, or the
    page came from this server (same host and port)."""
    return "*" in allowed or origin in allowed or (host is not None and
                                                    urlsplit(origin).netloc == host)


def _capped(receive, limit: int, limits):
    """``receive`` for a body of at most ``limit`` bytes that keeps arriving."""
    deadline = time.monotonic() + limits.body_seconds
    state = {"size": 0, "done": False}

    async def capped():
        if state["done"]:  # the body is in: what follows is the disconnect
            return await receive()
        left = deadline - time.monotonic()
        try:
            message = await asyncio.wait_for(receive(), min(limits.body_idle, max(left, 0.0)))
        except asyncio.TimeoutError:
            raise Refused(408, f"the body did not arrive in time ({limits.body_idle:g} s without "
                               f"a byte, or {limits.body_seconds:g} s in all)") from None
        if message["type"] == "http.request":
            state["size"] += len(message.get("body", b""))
            if state["size"] > limit:
                raise Refused(413, f"request body over {limit} bytes")
            state["done"] = not message.get("more_body", False)
        return message

    return capped


async def refuse(scope, receive, send, exc: Refused) -> None:
    """Answer a refusal: JSON with a ``detail``; on a WebSocket, an HTTP denial of the
    handshake (or close code 1008 where the server cannot send one)."""
    body = json.dumps({"detail": exc.detail}).encode()
    headers = [(b"content-type", b"application/json"),
               (b"content-length", str(len(body)).encode())]
    headers += [(k.lower().encode(), v.encode()) for k, v in (exc.headers or {}).items()]
    if scope["type"] == "http":
        await send({"type": "http.response.start", "status": exc.status, "headers": headers})
        await send({"type": "http.response.body", "body": body})
        return
    message = await receive()  # websocket.connect
    if message["type"] != "websocket.connect":
        return
    if "websocket.http.response" in scope.get("extensions", {}):
        await send({"type": "websocket.http.response.start", "status": exc.status,
                    "headers": headers})
        await send({"type": "websocket.http.response.body", "body": body})
    else:
        await send({"type": "websocket.close", "code": 1008, "reason": exc.detail[:120]})
