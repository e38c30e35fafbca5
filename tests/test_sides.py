"""Which faces a render node draws, as the server tells it: the mesh routes' ``double_sided``
(false for a glTF mesh whose material is not ``doubleSided``, ``MeshTable.single_sided``), on
a real ``wallcull serve`` over loopback, and the simulated render nodes that fetch their meshes
from it culling the back faces of those meshes (``clients.render``), losing no pixel against
the whole scene drawn so."""

from __future__ import annotations

import asyncio
import secrets
import shutil
from pathlib import Path
from urllib.parse import quote

import httpx
import msgpack
import numpy as np
import pytest
import trimesh

from wallcull.scene import load
from wallcull_clients.driver import Driver
from wallcull_clients.loadtest import kernels_loaded, running_server
from wallcull_clients.sim import decode_mesh, run_wall

ROOT = Path(__file__).resolve().parent.parent
TOKEN = secrets.token_hex(8)
AUTH = {"Authorization": f"Bearer {TOKEN}"}
MP = "application/msgpack"
GLTF = "TestScene.gltf"  # 4 of its 5 materials single-sided
WALL_2x2 = {"cols": 2, "rows": 2, "tile_size": [0.6, 0.34], "gap": [0.012, 0.012],
            "distance": 2.0}
SIZE = (160, 90)


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    scenes = tmp_path_factory.mktemp("scenes")
    for name in ("TestScene.gltf", "TestScene.bin"):
        shutil.copy(ROOT / "scenes" / name, scenes / name)
    return scenes


@pytest.fixture(scope="module")
def server(folder):
    with running_server(TOKEN, args=["--scenes", str(folder)]) as url:
        yield url


@pytest.fixture(scope="module")
def http(server):
    with httpx.Client(base_url=server, timeout=120) as client:
        yield client


def single_sided(path: str) -> dict[str, bool]:
    """Mesh key -> single-sided, as the scene loaded here (not through the server) says."""
    scene = load(path)
    return dict(zip(scene.meshes, scene.meshes.single_sided.tolist()))


def served(http, scene: str, key: str) -> tuple[dict, dict, str, str]:
    """Mesh ``key`` of ``scene`` in JSON and msgpack, and their ETags."""
    url = f"/scenes/{quote(scene, safe='')}/meshes/{quote(key, safe='')}"
    plain, packed = http.get(url), http.get(url, headers={"Accept": MP})
    assert plain.status_code == 200 and packed.status_code == 200, (plain.text, key)
    assert packed.headers["content-type"].startswith(MP)
    return (plain.json(), msgpack.unpackb(packed.content), plain.headers["etag"],
            packed.headers["etag"])


def test_the_mesh_routes_say_which_meshes_are_single_sided(http, folder):
    """``double_sided`` is false for exactly the meshes ``MeshTable.single_sided`` marks, in
    JSON and msgpack, by key and by node; the two formats keep their own ETags."""
    want = single_sided(str(folder / GLTF))
    assert 0 < sum(want.values()) < len(want)  # both kinds, or the test proves nothing
    nodes = http.get(f"/scenes/{GLTF}?nodes=true").json()["nodes"]
    assert set(k for k in nodes["mesh"] if k is not None) == set(want)
    for key, single in want.items():
        plain, packed, etag, packed_etag = served(http, GLTF, key)
        assert plain["double_sided"] is (not single), key
        assert packed["double_sided"] is (not single), key
        assert etag != packed_etag
    for row, key in enumerate(nodes["mesh"]):
        if key is not None:
            r = http.get(f"/scenes/{GLTF}/nodes/{nodes['id'][row]}/mesh")
            assert r.json()["double_sided"] is (not want[key])
            assert r.headers["etag"] == served(http, GLTF, key)[2]


def test_every_mesh_of_an_obj_scene_is_double_sided(http):
    """OBJ says nothing of sides: every mesh of the power plant is drawn with both faces."""
    keys = {k for k in http.get("/scenes/powerplant?nodes=true").json()["nodes"]["mesh"]
            if k is not None}
    assert len(keys) > 10
    for key in sorted(keys):
        plain, packed, _, _ = served(http, "powerplant", key)
        assert plain["double_sided"] is True and packed["double_sided"] is True, key


def test_a_mesh_whose_sides_change_changes_its_etag(http):
    """The same triangles, made single-sided by the file that replaces their scene: the mesh's
    answer says so under a new ETag (the answers are cached a year, immutable), in both
    formats, and the old ETag is no 304."""
    quad = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]],
                           [[0, 1, 2], [0, 2, 3]], process=False)
    seen = {}
    for double in (True, False):
        quad.visual = trimesh.visual.TextureVisuals(
            material=trimesh.visual.material.PBRMaterial(doubleSided=double))
        s = trimesh.Scene()
        s.add_geometry(quad, node_name="quad", geom_name="quad")
        r = http.post("/scenes?name=sides&replace=true", content=s.export(file_type="glb"),
                      headers={**AUTH, "Content-Type": "model/gltf-binary"})
        assert r.status_code == 201, r.text
        plain, packed, etag, packed_etag = served(http, "sides.glb", "quad")
        assert plain["double_sided"] is double and packed["double_sided"] is double
        seen[double] = plain, etag, packed_etag
    (before, *tags), (after, *new_tags) = seen[True], seen[False]
    for part in ("vertices", "faces"):
        assert before[part] == after[part]  # the same arrays
    assert set(tags).isdisjoint(new_tags)
    for tag, accept in zip(tags, ("application/json", MP)):
        r = http.get("/scenes/sides.glb/meshes/quad",
                     headers={"If-None-Match": tag, "Accept": accept})
        assert r.status_code == 200, accept


def render_or_skip():
    render = pytest.importorskip("wallcull_clients.render")
    try:
        render.reversed_z_available()
    except Exception as exc:  # noqa: BLE001 - no EGL here
        pytest.skip(f"no headless OpenGL: {exc}")
    return render


def test_render_nodes_cull_the_back_faces_the_server_marks_and_lose_no_pixel(server, http,
                                                                             folder):
    """Simulated render nodes (``--render``) of a 2 x 2 wall on the glTF scene, occlusion on,
    take ``double_sided`` from the mesh route: each tile they draw from their lists, every
    frame, equals the whole scene drawn with the back faces of the single-sided meshes culled
    (those the scene loaded here marks), with the tile's packet's matrices. Drawn with both
    faces, the flown-through scene differs (its enclosing single-sided mesh, seen from inside,
    hides everything): the nodes drew both faces of every mesh before the route said."""
    render = render_or_skip()
    frames_count = 7  # frames 0 and 6 of the fly path are inside the enclosing mesh

    async def go():
        await kernels_loaded(server)  # (a first frame otherwise waits for the compiler)
        async with Driver(server, TOKEN, timeout=120) as d:
            info = await d.call("POST", "/walls", {"wall": WALL_2x2, "scene": GLTF,
                                                   "occlusion": "on"}, auth=True)
            frames = (await d.frames(GLTF, info["wall"], "fly", 12))[:frames_count]
            made, images = [], {}

            def on_event(kind, tile, number):
                if kind == "ack":  # drawn: keep the tile's picture of the frame
                    client = next(c for c in made if c.tile == tile)
                    images[tile, number] = client.image.ids.copy()

            ready = asyncio.Event()
            task = asyncio.create_task(run_wall(
                server, info["id"], "all", mode="pull", token=TOKEN, render=True,
                render_size=SIZE, until=frames_count - 1, idle_timeout=20, made=made,
                on_event=on_event, ready=lambda clients: ready.set()))
            await asyncio.wait([task, asyncio.ensure_future(ready.wait())],
                               return_when=asyncio.FIRST_COMPLETED)
            if task.done():
                task.result()
            await d.run(info["id"], frames, rate=0, barrier=True, barrier_timeout=10)
            clients = await task
            return info, clients, images

    info, clients, images = asyncio.run(go())
    try:
        assert all(c.stats.errors == [] for c in clients)
        assert len(images) == 4 * frames_count
        single = single_sided(str(folder / GLTF))
        nodes = http.get(f"/scenes/{GLTF}?nodes=true").json()["nodes"]
        leaves = [(i, k, np.reshape(w, (4, 4))) for i, k, w in
                  zip(nodes["id"], nodes["mesh"], nodes["world"]) if k is not None]
        culled, both = render.TileRenderer(*SIZE), render.TileRenderer(*SIZE)
        for key in single:
            r = http.get(f"/scenes/{GLTF}/meshes/{quote(key, safe='')}")
            mesh = decode_mesh(r.json(), None)
            culled.upload(key, mesh.vertices, mesh.faces, single_sided=single[key])
            both.upload(key, mesh.vertices, mesh.faces)
        everything = [(k, w, i + 1) for i, k, w in leaves]
        differ = 0
        for (tile, number), ids in sorted(images.items()):
            r = http.get(f"/walls/{info['id']}/tiles/{tile}/packets/{number}?full=1",
                         headers=AUTH)
            assert r.status_code == 200, r.text
            pkt = r.json()
            view, proj = np.asarray(pkt["view"]), np.asarray(pkt["projection"])
            want = culled.render(everything, view, proj).ids
            np.testing.assert_array_equal(ids, want, err_msg=f"tile {tile}, frame {number}")
            differ += (both.render(everything, view, proj).ids != want).any()
        assert differ >= 4  # the frames inside the enclosing mesh, on every tile
        culled.release()
        both.release()
    finally:
        http.delete(f"/walls/{info['id']}", headers=AUTH)


def test_a_mesh_answer_without_double_sided_means_both_faces():
    """A server from before the field: its meshes are drawn with both faces."""
    array = {"dtype": "<f4", "shape": [0, 3], "data": b""}
    body = {"mesh": "m", "vertices": array, "faces": {**array, "dtype": "<u4"}}
    assert decode_mesh(body, None).double_sided is True
    assert decode_mesh({**body, "double_sided": False}, None).double_sided is False
