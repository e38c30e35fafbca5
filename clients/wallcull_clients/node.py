"""What a render node keeps between node messages (:mod:`wallcull.protocol`), and what it makes
of each: every tile's leaf list and the draw ranges of the leaves it shows in part, rebuilt
from the delta's base, its matrices (:mod:`wallcull_clients.frusta`), and the world transforms
of the leaves that moved.

A delta's base is the newest frame the node had acknowledged when the server made the
message; acknowledgements only grow, so the lists (and extents) older than the newest base
seen are dead and go. Those of newer frames stay: their acknowledgements may be in flight.
"""

from __future__ import annotations

import bisect
from collections import OrderedDict
from dataclasses import dataclass

import msgpack
import numpy as np

from wallcull import protocol
from wallcull.errors import InputError

from .frusta import Frusta


@dataclass
class TileFrame:
    """One tile of one frame, as a node draws it."""

    tile: int
    leaves: np.ndarray  # sorted leaf ids
    matrices: dict  # view, projection, near, far; left/right for stereo
    entry: dict  # the message's entry (shadows, mirrors, ...)
    ranges: dict  # leaf id -> (k, 2) triangle ranges, for the leaves drawn in part


class NodeState:
    """A render node's memory of its tiles (see the module docstring)."""

    def __init__(self, keep: int = 256):
        self.keep = keep
        self.lists: OrderedDict[int, dict[int, np.ndarray]] = OrderedDict()  # frame -> tile ->
        self.parts: dict[int, dict[int, dict]] = {}  # frame -> tile -> leaf -> ranges
        self.frusta = Frusta(keep)
        self.moved: dict[int, np.ndarray] = {}  # leaf id -> its world transform (4 x 4)
        self.frame = -1

    def reset(self) -> None:
        """Forget everything (a new stream starts from full lists)."""
        self.__init__(self.keep)

    def holds(self, base: int | None) -> bool:
        return base is None or base in self.lists

    def take(self, message: dict) -> list[TileFrame]:
        """Every tile of a node message, rebuilt. Raises :class:`InputError` when the message
        does not add up or its base is not held (ask for full lists then)."""
        number, base = message["frame"], message.get("base")
        if number <= self.frame:
            raise InputError(f"frame {number} arrived after frame {self.frame}")
        held = self.lists.get(base) if base is not None else {}
        if held is None:
            raise InputError(f"delta against frame {base}, which this node does not hold")
        held_parts = self.parts.get(base, {})
        lists = dict(held)  # a tile a delta leaves out keeps the base's list and ranges
        parts = dict(held_parts)
        entries = {tile: {"tile": tile, "count": len(held[tile])} for tile in held}
        for entry in message["tiles"]:
            tile = entry["tile"]
            if base is not None and tile not in held and "visible" not in entry:
                raise InputError(f"delta for tile {tile}, whose list of frame {base} is not held")
            lists[tile] = protocol.apply(held.get(tile), entry, base)
            parts[tile] = protocol.apply_parts(held_parts.get(tile, {}), entry, lists[tile], base)
            entries[tile] = entry
        try:
            matrices = self.frusta.take(message)
        except KeyError as exc:
            raise InputError(str(exc.args[0])) from None
        out = [TileFrame(tile, lists[tile], matrices[tile], entries[tile], parts.get(tile, {}))
               for tile in sorted(lists)]
        moved = message.get("transforms")
        if moved:
            for leaf, m in zip(moved["ids"], moved["matrices"]):
                self.moved[int(leaf)] = np.asarray(m, np.float64).reshape(4, 4)
        self.lists[number] = lists
        self.parts[number] = parts
        self.frame = number
        if base is not None:
            while self.lists and next(iter(self.lists)) < base:
                self.parts.pop(self.lists.popitem(last=False)[0], None)
        while len(self.lists) > self.keep:
            self.parts.pop(self.lists.popitem(last=False)[0], None)
        return out


# --------------------------------------------------------------------------- sizes

_KEY = {k: len(msgpack.packb(k)) for k in ("visible", "added", "removed", "extent", "depth")}


_THRESHOLDS = (128, 256, 1 << 16, 1 << 32)


def sorted_ints_len(values) -> int:
    """Bytes of a sorted list (or array) of ints >= 0 as msgpack encodes it, by bisection: a
    few microseconds, where encoding costs tens."""
    n = len(values)
    head = 1 if n < 16 else 3 if n < 1 << 16 else 5
    if isinstance(values, np.ndarray):
        below = np.searchsorted(values, _THRESHOLDS).tolist()
    else:
        below = [bisect.bisect_left(values, t) for t in _THRESHOLDS]
    return head + n + (n - below[0]) + (n - below[1]) + 2 * (n - below[2]) + 4 * (n - below[3])


def _float_len(value: float) -> int:
    """Bytes of a number in a node message: float32 when that holds it exactly."""
    return 5 if float(np.float32(value)) == value else 9


def _map_len(pairs: int) -> int:
    return 1 if pairs < 16 else 3


def _array_len(items: int) -> int:
    return 1 if items < 16 else 3 if items < 1 << 16 else 5


def full_size(message: dict, size: int, frames: list[TileFrame], held_frusta: dict) -> int:
    """The bytes ``message`` (``size`` bytes, a delta) would have taken with full lists, as the
    server would have encoded it: each entry's list as ``visible``, every extent and depth
    spelled out (``held_frusta``: ``{(tile, eye, key): value}`` as :class:`Frusta` keeps them),
    every tile the delta left out with its entry, no base. Exact, without encoding
    anything."""
    if message.get("base") is None:
        return size
    out = size - len(msgpack.packb(message["base"])) + 1  # nil
    lists = {f.tile: f.leaves for f in frames}
    sent = len(message["tiles"])
    out += _array_len(len(frames)) - _array_len(sent)
    entries = {e["tile"]: e for e in message["tiles"]}
    for tile in lists:
        if tile not in entries:  # left out: its entry would have been tile and count
            entries[tile] = {"tile": tile, "count": len(lists[tile])}
            out += 1 + len(msgpack.packb("tile")) + len(msgpack.packb(tile)) \
                + len(msgpack.packb("count")) + len(msgpack.packb(len(lists[tile])))
    ranges = {f.tile: f.ranges for f in frames}
    for entry in entries.values():
        tile, pairs = entry["tile"], len(entry)
        # ranges: a full message holds every partial leaf's, and no "whole"
        for key in ("ranges", "whole"):
            if key in entry:
                out -= len(msgpack.packb(key)) + len(msgpack.packb(entry[key]))
                pairs -= 1
        if ranges[tile]:
            out += len(msgpack.packb("ranges")) + len(msgpack.packb(
                [[leaf, *r.ravel().tolist()] for leaf, r in sorted(ranges[tile].items())]))
            pairs += 1
        if "visible" not in entry:
            for key in ("added", "removed"):
                if key in entry:
                    out -= _KEY[key] + sorted_ints_len(entry[key])
                    pairs -= 1
            out += _KEY["visible"] + sorted_ints_len(lists[tile])
            pairs += 1
        for eye in (None, "left", "right"):
            part = entry if eye is None else entry.get(eye)
            if part is None:
                continue
            part_pairs = len(part)
            if "extent" not in part:
                out += _KEY["extent"] + 1 + 4 * 9
                part_pairs += 1
            if "depth" not in part:
                n, f = held_frusta[tile, eye, "depth"]
                out += _KEY["depth"] + 1 + _float_len(n) + _float_len(f)
                part_pairs += 1
            if eye is None:
                pairs += part_pairs - len(part)
            else:
                out += _map_len(part_pairs) - _map_len(len(part))
        out += _map_len(pairs) - _map_len(len(entry))
    return out
