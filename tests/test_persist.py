"""What survives a restart (wallcull.persist): walls in SQLite under their ids, with their
options, their credentials (as digests only) and their frame numbers; uploads in the state
folder; one server per folder. And what the scene cache lets go of."""

from __future__ import annotations

import asyncio
import sqlite3

import pytest
from fastapi.testclient import TestClient

from wallcull.errors import InputError
from wallcull.limits import Limits
from wallcull.persist import StateFolder
from wallcull.server import create_app
from wallcull.service import SceneStore, Walls
from wallcull.wall import Wall

from .test_access import FRAME, OPERATOR, TOKEN, WALL, bearer
from .test_server import boxes_glb


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
        wid = c.post("/walls", json={"wall": WALL, "scene": "two.glb"},
                     headers=OPERATOR).json()["id"]
    assert (tmp_path / "scenes" / "two.glb").read_bytes() == boxes_glb()
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.get(f"/walls/{wid}").json()["scene"] == "two.glb"
    (tmp_path / "scenes" / "two.glb").unlink()  # a wall whose scene is gone is dropped
    with TestClient(create_app(None, token=TOKEN, state=tmp_path)) as c:
        assert c.get("/walls").json()["walls"] == []
    assert sqlite3.connect(tmp_path / "walls.sqlite3").execute(
        "SELECT COUNT(*) FROM credentials").fetchone() == (0,)


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
