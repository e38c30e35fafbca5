"""Hostile and unlucky clients, measured against a real server on loopback.

Each scenario starts ``wallcull serve`` in a subprocess (:class:`~.loadtest.Server`, its own
state folder), does to it what issue 10 found a client could do, and reports what it cost the
server: its resident memory (sampled every 20 ms), the statuses it answered, its frame rate,
how long its event loop stalled, how long nodes took to come back after it was killed.

    python -m wallcull_clients.hostile glb-bomb     # a 1 kB GLB declaring 10^8 vertices
    python -m wallcull_clients.hostile uploads      # 10 concurrent unauthenticated 60 MB uploads
    python -m wallcull_clients.hostile streams      # 1000 stream opens without a credential
    python -m wallcull_clients.hostile acks         # an ack with another tile's credential
    python -m wallcull_clients.hostile loop         # 1 MiB of updates; 100k nodes described
    python -m wallcull_clients.hostile restart      # SIGKILL mid-run on an 8 x 8 wall
    python -m wallcull_clients.hostile handshakes   # server CPU per TLS handshake, RSA and ECDSA
    python -m wallcull_clients.hostile all --json

The tests run bounded versions of the same functions (``tests/test_hardening.py``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import struct
import sys
import tempfile
import time
from contextlib import asynccontextmanager
from pathlib import Path

import numpy as np

from .driver import Driver
from .loadtest import ROOT, Server, _wall_spec, kernels_loaded
from .rawhttp import Connection

TOKEN = "hostile-operator-token"
MiB = 1 << 20


# --------------------------------------------------------------------------- measuring


class RSS:
    """The resident memory of a process, sampled every ``period`` seconds while in use."""

    def __init__(self, pid: int, period: float = 0.02):
        import psutil

        self.proc, self.period = psutil.Process(pid), period
        self.before = self.peak = self.after = self.proc.memory_info().rss

    async def __aenter__(self):
        self.before = self.peak = self.proc.memory_info().rss
        self._task = asyncio.ensure_future(self._sample())
        return self

    async def _sample(self):
        while True:
            self.peak = max(self.peak, self.proc.memory_info().rss)
            await asyncio.sleep(self.period)

    async def __aexit__(self, *exc):
        self._task.cancel()
        self.after = self.proc.memory_info().rss
        self.peak = max(self.peak, self.after)

    def report(self) -> dict:
        return {"rss_before_mb": self.before / MiB, "rss_peak_mb": self.peak / MiB,
                "rss_after_mb": self.after / MiB, "growth_mb": (self.peak - self.before) / MiB}


@asynccontextmanager
async def server(token: str | None = TOKEN, args=(), state: str | None = None, port=None,
                 prefix=()):
    s = Server(token, port=port, state=state, args=args, prefix=prefix)
    await s.start()
    await kernels_loaded(s.url)  # memory is measured once the kernels are in
    try:
        yield s
    finally:
        await s.stop()


class Probe:
    """Polls ``GET /health`` every ``period`` seconds (on one keep-alive connection, or on a
    new connection each time with ``fresh``) and keeps every answer's latency and every poll
    that got none: how long the server's event loop could not answer, and whether it ever
    did not."""

    def __init__(self, url: str, period: float = 0.05, fresh: bool = False,
                 timeout: float = 10.0):
        self.url, self.period, self.fresh, self.timeout = url, period, fresh, timeout
        self.latencies: list[float] = []
        self.failures: list[str] = []

    async def __aenter__(self):
        self._stop = False
        self._task = asyncio.ensure_future(self._run())
        await asyncio.sleep(0.2)
        return self

    async def _run(self):
        conn = None
        while not self._stop:
            t = time.perf_counter()
            try:
                if conn is None:
                    conn = Connection(self.url, timeout=self.timeout)
                r = await conn.request("GET", "/health", accept="application/json")
                if r.status != 200:
                    self.failures.append(f"HTTP {r.status}")
                self.latencies.append(time.perf_counter() - t)
            except (ConnectionError, OSError, asyncio.TimeoutError,
                    asyncio.IncompleteReadError) as exc:
                self.failures.append(type(exc).__name__)
                await conn.close()
                conn = None
            if self.fresh and conn is not None:
                await conn.close()
                conn = None
            await asyncio.sleep(max(0.0, self.period - (time.perf_counter() - t)))
        if conn is not None:
            await conn.close()

    async def __aexit__(self, *exc):
        self._stop = True
        await self._task

    def worst_ms(self) -> float:
        return 1e3 * max(self.latencies) if self.latencies else float("nan")

    def report(self) -> dict:
        lat = np.asarray(self.latencies) * 1e3
        return {"health_polls": len(self.latencies) + len(self.failures),
                "health_failed": len(self.failures),
                "health_worst_ms": float(lat.max()) if len(lat) else None,
                "health_p99_ms": float(np.percentile(lat, 99)) if len(lat) else None}


# --------------------------------------------------------------------------- hostile files


def glb(doc: dict, binary: bytes = b"") -> bytes:
    """A GLB of ``doc`` (JSON) and ``binary``."""
    j = json.dumps(doc, separators=(",", ":")).encode()
    j += b" " * (-len(j) % 4)
    out = struct.pack("<II", len(j), 0x4E4F534A) + j
    if binary:
        b = binary + b"\0" * (-len(binary) % 4)
        out += struct.pack("<II", len(b), 0x004E4942) + b
    return struct.pack("<4sII", b"glTF", 2, 12 + len(out)) + out


def vertex_bomb(count: int) -> bytes:
    """Issue 10's file: a POSITION accessor with no buffer view declaring ``count`` vertices,
    three of them given by a sparse part (about 600 bytes)."""
    values = np.zeros((3, 3), "<f4").tobytes()
    indices = np.arange(3, dtype="<u4").tobytes()
    return glb({
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"name": "bomb", "mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "buffers": [{"byteLength": len(indices) + len(values)}],
        "bufferViews": [{"buffer": 0, "byteLength": len(indices)},
                        {"buffer": 0, "byteOffset": len(indices), "byteLength": len(values)}],
        "accessors": [{"componentType": 5126, "type": "VEC3", "count": count,
                       "min": [0, 0, 0], "max": [1, 1, 1],
                       "sparse": {"count": 3, "indices": {"bufferView": 0, "componentType": 5125},
                                  "values": {"bufferView": 1}}}]}, indices + values)


def many_nodes(n: int, per: int = 100) -> bytes:
    """A GLB of ``n`` unit boxes (one shared mesh), in groups of ``per`` under one root."""
    box_v = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)], "<f4")
    box_f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], "<u4")
    v, f = box_v.tobytes(), box_f.tobytes()
    groups = (n + per - 1) // per
    nodes = [{"name": "root", "children": list(range(1, groups + 1))}]
    first = groups + 1
    for g in range(groups):
        kids = list(range(first + g * per, first + min((g + 1) * per, n)))
        nodes.append({"name": f"g{g}", "children": kids})
    nodes += [{"name": f"n{i}", "mesh": 0,
               "translation": [2.0 * (i % 100), 2.0 * (i // 100 % 100), -10.0 - 2 * (i // 10000)]}
              for i in range(n)]
    return glb({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
                "nodes": nodes,
                "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
                "buffers": [{"byteLength": len(v) + len(f)}],
                "bufferViews": [{"buffer": 0, "byteLength": len(v)},
                                {"buffer": 0, "byteOffset": len(v), "byteLength": len(f)}],
                "accessors": [{"bufferView": 0, "componentType": 5126, "type": "VEC3",
                               "count": 8, "min": [-.5] * 3, "max": [.5] * 3},
                              {"bufferView": 1, "componentType": 5125, "type": "SCALAR",
                               "count": 36}]}, v + f)


# --------------------------------------------------------------------------- raw requests


async def raw_post(url: str, target: str, size: int, token: str | None = None,
                   content_type: str = "model/gltf-binary", stall_after: int | None = None,
                   chunk: int = 1 << 16) -> dict:
    """POST ``size`` bytes (``glTF`` then zeros) to ``target``, as fast as the server reads
    them, or stalling after ``stall_after`` bytes; stops sending once the server has
    answered. Returns the status, the bytes sent and the seconds until the answer."""
    from urllib.parse import urlsplit

    parts = urlsplit(url)
    t0 = time.perf_counter()
    reader, writer = await asyncio.open_connection(parts.hostname, parts.port)
    head = [f"POST {target} HTTP/1.1", f"host: {parts.netloc}",
            f"content-type: {content_type}", f"content-length: {size}"]
    if token:
        head.append(f"authorization: Bearer {token}")
    writer.write(("\r\n".join(head) + "\r\n\r\n").encode())
    answer = asyncio.ensure_future(reader.readuntil(b"\r\n\r\n"))
    sent, block = 0, b"glTF" + bytes(chunk - 4)
    try:
        while sent < size and not answer.done():
            if stall_after is not None and sent >= stall_after:
                await asyncio.wait([answer], timeout=120)
                break
            piece = block[:min(chunk, size - sent)]
            writer.write(piece)
            sent += len(piece)
            drain = asyncio.ensure_future(writer.drain())
            await asyncio.wait([drain, answer], return_when=asyncio.FIRST_COMPLETED)
            if not drain.done():
                drain.cancel()
        status = int((await asyncio.wait_for(answer, 120)).split(b" ", 2)[1])
    except (ConnectionError, asyncio.IncompleteReadError, asyncio.TimeoutError):
        status = answer.result().split(b" ", 2)[1] if answer.done() and not \
            answer.exception() else 0
        status = int(status)
    finally:
        writer.close()
    return {"status": status, "sent": sent, "seconds": time.perf_counter() - t0}


async def open_stream(url: str, path: str, token: str | None = None, origin: str | None = None,
                      hold: asyncio.Event | None = None, headers: dict | None = None):
    """Try to open a stream; the HTTP status of a refused handshake, or 101. An accepted
    stream is closed at once, or held until ``hold`` is set: idle, never acknowledging (and
    reading only what the client library buffers, 16 messages)."""
    from websockets.asyncio.client import connect
    from websockets.exceptions import InvalidStatus

    query = f"?token={token}" if token else ""
    headers = {**({"Origin": origin} if origin else {}), **(headers or {})} or None
    try:
        async with connect("ws" + url[4:] + path + query, open_timeout=30,
                           additional_headers=headers, compression=None, max_queue=16):
            if hold is not None:
                await hold.wait()
            return 101
    except InvalidStatus as exc:
        return exc.response.status_code


# --------------------------------------------------------------------------- scenarios


async def glb_bomb(vertices: int = 10 ** 8) -> dict:
    """Upload the vertex bomb; the answer and the server's memory."""
    data = vertex_bomb(vertices)
    async with server() as s:
        async with RSS(s.proc.pid) as rss:
            async with Connection(s.url, TOKEN, timeout=300) as conn:
                r = await conn.request("POST", "/scenes?name=bomb", data, "model/gltf-binary",
                                       auth=True, accept="application/json")
            await asyncio.sleep(0.5)
    return {"scenario": "glb-bomb", "file_bytes": len(data), "declared_vertices": vertices,
            "status": r.status, "detail": r.detail(), **rss.report()}


async def uploads(count: int = 10, size: int = 60 * MiB, token: str | None = None,
                  stall: bool = False, args=()) -> dict:
    """``count`` concurrent uploads of ``size`` bytes with ``token`` (None: no credential)
    to a server with a token; ``stall``: each stops after 1 MB and waits."""
    async with server(args=args) as s:
        async with RSS(s.proc.pid) as rss:
            results = await asyncio.gather(*(
                raw_post(s.url, f"/scenes?name=flood{k}", size, token,
                         stall_after=MiB if stall else None) for k in range(count)))
        healthy = (await _health(s.url))["status"] == "ok"
    return {"scenario": "uploads", "count": count, "bytes_each": size, "stalled": stall,
            "statuses": sorted(r["status"] for r in results),
            "sent_mb": sum(r["sent"] for r in results) / MiB,
            "seconds_max": max(r["seconds"] for r in results), "healthy_after": healthy,
            **rss.report()}


async def _health(url: str) -> dict:
    async with Connection(url) as conn:
        return await conn.call("GET", "/health")


async def acks() -> dict:
    """Acknowledge tile 1 with tile 0's node credential, and with the driver's."""
    wall = {"cols": 2, "rows": 1, "tile_size": [0.6, 0.34], "distance": 2.0}
    async with server() as s:
        async with Driver(s.url, TOKEN) as d:
            info = await d.create_wall("fatehpur", wall)
            frames = await d.frames("fatehpur", wall, "orbit", 1)
            await d.post(info["id"], frames[0])
        creds, wid = info["credentials"], info["id"]
        out = {}
        for who, token in (("node 0", creds["nodes"][0]["token"]), ("driver", creds["driver"]),
                           ("node 1", creds["nodes"][1]["token"])):
            async with Connection(s.url, token) as conn:
                r = await conn.request("POST", f"/walls/{wid}/tiles/1/ack", b'{"frame": 0}',
                                       "application/json", auth=True, accept="application/json")
            out[who] = r.status
        async with Connection(s.url) as conn:
            barrier = await conn.call("GET", f"/walls/{wid}/barrier/0?timeout=0")
    return {"scenario": "acks", "ack_tile_1_with": out, "barrier_acked": barrier["acked"]}


async def streams(opens: int = 1000, wall: str = "examples/wall-8x8.json", seconds: float = 8.0,
                  token: str | None = TOKEN) -> dict:
    """An 8 x 8 wall of 64 streaming nodes and a driver posting as fast as it can: frames/s
    for ``seconds``, then while ``opens`` streams are opened without a credential, then for
    ``seconds`` more with whatever was accepted held open, idle (with ``token=None``, a
    server without a token: every open is accepted up to the per-tile cap)."""
    async with server(token) as s, _wall_running(s, _wall_spec(wall)) as run:
        before = await run.rate(seconds)
        statuses: dict = {}
        hold = asyncio.Event()  # accepted streams stay open, idle, until the end

        async def one(k):
            try:
                code = await open_stream(s.url, f"/walls/{run.wid}/tiles/{k % run.tiles}/stream",
                                         hold=hold)
            except Exception as exc:  # noqa: BLE001 - counted, whatever the failure
                code = type(exc).__name__
            statuses[code] = statuses.get(code, 0) + 1

        attack = [asyncio.ensure_future(one(k)) for k in range(opens)]
        during = await run.rate(seconds)
        after = await run.rate(seconds)
        hold.set()
        await asyncio.gather(*attack)
    return {"scenario": "streams", "opens": opens, "server_token": token is not None,
            "statuses": statuses, "frames_per_s_before": before, "frames_per_s_during": during,
            "frames_per_s_after": after, "kept_during": during / before,
            "kept_after": after / before}


class _Running:
    def __init__(self, url, wid, tiles, credentials=None):
        self.url, self.wid, self.tiles, self.credentials = url, wid, tiles, credentials

    async def latest(self) -> tuple[int, float]:
        async with Connection(self.url) as conn:
            return (await conn.call("GET", f"/walls/{self.wid}"))["latest"], time.monotonic()

    async def rate(self, seconds: float) -> float:
        """Frames per second the wall got over ``seconds``."""
        async with Connection(self.url) as conn:
            first = (await conn.call("GET", f"/walls/{self.wid}"))["latest"]
            t0 = time.monotonic()
            await asyncio.sleep(seconds)
            last = (await conn.call("GET", f"/walls/{self.wid}"))["latest"]
        return (last - first) / (time.monotonic() - t0)


@asynccontextmanager
async def _wall_running(s: Server, wall: dict, rate: float = 0.0, scene: str = "powerplant",
                        barrier: bool = False):
    """A wall of streaming node processes and a driver process posting at ``rate`` (0: flat
    out; with ``barrier``, each frame once every node has drawn the one before, so the rate
    is the nodes') for as long as the block runs."""
    tmp = tempfile.TemporaryDirectory()
    async with Driver(s.url, TOKEN) as d:
        info = await d.create_wall(scene, wall)
    creds = Path(tmp.name) / "credentials.json"
    creds.write_text(json.dumps(info["credentials"]))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    nodes = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "wallcull_clients.sim", "--server", s.url, "--wall", info["id"],
        "--credentials", str(creds), "--quiet", "--no-full-size", cwd=str(ROOT), env=env,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)
    await nodes.stdout.readline()  # {"ready": ...}
    async with Driver(s.url, TOKEN) as d:
        await d.wait_clients(info["id"], info["tiles"], 60)
    driver = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "wallcull_clients.driver", "--server", s.url, "--wall-id",
        info["id"], "--token", info["credentials"]["driver"], "--rate", str(rate), "--frames",
        "100000", *(["--barrier", "--barrier-timeout", "1"] if barrier else []), cwd=str(ROOT),
        env=env, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
    try:
        await asyncio.sleep(6.0)  # every node has its meshes, the frame rate has settled
        if driver.returncode is not None:
            raise RuntimeError(f"the driver failed: {(await driver.stderr.read()).decode()}")
        yield _Running(s.url, info["id"], info["tiles"], info["credentials"])
    finally:
        for p in (driver, nodes):
            if p.returncode is None:
                p.terminate()
                await p.wait()
        tmp.cleanup()


async def loop(updates_mb: float = 1.0, nodes: int = 100_000) -> dict:
    """How long the event loop stalls on a 1 MiB body of empty updates, and on describing a
    scene of ``nodes`` nodes (``GET /scenes/{name}?nodes=true``), seen by a probe."""
    wall = {"cols": 2, "rows": 1, "tile_size": [0.6, 0.34], "distance": 2.0}
    async with server() as s:
        async with Driver(s.url, TOKEN) as d:
            info = await d.create_wall("fatehpur", wall)
            frame = (await d.frames("fatehpur", wall, "orbit", 1))[0]
        k, data = 0, b""
        while True:  # the most empty updates that fit the body limit
            more = json.dumps({"frame": frame, "updates": {f"n{i}": {} for i in range(
                k + 5000)}}, separators=(",", ":")).encode()
            if len(more) > updates_mb * MiB:
                break
            k, data = k + 5000, more
        async with Probe(s.url) as idle:
            await asyncio.sleep(1.0)
        async with Connection(s.url, TOKEN, timeout=300) as conn, Probe(s.url) as p1:
            r1 = await conn.request("POST", f"/walls/{info['id']}/frames", data,
                                    "application/json", auth=True)
        async with Connection(s.url, TOKEN, timeout=600) as conn:
            up = await conn.request("POST", "/scenes?name=many", many_nodes(nodes),
                                    "model/gltf-binary", auth=True)
            await conn.request("GET", "/scenes/many.glb")
            async with Probe(s.url) as p2:
                t2 = time.perf_counter()
                r2 = await conn.request("GET", "/scenes/many.glb?nodes=true")
                t2 = time.perf_counter() - t2
    return {"scenario": "loop", "idle_worst_ms": idle.worst_ms(),
            "updates": {"bytes": len(data), "entries": k, "status": r1.status,
                        "worst_ms": p1.worst_ms()},
            "nodes": {"nodes": nodes, "upload_status": up.status, "status": r2.status,
                      "bytes": len(r2.body), "worst_ms": p2.worst_ms(), "ms": 1e3 * t2}}


async def restart(wall: str = "examples/wall-8x8.json", rate: float = 30.0,
                  seconds: float = 12.0, kill_at: float = 5.0, scene: str = "powerplant",
                  mode: str = "ws") -> dict:
    """A wall of nodes (streaming, or pulling with ``mode="pull"``) and a driver walking the
    scene; the server is killed (SIGKILL) once the driver has posted ``kill_at`` seconds'
    worth of frames, and started again on the same port and state folder. Reports the wall id before and after, how long after the restarted server
    answered its health check every node had a frame again, and whether any node ever saw a
    frame number go backwards."""
    spec = _wall_spec(wall)
    frames = int(rate * seconds)
    state = tempfile.TemporaryDirectory(prefix="wallcull-state-")
    tmp = tempfile.TemporaryDirectory()
    out = Path(tmp.name)
    s = Server(TOKEN, state=state.name)
    await s.start()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    procs = []
    try:
        async with Driver(s.url, TOKEN) as d:
            info = await d.create_wall(scene, spec)
        (out / "credentials.json").write_text(json.dumps(info["credentials"]))
        nodes = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "wallcull_clients.sim", "--server", s.url, "--wall", info["id"],
            "--credentials", str(out / "credentials.json"), "--until-frame", str(frames - 1),
            "--idle-timeout", "20", "--out", str(out / "nodes.json"), "--quiet",
            "--no-full-size", "--mode", mode, cwd=str(ROOT), env=env,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        procs.append(nodes)
        await nodes.stdout.readline()
        if mode == "ws":
            async with Driver(s.url, TOKEN) as d:
                await d.wait_clients(info["id"], info["tiles"], 60)
        driver = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "wallcull_clients.driver", "--server", s.url, "--wall-id",
            info["id"], "--token", info["credentials"]["driver"], "--rate", str(rate),
            "--frames", str(frames), "--out", str(out / "driver.json"), cwd=str(ROOT), env=env,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        procs.append(driver)
        # killed mid-run: once the driver has posted ``kill_at`` seconds' worth of frames
        # (however long a busy machine takes to get there), never before its first
        kill_frame = max(1, int(rate * kill_at))
        async with Connection(s.url) as conn:
            while (await conn.call("GET", f"/walls/{info['id']}"))["latest"] < kill_frame:
                if driver.returncode is not None:
                    raise RuntimeError(f"the driver exited early: "
                                       f"{(await driver.stderr.read()).decode()[-500:]}")
                await asyncio.sleep(0.05)
        killed = time.time()
        s.proc.send_signal(signal.SIGKILL)
        await s.proc.wait()
        s2 = Server(TOKEN, port=s.port, state=state.name)
        await s2.start()
        ready = time.time()
        async with Driver(s2.url, TOKEN) as d:
            after = await d.wall_info(info["id"])
        _, drv_err = await asyncio.wait_for(driver.communicate(), seconds * 10 + 120)
        _, node_err = await asyncio.wait_for(nodes.communicate(), 120)
        await s2.stop()
    finally:
        for p in procs:
            if p.returncode is None:
                p.terminate()
                await p.wait()
        await s.stop()
    tiles = json.loads((out / "nodes.json").read_text())["tiles"] \
        if (out / "nodes.json").exists() else []
    drv = json.loads((out / "driver.json").read_text()) if (out / "driver.json").exists() else {}
    tmp.cleanup()
    state.cleanup()
    resumed, backwards, before = [], 0, []
    for t in tiles:
        f, r = np.asarray(t["frame"]), np.asarray(t["recv"])
        backwards += int((np.diff(f) <= 0).sum())
        before.append(int(f[r < killed].max()) if (r < killed).any() else -1)
        later = r[(r > killed) & (f > before[-1])]
        resumed.append(float(later.min() - ready) if len(later) else float("inf"))
    return {"scenario": "restart", "mode": mode, "tiles": len(tiles), "wall_before": info["id"],
            "wall_after": after["id"], "restart_s": ready - killed,
            "resume_after_ready_s": {"max": max(resumed, default=None),
                                     "median": float(np.median(resumed)) if resumed else None},
            "frames_backwards": backwards, "last_frame_before_kill": max(before, default=None),
            "reconnects": sum(t["connects"] - 1 for t in tiles),
            "node_errors": sum(len(t["errors"]) for t in tiles),
            "nodes_exit": nodes.returncode, "driver_exit": driver.returncode,
            "driver_retries": drv.get("summary", {}).get("retries"),
            "driver_frames": drv.get("summary", {}).get("frames"),
            "driver_stderr": drv_err.decode(errors="replace")[-500:],
            "nodes_stderr": node_err.decode(errors="replace")[-500:]}


# --------------------------------------------------------------------------- issue 20: an attack
# beside a running wall, measured

#: The legitimate wall every attack runs beside: 16 streaming nodes, frames at 30 a second, each
#: posted once every node has drawn the one before (the swap barrier), so its frame rate is the
#: nodes'.
BESIDE, BESIDE_RATE = "examples/wall-4x4.json", 30.0


async def measured(name: str, attack, token: str | None = TOKEN, args=(), seconds: float = 5.0,
                   fresh_polls: bool = False, prefix=()) -> dict:
    """Run ``attack(server, running_wall)`` beside a legitimate wall, against a server of its
    own, with health polled every 50 ms: the attack's own report, plus the wall's frame rate
    before and during it (kept: during / before), the server's memory growth, the health
    polls' worst latency and failures, and the responses 500 the server counted."""
    async with server(token, args, prefix=prefix) as s, \
            _wall_running(s, _wall_spec(BESIDE), BESIDE_RATE, barrier=True) as run:
        first = await run.latest()
        await asyncio.sleep(seconds)
        settled = await run.latest()
        before = (settled[0] - first[0]) / (settled[1] - first[1])
        async with RSS(s.proc.pid) as rss, Probe(s.url, fresh=fresh_polls) as probe:
            t0 = time.monotonic()
            result = await attack(s, run)
            left = seconds - (time.monotonic() - t0)
            if left > 0:  # a short attack: measure the frame rate over at least ``seconds``
                await asyncio.sleep(left)
            end = await run.latest()
        during = (end[0] - settled[0]) / (end[1] - settled[1])
        async with Connection(s.url) as conn:
            text = (await conn.request("GET", "/metrics")).body.decode()
        errors_500 = sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
                         if line.startswith('wallcull_errors_total{status="500"}'))
    return {"scenario": name, **result, "frames_per_s_before": before,
            "frames_per_s_during": during, "kept": during / before if before else None,
            "responses_500": int(errors_500), **probe.report(), **rss.report()}


async def _stream_answer(url: str, path: str, payload, timeout: float = 120.0):
    """Send one message on a new stream; the answer that names an error (packets pushed
    meanwhile are skipped), or how the stream ended, and the time it took."""
    from websockets.asyncio.client import connect

    t = time.perf_counter()
    async with connect("ws" + url[4:] + path, max_size=None, open_timeout=30,
                       compression=None) as ws:
        await ws.send(payload)
        deadline = time.monotonic() + timeout
        while True:
            try:
                answer = await asyncio.wait_for(ws.recv(), max(0.0, deadline - time.monotonic()))
            except Exception as exc:  # noqa: BLE001 - how it ended is the answer
                answer = type(exc).__name__
                break
            if (b"error" if isinstance(answer, bytes) else "error") in answer:
                break
    text = answer if isinstance(answer, str) else answer[:200].decode("latin-1")
    return {"answer": text[:160], "seconds": time.perf_counter() - t}


async def messages(count: int = 50_000, seconds: float = 5.0) -> dict:
    """A 100,000-deep JSON array and msgpack array on a node stream and on the frame stream,
    then ``count`` small messages as fast as one socket takes them on a node stream."""
    async def attack(s, run):
        from websockets.asyncio.client import connect

        node = run.credentials["nodes"][0]["token"]
        driver = run.credentials["driver"]
        out = {}
        for what, path, payload in (
                ("node_json", f"/walls/{run.wid}/nodes/stream?format=json&token={node}",
                 "[" * 100_000),
                ("node_msgpack", f"/walls/{run.wid}/nodes/stream?token={node}",
                 b"\x91" * 100_000 + b"\xc0"),
                ("frames_json", f"/walls/{run.wid}/frames/stream?format=json&token={driver}",
                 "[" * 100_000),
                ("frames_msgpack", f"/walls/{run.wid}/frames/stream?token={driver}",
                 b"\x91" * 100_000 + b"\xc0")):
            out[f"deep_{what}"] = await _stream_answer(s.url, path, payload)
        t = time.perf_counter()
        async with connect("ws" + s.url[4:] + f"/walls/{run.wid}/tiles/0/stream?token={node}",
                           compression=None, max_queue=None) as ws:
            for _ in range(count):
                await ws.send(b"\x81\xa3ack\x00")  # {"ack": 0}, msgpack
        out["flood"] = {"messages": count, "seconds": time.perf_counter() - t}
        return out

    return await measured("messages", attack, seconds=seconds)


async def headers(connections: int = 1100, nofile: int = 1024, hold: float = 12.0,
                  seconds: float = 5.0) -> dict:
    """``connections`` connections that each send half a request header and wait, against a
    server limited to ``nofile`` file descriptors (``prlimit``); health is polled on a new
    connection each time, as a load balancer does."""
    async def attack(s, run):
        from urllib.parse import urlsplit

        parts = urlsplit(s.url)
        writers, failed = [], 0
        for _ in range(connections):
            try:
                reader, writer = await asyncio.open_connection(parts.hostname, parts.port)
                writer.write(b"GET /health HTTP/1.1\r\nhost: x\r\nx-slow: ")
                writers.append((reader, writer))
            except OSError:
                failed += 1
        await asyncio.sleep(hold)
        closed = sum(r.at_eof() or w.is_closing() for r, w in writers)
        for _, w in writers:
            w.close()
        return {"connections": connections, "nofile": nofile, "open_failed": failed,
                "closed_by_server": closed}

    return await measured("headers", attack, fresh_polls=True,
                          prefix=["prlimit", f"--nofile={nofile}:{nofile}", "--"],
                          args=["--limit", "header_seconds=5"], seconds=seconds)


async def prepare(kinds=("obb-hull", "obb-min"), seconds: float = 5.0, args=()) -> dict:
    """Walls asking for bounds that take long to fit (minimum-volume boxes of every leaf):
    fitted in a child process, the server keeps serving."""
    async def attack(s, run):
        out = {}
        async with Connection(s.url, TOKEN, timeout=600) as conn:
            for kind in kinds:
                t = time.perf_counter()
                r = await conn.request("POST", "/walls", json.dumps(
                    {"wall": _wall_spec("examples/wall-8x8.json"), "scene": "powerplant",
                     "bounds": kind}).encode(), "application/json", auth=True,
                    accept="application/json")
                out[kind] = {"status": r.status, "seconds": time.perf_counter() - t}
                if r.status == 201:
                    await conn.request("DELETE", f"/walls/{r.data()['id']}", auth=True)
        return out

    return await measured("prepare", attack, seconds=seconds, args=args)


#: Degenerate stereo: eyes a hair apart, or at the smallest doubles.
IPDS = (1e-300, 5e-324, 1e-15, 1e-9)


async def stereo(seconds: float = 5.0) -> dict:
    """Frames whose stereo is degenerate (``IPDS``) on a grid and on a CAVE, each timed."""
    async def attack(s, run):
        out = {}
        async with Driver(s.url, TOKEN) as d:
            for wall in ("examples/wall-8x8.json", "examples/wall-cave.json"):
                spec = _wall_spec(wall)
                info = await d.create_wall("fatehpur", spec)
                frame = (await d.frames("fatehpur", spec, "orbit", 1))[0]
                times = []
                async with Connection(s.url, TOKEN, timeout=300) as conn:
                    for ipd in IPDS:
                        body = {"frame": {**frame, "stereo": {"ipd": ipd}}}
                        t = time.perf_counter()
                        r = await conn.request("POST", f"/walls/{info['id']}/frames",
                                               json.dumps(body).encode(), "application/json",
                                               auth=True)
                        times.append({"ipd": ipd, "status": r.status,
                                      "seconds": time.perf_counter() - t})
                    await conn.request("DELETE", f"/walls/{info['id']}", auth=True)
                out[Path(wall).stem] = times
        return out

    return await measured("stereo", attack, seconds=seconds)


HUGE = {"cols": 256, "rows": 256, "tile_size": [0.1, 0.1], "distance": 2.0}


async def huge(consoles: int = 32, hold: float = 12.0, seconds: float = 5.0) -> dict:
    """A 256 x 256 wall: made, a frame posted, every tile's packets asked for in one answer,
    then ``consoles`` console streams opened without a credential and read for ``seconds``."""
    async def attack(s, run):
        from websockets.asyncio.client import connect

        out = {}
        async with Connection(s.url, TOKEN, timeout=600) as conn:
            t, rss = time.perf_counter(), s.ps.memory_info().rss
            r = await conn.request("POST", "/walls", json.dumps(
                {"wall": HUGE, "scene": "powerplant", "history": 4}).encode(),
                "application/json", auth=True, accept="application/json")
            out["create"] = {"status": r.status, "seconds": time.perf_counter() - t,
                             "rss_mb": (s.ps.memory_info().rss - rss) / MiB}
            wid = r.data()["id"]
            async with Driver(s.url, TOKEN) as d:
                frame = (await d.frames("powerplant", HUGE, "orbit", 1))[0]
            for packets in (False, True):
                t = time.perf_counter()
                r = await conn.request("POST", f"/walls/{wid}/frames", json.dumps(
                    {"frame": frame, "packets": packets}).encode(), "application/json",
                    auth=True)
                out["frame_packets" if packets else "frame"] = {
                    "status": r.status, "seconds": time.perf_counter() - t,
                    "rss_mb": (s.ps.memory_info().rss - rss) / MiB,
                    "detail": r.detail()[:120] if r.status >= 400 else None}
        received = [0] * consoles
        stop = asyncio.Event()

        async def console(k):
            async with connect("ws" + s.url[4:] + f"/walls/{wid}/console/stream",
                               max_size=None, compression=None) as ws:
                while not stop.is_set():
                    try:
                        received[k] += len(await asyncio.wait_for(ws.recv(), 0.5))
                    except asyncio.TimeoutError:
                        pass

        tasks = [asyncio.ensure_future(console(k)) for k in range(consoles)]
        await asyncio.sleep(hold)
        stop.set()
        results = await asyncio.gather(*tasks, return_exceptions=True)
        out["consoles"] = {"opened": consoles, "seconds": hold,
                           "failed": sum(isinstance(r, Exception) for r in results),
                           "mb_received": sum(received) / MiB,
                           "rss_mb": (s.ps.memory_info().rss - rss) / MiB}
        async with Connection(s.url, TOKEN) as conn:
            await conn.request("DELETE", f"/walls/{wid}", auth=True)
        return out

    return await measured("huge", attack, seconds=seconds)


async def answers(seconds: float = 5.0) -> dict:
    """The wrong answers issue 20 found, each asked again: statuses only."""
    async def attack(s, run):
        out = {}
        node = run.credentials["nodes"][0]["token"]
        async with Connection(s.url, node) as conn:
            r = await conn.request("GET", f"/walls/{run.wid}/tiles/%C2%B2/packets/latest",
                                   auth=True)
            out["unicode_tile_http"] = r.status
        out["unicode_tile_ws"] = await open_stream(s.url, f"/walls/{run.wid}/tiles/%C2%B2/stream",
                                                   node)
        out["disagreeing_credentials_ws"] = await open_stream(
            s.url, f"/walls/{run.wid}/tiles/0/stream", node,
            headers={"Authorization": "Bearer garbage"})
        glb_ = many_nodes(200)

        async def upload(k, replace=False):
            async with Connection(s.url, TOKEN, timeout=300) as conn:
                r = await conn.request("POST", f"/scenes?name=same{'&replace=true' * replace}",
                                       glb_, "model/gltf-binary", auth=True)
                return r.status

        out["same_name_uploads"] = sorted(await asyncio.gather(*(upload(k) for k in range(6))))
        async with Driver(s.url, TOKEN) as d:
            used = await d.create_wall("same.glb", _wall_spec("examples/wall-4x4.json"))
        out["replace_a_scene_a_wall_uses"] = await upload(0, replace=True)
        async with Connection(s.url, TOKEN) as conn:
            await conn.request("DELETE", f"/walls/{used['id']}", auth=True)
        out["replace_once_no_wall_uses_it"] = await upload(0, replace=True)
        return out

    return await measured("answers", attack, seconds=seconds)


async def state() -> dict:
    """Start a server on a state database that is not one, on a truncated one and on one
    with a wall spec that is not JSON: each start must fail in one line naming the file,
    leaving it as it was."""
    import sqlite3
    import subprocess

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        async with server(state=tmp) as s:
            async with Driver(s.url, TOKEN) as d:
                await d.create_wall("fatehpur", _wall_spec("examples/wall-4x4.json"))
        db = Path(tmp) / "walls.sqlite3"
        good = db.read_bytes()
        for case in ("not_a_database", "truncated", "spec_not_json"):
            if case == "not_a_database":
                db.write_bytes(b"\0" * 4096)
            elif case == "truncated":
                db.write_bytes(good[:len(good) // 2 + 100])
            else:
                db.write_bytes(good)
                con = sqlite3.connect(db)
                con.execute("UPDATE walls SET spec = '{\"wall\":'")
                con.commit()
                con.close()
            before = db.read_bytes()
            proc = subprocess.run([sys.executable, "-m", "wallcull.cli", "serve", "--state", tmp,
                                   "--port", "1"], capture_output=True, text=True, timeout=120)
            out[case] = {"exit": proc.returncode, "lines": proc.stderr.count("\n"),
                         "names_the_file": str(db) in proc.stderr,
                         "file_unchanged": db.read_bytes() == before,
                         "message": proc.stderr.strip()[:300]}
    return {"scenario": "state", **out}


async def handshakes(count: int = 3000, at_once: int = 4) -> dict:
    """Full TLS handshakes (a connection opened, its handshake made, closed; no session
    reused), ``at_once`` at a time, against ``wallcull serve --tls-cert`` with an RSA-2048 and
    with an ECDSA P-256 certificate (``trustme``, the tests' authority), and plain connections
    beside them: the server's CPU time per connection, all of it its event loop's."""
    import ssl

    import psutil
    import trustme

    from .loadtest import free_port

    async def connect(port, context):
        reader, writer = await asyncio.open_connection("127.0.0.1", port, ssl=context)
        return reader, writer

    out = {"connections": count, "at_once": at_once}
    with tempfile.TemporaryDirectory(prefix="wallcull-tls-") as folder:
        for name, key in (("plain", None), ("rsa2048", trustme.KeyType.RSA),
                          ("ecdsa_p256", trustme.KeyType.ECDSA)):
            args, context = [], None
            if key is not None:
                ca = trustme.CA(key_type=key)
                pem = Path(folder, f"{name}.pem")
                ca.issue_cert("127.0.0.1", key_type=key).private_key_and_cert_chain_pem \
                    .write_to_path(str(pem))
                args, context = ["--tls-cert", str(pem)], ssl.create_default_context()
                ca.configure_trust(context)
            port = free_port()
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "wallcull.cli", "serve", "--host", "127.0.0.1", "--port",
                str(port), "--state", "none", "--log-level", "warning", *args,
                stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
            try:
                while True:  # the kernels loaded: their CPU is not the handshakes'
                    try:
                        reader, writer = await connect(port, context)
                        writer.write(b"GET /health HTTP/1.1\r\nhost: x\r\n"
                                     b"connection: close\r\n\r\n")
                        ready = b'"ready"' in await reader.read()
                        writer.close()
                        if ready:
                            break
                    except OSError:
                        pass
                    await asyncio.sleep(0.2)
                server = psutil.Process(proc.pid)
                left = count

                async def one_after_another():
                    nonlocal left
                    while left > 0:
                        left -= 1
                        _, writer = await connect(port, context)
                        writer.close()

                cpu = sum(server.cpu_times()[:2])
                t = time.perf_counter()
                await asyncio.gather(*(one_after_another() for _ in range(at_once)))
                seconds = time.perf_counter() - t
                cpu = sum(server.cpu_times()[:2]) - cpu
            finally:
                proc.terminate()
                await proc.wait()
            out[name] = {"per_second": count / seconds, "server_cpu_ms_each": 1e3 * cpu / count}
    return out


SCENARIOS = {"glb-bomb": glb_bomb, "uploads": uploads, "streams": streams, "acks": acks,
             "loop": loop, "restart": restart, "messages": messages, "headers": headers,
             "prepare": prepare, "stereo": stereo, "huge": huge, "answers": answers,
             "state": state, "handshakes": handshakes}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m wallcull_clients.hostile",
                                description="Hostile clients against a real server, measured.")
    p.add_argument("scenario", choices=[*SCENARIOS, "all"])
    p.add_argument("--json", action="store_true", help="one JSON object per scenario")
    args = p.parse_args(argv)
    names = list(SCENARIOS) if args.scenario == "all" else [args.scenario]
    for name in names:
        result = asyncio.run(SCENARIOS[name]())
        if name == "streams":  # and a server with no token: idle nodes instead of refusals
            result = {"with_token": result, "without_token": asyncio.run(streams(token=None))}
        print(json.dumps(result) if args.json else json.dumps(result, indent=1), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
