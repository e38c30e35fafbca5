"""Scene settings: what a scene asks for beyond its geometry.

A scene may declare lights that cast shadows and planar mirrors; each tile then gets a shadow
frustum per light and a reflected view per mirror (:mod:`wallcull.fit`). A scene that declares
none gets neither: no computation, no bytes. The format (JSON)::

    {
      "up": [0, 1, 0],                       # for camera paths; default +y (glTF)
      "lights": [
        {"name": "sun", "position": [300, 400, 200]},                  # a point light
        {"name": "lamp", "type": "spot", "position": [0, 8, 0],
         "direction": [0, -1, 0], "angle": 35,                          # half-angle, degrees
         "resolution": [2048, 2048], "shadows": true}
      ],
      "mirrors": [
        {"name": "pool", "point": [50, -0.3, -55], "normal": [0, 1, 0],
         "polygon": [[35, -0.3, -71], [66, -0.3, -71], [66, -0.3, -40], [35, -0.3, -40]]}
      ]
    }

``shadows`` defaults to true and ``resolution`` (the shadow map's pixels) to 2048 x 2048. A
mirror reflects on the side its normal points to; ``polygon`` (optional, convex, in the plane)
bounds it, and culls what it cannot show. Settings come from a file beside the scene
(``<scene file>.wallcull.json``), from ``--settings FILE``, or from the bundled scene.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .errors import InputError
from .validate import as_vector


@dataclass(frozen=True)
class Light:
    name: str
    position: np.ndarray  # (3,) world
    kind: str = "point"  # "point" or "spot"
    direction: np.ndarray | None = None  # unit, spot lights
    angle: float = 180.0  # spot half-angle, degrees
    resolution: tuple[int, int] = (2048, 2048)


@dataclass(frozen=True, eq=False)
class Mirror:
    name: str
    plane: np.ndarray  # (4,) unit normal toward the reflective side, n . p + d = 0
    polygon: np.ndarray | None = None  # (k, 3) convex outline in the plane, or None: unbounded

    @cached_property
    def reflection(self) -> np.ndarray:
        """The 4x4 reflection through the plane (an involution, det -1)."""
        n, d = self.plane[:3], self.plane[3]
        m = np.eye(4)
        m[:3, :3] -= 2 * np.outer(n, n)
        m[:3, 3] = -2 * d * n
        return m


@dataclass(frozen=True)
class Settings:
    up: np.ndarray
    lights: tuple[Light, ...] = ()
    mirrors: tuple[Mirror, ...] = ()

    @property
    def empty(self) -> bool:
        return not self.lights and not self.mirrors


def _vec(value: Any, what: str, n: int = 3) -> np.ndarray:
    return np.array(as_vector(value, n, what))  # the wall's check: n finite numbers


def _unit(value: Any, what: str) -> np.ndarray:
    v = _vec(value, what)
    norm = np.linalg.norm(v)
    if norm == 0:
        raise InputError(f"{what} must not be zero")
    return v / norm


def parse(raw: Mapping[str, Any] | None) -> Settings:
    """Validate a settings document (see the module docstring)."""
    raw = dict(raw or {})
    unknown = set(raw) - {"up", "lights", "mirrors"}
    if unknown:
        raise InputError(f"unknown scene setting(s): {', '.join(sorted(unknown))}")
    up = _unit(raw.get("up", (0, 1, 0)), "settings up")
    lights = []
    for k, item in enumerate(raw.get("lights", [])):
        if not isinstance(item, Mapping):
            raise InputError(f"light {k} must be an object")
        name = str(item.get("name", f"light{k}"))
        kind = item.get("type", "point")
        if kind not in ("point", "spot"):
            raise InputError(f"light {name!r}: type must be 'point' or 'spot'")
        if not item.get("shadows", True):
            continue  # a light that casts no shadows needs no frustum
        res = item.get("resolution", (2048, 2048))
        if (not isinstance(res, (list, tuple)) or len(res) != 2
                or not all(isinstance(r, int) and 0 < r <= 1 << 15 for r in res)):
            raise InputError(f"light {name!r}: resolution must be two positive integers")
        direction, angle = None, 180.0
        if kind == "spot":
            direction = _unit(item.get("direction"), f"light {name!r} direction")
            angle = float(item.get("angle", 45.0))
            if not 0 < angle < 90:
                raise InputError(f"light {name!r}: spot angle must be in (0, 90) degrees")
        lights.append(Light(name, _vec(item.get("position"), f"light {name!r} position"), kind,
                            direction, angle, (res[0], res[1])))
    mirrors = []
    for k, item in enumerate(raw.get("mirrors", [])):
        if not isinstance(item, Mapping):
            raise InputError(f"mirror {k} must be an object")
        name = str(item.get("name", f"mirror{k}"))
        normal = _unit(item.get("normal"), f"mirror {name!r} normal")
        point = _vec(item.get("point"), f"mirror {name!r} point")
        polygon = None
        if item.get("polygon") is not None:
            polygon = np.asarray(item["polygon"], dtype=np.float64)
            if polygon.ndim != 2 or polygon.shape[1] != 3 or len(polygon) < 3:
                raise InputError(f"mirror {name!r}: polygon must be three or more points")
            size = np.ptp(polygon, axis=0).max()
            if not np.isfinite(polygon).all() or \
                    np.abs((polygon - point) @ normal).max() > 1e-6 * max(size, 1.0):
                raise InputError(f"mirror {name!r}: polygon must lie in the mirror's plane")
        mirrors.append(Mirror(name, np.append(normal, -normal @ point), polygon))
    return Settings(up, tuple(lights), tuple(mirrors))


def read(path: str | Path) -> dict:
    """A settings document from a JSON file."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"settings file not found: {path}") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"malformed JSON in {path.name}: {exc}") from None


def sidecar(scene_path: str | Path) -> dict:
    """The settings beside a scene file (``<file>.wallcull.json``), or none."""
    path = Path(f"{scene_path}.wallcull.json")
    return read(path) if path.is_file() else {}


def spot_contains(light: Light, points: np.ndarray) -> np.ndarray:
    """Which points a spot light's cone reaches (all, for a point light)."""
    if light.kind != "spot":
        return np.ones(len(points), dtype=bool)
    rel = points - light.position
    dist = np.linalg.norm(rel, axis=1)
    return rel @ light.direction >= dist * math.cos(math.radians(light.angle))
