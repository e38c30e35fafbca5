"""Write the example screens walls (SPEC section 2b) of this folder:

* ``wall-cave.json``: a 4-wall CAVE with a floor, 3 m cube, the nominal eye at its centre;
* ``wall-cave2.json``: a CAVE2-like cylinder, 18 columns x 4 rows of flat panels on 320 degrees
  around the eye, 3.65 m away, with 10 mm bezels;
* ``wall-angled.json``: three 1.6 x 0.9 m panels, the outer two turned 30 degrees toward the
  viewer about the edges they share with the middle one.

    python examples/make_screens.py
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def screen(bl, br, tl, resolution) -> dict:
    return {"bottom_left": np.round(bl, 9).tolist(), "bottom_right": np.round(br, 9).tolist(),
            "top_left": np.round(tl, 9).tolist(), "resolution": list(resolution)}


def cave(size: float = 3.0) -> dict:
    h = size / 2
    res = (1920, 1920)
    walls = [  # front, left, right, back, floor: each seen from inside the cube
        ((-h, -h, -h), (h, -h, -h), (-h, h, -h)),
        ((-h, -h, h), (-h, -h, -h), (-h, h, h)),
        ((h, -h, -h), (h, -h, h), (h, h, -h)),
        ((h, -h, h), (-h, -h, h), (h, h, h)),
        ((-h, -h, h), (h, -h, h), (-h, -h, -h)),
    ]
    return {"screens": [screen(*map(np.array, w), res) for w in walls],
            "near": 0.05, "far": 1000.0}


def cylinder(cols: int = 18, rows: int = 4, degrees: float = 320.0, radius: float = 3.65,
             height: float = 2.32, bezel: float = 0.01) -> dict:
    step = math.radians(degrees) / cols
    width = 2 * radius * math.sin(step / 2) - bezel  # each panel a chord of its column
    panel_h = (height - (rows - 1) * bezel) / rows
    out = []
    for r in range(rows):  # row 0 at the top, as on a grid
        top = height / 2 - r * (panel_h + bezel)
        for c in range(cols):  # column 0 at the left
            theta = -math.radians(degrees) / 2 + (c + 0.5) * step
            inward = np.array([math.sin(theta), 0.0, -math.cos(theta)])  # from the eye out
            right = np.array([math.cos(theta), 0.0, math.sin(theta)])
            mid = inward * radius * math.cos(step / 2)
            bl = mid - right * width / 2 + np.array([0, top - panel_h, 0])
            out.append(screen(bl, bl + right * width, bl + np.array([0, panel_h, 0]),
                              (1366, 768)))
    return {"screens": out, "near": 0.1, "far": 1000.0}


def angled(width: float = 1.6, height: float = 0.9, distance: float = 2.0,
           degrees: float = 30.0) -> dict:
    a = math.radians(degrees)
    y0, y1 = -height / 2, height / 2
    left_edge, right_edge = np.array([-width / 2, 0, -distance]), np.array([width / 2, 0, -distance])
    out_dir = np.array([math.cos(a), 0.0, math.sin(a)])  # the right panel runs right and toward us
    res = (1920, 1080)
    panels = [
        (left_edge - out_dir * [1, 0, -1] * width, left_edge),  # left: mirror of the right
        (left_edge, right_edge),
        (right_edge, right_edge + out_dir * width),
    ]
    out = []
    for a_, b_ in panels:
        bl, br = a_ + [0, y0, 0], b_ + [0, y0, 0]
        out.append(screen(bl, br, bl + [0, y1 - y0, 0], res))
    return {"screens": out, "near": 0.1, "far": 1000.0}


if __name__ == "__main__":
    for name, spec in (("cave", cave()), ("cave2", cylinder()), ("angled", angled())):
        (HERE / f"wall-{name}.json").write_text(json.dumps(spec, indent=1) + "\n")
        print(f"wall-{name}.json: {len(spec['screens'])} screens")
