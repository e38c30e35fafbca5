"""Bounding volumes of the object hierarchy: eigenvector OBBs (paper Alg. 1), AABBs, spheres.

Every bound is stored in one form, a *rounded box*: the Minkowski sum of an oriented box
(``center``, unit ``axes`` as rows, ``half`` extents) and a ball of ``radius``. Its extent along a
unit normal ``n`` is the sum of the two support functions::

    r = |n . a0| h0 + |n . a1| h1 + |n . a2| h2 + radius

so a box is tested against a plane by ``s = n . c + d`` and ``r`` alone (outside when
``s < -r``). An OBB has ``radius = 0``; an AABB has identity axes; a sphere has ``half = 0``.
The bound type is therefore a dial on the data, not a fork in the culling code.

Functions here work on *segments*: a flat ``(N, 3)`` array of points split into consecutive
groups by ``starts`` (CSR offsets), one group per node, all groups processed at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import optional

#: Bound types the culler accepts, fastest-to-compute first (see ``docs`` for the measured trade).
KINDS = ("obb", "aabb", "sphere", "obb-hull", "obb-min")

_EPS = np.finfo(np.float64).eps

# The eight corners of the unit box, as signs on the three half extents.
_CORNER_SIGNS = np.array(
    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)


@dataclass
class Bounds:
    """Rounded boxes of ``n`` nodes as structure of arrays (float64, C-contiguous)."""

    kind: str
    center: np.ndarray  # (n, 3)
    axes: np.ndarray  # (n, 3, 3), axes[i, k] is the k-th unit axis of node i
    half: np.ndarray  # (n, 3)
    radius: np.ndarray  # (n,)

    @classmethod
    def empty(cls, kind: str, n: int) -> "Bounds":
        return cls(kind, np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)),
                   np.zeros(n))

    def __len__(self) -> int:
        return len(self.center)

    def copy(self) -> "Bounds":
        return Bounds(self.kind, self.center.copy(), self.axes.copy(), self.half.copy(),
                      self.radius.copy())

    def take(self, index) -> "Bounds":
        return Bounds(self.kind, self.center[index], self.axes[index], self.half[index],
                      self.radius[index])

    def put(self, index, other: "Bounds") -> None:
        self.center[index] = other.center
        self.axes[index] = other.axes
        self.half[index] = other.half
        self.radius[index] = other.radius

    def extent(self, normals: np.ndarray) -> np.ndarray:
        """Support radius ``(n,)`` of each bound along its own unit normal ``normals (n, 3)``."""
        proj = np.abs(np.einsum("nkj,nj->nk", self.axes, normals))
        return (proj * self.half).sum(axis=1) + self.radius

    def reach(self, index, direction: np.ndarray) -> np.ndarray:
        """Support radius of bounds ``index`` along one unit ``direction (3,)``: how far each
        extends either side of its centre's depth along it."""
        return (np.abs(self.axes[index] @ direction) * self.half[index]).sum(axis=1) \
            + self.radius[index]

    def corners(self) -> np.ndarray:
        """``(n, 8, 3)`` corners of the boxes (the ball part not included)."""
        return _corners(self.center, self.axes, self.half)

    def world_corners(self) -> np.ndarray:
        """``(n, 8, 3)`` corners of a box enclosing each rounded box."""
        return _corners(self.center, self.axes, self.half + self.radius[:, None])

    def contains(self, index: int, points: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Which ``points (k, 3)`` lie in bound ``index`` grown by ``tol`` (for tests)."""
        local = (points - self.center[index]) @ self.axes[index].T
        outside = np.maximum(np.abs(local) - self.half[index], 0.0)
        return np.linalg.norm(outside, axis=1) <= self.radius[index] + tol


def _corners(center: np.ndarray, axes: np.ndarray, half: np.ndarray) -> np.ndarray:
    # signs (8, 3) @ half-scaled axes (n, 3, 3): a batched matmul, 4x faster than the einsum
    return center[:, None, :] + _CORNER_SIGNS @ (axes * half[:, :, None])


# --------------------------------------------------------------------------- segments


def segment_ids(starts: np.ndarray, total: int) -> np.ndarray:
    """Segment index of each of ``total`` points, for CSR ``starts`` (length ``k + 1``)."""
    return np.repeat(np.arange(len(starts) - 1), np.diff(starts)).astype(np.int64)[:total]


def _reduce(ufunc, values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    # reduceat on non-empty segments only; callers guarantee non-empty segments.
    return ufunc.reduceat(values, starts[:-1], axis=0)


def _pad(half: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Grow half extents by a few ulps of the coordinates' magnitude.

    A box rebuilt as ``center + axes.T @ t`` differs from the exact one by rounding on the order of
    ``eps * |coordinates|``; this margin keeps every input point inside the stored box as
    evaluated in float64, even at 1e7 from the origin.
    """
    return half + (16 * _EPS) * scale[:, None]


def pca_boxes(points: np.ndarray, starts: np.ndarray,
              fallback: np.ndarray | None = None) -> Bounds:
    """Eigenvector OBB of each point segment (paper section 4.1).

    The axes are the eigenvectors of the segment's covariance, computed about its mean (so large
    offsets do not cancel) and made right-handed; the extents are the points' projections onto
    them. Degenerate input is fine: ``eigh`` returns an orthonormal basis for any symmetric
    matrix, so a single point, repeated points, collinear or coplanar points and repeated
    eigenvalues all give a valid (possibly flat) box that encloses the points. With repeated
    eigenvalues that basis is arbitrary within their eigenspace (rounding picks it); where
    ``fallback`` axes ``(k, 3, 3)`` are given, such segments take them instead.
    """
    counts = np.diff(starts)
    seg = segment_ids(starts, len(points))
    mean = _reduce(np.add, points, starts) / counts[:, None]
    centered = points - mean[seg]
    cov = np.empty((len(counts), 3, 3))
    for i, j in zip(*np.triu_indices(3)):  # one entry at a time: (N,) temporaries
        cov[:, i, j] = cov[:, j, i] = _reduce(np.add, centered[:, i] * centered[:, j],
                                              starts) / counts
    values, vectors = np.linalg.eigh(cov)
    axes = np.ascontiguousarray(np.swapaxes(vectors, 1, 2))  # rows are axes
    flip = np.linalg.det(axes) < 0
    axes[flip, 2] *= -1
    if fallback is not None:
        gap = np.diff(values, axis=1).min(axis=1)
        repeated = gap <= 1e-6 * np.maximum(values[:, 2], np.finfo(float).tiny)
        axes[repeated] = fallback[repeated]
    return _fit_axes(points, centered, starts, seg, mean, axes, kind="obb")


def _fit_axes(points, centered, starts, seg, mean, axes, kind) -> Bounds:
    """The box with given ``axes`` per segment that encloses the segment's points."""
    lo = np.empty((len(starts) - 1, 3))
    hi = np.empty((len(starts) - 1, 3))
    for k in range(3):  # one axis at a time: (N, 3) temporaries, not (N, 3, 3)
        local = (centered * axes[seg, k]).sum(axis=1)
        lo[:, k] = _reduce(np.minimum, local, starts)
        hi[:, k] = _reduce(np.maximum, local, starts)
    center = mean + np.einsum("nk,nkj->nj", (lo + hi) / 2, axes)
    scale = _reduce(np.maximum, np.abs(points), starts).max(axis=1)
    half = _pad((hi - lo) / 2, scale)
    return Bounds(kind, center, axes, half, np.zeros(len(center)))


def aabb_boxes(points: np.ndarray, starts: np.ndarray) -> Bounds:
    """Axis-aligned box of each point segment."""
    lo = _reduce(np.minimum, points, starts)
    hi = _reduce(np.maximum, points, starts)
    scale = np.maximum(np.abs(lo), np.abs(hi)).max(axis=1)
    n = len(lo)
    return Bounds("aabb", (lo + hi) / 2, np.tile(np.eye(3), (n, 1, 1)),
                  _pad((hi - lo) / 2, scale), np.zeros(n))


def spheres(points: np.ndarray, starts: np.ndarray) -> Bounds:
    """Bounding sphere of each segment, centred on the segment's axis-aligned box.

    Not the minimal sphere (Welzl's is much slower to compute in bulk), but within a factor
    ``sqrt(3)`` of it and exact to compute; the trade against tighter spheres is measured.
    """
    box = aabb_boxes(points, starts)
    seg = segment_ids(starts, len(points))
    dist = np.linalg.norm(points - box.center[seg], axis=1)
    radius = _reduce(np.maximum, dist, starts)
    scale = np.abs(box.center).max(axis=1) + radius
    n = len(radius)
    return Bounds("sphere", box.center, box.axes, np.zeros((n, 3)),
                  radius + 16 * _EPS * scale)


def hull_pca_boxes(points: np.ndarray, starts: np.ndarray) -> Bounds:
    """Eigenvector OBB of the convex hull's vertices of each segment (less biased by dense
    tessellation than the raw points' eigenvectors)."""
    spatial = optional("scipy.spatial", "hull", "--bounds obb-hull")
    ConvexHull, QhullError = spatial.ConvexHull, spatial.QhullError  # noqa: N806

    kept, new_starts = [], [0]
    for a, b in zip(starts[:-1], starts[1:]):
        seg = points[a:b]
        try:
            seg = seg[ConvexHull(seg).vertices] if len(seg) > 4 else seg
        except (QhullError, ValueError):
            pass  # flat or degenerate: every point is a hull point
        kept.append(seg)
        new_starts.append(new_starts[-1] + len(seg))
    box = pca_boxes(np.concatenate(kept), np.asarray(new_starts))
    # Fit the extents to all the points (the hull's are the same up to rounding).
    seg = segment_ids(starts, len(points))
    return _fit_axes(points, points - box.center[seg], starts, seg, box.center, box.axes,
                     kind="obb-hull")


def min_volume_boxes(points: np.ndarray, starts: np.ndarray) -> Bounds:
    """trimesh's minimum-volume OBB of each segment (slow: the accuracy reference)."""
    import trimesh

    optional("scipy.spatial", "hull", "--bounds obb-min")  # trimesh's hulls: Qhull

    axes = np.empty((len(starts) - 1, 3, 3))
    for k, (a, b) in enumerate(zip(starts[:-1], starts[1:])):
        try:
            # a flat set's hull has no volume: trimesh's mass properties along the way divide
            # by it (the axes come out finite all the same)
            with np.errstate(divide="ignore", invalid="ignore"):
                to_origin, _ = trimesh.bounds.oriented_bounds(points[a:b])
            axes[k] = to_origin[:3, :3]
        except Exception:  # noqa: BLE001 - qhull on degenerate sets; fall back to PCA axes
            axes[k] = pca_boxes(points[a:b], np.array([0, b - a])).axes[0]
    flip = np.linalg.det(axes) < 0
    axes[flip, 2] *= -1
    seg = segment_ids(starts, len(points))
    mean = _reduce(np.add, points, starts) / np.diff(starts)[:, None]
    return _fit_axes(points, points - mean[seg], starts, seg, mean, axes, kind="obb-min")


LEAF_FITTERS = {
    "obb": pca_boxes,
    "aabb": aabb_boxes,
    "sphere": spheres,
    "obb-hull": hull_pca_boxes,
    "obb-min": min_volume_boxes,
}


# --------------------------------------------------------------------------- internal nodes


def enclose(children: Bounds, starts: np.ndarray, mode: str) -> Bounds:
    """Bounds of internal nodes from their children's bounds (paper Alg. 1, lines 3-6).

    ``children`` holds the child bounds of every parent consecutively, split by ``starts``.
    ``mode`` ``"obb"``: eigenvectors of the children's box corners (the paper's fast
    approximation); ``"aabb"``: the axis-aligned box of the corners; ``"sphere"``: a sphere
    enclosing the child spheres. A rounded child contributes the corners of its grown box, so
    every result encloses its children entirely.
    """
    if mode == "sphere":
        lo = _reduce(np.minimum, children.center - children.radius[:, None], starts)
        hi = _reduce(np.maximum, children.center + children.radius[:, None], starts)
        center = (lo + hi) / 2
        seg = segment_ids(starts, len(children))
        reach = np.linalg.norm(children.center - center[seg], axis=1) + children.radius
        radius = _reduce(np.maximum, reach, starts)
        scale = np.abs(center).max(axis=1) + radius
        n = len(center)
        return Bounds("sphere", center, np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)),
                      radius + 16 * _EPS * scale)
    corners = children.world_corners().reshape(-1, 3)
    corner_starts = starts * 8
    if mode == "aabb":
        return aabb_boxes(corners, corner_starts)
    # Where the corners' covariance has a repeated eigenvalue (one child whose box has two
    # equal sides, say), take the axes of the largest child: the eigenvectors are arbitrary
    # there, and a box turned 45 degrees within them can be twice as large as need be.
    volume = np.prod(children.half + children.radius[:, None], axis=1)
    seg = segment_ids(starts, len(children))
    largest = np.lexsort((-volume, seg))[starts[:-1]]
    box = pca_boxes(corners, corner_starts, fallback=children.axes[largest])
    box.kind = children.kind
    return box


def enclosing_mode(kind: str) -> str:
    """How internal nodes are bounded for a bound kind: OBB kinds follow Algorithm 1."""
    return kind if kind in ("aabb", "sphere") else "obb"


def transform(bounds: Bounds, rotation: np.ndarray, translation: np.ndarray) -> Bounds:
    """Bounds moved rigidly by per-node ``rotation (n, 3, 3)`` and ``translation (n, 3)``.

    A rigid motion maps an eigenvector OBB onto the eigenvector OBB of the moved points, so OBBs
    move exactly, with no refit.
    """
    center = np.einsum("nij,nj->ni", rotation, bounds.center) + translation
    axes = np.einsum("nkj,nij->nki", bounds.axes, rotation)
    return Bounds(bounds.kind, center, axes, bounds.half.copy(), bounds.radius.copy())


def axis_aligned(bounds: Bounds) -> Bounds:
    """The world-axis box around each bound: what an AABB scene keeps after a rotation.

    Conservative and cheap, but looser than the moved OBB: the paper's trade for dynamic parts.
    """
    reach = np.einsum("nkj,nk->nj", np.abs(bounds.axes), bounds.half)
    n = len(bounds)
    return Bounds(bounds.kind, bounds.center.copy(), np.tile(np.eye(3), (n, 1, 1)),
                  reach * (1 + 16 * _EPS) + 16 * _EPS * np.abs(bounds.center),
                  bounds.radius.copy())
