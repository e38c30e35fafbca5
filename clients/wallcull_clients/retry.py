"""Riding out a server restart: retries with exponential backoff, and failures that say why.

A render node or a driver that loses its server (a restart, a network blip) tries again after
50 ms, then twice as long each time up to half a second (with jitter, so that a wall of
nodes does not reconnect in lockstep), for up to ``give_up`` seconds of failing in a row.
Then, or at once when the server refuses for a reason retrying cannot fix (the wall is gone,
the credential is wrong), it stops with a :class:`ClientFailure` naming the reason: never a
silent exit.
"""

from __future__ import annotations

import asyncio
import random
import signal
import time
from typing import Awaitable, Callable, TypeVar

from .rawhttp import HTTPError

T = TypeVar("T")

#: What a restarting server looks like from a client.
TRANSIENT = (ConnectionError, OSError, asyncio.TimeoutError, asyncio.IncompleteReadError,
             EOFError)
#: HTTP answers worth retrying: the server is busy or not all there yet.
RETRY_STATUS = (429, 502, 503, 504)


class ClientFailure(RuntimeError):
    """A node or driver cannot go on; the message says why."""


class Stopped(ClientFailure):
    """A retry given up because the tool was told to stop (its ``stop`` event: a signal)."""


def stop_on_signals(stop: asyncio.Event, graceful: Callable[[], bool]) -> None:
    """SIGTERM and SIGINT set ``stop`` (the tool winds down and writes what it has). While
    ``graceful()`` is False, where the tool still waits (for its server, its wall, its nodes)
    and has nothing to write, they also cancel the task that called this: it ends at once,
    with :class:`asyncio.CancelledError` (``docker compose stop`` does not wait its 10 s)."""
    loop, task = asyncio.get_running_loop(), asyncio.current_task()

    def on_signal() -> None:
        stop.set()
        if not graceful():
            task.cancel()

    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, on_signal)


class Backoff:
    """The waits between tries (see the module docstring). With ``stop`` (an event a signal
    sets), a wait ends as soon as it is set, with :class:`Stopped`: a tool told to stop does
    not go on retrying a server for ``give_up`` seconds."""

    def __init__(self, give_up: float = 60.0, first: float = 0.05, cap: float = 0.5,
                 stop: asyncio.Event | None = None):
        self.give_up, self.first, self.cap, self.stop = give_up, first, cap, stop
        self.total = 0  # waits over this object's life: how often the server was away
        self.reset()

    def reset(self) -> None:
        """Call after a success: the next failure starts the wait over."""
        self.delay, self.since = self.first, None

    async def wait(self, error: str) -> None:
        """Sleep before the next try, or raise :class:`ClientFailure` once failures have gone
        on for ``give_up`` seconds."""
        now = time.monotonic()
        self.since = now if self.since is None else self.since
        self.total += 1
        if self.stop is not None and self.stop.is_set():
            raise Stopped(f"stopped while retrying: {error}")
        if now - self.since > self.give_up:
            raise ClientFailure(f"gave up after {self.give_up:g} s of retrying: {error}")
        delay = self.delay * random.uniform(0.5, 1.0)
        if self.stop is None:
            await asyncio.sleep(delay)
        else:
            try:
                await asyncio.wait_for(self.stop.wait(), delay)
            except asyncio.TimeoutError:
                pass
            else:
                raise Stopped(f"stopped while retrying: {error}")
        self.delay = min(2 * self.delay, self.cap)


async def retrying(call: Callable[[], Awaitable[T]], backoff: Backoff, what: str) -> T:
    """``await call()``, again after transient failures (see the module docstring)."""
    while True:
        try:
            result = await call()
        except TRANSIENT as exc:
            await backoff.wait(f"{what}: {exc!r}")
            continue
        except HTTPError as exc:
            if exc.status not in RETRY_STATUS:
                raise
            await backoff.wait(f"{what}: {exc}")
            continue
        backoff.reset()
        return result
