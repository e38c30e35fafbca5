"""The browser pages in a real headless Chromium (Playwright), against a real ``wallcull serve``
on loopback with a token:

* the tile client (``/walls/{wid}/view``) opened with a node credential draws its tiles, frame
  after frame (full lists, then deltas), and acknowledges each (the barrier counts them); its
  id buffer agrees on >= 99.7 % of pixels with ``clients.render`` drawing the same tile (the
  server's matrices and list, same size), on grid tiles and on CAVE screens; a stereo frame
  draws each eye in its half of the tile; screens of different aspect keep their own, grid
  tiles apart are packed side by side, and reversed-Z clips at the far plane without
  EXT_clip_control too;
* across a restart of its server (same port, state and scene folders): the page says it
  reconnects (no error), draws leaves the driver had moved at rest again, and takes a scene
  file replaced meanwhile anew; a page refused for too many streams on its tile says so;
* the scene of those comparisons is ``blocks``, made here: 1,330 boxes and spheres on a
  lattice around the viewer, none touching. On the power plant, whose beams meet and overlap
  everywhere, which of two coincident faces wins a pixel is the rasterizer's own precision
  (SwiftShader's float depth and coarser sub-pixel grid against llvmpipe's), 0.01 to 0.25 %
  of pixels at 640 x 360 (up to 1.2 % at 320 x 180); it is checked too, at 99 %;
* the operator console (``/walls/{wid}/console``) draws one element per tile and its numbers
  follow the frames and the acknowledgements; its legend shows the plan's colours, and each
  tile leads to its view page; it draws a wall of 32,768 tiles, shows every CAVE2 screen (none
  under another), draws only the newest of the statuses that came while it was busy, greys
  while its server is down, and says why it is refused (503, too many consoles);
* the index (``/``) leads to every wall's console and view pages; a page refused (an unknown
  wall, a bad query) is a page with the status; Swagger UI renders with every request that is
  not to the server refused.

``WALLCULL_SCREENSHOT=1`` also saves the console of a 4 x 4 wall with every tile drawn by the
client as ``docs/console.png`` (the README's picture).
"""

from __future__ import annotations

import base64
import json
import os
import secrets
import shutil
from contextlib import ExitStack
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pytest

try:
    from playwright.sync_api import sync_playwright
except ImportError:  # pragma: no cover - reported as the skip reason
    sync_playwright = None

ROOT = Path(__file__).resolve().parent.parent
CHROMIUM = os.environ.get("WALLCULL_CHROMIUM") or shutil.which("chromium") or \
    shutil.which("chromium-browser") or "/usr/bin/chromium"
if sync_playwright is None:
    pytest.skip("no playwright (pip install playwright; .ci/run installs the test extras)",
                allow_module_level=True)
if not Path(CHROMIUM).exists():
    pytest.skip(f"no chromium at {CHROMIUM} (Debian package chromium; .ci/run installs it)",
                allow_module_level=True)

import httpx  # noqa: E402
import jsonschema  # noqa: E402
import websockets.sync.client  # noqa: E402

from wallcull_clients.loadtest import free_port, running_server  # noqa: E402
from wallcull_clients.sim import decode_mesh  # noqa: E402
from wallcull.server.asyncapi import schema  # noqa: E402

TOKEN = secrets.token_hex(8)
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SCENE = "powerplant"
GRID = json.loads((ROOT / "examples" / "wall-4x4.json").read_text())
CAVE = json.loads((ROOT / "examples" / "wall-cave.json").read_text())
#: Two frames of each wall: the second reaches the page as a delta against the first.
GRID_FRAMES = [{"position": [0, 30, 160], "orientation": [1, 0, 0, 0], "eye": [0, 0, 0]},
               {"position": [5, 25, 120], "orientation": [1, 0, 0, 0], "eye": [0.1, 0, 0.2]}]
CAVE_FRAMES = [{"position": [0, 8, 45], "orientation": [1, 0, 0, 0]},
               {"position": [0, 15, 50], "orientation": [0.9961946980917455, 0, 0.08715574274765817, 0]}]
AGREE = 0.997
FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run",
         "--enable-unsafe-swiftshader", "--use-angle=swiftshader"]


@pytest.fixture(scope="module")
def server():
    with running_server(TOKEN, env={"PYTHONPATH": str(ROOT)}) as url:
        yield url


@pytest.fixture(scope="module")
def http(server):
    with httpx.Client(base_url=server, timeout=60) as client:
        yield client


@pytest.fixture(scope="module")
def browser():
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def renderer_available():
    from wallcull_clients import render

    try:
        render.reversed_z_available()  # creates the shared EGL context
    except Exception as exc:  # no EGL on this machine
        pytest.skip(f"no headless OpenGL (EGL) context for clients.render: {exc}")


def blocks_glb(size: float = 1.0, more: int = 0, points: bool = False) -> bytes:
    """Boxes and spheres on a 4 m lattice around the origin (the viewer), none touching; their
    meshes named by their order whatever their ``size``; ``more`` blocks on a wall behind them
    (z = -32 m); ``points``: and a glTF primitive of points among them (node ``points``)."""
    import trimesh

    rng = np.random.default_rng(7)
    scene, k = trimesh.Scene(), 0
    shapes = [trimesh.creation.icosphere(1, 0.5 * size), trimesh.creation.box([size] * 3)]
    lattice = range(-20, 21, 4)
    behind = [(-20 + 4 * (i % 11), -20 + 4 * (i // 11), -32) for i in range(more)]
    for p in [*np.array(np.meshgrid(lattice, lattice, lattice, indexing="ij")).reshape(3, -1).T,
              *np.array(behind, float).reshape(-1, 3)]:
        if np.abs(p).max() < 4:
            continue
        m = trimesh.transformations.random_rotation_matrix(rng.random(3))
        m[:3, :3] *= rng.uniform(0.6, 1.6)
        m[:3, 3] = p + rng.uniform(-1, 1, 3)
        scene.add_geometry(shapes[k % 2], node_name=f"b{k}", geom_name=("sphere", "box")[k % 2],
                           transform=m)
        k += 1
    if points:
        cloud = rng.uniform([-6, -6, -4], [10, 6, 8], (200, 3))
        scene.add_geometry(trimesh.PointCloud(cloud), node_name="points", geom_name="points")
    return scene.export(file_type="glb")


@pytest.fixture(scope="module")
def blocks(http) -> str:
    r = http.post("/scenes?name=blocks", content=blocks_glb(),
                  headers={**AUTH, "Content-Type": "model/gltf-binary"})
    assert r.status_code == 201, r.text
    return r.json()["name"]


def create_wall(http, wall: dict, nodes=None, scene: str = SCENE, **options) -> dict:
    r = http.post("/walls", json={"wall": wall, "scene": scene, "nodes": nodes, **options},
                  headers=AUTH)
    assert r.status_code == 201, r.text
    return r.json()


def post(http, wid: str, frame: dict) -> int:
    """Post a frame (its ``updates``, if any, go beside it); its number."""
    frame = dict(frame)
    body = {"frame": frame, "updates": frame.pop("updates", {})}
    r = http.post(f"/walls/{wid}/frames", json=body, headers=AUTH)
    assert r.status_code == 200, r.text
    return r.json()["frame"]


def open_page(browser, url: str, width=1280, height=720, init: str | None = None):
    """A page at ``url``, its errors kept; ``init``: a script run before the page's own."""
    page = browser.new_page(viewport={"width": width, "height": height})
    if init is not None:
        page.add_init_script(init)
    errors = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.goto(url)
    page.wallcull_errors = errors
    return page


def wait_acked(page, number: int) -> None:
    page.wait_for_function(f"window.wallcull && window.wallcull.acked >= {number}",
                           timeout=60_000)


def browser_ids(page, tile: int) -> np.ndarray:
    out = page.evaluate(f"window.wallcull.readIds({tile}, true)")
    return np.frombuffer(base64.b64decode(out["ids"]), "<u4").reshape(out["height"],
                                                                       out["width"])


class Reference:
    """``clients.render`` drawing what the server says a tile shows: its full packet's list and
    matrices (``GET .../packets/{n}?full=true``, which acknowledges nothing), the scene's
    meshes as the mesh route serves them (those not ``double_sided`` with their back faces
    culled), leaf ``i`` drawn with id ``i + 1``."""

    def __init__(self, http, scene: str):
        from wallcull_clients.render import TileRenderer

        self.http, self.renderers, self.TileRenderer = http, {}, TileRenderer
        nodes = http.get(f"/scenes/{scene}?nodes=true").json()["nodes"]
        self.mesh, self.names = [None] * nodes["count"], [None] * nodes["count"]
        self.world = np.zeros((nodes["count"], 4, 4))
        for row, i in enumerate(nodes["id"]):  # rows by node id (clusters have none)
            self.mesh[i], self.names[i] = nodes["mesh"][row], nodes["name"][row]
            self.world[i] = np.reshape(nodes["world"][row], (4, 4))
        self.meshes = {}
        for key in sorted({k for k in self.mesh if k is not None}):
            r = http.get(f"/scenes/{scene}/meshes/{quote(key, safe='')}")
            self.meshes[key] = decode_mesh(r.json(), r.headers.get("etag"))

    def packet(self, wid: str, tile: int, number: int) -> dict:
        r = self.http.get(f"/walls/{wid}/tiles/{tile}/packets/{number}?full=true",
                          headers=AUTH)
        assert r.status_code == 200, r.text
        return r.json()

    def ids(self, pkt: dict, width: int, height: int, eye: str | None = None,
            reversed_z: bool = False) -> np.ndarray:
        if (width, height) not in self.renderers:
            renderer = self.renderers[width, height] = self.TileRenderer(width, height)
            for key, mesh in self.meshes.items():
                renderer.upload(key, mesh.vertices, mesh.faces,
                                single_sided=not mesh.double_sided)
        part = pkt if eye is None else pkt[eye]
        world = self.world.copy()
        moved = pkt.get("transforms")  # a full packet's: every moved leaf it lists
        if moved:
            world[moved["ids"]] = np.asarray(moved["matrices"], np.float64).reshape(-1, 4, 4)
        draws = [(self.mesh[leaf], world[leaf], leaf + 1) for leaf in pkt["visible"]
                 if self.mesh[leaf] is not None]
        return self.renderers[width, height].render(
            draws, part["view"], part["projection"],
            reversed_z=reversed_z).ids

    def release(self):
        for r in self.renderers.values():
            r.release()


@pytest.fixture(scope="module")
def references(http, renderer_available, blocks):
    made = {}

    def of(scene: str) -> Reference:
        if scene not in made:
            made[scene] = Reference(http, scene)
        return made[scene]

    yield of
    for ref in made.values():
        ref.release()


def agreement(a: np.ndarray, b: np.ndarray) -> float:
    assert a.shape == b.shape
    return float((a == b).mean())


def check_tile(ids: np.ndarray, want: np.ndarray, what: str, bar: float = AGREE) -> None:
    share = agreement(ids, want)
    drawn = float((want > 0).mean())
    assert drawn > 0.05, f"{what}: the reference draws almost nothing ({drawn:.1%})"
    assert len(np.unique(want)) > 5, f"{what}: too few objects to compare"
    assert share >= bar, f"{what}: the browser's ids agree on {share:.4%} of pixels only"
    print(f"{what}: {share:.4%} of pixels agree, {drawn:.0%} drawn, {len(np.unique(want))} ids")


def barrier(http, wid: str, number: int) -> dict:
    return http.get(f"/walls/{wid}/barrier/{number}?timeout=0").json()


def turn(degrees: float) -> list[float]:
    """A unit quaternion: a turn about y."""
    half = np.radians(degrees) / 2
    return [float(np.cos(half)), 0.0, float(np.sin(half)), 0.0]


def in_front(frame: dict, offset) -> list:
    """A node's matrix (rows) that puts it at ``offset`` in the display space of ``frame``."""
    w, x, y, z = frame["orientation"]
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, 3] = rotation @ np.asarray(offset, float) + frame["position"]
    return m.tolist()


#: Frames in the middle of the blocks: the second reaches the page as a delta, the third also
#: moves a block (b0, from a corner of the lattice) into the view of grid tile 5.
BLOCK_FRAMES = [{"position": [2, 2, 14], "orientation": [1, 0, 0, 0]},
                {"position": [2, -2, 10], "orientation": turn(8), "eye": [0.1, 0, 0.2]}]
BLOCK_FRAMES.append({**BLOCK_FRAMES[1], "updates": {
    "b0": {"matrix": in_front(BLOCK_FRAMES[1], [-0.9, 0.5, -6])}}})


def compare_frames(http, browser, server, references, scene, wid, frames, tiles, size, token,
                   what, bar=AGREE, query=""):
    """Open the page of ``tiles``, post ``frames`` one by one, and compare each tile's ids
    with the reference (the whole leaves of the tile's list) once the page has acknowledged
    the frame; returns the canvas size, the last frame's ids by tile, and how many leaves the
    page drew in part, by their draw ranges, over the frames (checked against the packets)."""
    w, h = size
    page = open_page(browser, f"{server}/walls/{wid}/view?token={token}&ids=1&size={w}x{h}"
                              f"{query}")
    try:
        ranged = 0
        for frame in frames:
            number = post(http, wid, frame)
            wait_acked(page, number)
            assert page.evaluate("window.wallcull.drawn") == number
            drawn, partial = {}, 0
            for tile in tiles:
                pkt = references(scene).packet(wid, tile, number)
                partial += len(pkt.get("ranges", ()))
                want = references(scene).ids(pkt, w, h)
                drawn[tile] = browser_ids(page, tile)
                check_tile(drawn[tile], want, f"{what} {tile}, frame {number}", bar)
            assert page.evaluate("window.wallcull.ranged") == partial
            ranged += partial
            state = barrier(http, wid, number)  # the page's acknowledgements, and no other
            assert state["acked"] == len(tiles) and not state["complete"]
        assert page.evaluate("window.wallcull.fulls") == 0  # every delta applied
        assert page.wallcull_errors == []
        canvas = page.evaluate("[document.getElementById('wall').width, "
                               "document.getElementById('wall').height]")
        return canvas, drawn, ranged
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


# --------------------------------------------------------------------------- the tile client


def test_grid_tiles_match_the_reference_renderer(server, http, browser, references, blocks):
    info = create_wall(http, GRID, nodes=[[5, 6]], scene=blocks)
    token = next(n["token"] for n in info["credentials"]["nodes"] if n["tiles"] == [5, 6])
    # no ?tiles=: the node credential's own, side by side in one canvas
    canvas, drawn, _ = compare_frames(http, browser, server, references, blocks, info["id"],
                                      BLOCK_FRAMES, (5, 6), (640, 360), token, "grid tile")
    assert canvas == [1280, 360]
    b0 = references(blocks).names.index("b0")
    assert (drawn[5] == b0 + 1).mean() > 0.01  # the block moved into view, where it went


def test_a_leaf_of_points_is_drawn_as_nothing(server, http, browser, references):
    """A glTF primitive of points among the blocks: the server lists its leaf, a mesh of no
    triangles, and the page draws it as nothing, as ``clients.render`` does (whose upload of
    it raised, taking its render nodes down)."""
    r = http.post("/scenes?name=blocks-points", content=blocks_glb(points=True),
                  headers={**AUTH, "Content-Type": "model/gltf-binary"})
    assert r.status_code == 201, r.text
    scene = r.json()["name"]
    info = create_wall(http, GRID, nodes=[[5, 6]], scene=scene)
    token = next(n["token"] for n in info["credentials"]["nodes"] if n["tiles"] == [5, 6])
    points = references(scene).names.index("points")
    assert len(references(scene).meshes[references(scene).mesh[points]].faces) == 0
    listed = []
    real = references(scene).packet

    def packet(wid, tile, number):  # the packets compared, and whether they list the points
        pkt = real(wid, tile, number)
        listed.append(points in pkt["visible"])
        return pkt

    references(scene).packet = packet
    compare_frames(http, browser, server, references, scene, info["id"], BLOCK_FRAMES[:2],
                   (5, 6), (640, 360), token, "grid tile")
    assert any(listed)


def test_a_page_that_lost_its_lists_asks_for_full_ones(server, http, browser, references,
                                                      blocks):
    wid = create_wall(http, GRID, scene=blocks)["id"]
    w, h = 160, 90
    page = open_page(browser, f"{server}/walls/{wid}/view?tiles=5&token={TOKEN}&ids=1"
                              f"&size={w}x{h}")
    try:
        wait_acked(page, post(http, wid, BLOCK_FRAMES[0]))
        page.evaluate("window.wallcull.forget()")
        lost = post(http, wid, BLOCK_FRAMES[1])  # a delta against frame 0, which it dropped
        page.wait_for_function("window.wallcull.fulls === 1", timeout=30_000)
        assert page.evaluate("window.wallcull.acked") < lost
        number = post(http, wid, BLOCK_FRAMES[2])  # comes as full lists
        wait_acked(page, number)
        ref = references(blocks)
        check_tile(browser_ids(page, 5), ref.ids(ref.packet(wid, 5, number), w, h),
                   "grid tile 5 after full lists", bar=AGREE)
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def stall(page, ms: int) -> None:
    """Keep the page's main thread busy for ``ms`` milliseconds, from now on (a slow page:
    it reads and acknowledges nothing meanwhile)."""
    page.evaluate(f"setTimeout(() => {{ const t = Date.now(); while (Date.now() - t < {ms}); }},"
                  " 0)")


def test_two_pages_on_overlapping_tiles_both_keep_drawing(server, http, browser, references,
                                                         blocks):
    """A second page on tiles that a first one draws (6 of 5-6) falls behind (the server
    stops sending to it: its window) while the first acknowledges frame after frame, then the
    first stalls too. Each page gets deltas against what it acknowledged itself, so neither
    meets a delta it cannot apply, and both draw the newest frame right."""
    wid = create_wall(http, GRID, scene=blocks)["id"]
    w, h = 160, 90
    first = open_page(browser, f"{server}/walls/{wid}/view?tiles=5-6&token={TOKEN}&ids=1"
                               f"&size={w}x{h}")
    second = None
    try:
        number = post(http, wid, BLOCK_FRAMES[0])
        wait_acked(first, number)
        second = open_page(browser, f"{server}/walls/{wid}/view?tiles=6&token={TOKEN}&ids=1"
                                    f"&size={w}x{h}")
        wait_acked(second, number)
        stall(second, 3000)
        for k in range(1, 16):
            if k == 15:
                stall(first, 4000)  # the first page has not acknowledged the newest frame
            number = post(http, wid, {"position": [2, 2 - 0.25 * k, 14 - 0.25 * k],
                                      "orientation": turn(k)})
            if k < 15:
                wait_acked(first, number)
        for page in (first, second):
            wait_acked(page, number)
            assert page.evaluate("window.wallcull.fulls") == 0  # every delta applied
            assert page.wallcull_errors == []
        ref = references(blocks)
        want = ref.ids(ref.packet(wid, 6, number), w, h)
        check_tile(browser_ids(first, 6), want, "tile 6 on the first page")
        check_tile(browser_ids(second, 6), want, "tile 6 on the second page")
    finally:
        for page in (first, second):
            if page is not None:
                page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_cave_screens_match_the_reference_renderer(server, http, browser, references, blocks):
    wid = create_wall(http, CAVE, scene=blocks)["id"]
    compare_frames(http, browser, server, references, blocks, wid, BLOCK_FRAMES[:2],
                   (0, 1, 4), (512, 512), TOKEN, "CAVE screen", query="&tiles=0,1,4")


def test_the_power_plant_too(server, http, browser, references):
    """A real scene, at the rasterizers' own agreement on coincident faces (module doc); its
    leaves cut into clusters, the page draws those the tiles show in part by their ranges."""
    wid = create_wall(http, GRID)["id"]
    _, _, ranged = compare_frames(http, browser, server, references, SCENE, wid, GRID_FRAMES,
                                  (5, 6), (640, 360), TOKEN, "power plant tile", bar=0.99,
                                  query="&tiles=5-6")
    assert ranged > 0


def test_stereo_eyes_side_by_side(server, http, browser, references, blocks):
    wid = create_wall(http, GRID, scene=blocks)["id"]
    frame = {**BLOCK_FRAMES[0], "stereo": {"ipd": 0.5}}  # wide apart: the halves must differ
    number = post(http, wid, frame)
    w, h = 320, 180
    page = open_page(browser, f"{server}/walls/{wid}/view?tiles=6&token={TOKEN}&ids=1"
                              f"&size={w}x{h}")
    try:
        wait_acked(page, number)
        ids = browser_ids(page, 6)
        plain = page.evaluate("window.wallcull.readIds(6)")  # the plain form: an Array
        assert np.array_equal(np.asarray(plain["ids"], np.uint32).reshape(h, w), ids)
        ref = references(blocks)
        pkt = ref.packet(wid, 6, number)
        left, right = ids[:, :w // 2], ids[:, w // 2:]
        check_tile(left, ref.ids(pkt, w // 2, h, "left"), "left eye")
        check_tile(right, ref.ids(pkt, w - w // 2, h, "right"), "right eye")
        assert agreement(left, right) < AGREE
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


#: Two screens of different aspect, side by side in front of the viewer.
SCREENS = {"screens": [
    {"bottom_left": [-1.6, -0.9, -2], "bottom_right": [1.6, -0.9, -2],
     "top_left": [-1.6, 0.9, -2], "resolution": [1920, 1080]},
    {"bottom_left": [1.6, -0.9, -2], "bottom_right": [1.6, -0.9, -1.0],
     "top_left": [1.6, 0.9, -2], "resolution": [600, 1080]}]}


def test_screens_of_different_aspect_keep_their_own(server, http, browser, references, blocks):
    """Each screen at its own resolution, one scale for all (they were all drawn at the first
    screen's size, the second one squashed 3.2 times)."""
    wid = create_wall(http, SCREENS, scene=blocks)["id"]
    page = open_page(browser, f"{server}/walls/{wid}/view?tiles=0,1&token={TOKEN}&ids=1",
                     1400, 700)
    try:
        number = post(http, wid, BLOCK_FRAMES[0])
        wait_acked(page, number)
        sizes = [page.evaluate(f"(({{width, height}}) => [width, height])"
                               f"(window.wallcull.readIds({t}, true))") for t in (0, 1)]
        for (w, h), screen in zip(sizes, SCREENS["screens"]):
            aspect = screen["resolution"][0] / screen["resolution"][1]
            assert abs(w / h - aspect) < 0.01 * aspect, (sizes, aspect)
        assert sizes[0][1] == sizes[1][1]
        canvas = page.evaluate("[document.getElementById('wall').width, "
                               "document.getElementById('wall').height]")
        assert canvas == [sizes[0][0] + sizes[1][0], sizes[0][1]]
        assert 1398 <= canvas[0] <= 1400  # as wide as the window holds
        ref = references(blocks)
        for t, (w, h) in zip((0, 1), sizes):
            check_tile(browser_ids(page, t), ref.ids(ref.packet(wid, t, number), w, h),
                       f"screen {t} at {w} x {h}")
        assert page.wallcull_errors == []
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_tiles_apart_on_the_grid_are_drawn_side_by_side(server, http, browser, blocks):
    """A node of tiles 0 and 3 of a row: two tiles side by side, filling the canvas (they were
    at their grid cells, two empty cells between them)."""
    info = create_wall(http, GRID, nodes=[[0, 3]], scene=blocks)
    wid = info["id"]
    token = next(n["token"] for n in info["credentials"]["nodes"] if n["tiles"] == [0, 3])
    page = open_page(browser, f"{server}/walls/{wid}/view?token={token}&ids=1", 1000, 300)
    try:
        wait_acked(page, post(http, wid, BLOCK_FRAMES[0]))
        w, h = page.evaluate("(({width, height}) => [width, height])"
                             "(window.wallcull.readIds(0, true))")
        assert abs(w / h - 1920 / 1080) < 0.02 and w in (499, 500)  # the window's half
        assert page.evaluate("[document.getElementById('wall').width, "
                             "document.getElementById('wall').height]") == [2 * w, h]
        # no pixel left black (the canvas's background): both tiles fill it
        black = page.evaluate("""() => {
            const wall = document.getElementById('wall'), c = document.createElement('canvas');
            [c.width, c.height] = [wall.width, wall.height];
            const g = c.getContext('2d');
            g.drawImage(wall, 0, 0);
            const px = g.getImageData(0, 0, c.width, c.height).data;
            let n = 0;
            for (let i = 0; i < px.length; i += 4) if (!px[i] && !px[i + 1] && !px[i + 2]) n++;
            return n / (c.width * c.height); }""")
        assert black == 0, f"{black:.1%} of the canvas is black"
        assert page.wallcull_errors == []
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def quads_glb() -> bytes:
    """Three 2 x 2 quads 6 m before the viewer, a sphere 3 m behind each (as seen): ``away`` single-sided
    and turned away, ``both`` double-sided and turned away, ``mirrored`` single-sided, placed
    by a mirroring matrix (x flipped: its front, wound clockwise on the image, faces the
    viewer, as glTF reads a placement of negative determinant)."""
    import trimesh

    def quad(double):
        return trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]],
                               [[0, 1, 2], [0, 2, 3]], process=False, visual=
                               trimesh.visual.TextureVisuals(material=trimesh.visual.material
                                                             .PBRMaterial(doubleSided=double)))

    scene = trimesh.Scene()
    turned = np.diag([-1.0, 1.0, -1.0, 1.0])  # half a turn about y
    for name, x, double, m in (("away", -3, False, turned), ("both", 0, True, turned),
                               ("mirrored", 3, False, np.diag([-1.0, 1.0, 1.0, 1.0]))):
        m = m.copy()
        m[:3, 3] = [x, 0, -6]
        scene.add_geometry(quad(double), node_name=name, geom_name=name, transform=m)
        at = np.eye(4)
        at[:3, 3] = [1.5 * x, 0, -9]  # (behind the quad as the viewer sees it)
        scene.add_geometry(trimesh.creation.icosphere(2, 0.8), node_name=f"{name}-behind",
                           geom_name="sphere", transform=at)
    return scene.export(file_type="glb")


def test_single_sided_meshes_are_drawn_with_their_front_faces_alone(server, http, browser,
                                                                     references):
    """The page culls the back faces of the meshes the mesh route says are not
    ``double_sided``, the front by the placement's determinant, as ``clients.render`` does:
    the single-sided quad turned away is not drawn and its sphere shows; the double-sided one
    hides its sphere; the mirrored single-sided quad faces the viewer and hides its sphere."""
    r = http.post("/scenes?name=quads", content=quads_glb(),
                  headers={**AUTH, "Content-Type": "model/gltf-binary"})
    assert r.status_code == 201, r.text
    scene = r.json()["name"]
    ref = references(scene)
    assert {k: ref.meshes[k].double_sided for k in ("away", "both", "mirrored")} == {
        "away": False, "both": True, "mirrored": False}
    one = {"cols": 1, "rows": 1, "tile_size": [1.6, 0.9], "distance": 1.0,
           "resolution": [320, 180]}
    info = create_wall(http, one, scene=scene)
    wid, token = info["id"], info["credentials"]["nodes"][0]["token"]
    page = open_page(browser, f"{server}/walls/{wid}/view?token={token}&ids=1&size=320x180")
    try:
        number = post(http, wid, {"position": [0, 0, 0], "orientation": [1, 0, 0, 0]})
        wait_acked(page, number)
        ids = browser_ids(page, 0)
        want = ref.ids(ref.packet(wid, 0, number), 320, 180)
        assert agreement(ids, want) >= AGREE
        for drawn in (ids, want):
            seen = {ref.names[i - 1] for i in np.unique(drawn) if i}
            assert seen == {"away-behind", "both", "mirrored"}, seen
        assert page.wallcull_errors == []
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


#: An init script that hides EXT_clip_control from WebGL2, as on browsers without it.
NO_CLIP_CONTROL = """(() => { const get = WebGL2RenderingContext.prototype.getExtension;
  WebGL2RenderingContext.prototype.getExtension = function (name) {
    return name === 'EXT_clip_control' ? null : get.call(this, name); }; })();"""


def test_reversed_z_without_clip_control_still_clips_at_the_far_plane(server, http, browser,
                                                                       references, blocks):
    """Without EXT_clip_control the page's reversed-Z projection is made to fill GL's [-w, w]
    clip depth: the block that straddles the far plane (9 m; the server lists no block beyond
    it) is cut by it as the reference's glClipControl cuts it (it was drawn whole: 94 % of
    pixels agreed)."""
    wid = create_wall(http, {**GRID, "far": 9.0}, scene=blocks, reversed_z=True,
                      depth="wall")["id"]
    w, h = 320, 180
    page = open_page(browser, f"{server}/walls/{wid}/view?tiles=5&token={TOKEN}&ids=1"
                              f"&size={w}x{h}", init=NO_CLIP_CONTROL)
    try:
        assert page.evaluate("document.createElement('canvas').getContext('webgl2')"
                             ".getExtension('EXT_clip_control')") is None
        number = post(http, wid, BLOCK_FRAMES[0])
        wait_acked(page, number)
        ref = references(blocks)
        pkt = ref.packet(wid, 5, number)
        assert pkt["projection"][2][2] > 0  # reversed: near -> 1, far -> 0
        ids, want = browser_ids(page, 5), ref.ids(pkt, w, h, reversed_z=True)
        assert (want > 0).mean() > 0.05  # the block, as far as the far plane
        share = agreement(ids, want)
        assert share >= AGREE, f"the page's ids agree on {share:.4%} of pixels only"
        assert page.wallcull_errors == []
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


@pytest.mark.parametrize("query, status, why", [
    ("tiles=5", 401, "token"),  # no credential
    ("tiles=5&token=wrong", 401, "token"),
    ("tiles=5&token={other}", 403, "not tiles 5"),  # a node credential of other tiles
    ("token={driver}", 422, "no tiles"),  # the driver's: it implies no tiles
])
def test_a_page_refused_its_stream_says_why_and_stops(server, http, browser, query, status,
                                                      why):
    """A browser is not shown a refused handshake's answer; the page finds out why, says
    so, and does not try again (it said "stream closed (1006)" and retried forever)."""
    info = create_wall(http, GRID)
    wid, creds = info["id"], info["credentials"]
    post(http, wid, GRID_FRAMES[0])
    query = query.format(other=creds["nodes"][0]["token"], driver=creds["driver"])
    page = open_page(browser, f"{server}/walls/{wid}/view?{query}")
    try:
        page.wait_for_function("window.wallcull && window.wallcull.refused", timeout=60_000)
        assert page.evaluate("window.wallcull.refused") == status
        note = page.locator("#status").text_content()
        assert note.startswith(f"refused ({status}):") and why in note, note
        assert page.evaluate("window.wallcull.acked") == -1
        assert barrier(http, wid, 0)["acked"] == 0
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


class Restartable:
    """``wallcull serve`` that a test stops and starts again on the same port, state folder
    and scene folder (``--scenes``), as an operator restarts it: its pages reconnect."""

    def __init__(self, folder: Path, args=()):
        self.state, self.scenes = folder / "state", folder / "scenes"
        self.scenes.mkdir(parents=True)
        self.port, self.running = free_port(), None
        self.args = ["--scenes", str(self.scenes), *args]
        self.url = f"http://127.0.0.1:{self.port}"

    def start(self) -> None:
        self.running = running_server(TOKEN, env={"PYTHONPATH": str(ROOT)}, args=self.args,
                                      port=self.port, state=str(self.state))
        self.running.__enter__()

    def stop(self) -> None:
        if self.running is not None:
            self.running.__exit__(None, None, None)
            self.running = None

    def restart(self, then=None) -> None:
        """Stop, do ``then()`` (change its files) while it is down, start again."""
        self.stop()
        try:
            if then is not None:
                then()
        finally:  # up again, whatever ``then`` raised
            self.start()


@pytest.fixture(scope="module")
def restartable(tmp_path_factory):
    """A server of its own, one stream a tile (``streams_per_tile=1``), on ``blocks.glb`` in
    its scene folder."""
    srv = Restartable(tmp_path_factory.mktemp("restartable"), ["--limit", "streams_per_tile=1"])
    (srv.scenes / "blocks.glb").write_bytes(blocks_glb())
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture
def restartable_http(restartable):
    with httpx.Client(base_url=restartable.url, timeout=60) as client:
        yield client


def test_a_restart_puts_moved_leaves_back_at_rest(restartable, restartable_http, browser,
                                                 renderer_available):
    """A restarted server has forgotten moved leaves: its full lists carry none, and the page
    draws each leaf at rest again (a leaf the driver had moved stayed where it was moved).
    The restart's closes are a plain note, not errors."""
    http, url = restartable_http, restartable.url
    wid = create_wall(http, GRID, scene="blocks.glb")["id"]
    w, h = 160, 90
    page = open_page(browser, f"{url}/walls/{wid}/view?tiles=5&token={TOKEN}&ids=1"
                              f"&size={w}x{h}")
    ref = Reference(http, "blocks.glb")
    try:
        number = post(http, wid, BLOCK_FRAMES[0])
        wait_acked(page, number)
        at_rest = ref.ids(ref.packet(wid, 5, number), w, h)
        leaf = int(np.bincount(at_rest.ravel())[1:].argmax())  # the largest leaf in view
        moved = ref.world[leaf].copy()
        moved[0, 3] += 1.5  # aside, still listed
        number = post(http, wid, {**BLOCK_FRAMES[0],
                                  "updates": {ref.names[leaf]: {"matrix": moved.tolist()}}})
        wait_acked(page, number)
        check_tile(browser_ids(page, 5), ref.ids(ref.packet(wid, 5, number), w, h),
                   f"tile 5, leaf {leaf} moved")
        restartable.restart()
        number = post(http, wid, BLOCK_FRAMES[0])  # the first frame again: all at rest
        wait_acked(page, number)
        pkt = ref.packet(wid, 5, number)
        assert leaf in pkt["visible"] and "transforms" not in pkt
        check_tile(browser_ids(page, 5), at_rest, "tile 5 after a restart")
        # the stream lost, refused while the server was down, then back: no error said
        assert page.evaluate("window.wallcull.errors") == []
        assert page.evaluate("document.getElementById('status').className") == ""
    finally:
        ref.release()
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_a_scene_file_replaced_across_a_restart_is_fetched_again(restartable,
                                                                restartable_http, browser,
                                                                renderer_available):
    """The wall's scene file is replaced while the server is down (more leaves, smaller shapes
    under the same mesh names): once its stream is back, the page fetches the scene's nodes
    and its meshes again (past the browser's cache, which keeps a mesh by its name) and draws
    the new scene (it read the new leaf ids against the old table and drew old meshes: other
    blocks in other places, or, for a leaf past the table's end, a TypeError every frame and
    no acknowledgement)."""
    http, url = restartable_http, restartable.url
    (restartable.scenes / "swap.glb").write_bytes(blocks_glb())
    wid = create_wall(http, GRID, scene="swap.glb")["id"]
    w, h = 160, 90
    page = open_page(browser, f"{url}/walls/{wid}/view?tiles=5&token={TOKEN}&ids=1"
                              f"&size={w}x{h}")
    try:
        wait_acked(page, post(http, wid, BLOCK_FRAMES[0]))
        before = len(http.get("/scenes/swap.glb?nodes=true").json()["nodes"]["mesh"])
        restartable.restart(lambda: (restartable.scenes / "swap.glb").write_bytes(
            blocks_glb(size=0.6, more=121)))
        ref = Reference(http, "swap.glb")
        try:
            assert len(ref.mesh) > before
            number = post(http, wid, BLOCK_FRAMES[0])
            wait_acked(page, number)
            check_tile(browser_ids(page, 5), ref.ids(ref.packet(wid, 5, number), w, h),
                       "tile 5 of the new scene")
        finally:
            ref.release()
        assert page.evaluate("window.wallcull.errors") == []
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_a_page_refused_for_too_many_streams_says_so(restartable, restartable_http, browser):
    """A second page on a tile that already has its one stream (``streams_per_tile=1``): the
    probe finds no reason (the wall is there, the credential good), and the page says what it
    may be and that it tries again (it said "stream closed (1006)")."""
    http, url = restartable_http, restartable.url
    wid = create_wall(http, GRID, scene="blocks.glb")["id"]
    pages = []
    try:
        for _ in range(2):
            pages.append(open_page(browser, f"{url}/walls/{wid}/view?tiles=6&token={TOKEN}"
                                            "&size=64x36"))
            if len(pages) == 1:
                wait_acked(pages[0], post(http, wid, BLOCK_FRAMES[0]))
        second = pages[1]
        second.wait_for_function("document.getElementById('status').textContent"
                                 ".includes('too many streams')", timeout=60_000)
        note = second.locator("#status").text_content()
        assert note.startswith("refused by the server") and "retrying every 2 s" in note, note
        assert second.evaluate("window.wallcull.refused") is None
        assert second.evaluate("window.wallcull.acked") == -1
    finally:
        for page in pages:
            page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_a_console_greys_while_its_server_is_down_and_says_why_it_is_refused(
        restartable, restartable_http, browser, tmp_path):
    """The server stops: the console greys its plan and table (the last state, no longer
    known) and says the server does not answer; it comes back without the wall's scene file:
    refused (503), said with the reason; the file back, the wall back: the console says the
    newest frame was handed out before the restart (it said "no frame yet" where the API
    says ``latest``)."""
    http, url = restartable_http, restartable.url
    scene = restartable.scenes / "console.glb"
    scene.write_bytes(blocks_glb())
    wid = create_wall(http, GRID, scene="console.glb")["id"]
    number = post(http, wid, BLOCK_FRAMES[0])
    console = open_page(browser, f"{url}/walls/{wid}/console")
    summary = "document.getElementById('summary').textContent"
    try:
        console.wait_for_function(f"window.wallcull && window.wallcull.status && "
                                  f"window.wallcull.status.frame === {number}", timeout=60_000)
        assert not console.evaluate("document.body.classList.contains('stale')")

        def down():
            console.wait_for_function(f"document.body.classList.contains('stale') && "
                                      f"{summary}.includes('does not answer')", timeout=60_000)
            assert console.locator("#plan").evaluate(
                "e => getComputedStyle(e).filter") == "grayscale(1)"
            scene.rename(tmp_path / "away.glb")

        restartable.restart(down)
        console.wait_for_function(f"{summary}.startsWith('refused (503)')", timeout=60_000)
        assert "console.glb" in console.locator("#summary").text_content()
        (tmp_path / "away.glb").rename(scene)
        console.wait_for_function(f"!document.body.classList.contains('stale')",
                                  timeout=60_000)
        assert http.get(f"/walls/{wid}").json()["latest"] == number
        assert console.locator("#summary").text_content() == \
            f"frame {number} before the server restarted; none since"
        # what the browser logs of the requests and streams refused, and no other error
        assert [e for e in console.wallcull_errors if not e.startswith(
            ("Failed to load resource", "WebSocket connection to"))] == []
    finally:
        console.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


# --------------------------------------------------------------------------- the console


def status_of(page) -> dict:
    return page.evaluate("window.wallcull.status")


def test_the_consoles_token_goes_with_its_links_to_view_pages(server, http, browser):
    wid = create_wall(http, GRID)["id"]
    console = open_page(browser, f"{server}/walls/{wid}/console?token={TOKEN}")
    try:
        console.wait_for_function("window.wallcull && window.wallcull.updates > 0",
                                  timeout=30_000)
        href = console.locator("#row-5 a").get_attribute("href")
        assert href.endswith(f"/walls/{wid}/view?tiles=5&token={TOKEN}"), href
    finally:
        console.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_console_follows_frames_and_acks(server, http, browser):
    info = create_wall(http, GRID)
    wid = info["id"]
    console = open_page(browser, f"{server}/walls/{wid}/console")
    view = None
    try:
        console.wait_for_function("window.wallcull && window.wallcull.updates > 0",
                                  timeout=30_000)
        assert console.locator("#plan .tile").count() == 16
        assert console.locator("#tiles tbody tr").count() == 16
        assert status_of(console)["frame"] == -1
        assert console.locator("#summary").text_content() == "no frame yet"
        first = post(http, wid, GRID_FRAMES[0])
        console.wait_for_function(f"window.wallcull.status.frame === {first}", timeout=30_000)
        counts = status_of(console)["count"]
        assert counts[5] > 0
        assert console.locator("#tile-5 .count").text_content() == \
            f"{counts[5]} {'leaf' if counts[5] == 1 else 'leaves'}"
        view = open_page(browser, f"{server}/walls/{wid}/view?tiles=5-6&token={TOKEN}"
                                  "&size=160x90")
        second = post(http, wid, GRID_FRAMES[1])
        wait_acked(view, second)
        console.wait_for_function(f"window.wallcull.status.ack[5] === {second}",
                                  timeout=30_000)
        status = status_of(console)
        jsonschema.validate(status, schema("ConsoleStatus"),
                            cls=jsonschema.Draft202012Validator)  # as the AsyncAPI says
        assert status["state"][5] == status["state"][6] == "acked"
        assert status["streams"][5] == 1 and status["streams"][0] == 0
        assert status["latency_ms"][5] is not None and status["latency_ms"][5] >= 0
        assert status["count"] != counts  # the second frame's lists
        assert "acked" in console.locator("#tile-5").get_attribute("class")
        assert console.locator("#row-5 td").nth(2).text_content() == str(second)
        # the legend names every state the tiles can be in, in the plan's own colours
        legend = console.locator("#legend li")
        assert legend.count() == 5
        for state in ("offline", "waiting", "drawing", "acked", "lagging"):
            swatch = console.locator(f"#legend .{state} .swatch")
            colour = swatch.evaluate("e => getComputedStyle(e).backgroundColor")
            assert state in console.locator(f"#legend .{state}").text_content()
            plan = console.evaluate(f"""() => {{ const p = document.querySelector(
                '#plan .tile polygon'); const g = p.parentNode; const old = g.getAttribute(
                'class'); g.setAttribute('class', 'tile {state}'); const c = getComputedStyle(
                p).fill; g.setAttribute('class', old); return c; }}""")
            assert colour == plan, (state, colour, plan)
        # each tile, on the plan and in the table, leads to its view page
        for link in (console.locator("#plan a").filter(has=console.locator("#tile-5")),
                     console.locator("#row-5 a")):
            assert link.get_attribute("href").endswith(f"/walls/{wid}/view?tiles=5")
        with console.expect_navigation():
            console.locator("#row-6 a").click()
        assert console.url.endswith(f"/walls/{wid}/view?tiles=6")
        assert console.wallcull_errors == [] and view.wallcull_errors == []
    finally:
        console.close()
        if view is not None:
            view.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_the_index_leads_to_every_wall(server, http, browser):
    info = create_wall(http, GRID, nodes=[[0, 1, 4, 5]])
    wid = info["id"]
    page = open_page(browser, f"{server}/")
    try:
        row = page.locator(f"#wall-{wid}")
        assert row.count() == 1 and "powerplant" in row.text_content()
        assert "none yet" in row.text_content()  # its frame: none posted
        views = [a.get_attribute("href") for a in row.locator("a.view, a:has-text('tiles')")
                 .all()]
        assert f"/walls/{wid}/view" in views and f"/walls/{wid}/view?tiles=0-1,4-5" in views
        with page.expect_navigation():
            row.locator("a.console").click()
        page.wait_for_function("window.wallcull && window.wallcull.updates > 0",
                               timeout=30_000)
        assert page.locator("#plan .tile").count() == 16
        with page.expect_navigation():
            page.locator("header a").click()  # back to all walls
        assert page.locator(f"#wall-{wid}").count() == 1
        assert page.wallcull_errors == []
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


@pytest.mark.parametrize("path, status, text", [
    ("/walls/0123456789ab/console", 404, "no wall '0123456789ab'"),
    ("/walls/0123456789ab/view", 404, "no wall '0123456789ab'"),
    ("/walls/not-a-wall/console", 422, "wid"),
    ("/walls/{wid}/view?tiles=0-99", 404, "not tiles of this wall"),
    ("/walls/{wid}/view?tiles=3-1", 404, "runs backwards: write it 1-3"),
    ("/walls/{wid}/view?size=huge", 422, "size"),
])
def test_a_page_refused_is_a_page(server, http, browser, path, status, text):
    wid = create_wall(http, GRID)["id"]
    page = browser.new_page()
    try:
        response = page.goto(f"{server}{path.format(wid=wid)}")
        assert response.status == status
        assert response.headers["content-type"].startswith("text/html")
        assert page.locator("h1").text_content().startswith(str(status))
        assert text in page.locator(".detail").text_content()
        with page.expect_navigation():
            page.locator("main a").click()
        assert page.url == f"{server}/" and page.locator(f"#wall-{wid}").count() == 1
    finally:
        page.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_the_api_docs_need_no_network(server, http, browser):
    """Swagger UI comes from the server (the package's copy): with every request to anywhere
    else refused, it renders every operation of the API."""
    page = browser.new_page()
    elsewhere = []

    def only_the_server(route):
        if route.request.url.startswith((server, "data:", "blob:")):
            return route.continue_()
        elsewhere.append(route.request.url)
        return route.abort()

    page.route("**/*", only_the_server)
    try:
        page.goto(f"{server}/docs")
        page.wait_for_selector("#operations-walls-createWall", timeout=60_000)
        paths = http.get("/openapi.json").json()["paths"]
        assert page.locator(".opblock").count() == sum(len(ops) for ops in paths.values())
        assert elsewhere == []
    finally:
        page.close()


@pytest.mark.parametrize("name, tiles", [("cave", 5), ("angled", 3)])
def test_console_of_screens_around_the_viewer_is_a_top_view(server, http, browser, name, tiles):
    wall = json.loads((ROOT / "examples" / f"wall-{name}.json").read_text())
    wid = create_wall(http, wall)["id"]
    console = open_page(browser, f"{server}/walls/{wid}/console")
    try:
        console.wait_for_function("window.wallcull && window.wallcull.updates > 0",
                                  timeout=30_000)
        assert console.locator("#plan .tile").count() == tiles
        assert console.locator("#plan .viewer").count() == 1  # the viewer, seen from above
        boxes = [console.locator(f"#tile-{t} polygon").bounding_box() for t in range(tiles)]
        if name == "cave":  # the floor is an area, each wall a line around it
            floor = boxes[4]
            assert floor["width"] > 100 and floor["height"] > 100
            for wall_box in boxes[:4]:
                assert min(wall_box["width"], wall_box["height"]) < 0.1 * floor["width"]
        assert console.wallcull_errors == []
    finally:
        console.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_console_of_cave2_shows_and_leads_to_every_screen(server, http, browser):
    """CAVE2's 72 screens stand in 18 columns of 4 rows: from above, each column's four
    coincide (54 screens lay hidden under others). Unrolled around the viewer, each is on top
    at its own centre, and clicking there follows its own link."""
    wall = json.loads((ROOT / "examples" / "wall-cave2.json").read_text())
    wid = create_wall(http, wall)["id"]
    console = open_page(browser, f"{server}/walls/{wid}/console", 1600, 1000)
    try:
        console.wait_for_function("window.wallcull && window.wallcull.updates > 0",
                                  timeout=30_000)
        owners = console.evaluate("""() => [...document.querySelectorAll('#plan g.tile')].map(
            (g) => { const box = g.querySelector('polygon').getBoundingClientRect();
                     const at = document.elementFromPoint(box.x + box.width / 2,
                                                          box.y + box.height / 2);
                     const owner = at && at.closest('g.tile');
                     return [Number(g.dataset.tile), owner ? Number(owner.dataset.tile) : null,
                             box.width, box.height]; })""")
        assert len(owners) == 72
        hidden = [(t, on) for t, on, _, _ in owners if on != t]
        assert hidden == [], f"{len(hidden)} screens under others: {hidden[:8]}"
        assert all(w > 10 and h > 10 for _, _, w, h in owners)  # areas, not lines
        assert console.locator("#plan .viewer").count() == 0  # not a view from above
        box = console.locator("#tile-8 polygon").bounding_box()
        with console.expect_navigation():
            console.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        assert console.url.endswith(f"/walls/{wid}/view?tiles=8")
        assert console.wallcull_errors == []
    finally:
        console.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_console_of_a_wall_past_31k_tiles_is_drawn(server, http, browser):
    """128 x 256 tiles: the plan's extent spread 4 values a tile as a call's arguments, and
    Chromium's limit (about 124,000) threw a RangeError before anything was drawn."""
    wall = {"cols": 128, "rows": 256, "tile_size": [0.05, 0.03], "gap": [0.0, 0.0],
            "distance": 2.0, "near": 0.1, "far": 1000.0, "resolution": [64, 36]}
    wid = create_wall(http, wall, history=16)["id"]
    console = open_page(browser, f"{server}/walls/{wid}/console")
    try:
        console.wait_for_function("window.wallcull && (window.wallcull.updates > 0 || "
                                  "document.getElementById('summary').textContent"
                                  ".includes('Error'))", timeout=300_000)
        assert "Error" not in console.locator("#summary").text_content()
        assert console.locator("#plan .tile").count() == 128 * 256
        assert console.locator("#tiles tbody tr").count() == 128 * 256
        assert console.wallcull_errors == []
    finally:
        console.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


#: Counts the messages every WebSocket of a page receives (``window.received``).
COUNT_MESSAGES = """window.received = 0;
window.WebSocket = class extends window.WebSocket {
  constructor(...args) {
    super(...args);
    this.addEventListener("message", () => { window.received += 1; });
  }
};"""


def test_console_draws_only_the_newest_status(server, http, browser):
    """Statuses that came while the page was busy are dropped, the newest drawn once (each was
    drawn in turn, and a 64 x 64 wall's console fell ever further behind). The page is held
    in the debugger while frames come, as a page busy drawing is."""
    wid = create_wall(http, GRID)["id"]
    console = open_page(browser, f"{server}/walls/{wid}/console", init=COUNT_MESSAGES)
    cdp = None
    try:
        console.wait_for_function("window.wallcull && window.wallcull.updates > 0",
                                  timeout=30_000)
        before = console.evaluate("[window.received, window.wallcull.updates]")
        cdp = console.context.new_cdp_session(console)
        cdp.send("Debugger.enable")
        cdp.send("Debugger.pause")
        number = None
        url = server.replace("http", "ws", 1) + f"/walls/{wid}/console/stream?token={TOKEN}"
        # a console of its own sees each status the page is sent
        with websockets.sync.client.connect(url, ping_interval=None) as watch:
            for frame in GRID_FRAMES * 3:
                number = post(http, wid, frame)
                while json.loads(watch.recv(timeout=30))["frame"] != number:
                    pass
        cdp.send("Debugger.resume")
        console.wait_for_function(f"window.wallcull.status.frame === {number}",
                                  timeout=60_000)
        console.wait_for_function(f"window.received - {before[0]} >= 6", timeout=60_000)
        received, updates = console.evaluate("[window.received, window.wallcull.updates]")
        assert updates - before[1] < received - before[0], (before, received, updates)
        assert console.wallcull_errors == []
    finally:
        if cdp is not None:
            cdp.detach()
        console.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_a_console_status_that_changes_nothing_writes_nothing(server, http, browser):
    """A status whose tiles are as the last one's touches no element of the plan or the
    table: every status rewrote all of them, and a 64 x 64 wall's console spent 0.7 s of its
    thread on each one with nothing changed."""
    wid = create_wall(http, GRID)["id"]
    post(http, wid, GRID_FRAMES[0])
    console = open_page(browser, f"{server}/walls/{wid}/console")
    tiles = ("count", "state", "ack", "latency_ms", "streams")
    try:
        console.wait_for_function("window.wallcull && window.wallcull.updates > 0",
                                  timeout=30_000)
        console.evaluate("""(tiles) => {
            window.seen = [];  // [the status's tiles, mutations since the one before]
            let mutations = 0;
            new MutationObserver((records) => { mutations += records.length; }).observe(
                document.querySelector("main"),
                {subtree: true, childList: true, characterData: true, attributes: true});
            const api = window.wallcull;
            let updates = api.updates;
            setInterval(() => {
                if (api.updates === updates) return;
                updates = api.updates;
                window.seen.push([JSON.stringify(tiles.map((k) => api.status[k])), mutations]);
                mutations = 0;
            }, 5);
        }""", list(tiles))
        # a quiet wall's statuses (a few seconds apart) until two in a row are the same
        console.wait_for_function("""() => { const s = window.seen, n = s.length;
            return n >= 2 && s[n - 1][0] === s[n - 2][0]; }""", timeout=120_000)
        seen = console.evaluate("window.seen")
        assert seen[-1][1] == 0, seen[-1][1]  # the same tiles: not one element touched
        post(http, wid, GRID_FRAMES[1])  # other lists: what changed is drawn
        console.wait_for_function(f"""() => window.seen.length > {len(seen)} &&
            window.seen[window.seen.length - 1][0] !== {json.dumps(seen[-1][0])}""",
                                  timeout=60_000)
        assert console.evaluate("window.seen[window.seen.length - 1][1]") > 0
        assert console.wallcull_errors == []
    finally:
        console.close()
        http.delete(f"/walls/{wid}", headers=AUTH)


def test_a_console_refused_for_too_many_consoles_says_so(server, http, browser):
    """Every console slot for pages without a credential taken: the page says it is refused
    and retries (it said "disconnected; reconnecting", though it never connected)."""
    wid = create_wall(http, GRID)["id"]
    url = server.replace("http", "ws", 1) + f"/walls/{wid}/console/stream"
    console = None
    with ExitStack() as held:
        for _ in range(64):
            try:
                held.enter_context(websockets.sync.client.connect(url, ping_interval=None))
            except websockets.exceptions.InvalidStatus as refused:
                assert refused.response.status_code == 429
                break
        try:
            console = open_page(browser, f"{server}/walls/{wid}/console")
            console.wait_for_function("document.getElementById('summary').textContent"
                                      ".startsWith('refused')", timeout=60_000)
            note = console.locator("#summary").text_content()
            assert "too many consoles" in note and "retrying every 2 s" in note, note
        finally:
            if console is not None:
                console.close()
            http.delete(f"/walls/{wid}", headers=AUTH)


@pytest.mark.skipif(not os.environ.get("WALLCULL_SCREENSHOT"),
                    reason="WALLCULL_SCREENSHOT=1 saves docs/console.png")
def test_console_screenshot(server, http, browser):
    info = create_wall(http, GRID, nodes=[list(range(8)), list(range(8, 16))])
    wid = info["id"]
    tokens = [n["token"] for n in info["credentials"]["nodes"]]
    post(http, wid, GRID_FRAMES[0])
    views = [open_page(browser, f"{server}/walls/{wid}/view?token={t}&size=192x108")
             for t in tokens]
    console = open_page(browser, f"{server}/walls/{wid}/console", 1280, 720)
    try:
        number = post(http, wid, GRID_FRAMES[1])
        for v in views:
            wait_acked(v, number)
        console.wait_for_function(f"window.wallcull.status.ack.every(a => a === {number})",
                                  timeout=30_000)
        console.screenshot(path=str(ROOT / "docs" / "console.png"))
    finally:
        for p in (console, *views):
            p.close()
        http.delete(f"/walls/{wid}", headers=AUTH)
