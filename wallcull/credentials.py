"""Who may do what on a wall server: the operator's token, and the tokens issued with each wall.

* the **operator** holds the server's token (``--token``): scenes, walls, and everything else;
* a wall's **driver** credential posts that wall's frames;
* a **node** credential reads the packets of, streams and acknowledges its tiles of one wall.

Issued tokens are random (192 bits) and shown once, when the wall is created; the server keeps
only their SHA-256 digests, in memory and at rest. A token this long needs no slow hash: nobody
can enumerate 2^192 guesses. The operator's digest is compared in constant time; issued ones
are looked up by digest, so what a lookup's timing could reveal is bits of a digest of the
presented token, which say nothing about any real one.
"""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass
from typing import Iterable

from .errors import InputError

OPERATOR, DRIVER, NODE = "operator", "driver", "node"


@dataclass(frozen=True)
class Grant:
    """What one issued credential holds."""

    wall: str
    role: str  # DRIVER or NODE
    tiles: frozenset[int] = frozenset()  # a node's tiles

    def to_row(self) -> dict:
        return {"wall": self.wall, "role": self.role, "tiles": sorted(self.tiles)}


def digest(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8", "surrogateescape")).hexdigest()


def same_digest(a: str, b: str) -> bool:
    return secrets.compare_digest(a.encode(), b.encode())


def node_groups(tiles: int, nodes: Iterable[Iterable[int]] | None) -> list[list[int]]:
    """The tiles of each node: ``nodes`` as given (each tile at most once), then a node of its
    own for every tile no group names."""
    groups, seen = [], set()
    for group in nodes or ():
        group = sorted(set(group))
        bad = [t for t in group if not 0 <= t < tiles]
        if bad:
            raise InputError(f"node tiles {bad} are not tiles of this wall (0-{tiles - 1})")
        twice = seen.intersection(group)
        if twice:
            raise InputError(f"tiles {sorted(twice)} are given to two nodes")
        seen.update(group)
        groups.append(group)
    return groups + [[t] for t in range(tiles) if t not in seen]


def issue(wall: str, tiles: int, nodes=None) -> tuple[dict, dict[str, Grant]]:
    """New credentials of a wall: the tokens to hand out once, and their digests' grants."""
    driver = "wcd_" + secrets.token_urlsafe(24)
    grants = {digest(driver): Grant(wall, DRIVER)}
    shown = []
    for group in node_groups(tiles, nodes):
        token = "wcn_" + secrets.token_urlsafe(24)
        grants[digest(token)] = Grant(wall, NODE, frozenset(group))
        shown.append({"tiles": group, "token": token})
    return {"driver": driver, "nodes": shown}, grants
