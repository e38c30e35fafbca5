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
      ],
      "occlusion": {"exclude": ["glass_roof"], "budget": 20000, "texels": 32}
    }

``shadows`` defaults to true and ``resolution`` (the shadow map's pixels) to 2048 x 2048. A
mirror reflects on the side its normal points to; ``polygon`` (optional, convex, in the plane)
bounds it, and culls what it cannot show. ``occlusion`` matters only on a wall that turns
occlusion culling on: the nodes that never occlude (their subtrees with them), and the
occluder triangles a frame and buffer texels across a tile, instead of the wall's (see
:class:`wallcull.occlude.OcclusionOptions`). Settings come from a file beside the scene
(``<scene file>.wallcull.json``), from ``--settings FILE``, or from the bundled scene. The
document is :class:`wallcull.documents.SettingsSpec` (docs/settings.md describes it for users).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from . import documents
from .documents import SettingsSpec
from .errors import InputError


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
    #: nodes that never occlude, and the occlusion's budget and texels when the scene sets them
    exclude: tuple[str, ...] = ()
    occlusion: Mapping[str, int] = field(default_factory=dict)

    @property
    def empty(self) -> bool:
        return not self.lights and not self.mirrors


def parse(raw: Mapping[str, Any] | SettingsSpec | None) -> Settings:
    """Validate a settings document (:class:`~wallcull.documents.SettingsSpec`; see the module
    docstring): refused in one line when it is not one."""
    doc = documents.parse(SettingsSpec, {} if raw is None else raw, "settings")
    lights = tuple(
        Light(item.name or f"light{k}", np.array(item.position), item.type,
              None if item.type != "spot" else documents.unit(item.direction),
              item.angle if item.type == "spot" else 180.0, item.resolution)
        for k, item in enumerate(doc.lights)
        if item.shadows)  # a light that casts no shadows needs no frustum
    mirrors = []
    for k, item in enumerate(doc.mirrors):
        normal, point = documents.unit(item.normal), np.array(item.point)
        polygon = None if item.polygon is None else np.array(item.polygon)
        mirrors.append(Mirror(item.name or f"mirror{k}", np.append(normal, -normal @ point),
                              polygon))
    dials = {k: v for k in ("budget", "texels")
             if (v := getattr(doc.occlusion, k)) is not None}
    return Settings(documents.unit(doc.up or (0.0, 1.0, 0.0)), lights, tuple(mirrors),
                    tuple(doc.occlusion.exclude), dials)


def read(path: str | Path) -> dict:
    """A settings document from a JSON file: an object (``[]`` or ``null`` is no settings
    document, where it used to be taken for empty settings)."""
    path = Path(path)
    text = documents.read_text(path, "settings")
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"malformed JSON in {path.name}: {exc}") from None
    if not isinstance(doc, dict):
        raise InputError(f"settings must be an object, got "
                         f"{type(doc).__name__ if doc is not None else 'null'} in {path.name}")
    return doc


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
