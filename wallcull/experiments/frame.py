"""The whole frame as the server makes it: what a tile waits for is not the culling alone but the
culling, the per-tile leaf lists, the fitted frusta (with shadows and mirrors when the scene has
lights and mirrors) and every tile's packet encoded.

Two measurements, on the power plant's orbit (the whole scene in view), timed by
:func:`wallcull.bench.time_method` with ``stages`` (the numbers ``wallcull bench --json``
reports under ``stages``):

* **stages**: median and p99 of each stage on SPEC walls of 4 x 4, 8 x 8 and 64 x 64 tiles, with
  no lights, with a lamp and a floor mirror (``scenes/powerplant-lights.json``) and with three
  lights (one inside the plant, a spot, a far sun) and two mirrors, one bounded
  (``scenes/powerplant-lights3.json``);
* **the fitting effort**: shadow frusta from the symmetric bounding-sphere frustum, the paper's
  greedy quadrilateral, or the refined one (``--shadow-fit``): time per frame against the share
  of the shadow map the receivers fill.
"""

from __future__ import annotations

import json

import numpy as np

from .. import workers
from ..bench import time_method
from ..fit import FitOptions
from ..lowilie import EFFORTS
from . import common as C
from .context import ROOT, Context

SETTINGS = {"none": None, "lamp + mirror": "powerplant-lights.json",
            "3 lights + 2 mirrors": "powerplant-lights3.json"}
WALLS = ((4, 4), (8, 8), (64, 64))
STAGES = ("cull", "leaves", "fit", "encode")


def _settings(name: str) -> dict:
    file = SETTINGS[name]
    return json.loads((ROOT / "scenes" / file).read_text()) if file else {}


def run(ctx: Context) -> tuple[dict, str]:
    runs = [(w, s) for w in WALLS for s in SETTINGS]
    task = ctx.task("frame", len(runs) + 2 * len(EFFORTS))
    pristine = C.Pristine("powerplant")
    stages = {}
    for (cols, rows), name in runs:
        scene = pristine.fresh()
        scene.settings = _settings(name)
        wall = C.spec_wall(cols, rows)
        frames = C.path_frames(scene, wall, "orbit", ctx.size(120 if cols < 64 else 40, 6))
        timed = time_method(scene, wall, frames, "adaptive", "obb", stages=True)
        stages[f"{cols}x{rows} / {name}"] = {k: v for k, v in timed["stages"].items()}
        task.advance()
    efforts = {}
    for name in ("lamp + mirror", "3 lights + 2 mirrors"):
        scene = pristine.fresh()
        scene.settings = _settings(name)
        wall = C.spec_wall(8, 8)
        frames = C.path_frames(scene, wall, "orbit", ctx.size(120, 6))
        for effort in EFFORTS:
            timed = time_method(scene, wall, frames, "adaptive", "obb",
                                fit=FitOptions(shadow_fit=effort))
            efforts.setdefault(name, {})[effort] = {
                "fit_median_ms": timed["fit_median_ms"], "fit_p99_ms": timed["fit_p99_ms"],
                "coverage_mean": timed.get("shadow_coverage_mean")}
            task.advance()
    task.done()
    data = {"scene": "powerplant", "path": "orbit", "threads": workers.count(),
            "stages": stages, "efforts": efforts}
    return data, report(ctx, data)


def report(ctx: Context, data: dict) -> str:
    plt = C.pyplot()
    md = ["## The whole frame\n",
          "What a tile waits for each frame, stage by stage, as the server makes it: the "
          "culling, the per-tile leaf lists, the fitted frusta (shadows and mirrors included "
          "when the scene declares lights and mirrors) and every tile's entry of the node "
          "messages encoded as a delta against the previous frame, in one compiled pass, as "
          "the node streams and NATS send them (`wallcull/encode.py`; the last column is the "
          "per-tile packets of the tile streams instead, not in the total). The power plant's "
          "orbit, "
          f"adaptive, OBBs; the per-tile fits run on {data['threads']} threads "
          "(`WALLCULL_THREADS`). The same numbers as `wallcull bench --json` under `stages`:\n",
          "    wallcull bench powerplant --wall examples/wall-8x8.json --methods adaptive "
          "--fit --settings scenes/powerplant-lights.json --json\n"]
    rows = []
    for key, s in data["stages"].items():
        rows.append([key, *(f"{s[k]['median_ms']:.3f}" for k in STAGES),
                     f"**{s['total']['median_ms']:.3f}** / {s['total']['p99_ms']:.3f}",
                     C.nbytes(s["node_entry_bytes_per_frame"]),
                     f"{s['encode_packets']['median_ms']:.3f}"])
    md.append(C.table(["wall / settings", *(f"{k} ms" for k in STAGES), "total ms median / p99",
                       "node entries per frame", "per-tile packets ms"], rows))
    fig, axes = plt.subplots(1, len(WALLS), figsize=(10, 2.8))
    for ax, (cols, rows) in zip(axes, WALLS):
        keys = [k for k in data["stages"] if k.startswith(f"{cols}x{rows} /")]
        left = np.zeros(len(keys))
        for stage in STAGES:
            values = np.array([data["stages"][k][stage]["median_ms"] for k in keys])
            ax.barh(range(len(keys)), values, left=left, label=stage)
            left += values
        ax.set_yticks(range(len(keys)), [k.split(" / ")[1] for k in keys], fontsize=7)
        ax.invert_yaxis()
        ax.set_title(f"{cols} x {rows}", fontsize=9)
        ax.set_xlabel("ms per frame (median)", fontsize=8)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    md.append("\n" + ctx.savefig(fig, "frame-stages.png", "the stages of a frame") + "\n")

    md.append("\n**The fitting effort** (`--shadow-fit`; 8 x 8 wall): shadow frusta from the "
              "symmetric frustum around the receivers' bounding sphere, from the paper's greedy "
              "quadrilateral, or from the refined one. Coverage is the share of the shadow map "
              "the receivers' projected hull fills (mean over every fitted tile and light); fit "
              "time is the whole fit stage of a frame, mirrors and casters included.\n")
    rows = []
    for name, per in data["efforts"].items():
        for effort, e in per.items():
            coverage = e["coverage_mean"]
            rows.append([name, effort, f"{e['fit_median_ms']:.3f}", f"{e['fit_p99_ms']:.3f}",
                         "-" if coverage is None else f"{coverage:.3f}"])
    md.append(C.table(["settings", "effort", "fit ms median", "fit ms p99", "coverage"], rows))
    fig, ax = plt.subplots(figsize=(6, 3.4))
    for name, per in data["efforts"].items():
        xs = [per[e]["fit_median_ms"] for e in per]
        ys = [per[e]["coverage_mean"] or 0 for e in per]
        ax.plot(xs, ys, "o-", label=name)
        for effort, x, y in zip(per, xs, ys):
            ax.annotate(effort, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel("fit ms per frame (median)")
    ax.set_ylabel("shadow-map coverage")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8)
    fig.tight_layout()
    md.append("\n" + ctx.savefig(fig, "frame-effort.png", "fitting effort") + "\n")
    md.append("\nThe quadrilateral costs little of a frame: most of the fit stage is per tile and "
              "per light but not per quad (the receivers' bounds, the casters culled into each "
              "tile's light frustum, each mirror's reflected cull), so the refined quad's "
              "five-fold coverage over the bounding-sphere frustum comes nearly free.\n")
    return "\n".join(md)
