"""Leaves as instances of mesh templates: the templates once, the instances by transform.

A scene file (or a generator) stores each distinct mesh once and places it at many nodes; a
million-node plant has a few dozen templates. Here the templates live in one
:class:`MeshTable` (their vertices and faces concatenated), and nothing ever holds every
instance's world-space vertices at once:

* eigenvector OBBs are fitted once per template and moved by each instance's transform
  (:func:`moved_boxes`). A rigid or uniformly scaled motion maps the eigenvector OBB of a point
  set onto the eigenvector OBB of the moved points, so this is the box a fit of the moved points
  gives; so does a non-uniform scale along the template box's own axes (a pipe stretched along
  its length), the common case in CAD and in the bundled scenes. Any other affine map (a shear
  relative to the box) turns the box into a parallelepiped: those few instances are fitted again
  from their points;
* whatever needs points (the other bound types, the scene's box) gets them in chunks of bounded
  size (:func:`instance_points`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Iterator

import numpy as np

from . import bounds as bnd

#: Points per chunk of :func:`instance_points`: 2^21 points are 48 MB of float64.
CHUNK_POINTS = 1 << 21

#: Templates placed at least this often are transformed by matrix products (see
#: :func:`instance_points`).
BATCH = 16

#: Relative off-diagonal size of ``(A Q^T)^T (A Q^T)`` up to which an instance's transform ``A``
#: counts as mapping its template box ``Q`` onto a box (rounding is ~1e-16; a shear is far more).
SHEAR_TOLERANCE = 1e-9

_EPS = np.finfo(np.float64).eps


@dataclass(eq=False)
class MeshTable(Mapping):
    """Mesh templates as concatenated arrays; a read-only mapping ``key -> (vertices, faces)``.

    ``vertices[vertex_start[i]:vertex_start[i + 1]]`` are template ``i``'s vertices and
    ``faces[face_start[i]:face_start[i + 1]]`` its triangles, indexed from 0 within the template.
    The arrays may be memory-mapped and narrower than float64 / int64 (a prepared file keeps
    whatever holds them exactly); :meth:`mesh` always returns float64 and int64 copies.

    A template cut into clusters (:meth:`clustered`, :mod:`wallcull.clusters`) has its faces
    in cluster order, and a tree of clusters (groups over the clusters where there are many):
    its tree's nodes are ``cluster_start[i]:cluster_start[i + 1]``, in preorder, node ``c``
    the faces ``cluster_first[c]:cluster_first[c] + cluster_count[c]`` of the template (counted
    from its first face), under node ``cluster_start[i] + cluster_parent[c]`` (-1: on top). A
    template with no clusters is drawn whole. ``see_through[i]``: template ``i``'s material
    may show what lies behind it (glass, an alpha-tested leaf): it never occludes.
    ``single_sided[i]``: template ``i`` is a glTF mesh whose material is not ``doubleSided``,
    whose back faces a render node may cull: it occludes with its front faces alone.
    """

    keys_: list[str]
    vertex_start: np.ndarray  # (m + 1,) int64
    vertices: np.ndarray  # (V, 3) float
    face_start: np.ndarray  # (m + 1,) int64
    faces: np.ndarray  # (F, 3) int
    cluster_start: np.ndarray = None  # (m + 1,) int64; None: no clusters anywhere
    cluster_parent: np.ndarray = None  # (C,) int, a tree node's parent within its template's
    cluster_first: np.ndarray = None  # (C,) int, its first face in its template
    cluster_count: np.ndarray = None  # (C,) int, its faces
    see_through: np.ndarray = None  # (m,) bool; None: none is
    single_sided: np.ndarray = None  # (m,) bool; None: none is
    _index: dict = field(default=None, repr=False)

    def __post_init__(self):
        if self.see_through is None:
            self.see_through = np.zeros(len(self.keys_), dtype=bool)
        if self.single_sided is None:
            self.single_sided = np.zeros(len(self.keys_), dtype=bool)
        if self.cluster_start is None:
            self.cluster_start = np.zeros(len(self.keys_) + 1, dtype=np.int64)
            self.cluster_parent = self.cluster_first = self.cluster_count = \
                np.zeros(0, dtype=np.int64)

    @classmethod
    def from_meshes(cls, meshes: Mapping[str, tuple[np.ndarray, np.ndarray]],
                    see_through=None, single_sided=None) -> "MeshTable":
        """From ``key -> (vertices (v, 3), faces (f, 3))``, in the mapping's order;
        ``see_through`` and ``single_sided``: per mesh, in that order (None: none)."""
        keys = list(meshes)
        vs = [np.asarray(meshes[k][0], dtype=np.float64).reshape(-1, 3) for k in keys]
        fs = [np.asarray(meshes[k][1], dtype=np.int64).reshape(-1, 3) for k in keys]
        return cls(keys, _starts([len(v) for v in vs]),
                   np.concatenate(vs) if vs else np.zeros((0, 3)),
                   _starts([len(f) for f in fs]),
                   np.concatenate(fs) if fs else np.zeros((0, 3), dtype=np.int64),
                   see_through=None if see_through is None else np.array(see_through, bool),
                   single_sided=None if single_sided is None else np.array(single_sided, bool))

    def subset(self, used: np.ndarray) -> "MeshTable":
        """The templates ``used`` (indices, in that order) alone, without clusters."""
        if np.array_equal(used, np.arange(len(self))) and not self.clusters:
            return self
        return MeshTable.from_meshes({self.keys_[i]: self.mesh(i) for i in used},
                                     self.see_through[used], self.single_sided[used])

    def clustered(self, size: int | None, branching: int) -> "MeshTable":
        """The same templates with those of more than ``size`` faces cut into clusters under
        trees of ``branching`` (:func:`wallcull.clusters.cluster_faces`), their faces in
        cluster order; ``size`` None: no clusters."""
        from .clusters import cluster_faces

        faces, trees = [], []
        for i in range(len(self)):
            v, f = self.mesh(i)
            f, t = cluster_faces(v, f, size, branching)
            faces.append(f)
            trees.append(t)
        if not faces:
            return self
        return MeshTable(self.keys_, self.vertex_start, self.vertices, self.face_start,
                         np.concatenate(faces), _starts([len(t[0]) for t in trees]),
                         *(np.concatenate([t[k] for t in trees]) for k in range(3)),
                         see_through=self.see_through, single_sided=self.single_sided)

    @cached_property
    def face_neighbors(self) -> np.ndarray:
        """``(F, 3)``: per face, the face across each of its edges (vertices ``k``, ``k + 1``),
        as rows of ``faces``; -1 where the edge has no other face, or more than one."""
        f = np.asarray(self.faces, dtype=np.int64)
        template = np.repeat(np.arange(len(self)), np.diff(self.face_start))
        v = f + self.vertex_start[template][:, None]  # vertices numbered over the table
        a, b = v, np.roll(v, -1, axis=1)
        key = (np.minimum(a, b) * (len(self.vertices) + 1) + np.maximum(a, b)).reshape(-1)
        order = np.argsort(key, kind="stable")
        k = key[order]
        out = np.full(len(key), -1, dtype=np.int64)
        pair = np.flatnonzero(k[1:] == k[:-1])
        # an edge of exactly two faces: neither its left nor its right neighbour in the sort
        # carries the same key again
        lone = ((pair == 0) | (k[np.maximum(pair - 1, 0)] != k[pair])) & \
            ((pair + 2 >= len(k)) | (k[np.minimum(pair + 2, len(k) - 1)] != k[pair]))
        one, two = order[pair[lone]], order[pair[lone] + 1]
        out[one], out[two] = two // 3, one // 3
        return out.reshape(-1, 3)

    @property
    def clusters(self) -> int:
        """How many nodes the templates' cluster trees have in all."""
        return int(self.cluster_start[-1])

    @cached_property
    def cluster_meshes(self) -> "MeshTable":
        """Every node of the cluster trees as a template of its own: the vertices its faces use,
        and those faces renumbered. What a cluster's bound is fitted to (:func:`leaf_bounds`)."""
        c = self.clusters
        template = np.repeat(np.arange(len(self)), np.diff(self.cluster_start))
        start = self.face_start[template] + np.asarray(self.cluster_first, dtype=np.int64)
        count = np.asarray(self.cluster_count, dtype=np.int64)
        face_start = _starts(count)
        owner = np.repeat(np.arange(c), count)  # cluster of each face
        faces = np.asarray(self.faces[np.repeat(start - face_start[:-1], count)
                                      + np.arange(face_start[-1])], dtype=np.int64)
        faces += self.vertex_start[template][owner][:, None]  # into the table's vertices
        # (cluster, vertex) pairs, each once, by cluster then vertex
        span = max(len(self.vertices), 1)
        keys = owner[:, None] * span + faces
        unique = np.unique(keys)
        vertex_start = np.searchsorted(unique // span, np.arange(c + 1))
        local = np.searchsorted(unique, keys) - vertex_start[owner][:, None]
        return MeshTable([f"{i}" for i in range(c)], vertex_start,
                         np.asarray(self.vertices[unique % span], dtype=np.float64), face_start,
                         local)

    @property
    def index(self) -> dict[str, int]:
        if self._index is None:
            self._index = {k: i for i, k in enumerate(self.keys_)}
        return self._index

    @cached_property
    def vertex_count(self) -> np.ndarray:
        return np.diff(self.vertex_start)

    @cached_property
    def face_count(self) -> np.ndarray:
        return np.diff(self.face_start)

    @cached_property
    def boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo (m, 3), hi (m, 3))``: each template's box in its own coordinates (a template of
        no vertex: lo inf, hi -inf)."""
        lo, hi = np.full((len(self), 3), np.inf), np.full((len(self), 3), -np.inf)
        has = np.flatnonzero(self.vertex_count > 0)
        if len(has):
            v = np.asarray(self.vertices, dtype=np.float64)
            lo[has] = np.minimum.reduceat(v, self.vertex_start[has], axis=0)
            hi[has] = np.maximum.reduceat(v, self.vertex_start[has], axis=0)
        return lo, hi

    def mesh(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Template ``i`` as ``(vertices (v, 3) float64, faces (f, 3) int64)``, fresh copies."""
        a, b = self.vertex_start[i], self.vertex_start[i + 1]
        c, d = self.face_start[i], self.face_start[i + 1]
        return (np.array(self.vertices[a:b], dtype=np.float64),
                np.array(self.faces[c:d], dtype=np.int64))

    def __getitem__(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        return self.mesh(self.index[key])

    def __iter__(self):
        return iter(self.keys_)

    def __len__(self) -> int:
        return len(self.keys_)

    def __contains__(self, key) -> bool:
        return key in self.index


def _starts(counts) -> np.ndarray:
    out = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=out[1:])
    return out


# --------------------------------------------------------------------------- points


def instance_points(meshes: MeshTable, mesh_of: np.ndarray, world: np.ndarray,
                    budget: int = CHUNK_POINTS
                    ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """World-space vertices of instances, a bounded chunk at a time.

    ``mesh_of (k,)`` names each instance's template, ``world (k, 4, 4)`` places it. Yields
    ``(rows, points (P, 3) float64, starts (r + 1,))``: the instances ``rows`` (indices into the
    ``k``), their vertices ``A v + t`` as CSR segments in that order, about ``budget`` points at
    most (an instance with more is a chunk of its own). Every instance comes exactly once, in
    no particular order: the instances of a template placed :data:`BATCH` times or more come
    together, transformed by one matrix product a chunk; the others are gathered point by point.
    """
    for rows, p in _batched(meshes, mesh_of, world, budget):
        v = p.shape[2]
        yield rows, p.transpose(0, 2, 1).reshape(-1, 3), np.arange(len(rows) + 1) * v
    yield from _gathered(meshes, mesh_of, world, budget)


def instance_extremes(meshes: MeshTable, mesh_of: np.ndarray, world: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``(lo (k, 3), hi (k, 3))``: each instance's axis-aligned box of its world-space vertices,
    exactly (unpadded)."""
    lo = np.empty((len(mesh_of), 3))
    hi = np.empty((len(mesh_of), 3))
    for rows, p in _batched(meshes, mesh_of, world, CHUNK_POINTS):
        lo[rows], hi[rows] = p.min(axis=2), p.max(axis=2)
    for rows, points, starts in _gathered(meshes, mesh_of, world, CHUNK_POINTS):
        lo[rows] = np.minimum.reduceat(points, starts[:-1], axis=0)
        hi[rows] = np.maximum.reduceat(points, starts[:-1], axis=0)
    return lo, hi


def _batched(meshes: MeshTable, mesh_of: np.ndarray, world: np.ndarray, budget: int
             ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``(rows, points (r, 3, v))`` for the instances of templates placed :data:`BATCH` times
    or more, a chunk of one template's instances at a time."""
    mesh_of = np.asarray(mesh_of, dtype=np.int64)
    uses = np.bincount(mesh_of, minlength=len(meshes))
    order = np.argsort(mesh_of, kind="stable")
    first = np.searchsorted(mesh_of[order], np.arange(len(meshes) + 1))
    for m in np.flatnonzero(uses >= BATCH):
        v = np.asarray(meshes.vertices[meshes.vertex_start[m]:meshes.vertex_start[m + 1]],
                       dtype=np.float64).T
        step = max(1, budget // v.shape[1])
        for a in range(first[m], first[m + 1], step):
            rows = order[a:min(a + step, first[m + 1])]
            p = world[rows, :3, :3] @ v
            p += world[rows, :3, 3, None]
            yield rows, p


def _gathered(meshes: MeshTable, mesh_of: np.ndarray, world: np.ndarray, budget: int
              ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`instance_points` for the instances of templates placed fewer than
    :data:`BATCH` times, in consecutive runs, each point gathered and transformed alone."""
    mesh_of = np.asarray(mesh_of, dtype=np.int64)
    rare = np.flatnonzero(np.bincount(mesh_of, minlength=len(meshes))[mesh_of] < BATCH)
    counts = meshes.vertex_count[mesh_of[rare]]
    ends = np.cumsum(counts)
    i = 0
    while i < len(rare):
        before = ends[i - 1] if i else 0
        j = max(int(np.searchsorted(ends, before + budget, side="right")), i + 1)
        rows, c = rare[i:j], counts[i:j]
        starts = _starts(c)
        seg = np.repeat(np.arange(j - i), c)
        src = np.repeat(meshes.vertex_start[mesh_of[rows]] - starts[:-1], c) + np.arange(starts[-1])
        v = np.asarray(meshes.vertices[src], dtype=np.float64)
        m = world[rows]
        points = np.empty_like(v)
        for r in range(3):  # one output coordinate at a time: (P, 3) temporaries, not (P, 3, 3)
            a = m[:, r, :3][seg]
            points[:, r] = (v[:, 0] * a[:, 0] + v[:, 1] * a[:, 1] + v[:, 2] * a[:, 2]
                            + m[:, r, 3][seg])
        yield rows, points, starts
        i = j


def fit_points(kind: str, meshes: MeshTable, mesh_of: np.ndarray, world: np.ndarray) -> bnd.Bounds:
    """Bounds ``kind`` of instances fitted to their world-space points (chunk by chunk), as
    :data:`wallcull.bounds.LEAF_FITTERS` fits any point set."""
    out = bnd.Bounds.empty(kind, len(mesh_of))
    for rows, points, starts in instance_points(meshes, mesh_of, world):
        out.put(rows, bnd.LEAF_FITTERS[kind](points, starts))
    return out


# --------------------------------------------------------------------------- bounds


def leaf_bounds(kind: str, meshes: MeshTable, mesh_of: np.ndarray, world: np.ndarray) -> bnd.Bounds:
    """Bounds ``kind`` of instances ``mesh_of (k,)`` placed by ``world (k, 4, 4)``.

    Eigenvector OBBs come from the templates' boxes, moved (:func:`moved_boxes`); the other
    kinds are fitted to the points, chunk by chunk. Either way the result is what fitting each
    instance's world-space points gives (up to rounding, and up to the free choice of axes within
    a repeated eigenvalue)."""
    if kind != "obb":
        return fit_points(kind, meshes, mesh_of, world)
    return moved_boxes(meshes, mesh_of, world)


@dataclass
class _Templates:
    box: bnd.Bounds  # (m,) eigenvector OBBs in the templates' own coordinates
    variance: np.ndarray  # (m, 3): the points' variance along each box axis
    scale: np.ndarray  # (m,): the largest |coordinate| of the template's points


def _fit_templates(meshes: MeshTable) -> _Templates:
    v = np.asarray(meshes.vertices, dtype=np.float64)
    box = bnd.pca_boxes(v, meshes.vertex_start)
    seg = bnd.segment_ids(meshes.vertex_start, len(v))
    counts = meshes.vertex_count[:, None]
    mean = np.add.reduceat(v, meshes.vertex_start[:-1], axis=0) / counts
    variance = np.empty((len(meshes), 3))
    for k in range(3):  # variance along axis k: the eigenvalue that put it there
        d = ((v - mean[seg]) * box.axes[seg, k]).sum(axis=1)
        variance[:, k] = np.add.reduceat(d * d, meshes.vertex_start[:-1]) / counts[:, 0]
    scale = np.maximum.reduceat(np.abs(v), meshes.vertex_start[:-1], axis=0).max(axis=1)
    return _Templates(box, variance, scale)


def moved_boxes(meshes: MeshTable, mesh_of: np.ndarray, world: np.ndarray) -> bnd.Bounds:
    """Eigenvector OBBs of instances: each template's box, moved by its instance's transform.

    With ``A``, ``t`` an instance's transform and ``Q`` (rows) its template box's axes, the box
    maps to the parallelepiped spanned by ``P = A Q^T`` about ``A c + t``. Where ``P``'s columns
    are orthogonal (``P^T P`` diagonal: rigid, uniform, or scaled along the box's axes) that is a
    box, and the eigenvector box of the moved points: its axes are ``P``'s columns, ordered by
    the moved variance as ``eigh`` orders them, orthonormalized (Gram-Schmidt, the third as the
    cross product: right-handed) to remove rounding, and its half extents are the support of
    the parallelepiped along them, so the box encloses it even where ``P`` is off by rounding.
    Extents are padded by a few ulps of the world coordinates. Instances whose ``P`` is not
    orthogonal (a shear) are fitted again from their points."""
    mesh_of = np.asarray(mesh_of, dtype=np.int64)
    t = _fit_templates(meshes)
    box = t.box.take(mesh_of)
    a = world[:, :3, :3]
    p = a @ np.swapaxes(box.axes, 1, 2)  # columns: the images of the template's axes
    gram = np.swapaxes(p, 1, 2) @ p
    diag = np.diagonal(gram, axis1=1, axis2=2)
    off = np.abs(gram - diag[:, :, None] * np.eye(3)).max(axis=(1, 2))
    # A shear, or an axis squashed to nothing (a singular transform): refit from the points.
    sheared = ~((off <= SHEAR_TOLERANCE * diag.max(axis=1))
                & (diag.min(axis=1) > 1e-24 * diag.max(axis=1)))
    # Axis order: ascending moved variance (eigh's order), so that the box is the refit's.
    order = np.argsort(t.variance[mesh_of] * diag, axis=1, kind="stable")
    p = np.take_along_axis(p, order[:, None, :], axis=2)
    half_t = np.take_along_axis(box.half, order, axis=1)
    u0 = _unit(p[:, :, 0])
    u1 = _unit(p[:, :, 1] - (u0 * p[:, :, 1]).sum(axis=1, keepdims=True) * u0)
    axes = np.stack([u0, u1, np.cross(u0, u1)], axis=1)
    center = np.einsum("nij,nj->ni", a, box.center) + world[:, :3, 3]
    half = np.einsum("nkj,nj->nk", np.abs(axes @ p), half_t)  # support of the parallelepiped
    reach = np.abs(center).max(axis=1) + (np.abs(a).sum(axis=2).max(axis=1)
                                          * (t.scale[mesh_of] + np.abs(box.center).max(axis=1)))
    out = bnd.Bounds("obb", center, axes, half + (16 * _EPS) * reach[:, None], box.radius)
    if sheared.any():
        rows = np.flatnonzero(sheared)
        out.put(rows, fit_points("obb", meshes, mesh_of[rows], world[rows]))
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)
