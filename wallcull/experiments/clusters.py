"""Clusters below the leaf: what a tile draws against what its frustum holds, and what the
cluster size costs.

Every scene (the two bundled look-alikes and the third-party scenes of ``scenes/``) on the
8 x 8 wall, the ``orbit`` path (the whole scene in view) and the ``fly`` path (the camera inside
it), adaptive, OBBs, each cluster size of :data:`SIZES` and clusters off, each with occlusion
culling off and on, measured by :func:`wallcull.overdraw.measure`, the numbers ``wallcull
overdraw --occlusion`` prints: triangles drawn per frame summed over the tiles, over the exact
floor (the triangles not wholly outside a tile's frustum); draw calls; the median cull (and
occlusion) time. The speed-accuracy trade of the cluster size and of occlusion is the Pareto
front of time against triangles drawn.
"""

from __future__ import annotations

import json

import numpy as np

from .. import overdraw
from ..clusters import AUTO_SIZE
from ..scene import load_sizes
from ..wall import Wall
from . import common as C
from .context import ROOT, Context

SIZES = (32, 64, 128, 256, 512, 1024, 4096)
PATHS = ("orbit", "fly")
FILES = ("FM1_satellite.3DXML", "sportsCar.zip", "CesiumMilkTruck.glb")
BIG = 50_000  # scenes of more triangles than this hold the targets


def _wall() -> Wall:
    return Wall.from_dict(json.loads((ROOT / "examples" / "wall-8x8.json").read_text()))


def run(ctx: Context) -> tuple[dict, str]:
    specs = ["powerplant", "fatehpur",
             *(str(ctx.scenes_dir / f) for f in FILES if (ctx.scenes_dir / f).is_file())]
    sizes = ctx.size(SIZES, (AUTO_SIZE, 256))
    frames = ctx.size(60, 3)
    wall = _wall()
    task = ctx.task("clusters", len(specs) * len(PATHS) * frames)
    out = {}
    for spec in specs:
        scenes = load_sizes(spec, (None, *sizes))  # the file read once
        name = scenes[None].name
        out[name] = {}
        for path in PATHS:
            frame_list = C.path_frames(scenes[None], wall, path, frames)
            report = overdraw.measure(scenes, wall, frame_list, progress=task.advance,
                                      occlusion=True)
            out[name][path] = report.summary()
    task.done()
    data = {"wall": "examples/wall-8x8.json", "method": "adaptive", "bounds": "obb",
            "frames": frames, "sizes": list(sizes), "default": AUTO_SIZE, "scenes": out}
    return data, report_md(ctx, data)


def _by_size(summary: dict, occlusion: bool = False) -> dict:
    return {e["clusters"]: e for e in summary["settings"] if e["occlusion"] == occlusion}


def report_md(ctx: Context, data: dict) -> str:
    plt = C.pyplot()
    md = ["## Clusters below the leaf\n",
          "What the tiles draw, per frame summed over the 64 tiles of the 8 x 8 wall, over the "
          "exact floor (the triangles not wholly outside a tile's frustum), with each leaf's "
          "mesh cut into clusters of at most K triangles (`--clusters K`) or drawn whole "
          f"(`off`); adaptive, OBBs, {data['frames']} frames of each path. Draw calls: one per "
          "whole leaf, one per range of a leaf shown in part. The same numbers as\n",
          "    wallcull overdraw scenes/sportsCar.zip --wall examples/wall-8x8.json --path fly "
          "--sizes 64,256\n"]
    sizes = ["off", *data["sizes"]]
    for path in PATHS:
        md.append(f"\n**{path}** ({'the whole scene in view' if path == 'orbit' else 'the camera inside'}): "
                  "triangles drawn over the floor, draw calls and median cull ms per cluster size\n")
        rows = []
        for name, paths in data["scenes"].items():
            s = paths[path]
            by = _by_size(s)
            rows.append([name, f"{s['triangles']:,}", f"{s['floor']:,.0f}",
                         f"{s['none_over_floor']:.0f}",
                         *(f"{by[k]['over_floor']:.2f}" for k in sizes)])
            rows.append(["", "", "", "draw calls", *(f"{by[k]['draw_calls']:,.0f}" for k in sizes)])
            rows.append(["", "", "", "cull ms", *(f"{by[k]['cull_ms_median']:.3f}" for k in sizes)])
            occ = _by_size(s, True)
            rows.append(["", "", "", "with occlusion", *(f"{occ[k]['over_floor']:.2f}"
                                                          for k in sizes)])
            rows.append(["", "", "", "occlusion ms", *(f"{occ[k]['occlude_ms_median']:.3f}"
                                                        for k in sizes)])
        md.append(C.table(["scene", "triangles", "floor", "none / floor",
                           *(f"{k}" for k in sizes)], rows))
    fig, axes = plt.subplots(1, len(PATHS), figsize=(10, 4))
    for ax, path in zip(axes, PATHS):
        for j, (name, paths) in enumerate(data["scenes"].items()):
            by = _by_size(paths[path])
            xs = [by[k]["cull_ms_median"] for k in sizes]
            ys = [by[k]["over_floor"] for k in sizes]
            ax.plot(xs, ys, "-o", color=f"C{j}", label=name, ms=4)
            occ = _by_size(paths[path], True)
            ax.plot([occ[k]["cull_ms_median"] + occ[k]["occlude_ms_median"] for k in sizes],
                    [occ[k]["over_floor"] for k in sizes], ":^", color=f"C{j}", ms=4)
            for k, x, y in zip(sizes, xs, ys):
                if k in ("off", data["default"]) or k == sizes[1]:
                    ax.annotate(str(k), (x, y), fontsize=7, xytext=(3, 3),
                                textcoords="offset points")
        ax.set_yscale("log")
        ax.set_xlabel("cull (+ occlusion, dotted) ms per frame, median")
        ax.set_ylabel("triangles drawn / floor")
        ax.set_title(f"{path} path, 8 x 8")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    md.append("\n" + ctx.savefig(fig, "clusters.png",
                                 "cull time against triangles drawn, by cluster size") + "\n")
    md.append(_targets(data))
    md.append(_occlusion_targets(data))
    return "\n".join(md)


def _occlusion_targets(data: dict) -> str:
    """Occlusion on the fly path at the default: triangles drawn with it over without."""
    k = data["default"]
    rows = []
    for name, paths in data["scenes"].items():
        plain, occ = _by_size(paths["fly"]).get(k), _by_size(paths["fly"], True).get(k)
        if plain is None or occ is None:
            continue
        rows.append([name, f"{occ['triangles'] / max(plain['triangles'], 1):.2f}",
                     f"{occ['occlude_ms_median']:.2f}", f"{occ['over_floor']:.2f}"])
    return ("\nOcclusion culling on the fly path, at the default cluster size: triangles drawn "
            "with it over without (the target is <= 0.5 on powerplant and sportsCar), its time "
            "per frame, and what is drawn over the frustum floor:\n\n"
            + C.table(["scene", "with / without", "occlusion ms", "x floor"], rows) + "\n")


def _targets(data: dict) -> str:
    """The default's numbers on the big scenes, against drawn/floor <= 1.5 in view, <= 4 inside."""
    k = data["default"]
    rows = []
    for name, paths in data["scenes"].items():
        if paths["orbit"]["triangles"] <= BIG:
            continue
        orbit, fly = (_by_size(paths[p]).get(k) for p in PATHS)
        if orbit is None:
            continue
        rows.append([name, f"{orbit['over_floor']:.2f}", "yes" if orbit["over_floor"] <= 1.5
                     else "no", f"{fly['over_floor']:.2f}",
                     "yes" if fly["over_floor"] <= 4 else "no"])
    return (f"\nAt the default cluster size ({k}), scenes of more than {BIG:,} triangles, "
            "against drawn/floor <= 1.5 with the scene in view and <= 4 from inside:\n\n"
            + C.table(["scene", "orbit", "<= 1.5", "fly", "<= 4"], rows) + "\n")
