"""Every bound a server puts on what clients may make it do, with defaults and one text form.

A wall server runs for days on a shared network: no request may make it hold unbounded memory,
time or sockets. Each bound here is checked where the work would start, and refused with a 4xx
(or a WebSocket denial) that names it. ``wallcull serve --limit NAME=VALUE`` (repeatable) and
``$WALLCULL_LIMITS`` (``NAME=VALUE,NAME=VALUE``) change them; sizes take ``K``/``M``/``G``
(powers of 1024), counts ``k``/``M`` (powers of 1000).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from .errors import InputError

KiB, MiB, GiB = 1 << 10, 1 << 20, 1 << 30


@dataclass(frozen=True)
class Limits:
    # request bodies
    body: int = 1 * MiB  #: bytes of a JSON or msgpack body
    upload: int = 64 * MiB  #: bytes of an uploaded GLB
    body_idle: float = 10.0  #: seconds a body may go without a byte arriving
    body_seconds: float = 120.0  #: seconds a whole body may take to arrive
    uploads: int = 2  #: uploads received and parsed at once; more wait for none (503)
    # what an uploaded scene may declare, checked before anything is allocated for it
    vertices: int = 8_000_000  #: vertices, counted once per node that draws them
    faces: int = 8_000_000  #: triangles, counted once per node that draws them
    nodes: int = 250_000  #: nodes of the file
    scene_bytes: int = 1 * GiB  #: bytes of every accessor's data, as declared
    # the child process an upload is parsed in
    parse_memory: int = 2 * GiB  #: address space it may add to what it starts with
    parse_seconds: float = 120.0  #: seconds before it is killed
    # scenes held in memory
    scene_cache: int = 2 * GiB  #: bytes of scenes kept loaded; walls' scenes always stay
    # connections (wallcull.server.guard)
    connections: int = 4096  #: connections at once (always below the file-descriptor limit)
    header_seconds: float = 10.0  #: seconds a request's header may take to arrive
    # walls and streams
    walls: int = 32  #: walls at once
    streams: int = 16384  #: WebSocket streams at once, in all
    streams_per_wall: int = 8192  #: ... on one wall
    streams_per_tile: int = 4  #: ... on one tile
    stream_idle: float = 30.0  #: seconds a stream may wait for an acknowledgement before it is closed
    messages: int = 200  #: WebSocket messages a connection may send per second (a burst of as many)
    message_bytes: int = 64 * KiB  #: bytes of a message on a node's stream (a frame stream's: ``body``)
    consoles: int = 32  #: console streams opened without a credential at once, on the whole server (those with one have 32 of their own)
    open_bytes: int = 4 * MiB  #: bytes per second the server sends to console streams opened without a credential, all together

    def with_text(self, text: str) -> "Limits":
        """These limits with ``NAME=VALUE[,NAME=VALUE...]`` applied."""
        out = self
        for item in filter(None, (part.strip() for part in text.split(","))):
            name, eq, value = item.partition("=")
            name = name.strip().replace("-", "_")
            kinds = {f.name: f.type for f in fields(self)}
            if not eq or name not in kinds:
                raise InputError(f"unknown limit {item!r}: use NAME=VALUE with NAME one of "
                                 f"{', '.join(kinds)}")
            out = replace(out, **{name: _value(name, value.strip(), kinds[name])})
        return out


_SIZE = {"k": 1 << 10, "m": 1 << 20, "g": 1 << 30}
_COUNT = {"k": 10 ** 3, "m": 10 ** 6}
_BYTES = {name for name in Limits.__dataclass_fields__ if name.endswith("_bytes")} | {
    "body", "upload", "parse_memory", "scene_cache"}


def _value(name: str, text: str, kind) -> int | float:
    scales = _SIZE if name in _BYTES else _COUNT
    scale = scales.get(text[-1:].lower(), 1) if text else 1
    number = text[:-1] if scale > 1 else text
    try:
        value = float(number) * scale
    except ValueError:
        raise InputError(f"limit {name}: {text!r} is not a number") from None
    if not value > 0 or value != value or value == float("inf"):
        raise InputError(f"limit {name} must be a positive number, got {text!r}")
    return float(value) if kind in (float, "float") else int(value)
