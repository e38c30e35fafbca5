"""Build a bundled scene by name, and measure the shape of any scene tree.

The bundled scenes are generated, not stored: a few template meshes instanced thousands of times
(see :mod:`wallcull.bundled.meshes`) under a tree laid out by :mod:`wallcull.bundled.fatehpur` or
:mod:`wallcull.bundled.powerplant`. Generation is deterministic: the same name and seed give the same
node names, tree, transforms and vertices, bit for bit, because all randomness comes from one
``numpy.random.default_rng(seed)`` consumed in a fixed order.
"""

from __future__ import annotations

import copy
import hashlib
import math
import re
from typing import TYPE_CHECKING, Callable

import numpy as np

from . import fatehpur, powerplant
from .tree import Z_UP_TO_Y_UP, Tree, trs

if TYPE_CHECKING:  # imported where used: names and layouts load without trimesh
    import trimesh

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


#: Bumped whenever a generator's output changes: part of the key of a generated scene's
#: prepared file (see ``wallcull prepare``).
GENERATOR_VERSION = 1

#: ``NAME*K``: K copies of a bundled scene side by side on a square grid, one name each.
TILED: dict[str, str] = {
    "powerplant*K": "K power plants side by side on a grid 100 m apart (K = 10, 40, 200: "
                    "about 50k, 200k and 1M nodes)",
    "fatehpur*K": "K Fatehpur Sikri look-alikes side by side on a grid 360 m apart",
}
#: The most copies a ``NAME*K`` may ask for (256 power plants are about 1.3 M nodes).
MAX_COPIES = 256
_PITCH = {"fatehpur": 360.0, "powerplant": 100.0}  # metres between the copies' centres
_TILED_NAME = re.compile(r"^(?P<base>[a-z]+)\*(?P<count>[0-9]{1,6})$")


def parse(name: str) -> tuple[str, int | None]:
    """``(base, copies)`` of a bundled scene's name: ``("powerplant", None)`` for
    ``powerplant``, ``("powerplant", 40)`` for ``powerplant*40``. ``KeyError`` for any other
    name, ``ValueError`` for a count out of range."""
    match = _TILED_NAME.match(name)
    base, count = (match["base"], int(match["count"])) if match else (name, None)
    if base not in _GENERATORS:
        raise KeyError(f"unknown bundled scene {name!r}; known: "
                       f"{', '.join([*BUNDLED, *TILED])}")
    if count is not None and not 1 <= count <= MAX_COPIES:
        raise ValueError(f"{name}: the number of copies must be 1 to {MAX_COPIES}")
    return base, count


def is_bundled(name: str) -> bool:
    """Whether ``name`` names a bundled scene (a tiled one included, whatever its count)."""
    try:
        parse(name)
    except KeyError:
        return False
    except ValueError:
        return True
    return True


def copies(base: str, count: int) -> tuple[np.ndarray, list[str]]:
    """``(matrices (K, 4, 4), roots)``: the root transform and root name of each copy of
    ``base`` in ``base*K``, row by row on a grid of ``ceil(sqrt(K))`` columns centred on the
    origin in the ground plane (x, z of the y-up world)."""
    cols = math.ceil(math.sqrt(count))
    rows = math.ceil(count / cols)
    r, c = np.divmod(np.arange(count), cols)
    pitch = _PITCH[base]
    offsets = np.stack([(c - (cols - 1) / 2) * pitch, np.zeros(count),
                        (r - (rows - 1) / 2) * pitch], axis=1)
    width = len(str(count - 1))
    return (np.array([trs(o) @ Z_UP_TO_Y_UP for o in offsets]),
            [f"{base}{k:0{width}d}" for k in range(count)])


def build(name: str, seed: int = 0) -> trimesh.Scene:
    """The bundled scene ``name`` generated with ``seed``; ``KeyError`` for an unknown name.
    ``NAME*K`` builds every copy's nodes in the scene graph (slow for large K:
    :func:`wallcull.scene.load` tiles one copy's arrays instead, and gets the same scene)."""
    base, count = parse(name)
    tree = _GENERATORS[base](int(seed))
    if count is None:
        return tree.scene()
    matrices, roots = copies(base, count)
    return tree.scene(list(zip(roots, matrices)))


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
    ``name``; a tiled scene declares none. ``KeyError`` for an unknown name."""
    base, count = parse(name)
    return copy.deepcopy(_SETTINGS[base]) if count is None else {}


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
