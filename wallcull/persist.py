"""What survives a restart: the state folder of a server.

It holds ``walls.sqlite3`` (every wall's spec, scene, method, bounds and options, its last frame
number and its credentials' digests), ``scenes/`` (uploads, when the server has no ``--scenes``
folder) and ``lock``, which one server at a time holds. SQLite runs in WAL mode with
``synchronous=NORMAL``: a commit is an append to the log, durable when the process is killed
(not when the machine loses power), about 20 µs; so every frame's number is written before the
frame is published, and a restarted server never numbers a frame at or below one a client saw.
"""

from __future__ import annotations

import fcntl
import json
import os
import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path

from .credentials import Grant
from .errors import InputError

SCHEMA = """
CREATE TABLE IF NOT EXISTS walls (
    id TEXT PRIMARY KEY,
    created REAL NOT NULL,
    spec TEXT NOT NULL,                      -- JSON: the POST /walls body as validated
    last_frame INTEGER NOT NULL DEFAULT -1   -- the newest frame number handed out
);
CREATE TABLE IF NOT EXISTS credentials (
    digest TEXT PRIMARY KEY,                 -- SHA-256 of the token, hex; never the token
    wall TEXT NOT NULL REFERENCES walls(id) ON DELETE CASCADE,
    role TEXT NOT NULL,                      -- driver or node
    tiles TEXT NOT NULL                      -- JSON list of a node's tiles
);
"""
VERSION = 1


def default_folder() -> Path:
    """``$WALLCULL_STATE``, else ``$XDG_STATE_HOME/wallcull``, else ``~/.local/state/wallcull``."""
    if os.environ.get("WALLCULL_STATE"):
        return Path(os.environ["WALLCULL_STATE"])
    base = os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state"
    return Path(base) / "wallcull"


@dataclass
class WallRow:
    id: str
    created: float
    spec: dict
    last_frame: int
    grants: dict[str, Grant]


class StateFolder:
    """The folder, locked for this process, and its wall database."""

    def __init__(self, folder: str | os.PathLike):
        self.path = Path(folder).expanduser().resolve()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            self._lock = open(self.path / "lock", "a+")
        except OSError as exc:
            raise InputError(f"cannot use state folder {self.path}: {exc.strerror}") from None
        try:
            fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._lock.close()
            raise InputError(f"state folder {self.path} is in use by another wallcull server; "
                             "give this one its own (--state DIR)") from None
        self.scenes = self.path / "scenes"
        # frames are culled in worker threads: one connection, one lock
        self._db = sqlite3.connect(self.path / "walls.sqlite3", check_same_thread=False,
                                   isolation_level=None)
        self._mutex = threading.Lock()
        with self._mutex:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.execute("PRAGMA foreign_keys=ON")
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
            if version > VERSION:
                raise InputError(f"{self.path / 'walls.sqlite3'} was written by a newer "
                                 f"wallcull (schema {version}; this one knows {VERSION})")
            self._db.executescript(SCHEMA)
            self._db.execute(f"PRAGMA user_version={VERSION}")

    def add_wall(self, wid: str, created: float, spec: dict, grants: dict[str, Grant]) -> None:
        with self._mutex:  # one transaction: the wall with its credentials, or nothing
            self._db.execute("BEGIN")
            try:
                self._db.execute("INSERT INTO walls (id, created, spec) VALUES (?, ?, ?)",
                                 (wid, created, json.dumps(spec)))
                self._db.executemany(
                    "INSERT INTO credentials (digest, wall, role, tiles) VALUES (?, ?, ?, ?)",
                    [(d, wid, g.role, json.dumps(sorted(g.tiles))) for d, g in grants.items()])
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def remove_wall(self, wid: str) -> None:
        with self._mutex:
            self._db.execute("DELETE FROM walls WHERE id = ?", (wid,))

    def set_last_frame(self, wid: str, number: int) -> None:
        with self._mutex:
            self._db.execute("UPDATE walls SET last_frame = ? WHERE id = ? AND last_frame < ?",
                             (number, wid, number))

    def walls(self) -> list[WallRow]:
        with self._mutex:
            rows = self._db.execute(
                "SELECT id, created, spec, last_frame FROM walls ORDER BY created").fetchall()
            creds = self._db.execute("SELECT digest, wall, role, tiles FROM credentials").fetchall()
        grants: dict[str, dict[str, Grant]] = {}
        for d, wall, role, tiles in creds:
            grants.setdefault(wall, {})[d] = Grant(wall, role, frozenset(json.loads(tiles)))
        return [WallRow(wid, created, json.loads(spec), last, grants.get(wid, {}))
                for wid, created, spec, last in rows]

    def close(self) -> None:
        with self._mutex:
            self._db.close()
        self._lock.close()  # releases the lock
