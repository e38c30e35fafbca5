"""HTTP plumbing shared by the routes: content negotiation, the body codec middleware, refusals."""

from __future__ import annotations

import base64
import json
from typing import Any

from fastapi import Request
from fastapi.responses import JSONResponse, Response

from .. import protocol
from ..errors import InputError
from .metrics import Metrics


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

    def __init__(self, app, max_body: int, max_upload: int, metrics: Metrics | None = None):
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


class Refused(Exception):
    """A refusal with a status and a one-line detail (401, 403, ...)."""

    def __init__(self, status: int, detail: str):
        self.status, self.detail = status, detail


def status_handler(status: int, metrics: Metrics):
    """An exception handler answering ``status`` with the exception's message as ``detail``."""
    async def handle(request, exc):
        metrics.errors.labels(str(status)).inc()
        return JSONResponse({"detail": str(exc)}, status)
    return handle


def mesh_reply(request: Request, blob) -> Response:
    """A mesh, or 304 when the client's ETag matches."""
    headers = {"ETag": blob.etag, "Cache-Control": "public, max-age=31536000, immutable"}
    if request.headers.get("if-none-match") == blob.etag:
        return Response(status_code=304, headers=headers)
    return reply(request, blob.body, headers=headers)
