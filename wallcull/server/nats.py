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

Several nodes may take the same subject (two machines mirroring the same tiles): each names
itself in its acknowledgements and full requests (``{"ack": n, "node": "a1b2"}``; a node that
does not is one nameless subscriber), and a delta is against a frame every subscriber holds:
the oldest acknowledgement of those that acknowledged within the window, if that frame was
published on the subject (a newcomer's full lists may be a frame the others never got: it is
a base only while the nodes that got it are the only ones listening), and no
base published before it and no full lists answered since are newer (a node drops the frames
before each delta's base, and holds none from before its full lists; a slow node that left the
window takes the deltas meant for the others in order, so it comes back holding only frames
from their bases on); else the message has full lists.

Access control on a broker is the broker's (accounts and subject permissions); the server's
own tokens guard its HTTP and WebSocket API.
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections import deque
from dataclasses import dataclass, field

import msgpack
import numpy as np

from ..credentials import shown
from ..errors import InputError, optional
from ..service import Gone, NotFound, Unavailable, WallSession, Walls
from .messages import control
from .metrics import Metrics

log = logging.getLogger("wallcull")

#: Frames published to a node without an acknowledgement before it is skipped.
WINDOW = 8
#: Subscribers one node subject keeps track of (their names come from the network).
MAX_SUBSCRIBERS = 32
#: A prefix of subjects: tokens of letters, digits, ``_`` and ``-``, joined by dots (no
#: wildcard, no space, no empty token), short enough to leave room for the rest.
PREFIX = re.compile(r"^[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*$")
MAX_PREFIX = 64


def check_prefix(prefix: str) -> str:
    """``prefix``, or :class:`InputError` if it is no prefix of NATS subjects."""
    if not (PREFIX.match(prefix) and len(prefix) <= MAX_PREFIX):
        raise InputError(f"NATS prefix {prefix!r} must be tokens of letters, digits, '_' and "
                         f"'-' joined by dots, at most {MAX_PREFIX} characters (no '*', '>' "
                         "or spaces: a wildcard would take other servers' subjects)")
    return prefix


@dataclass
class _Subscriber:
    """One node on a subject: the newest frame it acknowledged, the first it holds."""

    acked: int = -1
    since: int = -1


@dataclass
class _Node:
    """A node subject of a wall: its tiles, the newest frame published, its subscribers."""

    subject: str
    tiles: np.ndarray
    sent: int = -1
    subscribers: dict = field(default_factory=dict)  # name (or None) -> _Subscriber
    #: no base may be older: every subscriber, forgotten ones too (a slow node is not a dead
    #: one), dropped the frames before the newest base published, and one answered full lists
    #: holds none from before them
    floor: int = -1
    #: the newest frames published on the subject: the only ones every subscriber received
    published: deque = field(default_factory=lambda: deque(maxlen=WINDOW))
    #: the newest full lists answered, and to whom: a base too while only they listen
    answered: int = -1
    holders: set = field(default_factory=set)
    #: a subscriber left the window: it may still listen (slow, not dead) and hold less
    left: bool = False
    #: frames still published in full to no one known: after the broker came back, when the
    #: nodes subscribe again (what was published meanwhile went to nobody)
    fresh: int = 0

    def base(self) -> tuple[bool, int | None]:
        """Whether to publish the next frame, and the base every subscriber holds (None: full
        lists). Subscribers silent for the window are forgotten."""
        low = self.sent - WINDOW + 1
        live = {k: v for k, v in self.subscribers.items() if self.sent < 0
                or max(v.acked, v.since) >= low}
        self.left |= len(live) < len(self.subscribers)
        self.subscribers = live
        if not live:
            return self.sent < 0 or self.fresh > 0, None
        oldest = min(v.acked for v in live.values())
        held = oldest in self.published or (oldest == self.answered and not self.left
                                             and live.keys() <= self.holders)
        return True, oldest if oldest >= self.floor and held else None

    def sent_frame(self, number: int, base: int | None) -> None:
        """Frame ``number`` was published on the subject, a delta against ``base``."""
        self.sent = number
        self.published.append(number)
        self.fresh = max(self.fresh - 1, 0)
        if base is not None:
            self.floor = max(self.floor, base)

    def lost(self) -> None:
        """The broker went away and came back: what was published meanwhile reached no one,
        and whoever listens now holds nothing this subject can count on. Full lists, to
        whoever subscribes, for a window's frames."""
        self.subscribers, self.holders, self.published = {}, set(), deque(maxlen=WINDOW)
        self.floor, self.left, self.fresh = max(self.floor, self.sent + 1), True, WINDOW

    def take(self, name, ack: int | None = None, since: int | None = None) -> None:
        """An acknowledgement (``ack``) or a full request answered with frame ``since``."""
        if since is not None:
            self.floor = max(self.floor, since)
            if since != self.answered:
                self.answered, self.holders = since, set()
            if len(self.holders) < MAX_SUBSCRIBERS:
                self.holders.add(name)
        found = self.subscribers.get(name)
        if found is None:
            if len(self.subscribers) >= MAX_SUBSCRIBERS:
                return
            found = self.subscribers[name] = _Subscriber(since=ack if since is None else since)
        if since is not None:
            found.acked, found.since = -1, since
        if ack is not None and ack > found.acked:
            found.acked = ack


async def _connect(url: str, timeout: float, reconnect: bool, **callbacks):
    """A connection to the broker at ``url``, or :class:`InputError` after ``timeout``
    seconds (a broker named but unreachable is a configuration error). ``reconnect``: once
    connected, reconnect for as long as it takes when the broker goes away."""
    nats = optional("nats", "nats", "--nats")
    failed: list = []

    async def quiet(exc):  # nats-py prints each failed attempt's traceback otherwise
        failed.append(exc)
        log.debug("NATS %s: %r", shown(url), exc)

    try:
        return await asyncio.wait_for(nats.connect(
            url, name="wallcull", connect_timeout=timeout, allow_reconnect=reconnect,
            max_reconnect_attempts=-1 if reconnect else 0, reconnect_time_wait=0.5,
            error_cb=quiet, **callbacks), timeout)
    except Exception as exc:  # nats raises its own errors, and OSError, for an absent broker
        if isinstance(exc, asyncio.TimeoutError):
            exc = failed[-1] if failed else "no answer"
        why = exc if isinstance(exc, str) else str(exc) or type(exc).__name__
        raise InputError(f"cannot reach the NATS broker at {shown(url)} within {timeout:g} s: "
                         f"{why}") from None


def check_broker(url: str, timeout: float = 10.0) -> None:
    """Connect to the broker at ``url`` and leave: :class:`InputError` if it cannot be
    reached (``wallcull serve --nats`` asks before it starts)."""
    async def probe():
        nc = await _connect(url, timeout, reconnect=False)
        await nc.close()

    asyncio.run(probe())


class NatsBridge:
    """The server's NATS connection: one publisher task per wall, two subscriptions."""

    def __init__(self, url: str, walls: Walls, metrics: Metrics, prefix: str = "wallcull"):
        self.url, self.walls, self.metrics, self.prefix = url, walls, metrics, prefix
        self.nc = None
        self.tasks: dict[str, asyncio.Task] = {}
        self.nodes: dict[tuple[str, str], _Node] = {}  # (wall, first tile) -> its node

    async def start(self, timeout: float = 10.0) -> None:
        """Connect (failing after ``timeout`` seconds: a broker named but unreachable is a
        configuration error), subscribe, and publish every wall held, now and as they come."""
        self.nc = await _connect(self.url, timeout, reconnect=True,
                                 disconnected_cb=self._away, reconnected_cb=self._back)
        await self.nc.subscribe(f"{self.prefix}.*.ack.*", cb=self._ack)
        await self.nc.subscribe(f"{self.prefix}.*.full.*", cb=self._full)
        for session in list(self.walls.sessions.values()):
            self.watch(session)
        self.walls.on_add.append(self.watch)
        log.info("publishing node messages on NATS %s (subjects %s.<wall>.node.<tile>)",
                 shown(self.url), self.prefix)

    @property
    def problem(self) -> str | None:
        """Why the bridge is not publishing (health shows it), or None."""
        if self.nc is not None and not self.nc.is_connected:
            return f"the NATS broker at {shown(self.url)} is away: reconnecting"
        return None

    async def _away(self) -> None:
        log.warning("the NATS broker at %s went away: reconnecting", shown(self.url))

    async def _back(self) -> None:
        log.info("the NATS broker at %s is back: full lists to every node", shown(self.url))
        for node in self.nodes.values():
            node.lost()

    async def close(self) -> None:
        if self.watch in self.walls.on_add:
            self.walls.on_add.remove(self.watch)
        for task in self.tasks.values():
            task.cancel()
        await asyncio.gather(*self.tasks.values(), return_exceptions=True)
        if self.nc is not None:
            try:  # a broker that is away cannot be drained: the stop goes on without it
                await asyncio.wait_for(self.nc.drain(), 5)
            except Exception as exc:  # noqa: BLE001 - nats-py raises its own, or a timeout
                log.warning("NATS %s not drained at the stop: %r", self.url, exc)
                await self.nc.close()

    def watch(self, session: WallSession) -> None:
        """Publish this wall's frames from now on (until it is deleted)."""
        if session.id not in self.tasks:
            self.tasks[session.id] = asyncio.create_task(self._publish(session))

    def subject(self, wid: str, kind: str, first: int) -> str:
        return f"{self.prefix}.{wid}.{kind}.{first}"

    async def _publish(self, session: WallSession) -> None:
        nodes = []
        for tiles in session.nodes:
            node = _Node(self.subject(session.id, "node", tiles[0]), np.asarray(tiles, np.int64))
            self.nodes[session.id, str(tiles[0])] = node
            nodes.append(node)
        last = -1
        refused: dict[str, str] = {}  # subject -> why its last publish failed (said once)
        try:
            while not session.closed:
                number = await session.next_frame(last)
                for node in nodes:
                    publish, base = node.base()
                    if not publish:
                        continue  # no subscriber acknowledged any of the last WINDOW frames
                    data, delta = session.node_message(node.tiles, number, full=base is None,
                                                       held=base)
                    try:
                        await self.nc.publish(node.subject, data)
                    except Exception as exc:  # noqa: BLE001 - nats-py's own: too large, a
                        # full buffer, a closed connection; this node misses this frame
                        self.metrics.errors.labels("nats").inc()
                        if str(exc) != refused.get(node.subject):
                            log.warning("NATS: frame %d not published on %s (%d bytes): %s",
                                        number, node.subject, len(data),
                                        str(exc) or type(exc).__name__)
                        refused[node.subject] = str(exc)
                        continue
                    refused.pop(node.subject, None)
                    self.metrics.packet(delta, len(data), "nats")
                    node.sent_frame(number, base if delta else None)
                last = number
        except NotFound:
            pass  # the wall was deleted
        finally:
            self.tasks.pop(session.id, None)
            for node in nodes:
                self.nodes.pop((session.id, str(node.tiles[0])), None)

    def _node(self, subject: str) -> tuple[WallSession, _Node]:
        """The wall and the node a subject names (``PREFIX.W.kind.T``)."""
        parts = subject.split(".")
        wid, first = parts[-3], parts[-1]
        session = self.walls.get(wid)
        node = self.nodes.get((wid, first))
        if node is None:
            raise NotFound(f"wall {wid} has no node of first tile {first}")
        return session, node

    async def _ack(self, msg) -> None:
        try:
            session, node = self._node(msg.subject)
            number, _, name = control(msgpack.unpackb(msg.data))
            if number is None:
                raise InputError("an acknowledgement needs ack")
            session.ack(node.tiles, number)
            node.take(name, ack=number)
        except Exception as exc:  # noqa: BLE001 - counted; it must not stop the subscription
            self.metrics.errors.labels("nats").inc()
            log.debug("NATS ack on %s refused: %r", msg.subject, exc)

    async def _full(self, msg) -> None:
        parts = msg.subject.split(".")
        if len(parts) < 3 or parts[-3] not in self.walls.sessions and \
                parts[-3] not in self.walls.unavailable:
            return  # not a wall of this server: another on the broker may hold it
        try:
            session, node = self._node(msg.subject)
            if session.latest < 0:
                raise NotFound("no frame yet")
            # empty, or {"node": name}
            name = control(msgpack.unpackb(msg.data))[2] if msg.data else None
            number = session.latest
            data, _ = session.node_message(node.tiles, number, full=True)
            node.take(name, since=number)
            self.metrics.packet(False, len(data), "nats")
        except (NotFound, Gone, Unavailable, InputError, ValueError,
                msgpack.UnpackException) as exc:
            data = msgpack.packb({"error": str(exc) or type(exc).__name__})
        if msg.reply:
            await msg.respond(data)
