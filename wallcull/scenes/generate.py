"""Build a bundled scene by name, and measure the shape of any scene tree.

The bundled scenes are generated, not stored: a few template meshes instanced thousands of times
(see :mod:`wallcull.scenes.meshes`) under a tree laid out by :mod:`wallcull.scenes.fatehpur` or
:mod:`wallcull.scenes.powerplant`. Generation is deterministic: the same name and seed give the same
node names, tree, transforms and vertices, bit for bit, because all randomness comes from one
``numpy.random.default_rng(seed)`` consumed in a fixed order.
"""

from __future__ import annotations

import copy

import hashlib
from typing import Callable

import numpy as np
import trimesh

from . import fatehpur, powerplant
from .tree import Tree

#: name -> one-line description of each bundled scene.
BUNDLED: dict[str, str] = {
    "fatehpur": "Fatehpur Sikri look-alike: a Mughal palace city on a 300 m site; "
                "~790 nodes (~300 internal), branching ~2.65, ~1.7 M triangles",
    "powerplant": "UNC power plant look-alike: a coal-fired station in 80 x 80 x 60 m; "
                  "~5,000 nodes (~1,130 internal), branching ~4.45, ~1 M triangles",
}

_GENERATORS: dict[str, Callable[[int], Tree]] = {
    "fatehpur": fatehpur.build,
    "powerplant": powerplant.build,
}


def build(name: str, seed: int = 0) -> trimesh.Scene:
    """The bundled scene ``name`` generated with ``seed``; ``KeyError`` for an unknown name."""
    if name not in _GENERATORS:
        raise KeyError(f"unknown bundled scene {name!r}; known: {', '.join(BUNDLED)}")
    return _GENERATORS[name](int(seed)).scene()


#: Scene settings (wallcull.settings format) of the bundled scenes. The Fatehpur look-alike
#: asks for a sun that casts shadows and a mirror on the Anup Talao's water (the tank spans
#: x 35..66, z -71..-40, its water 0.3 m below the rim); the power plant asks for nothing, so
#: it costs nothing for them.
_SETTINGS = {
    "fatehpur": {
        "lights": [{"name": "sun", "position": [320.0, 420.0, 260.0],
                    "resolution": [2048, 2048]}],
        "mirrors": [{"name": "anup_talao", "point": [50.6, -0.3, -55.3],
                     "normal": [0.0, 1.0, 0.0],
                     "polygon": [[35.1, -0.3, -70.8], [66.1, -0.3, -70.8], [66.1, -0.3, -39.8],
                                 [35.1, -0.3, -39.8]]}],
    },
    "powerplant": {},
}


def settings(name: str) -> dict:
    """Scene settings (lights, mirrors; see ``wallcull.settings``) of the bundled scene
    ``name``. ``KeyError`` for an unknown name."""
    if name not in _GENERATORS:
        raise KeyError(f"unknown bundled scene {name!r}; known: {', '.join(BUNDLED)}")
    return copy.deepcopy(_SETTINGS[name])


def tree_stats(scene: trimesh.Scene) -> dict:
    """The shape of a scene's node tree, counted as the paper counts it.

    Nodes are those of ``scene.graph`` except the base frame. ``leaves`` carry geometry,
    ``internal`` do not; ``branching`` is children per internal node; ``depth`` is the most
    edges from the base frame to a node; ``triangles`` sums each leaf's mesh (instances count
    once per node).
    """
    graph = scene.graph
    base = graph.base_frame
    children = graph.transforms.children
    parents = graph.transforms.parents
    nodes = [n for n in graph.nodes if n != base]
    geometry = set(graph.nodes_geometry)
    internal = [n for n in nodes if n not in geometry]
    depth = {base: 0}
    for n in _top_down(base, children):
        depth[n] = depth[parents[n]] + 1
    faces = {name: len(getattr(g, "faces", ())) for name, g in scene.geometry.items()}
    triangles = sum(faces.get(graph.transforms.node_data[n].get("geometry"), 0) for n in geometry)
    n_children = sum(len(children.get(n, ())) for n in internal)
    return {
        "nodes": len(nodes),
        "internal": len(internal),
        "leaves": len(geometry),
        "branching": n_children / max(1, len(internal)),
        "depth": max(depth.values()),
        "triangles": int(triangles),
    }


def digest(scene: trimesh.Scene) -> str:
    """A SHA-256 of everything that makes a scene: each node's name, parent, geometry name and
    matrix bytes in graph order, then each geometry's name, vertex and face bytes. Two scenes
    with equal digests are bit-identical for culling and rendering."""
    h = hashlib.sha256()
    transforms = scene.graph.transforms
    for (parent, child), edge in transforms.edge_data.items():
        h.update(f"{parent}>{child}:{edge.get('geometry', '')};".encode())
        h.update(np.ascontiguousarray(edge.get("matrix", np.eye(4)), dtype=np.float64).tobytes())
    for name, geom in scene.geometry.items():
        h.update(name.encode())
        h.update(np.ascontiguousarray(geom.vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(geom.faces, dtype=np.int64).tobytes())
    return h.hexdigest()


def _top_down(root, children: dict) -> list:
    """Nodes below ``root`` in breadth-first order (parents before children)."""
    order, frontier = [], [root]
    while frontier:
        frontier = [c for n in frontier for c in children.get(n, ())]
        order.extend(frontier)
    return order
