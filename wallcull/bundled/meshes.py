"""Template meshes: the few shapes every bundled scene is instanced from.

A generated scene holds each template once in ``scene.geometry`` and places it many times through
node transforms (translation, rotation, non-uniform scale), which is how a scene graph of
thousands of parts stays a few megabytes and builds in a second. Templates live in a unit frame
chosen so one transform fits them to a part:

* prisms (box, pipe, I-beam, grating, railing, stairs, ...) span ``[-0.5, 0.5]`` on each axis, or
  ``z in [-0.5, 0.5]`` with a unit cross-section for the long ones, so ``scale`` is the part's size;
* bodies of revolution (columns, domes, tanks) stand on ``z = 0`` with their axis on ``z`` and
  radius about 1, so ``scale = (r, r, height)``;
* architectural panels (arches, jali screens, walls) span ``x, y in [-0.5, 0.5]`` (width,
  thickness) and ``z in [0, 1]`` (height).

Everything here is plain numpy on ``(vertices, faces)`` pairs, built without randomness, so a
template is bit-identical on every call; :func:`template` caches the arrays and each build wraps
fresh copies in a :class:`trimesh.Trimesh`. Surfaces are closed and wound outward (positive
volume) unless a docstring says a part is an open tube; the tests check this.

Z is up in this module (the architect's convention); the scene root turns it into glTF's y-up.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Callable

import numpy as np

if TYPE_CHECKING:  # imported where used: names and layouts load without trimesh
    import trimesh

VF = tuple[np.ndarray, np.ndarray]  # (vertices (n, 3) float64, faces (m, 3) int64)

# The unit cube [-0.5, 0.5]^3 with outward winding (trimesh's own vertex order).
_CUBE_V = np.array(
    [[-1, -1, -1], [-1, -1, 1], [-1, 1, -1], [-1, 1, 1], [1, -1, -1], [1, -1, 1], [1, 1, -1], [1, 1, 1]],
    dtype=np.float64,
) * 0.5
_CUBE_F = np.array(
    [[1, 3, 0], [4, 1, 0], [0, 3, 2], [2, 4, 0], [1, 7, 3], [5, 1, 4],
     [5, 7, 1], [3, 7, 2], [6, 4, 2], [2, 7, 6], [6, 5, 4], [7, 5, 6]],
    dtype=np.int64,
)


# ---------------------------------------------------------------------------------------------
# building blocks


def merge(*parts: VF) -> VF:
    """Concatenate meshes into one vertex and face array (faces re-indexed)."""
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)])
    return vertices, faces


def transformed(part: VF, matrix: np.ndarray) -> VF:
    """Apply a 4x4 affine ``matrix`` to a mesh; flips the winding if it mirrors."""
    v, f = part
    v = v @ matrix[:3, :3].T + matrix[:3, 3]
    if np.linalg.det(matrix[:3, :3]) < 0:
        f = f[:, ::-1]
    return v, f


def boxes(centers: np.ndarray, sizes: np.ndarray, yaw: np.ndarray | None = None) -> VF:
    """Many axis-aligned boxes (optionally turned by ``yaw`` radians about z) as one mesh.

    ``centers`` and ``sizes`` are ``(n, 3)``; the result has ``12 n`` triangles.
    """
    centers = np.atleast_2d(np.asarray(centers, dtype=np.float64))
    sizes = np.broadcast_to(np.asarray(sizes, dtype=np.float64), centers.shape)
    v = _CUBE_V[None] * sizes[:, None]
    if yaw is not None:
        c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        v = np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], -1)
    v = (v + centers[:, None]).reshape(-1, 3)
    f = (_CUBE_F[None] + 8 * np.arange(len(centers))[:, None, None]).reshape(-1, 3)
    return v, f


def grid_faces(rings: int, sections: int, closed: bool = True) -> np.ndarray:
    """Triangles joining ``rings`` consecutive loops of ``sections`` vertices each.

    Vertex ``(i, j)`` is ``i * sections + j``. With the loops running counter-clockwise seen from
    the end of the sweep and the sweep going forward, the triangles face outward.
    """
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(sections if closed else sections - 1), indexing="ij")
    a = i * sections + j
    b = i * sections + (j + 1) % sections
    c = a + sections
    d = b + sections
    return np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], -1).reshape(-1, 3)


def lathe(profile: np.ndarray, sections: int) -> VF:
    """Surface of revolution about z of a ``(m, 2)`` profile of ``(radius, z)``, bottom to top.

    End points on the axis (radius 0) become single pole vertices, so a profile that starts and
    ends on the axis gives a closed solid with ``2 (m - 2) sections`` triangles.
    """
    profile = np.array(profile, dtype=np.float64)
    profile[np.abs(profile[:, 0]) < 1e-9, 0] = 0.0  # cos(pi/2) is not quite 0: snap to the axis
    pole0, pole1 = profile[0, 0] == 0.0, profile[-1, 0] == 0.0
    ring = profile[int(pole0): len(profile) - int(pole1)]
    t = 2.0 * np.pi * np.arange(sections) / sections
    v = np.stack(
        [ring[:, :1] * np.cos(t), ring[:, :1] * np.sin(t), np.broadcast_to(ring[:, 1:], (len(ring), sections))],
        -1,
    ).reshape(-1, 3)
    f = [grid_faces(len(ring), sections)]
    j = np.arange(sections)
    n = len(v)
    if pole0:
        f.append(np.stack([np.full(sections, n), (j + 1) % sections, j], -1))
        v = np.vstack([v, [0.0, 0.0, profile[0, 1]]])
    if pole1:
        top = (len(ring) - 1) * sections
        f.append(np.stack([np.full(sections, len(v)), top + j, top + (j + 1) % sections], -1))
        v = np.vstack([v, [0.0, 0.0, profile[-1, 1]]])
    return v, np.concatenate(f)


def sweep(centers: np.ndarray, normals: np.ndarray, binormals: np.ndarray, radius: float, sections: int) -> VF:
    """An open tube of ``radius`` around a polyline given with its normal frames ``(m, 3)`` each.

    The frames (normal, binormal, tangent) must be right-handed so the tube faces outward.
    """
    t = 2.0 * np.pi * np.arange(sections) / sections
    ring = np.cos(t)[None, :, None] * normals[:, None] + np.sin(t)[None, :, None] * binormals[:, None]
    v = (centers[:, None] + radius * ring).reshape(-1, 3)
    return v, grid_faces(len(centers), sections)


def cylinder(sections: int, radius: float = 1.0, z0: float = -0.5, z1: float = 0.5) -> VF:
    """A closed cylinder on the z axis from ``z0`` to ``z1``: ``4 sections`` triangles."""
    return lathe([[0.0, z0], [radius, z0], [radius, z1], [0.0, z1]], sections)


def torus_arc(angle: float, bend: float, radius: float, segments: int, sections: int) -> VF:
    """An open bent tube: the arc of ``bend`` radius from the origin, leaving along +z, turning
    toward +x by ``angle`` radians, around its centre ``(bend, 0, 0)``."""
    th = np.linspace(0.0, angle, segments + 1)
    c = np.stack([bend * (1 - np.cos(th)), np.zeros_like(th), bend * np.sin(th)], -1)
    n = np.stack([-np.cos(th), np.zeros_like(th), np.sin(th)], -1)  # away from the bend centre
    b = np.cross(np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1), n)  # tangent x normal
    return sweep(c, n, b, radius, sections)


def ring_torus(major: float, minor: float, segments: int, sections: int) -> VF:
    """A closed torus about z (a hand wheel, a ring moulding): ``2 segments sections`` triangles."""
    v, f = torus_arc(2.0 * np.pi, major, minor, segments, sections)
    v, f = v[: segments * sections], f.copy()
    f[f >= segments * sections] -= segments * sections  # close the loop onto the first ring
    # centre the ring on the origin, then lay its x-z plane down onto x-y
    return transformed((v, f), _rot_x90() @ _shift(-major, 0.0, 0.0))


# ---------------------------------------------------------------------------------------------
# industrial templates


def pipe(sections: int) -> VF:
    """A straight pipe (closed cylinder) of radius 1 on z in [-0.5, 0.5]."""
    return cylinder(sections)


def elbow(degrees: float, sections: int, segments: int) -> VF:
    """A pipe bend of unit pipe radius, bend radius 1.5 (the long-radius standard), open ends.

    Placed with uniform scale ``r`` (the pipe radius) at the start of the bend, with local z the
    incoming direction and local x toward the outgoing one (see ``tree.polyline_pipe``).
    """
    return torus_arc(np.radians(degrees), 1.5, 1.0, segments, sections)


def ibeam() -> VF:
    """A wide-flange I-beam along z in [-0.5, 0.5]: flanges across x, web along y (the depth)."""
    return boxes([[0, 0.45, 0], [0, -0.45, 0], [0, 0, 0]], [[1, 0.1, 1], [1, 0.1, 1], [0.12, 0.8, 1]])


def grating(bars: int) -> VF:
    """A floor grating panel (x, y in [-0.5, 0.5], z in [-0.5, 0.5]): a frame and bearing bars."""
    x = (np.arange(bars) + 0.5) / bars - 0.5
    c = np.concatenate([[[0, -0.48, 0], [0, 0.48, 0], [-0.48, 0, 0], [0.48, 0, 0]], np.stack([x, 0 * x, 0 * x], -1)])
    s = np.concatenate([[[1, 0.04, 1], [1, 0.04, 1], [0.04, 1, 1], [0.04, 1, 1]], np.tile([[0.01, 0.96, 0.9]], (bars, 1))])
    return boxes(c, s)


def railing(posts: int, sections: int) -> VF:
    """A guard rail along x in [-0.5, 0.5], z in [0, 1]: round posts, a top rail, a knee rail."""
    x = np.linspace(-0.48, 0.48, posts)
    parts = [transformed(cylinder(sections, 0.02, 0.0, 1.0), _shift(xi, 0, 0)) for xi in x]
    rail = transformed(cylinder(sections, 0.025, -0.5, 0.5), _turn_to_x())
    parts += [transformed(rail, _shift(0, 0, 1.0)), transformed(rail, _shift(0, 0, 0.5))]
    parts.append(boxes([[0, 0, 0.05]], [[1, 0.01, 0.1]]))
    return merge(*parts)


def stair_flight(steps: int) -> VF:
    """A straight stair rising +z over a run along +x, both in [-0.5, 0.5]: treads and stringers.

    Scale to (run, width, rise); the stringers are sheared boxes, so the flight is one compact,
    sloped part whose best box is oriented, not axis-aligned.
    """
    k = np.arange(steps)
    tread = boxes(np.stack([(k + 0.5) / steps - 0.5, 0 * k, (k + 1) / steps - 0.5 - 0.02], -1),
                  [[1.0 / steps + 0.02, 0.9, 0.03]])
    v, f = boxes([[0, -0.47, 0], [0, 0.47, 0]], [[0.88, 0.06, 0.12]])
    v[:, 2] += v[:, 0]  # shear the stringers along the slope
    return merge(tread, (v, f))


def ladder(rungs: int) -> VF:
    """A cage-less ladder: two rails on x = +-0.5, rungs along x, z in [0, 1]."""
    z = (np.arange(rungs) + 0.5) / rungs
    return merge(boxes([[-0.5, 0, 0.5], [0.5, 0, 0.5]], [[0.1, 0.3, 1]]),
                 boxes(np.stack([0 * z, 0 * z, z], -1), [[1, 0.2, 0.015]]))


def vessel(sections: int, rings: int, head: float = 0.25) -> VF:
    """A pressure vessel / tank: a cylinder of radius 1 on z in [0, 1] with elliptical heads of
    depth ``head`` inside that range."""
    a = np.linspace(0.0, np.pi / 2, rings)
    bottom = np.stack([np.sin(a), head * (1 - np.cos(a))], -1)
    prof = np.concatenate([bottom, bottom[::-1] * [1, -1] + [0, 1]])
    prof[[0, -1], 0] = 0.0  # exact poles, so the lathe closes the heads
    return lathe(prof, sections)


def valve(sections: int) -> VF:
    """A gate valve for a pipe of unit radius along z: body, flanges, bonnet, stem, hand wheel."""
    a = np.linspace(-np.pi / 2, np.pi / 2, sections // 2)
    body = lathe(np.stack([1.6 * np.cos(a), 1.6 * np.sin(a)], -1), sections)
    flange = cylinder(sections, 1.8, -0.15, 0.15)
    bonnet = transformed(cylinder(sections, 0.9, 0.0, 2.2), _turn_to_x())
    stem = transformed(cylinder(max(8, sections // 4), 0.15, 0.0, 4.5), _turn_to_x())
    wheel = transformed(ring_torus(1.4, 0.12, sections, max(6, sections // 4)), _turn_to_x() @ _shift(0, 0, 4.2))
    return merge(body, transformed(flange, _shift(0, 0, -1.5)), transformed(flange, _shift(0, 0, 1.5)),
                 bonnet, stem, wheel)


def pump(sections: int) -> VF:
    """A pump set on a skid, the shaft along x in [-0.5, 0.5]: base, finned motor, volute, nozzle."""
    base = boxes([[0, 0, 0.05]], [[1.0, 0.45, 0.1]])
    motor = transformed(cylinder(sections, 0.15, -0.5, -0.05), _shift(0, 0, 0.3) @ _turn_to_x())
    k = 2 * np.pi * np.arange(24) / 24
    fins = boxes(np.stack([np.full(24, -0.27), 0.16 * np.cos(k), 0.3 + 0.16 * np.sin(k)], -1), [[0.4, 0.02, 0.02]])
    casing = transformed(lathe(_ellipse_profile(0.2, 0.12, sections // 2), sections), _shift(0.25, 0, 0.3) @ _rot_x90())
    nozzle = transformed(cylinder(sections, 0.07, 0.0, 0.25), _shift(0.25, 0, 0.4))
    return merge(base, motor, fins, casing, nozzle)


def stack(sections: int, rings: int) -> VF:
    """A chimney: a slightly tapered shell, radius 1 at the foot, z in [0, 1], with a cap band."""
    z = np.linspace(0.0, 0.98, rings)
    r = 1.0 - 0.3 * z
    band = [[r[-1] + 0.05, 0.98], [r[-1] + 0.05, 1.0], [0.0, 1.0]]
    return lathe(np.concatenate([[[0.0, 0.0]], np.stack([r, z], -1), band]), sections)


# ---------------------------------------------------------------------------------------------
# architectural templates (Mughal red sandstone)


def onion_dome(sections: int, rings: int) -> VF:
    """A bulbous Mughal dome of base radius 1 on z = 0, swelling to 1.15 and ending in a point
    at z = 1.7 (the finial is a separate part)."""
    t = np.linspace(0.0, 1.0, rings)
    r = (1.0 + 0.5 * np.sin(np.pi * np.clip(t * 1.4, 0, 1))) * np.cos(0.5 * np.pi * t) ** 1.3
    r = r / r.max() * 1.15
    r[0] = 1.0
    z = 1.7 * (1 - np.cos(0.5 * np.pi * t) ** 0.9) ** 0.85
    prof = np.concatenate([[[0.0, 0.0]], np.stack([r, z], -1)[:-1], [[0.0, 1.7]]])
    return lathe(prof, sections)


def column(sections: int, rings: int, variant: int) -> VF:
    """A carved column of radius ~1 (scaled to the real one) on z in [0, 1]: base mouldings, a
    shaft banded by ``variant``-dependent rings, a bracket capital. Deterministic per variant."""
    z = np.linspace(0.0, 1.0, rings)
    bands = 3 + variant % 4
    shaft = 0.7 + 0.08 * np.abs(np.sin(np.pi * bands * z)) ** (1 + variant % 3)
    base = np.where(z < 0.08, 1.0, 0.0)
    capital = np.where(z > 0.88, 0.35 + 0.65 * (z - 0.88) / 0.12, 0.0)
    r = np.maximum(shaft, np.maximum(base, capital + 0.6 * (z > 0.88)))
    r = r / r.max()
    prof = np.concatenate([[[0.0, 0.0]], np.stack([r, z], -1), [[0.0, 1.0]]])
    return lathe(prof, sections)


def finial(sections: int) -> VF:
    """A kalasha finial: stacked bulbs on a spike, radius 1, z in [0, 1]."""
    z = np.linspace(0.0, 1.0, 24)
    r = 0.2 + 0.8 * np.abs(np.sin(2.5 * np.pi * z)) * (1 - z)
    prof = np.concatenate([[[0.0, 0.0]], np.stack([r, z], -1)[:-1], [[0.0, 1.0]]])
    return lathe(prof, sections)


def arch_panel(points: int, pointed: float = 0.35) -> VF:
    """A wall panel pierced by a pointed arch: x (width), y (thickness) in [-0.5, 0.5], z in [0, 1].

    The opening is 0.6 wide, springs at z = 0.5 and peaks near 0.89; the solid is closed. Front
    and back faces are strips pairing ``points`` samples of the opening with the same number of
    samples of the outer rectangle, both walked from the bottom left, over the top, to the
    bottom right.
    """
    half, spring = 0.3, 0.5
    # two arcs of radius rho centred at +-pointed*half on the springing line meet at the apex
    rho = half * (1 + pointed)
    theta = np.arccos(-(pointed * half) / rho)  # the apex (x = 0) seen from the left arc's centre
    n_side = points // 4
    n_arc = points // 2 - n_side
    left_arc = np.linspace(np.pi, theta, n_arc)
    left = np.stack([pointed * half + rho * np.cos(left_arc), spring + rho * np.sin(left_arc)], -1)
    jamb = np.stack([np.full(n_side, -half), np.linspace(0.0, spring, n_side, endpoint=False)], -1)
    inner_l = np.concatenate([jamb, left])
    inner = np.concatenate([inner_l, inner_l[::-1][1:] * [-1, 1]])
    # outer rectangle sampled at the same relative arc length
    length = np.r_[0, np.cumsum(np.linalg.norm(np.diff(inner, axis=0), axis=1))]
    s = length / length[-1] * 3.0  # left side [0,1], top [1,2], right side [2,3]
    outer = np.where(s[:, None] < 1, np.stack([np.full_like(s, -0.5), s], -1),
                     np.where(s[:, None] < 2, np.stack([s - 1.5, np.ones_like(s)], -1),
                              np.stack([np.full_like(s, 0.5), 3 - s], -1)))
    # the corners of the rectangle must be vertices, or the face would cut them off
    outer[np.argmin(np.abs(s - 1))] = [-0.5, 1.0]
    outer[np.argmin(np.abs(s - 2))] = [0.5, 1.0]
    m = len(inner)
    loop = np.concatenate([inner, outer[::-1]])  # one closed outline: opening then rectangle back
    front = np.stack([loop[:, 0], np.full(2 * m, -0.5), loop[:, 1]], -1)
    back = front * [1, -1, 1]
    v = np.concatenate([front, back])
    k = np.arange(m - 1)
    i0, i1, o0, o1 = k, k + 1, 2 * m - 1 - k, 2 * m - 2 - k
    face_front = np.concatenate([np.stack([i0, i1, o0], -1), np.stack([i1, o1, o0], -1)])
    face_back = face_front[:, ::-1] + 2 * m
    # the side walls: the outline extruded front to back, which closes the solid
    a = np.arange(2 * m)
    b = (a + 1) % (2 * m)
    sides = np.concatenate([np.stack([a, a + 2 * m, b], -1), np.stack([b, a + 2 * m, b + 2 * m], -1)])
    return v, np.concatenate([face_front, face_back, sides])


def jali(cols: int, rows: int, sections: int) -> VF:
    """A pierced stone screen: a frame around a lattice of small ring rosettes on bars.
    x (width), y (thickness) in [-0.5, 0.5], z in [0, 1]."""
    frame = boxes([[0, 0, 0.03], [0, 0, 0.97], [-0.47, 0, 0.5], [0.47, 0, 0.5]],
                  [[1, 1, 0.06], [1, 1, 0.06], [0.06, 1, 1], [0.06, 1, 1]])
    x = -0.44 + 0.88 * (np.arange(cols) + 0.5) / cols
    z = 0.06 + 0.88 * (np.arange(rows) + 0.5) / rows
    bars = merge(boxes(np.stack([x, 0 * x, np.full(cols, 0.5)], -1), [[0.01, 0.6, 0.88]]),
                 boxes(np.stack([np.zeros(rows), 0 * z, z], -1), [[0.88, 0.6, 0.01]]))
    r = 0.35 * min(0.88 / cols, 0.88 / rows)
    ring = transformed(ring_torus(r, r * 0.25, sections, 6), _rot_x90())
    gx, gz = np.meshgrid(x, z, indexing="ij")
    rv, rf = ring
    v = (rv[None] + np.stack([gx.ravel(), 0 * gx.ravel(), gz.ravel()], -1)[:, None]).reshape(-1, 3)
    f = (rf[None] + len(rv) * np.arange(gx.size)[:, None, None]).reshape(-1, 3)
    return merge(frame, bars, (v, f))


def battlement(merlons: int) -> VF:
    """A fort wall with a merlon crest: x (length), y (thickness) in [-0.5, 0.5], z in [0, 1]."""
    x = -0.5 + (np.arange(merlons) + 0.5) / merlons
    crest = boxes(np.stack([x, np.full(merlons, -0.35), np.full(merlons, 0.93)], -1), [[0.6 / merlons, 0.3, 0.14]])
    return merge(boxes([[0, 0, 0.43]], [[1, 1, 0.86]]), crest)


def chhajja(brackets: int) -> VF:
    """A sloping stone eave with corbel brackets, ringing a square roof: x, y in [-0.5, 0.5],
    z in [0, 1] (thin slab on top, brackets below)."""
    v, f = boxes([[0, 0, 0.85]], [[1, 1, 0.3]])
    top = v[:, 2] > 0.9
    v[top, :2] *= 0.85  # the slab slopes down and out
    k = (np.arange(brackets) + 0.5) / brackets - 0.5
    edge = np.concatenate([np.stack([k, np.full_like(k, -0.42)], -1), np.stack([k, np.full_like(k, 0.42)], -1),
                           np.stack([np.full_like(k, -0.42), k], -1), np.stack([np.full_like(k, 0.42), k], -1)])
    br = boxes(np.c_[edge, np.full(len(edge), 0.45)], [[0.35 / brackets, 0.35 / brackets, 0.5]])
    return merge((v, f), br)


def pillars(sections: int, rings: int) -> VF:
    """The four columns of a chhatri at the corners of x, y in [-0.5, 0.5], z in [0, 1]."""
    col = column(sections, rings, 1)
    col = (col[0] * [0.08, 0.08, 1.0], col[1])
    return merge(*[transformed(col, _shift(x, y, 0)) for x in (-0.42, 0.42) for y in (-0.42, 0.42)])


def tusk_ring(tusks: int, sections: int) -> VF:
    """A ring of stone elephant tusks studding a tower (the Hiran Minar), about a unit circle
    at z = 0, each tusk a cone pointing outward and slightly up."""
    cone = lathe([[0.0, 0.0], [0.06, 0.0], [0.0, 0.6]], sections)
    parts = []
    for k in range(tusks):
        a = 2 * np.pi * k / tusks
        m = _rot_z(a) @ _shift(1.0, 0, 0) @ _rot_y(np.radians(70))
        parts.append(transformed(cone, m))
    return merge(*parts)


def steps(n: int) -> VF:
    """A flight of ``n`` solid steps rising along +x: x, y in [-0.5, 0.5], z in [0, 1]."""
    k = np.arange(n)  # step k covers x in [k/n - 0.5, 0.5] up to height (k + 1) / n
    return boxes(np.stack([k / (2 * n), 0 * k, (k + 1) / (2 * n)], -1),
                 np.stack([1 - k / n, np.ones(n), (k + 1) / n], -1))


# ---------------------------------------------------------------------------------------------
# small matrix helpers (module-private; scenes use tree.py's)


def _shift(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = x, y, z
    return m


def _rot_z(a: float) -> np.ndarray:
    m = np.eye(4)
    c, s = np.cos(a), np.sin(a)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


def _rot_y(a: float) -> np.ndarray:
    m = np.eye(4)
    c, s = np.cos(a), np.sin(a)
    m[0, 0], m[0, 2], m[2, 0], m[2, 2] = c, s, -s, c
    return m


def _rot_x90() -> np.ndarray:
    """Turn z into -y (a shape standing on z now faces the viewer along -y)."""
    return np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])


def _turn_to_x() -> np.ndarray:
    """Turn z into +x (lay a shape built along z down along x)."""
    return _rot_y(np.pi / 2)


def _ellipse_profile(radius: float, half_height: float, n: int) -> np.ndarray:
    a = np.linspace(-np.pi / 2, np.pi / 2, n)
    return np.stack([radius * np.cos(a), half_height * np.sin(a)], -1)


# ---------------------------------------------------------------------------------------------
# the catalogue

#: name -> factory; names encode the tessellation so two resolutions are two templates.
TEMPLATES: dict[str, Callable[[], VF]] = {
    "box": lambda: boxes([[0, 0, 0]], [[1, 1, 1]]),
    "pipe8": lambda: pipe(8),
    "pipe16": lambda: pipe(16),
    "pipe32": lambda: pipe(32),
    "elbow90_16": lambda: elbow(90, 16, 8),
    "elbow90_32": lambda: elbow(90, 32, 12),
    "elbow45_16": lambda: elbow(45, 16, 6),
    "elbow45_32": lambda: elbow(45, 32, 8),
    "ibeam": ibeam,
    "grating": lambda: grating(24),
    "railing": lambda: railing(4, 12),
    "stairs": lambda: stair_flight(14),
    "ladder": lambda: ladder(20),
    "vessel": lambda: vessel(64, 16),
    "drum": lambda: vessel(48, 10, head=0.1),
    "valve": lambda: valve(24),
    "pump": lambda: pump(32),
    "stack": lambda: stack(64, 40),
    "onion_dome": lambda: onion_dome(96, 48),
    "small_dome": lambda: onion_dome(48, 24),
    "finial": lambda: finial(24),
    **{f"column{k}": functools.partial(column, 64, 40, k) for k in range(6)},
    "pier": lambda: column(32, 24, 0),
    "arch": lambda: arch_panel(160),
    "jali": lambda: jali(16, 24, 8),
    "battlement": lambda: battlement(24),
    "chhajja": lambda: chhajja(12),
    "pillars": lambda: pillars(32, 24),
    "tusks": lambda: tusk_ring(12, 16),
    "steps": lambda: steps(8),
}


@functools.lru_cache(maxsize=None)
def _cached(name: str) -> VF:
    v, f = TEMPLATES[name]()
    v = np.ascontiguousarray(v, dtype=np.float64)
    f = np.ascontiguousarray(f, dtype=np.int64)
    v.flags.writeable = False
    f.flags.writeable = False
    return v, f


def template(name: str) -> trimesh.Trimesh:
    """A fresh mesh of the named template (its own copies of the cached arrays).

    ``process=False`` keeps vertices exactly as built: merging or reordering would only cost time
    and could differ between trimesh versions.
    """
    import trimesh  # only here: the bundled scenes' names and layouts load without it

    v, f = _cached(name)
    return trimesh.Trimesh(vertices=v.copy(), faces=f.copy(), process=False)
