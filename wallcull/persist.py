"""What survives a restart: the state folder of a server.

It holds ``walls.sqlite3`` (every wall's spec, scene, method, bounds and options, its last frame
number and its credentials' digests), ``scenes/`` (uploads, when the server has no ``--scenes``
folder) and ``lock``, which one server at a time holds. SQLite runs in WAL mode with
``synchronous=NORMAL``: a commit is an append to the log, durable when the process is killed
(not when the machine loses power), about 20 µs; so every frame's number is written before the
frame is published, and a restarted server never numbers a frame at or below one a client saw.

What is found at start is checked before anything is served: a database that is not one,
truncated, corrupt or whose walls' specs do not parse stops the server with one line naming the
file, what is wrong and what to do; the file is never written to. A write that fails later
(disk full, a read-only folder) raises :class:`StateWriteFailed` for the request that asked for
it (507 or 503), and :attr:`StateFolder.failure` says why until a write succeeds again; frames
go on from memory meanwhile.
"""

from __future__ import annotations

import fcntl
import json
import os
import sqlite3
import threading
from dataclasses import dataclass
from typing import Callable
from pathlib import Path

from .credentials import DRIVER, Issued
from .errors import InputError

SCHEMA = """
CREATE TABLE IF NOT EXISTS walls (
    id TEXT PRIMARY KEY,
    created REAL NOT NULL,
    spec TEXT NOT NULL,                      -- JSON: the POST /walls body as validated
    last_frame INTEGER NOT NULL DEFAULT -1   -- no frame number above it was handed out
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


class StateWriteFailed(RuntimeError):
    """The state folder could not be written: ``status`` 507 when the disk is full, 503
    otherwise (a read-only folder, an I/O error)."""

    def __init__(self, status: int, reason: str):
        super().__init__(reason)
        self.status = status


def _full(folder: Path) -> bool:
    """Whether the disk holding ``folder`` is (nearly) full: SQLite reports a full disk at
    times as a "disk I/O error"."""
    try:
        s = os.statvfs(folder)
    except OSError:
        return False
    return s.f_bavail * s.f_frsize < FULL_BELOW


#: Free bytes below which a disk counts as full.
FULL_BELOW = 1 << 20


@dataclass
class WallRow:
    id: str
    created: float
    spec: dict
    last_frame: int
    grants: Issued


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
        self.file = self.path / "walls.sqlite3"
        #: why the last write failed, until one succeeds again (health and metrics show it)
        self.failure: str | None = None
        self.lost: str | None = None  # see :meth:`check`
        self._identity: tuple | None = None  # the lock's and database's, once open
        self._mutex = threading.Lock()  # frames are culled in worker threads: one connection
        try:
            self._open()
            self.rows = self._read()
            self._probe()
        except BaseException:
            self.close()
            raise
        self._identity = self._files()

    def _probe(self) -> None:
        """Write, and take it back: a database or folder that cannot be written stops the
        start (it used to start, healthy, until its first write), and the file is untouched."""
        try:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.execute(f"PRAGMA user_version={VERSION}")
            finally:
                if self._db.in_transaction:
                    self._db.execute("ROLLBACK")
        except sqlite3.OperationalError as exc:
            raise InputError(str(self._unwritable(exc))) from None

    def _unwritable(self, exc: sqlite3.OperationalError) -> StateWriteFailed:
        """What a write that failed says: 507 when the disk is full, 503 else, and why."""
        text = str(exc)
        full = "full" in text or _full(self.path)
        return StateWriteFailed(507 if full else 503, (
            f"cannot write the state database {self.file}: {text}"
            + (" (free some space)" if full else
               " (is the folder, the database or its -wal or -shm file read-only?)"
               if "readonly" in text else "")))

    def _files(self) -> tuple | None:
        """What the lock and the database are on the disk (device and inode), or None where
        one is gone."""
        try:
            return tuple((s.st_dev, s.st_ino) for s in (os.stat(self.path / "lock"),
                                                         os.stat(self.file)))
        except OSError:
            return None

    def check(self) -> str | None:
        """Why the folder can no longer be trusted, or None: its lock or database removed,
        moved or replaced while the server runs (a second server could then take it, and
        every write here would be lost). Once it is, every write is refused, frames beyond
        those written down included, until a restart."""
        if self.lost is None and self._identity is not None \
                and self._files() != self._identity:
            self.lost = self.failure = (
                f"the state folder {self.path} was moved, deleted or replaced while the server "
                "ran: its walls are no longer written down; restart the server")
        return self.lost

    def _open(self) -> None:
        """Open and check the database (creating it when there is none), or refuse to start."""
        fresh = not self.file.exists() or self.file.stat().st_size == 0
        try:
            self._db = sqlite3.connect(self.file, check_same_thread=False, isolation_level=None)
            if not fresh:  # reads every page: a truncated or damaged file is found here
                problems = [r[0] for r in self._db.execute("PRAGMA quick_check").fetchall()]
                if problems != ["ok"]:
                    raise self._corrupt("; ".join(problems[:3]))
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
            if version > VERSION:
                raise InputError(f"{self.file} was written by a newer wallcull (schema "
                                 f"{version}; this one knows {VERSION}): run that version, or "
                                 "move the file aside to start with no walls")
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.execute("PRAGMA foreign_keys=ON")
            if fresh or version < VERSION:
                self._db.executescript(SCHEMA)
                self._db.execute(f"PRAGMA user_version={VERSION}")
        except sqlite3.DatabaseError as exc:
            raise self._corrupt(str(exc)) from None

    def _corrupt(self, what: str) -> InputError:
        if _full(self.path):  # not damage: the disk is full (SQLite says "disk I/O error")
            return InputError(f"state database {self.file} cannot be opened ({what}): the disk "
                              "holding it is full; free some space (the database is left "
                              "untouched)")
        return InputError(f"state database {self.file} cannot be used ({what}); it is left "
                          "untouched: move it aside to start with no walls, or restore it from "
                          "a backup")

    def _read(self) -> list["WallRow"]:
        """Every wall row, its spec parsed (refused at start, naming the wall, when one is
        not a JSON object)."""
        try:
            rows = self._db.execute(
                "SELECT id, created, spec, last_frame FROM walls ORDER BY created").fetchall()
            creds = self._db.execute("SELECT digest, wall, role, tiles FROM credentials"
                                     ).fetchall()
        except sqlite3.DatabaseError as exc:
            raise self._corrupt(str(exc)) from None
        found: dict[str, tuple[list, list]] = {}  # wall -> its digests, whose each is
        try:
            for d, wall, role, tiles in creds:
                digests, groups = found.setdefault(wall, ([], []))
                digests.append(bytes.fromhex(d))
                groups.append(None if role == DRIVER else json.loads(tiles))
            grants = {wall: Issued(wall, *both) for wall, both in found.items()}
        except (TypeError, ValueError) as exc:
            raise self._corrupt(f"a credential does not parse: {exc}") from None
        out = []
        for wid, created, spec, last in rows:
            try:
                spec = json.loads(spec)
            except (TypeError, ValueError) as exc:
                spec = exc
            if not isinstance(spec, dict):
                raise self._corrupt(f"the spec of wall {wid} is not a JSON object: {spec}")
            out.append(WallRow(wid, created, spec, last, grants.get(wid, Issued(wid, [], []))))
        return out

    def _write(self, work: Callable[[sqlite3.Connection], None]) -> None:
        """Run ``work`` in one transaction, or raise :class:`StateWriteFailed` (and remember
        why) when the folder cannot take it."""
        with self._mutex:
            if self.check() is not None:  # not this server's folder any more
                raise StateWriteFailed(503, self.lost)
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    work(self._db)
                    self._db.execute("COMMIT")
                finally:
                    if self._db.in_transaction:  # (SQLite ends it itself on a full disk)
                        self._db.execute("ROLLBACK")
            except sqlite3.OperationalError as exc:
                failed = self._unwritable(exc)
                self.failure = str(failed)
                raise failed from None
        self.failure = None

    def add_wall(self, wid: str, created: float, spec: dict, issued: Issued) -> None:
        def add(db):  # one transaction: the wall with its credentials, or nothing
            db.execute("INSERT INTO walls (id, created, spec) VALUES (?, ?, ?)",
                       (wid, created, json.dumps(spec)))
            db.executemany(
                "INSERT INTO credentials (digest, wall, role, tiles) VALUES (?, ?, ?, ?)",
                ((d, wid, role, tiles) for d, role, tiles in issued.rows()))
        self._write(add)

    def remove_wall(self, wid: str) -> None:
        self._write(lambda db: db.execute("DELETE FROM walls WHERE id = ?", (wid,)))

    def set_last_frame(self, wid: str, number: int) -> None:
        """Frame numbers up to ``number`` may be handed out (never lowers what is written)."""
        self._write(lambda db: db.execute(
            "UPDATE walls SET last_frame = ? WHERE id = ? AND last_frame < ?",
            (number, wid, number)))

    def settle_last_frame(self, wid: str, number: int) -> None:
        """``number`` is the last frame number handed out (a clean stop: it may lower a
        number written ahead, :class:`wallcull.service.FrameNumbers`)."""
        self._write(lambda db: db.execute("UPDATE walls SET last_frame = ? WHERE id = ?",
                                          (number, wid)))

    def walls(self) -> list[WallRow]:
        """The walls found at start (checked then)."""
        return self.rows

    def close(self) -> None:
        db = self.__dict__.get("_db")
        if db is not None:
            with self._mutex:
                db.close()
        self._lock.close()  # releases the lock
