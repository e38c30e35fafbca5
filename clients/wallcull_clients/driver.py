"""The load driver: moves the camera along a scene's walkthrough and posts frames at a rate.

Every frame it posts ``{"frame": ...}`` (msgpack) over the wall's frame stream (one WebSocket,
``--post stream``, the default) or to ``POST /walls/{wid}/frames`` (``--post http``), recording
the time it sent the frame and the time the answer came back. With ``barrier`` it then waits on the
swap barrier, ``GET /walls/{wid}/barrier/{n}``, until every tile has acknowledged frame ``n``
(or ``barrier_timeout`` seconds), and records when it completed: frame ``n + 1`` is never posted
before the barrier of ``n`` has answered. Frames are paced from a fixed schedule (frame ``k`` no
earlier than ``t0 + k / rate``). A driver that falls behind by more than a frame period (a
server that stalled, a barrier that waited) skips the slots it missed and posts the frame of the
current one, as a tracker sends its newest pose rather than a backlog; the last frame is always
posted, and the summary counts the frames skipped (``--no-skip``: post every frame, the late ones
at once).

The camera follows :func:`wallcull.paths.camera_path` around the scene's bounds (from
``GET /scenes/{name}``), one loop every ``path_frames`` frames.

Every request is retried with backoff while the server is away (:mod:`.retry`); the driver
fails with a message and a non-zero status when the server stays away longer than
``--retry-for`` seconds or refuses a request for good.

    python -m wallcull_clients.driver --server http://127.0.0.1:8000 --scene powerplant \\
        --wall examples/wall-8x8.json --rate 60 --frames 600 [--barrier] [--path fly] \\
        [--credentials-out credentials.json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Callable
from urllib.parse import quote

import msgpack
import numpy as np
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from wallcull.documents import MAX_IPD
from wallcull.errors import InputError
from wallcull.paths import PATHS, camera_path
from wallcull.wall import Wall

from .rawhttp import Connection, HTTPError, run
from .retry import Backoff, ClientFailure, Stopped, retrying, stop_on_signals

PATH_FRAMES = 600  # one loop of the walkthrough: 10 s at 60 frames/s


@dataclass
class FrameLog:
    """What the driver saw of each frame (parallel lists, one entry per posted frame)."""

    frame: list[int] = field(default_factory=list)  # the server's frame number
    send: list[float] = field(default_factory=list)  # time.time() before the POST
    done: list[float] = field(default_factory=list)  # time.time() when its answer came
    total_ms: list[float] = field(default_factory=list)  # the server's own time for the frame
    cull_ms: list[float] = field(default_factory=list)
    barrier_done: list[float] = field(default_factory=list)  # when the barrier answered
    barrier_complete: list[bool] = field(default_factory=list)
    barrier_acked: list[int] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)  # path frames whose slot had passed

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def path_frames(kind: str, lo, hi, wall: dict, count: int, loop: int = PATH_FRAMES,
                up=(0.0, 1.0, 0.0), stereo: float | None = None) -> list[dict]:
    """``count`` frame dicts (SPEC section 3) of path ``kind``, repeating every ``loop``;
    ``stereo``: stereo frames, the eyes this far apart (m) across an untracked head."""
    loop = max(1, min(loop, count)) if loop else count
    frames = [f.to_dict() for f in camera_path(kind, np.asarray(lo, float),
                                               np.asarray(hi, float), Wall.from_dict(wall),
                                               loop, up=up)]
    if stereo is not None:
        for f in frames:
            f["stereo"] = {"ipd": stereo, "head": [1.0, 0.0, 0.0, 0.0]}
    return [frames[k % loop] for k in range(count)]


def ipd(text: str) -> float:
    """An interpupillary distance from the command line: over 0 and at most ``MAX_IPD`` m,
    as the server takes it."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value <= MAX_IPD:
        raise argparse.ArgumentTypeError(f"an interpupillary distance is over 0 and at most "
                                         f"{MAX_IPD:g} m, got {text}")
    return value


class Driver:
    """Posts frames to one wall of a server (see the module docstring). Every request is
    retried with backoff while the server is away (a restart), for up to ``retry_for``
    seconds; the server numbers frames on after the last one it handed out, so frames stay
    in order across a restart (one whose answer was lost is posted again, as a new frame).
    ``stop``: an event that ends the retrying at once (:class:`.retry.Stopped`) and the run."""

    def __init__(self, server: str, token: str | None = None, timeout: float = 30.0,
                 retry_for: float = 60.0, stop: asyncio.Event | None = None):
        self.server = server.rstrip("/")
        self.token = token
        self.conn = Connection(server, token, timeout)
        self._frames = None  # the frame stream, once opened
        self.log = FrameLog()
        self.backoff = Backoff(retry_for, stop=stop)

    @property
    def retries(self) -> int:
        """Requests sent again because the server was away."""
        return self.backoff.total

    async def call(self, method: str, target: str, payload=None, **kwargs):
        """``Connection.call``, retried (see the class docstring)."""
        return await retrying(lambda: self.conn.call(method, target, payload, **kwargs),
                              self.backoff, f"{method} {target}")

    async def close(self) -> None:
        await self._close_frames()
        await self.conn.close()

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc):
        await self.close()

    async def create_wall(self, scene: str, wall: dict, method: str = "adaptive",
                          bounds: str = "obb", history: int = 64, settings: dict | None = None,
                          shadow_fit: str = "refined", nodes: list | None = None) -> dict:
        """``POST /walls``; returns the wall's info (``id``, ``tiles``, ...) and its
        ``credentials`` (the driver's and one per node, shown this once). ``settings``: lights
        and mirrors for this wall instead of the scene's own; ``nodes``: the tiles of each node
        credential (default: one per tile)."""
        body = {"wall": wall, "scene": scene, "method": method, "bounds": bounds,
                "history": history, "shadow_fit": shadow_fit}
        if settings is not None:
            body["settings"] = settings
        if nodes is not None:
            body["nodes"] = nodes
        return await self.call("POST", "/walls", body, auth=True)

    async def wall_info(self, wid: str) -> dict:
        return await self.call("GET", f"/walls/{wid}")

    async def frames(self, scene: str, wall: dict, kind: str, count: int,
                     loop: int = PATH_FRAMES, stereo: float | None = None) -> list[dict]:
        """The walkthrough's frames around the scene's bounds, as the server reports them
        (``stereo``: see :func:`path_frames`)."""
        info = await self.call("GET", f"/scenes/{quote(scene, safe='')}")
        return path_frames(kind, info["bounds"]["min"], info["bounds"]["max"], wall, count,
                           loop, info.get("settings", {}).get("up", (0.0, 1.0, 0.0)), stereo)

    async def wait_clients(self, wid: str, count: int, timeout: float) -> int:
        """Wait until ``count`` nodes stream from the wall; returns how many do."""
        deadline = time.monotonic() + timeout
        while True:
            subscribers = (await self.wall_info(wid))["subscribers"]
            if subscribers >= count or time.monotonic() > deadline:
                return subscribers
            await asyncio.sleep(0.1)

    async def post(self, wid: str, frame: dict) -> dict:
        """Post one frame: over the frame stream when :meth:`stream_frames` opened it (and
        over HTTP again while the server is away: a restart), else ``POST .../frames``. A
        wall gone (deleted, or missing after a restart) is a :class:`ClientFailure` saying so."""
        try:
            if self._frames is not None:
                try:
                    await self._frames.send(msgpack.packb({"frame": frame}))
                    answer = msgpack.unpackb(await self._frames.recv())
                except (OSError, ConnectionClosed):
                    await self._close_frames()
                else:
                    if "error" in answer:
                        raise HTTPError(answer["status"], answer["error"], "POST",
                                        "frame stream")
                    return answer
            return await self.call("POST", f"/walls/{wid}/frames", {"frame": frame},
                                   auth=True, body_format="msgpack")
        except HTTPError as exc:
            # its wall gone (its credential forgotten with it)?
            if exc.status in (401, 404) and await self.conn.wall_deleted(wid):
                raise ClientFailure(f"wall {wid} was deleted") from None
            raise

    async def stream_frames(self, wid: str) -> None:
        """Post this wall's frames over one WebSocket (``/walls/{wid}/frames/stream``) from now
        on: a few tens of microseconds of server time a frame, where a request takes a
        millisecond."""
        query = f"?token={quote(self.token, safe='')}" if self.token else ""
        self._frames = await connect(f"ws{self.server[len('http'):]}/walls/{wid}/frames/stream"
                                     f"{query}", max_size=None, compression=None)

    async def _close_frames(self) -> None:
        frames, self._frames = self._frames, None
        if frames is not None:
            await frames.close()

    async def barrier(self, wid: str, number: int, timeout: float) -> dict:
        return await self.call("GET", f"/walls/{wid}/barrier/{number}?timeout={timeout:g}")

    async def run(self, wid: str, frames: list[dict], rate: float = 60.0, barrier: bool = False,
                  barrier_timeout: float = 1.0, on_event: Callable | None = None,
                  stop: asyncio.Event | None = None,
                  progress: Callable[[int], None] | None = None,
                  skip: bool = False) -> FrameLog:
        """Post ``frames`` in order at ``rate`` per second (0: as fast as possible). With
        ``skip``, a driver behind its schedule by more than a frame period skips the frames
        whose slots have passed (``log.skipped``; never the last frame). The run ends early
        when ``stop`` is set, also while a request is being retried.

        ``on_event(kind, frame)`` is called with ``"post"`` just before a frame is sent,
        ``"posted"`` when its answer came and ``"barrier"`` when its barrier answered.
        """
        log = self.log
        period = 1.0 / rate if rate > 0 else 0.0
        t0 = time.monotonic()
        k = -1
        while k + 1 < len(frames):
            k += 1
            if stop is not None and stop.is_set():
                break
            delay = t0 + k * period - time.monotonic()
            if skip and period and -delay > period:  # behind: the current slot's frame
                now_k = min(int((time.monotonic() - t0) / period), len(frames) - 1)
                if now_k > k:
                    log.skipped.extend(range(k, now_k))
                    k = now_k
                delay = t0 + k * period - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            frame = frames[k]
            if on_event:
                on_event("post", log.frame[-1] + 1 if log.frame else None)
            send = time.time()
            try:
                answer = await self.post(wid, frame)
            except Stopped:
                break
            done = time.time()
            number = answer["frame"]
            log.frame.append(number)
            log.send.append(send)
            log.done.append(done)
            log.total_ms.append(answer["timings"]["total_ms"])
            log.cull_ms.append(answer["timings"]["cull_ms"])
            if on_event:
                on_event("posted", number)
            if barrier:
                try:
                    state = await self.barrier(wid, number, barrier_timeout)
                except Stopped:
                    break
                log.barrier_done.append(time.time())
                log.barrier_complete.append(bool(state["complete"]))
                log.barrier_acked.append(int(state["acked"]))
                if on_event:
                    on_event("barrier", number, state)
            if progress:
                progress(k + 1)
        return log


def summary(log: FrameLog) -> dict:
    """Achieved rate, post round trips and barrier latencies (ms)."""
    out: dict = {"frames": len(log.frame), "skipped": len(log.skipped)}
    if len(log.send) > 1:
        out["rate"] = (len(log.send) - 1) / (log.send[-1] - log.send[0])
    if log.frame:
        rtt = (np.asarray(log.done) - np.asarray(log.send)) * 1e3
        out["post_ms"] = {"p50": float(np.median(rtt)), "p99": float(np.percentile(rtt, 99))}
    if log.barrier_done:
        lat = (np.asarray(log.barrier_done) - np.asarray(log.send)) * 1e3
        out["barrier_ms"] = {"p50": float(np.median(lat)), "p99": float(np.percentile(lat, 99))}
        out["barrier_incomplete"] = int(len(log.barrier_complete) - sum(log.barrier_complete))
    return out


# --------------------------------------------------------------------------- command line


def read_wall(text: str) -> dict:
    from wallcull.documents import read_json

    return read_json(text, "--wall")


def _count_or_all(text: str):
    if text == "all":
        return text
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"expected a number or 'all', got {text!r}")
    return int(text)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m wallcull_clients.driver",
                                description="Post a walkthrough's frames to a wallcull wall.")
    p.add_argument("--server", default=os.environ.get("WALLCULL_SERVER", "http://127.0.0.1:8000"))
    p.add_argument("--scene", default="powerplant")
    p.add_argument("--wall", default="examples/wall-4x4.json",
                   help="WALL.json (or inline JSON) of the wall to create")
    p.add_argument("--wall-id", help="drive this existing wall instead of creating one")
    p.add_argument("--method", default="adaptive")
    p.add_argument("--bounds", default="obb")
    p.add_argument("--history", type=int, default=64)
    p.add_argument("--rate", type=float, default=60.0, help="frames per second (0: flat out)")
    p.add_argument("--frames", type=int, default=600)
    p.add_argument("--path", choices=PATHS, default="orbit")
    p.add_argument("--path-frames", type=int, default=PATH_FRAMES,
                   help="frames per loop of the path")
    p.add_argument("--stereo", type=ipd, metavar="IPD",
                   help="post stereo frames, the eyes this far apart (m, e.g. 0.064)")
    p.add_argument("--post", choices=("stream", "http"), default="stream",
                   help="post frames over one WebSocket (the frame stream) or one request each")
    p.add_argument("--no-skip", action="store_true",
                   help="post every frame, the late ones at once, instead of skipping the "
                        "slots a driver behind its schedule missed")
    p.add_argument("--barrier", action="store_true", help="wait on the swap barrier every frame")
    p.add_argument("--barrier-timeout", type=float, default=1.0)
    p.add_argument("--wait-clients", type=_count_or_all, default=0, metavar="N|all",
                   help="before driving, wait until N nodes (all: one per tile) stream from "
                        "the wall (WebSocket nodes; pulling nodes need no wait)")
    p.add_argument("--wait-timeout", type=float, default=60.0)
    p.add_argument("--token", default=os.environ.get("WALLCULL_TOKEN") or None,
                   help="the server's (operator's) token, or with --wall-id the wall's driver "
                        "credential (default: $WALLCULL_TOKEN)")
    p.add_argument("--credentials-out", metavar="FILE",
                   help="write the created wall's credentials here (mode 0600) for the nodes "
                        "(python -m wallcull_clients.sim --credentials FILE)")
    p.add_argument("--retry-for", type=float, default=60.0, metavar="SECONDS",
                   help="how long to keep retrying a lost server before failing")
    p.add_argument("--out", help="write the per-frame log to this JSON file")
    p.add_argument("--delete", action="store_true", help="delete the wall when done")
    return p


async def _wait_server(server: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            async with Connection(server, timeout=5) as conn:
                await conn.call("GET", "/health")
                return
        except (ConnectionError, OSError, asyncio.TimeoutError, HTTPError):
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)


async def _main(args) -> int:
    stop, driving = asyncio.Event(), [False]
    stop_on_signals(stop, lambda: driving[0])
    wall = None if args.wall_id else read_wall(args.wall)  # bad input before any wall is made
    for path in (args.credentials_out, args.out):
        if path and not os.path.isdir(os.path.dirname(os.path.abspath(path))):
            raise InputError(f"no folder for {path}")
    await _wait_server(args.server, args.wait_timeout)
    async with Driver(args.server, args.token, retry_for=args.retry_for, stop=stop) as driver:
        if args.wall_id:
            info = await driver.wall_info(args.wall_id)
        else:
            info = await driver.create_wall(args.scene, wall, args.method, args.bounds,
                                            args.history)
        wid = info["id"]
        try:
            if args.credentials_out and not args.wall_id:
                write_private(args.credentials_out, {"wall": wid,
                                                     "credentials": info["credentials"]})
            print(json.dumps({"wall": wid, "tiles": info["tiles"], "scene": info["scene"]}),
                  flush=True)
            frames = await driver.frames(info["scene"], info["wall"], args.path, args.frames,
                                         args.path_frames, args.stereo)
            if args.wait_clients:
                want = info["tiles"] if args.wait_clients == "all" else args.wait_clients
                n = await driver.wait_clients(wid, want, args.wait_timeout)
                print(json.dumps({"subscribers": n}), flush=True)
                if n < want:
                    print(f"clients.driver: only {n} of {want} nodes stream from wall {wid} "
                          f"after {args.wait_timeout:g} s: driving anyway", file=sys.stderr)
            if args.post == "stream":
                await driver.stream_frames(wid)
            driving[0] = True  # from now on a signal ends the run, with its summary
            # the span of the posts, for whoever measures it (wallcull loadtest's CPU)
            print(json.dumps({"driving": True, "cpu_seconds": time.process_time()}), flush=True)
            log = await driver.run(wid, frames, args.rate, args.barrier, args.barrier_timeout,
                                   stop=stop, skip=not args.no_skip)
            print(json.dumps({"driven": True, "cpu_seconds": time.process_time()}), flush=True)
        except BaseException:
            if args.delete:  # the wall this run made or drove goes, whatever stopped it
                await asyncio.shield(driver.call("DELETE", f"/walls/{wid}", auth=True))
            raise
        result = {"wall": wid, "summary": {**summary(log), "retries": driver.retries}}
        if args.out:
            tmp = f"{args.out}.tmp"
            with open(tmp, "w") as f:
                json.dump({**result, "log": log.to_dict(), "cpu_seconds": time.process_time()}, f)
            os.replace(tmp, args.out)
        if args.delete:
            await driver.call("DELETE", f"/walls/{wid}", auth=True)
        print(json.dumps(result), flush=True)
    return 0


def write_private(path: str, data: dict) -> None:
    """JSON readable by this user only (credentials), whatever the file was before."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.fchmod(fd, 0o600)  # (an existing file keeps its mode through open)
    with os.fdopen(fd, "w") as f:
        json.dump(data, f)


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if not 0 < args.barrier_timeout <= 10:
        parser().error("--barrier-timeout must be over 0 and at most 10 seconds")
    if args.frames < 1 or args.path_frames < 2 or args.history < 2:
        parser().error("--frames must be at least 1, --path-frames and --history at least 2")
    for name in ("rate", "wait_timeout", "retry_for"):
        if not 0 <= getattr(args, name) < float("inf") or name != "rate" and not \
                getattr(args, name):
            parser().error(f"--{name.replace('_', '-')} must be a positive number")
    try:
        return run(_main(args))
    except (ConnectionError, OSError, asyncio.TimeoutError, HTTPError, ValueError,
            InputError, ClientFailure) as exc:
        print(f"clients.driver: error: {exc}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, asyncio.CancelledError):  # a signal before the frames went
        print("clients.driver: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
