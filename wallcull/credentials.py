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
from collections.abc import Sequence
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
        node's of those tiles (as the state database's rows have them)."""
        groups = list(groups)
        raw = np.frombuffer(b"".join(digests), np.uint8).reshape(-1, 32)
        if len(raw) != len(groups):
            raise ValueError("one digest per credential")
        nodes = [g for g in groups if g is not None]
        start = np.cumsum([0] + [len(g) for g in nodes], dtype=np.int64)
        tiles = np.fromiter((t for g in nodes for t in g), np.int64, int(start[-1]))
        holder = np.cumsum([g is not None for g in groups]) - 1
        holder[[g is None for g in groups]] = -1
        self._keep(wall, raw, holder, start, tiles)

    @classmethod
    def of_nodes(cls, wall: str, driver: bytes, nodes: bytes, start: np.ndarray,
                 tiles: np.ndarray) -> "Issued":
        """The driver's digest, and the nodes' (``nodes``: 32 bytes each) of the tiles
        ``tiles[start[k]:start[k + 1]]``."""
        raw = np.frombuffer(driver + nodes, np.uint8).reshape(-1, 32)
        out = cls.__new__(cls)
        out._keep(wall, raw, np.arange(-1, len(raw) - 1), start, tiles)
        return out

    def _keep(self, wall, raw, holder, start, tiles) -> None:
        """Digests ``raw (n, 32)`` of holders ``holder`` (-1: the driver; k: node k, of tiles
        ``tiles[start[k]:start[k + 1]]``, no tile twice): kept sorted by digest, the nodes by
        their first tile, each node's tiles sorted."""
        self.wall = wall
        size = np.diff(start)
        node_of = np.repeat(np.arange(len(size)), size)
        tiles = np.asarray(tiles, np.int64)[np.lexsort((tiles, node_of))]  # sorted in each
        first = np.full(len(size), -1)  # (a node of no tiles: first, as sorted lists sort)
        first[size > 0] = tiles[start[:-1][size > 0]]
        by_first = np.argsort(first, kind="stable")
        rank = np.empty(len(size), np.int64)
        rank[by_first] = np.arange(len(size))
        self._start = np.concatenate([[0], np.cumsum(size[by_first])]).astype(np.int64)
        move = np.repeat(start[by_first] - self._start[:-1], size[by_first])
        self._tiles = tiles[np.arange(len(tiles)) + move].astype(np.int32)
        holder = np.asarray(holder, np.int64)
        holder = np.where(holder < 0, -1, rank[np.maximum(holder, 0)] if len(size) else -1)
        prefix = raw[:, :8].copy().view(">u8").ravel().astype(np.uint64)
        order = np.argsort(prefix, kind="stable")
        self._prefix, self._digests = prefix[order], raw[order]
        self._holder = holder[order].astype(np.int32)

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

    def nodes(self, limit: int | None = None) -> list[list[int]]:
        """Each node credential's tiles, sorted (by first tile); the first ``limit`` only,
        when given."""
        start = self._start if limit is None else self._start[:limit + 1]
        tiles, start = self._tiles[:start[-1]].tolist(), start.tolist()
        return [tiles[a:b] for a, b in zip(start[:-1], start[1:])]

    @property
    def node_count(self) -> int:
        return len(self._start) - 1

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


def node_groups(tiles: int, nodes: Iterable[Iterable[int]] | None
                ) -> tuple[np.ndarray, np.ndarray]:
    """The tiles of each node, ``(start, tiles)``: node ``k``'s are ``tiles[start[k]:start[k +
    1]]``, ``nodes`` as given (each tile at most once), then a node of its own for every tile
    no group names (arrays: 65,536 of them on a 256 x 256 wall)."""
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
    alone = np.ones(tiles, bool)
    alone[list(seen)] = False
    rest = np.flatnonzero(alone)
    size = np.concatenate([[len(g) for g in groups], np.ones(len(rest), np.int64)])
    start = np.concatenate([[0], np.cumsum(size)]).astype(np.int64)
    return start, np.concatenate([np.array([t for g in groups for t in g], np.int64), rest])


class Shown(Sequence):
    """A new wall's node credentials, shown once: ``{"tiles": [...], "token": "wcn_..."}``
    each, made when read (the answer is encoded a piece at a time: a 256 x 256 wall's 65,536
    as dicts took 13 MB more)."""

    def __init__(self, start: np.ndarray, tiles: np.ndarray, tokens: list[str]):
        self._start, self._tiles, self._tokens = start.tolist(), tiles.tolist(), tokens

    def __len__(self) -> int:
        return len(self._tokens)

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        k = range(len(self))[k]  # negative indices, and IndexError
        return {"tiles": self._tiles[self._start[k]:self._start[k + 1]],
                "token": self._tokens[k]}


def issue(wall: str, tiles: int, nodes=None) -> tuple[dict, Issued]:
    """New credentials of a wall: the tokens to hand out once (the nodes' a :class:`Shown`),
    and what the server keeps."""
    driver = "wcd_" + secrets.token_urlsafe(24)
    start, flat = node_groups(tiles, nodes)
    tokens = ["wcn_" + secrets.token_urlsafe(24) for _ in range(len(start) - 1)]
    issued = Issued.of_nodes(wall, raw_digest(driver),
                             b"".join(raw_digest(token) for token in tokens), start, flat)
    return {"driver": driver, "nodes": Shown(start, flat, tokens)}, issued


def shown(url: str) -> str:
    """``url`` as it may be shown (a log, ``/health``, an error): a user, password or token
    before the host (``nats://user:secret@host``, ``nats://TOKEN@host``) is replaced by
    ``***``; several URLs, comma-separated, each so."""
    from urllib.parse import urlsplit

    def one(part: str) -> str:
        try:
            netloc = urlsplit(part.strip()).netloc
        except ValueError:
            return "***"
        if "@" not in netloc:
            return part
        return part.replace(netloc, "***@" + netloc.rsplit("@", 1)[1], 1)

    return ",".join(one(p) for p in str(url).split(","))
