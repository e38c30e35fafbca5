"""Compile every numba kernel once, so that no client waits for a compiler.

The kernels are compiled with ``cache=True``: the first process to use one writes it to
numba's cache (a folder keyed by the kernel modules' digest: see ``wallcull._kernel_cache``),
and every later process loads it in milliseconds. :func:`culling` runs what a
mono frame on a grid needs; :func:`the_rest` runs stereo, screens walls, shadow and mirror
frusta and the packet encoders. The server runs both in a worker thread as it starts. ``python -m wallcull.warm`` runs both: the Dockerfile does
at image build, so that a fresh container answers its health check in seconds rather than
after minutes of compiling.
"""

from __future__ import annotations

import sys
import time

#: Lights (a far sun, a lamp inside the scene: a cube map) and a mirror, for the fit kernels.
SETTINGS = {
    "lights": [{"name": "sun", "position": [40, 60, 30]},
               {"name": "lamp", "type": "spot", "position": [1, 0.5, -5],
                "direction": [0, -1, 0], "angle": 35},
               {"name": "bulb", "position": [1, 0, -5]}],
    "mirrors": [{"name": "floor", "point": [0, -0.6, 0], "normal": [0, 1, 0],
                 "polygon": [[-20, -0.6, -20], [20, -0.6, -20], [20, -0.6, 20],
                             [-20, -0.6, 20]]}]}
GRID = {"cols": 2, "rows": 2, "tile_size": [1, 1], "distance": 1}
SCREENS = {"screens": [
    {"bottom_left": [-1, -1, -1], "bottom_right": [1, -1, -1], "top_left": [-1, 1, -1]},
    {"bottom_left": [-1, -1, 1], "bottom_right": [-1, -1, -1], "top_left": [-1, 1, 1]},
    {"bottom_left": [1, -1, -1], "bottom_right": [1, -1, 1], "top_left": [1, 1, -1]}],
    "near": 0.05, "far": 100}
MONO = {"position": [0, 0, 0], "orientation": [1, 0, 0, 0]}
STEREO = {**MONO, "stereo": {"ipd": 0.064}}


def _scene():
    import numpy as np
    import trimesh

    from .scene import Scene

    scene = trimesh.Scene()
    for k in range(3):
        m = np.eye(4)
        m[:3, 3] = [k, 0, -5]
        scene.add_geometry(trimesh.creation.box(), node_name=f"b{k}", transform=m)
    return Scene.from_trimesh(scene)


def culling() -> None:
    """Every traversal, with and without pseudo-groups, on a mono frame of a grid."""
    from .cull import METHODS
    from .pipeline import Session
    from .wall import Wall

    scene, wall = _scene(), Wall.from_dict(GRID)
    for method in METHODS:
        for pseudo in (False, True):
            Session(scene, wall, method, pseudo_groups=pseudo).frame(MONO)


def the_rest() -> None:
    """Stereo, screens, shadow and mirror frusta, and the encoders of packets and node
    messages, through the server's own path (:class:`wallcull.service.Walls`)."""
    import numpy as np

    from .fit import FitOptions
    from .service import Walls
    from .wall import Wall

    scene = _scene()
    for spec in (GRID, SCREENS):
        wall = Wall.from_dict(spec)
        tiles = np.arange(wall.tiles)
        for settings in (None, SETTINGS):
            session = Walls().create(scene, wall, "adaptive", "obb", False, 4, FitOptions(),
                                     settings=settings)
            for frame in (MONO, STEREO, MONO):  # full lists, then deltas against the acks
                number, _ = session.post_frame(frame)
                session.packet_bytes(0, number, since=0)
                session.node_message(tiles, number, since=0)
                session.node_message(tiles, number, since=0, binary=False)
                session.ack(tiles, number)


def everything() -> tuple[float, float]:
    """:func:`culling`, then :func:`the_rest`; the seconds each took."""
    t0 = time.perf_counter()
    culling()
    t1 = time.perf_counter()
    the_rest()
    return t1 - t0, time.perf_counter() - t1


def main() -> int:
    first, rest = everything()
    print(f"wallcull kernels ready: culling {first:.1f} s, the rest {rest:.1f} s",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
