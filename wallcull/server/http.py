"""HTTP plumbing shared by the routes: content negotiation, bodies decoded and validated off the
event loop, large answers encoded off it, refusals."""

from __future__ import annotations

import asyncio
import base64
import json
import time
from collections.abc import Sequence
from typing import Any, Callable

import msgpack
import numpy as np
from fastapi import Depends, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import ValidationError

from .. import protocol
from ..documents import problems
from ..workers import background
from ..errors import InputError
from .metrics import Metrics
from .models import PATTERN_WORDS

#: Bodies up to this size are decoded on the event loop; larger ones in a worker thread.
INLINE_BODY = 16 << 10
#: Lists longer than this are encoded piece by piece (each piece a short C call, so that the
#: worker thread lets go of the GIL between them and the event loop keeps running).
PIECE = 4096
#: msgpack can nest deeper than anything the schema describes; refused beyond this.
MAX_DEPTH = 32


def reply(request: Request, payload: Any, status: int = 200, headers=None) -> Response:
    """``payload`` as msgpack when the client accepts it, else JSON (bytes as base64)."""
    if protocol.wants_msgpack(request.headers.get("accept")):
        return Response(protocol.encode(payload, True), status, headers,
                        media_type=protocol.MSGPACK)
    return Response(json.dumps(payload, default=_b64, separators=(",", ":")), status, headers,
                    media_type=protocol.JSON)


async def reply_large(request: Request, build: Callable[[], Any], status: int = 200
                      ) -> Response:
    """:func:`reply` with ``build()`` and its encoding done in a worker thread, in pieces."""
    binary = protocol.wants_msgpack(request.headers.get("accept"))
    body = await background(lambda: encode_in_pieces(build(), binary))
    return Response(body, status, media_type=protocol.MSGPACK if binary else protocol.JSON)


def encode_in_pieces(obj: Any, binary: bool) -> bytes:
    """The bytes :func:`reply` would send for ``obj``, long lists encoded a piece at a time;
    numpy arrays (rows) are encoded as the nested lists ``tolist`` would give, a piece of
    rows at a time (a float's NaN as null: "none"), and other sequences (rows made when read)
    as lists."""
    parts: list[bytes] = []
    _encode_into(parts, obj, binary)
    return b"".join(parts)


def _encode_into(parts: list, value: Any, binary: bool) -> None:
    """:func:`encode_in_pieces`, appending to ``parts``. A function of the module, not one
    nested in it: a nested function that calls itself is a reference cycle, which kept every
    answer's pieces (a 256 x 256 wall's console status: 1.4 MB, four a second) until the
    garbage collector's next full pass."""
    if isinstance(value, dict):
        parts.append(_msgpack_header(len(value), map_=True) if binary else b"{")
        for k, (key, item) in enumerate(value.items()):
            if binary:
                parts.append(msgpack.packb(key, use_bin_type=True))
            else:
                parts.append((b"," if k else b"") + json.dumps(key).encode() + b":")
            _encode_into(parts, item, binary)
        if not binary:
            parts.append(b"}")
    elif isinstance(value, (np.ndarray, Sequence)) and not isinstance(value, (str, bytes)) \
            and len(value) > PIECE:
        parts.append(_msgpack_header(len(value)) if binary else b"[")
        for k in range(0, len(value), PIECE):
            piece = value[k:k + PIECE]
            piece = _rows(piece) if isinstance(piece, np.ndarray) else piece
            if binary:
                encoded = msgpack.packb(piece, use_bin_type=True)
                parts.append(encoded[len(_msgpack_header(len(piece))):])
            else:
                parts.append((b"," if k else b"") + json.dumps(
                    piece, default=_b64, separators=(",", ":"))[1:-1].encode())
        if not binary:
            parts.append(b"]")
    elif isinstance(value, np.ndarray):
        _encode_into(parts, _rows(value), binary)
    elif isinstance(value, Sequence) and not isinstance(value, (str, bytes, list, tuple)):
        _encode_into(parts, list(value), binary)  # rows made when read (credentials.Shown)
    elif binary:
        parts.append(msgpack.packb(value, use_bin_type=True))
    else:
        parts.append(json.dumps(value, default=_b64, separators=(",", ":")).encode())


def _rows(array) -> list:
    """``array.tolist()``, with None for a float's NaN (JSON has no NaN)."""
    rows = array.tolist()
    if array.dtype.kind == "f" and array.ndim == 1 and np.isnan(array).any():
        rows = [None if x != x else x for x in rows]
    return rows


def _msgpack_header(n: int, map_: bool = False) -> bytes:
    packer = msgpack.Packer()
    return packer.pack_map_header(n) if map_ else packer.pack_array_header(n)


def _b64(value):
    if isinstance(value, (bytes, bytearray)):
        return base64.b64encode(value).decode()
    raise TypeError(f"cannot encode {type(value).__name__}")


# --------------------------------------------------------------------------- request bodies


def body_of(model) -> Any:
    """A route parameter: the request body (JSON, or msgpack by ``Content-Type``) validated
    as ``model`` (its ``from_body`` when it has one), off the event loop when it is large.
    The OpenAPI document gets the model's schema from :mod:`.openapi`."""

    async def parse(request: Request):
        raw = await request.body()
        ctype = request.headers.get("content-type", protocol.JSON).split(";")[0].strip().lower()
        if len(raw) <= INLINE_BODY:
            return decode_body(model, raw, ctype)
        return await asyncio.to_thread(decode_body, model, raw, ctype)

    parse.body_model = model
    return Depends(parse)


def decode_body(model, raw: bytes, ctype: str):
    if ctype in (protocol.MSGPACK, "application/x-msgpack"):
        try:
            data = protocol.decode(raw, True)
        except InputError as exc:
            raise Refused(400, str(exc)) from None
        _json_like(data)
    elif ctype in (protocol.JSON, "", "*/*") or ctype.endswith("+json"):
        try:
            data = json.loads(raw)
        except (ValueError, RecursionError) as exc:
            raise RequestValidationError([{"loc": ("body",), "type": "json_invalid",
                                           "msg": f"JSON decode error: {exc}"[:300]}]) from None
    else:
        raise Refused(415, f"a body is JSON or msgpack (application/msgpack), not {ctype!r}")
    try:
        return model.from_body(data) if hasattr(model, "from_body") else \
            model.model_validate(data)
    except ValidationError as exc:
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])}
                                      for e in exc.errors()]) from None


def decode_message(raw: bytes | None, text: str | None, limit: int) -> Any:
    """A WebSocket message (msgpack ``raw`` bytes or JSON ``text``) of at most ``limit``
    bytes, with the depth limit of request bodies: an :class:`InputError` otherwise."""
    data = raw if raw is not None else (text or "").encode()
    if len(data) > limit:
        raise InputError(f"a message may have at most {limit} bytes, this one has {len(data)}")
    value = protocol.decode(data, raw is not None)
    try:
        _json_like(value)
    except Refused as exc:
        raise InputError(exc.detail.replace("msgpack body", "message")) from None
    return value


class Budget:
    """``rate`` units a second (messages, bytes), in bursts of as many: :meth:`spend` sleeps
    while the budget is overdrawn. A stream that sends faster than its budget of messages is
    read more slowly, so that its socket fills and the client's own sends block; streams that
    share a budget of bytes are sent to less often. Either way the cost to the server stays
    within ``rate`` a second, and other connections keep theirs."""

    def __init__(self, rate: float):
        self.rate, self.level, self.at = rate, rate, time.monotonic()

    async def spend(self, amount: float = 1) -> None:
        now = time.monotonic()
        self.level = min(self.rate, self.level + (now - self.at) * self.rate) - amount
        self.at = now
        if self.level < 0:
            await asyncio.sleep(-self.level / self.rate)


def _json_like(data: Any) -> None:
    """Refuse msgpack that JSON could not have said: bytes, or nesting deeper than
    ``MAX_DEPTH`` (walked without recursion: the input may be 1,000 levels deep)."""
    stack = [(data, 0)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, (bytes, bytearray)):
            raise Refused(400, "msgpack body holds values JSON cannot carry (bytes)")
        if isinstance(value, (dict, list)):
            if depth >= MAX_DEPTH:
                raise Refused(400, f"msgpack body nests deeper than {MAX_DEPTH} levels")
            items = value.items() if isinstance(value, dict) else enumerate(value)
            for k, v in items:
                if isinstance(k, (bytes, bytearray)):
                    raise Refused(400, "msgpack body holds values JSON cannot carry (bytes)")
                stack.append((v, depth + 1))


# --------------------------------------------------------------------------- refusals


class Refused(Exception):
    """A refusal with a status and a one-line detail (401, 403, ...)."""

    def __init__(self, status: int, detail: str, headers: dict | None = None):
        self.status, self.detail, self.headers = status, detail, headers


def refusal_detail(exc: RequestValidationError) -> str:
    """A validation error's one-line detail: where, and what."""
    detail = "; ".join(f"{'.'.join(map(str, e['loc']))}: {_said(e)}"
                       for e in problems(exc.errors()))
    return detail[:2000]


def _said(error: dict) -> str:
    words = PATTERN_WORDS.get((error.get("ctx") or {}).get("pattern"))
    if error["type"] != "string_pattern_mismatch" or words is None:
        return error["msg"]
    given = repr(error["input"])
    return f"{words}, got {given if len(given) <= 80 else given[:77] + '...'}"


def status_handler(status: int, metrics: Metrics):
    """An exception handler answering ``status`` with the exception's message as ``detail``."""
    async def handle(request, exc):
        metrics.errors.labels(str(status)).inc()
        return JSONResponse({"detail": str(exc)}, status)
    return handle


def mesh_reply(request: Request, blob) -> Response:
    """A mesh, or 304 when the client holds it: ``If-None-Match`` names its ETag (weakly, in
    a list: RFC 9110, section 13.1.2) or is ``*``. JSON and msgpack are two representations:
    each has its own ETag, and ``Vary: Accept`` keeps a cache from answering one for the
    other."""
    binary = protocol.wants_msgpack(request.headers.get("accept"))
    etag = blob.etag[:-1] + '-msgpack"' if binary else blob.etag
    headers = {"ETag": etag, "Cache-Control": "public, max-age=31536000, immutable",
               "Vary": "Accept"}
    if holds(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    return reply(request, blob.body, headers=headers)


def holds(if_none_match: str | None, etag: str) -> bool:
    if not if_none_match:
        return False
    tags = [t.strip() for t in if_none_match.split(",")]
    return "*" in tags or etag.removeprefix("W/") in (t.removeprefix("W/") for t in tags)
