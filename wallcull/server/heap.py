"""The server process's C heap: glibc's allocator, set for a server that makes big, short-lived
buffers in a few threads.

Two defaults of glibc's ``malloc`` make a long-running server keep memory it no longer uses:

* every thread that allocates gets an arena of its own, up to eight per core, and an arena
  keeps what its thread freed for that thread; the server's worker threads (culling, encoding
  a console's status) each held megabytes this way;
* a buffer over the mapping threshold (128 kB at first) is mapped, and unmapped when freed,
  but each such free raises the threshold to the buffer's size (up to 32 MB): after the first
  2 MB status of a 256 x 256 wall, every later one is cut from an arena, and the arena's
  free space is fragmented by what lives between them.

:func:`tune` sets two arenas and a fixed mapping threshold of 1 MB: buffers of 1 MB and more
(big walls' per-tile tables, console statuses, whole packets) go back to the system when
freed; smaller ones (every array of a wall of up to 64 x 64 tiles) stay on the heap, as
before. Measured with ``python -m wallcull_clients.hostile huge`` (docs/hardening.md). The
environment's own ``MALLOC_ARENA_MAX`` or ``MALLOC_MMAP_THRESHOLD_`` wins: then nothing is
changed. Elsewhere than glibc, nothing is done.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

#: glibc's mallopt parameters (malloc.h).
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8

ARENAS = 2
MAP_FROM = 1 << 20


def tune() -> dict:
    """Set glibc's arenas and mapping threshold (see the module docstring); returns what was
    set, ``{}`` when nothing was (not glibc, or the environment chose)."""
    if os.environ.get("MALLOC_ARENA_MAX") or os.environ.get("MALLOC_MMAP_THRESHOLD_"):
        return {}
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # glibc only: other C libraries' mallopt differ
    except (OSError, AttributeError, TypeError):
        return {}
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    done = {}
    if mallopt(M_ARENA_MAX, ARENAS):
        done["arenas"] = ARENAS
    if mallopt(M_MMAP_THRESHOLD, MAP_FROM):
        done["mmap_threshold"] = MAP_FROM
    return done
