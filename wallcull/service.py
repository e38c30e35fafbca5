"""What a culling server holds: scenes, wall sessions, frame history, acknowledgements.

No HTTP here: :mod:`wallcull.server` maps routes onto these objects. Everything runs on the
server's event loop; the culling of a frame (a millisecond or two) runs inline, scene loading
(seconds) in a worker thread.
"""

from __future__ import annotations

import asyncio
import hashlib
import io
import os
import re
import secrets
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from . import protocol
from .errors import InputError
from .fit import FitOptions
from .pipeline import Session
from .scene import Scene, load
from .wall import Frame

#: File types a scene folder may hold (what ``trimesh`` reads as a scene).
SCENE_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl", ".off", ".3dxml", ".zip", ".dae")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")


#: A wall's history holds at most this many tile-frames (frames x tiles): about 150 bytes
#: each, plus its lists, so a 64 x 64 wall keeps up to 256 frames.
MAX_TILE_FRAMES = 1 << 20


class NotFound(LookupError):
    """An unknown scene, wall, tile, node or frame."""


class Conflict(RuntimeError):
    """A request that contradicts the server's state (a frame out of order, a name taken)."""


class Gone(LookupError):
    """A frame that has left the history."""


# --------------------------------------------------------------------------- scenes


class SceneStore:
    """The bundled scenes plus the files of one folder; scenes load once and stay cached.

    Names resolve only to files directly inside the folder: no separators, no ``..``, and the
    resolved path must still lie in the folder (a symlink pointing out is refused).
    """

    def __init__(self, folder: str | os.PathLike | None = None, max_upload: int = 64 << 20):
        self.folder = Path(folder).resolve() if folder else None
        self.max_upload = max_upload
        self.cache: dict[str, Scene] = {}
        self.uploaded: dict[str, Scene] = {}  # uploads kept in memory when there is no folder
        self._locks: dict[str, asyncio.Lock] = {}

    def names(self) -> list[dict]:
        from wallcull import scenes as bundled

        out = [{"name": n, "source": "bundled", "description": d}
               for n, d in bundled.BUNDLED.items()]
        if self.folder and self.folder.is_dir():
            for p in sorted(self.folder.iterdir()):
                if p.is_file() and p.suffix.lower() in SCENE_SUFFIXES and _NAME.match(p.name) \
                        and p.resolve().parent == self.folder:  # not a symlink pointing out
                    out.append({"name": p.name, "source": "folder", "bytes": p.stat().st_size})
        out += [{"name": n, "source": "upload"} for n in self.uploaded]
        return out

    def path(self, name: str) -> Path:
        if not _NAME.match(name):
            raise InputError(f"invalid scene name {name!r}: letters, digits, '_', '-', '.' only")
        if self.folder is None:
            raise NotFound(f"no scene {name!r} (the server has no scene folder)")
        path = (self.folder / name).resolve()
        if path.parent != self.folder:
            raise NotFound(f"no scene {name!r}")
        return path

    async def get(self, name: str) -> Scene:
        from wallcull import scenes as bundled

        if name in self.cache:
            return self.cache[name]
        if name in self.uploaded:
            return self.uploaded[name]
        builtin = bundled.is_bundled(name)  # powerplant*K too
        if not builtin:
            path = self.path(name)
            if not path.is_file() or path.suffix.lower() not in SCENE_SUFFIXES:
                raise NotFound(f"no scene {name!r}")
        lock = self._locks.setdefault(name, asyncio.Lock())
        async with lock:  # one load per scene, however many ask at once
            if name not in self.cache:
                spec = name if builtin else str(self.path(name))
                # mapped from its prepared file, which the first load writes
                self.cache[name] = await asyncio.to_thread(
                    lambda: usable(load(spec, cache="write")))
                self.cache[name].name = name
        return self.cache[name]

    async def upload(self, name: str, data: bytes, replace: bool = False) -> Scene:
        """Store a GLB: checked, parsed (nothing in it is executed), then saved atomically."""
        from wallcull import scenes as bundled

        if not name.lower().endswith(".glb"):
            name += ".glb"
        if not _NAME.match(name):
            raise InputError(f"invalid scene name {name!r}: letters, digits, '_', '-', '.' only")
        if name in bundled.BUNDLED:
            raise Conflict(f"{name!r} is a bundled scene")
        if len(data) > self.max_upload:
            raise InputError(f"upload of {len(data)} bytes exceeds {self.max_upload}")
        if data[:4] != b"glTF":
            raise InputError("an upload must be a binary glTF (.glb) file")
        exists = name in self.uploaded or (self.folder and (self.folder / name).exists())
        if exists and not replace:
            raise Conflict(f"scene {name!r} exists; pass replace=true to overwrite it")
        scene = await asyncio.to_thread(_parse_glb, data, name)
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
            tmp = self.folder / f".{name}.{secrets.token_hex(4)}.tmp"
            tmp.write_bytes(data)
            os.replace(tmp, self.folder / name)
        else:
            self.uploaded[name] = scene
        self.cache[name] = scene
        return scene


def _parse_glb(data: bytes, name: str) -> Scene:
    import trimesh

    try:
        loaded = trimesh.load(io.BytesIO(data), file_type="glb")
    except Exception as exc:  # noqa: BLE001 - a parser failure is bad input
        raise InputError(f"cannot read the uploaded GLB: {exc}") from None
    if not isinstance(loaded, trimesh.Scene):
        loaded = trimesh.Scene(loaded)
    if not loaded.geometry:
        raise InputError("the uploaded GLB has no geometry")
    try:
        with np.errstate(all="ignore"):  # odd files overflow on their way to being refused
            return usable(Scene.from_trimesh(loaded, name=name))
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - whatever an odd file trips is bad input
        raise InputError(f"cannot use the uploaded GLB: {type(exc).__name__}: {exc}") from None


def usable(scene: Scene) -> Scene:
    """``scene``, once it is known to have leaves and finite bounds (computed here, in the
    loading thread, rather than by the first wall): a file can be well formed and still carry
    no drawable node, NaN vertices or transforms that overflow."""
    if not len(scene.leaves):
        raise InputError(f"scene {scene.name!r} has no node that carries geometry")
    if not np.isfinite(scene.box).all():
        raise InputError(f"scene {scene.name!r} has vertices that are not finite in the world")
    try:
        b = scene.bounds("obb")
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
        raise InputError(f"scene {scene.name!r} cannot be bounded: {exc}") from None
    if not all(np.isfinite(a).all() for a in (b.center, b.axes, b.half, b.radius)):
        raise InputError(f"scene {scene.name!r} is too large to bound in float64")
    return scene


def describe(scene: Scene, nodes: bool = True) -> dict:
    """A scene's shape: stats, bounds, settings and (optionally) every node."""
    out = {"name": scene.name, "stats": scene.stats, "settings": scene.settings,
           "bounds": {"min": scene.box[0].tolist(), "max": scene.box[1].tolist()}}
    if nodes:
        out["nodes"] = {
            "name": list(scene.names), "parent": scene.parent.tolist(),
            "leaf": scene.is_leaf.tolist(), "synthetic": scene.synthetic.tolist(),
            "mesh": scene.geometry,
            "world": scene.world.reshape(len(scene), 16).tolist(),
        }
    return out


@dataclass
class MeshBlob:
    """One mesh, encoded once: typed arrays as bytes, and its ETag."""

    body: dict
    etag: str


#: Bytes of encoded meshes a scene keeps for the mesh routes; beyond them the least recently
#: served are dropped and read again (from the prepared file) when asked for.
MESH_CACHE_BYTES = 64 << 20


def mesh_blob(scene: Scene, key: str) -> MeshBlob:
    """Mesh ``key`` of a scene as typed arrays (little-endian float32 vertices, uint32 faces),
    its ETag the hash of those bytes. Encoded meshes are kept up to :data:`MESH_CACHE_BYTES`
    per scene, least recently served dropped first: a scene of many distinct meshes is never
    held in memory whole."""
    cache = scene.__dict__.setdefault("_mesh_blobs", OrderedDict())
    if key in cache:
        cache.move_to_end(key)
        return cache[key]
    if key not in scene.meshes:
        raise NotFound(f"no mesh {key!r} in scene {scene.name!r}")
    v, f = scene.meshes[key]
    vb = np.ascontiguousarray(v, dtype="<f4").tobytes()
    fb = np.ascontiguousarray(f, dtype="<u4").tobytes()
    etag = '"' + hashlib.sha256(vb + b"|" + fb).hexdigest()[:32] + '"'
    blob = cache[key] = MeshBlob({"mesh": key,
                                  "vertices": {"dtype": "<f4", "shape": [len(v), 3], "data": vb},
                                  "faces": {"dtype": "<u4", "shape": [len(f), 3], "data": fb}},
                                 etag)
    held = sum(len(b.body["vertices"]["data"]) + len(b.body["faces"]["data"])
               for b in cache.values())
    while held > MESH_CACHE_BYTES and len(cache) > 1:
        _, old = cache.popitem(last=False)
        held -= len(old.body["vertices"]["data"]) + len(old.body["faces"]["data"])
    return blob


# --------------------------------------------------------------------------- walls


@dataclass
class WallSession:
    """One wall culling one scene: frames in, packets out, acknowledgements back."""

    id: str
    session: Session
    history: protocol.History
    created: float = field(default_factory=time.time)
    acks: np.ndarray = None  # per tile, last acknowledged frame (-1: none)
    subscribers: int = 0
    closed: bool = False
    _new_frame: asyncio.Event = field(default_factory=asyncio.Event)
    _new_ack: asyncio.Event = field(default_factory=asyncio.Event)
    _tile_acked: dict = field(default_factory=dict)  # tile -> Event its next ack sets
    _frame_lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    _ever_moved: np.ndarray = None

    def __post_init__(self):
        self.acks = np.full(self.wall.tiles, -1, dtype=np.int64)
        self._ever_moved = np.zeros(0, dtype=np.int64)

    @property
    def wall(self):
        return self.session.wall

    @property
    def scene(self) -> Scene:
        return self.session.scene

    @property
    def latest(self) -> int:
        return self.history.latest

    def info(self) -> dict:
        s = self.session
        return {"id": self.id, "scene": self.scene.name, "wall": self.wall.to_dict(),
                "tiles": self.wall.tiles, "method": s.method, "bounds": s.state.kind,
                "pseudo_groups": s.culler.pseudo_groups, "latest": self.latest,
                "history": self.history.size, "subscribers": self.subscribers}

    def check_tile(self, tile: int) -> None:
        if not 0 <= tile < self.wall.tiles:
            raise NotFound(f"no tile {tile} on wall {self.id} ({self.wall.tiles} tiles)")

    def compute_frame(self, frame: Mapping[str, Any], updates: Mapping[str, Any] | None = None,
                      number: int | None = None, refit: str | None = None
                      ) -> tuple[protocol.FrameRecord, dict]:
        """Move, cull and fit a frame: its record (not yet published) and per-stage timings
        (ms). Touches no asyncio object, so it may run in a worker thread; one at a time."""
        posted, t0 = time.time(), time.perf_counter()
        if number is None:
            number = self.latest + 1
        elif number <= self.latest:
            raise Conflict(f"frame {number} is out of order: frame {self.latest} is already in")
        # Validate the whole request before anything moves: a refused frame changes nothing.
        frame = Frame.from_dict(frame, self.wall)
        changed = np.zeros(0, dtype=np.int64)
        if updates:
            self.session.move(updates, refit)
            moved = np.array([self.scene.index[n] for n in updates])
            changed = np.unique(self.scene.subtree_leaves(moved))
            self._ever_moved = np.union1d(self._ever_moved, changed)
        t1 = time.perf_counter()
        result = self.session.frame(frame)
        t2 = time.perf_counter()
        start, leaves = result.visibility.leaf_lists()
        posed = self._ever_moved
        record = protocol.FrameRecord(number, posted, start, leaves, result.fits, changed, posed,
                                      self.session.state.world[posed])
        return record, {"update_ms": (t1 - t0) * 1e3, "cull_ms": result.timings["cull_ms"],
                        "fit_ms": result.timings["fit_ms"],
                        "lists_ms": (time.perf_counter() - t2) * 1e3,
                        "total_ms": (time.perf_counter() - t0) * 1e3}

    def publish(self, record: protocol.FrameRecord) -> int:
        """Make a computed frame visible and wake whoever waits for it (on the event loop)."""
        if record.number <= self.latest:
            raise Conflict(f"frame {record.number} is out of order: frame {self.latest} is in")
        self.history.add(record)
        old, self._new_frame = self._new_frame, asyncio.Event()
        old.set()
        return record.number

    def post_frame(self, frame: Mapping[str, Any], updates: Mapping[str, Any] | None = None,
                   number: int | None = None, refit: str | None = None) -> tuple[int, dict]:
        """Compute and publish a frame in the caller's thread; its number and timings."""
        record, timings = self.compute_frame(frame, updates, number, refit)
        return self.publish(record), timings

    async def post_frame_async(self, frame: Mapping[str, Any],
                               updates: Mapping[str, Any] | None = None,
                               number: int | None = None, refit: str | None = None
                               ) -> tuple[int, dict]:
        """:meth:`post_frame` with the work in a worker thread, so that the event loop keeps
        serving packets while a frame is culled and fitted; frames of one wall go one at a
        time, in order."""
        async with self._frame_lock:
            record, timings = await asyncio.to_thread(self.compute_frame, frame, updates, number,
                                                      refit)
            return self.publish(record), timings

    async def _wait(self, done, event, timeout: float) -> bool:
        """Wait until ``done()``, waking whenever ``event()`` is set (read again each time:
        events are replaced once set); False after ``timeout`` seconds. A deleted wall raises
        :class:`NotFound` (close() leaves the events set: waiting again would spin)."""
        deadline = time.monotonic() + timeout
        while not done():
            if self.closed:
                raise NotFound(f"wall {self.id} was deleted")
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            try:
                await asyncio.wait_for(event().wait(), left)
            except asyncio.TimeoutError:
                return False
        return True

    async def wait_frame(self, number: int, timeout: float) -> bool:
        """Wait until frame ``number`` exists (or the timeout passes)."""
        return await self._wait(lambda: self.latest >= number, lambda: self._new_frame, timeout)

    async def next_frame(self, after: int) -> int:
        """The newest frame number once one newer than ``after`` exists."""
        while self.latest <= after:
            if self.closed:
                raise NotFound(f"wall {self.id} was deleted")
            await self._new_frame.wait()
        return self.latest

    def close(self) -> None:
        """Wake everyone waiting on this wall: it is being deleted."""
        self.closed = True
        for event in (self._new_frame, self._new_ack, *self._tile_acked.values()):
            event.set()

    def packet(self, tile: int, number: int, full: bool = False, since: int = -1) -> dict:
        """Tile ``tile``'s packet of frame ``number``: a delta against the tile's acknowledged
        frame if that is at least ``since``, else a full list. A stream passes its first frame
        as ``since``: a node that reconnected holds nothing from before it."""
        self.check_tile(tile)
        if number > self.latest or number < 0:
            raise NotFound(f"frame {number} does not exist yet (latest {self.latest})")
        if self.history.get(number) is None:
            if number > self.history.oldest:
                raise NotFound(f"there is no frame {number}: frame numbers skipped it")
            raise Gone(f"frame {number} has left the history (oldest {self.history.oldest})")
        ack = int(self.acks[tile])
        base = None if full or ack < 0 or ack < since else ack
        return protocol.packet(self.history, number, tile, base)

    def ack(self, tile: int, number: int) -> None:
        self.check_tile(tile)
        if number > self.latest:
            raise Conflict(f"cannot acknowledge frame {number}: latest is {self.latest}")
        if number > self.acks[tile]:
            self.acks[tile] = number
            old, self._new_ack = self._new_ack, asyncio.Event()
            old.set()
            waiter = self._tile_acked.pop(tile, None)
            if waiter is not None:
                waiter.set()

    async def wait_acked(self, tile: int, number: int, timeout: float) -> bool:
        """Wait until ``tile`` has acknowledged frame ``number`` or a later one (a stream's
        flow control); False on timeout."""
        return await self._wait(lambda: self.acks[tile] >= number,
                                lambda: self._tile_acked.setdefault(tile, asyncio.Event()),
                                timeout)

    def barrier_state(self, number: int) -> dict:
        acked = int((self.acks >= number).sum())
        return {"frame": number, "acked": acked, "tiles": self.wall.tiles,
                "complete": acked == self.wall.tiles}

    async def barrier(self, number: int, timeout: float) -> dict:
        """Wait until every tile has acknowledged frame ``number`` (the swap barrier)."""
        await self._wait(lambda: self.barrier_state(number)["complete"], lambda: self._new_ack,
                         timeout)
        return self.barrier_state(number)


class Walls:
    """The wall sessions of a server, by id, with a cap on how many exist at once."""

    def __init__(self, limit: int = 32):
        self.limit = limit
        self.sessions: dict[str, WallSession] = {}

    def create(self, scene: Scene, wall, method: str, bounds: str, pseudo_groups: bool,
               history: int, fit: FitOptions = FitOptions()) -> WallSession:
        if len(self.sessions) >= self.limit:
            raise Conflict(f"the server already holds {self.limit} walls; delete one first")
        if history * wall.tiles > MAX_TILE_FRAMES:
            raise InputError(f"a history of {history} frames of {wall.tiles} tiles is more than "
                             f"{MAX_TILE_FRAMES:,} tile-frames; ask for at most "
                             f"{max(2, MAX_TILE_FRAMES // wall.tiles)} frames")
        session = Session(scene, wall, method, bounds, pseudo_groups, fit)
        wid = secrets.token_hex(6)
        self.sessions[wid] = WallSession(wid, session, protocol.History(history))
        return self.sessions[wid]

    def get(self, wid: str) -> WallSession:
        try:
            return self.sessions[wid]
        except KeyError:
            raise NotFound(f"no wall {wid!r}") from None

    def delete(self, wid: str) -> None:
        self.get(wid)
        del self.sessions[wid]
