"""The client tools' command lines (simulated nodes, the driver, the picture): they stop when
told, say why they cannot go on in one line, and leave no wall behind when asked not to."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import secrets
import signal
import stat
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

import httpx
import pytest

from wallcull import cli
from wallcull.errors import InputError
from wallcull.server import settings_from_env
from wallcull_clients import broker, picture
from wallcull_clients.driver import Driver, write_private
from wallcull_clients.loadtest import free_port, running_server
from wallcull_clients.sim import NodeClient, find_wall, run_wall, shared_scene

ROOT = Path(__file__).resolve().parents[1]
TOKEN = secrets.token_hex(8)
AUTH = {"Authorization": f"Bearer {TOKEN}"}
WALL = {"cols": 2, "rows": 1, "tile_size": [0.6, 0.34], "gap": [0.01, 0.01], "distance": 2.0}
FRAME = {"position": [0.0, 20.0, 300.0], "orientation": [1.0, 0.0, 0.0, 0.0]}


@pytest.fixture(scope="module")
def server():
    with running_server(TOKEN) as url:
        yield url


def tool(*argv, env=None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", *argv], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "WALLCULL_TOKEN": TOKEN, **(env or {})})


def catches_sigterm(proc: subprocess.Popen) -> bool:
    """Whether the process has its own SIGTERM handler installed (its event loop's)."""
    status = Path(f"/proc/{proc.pid}/status").read_text()
    caught = int(next(line for line in status.splitlines() if line.startswith("SigCgt:"))
                 .split()[1], 16)
    return bool(caught >> (signal.SIGTERM - 1) & 1)


def wait_for(predicate, what: str, proc: subprocess.Popen | None = None):
    deadline = time.monotonic() + 120
    while not predicate():
        assert proc is None or proc.poll() is None, f"exited before {what}: {proc.stderr.read()}"
        assert time.monotonic() < deadline, f"never {what}"
        time.sleep(0.05)


@pytest.mark.parametrize("argv", [
    ("wallcull_clients.sim", "--reconnect-for", "600"),
    ("wallcull_clients.driver", "--wait-timeout", "600", "--retry-for", "600"),
], ids=["sim", "driver"])
def test_a_client_waiting_for_its_server_stops_at_once_on_sigterm(argv):
    """Before it drives or draws, a signal ends a client (it used to be ignored until the
    client's own wait, a minute or ten, ran out: `docker compose stop` then killed it)."""
    proc = tool(*argv, "--server", f"http://127.0.0.1:{free_port()}")
    try:
        wait_for(lambda: catches_sigterm(proc), "a SIGTERM handler", proc)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=120) == 130, proc.stderr.read()
    finally:
        proc.kill()
        proc.wait()


def test_a_node_names_what_it_cannot_reach(server):
    nowhere = f"http://127.0.0.1:{free_port()}"
    proc = tool("wallcull_clients.sim", "--server", nowhere, "--reconnect-for", "0.5")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2 and f"cannot reach {nowhere} within 0.5 s" in err, err
    # a wall id the server does not hold: at once, not after a minute of asking
    proc = tool("wallcull_clients.sim", "--server", server, "--wall", "0123456789ab")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2, err
    assert err.strip().endswith(f"no wall '0123456789ab' on {server}"), err


def test_a_node_over_nats_names_an_unreachable_broker(server):
    if broker.find() is None:
        pytest.skip("no nats-server (Debian package nats-server; .ci/run installs it)")
    wid = httpx.post(f"{server}/walls", json={"wall": WALL, "scene": "fatehpur"},
                     headers=AUTH, timeout=60).json()["id"]
    try:
        proc = tool("wallcull_clients.sim", "--server", server, "--wall", wid, "--nats",
                    "nats://127.0.0.1:1", "--reconnect-for", "1")
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 2, err
        assert "cannot reach the NATS broker at nats://127.0.0.1:1 within 1 s" in err, err
        assert "Traceback" not in err
    finally:
        httpx.delete(f"{server}/walls/{wid}", headers=AUTH, timeout=60)


def test_a_node_over_nats_with_no_server_on_its_broker_gives_up_in_one_line(server):
    """A full request no server is subscribed for is answered "no responders" at once: the
    node crashed on it with a traceback (status 1). It asks again with backoff, and after
    --reconnect-for seconds of that says so in one line."""
    if broker.find() is None:
        pytest.skip("no nats-server (Debian package nats-server; .ci/run installs it)")
    wid = httpx.post(f"{server}/walls", json={"wall": WALL, "scene": "fatehpur"},
                     headers=AUTH, timeout=60).json()["id"]
    try:
        with broker.Broker() as nats:  # the server is not on it
            proc = tool("wallcull_clients.sim", "--server", server, "--wall", wid, "--nats",
                        nats.url, "--tiles", "0", "--reconnect-for", "1", "--quiet")
            _, err = proc.communicate(timeout=120)
        assert proc.returncode == 2, err
        assert err.strip() == ("clients.sim: error: gave up after 1 s of retrying: tile 0: no "
                               "culling server on the NATS broker answers full requests"), err
    finally:
        httpx.delete(f"{server}/walls/{wid}", headers=AUTH, timeout=60)


def test_a_node_over_nats_waits_for_its_server_to_join_the_broker():
    """A node started before its server is on the broker (or back from the broker's restart
    before the server is) keeps asking, and draws once the server joins the broker."""
    if broker.find() is None:
        pytest.skip("no nats-server (Debian package nats-server; .ci/run installs it)")
    with broker.Broker() as nats, tempfile.TemporaryDirectory() as state, ExitStack() as stack:
        port = free_port()
        url = stack.enter_context(running_server(TOKEN, port=port, state=state))  # no --nats

        async def scenario():
            # (patient: server B's first frame may wait for the kernels A did not compile)
            async with Driver(url, TOKEN, timeout=600) as driver:
                wid = (await driver.create_wall("fatehpur", WALL))["id"]
                made = []
                nodes = asyncio.create_task(run_wall(url, wid, "all", token=TOKEN, until=3,
                                                     nats=nats.url, reconnect_for=120,
                                                     made=made))
                deadline = time.monotonic() + 120
                while not any(c.backoff.total for c in made):  # "no responders", waited out
                    if nodes.done():
                        nodes.result()  # (its failure)
                        pytest.fail("the node stopped")
                    assert time.monotonic() < deadline, "the node never asked"
                    await asyncio.sleep(0.05)
                await asyncio.to_thread(stack.close)  # the same server, now on the broker
                await asyncio.to_thread(stack.enter_context, running_server(
                    TOKEN, port=port, state=state, args=["--nats", nats.url]))
                await driver.post(wid, FRAME)
                deadline = time.monotonic() + 120
                while not nodes.done():  # until the nodes have drawn frame 3
                    assert time.monotonic() < deadline, "the nodes never drew"
                    await driver.post(wid, FRAME)
                    await asyncio.sleep(0.05)
                return nodes.result()

        for c in asyncio.run(scenario()):
            for s in c.tile_stats.values():
                assert s.errors == [] and s.frame[-1] >= 3, (s.tile, s.frame[-5:])


def test_auto_takes_the_newest_wall_with_no_frame_yet(server):
    """A wall an earlier run drove (it has frames) is passed over for the newest one with
    none: the one a driver has just made and waits on its nodes to drive."""
    def make() -> str:
        r = httpx.post(f"{server}/walls", json={"wall": WALL, "scene": "fatehpur"},
                       headers=AUTH, timeout=60)
        assert r.status_code == 201, r.text
        return r.json()["id"]

    fresh, driven = make(), make()
    try:
        r = httpx.post(f"{server}/walls/{driven}/frames", json={"frame": FRAME}, headers=AUTH,
                       timeout=60)
        assert r.status_code == 200, r.text
        assert asyncio.run(find_wall(server, "auto", 30))["id"] == fresh
    finally:
        for wid in (fresh, driven):
            httpx.delete(f"{server}/walls/{wid}", headers=AUTH, timeout=60)


def test_a_driver_checks_its_options_before_it_makes_a_wall(server, tmp_path):
    def walls() -> int:
        return len(httpx.get(f"{server}/walls", timeout=60).json()["walls"])

    before = walls()
    for argv, why in ((["--credentials-out", str(tmp_path / "no" / "c.json")], "no folder"),
                      (["--barrier", "--barrier-timeout", "50"], "--barrier-timeout"),
                      (["--frames", "-5"], "--frames")):
        proc = tool("wallcull_clients.driver", "--server", server, "--scene", "fatehpur",
                    "--wall", json.dumps(WALL), "--frames", "3", "--delete", *argv)
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 2 and why in err, err
    assert walls() == before


def test_credentials_are_written_for_their_owner_only(tmp_path):
    path = tmp_path / "c.json"
    path.write_text("{}")
    path.chmod(0o644)  # a file that was there: open() keeps its mode
    write_private(str(path), {"credentials": {"nodes": []}})
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert json.loads(path.read_text()) == {"credentials": {"nodes": []}}


@pytest.mark.parametrize("content, why", [
    ("[1, 2]", "holds no wall's credentials"),
    ('{"x": 1}', "holds no wall's credentials"),
    ("not json", "is not JSON"),
])
def test_a_node_refuses_a_credentials_file_that_holds_none_in_one_line(tmp_path, content, why):
    (tmp_path / "c.json").write_text(content)
    proc = tool("wallcull_clients.sim", "--server", f"http://127.0.0.1:{free_port()}",
                "--credentials", str(tmp_path / "c.json"))
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2 and why in err and err.count("\n") == 1, err


@pytest.mark.parametrize("argv, why", [
    (["--cache-bytes", "inf"], "finite"),
    (["--idle-timeout", "-5"], "--idle-timeout"),
    (["--tiles-per-node", "0"], "--tiles-per-node"),
])
def test_a_node_refuses_numbers_out_of_range(argv, why):
    proc = tool("wallcull_clients.sim", *argv)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2 and why in err and "Traceback" not in err, err


@pytest.mark.parametrize("argv, why", [
    (["--wall", "/nonexistent.json"], "--wall file not found"),
    (["--wall", str(ROOT / "examples" / "wall-cave.json")], "grid of tiles"),
    (["--out", "/nonexistent/p.png"], "no folder"),
    (["no_such_scene"], "unknown scene"),
])
def test_the_picture_refuses_in_one_line(capsys, argv, why):
    assert picture.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("picture: error:") and why in err and err.count("\n") == 1, err


@pytest.mark.parametrize("argv", [["--frame", "500"], ["--frame", "-1"], ["--pixels", "0"]])
def test_the_picture_refuses_frames_and_sizes_it_has_not(argv):
    with pytest.raises(SystemExit) as refused:
        picture.main(argv)
    assert refused.value.code == 2


def test_an_empty_token_in_the_environment_is_refused():
    """``--token ''`` is refused; so is ``WALLCULL_TOKEN=`` (it left the server open)."""
    with pytest.raises(InputError, match="WALLCULL_TOKEN is set but empty"):
        settings_from_env({"WALLCULL_TOKEN": " ", "WALLCULL_STATE": "none"})
    with pytest.raises(InputError, match="WALLCULL_LIMITS: unknown limit"):
        settings_from_env({"WALLCULL_LIMITS": "garbage", "WALLCULL_STATE": "none"})
    assert settings_from_env({"WALLCULL_STATE": "none"})["token"] is None


def test_a_cache_that_is_no_folder_is_refused_as_the_server_starts(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match="WALLCULL_CACHE .* is not a folder"):
        settings_from_env({"WALLCULL_CACHE": str(tmp_path / "file"), "WALLCULL_STATE": "none"})
    assert settings_from_env({"WALLCULL_CACHE": str(tmp_path / "new"), "WALLCULL_STATE": "none"})


@pytest.mark.parametrize("threads", ["two", "0", "-1", "1.5", " "])
def test_a_thread_count_that_is_no_count_is_refused_as_the_server_or_a_command_starts(
        threads, monkeypatch, capsys):
    with pytest.raises(InputError, match="WALLCULL_THREADS must be a whole number"):
        settings_from_env({"WALLCULL_THREADS": threads, "WALLCULL_STATE": "none"})
    monkeypatch.setenv("WALLCULL_THREADS", threads)
    assert cli.main(["scenes"]) == 2
    assert "WALLCULL_THREADS" in capsys.readouterr().err
    monkeypatch.setenv("WALLCULL_THREADS", "3")
    assert settings_from_env({"WALLCULL_THREADS": "3", "WALLCULL_STATE": "none"})


def test_the_server_and_its_clients_speak_tls(tmp_path):
    """``wallcull serve --tls-cert``: a driver and a node drive and draw a wall over https://
    and wss://, trusting the authority ``SSL_CERT_FILE`` names; a node that does not trust it
    stops at once and says so (no retrying mends a certificate)."""
    import trustme

    ca = trustme.CA()
    pem, authority, wall, report = (tmp_path / name for name in (
        "server.pem", "ca.pem", "wall.json", "node.json"))
    ca.issue_cert("127.0.0.1").private_key_and_cert_chain_pem.write_to_path(str(pem))
    ca.cert_pem.write_to_path(str(authority))
    wall.write_text(json.dumps(WALL))
    with running_server(TOKEN, args=["--tls-cert", str(pem)], ca=str(authority)) as url:
        assert url.startswith("https://")
        proc = tool("wallcull_clients.sim", "--server", url, "--reconnect-for", "600")
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 2 and "certificate is not trusted" in err, err
        assert "Traceback" not in err
        trust = {"SSL_CERT_FILE": str(authority)}
        node = tool("wallcull_clients.sim", "--server", url, "--until-frame", "4", "--quiet",
                    "--out", str(report), env=trust)
        driver = tool("wallcull_clients.driver", "--server", url, "--scene", "fatehpur",
                      "--wall", str(wall), "--frames", "5", "--rate", "0", "--wait-clients",
                      "all", "--barrier", "--barrier-timeout", "10", "--delete", env=trust)
        out, err = driver.communicate(timeout=300)
        assert driver.returncode == 0, err
        _, err = node.communicate(timeout=300)
        assert node.returncode == 0, err
    tiles = json.loads(report.read_text())["tiles"]
    assert sorted(t["tile"] for t in tiles) == [0, 1]
    assert all(t["frame"] == [0, 1, 2, 3, 4] for t in tiles), tiles


def test_serve_refuses_tls_files_it_cannot_use(tmp_path, capsys):
    (tmp_path / "x.pem").write_text("not a certificate")
    for argv, why in [(["--tls-key", "k.pem"], "--tls-key needs --tls-cert"),
                      (["--tls-cert", str(tmp_path / "none.pem")], "No such file"),
                      (["--tls-cert", str(tmp_path / "x.pem")], "cannot serve TLS")]:
        assert cli.main(["serve", "--state", "none", *argv]) == 2
        err = capsys.readouterr().err
        assert why in err and len(err.strip().splitlines()) == 1, err


def test_limits_read_sizes_in_binary_and_counts_in_decimal():
    """Every limit of bytes takes K, M and G as 1024s (``message_bytes`` and ``open_bytes``
    used to be read as counts: 64K was 64,000); counts take k and M as 1000s."""
    from wallcull.limits import Limits

    limits = Limits().with_text("message_bytes=64K,open_bytes=4M,body=1M,scene_bytes=1G,"
                                "faces=8M,nodes=250k")
    assert (limits.message_bytes, limits.open_bytes, limits.body, limits.scene_bytes) == (
        64 << 10, 4 << 20, 1 << 20, 1 << 30)
    assert (limits.faces, limits.nodes) == (8_000_000, 250_000)


@pytest.mark.parametrize("prefix", ["a b", "*", "x.>", "a.", "a..b", "p" * 65])
def test_a_nats_prefix_that_is_no_subject_prefix_is_refused_in_one_line(prefix, capsys):
    """A wildcard took every other server's subjects; spaces, empty tokens or a prefix too
    long crashed the start with a traceback, or each wall's publisher at its first frame."""
    assert cli.main(["serve", "--state", "none", "--nats", "nats://127.0.0.1:1",
                     "--nats-prefix", prefix]) == 2
    err = capsys.readouterr().err
    assert "NATS prefix" in err and len(err.strip().splitlines()) == 1, err


def _wall_drawn(server, frames: int) -> str:
    """A wall of ``WALL`` with ``frames`` frames posted (no node yet)."""
    r = httpx.post(f"{server}/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=AUTH,
                   timeout=60)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _post(server, wid) -> int:
    r = httpx.post(f"{server}/walls/{wid}/frames", json={"frame": FRAME}, headers=AUTH,
                   timeout=60)
    assert r.status_code == 200, r.text
    return r.json()["frame"]


def _post_and_wait_acks(server, wid, count):
    for _ in range(count):
        r = httpx.post(f"{server}/walls/{wid}/frames", json={"frame": FRAME}, headers=AUTH,
                       timeout=60)
        assert r.status_code == 200, r.text
        last = r.json()["frame"]
    r = httpx.get(f"{server}/walls/{wid}/barrier/{last}?timeout=10", timeout=60)
    assert r.json()["complete"], r.text  # every tile drew the last frame
    return last


def test_a_node_whose_wall_is_deleted_still_writes_what_it_drew(server, tmp_path):
    """A run that ends on a failure writes its records, marked incomplete with the reason,
    then exits 2 as before (the records were lost)."""
    wid = _wall_drawn(server, 0)
    out = tmp_path / "nodes.json"
    node = tool("wallcull_clients.sim", "--server", server, "--wall", wid, "--quiet",
                "--out", str(out))
    try:
        wait_for(lambda: httpx.get(f"{server}/walls/{wid}", timeout=60).json()["subscribers"]
                 == 2, "both nodes streaming", node)
        _post_and_wait_acks(server, wid, 3)
        httpx.delete(f"{server}/walls/{wid}", headers=AUTH, timeout=60)
        _, err = node.communicate(timeout=120)
    finally:
        node.kill()
    assert node.returncode == 2 and f"wall {wid} was deleted" in err, err
    report = json.loads(out.read_text())
    assert report["complete"] is False and "was deleted" in report["reason"]
    assert sorted(t["tile"] for t in report["tiles"]) == [0, 1]
    assert all(len(t["frame"]) == 3 for t in report["tiles"]), report["tiles"]


def test_a_node_over_nats_whose_wall_is_deleted_says_so_in_one_line():
    """Its one line came after nats-py's tracebacks (a pong for a cancelled flush, a drain's
    gathered futures never retrieved)."""
    if broker.find() is None:
        pytest.skip("no nats-server (Debian package nats-server; .ci/run installs it)")
    with broker.Broker() as nats, running_server(TOKEN, args=["--nats", nats.url]) as url:
        # 16 nodes, that find the wall gone all at once: one ended the run as others left
        # the broker (their drains cancelled)
        r = httpx.post(f"{url}/walls", json={"wall": {**WALL, "cols": 4, "rows": 4},
                                            "scene": "fatehpur"}, headers=AUTH, timeout=60)
        wid = r.json()["id"]
        node = tool("wallcull_clients.sim", "--server", url, "--wall", wid, "--nats", nats.url,
                    "--quiet")
        try:
            assert json.loads(node.stdout.readline())["ready"]  # both subscribed
            deadline = time.monotonic() + 120
            while not httpx.get(f"{url}/walls/{wid}/barrier/{_post(url, wid)}?timeout=1",
                                timeout=60).json()["complete"]:  # both drew a frame
                assert node.poll() is None and time.monotonic() < deadline, "never drawn"
            httpx.delete(f"{url}/walls/{wid}", headers=AUTH, timeout=60)
            _, err = node.communicate(timeout=120)
        finally:
            node.kill()
    assert node.returncode == 2, err
    assert err.strip().startswith("clients.sim: error: tile ") and \
        err.strip().endswith(f": wall {wid} was deleted") and len(err.splitlines()) == 1, err


def test_a_node_over_nats_cancelled_as_it_leaves_the_broker_leaves_quietly(server, caplog):
    """A NATS node's run cancelled while it drains its connection (the run ends because
    another node failed) finishes leaving the broker: its cancelled flush made nats-py print
    a pong's InvalidStateError, and its drain a gathered CancelledError never retrieved."""
    import gc

    if broker.find() is None:
        pytest.skip("no nats-server (Debian package nats-server; .ci/run installs it)")
    wid = _wall_drawn(server, 0)

    async def scenario():
        problems = []
        asyncio.get_running_loop().set_exception_handler(
            lambda loop, context: problems.append(context["message"]))
        node = NodeClient(server, wid, [0], await shared_scene(server, "fatehpur"),
                          token=TOKEN, nats=nats.url, reconnect_for=120)
        run = asyncio.create_task(node.run())
        await asyncio.wait_for(node.connected.wait(), 120)
        nc = node._nc
        run.cancel()
        while node._nc is not None:  # until it leaves the broker ...
            await asyncio.sleep(0)
        run.cancel()  # ... and the run ends meanwhile
        await asyncio.wait([run], timeout=60)
        assert run.cancelled(), "the run did not end"
        deadline = time.monotonic() + 60
        while not nc.is_closed:  # (what it left running, not awaited)
            assert time.monotonic() < deadline, "its connection was left open"
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.1)
        gc.collect()
        return problems

    with caplog.at_level(logging.WARNING), broker.Broker() as nats:
        assert asyncio.run(scenario()) == []
    assert [r.getMessage() for r in caplog.records] == []


@pytest.mark.parametrize("post", ["stream", "http"])
def test_a_driver_whose_wall_is_deleted_says_so(server, post):
    """Driving with the wall's own credential, it was told 401 "the token is not one this
    server holds" and said so, as if its token were wrong."""
    info = httpx.post(f"{server}/walls", json={"wall": WALL, "scene": "fatehpur"},
                      headers=AUTH, timeout=60).json()
    wid = info["id"]
    driver = tool("wallcull_clients.driver", "--server", server, "--wall-id", wid, "--token",
                  info["credentials"]["driver"], "--post", post, "--rate", "20", "--frames",
                  "100000")
    try:
        wait_for(lambda: httpx.get(f"{server}/walls/{wid}", timeout=60).json()["latest"] >= 0,
                 "driving", driver)
        httpx.delete(f"{server}/walls/{wid}", headers=AUTH, timeout=60)
        _, err = driver.communicate(timeout=120)
    finally:
        driver.kill()
    assert driver.returncode == 2, err
    assert err.strip() == f"clients.driver: error: wall {wid} was deleted", err


def test_a_pulling_node_whose_wall_is_deleted_says_so(server, tmp_path):
    """With its own credential it was told 401 and said that, as if its token were wrong."""
    info = httpx.post(f"{server}/walls", json={"wall": WALL, "scene": "fatehpur"},
                      headers=AUTH, timeout=60).json()
    wid = info["id"]
    write_private(tmp_path / "credentials.json", info)
    node = tool("wallcull_clients.sim", "--server", server, "--wall", wid, "--mode", "pull",
                "--credentials", str(tmp_path / "credentials.json"), "--quiet",
                env={"WALLCULL_TOKEN": ""})
    try:
        assert json.loads(node.stdout.readline())["ready"]
        _post_and_wait_acks(server, wid, 2)
        httpx.delete(f"{server}/walls/{wid}", headers=AUTH, timeout=60)
        _, err = node.communicate(timeout=120)
    finally:
        node.kill()
    assert node.returncode == 2, err
    assert re.fullmatch(rf"clients\.sim: error: tile [01]: wall {wid} was deleted", err.strip()), err


def test_a_streaming_node_whose_wall_is_missing_after_a_restart_says_so(tmp_path):
    """Its stream's handshake with its own credential was refused 401, and it said that."""
    port = free_port()
    with ExitStack() as stack:
        url = stack.enter_context(running_server(TOKEN, port=port))
        info = httpx.post(f"{url}/walls", json={"wall": WALL, "scene": "fatehpur"},
                          headers=AUTH, timeout=60).json()
        wid = info["id"]
        write_private(tmp_path / "credentials.json", info)
        node = tool("wallcull_clients.sim", "--server", url, "--wall", wid, "--credentials",
                    str(tmp_path / "credentials.json"), "--quiet", env={"WALLCULL_TOKEN": ""})
        try:
            wait_for(lambda: httpx.get(f"{url}/walls/{wid}", timeout=60).json()["subscribers"]
                     == 2, "both nodes streaming", node)
            stack.close()
            stack.enter_context(running_server(TOKEN, port=port))  # another state folder
            _, err = node.communicate(timeout=120)
        finally:
            node.kill()
    assert node.returncode == 2, err
    assert re.fullmatch(rf"clients\.sim: error: tile [01]: wall {wid} was deleted", err.strip()), err


def test_a_node_stopped_by_its_idle_timeout_says_so(server, tmp_path):
    wid = _wall_drawn(server, 0)
    node = tool("wallcull_clients.sim", "--server", server, "--wall", wid, "--quiet",
                "--idle-timeout", "2", "--out", str(tmp_path / "nodes.json"))
    try:
        wait_for(lambda: httpx.get(f"{server}/walls/{wid}", timeout=60).json()["subscribers"]
                 == 2, "both nodes streaming", node)
        last = _post_and_wait_acks(server, wid, 2)
        _, err = node.communicate(timeout=120)
    finally:
        node.kill()
        httpx.delete(f"{server}/walls/{wid}", headers=AUTH, timeout=60)
    assert node.returncode == 0, err  # a stop it was told to make, not a failure
    assert err == (f"clients.sim: stopped: no packet for 2 s (--idle-timeout) on 2 of 2 "
                   f"nodes; last frame taken {last}\n"), err
    assert json.loads((tmp_path / "nodes.json").read_text())["complete"] is True


def test_an_interrupted_command_says_so_in_one_line(monkeypatch, capsys):
    def interrupted(args):
        raise KeyboardInterrupt
    monkeypatch.setattr(cli, "cmd_scenes", interrupted)
    assert cli.main(["scenes"]) == 130
    assert capsys.readouterr().err == "wallcull: interrupted\n"
