"""The object hierarchy as wallcull built it before instancing: per-node Python loops over a
mutable tree, and every leaf's bound fitted to its world-space points. Kept as the reference the
vectorized, instance-aware build (wallcull.hierarchy, wallcull.instances) is held to."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from wallcull import bounds as bnd
from wallcull.hierarchy import read_trimesh, spatial_groups

_RANDOM_SUFFIX = re.compile(r"^(?P<node>.*)_[0-9a-f]{6}$")


def old_arrays(scene, hierarchy: str = "auto", branching: int = 8) -> dict:
    """The arrays the old ``Scene.from_trimesh`` built (``geometry`` a list of mesh keys)."""
    tree = _FileTree.read(scene)
    if hierarchy == "auto":
        tree.group_wide_parents(branching, 4 * branching)
    return tree.flatten()


def old_leaf_bounds(arrays: dict, kind: str) -> bnd.Bounds:
    """Every leaf's bound fitted to its world-space points, as before (leaves in preorder)."""
    leaves = [i for i, g in enumerate(arrays["geometry"]) if g is not None]
    chunks = [arrays["meshes"][arrays["geometry"][i]][0] @ arrays["world"][i][:3, :3].T
              + arrays["world"][i][:3, 3] for i in leaves]
    starts = np.zeros(len(chunks) + 1, dtype=np.int64)
    np.cumsum([len(c) for c in chunks], out=starts[1:])
    return bnd.LEAF_FITTERS[kind](np.concatenate(chunks), starts)


@dataclass
class _FileTree:
    """The file's node tree as Python lists; mutable while loading, then flattened."""

    names: list[str]
    parent: list[int]
    kids: list[list[int]]
    local: list[np.ndarray]
    geometry: list[str | None]
    synthetic: list[bool]
    meshes: dict[str, tuple[np.ndarray, np.ndarray]]

    @classmethod
    def read(cls, scene) -> "_FileTree":
        graph = scene.graph
        forest = graph.transforms
        root = graph.base_frame
        meshes = dict(read_trimesh(scene)[1].items())  # the usable meshes, as before
        tree = cls([], [], [], [], [], [], meshes)
        stack = [(root, -1)]
        while stack:
            node, parent = stack.pop()
            data = forest.edge_data.get((forest.parents.get(node), node), {}) if parent >= 0 else {}
            matrix = np.asarray(data.get("matrix", np.eye(4)), dtype=np.float64)
            geom = data.get("geometry", forest.node_data.get(node, {}).get("geometry"))
            name = str(node)
            match = _RANDOM_SUFFIX.match(name)
            if (parent >= 0 and geom is not None and match
                    and match["node"] == tree.names[parent] and np.allclose(matrix, np.eye(4))):
                name = f"{match['node']}:{geom}"
            index = tree.add(name, parent, matrix, geom if geom in meshes else None)
            for child in reversed(forest.children.get(node, [])):
                stack.append((child, index))
        tree.split_self_geometry()
        tree.prune()
        return tree

    def add(self, name, parent, local, geometry, synthetic=False) -> int:
        self.names.append(name)
        self.parent.append(parent)
        self.kids.append([])
        self.local.append(local)
        self.geometry.append(geometry)
        self.synthetic.append(synthetic)
        index = len(self.names) - 1
        if parent >= 0:
            self.kids[parent].append(index)
        return index

    def split_self_geometry(self) -> None:
        """A node with geometry and children: move its geometry to a leaf child of its name."""
        for i in range(len(self.names)):
            if self.geometry[i] is not None and self.kids[i]:
                leaf = self.add(self.names[i], i, np.eye(4), self.geometry[i])
                self.kids[i].insert(0, self.kids[i].pop())  # own geometry first
                self.geometry[i] = None
                assert self.kids[i][0] == leaf

    def prune(self) -> None:
        """Drop subtrees without geometry: they can never be visible."""
        keep = [g is not None for g in self.geometry]
        keep[0] = True
        for i in range(len(self.names) - 1, 0, -1):  # children are numbered after parents
            if keep[i]:
                keep[self.parent[i]] = True
        for i in range(len(self.names)):
            self.kids[i] = [k for k in self.kids[i] if keep[k]]

    def world(self) -> list[np.ndarray]:
        out: list[np.ndarray] = [None] * len(self.names)  # type: ignore[list-item]
        order = [0]
        out[0] = self.local[0]
        for i in order:
            for k in self.kids[i]:
                out[k] = out[i] @ self.local[k]
                order.append(k)
        return out

    def group_wide_parents(self, branching: int, threshold: int) -> None:
        """Give every parent with more than ``threshold`` children a spatial hierarchy."""
        world = self.world()
        centers = self._subtree_centers(world)
        for parent in range(len(self.names)):
            kids = self.kids[parent]
            if len(kids) > threshold:
                self.kids[parent] = []
                groups = spatial_groups(np.array([centers[k] for k in kids]), branching)
                self._attach(parent, np.array(kids), groups, world)

    def _attach(self, parent: int, kids: np.ndarray, groups, world) -> None:
        for group in groups:
            if isinstance(group, np.ndarray) and len(group) == 1:
                index = int(kids[group[0]])
                self.kids[parent].append(index)
                self.parent[index] = parent
                continue
            name = f"{self.names[parent]}#g{len(self.kids[parent])}"
            node = self.add(name, parent, np.eye(4), None, synthetic=True)
            if isinstance(group, np.ndarray):
                for j in group:
                    self.kids[node].append(int(kids[j]))
                    self.parent[int(kids[j])] = node
            else:
                self._attach(node, kids, group, world)
            # Children keep their world pose: a synthetic group has the identity local frame
            # relative to its parent, so re-parenting under it changes nothing.

    def _subtree_centers(self, world) -> list[np.ndarray]:
        lo = [np.full(3, np.inf) for _ in self.names]
        hi = [np.full(3, -np.inf) for _ in self.names]
        for i in range(len(self.names) - 1, -1, -1):
            g = self.geometry[i]
            if g is not None:
                v = self.meshes[g][0] @ world[i][:3, :3].T + world[i][:3, 3]
                lo[i] = np.minimum(lo[i], v.min(axis=0))
                hi[i] = np.maximum(hi[i], v.max(axis=0))
            p = self.parent[i]
            if p >= 0:
                lo[p] = np.minimum(lo[p], lo[i])
                hi[p] = np.maximum(hi[p], hi[i])
        # nodes without geometry below them (pruned later) have no box; centre them anywhere
        return [(a + b) / 2 if np.isfinite(a).all() else np.zeros(3) for a, b in zip(lo, hi)]

    def flatten(self) -> dict:
        """Depth-first preorder arrays."""
        order, stack = [], [0]
        while stack:
            i = stack.pop()
            order.append(i)
            stack.extend(reversed(self.kids[i]))
        new = {old: k for k, old in enumerate(order)}
        n = len(order)
        parent = np.array([new[self.parent[i]] if self.parent[i] >= 0 else -1 for i in order])
        child_count = np.array([len(self.kids[i]) for i in order], dtype=np.int64)
        child_start = np.zeros(n, dtype=np.int64)
        np.cumsum(child_count[:-1], out=child_start[1:])
        children = np.array([new[k] for i in order for k in self.kids[i]], dtype=np.int64)
        local = np.array([self.local[i] for i in order])
        world_list = self.world()
        world = np.array([world_list[i] for i in order])
        geometry = [self.geometry[i] for i in order]
        is_leaf = np.array([g is not None for g in geometry])
        used = {g for g in geometry if g is not None}
        return dict(
            names=[self.names[i] for i in order], parent=parent.astype(np.int64),
            child_start=child_start, child_count=child_count, children=children,
            is_leaf=is_leaf, synthetic=np.array([self.synthetic[i] for i in order]),
            local=local, world=world, geometry=geometry,
            meshes={k: v for k, v in self.meshes.items() if k in used},
        )


