"""Connections before they are requests: a cap below the file-descriptor limit, and a deadline
for a request's header.

uvicorn accepts every connection and waits for its header as long as the client likes: 1,100
connections that each send half a header hold every file descriptor of a server with the
common limit of 1,024, and then nothing else gets in, not even a health check. This
protocol (uvicorn's httptools protocol, with these additions) bounds both:

* a request's header must be complete within ``limits.header_seconds`` of its first byte
  (or of the connection's accept, for the first request, its TLS handshake included); else
  the connection is closed;
* at most :func:`connection_cap` connections are open at once (``limits.connections``, and
  always below the process's file-descriptor limit, which is raised to its hard limit first).
  When one more arrives, one makes room: the connection that has been waiting longest for its
  header (or its handshake), else the one kept alive longest between two requests, else the
  oldest long poll (:func:`long_poll`: the barrier, a packet's ``wait``), answered 503 with
  ``Retry-After``. A server under a slow-header flood, or under thousands of long polls of
  the open barrier route, keeps taking new clients; a stream, an upload or a request being
  worked on is never dropped for one. When nothing can make room, the new one is closed;
* with ``tls``, the guard serves TLS itself, with the loop's own TLS layer: the loop's
  ``create_server(ssl=...)`` hands a connection to the protocol only after its handshake, so
  connections in their handshake were outside the cap and held for asyncio's 60 s.

Behind a reverse proxy (nginx, HAProxy, Caddy), the proxy's own header timeouts and connection
limits do this job as well; docs/hardening.md says how.

The WebSocket protocol (:class:`Refusals`, uvicorn's own) counts a refused handshake, an HTTP
response in place of the upgrade (404, 422, 429, ...), as done: uvicorn logged every refusal
at ERROR level as an application that never completed its handshake.
"""

from __future__ import annotations

import asyncio
import resource
import ssl
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


def protocol(limits: Limits, tls: ssl.SSLContext | None = None) -> type:
    """uvicorn's ``http`` protocol class for these limits (see the module docstring); with
    ``tls``, it serves TLS itself (give uvicorn no certificate then)."""
    cap = connection_cap(limits)
    waiting: OrderedDict = OrderedDict()  # connections without a complete header, oldest first
    idle: OrderedDict = OrderedDict()  # connections kept alive between requests, oldest first
    polls: OrderedDict = OrderedDict()  # connections in a long poll, oldest first

    class Guarded(HttpToolsProtocol):
        max_connections = cap
        _deadline = None
        _accepted = None  # with TLS: the TCP transport, from the accept on

        def connection_made(self, transport) -> None:
            if tls is not None and self._accepted is None:
                # counted, and on the header's clock, from the accept: the handshake is part
                # of the first request's header (the loop's own handshake is invisible here,
                # and held a silent client for 60 s); the TLS layer is the loop's, made here,
                # and makes this connection again once its handshake is done
                self._accepted = transport
                self.connections.add(self)
                if self._room():
                    self._wait_for_header()
                    handshake = self.loop.create_future()
                    handshake.add_done_callback(self._handshake_done)
                    secure = _tls_protocol(self.loop)(
                        self.loop, self, tls, handshake, server_side=True,
                        ssl_handshake_timeout=limits.header_seconds)
                    transport.set_protocol(secure)
                    secure.connection_made(transport)
                return
            super().connection_made(transport)
            if tls is None and self._room():
                self._wait_for_header()

        def _handshake_done(self, handshake) -> None:
            if not handshake.cancelled():
                handshake.exception()  # seen (a connection closed in its handshake: None)
            if self.transport is None:  # never made for the app: the TLS layer closed it
                self._forget()

        def _room(self) -> bool:
            """Whether this new connection is taken: below the cap, or once the connection
            that has waited longest for its header, else the one idle longest between
            requests, else the oldest long poll (answered 503), makes room; else it is
            closed (every connection is doing work)."""
            if len(self.connections) <= cap:
                return True
            for queue in (waiting, idle):
                if queue:
                    oldest, _ = queue.popitem(last=False)
                    oldest._give_up()
                    return True
            if polls:
                _, evict = polls.popitem(last=False)
                evict()
                return True
            self.connections.discard(self)
            (self._accepted or self.transport).abort()
            return False

        def on_message_begin(self) -> None:
            idle.pop(self, None)
            super().on_message_begin()
            self._wait_for_header()

        def on_headers_complete(self) -> None:
            self._header_done()
            self.scope[LONG_POLL] = self._long_poll
            super().on_headers_complete()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing() and self.timeout_keep_alive_task is not None:
                idle[self] = None  # waits for a next request: the first to go for a new one

        def connection_lost(self, exc) -> None:
            self._forget()
            if self.transport is None:  # closed before its TLS handshake was done
                return
            super().connection_lost(exc)

        def shutdown(self) -> None:
            if self.transport is None:
                self._accepted.abort()
            else:
                super().shutdown()

        def _long_poll(self, evict) -> None:
            if evict is None:
                polls.pop(self, None)
            else:
                polls[self] = evict

        def _forget(self) -> None:
            self._header_done()
            idle.pop(self, None)
            polls.pop(self, None)
            self.connections.discard(self)

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
            idle.pop(self, None)
            transport = self.transport or self._accepted
            if not transport.is_closing():
                transport.abort()

    return Guarded


def _tls_protocol(loop) -> type:
    """The TLS layer the loop's own ``start_tls`` uses: uvloop's, else asyncio's."""
    if type(loop).__module__.startswith("uvloop"):
        from uvloop.loop import SSLProtocol
    else:
        from asyncio.sslproto import SSLProtocol
    return SSLProtocol


#: The key, in a request's scope on a guarded connection, of what :func:`long_poll` tells the
#: guard with.
LONG_POLL = "wallcull.long_poll"


async def long_poll(scope: dict, waiting):
    """``await waiting`` (a long poll's coroutine), unless the guard needs the connection
    for a new one first: then :class:`~.http.Refused` 503 with ``Retry-After`` and the
    connection closed. Anywhere but on a guarded connection, ``await waiting``."""
    tell = scope.get(LONG_POLL)
    if tell is None:
        return await waiting
    task = asyncio.current_task()
    evicted = []

    def evict() -> None:  # the guard's: room for a new connection (no task of its own)
        evicted.append(True)
        task.cancel()

    tell(evict)
    try:
        return await waiting
    except asyncio.CancelledError:
        if not evicted:
            raise
        getattr(task, "uncancel", lambda: None)()  # Python 3.11 counts cancellations
        from .http import Refused

        raise Refused(503, "the server is at its connection cap: this long poll made room for "
                      "a new connection; ask again", {"Retry-After": "1", "Connection": "close"}
                      ) from None
    finally:
        tell(None)


class Refusals(WebSocketsSansIOProtocol):
    """uvicorn's WebSocket protocol, with the handshake complete once a refusal's response is
    sent (see the module docstring)."""

    async def send(self, message) -> None:
        await super().send(message)
        if message["type"] == "websocket.http.response.body" and not message.get("more_body"):
            self.handshake_complete = True
