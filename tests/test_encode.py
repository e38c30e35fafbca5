"""The compiled packet encoder (wallcull.encode) against the reference: every packet decodes to
exactly the dict wallcull.protocol.packet builds, for full lists and deltas, shadows (Low-Ilie
frusta, cube maps, spot lights), mirrors and the transforms of moved leaves."""

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
            seen["mirrors"] += len(pkt.get("mirrors", []))
            for shadow in pkt.get("shadows", []):
                seen["shadows"] += 1
                seen["cube"] += shadow.get("cube", False)
    return seen


def test_packets_with_lights_and_mirrors_decode_to_the_dicts():
    settings_ = json.loads((ROOT / "examples" / "powerplant-lights3.json").read_text())
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
