"""Digests of what ``adaptive`` lists, frame by frame, on random and real scenes over grids,
screens walls and stereo frames (``tests/test_cull_lists.py``). Written by the scalar kernel
of ``main`` at e1ba9f6; a block kernel was held to them (docs/fanout.md, the box-plane test).
A change that means to change the lists rewrites them, and says so:

    python -m tests.adaptive_lists          # rewrites tests/data/adaptive-lists.json
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from wallcull.cull import Culler
from wallcull.paths import scene_path
from wallcull.scene import Scene, SceneState, load
from wallcull.wall import Frame, Frusta, Wall

from .randscene import look_at_frame, random_scene, random_wall

DATA = Path(__file__).parent / "data" / "adaptive-lists.json"
EXAMPLES = Path(__file__).parent.parent / "examples"


def _example(name: str) -> Wall:
    return Wall.from_dict(json.loads((EXAMPLES / f"wall-{name}.json").read_text()))


def _stereo(frames, wall, ipd=0.064):
    return [Frame.make(f.position, f.orientation, f.eye, wall, (ipd, (1.0, 0.0, 0.0, 0.0)))
            for f in frames]


def cases():
    """``(name, scene, wall, frames, fine)``: the real scenes on the example walls (the
    64 x 64 frames' second runs in threads), and random scenes (some leaves cut into clusters)
    on random grids (gaps, no gaps, overlaps), in mono and stereo."""
    plant = load("powerplant")
    for wall_name, count in (("4x4", 3), ("8x8", 4), ("64x64", 2), ("cave", 3), ("cave2", 3),
                             ("angled", 3)):
        wall = _example(wall_name)
        frames = scene_path(plant, wall, "orbit", count)
        yield f"powerplant-{wall_name}", plant, wall, frames, None
    wall = _example("8x8")
    yield "powerplant-8x8-stereo", plant, wall, _stereo(scene_path(plant, wall, "orbit", 3),
                                                         wall), None
    cave = _example("cave")
    yield "powerplant-cave-stereo", plant, cave, _stereo(scene_path(plant, cave, "orbit", 2),
                                                          cave), None
    yield "powerplant-8x8-fine0", plant, wall, scene_path(plant, wall, "orbit", 2), 0.0
    yield "powerplant-8x8-fly", plant, wall, scene_path(plant, wall, "fly", 4), None
    fateh = load("fatehpur")
    yield "fatehpur-8x8-fly", fateh, wall, scene_path(fateh, wall, "fly", 3), None
    for seed in range(24):
        rng = np.random.default_rng(seed)
        scene = Scene.from_trimesh(random_scene(seed, leaves=int(rng.integers(5, 40)),
                                                flat=seed % 4 == 3, big=0.3))
        spec = random_wall(rng)
        frames = []
        for _ in range(3):
            frame = look_at_frame(rng, scene.leaf_points[0].mean(axis=0),
                                  float(rng.uniform(2, 25)), spec)
            if seed % 3 == 0:
                frame["stereo"] = {"ipd": float(rng.uniform(0.05, 0.3))}
            try:
                frames.append(Frame.from_dict(frame, Wall.from_dict(spec)))
            except Exception:  # an eye behind the wall: refused
                continue
        yield f"random-{seed}", scene, Wall.from_dict(spec), frames, (0.0 if seed % 2 else None)


def digests() -> dict[str, list]:
    """Per case, per frame: the sha256 of the tile lists (CSR) and the box-plane tests."""
    out = {}
    for name, scene, wall, frames, fine in cases():
        state = SceneState(scene)
        culler = Culler(state, wall, "adaptive") if fine is None else \
            Culler(state, wall, "adaptive", fine=fine)
        rows = []
        for frame in frames:
            vis = culler.cull(Frusta.build(wall, frame))
            h = hashlib.sha256(np.ascontiguousarray(vis.start, np.int64).tobytes()
                               + np.ascontiguousarray(vis.nodes, np.int64).tobytes())
            rows.append([h.hexdigest()[:24], int(vis.stats["tests"]), len(vis.nodes)])
        out[name] = rows
    return out


if __name__ == "__main__":
    DATA.write_text(json.dumps(digests(), indent=1) + "\n")
