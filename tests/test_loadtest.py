"""``wallcull loadtest`` and the simulated clients it runs, bounded to a few seconds each.

The load tests here run the real thing (a ``wallcull serve`` subprocess, node processes, the
driver process) on a 2 x 2 wall for a few seconds and check the report's shape and invariants,
never its timings. The full-size runs (8 x 8, 60 frames/s, 10 s; 20,000 requests) are
``@pytest.mark.slow``: ``python -m pytest -m slow tests/test_loadtest.py``.
"""

import asyncio
import json
import os
import secrets
import signal
import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest

from wallcull_clients.driver import Driver
from wallcull_clients.rawhttp import Connection
from wallcull_clients.sim import (Mesh, MeshCache, TileClient, msgpack_ints_len, parse_tiles,
                         shared_scene, sorted_ints_len)
from wallcull import protocol
from wallcull_clients.loadtest import analyze, free_port, kernels_loaded, running_server, split

ROOT = Path(__file__).resolve().parent.parent
WALL_2x2 = {"cols": 2, "rows": 2, "tile_size": [0.6, 0.34], "gap": [0.012, 0.012],
            "distance": 2.0}
TOKEN = secrets.token_hex(8)


def loadtest(tmp_path, *args, timeout=180):
    out = tmp_path / "report"
    proc = subprocess.run([sys.executable, "-m", "wallcull.cli", "loadtest", *args,
                           "--out", str(out), "--json"], capture_output=True, text=True,
                          timeout=timeout, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert json.loads((out / "report.json").read_text()) == report
    assert (out / "report.md").read_text().startswith("# wallcull load test")
    return report


def check_walkthrough(report, tiles, frames):
    assert report["kind"] == "walkthrough"
    # a driver behind its schedule skips the frames whose slots passed (a busy machine)
    assert report["frames_posted"] + report["driver"]["skipped"] == frames
    assert report["frames_per_s"] > 0
    assert report["errors"]["node_errors"] == 0 and report["errors"]["process_errors"] == []
    assert report["errors"]["tiles_missing"] == 0
    assert len(report["tiles"]) == tiles
    assert report["nodes"]["every_tile_got_packets"]
    assert all(t["packets"] > 0 for t in report["tiles"])
    lat = report["latency_ms"]
    for key in ("all_tiles", "all_tiles_from_send", "display", "per_tile"):
        assert lat[key]["n"] > 0
        assert 0 < lat[key]["min"] <= lat[key]["p50"] <= lat[key]["p99"] <= lat[key]["max"]
    # the frame reaches all tiles no sooner than it reaches the median tile
    assert lat["all_tiles"]["p50"] >= lat["per_tile"]["p50"]
    assert lat["all_tiles_from_send"]["p50"] > lat["all_tiles"]["p50"]
    b = report["bytes"]
    assert b["delta_packets"] > 0
    assert 0 < b["per_frame"] < b["per_frame_if_full"]
    assert 0 < b["lists_per_frame"] < b["lists_per_frame_if_full"]
    assert b["reduction"] > 1 and b["lists_reduction"] > b["reduction"]
    assert report["dropped"]["tile_frames"] >= 0
    for name in ("server", "clients", "driver"):
        assert report["cpu"][name]["seconds"] > 0
    assert report["server_metrics"]["frames"] == report["frames_posted"]
    assert report["nodes"]["mesh_fetches"] > 0


def test_loadtest_ws(tmp_path):
    report = loadtest(tmp_path, "--wall", json.dumps(WALL_2x2), "--rate", "60",
                      "--duration", "3", "--mode", "ws", "--prefetch")
    check_walkthrough(report, 4, 180)
    assert report["config"]["mode"] == "ws" and "barrier" not in report
    # each of the 4 nodes fetched every mesh of the scene once, before the first frame, not
    # only those its tile showed
    from wallcull.scene import load

    assert report["config"]["prefetch"]
    assert report["nodes"]["mesh_fetches"] == 4 * len(load("powerplant").meshes)


def test_loadtest_render_nodes_size_full_lists_on_sampled_frames(tmp_path):
    """Render nodes of two tiles each: their messages are sized as full lists on one frame in
    ``FULL_SIZE_EVERY``, and the report's reduction comes from those frames alone."""
    from wallcull_clients.sim import FULL_SIZE_EVERY

    report = loadtest(tmp_path, "--wall", json.dumps(WALL_2x2), "--rate", "60",
                      "--duration", "3", "--tiles-per-node", "2", "--prefetch", "--warmup", "0")
    check_walkthrough(report, 4, 180)
    b = report["bytes"]
    # the node messages, once each (they were counted once a tile), as the server sent them
    sent = report["server_metrics"]["packets"]
    assert b["counted"] == "node messages"
    assert (b["full_packets"], b["delta_packets"]) == (sent["full/ws"], sent["delta/ws"])
    assert "| node messages full / delta |" in (tmp_path / "report" / "report.md").read_text()
    measured = report["frames_measured"]
    assert 0 < b["sampled_frames"] <= measured // FULL_SIZE_EVERY + 1
    assert 0 < b["sampled_per_frame"] < b["per_frame_if_full"]


def test_loadtest_pull_barrier_two_processes(tmp_path):
    # a busy machine may hold a frame's last acknowledgement back for more than a second
    report = loadtest(tmp_path, "--wall", json.dumps(WALL_2x2), "--rate", "40",
                      "--duration", "3", "--mode", "pull", "--barrier", "--clients-procs", "2",
                      "--path", "fly", "--barrier-timeout", "10")
    check_walkthrough(report, 4, 120)
    assert report["config"]["clients_procs"] == 2
    # pulling every frame number with the barrier: nothing is ever dropped
    assert report["dropped"] == {"tile_frames": 0, "frames_not_on_every_tile": 0}
    assert report["barrier"]["incomplete"] == 0
    assert report["barrier"]["latency_ms"]["p50"] > 0


def test_loadtest_requests(tmp_path):
    report = loadtest(tmp_path, "--wall", json.dumps(WALL_2x2), "--requests", "400",
                      "--concurrency", "8")
    assert report["kind"] == "requests"
    assert report["requests"] == 400 and report["status"] == {"200": 400}
    assert report["requests_per_s"] > 0 and report["bytes_per_response"] > 100
    assert report["server_metrics"]["packets"]["full/http"] == 400


async def _health_server(answers):
    """A loopback HTTP server whose ``GET /health`` answers ``kernels: loading`` to the first
    ``answers[0]`` requests and ``ready`` after (``answers[1]`` counts the requests)."""
    async def handle(reader, writer):
        while await reader.readuntil(b"\r\n\r\n"):
            answers[1] += 1
            body = json.dumps({"status": "ok", "kernels": "loading" if answers[1] <= answers[0]
                               else "ready"}).encode()
            writer.write(b"HTTP/1.1 200 OK\r\ncontent-type: application/json\r\n"
                         b"content-length: %d\r\n\r\n%s" % (len(body), body))
            await writer.drain()
    return await asyncio.start_server(handle, "127.0.0.1", 0)


def test_load_tests_wait_for_the_servers_kernels():
    """A server still compiling its kernels (a fresh install) is not measured: the load test
    waits on ``/health`` until they are in, and gives up with a clear error if they never
    come. (Measured without the wait, the first load test after an install saw every node's
    stream idle while the server compiled, and reported every tile-frame dropped.)"""
    async def main():
        answers = [5, 0]
        server = await _health_server(answers)
        url = f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}"
        async with server:
            waited = await kernels_loaded(url)
            assert answers[1] == 6 and waited > 0  # five "loading", then "ready"
            assert await kernels_loaded(url) == 0.0 and answers[1] == 7
            answers[:] = [10 ** 9, 0]
            with pytest.raises(RuntimeError, match="still compiling its kernels"):
                await kernels_loaded(url, timeout=0.3)
            assert answers[1] > 1

    asyncio.run(main())


def test_a_load_test_without_its_progress_bar_asks_the_server_nothing_while_it_runs():
    """The progress bar asks the server for the wall's latest frame twice a second; without
    the bar (``--json``, a measured run) nothing is asked, so that the server's measured CPU
    is the wall's alone."""
    from wallcull_clients.loadtest import _watch

    async def main():
        counted = [0, 0]
        server = await _health_server(counted)
        url = f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}"
        async with server:
            for show in (False, True):
                counted[1] = 0
                drv = await asyncio.create_subprocess_exec(
                    sys.executable, "-c", "import sys; sys.stdin.read()",
                    stdin=asyncio.subprocess.PIPE)
                watch = asyncio.create_task(_watch(url, "w", 10, drv, show))
                if show:  # the bar asks at once: the driver ends once it has
                    while counted[1] == 0:
                        await asyncio.sleep(0.01)
                drv.stdin.close()
                await watch
                assert (counted[1] > 0) == show

    asyncio.run(main())


def test_loadtest_bad_arguments(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "wallcull.cli", "loadtest",
                           "--clients-procs", "0"], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.startswith("wallcull: error:")


@pytest.mark.parametrize("args,said", [
    (["--duration", "inf"], "--duration must be a positive number of seconds, got inf"),
    (["--duration", "nan"], "--duration must be a positive number of seconds, got nan"),
    (["--rate", "inf", "--duration", "2"], "--rate must be 0 (as fast as it goes) or a "),
    (["--nats", "nats://127.0.0.1:4222"], "--nats is the broker of --transport nats"),
    (["--stereo", "2"], "argument --stereo: an interpupillary distance is over 0 and at most "
                        "1 m, got 2"),
    (["--server", "http://127.0.0.1:9", "--transport", "nats"],
     "--transport nats with --server needs the server's broker: --nats URL")])
def test_loadtest_refuses_what_it_cannot_run_in_one_line(capsys, args, said):
    """Infinite or NaN durations and rates were internal errors (or blamed --warmup); a
    --nats without NATS was ignored; NATS on a --server with a broker of our own measured
    nothing (the server never publishes there)."""
    from wallcull.cli import main

    assert main(["loadtest", *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"wallcull: error: {said}"), err


def test_loadtest_whose_server_cannot_reach_its_broker_says_so_in_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "wallcull.cli", "loadtest", "--transport",
                           "nats", "--nats", f"nats://127.0.0.1:{free_port()}"],
                          capture_output=True, text=True, timeout=180, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(
        "wallcull: error: the server exited with status 2: cannot reach the NATS broker"), \
        proc.stderr


def test_loadtest_whose_tiles_hear_nothing_fails(server, tmp_path):
    """Nodes on a broker the server does not publish to: every tile-frame is dropped, and the
    run fails (status 1, one line) instead of passing with nothing measured."""
    from wallcull_clients.broker import Broker

    with Broker() as broker:
        proc = subprocess.run([sys.executable, "-m", "wallcull.cli", "loadtest", "--server",
                               server, "--token", TOKEN, "--wall", json.dumps(WALL_2x2),
                               "--transport", "nats", "--nats", broker.url, "--rate", "20",
                               "--duration", "1", "--warmup", "0", "--out",
                               str(tmp_path / "report"), "--json"],
                              capture_output=True, text=True, timeout=180, cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr == ("wallcull: error: 4 of 4 tiles got no packet: the nodes heard "
                           "nothing from the server (with --server and --transport nats, is "
                           "--nats the server's broker?)\n")
    assert json.loads(proc.stdout)["nodes"]["every_tile_got_packets"] is False


def test_loadtest_as_fast_as_it_goes_keeps_its_warmup(server, tmp_path):
    """--rate 0: the warm-up's seconds are frames at the rate achieved (they were none)."""
    report = loadtest(tmp_path, "--server", server, "--token", TOKEN, "--wall",
                      json.dumps(WALL_2x2), "--rate", "0", "--duration", "1", "--warmup", "0.5")
    assert report["config"]["warmup_frames"] == min(
        round(0.5 * report["driver"]["rate"]), report["config"]["frames"] - 2) > 0


@pytest.mark.slow
@pytest.mark.parametrize("path", ["orbit", "fly"])
def test_loadtest_8x8_full_size(tmp_path, path):
    """The benchmark configuration: 64 nodes, 60 frames/s, 10 s (timings recorded, not
    asserted; see docs and the loadtest report)."""
    report = loadtest(tmp_path, "--wall", str(ROOT / "examples" / "wall-8x8.json"),
                      "--duration", "10", "--path", path, timeout=600)
    check_walkthrough(report, 64, 600)


@pytest.mark.slow
def test_loadtest_requests_full_size(tmp_path):
    report = loadtest(tmp_path, "--requests", "20000", "--concurrency", "64", timeout=600)
    assert report["status"] == {"200": 20000}


# --------------------------------------------------------------------------- the pieces


def test_mesh_cache_is_lru_by_bytes():
    def mesh(key, triangles):
        return Mesh(key, f'"{key}"', np.zeros((3, 3), "<f4"), np.zeros((triangles, 3), "<u4"))

    evicted = []
    cache = MeshCache(budget=36 + 12 * 10 + 36 + 12 * 10, on_evict=evicted.append)
    assert cache.put(mesh("a", 10)) == [] and cache.put(mesh("b", 10)) == []
    assert cache.get("a") is not None  # a is now the most recently used
    assert cache.put(mesh("c", 10)) == ["b"] and evicted == ["b"]
    assert cache.get("b") is None and "a" in cache and "c" in cache
    assert cache.bytes == 2 * (36 + 120) and cache.evictions == 1
    assert cache.put(mesh("huge", 1000)) == ["a", "c"]  # alone, but in: it must be drawn
    assert list(cache.entries) == ["huge"] and cache.evictions == 3
    assert (cache.hits, cache.misses) == (1, 1)
    assert cache.put(mesh("huge", 5)) == [] and cache.bytes == 36 + 60  # replaced, not doubled


@pytest.mark.parametrize("hi", [100, 200, 300, 70_000, 1 << 33])
@pytest.mark.parametrize("n", [0, 1, 15, 16, 300, 70_000])
def test_msgpack_ints_len_is_exact(n, hi):
    v = np.random.default_rng(n + hi).integers(0, hi, n)
    assert msgpack_ints_len(v) == len(msgpack.packb(v.tolist()))
    v.sort()
    assert sorted_ints_len(v) == sorted_ints_len(v.tolist()) == len(msgpack.packb(v.tolist()))


def test_tiles_and_splits():
    from wallcull.validate import tiles_text

    assert parse_tiles("0-3,7, 9-10") == [0, 1, 2, 3, 7, 9, 10]
    assert tiles_text([0, 1, 2, 3, 7, 9, 10]) == "0-3,7,9-10"
    rng = np.random.default_rng(5)
    for _ in range(200):  # the short form reads back as the same tiles
        tiles = sorted(set(rng.integers(0, 40, rng.integers(1, 30)).tolist()))
        assert parse_tiles(tiles_text(tiles)) == tiles
    assert parse_tiles("all", 4) == [0, 1, 2, 3]
    assert parse_tiles("3,1-2,2") == [1, 2, 3]
    for bad in ("", "a-b", "3-", "-1", "5-3", "99999999999"):
        with pytest.raises(ValueError):
            parse_tiles(bad)
    with pytest.raises(ValueError, match="0-63"):
        parse_tiles("60-64", 64)
    with pytest.raises(ValueError, match="'5-3' runs backwards: write it 3-5"):
        parse_tiles("5-3", 64)
    assert split(64, 3) == [(0, 20), (21, 42), (43, 63)]
    assert split(2, 5) == [(0, 0), (1, 1)]


def test_analyze_counts_drops_and_takes_the_latest_tile():
    driver = {"log": {"frame": [0, 1, 2], "send": [9.0, 10.0, 11.0]}}

    def tile(t, frames, recv):
        n = len(frames)
        return {"tile": t, "frame": frames, "recv": recv,
                "posted": [10.0 + f - 1 + 0.001 for f in frames], "full": [True] + [False] * (n - 1),
                "bytes": [100] * n, "full_bytes": [300] * n, "list_bytes": [10] * n,
                "full_list_bytes": [200] * n, "fit_bytes": [50] * n, "errors": [],
                "base_misses": 0, "mesh_fetches": 1, "mesh_not_modified": 0, "mesh_bytes": 9}

    # tile 1 never saw frame 1 (conflated), and got frame 2 late
    out = analyze(driver, [tile(0, [0, 1, 2], [9.011, 10.011, 11.011]),
                           tile(1, [0, 2], [9.021, 11.051])])
    assert out["dropped"] == {"tile_frames": 1, "frames_not_on_every_tile": 1}
    assert out["latency_ms"]["all_tiles"]["n"] == 2  # frames 0 and 2
    assert out["latency_ms"]["all_tiles"]["max"] == pytest.approx(50.0)
    assert out["latency_ms"]["all_tiles"]["min"] == pytest.approx(20.0)
    # display latency covers frame 1 too: tile 1 first showed a frame >= 1 at 11.051
    assert out["latency_ms"]["display"]["n"] == 3
    assert out["latency_ms"]["display"]["max"] == pytest.approx(1050.0)
    assert out["bytes"]["per_frame"] == pytest.approx(500 / 3)
    assert out["bytes"]["reduction"] == pytest.approx(3.0)
    assert [t["dropped"] for t in out["tiles"]] == [0, 1]


def test_analyze_weighs_full_lists_on_the_frames_nodes_sampled():
    """Render nodes size their messages as full lists on some frames only (NaN on the others,
    ``sim.FULL_SIZE_EVERY``): the reduction is over those frames' packets alone, against what
    the same packets weighed; the bytes received are over every frame."""
    nan = float("nan")
    driver = {"log": {"frame": [0, 1, 2, 3], "send": [9.0, 10.0, 11.0, 12.0]}}

    def tile(t):
        return {"tile": t, "frame": [0, 1, 2, 3], "recv": [9.01, 10.01, 11.01, 12.01],
                "posted": [9.0, 10.0, 11.0, 12.0], "full": [True, False, False, False],
                "bytes": [400, 100, 50, 100], "full_bytes": [400, nan, 300, nan],
                "list_bytes": [40, nan, 5, nan], "full_list_bytes": [40, nan, 30, nan],
                "fit_bytes": [20, nan, 20, nan], "errors": [], "base_misses": 0,
                "mesh_fetches": 1, "mesh_not_modified": 0, "mesh_bytes": 9}

    b = analyze(driver, [tile(0), tile(1)])["bytes"]
    assert b["per_frame"] == pytest.approx(2 * 650 / 4)  # every frame received
    assert b["sampled_frames"] == 2
    assert b["per_frame_if_full"] == pytest.approx(2 * 700 / 2)
    assert b["reduction"] == pytest.approx(700 / 450)  # frames 0 and 2 alone
    assert b["lists_reduction"] == pytest.approx(70 / 45)
    assert b["fits_per_frame"] == pytest.approx(2 * 40 / 2)


# --------------------------------------------------------------------------- against a server


@pytest.fixture(scope="module")
def server():
    with running_server(TOKEN) as url:
        yield url


async def _wall_with_frames(url, count, scene="fatehpur"):
    async with Driver(url, TOKEN) as d:
        info = await d.create_wall(scene, WALL_2x2)
        frames = await d.frames(scene, info["wall"], "fly", count, loop=40)
        for f in frames:
            await d.post(info["id"], f)
    return info


def test_full_size_arithmetic_matches_the_server(server):
    """What a node computes a delta would have cost as a full list equals the byte count of
    the server's own full packet of that frame."""

    async def go():
        info = await _wall_with_frames(server, 12)
        scene = await shared_scene(server, info["scene"])
        checked = 0
        for tile in range(info["tiles"]):
            client = TileClient(server, info["id"], tile, scene, mode="pull", token=TOKEN)
            async with Connection(server, TOKEN) as conn:
                base = await conn.request("GET", f"/walls/{info['id']}/tiles/{tile}/packets/3",
                                          auth=True)
                await client.receive(base.data(), len(base.body), 0.0)  # acks frame 3
                delta = await conn.request("GET", f"/walls/{info['id']}/tiles/{tile}/packets/11",
                                           auth=True)
                full = await conn.request(
                    "GET", f"/walls/{info['id']}/tiles/{tile}/packets/11?full=1", auth=True)
            assert delta.data()["base"] == 3 and full.data()["base"] is None
            await client.receive(delta.data(), len(delta.body), 0.0)
            assert client.stats.full_bytes[-1] == len(full.body)
            assert client.stats.full_list_bytes[-1] == len(msgpack.packb(full.data()["visible"]))
            assert client.lists[11].tolist() == full.data()["visible"]
            checked += len(full.data()["visible"]) > 0
            await client.http.close()
        assert checked  # some tile had a non-empty list

    asyncio.run(go())


def test_fitted_frusta_bytes_count_a_stereo_packets_eyes(server):
    """The fitted frusta of a stereo packet are its view and projection and each eye's: the
    bytes a node counts are what they take in the server's packet (the eyes were left out,
    a third of them)."""

    async def go():
        async with Driver(server, TOKEN) as d:
            info = await d.create_wall("fatehpur", WALL_2x2)
            frame = (await d.frames("fatehpur", info["wall"], "orbit", 1))[0]
            await d.post(info["id"], {**frame, "stereo": {"ipd": 0.064}})
        scene = await shared_scene(server, info["scene"])
        client = TileClient(server, info["id"], 1, scene, mode="pull", token=TOKEN)
        async with Connection(server, TOKEN) as conn:
            got = await conn.request("GET", f"/walls/{info['id']}/tiles/1/packets/latest",
                                     accept="application/msgpack", auth=True)
        await client.receive(got.data(), len(got.body), 0.0)
        await client.http.close()
        return got.data(), client.stats.fit_bytes[-1]

    pkt, fit = asyncio.run(go())
    assert {"left", "right"} <= set(pkt)
    rest = {k: v for k, v in pkt.items() if k not in ("view", "projection", "left", "right")}
    assert fit == len(msgpack.packb(pkt)) - len(msgpack.packb(rest))


def test_node_repairs_a_missing_base_with_a_full_list(server):
    """A delta against a frame the node no longer holds: it fetches the full list instead,
    rebuilds the right list and acknowledges it."""

    async def go():
        info = await _wall_with_frames(server, 6)
        scene = await shared_scene(server, info["scene"])
        tile = 3
        client = TileClient(server, info["id"], tile, scene, mode="pull", token=TOKEN)
        await client.run(until=2, start=2)  # full packet of frame 2, acked
        client.lists.clear()  # forget it
        await client.run(until=5, start=5)  # frame 5 comes as a delta against 2
        async with Connection(server, TOKEN) as conn:
            truth = (await conn.call("GET", f"/walls/{info['id']}/tiles/{tile}/packets/5"
                                            "?full=1", auth=True))["visible"]
            acked = await conn.call("GET", f"/walls/{info['id']}/barrier/5?timeout=0")
        assert client.stats.base_misses == 1 and client.stats.repairs == 1
        assert client.stats.frame == [2, 5] and client.stats.full == [True, True]
        assert client.lists[5].tolist() == truth
        assert acked["acked"] == 1  # this tile acknowledged frame 5
        assert client.stats.errors == []

    asyncio.run(go())


def test_node_keeps_lists_until_the_server_has_seen_newer_acks(server):
    """Deltas can be based on an older acknowledgement than the newest frame the node took
    (acks in flight): the node keeps every list from the newest base on."""

    async def go():
        info = await _wall_with_frames(server, 30)
        scene = await shared_scene(server, info["scene"])
        client = TileClient(server, info["id"], 0, scene, mode="pull", token=TOKEN, keep=256)
        held = {}
        client.on_list = lambda tile, frame, leaves: held.update({frame: leaves})
        await client.run(until=4)  # frames 0..4, each a delta against the one before
        assert client.stats.full == [True, False, False, False, False]
        assert list(client.lists) == [3, 4]  # 3 was frame 4's base; 4 may be the next one
        return client

    asyncio.run(go())


def test_pull_and_stream_nodes_against_a_real_server(server):
    """A few frames through both transports with a mesh budget too small for the scene:
    evictions are counted and meshes come back as 304s (revalidated by ETag)."""

    async def go():
        async with Driver(server, TOKEN) as d:
            info = await d.create_wall("powerplant", WALL_2x2)
            frames = await d.frames("powerplant", info["wall"], "orbit", 8)
            scene = await shared_scene(server, "powerplant")
            clients = [TileClient(server, info["id"], t, scene, mode=mode, token=TOKEN,
                                  cache_bytes=40_000)
                       for t, mode in ((0, "pull"), (1, "pull"), (2, "ws"), (3, "ws"))]
            tasks = [asyncio.create_task(c.run(until=7, idle_timeout=10)) for c in clients]
            for c in clients:
                await c.connected.wait()
            assert await d.wait_clients(info["id"], 2, 10) == 2
            await d.run(info["id"], frames, rate=0, barrier=True, barrier_timeout=10)
            await asyncio.gather(*tasks)
            barrier = await d.barrier(info["id"], 7, 0)
        assert barrier["complete"] and barrier["acked"] == 4
        for c in clients:
            assert c.stats.errors == [] and c.stats.frame[-1] == 7
            assert c.stats.triangles[-1] > 0
            assert c.cache.bytes <= 40_000 or len(c.cache.entries) == 1
        for pull in clients[:2]:
            assert pull.stats.frame == list(range(8))
            assert sum(pull.stats.full) == 1  # the first; then deltas against the last ack
        assert sum(c.cache.evictions for c in clients) > 0
        assert sum(c.stats.mesh_not_modified for c in clients) > 0

    asyncio.run(go())


def test_protocol_apply_is_what_the_nodes_use():
    """The node's rebuild is protocol.apply: a packet whose count disagrees is an error the
    node records (and it asks for a full list) rather than a wrong list drawn."""
    from wallcull_clients.sim import SceneInfo

    scene = SceneInfo("s", ["m"], np.array([-1, 0, 0]), np.tile(np.eye(4), (3, 1, 1)),
                      np.array([1, 2]))
    client = TileClient("http://127.0.0.1:9", "w", 0, scene, mode="pull")
    client.lists[4] = np.array([1])
    bad = {"frame": 5, "tile": 0, "time": 0.0, "base": 4, "added": [2], "removed": [],
           "count": 3, "view": np.eye(4).tolist(), "projection": np.eye(4).tolist()}

    async def go():
        assert not await client.receive(bad, 10, 0.0)

    asyncio.run(go())
    assert client.stats.errors and "does not add up" in client.stats.errors[0]
    assert protocol.apply(np.array([1]), {**bad, "count": 2}).tolist() == [1, 2]


def _rendered(server, wall: dict, stereo: float | None = None, **options) -> list:
    """Three orbit frames of a wall on fatehpur (``stereo``: stereo frames, the eyes this far
    apart), drawn by pulling nodes with the real OpenGL renderer (``--render``; skipped
    without headless OpenGL); the nodes, once they stop (the wall then deleted)."""
    render = pytest.importorskip("wallcull_clients.render")
    try:
        render.reversed_z_available()
    except Exception as exc:  # noqa: BLE001 - no EGL here
        pytest.skip(f"no headless OpenGL: {exc}")
    from wallcull_clients.sim import run_wall

    async def go():
        async with Driver(server, TOKEN) as d:
            info = await d.create_wall("fatehpur", wall)
            frames = await d.frames("fatehpur", info["wall"], "orbit", 3, stereo=stereo)
            ready = asyncio.Event()
            task = asyncio.create_task(run_wall(
                server, info["id"], "all", mode="pull", token=TOKEN, render=True, until=2,
                idle_timeout=10, ready=lambda clients: ready.set(), **options))
            await asyncio.wait([task, asyncio.ensure_future(ready.wait())],
                               return_when=asyncio.FIRST_COMPLETED)
            if task.done():  # the nodes failed before they were ready
                return task.result()
            await d.run(info["id"], frames, rate=0, barrier=True, barrier_timeout=10)
            await d.call("DELETE", f"/walls/{info['id']}", auth=True)
            return await task

    return asyncio.run(go())


def test_render_nodes_draw_their_lists_with_the_packet_matrices(server):
    """--render: each node draws its leaves with the real OpenGL renderer, with the view and
    projection of its packet. Every pixel drawn belongs to a leaf of the tile's list, and tiles
    with leaves in view draw some."""
    clients = _rendered(server, WALL_2x2, render_size=(96, 54))
    drawn = 0
    for c in clients:
        ids = np.unique(c.image.ids)
        leaves = set((c.lists[2] + 1).tolist())
        assert set(ids[ids > 0].tolist()) <= leaves
        drawn += (c.image.ids > 0).sum() > 0
        assert c.stats.triangles[-1] >= 0 and c.stats.errors == []
    assert drawn >= 2  # the orbit keeps the model in the middle of the wall


def test_render_nodes_draw_both_eyes_of_stereo_frames(server):
    """A driver posting stereo frames (``--stereo``): each node draws its tile once per eye,
    with that eye's matrices (it drew the centre's view alone), and only its list's leaves."""
    clients = _rendered(server, WALL_2x2, stereo=0.5, render_size=(96, 54))
    differ = 0
    for c in clients:
        assert c.stats.errors == [] and c.image is None
        left, right = c.images[c.tile, "left"].ids, c.images[c.tile, "right"].ids
        leaves = set((c.lists[2] + 1).tolist())
        for ids in (left, right):
            assert set(np.unique(ids[ids > 0]).tolist()) <= leaves
        differ += not np.array_equal(left, right)
    assert differ >= 2  # eyes half a metre apart see the model from two sides


def test_render_nodes_of_a_screens_wall_draw_each_screen_at_its_own_size(server):
    """--render on a CAVE (screens, each with its own resolution): every node draws at an
    eighth of its screen's resolution (the nodes died on the wall's resolution, which only a
    grid has)."""
    cave = json.loads((ROOT / "examples" / "wall-cave.json").read_text())
    cave["screens"][1]["resolution"] = [960, 480]
    clients = _rendered(server, cave)
    assert len(clients) == len(cave["screens"])
    for c, screen in zip(clients, cave["screens"]):
        w, h = screen["resolution"]
        assert c.image.ids.shape == (h // 8, w // 8)
        ids = np.unique(c.image.ids)
        assert set(ids[ids > 0].tolist()) <= set((c.lists[2] + 1).tolist())
        assert c.stats.errors == []
    assert sum((c.image.ids > 0).any() for c in clients) >= 1


# --------------------------------------------------------------------------- failures, told


def test_analyze_counts_a_tile_without_records_as_dropped_on_every_frame():
    """A node process that died leaves no records: its tiles are dropped on every measured
    frame, so no frame reached "all tiles" and the latency over all tiles is not measured."""
    driver = {"log": {"frame": [0, 1, 2], "send": [9.0, 10.0, 11.0]}}
    tile = {"tile": 0, "frame": [0, 1, 2], "recv": [9.01, 10.01, 11.01],
            "posted": [9.0, 10.0, 11.0], "full": [True, False, False], "bytes": [300, 100, 100],
            "errors": [], "base_misses": 0, "mesh_fetches": 1, "mesh_not_modified": 0,
            "mesh_bytes": 9}
    out = analyze(driver, [tile], count=3)
    assert [t["tile"] for t in out["tiles"]] == [0, 1, 2]
    assert [t["dropped"] for t in out["tiles"]] == [0, 3, 3]
    assert out["dropped"] == {"tile_frames": 6, "frames_not_on_every_tile": 3}
    assert out["latency_ms"]["all_tiles"] == {"n": 0}
    assert out["errors"]["tiles_missing"] == 2 and out["errors"]["tiles_missing_ids"] == [1, 2]
    assert not out["nodes"]["every_tile_got_packets"]


def test_analyze_weighs_bytes_over_the_frames_received():
    """Bytes per frame received are over the frames some tile received: a frame no tile got
    does not thin the mean (it used to divide by every measured frame)."""
    driver = {"log": {"frame": [0, 1, 2, 3], "send": [9.0, 10.0, 11.0, 12.0]}}
    tile = {"tile": 0, "frame": [0, 1, 3], "recv": [9.01, 10.01, 12.01],
            "posted": [9.0, 10.0, 12.0], "full": [True, False, False], "bytes": [300, 100, 200],
            "errors": [], "base_misses": 0, "mesh_fetches": 1, "mesh_not_modified": 0,
            "mesh_bytes": 9}
    b = analyze(driver, [tile])["bytes"]
    assert b["received_frames"] == 3 and b["per_frame"] == pytest.approx(600 / 3)


@pytest.mark.parametrize("warmup", ["-1", "2", "5"])
def test_loadtest_refuses_a_warmup_out_of_range(warmup):
    proc = subprocess.run([sys.executable, "-m", "wallcull.cli", "loadtest", "--duration", "2",
                           "--warmup", warmup], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr == ("wallcull: error: --warmup must be 0 or more and less than "
                           f"--duration (2 s), got {warmup}\n")


def start_loadtest(tmp_path, *args) -> subprocess.Popen:
    """``wallcull loadtest`` in a process group of its own (a terminal's Ctrl-C reaches the
    whole group), reporting to ``tmp_path / "report"``."""
    return subprocess.Popen([sys.executable, "-m", "wallcull.cli", "loadtest", *args, "--out",
                             str(tmp_path / "report"), "--json"], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def stopped_while_driving(tmp_path, stop, *args, timeout: float = 180):
    """``wallcull loadtest *args`` (:func:`start_loadtest`), with ``stop(proc)`` called once
    its driver runs; ``(status, stdout, stderr, driver process)``."""
    proc = start_loadtest(tmp_path, *args)
    try:
        driver = child(proc, "wallcull_clients.driver")
        stop(proc)
        out, err = proc.communicate(timeout=timeout)
    finally:
        proc.kill()
    return proc.returncode, out, err, driver


def interrupt(proc: subprocess.Popen) -> None:
    """Ctrl-C at a terminal: SIGINT to the whole process group."""
    os.killpg(proc.pid, signal.SIGINT)


def child(proc: subprocess.Popen, *words: str):
    """The first process under ``proc`` whose command line holds ``words``, once it runs."""
    import time

    import psutil

    deadline = time.monotonic() + 180
    while True:
        assert proc.poll() is None, proc.communicate()
        for c in psutil.Process(proc.pid).children(recursive=True):
            try:
                if all(w in c.cmdline() for w in words):
                    return c
            except psutil.Error:
                pass
        assert time.monotonic() < deadline, f"no {words} under the load test"
        time.sleep(0.05)


def strict_json(text: str):
    def refuse(name):
        raise ValueError(f"{name} is not JSON")
    return json.loads(text, parse_constant=refuse)


def test_loadtest_a_node_process_that_dies_fails_the_run(tmp_path):
    """Two node processes, one SIGKILLed once the driver runs: its tiles count as dropped on
    every measured frame, the report names them and the process, the latency target is
    missed, and the run ends with status 1 and one line."""
    status, out, err, _ = stopped_while_driving(
        tmp_path, lambda proc: child(proc, "wallcull_clients.sim", "0-1").kill(),
        "--wall", json.dumps(WALL_2x2), "--rate", "30", "--duration", "3", "--clients-procs", "2")
    assert status == 1, err
    assert err.count("\n") == 1 and err.startswith("wallcull: error: node process 0 (tiles "
                                                   "0-1) was killed by SIGKILL"), err
    report = strict_json(out)
    assert report["errors"]["tiles_missing"] == 2
    assert report["errors"]["tiles_missing_ids"] == [0, 1]
    measured = report["frames_measured"]
    assert [t["dropped"] for t in report["tiles"][:2]] == [measured, measured]
    assert report["dropped"]["tile_frames"] >= 2 * measured
    assert report["dropped"]["frames_not_on_every_tile"] == measured
    assert report["latency_ms"]["all_tiles"] == {"n": 0}
    assert report["targets"]["p99_all_tiles_ms"]["met"] is False
    md = (tmp_path / "report" / "report.md").read_text()
    assert "**The run failed.** Node process 0 (tiles 0-1) was killed by SIGKILL." in md
    assert "Tiles 0-1 left no records" in md
    assert "| tiles with no records (dropped on every frame) | 2: 0-1 |" in md


def walls(url) -> list[str]:
    async def go():
        async with Connection(url) as conn:
            return [w["id"] for w in (await conn.call("GET", "/walls"))["walls"]]
    return asyncio.run(go())


def test_loadtest_against_a_running_server_writes_json_and_leaves_no_wall(server, tmp_path):
    """``--server``: the server's CPU is not measured: null in the JSON (no bare NaN), "not
    measured" in the report; and the wall each run made there is deleted when it ends."""
    before = walls(server)
    report = loadtest(tmp_path, "--server", server, "--token", TOKEN, "--wall",
                      json.dumps(WALL_2x2), "--rate", "30", "--duration", "1", "--warmup", "0")
    strict_json((tmp_path / "report" / "report.json").read_text())
    assert report["cpu"]["server"] == {"seconds": None, "percent": None}
    assert report["cpu"]["server_us_per_tile_frame"] is None
    assert report["cpu"]["others"]["percent"] is not None
    assert report["cpu"]["others"]["server_included"]
    target = report["targets"]["server_us_per_tile_frame"]
    assert target["value"] is None and target["met"] is None
    md = (tmp_path / "report" / "report.md").read_text()
    assert "| server_us_per_tile_frame | 25 | - | not measured |" in md
    assert "nan" not in md
    assert walls(server) == before
    report = loadtest(tmp_path, "--server", server, "--token", TOKEN, "--wall",
                      json.dumps(WALL_2x2), "--requests", "50", "--concurrency", "2")
    assert report["cpu"]["server"] == {"seconds": None, "percent": None}
    assert walls(server) == before


def test_loadtest_interrupted_against_a_running_server_leaves_no_wall(server, tmp_path):
    before = walls(server)
    status, _, err, _ = stopped_while_driving(
        tmp_path, interrupt, "--server", server, "--token", TOKEN, "--wall",
        json.dumps(WALL_2x2), "--rate", "30", "--duration", "30", timeout=120)
    assert status == 130 and err == "wallcull: interrupted\n", err
    assert walls(server) == before


def test_loadtest_interrupted_stops_its_driver_too(tmp_path):
    """Ctrl-C (SIGINT to the group) stops the server, the nodes and the driver: the driver,
    retrying the server that went, stops at once instead of for its minute of retrying, and
    the load test waits for it; one line says why the run ended."""
    import psutil

    status, _, err, driver = stopped_while_driving(
        tmp_path, interrupt, "--wall", json.dumps(WALL_2x2), "--rate", "30", "--duration", "30",
        timeout=120)
    assert status == 130 and err == "wallcull: interrupted\n", err
    try:
        assert driver.wait(timeout=5) is not None or not driver.is_running()
    except psutil.NoSuchProcess:
        pass


def test_loadtest_whose_server_dies_fails_in_one_line(tmp_path):
    status, _, err, _ = stopped_while_driving(
        tmp_path, lambda proc: child(proc, "wallcull.cli", "serve").kill(),
        "--wall", json.dumps(WALL_2x2), "--rate", "30", "--duration", "30", "--retry-for", "1",
        timeout=120)
    assert status == 2, err
    # (gave up after 1 s of retrying; or, killed as it opened its frame stream, refused)
    assert err.count("\n") == 1 and err.startswith("wallcull: error: the driver exited 2: "
                                                   "clients.driver: error: "), err


def test_loadtest_says_what_is_wrong_with_a_server_in_one_line(tmp_path):
    with running_server("secret-token") as url:
        for args, why in ((["--server", url], f"the server at {url} wants a token (HTTP 401): "
                                              "give it with --token (or $WALLCULL_TOKEN)"),
                          (["--server", url, "--token", "wrong"], "refused the token"),
                          (["--server", f"http://127.0.0.1:{free_port()}"], "cannot reach"),
                          (["--server", url, "--requests", "5"], "wants a token")):
            proc = subprocess.run([sys.executable, "-m", "wallcull.cli", "loadtest", *args,
                                   "--wall", json.dumps(WALL_2x2)], capture_output=True,
                                  text=True, timeout=120, cwd=tmp_path,
                                  env={k: v for k, v in os.environ.items()
                                       if k != "WALLCULL_TOKEN"})
            assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
            assert proc.stderr.startswith("wallcull: error:") and why in proc.stderr, proc.stderr


def test_request_throughput_counts_200_answers_alone(server):
    """Answers that are errors (an unknown wall's) are no throughput, and miss the target."""
    from wallcull_clients.loadtest import hammer, requests_targets

    result = asyncio.run(hammer(server, ["/walls/0123456789ab/tiles/0/packets/latest"], 40, 2,
                                token=TOKEN))
    assert result["requests"] == 40 and result["ok"] == 0 and result["not_ok"] == 40
    assert result["requests_per_s"] == 0 and "200" not in result["status"]
    assert requests_targets({**result, "requests_per_s": 1e9})["requests_per_s"]["met"] is False


def test_the_request_generator_marks_its_timed_window(server):
    """The generator says when its timed window opens and closes, so that the server's CPU
    is sampled over the same window (it was sampled from before the generator's start-up to
    after its exit, and divided by the shorter window)."""
    info = asyncio.run(_wall_with_frames(server, 1))
    proc = subprocess.run([sys.executable, "-m", "wallcull_clients.loadtest", "--server",
                           server, "--wall-id", info["id"], "--tiles", "4", "--requests", "20",
                           "--concurrency", "2", "--token", TOKEN],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = [strict_json(line) for line in proc.stdout.splitlines()]
    assert lines[:2] == [{"mark": "start"}, {"mark": "end"}]
    assert lines[2]["status"] == {"200": 20} and lines[2]["ok"] == 20


def test_a_driver_behind_its_schedule_skips_the_missed_slots(server):
    """A stall (here the driver's own loop, blocked 0.6 s) is followed by the newest frame,
    not the backlog posted flat out; the frames skipped are counted."""
    import time

    from wallcull_clients.driver import summary

    async def go():
        async with Driver(server, TOKEN) as d:
            info = await d.create_wall("fatehpur", WALL_2x2)
            frames = await d.frames("fatehpur", info["wall"], "fly", 40, loop=40)
            await d.post(info["id"], frames[0])  # the wall's first frame, which is slow
            d.log.frame.clear()

            posted = []

            def stall(kind, number, *rest):
                if kind == "posted":
                    posted.append(number)
                    if len(posted) == 6:
                        time.sleep(0.6)  # the whole loop stalls, as behind a stopped server
            log = await d.run(info["id"], frames, rate=20, on_event=stall, skip=True)
            await d.call("DELETE", f"/walls/{info['id']}", auth=True)
            return log

    log = asyncio.run(go())
    s = summary(log)
    assert s["skipped"] >= 8 and s["frames"] + s["skipped"] == 40
    # the stall's slots, skipped in a row (a loaded machine may skip a slot elsewhere too)
    runs = np.split(np.asarray(log.skipped), np.flatnonzero(np.diff(log.skipped) != 1) + 1)
    assert max(len(r) for r in runs) >= 8, log.skipped
    stalled = 5  # the sixth frame posted
    # after the stall, the frames keep their period (20 a second): no burst
    after = np.asarray(log.send[stalled + 1:])
    assert (after < after[0] + 0.3).sum() <= 8, np.diff(after)


def test_a_retry_stops_when_its_tool_is_told_to_stop():
    from wallcull_clients.retry import Backoff, Stopped, retrying

    async def go():
        stop = asyncio.Event()
        backoff = Backoff(60, stop=stop)

        async def refused():
            raise ConnectionRefusedError("nobody there")
        asyncio.get_running_loop().call_later(0.3, stop.set)
        t0 = asyncio.get_running_loop().time()
        with pytest.raises(Stopped, match="stopped while retrying"):
            await retrying(refused, backoff, "GET /")
        return asyncio.get_running_loop().time() - t0

    assert asyncio.run(go()) < 5


def test_the_driver_marks_its_posting_span(server):
    """The driver says when its posts begin and end, with its CPU time at each, and the load
    test samples every process's CPU at those two lines (the window began before the driver's
    start-up and imports, which diluted every percentage and counted its imports)."""
    from wallcull_clients.loadtest import _driving_span

    info = asyncio.run(_wall_with_frames(server, 1))
    proc = subprocess.run([sys.executable, "-m", "wallcull_clients.driver", "--server", server,
                           "--wall-id", info["id"], "--token", TOKEN, "--frames", "3",
                           "--rate", "0"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = [strict_json(line) for line in proc.stdout.splitlines()]
    driving, driven = lines[1], lines[2]
    assert driving["driving"] and driven["driven"]
    assert 0 < driving["cpu_seconds"] <= driven["cpu_seconds"]

    async def go():
        stream = asyncio.StreamReader()
        stream.feed_data(proc.stdout.encode())
        stream.feed_eof()
        samples = iter(range(10))
        return await _driving_span(stream, lambda: next(samples))

    start, end, cpu = asyncio.run(go())
    assert (start, end) == (0, 1)
    assert cpu == pytest.approx(driven["cpu_seconds"] - driving["cpu_seconds"])
