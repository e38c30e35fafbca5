"""Occlusion culling: how its occluders are chosen, and how many, against what it hides.

The two scenes the occlusion targets name (the power plant and the sports car) flown through on
the 8 x 8 wall (the ``fly`` path, the camera inside), clusters on, adaptive, OBBs; occlusion on
every frame with each way of choosing occluders (:data:`wallcull.occlude.CHOICES`: the most
image per triangle, the most image, or what the frame before showed) and each triangle budget of
:data:`BUDGETS`. Every frame is culled by every setting in turn, so that they share the
machine's load; each keeps its own occluder, so ``visible`` chooses from its own frame before
(on the first frame, which has none, from the frame's lists). Reported: the triangles the 64
tiles draw a frame (and over those drawn without occlusion), the occluders' triangles, and the
occlusion's median time a frame. The trade is the Pareto front of time against triangles
drawn.
"""

from __future__ import annotations

import json

import numpy as np

from ..occlude import CHOICES, OcclusionOptions
from ..pipeline import Session
from ..scene import load
from ..wall import Wall
from . import common as C
from .context import ROOT, Context

BUDGETS = (5_000, 10_000, 20_000, 40_000)
#: Buffer texels across a tile, tried with the default choice and budget.
TEXELS = (16, 24, 32, 48)
DEFAULT = (OcclusionOptions().choice, OcclusionOptions().budget, OcclusionOptions().texels)
SCENES = ("powerplant", "sportsCar.zip")


def run(ctx: Context) -> tuple[dict, str]:
    wall = Wall.from_dict(json.loads((ROOT / "examples" / "wall-8x8.json").read_text()))
    specs = [s for s in ctx.size(SCENES, SCENES[:1])
             if "." not in s or (ctx.scenes_dir / s).is_file()]
    budgets = ctx.size(BUDGETS, (DEFAULT[1],))
    texels = ctx.size(TEXELS, (16, DEFAULT[2]))
    frames = ctx.size(60, 3)
    task = ctx.task("occluders", len(specs) * frames)
    out = {}
    for spec in specs:
        scene = load(spec if "." not in spec else str(ctx.scenes_dir / spec))
        settings = [(choice, budget, DEFAULT[2]) for choice in CHOICES for budget in budgets]
        settings += [(*DEFAULT[:2], t) for t in texels if t != DEFAULT[2]]
        path = C.path_frames(scene, wall, "fly", frames)  # the frames `wallcull overdraw` takes
        Session(scene, wall, occlusion=OcclusionOptions()).frame(path[0])  # compiles
        sessions = {None: Session(scene, wall)}
        for choice, budget, t in settings:
            sessions[choice, budget, t] = Session(
                scene, wall, occlusion=OcclusionOptions(budget=budget, choice=choice, texels=t))
        drawn = {key: [] for key in sessions}
        times = {key: [] for key in settings}
        occluders = {key: [] for key in settings}
        for frame in path:
            for key, s in sessions.items():
                result = s.frame(frame)
                drawn[key].append(int(result.visibility.triangles().sum()))
                if key is not None:
                    times[key].append(result.timings["occlude_ms"])
                    occluders[key].append(result.visibility.stats["occluder_triangles"])
            task.advance()
        plain = float(np.mean(drawn[None]))
        out[scene.name] = {"without": plain, "settings": [
            {"choice": key[0], "budget": key[1], "texels": key[2],
             "triangles": float(np.mean(drawn[key])),
             "ratio": float(np.mean(drawn[key])) / max(plain, 1.0),
             "occluder_triangles": float(np.median(occluders[key])),
             "occlude_ms_median": float(np.median(times[key]))} for key in settings]}
    task.done()
    data = {"wall": "examples/wall-8x8.json", "path": "fly", "frames": frames,
            "budgets": list(budgets), "choices": list(CHOICES), "texels": list(texels),
            "default": list(DEFAULT),
            "scenes": out}
    return data, report_md(ctx, data)


def report_md(ctx: Context, data: dict) -> str:
    choice0, budget0, texels0 = data["default"]
    md = ["## Choosing occluders\n",
          "Occlusion culling on the 8 x 8 wall, the camera flying through each scene "
          f"({data['frames']} frames, clusters on): triangles drawn a frame over those drawn "
          "without occlusion, and the occlusion's median ms a frame, for each way of choosing "
          "occluders and each budget of occluder triangles a frame. `image`: the units that "
          "cover the most image per triangle (the default); `area`: the most image, the largest "
          "nearby first; `visible`: as `image`, among what the frame before showed (temporal "
          f"coherence). Buffers of {texels0} texels across a tile, but in the last table. "
          "Every frame is culled by every setting in turn.\n"]
    header = ["scene", "choice", *(f"{b:,}: drawn / without" for b in data["budgets"]),
              *(f"{b:,}: ms" for b in data["budgets"])]
    rows = []
    for name, s in data["scenes"].items():
        for choice in data["choices"]:
            by = {e["budget"]: e for e in s["settings"]
                  if e["choice"] == choice and e["texels"] == texels0}
            rows.append([name, choice, *(f"{by[b]['ratio']:.3f}" for b in data["budgets"]),
                         *(f"{by[b]['occlude_ms_median']:.2f}" for b in data["budgets"])])
    md.append(C.table(header, rows))
    md.append(f"\nThe buffer's texels across a tile, with `{choice0}` and {budget0:,} triangles:"
              "\n")
    rows = []
    for name, s in data["scenes"].items():
        by = {e["texels"]: e for e in _by_texels(s, data)}
        rows.append([name, *(f"{by[t]['ratio']:.3f}, {by[t]['occlude_ms_median']:.2f} ms"
                             for t in data["texels"])])
    md.append(C.table(["scene", *(f"{t} texels" for t in data["texels"])], rows))
    plt = C.pyplot()
    fig, axes = plt.subplots(1, len(data["scenes"]), figsize=(5 * len(data["scenes"]), 4),
                             squeeze=False)
    for ax, (name, s) in zip(axes[0], data["scenes"].items()):
        for j, choice in enumerate(data["choices"]):
            by = [e for e in s["settings"] if e["choice"] == choice and e["texels"] == texels0]
            ax.plot([e["occlude_ms_median"] for e in by], [e["ratio"] for e in by], "-o",
                    color=f"C{j}", label=choice, ms=4)
            for e in by:
                ax.annotate(f"{e['budget'] // 1000}k", (e["occlude_ms_median"], e["ratio"]),
                            fontsize=7, xytext=(3, 3), textcoords="offset points")
        by = _by_texels(s, data)
        ax.plot([e["occlude_ms_median"] for e in by], [e["ratio"] for e in by], ":s",
                color="black", label=f"{choice0}, {budget0 // 1000}k, by texels", ms=3)
        for e in by:
            ax.annotate(f"{e['texels']} tx", (e["occlude_ms_median"], e["ratio"]), fontsize=7,
                        xytext=(3, -9), textcoords="offset points")
        ax.axhline(0.5, color="grey", lw=0.8, ls="--")  # the target: at most half
        ax.set_xlabel("occlusion ms per frame, median")
        ax.set_ylabel("triangles drawn / without occlusion")
        ax.set_title(f"{name}, fly path, 8 x 8")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    md.append("\n" + ctx.savefig(fig, "occluders.png",
                                 "occlusion time against triangles drawn, by occluder choice, "
                                 "budget and texels") + "\n")
    return "\n".join(md)


def _by_texels(s: dict, data: dict) -> list[dict]:
    """The default choice and budget's settings, by the buffer's texels."""
    choice0, budget0, _ = data["default"]
    return sorted((e for e in s["settings"] if e["choice"] == choice0
                   and e["budget"] == budget0), key=lambda e: e["texels"])
