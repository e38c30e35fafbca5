"""Fig. 4 of the paper: culling time per frame of the four traversals over a long walkthrough
with the whole scene in view, on the Fatehpur Sikri and power-plant look-alikes, 4 x 4 wall."""

from __future__ import annotations

import numpy as np

from ..cull import METHODS
from . import common as C

SCENES = ("fatehpur", "powerplant")


def run(ctx: C.Context) -> tuple[dict, str]:
    frames_n = ctx.size(4000, 12)
    fly_n = ctx.size(1000, 6)
    wall = C.spec_wall(4, 4)
    data: dict = {"wall": wall.to_dict(), "path": "orbit", "frames": frames_n,
                  "fly_frames": fly_n, "scenes": {}}
    task = ctx.task("fig4", len(SCENES) * len(METHODS) * (frames_n + fly_n))
    for name in SCENES:
        scene = C.Pristine(name).fresh()
        scene.bounds("obb")
        orbit = C.path_frames(scene, wall, "orbit", frames_n)
        fly = C.path_frames(scene, wall, "fly", fly_n)
        entry: dict = {"scene": C.scene_stats(scene), "methods": {}, "series": {},
                       "fly": {}}
        runs = C.walk_all([C.Run(scene, wall, orbit, m) for m in METHODS], task)
        fly_runs = C.walk_all([C.Run(scene, wall, fly, m) for m in METHODS], task)
        for method, s, f in zip(METHODS, runs, fly_runs):
            entry["methods"][method] = C.walk_summary(s)
            entry["series"][method] = {"cull_ms": C.rounded(s["cull_ms"]),
                                       "tests": s["tests"].tolist()}
            entry["fly"][method] = C.walk_summary(f)
        times = np.array([entry["series"][m]["cull_ms"] for m in METHODS])
        fastest = np.argmin(times, axis=0)
        entry["fastest_share"] = {m: float(np.mean(fastest == i)) for i, m in enumerate(METHODS)}
        data["scenes"][name] = entry
    task.done()
    return data, report(ctx, data)


def report(ctx: C.Context, data: dict) -> str:
    plt = C.pyplot()
    md = ["## Fig. 4: the four traversals over a walkthrough\n",
          f"{data['frames']} frames of the `orbit` path (the whole scene in view and filling the "
          f"wall: the paper's worst case) on the 4 x 4 wall of SPEC section 2, eigenvector OBBs. "
          f"Every method culls every frame. Time is the culling step alone "
          f"(`Session.frame(...).timings[\"cull_ms\"]`: the frame's planes, the first-level cull "
          f"and the traversal), after {C.WARMUP_FRAMES} warm-up frames.\n"]
    for key, ylabel, fname, caption in (
            ("cull_ms", "culling time per frame (ms)", "fig4.png",
             "Fig. 4: culling time per frame"),
            ("tests", "box-plane tests per frame", "fig4-tests.png",
             "Fig. 4, box-plane tests per frame")):
        fig, axes = plt.subplots(1, len(data["scenes"]), figsize=(12, 4.2), squeeze=False)
        for ax, (label, (name, entry)) in zip(axes[0], zip("ab", data["scenes"].items())):
            for method in METHODS:
                color, _ = C.METHOD_STYLE[method]
                y = entry["series"][method][key]
                ax.plot(np.arange(len(y)), y, lw=0.6, color=color, label=C.METHOD_LABEL[method])
            ax.set_yscale("log")
            ax.set_xlabel("frame")
            ax.set_ylabel(ylabel)
            s = entry["scene"]
            ax.set_title(f"({label}) {name}: {s['nodes']} nodes, {s['leaves']} leaves")
            ax.grid(True, which="both", alpha=0.3)
        axes[0][0].legend(loc="best", fontsize=8)
        fig.tight_layout()
        md.append(ctx.savefig(fig, fname, caption) + "\n")
    for name, entry in data["scenes"].items():
        s = entry["scene"]
        md.append(f"**{name}** ({s['nodes']} nodes: {s['internal']} internal, {s['leaves']} "
                  f"leaves, branching {s['branching']:.2f}, {s['triangles']:,} triangles)\n")
        rows = []
        for m in METHODS:
            r, f = entry["methods"][m], entry["fly"][m]
            rows.append([m, C.ms(r["median_ms"]), C.ms(r["p99_ms"]), C.ms(r["mean_ms"]),
                         f"{r['tests_per_frame']:,.0f}", f"{r['nodes_per_frame']:,.0f}",
                         C.pct(entry["fastest_share"][m]), C.ms(f["median_ms"]),
                         f"{f['tests_per_frame']:,.0f}"])
        md.append(C.table(["method", "median ms", "p99 ms", "mean ms", "tests/frame",
                           "nodes listed/frame", "fastest in", "fly: median ms",
                           "fly: tests/frame"], rows) + "\n")
        a, o, f = (entry["methods"][m]["median_ms"] for m in ("adaptive", "oh", "fh"))
        md.append(f"Adaptive median {C.ms(a)} ms: {o / a:.2f}x faster than `oh`, {f / a:.2f}x "
                  f"than `fh`; the fastest of the four in "
                  f"{C.pct(entry['fastest_share']['adaptive'])} of the frames. The `fly` columns "
                  f"are {data['fly_frames']} frames of a flight through the scene (most of it "
                  f"culled by the first level): the typical case, not the worst.\n")
    md.append(against_paper(data))
    return "\n".join(md)


def against_paper(data: dict) -> str:
    scenes = data["scenes"]
    med = {n: {m: e["methods"][m]["median_ms"] for m in METHODS} for n, e in scenes.items()}
    share = {n: e["fastest_share"] for n, e in scenes.items()}
    parts = ["*Against the paper.* The paper's Fig. 4 has adaptive the fastest almost "
             "throughout, then `fh`, then `oh` on Fatehpur; on the power plant `oh` and `fh` "
             "coincide and adaptive takes about 5 ms against 14 ms for `oh`, 2.8x."]
    for name in scenes:
        r = med[name]["oh"] / med[name]["adaptive"]
        lead = ("level with `oh`" if 0.9 <= r <= 1.1 else
                f"{r:.1f}x faster than `oh`" if r > 1 else f"{1 / r:.1f}x slower than `oh`")
        parts.append(
            f"On {name} adaptive is {lead} (medians {C.ms(med[name]['adaptive'])} and "
            f"{C.ms(med[name]['oh'])} ms) and the fastest of the four in "
            f"{C.pct(share[name]['adaptive'])} of the frames, `oh` in "
            f"{C.pct(share[name]['oh'])}; `fh` takes {med[name]['fh'] / med[name]['adaptive']:.1f}x "
            f"adaptive's time and `naive` {med[name]['naive'] / med[name]['adaptive']:.1f}x.")
    worst = max(m["oh"] / m["adaptive"] for m in med.values())
    order = all(m["fh"] > m["adaptive"] and m["naive"] == max(m.values()) for m in med.values())
    parts.append(
        ("As in the paper, adaptive stays ahead of `fh` and `naive` is last" if order else
         "The paper's order of adaptive, `fh` and `naive` does not hold on every scene here")
        + "; what differs is `oh`, which on 16 tiles "
        + ("keeps up with adaptive" if worst < 1.25 else
           f"trails adaptive by at most {worst:.1f}x, not 2.8x")
        + ". Our `oh` is the "
        "strong form of the common approach: it "
        "starts from the first-level cull's roots and masks planes (Assarsson and Moller), so "
        "each tile costs about the nodes near it. The box-plane tests per frame say the same: "
        + "; ".join(f"{n}: `oh` {e['methods']['oh']['tests_per_frame']:,.0f}, adaptive "
                    f"{e['methods']['adaptive']['tests_per_frame']:,.0f}"
                    for n, e in scenes.items())
        + ". How the lead changes as the wall grows is Fig. 5's question.")
    if "powerplant" in med:
        parts.append(f"Absolute times are about {5 / med['powerplant']['adaptive']:.0f}x below "
                     f"the paper's (adaptive on the power plant: "
                     f"{C.ms(med['powerplant']['adaptive'])} ms against about 5 ms): compiled "
                     "kernels over flat arrays on a current core, against a 2006 scene-graph "
                     "traversal, on look-alike scenes.")
    return " ".join(parts) + "\n"
