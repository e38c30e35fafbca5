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
import json
import secrets
from dataclasses import dataclass
from typing import Iterable, Iterator

import numpy as np

from .errors import InputError

OPERATOR, DRIVER, NODE = "operator", "driver", "node"


@dataclass(frozen=True)
class Grant:
    """What one issued credential holds."""

    wall: str
    role: str  # DRIVER or NODE
    tiles: frozenset[int] = frozenset()  # a node's tiles


class Issued:
    """One wall's issued credentials as the server keeps them: each one's SHA-256 digest, in
    one array sorted by its first 8 bytes, and whose it is (the driver's, or a node's: the
    nodes' tiles in one array). A 256 x 256 wall's 65,537 credentials take 3.5 MB so, where a
    dict of their digests to objects took 40 MB; a lookup is a binary search."""

    def __init__(self, wall: str, digests: Iterable[bytes], groups: Iterable[list[int] | None]):
        """``digests[k]`` (32 bytes) is the driver's when ``groups[k]`` is None, else the
        node's of those tiles."""
        self.wall = wall
        groups = list(groups)
        raw = np.frombuffer(b"".join(digests), np.uint8).reshape(-1, 32)
        if len(raw) != len(groups):
            raise ValueError("one digest per credential")
        nodes = sorted(sorted(g) for g in groups if g is not None)
        where = {tuple(g): k for k, g in enumerate(nodes)}  # (each tile is one node's)
        holder = np.array([-1 if g is None else where[tuple(sorted(g))] for g in groups],
                          np.int32)
        prefix = raw[:, :8].copy().view(">u8").ravel().astype(np.uint64)
        order = np.argsort(prefix, kind="stable")
        self._prefix, self._digests, self._holder = prefix[order], raw[order], holder[order]
        self._start = np.cumsum([0] + [len(g) for g in nodes], dtype=np.int64)
        self._tiles = np.fromiter((t for g in nodes for t in g), np.int32, int(self._start[-1]))

    def __len__(self) -> int:
        return len(self._holder)

    def find(self, raw: bytes) -> Grant | None:
        """What the credential of digest ``raw`` (32 bytes) holds, if it is one of these."""
        key = np.frombuffer(raw[:8], ">u8").astype(np.uint64)
        lo, hi = np.searchsorted(self._prefix, key, "left")[0], \
            np.searchsorted(self._prefix, key, "right")[0]
        for k in range(lo, hi):
            if self._digests[k].tobytes() == raw:
                node = int(self._holder[k])
                if node < 0:
                    return Grant(self.wall, DRIVER)
                return Grant(self.wall, NODE, frozenset(self._group(node)))
        return None

    def _group(self, node: int) -> list[int]:
        return self._tiles[self._start[node]:self._start[node + 1]].tolist()

    def nodes(self) -> list[list[int]]:
        """Each node credential's tiles, sorted (by first tile)."""
        tiles, start = self._tiles.tolist(), self._start.tolist()
        return [tiles[a:b] for a, b in zip(start[:-1], start[1:])]

    def rows(self) -> Iterator[tuple[str, str, str]]:
        """(hex digest, role, tiles as JSON) of each credential: the state database's rows."""
        for raw, node in zip(self._digests, self._holder.tolist()):
            tiles = [] if node < 0 else self._group(node)
            yield raw.tobytes().hex(), DRIVER if node < 0 else NODE, json.dumps(tiles)


def digest(token: str) -> str:
    return raw_digest(token).hex()


def raw_digest(token: str) -> bytes:
    return hashlib.sha256(token.encode("utf-8", "surrogateescape")).digest()


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


def issue(wall: str, tiles: int, nodes=None) -> tuple[dict, Issued]:
    """New credentials of a wall: the tokens to hand out once, and what the server keeps."""
    driver = "wcd_" + secrets.token_urlsafe(24)
    shown = [{"tiles": group, "token": "wcn_" + secrets.token_urlsafe(24)}
             for group in node_groups(tiles, nodes)]
    issued = Issued(wall, [raw_digest(driver), *(raw_digest(n["token"]) for n in shown)],
                    [None, *(n["tiles"] for n in shown)])
    return {"driver": driver, "nodes": shown}, issued
