"""Clusters: a mesh's triangles cut into small, spatially compact runs, so that a tile draws
what it shows and little more.

Scene files come in coarse pieces (a car body as one mesh, a building as a dozen), and a tile's
render node draws every triangle of every leaf in its list. So every mesh template with more
than ``size`` triangles is split into clusters of at most ``size`` triangles, and its faces are
reordered so that each cluster is one contiguous run of its index buffer. The clusters become
children of their leaf in the object hierarchy (:func:`wallcull.hierarchy.build`), bounded like
any node, and the traversal culls them in the pass it already makes; a tile then gets, for each
leaf it shows only in part, the triangle ranges of the clusters it sees (:mod:`wallcull.cull`).
Instances share their template's clusters, as they share its triangles.

The split is a k-d tree on the triangles' centroids: a run is cut at a median of its axis of
largest spread, in proportion to the clusters each side receives, until every run holds at most
``size`` triangles. So clusters are balanced (between about ``size / 2`` and ``size``
triangles), compact (their boxes small), and consecutive clusters are neighbours in space: the
clusters a tile sees tend to be runs, which merge into fewer draw ranges. A mesh of more than
``branching`` clusters gets a tree of them (:func:`tree`): consecutive clusters grouped
``branching`` at a time, level by level, so that a traversal unfolds a big mesh step by step
as it does the scene's own nodes. A group, too, is one run of triangles. A meshlet builder
(meshoptimizer's) optimises for a GPU's vertex reuse within 64 to 256 vertices, not for boxes
that a frustum culls; at the sizes measured best here (``docs/clusters.md``) the spatial split
is what counts.
"""

from __future__ import annotations

import numpy as np

#: The sizes a scene may ask for; ``off`` (None) keeps leaves whole.
MIN_SIZE, MAX_SIZE = 32, 4096
#: ``auto``, the default: clusters of :data:`AUTO_SIZE` triangles, coarser (the size doubled)
#: while the scene would get more cluster nodes than :func:`budget` allows.
AUTO = "auto"
#: Triangles per cluster with ``auto``: the smallest size that holds the measured targets on
#: every scene (docs/clusters.md); the traversal lists small clusters whole (wallcull.cull.FINE)
AUTO_SIZE = 32
#: ... and at most this many cluster nodes, or twice the scene's own nodes if more: a scene of
#: many instances of mid-sized meshes gets coarser clusters, not a hierarchy (and prepared file)
#: many times its size, nor a cull that unfolds them all. The power plant (3,899 leaves of 250
#: triangles on average) gets 64: on 8 x 8 its cull takes 0.61 ms against 0.77 ms with 32, for
#: 1.13x the frustum floor on the orbit instead of 1.11x (docs/clusters.md).
BUDGET = 1 << 14


def budget(nodes: int) -> int:
    """The most cluster nodes ``auto`` gives a scene of ``nodes`` nodes."""
    return max(BUDGET, 2 * nodes)


def tree_nodes(faces: np.ndarray, size: int, branching: int) -> np.ndarray:
    """How many nodes each mesh's cluster tree has (:func:`tree`), from its faces (exact)."""
    count = np.where(faces > size, -(-faces // size), 0)
    total = count.copy()
    level = count
    while (level > branching).any():
        level = np.where(level > branching, -(-level // branching), 0)
        total += level
    return total


def resolve(size, faces: np.ndarray, instances: np.ndarray, nodes: int, branching: int
            ) -> int | None:
    """The cluster size a scene gets for the setting ``size`` (None, a number, or ``auto``),
    its meshes having ``faces`` triangles and ``instances`` leaves each."""
    if size != AUTO:
        return size
    size = AUTO_SIZE
    while size < MAX_SIZE and (instances * tree_nodes(faces, size, branching)).sum() \
            > budget(nodes):
        size *= 2
    return size


def parse_size(value) -> int | str | None:
    """A cluster size setting: ``"off"`` (or None), ``"auto"``, or a number of triangles in
    ``[MIN_SIZE, MAX_SIZE]``. Raises :class:`ValueError` with a one-line reason."""
    if value is None or (isinstance(value, str) and value.strip().lower() == "off"):
        return None
    if isinstance(value, str) and value.strip().lower() == AUTO:
        return AUTO
    try:
        size = int(value)
        if isinstance(value, float) and value != size:
            raise ValueError
    except (TypeError, ValueError):
        raise ValueError(f"cluster size must be 'off', 'auto' or a whole number of triangles, "
                         f"got {value!r}") from None
    if not MIN_SIZE <= size <= MAX_SIZE:
        raise ValueError(f"cluster size must be 'off', 'auto' or between {MIN_SIZE} and "
                         f"{MAX_SIZE} triangles, got {size}")
    return size


def split(centroids: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Cut ``(f, 3)`` triangle centroids into runs of at most ``size``.

    Returns ``(order (f,), starts (c + 1,))``: the triangles reordered so that cluster ``k`` is
    ``order[starts[k]:starts[k + 1]]``, clusters in k-d order (neighbours in space come
    together). One cluster (``order`` the identity) when ``f <= size``."""
    f = len(centroids)
    order = np.arange(f)
    if f <= size:
        return order, np.array([0, f], dtype=np.int64)
    bounds = [0]
    stack = [(0, f, -(-f // size))]  # (first, end, clusters), left before right
    while stack:
        lo, hi, parts = stack.pop()
        if parts == 1:
            bounds.append(hi)
            continue
        run = order[lo:hi]
        c = centroids[run]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        first = parts // 2
        # the first side gets ``first`` clusters' share, so neither side exceeds its clusters
        cut = (hi - lo) * first // parts
        part = np.argpartition(c[:, axis], cut - 1) if 0 < cut < hi - lo else np.arange(hi - lo)
        order[lo:hi] = run[part]
        stack.append((lo + cut, hi, parts - first))
        stack.append((lo, lo + cut, first))
    return order, np.asarray(bounds, dtype=np.int64)


def tree(starts: np.ndarray, branching: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The clusters ``starts`` (CSR offsets of consecutive runs of faces) under groups of at
    most ``branching``, level by level, until at most ``branching`` nodes are left on top.

    Returns the tree in preorder as ``(parent, first, count)``: each node's parent (an index
    into these arrays, -1 on top), first face and faces. Its childless nodes are the clusters,
    in order; every group is the run of its children's faces."""
    level = [(int(a), int(b - a), []) for a, b in zip(starts[:-1], starts[1:])]
    while len(level) > branching:
        groups = -(-len(level) // branching)
        cuts = np.linspace(0, len(level), groups + 1).round().astype(int)  # even groups
        level = [(level[a][0], sum(c for _, c, _ in level[a:b]), level[a:b])
                 for a, b in zip(cuts[:-1], cuts[1:])]
    parent, first, count = [], [], []
    stack = [(node, -1) for node in reversed(level)]
    while stack:
        (f, c, kids), up = stack.pop()
        parent.append(up)
        first.append(f)
        count.append(c)
        stack.extend((kid, len(parent) - 1) for kid in reversed(kids))
    return (np.array(parent, dtype=np.int64), np.array(first, dtype=np.int64),
            np.array(count, dtype=np.int64))


def cluster_faces(vertices: np.ndarray, faces: np.ndarray, size: int | None, branching: int
                  ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """One template's faces reordered into clusters, and the tree of its clusters
    (:func:`tree`): ``(faces (f, 3), (parent, first, count))``. No clusters (empty arrays)
    when ``size`` is None or the template has at most ``size`` faces: its leaf stays whole."""
    faces = np.asarray(faces)
    if size is None or len(faces) <= size:
        none = np.zeros(0, dtype=np.int64)
        return faces, (none, none, none)
    centroids = np.asarray(vertices, dtype=np.float64)[faces].mean(axis=1)
    order, starts = split(centroids, size)
    return faces[order], tree(starts, branching)
