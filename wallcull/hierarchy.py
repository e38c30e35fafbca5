"""The object hierarchy built from a file's node tree, with numpy over whole arrays.

The file's nodes come in as a :class:`NodeTable` (read from a ``trimesh.Scene`` by
:func:`read_trimesh`, or tiled by a generator with :func:`replicate`) and leave as the flat
depth-first preorder arrays of :class:`wallcull.scene.Scene` (:func:`build`). On the way, as
SPEC section 4 and the README describe:

1. a node that carries geometry *and* has children becomes an internal node whose first child
   is a leaf of the same name carrying that geometry;
2. subtrees without geometry are dropped: they can never be visible;
3. (``hierarchy="auto"``) a parent with more than ``4 * branching`` children gets a spatial
   hierarchy of *synthetic* groups (:func:`spatial_groups`), named ``<parent>#g<k>``;
4. the nodes are put in depth-first preorder, children in their file order;
5. (``clusters``) every leaf whose mesh template has clusters (:mod:`wallcull.clusters`) gets
   their tree below it, named ``#c<k>``, in the template's preorder, right after it.

Only reading a trimesh graph and the spatial grouping of wide parents loop in Python (per node
and per group); everything else is a handful of numpy calls per tree level.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from .clusters import resolve as resolve_clusters
from .errors import InputError
from .instances import MeshTable, instance_extremes
from .validate import MAX_DEPTH

# trimesh names the extra primitives of a multi-primitive glTF mesh "<node>_<6 random hex>";
# the names change on every load, so they are replaced with "<node>:<geometry name>".
_RANDOM_SUFFIX = re.compile(r"^(?P<node>.*)_[0-9a-f]{6}$")


@dataclass
class NodeTable:
    """A file's node tree as arrays, parents before children (node 0 is the base frame).

    Siblings are ordered by index. ``mesh`` names a template of the scene's :class:`MeshTable`.
    """

    names: list[str]  # (n,)
    parent: np.ndarray  # (n,) int64, -1 at node 0
    local: np.ndarray  # (n, 4, 4) float64, transform relative to the parent
    mesh: np.ndarray  # (n,) int64 template index, -1 for none

    def __len__(self) -> int:
        return len(self.names)


def read_trimesh(scene) -> tuple[NodeTable, MeshTable]:
    """The node tree and mesh templates of a ``trimesh.Scene``, in depth-first order from its
    base frame (children in the graph's order). Meshes without vertices count as none; a mesh
    with a vertex that is not finite, a face that is no triangle or that names a vertex it has
    not, or a name that is not Unicode, is refused (:class:`InputError`, naming it): dropped,
    it would take its nodes with it in silence, and kept, it would be drawn and occlude wrong."""
    meshes, see_through, single_sided = {}, [], []
    for key, geom in scene.geometry.items():
        vertices = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), dtype=np.float64)
        faces = np.asarray(getattr(geom, "faces", np.zeros((0, 3))), dtype=np.int64)
        if len(vertices):
            _check_mesh(_text(key, "mesh"), vertices, faces)
            meshes[key] = (vertices.reshape(-1, 3), faces.reshape(-1, 3))
            see_through.append(_see_through(geom))
            single_sided.append(_single_sided(geom))
    index = {k: i for i, k in enumerate(meshes)}
    forest = scene.graph.transforms
    edge_data, node_data, parents = forest.edge_data, forest.node_data, forest.parents
    children = forest.children
    eye = np.eye(4)
    names, parent, local, mesh = [], [], [], []
    stack = [(scene.graph.base_frame, -1, 0)]
    reached = set()
    while stack:
        node, up, depth = stack.pop()
        reached.add(node)
        if depth > MAX_DEPTH + 1:  # (below the base frame)
            raise InputError(f"the scene's nodes are over {MAX_DEPTH:,} deep; a scene's may be "
                             f"at most {MAX_DEPTH:,}")
        data = edge_data.get((parents.get(node), node), {}) if up >= 0 else {}
        matrix = data.get("matrix", eye)
        geom = data.get("geometry", node_data.get(node, {}).get("geometry"))
        name = _text(str(node), "node")
        if up >= 0 and geom is not None:
            match = _RANDOM_SUFFIX.match(name)
            if match and match["node"] == names[up] and np.allclose(matrix, eye):
                name = f"{match['node']}:{geom}"
        at = len(names)
        names.append(name)
        parent.append(up)
        local.append(matrix)
        mesh.append(index.get(geom, -1))
        stack.extend((child, at, depth + 1) for child in reversed(children.get(node, ())))
    lost = [n for n in scene.graph.nodes_geometry if n not in reached]
    if lost:  # a reader left them hanging from a parent it dropped: geometry lost in silence
        raise InputError(f"{len(lost)} node(s) with geometry ({_text(str(lost[0]), 'node')!r}"
                         f"{', ...' if len(lost) > 1 else ''}) hang from no root of the scene "
                         "as read (their nodes form a cycle, or the reader dropped a parent)")
    return (NodeTable(names, np.array(parent, dtype=np.int64),
                      np.array(local, dtype=np.float64).reshape(-1, 4, 4),
                      np.array(mesh, dtype=np.int64)),
            MeshTable.from_meshes(meshes, see_through, single_sided))


def _text(name: str, what: str) -> str:
    """``name``, if it is Unicode that can be written down (UTF-8): JSON lets a file name a
    node with half a surrogate pair, which no prepared file, packet or page can hold."""
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(f"{what} name {name!r} is not valid Unicode (half a surrogate pair)"
                         ) from None
    return name


def _check_mesh(key: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    if not np.isfinite(vertices).all():
        bad = int(np.flatnonzero(~np.isfinite(vertices).all(axis=-1))[0])
        raise InputError(f"mesh {key!r} has a vertex that is not finite (vertex {bad}: "
                         f"{vertices[bad].tolist()})")
    if not faces.size:
        return
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"mesh {key!r} has faces that are not triangles (shape "
                         f"{list(faces.shape)})")
    lo, hi = int(faces.min()), int(faces.max())
    if lo < 0 or hi >= len(vertices):
        raise InputError(f"mesh {key!r} has a face naming vertex {lo if lo < 0 else hi}, "
                         f"outside its {len(vertices)} vertices")


#: An MTL illumination model with transparency (glass, refraction).
_CLEAR_MODELS = {4, 6, 7, 9}


def _see_through(geom) -> bool:
    """Whether a mesh's material may show what lies behind it, so that it must never occlude:
    a glTF material whose ``alphaMode`` is ``BLEND`` or ``MASK``, or an OBJ material (MTL)
    with a dissolve ``d`` below 1, a transparency ``Tr`` above 0, an alpha map ``map_d``, a
    transmission filter ``Tf`` below 1 or an illumination model with transparency (4, 6, 7,
    9). Any value that cannot be read counts as see-through."""
    material = getattr(getattr(geom, "visual", None), "material", None)
    if material is None:
        return False
    if str(getattr(material, "alphaMode", None) or "OPAQUE").upper() in ("BLEND", "MASK"):
        return True
    mtl = getattr(material, "kwargs", None) or {}

    def numbers(key):
        value = mtl.get(key)
        values = value if isinstance(value, (list, tuple, np.ndarray)) else [value]
        return [float(v) for v in values if v is not None]

    try:
        return (any(v < 1 for v in numbers("d")) or any(v > 0 for v in numbers("tr"))
                or "map_d" in mtl or any(v < 1 for v in numbers("tf"))
                or any(int(v) in _CLEAR_MODELS for v in numbers("illum")))
    except (TypeError, ValueError):
        return True


def _single_sided(geom) -> bool:
    """Whether a mesh is a glTF primitive whose material is not ``doubleSided`` (glTF's
    default material, of a primitive that names none, is not): glTF asks renderers to cull
    its back faces, so they hide nothing. trimesh marks what its glTF reader made with
    ``from_gltf_primitive`` in the mesh's metadata. Other formats say nothing of sides: their
    meshes are drawn, and occlude, with both faces."""
    if "from_gltf_primitive" not in (getattr(geom, "metadata", None) or {}):
        return False
    material = getattr(getattr(geom, "visual", None), "material", None)
    return getattr(material, "doubleSided", None) is not True


def replicate(nodes: NodeTable, matrices: np.ndarray, roots: list[str]) -> NodeTable:
    """The base frame with ``len(roots)`` copies of the subtree of node 1 (its only child).

    Copy ``k`` has the root name ``roots[k]`` and the root transform ``matrices[k]``; names
    that start with the original root's name get that prefix replaced, so copies stay distinct,
    as a scene graph needs. The result is the table :func:`read_trimesh` gives for a scene
    built that way, copies in order."""
    if len(nodes) < 2 or (nodes.parent[1:] == 0).sum() != 1:
        raise ValueError("replicate needs a tree whose base frame has exactly one child")
    sub = len(nodes) - 1
    old = nodes.names[1]
    tail = [name[len(old):] if name.startswith(old) else None for name in nodes.names[1:]]
    names = [nodes.names[0]]
    for root in roots:
        names += [root + t if t is not None else n for t, n in zip(tail, nodes.names[1:])]
    k = len(roots)
    shift = np.repeat(np.arange(k, dtype=np.int64) * sub, sub)
    parent = np.tile(nodes.parent[1:], k)
    parent = np.where(parent > 0, parent + shift, 0)
    local = np.concatenate([nodes.local[:1], np.tile(nodes.local[1:], (k, 1, 1))])
    local[1 + np.arange(k) * sub] = matrices
    return NodeTable(names, np.concatenate([[-1], parent]), local,
                     np.concatenate([nodes.mesh[:1], np.tile(nodes.mesh[1:], k)]))


# --------------------------------------------------------------------------- tree arrays


def depths(parent: np.ndarray) -> np.ndarray:
    """``(n,)`` edges from each node up to the root (``parent[root] = -1``)."""
    depth = np.zeros(len(parent), dtype=np.int64)
    node = np.arange(len(parent))
    up = parent.copy()
    while len(node):
        going = up >= 0
        node, up = node[going], up[going]
        depth[node] += 1
        up = parent[up]
    return depth


def levels(depth: np.ndarray) -> list[np.ndarray]:
    """Node ids at each depth, ascending within a level."""
    order = np.argsort(depth, kind="stable")
    cuts = np.searchsorted(depth[order], np.arange(1, int(depth.max(initial=0)) + 1))
    return np.split(order, cuts)


def subtree_sizes(parent: np.ndarray, by_level: list[np.ndarray]) -> np.ndarray:
    """``(n,)`` nodes in each node's subtree, itself included."""
    size = np.ones(len(parent), dtype=np.int64)
    for level in reversed(by_level[1:]):
        np.add.at(size, parent[level], size[level])
    return size


def world_transforms(parent: np.ndarray, local: np.ndarray,
                     by_level: list[np.ndarray]) -> np.ndarray:
    """``(n, 4, 4)`` transforms to the world: each parent's times the node's local one."""
    world = np.empty_like(local)
    world[by_level[0]] = local[by_level[0]]
    for level in by_level[1:]:
        world[level] = world[parent[level]] @ local[level]
    return world


def preorder(parent: np.ndarray, rank: np.ndarray) -> np.ndarray:
    """Depth-first preorder of a tree rooted at node 0: ``order`` such that ``order[k]`` is the
    ``k``-th node visited, children in ascending ``rank``."""
    n = len(parent)
    by_level = levels(depths(parent))
    size = subtree_sizes(parent, by_level)
    kids = np.lexsort((rank, parent))[1:]  # node 0 (parent -1) sorts first
    # a child's offset in its parent's subtree: 1 + the sizes of its earlier siblings
    before = np.cumsum(size[kids]) - size[kids]
    first = np.r_[True, parent[kids][1:] != parent[kids][:-1]]
    offset = np.zeros(n, dtype=np.int64)
    offset[kids] = 1 + before - before[np.maximum.accumulate(np.where(first, np.arange(len(kids)), 0))]
    position = np.zeros(n, dtype=np.int64)
    for level in by_level[1:]:
        position[level] = position[parent[level]] + offset[level]
    order = np.empty(n, dtype=np.int64)
    order[position] = np.arange(n)
    return order


# --------------------------------------------------------------------------- building


def build(nodes: NodeTable, meshes: MeshTable, hierarchy: str = "auto", branching: int = 8,
          clusters: int | str | None = None) -> dict:
    """The flat preorder arrays of a :class:`wallcull.scene.Scene` (its constructor's keyword
    arguments but ``name`` and ``settings``) from a file's node tree, with leaves cut into
    clusters of at most ``clusters`` triangles (None: whole; ``"auto"``: see
    :func:`wallcull.clusters.resolve`)."""
    names = list(nodes.names)
    parent, local, mesh = nodes.parent, nodes.local, nodes.mesh
    n = len(names)
    rank = np.arange(n, dtype=np.int64)
    # 1. own geometry under children: a leaf of the same name, first among the children
    has_kids = np.bincount(parent[1:], minlength=n) > 0
    split = np.flatnonzero(has_kids & (mesh >= 0))
    if len(split):
        names += [names[i] for i in split]
        parent = np.concatenate([parent, split])
        local = np.concatenate([local, np.broadcast_to(np.eye(4), (len(split), 4, 4))])
        mesh = np.concatenate([mesh, mesh[split]])
        mesh[split] = -1
        rank = np.concatenate([rank, np.full(len(split), -1)])
    # 2. drop subtrees without geometry
    by_level = levels(depths(parent))
    keep = mesh >= 0
    keep[0] = True
    for level in reversed(by_level[1:]):
        keep[parent[level[keep[level]]]] = True
    if not keep.all():
        renumber = np.cumsum(keep) - 1
        names = [name for name, k in zip(names, keep) if k]
        parent = np.where(parent[keep] >= 0, renumber[np.maximum(parent[keep], 0)], -1)
        local, mesh, rank = local[keep], mesh[keep], rank[keep]
        by_level = levels(depths(parent))
    synthetic = np.zeros(len(names), dtype=bool)
    world = world_transforms(parent, local, by_level)
    # 3. spatial groups under wide parents
    if hierarchy == "auto":
        grouped = _group_wide_parents(names, parent, rank, mesh, world, meshes, by_level,
                                      branching, 4 * branching)
        if grouped is not None:
            names, parent, rank, new = grouped
            local = np.concatenate([local, np.broadcast_to(np.eye(4), (new, 4, 4))])
            mesh = np.concatenate([mesh, np.full(new, -1)])
            synthetic = np.concatenate([synthetic, np.ones(new, dtype=bool)])
            # A group's frame is the identity relative to its parent: it and everything under
            # it keep their world transforms; a group's is that of the file node above it.
            above = parent[-new:]
            while synthetic[above].any():
                above = np.where(synthetic[above], parent[above], above)
            world = np.concatenate([world, world[above]])
    # 4. depth-first preorder
    order = preorder(parent, rank)
    new_id = np.empty(len(order), dtype=np.int64)
    new_id[order] = np.arange(len(order))
    parent = np.where(parent[order] >= 0, new_id[np.maximum(parent[order], 0)], -1)
    local, mesh, synthetic = local[order], mesh[order], synthetic[order]
    world = world[order]
    used, mesh_of = np.unique(mesh, return_inverse=True)
    mesh_of = mesh_of.reshape(-1) - (used[0] < 0)  # -1 stays -1 when some node has no mesh
    meshes = meshes.subset(used[used >= 0])
    size = resolve_clusters(clusters, meshes.face_count,
                            np.bincount(mesh_of[mesh_of >= 0], minlength=len(meshes)),
                            len(parent), branching)
    out = dict(names=[names[i] for i in order], parent=parent, is_leaf=mesh >= 0,
               synthetic=synthetic, local=local, world=world, mesh_of=mesh_of.astype(np.int64),
               meshes=meshes.clustered(size, branching))
    # 5. clusters under their leaves
    out = _with_clusters(**out) if out["meshes"].clusters else \
        dict(out, cluster_of=np.full(len(parent), -1, dtype=np.int64))
    return dict(out, **_children(out["parent"]), cluster_size=size)


def _children(parent: np.ndarray) -> dict:
    """Children in CSR form of a tree in preorder: ``child_start``, ``child_count``,
    ``children``, each node's children in preorder."""
    child_count = np.bincount(parent[1:], minlength=len(parent)).astype(np.int64)
    child_start = np.zeros(len(parent), dtype=np.int64)
    np.cumsum(child_count[:-1], out=child_start[1:])
    children = np.argsort(parent[1:], kind="stable").astype(np.int64) + 1
    return dict(child_start=child_start, child_count=child_count, children=children)


def _with_clusters(names, parent, is_leaf, synthetic, local, world, mesh_of, meshes) -> dict:
    """Step 5 of :func:`build`: each leaf's cluster tree inserted below it, in preorder right
    after it (a leaf has no other children), so every subtree stays a contiguous range."""
    n = len(parent)
    per_mesh = np.diff(meshes.cluster_start)
    count = np.where(is_leaf, per_mesh[np.maximum(mesh_of, 0)], 0)
    position = np.arange(n) + np.cumsum(count) - count  # old node -> new id
    total = n + int(count.sum())
    leaf = np.repeat(np.arange(n), count)  # each cluster's leaf, old ids
    k = np.arange(len(leaf)) - np.repeat(np.cumsum(count) - count, count)  # index in its leaf
    at = position[leaf] + 1 + k  # each cluster's new id
    new_parent = np.empty(total, dtype=np.int64)
    new_parent[position] = np.where(parent >= 0, position[np.maximum(parent, 0)], -1)
    up = np.asarray(meshes.cluster_parent, dtype=np.int64)[meshes.cluster_start[mesh_of[leaf]] + k]
    new_parent[at] = np.where(up >= 0, position[leaf] + 1 + up, position[leaf])

    def spread(old, fill):
        a = np.empty((total, *old.shape[1:]), dtype=old.dtype)
        a[position] = old
        a[at] = fill
        return a

    labels = np.array([f"#c{j}" for j in range(int(count.max()))], dtype=object)
    all_names = np.empty(total, dtype=object)
    all_names[position] = names
    all_names[at] = labels[k]
    cluster_of = np.full(total, -1, dtype=np.int64)
    cluster_of[at] = meshes.cluster_start[mesh_of[leaf]] + k
    return dict(names=all_names.tolist(), parent=new_parent, is_leaf=spread(is_leaf, False),
                synthetic=spread(synthetic, False), local=spread(local, np.eye(4)),
                world=spread(world, world[leaf]), mesh_of=spread(mesh_of, -1), meshes=meshes,
                cluster_of=cluster_of)


def _group_wide_parents(names, parent, rank, mesh, world, meshes, by_level, branching,
                        threshold):
    """Step 3 of :func:`build`: ``(names, parent, rank, added)`` with synthetic groups appended,
    or None where no parent has more than ``threshold`` children."""
    n = len(names)
    kids_of = np.bincount(parent[1:], minlength=n)
    wide = np.flatnonzero(kids_of > threshold)
    if not len(wide):
        return None
    centers = _subtree_centers(parent, mesh, world, meshes, by_level)
    names, parent, rank = list(names), list(parent), list(rank)
    order = np.lexsort((np.asarray(rank), np.asarray(parent)))
    siblings = np.asarray(parent)[order]
    for p in wide:
        lo, hi = np.searchsorted(siblings, [p, p + 1])
        kids = order[lo:hi]
        _attach(names, parent, rank, int(p), kids, spatial_groups(centers[kids], branching))
    return names, np.asarray(parent, dtype=np.int64), np.asarray(rank, dtype=np.int64), \
        len(names) - n


def _attach(names, parent, rank, at: int, kids: np.ndarray, groups) -> None:
    count = 0
    for group in groups:
        if isinstance(group, np.ndarray) and len(group) == 1:
            node = int(kids[group[0]])
        else:
            node = len(names)
            names.append(f"{names[at]}#g{count}")
            parent.append(at)
            rank.append(0)
            if isinstance(group, np.ndarray):
                for j, k in enumerate(kids[group]):
                    parent[k], rank[k] = node, j
            else:
                _attach(names, parent, rank, node, kids, group)
        # Children keep their world pose: a synthetic group has the identity local frame
        # relative to its parent, so re-parenting under it changes nothing.
        parent[node], rank[node] = at, count
        count += 1


def _subtree_centers(parent, mesh, world, meshes: MeshTable, by_level) -> np.ndarray:
    """``(n, 3)``: the centre of the axis-aligned box of each subtree's world-space points."""
    n = len(parent)
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    leaves = np.flatnonzero(mesh >= 0)
    lo[leaves], hi[leaves] = instance_extremes(meshes, mesh[leaves], world[leaves])
    for level in reversed(by_level[1:]):
        np.minimum.at(lo, parent[level], lo[level])
        np.maximum.at(hi, parent[level], hi[level])
    return (lo + hi) / 2


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
