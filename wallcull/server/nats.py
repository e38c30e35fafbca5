"""Scale-out through NATS: every frame's node messages published on a broker, acknowledgements
taken back from it (``wallcull serve --nats nats://HOST:PORT``).

The WebSocket streams stay the embedded default; with a broker, render nodes on any number of
machines subscribe there instead, and several culling servers (one per wall) share one NATS
cluster: subjects are named after the wall. With ``PREFIX`` the ``--nats-prefix`` (default
``wallcull``), a wall ``W`` and a node named after its first tile ``T`` (the wall's ``nodes``,
as ``GET /walls/{wid}`` lists them: one node credential each)::

    PREFIX.W.node.T   the server publishes the node's message of every frame (msgpack,
                      wallcull.protocol's node message): deltas against what it acknowledged
    PREFIX.W.ack.T    the node publishes {"ack": n} once it has drawn frame n
    PREFIX.W.full.T   a request: the reply is the newest frame's message with full lists

A node that joins, or that holds no longer the base of a delta it gets, asks for full lists
(request/reply), draws them, acknowledges, and takes the deltas from then on. A node that has
not acknowledged any of the last ``WINDOW`` frames published to it is published nothing more
(as a WebSocket stream is) until it acknowledges or asks again: a dead node costs nothing.

Access control on a broker is the broker's (accounts and subject permissions); the server's
own tokens guard its HTTP and WebSocket API.
"""

from __future__ import annotations

import asyncio
import logging

import msgpack
import numpy as np

from ..errors import InputError, optional
from ..service import Gone, NotFound, WallSession, Walls
from .metrics import Metrics

log = logging.getLogger("wallcull")

#: Frames published to a node without an acknowledgement before it is skipped.
WINDOW = 8


class NatsBridge:
    """The server's NATS connection: one publisher task per wall, two subscriptions."""

    def __init__(self, url: str, walls: Walls, metrics: Metrics, prefix: str = "wallcull"):
        self.url, self.walls, self.metrics, self.prefix = url, walls, metrics, prefix
        self.nc = None
        self.tasks: dict[str, asyncio.Task] = {}

    async def start(self, timeout: float = 10.0) -> None:
        """Connect (failing after ``timeout`` seconds: a broker named but unreachable is a
        configuration error), subscribe, and publish every wall already held."""
        nats = optional("nats", "nats", "--nats")
        try:
            self.nc = await nats.connect(self.url, name="wallcull", connect_timeout=timeout,
                                         max_reconnect_attempts=-1, reconnect_time_wait=0.5,
                                         allow_reconnect=True)
        except Exception as exc:  # nats raises its own errors, and OSError, for an absent broker
            raise RuntimeError(f"cannot reach the NATS broker at {self.url}: {exc!r}") from None
        await self.nc.subscribe(f"{self.prefix}.*.ack.*", cb=self._ack)
        await self.nc.subscribe(f"{self.prefix}.*.full.*", cb=self._full)
        for session in list(self.walls.sessions.values()):
            self.watch(session)
        log.info("publishing node messages on NATS %s (subjects %s.<wall>.node.<tile>)",
                 self.url, self.prefix)

    async def close(self) -> None:
        for task in self.tasks.values():
            task.cancel()
        await asyncio.gather(*self.tasks.values(), return_exceptions=True)
        if self.nc is not None:
            await self.nc.drain()

    def watch(self, session: WallSession) -> None:
        """Publish this wall's frames from now on (until it is deleted)."""
        self.tasks[session.id] = asyncio.create_task(self._publish(session))

    def subject(self, wid: str, kind: str, first: int) -> str:
        return f"{self.prefix}.{wid}.{kind}.{first}"

    async def _publish(self, session: WallSession) -> None:
        nodes = [(self.subject(session.id, "node", tiles[0]), np.asarray(tiles, np.int64))
                 for tiles in session.nodes]
        sent = [-1] * len(nodes)  # the newest frame published to each node
        last = -1
        try:
            while not session.closed:
                number = await session.next_frame(last)
                for k, (subject, tiles) in enumerate(nodes):
                    if sent[k] >= 0 and session.acks[tiles].min() < sent[k] - WINDOW + 1:
                        continue  # none of the last WINDOW frames it was sent acknowledged
                    data, delta = session.node_message(tiles, number)
                    await self.nc.publish(subject, data)
                    self.metrics.packet(delta, len(data), "nats")
                    sent[k] = number
                last = number
        except NotFound:
            pass  # the wall was deleted
        except Exception:
            log.exception("NATS publisher of wall %s stopped", session.id)
            raise
        finally:
            self.tasks.pop(session.id, None)

    def _node(self, subject: str) -> tuple[WallSession, np.ndarray]:
        """The wall and the node's tiles a subject names (``PREFIX.W.kind.T``)."""
        parts = subject.split(".")
        wid, first = parts[-3], parts[-1]
        session = self.walls.get(wid)
        for tiles in session.nodes:
            if str(tiles[0]) == first:
                return session, np.asarray(tiles, np.int64)
        raise NotFound(f"wall {wid} has no node of first tile {first}")

    async def _ack(self, msg) -> None:
        try:
            session, tiles = self._node(msg.subject)
            number = msgpack.unpackb(msg.data).get("ack")
            if not isinstance(number, int) or isinstance(number, bool):
                raise InputError("ack must be a frame number")
            session.ack(tiles, number)
        except Exception as exc:  # noqa: BLE001 - counted; it must not stop the subscription
            self.metrics.errors.labels("nats").inc()
            log.debug("NATS ack on %s refused: %r", msg.subject, exc)

    async def _full(self, msg) -> None:
        try:
            session, tiles = self._node(msg.subject)
            if session.latest < 0:
                raise NotFound("no frame yet")
            data, _ = session.node_message(tiles, session.latest, full=True)
            self.metrics.packet(False, len(data), "nats")
        except (NotFound, Gone) as exc:
            data = msgpack.packb({"error": str(exc)})
        if msg.reply:
            await msg.respond(data)
