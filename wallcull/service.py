"""What a culling server holds: scenes, wall sessions, frame history, acknowledgements.

No HTTP here: :mod:`wallcull.server` maps routes onto these objects. Everything runs on the
server's event loop but what can take long: a frame's culling and fitting and the making of a
wall run in a worker thread; an upload's parse, the preparing of a scene not seen before and
the fitting of bounds other than OBBs in a child process with a time and memory budget
(:mod:`wallcull.sandbox`).
"""

from __future__ import annotations

import asyncio
import errno
import gc
import hashlib
import logging
import os
import re
import secrets
import tempfile
import threading
import time
from collections import Counter, OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from . import bounds as bnd
from . import credentials, encode, protocol, sandbox
from .credentials import Grant
from .errors import InputError, WriteFailed
from .fit import FitOptions
from .limits import Limits
from .occlude import OcclusionOptions
from .persist import StateFolder, StateWriteFailed, WallRow
from .prepared import cache_dir
from .pipeline import Session
from .scene import Scene, bounds_of, load, prepare_path, usable
from .uploads import parse_sandboxed
from .validate import MAX_FRAME
from .wall import Frame, Wall
from .workers import background

log = logging.getLogger("wallcull")

#: File types a scene folder may hold (what ``trimesh`` reads as a scene).
SCENE_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl", ".off", ".3dxml", ".zip", ".dae")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")


#: A wall's history holds at most this many tile-frames (frames x tiles): about 150 bytes
#: each, plus its lists, so a 64 x 64 wall keeps up to 256 frames.
MAX_TILE_FRAMES = 1 << 20


#: Seconds a scene file that failed to prepare (too big for the limits, or broken) is
#: refused at once with the same answer, unless it changes (its size or modification time).
FAILED_PREPARE_SECONDS = 600


class NotFound(LookupError):
    """An unknown scene, wall, tile, node or frame."""


class Conflict(RuntimeError):
    """A request that contradicts the server's state (a frame out of order, a name taken)."""


class Gone(LookupError):
    """A frame that has left the history."""


class Unavailable(LookupError):
    """A wall of the state folder whose scene cannot be loaded now (503: retry later)."""


# --------------------------------------------------------------------------- scenes


class SceneStore:
    """The bundled scenes plus the files of one folder; scenes load once and stay cached while
    a wall uses them or the cache's memory budget (``limits.scene_cache``) has room.

    Names resolve only to files directly inside the folder: no separators, no ``..``, and the
    resolved path must still lie in the folder (a symlink pointing out is refused).
    """

    def __init__(self, folder: str | os.PathLike | None = None, limits: Limits = Limits(),
                 in_use: Callable[[], dict] = dict):
        self.folder = Path(folder).resolve() if folder else None
        self.limits = limits
        self.max_upload = limits.upload
        self.in_use = in_use  # scene name -> ids of the walls using it: never evicted
        self.cache: OrderedDict[str, Scene] = OrderedDict()  # least recently used first
        self.uploaded: dict[str, Scene] = {}  # uploads kept in memory when there is no folder
        self._locks: dict[str, asyncio.Lock] = {}
        self.receiving: set[str] = set()  # names of uploads in progress
        self.failed: dict[tuple, tuple[float, str]] = {}  # (file, size, mtime) -> (until, why)
        self.unwritable_told: set[int | None] = set()  # errnos of the cache folder logged

    def names(self) -> list[dict]:
        from wallcull import bundled

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
        from wallcull import bundled

        if name in self.cache:
            self.cache.move_to_end(name)
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
                spec = self.spec(name)
                failed = self.failed.get(key := _as_found(spec))
                if failed is not None and time.monotonic() < failed[0]:
                    raise InputError(failed[1])  # at once: nothing it depends on has changed
                # mapped from its prepared file, which a child process writes first when
                # there is none (building a scene takes seconds to minutes)
                scene = await background(load, spec, cache="map")
                if scene is None:
                    await self._prepare(name, spec, key)
                    try:
                        scene = await background(load, spec, cache="write")
                    except WriteFailed as exc:
                        raise self._unwritable(exc) from None
                scene = await background(lambda: settled(usable(scene)))
                scene.name = name
                self.remember(name, scene)
                return scene
        return self.cache[name]

    async def _prepare(self, name: str, spec: str, key: tuple) -> None:
        """Write the prepared file of scene ``name`` in a child process (``parse_memory``,
        ``parse_seconds``). A failure is remembered under ``key`` (:func:`_as_found`: the
        file and the cache folder as they are) for :data:`FAILED_PREPARE_SECONDS`, and
        answered again at once by :meth:`get`: a file too big for the limits would otherwise
        take a new child and minutes per request. A cache folder that is full or read-only is
        the server's problem: 507 or 503."""
        self.failed.pop(key, None)
        try:
            await background(
                sandbox.run, prepare_path, (spec,), seconds=self.limits.parse_seconds,
                memory=self.limits.parse_memory, what=f"preparing scene {name!r}")
        except WriteFailed as exc:
            raise self._unwritable(exc) from None
        except InputError as exc:
            message = str(exc)
            if "bytes of memory" in message or "took over" in message:
                which = "parse_memory" if "memory" in message else "parse_seconds"
                message = (f"{message.rstrip('.')}: prepare it ahead with `wallcull prepare "
                           f"FILE` under the server's WALLCULL_CACHE (the server maps it then), "
                           f"or raise --limit {which}=...")
            while len(self.failed) >= 256:  # the oldest first
                self.failed.pop(next(iter(self.failed)))
            self.failed[key] = (time.monotonic() + FAILED_PREPARE_SECONDS, message)
            log.warning("wallcull: %s (answered so for %d s, or until the file or the cache "
                        "folder changes)", message, FAILED_PREPARE_SECONDS)
            raise InputError(message) from None

    def _unwritable(self, exc: WriteFailed) -> StateWriteFailed:
        """The answer to a prepared file the cache folder could not take: 507 for a full disk,
        503 otherwise (read-only, no permission), logged once per reason."""
        full = exc.errno in (errno.ENOSPC, errno.EDQUOT)
        if exc.errno not in self.unwritable_told:
            self.unwritable_told.add(exc.errno)
            log.error("wallcull: the scene cache folder cannot be written: %s (scenes without "
                      "a prepared file are refused with %d until it can)", exc,
                      507 if full else 503)
        return StateWriteFailed(507 if full else 503, f"{exc} (the server's scene cache "
                                "folder, WALLCULL_CACHE; not a problem of the scene)")

    def lock(self, key: str) -> asyncio.Lock:
        """The lock of ``key`` (a scene's name, or a name and a task on it)."""
        return self._locks.setdefault(key, asyncio.Lock())

    def spec(self, name: str) -> str:
        """What :func:`wallcull.scene.load` takes for scene ``name`` (bundled or a file)."""
        from wallcull import bundled

        return name if bundled.is_bundled(name) else str(self.path(name))

    async def bounds(self, scene: Scene, kind: str) -> None:
        """Make sure ``scene`` holds bounds of ``kind``: fitted in a child process
        (:mod:`wallcull.sandbox`, ``limits.parse_seconds``) for every kind but the OBBs its
        prepared file holds. Minimum-volume boxes of a large scene take minutes."""
        cache = scene.__dict__.setdefault("_bounds", {})
        if kind not in bnd.KINDS:
            raise InputError(f"unknown bound type {kind!r}; choose from {', '.join(bnd.KINDS)}")
        async with self._locks.setdefault(f"{scene.name}\0{kind}", asyncio.Lock()):
            if kind in cache or kind == "obb":
                return
            if scene.name in self.uploaded:  # no file to load it from in a child: a thread
                await background(scene.bounds, kind)
                return
            cache[kind] = await background(
                sandbox.run, bounds_of, (self.spec(scene.name), kind),
                seconds=self.limits.parse_seconds, memory=self.limits.parse_memory,
                what=f"fitting {kind} bounds to scene {scene.name!r}")

    # ------------------------------------------------------------------ uploads

    def upload_name(self, name: str, replace: bool = False) -> str:
        """The file name an upload called ``name`` gets, refused before its body is read when it
        is not a plain name, is a bundled scene's, or exists and ``replace`` is false."""
        from wallcull import bundled

        if not name.lower().endswith(".glb"):
            name += ".glb"
        if not _NAME.match(name):
            raise InputError(f"invalid scene name {name!r}: letters, digits, '_', '-', '.' only")
        if name in bundled.BUNDLED:
            raise Conflict(f"{name!r} is a bundled scene")
        if name in self.receiving:
            raise Conflict(f"scene {name!r} is being uploaded by another request")
        target = self.folder / name if self.folder else None
        if target is not None and not target.is_symlink() and target.exists() \
                and not target.is_file():  # a link is replaced, never followed
            raise Conflict(f"{name!r} in the scene folder is not a file (a folder, or a "
                           "device): an upload cannot take its place")
        exists = name in self.uploaded or (target is not None and target.exists())
        if exists and not replace:
            raise Conflict(f"scene {name!r} exists; pass replace=true to overwrite it")
        self._not_in_use(name)
        self.receiving.add(name)  # until release(): a second upload of the name is a 409
        return name

    def release(self, name: str) -> None:
        """The upload of ``name`` (from :meth:`upload_name`) has ended, stored or not."""
        self.receiving.discard(name)

    def _not_in_use(self, name: str) -> None:
        """Refuse to replace a scene a wall culls: its nodes would fetch meshes the wall does
        not cull, and the wall would switch geometry at its next restart."""
        users = self.in_use().get(name)
        if users:
            raise Conflict(f"scene {name!r} is used by wall(s) {', '.join(sorted(users))}; "
                           "delete them first, or upload under another name")

    def sweep(self, now: float | None = None) -> list[str]:
        """Remove the spooled bodies (:meth:`spool`) no upload can still be writing or
        parsing: older than a body may take to arrive and be parsed, and a minute (a server
        killed mid-upload leaves its spool behind); returns their names."""
        if self.folder is None or not self.folder.is_dir():
            return []
        limit = (time.time() if now is None else now) - (
            self.limits.body_seconds + self.limits.parse_seconds + 60)
        gone = []
        for path in self.folder.glob(".upload.*.tmp"):
            try:
                if path.is_file() and path.stat().st_mtime < limit:
                    path.unlink()
                    gone.append(path.name)
            except OSError:
                continue  # taken by its upload meanwhile, or not ours to remove
        return gone

    def spool(self):
        """A temporary file for an upload's body, beside its destination (so that moving it
        into the folder is atomic), or in the system's temporary folder without one."""
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
        return tempfile.NamedTemporaryFile(prefix=".upload.", suffix=".tmp", delete=False,
                                           dir=self.folder)

    async def upload(self, name: str, path: Path) -> Scene:
        """Store the GLB at ``path`` (an upload's spooled body, see :meth:`spool`) as scene
        ``name`` (from :meth:`upload_name`): checked and parsed in a sandbox
        (:mod:`wallcull.uploads`), then moved into the folder atomically."""
        scene = await background(lambda: settled(parse_sandboxed(path, name,
                                                                        self.limits)))
        # after a load of the file being replaced has ended (:meth:`get` holds the name's
        # lock while it loads): it would cache the old scene over this one
        async with self._locks.setdefault(name, asyncio.Lock()):
            self._not_in_use(name)  # a wall may have been created on it meanwhile
            if self.folder is not None:
                os.replace(path, self.folder / name)
            else:  # held in memory for good (never evicted: nothing could load it again)
                held = footprint(scene) + sum(footprint(s) for n, s in self.uploaded.items()
                                              if n != name)
                if held > self.limits.scene_cache:
                    raise Conflict(f"this server keeps uploads in memory only (it has no "
                                   f"scene folder), and with {name!r} they would hold "
                                   f"{held:,} bytes, over its scene cache of "
                                   f"{self.limits.scene_cache:,}: give it a folder (--scenes "
                                   "or --state), or replace an upload")
                self.uploaded[name] = scene
            self.remember(name, scene)
        return scene

    # ------------------------------------------------------------------ the memory budget

    def remember(self, name: str, scene: Scene) -> None:
        """Cache ``scene``, then evict what the budget no longer has room for (never
        ``scene`` itself: whoever loaded it is about to use it)."""
        self.cache[name] = scene
        self.cache.move_to_end(name)
        self.evict(keep=name)

    def evict(self, keep: str | None = None) -> list[str]:
        """Drop the least recently used scenes that no wall uses (and that can be loaded again)
        until the cache fits ``limits.scene_cache``; returns their names."""
        sizes = {name: footprint(scene) for name, scene in self.cache.items()}
        total, used, dropped = sum(sizes.values()), self.in_use(), []
        for name in list(self.cache):
            if total <= self.limits.scene_cache:
                break
            if name in used or name in self.uploaded or name == keep:
                continue
            total -= sizes[name]
            del self.cache[name]
            dropped.append(name)
        return dropped


def _as_found(spec: str) -> tuple:
    """Scene file ``spec`` and the cache folder as they are now (sizes and modification
    times): what a remembered failure to prepare it holds for. A new prepared file (the
    operator ran ``wallcull prepare``) changes the folder's time, a new scene file its own."""
    def stamp(path) -> tuple:
        try:
            st = os.stat(path)
            return st.st_size, st.st_mtime_ns
        except OSError:  # a bundled scene, a cache folder not made yet
            return None, None

    return spec, *stamp(spec), *stamp(cache_dir())


def settled(obj=None):
    """``obj``, after moving every object alive now out of the garbage collector's sight
    (``gc.freeze``). A server holds scenes of hundreds of thousands of objects for days; a
    full collection walks them all, holding the GIL for 50-100 ms, and any request that
    allocates a lot (a 1 MiB JSON body) can set one off mid-parse, stalling the event loop.
    Frozen objects are still freed by reference counting when nothing refers to them any more;
    only a cycle among objects alive at a freeze (requests in flight while a scene loads, a
    few kilobytes) is never collected. Costs one full collection (50-100 ms) per scene load."""
    gc.collect()
    gc.freeze()
    return obj


def footprint(obj, _depth: int = 0) -> int:
    """Bytes of the arrays, byte strings and text an object holds, through its attributes,
    dicts, lists and tuples (an estimate of what evicting it frees; small objects count 0)."""
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, (bytes, bytearray, str)):
        return len(obj)
    if _depth > 6:
        return 0
    if isinstance(obj, dict):
        return sum(footprint(k, _depth + 1) + footprint(v, _depth + 1) for k, v in obj.items())
    if isinstance(obj, (list, tuple)):
        if obj and isinstance(obj[0], (int, float)):
            return 8 * len(obj)
        return sum(footprint(v, _depth + 1) for v in obj)
    if hasattr(obj, "__dict__"):
        return footprint(vars(obj), _depth + 1)
    return 0


def describe(scene: Scene, nodes: bool = True, arrays: bool = False) -> dict:
    """A scene's shape: stats, bounds, settings and (optionally) its node table. ``arrays``:
    the per-node columns stay numpy arrays (for an encoder that turns them into lists a piece
    at a time: a 100,000-node scene is 2.3 million numbers).

    The table has a row per node but the clusters (which lists never name: they are parts of
    a leaf's triangles, most of a big scene's rows), in id order; ``id`` holds each row's node
    id, ``count`` the number of ids (clusters included): ids are the culling's, the same in
    frames, packets and the node mesh route."""
    out = {"name": scene.name, "stats": scene.stats, "settings": scene.settings,
           "bounds": {"min": scene.box[0].tolist(), "max": scene.box[1].tolist()}}
    if nodes:
        keep = np.flatnonzero(np.asarray(scene.cluster_of) < 0)
        whole = len(keep) == len(scene)
        names, meshes = list(scene.names), scene.geometry
        columns = {"id": keep, "parent": np.asarray(scene.parent)[keep],
                   "leaf": np.asarray(scene.is_leaf)[keep],
                   "synthetic": np.asarray(scene.synthetic)[keep],
                   "world": np.asarray(scene.world).reshape(len(scene), 16)[keep]}
        out["nodes"] = {"count": len(scene),
                        "name": names if whole else [names[i] for i in keep.tolist()],
                        "mesh": list(meshes) if whole else [meshes[i] for i in keep.tolist()],
                        **{k: v if arrays else v.tolist() for k, v in columns.items()}}
    return out


@dataclass
class MeshBlob:
    """One mesh, encoded once: typed arrays as bytes, and its ETag."""

    body: dict
    etag: str


#: Bytes of encoded meshes a scene keeps for the mesh routes; beyond them the least recently
#: served are dropped and read again (from the prepared file) when asked for.
MESH_CACHE_BYTES = 64 << 20


class _MeshCache:
    """A scene's encoded meshes, least recently served first, within ``MESH_CACHE_BYTES``;
    safe to fill from a thread while the event loop serves from it."""

    def __init__(self):
        self.blobs: OrderedDict[str, MeshBlob] = OrderedDict()
        self.held = 0
        self.lock = threading.Lock()


def _mesh_cache(scene: Scene) -> _MeshCache:
    cache = scene.__dict__.get("_mesh_cache")
    if cache is None:
        cache = scene.__dict__.setdefault("_mesh_cache", _MeshCache())
    return cache


def _blob_bytes(blob: MeshBlob) -> int:
    return len(blob.body["vertices"]["data"]) + len(blob.body["faces"]["data"])


def mesh_blob(scene: Scene, key: str) -> MeshBlob:
    """Mesh ``key`` of a scene as typed arrays (little-endian float32 vertices, uint32 faces)
    and ``double_sided``: false for a glTF mesh whose material is not ``doubleSided``
    (:attr:`MeshTable.single_sided <wallcull.instances.MeshTable>`), whose back faces a render
    node may cull; its ETag the hash of those bytes and the flag (an answer is cached for a
    year: one that changes sides must change its ETag). Encoded meshes are kept up to
    :data:`MESH_CACHE_BYTES` per scene, least recently served dropped first: a scene of many
    distinct meshes is never held in memory whole."""
    cache = _mesh_cache(scene)
    with cache.lock:
        found = cache.blobs.get(key)
        if found is not None:
            cache.blobs.move_to_end(key)
            return found
    if key not in scene.meshes:
        raise NotFound(f"no mesh {key!r} in scene {scene.name!r}")
    number = scene.meshes.index[key]
    v, f = scene.meshes.mesh(number)
    double = not bool(scene.meshes.single_sided[number])
    vb = np.ascontiguousarray(v, dtype="<f4").tobytes()
    fb = np.ascontiguousarray(f, dtype="<u4").tobytes()
    sides = b"|double" if double else b"|single"
    etag = '"' + hashlib.sha256(vb + b"|" + fb + sides).hexdigest()[:32] + '"'
    blob = MeshBlob({"mesh": key, "double_sided": double,
                     "vertices": {"dtype": "<f4", "shape": [len(v), 3], "data": vb},
                     "faces": {"dtype": "<u4", "shape": [len(f), 3], "data": fb}}, etag)
    with cache.lock:
        if key not in cache.blobs:
            cache.blobs[key] = blob
            cache.held += _blob_bytes(blob)
        while cache.held > MESH_CACHE_BYTES and len(cache.blobs) > 1:
            _, old = cache.blobs.popitem(last=False)
            cache.held -= _blob_bytes(old)
    return blob


def warm_meshes(scene: Scene) -> int:
    """Encode a scene's meshes ahead of the render nodes' first requests, while they fit in
    ``MESH_CACHE_BYTES`` (run in a thread when a wall is created: encoding a mesh on the event
    loop when a node first asks for it stalled every stream, and nodes waiting for meshes
    fell behind). Returns how many were encoded."""
    count = 0
    for key in list(scene.meshes.keys()):
        if _mesh_cache(scene).held >= MESH_CACHE_BYTES:
            break
        mesh_blob(scene, key)
        count += 1
    return count


# --------------------------------------------------------------------------- walls

#: Console states (:meth:`WallSession.status`): a tile with no stream is offline once its last
#: ack is this old (s); a tile is lagging when the newest frame it has not drawn is this old
#: (s), or when it is more than this many frames behind.
LIVE, LAG, LAG_FRAMES = 5.0, 0.5, 8


@dataclass
class WallSession:
    """One wall culling one scene: frames in, packets out, acknowledgements back."""

    id: str
    session: Session
    history: protocol.History
    created: float = field(default_factory=time.time)
    acks: np.ndarray = None  # per tile, last acknowledged frame (-1: none)
    acked_at: np.ndarray = None  # per tile, server clock when its newest ack came (0: never)
    subscribers: int = 0  # node and tile streams open
    consoles: int = 0  # console streams open
    closed: bool = False
    #: no frame number above it was handed out before a restart: numbers continue after it
    floor: int = -1
    #: called with every frame's number before the frame is published (in the frame's thread):
    #: the state folder writes it down, so that a restart never reuses a number
    on_number: Callable[[int], None] | None = None
    streams: Counter = field(default_factory=Counter)  # open streams per tile
    issued: credentials.Issued | None = None  # its credentials' digests (the server's)
    credentials: dict | None = None  # as issued, to be shown once (never kept on disk)
    gone: asyncio.Event = field(default_factory=asyncio.Event)  # set when it is deleted
    #: time.monotonic() of its newest frame, acknowledgement or stream (``--wall-ttl``)
    active: float = field(default_factory=time.monotonic)
    _new_frame: asyncio.Event = field(default_factory=asyncio.Event)
    _new_ack: asyncio.Event = field(default_factory=asyncio.Event)
    _frame_lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    # leaves moved in frames computed but not published (refused after their moves, say):
    # the next record carries them as its own, so that a node is told where they went
    _unsent: np.ndarray = None

    def __post_init__(self):
        self.acks = np.full(self.wall.tiles, -1, dtype=np.int64)
        self.acked_at = np.zeros(self.wall.tiles)
        self._unsent = np.zeros(0, dtype=np.int64)

    @property
    def wall(self):
        return self.session.wall

    @property
    def scene(self) -> Scene:
        return self.session.scene

    @property
    def nodes(self) -> list[list[int]]:
        """The tiles of each node credential."""
        return [] if self.issued is None else self.issued.nodes()

    @property
    def latest(self) -> int:
        """The newest frame held (-1: none since the server started)."""
        return self.history.latest

    @property
    def newest(self) -> int:
        """The newest frame number handed out, before a restart too (after a kill, the
        number written down ahead: see :class:`FrameNumbers`)."""
        return max(self.history.latest, self.floor)

    def info(self) -> dict:
        """What ``GET /walls/{wid}`` shows: among it every option the wall was created with
        (:func:`spec_of`, what a restart makes it again from), so that it can be created again
        as it was (a leaked credential's revocation)."""
        return {"id": self.id, **spec_of(self), "tiles": self.wall.tiles,
                "latest": self.newest, "subscribers": self.subscribers, "nodes": self.nodes}

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
            number = self.newest + 1
            if number > MAX_FRAME:
                raise Conflict(f"wall {self.id} has used every frame number (the last is "
                               f"{MAX_FRAME}): create it again")
        elif number <= self.newest:
            raise Conflict(f"frame {number} is out of order: frame {self.newest} is already in")
        # Validate the whole request before anything moves: a refused frame changes nothing.
        frame = Frame.from_dict(frame, self.wall)
        if self.on_number is not None:  # its number written down (or the frame refused)
            self.on_number(number)
        changed = self._unsent
        if updates:
            self.session.move(updates, refit)
            moved = np.array([self.scene.index[n] for n in updates])
            changed = self._unsent = np.union1d(changed, self.scene.subtree_leaves(moved))
        t1 = time.perf_counter()
        result = self.session.frame(frame)
        start, leaves = result.leaves
        # only the transforms of the leaves this frame moved: the history has the others'
        record = protocol.FrameRecord(number, posted, start, leaves, result.fits, changed,
                                      self.session.state.world[changed], result.parts)
        t2 = time.perf_counter()
        # every tile's node-message entry against the frame before, encoded here (often a
        # worker thread) rather than on the event loop when the first stream asks for it
        encode.entries(record, self.history.get(self.latest))
        t3 = time.perf_counter()
        return record, {"update_ms": (t1 - t0) * 1e3, **result.timings,
                        "encode_ms": (t3 - t2) * 1e3,
                        "total_ms": (time.perf_counter() - t0) * 1e3}

    def publish(self, record: protocol.FrameRecord) -> int:
        """Make a computed frame visible and wake whoever waits for it (on the event loop)."""
        if self.closed:
            raise NotFound(f"wall {self.id} was deleted")
        if record.number <= self.latest:
            raise Conflict(f"frame {record.number} is out of order: frame {self.latest} is in")
        self.history.add(record)
        if self._unsent is record.changed:  # (else a frame computed since carries them)
            self._unsent = np.zeros(0, dtype=np.int64)
        self.active = time.monotonic()
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
            if self.closed:  # deleted while this frame waited its turn
                raise NotFound(f"wall {self.id} was deleted")
            record, timings = await asyncio.to_thread(self.compute_frame, frame, updates, number,
                                                      refit)
            return self.publish(record), timings  # (NotFound if deleted while it was culled)

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
        for event in (self._new_frame, self._new_ack, self.gone):
            event.set()

    def _base(self, tiles, number: int, full: bool, since: int,
              held: int | None = None) -> int | None:
        """What the packet (or node message) of ``tiles`` for frame ``number`` is a delta
        against: the frame they have all acknowledged if that is at least ``since``, else None
        (full lists). ``held``: a stream's own newest acknowledgement, used instead of the
        tiles' (another node on the same tiles may have acknowledged a frame that this one
        never received)."""
        if number > self.latest or number < 0:
            raise NotFound(f"frame {number} does not exist yet (latest {self.latest})")
        if self.history.get(number) is None:
            if number > self.history.oldest:
                raise NotFound(f"there is no frame {number}: frame numbers skipped it")
            raise Gone(f"frame {number} has left the history (oldest {self.history.oldest})")
        ack = int(self.acks[tiles].min()) if held is None else held
        base = None if full or ack < 0 or ack < since else ack
        held = base is not None and base < number and self.history.get(base) is not None
        return base if held else None

    def packet(self, tile: int, number: int, full: bool = False, since: int = -1,
               held: int | None = None) -> dict:
        """Tile ``tile``'s packet of frame ``number``: a delta against the tile's acknowledged
        frame if that is at least ``since``, else a full list. A stream passes its first frame
        as ``since``: a node that reconnected holds nothing from before it, and ``held`` (see
        :meth:`node_message`)."""
        self.check_tile(tile)
        return protocol.packet(self.history, number, tile,
                               self._base(tile, number, full, since, held))

    def packet_bytes(self, tile: int, number: int, full: bool = False,
                     since: int = -1, held: int | None = None) -> tuple[memoryview, bool]:
        """:meth:`packet` as msgpack bytes, and whether it is a delta. The first tile to ask
        for a frame against a base encodes every tile's packet of that frame against it
        (:mod:`wallcull.encode`); the others take their slice. ``held``: see
        :meth:`node_message`."""
        self.check_tile(tile)
        base = self._base(tile, number, full, since, held)
        record = self.history.get(number)
        cache = record.__dict__.setdefault("_encoded", {})
        encoded = cache.get(base)
        if encoded is None:
            encoded = cache[base] = encode.frame_packets(self.history, number,
                                                         np.arange(self.wall.tiles), base)
            while len(cache) > 4:
                cache.pop(next(iter(cache)))
        return encoded[tile], base is not None

    def node_message(self, tiles: np.ndarray, number: int, full: bool = False,
                     since: int = -1, binary: bool = True,
                     held: int | None = None) -> tuple[bytes, bool]:
        """The node message of ``tiles`` (sorted, checked) for frame ``number``, msgpack or
        JSON, and whether it is a delta: against the frame all of them acknowledged if that
        is at least ``since`` (a stream's first frame), else full lists. A stream passes
        ``held``, the newest frame acknowledged on itself: several nodes may drive the same
        tiles, and each gets deltas against what it holds."""
        base = self._base(tiles, number, full, since, held)
        if binary:
            return encode.node_message(self.history, number, tiles, base), base is not None
        message = protocol.node_message(self.history, number, tiles, base)
        return protocol.encode(message, False), message["base"] is not None

    def check_tiles(self, tiles) -> np.ndarray:
        """``tiles`` as a sorted array of this wall's tiles (or :class:`NotFound`)."""
        tiles = np.unique(np.asarray(tiles, np.int64))
        if not len(tiles) or tiles[0] < 0 or tiles[-1] >= self.wall.tiles:
            raise NotFound(f"tiles {tiles.tolist()[:8]} are not tiles of wall {self.id} "
                           f"({self.wall.tiles} tiles)")
        return tiles

    def ack(self, tiles, number: int) -> None:
        """Tiles ``tiles`` (a tile or a sorted array of them) have drawn frame ``number``."""
        if isinstance(tiles, (int, np.integer)):
            self.check_tile(int(tiles))
        if number > self.latest:
            raise Conflict(f"cannot acknowledge frame {number}: latest is {self.latest}")
        self.active = time.monotonic()
        tiles = np.atleast_1d(tiles)
        moved = tiles[self.acks[tiles] < number]  # a tile that drew a newer frame keeps its time
        if len(moved):
            self.acks[moved] = number
            self.acked_at[moved] = time.time()
            old, self._new_ack = self._new_ack, asyncio.Event()
            old.set()

    def status(self, now: float | None = None) -> dict:
        """What the operator console shows (:mod:`wallcull.server.pages`), per tile as columns:
        the newest frame's list size, the newest acknowledged frame, the latency of that
        acknowledgement (from the frame's post to the ack, ms; null once the frame has left
        the history), the streams open, and a state: ``acked`` (the newest frame is drawn,
        however long ago), ``offline`` (no stream, no ack for ``LIVE`` seconds), ``waiting``
        (no frame yet), ``drawing`` (not yet) or ``lagging`` (more than ``LAG`` seconds or
        ``LAG_FRAMES`` frames behind); and ``newest``, the newest frame number handed out,
        before a restart too (``frame`` is the newest held: -1 after a restart until a frame
        comes). Numpy over the tiles: cheap, and off the frame path; the columns are
        arrays (a latency unknown is NaN), encoded a piece at a time (a 256 x 256 wall's as
        lists of Python objects took 20 MB at their peak)."""
        now = time.time() if now is None else now
        latest = self.latest
        record = self.history.get(latest)
        tiles = self.wall.tiles
        counts = np.diff(record.start) if record is not None else np.zeros(tiles, np.int64)
        # copied first (one C call each): a console computes this in a worker thread
        acks, acked_at, streams = self.acks.copy(), self.acked_at.copy(), np.zeros(tiles, np.int64)
        for t, n in dict(self.streams).items():
            streams[t] = n
        posted_at = np.full(tiles, np.nan)
        for n, r in dict(self.history.frames).items():
            posted_at[acks == n] = r.time
        latency = np.round((acked_at - posted_at) * 1e3, 2)
        latency[acked_at <= 0] = np.nan
        live = (streams > 0) | (now - acked_at < LIVE)
        behind = (latest - acks > LAG_FRAMES) | \
            ((acks < latest) & (record is not None and now - record.time > LAG))
        # a tile that drew the newest frame has drawn it, streaming or not (a node that pulls
        # over HTTP, a driver pausing): counted as the barrier counts it
        drawn = (acks >= latest) & (latest >= 0)
        state = np.where(drawn, "acked", np.where(~live, "offline", np.where(
            latest < 0, "waiting", np.where(behind, "lagging", "drawing"))))
        return {"wall": self.id, "frame": latest, "newest": self.newest, "time": now,
                "posted": None if record is None else record.time,
                "count": counts, "ack": acks, "latency_ms": latency, "streams": streams,
                "state": state}

    def barrier_state(self, number: int) -> dict:
        acked = int((self.acks >= number).sum())
        return {"frame": number, "acked": acked, "tiles": self.wall.tiles,
                "complete": acked == self.wall.tiles}

    async def barrier(self, number: int, timeout: float) -> dict:
        """Wait until every tile has acknowledged frame ``number`` (the swap barrier)."""
        await self._wait(lambda: self.barrier_state(number)["complete"], lambda: self._new_ack,
                         timeout)
        return self.barrier_state(number)


def check_history(wall, history: int) -> None:
    if history * wall.tiles > MAX_TILE_FRAMES:
        raise InputError(f"a history of {history} frames of {wall.tiles} tiles is more than "
                         f"{MAX_TILE_FRAMES:,} tile-frames; ask for at most "
                         f"{max(2, MAX_TILE_FRAMES // wall.tiles)} frames")


def spec_of(session: WallSession) -> dict:
    """What a restart needs to make ``session`` again (the state folder keeps it as JSON)."""
    s = session.session
    fit = s.fit_options or FitOptions()
    return {"wall": session.wall.to_dict(), "scene": session.scene.name, "method": s.method,
            "bounds": s.state.kind, "pseudo_groups": s.culler.pseudo_groups,
            "history": session.history.size, "depth": fit.depth, "reversed_z": fit.reversed_z,
            "shadow_fit": fit.shadow_fit, "occlusion": s.occlusion, "settings": s.raw_settings}


class FrameNumbers:
    """A wall's frame numbers written down in the state folder ahead of use, so that a
    restart, even after ``SIGKILL``, never hands out a number again: a number beyond what is
    written down writes ``AHEAD`` more (one write in ``AHEAD`` frames, where a write a frame
    at 60 frames/s was 60 SQLite transactions a second, a wall's 20 GB of log a day), and a
    clean stop writes the last one handed out (:meth:`settle`). After a kill the numbers go on
    up to ``AHEAD`` past the last one handed out.

    A frame whose number is beyond what is written down, and cannot be written (a full
    disk, a read-only folder, a folder moved away), is refused (:class:`StateWriteFailed`:
    507 or 503), before it changes anything: served, its number could be handed out again
    after a restart, to another frame, and a node holding the first would take the second for
    it. So a wall whose state folder fails stops within ``AHEAD`` frames, and says why (health
    and metrics too), until the folder is mended."""

    AHEAD = 1024

    def __init__(self, state: StateFolder, wid: str, floor: int):
        self.state, self.wid = state, wid
        self.written = self.handed = floor  # written down up to; handed out up to
        self._lock = threading.Lock()  # the frame's thread, and the event loop's at a stop

    def __call__(self, number: int) -> None:
        """Frame ``number`` is about to be computed and published (StateWriteFailed when its
        number cannot be written down: see the class docstring)."""
        with self._lock:
            if number > self.written:
                self._write(number + self.AHEAD, self.state.set_last_frame)
            self.handed = max(self.handed, number)

    def settle(self) -> None:
        with self._lock:
            try:
                self._write(self.handed, self.state.settle_last_frame)
            except StateWriteFailed:
                pass  # (logged) what is written stays ahead of every number handed out

    def _write(self, number: int, how: Callable[[str, int], None]) -> None:
        try:
            how(self.wid, number)
            self.written = number
        except StateWriteFailed as exc:
            log.warning("%s", exc)
            raise


class Walls:
    """The wall sessions of a server, by id, with a cap on how many exist at once, the grants
    of their credentials, and (with a state folder) what a restart needs to bring them back.
    A wall of the state folder whose scene cannot be loaded (its file is missing) is kept,
    *unavailable* (:class:`Unavailable`, 503), and comes back when its scene does
    (:meth:`retry`)."""

    def __init__(self, limit: int = 32, state: StateFolder | None = None):
        self.limit = limit
        self.state = state
        self.sessions: dict[str, WallSession] = {}
        self.grants: dict[str, credentials.Issued] = {}  # wall id -> its credentials
        #: walls of the state folder waiting for their scene: id -> (row, why)
        self.unavailable: dict[str, tuple[WallRow, str]] = {}
        self.making: dict[str, int] = {}  # walls being made, how many on each scene
        #: called with every wall as it joins (the NATS bridge publishes it from then on)
        self.on_add: list[Callable[[WallSession], None]] = []

    def create(self, scene: Scene, wall, method: str, bounds: str, pseudo_groups: bool,
               history: int, fit: FitOptions = FitOptions(), nodes=None,
               settings: Mapping[str, Any] | None = None, occlusion: str = "off"
               ) -> WallSession:
        """A new wall, with its credentials in ``.credentials``, to be shown this once:
        ``{"driver": token, "nodes": [{"tiles", "token"}, ...]}`` (``nodes`` groups tiles
        under one node credential; by default a node per tile). ``settings``: lights and
        mirrors for this wall instead of the scene's own. With a state folder, the wall is
        written down before it is returned. (The server does the same in steps: the slow ones
        in a worker thread, :meth:`reservation`, :meth:`build`, :meth:`register`.)"""
        with self.reservation(scene.name):
            session, grants = self.build(scene, wall, method, bounds, pseudo_groups, history,
                                         fit, nodes, settings, occlusion)
            self.register(session, grants)
        return session

    @contextmanager
    def reservation(self, scene: str):
        """Hold a place for a wall being made on ``scene`` (refused when there is none: 409),
        and the scene with it: an upload may not replace a scene while a wall is being made
        on it, which would cull the old scene while the server serves the new one."""
        self.check_room()
        self.making[scene] = self.making.get(scene, 0) + 1
        try:
            yield
        finally:
            self.making[scene] -= 1
            if not self.making[scene]:
                del self.making[scene]

    def check_room(self) -> None:
        if len(self.sessions) + len(self.unavailable) + sum(self.making.values()) >= self.limit:
            raise Conflict(f"the server already holds {self.limit} walls; delete one first")

    def build(self, scene: Scene, wall, method: str, bounds: str, pseudo_groups: bool,
              history: int, fit: FitOptions = FitOptions(), nodes=None,
              settings: Mapping[str, Any] | None = None,
              occlusion: str = "off") -> tuple[WallSession, dict]:
        """Make a wall, issue its credentials and write it to the state folder: seconds for a
        256 x 256 wall (65,536 credentials), so the server runs it in a worker thread. The
        wall is the server's once :meth:`register` is called (on the event loop)."""
        session = self.make(secrets.token_hex(6), scene, wall, method, bounds, pseudo_groups,
                            history, fit, settings, occlusion)
        session.credentials, session.issued = credentials.issue(session.id, wall.tiles, nodes)
        if self.state is not None:
            self.state.add_wall(session.id, session.created, spec_of(session), session.issued)
        return session, session.issued

    def register(self, session: WallSession, issued: credentials.Issued) -> None:
        self._add(session, issued)

    @staticmethod
    def make(wid: str, scene: Scene, wall, method: str, bounds: str,
                 pseudo_groups: bool, history: int, fit: FitOptions,
                 settings: Mapping[str, Any] | None = None, occlusion: str = "off"
                 ) -> WallSession:
        check_history(wall, history)
        session = Session(scene, wall, method, bounds, pseudo_groups, fit, settings,
                          occlusion=OcclusionOptions.parse(occlusion))
        return WallSession(wid, session, protocol.History(history))

    def _add(self, session: WallSession, issued: credentials.Issued) -> None:
        if self.state is not None:
            session.on_number = FrameNumbers(self.state, session.id, session.floor)
        session.issued = issued
        self.grants[session.id] = issued
        self.sessions[session.id] = session
        for added in self.on_add:  # created, restored at start, or back with its scene
            added(session)

    def check_specs(self) -> None:
        """Refuse to start (one line naming the state database and the wall) when a wall
        of the state folder cannot be made whatever its scene: its spec is not one this
        server reads. Nothing is changed on disk."""
        if self.state is None:
            return
        for row in self.state.walls():
            try:
                spec = row.spec
                Wall.from_dict(spec["wall"])
                FitOptions(spec["depth"], spec["reversed_z"], spec.get("shadow_fit", "refined"))
                OcclusionOptions.parse(spec.get("occlusion", "off"))
                for key in ("scene", "method", "bounds", "pseudo_groups", "history"):
                    spec[key]
            except (InputError, KeyError, TypeError, ValueError) as exc:
                what = f"missing {exc}" if isinstance(exc, KeyError) else str(exc)
                raise InputError(f"state database {self.state.file}: wall {row.id} has a spec "
                                 f"this server cannot read ({what}); the file is left "
                                 "untouched: run the wallcull that wrote it, or move the file "
                                 "aside to start with no walls") from None

    async def restore(self, store: SceneStore) -> list[str]:
        """Bring back the walls of the state folder, under their ids, with their credentials,
        numbering frames after the last one handed out. A wall whose scene cannot be loaded
        now is kept unavailable (with a warning) until :meth:`retry` finds it. Returns the
        ids restored."""
        if self.state is None:
            return []
        for row in self.state.walls():
            self.unavailable[row.id] = (row, "not restored yet")
            self.grants[row.id] = row.grants
        return await self.retry(store)

    async def retry(self, store: SceneStore) -> list[str]:
        """Restore the unavailable walls whose scenes load now; the ids restored."""
        out = []
        for wid, (row, _) in list(self.unavailable.items()):
            spec = row.spec
            try:
                scene = await store.get(spec["scene"])
                fit = FitOptions(spec["depth"], spec["reversed_z"],
                                 spec.get("shadow_fit", "refined"))
                await store.bounds(scene, spec["bounds"])
                session = await background(
                    self.make, row.id, scene, Wall.from_dict(spec["wall"]), spec["method"],
                    spec["bounds"], spec["pseudo_groups"], spec["history"], fit,
                    spec.get("settings"), spec.get("occlusion", "off"))
            except (InputError, NotFound, OSError) as exc:
                reason = f"its scene {spec['scene']!r} cannot be loaded: {exc}"
                if self.unavailable.get(wid, (None, ""))[1] != reason:
                    log.warning("wall %s is unavailable until %s comes back: %s", wid,
                                spec["scene"], exc)
                if wid in self.unavailable:  # not deleted meanwhile
                    self.unavailable[wid] = (row, reason)
                continue
            if self.unavailable.pop(wid, None) is None:
                continue  # deleted while its scene loaded
            session.created, session.floor = row.created, row.last_frame
            self._add(session, row.grants)
            out.append(row.id)
        return out

    def grant(self, token: str) -> Grant | None:
        """What an issued credential holds, or None."""
        raw = credentials.raw_digest(token)
        for wid, issued in self.grants.items():
            found = issued.find(raw)
            if found is not None:
                return found if wid in self.sessions or wid in self.unavailable else None
        return None

    def get(self, wid: str) -> WallSession:
        try:
            return self.sessions[wid]
        except KeyError:
            if wid in self.unavailable:
                raise Unavailable(f"wall {wid} is unavailable: "
                                  f"{self.unavailable[wid][1]}; it comes back when its scene "
                                  "does") from None
            raise NotFound(f"no wall {wid!r}") from None

    def delete(self, wid: str) -> None:
        """Delete a wall (an unavailable one too): on disk first, so that a failed write
        leaves it whole."""
        if wid in self.unavailable:
            if self.state is not None:
                self.state.remove_wall(wid)
            self.unavailable.pop(wid)
            self.grants.pop(wid, None)
            return
        session = self.get(wid)
        if self.state is not None:
            self.state.remove_wall(wid)
        self.forget(wid)

    def settle(self) -> None:
        """At a clean stop: every wall's last frame number written down as it is, so that a
        restart numbers on right after it (see :class:`FrameNumbers`)."""
        for session in self.sessions.values():
            if isinstance(session.on_number, FrameNumbers):
                session.on_number.settle()

    def forget(self, wid: str) -> None:
        """Delete a wall from memory (once :meth:`StateFolder.remove_wall` has, from disk)."""
        session = self.get(wid)
        session.close()
        del self.sessions[wid]
        self.grants.pop(wid, None)

    def idle(self, ttl: float) -> list[str]:
        """The walls with no stream open and no frame or acknowledgement for ``ttl`` s."""
        now = time.monotonic()
        return [wid for wid, w in self.sessions.items()
                if w.subscribers + w.consoles == 0 and now - w.active > ttl]

    def scene_names(self) -> dict[str, set[str]]:
        """The scenes walls use, with the walls' ids (the scene cache keeps them; an upload
        may not replace them; an unavailable wall's scene may be uploaded again)."""
        out: dict[str, set[str]] = {name: {"one being made"} for name in self.making}
        for w in self.sessions.values():
            out.setdefault(w.scene.name, set()).add(w.id)
        return out
