"""What survives a restart (wallcull.persist): walls in SQLite under their ids, with their
options, their credentials (as digests only) and their frame numbers; uploads in the state
folder; one server per folder. And what the scene cache lets go of."""

from __future__ import annotations

import asyncio
import errno
import json
import os
import sqlite3
import subprocess
import sys
import time

import pytest
from fastapi.testclient import TestClient

from wallcull.errors import InputError
from wallcull.limits import Limits
from wallcull.persist import StateFolder
from wallcull.server import create_app
from wallcull.scene import load
from wallcull.service import FrameNumbers, SceneStore, Walls
from wallcull.wall import Wall

from .test_access import FRAME, OPERATOR, TOKEN, WALL, bearer
from .test_server import assert_documented, boxes_glb


def test_walls_come_back_after_a_restart(tmp_path):
    spec = {"wall": {**WALL, "gap": [0.01, -0.02]}, "scene": "fatehpur", "method": "oh",
            "bounds": "aabb", "history": 8, "depth": "wall", "reversed_z": True}
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        info = c.post("/walls", json=spec, headers=OPERATOR).json()
        driver = bearer(info["credentials"]["driver"])
        node0 = bearer(info["credentials"]["nodes"][0]["token"])
        for _ in range(5):
            c.post(f"/walls/{info['id']}/frames", json={"frame": FRAME}, headers=driver)
        before = c.get(f"/walls/{info['id']}").json()
        gone = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=OPERATOR)
        assert c.delete(f"/walls/{gone.json()['id']}", headers=OPERATOR).status_code == 204
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert [w["id"] for w in c.get("/walls").json()["walls"]] == [info["id"]]
        after = c.get(f"/walls/{info['id']}").json()
        assert after == before and after["latest"] == 4 and after["method"] == "oh"
        # the console says so too: frame 4 was the newest handed out, none held since
        with c.websocket_connect(f"/walls/{info['id']}/console/stream",
                                 headers=OPERATOR) as ws:
            status = json.loads(ws.receive_text())
        assert status["newest"] == 4 and status["frame"] == -1
        # the same credentials; numbers go on after the last one handed out
        r = c.post(f"/walls/{info['id']}/frames", json={"frame": FRAME}, headers=driver)
        assert r.status_code == 200 and r.json()["frame"] == 5
        r = c.post(f"/walls/{info['id']}/frames", json={"frame": FRAME, "number": 5},
                   headers=driver)
        assert r.status_code == 409
        pkt = c.get(f"/walls/{info['id']}/tiles/0/packets/latest", headers=node0).json()
        assert pkt["frame"] == 5 and pkt["base"] is None  # a full list after the restart
        assert pkt["projection"][2][2] != pytest.approx(-1.0)  # reversed-Z survived
        r = c.get(f"/walls/{info['id']}/tiles/0/packets/4", headers=node0)
        assert r.status_code == 410  # frames themselves do not survive: nodes get full lists
        assert c.get(f"/walls/{info['id']}/tiles/1/packets/5", headers=node0).status_code == 403


def test_frame_numbers_are_written_ahead_and_exactly_at_a_clean_stop(tmp_path, monkeypatch):
    """One write for every ``AHEAD`` frames, never below a number handed out; a clean stop
    writes the last number handed out, a kill leaves the one written ahead: after either,
    numbers go on above every number handed out."""
    monkeypatch.setattr(FrameNumbers, "AHEAD", 4)
    folder = StateFolder(tmp_path)
    writes = []
    set_last_frame = folder.set_last_frame
    monkeypatch.setattr(folder, "set_last_frame",
                        lambda wid, n: (writes.append(n), set_last_frame(wid, n)))

    def on_disk():
        with sqlite3.connect(tmp_path / "walls.sqlite3") as db:
            return db.execute("SELECT last_frame FROM walls").fetchone()[0]

    walls = Walls(state=folder)
    session = walls.create(load("fatehpur"), Wall.from_dict(WALL), "adaptive", "obb", False, 8)
    for number in range(11):
        record, _ = session.compute_frame(FRAME)
        assert record.number == number and on_disk() >= number
        session.publish(record)
    assert writes == [4, 9, 14] and on_disk() == 14
    folder.close()  # killed: what was written ahead stays
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.get(f"/walls/{session.id}").json()["latest"] == 14
        again = c.app.state.server.walls.get(session.id)
        record, _ = again.compute_frame(FRAME)
        again.publish(record)
        assert record.number == 15 and on_disk() == 15 + 4
    assert on_disk() == 15  # a clean stop: the last number handed out
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.get(f"/walls/{session.id}").json()["latest"] == 15


def test_only_digests_of_credentials_are_at_rest(tmp_path):
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        info = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"},
                      headers=OPERATOR).json()
    tokens = [info["credentials"]["driver"], TOKEN,
              *(n["token"] for n in info["credentials"]["nodes"])]
    for path in tmp_path.rglob("*"):
        if path.is_file():
            data = path.read_bytes()
            assert not any(t.encode() in data for t in tokens), path
    rows = sqlite3.connect(tmp_path / "walls.sqlite3").execute(
        "SELECT digest, role, tiles FROM credentials").fetchall()
    assert len(rows) == 5 and all(len(d) == 64 for d, _, _ in rows)


def test_uploads_and_the_walls_on_them_survive(tmp_path):
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.post("/scenes?name=two", content=boxes_glb(), headers=OPERATOR).status_code == 201
        info = c.post("/walls", json={"wall": WALL, "scene": "two.glb"}, headers=OPERATOR).json()
        wid = info["id"]
    assert (tmp_path / "scenes" / "two.glb").read_bytes() == boxes_glb()
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.get(f"/walls/{wid}").json()["scene"] == "two.glb"
    (tmp_path / "scenes" / "two.glb").unlink()
    driver = bearer(info["credentials"]["driver"])
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        # the wall whose scene is gone stays, unavailable (503: retry), and health says why
        r = c.get(f"/walls/{wid}")
        assert r.status_code == 503 and "two.glb" in r.json()["detail"], r.text
        assert r.headers["retry-after"]
        node = bearer(info["credentials"]["nodes"][0]["token"])
        for r in (r, c.post(f"/walls/{wid}/frames", json={"frame": FRAME}, headers=driver),
                  c.get(f"/walls/{wid}/tiles/0/packets/latest", headers=node),
                  c.post(f"/walls/{wid}/tiles/0/ack", json={"frame": 0}, headers=node),
                  c.get(f"/walls/{wid}/barrier/0?timeout=0"),
                  c.get(f"/walls/{wid}/view"), c.get(f"/walls/{wid}/console")):
            assert r.status_code == 503, (r.request.url, r.text)
            assert_documented(c, r)  # (and so does the document)
        health = c.get("/health").json()
        assert health["status"] == "degraded" and health["walls_unavailable"] == [wid]
        assert "wallcull_walls_unavailable 1.0" in c.get("/metrics").text
        assert c.post(f"/walls/{wid}/frames", json={"frame": FRAME},
                      headers=driver).status_code == 503  # its credentials still hold
        for page in ("view", "console"):  # its pages are pages that say so
            r = c.get(f"/walls/{wid}/{page}")
            assert r.status_code == 503 and r.headers["content-type"].startswith("text/html")
            assert "two.glb" in r.text and "Service Unavailable" in r.text
            # it loads itself again (it stayed an error after the wall came back)
            assert '<meta http-equiv="refresh" content="5">' in r.text
            assert r.headers["retry-after"] == "5"
        row = c.get("/").text.split(f'id="wall-{wid}"')[1].split("</tr>")[0]
        assert "unavailable" in row and "two.glb" in row  # the index lists it, and why
        # the scene comes back (uploaded again): so does the wall, with its credentials
        assert c.post("/scenes?name=two", content=boxes_glb(),
                      headers=OPERATOR).status_code == 201
        assert c.get(f"/walls/{wid}").status_code == 200
        assert c.post(f"/walls/{wid}/frames", json={"frame": FRAME},
                      headers=driver).status_code == 200
        assert c.get("/health").json()["status"] == "ok"
    assert sqlite3.connect(tmp_path / "walls.sqlite3").execute(
        "SELECT COUNT(*) FROM credentials").fetchone() == (5,)


def test_a_wall_comes_back_when_its_scene_file_does(tmp_path, monkeypatch):
    """The file put back by hand (not uploaded): the server finds it on its own."""
    import wallcull.server as srv

    monkeypatch.setattr(srv, "RETRY_PERIOD", 0.05)
    scenes = tmp_path / "scenes"
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.post("/scenes?name=two", content=boxes_glb(), headers=OPERATOR).status_code == 201
        wid = c.post("/walls", json={"wall": WALL, "scene": "two.glb"},
                     headers=OPERATOR).json()["id"]
    (scenes / "two.glb").rename(tmp_path / "away.glb")
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.get(f"/walls/{wid}").status_code == 503
        assert c.delete(f"/walls/{wid}", headers=OPERATOR).status_code != 500
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.get(f"/walls/{wid}").status_code == 404  # deleted while unavailable: gone
        c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=OPERATOR)
    (tmp_path / "away.glb").rename(scenes / "two.glb")
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert [w["scene"] for w in c.get("/walls").json()["walls"]] == ["fatehpur"]
    # and one that was unavailable at start comes back by itself once the file is there
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        wid = c.post("/walls", json={"wall": WALL, "scene": "two.glb"},
                     headers=OPERATOR).json()["id"]
    (scenes / "two.glb").rename(tmp_path / "away.glb")
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.get(f"/walls/{wid}").status_code == 503
        (tmp_path / "away.glb").rename(scenes / "two.glb")
        deadline = time.monotonic() + 60
        while c.get(f"/walls/{wid}").status_code != 200:
            assert time.monotonic() < deadline, c.get("/health").json()
            time.sleep(0.05)


def _damaged(tmp_path, damage) -> str:
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=OPERATOR)
    db = tmp_path / "walls.sqlite3"
    damage(db)
    before = db.read_bytes()
    with pytest.raises(InputError) as exc:
        create_app(None, token=TOKEN, state=tmp_path)
    assert db.read_bytes() == before  # never written to: kept for inspection
    message = str(exc.value)
    assert str(db) in message and "\n" not in message and "move" in message
    StateFolder(tmp_path / "other").close()
    return message


def test_a_truncated_state_database_is_refused_naming_it(tmp_path):
    def truncate(db):
        data = db.read_bytes()
        db.write_bytes(data[:len(data) // 2 + 100])
    assert "cannot be used" in _damaged(tmp_path, truncate)


def test_a_state_database_that_is_not_one_is_refused_naming_it(tmp_path):
    assert "not a database" in _damaged(tmp_path, lambda db: db.write_bytes(b"x" * 8192))


def test_a_wall_spec_that_is_not_json_is_refused_naming_the_wall(tmp_path):
    def garble(db):
        with sqlite3.connect(db) as con:
            con.execute("UPDATE walls SET spec = '{\"wall\": [1, 2'")
        con.close()
    assert "spec" in _damaged(tmp_path, garble)


def test_a_wall_spec_this_server_cannot_read_is_refused(tmp_path):
    def garble(db):
        with sqlite3.connect(db) as con:
            con.execute("""UPDATE walls SET spec = json_set(spec, '$.wall.cols', -3)""")
        con.close()
    assert "cols" in _damaged(tmp_path, garble)


def test_the_cli_says_it_in_one_line_with_status_2(tmp_path):
    (tmp_path / "walls.sqlite3").write_bytes(b"SQLite format 3\0" + b"\xff" * 4000)
    proc = subprocess.run([sys.executable, "-m", "wallcull.cli", "serve", "--state",
                           str(tmp_path), "--port", "1"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and "walls.sqlite3" in proc.stderr, proc.stderr


@pytest.mark.parametrize("pragma, status", [("max_page_count", 507), ("query_only", 503)])
def test_failed_state_writes_are_507_or_503_and_frames_stop_where_numbers_are_written(
        tmp_path, monkeypatch, pragma, status):
    """A full disk (SQLite's page limit stands in for it) or a read-only database: writes
    are refused with the reason, health and metrics say so; frames whose numbers are written
    down go on, the next is refused (served, its number could be handed out again after a
    restart); all is well again once writes succeed."""
    monkeypatch.setattr(FrameNumbers, "AHEAD", 4)
    app = create_app(None, token=TOKEN, state=tmp_path)
    with TestClient(app) as c:
        info = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=OPERATOR).json()
        driver = bearer(info["credentials"]["driver"])
        node0 = bearer(info["credentials"]["nodes"][0]["token"])
        frames = f"/walls/{info['id']}/frames"
        assert c.post(frames, json={"frame": FRAME}, headers=driver).json()["frame"] == 0
        db = app.state.server.walls.state._db
        pages = db.execute("PRAGMA page_count").fetchone()[0]
        db.execute(f"PRAGMA {pragma} = {pages if pragma == 'max_page_count' else 1}")
        r = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=OPERATOR)
        if pragma == "max_page_count" and r.status_code == 201:  # the page had room left
            for _ in range(50):
                r = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=OPERATOR)
                if r.status_code != 201:
                    break
        assert r.status_code == status, r.text
        assert "walls.sqlite3" in r.json()["detail"]
        assert_documented(c, r)
        health = c.get("/health").json()
        assert health["status"] == "degraded" and "walls.sqlite3" in health["problems"][0]
        assert "wallcull_state_write_failing 1.0" in c.get("/metrics").text
        for number in range(1, 5):  # written down up to 4: culled and served
            assert c.post(frames, json={"frame": FRAME}, headers=driver).json()["frame"] == number
        r = c.post(frames, json={"frame": FRAME}, headers=driver)
        if pragma == "query_only":  # (the page limit still takes a number in its page)
            assert r.status_code == status and "walls.sqlite3" in r.json()["detail"], r.text
            assert_documented(c, r)
            assert c.get(f"/walls/{info['id']}/tiles/0/packets/latest",
                         headers=node0).json()["frame"] == 4
        if pragma == "query_only":  # (a full disk still lets a wall be deleted)
            walls = len(c.get("/walls").json()["walls"])
            r = c.delete(f"/walls/{info['id']}", headers=OPERATOR)
            assert r.status_code == status
            assert_documented(c, r)
            assert len(c.get("/walls").json()["walls"]) == walls  # a failed delete keeps it
        db.execute("PRAGMA max_page_count = 1000000" if pragma == "max_page_count"
                   else "PRAGMA query_only = 0")
        assert c.post(frames, json={"frame": FRAME}, headers=driver).status_code == 200
        assert c.delete(f"/walls/{info['id']}", headers=OPERATOR).status_code == 204
        assert c.get("/health").json()["status"] == "ok"


@pytest.mark.parametrize("how", ["deleted", "moved", "lock deleted"])
def test_a_state_folder_taken_away_while_the_server_runs_is_written_no_more(
        tmp_path, monkeypatch, how):
    """Its folder deleted or moved, or its lock deleted (a second server could then take the
    folder), a server went on answering 201 to new walls it could never bring back, and its
    clean stop could write a frame number below one the other server handed out. Now every
    write is refused, and frames beyond the numbers written down; health says why."""
    import shutil

    monkeypatch.setattr(FrameNumbers, "AHEAD", 4)
    folder = tmp_path / "state"
    app = create_app(None, token=TOKEN, state=folder)
    with TestClient(app) as c:
        info = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=OPERATOR).json()
        driver = bearer(info["credentials"]["driver"])
        frames = f"/walls/{info['id']}/frames"
        assert c.post(frames, json={"frame": FRAME}, headers=driver).json()["frame"] == 0
        if how == "deleted":
            shutil.rmtree(folder)
        elif how == "moved":
            folder.rename(tmp_path / "elsewhere")
        else:
            (folder / "lock").unlink()
            other = StateFolder(folder)  # a second server may now take the folder
        r = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=OPERATOR)
        assert r.status_code == 503 and "moved, deleted or replaced" in r.json()["detail"]
        health = c.get("/health").json()
        assert health["status"] == "degraded" and "moved, deleted" in health["problems"][0]
        for number in range(1, 5):
            assert c.post(frames, json={"frame": FRAME}, headers=driver).json()["frame"] == number
        assert c.post(frames, json={"frame": FRAME}, headers=driver).status_code == 503
    if how == "lock deleted":  # the clean stop wrote nothing below what is on disk
        assert [r.last_frame for r in other.walls()] == [4]
        other.close()


def test_idle_walls_expire_with_wall_ttl_and_not_without(tmp_path, monkeypatch):
    import wallcull.server as srv

    monkeypatch.setattr(srv, "RETRY_PERIOD", 0.05)
    # a TTL far above a frame's round trip, even on a loaded machine
    with TestClient(create_app(None, token=TOKEN, state=tmp_path, wall_ttl=3.0)) as c:
        info = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}, headers=OPERATOR).json()
        driver = bearer(info["credentials"]["driver"])
        t0 = time.monotonic()
        while time.monotonic() - t0 < 4.0:  # kept while frames come
            assert c.post(f"/walls/{info['id']}/frames", json={"frame": FRAME},
                          headers=driver).status_code == 200
            time.sleep(0.05)
        deadline = time.monotonic() + 60
        while c.get(f"/walls/{info['id']}").status_code != 404:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert "wallcull_walls_expired_total 1.0" in c.get("/metrics").text
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.get("/walls").json()["walls"] == []  # gone from the state folder too
        wid = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"},
                     headers=OPERATOR).json()["id"]
        time.sleep(3.5)
        assert c.get(f"/walls/{wid}").status_code == 200  # off by default


def test_one_server_per_state_folder(tmp_path):
    first = StateFolder(tmp_path)
    with pytest.raises(InputError, match="in use by another"):
        StateFolder(tmp_path)
    first.close()
    StateFolder(tmp_path).close()  # free again once the first let go


def test_the_scene_cache_keeps_walls_scenes_and_evicts_the_rest():
    walls = Walls()
    store = SceneStore(None, Limits(scene_cache=1), in_use=walls.scene_names)

    async def go():
        fatehpur = await store.get("fatehpur")
        walls.create(fatehpur, Wall.from_dict(WALL), "adaptive", "obb", False, 8)
        plant = await store.get("powerplant")  # over budget, but whoever asked gets it
        assert list(store.cache) == ["fatehpur", "powerplant"]
        assert await store.get("fatehpur") is fatehpur  # the wall's stays, the same object
        assert store.evict() == ["powerplant"]  # nobody uses it
        assert await store.get("powerplant") is not plant  # loaded again
        walls.delete(next(iter(walls.sessions)))
        assert store.evict() == ["fatehpur", "powerplant"] and not store.cache

    asyncio.run(go())


@pytest.mark.parametrize("code, status", [(errno.ENOSPC, 507), (errno.EROFS, 503)])
def test_an_upload_the_scene_folder_cannot_take_is_507_or_503(tmp_path, monkeypatch, code,
                                                              status):
    def cannot(self):
        raise OSError(code, os.strerror(code))

    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        monkeypatch.setattr(SceneStore, "spool", cannot)
        r = c.post("/scenes?name=two", content=boxes_glb(), headers=OPERATOR)
        assert r.status_code == status and os.strerror(code) in r.json()["detail"], r.text
        assert_documented(c, r)
        monkeypatch.undo()
        assert c.post("/scenes?name=two", content=boxes_glb(),
                      headers=OPERATOR).status_code == 201  # the name was let go
