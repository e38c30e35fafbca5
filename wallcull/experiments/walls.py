"""Walls that are not a flat grid seen by one eye: an angled three-panel wall, a CAVE of four
walls and a floor, and a CAVE2-like cylinder of 72 screens (``examples/``), beside the 8 x 8
grid, each mono and stereo.

The power plant, OBBs; the orbit path, which for walls that surround the user (the CAVEs) is a
ring inside the plant with the camera looking along it (:func:`wallcull.paths.camera_path`).
Each configuration's three hierarchy methods are timed in turns over the same frames
(:func:`wallcull.bench.in_turns`), as ``wallcull bench --wall ... [--stereo IPD]`` times them. Stereo frames are the same frames with two eyes 64 mm apart, the head level with the
display (SPEC section 3): a grid is culled once against planes that hold both eyes' frusta, a
screens wall eye by eye and merged.
"""

from __future__ import annotations

import json

import numpy as np

from ..bench import in_turns, timing
from ..wall import Frame, Wall
from . import common as C
from .context import ROOT, Context

WALLS = {"8 x 8 grid": "wall-8x8.json", "angled, 3 panels": "wall-angled.json",
         "CAVE + floor, 5": "wall-cave.json", "CAVE2-like, 72": "wall-cave2.json"}
METHODS = ("adaptive", "oh", "fh")
IPD = 0.064


def _wall(file: str) -> Wall:
    return Wall.from_dict(json.loads((ROOT / "examples" / file).read_text()))


def run(ctx: Context) -> tuple[dict, str]:
    runs = [(name, eyes) for name in WALLS for eyes in ("mono", "stereo")]
    task = ctx.task("walls", len(runs) * len(METHODS))
    pristine = C.Pristine("powerplant")
    scene = pristine.fresh()
    out: dict = {}
    for name, eyes in runs:
        wall = _wall(WALLS[name])
        frames = C.path_frames(scene, wall, "orbit", ctx.size(120, 6))
        if eyes == "stereo":
            frames = [Frame.make(f.position, f.orientation, f.eye, wall,
                                 (IPD, (1.0, 0.0, 0.0, 0.0))) for f in frames]
        timed = in_turns({m: timing(scene, wall, frames, m, "obb") for m in METHODS},
                         len(frames))  # the methods in turns: of the same minutes
        per = {m: {k: timed[m][k] for k in ("median_ms", "p99_ms", "tests_per_frame",
                                            "nodes_per_frame")} for m in METHODS}
        task.advance(len(METHODS))
        out.setdefault(name, {"tiles": wall.tiles})[eyes] = per
    task.done()
    data = {"scene": "powerplant", "path": "orbit", "bounds": "obb", "ipd": IPD, "walls": out}
    return data, report(ctx, data)


def report(ctx: Context, data: dict) -> str:
    plt = C.pyplot()
    md = ["## Screens anywhere and stereo\n",
          "Walls given screen by screen (SPEC section 2b): an angled three-panel wall, a CAVE "
          "(four walls and a floor around the user) and a CAVE2-like cylinder (18 columns x 4 "
          "rows on 320 degrees), beside the 8 x 8 grid; each mono and stereo "
          f"(eyes {data['ipd'] * 1000:.0f} mm apart). The power plant, OBBs, the orbit path: "
          "around the plant for the grid and the angled wall, a ring inside it for the CAVEs. "
          "Median culling time per frame (the frame's planes included) and box-plane tests:\n",
          "    wallcull bench powerplant --wall examples/wall-cave2.json --methods adaptive,oh,fh"
          "\n    wallcull bench powerplant --wall examples/wall-8x8.json --stereo 0.064\n"]
    rows = []
    for name, w in data["walls"].items():
        for eyes in ("mono", "stereo"):
            per = w[eyes]
            rows.append([name if eyes == "mono" else "", w["tiles"] if eyes == "mono" else "",
                         eyes, *(f"{per[m]['median_ms']:.3f}" for m in METHODS),
                         *(f"{per[m]['tests_per_frame'] / 1e3:.1f} k" for m in METHODS),
                         f"{per['adaptive']['nodes_per_frame']:.0f}"])
    md.append(C.table(["wall", "tiles", "eyes", *(f"{m} ms" for m in METHODS),
                       *(f"{m} tests" for m in METHODS), "pairs listed"], rows))
    ratios = {name: w["stereo"]["adaptive"]["median_ms"] / w["mono"]["adaptive"]["median_ms"]
              for name, w in data["walls"].items()}
    md.append("\nStereo against mono, adaptive: "
              + ", ".join(f"{name} {r:.2f}x" for name, r in ratios.items()) + ".\n")
    fig, ax = plt.subplots(figsize=(7, 3.2))
    names = list(data["walls"])
    x = np.arange(len(names))
    for k, eyes in enumerate(("mono", "stereo")):
        for j, method in enumerate(METHODS):
            values = [data["walls"][n][eyes][method]["median_ms"] for n in names]
            ax.bar(x + (k * len(METHODS) + j - 2.5) * 0.13, values, 0.13,
                   label=f"{method}, {eyes}", alpha=1.0 if k == 0 else 0.55,
                   color=f"C{j}")
    ax.set_xticks(x, names, fontsize=8)
    ax.set_ylabel("ms per frame (median)")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    md.append("\n" + ctx.savefig(fig, "walls.png", "culling time by wall and eyes") + "\n")
    md.append("\nA screens wall's splits are planes through the eye and a screen's edge, checked "
              "every frame; where no such plane separates two groups (the floor from the walls "
              "of a CAVE) each child is bounded by its own screen's six planes. Unlike a grid's "
              "splits, which are the tiles' own side planes, a screens split is not linked to "
              "the planes of the tiles below it, so an object that reaches a screen is tested "
              "against all six of them there: adaptive's advantage over `oh` is smaller than on "
              "grids.\n")
    return "\n".join(md)
