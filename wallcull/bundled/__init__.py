"""Bundled scenes: deterministic, seeded look-alikes of the paper's two models.

``build("fatehpur")`` (the Fatehpur Sikri palace city) and ``build("powerplant")`` (the UNC
power plant) return a :class:`trimesh.Scene` whose node tree has the paper's shape: node counts,
branching factor and triangle totals close to those reported in its section 5. Leaves are
template meshes instanced under named, stable nodes (``"powerplant/units/unit2/pipes/run07/
spool1/bend02"``). Scenes are z-up internally; their root node turns them to glTF's y-up.

``powerplant*K`` (and ``fatehpur*K``) names K copies side by side (:data:`TILED`), for scenes of
up to about a million nodes.
"""

from .generate import (BUNDLED, GENERATOR_VERSION, MAX_COPIES, TILED, build, copies, is_bundled,
                       parse, settings)

__all__ = ["BUNDLED", "GENERATOR_VERSION", "MAX_COPIES", "TILED", "build", "copies", "is_bundled",
           "parse", "settings"]
