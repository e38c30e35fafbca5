"""``wallcull loadtest``: a real server, a wall of simulated render nodes and a driver, measured.

Walkthrough mode (the default)::

    wallcull loadtest --scene powerplant --wall examples/wall-8x8.json --rate 60 --duration 10 \\
        --mode ws --clients-procs 1 [--barrier] [--path orbit|fly] --out DIR [--json]

starts ``wallcull serve`` on a free loopback port, creates the wall, starts the render nodes
(``python -m wallcull_clients.sim``, the tiles split over ``--clients-procs`` processes, each node an
asyncio task) and, once every node is connected, the driver (``python -m wallcull_clients.driver``), which
posts ``rate x duration`` frames of the camera path. It then writes ``report.json`` and
``report.md`` to ``--out``:

* frames/s the driver achieved;
* frame-to-all-tiles latency per frame: the latest arrival over all tiles minus the server's post
  time (``packet["time"]``), over the frames every tile received (p50/p99/max); also from the
  driver's send time, and the *display* latency (until every tile holds that frame or a newer
  one, which also covers frames conflated away);
* per-tile latency (every packet, pooled), and per tile in ``tiles``;
* bytes per frame as received (deltas) against the same packets as full lists (each node
  re-encodes every delta it gets as the full packet the server would have sent), in total and for
  the leaf-id lists alone, and the bytes of the fitted frusta that every packet carries;
* CPU seconds and percent of the server, the node processes and the driver (psutil), over the
  span of the driver's posts (from its ``{"driving": ...}`` line to its ``{"driven": ...}``
  line; its start-up and imports left out);
* frames dropped (tile-frames a node never saw: conflation on the stream, or history loss;
  every measured frame of a tile whose node process left no records), errors, barrier
  timeouts, frames the driver skipped behind its schedule, and the server's own counters
  (``/metrics``).

A node process that fails fails the run: the report is written, saying which process and
tiles, and ``wallcull loadtest`` exits with status 1. Values not measured (the server's CPU
with ``--server``) are null in the JSON. A wall made on a ``--server`` is deleted at the end.

The first ``--warmup`` seconds of frames (nodes fetching their meshes) are left out of the
latency and bytes statistics; everything else counts.

Request mode::

    wallcull loadtest --requests 20000 [--concurrency 64]

creates a wall, posts one frame, then a separate process (``python -m wallcull_clients.loadtest``) sends
``GET /walls/{wid}/tiles/{t}/packets/latest`` over ``--concurrency`` keep-alive connections
(tiles spread over the connections; no tile has acknowledged anything, so each answer is a full
list) and reports requests/s: the 200 answers a second, the others apart; the server's CPU
is sampled as the generator opens and closes its timed window. The load generator is the minimal asyncio HTTP/1.1 client of
:mod:`wallcull_clients.rawhttp` (on uvloop when installed): ``httpx`` tops out near the rates measured.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import secrets
import socket
import sys
import tempfile
import time
from collections import Counter
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

import numpy as np

from .broker import Broker

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_WALL = "examples/wall-8x8.json"


# --------------------------------------------------------------------------- processes


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def machine_busy() -> float:
    """CPU seconds the whole machine has spent busy (all cores, all processes)."""
    import psutil

    t = psutil.cpu_times()
    return sum(t) - t.idle - getattr(t, "iowait", 0.0)


def cpu_seconds(proc) -> float:
    """User + system CPU seconds of a psutil process (0 once it is gone)."""
    import psutil

    try:
        t = proc.cpu_times()
        return t.user + t.system
    except psutil.Error:
        return float("nan")


class Server:
    """``wallcull serve`` in a subprocess on a free loopback port, with a state folder of its
    own (a temporary one unless ``state`` is given) and ``args`` added to its command line."""

    def __init__(self, token: str | None = None, port: int | None = None,
                 log_level: str = "warning", state: str | None = None, args=(), prefix=()):
        self.token = token
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_level = log_level
        self._state = tempfile.TemporaryDirectory(prefix="wallcull-state-") if state is None \
            else None
        self.state = state or self._state.name
        self.args = list(args)
        self.prefix = list(prefix)  # a command the server runs under (``prlimit ... --``)
        self.proc = None
        self.log = tempfile.TemporaryFile()

    async def start(self, timeout: float = 120.0) -> "Server":
        import psutil

        from wallcull_clients.rawhttp import Connection

        cmd = [*self.prefix, sys.executable, "-m", "wallcull.cli", "serve", "--host", "127.0.0.1",
               "--port", str(self.port), "--log-level", self.log_level, "--state", self.state,
               *self.args]
        if self.token:
            cmd += ["--token", self.token]
        self.proc = await asyncio.create_subprocess_exec(*cmd, stdout=self.log, stderr=self.log)
        self.ps = psutil.Process(self.proc.pid)
        deadline = time.monotonic() + timeout
        while True:
            if self.proc.returncode is not None:
                raise RuntimeError(f"the server exited with status {self.proc.returncode}: "
                                   f"{self.output()[-2000:]}")
            try:
                async with Connection(self.url, timeout=5) as conn:
                    await conn.call("GET", "/health")
                return self
            except (ConnectionError, OSError, asyncio.TimeoutError):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the server did not answer /health in {timeout:g} s"
                                       ) from None
                await asyncio.sleep(0.2)

    def output(self) -> str:
        self.log.seek(0)
        return self.log.read().decode(errors="replace")

    async def stop(self) -> None:
        if self.proc is not None and self.proc.returncode is None:
            self.proc.terminate()
            try:
                await asyncio.wait_for(self.proc.wait(), 10)
            except asyncio.TimeoutError:
                self.proc.kill()
                await self.proc.wait()
        if self._state is not None:
            self._state.cleanup()

    async def __aenter__(self):
        return await self.start()

    async def __aexit__(self, *exc):
        await self.stop()


@contextmanager
def running_server(token: str | None = None, timeout: float = 120.0, env: dict | None = None,
                   args=(), ca: str | None = None, port: int | None = None,
                   state: str | None = None):
    """``wallcull serve`` on a free loopback port (or ``port``), with a temporary state folder
    (or ``state``, kept: a server started again there finds its walls), for the ``with``
    block (no event loop needed, for tests); yields its base URL (``https://`` when ``args``
    hold ``--tls-cert``, ``ca`` then the file of the authority that signed it)."""
    import ssl
    import subprocess
    import urllib.request

    port = port or free_port()
    temporary = None if state else tempfile.TemporaryDirectory(prefix="wallcull-state-")
    cmd = [sys.executable, "-m", "wallcull.cli", "serve", "--host", "127.0.0.1", "--port",
           str(port), "--log-level", "warning", "--state", state or temporary.name, *args] + \
        (["--token", token] if token else [])
    log = tempfile.TemporaryFile()
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                            env={**os.environ, **(env or {})})
    url = f"{'https' if '--tls-cert' in args else 'http'}://127.0.0.1:{port}"
    context = ssl.create_default_context(cafile=ca) if ca else None
    try:
        deadline = time.monotonic() + timeout
        while True:
            if proc.poll() is not None:
                log.seek(0)
                raise RuntimeError(f"the server exited ({proc.returncode}): "
                                   f"{log.read().decode(errors='replace')[-2000:]}")
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2, context=context):
                    break
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the server did not answer /health in {timeout:g} s"
                                       ) from None
                time.sleep(0.1)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()
        if temporary is not None:
            temporary.cleanup()


async def metrics(url: str) -> dict:
    """The server's counters: packets and bytes by kind and transport, stage times, errors."""
    from prometheus_client.parser import text_string_to_metric_families

    from wallcull_clients.rawhttp import Connection

    async with Connection(url) as conn:
        r = await conn.request("GET", "/metrics", accept="text/plain")
    out: dict = {"packets": {}, "packet_bytes": {}, "stage_seconds": {}, "errors": {}}
    for family in text_string_to_metric_families(r.body.decode()):
        for s in family.samples:
            if s.name == "wallcull_frames_total":
                out["frames"] = s.value
            elif s.name == "wallcull_packets_total":
                out["packets"][f"{s.labels['kind']}/{s.labels['transport']}"] = s.value
            elif s.name == "wallcull_packet_bytes_total":
                out["packet_bytes"][f"{s.labels['kind']}/{s.labels['transport']}"] = s.value
            elif s.name in ("wallcull_stage_seconds_sum", "wallcull_stage_seconds_count"):
                entry = out["stage_seconds"].setdefault(s.labels["stage"], {})
                entry["sum" if s.name.endswith("sum") else "count"] = s.value
            elif s.name == "wallcull_errors_total":
                out["errors"][s.labels["status"]] = s.value
    for entry in out["stage_seconds"].values():
        if entry.get("count"):
            entry["mean_ms"] = entry["sum"] / entry["count"] * 1e3
    return out


def split(tiles: int, parts: int) -> list[tuple[int, int]]:
    """``parts`` contiguous, near-equal ranges ``(first, last)`` covering ``range(tiles)``."""
    parts = max(1, min(parts, tiles))
    bounds = np.linspace(0, tiles, parts + 1).round().astype(int)
    return [(int(a), int(b) - 1) for a, b in zip(bounds[:-1], bounds[1:])]


def last_line(err: bytes | str) -> str:
    """The last non-empty line of a process's stderr (its one-line reason), or ""."""
    text = err.decode(errors="replace") if isinstance(err, bytes) else err
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else ""


def started(exc: RuntimeError) -> str:
    """A server or broker that would not start, in one line: what happened and the last line
    it said (``the server exited with status 2: cannot reach the NATS broker ...``)."""
    what, _, said = str(exc).partition(": ")
    why = last_line(said).removeprefix("wallcull: error: ")
    return f"{what}: {why}" if why else what


def exit_text(status: int) -> str:
    """``exited 2``, or ``was killed by SIGKILL``."""
    import signal

    if status < 0:
        try:
            return f"was killed by {signal.Signals(-status).name}"
        except ValueError:
            pass
    return f"exited {status}"


def finite(obj):
    """``obj`` with every NaN or infinite float replaced by None (null in JSON: not measured),
    so that ``json.dumps(..., allow_nan=False)`` takes it."""
    if isinstance(obj, float):
        return obj if obj == obj and abs(obj) != float("inf") else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, np.generic):
        return finite(obj.item())
    return obj


def to_json(report: dict, **kwargs) -> str:
    return json.dumps(finite(report), allow_nan=False, **kwargs)


async def _reach(url: str, progress: bool) -> None:
    """Wait for the server's kernels (:func:`kernels_loaded`), or refuse in one line a server
    that cannot be reached."""
    from wallcull.errors import InputError

    try:
        await kernels_loaded(url, progress)
    except (ConnectionError, OSError, asyncio.TimeoutError) as exc:
        raise InputError(f"cannot reach the server at {url}: {exc}") from None
    except ValueError as exc:
        raise InputError(f"--server {url}: {exc}") from None


def _refused(exc, url: str, given_token: bool) -> Exception:
    """The one-line error for a server's refusal of the wall this run makes."""
    from wallcull.errors import InputError

    if exc.status in (401, 403):
        if given_token:
            return InputError(f"the server at {url} refused the token (HTTP {exc.status}: "
                              f"{exc.detail}): give the server's operator token with --token")
        return InputError(f"the server at {url} wants a token (HTTP {exc.status}): give it "
                          "with --token (or $WALLCULL_TOKEN)")
    return InputError(f"the server refused the wall: HTTP {exc.status}: {exc.detail}")


async def delete_wall(url: str, token: str | None, wid: str) -> None:
    """Delete the wall this run made on a server it did not start (best effort: a server that
    is gone is told on stderr, in one line)."""
    from wallcull_clients.rawhttp import Connection, HTTPError

    try:
        async with Connection(url, token, timeout=10) as conn:
            await conn.call("DELETE", f"/walls/{wid}", auth=True, expect=(200, 202, 204, 404))
    except (ConnectionError, OSError, asyncio.TimeoutError, HTTPError) as exc:
        print(f"wallcull: warning: could not delete wall {wid} on {url}: {exc}",
              file=sys.stderr)


async def _read_json_line(stream, timeout: float, what: str, proc) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise RuntimeError(f"{what} did not report in {timeout:g} s")
        try:
            line = await asyncio.wait_for(stream.readline(), left)
        except asyncio.TimeoutError:
            raise RuntimeError(f"{what} did not report in {timeout:g} s") from None
        if not line:
            from wallcull.errors import InputError

            err = last_line(await proc.stderr.read())
            raise InputError(f"{what} exited before reporting: {err}")
        line = line.strip()
        if line.startswith(b"{"):
            return json.loads(line)


# --------------------------------------------------------------------------- statistics


def pct(values, q) -> float | None:
    values = np.asarray(values, dtype=float)
    return float(np.percentile(values, q)) if len(values) else None


def dist(values_ms) -> dict:
    v = np.asarray(values_ms, dtype=float)
    if not len(v):
        return {"n": 0}
    return {"n": int(len(v)), "p50": pct(v, 50), "p99": pct(v, 99), "max": float(v.max()),
            "mean": float(v.mean()), "min": float(v.min())}


def no_records(tile: int) -> dict:
    """The records of a tile whose node process left none (it died): nothing received, so
    every measured frame counts as dropped on it."""
    return {"tile": tile, "frame": [], "recv": [], "posted": [], "full": [], "bytes": [],
            "errors": [], "base_misses": 0, "mesh_fetches": 0, "mesh_not_modified": 0,
            "mesh_bytes": 0, "missing": True}


def analyze(driver: dict, tiles: list[dict], warmup_frames: int = 0,
            count: int | None = None) -> dict:
    """The walkthrough statistics from the driver's log and every node's records. ``count``:
    the wall's tiles; a tile with no records (its node process died) then counts as dropped
    on every measured frame, so "all tiles" is every tile of the wall."""
    if count is not None:
        held = {t["tile"] for t in tiles}
        tiles = sorted([*tiles, *(no_records(t) for t in range(count) if t not in held)],
                       key=lambda t: t["tile"])
    log = driver["log"]
    frames = np.asarray(log["frame"], dtype=np.int64)
    send = np.asarray(log["send"], dtype=float)
    measured = frames[warmup_frames:]
    out: dict = {"frames_posted": int(len(frames)), "frames_measured": int(len(measured))}
    if len(send) > 1:
        out["frames_per_s"] = (len(send) - 1) / (send[-1] - send[0])
        out["driver_seconds"] = float(send[-1] - send[0])
    # server post time of each frame, from whichever node saw it
    posted = {}
    for t in tiles:
        posted.update(zip(t["frame"], t["posted"]))
    server_time = np.array([posted.get(int(n), np.nan) for n in measured])
    send_of = dict(zip(frames.tolist(), send.tolist()))
    sent = np.array([send_of[int(n)] for n in measured])
    # arrivals: exact (tile got frame n) and display (first frame >= n)
    exact = np.full((len(tiles), len(measured)), np.nan)
    shown = np.full((len(tiles), len(measured)), np.nan)
    per_tile = []
    in_window = set(measured.tolist())
    for i, t in enumerate(tiles):
        f = np.asarray(t["frame"], dtype=np.int64)
        r = np.asarray(t["recv"], dtype=float)
        order = np.argsort(f, kind="stable")
        f, r = f[order], r[order]
        idx = np.searchsorted(f, measured)
        ok = idx < len(f)
        shown[i, ok] = r[idx[ok]]
        hit = ok.copy()
        hit[ok] = f[idx[ok]] == measured[ok]
        exact[i, hit] = r[idx[hit]]
        mask = np.isin(np.asarray(t["frame"]), measured)
        lat = (np.asarray(t["recv"])[mask] - np.asarray(t["posted"])[mask]) * 1e3
        got = len(set(t["frame"]) & in_window)
        per_tile.append({"tile": t["tile"], "packets": len(t["frame"]),
                         "full": int(sum(t["full"])), "dropped": len(measured) - got,
                         "p50_ms": pct(lat, 50), "p99_ms": pct(lat, 99),
                         "bytes": int(sum(t["bytes"])), "cache": t.get("cache", {}),
                         "mesh_fetches": t["mesh_fetches"], "base_misses": t["base_misses"],
                         "errors": len(t["errors"]), **({"missing": True} if t.get("missing")
                                                        else {})})
    complete = ~np.isnan(exact).any(axis=0) & ~np.isnan(server_time)
    all_tiles = (exact.max(axis=0)[complete] - server_time[complete]) * 1e3
    from_send = (exact.max(axis=0)[complete] - sent[complete]) * 1e3
    disp_ok = ~np.isnan(shown).any(axis=0) & ~np.isnan(server_time)
    display = (shown.max(axis=0)[disp_ok] - server_time[disp_ok]) * 1e3
    pooled = np.concatenate([
        (np.asarray(t["recv"]) - np.asarray(t["posted"]))[np.isin(t["frame"], measured)]
        for t in tiles]) * 1e3 if tiles else np.zeros(0)
    out["latency_ms"] = {"all_tiles": dist(all_tiles), "all_tiles_from_send": dist(from_send),
                         "display": dist(display), "per_tile": dist(pooled)}
    out["dropped"] = {"tile_frames": int(np.isnan(exact).sum()),
                      "frames_not_on_every_tile": int((~complete).sum())}
    # bytes, over the measured window; sizes as full lists where a node worked them out (a
    # render node on the frames it samples, NaN on the others: sim.FULL_SIZE_EVERY), each
    # against what the same packets weighed
    sums, sampled_frames, received = Counter(), set(), set()
    for t in tiles:
        frame = np.asarray(t["frame"], dtype=np.int64)
        mask = np.isin(frame, measured)
        full = np.asarray(t["full"], dtype=bool)
        size = np.asarray(t["bytes"], dtype=float)
        sums["bytes"] += size[mask].sum()
        received.update(frame[mask].tolist())
        if len(t.get("full_bytes", ())) == len(mask) and len(mask):
            sampled = mask & ~np.isnan(np.asarray(t["full_bytes"], dtype=float))
            sampled_frames.update(frame[sampled].tolist())
            sums["sampled_bytes"] += size[sampled].sum()
            for key in ("full_bytes", "list_bytes", "full_list_bytes", "fit_bytes"):
                if len(t.get(key, ())) == len(mask):
                    sums[key] += np.asarray(t[key], dtype=float)[sampled].sum()
        if t.get("mode") == "node":  # a node's messages, once each (on its first tile)
            if "messages" in t:
                got = np.isin(np.asarray(t["messages"]["frame"], dtype=np.int64), measured)
                sums["packets"] += int(got.sum())
                sums["full_packets"] += int((got & np.asarray(t["messages"]["full"],
                                                              dtype=bool)).sum())
            continue
        sums["packets"] += int(mask.sum())
        sums["full_packets"] += int((mask & full).sum())
    # per frame received: a frame no tile got weighs nothing, and must not thin the mean
    n, m = max(len(received), 1), max(len(sampled_frames), 1)
    b = {"packets": sums["packets"], "full_packets": sums["full_packets"],
         "delta_packets": sums["packets"] - sums["full_packets"],
         # what "packets" counts: a tile's packets, or a node's messages (once, not a tile)
         "counted": ("node messages" if any(t.get("mode") == "node" for t in tiles)
                     else "tile packets"),
         "per_frame": sums["bytes"] / n, "received_frames": len(received),
         "sampled_frames": len(sampled_frames),
         "sampled_per_frame": sums["sampled_bytes"] / m,
         "per_frame_if_full": sums["full_bytes"] / m,
         "lists_per_frame": sums["list_bytes"] / m,
         "lists_per_frame_if_full": sums["full_list_bytes"] / m,
         "fits_per_frame": sums["fit_bytes"] / m}
    b["reduction"] = (b["per_frame_if_full"] / b["sampled_per_frame"]
                      if b["sampled_per_frame"] else None)
    b["lists_reduction"] = (b["lists_per_frame_if_full"] / b["lists_per_frame"]
                            if b["lists_per_frame"] else None)
    out["bytes"] = b
    if log.get("barrier_done"):
        bd = np.asarray(log["barrier_done"], dtype=float)
        out["barrier"] = {"latency_ms": dist((bd - send)[warmup_frames:] * 1e3),
                          "incomplete": int(len(log["barrier_complete"])
                                            - sum(log["barrier_complete"]))}
    out["errors"] = {"node_errors": sum(len(t["errors"]) for t in tiles),
                     "base_misses": sum(t["base_misses"] for t in tiles),
                     "examples": [e for t in tiles for e in t["errors"]][:5],
                     "tiles_missing": sum(bool(t.get("missing")) for t in tiles),
                     "tiles_missing_ids": [t["tile"] for t in tiles if t.get("missing")]}
    out["tiles"] = per_tile
    out["nodes"] = {"mesh_fetches": sum(t["mesh_fetches"] for t in tiles),
                    "mesh_not_modified": sum(t["mesh_not_modified"] for t in tiles),
                    "mesh_bytes": sum(t["mesh_bytes"] for t in tiles),
                    "cache_misses": sum(t.get("cache", {}).get("misses", 0) for t in tiles),
                    "cache_evictions": sum(t.get("cache", {}).get("evictions", 0)
                                           for t in tiles),
                    "every_tile_got_packets": all(len(t["frame"]) > 0 for t in tiles)}
    return out


# --------------------------------------------------------------------------- walkthrough


def _wall_spec(text: str) -> dict:
    from wallcull.documents import read_json

    path = Path(text)
    if not text.strip().startswith("{") and not path.exists() and (ROOT / text).exists():
        text = str(ROOT / text)  # examples/... from anywhere
    return read_json(text, "--wall")


async def walkthrough(scene: str = "powerplant", wall: dict | str = DEFAULT_WALL,
                      rate: float = 60.0, duration: float = 10.0, mode: str = "ws",
                      clients_procs: int = 1, barrier: bool = False, path: str = "orbit",
                      path_frames: int | None = None, warmup: float = 0.5,
                      cache_bytes: str = "256M", history: int = 64, method: str = "adaptive",
                      server: str | None = None, token: str | None = None,
                      progress: bool = True, workdir: str | None = None,
                      render: bool = False, draw_time: float = 0.0,
                      settings: dict | None = None, shadow_fit: str = "refined",
                      tiles_per_node: int = 1, transport: str = "ws",
                      nats: str | None = None, prefetch: bool = False,
                      barrier_timeout: float = 1.0, retry_for: float = 60.0,
                      stereo: float | None = None) -> dict:
    """Run one walkthrough load test (see the module docstring) and return its report.
    ``transport`` "nats": the nodes take their messages from a NATS broker (``nats``, or one
    started here), the server publishing there. ``prefetch``: every node fetches the scene's
    meshes before the first frame, as a render PC loads its scene before it joins a wall.
    ``retry_for``: how long the driver and the nodes wait for a server that went away.
    ``stereo``: the driver posts stereo frames, the eyes this far apart (m).
    A wall made on a ``server`` this run did not start is deleted when the run ends, however
    it ends."""
    import psutil

    from wallcull.errors import InputError
    from wallcull_clients.driver import PATH_FRAMES, Driver
    from wallcull_clients.rawhttp import Connection, HTTPError
    from wallcull.wall import Wall

    host = machine()  # before we load it
    wall = _wall_spec(wall) if isinstance(wall, str) else wall
    frames = max(2, int(round(rate * duration))) if rate > 0 else max(2, int(duration * 60))
    given_token = token is not None
    token = token or secrets.token_hex(8)
    tmp = tempfile.TemporaryDirectory(dir=workdir)
    broker = Broker() if transport == "nats" and nats is None else None
    if broker is not None:
        try:
            nats = broker.start().url
        except RuntimeError as exc:
            broker.stop()
            raise InputError(started(exc)) from None
    own = Server(token, args=["--nats", nats] if transport == "nats" else ()) \
        if server is None else None
    procs: list = []
    drv = wid = None
    url = server
    try:
        if own:
            try:
                await own.start()
            except RuntimeError as exc:
                raise InputError(started(exc)) from None
        url = own.url if own else server
        await _reach(url, progress)
        async with Driver(url, token, retry_for=retry_for) as d:
            count = Wall.from_dict(wall).tiles
            groups = [list(range(k, min(k + tiles_per_node, count)))
                      for k in range(0, count, tiles_per_node)]
            try:
                info = await d.create_wall(scene, wall, method, "obb", history, settings,
                                           shadow_fit, groups if tiles_per_node > 1 else None)
            except HTTPError as exc:
                if exc.status not in (401, 403, 404, 409, 422):
                    raise
                raise _refused(exc, url, given_token) from None
        wid, tiles = info["id"], info["tiles"]
        # least privilege, as a lab would run it: each node its own credential, the driver
        # the wall's driver credential; the operator's token only created the wall
        credentials = f"{tmp.name}/credentials.json"
        Path(credentials).write_text(json.dumps(info["credentials"]))
        ranges = [(groups[a][0], groups[b][-1]) for a, b in split(len(groups), clients_procs)]
        for k, (a, b) in enumerate(ranges):
            cmd = [sys.executable, "-m", "wallcull_clients.sim", "--server", url, "--wall", wid,
                   "--tiles", f"{a}-{b}", "--mode", mode, "--credentials", credentials,
                   "--until-frame", str(frames - 1), "--idle-timeout", "5",
                   "--cache-bytes", str(cache_bytes), "--out", f"{tmp.name}/nodes-{k}.json",
                   "--quiet", "--draw-time", str(draw_time), "--reconnect-for", f"{retry_for:g}",
                   "--tiles-per-node", str(tiles_per_node)] + (["--render"] if render else []) \
                + (["--nats", nats] if transport == "nats" else []) \
                + (["--prefetch"] if prefetch else [])
            procs.append(await asyncio.create_subprocess_exec(
                *cmd, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
                cwd=str(ROOT)))
        for k, p in enumerate(procs):
            await _read_json_line(p.stdout, 120, f"render node process {k}", p)
        async with Driver(url, token, retry_for=retry_for) as d:
            if mode == "ws" and transport == "ws":  # NATS nodes said they subscribed
                got = await d.wait_clients(wid, len(groups), 30)
                if got < len(groups):
                    raise InputError(f"only {got} of {len(groups)} nodes subscribed in 30 s")
        server_ps = own.ps if own else None
        broker_ps = psutil.Process(broker.proc.pid) if broker is not None else None
        client_ps = [psutil.Process(p.pid) for p in procs]
        cmd = [sys.executable, "-m", "wallcull_clients.driver", "--server", url, "--wall-id", wid,
               "--rate", str(rate), "--frames", str(frames), "--path", path,
               "--path-frames", str(path_frames or PATH_FRAMES), "--retry-for", f"{retry_for:g}",
               "--token", info["credentials"]["driver"], "--out", f"{tmp.name}/driver.json"]
        if barrier:
            cmd += ["--barrier", "--barrier-timeout", str(barrier_timeout)]
        if stereo is not None:
            cmd += ["--stereo", repr(stereo)]
        def sample() -> dict:
            return {"server": cpu_seconds(server_ps) if server_ps else float("nan"),
                    "broker": cpu_seconds(broker_ps) if broker_ps else 0.0,
                    "clients": [cpu_seconds(p) for p in client_ps],  # nan for those gone
                    "machine": machine_busy(), "loadtest": cpu_seconds(psutil.Process()),
                    "t": time.monotonic()}

        before = sample()
        drv = await asyncio.create_subprocess_exec(*cmd, stdout=asyncio.subprocess.PIPE,
                                                   stderr=asyncio.subprocess.PIPE,
                                                   cwd=str(ROOT))
        # the window is the span of the posts: from the driver's "driving" line (its start-up,
        # imports and path building left out) to its "driven" line
        span = asyncio.ensure_future(_driving_span(drv.stdout, sample))
        await _watch(url, wid, frames, drv, progress)
        cpu0, cpu1, drv_cpu = await span
        cpu0, cpu1 = cpu0 or before, cpu1 or sample()  # (a driver that never drove: its run)
        wall_s = max(cpu1["t"] - cpu0["t"], 1e-9)
        clients_at_end = cpu1["clients"]
        cpu0["clients"] = sum(cpu0["clients"])
        _, drv_err = await drv.communicate()
        if drv.returncode != 0:
            raise InputError(f"the driver {exit_text(drv.returncode)}: {last_line(drv_err)}")
        driver = json.loads(Path(f"{tmp.name}/driver.json").read_text())
        last = driver["log"]["frame"][-1] if driver["log"]["frame"] else -1
        if last < frames - 1:  # the driver skipped late frames: the nodes wait for no more
            try:
                async with Connection(url, timeout=15) as conn:
                    await conn.call("GET", f"/walls/{wid}/barrier/{last}?timeout=5")
            except (ConnectionError, OSError, asyncio.TimeoutError, HTTPError):
                pass
            for p in procs:
                if p.returncode is None:
                    p.terminate()  # a node told to stop writes its records and exits 0
        node_errors = []
        for k, p in enumerate(procs):
            try:
                _, err = await asyncio.wait_for(p.communicate(), 30)
            except asyncio.TimeoutError:
                p.terminate()
                _, err = await p.communicate()
            if p.returncode not in (0, 1):
                why = last_line(err)
                node_errors.append(f"node process {k} (tiles {ranges[k][0]}-{ranges[k][1]}) "
                                   f"{exit_text(p.returncode)}{': ' + why if why else ''}")
        # the driver's CPU over the span, as it reported it; the node processes report their
        # own CPU time when they finish (they may exit before anyone could sample them)
        drv_cpu = drv_cpu if drv_cpu is not None else driver["cpu_seconds"]
        nodes, cpu1["clients"] = [], 0.0
        for k in range(len(procs)):
            f = Path(f"{tmp.name}/nodes-{k}.json")
            if f.exists():
                part = json.loads(f.read_text())
                nodes += part["tiles"]
                alive = clients_at_end[k]
                cpu1["clients"] += part["cpu_seconds"] if alive != alive else alive
        server_metrics = await metrics(url)
    finally:
        if drv is not None and drv.returncode is None:
            drv.terminate()  # a driver told to stop ends its run, retrying or not
        for p in [*procs, *([drv] if drv is not None else [])]:
            if p.returncode is None:
                p.terminate()
                try:
                    await asyncio.wait_for(p.wait(), 10)
                except asyncio.TimeoutError:
                    p.kill()
                    await p.wait()
        if wid is not None and own is None:  # the user's server keeps no wall of ours
            await delete_wall(url, token, wid)
        if own:
            await own.stop()
        if broker is not None:
            broker.stop()
        tmp.cleanup()
    # (--rate 0, as fast as it goes: the warm-up's frames at the rate the driver achieved)
    per_s = rate if rate > 0 else driver["summary"].get("rate") or 0.0
    warm = min(int(round(warmup * per_s)), max(frames - 2, 0))
    report = {"kind": "walkthrough",
              "config": {"scene": scene, "wall": wall, "tiles": tiles, "rate": rate,
                         "duration": duration, "frames": frames, "mode": mode,
                         "clients_procs": len(procs), "barrier": barrier, "path": path,
                         "settings": settings, "shadow_fit": shadow_fit,
                         "path_frames": path_frames or PATH_FRAMES, "warmup_frames": warm,
                         "cache_bytes": cache_bytes, "method": method, "render": render,
                         "draw_time": draw_time, "tiles_per_node": tiles_per_node,
                         "nodes": len(groups), "transport": transport, "prefetch": prefetch,
                         "stereo": stereo},
              "machine": host}
    report.update(analyze(driver, nodes, warm, count=tiles))
    report["driver"] = driver["summary"]
    report["cpu"] = {name: {"seconds": cpu1[name] - cpu0[name],
                            "percent": 100 * (cpu1[name] - cpu0[name]) / wall_s}
                     for name in cpu0 if name != "t"}
    report["cpu"]["driver"] = {"seconds": drv_cpu, "percent": 100 * drv_cpu / wall_s}
    # everything else the machine did meanwhile (with --server, the server among it: its CPU
    # is not sampled)
    ours = sum(report["cpu"][k]["seconds"] for k in ("server", "broker", "clients", "driver",
                                                     "loadtest")
               if report["cpu"][k]["seconds"] == report["cpu"][k]["seconds"])
    others = report["cpu"]["machine"]["seconds"] - ours
    report["cpu"]["others"] = {"seconds": others, "percent": 100 * others / wall_s,
                               "server_included": own is None}
    report["cpu"]["window_s"] = wall_s
    # the server's CPU per tile-frame posted meanwhile: culling, fitting, encoding, sending
    report["cpu"]["server_us_per_tile_frame"] = \
        1e6 * report["cpu"]["server"]["seconds"] / max(report["frames_posted"] * tiles, 1)
    report["server_metrics"] = server_metrics
    report["errors"]["process_errors"] = node_errors
    report["targets"] = walkthrough_targets(report)
    return finite(report)


#: The issues' targets: 60 frames/s sustained, frame-to-all-tiles p99 under 50 ms, deltas at
#: least 10x smaller than full lists and whole packets (or node messages) 5x, the server's
#: CPU at most 25 us per tile-frame, 2,000 single-packet requests/s.
TARGETS = {"p99_all_tiles_ms": 50.0, "bytes_reduction_lists": 10.0,
           "bytes_reduction_packets": 5.0, "server_us_per_tile_frame": 25.0,
           "requests_per_s": 2000.0}


def walkthrough_targets(report: dict) -> dict:
    """The targets, met or not, for this run's configuration (the rate is the one asked).
    ``met`` is None for a target this run could not measure (the server's CPU, with
    ``--server``)."""
    rate, achieved = report["config"]["rate"], report.get("frames_per_s") or 0.0
    us = finite(report["cpu"]["server_us_per_tile_frame"])
    p99 = report["latency_ms"]["all_tiles"].get("p99")
    b = report["bytes"]
    errors = report["errors"]
    whole = report["dropped"]["tile_frames"] == 0 and not errors.get("tiles_missing") \
        and not errors.get("process_errors")
    return {
        "rate": {"target": rate, "value": achieved, "met": bool(achieved >= 0.99 * rate)},
        # met only with nothing dropped: a frame a tile never got has no latency to count
        "p99_all_tiles_ms": {"target": TARGETS["p99_all_tiles_ms"], "value": p99,
                             "met": bool(p99 is not None and p99 < TARGETS["p99_all_tiles_ms"]
                                         and whole),
                             "and": "no tile-frame dropped, every node process to its end"},
        "bytes_reduction_lists": {"target": TARGETS["bytes_reduction_lists"],
                                  "value": b["lists_reduction"],
                                  "met": bool((b["lists_reduction"] or 0)
                                              >= TARGETS["bytes_reduction_lists"])},
        "bytes_reduction_packets": {"target": TARGETS["bytes_reduction_packets"],
                                    "value": b["reduction"],
                                    "met": bool((b["reduction"] or 0)
                                                >= TARGETS["bytes_reduction_packets"])},
        "server_us_per_tile_frame": {"target": TARGETS["server_us_per_tile_frame"],
                                     "value": us,
                                     "met": None if us is None else
                                     bool(us <= TARGETS["server_us_per_tile_frame"])},
    }


#: How long a load test waits for a server to compile its kernels: minutes on a fresh install
#: of a 2-core machine, once (numba then loads them from its cache in seconds).
KERNELS_TIMEOUT = 1800.0


async def kernels_loaded(url: str, show: bool = False, timeout: float = KERNELS_TIMEOUT) -> float:
    """Wait until the server at ``url`` has its compiled kernels (``GET /health``: ``kernels``
    no longer ``loading``), with a spinner; the seconds waited. A server still compiling
    computes its first frames in seconds instead of milliseconds: measured then, every node
    would see its stream idle and the report would be of the compiler."""
    from rich.console import Console
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from wallcull_clients.rawhttp import Connection

    t0 = time.monotonic()
    async with Connection(url) as conn:
        if (await conn.call("GET", "/health")).get("kernels") != "loading":
            return 0.0
        with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                      console=Console(stderr=True), disable=not show, transient=True) as bar:
            bar.add_task("the server is compiling its kernels (once after an install, "
                         "a few minutes)", total=None)
            while (await conn.call("GET", "/health")).get("kernels") == "loading":
                if time.monotonic() - t0 > timeout:
                    raise RuntimeError(f"the server at {url} was still compiling its kernels "
                                       f"after {timeout:g} s")
                await asyncio.sleep(0.1)
    return time.monotonic() - t0


async def _driving_span(stdout, sample) -> tuple:
    """Read the driver's JSON lines to its end; ``(sample() at "driving", sample() at
    "driven", the driver's CPU seconds between the two)``, None for a line that never came."""
    start = end = cpu = None
    async for line in stdout:
        try:
            said = json.loads(line)
        except ValueError:
            continue
        if not isinstance(said, dict):
            continue
        if said.get("driving"):
            start, cpu = sample(), said["cpu_seconds"]
        elif said.get("driven") and start is not None:
            end, cpu = sample(), said["cpu_seconds"] - cpu
    return start, end, (cpu if end is not None else None)


async def _watch(url, wid, frames, drv, show: bool) -> None:
    """Wait for the driver to finish, with a progress bar of the wall's latest frame (asked
    of the server twice a second; not asked at all without the bar, so that a measured run's
    server serves the wall alone)."""
    if not show:
        await drv.wait()
        return
    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                               TimeElapsedColumn)

    from wallcull_clients.rawhttp import Connection

    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[rate]}"), TimeElapsedColumn())
    console = Console(stderr=True)
    with Progress(*columns, console=console, disable=not show, transient=True) as bar:
        task = bar.add_task("frames", total=frames, rate="")
        t0 = time.monotonic()
        async with Connection(url) as conn:
            while drv.returncode is None:
                try:
                    latest = (await conn.call("GET", f"/walls/{wid}"))["latest"] + 1
                except Exception:  # noqa: BLE001 - the bar is best effort
                    latest = 0
                elapsed = time.monotonic() - t0
                bar.update(task, completed=latest,
                           rate=f"{latest / elapsed:5.1f} frames/s" if elapsed > 0 else "")
                try:
                    await asyncio.wait_for(drv.wait(), 0.5)
                except asyncio.TimeoutError:
                    pass


def machine() -> dict:
    import platform

    import psutil

    return {"python": platform.python_version(), "cpu": platform.processor() or
            platform.machine(), "cores": os.cpu_count(),
            "cores_physical": psutil.cpu_count(logical=False),
            "load_average_1m": os.getloadavg()[0]}


# --------------------------------------------------------------------------- request throughput


async def hammer(server: str, targets: list[str], total: int, concurrency: int,
                 accept: str = "application/msgpack", duration: float | None = None,
                 token: str | None = None, mark: Callable[[str], None] | None = None) -> dict:
    """``total`` GETs (or as many as fit in ``duration`` seconds) over ``concurrency``
    keep-alive connections, connection ``i`` asking for ``targets[i % len(targets)]``
    (with ``token`` as a bearer token: packets need a credential). ``requests_per_s`` counts
    the 200 answers alone; the others are ``not_ok`` (and by status in ``status``).
    ``mark("start")`` and ``mark("end")`` are called as the timed window opens and closes."""
    from wallcull_clients.rawhttp import Connection

    issued = 0
    statuses: Counter = Counter()
    latencies: list[float] = []
    received = 0
    stop_at = None

    async def worker(i: int):
        nonlocal issued, received
        conn = Connection(server, token, timeout=30)
        target = targets[i % len(targets)]
        try:
            while issued < total and (stop_at is None or time.perf_counter() < stop_at):
                issued += 1
                t = time.perf_counter()
                r = await conn.request("GET", target, accept=accept, auth=True)
                latencies.append(time.perf_counter() - t)
                statuses[r.status] += 1
                received += len(r.body)
        finally:
            await conn.close()

    if mark:
        mark("start")
    t0, cpu0 = time.perf_counter(), time.process_time()
    if duration:
        stop_at = t0 + duration
    await asyncio.gather(*(worker(i) for i in range(concurrency)))
    elapsed = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    if mark:
        mark("end")
    lat = np.asarray(latencies) * 1e3
    done = len(latencies)
    ok = statuses.get(200, 0)
    return {"requests": done, "ok": ok, "not_ok": done - ok, "seconds": elapsed,
            "requests_per_s": ok / elapsed, "generator_cpu_seconds": cpu,
            "concurrency": concurrency, "status": {str(k): v for k, v in statuses.items()},
            "bytes_per_response": received / done if done else 0,
            "latency_ms": {"p50": pct(lat, 50), "p99": pct(lat, 99), "max": float(lat.max())
                           if len(lat) else None}}


def requests_targets(result: dict) -> dict:
    """The request target: 200 answers a second, and no answer but 200."""
    return {"requests_per_s": {
        "target": TARGETS["requests_per_s"], "value": result["requests_per_s"],
        "met": bool(result["requests_per_s"] >= TARGETS["requests_per_s"]
                    and result["not_ok"] == 0),
        "and": "every answer 200"}}


async def requests_test(requests: int = 20000, concurrency: int = 64,
                        scene: str = "powerplant", wall: dict | str = DEFAULT_WALL,
                        server: str | None = None, token: str | None = None,
                        progress: bool = True) -> dict:
    """Single-packet request throughput of one server (see the module docstring). The
    server's CPU is sampled as the generator opens and closes its timed window. A wall made
    on a ``server`` this run did not start is deleted when the run ends, however it ends."""
    from wallcull.errors import InputError
    from wallcull_clients.driver import Driver
    from wallcull_clients.rawhttp import HTTPError

    wall = _wall_spec(wall) if isinstance(wall, str) else wall
    given_token = token is not None
    token = token or secrets.token_hex(8)
    own = Server(token) if server is None else None
    url, wid, gen = server, None, None
    try:
        if own:
            try:
                await own.start()
            except RuntimeError as exc:
                raise InputError(started(exc)) from None
        url = own.url if own else server
        await _reach(url, progress)
        async with Driver(url, token) as d:
            try:
                info = await d.create_wall(scene, wall)
            except HTTPError as exc:
                if exc.status not in (401, 403, 404, 409, 422):
                    raise
                raise _refused(exc, url, given_token) from None
            wid = info["id"]
            frames = await d.frames(scene, info["wall"], "orbit", 1)
            await d.post(wid, frames[0])
        cmd = [sys.executable, "-m", "wallcull_clients.loadtest", "--server", url, "--wall-id",
               wid, "--tiles", str(info["tiles"]), "--requests", str(requests),
               "--concurrency", str(concurrency)]
        gen = await asyncio.create_subprocess_exec(*cmd, stdout=asyncio.subprocess.PIPE,
                                                   stderr=asyncio.subprocess.PIPE,
                                                   cwd=str(ROOT),
                                                   env={**os.environ, "WALLCULL_TOKEN": token})
        from rich.console import Console
        from rich.progress import Progress

        marks, result = {}, None
        with Progress(console=Console(stderr=True), disable=not progress,
                      transient=True) as bar:
            bar.add_task(f"{requests} requests, {concurrency} connections", total=None)
            while True:
                line = await gen.stdout.readline()
                if not line:
                    break
                data = json.loads(line)
                if "mark" in data:  # the generator's timed window opens or closes
                    marks[data["mark"]] = (time.monotonic(),
                                           cpu_seconds(own.ps) if own else float("nan"))
                else:
                    result = data
        err = await gen.stderr.read()
        await gen.wait()
        if gen.returncode != 0 or result is None or len(marks) != 2:
            raise InputError(f"the load generator {exit_text(gen.returncode)}: "
                             f"{last_line(err)}")
        gen_cpu = result.pop("generator_cpu_seconds")
        window = marks["end"][0] - marks["start"][0]
        server_s = marks["end"][1] - marks["start"][1]
        server_metrics = await metrics(url)
    finally:
        if gen is not None and gen.returncode is None:
            gen.kill()
            await gen.wait()
        if wid is not None and own is None:  # the user's server keeps no wall of ours
            await delete_wall(url, token, wid)
        if own:
            await own.stop()
    return finite({
        "kind": "requests",
        "config": {"scene": scene, "wall": wall, "tiles": info["tiles"],
                   "requests": requests, "concurrency": concurrency,
                   "target": "/walls/{wid}/tiles/{t}/packets/latest (full packets)"},
        "machine": machine(), **result,
        "targets": requests_targets(result),
        "cpu": {"server": {"seconds": server_s, "percent": 100 * server_s / window},
                "generator": {"seconds": gen_cpu, "percent": 100 * gen_cpu / result["seconds"]},
                "window_s": window},
        "server_metrics": server_metrics})


def _hammer_main(argv=None) -> int:
    """``python -m wallcull_clients.loadtest``: the request-mode load generator. It prints
    ``{"mark": "start"}`` and ``{"mark": "end"}`` as its timed window opens and closes (the
    caller samples the server's CPU then), then the result, each a JSON line."""
    p = argparse.ArgumentParser(prog="python -m wallcull_clients.loadtest")
    p.add_argument("--server", required=True)
    p.add_argument("--wall-id", required=True)
    p.add_argument("--tiles", type=int, default=1)
    p.add_argument("--requests", type=int, default=10000)
    p.add_argument("--concurrency", type=int, default=64)
    p.add_argument("--duration", type=float)
    p.add_argument("--token", default=os.environ.get("WALLCULL_TOKEN") or None,
                   help="a token that may read the packets (default: $WALLCULL_TOKEN)")
    args = p.parse_args(argv)
    try:
        import uvloop
    except ImportError:
        uvloop = None

    def mark(kind: str) -> None:
        print(json.dumps({"mark": kind}), flush=True)

    targets = [f"/walls/{args.wall_id}/tiles/{t}/packets/latest" for t in range(args.tiles)]
    coro = hammer(args.server, targets, args.requests, args.concurrency,
                  duration=args.duration, token=args.token, mark=mark)
    result = uvloop.run(coro) if uvloop else asyncio.run(coro)
    print(to_json(result), flush=True)
    return 0


# --------------------------------------------------------------------------- reports


def _f(v, fmt="{:.1f}") -> str:
    return "-" if v is None or v != v else fmt.format(v)


def _pc(v) -> str:
    """A CPU percentage, or "not measured"."""
    return "not measured" if v is None or v != v else f"{v:.0f}%"


def tiles_text(tiles) -> str:
    from wallcull.validate import tiles_text as text

    return text(sorted(tiles))


def markdown(report: dict) -> str:
    c = report["config"]
    m = report["machine"]
    lines = [f"# wallcull load test ({report['kind']})", ""]
    if report["kind"] == "requests":
        lines += [f"{c['requests']} requests of `{c['target']}` over {c['concurrency']} "
                  f"keep-alive connections; scene {c['scene']}, {c['tiles']} tiles; "
                  f"{m['cores']} cores.", "",
                  "| metric | value |", "|---|---|",
                  f"| requests/s (200 answers) | {report['requests_per_s']:.0f} |",
                  f"| answers not 200 | {report['not_ok']} of {report['requests']} |",
                  f"| latency p50 / p99 ms | {_f(report['latency_ms']['p50'], '{:.2f}')} / "
                  f"{_f(report['latency_ms']['p99'], '{:.2f}')} |",
                  f"| statuses | {report['status']} |",
                  f"| bytes per response | {report['bytes_per_response']:.0f} |",
                  f"| server CPU | {_pc(report['cpu']['server']['percent'])} |",
                  f"| generator CPU | {_pc(report['cpu']['generator']['percent'])} |", ""]
        return "\n".join(lines + _targets_md(report))
    lat, b = report["latency_ms"], report["bytes"]
    w = c["wall"]
    shape = f"{w['cols']} x {w['rows']} wall" if "cols" in w else f"wall of {c['tiles']} screens"
    lines += [f"Scene {c['scene']}, {shape} ({c['nodes']} nodes of {c['tiles_per_node']} "
              f"tile(s) in {c['clients_procs']} process(es), mode {c['mode']}, over "
              f"{c['transport']}), "
              f"{c['frames']} frames of the "
              f"{c['path']} path (a loop every {c['path_frames']} frames"
              f"{', stereo, ipd %g m' % c['stereo'] if c.get('stereo') else ''}) at "
              f"{c['rate']:g} frames/s{', swap barrier every frame' if c['barrier'] else ''}; "
              f"first "
              f"{c['warmup_frames']} frames left out of latency and bytes; {m['cores']} cores.",
              "", "| metric | value |", "|---|---|",
              f"| frames/s achieved | {_f(report.get('frames_per_s'))} |",
              f"| frame-to-all-tiles latency p50 / p99 / max ms | "
              f"{_f(lat['all_tiles'].get('p50'), '{:.2f}')} / "
              f"{_f(lat['all_tiles'].get('p99'), '{:.2f}')} / "
              f"{_f(lat['all_tiles'].get('max'), '{:.2f}')} |",
              f"| same, from the driver's send, p50 / p99 ms | "
              f"{_f(lat['all_tiles_from_send'].get('p50'), '{:.2f}')} / "
              f"{_f(lat['all_tiles_from_send'].get('p99'), '{:.2f}')} |",
              f"| display latency (every tile at n or newer) p50 / p99 ms | "
              f"{_f(lat['display'].get('p50'), '{:.2f}')} / "
              f"{_f(lat['display'].get('p99'), '{:.2f}')} |",
              f"| per-tile latency p50 / p99 ms | {_f(lat['per_tile'].get('p50'), '{:.2f}')} / "
              f"{_f(lat['per_tile'].get('p99'), '{:.2f}')} |",
              f"| bytes/frame received (deltas, over the {b['received_frames']} frames some "
              f"tile received) | {b['per_frame']:.0f} |",
              f"| bytes/frame as full lists (on {b['sampled_frames']} frames sized so) | "
              f"{b['per_frame_if_full']:.0f} |",
              f"| reduction, whole packets (the same frames' deltas: "
              f"{b['sampled_per_frame']:.0f} bytes/frame) | {_f(b['reduction'])}x |",
              f"| leaf-id bytes/frame: deltas / full | {b['lists_per_frame']:.0f} / "
              f"{b['lists_per_frame_if_full']:.0f} ({_f(b['lists_reduction'])}x) |",
              f"| fitted-frusta bytes/frame (in every packet) | {b['fits_per_frame']:.0f} |",
              f"| {b.get('counted', 'packets')} full / delta | {b['full_packets']} / "
              f"{b['delta_packets']} |",
              f"| tile-frames dropped | {report['dropped']['tile_frames']} "
              f"({report['dropped']['frames_not_on_every_tile']} frames not on every tile) |",
              f"| frames the driver skipped (behind its schedule) | "
              f"{report.get('driver', {}).get('skipped', 0)} |"]
    if "barrier" in report:
        bl = report["barrier"]["latency_ms"]
        lines.append(f"| barrier latency p50 / p99 ms (incomplete) | {_f(bl.get('p50'), '{:.2f}')}"
                     f" / {_f(bl.get('p99'), '{:.2f}')} ({report['barrier']['incomplete']}) |")
    cpu, errors = report["cpu"], report["errors"]
    lines += [f"| CPU server / nodes / driver (% of one core) | {_pc(cpu['server']['percent'])} / "
              f"{_pc(cpu['clients']['percent'])} / {_pc(cpu['driver']['percent'])} |",
              f"| server CPU per tile-frame | "
              f"{_f(cpu['server_us_per_tile_frame'], '{:.1f} us')} |",
              *([f"| NATS broker CPU (% of one core) | {_pc(cpu['broker']['percent'])} |"]
                if c["transport"] == "nats" else []),
              f"| CPU of other processes on the machine meanwhile"
              f"{' (the server among them)' if cpu['others'].get('server_included') else ''} | "
              f"{_pc(cpu['others']['percent'])} |",
              f"| errors | {errors['node_errors']} node, "
              f"{errors['base_misses']} base misses, "
              f"{len(errors['process_errors'])} process |",
              f"| tiles with no records (dropped on every frame) | "
              f"{errors.get('tiles_missing', 0)}"
              f"{': ' + tiles_text(errors['tiles_missing_ids']) if errors.get('tiles_missing') else ''}"
              f" |", ""]
    if errors["process_errors"] or errors.get("tiles_missing"):
        lines += ["**The run failed.** " + " ".join(
            f"{e[0].upper()}{e[1:]}." for e in errors["process_errors"]) +
            (f" Tiles {tiles_text(errors['tiles_missing_ids'])} left no records: each counts "
             "as dropped on every measured frame." if errors.get("tiles_missing") else ""), ""]
    lines += [*_targets_md(report),
              "| tile | packets | full | dropped | p50 ms | p99 ms | mesh fetches | evictions |",
              "|---|---|---|---|---|---|---|---|"]
    for t in report["tiles"]:
        lines.append(f"| {t['tile']} | {t['packets']} | {t['full']} | {t['dropped']} | "
                     f"{_f(t['p50_ms'], '{:.2f}')} | {_f(t['p99_ms'], '{:.2f}')} | "
                     f"{t['mesh_fetches']} | {t['cache'].get('evictions', 0)} |")
    return "\n".join(lines) + "\n"


def _targets_md(report: dict) -> list[str]:
    lines = ["| target | wanted | measured | |", "|---|---|---|---|"]
    for name, t in report.get("targets", {}).items():
        value = _f(t["value"])
        wanted = f"{t['target']:g}" + (f", {t['and']}" if "and" in t else "")
        verdict = "not measured" if t["met"] is None else "met" if t["met"] else "**missed**"
        lines.append(f"| {name} | {wanted} | {value} | {verdict} |")
    return lines + [""]


def write(report: dict, out: str | None) -> None:
    if not out:
        return
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "report.json").write_text(to_json(report, indent=1))
    (folder / "report.md").write_text(markdown(report))


# --------------------------------------------------------------------------- command line


def register(sub) -> None:
    """Add ``wallcull loadtest`` to the CLI's subparsers."""
    from .driver import ipd

    q = sub.add_parser("loadtest", help="measure a real server with simulated render nodes")
    q.add_argument("--scene", default="powerplant")
    q.add_argument("--wall", default=DEFAULT_WALL, help="WALL.json, or the JSON inline")
    q.add_argument("--rate", type=float, default=60.0, help="frames per second")
    q.add_argument("--duration", type=float, default=10.0, help="seconds of frames")
    q.add_argument("--mode", choices=("ws", "pull"), default="ws")
    q.add_argument("--clients-procs", type=int, default=1, metavar="K",
                   help="render node processes (the tiles are split between them)")
    q.add_argument("--tiles-per-node", type=int, default=1, metavar="K",
                   help="each render node drives K consecutive tiles over one stream")
    q.add_argument("--transport", choices=("ws", "nats"), default="ws",
                   help="the nodes' messages over the server's WebSockets, or a NATS broker "
                        "(--nats URL, else a nats-server started for the run)")
    q.add_argument("--nats", metavar="URL", help="--transport nats: this broker")
    q.add_argument("--prefetch", action="store_true",
                   help="nodes fetch every mesh before the first frame (as a render PC loads "
                        "its scene), instead of as they come into view")
    q.add_argument("--barrier", action="store_true", help="the driver waits on the swap barrier")
    q.add_argument("--barrier-timeout", type=float, default=1.0, metavar="SECONDS",
                   help="how long the driver waits on the barrier before posting the next "
                        "frame anyway (at most 10)")
    q.add_argument("--path", choices=("orbit", "fly"), default="orbit")
    q.add_argument("--path-frames", type=int, help="frames per loop of the path (default 600)")
    q.add_argument("--stereo", type=ipd, metavar="IPD",
                   help="the driver posts stereo frames, the eyes this far apart (m, e.g. 0.064)")
    q.add_argument("--warmup", type=float, default=0.5,
                   help="seconds of first frames left out of latency and bytes")
    q.add_argument("--cache-bytes", default="256M", help="mesh cache budget per node")
    q.add_argument("--draw-time", type=float, default=0.0, metavar="SECONDS",
                   help="simulated drawing time per frame of every node (a slow GPU)")
    q.add_argument("--render", action="store_true",
                   help="the nodes draw with the headless OpenGL renderer (slow on a CPU)")
    q.add_argument("--history", type=int, default=64)
    q.add_argument("--settings", metavar="SETTINGS.json",
                   help="lights and mirrors for the wall instead of the scene's own")
    q.add_argument("--shadow-fit", choices=("sphere", "greedy", "refined"), default="refined",
                   help="shadow-frustum fitting effort")
    q.add_argument("--requests", type=int, metavar="N",
                   help="instead: N single-packet GETs from a separate process; requests/s")
    q.add_argument("--concurrency", type=int, default=64,
                   help="--requests: keep-alive connections")
    q.add_argument("--retry-for", type=float, default=60.0, metavar="SECONDS",
                   help="how long the driver and the nodes wait for a server that went away "
                        "before the run fails")
    q.add_argument("--server", help="use this running server instead of starting one (the "
                                    "wall the run makes there is deleted when it ends)")
    q.add_argument("--token", default=os.environ.get("WALLCULL_TOKEN") or None,
                   help="the running server's token (default: $WALLCULL_TOKEN)")
    q.add_argument("--out", help="folder for report.json and report.md")
    q.add_argument("--json", action="store_true", help="print the report as JSON")
    q.set_defaults(func=cmd_loadtest)


def cmd_loadtest(args) -> int:
    from wallcull.errors import InputError
    from wallcull.settings import read as read_settings

    if args.clients_procs < 1 or args.tiles_per_node < 1:
        raise InputError("--clients-procs and --tiles-per-node must be at least 1")
    if (args.tiles_per_node > 1 or args.transport == "nats") and args.mode != "ws":
        raise InputError("nodes of several tiles, and NATS, take node messages: --mode ws")
    if not 0 < args.duration < float("inf"):
        raise InputError(f"--duration must be a positive number of seconds, got "
                         f"{args.duration:g}")
    if not 0 <= args.rate < float("inf"):
        raise InputError(f"--rate must be 0 (as fast as it goes) or a positive number of "
                         f"frames a second, got {args.rate:g}")
    if args.nats and args.transport != "nats":
        raise InputError("--nats is the broker of --transport nats: give both, or neither")
    if args.transport == "nats" and args.server and not args.nats:
        raise InputError("--transport nats with --server needs the server's broker: --nats URL "
                         "(the one it was started with); a broker of our own would hear "
                         "nothing from it")
    if args.requests is None and not 0 <= args.warmup < args.duration:
        raise InputError(f"--warmup must be 0 or more and less than --duration "
                         f"({args.duration:g} s), got {args.warmup:g}")
    if not 0 < args.retry_for < float("inf"):
        raise InputError("--retry-for must be a positive number of seconds")
    if args.requests is not None and (args.requests < 1 or args.concurrency < 1):
        raise InputError("--requests and --concurrency must be at least 1")
    if not 0 < args.barrier_timeout <= 10:
        raise InputError(f"--barrier-timeout must be over 0 and at most 10 s, got "
                         f"{args.barrier_timeout:g}")
    wall = _wall_spec(args.wall)
    settings = None
    if args.settings:  # refused here, before a server starts, as the server would
        from wallcull.settings import parse as parse_settings

        settings = read_settings(args.settings)
        parse_settings(settings)
    progress = sys.stderr.isatty()
    if args.requests:
        report = asyncio.run(requests_test(args.requests, args.concurrency, args.scene, wall,
                                           args.server, args.token, progress))
    else:
        report = asyncio.run(walkthrough(
            args.scene, wall, args.rate, args.duration, args.mode, args.clients_procs,
            args.barrier, args.path, args.path_frames, args.warmup, args.cache_bytes,
            args.history, server=args.server, token=args.token, progress=progress,
            render=args.render, draw_time=args.draw_time,
            settings=settings, shadow_fit=args.shadow_fit, tiles_per_node=args.tiles_per_node,
            transport=args.transport, nats=args.nats, prefetch=args.prefetch,
            barrier_timeout=args.barrier_timeout, retry_for=args.retry_for,
            stereo=args.stereo))
    write(report, args.out)
    if args.json:
        print(to_json(report))
    else:
        from rich.console import Console
        from rich.markdown import Markdown

        text = markdown(report)
        if report["kind"] == "walkthrough":  # the per-tile table is in the file
            text = text.split("\n| tile |")[0]
        Console().print(Markdown(text))
    errors = report.get("errors", {})
    if report["kind"] == "walkthrough" and not errors.get("process_errors") \
            and not errors.get("tiles_missing") and not report["nodes"]["every_tile_got_packets"]:
        silent = sum(not t["packets"] for t in report["tiles"])
        print(f"wallcull: error: {silent} of {len(report['tiles'])} tiles got no packet: the "
              f"nodes heard nothing from the server (with --server and --transport nats, is "
              f"--nats the server's broker?)", file=sys.stderr)
        return 1
    if errors.get("process_errors") or errors.get("tiles_missing"):
        # measured, but not the whole wall: the report says what is missing, and so does this
        first = (errors["process_errors"] or ["a node process left no records"])[0]
        missing = errors.get("tiles_missing", 0)
        print(f"wallcull: error: {first}" + (f"; {missing} tiles left no records and count as "
                                               "dropped on every frame" if missing else ""),
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(_hammer_main())
