"""Work a client can make long or large, run in a child process the server can give up on.

Parsing an uploaded file, preparing a scene the server has not seen, fitting minimum-volume
boxes to every leaf: each can take seconds to minutes and gigabytes, and none of it may run
where requests are served. :func:`run` calls a function in a child forked from a small server
process that has numpy, trimesh and wallcull's scene code already imported (multiprocessing's
``forkserver``: a child starts in milliseconds), with ``RLIMIT_AS`` (address space) and
``RLIMIT_CPU`` set and a wall-clock deadline. A child that allocates too much, loops or crashes
costs an :class:`~wallcull.errors.InputError` that says so, never the server. The answer comes
back pickled. (The child runs as the same user: it contains memory, time and crashes, not code
execution.)
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from multiprocessing import spawn
from typing import Any, Callable

from .errors import InputError, WriteFailed

_context_lock = threading.Lock()
_context = None
CHILD = "wallcull-child"
#: The environment variables a child takes from its parent as they are when it is started
#: (the forkserver's own copy is the environment when the forkserver started).
ENV_PREFIX = "WALLCULL_"


def _forkserver():
    """The forkserver context, with the heavy modules imported once in its server process."""
    global _context
    with _context_lock:
        if _context is None:
            ctx = multiprocessing.get_context("forkserver")
            ctx.set_forkserver_preload(["numpy", "trimesh", "wallcull.scene", "wallcull.uploads",
                                        "wallcull.bounds"])
            spawn.get_preparation_data = _without_main
            _context = ctx
    return _context


def _without_main(name, _original=spawn.get_preparation_data):
    """multiprocessing's data for a new child, less ``__main__`` for a wallcull child: it
    needs nothing from it, and importing it again there would run a script without a main
    guard (or fail on ``python - < script``)."""
    data = _original(name)
    if name.startswith(CHILD):
        data.pop("init_main_from_name", None)
        data.pop("init_main_from_path", None)
    return data


def _child(conn, target: Callable, args: tuple, memory: int, seconds: float, what: str,
           env: dict) -> None:
    """The child's side: the parent's ``WALLCULL_*`` settings (``env``: where prepared scenes
    go, ...), limits, then the work; the answer goes back on ``conn``."""
    import resource

    for key in [k for k in os.environ if k.startswith(ENV_PREFIX)]:
        del os.environ[key]
    os.environ.update(env)

    with open("/proc/self/status") as f:
        vm = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
    resource.setrlimit(resource.RLIMIT_AS, (vm + memory, vm + memory))
    cpu = int(seconds) + 1
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 5))
    try:
        answer = ("done", target(*args))
    except WriteFailed as exc:  # a disk problem, not the input's: its type goes back too
        answer = ("raised", exc)
    except InputError as exc:
        answer = ("refused", str(exc))
    except MemoryError:
        answer = ("refused", f"{what} needs more than {memory:,} bytes of memory")
    except RecursionError:
        answer = ("refused", f"{what}: its input nests too deeply")
    try:
        conn.send(answer)
    except MemoryError:
        conn.send(("refused", f"{what}: the answer is too large to hand back"))
    conn.close()


def run(target: Callable, args: tuple, *, seconds: float, memory: int, what: str) -> Any:
    """``target(*args)`` in a child process with ``memory`` bytes of address space (beyond
    what it starts with) and ``seconds`` of time; ``target`` and its answer must pickle.
    Blocking: call it from a worker thread. Whatever goes wrong in the child is an
    :class:`InputError` starting with ``what`` (e.g. ``"parsing the uploaded GLB"``), but a
    :class:`WriteFailed` (a full or read-only disk), which comes back as it was raised."""
    ctx = _forkserver()
    receive, send = ctx.Pipe(duplex=False)
    env = {k: v for k, v in os.environ.items() if k.startswith(ENV_PREFIX)}
    proc = ctx.Process(target=_child, args=(send, target, args, memory, seconds, what, env),
                       daemon=True, name=f"{CHILD}-{what[:40]}")
    proc.start()
    send.close()
    try:
        if not receive.poll(seconds):
            raise InputError(f"{what} took over {seconds:g} s: refused (a limit: "
                             "--limit parse_seconds=...)")
        try:
            kind, value = receive.recv()
        except (EOFError, OSError):
            proc.join(5)
            raise InputError(f"{what}: the worker process died (exit status "
                             f"{proc.exitcode}): refused") from None
    finally:
        receive.close()
        if proc.is_alive():
            proc.kill()
        proc.join(5)
    if kind == "refused":
        raise InputError(value)
    if kind == "raised":
        raise value
    return value
