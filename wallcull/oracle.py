"""The exact visibility oracle, independent of the culling code (SPEC section 5).

A leaf is truly in a tile if one of its triangles, clipped against the tile frustum's six
planes, leaves something. The planes are built here from the wall spec alone (the eye, the
tile's corners, cross products; scipy's quaternion), not from :mod:`wallcull.wall`, and nothing
here imports the culler: the tests hold the culler to this module, and the benchmark counts
false positives with it. A frustum shrunk by ``tol`` gives the leaves that meet the frustum by
more than the contract's tolerance: the culler must never miss one.

Clipping is exact but slow, so two exact shortcuts come first: a triangle with a vertex inside
every plane is in; one with all three vertices outside the same plane is out. Only the rest are
clipped.
"""

from __future__ import annotations

import numpy as np

from .errors import optional


def rotations():
    """scipy's rotations, the oracle's own (independent of wallcull's quaternion code); an
    install without them refuses the oracle in one line."""
    return optional("scipy.spatial.transform", "experiments", "the exact oracle").Rotation


def _rotation(q):
    """The rotation of a unit quaternion ``(w, x, y, z)`` (scipy is scalar-last)."""
    w, x, y, z = q
    return rotations().from_quat([x, y, z, w])


def tile_planes_display(wall: dict, eye, tile: int) -> np.ndarray:
    """``(6, 4)`` inward unit planes of a tile frustum, display space, from first principles."""
    if "screens" in wall:
        return screen_planes_display(wall, eye, tile)
    cols, rows = wall["cols"], wall["rows"]
    w, h = wall["tile_size"]
    gx, gy = wall.get("gap", (0, 0))
    D = wall["distance"]
    W, H = cols * w + (cols - 1) * gx, rows * h + (rows - 1) * gy
    r, c = divmod(tile, cols)
    x0 = -W / 2 + c * (w + gx)
    x1 = x0 + w
    y1 = H / 2 - r * (h + gy)
    y0 = y1 - h
    e = np.asarray(eye, dtype=float)
    corners = np.array([[x0, y0, -D], [x1, y0, -D], [x1, y1, -D], [x0, y1, -D]])
    inside = np.array([(x0 + x1) / 2, (y0 + y1) / 2, -D])
    planes = []
    for k in range(4):
        n = np.cross(corners[k] - e, corners[(k + 1) % 4] - e)
        n /= np.linalg.norm(n)
        d = -n @ e
        if n @ inside + d < 0:
            n, d = -n, -d
        planes.append([*n, d])
    near, far = wall.get("near", 0.1), wall.get("far", 1000.0)
    planes.append([0, 0, -1, e[2] - near])  # z <= ez - near
    planes.append([0, 0, 1, far - e[2]])  # z >= ez - far
    return np.array(planes, dtype=float)


def screen_planes_display(wall: dict, eye, tile: int) -> np.ndarray:
    """``(6, 4)`` planes of a screen's frustum (SPEC section 2b): through the eye and each of
    its four edges, and parallel to it at ``near`` and ``far`` from the eye."""
    s = wall["screens"][tile]
    bl, br, tl = (np.asarray(s[k], dtype=float) for k in ("bottom_left", "bottom_right",
                                                         "top_left"))
    corners = np.array([bl, br, br + tl - bl, tl])
    inside = corners.mean(axis=0)
    e = np.asarray(eye, dtype=float)
    planes = []
    for k in range(4):
        n = np.cross(corners[k] - e, corners[(k + 1) % 4] - e)
        n /= np.linalg.norm(n)
        d = -n @ e
        if n @ inside + d < 0:
            n, d = -n, -d
        planes.append([*n, d])
    normal = np.cross(br - bl, tl - bl)
    normal /= np.linalg.norm(normal)  # toward the seen side, where the eye is
    near, far = wall.get("near", 0.1), wall.get("far", 1000.0)
    # distance from the eye along -normal between near and far
    planes.append([*(-normal), normal @ e - near])
    planes.append([*normal, far - normal @ e])
    return np.array(planes, dtype=float)


def eyes_of(frame: dict) -> list:
    """The frame's eyes in display space: one, or left and right for a stereo frame."""
    eye = np.asarray(frame.get("eye", (0, 0, 0)), dtype=float)
    stereo = frame.get("stereo")
    if not stereo:
        return [eye]
    across = _rotation(stereo.get("head", (1, 0, 0, 0))).apply([1.0, 0, 0]) * stereo["ipd"] / 2
    return [eye - across, eye + across]


def to_display(frame: dict, points: np.ndarray) -> np.ndarray:
    """World points to display space: ``p_d = R^T (p_w - t)``."""
    rot = _rotation(frame["orientation"])
    return rot.inv().apply(np.asarray(points, dtype=float) - np.asarray(frame["position"]))


def clip_triangles(tris: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Which triangles ``(k, 3, 3)`` keep a non-empty part after clipping against ``planes``.

    Sutherland-Hodgman, vectorized over triangles: polygons are padded to a fixed vertex count.
    A part that survives is non-empty: a polygon with at least one vertex inside every plane.
    """
    return _clipped(tris, planes)[1] > 0


def clipped_depths(tris: np.ndarray, planes: np.ndarray, axis: np.ndarray,
                   origin: np.ndarray) -> np.ndarray:
    """Per triangle ``(k, 3, 3)``, the least depth along ``axis`` from ``origin`` of its part
    within ``planes`` (the polygon :func:`clip_triangles` clips; ``inf`` where none is left)."""
    poly, count = _clipped(tris, planes)
    depth = (poly - origin) @ np.asarray(axis, float)
    depth[np.arange(poly.shape[1])[None, :] >= count[:, None]] = np.inf
    return depth.min(axis=1) if len(depth) else np.zeros(0)


def _clipped(tris: np.ndarray, planes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The polygons ``(k, 3 + p, 3)`` left of the triangles by the ``p`` planes, and their
    vertex counts."""
    k = len(tris)
    cap = 3 + len(planes)
    poly = np.zeros((k, cap, 3))
    poly[:, :3] = tris
    count = np.full(k, 3)
    for plane in planes:
        if not k:
            break
        dist = poly @ plane[:3] + plane[3]
        valid = np.arange(cap)[None, :] < count[:, None]
        nxt = (np.arange(cap)[None, :] + 1) % np.maximum(count, 1)[:, None]
        d0, d1 = dist, np.take_along_axis(dist, nxt, axis=1)
        p1 = np.take_along_axis(poly, nxt[:, :, None], axis=1)
        in0, in1 = d0 >= 0, d1 >= 0
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(in0 != in1, d0 / (d0 - d1), 0.0)
        cross = poly + t[:, :, None] * (p1 - poly)
        # Each edge emits its start vertex if inside, then the crossing if the edge crosses.
        out = np.stack([poly, cross], axis=2).reshape(k, 2 * cap, 3)
        keep = np.stack([valid & in0, valid & (in0 != in1)], axis=2).reshape(k, 2 * cap)
        order = np.argsort(~keep, axis=1, kind="stable")
        out = np.take_along_axis(out, order[:, :, None], axis=1)[:, :cap]
        count = np.minimum(keep.sum(axis=1), cap)
        poly = out
    return poly, count


def triangles_meet(tris: np.ndarray, planes: np.ndarray) -> bool:
    """Whether any of the triangles ``(k, 3, 3)`` meets the convex region ``planes (p, 4)``."""
    dist = tris @ planes[:, :3].T + planes[:, 3]  # (k, 3, p)
    if (dist >= 0).all(axis=2).any():
        return True
    undecided = ~(dist < 0).all(axis=1).any(axis=1)
    return bool(undecided.any() and clip_triangles(tris[undecided], planes).any())


def tile_frusta(wall: dict, frame: dict, tile: int, tol: float = 0.0) -> list:
    """A tile's frusta in display space, one per eye, each ``(6, 4)`` moved inward by
    ``tol``."""
    out = []
    for eye in eyes_of(frame):
        planes = tile_planes_display(wall, eye, tile)
        planes[:, 3] -= tol
        out.append(planes)
    return out


def meets(tris: np.ndarray, frusta: list) -> bool:
    """Whether any of the triangles meets any of the frusta (either eye's)."""
    return any(triangles_meet(tris, planes) for planes in frusta)


def tiles_of(wall: dict) -> int:
    return len(wall["screens"]) if "screens" in wall else wall["cols"] * wall["rows"]


def leaf_triangles_display(scene, frame: dict, leaf: int, world=None) -> np.ndarray:
    """A leaf's triangles in display space (point-only geometry as degenerate triangles);
    ``world`` overrides the scene's rest transforms (a moved scene)."""
    v, f = scene.leaf_mesh(leaf)
    m = (scene.world if world is None else world)[leaf]
    pts = to_display(frame, v @ m[:3, :3].T + m[:3, 3])
    return pts[f] if len(f) else np.repeat(pts[:, None], 3, axis=1)


def visible_leaves(scene, wall: dict, frame: dict, tol: float, world=None) -> list[set[int]]:
    """Per tile, the leaf ids with a triangle in the tile frustum (of either eye) shrunk by
    ``tol``."""
    tiles = tiles_of(wall)
    frusta = [tile_frusta(wall, frame, t, tol) for t in range(tiles)]
    out = [set() for _ in range(tiles)]
    for leaf in scene.leaves:
        tris = leaf_triangles_display(scene, frame, leaf, world)
        for t in range(tiles):
            if meets(tris, frusta[t]):
                out[t].add(int(leaf))
    return out


def visible_units(scene, wall: dict, frame: dict, tol: float, world=None) -> list[set[int]]:
    """Per tile, the childless nodes (clusters, and leaves not cut into clusters) with a
    triangle in the tile frustum (of either eye) shrunk by ``tol``: a cluster's triangles are
    its run of its leaf's mesh (``scene.cluster_faces``)."""
    tiles = tiles_of(wall)
    frusta = [tile_frusta(wall, frame, t, tol) for t in range(tiles)]
    first, count = scene.cluster_faces
    out = [set() for _ in range(tiles)]
    for leaf in scene.leaves:
        tris = leaf_triangles_display(scene, frame, leaf, world)
        below = np.arange(leaf, leaf + scene.size[leaf])
        for unit in below[scene.child_count[below] == 0]:
            part = tris[first[unit]:first[unit] + count[unit]] if unit != leaf else tris
            for t in range(tiles):
                if meets(part, frusta[t]):
                    out[t].add(int(unit))
    return out


def false_positives(scene, wall: dict, frame: dict, reported: list, tol: float,
                    world=None) -> tuple[int, int]:
    """``(false, total)``: reported (leaf, tile) pairs whose leaf does not meet the tile frustum
    grown by ``tol``, out of all reported pairs. ``reported[t]`` lists tile ``t``'s leaf ids."""
    false = total = 0
    cache: dict[int, np.ndarray] = {}
    for t, leaves in enumerate(reported):
        frusta = tile_frusta(wall, frame, t, -tol)
        for leaf in leaves:
            if leaf not in cache:
                cache[leaf] = leaf_triangles_display(scene, frame, leaf, world)
            total += 1
            false += not meets(cache[leaf], frusta)
    return false, total
