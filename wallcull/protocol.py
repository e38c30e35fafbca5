"""The wire: codecs (msgpack and JSON carry the same schema) and per-tile packets with deltas.

A *packet* tells one tile's render node what to draw for one frame::

    {"frame": n, "tile": t, "time": <server clock when frame n was posted, s>,
     "base": b,                      # the frame the delta is against, or null for a full list
     "visible": [leaf ids],          # full packets only
     "added": [ids], "removed": [ids],   # deltas only: list(n) = list(b) + added - removed
     "count": len(list(n)),          # for the client to check itself
     "ranges": [[leaf, first, count, first, count, ...], ...],  # leaves drawn in part
     "whole": [ids],                 # deltas only: partial in the base, drawn whole now
     "transforms": {"ids": [...], "matrices": [[16 floats, row by row], ...]},  # moved leaves
     ...fitted frusta ("view", "projection", ...: see wallcull.fit)}

Lists hold leaf ids (``scene.leaves``), sorted. The base of a delta is the frame the tile last
acknowledged, so a render node keeps the lists of the frames it has not yet seen acknowledged;
it asks for a full packet (or gets one) when it is new, when it asks, or when its
acknowledged frame has fallen out of the server's history. A stream makes deltas only
against frames acknowledged since it opened, so a node that reconnects without its lists gets
full ones until an acknowledgement on the new stream lands; over HTTP, such a node asks with
``full=true`` and acknowledges that frame before asking for deltas. ``transforms`` carries the
world transforms of the leaves in the list that moved (dynamic scenes) and that the client may
not have: every moved leaf in a full packet; in a delta, the added ones and those that moved
since the base.

A leaf of the list that the tile shows only in part (its clusters, :mod:`wallcull.clusters`)
comes with its *draw ranges*: the runs ``[first, first + count)`` of its mesh's triangles to
draw, sorted, adjacent ones merged; every other listed leaf is drawn whole. A full packet
carries every partial leaf's ranges; a delta those new or changed since the base, and in
``whole`` the base's partial leaves still listed and now drawn whole (a leaf that leaves the
list takes its ranges with it). Empty ``ranges`` and ``whole`` are left out.

A *node message* carries one frame to a render node that drives several tiles (one message
and one acknowledgement per node per frame; a node of one tile is the special case). What the
tiles share goes once; each tile's projection goes as its frustum's extent and depth range,
which a node turns back into the exact matrix (:mod:`wallcull_clients.frusta`)::

    {"frame": n, "time": t, "base": b,          # one base for every tile: the node's ack
     "reversed_z": true,                        # when the projections are (shadows' never)
     "view": {"rotation": [w, x, y, z], "translation": [x, y, z]},  # a grid's, shared
     "left": {"view": ...}, "right": {...},     # a grid's eye views, stereo frames
     "transforms": {"ids": [...], "matrices": [...]},   # moved leaves any tile may lack
     "tiles": [{"tile": t,                    # a delta leaves out the tiles with nothing new
                "visible": [...],               # the list, or the delta's non-empty parts
                "added": [...], "removed": [...],  # (when shorter than the list)
                "count": c,
                "ranges": [...], "whole": [...],  # as in a packet
                "view": {...},                  # screens: each tile's own eye space
                "extent": [l/n, r/n, b/n, t/n], # the frustum's sides, as tangents
                "depth": [n, f],                # its near and far distances
                "shadows": [...], "mirrors": [...],          # as in a packet
                "left": {"view"?, "extent"?, "depth", "mirrors"?}, "right": {...}}, ...]}

A view is rigid: the rotation of the unit quaternion, then the translation. A tile's extent
is the same from frame to frame while the tracked eye stays put, and its depth range while
what it shows keeps its depth (a tile showing nothing keeps the wall's), so a delta carries
each only when it changed since the base: a node keeps them by frame, like its lists. A
tight depth range is rounded outward to float32 (:func:`wallcull.fit.depth_ranges`), which
then carries it exactly in 5 bytes a number. So a delta of a tile whose list did not change
costs 10 to 25 bytes, where a packet repeats 300 bytes of matrices, and a tile with nothing
new (the same list, extent and depth, no view, shadows, mirrors or eyes of its own) has no
entry in a delta at all: the node keeps the base's. On a 16 x 16 wall most tiles are empty or
unchanged from one frame to the next; leaving them out took a delta from 16.3 to 11.4 kB.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
from numba import njit

from .errors import InputError

MSGPACK = "application/msgpack"
JSON = "application/json"


def wants_msgpack(accept: str | None) -> bool:
    """Whether an ``Accept`` header prefers msgpack to JSON (q-values honoured)."""
    if not accept:
        return False
    best, best_q = None, 0.0  # q=0 means "not acceptable" (RFC 9110, 12.4.2)
    for part in accept.lower().split(","):
        media, *params = [p.strip() for p in part.split(";")]
        q = 1.0
        for p in params:
            if p.startswith("q="):
                try:
                    q = float(p[2:])
                except ValueError:
                    q = 0.0
        if media in (MSGPACK, "application/x-msgpack", JSON, "*/*", "application/*") and q > best_q:
            best, best_q = media, q
    return best in (MSGPACK, "application/x-msgpack")


def encode(obj: Any, msgpack_format: bool) -> bytes:
    if msgpack_format:
        return msgpack.packb(obj, use_bin_type=True)
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def decode(body: bytes, msgpack_format: bool) -> Any:
    """Parse a request body; malformed input is an :class:`InputError`."""
    try:
        if msgpack_format:
            return msgpack.unpackb(body, raw=False, strict_map_key=True)
        return json.loads(body)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError,
            TypeError, RecursionError) as exc:  # RecursionError: JSON nested too deep
        kind = "msgpack" if msgpack_format else "JSON"
        raise InputError(f"malformed {kind} body: {type(exc).__name__}: {exc}".rstrip(": ")
                         ) from None


def rows(m: np.ndarray) -> list:
    """A matrix as nested lists, row by row (SPEC section 1)."""
    return np.asarray(m, dtype=np.float64).tolist()


@dataclass
class FrameRecord:
    """What the server keeps of one frame: per-tile leaf lists, fits, moved leaves, and the
    draw ranges of the leaves each tile shows in part (``parts``: CSR ``(part_start (tiles +
    1,), part_leaf, range_start, ranges (R, 2))`` as :meth:`wallcull.cull.Visibility.
    draw_ranges` gives them; None: every leaf drawn whole).

    A record keeps the transforms of the leaves that moved in its frame only; the pose of any
    other leaf that ever moved is that of the newest frame before that moved it
    (:meth:`History.poses`), so that a record's size does not grow with every leaf moved
    before it."""

    number: int
    time: float
    start: np.ndarray  # (tiles + 1,) CSR offsets into leaves
    leaves: np.ndarray  # per-tile sorted leaf ids, concatenated
    fits: list[dict]  # per tile, JSON-ready fitted frusta
    changed: np.ndarray  # sorted leaf ids whose world transform changed in this frame
    changed_world: np.ndarray  # (len(changed), 4, 4) their world transforms at this frame
    parts: tuple | None = None

    def __post_init__(self):
        if self.parts is None:
            none = np.zeros(0, np.int64)
            self.parts = (np.zeros(len(self.start), np.int64), none, np.zeros(1, np.int64),
                          np.zeros((0, 2), np.int64))

    def tile(self, tile: int) -> np.ndarray:
        return self.leaves[self.start[tile]:self.start[tile + 1]]

    def tile_parts(self, tile: int, which=None) -> list[list[int]]:
        """Tile ``tile``'s partial leaves on the wire: ``[[leaf, first, count, first, count,
        ...], ...]`` (``which``: indices into the frame's parts, else all of the tile's)."""
        part_start, part_leaf, range_start, ranges = self.parts
        if which is None:
            which = range(part_start[tile], part_start[tile + 1])
        return [[int(part_leaf[p]), *ranges[range_start[p]:range_start[p + 1]].ravel().tolist()]
                for p in which]


@dataclass
class History:
    """The last ``size`` frames, by number, and what it takes to know the pose of every leaf
    that ever moved at any held frame (:meth:`poses`) while each record keeps only the leaves
    its frame moved: per leaf, the newest frame that moved it, and the poses the frames that
    have left gave (each leaf's newest). Frames are added in order of their numbers."""

    size: int = 64
    frames: OrderedDict = field(default_factory=OrderedDict)
    #: the number of the first frame added that moved a leaf (None: none yet)
    first_moved: int | None = None
    # by leaf id: the newest frame that moved it (-1: none), and its row in _gone_world, the
    # poses of the frames that have left the history (-1: none)
    _last: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    _gone_row: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32), repr=False)
    _gone_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)), repr=False)
    _gone_count: int = 0
    _lock: Any = field(default_factory=threading.Lock, repr=False)

    def add(self, record: FrameRecord) -> None:
        with self._lock:
            self.frames[record.number] = record
            ids = record.changed
            if len(ids):
                if self.first_moved is None:
                    self.first_moved = record.number
                self._last = _grown(self._last, int(ids.max()) + 1)
                self._last[ids] = record.number
            while len(self.frames) > self.size:
                self._keep_poses(self.frames.popitem(last=False)[1])

    def _keep_poses(self, record: FrameRecord) -> None:
        ids = record.changed
        if not len(ids):
            return
        self._gone_row = _grown(self._gone_row, int(ids.max()) + 1)
        new = ids[self._gone_row[ids] < 0]
        if self._gone_count + len(new) > len(self._gone_world):
            grown = np.empty((max(self._gone_count + len(new), 2 * len(self._gone_world)), 4, 4))
            grown[:self._gone_count] = self._gone_world[:self._gone_count]
            self._gone_world = grown
        self._gone_row[new] = np.arange(self._gone_count, self._gone_count + len(new))
        self._gone_count += len(new)
        self._gone_world[self._gone_row[ids]] = record.changed_world

    def get(self, number: int) -> FrameRecord | None:
        return self.frames.get(number)

    @property
    def latest(self) -> int:
        return next(reversed(self.frames)) if self.frames else -1

    @property
    def oldest(self) -> int:
        return next(iter(self.frames)) if self.frames else -1

    def changed_since(self, base: int, number: int) -> np.ndarray:
        """Leaves moved in the held frames numbered ``(base, number]``. Every frame posted in
        that range is held when ``base`` is. Numbers may skip: walk the held frames, never the
        range (a jump to 2**40 would take forever)."""
        parts = [r.changed for k, r in self.frames.items() if base < k <= number]
        return np.unique(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)

    def dynamic(self, record: FrameRecord) -> bool:
        """Whether any leaf moved in ``record``'s frame or before."""
        return bool(len(record.changed)) or (self.first_moved is not None
                                             and self.first_moved <= record.number)

    def poses(self, record: FrameRecord, leaves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(ids, world (k, 4, 4))``: of the sorted ``leaves``, those moved in ``record``'s
        frame or before, with their world transforms at that frame: each from the newest frame
        up to it that moved the leaf (its record if held, else the poses of the frames that
        have left)."""
        leaves = np.asarray(leaves, np.int64)
        with self._lock:
            if self.frames.get(record.number) is not record:
                return self._walk(record, leaves)
            stamp = np.full(len(leaves), -1, np.int64)
            inside = leaves < len(self._last)
            stamp[inside] = self._last[leaves[inside]]
            world = np.empty((len(leaves), 4, 4))
            found = (stamp >= 0) & (stamp <= record.number)
            gone = np.flatnonzero(found & (stamp < self.oldest))
            world[gone] = self._gone_world[self._gone_row[leaves[gone]]]
            held = np.flatnonzero(found & (stamp >= self.oldest))
            held = held[np.argsort(stamp[held], kind="stable")]
            numbers, first = np.unique(stamp[held], return_index=True)
            for number, group in zip(numbers.tolist(), np.split(held, first[1:])):
                r = self.frames[number]
                world[group] = r.changed_world[np.searchsorted(r.changed, leaves[group])]
            # moved again since: their pose at this frame is in the frames before it
            later = np.flatnonzero(stamp > record.number)
            if len(later):
                ids, moved = self._walk(record, leaves[later])
                hit = later[np.isin(leaves[later], ids, assume_unique=True)]
                world[hit] = moved
                found[hit] = True
        return leaves[found], world[found]

    def _walk(self, record: FrameRecord, leaves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`poses` by walking the records from ``record`` back, then the poses of the
        frames that have left (for a few leaves, or a record not held)."""
        older = [r for k, r in reversed(self.frames.items())
                 if k < record.number and len(r.changed)]
        world = np.empty((len(leaves), 4, 4))
        found = np.zeros(len(leaves), bool)
        for r in (record, *older):
            if found.all():
                break
            if not len(r.changed):
                continue
            at = np.minimum(np.searchsorted(r.changed, leaves), len(r.changed) - 1)
            hit = (r.changed[at] == leaves) & ~found
            world[hit] = r.changed_world[at[hit]]
            found |= hit
        rest = np.flatnonzero(~found)
        rest = rest[leaves[rest] < len(self._gone_row)]
        row = self._gone_row[leaves[rest]]
        rest, row = rest[row >= 0], row[row >= 0]
        world[rest] = self._gone_world[row]
        found[rest] = True
        return leaves[found], world[found]


def _grown(a: np.ndarray, n: int) -> np.ndarray:
    """``a`` (by leaf id) long enough for ``n`` ids, doubling, new ids at -1."""
    if n <= len(a):
        return a
    out = np.full(max(n, 2 * len(a)), -1, a.dtype)
    out[:len(a)] = a
    return out


def tile_deltas(record: FrameRecord, prior: FrameRecord):
    """Every tile's delta of ``record`` against ``prior`` at once, in CSR form
    ``(added, added_start, removed, removed_start)``, cached on ``record``: the streams ask for
    every tile against the same base. One compiled merge of each tile's two sorted lists."""
    return _per_base(record, "_deltas", prior, lambda: _merge_deltas(
        record.start, record.leaves, prior.start, prior.leaves))


def _per_base(record: FrameRecord, name: str, prior: FrameRecord, compute):
    """``compute()``, kept on ``record`` under ``name`` for the base ``prior`` (the last four
    bases asked for)."""
    cache = record.__dict__.setdefault(name, {})
    if prior.number not in cache:
        cache[prior.number] = compute()
        while len(cache) > 4:
            cache.pop(next(iter(cache)))
    return cache[prior.number]


@njit(cache=True, nogil=True)
def _merge_deltas(start, leaves, prior_start, prior_leaves):
    tiles = start.shape[0] - 1
    added = np.empty(leaves.shape[0], np.int64)
    removed = np.empty(prior_leaves.shape[0], np.int64)
    added_start = np.zeros(tiles + 1, np.int64)
    removed_start = np.zeros(tiles + 1, np.int64)
    na = nr = 0
    for t in range(tiles):
        i, j = start[t], prior_start[t]
        i_end, j_end = start[t + 1], prior_start[t + 1]
        while i < i_end or j < j_end:
            if j >= j_end or (i < i_end and leaves[i] < prior_leaves[j]):
                added[na] = leaves[i]
                na += 1
                i += 1
            elif i >= i_end or prior_leaves[j] < leaves[i]:
                removed[nr] = prior_leaves[j]
                nr += 1
                j += 1
            else:
                i += 1
                j += 1
        added_start[t + 1] = na
        removed_start[t + 1] = nr
    return added[:na], added_start, removed[:nr], removed_start


def part_deltas(record: FrameRecord, prior: FrameRecord):
    """Every tile's change of draw ranges from ``prior`` to ``record``, in CSR form ``(changed,
    changed_start, whole, whole_start)``, cached on ``record``: the partial leaves whose ranges
    are new or differ (indices into ``record.parts``), and the leaves partial in ``prior``,
    still listed, now drawn whole."""
    return _per_base(record, "_part_deltas", prior, lambda: _merge_parts(
        record.start, record.leaves, *record.parts, *prior.parts))


@njit(cache=True, nogil=True)
def _merge_parts(start, leaves, part_start, part_leaf, range_start, ranges,
                 prior_part_start, prior_part_leaf, prior_range_start, prior_ranges):
    tiles = start.shape[0] - 1
    changed = np.empty(part_leaf.shape[0], np.int64)
    whole = np.empty(prior_part_leaf.shape[0], np.int64)
    changed_start = np.zeros(tiles + 1, np.int64)
    whole_start = np.zeros(tiles + 1, np.int64)
    nc = nw = 0
    for t in range(tiles):
        i, j, li = part_start[t], prior_part_start[t], start[t]
        while i < part_start[t + 1] or j < prior_part_start[t + 1]:
            if j >= prior_part_start[t + 1] or (i < part_start[t + 1]
                                                 and part_leaf[i] < prior_part_leaf[j]):
                changed[nc] = i  # partial now, not before
                nc += 1
                i += 1
            elif i >= part_start[t + 1] or prior_part_leaf[j] < part_leaf[i]:
                leaf = prior_part_leaf[j]  # partial before, not now: whole, if still listed
                while li < start[t + 1] and leaves[li] < leaf:
                    li += 1
                if li < start[t + 1] and leaves[li] == leaf:
                    whole[nw] = leaf
                    nw += 1
                j += 1
            else:
                a, b = range_start[i], range_start[i + 1]
                c, d = prior_range_start[j], prior_range_start[j + 1]
                same = b - a == d - c
                k = 0
                while same and k < b - a:
                    same = (ranges[a + k, 0] == prior_ranges[c + k, 0]
                            and ranges[a + k, 1] == prior_ranges[c + k, 1])
                    k += 1
                if not same:
                    changed[nc] = i
                    nc += 1
                i += 1
                j += 1
        changed_start[t + 1] = nc
        whole_start[t + 1] = nw
    return changed[:nc], changed_start, whole[:nw], whole_start


def _parts(record: FrameRecord, prior: FrameRecord | None, tile: int) -> dict:
    """A tile's draw ranges in a packet or entry: all of them (``ranges``) when ``prior`` is
    None, else those new or changed since it (``ranges``) and the leaves drawn whole again
    (``whole``); empty keys left out."""
    out: dict[str, Any] = {}
    if prior is None:
        ranges = record.tile_parts(tile)
    else:
        changed, c_start, whole, w_start = part_deltas(record, prior)
        ranges = record.tile_parts(tile, changed[c_start[tile]:c_start[tile + 1]])
        if w_start[tile + 1] > w_start[tile]:
            out["whole"] = whole[w_start[tile]:w_start[tile + 1]].tolist()
    if ranges:
        out["ranges"] = ranges
    return out


def packet(history: History, number: int, tile: int, base: int | None) -> dict:
    """Tile ``tile``'s packet of frame ``number``, a delta against frame ``base`` when given
    and still held (else a full list)."""
    record = history.frames[number]
    current = record.tile(tile)
    out: dict[str, Any] = {"frame": number, "tile": tile, "time": record.time}
    prior = history.get(base) if base is not None and base < number else None
    added = None
    if prior is None:
        out["base"] = None
        out["visible"] = current.tolist()
    else:
        added_all, a_start, removed_all, r_start = tile_deltas(record, prior)
        added = added_all[a_start[tile]:a_start[tile + 1]]
        out["base"] = base
        out["added"] = added.tolist()
        out["removed"] = removed_all[r_start[tile]:r_start[tile + 1]].tolist()
    out["count"] = len(current)
    out.update(_parts(record, prior, tile))
    moved = transforms(history, record, tile, out["base"], added)
    if moved is not None:
        out["transforms"] = moved
    out.update(record.fits[tile])
    return out


def transforms(history: History, record: FrameRecord, tiles, base: int | None,
               added: np.ndarray | None) -> dict | None:
    """The world transforms a packet or node message carries (moved leaves the node may not
    have) for ``tiles`` (a tile or several): every moved leaf of their full lists; in a delta
    against ``base``, the ``added`` leaves and those of the lists that moved since the base.
    None when there are none."""
    if not history.dynamic(record):
        return None  # nothing ever moved
    tiles = np.atleast_1d(tiles)
    current = record.tile(int(tiles[0])) if len(tiles) == 1 else \
        np.unique(np.concatenate([record.tile(int(t)) for t in tiles]))
    if base is None:
        send = current
    else:
        send = np.union1d(added, np.intersect1d(current, history.changed_since(base,
                                                                               record.number),
                                                assume_unique=True))
    if not len(send):
        return None
    ids, world = history.poses(record, send)
    if not len(ids):
        return None
    return {"ids": ids.tolist(), "matrices": world.reshape(-1, 16).tolist()}


def node_head(number: int, time: float, fits, base: int | None) -> dict:
    """What every node message of a frame shares (see the module docstring)."""
    head: dict[str, Any] = {"frame": number, "time": float(time), "base": base}
    if fits.reversed_z:
        head["reversed_z"] = True
    if fits.view.ndim == 2:  # a grid: one view for every tile
        c = fits.compact
        head["view"] = _rigid(c.rotation[0], c.translation[0])
        for e, key in zip(range(len(fits.eyes)), ("left", "right")):
            head[key] = {"view": _rigid(c.e_rotation[e, 0], c.e_translation[e, 0])}
    return head


def _frustum(sends, tangents: np.ndarray, depth: np.ndarray) -> dict:
    """A tile's (or an eye's) extent and depth range, those that ``sends``."""
    out = {}
    if sends[0]:
        out["extent"] = tangents.tolist()
    if sends[1]:
        out["depth"] = depth.tolist()
    return out


def _rigid(rotation: np.ndarray, translation: np.ndarray) -> dict:
    return {"rotation": rotation.tolist(), "translation": translation.tolist()}


def node_message(history: History, number: int, tiles, base: int | None) -> dict:
    """The node message of frame ``number`` for ``tiles`` (see the module docstring): deltas
    against frame ``base`` when it is given and still held, else full lists. The reference the
    compiled encoder (:func:`wallcull.encode.node_message`) is held to, and the JSON form."""
    record = history.frames[number]
    tiles = [int(t) for t in tiles]
    prior = history.get(base) if base is not None and base < number else None
    base = None if prior is None else base
    fits = record.fits
    c = fits.compact
    own_view = fits.view.ndim == 3
    sends = np.ones((len(fits), 2), bool) if prior is None else c.changed(prior.fits.compact)
    out = node_head(number, record.time, fits, base)
    entries, added = [], []
    for t in tiles:
        pkt = packet(history, number, t, base)
        entry: dict[str, Any] = {"tile": t}
        changes = 0 if base is None else len(pkt["added"]) + len(pkt["removed"])
        if base is None or 0 < changes >= pkt["count"]:
            entry["visible"] = record.tile(t).tolist()  # no longer than the delta
        else:
            entry.update({k: pkt[k] for k in ("added", "removed") if pkt[k]})
        if base is not None:
            added += pkt["added"]
        entry["count"] = pkt["count"]
        entry.update({k: pkt[k] for k in ("ranges", "whole") if k in pkt})
        if own_view:
            entry["view"] = _rigid(c.rotation[t], c.translation[t])
        entry.update(_frustum(sends[t], c.tangents[t], c.depth[t]))
        entry.update({k: pkt[k] for k in ("shadows", "mirrors") if k in pkt})
        for e, key in zip(range(len(fits.eyes)), ("left", "right")):
            part: dict[str, Any] = {}
            if own_view:
                part["view"] = _rigid(c.e_rotation[e, t], c.e_translation[e, t])
            part.update(_frustum(sends[t], c.e_tangents[e, t], c.e_depth[e, t]))
            if "mirrors" in pkt[key]:
                part["mirrors"] = pkt[key]["mirrors"]
            entry[key] = part
        if base is not None and changes == 0 and set(entry) <= {"tile", "count"}:
            continue  # nothing new: the node keeps the base's list and frusta
        entries.append(entry)
    moved = transforms(history, record, tiles, base,
                       None if base is None else np.unique(np.array(added, np.int64)))
    if moved is not None:
        out["transforms"] = moved
    out["tiles"] = entries
    return out


_OWN = object()  # apply(): the packet's own base


def apply_parts(held: dict | None, pkt: dict, leaves: np.ndarray, base: Any = _OWN) -> dict:
    """A client's draw ranges after a packet (or a node message's tile entry, with the
    message's ``base``): ``{leaf: ranges (k, 2)}`` of the leaves drawn in part, every other
    leaf of ``leaves`` (the list after the packet) drawn whole. A full packet holds them all;
    a delta holds those new or changed since the base (``ranges``), and the base's partial
    leaves drawn whole again (``whole``); the base's others stay, if still listed."""
    base = pkt.get("base") if base is _OWN else base
    out = {}
    if base is not None:
        if held is None:
            raise InputError(f"delta against frame {base}, whose ranges are not held")
        whole = set(pkt.get("whole", ()))
        kept = [leaf for leaf in held if leaf not in whole]
        out = {leaf: held[leaf] for leaf, ok in zip(kept, _listed(kept, leaves)) if ok}
    for item in pkt.get("ranges", ()):
        if len(item) < 3 or len(item) % 2 != 1:
            raise InputError(f"a tile's ranges must be [leaf, first, count, ...], got {item}")
        out[int(item[0])] = np.asarray(item[1:], dtype=np.int64).reshape(-1, 2)
    return out


def _listed(ids: list, leaves: np.ndarray) -> np.ndarray:
    """Whether each of ``ids`` is in ``leaves``: by binary search where ``leaves`` is sorted,
    as lists are (a node applies a delta every frame, and ``np.isin`` sorts both)."""
    ids = np.asarray(ids, np.int64)
    if not len(ids) or not len(leaves):
        return np.zeros(len(ids), bool)
    leaves = np.asarray(leaves)
    if (leaves[1:] < leaves[:-1]).any():
        return np.isin(ids, leaves)
    at = np.minimum(np.searchsorted(leaves, ids), len(leaves) - 1)
    return leaves[at] == ids


def apply(held: np.ndarray | None, pkt: dict, base: Any = _OWN) -> np.ndarray:
    """A client's list after a packet (or a node message's tile entry, with the message's
    ``base``): the full list (``visible``), or ``held`` (the base frame's list) plus the
    delta. Raises :class:`InputError` when the result contradicts the packet's count."""
    base = pkt.get("base") if base is _OWN else base
    if base is None or "visible" in pkt:
        out = np.asarray(pkt["visible"], dtype=np.int64)
    else:
        if held is None:
            raise InputError(f"delta against frame {base}, whose list is not held")
        out = _apply_delta(np.asarray(held, dtype=np.int64),
                           np.asarray(pkt.get("removed", ()), dtype=np.int64),
                           np.asarray(pkt.get("added", ()), dtype=np.int64))
    if len(out) != pkt["count"]:
        what = f"packet of frame {pkt['frame']}" if "frame" in pkt else \
            f"tile {pkt.get('tile')}'s list"
        raise InputError(f"{what} does not add up: {len(out)} leaves, count {pkt['count']}")
    return out


@njit(cache=True)
def _apply_delta(held, removed, added):
    """``(held - removed) | added`` of sorted id arrays, sorted and unique, in one merge (what
    ``np.union1d(np.setdiff1d(held, removed), added)`` gives, without its sorts)."""
    out = np.empty(held.shape[0] + added.shape[0], np.int64)
    i = j = k = n = 0
    while i < held.shape[0] or k < added.shape[0]:
        if k >= added.shape[0] or (i < held.shape[0] and held[i] < added[k]):
            value = held[i]
            i += 1
            while j < removed.shape[0] and removed[j] < value:
                j += 1
            if j < removed.shape[0] and removed[j] == value:
                continue
        else:
            value = added[k]
            k += 1
            if i < held.shape[0] and held[i] == value:
                i += 1
        if n == 0 or out[n - 1] != value:
            out[n] = value
            n += 1
    return out[:n]
