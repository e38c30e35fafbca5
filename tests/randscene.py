"""Random scenes, walls and frames for property tests, all from one seed."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation


def random_mesh(rng: np.random.Generator, kind: str | None = None) -> trimesh.Trimesh:
    """A small mesh; degenerate kinds included (flat, a segment, a point, repeated points).
    ``"many"``: a soup of 40 to 400 triangles, to be cut into clusters."""
    kind = kind or rng.choice(["box", "blob", "blob", "flat", "line", "point", "sliver"])
    if kind == "box":
        return trimesh.creation.box(extents=rng.uniform(0.05, 2.0, 3))
    if kind == "many":
        n = int(rng.integers(20, 200))
        v = rng.normal(size=(n, 3)) * rng.uniform(0.05, 3.0, 3)
        # triangles between near neighbours mostly, a few long ones across
        f = np.sort(rng.integers(0, n, size=(int(rng.integers(40, 400)), 3)), axis=1)
        v = v[np.argsort(v[:, int(rng.integers(3))])]
        near = rng.random(len(f)) < 0.8
        f[near] = f[near, :1] + np.sort(rng.integers(0, 4, size=(near.sum(), 3)), axis=1)
        return trimesh.Trimesh(vertices=v, faces=np.minimum(f, n - 1), process=False)
    n = int(rng.integers(3, 24))
    if kind == "blob":
        v = rng.normal(size=(n, 3)) * rng.uniform(0.05, 1.5, 3)
    elif kind == "flat":
        v = np.c_[rng.normal(size=(n, 2)), np.zeros(n)]
    elif kind == "line":
        v = np.outer(rng.uniform(-1, 1, n), rng.normal(size=3))
    elif kind == "point":
        v = np.repeat(rng.normal(size=(1, 3)), n, axis=0)
    else:  # sliver: nearly coincident points
        v = rng.normal(size=(1, 3)) + 1e-7 * rng.normal(size=(n, 3))
    f = rng.integers(0, n, size=(max(1, n - 2), 3))
    return trimesh.Trimesh(vertices=v, faces=f, process=False)


def random_transform(rng: np.random.Generator, spread: float, scale: bool = True) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()
    if scale and rng.random() < 0.3:
        m[:3, :3] *= rng.uniform(0.3, 2.0, 3)  # non-uniform scale in the node's frame
    m[:3, 3] = rng.normal(size=3) * spread
    return m


def random_scene(seed: int, leaves: int = 20, offset=(0.0, 0.0, 0.0), flat: bool = False,
                 self_geometry: bool = True, big: float = 0.0) -> trimesh.Scene:
    """A random node tree of depth up to 4 with random leaf meshes; the root group is moved by
    ``offset`` (tests of large coordinates); a fraction ``big`` of the leaves have meshes of
    many triangles (to be cut into clusters)."""
    rng = np.random.default_rng(seed)
    scene = trimesh.Scene()
    top = np.eye(4)
    top[:3, 3] = offset
    scene.graph.update(frame_from=scene.graph.base_frame, frame_to="root", matrix=top)
    groups = ["root"]
    for i in range(leaves):
        parent = "root" if flat else groups[int(rng.integers(len(groups)))]
        if not flat and rng.random() < 0.35:
            name = f"g{i}"
            scene.graph.update(frame_from=parent, frame_to=name,
                               matrix=random_transform(rng, 3.0, scale=False))
            groups.append(name)
            parent = name
        mesh = random_mesh(rng, "many" if big and rng.random() < big else None)
        geom = f"mesh{i}"
        scene.add_geometry(mesh, geom_name=geom, node_name=f"leaf{i}", parent_node_name=parent,
                           transform=random_transform(rng, 4.0))
    if self_geometry and not flat and len(groups) > 1:
        # A node that carries geometry and has children (SPEC section 4).
        scene.graph.update(frame_from="root", frame_to="g_self", matrix=np.eye(4),
                           geometry="selfmesh")
        scene.geometry["selfmesh"] = random_mesh(rng, "box")
        scene.add_geometry(random_mesh(rng, "blob"), geom_name="selfkid", node_name="g_self_kid",
                           parent_node_name="g_self", transform=random_transform(rng, 1.0))
    return scene


def random_wall(rng: np.random.Generator) -> dict:
    w, h = rng.uniform(0.2, 1.0), rng.uniform(0.2, 1.0)
    gap = [float(rng.choice([0.0, rng.uniform(0.01, 0.3) * w, -rng.uniform(0.01, 0.3) * w])),
           float(rng.choice([0.0, rng.uniform(0.01, 0.3) * h, -rng.uniform(0.01, 0.3) * h]))]
    return {"cols": int(rng.integers(1, 6)), "rows": int(rng.integers(1, 6)),
            "tile_size": [w, h], "gap": gap, "distance": float(rng.uniform(0.5, 3.0)),
            "near": float(rng.uniform(0.01, 0.3)), "far": float(rng.uniform(8.0, 60.0))}


def look_at_frame(rng: np.random.Generator, target: np.ndarray, distance: float,
                  wall: dict) -> dict:
    """A frame whose camera sits ``distance`` from ``target`` looking roughly at it."""
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    position = target + direction * distance
    forward = -(direction + 0.3 * rng.normal(size=3))
    forward /= np.linalg.norm(forward)
    up = rng.normal(size=3)
    x = np.cross(forward, up)
    x /= np.linalg.norm(x)
    y = np.cross(x, forward)
    rot = np.stack([x, y, -forward], axis=1)  # columns: display axes in the world
    qx, qy, qz, qw = Rotation.from_matrix(rot).as_quat()
    eye_z = rng.uniform(-wall["distance"] + wall.get("near", 0.1) + 0.05, 1.0)
    eye = [float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(eye_z)]
    return {"position": position.tolist(), "orientation": [qw, qx, qy, qz], "eye": eye}
