"""Threads for the per-tile kernels: the shadow fits and the region culls of a frame split into
chunks of tiles, each chunk a compiled kernel that releases the GIL.

Every tile's fit and caster cull is independent of the others', so a frame's can run on all of
a server's cores at once. ``WALLCULL_THREADS`` (default: the number of cores, at most 8) sets
how many; ``1`` runs everything in the calling thread. Work below ``MIN_CHUNK`` items per
thread is not split: handing it over costs more than it saves.
"""

from __future__ import annotations

import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence

import numpy as np

from .errors import InputError

#: Items (tiles or regions) a thread is given at least.
MIN_CHUNK = 8
#: Parts a thread's share of the shadow fits and caster culls is cut into: with a mirror's
#: cull beside them on two cores, the thread the system runs late takes fewer (see :func:`run`).
SPLIT = 3


#: The machine's cores, at most 8 (asked once: ``os.cpu_count`` reads the system each time,
#: 5 us, and a frame asks a few times).
_CORES = max(1, min(8, os.cpu_count() or 1))


def count(environ=os.environ) -> int:
    """Threads the kernels may use: ``WALLCULL_THREADS``, else the cores (at most 8).
    :class:`~wallcull.errors.InputError` if it is set to anything but a whole number from 1
    (the command line and the server ask once as they start, so a typo is named there)."""
    value = environ.get("WALLCULL_THREADS")
    if not value:
        return _CORES
    if not (value.strip().isascii() and value.strip().isdigit() and int(value) >= 1):
        raise InputError(f"WALLCULL_THREADS must be a whole number of threads from 1, got "
                         f"{value!r}")
    return int(value)


_pool: ThreadPoolExecutor | None = None
_lock = threading.Lock()
_pool_size = 0


class Balance:
    """The shares of its work a split that repeats every frame gives each thread: equal at
    first, then each frame corrected by how long each part took (:meth:`took`), for work whose
    cost the split's estimate cannot know (what nearer occluders leave to draw, what a test
    settles early)."""

    def __init__(self):
        self.shares = np.ones(1)

    def of(self, parts: int) -> np.ndarray:
        """The shares of ``parts`` parts (summing to 1)."""
        if len(self.shares) != parts:
            self.shares = np.full(parts, 1 / parts)
        return self.shares

    #: Every part keeps at least this share of an equal one (a part given nothing would
    #: take no time, and never be given anything again).
    FLOOR = 0.05

    def took(self, seconds: Sequence[float]) -> None:
        """Each part of the last split took ``seconds``: move the shares halfway to those
        that would have made them equal (each at least ``FLOOR`` of an equal share)."""
        seconds = np.asarray(seconds, np.float64)
        if len(seconds) != len(self.shares) or not (seconds > 0).all():
            return
        fair = self.shares / seconds  # work a second, each
        fair = self.FLOOR / len(fair) + (1 - self.FLOOR) * fair / fair.sum()
        self.shares = self.shares + 0.5 * (fair - self.shares)


def chunks(items: int, work: np.ndarray | None = None, min_work: int = 0, per_thread: int = 1
           ) -> list[tuple[int, int]]:
    """``[start, stop)`` ranges splitting ``items`` into at most ``per_thread`` x
    :func:`count` parts of at least ``MIN_CHUNK`` items each, of equal ``work`` (its cumulative
    sum, ``(items + 1,)``, for example a CSR ``start`` array) when given, else of equal size;
    with ``min_work``, of at least that much work each. More parts than threads let
    :func:`run` even out threads that the system gives less time (one busy beside them)."""
    threads = count()
    parts = max(1, min(threads * per_thread if threads > 1 else 1, items // MIN_CHUNK))
    if min_work and work is not None:
        parts = max(1, min(parts, int(work[-1] - work[0]) // min_work))
    if work is None or parts == 1 or work[-1] <= work[0]:
        edges = [round(items * k / parts) for k in range(parts + 1)]
    else:
        goal = work[0] + (work[-1] - work[0]) * np.arange(1, parts) / parts
        edges = [0, *np.searchsorted(work, goal).tolist(), items]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _executor(size: int) -> ThreadPoolExecutor:
    """The kernels' pool, with at least ``size`` threads."""
    global _pool, _pool_size
    with _lock:  # a task run :func:`aside` may split its work too
        if _pool is None or _pool_size < size:
            _pool_size = size
            _pool = ThreadPoolExecutor(size, thread_name_prefix="wallcull-kernel")
        return _pool


def run(task: Callable[[int, int, int], object], ranges: Sequence[tuple[int, int]]) -> list:
    """``task(k, start, stop)`` for every range ``k``, in this thread and up to
    :func:`count` - 1 of the pool's, each taking the next range not yet taken until none is
    left: a thread busy elsewhere (with a task run :func:`aside`, or not given a core) takes
    fewer, or none, and is not waited for; results in order."""
    helpers = min(len(ranges), count()) - 1
    if helpers <= 0:
        return [task(k, *r) for k, r in enumerate(ranges)]
    pool = _executor(helpers)
    results: list = [None] * len(ranges)
    taken = itertools.count()  # next() of a count is atomic under the interpreter's lock

    def work():
        for k in taken:
            if k >= len(ranges):
                return
            results[k] = task(k, *ranges[k])

    futures = [pool.submit(work) for _ in range(helpers)]
    work()
    for f in futures:
        if not f.cancel():  # one not started yet would find nothing left
            f.result()
    return results


def aside(task: Callable[[], object]) -> Callable[[], object]:
    """Start ``task()`` in the pool, beside whatever the caller does next (which may split its
    own kernels with :func:`run`: their parts then go to the threads the task leaves free),
    and return a function that waits for its result (or runs it, if no thread has taken it
    yet). With one thread it runs when its result is asked for."""
    if count() == 1:
        return task
    future = _executor(count() - 1).submit(task)
    return lambda: task() if future.cancel() else future.result()


_background: ThreadPoolExecutor | None = None


async def background(task: Callable, *args, **kwargs):
    """``task(*args, **kwargs)`` in a pool of its own, for work that takes long but that
    nobody waits on to the millisecond (making a 256 x 256 wall, loading a scene, encoding a
    large answer, a console's status, loading the kernels), so that frames, which use the
    event loop's default pool, never queue behind it. (Not at a lower priority: a thread the
    system runs less often would hold the interpreter's lock, or numba's compiler lock, for
    longer, and the event loop would wait on it.)"""
    import asyncio
    import functools

    global _background
    if _background is None:
        _background = ThreadPoolExecutor(4, thread_name_prefix="wallcull-background")
    return await asyncio.get_running_loop().run_in_executor(
        _background, functools.partial(task, *args, **kwargs))
