"""The compiled packet encoder (wallcull.encode) against the reference: every packet decodes to
exactly the dict wallcull.protocol.packet builds, for full lists and deltas, shadows (Low-Ilie
frusta, cube maps, spot lights), mirrors and the transforms of moved leaves; every node message
(several tiles in one) to the dict wallcull.protocol.node_message builds, on grids, screens
and stereo frames."""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from numba import njit

from wallcull import encode, protocol
from wallcull.scene import Scene, load
from wallcull.service import Walls
from wallcull.wall import Wall

from .randscene import look_at_frame, random_scene

ROOT = Path(__file__).resolve().parent.parent


@njit
def _one(kind, value):
    out = np.empty(16, np.uint8)
    bits = np.empty(1)
    if kind == 0:
        end = encode._int(out, 0, np.int64(value))
    else:
        end = encode._float(out, 0, value, bits)
    return out[:end]


@settings(max_examples=300, deadline=None)
@given(st.integers(-2**63, 2**64 - 1) | st.sampled_from([0, 127, 128, 255, 256, 65535, 65536,
                                                          2**32 - 1, 2**32, -32, -33, -128,
                                                          -129, -32768, -32769, -2**31,
                                                          -2**31 - 1]))
def test_integers_take_msgpacks_shortest_form(value):
    if value >= 2**63:
        return  # beyond int64: ids and frame numbers never are
    assert _one(0, value).tobytes() == msgpack.packb(value)


@settings(deadline=None)  # the first example compiles
@given(st.floats(allow_nan=False))
def test_floats_are_float64(value):
    assert _one(1, value).tobytes() == msgpack.packb(value)


def _check_frame(session, number: int, bases) -> dict:
    """Every tile's packet of frame ``number``, full and against each of ``bases``, bytes
    against dict; returns what the packets carried (to show the test is not vacuous)."""
    seen = {"shadows": 0, "cube": 0, "mirrors": 0, "transforms": 0, "delta": 0}
    tiles = np.arange(session.wall.tiles)
    for base in [None, *bases]:
        got = encode.frame_packets(session.history, number, tiles, base)
        for t, data in zip(tiles, got):
            pkt = msgpack.unpackb(data, raw=False)
            expect = protocol.packet(session.history, number, int(t), base)
            assert pkt == expect, (number, t, base)
            seen["delta"] += pkt["base"] is not None
            seen["transforms"] += "transforms" in pkt
            seen["ranges"] = seen.get("ranges", 0) + len(pkt.get("ranges", []))
            seen["whole"] = seen.get("whole", 0) + len(pkt.get("whole", []))
            seen["mirrors"] += len(pkt.get("mirrors", []))
            for shadow in pkt.get("shadows", []):
                seen["shadows"] += 1
                seen["cube"] += shadow.get("cube", False)
        for group in _groups(len(tiles)):  # node messages: consecutive tiles, and scattered
            got = msgpack.unpackb(encode.node_message(session.history, number, group, base))
            assert got == protocol.node_message(session.history, number, group, base), \
                (number, group, base)
            seen["nodes"] = seen.get("nodes", 0) + 1
    return seen


def _groups(tiles: int) -> list[list[int]]:
    """Nodes of four consecutive tiles, a node of every tile, one of scattered tiles."""
    return [list(range(k, min(k + 4, tiles))) for k in range(0, tiles, 4)] + \
        [list(range(tiles)), sorted({0, tiles - 1, tiles // 2})]


def test_packets_with_lights_and_mirrors_decode_to_the_dicts():
    settings_ = json.loads((ROOT / "scenes" / "powerplant-lights3.json").read_text())
    scene = load("powerplant", settings=settings_)
    wall = Wall.from_dict(json.loads((ROOT / "examples" / "wall-4x4.json").read_text()))
    from wallcull.paths import scene_path

    session = Walls().create(scene, wall, "adaptive", "obb", False, 8)
    frames = scene_path(scene, wall, "orbit", 12)[::3]
    seen = {}
    for k, frame in enumerate(frames):
        number, _ = session.post_frame(frame.to_dict())
        for key, value in _check_frame(session, number, range(k)).items():
            seen[key] = seen.get(key, 0) + value
    assert seen["shadows"] and seen["cube"] and seen["mirrors"] and seen["delta"], seen
    assert seen["ranges"] and seen["whole"], seen  # leaves drawn in part, and whole again


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_packets_of_a_moving_scene_carry_the_same_transforms(seed):
    rng = np.random.default_rng(seed)
    scene = Scene.from_trimesh(random_scene(seed, leaves=14), name=f"rand{seed}")
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [0.6, 0.4], "gap": [0.02, 0.0],
                           "distance": 1.5, "far": 200.0})
    session = Walls().create(scene, wall, "adaptive", "obb", False, 6)
    movable = [n for i, n in enumerate(scene.names) if i > 0 and not scene.synthetic[i]]
    center = scene.leaf_points[0].mean(axis=0)
    transforms = 0
    for i in range(8):
        updates = {}
        for name in rng.choice(movable, size=int(rng.integers(0, 4)), replace=False):
            q = rng.normal(size=4)
            updates[str(name)] = {"position": (rng.normal(size=3) * 3).tolist(),
                                  "orientation": (q / np.linalg.norm(q)).tolist()}
        frame = look_at_frame(rng, center, float(rng.uniform(6, 20)), wall.to_dict())
        number, _ = session.post_frame(frame, updates)
        transforms += _check_frame(session, number, range(max(0, i - 3), i))["transforms"]
    assert transforms


def test_any_subset_of_tiles_in_any_order():
    scene = load("powerplant")
    wall = Wall.from_dict(json.loads((ROOT / "examples" / "wall-8x8.json").read_text()))
    from wallcull.paths import scene_path

    session = Walls().create(scene, wall, "adaptive", "obb", False, 4)
    for frame in scene_path(scene, wall, "fly", 2):
        session.post_frame(frame.to_dict())
    tiles = np.array([63, 0, 17, 17, 42])
    got = encode.frame_packets(session.history, 1, tiles, 0)
    for t, data in zip(tiles, got):
        assert msgpack.unpackb(data) == protocol.packet(session.history, 1, int(t), 0)


@pytest.mark.parametrize("wall_file, stereo", [("wall-4x4.json", True), ("wall-cave.json", False),
                                               ("wall-cave.json", True),
                                               ("wall-angled.json", False)])
def test_screens_and_stereo_packets_and_node_messages(wall_file, stereo):
    settings_ = json.loads((ROOT / "scenes" / "powerplant-lights.json").read_text())
    scene = load("powerplant", settings=settings_)
    wall = Wall.from_dict(json.loads((ROOT / "examples" / wall_file).read_text()))
    from wallcull.fit import FitOptions
    from wallcull.paths import scene_path

    session = Walls().create(scene, wall, "adaptive", "obb", False, 8,
                             FitOptions(reversed_z=stereo))
    seen = {}
    for k, frame in enumerate(scene_path(scene, wall, "orbit", 12)[::4]):
        spec = frame.to_dict()
        if stereo:
            spec["stereo"] = {"ipd": 0.064}
        number, _ = session.post_frame(spec)
        for key, value in _check_frame(session, number, range(k)).items():
            seen[key] = seen.get(key, 0) + value
    assert seen["delta"] and seen["nodes"], seen


@pytest.mark.parametrize("wall_file, stereo, reversed_z", [
    ("wall-64x64.json", False, False), ("wall-8x8.json", True, True),
    ("wall-cave2.json", False, True), ("wall-cave.json", True, False)])
def test_a_node_rebuilds_the_servers_matrices_from_the_extents(wall_file, stereo, reversed_z):
    """clients.frusta turns node messages (full, then deltas that leave out extents that did
    not change) back into every tile's view and projection, and each eye's: equal to the
    server's fits within 1e-6 of the matrix's largest entry."""
    from wallcull_clients.frusta import Frusta
    from wallcull.fit import FitOptions
    from wallcull.paths import scene_path

    scene = load("powerplant")
    wall = Wall.from_dict(json.loads((ROOT / "examples" / wall_file).read_text()))
    session = Walls().create(scene, wall, "adaptive", "obb", False, 4,
                             FitOptions(reversed_z=reversed_z))
    node, checked, left_out = Frusta(), 0, 0
    for k, frame in enumerate(scene_path(scene, wall, "fly", 8)[::3]):
        spec = frame.to_dict()
        if stereo:
            spec["stereo"] = {"ipd": 0.064,
                              "head": [0.98, 0.0, float(np.sqrt(1 - 0.98 ** 2)), 0.0]}
        number, _ = session.post_frame(spec)
        message = msgpack.unpackb(encode.node_message(session.history, number,
                                                      range(wall.tiles), number - 1 if k else None))
        left_out += sum("extent" not in e for e in message["tiles"])
        fits = session.history.get(number).fits
        for tile, got in node.take(message).items():
            want = fits[tile]
            for part in (["left", "right"] if stereo else []) + [None]:
                g, w = (got, want) if part is None else (got[part], want[part])
                for key in ("view", "projection"):
                    w_m = np.asarray(w[key])
                    assert np.abs(g[key] - w_m).max() <= 1e-6 * np.abs(w_m).max(), \
                        (tile, part, key)
                assert (g["near"], g["far"]) == (w["near"], w["far"])
                checked += 1
    assert checked >= 3 * wall.tiles and left_out, (checked, left_out)


def test_a_node_tells_what_its_deltas_would_have_cost_as_full_lists():
    """clients.node.full_size: exactly the bytes of the server's full message of the frame."""
    from wallcull_clients.node import NodeState, full_size
    from wallcull.fit import FitOptions
    from wallcull.paths import scene_path

    scene = load("powerplant")
    for wall_file, stereo in (("wall-8x8.json", False), ("wall-cave.json", True)):
        wall = Wall.from_dict(json.loads((ROOT / "examples" / wall_file).read_text()))
        session = Walls().create(scene, wall, "adaptive", "obb", False, 4, FitOptions())
        tiles = list(range(min(wall.tiles, 6)))
        node, deltas = NodeState(), 0
        for k, frame in enumerate(scene_path(scene, wall, "orbit", 40)[:6]):
            spec = frame.to_dict() | ({"stereo": {"ipd": 0.06}} if stereo else {})
            number, _ = session.post_frame(spec)
            raw = encode.node_message(session.history, number, tiles, number - 1 if k else None)
            message = msgpack.unpackb(raw)
            frames = node.take(message)
            whole = encode.node_message(session.history, number, tiles, None)
            assert full_size(message, len(raw), frames, node.frusta.held[number]) == len(whole)
            deltas += message["base"] is not None
        assert deltas == 5


def test_a_delta_leaves_out_the_tiles_with_nothing_new():
    """On a big wall most tiles keep their list, extent and depth from one frame to the next
    (empty ones above all): a delta leaves them out, and a node keeps the base's, so that
    every tile's list and matrices are still those of the full message."""
    from wallcull_clients.node import NodeState
    from wallcull.fit import FitOptions
    from wallcull.paths import scene_path

    scene = load("powerplant")
    wall = Wall.from_dict(json.loads((ROOT / "examples" / "wall-16x16.json").read_text()))
    session = Walls().create(scene, wall, "adaptive", "obb", False, 4, FitOptions())
    tiles = np.arange(wall.tiles)
    node, left_out = NodeState(), 0
    for k, frame in enumerate(scene_path(scene, wall, "orbit", 600)[:5]):
        number, _ = session.post_frame(frame.to_dict())
        message = msgpack.unpackb(encode.node_message(session.history, number, tiles,
                                                      number - 1 if k else None))
        assert message == protocol.node_message(session.history, number, tiles,
                                                number - 1 if k else None)
        left_out += wall.tiles - len(message["tiles"])
        whole = NodeState().take(msgpack.unpackb(encode.node_message(session.history, number,
                                                                     tiles, None)))
        got = node.take(message)
        assert [f.tile for f in got] == tiles.tolist()
        for g, w in zip(got, whole):
            assert g.leaves.tolist() == w.leaves.tolist()
            for key in ("view", "projection"):
                np.testing.assert_array_equal(g.matrices[key], w.matrices[key])
    assert left_out > 4 * wall.tiles // 2  # most of every delta's tiles
