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
    every tile against the same base, and one pass over (tile, leaf) keys costs about what two
    ``setdiff1d`` of one tile do."""
    cache = record.__dict__.setdefault("_deltas", {})
    if prior.number not in cache:
        tiles = len(record.start) - 1
        n = int(max(record.leaves.max(initial=-1), prior.leaves.max(initial=-1))) + 1
        kc = np.repeat(np.arange(tiles), np.diff(record.start)) * n + record.leaves
        kp = np.repeat(np.arange(tiles), np.diff(prior.start)) * n + prior.leaves
        if tiles * n <= 1 << 24:
            seen = np.zeros(tiles * n, dtype=bool)
            seen[kp] = True
            added = kc[~seen[kc]]
            seen[:] = False
            seen[kc] = True
            removed = kp[~seen[kp]]
        else:  # very large walls: sorted merges instead of a mask
            added = kc[~np.isin(kc, kp, assume_unique=True)]
            removed = kp[~np.isin(kp, kc, assume_unique=True)]
        edges = np.arange(tiles + 1)
        cache[prior.number] = (added % n, np.searchsorted(added // n, edges),
                               removed % n, np.searchsorted(removed // n, edges))
        while len(cache) > 4:
            cache.pop(next(iter(cache)))
    return cache[prior.number]


def packet(history: History, number: int, tile: int, base: int | None) -> dict:
    """Tile ``tile``'s packet of frame ``number``, a delta against frame ``base`` when given
    and still held (else a full list)."""
    record = history.frames[number]
    current = record.tile(tile)
    out: dict[str, Any] = {"frame": number, "tile": tile, "time": record.time}
    prior = history.get(base) if base is not None and base < number else None
    if prior is None:
        out["base"] = None
        out["visible"] = current.tolist()
        send = current
    else:
        added_all, a_start, removed_all, r_start = tile_deltas(record, prior)
        added = added_all[a_start[tile]:a_start[tile + 1]]
        out["base"] = base
        out["added"] = added.tolist()
        out["removed"] = removed_all[r_start[tile]:r_start[tile + 1]].tolist()
        if len(record.posed):  # else nothing ever moved: no transforms to send
            send = np.union1d(added, np.intersect1d(
                current, history.changed_since(base, number), assume_unique=True))
        else:
            send = added
    out["count"] = len(current)
    if len(record.posed) and len(send):
        hit = np.isin(record.posed, send, assume_unique=True)
        if hit.any():
            out["transforms"] = {"ids": record.posed[hit].tolist(),
                                 "matrices": record.posed_world[hit].reshape(-1, 16).tolist()}
    out.update(record.fits[tile])
    return out


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
