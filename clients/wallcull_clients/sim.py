"""Simulated render clients: one per tile, as asyncio tasks, pulling or streaming packets.

A :class:`TileClient` plays one render node of the wall. Every frame it

1. receives its tile's packet, over a WebSocket stream (``mode="ws"``; the server pushes the
   newest frame, conflating when the node is slow) or by long-polling ``GET .../packets/{n}``
   for every frame number in turn (``mode="pull"``);
2. rebuilds the frame's leaf list with :func:`wallcull.protocol.apply` from the list of the
   delta's base frame. The server bases a delta on the last frame the tile *acknowledged* that
   it has taken, which is older than the last one the node received while acks are in flight
   (by one or two frames normally, by many when the node or the server lags). So the node keeps
   the lists of every frame from the newest base it has seen on (older ones can never be bases
   again), at most ``keep`` (256) of them. A node missing a base asks for a full list
   (``GET ...?full=1``; a WebSocket node repairs the frame over HTTP and, when even that is
   gone, sends ``{"full": true}`` so its next packet is full);
3. "draws": makes sure every mesh its leaves use is in its cache (fetching the missing ones),
   then counts the triangles, or with ``renderer`` draws them with
   :class:`clients.render.TileRenderer` using the packet's view and projection (the back faces
   of the meshes the mesh route says are not ``double_sided`` culled, as glTF asks);
4. acknowledges the frame (``{"ack": n}`` on the stream, ``POST .../ack`` when pulling).

Geometry: the scene description (``GET /scenes/{name}?nodes=true``: every leaf's id, mesh key
and rest world transform) is fetched once per process and shared (:class:`SceneInfo`); each node
has its own :class:`MeshCache`, an LRU by bytes standing for GPU memory, in front of a host
copy. A mesh missing from the GPU cache that the host still holds is revalidated with
``If-None-Match`` (a scene can be replaced by an upload under the same name, so the ETag is what
makes the copy safe); a 304 costs a few bytes instead of the mesh.

Per packet a node records the receive time, the server's post time (``packet["time"]``: their
difference is the frame-to-tile latency; both are ``time.time()`` on the same clock when client
and server share a host), the bytes received, whether it was full or a delta, and the size the
same packet would have had as a full list (re-encoded exactly as the server would; for a
render node's message, on one frame in :data:`FULL_SIZE_EVERY`).

Each node sends its own credential (``--credentials FILE``: the wall's credentials as
``POST /walls`` answered them; or one ``--token`` for all). When the server goes away (a
restart) a node reconnects with backoff (:mod:`.retry`) to the same wall, and its new stream
starts from a full list; it fails with a message and a non-zero status when the server refuses
it for good (the wall was deleted, the credential is refused) or stays away longer than
``--reconnect-for`` seconds. It never exits silently.

Run a wall of them::

    python -m wallcull_clients.sim --server http://127.0.0.1:8000 --wall ID --tiles 0-63 --mode ws \
        --credentials credentials.json
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import secrets
import sys
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable
from urllib.parse import quote

import msgpack
import numpy as np

from wallcull import protocol
from wallcull.credentials import shown
from wallcull.errors import InputError
from wallcull.validate import parse_tiles, tiles_text

from .frusta import EYES
from .node import NodeState, full_size, sorted_ints_len
from .rawhttp import MSGPACK, Connection, HTTPError, run
from .retry import Backoff, ClientFailure, retrying, stop_on_signals

try:
    from asyncio import timeout as _timeout  # Python 3.11+
except ImportError:  # pragma: no cover - 3.10
    _timeout = None


#: Seconds a NATS node hears nothing before it asks for full lists again (a frame lost while
#: the broker was away, or a wall that is gone).
NATS_QUIET = 5.0


async def _next(source, timeout: float | None):
    """The next message of a WebSocket (``recv``) or a queue (``get``), or
    :class:`asyncio.TimeoutError` after ``timeout`` seconds (None: no limit). On Python 3.11 and
    later without a task per message, as ``wait_for`` makes (with a UUID, in nats-py's
    ``next_msg``): a few percent of a simulated node's CPU."""
    take = source.recv if hasattr(source, "recv") else source.get
    if timeout is None:
        return await take()
    if _timeout is None:  # Python 3.10
        return await asyncio.wait_for(take(), timeout)
    async with _timeout(timeout):
        return await take()


KEEP = 256  # at most this many lists of recent frames kept for delta bases (see _prune)
DEFAULT_CACHE = 256 << 20
#: A render node's message is sized as full lists on the frames whose number this divides (the
#: others record NaN there): worked out on every message, it was a seventh of the simulated
#: nodes' CPU, which on a 16 x 16 wall shares the server's two cores.
FULL_SIZE_EVERY = 8
#: ``--wall auto``: how long to wait for a wall with no frame yet (the one a driver has just
#: created and drives once its nodes stream) before taking the newest wall.
AUTO_GRACE = 30.0


# --------------------------------------------------------------------------- the scene


@dataclass
class SceneInfo:
    """What a render node needs to know of the scene: per node, its mesh and rest transform."""

    name: str
    keys: list[str]  # mesh keys, indexed by mesh number
    mesh_of: np.ndarray  # (n,) mesh number of each node, -1 where it carries none
    world: np.ndarray  # (n, 4, 4) rest world transforms
    leaves: np.ndarray  # leaf node ids

    @classmethod
    def from_description(cls, data: dict) -> "SceneInfo":
        nodes = data["nodes"]
        keys = sorted({k for k in nodes["mesh"] if k is not None})
        number = {k: i for i, k in enumerate(keys)}
        # rows leave the clusters out: a row's node id is its "id", ids run to "count"
        count = nodes.get("count", len(nodes["mesh"]))
        ids = np.asarray(nodes.get("id", range(len(nodes["mesh"]))), dtype=np.int64)
        mesh_of = np.full(count, -1, dtype=np.int64)
        mesh_of[ids] = [-1 if k is None else number[k] for k in nodes["mesh"]]
        world = np.zeros((count, 4, 4))
        world[ids] = np.asarray(nodes["world"], dtype=np.float64).reshape(-1, 4, 4)
        leaves = ids[np.asarray(nodes["leaf"], dtype=bool)]
        return cls(data["name"], keys, mesh_of, world, leaves)

    @classmethod
    async def fetch(cls, conn: Connection, name: str) -> "SceneInfo":
        return cls.from_description(await conn.call("GET", f"/scenes/{quote(name, safe='')}"
                                                           "?nodes=true"))


_scene_cache: dict[tuple[str, str], asyncio.Future] = {}


async def shared_scene(server: str, name: str) -> SceneInfo:
    """The scene description, fetched once per process and server however many nodes ask."""
    key = (server, name)
    if key not in _scene_cache:
        _scene_cache[key] = asyncio.ensure_future(_fetch_scene(server, name))
    try:
        return await asyncio.shield(_scene_cache[key])
    except Exception:
        _scene_cache.pop(key, None)
        raise


async def _fetch_scene(server: str, name: str) -> SceneInfo:
    async with Connection(server, timeout=120) as conn:
        return await SceneInfo.fetch(conn, name)


# --------------------------------------------------------------------------- geometry cache


@dataclass
class Mesh:
    key: str
    etag: str | None
    vertices: np.ndarray  # (v, 3) float32
    faces: np.ndarray  # (f, 3) uint32
    #: False: a single-sided glTF mesh, drawn with its back faces culled (the mesh route's
    #: ``double_sided``; a server that does not send it means both faces)
    double_sided: bool = True

    @property
    def nbytes(self) -> int:
        return self.vertices.nbytes + self.faces.nbytes

    @property
    def triangles(self) -> int:
        return len(self.faces)


def decode_mesh(body: dict, etag: str | None) -> Mesh:
    def array(part):
        data = part["data"]
        if isinstance(data, str):  # JSON carries bytes as base64
            import base64

            data = base64.b64decode(data)
        return np.frombuffer(data, dtype=part["dtype"]).reshape(part["shape"])

    return Mesh(body["mesh"], etag, array(body["vertices"]), array(body["faces"]),
                bool(body.get("double_sided", True)))


class MeshCache:
    """An LRU cache of meshes bounded by bytes (the node's GPU memory).

    ``put`` evicts least recently used meshes until the new one fits; a mesh larger than the
    whole budget still goes in (the node must draw it) and stays alone. ``on_evict(key)`` lets a
    renderer free the GPU copy.
    """

    def __init__(self, budget: int, on_evict: Callable[[str], None] | None = None):
        if budget < 0:
            raise ValueError(f"cache budget must be >= 0 bytes, got {budget}")
        self.budget = budget
        self.on_evict = on_evict
        self.entries: OrderedDict[str, Mesh] = OrderedDict()
        self.bytes = 0
        self.hits = self.misses = self.evictions = 0
        self.peak_bytes = 0

    def __contains__(self, key) -> bool:
        return key in self.entries

    def get(self, key: str) -> Mesh | None:
        mesh = self.entries.get(key)
        if mesh is None:
            self.misses += 1
            return None
        self.entries.move_to_end(key)
        self.hits += 1
        return mesh

    def put(self, mesh: Mesh) -> list[str]:
        """Insert (or replace) ``mesh``; returns the keys evicted to make room."""
        evicted = []
        old = self.entries.pop(mesh.key, None)
        if old is not None:
            self.bytes -= old.nbytes
        while self.entries and self.bytes + mesh.nbytes > self.budget:
            key, gone = self.entries.popitem(last=False)
            self.bytes -= gone.nbytes
            self.evictions += 1
            evicted.append(key)
            if self.on_evict:
                self.on_evict(key)
        self.entries[mesh.key] = mesh
        self.bytes += mesh.nbytes
        self.peak_bytes = max(self.peak_bytes, self.bytes)
        return evicted

    def stats(self) -> dict:
        return {"budget": self.budget, "bytes": self.bytes, "peak_bytes": self.peak_bytes,
                "meshes": len(self.entries), "hits": self.hits, "misses": self.misses,
                "evictions": self.evictions}


# --------------------------------------------------------------------------- one render node


@dataclass
class TileStats:
    """Per-packet records (parallel lists) and counters of one node."""

    tile: int
    frame: list[int] = field(default_factory=list)
    recv: list[float] = field(default_factory=list)  # time.time() when the packet arrived
    posted: list[float] = field(default_factory=list)  # packet["time"]: server time of the post
    full: list[bool] = field(default_factory=list)
    bytes: list[int] = field(default_factory=list)  # as received (after any WS inflation)
    full_bytes: list[int] = field(default_factory=list)  # the same packet as a full list
    list_bytes: list[int] = field(default_factory=list)  # encoded ids: visible, or added+removed
    full_list_bytes: list[int] = field(default_factory=list)  # encoded ids of the whole list
    fit_bytes: list[int] = field(default_factory=list)  # encoded view + projection
    leaves: list[int] = field(default_factory=list)
    triangles: list[int] = field(default_factory=list)
    base_misses: int = 0  # deltas whose base the node no longer held
    repairs: int = 0  # full packets fetched to repair a base miss
    errors: list[str] = field(default_factory=list)
    mesh_fetches: int = 0
    mesh_not_modified: int = 0
    mesh_bytes: int = 0
    acks: int = 0
    connects: int = 0  # streams opened (or pull loops started); more than one: reconnected
    acks_lost: int = 0  # acknowledgements the server could not take (it restarted meanwhile)

    def to_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items()}


def _packed_len(obj, binary: bool) -> int:
    return len(protocol.encode(obj, binary))


_ADDED, _REMOVED, _VISIBLE = (msgpack.packb(k) for k in ("added", "removed", "visible"))


def wire_ranges(parts: dict) -> list[list[int]]:
    """A tile's draw ranges as a full packet carries them (:mod:`wallcull.protocol`)."""
    return [[leaf, *r.ravel().tolist()] for leaf, r in sorted(parts.items())]


def _full_ranges_len(pkt: dict, parts: dict) -> int:
    """Bytes a delta packet's draw ranges would change by as a full packet: all of the tile's
    ranges in place of the delta's ``ranges`` and ``whole`` (msgpack, map header included)."""
    out, pairs = 0, len(pkt)
    for key in ("ranges", "whole"):
        if key in pkt:
            out -= len(msgpack.packb(key)) + len(msgpack.packb(pkt[key]))
            pairs -= 1
    if parts:
        out += len(msgpack.packb("ranges")) + len(msgpack.packb(wire_ranges(parts)))
        pairs += 1
    # the full packet's map: "visible" for "added" and "removed" (one pair fewer)
    return out + _map_header_len(pairs - 1) - _map_header_len(len(pkt))


def _map_header_len(pairs: int) -> int:
    return 1 if pairs < 16 else 3


def msgpack_ints_len(values) -> int:
    """Bytes of a list of ints >= 0 as msgpack encodes it, without encoding it: the header
    (fixarray / array16 / array32) plus 1, 2, 3, 5 or 9 bytes per value."""
    v = np.asarray(values, dtype=np.int64)
    n = len(v)
    head = 1 if n < 16 else 3 if n < 1 << 16 else 5
    if not n:
        return head
    if v.min() < 0:
        return len(msgpack.packb(v.tolist()))  # negative ints: not in our packets
    size = (1 + (v >= 128) + (v >= 256) + 2 * (v >= 1 << 16) + 4 * (v >= 1 << 32)).sum()
    return head + int(size)


class TileClient:
    """One simulated render node (see the module docstring).

    ``on_list(tile, frame, leaves)`` is called with every list the node rebuilds (tests compare
    them with the in-process culler); ``on_event(kind, tile, frame)`` with ``"ack"`` just before
    an acknowledgement is sent and ``"acked"`` once the server has taken it (pull mode).
    """

    def __init__(self, server: str, wall_id: str, tile: int, scene: SceneInfo, *,
                 mode: str = "ws", token: str | None = None, binary: bool = True,
                 cache_bytes: int = DEFAULT_CACHE, renderer=None, keep: int = KEEP,
                 measure_full: bool = True, wait: float = 5.0, draw_time: float = 0.0,
                 on_list: Callable | None = None, on_event: Callable | None = None,
                 reconnect_for: float = 60.0, prefetch: bool = False):
        if mode not in ("ws", "pull"):
            raise ValueError(f"mode must be ws or pull, got {mode!r}")
        self.server, self.wall_id, self.tile, self.scene = server.rstrip("/"), wall_id, tile, scene
        self.mode, self.token, self.binary = mode, token, binary
        self.renderers = {} if renderer is None else {tile: renderer}
        self.cache = MeshCache(cache_bytes, on_evict=self._evict)
        self.host: dict[str, Mesh] = {}  # host copies of every mesh fetched (see module doc)
        self.triangles_of = np.zeros(len(scene.keys), dtype=np.int64)
        self.keep = keep
        self.measure_full = measure_full
        self.wait = wait
        self.draw_time = draw_time
        self.prefetch = prefetch
        self.on_list, self.on_event = on_list, on_event
        self.lists: OrderedDict[int, np.ndarray] = OrderedDict()
        self.parts: dict[int, dict] = {}  # frame -> leaf -> draw ranges, beside self.lists
        self.world = scene.world  # copied on the first moved leaf
        self.stats = TileStats(tile)
        self.http = Connection(server, token)
        self.last_frame = -1
        self.images = {}  # the last frame drawn per tile (per eye: (tile, eye)), with a renderer
        self._counted = {}  # tile -> (its list, triangles, cache evictions) when last counted
        self.connected = asyncio.Event()
        self.idle_stop = False  # it stopped because no packet came for idle_timeout seconds
        self._ws = None
        self._accept = MSGPACK if binary else "application/json"
        self._base = f"/walls/{wall_id}/tiles/{tile}"
        self.backoff = Backoff(reconnect_for)  # how long a lost server is waited for

    def _evict(self, key: str) -> None:
        for renderer in self.renderers.values():
            renderer.evict(key)

    def records(self) -> list[dict]:
        """What the node recorded, one dict per tile (``--out``)."""
        return [{**self.stats.to_dict(), "cache": self.cache.stats(), "mode": self.mode}]

    # ------------------------------------------------------------------ packets

    async def receive(self, pkt: dict, size: int, recv: float) -> bool:
        """Take one packet: rebuild, record, draw, acknowledge. False when it had to be
        dropped (a delta with no base that could not be repaired)."""
        if "error" in pkt:
            self.stats.errors.append(str(pkt["error"]))
            return False
        number = pkt["frame"]
        base = pkt.get("base")
        held = None if base is None else self.lists.get(base)
        if base is not None and held is None:
            self.stats.base_misses += 1
            repaired = await self._repair(number)
            if repaired is None:
                return False
            pkt, size, recv = repaired
            self.stats.repairs += 1
        try:
            delta = pkt.get("base") is not None
            leaves = protocol.apply(held if delta else None, pkt)
            parts = protocol.apply_parts(self.parts.get(pkt.get("base")) if delta else None,
                                         pkt, leaves)
        except InputError as exc:
            self.stats.errors.append(f"frame {number}: {exc}")
            self.lists.clear()  # start over from a full list
            await self._ask_full()
            return False
        self.lists[number] = leaves
        self.parts[number] = parts
        self._prune(pkt.get("base"))
        self._record(pkt, leaves, parts, size, recv)
        if self.on_list is not None:
            self.on_list(self.tile, number, leaves)
        await self.draw(leaves, parts, pkt)
        await self.acknowledge(number)
        self.last_frame = number
        return True

    def _prune(self, base: int | None) -> None:
        """Drop the lists no future delta can be based on. A delta's base is the newest
        acknowledgement the server had taken when it made the packet, and those only grow, so
        lists older than the newest base seen are dead; newer ones may still be bases (their
        acks may be in flight). ``keep`` bounds the rest when acks lag very far behind."""
        if base is not None:
            while self.lists and next(iter(self.lists)) < base:
                self.parts.pop(self.lists.popitem(last=False)[0], None)
        while len(self.lists) > self.keep:
            self.parts.pop(self.lists.popitem(last=False)[0], None)

    def _record(self, pkt: dict, leaves: np.ndarray, parts: dict, size: int,
                recv: float) -> None:
        s = self.stats
        full = pkt.get("base") is None
        s.frame.append(pkt["frame"])
        s.recv.append(recv)
        s.posted.append(pkt["time"])
        s.full.append(full)
        s.bytes.append(size)
        s.leaves.append(len(leaves))
        if not self.measure_full:
            return
        if self.binary:  # exact msgpack arithmetic: cheap enough to do for every packet
            whole = sorted_ints_len(leaves)
            if full:
                s.full_bytes.append(size)
                s.list_bytes.append(whole)
            else:
                added, removed = sorted_ints_len(pkt["added"]), sorted_ints_len(pkt["removed"])
                s.full_bytes.append(size - (len(_ADDED) + added) - (len(_REMOVED) + removed)
                                    + len(_VISIBLE) + whole
                                    - sorted_ints_len([pkt["base"]]) + 1 + 1
                                    + _full_ranges_len(pkt, parts))
                s.list_bytes.append(added + removed)
        else:
            ids = leaves.tolist()
            whole = _packed_len(ids, False)
            if full:
                s.full_bytes.append(size)
                s.list_bytes.append(whole)
            else:
                as_full = {k: v for k, v in pkt.items()
                           if k not in ("added", "removed", "ranges", "whole")}
                as_full["base"] = None
                as_full["visible"] = ids
                if parts:
                    as_full["ranges"] = wire_ranges(parts)
                s.full_bytes.append(_packed_len(as_full, False))
                s.list_bytes.append(_packed_len(pkt["added"], False)
                                    + _packed_len(pkt["removed"], False))
        s.full_list_bytes.append(whole)
        s.fit_bytes.append(_packed_len({k: pkt[k] for k in FIT_KEYS if k in pkt},
                                       self.binary) - 1)  # less the map's own header

    async def _repair(self, number: int):
        """A full packet of frame ``number`` over HTTP, or None when it is gone."""
        try:
            r = await self.http.request("GET", f"{self._base}/packets/{number}?full=1&wait=0",
                                        accept=self._accept, auth=True)
        except (ConnectionError, OSError, asyncio.TimeoutError):
            r = None  # the server is restarting: the stream will reconnect and start full
        if r is None or r.status != 200:
            await self._ask_full()
            return None
        return r.data(), len(r.body), time.time()

    async def _ask_full(self) -> None:
        if self._ws is not None:
            await self._ws.send(protocol.encode({"full": True}, self.binary)
                                if self.binary else json.dumps({"full": True}))

    # ------------------------------------------------------------------ drawing

    async def draw(self, leaves: np.ndarray, parts: dict, pkt: dict) -> int:
        """Make sure every mesh is cached, then count (or render) the triangles."""
        self.move(pkt.get("transforms"))
        triangles = await self.draw_tile(self.tile, self.stats, leaves, parts, pkt)
        if self.draw_time:  # a GPU busy for this long: the node's own time, not the process's
            await asyncio.sleep(self.draw_time)
        return triangles

    def move(self, transforms: dict | None) -> None:
        """Take the world transforms of moved leaves (a packet's or a message's)."""
        if not transforms:
            return
        if self.world is self.scene.world:
            self.world = self.scene.world.copy()
        self.world[np.asarray(transforms["ids"], dtype=np.int64)] = np.asarray(
            transforms["matrices"], dtype=np.float64).reshape(-1, 4, 4)

    async def draw_tile(self, tile: int, stats: TileStats, leaves: np.ndarray, parts: dict,
                        matrices: dict) -> int:
        """One tile's list: its meshes cached (fetched once per node), its triangles counted
        (a leaf drawn in part: its ranges'), and drawn when the tile has a renderer, with the
        ``view`` and ``projection`` of ``matrices`` (a stereo tile's: each eye's). A list a
        node message left as it was (the same arrays), with nothing evicted since, has its
        meshes and its count."""
        renderer = self.renderers.get(tile)
        counted = self._counted.get(tile)
        if counted is None or counted[0] is not leaves or counted[1] is not parts \
                or counted[3] != self.cache.evictions:
            mesh_of = self.scene.mesh_of
            uses = np.bincount(mesh_of[leaves], minlength=len(self.scene.keys))
            for m in np.flatnonzero(uses).tolist():
                if self.cache.get(self.scene.keys[m]) is None:
                    await self.fetch_mesh(m)
            triangles = int(uses @ self.triangles_of) - sum(
                int(self.triangles_of[mesh_of[leaf]]) - int(r[:, 1].sum())
                for leaf, r in parts.items())
            counted = self._counted[tile] = (leaves, parts, triangles, self.cache.evictions)
        stats.triangles.append(counted[2])
        if renderer is not None:
            keys = self.scene.keys
            draws = [(keys[m], self.world[leaf], leaf + 1, parts.get(leaf))
                     for leaf, m in zip(leaves.tolist(), self.scene.mesh_of[leaves].tolist())]
            for eye in [e for e in EYES if e in matrices] or [None]:
                m = matrices if eye is None else matrices[eye]
                self.images[tile if eye is None else (tile, eye)] = renderer.render(
                    draws, np.asarray(m["view"]), np.asarray(m["projection"]))
        return counted[2]

    @property
    def image(self):
        """The last frame drawn of this client's tile, with a renderer (clients.render.Image;
        of a stereo frame, ``images[tile, eye]``)."""
        return self.images.get(self.tile)

    async def fetch_mesh(self, number: int) -> Mesh:
        key = self.scene.keys[number]
        held = self.host.get(key)
        headers = {"if-none-match": held.etag} if held is not None and held.etag else None
        r = await retrying(lambda: self.http.request(
            "GET", f"/scenes/{quote(self.scene.name, safe='')}/meshes/{quote(key, safe='')}",
            accept=self._accept, headers=headers), self.backoff, f"mesh {key}")
        if r.status == 304 and held is not None:
            self.stats.mesh_not_modified += 1
            mesh = held
        elif r.status == 200:
            self.stats.mesh_fetches += 1
            self.stats.mesh_bytes += len(r.body)
            mesh = decode_mesh(r.data(), r.headers.get("etag"))
            self.host[key] = mesh
        else:
            raise HTTPError(r.status, r.detail(), "GET", f"mesh {key}")
        self.cache.put(mesh)
        self.triangles_of[number] = mesh.triangles
        for renderer in self.renderers.values():
            renderer.upload(key, mesh.vertices, mesh.faces, single_sided=not mesh.double_sided)
        return mesh

    # ------------------------------------------------------------------ acknowledging

    async def acknowledge(self, number: int) -> None:
        if self.on_event is not None:
            self.on_event("ack", self.tile, number)
        if self._ws is not None:
            await self._ws.send(protocol.encode({"ack": number}, self.binary)
                                if self.binary else json.dumps({"ack": number}))
        else:
            try:
                await retrying(lambda: self.http.call("POST", f"{self._base}/ack",
                                                      {"frame": number}, auth=True),
                               self.backoff, f"acknowledging frame {number}")
            except HTTPError as exc:
                if exc.status != 409:
                    raise
                self.stats.acks_lost += 1  # a frame from before a restart: nothing to ack
                return
            if self.on_event is not None:
                self.on_event("acked", self.tile, number)
        self.stats.acks += 1

    # ------------------------------------------------------------------ the loops

    async def run(self, until: int | None = None, idle_timeout: float | None = None,
                  start: int | str = 0) -> TileStats:
        """Receive packets until frame ``until`` has been taken, or nothing came for
        ``idle_timeout`` seconds (after a first packet), or the task is cancelled."""
        try:
            if self.prefetch:  # as a render PC loads its scene before it joins the wall
                for number in range(len(self.scene.keys)):
                    if self.cache.get(self.scene.keys[number]) is None:
                        await self.fetch_mesh(number)
            if self.mode == "ws":
                await self._run_ws(until, idle_timeout)
            else:
                await self._run_pull(until, idle_timeout, start)
        finally:
            await self.http.close()
        return self.stats

    def _done(self, until) -> bool:
        return until is not None and self.last_frame >= until

    async def _run_ws(self, until, idle_timeout) -> None:
        """Stream, reconnecting with backoff whenever the stream breaks (a server restart, a
        closed idle stream); fail with :class:`ClientFailure` when the server refuses the
        stream for good (wall deleted, credential refused) or stays away too long."""
        from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

        while True:
            try:
                if await self._stream(until, idle_timeout):
                    return
                reason = "the stream ended"
            except ConnectionClosed as exc:
                code = exc.rcvd.code if exc.rcvd is not None else None
                if code == 4404:
                    raise ClientFailure(f"tile {self.tile}: wall {self.wall_id} was deleted"
                                        ) from None
                reason = f"the stream closed (code {code})"
            except InvalidStatus as exc:
                status, body = exc.response.status_code, exc.response.body or b""
                detail = body.decode(errors="replace")[:300]
                if status in (401, 404):  # its wall gone (a credential forgotten with it)?
                    await self._check_wall()
                if status not in (429, 500, 502, 503, 504):
                    raise ClientFailure(f"tile {self.tile}: the server refused the stream: "
                                        f"HTTP {status}: {detail}") from None
                reason = f"HTTP {status}: {detail}"
            except (OSError, asyncio.TimeoutError, InvalidHandshake) as exc:
                reason = repr(exc)
            await self.backoff.wait(f"tile {self.tile}: {reason}")

    def stream_url(self, path: str | None = None, query: str = "") -> str:
        query += f"{'&' if query else ''}format={'msgpack' if self.binary else 'json'}"
        if self.token:
            query += f"&token={quote(self.token, safe='')}"
        return f"ws{self.server[len('http'):]}{path or self._base + '/stream'}?{query}"

    async def _stream(self, until, idle_timeout) -> bool:
        """One stream, until frame ``until`` or ``idle_timeout`` (True: done)."""
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed

        async with connect(self.stream_url(), max_size=None, compression=None,
                           open_timeout=10) as ws:
            self._ws = ws
            self.stats.connects += 1
            self.backoff.reset()
            self.connected.set()
            try:
                while not self._done(until):
                    timeout = idle_timeout if self.last_frame >= 0 else None
                    try:
                        message = await _next(ws, timeout)
                    except asyncio.TimeoutError:
                        self.idle_stop = True
                        return True
                    recv = time.time()
                    data = message if isinstance(message, bytes) else message.encode()
                    pkt = protocol.decode(data, self.binary)
                    await self.receive(pkt, len(data), recv)
                return True
            except ConnectionClosed as exc:
                if exc.rcvd is not None and exc.rcvd.code == 1000 and self._done(until):
                    return True
                raise
            finally:
                self._ws = None

    async def _run_pull(self, until, idle_timeout, start) -> None:
        number = None if start == "latest" else int(start)
        self.connected.set()
        self.stats.connects += 1
        idle_since = time.monotonic()
        while not self._done(until):
            target = "latest" if number is None else str(number)
            try:
                r = await self.http.request("GET", f"{self._base}/packets/{target}"
                                                   f"?wait={self.wait:g}", accept=self._accept,
                                            auth=True)
            except (ConnectionError, OSError, asyncio.TimeoutError) as exc:
                await self.backoff.wait(f"tile {self.tile}: GET packet {target}: {exc!r}")
                idle_since = time.monotonic()
                continue
            recv = time.time()
            self.backoff.reset()
            if r.status == 200:
                pkt = r.data()
                await self.receive(pkt, len(r.body), recv)
                number = pkt["frame"] + 1
                idle_since = time.monotonic()
            elif r.status == 404 and r.detail().startswith(("frame", "no frame")):
                if (idle_timeout is not None and self.last_frame >= 0
                        and time.monotonic() - idle_since > idle_timeout):
                    self.idle_stop = True
                    return
            elif r.status in (410, 404) and r.detail().startswith(("frame", "there is no")):
                number = None  # fell out of the history, or a number never posted: the newest
            elif r.status in (401, 403, 404):
                if r.status != 403:  # its wall gone (a credential forgotten with it)?
                    await self._check_wall()
                raise ClientFailure(f"tile {self.tile}: GET packet {target}: HTTP {r.status}: "
                                    f"{r.detail()}")
            else:
                self.stats.errors.append(f"GET packet {target}: HTTP {r.status}: {r.detail()}")
                await asyncio.sleep(0.05)

    async def _check_wall(self) -> None:
        """ClientFailure if the server says the wall is gone (:meth:`.rawhttp.Connection.
        wall_deleted`; its NATS subjects are answered by no one too)."""
        if await self.http.wall_deleted(self.wall_id):
            raise ClientFailure(f"tile {self.tile}: wall {self.wall_id} was deleted")


# --------------------------------------------------------------------------- a node of tiles


class NodeClient(TileClient):
    """A render node driving several tiles over one connection: the node stream (one message
    per frame with all of its tiles, one acknowledgement: :mod:`wallcull.protocol`). Its tiles
    share one mesh cache (one GPU); each may have its own renderer (one output each). A
    message with a delta against a frame it no longer holds makes it ask for full lists
    (``{"full": true}``) and wait for them. Stats are kept per tile, as the tile clients keep
    them; each tile's ``bytes`` is its share of the message."""

    def __init__(self, server: str, wall_id: str, tiles: list[int], scene: SceneInfo, *,
                 renderers: dict | None = None, nats: str | None = None,
                 nats_prefix: str = "wallcull", **kwargs):
        super().__init__(server, wall_id, min(tiles), scene, **kwargs)
        self.tiles = sorted(tiles)
        self.tile_stats = {t: TileStats(t) for t in self.tiles}
        self.stats = self.tile_stats[self.tiles[0]]
        self.renderers = dict(renderers or {})
        self.node = NodeState(self.keep)
        self.nats, self.nats_prefix = nats, nats_prefix
        self._nc = None  # the NATS connection, with nats
        self._wants_full = False
        # its name in acknowledgements and full requests over NATS: other nodes may take the
        # same subject, and each gets deltas against what all of them hold
        self.name = secrets.token_hex(4)
        # the messages taken, once each (a tile's records hold one entry a tile)
        self.messages = {"frame": [], "full": []}

    def records(self) -> list[dict]:
        cache = self.cache.stats()
        return [{**self.tile_stats[t].to_dict(), "cache": cache if t == self.tile else {},
                 "mode": "node", **({"messages": self.messages} if t == self.tile else {})}
                for t in self.tiles]

    def stream_url(self, path: str | None = None, query: str = "") -> str:
        return super().stream_url(f"/walls/{self.wall_id}/nodes/stream",
                                  "tiles=" + tiles_text(self.tiles))

    async def receive(self, message: dict, size: int, recv: float) -> bool:
        """Take one node message: rebuild, record, draw every tile, acknowledge once."""
        if "error" in message:
            self.stats.errors.append(str(message["error"]))
            return False
        number = message["frame"]
        if number <= self.node.frame:
            return False  # published before the full lists it asked for: stale
        if not self.node.holds(message.get("base")):
            self.stats.base_misses += 1  # its base went (a reconnection): start over
            self.node.reset()
            await self._ask_full()
            return False
        try:
            frames = self.node.take(message)
        except InputError as exc:
            self.stats.errors.append(f"frame {number}: {exc}")
            self.node.reset()
            await self._ask_full()
            return False
        self.move(message.get("transforms"))
        self.messages["frame"].append(number)
        self.messages["full"].append(message.get("base") is None)
        whole = full_size(message, size, frames, self.node.frusta.held[number]) \
            if self.measure_full and self.binary and number % FULL_SIZE_EVERY == 0 else None
        for frame in frames:
            stats = self.tile_stats[frame.tile]
            self._record_tile(stats, message, frame, size, whole, recv)
            if self.on_list is not None:
                self.on_list(frame.tile, number, frame.leaves)
            await self.draw_tile(frame.tile, stats, frame.leaves, frame.ranges, frame.matrices)
        if self.draw_time:
            await asyncio.sleep(self.draw_time)
        await self.acknowledge(number)
        self.last_frame = number
        return True

    def _record_tile(self, s: TileStats, message: dict, frame, size: int, whole: int | None,
                     recv: float) -> None:
        share = len(self.tiles)
        entry = frame.entry
        s.frame.append(message["frame"])
        s.recv.append(recv)
        s.posted.append(message["time"])
        s.full.append("visible" in entry)
        s.bytes.append(size / share)
        s.leaves.append(len(frame.leaves))
        if not (self.measure_full and self.binary):
            return
        if whole is None:  # a frame not sampled (FULL_SIZE_EVERY)
            for column in (s.full_bytes, s.full_list_bytes, s.list_bytes, s.fit_bytes):
                column.append(math.nan)
            return
        listed = sorted_ints_len(frame.leaves)
        s.full_bytes.append(whole / share)
        s.full_list_bytes.append(listed)
        s.list_bytes.append(listed if "visible" in entry else
                            sum(sorted_ints_len(entry[k]) for k in ("added", "removed")
                                if k in entry))
        s.fit_bytes.append(sum(_packed_len(entry[k], True)
                               for k in ("view", "extent", "depth", "left", "right")
                               if k in entry))

    async def acknowledge(self, number: int) -> None:
        if self.on_event is not None:
            for tile in self.tiles:
                self.on_event("ack", tile, number)
        if self._nc is not None:
            await self._nc.publish(self.subject("ack"), msgpack.packb({"ack": number,
                                                                      "node": self.name}))
        else:
            await self._ws.send(protocol.encode({"ack": number}, self.binary)
                                if self.binary else json.dumps({"ack": number}))
        self.stats.acks += 1

    async def _ask_full(self) -> None:
        if self.nats:
            self._wants_full = True  # asked by the loop (request and reply)
        else:
            await super()._ask_full()

    # ------------------------------------------------------------------ over NATS

    def subject(self, kind: str) -> str:
        """This node's NATS subject of ``kind`` (node, ack, full: wallcull.server.nats)."""
        return f"{self.nats_prefix}.{self.wall_id}.{kind}.{self.tiles[0]}"

    async def run(self, until: int | None = None, idle_timeout: float | None = None,
                  start: int | str = 0) -> TileStats:
        if not self.nats:
            return await super().run(until, idle_timeout, start)
        try:
            await self._run_nats(until, idle_timeout)
        finally:
            await self.http.close()
        return self.stats

    async def _run_nats(self, until, idle_timeout) -> None:
        """Subscribe to the node's subject, ask for full lists, then take every message; the
        broker reconnects by itself (nats-py), and a node that loses its base, or is back
        with the broker, or hears nothing for ``NATS_QUIET`` seconds, asks again. A request
        nobody answers (no server holds the wall) is checked over HTTP: a deleted wall ends
        the node. One no server is subscribed for (none on the broker yet, or back after the
        broker's restart: "no responders") is asked again with backoff, for up to
        ``--reconnect-for`` seconds in a row."""
        import nats
        from nats.errors import NoRespondersError
        from nats.errors import TimeoutError as NatsTimeout

        inbox: asyncio.Queue = asyncio.Queue()

        async def arrived(msg) -> None:  # in order, from the subscription's own task
            inbox.put_nowait(msg)

        failed: list = []

        async def quiet(exc) -> None:  # nats-py prints every failed try's traceback otherwise
            failed.append(exc)

        async def back() -> None:  # what the server published meanwhile went to no one
            self._wants_full = True

        try:  # the first connection within --reconnect-for; later, for as long as it takes
            self._nc = await asyncio.wait_for(nats.connect(
                self.nats, name=f"wallcull-node-{self.wall_id}-{self.tiles[0]}",
                max_reconnect_attempts=-1, reconnect_time_wait=0.5, error_cb=quiet,
                reconnected_cb=back), self.backoff.give_up)
        except asyncio.TimeoutError:
            why = failed[-1] if failed else "no answer"
            raise ClientFailure(f"cannot reach the NATS broker at {shown(self.nats)} within "
                                f"{self.backoff.give_up:g} s: {why}") from None
        try:
            await self._nc.subscribe(self.subject("node"), cb=arrived)
            self.stats.connects += 1
            self.connected.set()
            self._wants_full = True
            unanswered, heard = 0, time.monotonic()
            while not self._done(until):
                if self._wants_full:
                    self._wants_full = False
                    try:
                        reply = await self._nc.request(
                            self.subject("full"), msgpack.packb({"node": self.name}), timeout=5)
                    except (NatsTimeout, NoRespondersError) as exc:
                        self._wants_full = True  # no server yet, or none holds the wall
                        unanswered += 1
                        if unanswered % 3 == 0:
                            await self._check_wall()
                        if isinstance(exc, NoRespondersError):  # answered at once: wait
                            await self.backoff.wait(f"tile {self.tile}: no culling server "
                                                    "on the NATS broker answers full requests")
                        continue
                    unanswered = 0
                    self.backoff.reset()
                    await self._take(reply.data)
                    continue
                wait = NATS_QUIET
                if idle_timeout and self.last_frame >= 0:  # idle for good after that long
                    wait = min(wait, heard + idle_timeout - time.monotonic())
                    if wait <= 0:
                        self.idle_stop = True
                        return
                try:
                    msg = await _next(inbox, wait)
                except asyncio.TimeoutError:
                    self._wants_full = True  # nothing for a while: a lost frame, or no wall
                    continue
                heard = time.monotonic()
                await self._take(msg.data)
        finally:
            nc, self._nc = self._nc, None
            leaving = asyncio.ensure_future(nc.drain())
            try:  # not cut short by the run's end (another node failed meanwhile): nats-py
                await asyncio.shield(leaving)  # printed its cancelled flush's tracebacks
            except asyncio.CancelledError:
                await leaving
                raise

    async def _take(self, data: bytes) -> None:
        recv = time.time()
        message = msgpack.unpackb(data)
        if "error" in message:  # a full request before any frame: ask again shortly
            await asyncio.sleep(0.1)
            self._wants_full = True
            return
        await self.receive(message, len(data), recv)


# --------------------------------------------------------------------------- a wall of them


#: A tile packet's fitted frusta: its view and projection, and a stereo tile's eyes' own.
FIT_KEYS = ("view", "projection", "left", "right")


async def find_wall(server: str, wall: str, timeout: float = 60.0) -> dict:
    """The info of wall ``wall``, waiting up to ``timeout`` seconds for the server. ``"auto"``
    waits for a wall, and takes the newest with no frame yet (the one a driver has just made
    and drives once its nodes stream: a wall left from an earlier run has frames), or after
    :data:`AUTO_GRACE` seconds the newest."""
    t0 = time.monotonic()
    reached, problem = False, None
    while True:
        try:
            async with Connection(server) as conn:
                if wall != "auto":
                    return await conn.call("GET", f"/walls/{wall}")
                walls = (await conn.call("GET", "/walls"))["walls"]
                reached = True
                fresh = [w for w in walls if w.get("latest", -1) < 0]
                if fresh or walls and time.monotonic() - t0 > AUTO_GRACE:
                    return (fresh or walls)[-1]
        except (ConnectionError, OSError) as exc:
            problem = exc  # the server is not up yet
        except HTTPError as exc:
            if exc.status == 404:
                raise ClientFailure(f"no wall {wall!r} on {server}") from None
            if exc.status not in (502, 503, 504):
                raise
            reached, problem = True, exc
        if time.monotonic() - t0 > timeout:
            if not reached:
                raise ClientFailure(f"cannot reach {server} within {timeout:g} s: {problem}")
            raise ClientFailure(f"no wall on {server} after {timeout:g} s")
        await asyncio.sleep(0.2)


def node_tokens(path: str) -> dict[int, str]:
    """Tile -> node credential, from a file holding a wall's credentials (see ``--credentials``)."""
    with open(path) as f:
        try:
            data = json.load(f)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"--credentials {path} is not JSON: {exc}") from None
    data = data.get("credentials", data) if isinstance(data, dict) else data
    try:
        return {int(t): str(node["token"]) for node in data["nodes"] for t in node["tiles"]}
    except (TypeError, KeyError, ValueError):
        raise ValueError(f"--credentials {path} holds no wall's credentials (POST /walls "
                         "answers them: {\"nodes\": [{\"tiles\": [...], \"token\": ...}]})"
                         ) from None


def make_renderers(tiles, wall: dict, size: tuple[int, int] | None):
    """A renderer for each tile: ``size``, else an eighth of the tile's resolution (a grid's
    tiles share the wall's; each screen of a screens wall has its own)."""
    from .render import TileRenderer

    def eighth(t: int) -> tuple[int, int]:
        w, h = wall["screens"][t].get("resolution", (1920, 1080)) if "screens" in wall \
            else wall["resolution"]
        return max(w // 8, 1), max(h // 8, 1)

    return {t: TileRenderer(*(size or eighth(t))) for t in tiles}


async def run_wall(server: str, wall: str, tiles: str | list[int] = "all", *, mode: str = "ws",
                   token: str | None = None, tokens: dict[int, str] | None = None,
                   binary: bool = True,
                   cache_bytes: int = DEFAULT_CACHE, render: bool = False,
                   render_size: tuple[int, int] | None = None, until: int | None = None,
                   idle_timeout: float | None = None, start: int | str = 0,
                   measure_full: bool = True, draw_time: float = 0.0, on_list=None,
                   on_event=None,
                   ready: Callable[[list[TileClient]], None] | None = None,
                   stop: asyncio.Event | None = None,
                   reconnect_for: float = 60.0, tiles_per_node: int = 1,
                   prefetch: bool = False,
                   nats: str | None = None, made: list | None = None) -> list[TileClient]:
    """Run the nodes of ``tiles`` on wall ``wall`` (an id, or ``"auto"``) until they stop
    (see :meth:`TileClient.run`) or ``stop`` is set; returns the clients with their stats.
    With ``tiles_per_node`` above 1, each node drives that many consecutive tiles over the
    node stream (:class:`NodeClient`); with ``nats`` (a broker's URL), the nodes are the
    wall's own (its ``nodes``) among ``tiles`` and take their messages from the broker. Each
    node sends ``tokens[tile]`` (its node credential, of its first tile) when given, else
    ``token``. ``made``: a list the clients are added to as soon as they exist, so that a
    caller still has what they recorded when the run ends on an error."""
    info = await find_wall(server, wall, reconnect_for)
    ids = parse_tiles(tiles, info["tiles"]) if isinstance(tiles, str) else list(tiles)
    bad = [t for t in ids if not 0 <= t < info["tiles"]]
    if bad:
        raise ValueError(f"wall {info['id']} has {info['tiles']} tiles; no tile {bad[0]}")
    scene = await shared_scene(server, info["scene"])
    renderers = make_renderers(ids, info["wall"], render_size) if render else {}
    common = dict(mode=mode, binary=binary, cache_bytes=cache_bytes, measure_full=measure_full,
                  draw_time=draw_time, on_list=on_list, on_event=on_event,
                  reconnect_for=reconnect_for, prefetch=prefetch)
    if tiles_per_node > 1 or nats:
        if mode != "ws":
            raise ValueError("nodes of several tiles take the node stream: mode ws")
        groups = [ids[k:k + tiles_per_node] for k in range(0, len(ids), tiles_per_node)]
        if nats:  # the broker's subjects are the wall's nodes
            groups = [g for g in info["nodes"] if set(g) <= set(ids)]
            common["nats"] = nats
        clients = [NodeClient(server, info["id"], g, scene, token=(tokens or {}).get(g[0], token),
                              renderers={t: renderers[t] for t in g if t in renderers}, **common)
                   for g in groups]
    else:
        clients = [TileClient(server, info["id"], t, scene, token=(tokens or {}).get(t, token),
                              renderer=renderers.get(t), **common) for t in ids]
    if made is not None:
        made.extend(clients)
    tasks = [asyncio.create_task(c.run(until, idle_timeout, start)) for c in clients]
    waits = [asyncio.ensure_future(c.connected.wait()) for c in clients]
    connected = asyncio.gather(*waits)
    done, _ = await asyncio.wait([connected, *tasks], return_when=asyncio.FIRST_COMPLETED)
    if ready is not None and all(c.connected.is_set() for c in clients):
        ready(clients)
    stopper = asyncio.ensure_future(stop.wait()) if stop is not None else None
    try:
        pending = set(tasks)
        while pending:
            waiting = pending | ({stopper} if stopper else set())
            done, _ = await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
            pending -= done
            if stopper in done:
                break
            for task in done:
                if task.exception() is not None:
                    raise task.exception()
    finally:
        for task in [*tasks, *waits, connected, *([stopper] if stopper else [])]:
            task.cancel()
        await asyncio.gather(*tasks, *waits, connected, return_exceptions=True)
        for r in renderers.values():
            r.release()
    return clients


def wall_report(clients: list[TileClient], failure: str | None = None) -> dict:
    """Everything the nodes recorded, JSON-ready (what ``--out`` writes). ``failure``: why the
    run ended early (then ``complete`` is false: the records stop where the run did)."""
    out = {"complete": failure is None, "tiles": [record for c in clients
                                                  for record in c.records()],
           "cpu_seconds": time.process_time()}  # this process's, since it started
    if failure is not None:
        out["reason"] = failure
    return out


def write_report(path: str, report: dict) -> None:
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        json.dump(report, f)
    os.replace(tmp, path)


def summary_rows(clients: list[TileClient]) -> list[dict]:
    rows = []
    for c in clients:
        for s in getattr(c, "tile_stats", {c.tile: c.stats}).values():
            lat = (np.asarray(s.recv) - np.asarray(s.posted)) * 1e3
            rows.append({"tile": s.tile, "packets": len(s.frame), "full": int(sum(s.full)),
                         "bytes": int(sum(s.bytes)),
                         "p50_ms": float(np.median(lat)) if len(lat) else float("nan"),
                         "p99_ms": float(np.percentile(lat, 99)) if len(lat) else float("nan"),
                         "misses": c.cache.misses, "evictions": c.cache.evictions,
                         "base_misses": s.base_misses, "errors": len(s.errors)})
    return rows


# --------------------------------------------------------------------------- command line


def size_bytes(text: str) -> int:
    """``"256M"``, ``"1G"``, ``"65536"`` to bytes."""
    text = text.strip().upper().removesuffix("B")
    scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(text[-1:], 1)
    try:
        value = float(text[:-1] if scale > 1 else text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"bad size {text!r}: use e.g. 65536, 64M, 1G") from None
    if not 0 <= value < 1 << 62:
        raise argparse.ArgumentTypeError(f"a size must be >= 0 and finite, got {text!r}")
    return int(value * scale)


def pixels(text: str) -> tuple[int, int]:
    w, _, h = text.lower().partition("x")
    if not (w.isdigit() and h.isdigit() and int(w) > 0 and int(h) > 0):
        raise argparse.ArgumentTypeError(f"bad size {text!r}: use WIDTHxHEIGHT, e.g. 240x135")
    return int(w), int(h)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m wallcull_clients.sim",
                                description="Simulated render clients of a wallcull wall.")
    p.add_argument("--server", default=os.environ.get("WALLCULL_SERVER", "http://127.0.0.1:8000"))
    p.add_argument("--wall", default="auto",
                   help="wall id, or 'auto': wait for a wall, and take the newest with no frame "
                        f"yet (a driver's new wall), or after {AUTO_GRACE:g} s the newest")
    p.add_argument("--tiles", default="all", help="tile ids: 'all', N-M, or a comma list")
    p.add_argument("--mode", choices=("ws", "pull"), default="ws",
                   help="ws: subscribe to the stream; pull: long-poll every frame number")
    p.add_argument("--format", choices=("msgpack", "json"), default="msgpack")
    p.add_argument("--tiles-per-node", type=int, default=1, metavar="K",
                   help="each node drives K consecutive tiles over one node stream (ws)")
    p.add_argument("--nats", metavar="URL",
                   help="take node messages from this NATS broker (the wall's own nodes; "
                        "the server runs with --nats)")
    p.add_argument("--token", default=os.environ.get("WALLCULL_TOKEN") or None,
                   help="the server's (operator's) token, for tiles --credentials does not "
                        "cover (default: $WALLCULL_TOKEN)")
    p.add_argument("--credentials", metavar="FILE",
                   help="the wall's credentials as POST /walls answered them (JSON: the whole "
                        "answer, or its 'credentials'); each tile uses its node's")
    p.add_argument("--reconnect-for", type=float, default=60.0, metavar="SECONDS",
                   help="how long a node keeps reconnecting to a lost server before it fails")
    p.add_argument("--cache-bytes", type=size_bytes, default=DEFAULT_CACHE,
                   help="mesh cache budget per node (LRU by bytes), e.g. 64M")
    p.add_argument("--render", action="store_true",
                   help="draw with the headless OpenGL renderer instead of counting triangles")
    p.add_argument("--render-size", type=pixels, help="WxH pixels (default: resolution / 8)")
    p.add_argument("--draw-time", type=float, default=0.0, metavar="SECONDS",
                   help="simulated drawing time per frame (each node waits this long, as if "
                        "its GPU were busy; the nodes of a process wait concurrently)")
    p.add_argument("--start", default="0", help="pull: first frame number, or 'latest'")
    p.add_argument("--until-frame", type=int, help="stop once this frame has been taken")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--idle-timeout", type=float,
                   help="stop when no packet came for this many seconds (after the first)")
    p.add_argument("--prefetch", action="store_true",
                   help="fetch every mesh of the scene (within the cache) before streaming")
    p.add_argument("--no-full-size", action="store_true",
                   help="do not compute what each delta would have cost as a full list")
    p.add_argument("--out", help="write every record to this JSON file")
    p.add_argument("--quiet", action="store_true", help="no summary table")
    return p


async def _main(args) -> int:
    stop, streaming = asyncio.Event(), [False]
    stop_on_signals(stop, lambda: streaming[0])
    if args.duration:
        asyncio.get_running_loop().call_later(args.duration, stop.set)

    def ready(clients):
        streaming[0] = True  # from now on a signal winds the nodes down, with their report
        print(json.dumps({"ready": True, "tiles": [t for c in clients
                                                  for t in getattr(c, "tiles", [c.tile])]}),
              flush=True)

    start = args.start if args.start == "latest" else int(args.start)
    tokens = node_tokens(args.credentials) if args.credentials else None
    made: list[TileClient] = []
    try:
        clients = await run_wall(args.server, args.wall, args.tiles, mode=args.mode,
                             token=args.token, tokens=tokens, binary=args.format == "msgpack",
                             cache_bytes=args.cache_bytes, render=args.render,
                             render_size=args.render_size, until=args.until_frame,
                             idle_timeout=args.idle_timeout, start=start,
                             measure_full=not args.no_full_size, draw_time=args.draw_time,
                             ready=ready, stop=stop, reconnect_for=args.reconnect_for,
                             tiles_per_node=args.tiles_per_node, nats=args.nats,
                             prefetch=args.prefetch, made=made)
    except Exception as exc:
        if args.out and made:  # what was drawn before the failure, marked incomplete
            write_report(args.out, wall_report(made, failure=str(exc)))
        raise
    if args.out:
        write_report(args.out, wall_report(clients))
    idle = [c for c in clients if c.idle_stop]
    if idle:  # never a silent stop: the frames may still have been coming
        last = max(c.last_frame for c in clients)
        print(f"clients.sim: stopped: no packet for {args.idle_timeout:g} s (--idle-timeout) "
              f"on {len(idle)} of {len(clients)} nodes; last frame taken {last}",
              file=sys.stderr)
    if not args.quiet:
        from rich.console import Console
        from rich.table import Table

        rows = summary_rows(clients)
        table = Table(title="simulated render nodes")
        for col in rows[0] if rows else []:
            table.add_column(col, justify="right")
        for row in rows:
            table.add_row(*(f"{v:.2f}" if isinstance(v, float) else str(v) for v in row.values()))
        Console(stderr=True).print(table)
    errors = sum(len(c.stats.errors) for c in clients)
    return 1 if errors else 0


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.start != "latest" and not args.start.isdigit():
        parser().error("--start must be a frame number or 'latest'")
    try:
        if args.tiles.strip() != "all":
            parse_tiles(args.tiles)
    except ValueError as exc:
        parser().error(str(exc))
    for name in ("reconnect_for", "duration", "idle_timeout", "draw_time"):
        value = getattr(args, name)
        if value is not None and not 0 <= value < math.inf or name != "draw_time" and value == 0:
            parser().error(f"--{name.replace('_', '-')} must be a positive number of seconds")
    if args.tiles_per_node < 1 or args.until_frame is not None and args.until_frame < 0:
        parser().error("--tiles-per-node must be at least 1 and --until-frame at least 0")
    try:
        return run(_main(args))
    except (ConnectionError, OSError, TimeoutError, HTTPError, ValueError,
            ClientFailure) as exc:
        print(f"clients.sim: error: {exc}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, asyncio.CancelledError):  # a signal before the nodes streamed
        print("clients.sim: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
