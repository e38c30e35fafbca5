"""Camera paths through a scene, as frames for a wall: deterministic, any scene.

* ``orbit``: the camera circles the scene, rising and falling, on each frame at the distance
  where the scene's bounding box just fits inside the primary frustum's side planes, so the
  whole scene is in view and fills the wall: the paper's worst case (section 5, Fig. 4). (A wall whose ``far`` is
  shorter than that distance plus the sphere's radius cuts the far side off.)
* ``fly``: the camera flies a closed loop through the scene at a third of its height, looking
  along the path: what a user walking through the model sees, with most of it culled.

A wall of screens that no plane through the eye can hold on one side (a CAVE, a cylinder:
the screens surround the viewer) has no outer edges to fit the scene into: its orbit runs
inside the scene, the camera circling the centre at a quarter of the scene's extent, level,
looking along the circle, the model all around.
"""

from __future__ import annotations

import numpy as np

from .documents import unit
from .errors import InputError
from .wall import Frame, Wall, display_planes, matrix_quaternion

PATHS = ("orbit", "fly")
#: The most frames a camera path has (a day at 120 Hz is ten million).
MAX_FRAMES = 10_000_000


def look_rotation(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Rotation whose columns are display x, y, z in the world, looking along ``forward``."""
    z = -forward / np.linalg.norm(forward)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-9 * np.linalg.norm(up):  # looking straight along up
        x = np.cross(np.roll(up, 1), z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _frame(position, forward, up, wall: Wall) -> Frame:
    q = matrix_quaternion(look_rotation(np.asarray(forward, float), np.asarray(up, float)))
    return Frame.make(position, q, (0.0, 0.0, 0.0), wall)


def camera_path(kind: str, lo: np.ndarray, hi: np.ndarray, wall: Wall, frames: int,
                up=(0.0, 1.0, 0.0)) -> list[Frame]:
    """``frames`` frames of path ``kind`` around the box ``[lo, hi]`` (world space)."""
    if not 1 <= frames <= MAX_FRAMES:
        raise InputError(f"frames must be 1 to {MAX_FRAMES:,}, got {frames}")
    up = unit(up)
    center = (lo + hi) / 2
    # an orthonormal basis (a, b, up) of the world around the up axis
    a = np.cross(up, [1.0, 0, 0] if abs(up[0]) < 0.9 else [0, 0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(a, up)
    t = 2 * np.pi * np.arange(frames) / frames
    if kind == "orbit":
        elevation = np.radians(20 + 12 * np.sin(2 * t))
        away = (np.cos(elevation)[:, None] * (np.cos(t)[:, None] * a + np.sin(t)[:, None] * b)
                + np.sin(elevation)[:, None] * up)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])]) - center
        sides = _sides(wall)
        if sides is None:  # screens all around: orbit inside
            radius = 0.25 * np.linalg.norm((hi - lo) - ((hi - lo) @ up) * up)
            around = np.cos(t)[:, None] * a + np.sin(t)[:, None] * b
            along = -np.sin(t)[:, None] * a + np.cos(t)[:, None] * b
            return [_frame(center + radius * p, f, up, wall) for p, f in zip(around, along)]
        frames_out = []
        for d in away:
            # Camera at center + L d: corner p is inside side plane n (through the eye) when
            # n . (p - L d) >= 0, i.e. L >= (n . p) / (n . d) as n . d < 0. The nearest such L
            # puts the scene's box just inside the wall's outer edges.
            normals = sides @ look_rotation(-d, up).T
            reach = 1.02 * max(float(((corners @ normals.T) / (normals @ d)).max()), 0.0)
            reach = max(reach, 1.02 * wall.near + np.linalg.norm(hi - lo) / 2)
            frames_out.append(_frame(center + reach * d, -d, up, wall))
        return frames_out
    if kind == "fly":
        extent = hi - lo
        span_a, span_b = abs(extent @ a) * 0.35, abs(extent @ b) * 0.35
        height = (lo @ up) + 0.33 * (extent @ up) - center @ up
        pos = (center + height * up + span_a * np.sin(t)[:, None] * a
               + span_b * np.sin(2 * t)[:, None] * b)
        vel = span_a * np.cos(t)[:, None] * a + 2 * span_b * np.cos(2 * t)[:, None] * b
        return [_frame(p, v - 0.15 * np.linalg.norm(v) * up, up, wall) for p, v in zip(pos, vel)]
    raise InputError(f"unknown path {kind!r}; choose from {', '.join(PATHS)}")


def _sides(wall) -> np.ndarray | None:
    """Inward normals of the planes through the eye that bound every tile frustum (display
    space, eye at the origin): a grid's outer edges, or the cone around a wall of screens;
    None when the screens surround the eye."""
    if wall.kind == "grid":
        return display_planes(wall, np.zeros(3))[wall.layout.primary_planes[:4], :3]
    planes = wall.primary_planes(np.zeros(3))[6:]  # past the box around the eye
    return planes[:, :3] if len(planes) else None


def scene_path(scene, wall: Wall, kind: str, frames: int) -> list[Frame]:
    """``frames`` frames of path ``kind`` around a scene at rest: the box of its leaves' points,
    turned about the scene's up axis (its settings' ``up``, +y by default)."""
    return camera_path(kind, scene.box[0], scene.box[1], wall, frames,
                       up=scene.settings.get("up") or (0, 1, 0))
