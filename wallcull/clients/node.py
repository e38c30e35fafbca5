"""What a render node keeps between node messages (:mod:`wallcull.protocol`), and what it makes
of each: every tile's leaf list, rebuilt from the delta's base, and its matrices
(:mod:`wallcull.clients.frusta`), and the world transforms of the leaves that moved.

A delta's base is the newest frame the node had acknowledged when the server made the
message; acknowledgements only grow, so the lists (and extents) older than the newest base
seen are dead and go. Those of newer frames stay: their acknowledgements may be in flight.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

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


class NodeState:
    """A render node's memory of its tiles (see the module docstring)."""

    def __init__(self, keep: int = 256):
        self.keep = keep
        self.lists: OrderedDict[int, dict[int, np.ndarray]] = OrderedDict()  # frame -> tile ->
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
        lists = {}
        for entry in message["tiles"]:
            tile = entry["tile"]
            if base is not None and tile not in held and "visible" not in entry:
                raise InputError(f"delta for tile {tile}, whose list of frame {base} is not held")
            lists[tile] = protocol.apply(held.get(tile), entry, base)
        try:
            matrices = self.frusta.take(message)
        except KeyError as exc:
            raise InputError(str(exc.args[0])) from None
        out = [TileFrame(e["tile"], lists[e["tile"]], matrices[e["tile"]], e)
               for e in message["tiles"]]
        moved = message.get("transforms")
        if moved:
            for leaf, m in zip(moved["ids"], moved["matrices"]):
                self.moved[int(leaf)] = np.asarray(m, np.float64).reshape(4, 4)
        self.lists[number] = lists
        self.frame = number
        if base is not None:
            while self.lists and next(iter(self.lists)) < base:
                self.lists.popitem(last=False)
        while len(self.lists) > self.keep:
            self.lists.popitem(last=False)
        return out
