"""Connections before they are requests: a cap below the file-descriptor limit, and a deadline
for a request's header.

uvicorn accepts every connection and waits for its header as long as the client likes: 1,100
connections that each send half a header hold every file descriptor of a server with the
common limit of 1,024, and then nothing else gets in, not even a health check. This
protocol (uvicorn's httptools protocol, with two additions) bounds both:

* a request's header must be complete within ``limits.header_seconds`` of its first byte
  (or of the connection, for the first request); else the connection is closed;
* at most :func:`connection_cap` connections are open at once (``limits.connections``, and
  always below the process's file-descriptor limit, which is raised to its hard limit first).
  When one more arrives, the connection that has been waiting longest for its header is closed
  to make room: a server under a slow-header flood keeps taking new clients, and a connection
  whose request is complete (a stream, a long poll, an upload) is never dropped for one. When
  every connection has a complete request, the new one is closed at once.

Behind a reverse proxy (nginx, HAProxy, Caddy), the proxy's own header timeouts and connection
limits do this job as well; docs/hardening.md says how.

The WebSocket protocol (:class:`Refusals`, uvicorn's own) counts a refused handshake, an HTTP
response in place of the upgrade (404, 422, 429, ...), as done: uvicorn logged every refusal
at ERROR level as an application that never completed its handshake.
"""

from __future__ import annotations

import resource
from collections import OrderedDict

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from ..limits import Limits

#: File descriptors kept for everything but client connections: the state database, scene
#: and prepared files, child processes' pipes, the NATS connection, logs.
RESERVED_FDS = 64


def connection_cap(limits: Limits) -> int:
    """Client connections at most: ``limits.connections``, below the descriptor limit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and soft < hard:
        try:  # the soft limit is a default, not a choice: take what the system allows
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (ValueError, OSError):
            pass
    room = soft - max(RESERVED_FDS, soft // 8) if soft != resource.RLIM_INFINITY else \
        limits.connections
    return max(16, min(limits.connections, room))


def protocol(limits: Limits) -> type:
    """uvicorn's ``http`` protocol class for these limits (see the module docstring)."""
    cap = connection_cap(limits)
    waiting: OrderedDict = OrderedDict()  # connections without a complete header, oldest first

    class Guarded(HttpToolsProtocol):
        max_connections = cap
        _deadline = None

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            if len(self.connections) > cap:
                if not waiting:  # every connection is doing work: this one waits for none
                    transport.abort()
                    return
                oldest, _ = waiting.popitem(last=False)
                oldest._give_up()
            self._wait_for_header()

        def on_message_begin(self) -> None:
            super().on_message_begin()
            self._wait_for_header()

        def on_headers_complete(self) -> None:
            self._header_done()
            super().on_headers_complete()

        def connection_lost(self, exc) -> None:
            self._header_done()
            super().connection_lost(exc)

        def _wait_for_header(self) -> None:
            if self._deadline is None:
                waiting[self] = None
                self._deadline = self.loop.call_later(limits.header_seconds, self._give_up)

        def _header_done(self) -> None:
            waiting.pop(self, None)
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None

        def _give_up(self) -> None:
            self._header_done()
            if not self.transport.is_closing():
                self.transport.abort()

    return Guarded


class Refusals(WebSocketsSansIOProtocol):
    """uvicorn's WebSocket protocol, with the handshake complete once a refusal's response is
    sent (see the module docstring)."""

    async def send(self, message) -> None:
        await super().send(message)
        if message["type"] == "websocket.http.response.body" and not message.get("more_body"):
            self.handshake_complete = True
