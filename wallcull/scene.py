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
* nodes that carry no geometry anywhere below them are dropped: they can never be visible;
* a leaf whose mesh has more triangles than a cluster holds gets its *clusters* as children
  (:mod:`wallcull.clusters`): parts of its triangles, culled like any node. A leaf stays a leaf
  (it is what lists name); a tile that sees only some of its clusters draws their triangle
  ranges. Clusters never appear in a list of names either.

The arrays are built by :mod:`wallcull.hierarchy`; leaves are instances of mesh templates
(:mod:`wallcull.instances`). :func:`load` maps a *prepared* scene (:func:`prepare`, stored by
:mod:`wallcull.prepared`) instead of building it when the source has one that is current.
"""

from __future__ import annotations

import functools
import io
import hashlib
import itertools
import logging
import os
import re
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from . import bounds as bnd
from . import clusters as clusters_mod
from . import hierarchy as tree
from . import prepared
from . import bundled
from . import gltf
from .errors import InputError, WriteFailed
from .hierarchy import spatial_groups  # noqa: F401 - part of this module's interface
from .instances import MeshTable, instance_extremes, instance_points, leaf_bounds

log = logging.getLogger("wallcull")

#: Default branching factor of the automatic spatial hierarchy.
BRANCHING = 8
#: Default cluster size: leaves of more triangles are cut into clusters of at most this many.
CLUSTERS = clusters_mod.AUTO


@dataclass
class Scene:
    """A scene's object hierarchy and geometry. Immutable once built; see :class:`SceneState`.

    Leaves are instances of mesh templates: ``mesh_of[i]`` names leaf ``i``'s template in
    ``meshes`` (:mod:`wallcull.instances`), placed by ``world[i]``. A scene mapped from a prepared
    file (:func:`load`) holds its arrays memory-mapped and its names as a
    :class:`~wallcull.prepared.StringTable`; it reads a mesh's triangles only when asked for them.
    """

    name: str
    names: Sequence[str]  # (n,) a list, or a StringTable when mapped from a prepared file
    parent: np.ndarray  # (n,) int64, -1 at the root
    child_start: np.ndarray  # (n,) int64
    child_count: np.ndarray  # (n,) int64
    children: np.ndarray  # (n - 1,) int64
    is_leaf: np.ndarray  # (n,) bool: carries geometry, has no children
    synthetic: np.ndarray  # (n,) bool: a spatial group, not a node of the file
    local: np.ndarray  # (n, 4, 4) transform relative to the parent
    world: np.ndarray  # (n, 4, 4) rest transform to world
    mesh_of: np.ndarray  # (n,) int64: a leaf's template in ``meshes``, -1 elsewhere
    meshes: MeshTable  # the templates: key -> (vertices (v, 3), faces (f, 3)), local coordinates
    cluster_of: np.ndarray  # (n,) int64: a cluster's index in ``meshes``' clusters, -1 elsewhere
    settings: dict = field(default_factory=dict)
    hierarchy: str = "file"  # "file" or "auto:<branching>"
    cluster_size: int | None = None  # the most triangles a cluster holds; None: leaves whole
    prepared: Path | None = None  # the prepared file the arrays are mapped from, if any

    # ------------------------------------------------------------------ structure

    def __len__(self) -> int:
        return len(self.names)

    def __repr__(self) -> str:
        return (f"Scene({self.name!r}, {len(self)} nodes, {len(self.meshes)} meshes, "
                f"hierarchy {self.hierarchy!r})")

    @cached_property
    def depth(self) -> np.ndarray:
        return tree.depths(self.parent)

    @cached_property
    def size(self) -> np.ndarray:
        """Subtree sizes: node ``i``'s subtree is ``[i, i + size[i])``."""
        return tree.subtree_sizes(self.parent, self.levels)

    @cached_property
    def leaves(self) -> np.ndarray:
        """Leaf node ids in preorder."""
        return np.flatnonzero(self.is_leaf)

    @cached_property
    def leaf_child_count(self) -> np.ndarray:
        """``child_count`` with the leaves' clusters cut off: for a traversal whose answer is
        leaves (a shadow's casters), which unfolding clusters would only slow."""
        return np.where(self.is_leaf, 0, self.child_count)

    @cached_property
    def leaf_range(self) -> tuple[np.ndarray, np.ndarray]:
        """``(start, count)``: the leaves under node ``i`` are ``leaves[start[i]:start[i]+count[i]]``."""
        return self._range(self.is_leaf)

    @cached_property
    def units(self) -> np.ndarray:
        """The nodes with no children, in preorder: what a traversal tests last (clusters, and
        leaves without clusters)."""
        return np.flatnonzero(self.child_count == 0)

    @cached_property
    def unit_range(self) -> tuple[np.ndarray, np.ndarray]:
        """``(start, count)`` of the :attr:`units` under each node, as :attr:`leaf_range`."""
        return self._range(self.child_count == 0)

    def _range(self, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rank = np.cumsum(mask) - mask  # marked nodes before each node
        end = np.concatenate([rank, [int(mask.sum())]])[np.arange(len(self)) + self.size]
        return rank, end - rank

    @cached_property
    def clusters(self) -> np.ndarray:
        """Cluster node ids in preorder: each leaf's, in its mesh's cluster order."""
        return np.flatnonzero(self.cluster_of >= 0)

    @cached_property
    def cluster_leaf(self) -> np.ndarray:
        """``(n,)``: a cluster's leaf (a group of clusters' too), -1 for every other node."""
        out = np.full(len(self), -1, dtype=np.int64)
        c = self.clusters
        if len(c):
            # a node of a leaf's cluster tree lies after its leaf, within the leaf's subtree
            leaves = self.leaves
            at = np.searchsorted(leaves, c) - 1
            out[c] = leaves[at]
        return out

    @cached_property
    def cluster_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """``(first (n,), count (n,))``: per node, the triangles of its leaf's mesh it stands
        for: a cluster's run, a leaf's whole mesh from 0, nothing elsewhere."""
        m = self.meshes
        first = np.zeros(len(self), dtype=np.int64)
        count = np.zeros(len(self), dtype=np.int64)
        count[self.leaves] = m.face_count[self.mesh_of[self.leaves]]
        c = self.clusters
        first[c] = m.cluster_first[self.cluster_of[c]]
        count[c] = m.cluster_count[self.cluster_of[c]]
        return first, count

    @cached_property
    def levels(self) -> list[np.ndarray]:
        """Node ids at each depth."""
        return tree.levels(self.depth)

    @cached_property
    def index(self) -> dict[str, int]:
        """Name -> node id. A node that is also its own geometry leaf maps to the internal node."""
        out: dict[str, int] = {}
        hidden = (self.synthetic | (self.cluster_of >= 0)).tolist()
        for i, (name, skip) in enumerate(zip(self.names, hidden)):
            if not skip:
                out.setdefault(name, i)
        return out

    @cached_property
    def real_cover(self) -> Sequence[np.ndarray]:
        """For each node, the nearest non-synthetic nodes covering its subtree (itself if real)."""
        return _Cover(self)

    @cached_property
    def geometry(self) -> list[str | None]:
        """Per node: the mesh key of a leaf, else None."""
        keys = list(self.meshes)
        return [keys[m] if m >= 0 else None for m in self.mesh_of.tolist()]

    def subtree_leaves(self, nodes: np.ndarray) -> np.ndarray:
        """Leaf ids under each of ``nodes``, concatenated in order."""
        start, count = self.leaf_range
        s, c = start[nodes], count[nodes]
        offsets = np.repeat(s - np.cumsum(c) + c, c)
        return self.leaves[np.arange(int(c.sum())) + offsets]

    @cached_property
    def stats(self) -> dict:
        internal = ~self.is_leaf & (self.cluster_of < 0)
        internal[0] = False  # the base frame is not a node of the model
        kids = self.child_count[internal]
        tris = self.meshes.face_count[self.mesh_of[self.leaves]].sum()
        clusters = len(self.clusters)
        return {
            "nodes": len(self) - 1 - clusters, "internal": int(internal.sum()),
            "leaves": len(self.leaves), "clusters": clusters,
            "cluster_size": self.cluster_size, "synthetic": int(self.synthetic.sum()),
            "depth": int(self.depth[self.cluster_of < 0].max()),
            "branching": float(kids.mean()) if len(kids) else 0.0, "triangles": int(tris),
            "hierarchy": self.hierarchy,
        }

    # ------------------------------------------------------------------ geometry

    @cached_property
    def box(self) -> np.ndarray:
        """``(2, 3)``: the lowest and highest world coordinates of the leaves' points at rest."""
        lo, hi = instance_extremes(self.meshes, self.mesh_of[self.leaves],
                                   self.world[self.leaves])
        return np.stack([lo.min(axis=0), hi.max(axis=0)])

    @cached_property
    def leaf_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo (L, 3), hi (L, 3))``: each leaf's box at rest, in the order of :attr:`leaves`
        (their union is :attr:`box`); made when first asked for (by
        :meth:`SceneState.box`, once a node moved)."""
        return instance_extremes(self.meshes, self.mesh_of[self.leaves], self.world[self.leaves])

    @cached_property
    def leaf_points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(points (N, 3), starts (L + 1,))``: each leaf's vertices in world space, at rest.
        Every instance's vertices at once: for small scenes and tests (a million-node scene's
        would take gigabytes; see :func:`wallcull.instances.instance_points`)."""
        counts = self.meshes.vertex_count[self.mesh_of[self.leaves]]
        starts = np.zeros(len(counts) + 1, dtype=np.int64)
        np.cumsum(counts, out=starts[1:])
        points = np.empty((starts[-1], 3))
        for rows, p, at in instance_points(self.meshes, self.mesh_of[self.leaves],
                                           self.world[self.leaves]):
            points[np.repeat(starts[rows] - at[:-1], np.diff(at)) + np.arange(at[-1])] = p
        return points, starts

    def leaf_mesh(self, leaf: int) -> tuple[np.ndarray, np.ndarray]:
        """``(vertices (v, 3) float64, faces (f, 3) int64)`` of a leaf in its own frame, read on
        demand (from the prepared file, for a mapped scene): what renderers and the oracle draw."""
        return self.meshes.mesh(int(self.mesh_of[leaf]))

    def leaf_vertices(self, leaf: int, world: np.ndarray | None = None) -> np.ndarray:
        """``(v, 3)`` vertices of one leaf in world space (at rest unless ``world`` is given)."""
        m = self.world[leaf] if world is None else world
        return self.leaf_mesh(leaf)[0] @ m[:3, :3].T + m[:3, 3]

    def leaf_triangles(self, leaf: int, world: np.ndarray | None = None) -> np.ndarray:
        """``(f, 3, 3)`` triangles of one leaf in world space."""
        return self.leaf_vertices(leaf, world)[self.leaf_mesh(leaf)[1]]

    def bounds(self, kind: str = "obb") -> bnd.Bounds:
        """Bounds of every node at rest (paper Alg. 1), computed once per kind."""
        cache = self.__dict__.setdefault("_bounds", {})
        if kind not in cache:
            cache[kind] = compute_bounds(self, kind)
        return cache[kind]

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_trimesh(cls, scene, name: str = "scene", hierarchy: str = "auto",
                     branching: int = BRANCHING, settings: Mapping | None = None,
                     clusters: int | str | None = CLUSTERS) -> "Scene":
        """Build from a ``trimesh.Scene`` following its node tree (SPEC section 4).

        ``hierarchy="auto"`` adds a spatial hierarchy under any parent with more than
        ``4 * branching`` children; ``"file"`` keeps the file's tree as it is. Leaves with more
        than ``clusters`` triangles are cut into clusters (None: never; ``"auto"``:
        :func:`wallcull.clusters.resolve`).
        """
        _check_hierarchy(hierarchy, branching)
        return cls.from_nodes(*tree.read_trimesh(scene), name, hierarchy, branching, settings,
                              clusters)

    @classmethod
    def from_nodes(cls, nodes: tree.NodeTable, meshes: MeshTable, name: str = "scene",
                   hierarchy: str = "auto", branching: int = BRANCHING,
                   settings: Mapping | None = None, clusters: int | str | None = CLUSTERS
                   ) -> "Scene":
        """Build from a file's node tree as arrays (:mod:`wallcull.hierarchy`)."""
        _check_hierarchy(hierarchy, branching)
        _check_clusters(clusters)
        label = "file" if hierarchy == "file" else f"auto:{branching}"
        return cls(name=name, settings=dict(settings or {}), hierarchy=label,
                   **tree.build(nodes, meshes, hierarchy, branching, clusters))


def _check_hierarchy(hierarchy: str, branching: int) -> None:
    if hierarchy not in ("auto", "file"):
        raise InputError(f"hierarchy must be 'auto' or 'file', got {hierarchy!r}")
    if branching < 2:
        raise InputError(f"branching must be at least 2, got {branching}")


def _check_clusters(clusters: int | str | None) -> None:
    if clusters is not None:
        parse_clusters(clusters)  # in range, or a one-line InputError


def parse_clusters(value) -> int | str | None:
    """A cluster size setting (``"off"``, None, ``"auto"`` or a number of triangles),
    checked."""
    try:
        return clusters_mod.parse_size(value)
    except ValueError as exc:
        raise InputError(str(exc)) from None


class _Cover(Sequence):
    """:attr:`Scene.real_cover`, computed per synthetic node when asked (they are few)."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self.memo: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.scene)

    def __getitem__(self, i) -> np.ndarray:
        s = self.scene
        i = int(i)
        if not s.synthetic[i]:
            return np.array([i])
        if i not in self.memo:
            kids = s.children[s.child_start[i]:s.child_start[i] + s.child_count[i]]
            self.memo[i] = np.concatenate([self[k] for k in kids])
        return self.memo[i]


def compute_bounds(scene: Scene, kind: str) -> bnd.Bounds:
    """Preprocess bottom-up (paper Alg. 1): leaves from their templates (OBBs: each template
    fitted once, moved by its instances' transforms; :mod:`wallcull.instances`), parents from
    their children."""
    if kind not in bnd.LEAF_FITTERS:
        raise InputError(f"unknown bound type {kind!r}; choose from {', '.join(bnd.KINDS)}")
    out = bnd.Bounds.empty(kind, len(scene))
    fit_units(scene, out, scene.units, scene.world)
    refit(scene, out, np.flatnonzero(scene.child_count > 0), bnd.enclosing_mode(kind))
    return out


def fit_units(scene: Scene, bounds: bnd.Bounds, nodes: np.ndarray, world: np.ndarray) -> None:
    """Fit the bounds of ``nodes``, childless leaves or clusters, to their triangles placed by
    ``world`` (every node's), from their templates (:func:`leaf_bounds`). Every other node is
    bounded by its children (:func:`refit`): a leaf cut into clusters too, so that bounds nest
    and a node outside a plane has every node below it outside."""
    for meshes, template in ((scene.meshes, scene.mesh_of),
                             (scene.meshes.cluster_meshes, scene.cluster_of)):
        these = nodes[template[nodes] >= 0]
        if len(these):
            bounds.put(these, leaf_bounds(bounds.kind, meshes, template[these], world[these]))


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

    Until something moves, a state shares its scene's arrays (bounds, local and world
    transforms: 1.3 GB at a million nodes with their 1.5 million clusters), and the culler
    shares the scene's packed records too (:func:`wallcull.cull.packed`); the first move
    copies them. A move then backs up, checks and re-packs only the rows it changes: the moved
    subtrees and the refit ancestors.
    """

    def __init__(self, scene: Scene, kind: str = "obb"):
        self.scene = scene
        self.kind = kind
        self.bounds = scene.bounds(kind)
        # The leaves' bounds moved rigidly and never re-boxed: what an axis-aligned refit boxes
        # each frame, so that boxes of boxes of boxes do not grow frame after frame.
        self.exact = self.bounds
        self.local = scene.local
        self.world = scene.world
        self._shared = True
        self.version = 0  # counts moves: what caches of the bounds key on
        # rows whose bounds changed since :meth:`changed_rows` last looked (None: too many
        # to list, take them all)
        self._changed: list[np.ndarray] | None = []
        self._changed_count = 0

    @property
    def shared(self) -> bool:
        """Whether the state still reads its scene's arrays (nothing moved yet)."""
        return self._shared

    def _own(self) -> None:
        """Copy the scene's arrays before the first change (copy-on-write)."""
        if self._shared:
            self.bounds, self.exact = self.bounds.copy(), self.exact.copy()
            self.local, self.world = self.local.copy(), self.world.copy()
            self._shared = False

    def _note_changed(self, rows: np.ndarray) -> None:
        if self._changed is not None:
            self._changed.append(rows)
            self._changed_count += len(rows)
            if self._changed_count > len(self.scene) // 2:
                self._changed = None

    def box(self) -> np.ndarray:
        """``(2, 3)``: the lowest and highest world coordinates of the scene as its nodes now
        lie: :attr:`Scene.box` until a node moved; then the leaves at rest by their boxes at
        rest, and each leaf placed elsewhere by the corners of its mesh's own box where it now
        lies (exact for a leaf placed without a turn, a bound otherwise). Kept until the next
        move."""
        if self.shared:
            return self.scene.box
        cache = self.__dict__.get("_box")
        if cache is not None and cache[0] == self.version:
            return cache[1]
        scene = self.scene
        leaves = scene.leaves
        world = self.world[leaves]
        moved = (world != scene.world[leaves]).reshape(len(leaves), 16).any(axis=1)
        lo, hi = scene.leaf_boxes
        lo, hi = lo[~moved], hi[~moved]
        if moved.any():
            at, mesh = world[moved], scene.mesh_of[leaves[moved]]
            low, high = scene.meshes.boxes
            corner = np.array([[i & 1, i >> 1 & 1, i >> 2 & 1] for i in range(8)], bool)
            corners = np.where(corner, high[mesh][:, None], low[mesh][:, None])  # (k, 8, 3)
            p = corners @ at[:, :3, :3].transpose(0, 2, 1) + at[:, None, :3, 3]
            lo, hi = np.concatenate([lo, p.min(axis=1)]), np.concatenate([hi, p.max(axis=1)])
        box = np.stack([lo.min(axis=0), hi.max(axis=0)])
        self.__dict__["_box"] = (self.version, box)
        return box

    def changed_rows(self) -> np.ndarray | None:
        """The sorted ids of the rows whose bounds changed since the last call (None: so many
        that every row should be taken as changed), and forget them: for the one cache that
        follows the bounds row by row (:func:`wallcull.cull.packed`)."""
        rows = self._changed
        self._changed, self._changed_count = [], 0
        if rows is None:
            return None
        return np.unique(np.concatenate(rows)) if rows else np.zeros(0, dtype=np.int64)

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
        nodes = np.array(ids)
        mode = self._mode(refit_mode)
        sub, up = self.reach(nodes, mode)
        rows = np.union1d(sub, up)
        self._own()
        # All or nothing: composed down a chain of nodes, updates that are fine alone can still
        # collapse or overflow a world transform; then the scene stays as it was. Only the rows
        # the move changes are backed up and checked (every other row is as the last move,
        # checked in turn, left it): local transforms of the moved nodes, world transforms
        # and exact bounds of their subtrees, bounds of those and of the refit ancestors.
        saved = (self.local[nodes], self.world[sub], self.bounds.take(rows),
                 self.exact.take(sub))
        try:
            with np.errstate(all="ignore"):
                self._move(nodes, np.array(local), mode, sub, up)
                world, b = self.world[sub], self.bounds
                sound = (np.isfinite(world).all() and np.isfinite(b.center[rows]).all()
                         and np.isfinite(b.half[rows]).all()
                         and np.isfinite(b.radius[rows]).all()
                         and (np.abs(np.linalg.det(world[:, :3, :3])) > 0).all())
        except (np.linalg.LinAlgError, FloatingPointError, ValueError):
            sound = False
        if not sound:
            self.local[nodes], self.world[sub] = saved[0], saved[1]
            self.bounds.put(rows, saved[2])
            self.exact.put(sub, saved[3])
            self._note_changed(rows)
            self.version += 1
            raise InputError("the updates collapse or overflow world transforms in float64")
        return up

    def _mode(self, refit_mode: str | None) -> str:
        mode = refit_mode or bnd.enclosing_mode(self.kind)
        if mode not in ("obb", "aabb", "sphere"):
            raise InputError(f"refit must be 'obb' or 'aabb', got {mode!r}")
        return mode

    def reach(self, nodes: np.ndarray, refit_mode: str | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        """``(sub, up)``: the sorted ids of the nodes in the subtrees of ``nodes`` (whose world
        transforms and bounds a move of ``nodes`` changes) and of the ancestors it refits.
        A move changes no other row."""
        scene, mode = self.scene, self._mode(refit_mode)
        levels, parent = scene.levels, scene.parent
        inside = np.zeros(len(scene), dtype=bool)
        inside[nodes] = True
        for level in levels[1:]:
            inside[level] |= inside[parent[level]]
        # Only the strict ancestors of moved nodes are refit, bottom up; that includes moved
        # nodes above other moved nodes, whose rigid motion alone no longer fits their subtree.
        above = np.zeros(len(scene), dtype=bool)
        above[parent[nodes[nodes > 0]]] = True
        if mode == "aabb":  # moved internal nodes: refit from their children
            above[nodes[~scene.is_leaf[nodes]]] = True
        for level in reversed(levels[1:]):
            above[parent[level[above[level]]]] = True
        return np.flatnonzero(inside), np.flatnonzero(above)

    def move_nodes(self, nodes: np.ndarray, local: np.ndarray,
                   refit_mode: str | None = None) -> np.ndarray:
        """:meth:`move` by node ids and ``(k, 4, 4)`` local transforms, unchecked.

        Where the resulting world motion of a subtree is rigid, its bounds move with it exactly;
        where it is not (a scale changed, or a turn under a non-uniformly scaled parent), its
        leaves are fit again in their new pose, from their templates (:func:`leaf_bounds`).
        """
        mode = self._mode(refit_mode)
        sub, up = self.reach(nodes, mode)
        self._own()
        return self._move(nodes, local, mode, sub, up)

    def _move(self, nodes: np.ndarray, local: np.ndarray, mode: str, sub: np.ndarray,
              up: np.ndarray) -> np.ndarray:
        scene = self.scene
        self._note_changed(np.union1d(sub, up))
        self.local[nodes] = local
        levels, parent = scene.levels, scene.parent
        # Every node in a moved subtree gets a new world transform, top down.
        inside = np.zeros(len(scene), dtype=bool)
        inside[sub] = True
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
        leaves = scene.is_leaf[moving] | (scene.cluster_of[moving] >= 0)  # and their clusters
        self.exact.put(moving[leaves], bnd.transform(self.exact.take(moving[leaves]),
                                                     rot[rigid][leaves], delta[rigid, :3, 3][leaves]))
        if not rigid.all():
            # Under a scaled parent the motion of a subtree is not rigid in world space:
            # fit its leaves again and refit the subtree above them.
            self._refit_leaves(sub[~rigid])
        if mode == "aabb":
            # Moved leaves: the axis-aligned box of their exact bound. Moved internal nodes:
            # refit from their children (they are in ``up``), never a box of last frame's box.
            moved_leaves = nodes[scene.is_leaf[nodes]]
            self.bounds.put(moved_leaves, bnd.axis_aligned(self.exact.take(moved_leaves)))
        refit(scene, self.bounds, up, mode)
        self.version += 1
        return up

    def _refit_leaves(self, nodes: np.ndarray) -> None:
        scene = self.scene
        fit_units(scene, self.bounds, nodes[scene.child_count[nodes] == 0], self.world)
        refit(scene, self.bounds, nodes[scene.child_count[nodes] > 0],
              bnd.enclosing_mode(self.kind))
        fitted = nodes[scene.is_leaf[nodes] | (scene.cluster_of[nodes] >= 0)]
        self.exact.put(fitted, self.bounds.take(fitted))


def node_matrix(value: Any, name: str = "node") -> np.ndarray:
    """A validated local transform: an invertible affine 4x4 matrix, or glTF-style
    ``{"position": [x, y, z], "orientation": [w, x, y, z], "scale": [sx, sy, sz]}`` (scale
    optional), composed as translation x rotation x scale."""
    from .validate import QUATERNION_TOLERANCE
    from .wall import quaternion_matrix

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
    scales = np.linalg.svd(m[:3, :3], compute_uv=False)  # (a determinant would overflow)
    if scales.min() < 1e-12 * max(scales.max(), 1e-300) and scales.max() <= 1e9:
        raise InputError(f"update of {name!r} is singular (a zero scale)")
    if scales.min() < 1e-9 or scales.max() > 1e9 or np.abs(m[:3, 3]).max() > 1e15:
        raise InputError(f"update of {name!r} is out of range: scales must lie between 1e-9 "
                         "and 1e9 and positions within 1e15")
    return m


# --------------------------------------------------------------------------- loading


_READING = threading.Lock()


def _trimesh_load(source, **kwargs):
    """``trimesh.load``, one at a time, naming a glTF mesh's extra primitives by a count
    rather than trimesh's 6 random hex digits: two of those alike drop a primitive (a node of
    2,000 primitives lost one in about eight loads), and the leaf ids would move from one load
    of the same file to the next. (Their names then become ``<node>:<geometry>``:
    :func:`wallcull.hierarchy.read_trimesh`.)"""
    import trimesh

    count = itertools.count(1)
    with _READING:
        random_id, trimesh.util.unique_id = trimesh.util.unique_id, \
            lambda length=12: f"{next(count):0{length}x}"
        try:
            return trimesh.load(source, **kwargs)
        finally:
            trimesh.util.unique_id = random_id


def read_glb(data: bytes):
    """A GLB's bytes read as :func:`load_trimesh` reads files (made plain first: :mod:`.gltf`)."""
    made = gltf.plain_bytes(data, ".glb", _no_file, "the uploaded GLB")
    return _trimesh_load(io.BytesIO(made or data), file_type="glb")


def _no_file(uri: str) -> bytes:
    raise KeyError(f"an upload names no file beside it ({uri!r})")


def load_trimesh(path: str | os.PathLike):
    """Read a scene file with trimesh (SPEC section 4), with a one-line error on failure."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(f"scene file not found: {path}")
    check_archive(path)
    gltf.check_file(path)
    suffix = path.suffix.lower()
    kwargs = {"split_groups": True} if suffix in (".obj", ".zip") else {}
    made = gltf.plain_file(path)  # the file made plain (:mod:`.gltf`); None: read as it is
    if suffix == ".gltf" or (suffix == ".glb" and made is not None):
        kwargs["resolver"] = gltf.resolver(path)  # the files beside it, names decoded
    if made is not None:
        kwargs["file_type"] = "zip" if suffix == ".zip" else "glb"
    try:
        loaded = _trimesh_load(str(path) if made is None else io.BytesIO(made), **kwargs)
    except ModuleNotFoundError as exc:  # trimesh's readers of XML formats (3DXML, ...)
        # (trimesh re-raises a reader's import error from its message alone: no name)
        needs = exc.name or next(iter(re.findall(r"named '([\w.]+)'", str(exc))), None)
        raise InputError(f"cannot read scene {path.name}: trimesh's reader needs "
                         f"{needs or 'a module'}, which this install lacks: "
                         "pip install 'wallcull[formats]'") from None
    except Exception as exc:  # noqa: BLE001 - any parser failure is bad input
        raise InputError(f"cannot read scene {path.name}: {exc}") from None
    if not isinstance(loaded, trimesh.Scene):
        loaded = trimesh.Scene(loaded)
    if not loaded.geometry:
        raise InputError(f"scene {path.name} has no geometry")
    return loaded


#: A zip member that inflates to more than this many times its packed size, once past
#: ``INFLATE_FREE`` bytes, is refused as a zip bomb: the convention of Apache POI's
#: ``ZipSecureFile``. Meshes pack 2 to 10 times (an OBJ's text at most about 20); a bomb's
#: zeros, about 1,000.
INFLATE_RATIO, INFLATE_FREE = 100, 64 * 1024 * 1024


def check_archive(path: Path) -> None:
    """Refuse a zip that would inflate out of all proportion to its size, from its directory
    before a byte of it is inflated (Python's zipfile never inflates past the sizes the
    directory declares). The server's sandbox bounds what a scene may take; the command line
    has no sandbox, and a 1.5 MB zip took 4.8 GB before it was found to be no scene."""
    import zipfile

    if path.suffix.lower() != ".zip" or not zipfile.is_zipfile(path):
        return
    with zipfile.ZipFile(path) as z:
        for info in z.infolist():
            if info.file_size > INFLATE_FREE and \
                    info.file_size > INFLATE_RATIO * max(info.compress_size, 1):
                raise InputError(
                    f"cannot read scene {path.name}: its member {info.filename!r} inflates "
                    f"{info.file_size / max(info.compress_size, 1):,.0f} times, to "
                    f"{info.file_size / 2 ** 30:.1f} GiB: a zip bomb, not a scene (no mesh "
                    f"packs more than {INFLATE_RATIO} times; unpack it yourself if it is real)")


def usable(scene):
    """``scene``, once it is known to have leaves and finite bounds (computed here, in the
    loading process or thread, rather than by the first wall): a file can be well formed and
    still carry no drawable node, NaN vertices or transforms that overflow."""
    if not len(scene.leaves):
        raise InputError(f"scene {scene.name!r} has no node that carries geometry")
    if not np.isfinite(scene.box).all():
        raise InputError(f"scene {scene.name!r} has vertices that are not finite in the world")
    try:
        b = scene.bounds("obb")
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
        raise InputError(f"scene {scene.name!r} cannot be bounded: {exc}") from None
    if not all(np.isfinite(a).all() for a in (b.center, b.axes, b.half, b.radius)):
        raise InputError(f"scene {scene.name!r} is too large to bound in float64")
    return scene


@dataclass(frozen=True)
class Source:
    """Where a scene comes from: a bundled generator (``path`` None) or a scene file."""

    spec: str
    path: Path | None

    @classmethod
    def of(cls, spec: str) -> "Source":
        """The source ``spec`` names (:func:`load`); :class:`InputError` if there is none."""
        try:
            base, count = bundled.parse(spec)
            # one spelling a scene: powerplant*0200 is powerplant*200 (and its prepared file)
            return cls(base if count is None else f"{base}*{count}", None)
        except KeyError:
            pass  # not a bundled scene: a file
        except ValueError as exc:
            raise InputError(str(exc)) from None
        path = Path(spec)
        if not path.exists() and os.sep not in spec and "." not in spec:
            raise InputError(f"unknown scene {spec!r}: not a file, and the bundled scenes are "
                             f"{', '.join([*sorted(bundled.BUNDLED), *bundled.TILED])}")
        if not path.is_file():
            raise InputError(f"scene file not found: {path}")
        return cls(spec, path)

    @property
    def name(self) -> str:
        return self.spec if self.path is None else self.path.stem

    def settings(self) -> dict:
        """The scene's own settings: the bundled scene's, or the file's sidecar."""
        from . import settings as cfg

        return bundled.settings(self.spec) if self.path is None else cfg.sidecar(self.spec)

    def identity(self, hierarchy: str, branching: int, clusters: int | str | None) -> str:
        """The source and build options, not the content: names its prepared file."""
        where = f"bundled:{self.spec}" if self.path is None else f"file:{self.path.resolve()}"
        return f"{where}|{hierarchy}|{branching}|{clusters}"

    def key(self, hierarchy: str, branching: int, clusters: int | str | None) -> dict:
        """What a prepared file must have been built from to be current: the source's content
        (a file's SHA-256, or a generator's name, copies, seed and version), the options, and
        the code that builds it."""
        if self.path is None:
            base, count = bundled.parse(self.spec)
            source = {"generator": base, "copies": count, "seed": 0,
                      "version": bundled.GENERATOR_VERSION}
        else:
            source = {"sha256": _file_hash(self.path)}
        return {"source": source, "hierarchy": hierarchy, "branching": branching,
                "clusters": clusters, "format": PREPARED_FORMAT, "code": _code_version()}

    def read(self) -> tuple[tree.NodeTable, MeshTable]:
        """The source's node tree and meshes (``NAME*K``: one copy read, then tiled as
        arrays): what :meth:`build` builds from, which it leaves as they are."""
        if self.path is None:
            base, count = bundled.parse(self.spec)
            nodes, meshes = tree.read_trimesh(bundled.build(base))
            if count is not None:
                nodes = tree.replicate(nodes, *bundled.copies(base, count))
            return nodes, meshes
        return tree.read_trimesh(load_trimesh(self.path))

    def build(self, hierarchy: str, branching: int, clusters: int | str | None,
              read: tuple | None = None) -> Scene:
        """The scene built from its source, or from what :meth:`read` gave."""
        nodes, meshes = read or self.read()
        with np.errstate(all="ignore"):  # odd files overflow on their way to being refused
            return usable(Scene.from_nodes(nodes, meshes, self.name, hierarchy, branching,
                                           clusters=clusters))

    def prepared(self, hierarchy: str, branching: int, clusters: int | str | None
                 ) -> tuple[Path, dict]:
        """Where the prepared file of these options lies, and the key it must hold."""
        options = (hierarchy, branching, clusters)
        return prepared.cache_path(self.name, self.identity(*options)), self.key(*options)


#: How :func:`load` uses prepared files: ``read`` a current one, also ``write`` one when there
#: is none, or leave them ``off``.
CACHE_MODES = ("read", "write", "off", "map")


def load(spec: str, hierarchy: str = "auto", branching: int = BRANCHING,
         settings: Mapping[str, Any] | None = None, cache: str = "read",
         clusters: int | str | None = CLUSTERS) -> Scene:
    """A bundled scene by name (``wallcull scenes``; ``powerplant*K`` too) or a scene file by
    path, its leaves cut into clusters of at most ``clusters`` triangles (None: whole;
    ``"auto"``, the default: :func:`wallcull.clusters.resolve`). Its
    settings (:mod:`wallcull.settings`) are ``settings`` if given, else the bundled scene's or
    the file's sidecar ``<file>.wallcull.json``.

    With ``cache="read"`` a current prepared file of the source (:func:`prepare`) is mapped
    instead of building the scene; ``"write"`` also writes one when there is none; ``"off"``
    ignores them; ``"map"`` only maps, returning None where there is no current file (the
    server, which prepares scenes in a child process: :mod:`wallcull.sandbox`). A stale or corrupt prepared file is never used: it is
    rebuilt, with a one-line warning on the ``wallcull`` logger."""
    from . import settings as cfg

    if cache not in CACHE_MODES:
        raise ValueError(f"cache must be one of {CACHE_MODES}, got {cache!r}")
    _check_hierarchy(hierarchy, branching)
    _check_clusters(clusters)
    source = Source.of(spec)
    raw = source.settings() if settings is None else settings
    if cache == "off":
        scene = source.build(hierarchy, branching, clusters)
    else:
        path, key = source.prepared(hierarchy, branching, clusters)
        scene, problem = _map_current(path, key, source.name)
        if scene is None and cache == "map":
            return None
        if scene is None:
            scene = source.build(hierarchy, branching, clusters)
            if problem or cache == "write":
                _write_prepared(scene, path, key)
    cfg.parse(raw)  # refuse bad settings when the scene loads, not mid-frame
    scene.settings = dict(raw or {})
    return scene


def load_sizes(spec: str, sizes: Sequence, hierarchy: str = "auto",
               branching: int = BRANCHING) -> dict:
    """``{size: load(spec, clusters=size, cache="off")}`` for each of ``sizes``, the source
    read once (a comparison of cluster sizes, without parsing the file again for each)."""
    from . import settings as cfg

    source = Source.of(spec)
    _check_hierarchy(hierarchy, branching)
    for size in sizes:
        _check_clusters(size)
    raw = source.settings()
    cfg.parse(raw)
    raw = dict(raw or {})
    read = source.read()
    out = {}
    for size in sizes:
        out[size] = scene = source.build(hierarchy, branching, size, read)
        scene.settings = dict(raw)
    return out


def prepare(spec: str, hierarchy: str = "auto", branching: int = BRANCHING,
            force: bool = False, clusters: int | str | None = CLUSTERS
            ) -> tuple[Path, Scene | None]:
    """Write the prepared file of a scene: its hierarchy, clusters, names, OBBs, box and meshes,
    in :func:`wallcull.prepared.cache_dir`. Returns its path and the scene built, or None where a
    current file was already there (and ``force`` is not set)."""
    _check_hierarchy(hierarchy, branching)
    _check_clusters(clusters)
    source = Source.of(spec)
    path, key = source.prepared(hierarchy, branching, clusters)
    if not force and _map_current(path, key, source.name)[0] is not None:
        return path, None
    scene = source.build(hierarchy, branching, clusters)
    _write_prepared(scene, path, key, quiet=False)
    return path, scene


def prepare_path(spec: str) -> str:
    """:func:`prepare` with the default options, answering the file's path only (what a child
    process hands back: :mod:`wallcull.sandbox`)."""
    return str(prepare(spec)[0])


def bounds_of(spec: str, kind: str) -> bnd.Bounds:
    """The bounds of kind ``kind`` of the scene ``spec`` names, loaded as :func:`load` does
    (what a child process computes for the server: :mod:`wallcull.sandbox`)."""
    return load(spec).bounds(kind)


# --------------------------------------------------------------------------- prepared scenes

#: Version of what a prepared scene holds: part of its key.
PREPARED_FORMAT = 3

#: Code whose changes make prepared scenes stale: it decides what they hold (the readers of
#: files included: what glTF is made plain, what a file may hold).
_BUILDERS = ("bounds.py", "clusters.py", "hierarchy.py", "instances.py", "prepared.py", "scene.py",
             "gltf.py", "validate.py", "bundled")


@functools.lru_cache(maxsize=None)
def _code_version() -> str:
    """A hash of the code in :data:`_BUILDERS` (the files there are missing count as none) and
    of the versions of the libraries that read scene files (trimesh, DracoPy)."""
    from importlib import metadata

    h = hashlib.sha256()
    for library in ("trimesh", "DracoPy"):
        try:
            h.update(f"{library} {metadata.version(library)}\0".encode())
        except metadata.PackageNotFoundError:
            h.update(f"{library} none\0".encode())
    here = Path(__file__).parent
    for name in _BUILDERS:
        path = here / name
        for f in sorted(path.rglob("*.py")) if path.is_dir() else [path] * path.is_file():
            h.update(f.relative_to(here).as_posix().encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:32]


def _file_hash(path: Path) -> str:
    """SHA-256 of a scene file, and of the files it names beside it: the buffers of a glTF
    (``.gltf`` or ``.glb``), the material libraries of an OBJ (whose transparency decides
    what occludes)."""
    h = hashlib.sha256()
    files = [path]
    suffix = path.suffix.lower()
    try:
        if suffix in (".gltf", ".glb"):
            doc = gltf.read_document(path) or {}
            files += [gltf.beside(path, b["uri"]) for b in doc.get("buffers", [])
                      if not str(b.get("uri", "data:")).startswith("data:")]
        elif suffix == ".obj":
            with open(path, "rb") as f:
                for line in f:
                    if line.startswith(b"mtllib"):
                        files += [path.parent / name.decode(errors="replace")
                                  for name in line.split()[1:]]
    except (ValueError, TypeError, AttributeError, KeyError, OSError):
        pass  # the reader will say what is wrong with it
    for f in files:
        try:
            with open(f, "rb") as stream:
                while chunk := stream.read(16 << 20):
                    h.update(chunk)
        except OSError:
            h.update(b"missing:" + str(f).encode())
    return h.hexdigest()


def _map_current(path: Path, key: dict, name: str) -> tuple[Scene | None, str | None]:
    """``(scene, None)`` mapped from ``path`` if it holds the scene of ``key``; else
    ``(None, problem)``, ``problem`` None where there is no file, and the file is reported."""
    if not path.exists():
        return None, None
    try:
        if prepared.read_meta(path).get("key") != key:
            problem = "stale (its source or wallcull changed)"
        else:
            return _scene_from_arrays(*prepared.read(path), name, path), None
    except prepared.Corrupt as exc:
        problem = f"corrupt ({exc})"
    except OSError as exc:
        problem = f"unreadable ({exc.strerror or exc})"
    log.warning("wallcull: prepared scene %s is %s: rebuilding it", path, problem)
    return None, problem


def _write_prepared(scene: Scene, path: Path, key: dict, quiet: bool = True) -> None:
    b = scene.bounds("obb")
    names, name_offsets = prepared.encode_strings(scene.names)
    keys, key_offsets = prepared.encode_strings(list(scene.meshes))
    m = scene.meshes
    vertices = np.asarray(m.vertices, dtype=np.float64)
    narrow = vertices.astype(np.float32)
    faces = np.asarray(m.faces)
    arrays = {
        "name_bytes": names, "name_offsets": name_offsets, "parent": scene.parent,
        "child_start": scene.child_start, "child_count": scene.child_count,
        "children": scene.children, "is_leaf": scene.is_leaf, "synthetic": scene.synthetic,
        "local": scene.local, "world": scene.world, "mesh_of": scene.mesh_of,
        "cluster_of": scene.cluster_of, "cluster_start": m.cluster_start,
        "cluster_parent": m.cluster_parent, "cluster_first": m.cluster_first,
        "cluster_count": m.cluster_count,
        "mesh_key_bytes": keys, "mesh_key_offsets": key_offsets,
        "vertex_start": m.vertex_start, "face_start": m.face_start,
        "see_through": m.see_through, "single_sided": m.single_sided,
        # the narrowest types that hold the meshes exactly
        "vertices": narrow if np.array_equal(narrow, vertices) else vertices,
        "faces": faces.astype(np.int32) if not faces.size or (
            faces.min() >= -2**31 and faces.max() < 2**31) else faces,
        "obb_center": b.center, "obb_axes": b.axes, "obb_half": b.half, "obb_radius": b.radius,
        "box": scene.box,
    }
    meta = {"key": key, "hierarchy": scene.hierarchy, "nodes": len(scene),
            "cluster_size": scene.cluster_size}
    try:
        prepared.write(path, arrays, meta)
    except OSError as exc:
        if not quiet:
            raise WriteFailed(f"cannot write {path}: {exc.strerror or exc}", exc.errno) from None
        log.warning("wallcull: cannot write prepared scene %s: %s", path, exc.strerror or exc)


#: What a prepared scene holds: array -> (dtype kinds, shape), ``n`` nodes, ``m`` meshes,
#: ``None`` any length.
_LAYOUT = {
    "name_bytes": ("u", (None,)), "name_offsets": ("i", ("n+1",)), "parent": ("i", ("n",)),
    "child_start": ("i", ("n",)), "child_count": ("i", ("n",)), "children": ("i", ("n-1",)),
    "is_leaf": ("b", ("n",)), "synthetic": ("b", ("n",)), "local": ("f", ("n", 4, 4)),
    "world": ("f", ("n", 4, 4)), "mesh_of": ("i", ("n",)), "cluster_of": ("i", ("n",)),
    "cluster_start": ("i", ("m+1",)), "cluster_parent": ("i", ("c",)),
    "cluster_first": ("i", ("c",)),
    "cluster_count": ("i", ("c",)), "mesh_key_bytes": ("u", (None,)),
    "mesh_key_offsets": ("i", ("m+1",)), "vertex_start": ("i", ("m+1",)),
    "face_start": ("i", ("m+1",)), "see_through": ("b", ("m",)),
    "single_sided": ("b", ("m",)), "vertices": ("f", (None, 3)),
    "faces": ("i", (None, 3)), "obb_center": ("f", ("n", 3)), "obb_axes": ("f", ("n", 3, 3)),
    "obb_half": ("f", ("n", 3)), "obb_radius": ("f", ("n",)), "box": ("f", (2, 3)),
}


def _scene_from_arrays(arrays: dict, meta: dict, name: str, path: Path) -> Scene:
    """A scene over a prepared file's arrays (nothing copied), once their layout is checked."""
    try:
        sizes = {"n": len(arrays["parent"]), "m": len(arrays["vertex_start"]) - 1,
                 "c": len(arrays["cluster_first"])}
        sizes.update({"n+1": sizes["n"] + 1, "n-1": sizes["n"] - 1, "m+1": sizes["m"] + 1})
        for key, (kind, shape) in _LAYOUT.items():
            a = arrays[key]
            want = tuple(a.shape[k] if d is None else sizes.get(d, d) for k, d in enumerate(shape))
            if a.dtype.kind != kind or a.shape != want:
                raise prepared.Corrupt(f"array {key} is {a.dtype}{list(a.shape)}")
        if set(arrays) != set(_LAYOUT):
            raise prepared.Corrupt("unexpected arrays")
        names = prepared.StringTable(arrays["name_bytes"], arrays["name_offsets"])
        keys = list(prepared.StringTable(arrays["mesh_key_bytes"], arrays["mesh_key_offsets"]))
        meshes = MeshTable(keys, arrays["vertex_start"], arrays["vertices"], arrays["face_start"],
                           arrays["faces"], arrays["cluster_start"], arrays["cluster_parent"],
                           arrays["cluster_first"], arrays["cluster_count"],
                           arrays["see_through"], arrays["single_sided"])
        scene = Scene(name=name, names=names, parent=arrays["parent"],
                      child_start=arrays["child_start"], child_count=arrays["child_count"],
                      children=arrays["children"], is_leaf=arrays["is_leaf"],
                      synthetic=arrays["synthetic"], local=arrays["local"], world=arrays["world"],
                      mesh_of=arrays["mesh_of"], meshes=meshes, cluster_of=arrays["cluster_of"],
                      hierarchy=str(meta["hierarchy"]), cluster_size=meta.get("cluster_size"),
                      prepared=path)
    except (KeyError, TypeError, IndexError) as exc:
        raise prepared.Corrupt(f"unexpected layout ({type(exc).__name__}: {exc})") from None
    scene.__dict__["_bounds"] = {"obb": bnd.Bounds("obb", arrays["obb_center"], arrays["obb_axes"],
                                                   arrays["obb_half"], arrays["obb_radius"])}
    scene.__dict__["box"] = arrays["box"]
    return scene
