"""The object hierarchy (OH) as flat arrays: loading, preprocessing (paper Alg. 1), dynamic refit.

Nodes are stored in depth-first preorder, so a node's subtree is the contiguous range
``[i, i + size[i])`` and the leaves under it are a contiguous run of ``leaves``. Children are in
CSR form (``child_start``, ``child_count``, ``children``). Node 0 is the root, the file's base
frame. Three kinds of node exist besides the file's own:

* a node that carries geometry *and* has children becomes an internal node whose first child is
  a leaf of the same name carrying its own geometry (SPEC section 4: it "counts as a leaf for its
  own geometry");
* a parent with too many children (a flat scene, as an OBJ of many groups loads) gets a spatial
  hierarchy of *synthetic* group nodes, ``branching`` children each (see :func:`spatial_groups`);
  synthetic nodes never appear in a list of names;
* nodes that carry no geometry anywhere below them are dropped: they can never be visible.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from . import bounds as bnd
from .errors import InputError

#: Default branching factor of the automatic spatial hierarchy.
BRANCHING = 8


@dataclass
class Scene:
    """A scene's object hierarchy and geometry. Immutable once built; see :class:`SceneState`."""

    name: str
    names: list[str]
    parent: np.ndarray  # (n,) int64, -1 at the root
    child_start: np.ndarray  # (n,) int64
    child_count: np.ndarray  # (n,) int64
    children: np.ndarray  # (n - 1,) int64
    is_leaf: np.ndarray  # (n,) bool: carries geometry, has no children
    synthetic: np.ndarray  # (n,) bool: a spatial group, not a node of the file
    local: np.ndarray  # (n, 4, 4) transform relative to the parent
    world: np.ndarray  # (n, 4, 4) rest transform to world
    geometry: list[str | None]  # per node: mesh key of a leaf, else None
    meshes: dict[str, tuple[np.ndarray, np.ndarray]]  # key -> (vertices (v, 3), faces (f, 3))
    settings: dict = field(default_factory=dict)
    hierarchy: str = "file"  # "file" or "auto:<branching>"

    # ------------------------------------------------------------------ structure

    def __len__(self) -> int:
        return len(self.names)

    @cached_property
    def depth(self) -> np.ndarray:
        depth = np.zeros(len(self), dtype=np.int64)
        for i in range(1, len(self)):  # preorder: parents come first
            depth[i] = depth[self.parent[i]] + 1
        return depth

    @cached_property
    def size(self) -> np.ndarray:
        """Subtree sizes: node ``i``'s subtree is ``[i, i + size[i])``."""
        size = np.ones(len(self), dtype=np.int64)
        for i in range(len(self) - 1, 0, -1):
            size[self.parent[i]] += size[i]
        return size

    @cached_property
    def leaves(self) -> np.ndarray:
        """Leaf node ids in preorder."""
        return np.flatnonzero(self.is_leaf)

    @cached_property
    def leaf_range(self) -> tuple[np.ndarray, np.ndarray]:
        """``(start, count)``: the leaves under node ``i`` are ``leaves[start[i]:start[i]+count[i]]``."""
        rank = np.cumsum(self.is_leaf) - self.is_leaf  # leaves before each node
        end = np.concatenate([rank, [len(self.leaves)]])[np.arange(len(self)) + self.size]
        return rank, end - rank

    @cached_property
    def levels(self) -> list[np.ndarray]:
        """Node ids at each depth."""
        return [np.flatnonzero(self.depth == d) for d in range(int(self.depth.max()) + 1)]

    @cached_property
    def index(self) -> dict[str, int]:
        """Name -> node id. A node that is also its own geometry leaf maps to the internal node."""
        out: dict[str, int] = {}
        for i, name in enumerate(self.names):
            if not self.synthetic[i]:
                out.setdefault(name, i)
        return out

    @cached_property
    def real_cover(self) -> list[np.ndarray]:
        """For each node, the nearest non-synthetic nodes covering its subtree (itself if real)."""
        cover: list[np.ndarray] = [None] * len(self)  # type: ignore[list-item]
        for i in range(len(self) - 1, -1, -1):
            if not self.synthetic[i]:
                cover[i] = np.array([i])
            else:
                kids = self.children[self.child_start[i]:self.child_start[i] + self.child_count[i]]
                cover[i] = np.concatenate([cover[k] for k in kids])
        return cover

    def subtree_leaves(self, nodes: np.ndarray) -> np.ndarray:
        """Leaf ids under each of ``nodes``, concatenated in order."""
        start, count = self.leaf_range
        s, c = start[nodes], count[nodes]
        offsets = np.repeat(s - np.cumsum(c) + c, c)
        return self.leaves[np.arange(int(c.sum())) + offsets]

    @cached_property
    def stats(self) -> dict:
        internal = ~self.is_leaf
        internal[0] = False  # the base frame is not a node of the model
        kids = self.child_count[internal]
        tris = sum(len(self.meshes[self.geometry[i]][1]) for i in self.leaves)
        return {
            "nodes": len(self) - 1, "internal": int(internal.sum()), "leaves": len(self.leaves),
            "synthetic": int(self.synthetic.sum()), "depth": int(self.depth.max()),
            "branching": float(kids.mean()) if len(kids) else 0.0, "triangles": int(tris),
            "hierarchy": self.hierarchy,
        }

    # ------------------------------------------------------------------ geometry

    @cached_property
    def leaf_points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(points (N, 3), starts (L + 1,))``: each leaf's vertices in world space, at rest."""
        chunks = [self.leaf_vertices(i) for i in self.leaves]
        starts = np.zeros(len(chunks) + 1, dtype=np.int64)
        np.cumsum([len(c) for c in chunks], out=starts[1:])
        return np.concatenate(chunks), starts

    def leaf_vertices(self, leaf: int, world: np.ndarray | None = None) -> np.ndarray:
        """``(v, 3)`` vertices of one leaf in world space (at rest unless ``world`` is given)."""
        m = self.world[leaf] if world is None else world
        return self.meshes[self.geometry[leaf]][0] @ m[:3, :3].T + m[:3, 3]

    def leaf_triangles(self, leaf: int, world: np.ndarray | None = None) -> np.ndarray:
        """``(f, 3, 3)`` triangles of one leaf in world space."""
        return self.leaf_vertices(leaf, world)[self.meshes[self.geometry[leaf]][1]]

    def bounds(self, kind: str = "obb") -> bnd.Bounds:
        """Bounds of every node at rest (paper Alg. 1), computed once per kind."""
        cache = self.__dict__.setdefault("_bounds", {})
        if kind not in cache:
            cache[kind] = compute_bounds(self, kind)
        return cache[kind]

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_trimesh(cls, scene, name: str = "scene", hierarchy: str = "auto",
                     branching: int = BRANCHING, settings: Mapping | None = None) -> "Scene":
        """Build from a ``trimesh.Scene`` following its node tree (SPEC section 4).

        ``hierarchy="auto"`` adds a spatial hierarchy under any parent with more than
        ``4 * branching`` children; ``"file"`` keeps the file's tree as it is.
        """
        if hierarchy not in ("auto", "file"):
            raise InputError(f"hierarchy must be 'auto' or 'file', got {hierarchy!r}")
        if branching < 2:
            raise InputError(f"branching must be at least 2, got {branching}")
        tree = _FileTree.read(scene)
        if hierarchy == "auto":
            tree.group_wide_parents(branching, 4 * branching)
        flat = tree.flatten()
        label = "file" if hierarchy == "file" else f"auto:{branching}"
        return cls(name=name, settings=dict(settings or {}), hierarchy=label, **flat)


def compute_bounds(scene: Scene, kind: str) -> bnd.Bounds:
    """Preprocess bottom-up (paper Alg. 1): leaves from their points, parents from children."""
    if kind not in bnd.LEAF_FITTERS:
        raise InputError(f"unknown bound type {kind!r}; choose from {', '.join(bnd.KINDS)}")
    points, starts = scene.leaf_points
    out = bnd.Bounds.empty(kind, len(scene))
    out.put(scene.leaves, bnd.LEAF_FITTERS[kind](points, starts))
    refit(scene, out, np.flatnonzero(~scene.is_leaf), bnd.enclosing_mode(kind))
    return out


def refit(scene: Scene, bounds: bnd.Bounds, nodes: np.ndarray, mode: str) -> None:
    """Recompute the bounds of internal ``nodes`` from their children, deepest level first."""
    nodes = np.asarray(nodes)
    if not len(nodes):
        return
    depth = scene.depth[nodes]
    for d in range(int(depth.max()), -1, -1):
        level = nodes[depth == d]
        if not len(level):
            continue
        counts = scene.child_count[level]
        starts = np.zeros(len(level) + 1, dtype=np.int64)
        np.cumsum(counts, out=starts[1:])
        kids = scene.children[np.repeat(scene.child_start[level] - starts[:-1], counts)
                              + np.arange(starts[-1])]
        bounds.put(level, bnd.enclose(bounds.take(kids), starts, mode))


class SceneState:
    """A scene's bounds in their current pose: what the culler reads, and what moves.

    ``move`` applies node updates (paper section 5, Fig. 6): the moved subtrees' bounds follow
    rigidly (exact for OBBs), and only the moved nodes' ancestors are refit.
    ``refit="aabb"`` bounds the moved nodes and their ancestors by axis-aligned boxes instead,
    the cheaper refit the paper suggests for dynamic parts, at a cost in false positives.
    """

    def __init__(self, scene: Scene, kind: str = "obb"):
        self.scene = scene
        self.kind = kind
        self.bounds = scene.bounds(kind).copy()
        # The leaves' bounds moved rigidly and never re-boxed: what an axis-aligned refit boxes
        # each frame, so that boxes of boxes of boxes do not grow frame after frame.
        self.exact = self.bounds.copy()
        self.local = scene.local.copy()
        self.world = scene.world.copy()
        self.version = 0  # counts moves: what caches of the bounds key on

    def move(self, updates: Mapping[str, Any], refit_mode: str | None = None) -> np.ndarray:
        """Set the local transforms of named nodes; returns the ids of the refit ancestors.

        ``updates`` maps a node name to its new local transform (relative to its parent), as
        :func:`node_matrix` accepts it.
        """
        ids, local = [], []
        for name, value in updates.items():
            node = self.scene.index.get(name)
            if node is None or node == 0:
                raise InputError(f"cannot move unknown node {name!r}")
            ids.append(node)
            local.append(node_matrix(value, name))
        if not ids:
            return np.zeros(0, dtype=np.int64)
        # All or nothing: composed down a chain of nodes, updates that are fine alone can still
        # collapse or overflow a world transform; then the scene stays as it was.
        saved = [a.copy() for a in (self.local, self.world)], self.bounds.copy(), self.exact.copy()
        try:
            with np.errstate(all="ignore"):
                up = self.move_nodes(np.array(ids), np.array(local), refit_mode)
                sound = (np.isfinite(self.world).all() and np.isfinite(self.bounds.center).all()
                         and np.isfinite(self.bounds.half).all()
                         and np.isfinite(self.bounds.radius).all()
                         and (np.abs(np.linalg.det(self.world[:, :3, :3])) > 0).all())
        except (np.linalg.LinAlgError, FloatingPointError, ValueError):
            sound = False
        if not sound:
            (self.local, self.world), self.bounds, self.exact = saved
            self.version += 1
            raise InputError("the updates collapse or overflow world transforms in float64")
        return up

    def move_nodes(self, nodes: np.ndarray, local: np.ndarray,
                   refit_mode: str | None = None) -> np.ndarray:
        """:meth:`move` by node ids and ``(k, 4, 4)`` local transforms, unchecked.

        Where the resulting world motion of a subtree is rigid, its bounds move with it exactly;
        where it is not (a scale changed, or a turn under a non-uniformly scaled parent), its
        leaves are fit again from their points.
        """
        scene = self.scene
        mode = refit_mode or bnd.enclosing_mode(self.kind)
        if mode not in ("obb", "aabb", "sphere"):
            raise InputError(f"refit must be 'obb' or 'aabb', got {mode!r}")
        self.local[nodes] = local
        levels, parent = scene.levels, scene.parent
        # Every node in a moved subtree gets a new world transform, top down.
        inside = np.zeros(len(scene), dtype=bool)
        inside[nodes] = True
        for level in levels[1:]:
            inside[level] |= inside[parent[level]]
        sub = np.flatnonzero(inside)
        old = self.world[sub]
        for level in levels[1:]:
            level = level[inside[level]]
            self.world[level] = self.world[parent[level]] @ self.local[level]
        delta = self.world[sub] @ np.linalg.inv(old)
        rot = delta[:, :3, :3]
        rigid = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(3)).max(axis=(1, 2)) < 1e-9
        moving = sub[rigid]
        self.bounds.put(moving, bnd.transform(self.bounds.take(moving), rot[rigid],
                                              delta[rigid, :3, 3]))
        leaves = scene.is_leaf[moving]
        self.exact.put(moving[leaves], bnd.transform(self.exact.take(moving[leaves]),
                                                     rot[rigid][leaves], delta[rigid, :3, 3][leaves]))
        if not rigid.all():
            # Under a scaled parent the motion of a subtree is not rigid in world space:
            # fit its leaves again from their points and refit the subtree above them.
            self._refit_from_points(sub[~rigid])
        # Only the strict ancestors of moved nodes are refit, bottom up; that includes moved
        # nodes above other moved nodes, whose rigid motion alone no longer fits their subtree.
        above = np.zeros(len(scene), dtype=bool)
        above[parent[nodes[nodes > 0]]] = True
        if mode == "aabb":
            # Moved leaves: the axis-aligned box of their exact bound. Moved internal nodes:
            # refit from their children, never a box of last frame's box.
            moved_leaves = nodes[scene.is_leaf[nodes]]
            self.bounds.put(moved_leaves, bnd.axis_aligned(self.exact.take(moved_leaves)))
            above[nodes[~scene.is_leaf[nodes]]] = True
        for level in reversed(levels[1:]):
            above[parent[level[above[level]]]] = True
        up = np.flatnonzero(above)
        refit(scene, self.bounds, up, mode)
        self.version += 1
        return up

    def _refit_from_points(self, nodes: np.ndarray) -> None:
        scene = self.scene
        leaves = nodes[scene.is_leaf[nodes]]
        chunks = [scene.leaf_vertices(i, self.world[i]) for i in leaves]
        starts = np.zeros(len(chunks) + 1, dtype=np.int64)
        np.cumsum([len(c) for c in chunks], out=starts[1:])
        fitted = bnd.LEAF_FITTERS[self.kind](np.concatenate(chunks), starts)
        self.bounds.put(leaves, fitted)
        self.exact.put(leaves, fitted)
        refit(scene, self.bounds, nodes[~scene.is_leaf[nodes]], bnd.enclosing_mode(self.kind))


def node_matrix(value: Any, name: str = "node") -> np.ndarray:
    """A validated local transform: an invertible affine 4x4 matrix, or glTF-style
    ``{"position": [x, y, z], "orientation": [w, x, y, z], "scale": [sx, sy, sz]}`` (scale
    optional), composed as translation x rotation x scale."""
    from .wall import QUATERNION_TOLERANCE, quaternion_matrix

    if isinstance(value, Mapping):
        try:
            t = np.asarray(value["position"], dtype=np.float64).reshape(3)
            q = np.asarray(value["orientation"], dtype=np.float64).reshape(4)
            scale = np.asarray(value.get("scale", (1, 1, 1)), dtype=np.float64).reshape(3)
        except (KeyError, ValueError, TypeError) as exc:
            raise InputError(f"update of {name!r} needs position [x,y,z] and orientation "
                             f"[w,x,y,z]: {exc}") from None
        if not (np.isfinite(t).all() and np.isfinite(q).all() and np.isfinite(scale).all()):
            raise InputError(f"update of {name!r} is not finite")
        norm = np.linalg.norm(q)
        if abs(norm - 1) > QUATERNION_TOLERANCE:
            raise InputError(f"update of {name!r}: orientation is not a unit quaternion "
                             f"(norm {norm:.9g})")
        m = np.eye(4)
        m[:3, :3] = quaternion_matrix(q / norm) * scale
        m[:3, 3] = t
    else:
        try:
            m = np.asarray(value, dtype=np.float64).reshape(4, 4)
        except (ValueError, TypeError):
            raise InputError(f"update of {name!r} must be a 4x4 matrix or position/orientation"
                             ) from None
        if not np.isfinite(m).all() or not np.array_equal(m[3], [0, 0, 0, 1]):
            raise InputError(f"update of {name!r} is not a finite affine 4x4 matrix "
                             "(last row 0, 0, 0, 1)")
    r = m[:3, :3]
    if abs(np.linalg.det(r)) <= 1e-12 * max(np.abs(r).max(), 1e-300) ** 3:
        raise InputError(f"update of {name!r} is singular (a zero scale)")
    scales = np.linalg.svd(r, compute_uv=False)
    if scales.min() < 1e-9 or scales.max() > 1e9 or np.abs(m[:3, 3]).max() > 1e15:
        raise InputError(f"update of {name!r} is out of range: scales must lie between 1e-9 "
                         "and 1e9 and positions within 1e15")
    return m


# --------------------------------------------------------------------------- the file's tree

# trimesh names the extra primitives of a multi-primitive glTF mesh "<node>_<6 random hex>";
# the names change on every load, so they are replaced with "<node>:<geometry name>".
_RANDOM_SUFFIX = re.compile(r"^(?P<node>.*)_[0-9a-f]{6}$")


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
        meshes = {}
        for key, geom in scene.geometry.items():
            vertices = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), dtype=np.float64)
            faces = np.asarray(getattr(geom, "faces", np.zeros((0, 3))), dtype=np.int64)
            if len(vertices) and np.isfinite(vertices).all():
                meshes[key] = (vertices.reshape(-1, 3), faces.reshape(-1, 3))
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


def spatial_groups(centers: np.ndarray, branching: int):
    """Split points into at most ``branching`` spatially compact groups, recursively.

    Returns a list of groups; a group is an index array (at most ``branching`` items) or, when
    larger, a nested list of groups. Each split cuts the set at a median of the axis of largest
    spread, in proportion to the number of groups each side receives, so groups are balanced and
    compact (a k-d tree whose nodes have ``branching`` children).
    """
    index = np.arange(len(centers))

    def split(idx: np.ndarray, parts: int) -> list[np.ndarray]:
        if parts == 1 or len(idx) <= 1:
            return [idx]
        spread = np.ptp(centers[idx], axis=0)
        axis = int(np.argmax(spread))
        order = idx[np.argsort(centers[idx, axis], kind="stable")]
        first = parts // 2
        cut = int(round(len(order) * first / parts))
        return split(order[:cut], first) + split(order[cut:], parts - first)

    def build(idx: np.ndarray):
        if len(idx) <= branching:
            return idx
        return [build(part) for part in split(idx, branching) if len(part)]

    top = build(index)
    return top if isinstance(top, list) else [top]


# --------------------------------------------------------------------------- loading


def load_trimesh(path: str | os.PathLike):
    """Read a scene file with trimesh (SPEC section 4), with a one-line error on failure."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(f"scene file not found: {path}")
    kwargs = {"split_groups": True} if path.suffix.lower() in (".obj", ".zip") else {}
    try:
        loaded = trimesh.load(str(path), **kwargs)
    except Exception as exc:  # noqa: BLE001 - any parser failure is bad input
        raise InputError(f"cannot read scene {path.name}: {exc}") from None
    if not isinstance(loaded, trimesh.Scene):
        loaded = trimesh.Scene(loaded)
    if not loaded.geometry:
        raise InputError(f"scene {path.name} has no geometry")
    return loaded


def load(spec: str, hierarchy: str = "auto", branching: int = BRANCHING,
         settings: Mapping[str, Any] | None = None) -> Scene:
    """A bundled scene by name (``wallcull scenes``) or a scene file by path. Its settings
    (:mod:`wallcull.settings`) are ``settings`` if given, else the bundled scene's or the
    file's sidecar ``<file>.wallcull.json``."""
    from wallcull import scenes as bundled

    from . import settings as cfg

    if spec in bundled.BUNDLED:
        raw = bundled.settings(spec) if settings is None else settings
        scene = Scene.from_trimesh(bundled.build(spec), name=spec, hierarchy=hierarchy,
                                   branching=branching, settings=raw)
    elif not Path(spec).exists() and os.sep not in spec and "." not in spec:
        raise InputError(f"unknown scene {spec!r}: not a file, and the bundled scenes are "
                         f"{', '.join(sorted(bundled.BUNDLED))}")
    else:
        raw = cfg.sidecar(spec) if settings is None else settings
        scene = Scene.from_trimesh(load_trimesh(spec), name=Path(spec).stem, hierarchy=hierarchy,
                                   branching=branching, settings=raw)
    cfg.parse(scene.settings)  # refuse bad settings when the scene loads, not mid-frame
    return scene
