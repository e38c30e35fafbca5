"""The wire: codecs (msgpack and JSON carry the same schema) and per-tile packets with deltas.

A *packet* tells one tile's render node what to draw for one frame::

    {"frame": n, "tile": t, "time": <server clock when frame n was posted, s>,
     "base": b,                      # the frame the delta is against, or null for a full list
     "visible": [leaf ids],          # full packets only
     "added": [ids], "removed": [ids],   # deltas only: list(n) = list(b) + added - removed
     "count": len(list(n)),          # for the client to check itself
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
"""

from __future__ import annotations

import json
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
    """What the server keeps of one frame: per-tile leaf lists, fits, and moved leaves."""

    number: int
    time: float
    start: np.ndarray  # (tiles + 1,) CSR offsets into leaves
    leaves: np.ndarray  # per-tile sorted leaf ids, concatenated
    fits: list[dict]  # per tile, JSON-ready fitted frusta
    changed: np.ndarray  # leaf ids whose world transform changed in this frame
    posed: np.ndarray  # sorted ids of every leaf ever moved
    posed_world: np.ndarray  # (len(posed), 4, 4) their world transforms at this frame

    def tile(self, tile: int) -> np.ndarray:
        return self.leaves[self.start[tile]:self.start[tile + 1]]


@dataclass
class History:
    """The last ``size`` frames, by number."""

    size: int = 64
    frames: OrderedDict = field(default_factory=OrderedDict)

    def add(self, record: FrameRecord) -> None:
        self.frames[record.number] = record
        while len(self.frames) > self.size:
            self.frames.popitem(last=False)

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


def tile_deltas(record: FrameRecord, prior: FrameRecord):
    """Every tile's delta of ``record`` against ``prior`` at once, in CSR form
    ``(added, added_start, removed, removed_start)``, cached on ``record``: the streams ask for
    every tile against the same base. One compiled merge of each tile's two sorted lists."""
    cache = record.__dict__.setdefault("_deltas", {})
    if prior.number not in cache:
        cache[prior.number] = _merge_deltas(record.start, record.leaves, prior.start,
                                            prior.leaves)
        while len(cache) > 4:
            cache.pop(next(iter(cache)))
    return cache[prior.number]


@njit(cache=True)
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
    moved = transforms(history, record, tile, out["base"], added)
    if moved is not None:
        out["transforms"] = moved
    out.update(record.fits[tile])
    return out


def transforms(history: History, record: FrameRecord, tile: int, base: int | None,
               added: np.ndarray | None) -> dict | None:
    """The world transforms a tile's packet carries (moved leaves the node may not have):
    every moved leaf of a full list; in a delta against ``base``, the ``added`` leaves and
    those that moved since the base. None when there are none."""
    if not len(record.posed):
        return None  # nothing ever moved
    current = record.tile(tile)
    if base is None:
        send = current
    else:
        send = np.union1d(added, np.intersect1d(current, history.changed_since(base,
                                                                               record.number),
                                                assume_unique=True))
    if not len(send):
        return None
    hit = np.isin(record.posed, send, assume_unique=True)
    if not hit.any():
        return None
    return {"ids": record.posed[hit].tolist(),
            "matrices": record.posed_world[hit].reshape(-1, 16).tolist()}


def apply(held: np.ndarray | None, pkt: dict) -> np.ndarray:
    """A client's list after a packet: the full list, or ``held`` (the base frame's list) plus
    the delta. Raises :class:`InputError` when the result contradicts the packet's count."""
    if pkt.get("base") is None:
        out = np.asarray(pkt["visible"], dtype=np.int64)
    else:
        if held is None:
            raise InputError(f"delta against frame {pkt['base']}, whose list is not held")
        keep = np.setdiff1d(held, np.asarray(pkt["removed"], dtype=np.int64), assume_unique=True)
        out = np.union1d(keep, np.asarray(pkt["added"], dtype=np.int64))
    if len(out) != pkt["count"]:
        raise InputError(f"packet of frame {pkt['frame']} does not add up: {len(out)} leaves, "
                         f"count {pkt['count']}")
    return out
