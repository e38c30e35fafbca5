"""Fig. 6 of the paper: dynamic scenes. A share of the power plant's leaves moves every frame
(:class:`wallcull.bench.Motion`); the moved nodes and their ancestors are refit with eigenvector
OBBs or with AABBs (``SceneState.move_nodes(..., refit)``) before the frame is culled."""

from __future__ import annotations

import numpy as np

from ..bench import Motion
from ..pipeline import Session
from . import common as C

SCENE = "powerplant"
METHOD = "adaptive"
FRACTIONS = (0.0, 0.01, 0.05, 0.10, 0.25, 0.50, 1.0)
QUICK_FRACTIONS = (0.0, 0.10, 1.0)
REFITS = ("obb", "aabb")
#: Share of the leaves moving in the drift measurement.
DRIFT_FRACTION = 0.25


def run(ctx: C.Context) -> tuple[dict, str]:
    frames_n = ctx.size(240, 6)
    oracle_n = ctx.size(8, 1)
    drift_n = ctx.size(240, 6)
    fractions = ctx.size(FRACTIONS, QUICK_FRACTIONS)
    wall = C.spec_wall(4, 4)
    scene = C.Pristine(SCENE).fresh()
    scene.bounds("obb")
    frames = C.path_frames(scene, wall, "orbit", frames_n)
    checked = C.spaced(oracle_n, frames_n, ctx.seed)
    oracle = C.Oracle(scene, wall)
    task = ctx.task("fig6", len(fractions) * len(REFITS) * (frames_n + len(checked))
                    + 2 * drift_n)
    rows = []
    for fraction in fractions:
        motion = Motion(scene, fraction, seed=ctx.seed)
        refits = REFITS if fraction else REFITS[:1]  # nothing moves: one run
        series = C.walk_all([C.Run(scene, wall, frames, METHOD, motion=motion, refit=refit)
                             for refit in refits], task)
        if not fraction:
            task.advance(frames_n + len(checked))
        for refit, s in zip(refits, series):
            summary = C.walk_summary(s)
            # accuracy: the same poses, one frame at a time, against the exact oracle
            parts = []
            for k in checked:
                session = Session(scene, wall, METHOD, "obb")  # the pose of frame k, from rest
                if len(motion.nodes):
                    session.state.move_nodes(motion.nodes, motion.at(k), refit)
                reported = C.leaf_pairs(session, frames[k])
                parts.append(oracle.false_pairs((fraction, k), frames[k], reported,
                                                session.state.world))
                task.advance()
            rows.append({"fraction": fraction, "moving": len(motion.nodes), "refit": refit,
                         **summary, "update_plus_cull_ms": float(np.median(
                             s["cull_ms"] + s.get("refit_ms", 0.0))),
                         "accuracy": C.accuracy_sum(parts, len(checked))})
    drift = measure_drift(scene, wall, frames, DRIFT_FRACTION, drift_n, ctx.seed, oracle, task)
    task.done()
    data = {"scene": C.scene_stats(scene), "wall": wall.to_dict(), "method": METHOD,
            "frames": frames_n, "oracle_frames": checked, "rows": rows, "drift": drift}
    return data, report(ctx, data)


def measure_drift(scene, wall, frames, fraction, n, seed, oracle, task) -> dict:
    """The product's own frame-after-frame updates, without going back to the rest pose: each
    ``move_nodes`` starts from the bounds the previous one left. How much bigger the moved
    leaves' boxes are after ``n`` frames than the same pose reached from rest, and the false
    positives of the last frame."""
    motion = Motion(scene, fraction, seed=seed)
    last = n - 1
    frame = frames[last % len(frames)]
    out = {"fraction": fraction, "frames": n}
    for refit in REFITS:
        chained = Session(scene, wall, METHOD, "obb")
        for k in range(n):
            chained.state.move_nodes(motion.nodes, motion.at(k), refit)
            task.advance()
        direct = Session(scene, wall, METHOD, "obb")
        direct.state.move_nodes(motion.nodes, motion.at(last), refit)
        vol = [np.prod(2 * s.state.bounds.half[motion.nodes]
                       + 2 * s.state.bounds.radius[motion.nodes, None], axis=1)
               for s in (chained, direct)]
        acc = {}
        for label, s in (("chained", chained), ("from_rest", direct)):
            part = oracle.false_pairs(("drift", last), frame, C.leaf_pairs(s, frame),
                                      s.state.world)
            acc[label] = C.accuracy_sum([part], 1)
        out[refit] = {"volume_ratio_mean": float(np.mean(vol[0] / np.maximum(vol[1], 1e-300))),
                      "volume_ratio_max": float(np.max(vol[0] / np.maximum(vol[1], 1e-300))),
                      "accuracy": acc}
    return out


def report(ctx: C.Context, data: dict) -> str:
    plt = C.pyplot()
    rows = data["rows"]
    s = data["scene"]
    md = ["## Fig. 6: dynamic scenes\n",
          f"The power-plant look-alike ({s['leaves']} leaves) on the 4 x 4 SPEC wall, "
          f"{data['frames']} frames of the `orbit` path, method `{data['method']}`, eigenvector "
          "OBBs at rest. Before each frame a fixed, seeded share of the leaves takes a new pose "
          "(`wallcull.bench.Motion`: each part turns by up to ~11 degrees about its own axis and "
          "shifts by up to 2% of the scene), and `SceneState.move_nodes` updates the bounds: the "
          "moved leaves' boxes follow rigidly, then their ancestors are refit, with eigenvector "
          "OBBs of the children's corners (Alg. 1, `refit obb`) or with axis-aligned boxes for "
          "the moved leaves and all their ancestors (`refit aabb`). *update* is that call's time; "
          "*cull* is the culling step as elsewhere. False positives are counted against the "
          f"exact oracle on {len(data['oracle_frames'])} of the frames (frames "
          f"{', '.join(map(str, data['oracle_frames']))}), in the moved pose.\n",
          "Updates chain frame after frame, as in the product; the last table checks that "
          "they do not drift from the same pose reached from rest.\n"]
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    labels = [f"{100 * f:g}%" for f in sorted({r["fraction"] for r in rows})]
    x = {f: i for i, f in enumerate(sorted({r["fraction"] for r in rows}))}
    for refit, color in zip(REFITS, ("tab:green", "tab:red")):
        mine = [r for r in rows if r["refit"] == refit or r["fraction"] == 0]
        xs = [x[r["fraction"]] for r in mine]
        axes[0].plot(xs, [update_ms(r) for r in mine], marker="o", color=color,
                     label=f"refit {refit}")
        axes[1].plot(xs, [r["median_ms"] for r in mine], marker="o", color=color,
                     label=f"refit {refit}")
        axes[2].plot(xs, [100 * r["accuracy"]["rate"] for r in mine], marker="o", color=color,
                     label=f"refit {refit}")
    for ax, title in zip(axes, ("update (move + refit), median ms", "culling, median ms",
                                "false positives, % of reported pairs")):
        ax.set_xticks(range(len(labels)), labels)
        ax.set_xlabel("leaves moving each frame")
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    md.append(ctx.savefig(fig, "fig6.png", "Fig. 6: update time, culling time and false "
                                            "positives against the share of moving leaves")
              + "\n")
    table_rows = []
    for r in rows:
        table_rows.append([f"{100 * r['fraction']:g}%", r["moving"],
                           r["refit"] if r["fraction"] else "-", C.ms(update_ms(r)), C.ms(r["median_ms"]), C.ms(r["p99_ms"]),
                           C.ms(r["update_plus_cull_ms"]), f"{r['tests_per_frame']:,.0f}",
                           f"{C.pct(r['accuracy']['rate'])} ({r['accuracy']['false_positives']} "
                           f"of {r['accuracy']['reported']})"])
    md.append(C.table(["moving", "leaves", "refit", "update ms", "cull ms", "cull p99 ms",
                       "update + cull ms", "tests/frame", "false positives"], table_rows) + "\n")
    md.append(trade_text(rows))
    d = data["drift"]
    md.append(f"**Drift of frame-after-frame updates** ({100 * d['fraction']:g}% moving, "
              f"{d['frames']} frames, each `move_nodes` starting from the bounds the previous one "
              "left, as a server does): the moved leaves' box volume against the same pose "
              "reached from rest, and the false positives of the last frame.\n")
    md.append(C.table(["refit", "volume ratio, mean", "volume ratio, max",
                       "false positives, chained", "false positives, from rest"],
                      [[refit, f"{d[refit]['volume_ratio_mean']:.3g}",
                        f"{d[refit]['volume_ratio_max']:.3g}",
                        C.pct(d[refit]["accuracy"]["chained"]["rate"]),
                        C.pct(d[refit]["accuracy"]["from_rest"]["rate"])] for refit in REFITS])
              + "\n")
    ratio = d["aabb"]["volume_ratio_mean"]
    if ratio > 1.5:
        md.append(f"With `refit aabb` the boxes grow without bound ({ratio:.3g}x the volume "
                  f"after {d['frames']} frames): `move_nodes` moves the previous frame's "
                  "axis-aligned box rigidly and takes the axis-aligned box of that, so every turn "
                  "inflates it. Eigenvector OBBs move exactly and do not drift.\n")
    else:
        md.append("Neither refit drifts: chained updates give the boxes of the same pose "
                  "reached from rest.\n")
    md.append(against_paper(rows))
    return "\n".join(md)


def update_ms(row: dict) -> float:
    return row["update"]["median_ms"] if "update" in row else 0.0


def trade_text(rows: list[dict]) -> str:
    by = {(r["fraction"], r["refit"]): r for r in rows}
    fracs = sorted({r["fraction"] for r in rows if r["fraction"] > 0})
    if not fracs:
        return ""
    f = 0.25 if 0.25 in fracs else fracs[-1]
    o, a = by[(f, "obb")], by[(f, "aabb")]
    return (f"At {100 * f:g}% moving, the update takes {C.ms(update_ms(o))} ms with "
            f"OBBs against {C.ms(update_ms(a))} ms with AABBs; culling "
            f"{C.ms(o['median_ms'])} against {C.ms(a['median_ms'])} ms; false positives "
            f"{C.pct(o['accuracy']['rate'])} against {C.pct(a['accuracy']['rate'])}.\n")


def against_paper(rows: list[dict]) -> str:
    moving = [r for r in rows if r["fraction"] > 0]
    if not moving:
        return ""
    by = {(r["fraction"], r["refit"]): r for r in rows}
    fracs = sorted({r["fraction"] for r in moving})
    lo, hi = fracs[0], fracs[-1]
    faster = all(update_ms(by[(f, "aabb")]) < update_ms(by[(f, "obb")]) for f in fracs)
    tighter = all(by[(f, "aabb")]["accuracy"]["rate"] >= by[(f, "obb")]["accuracy"]["rate"]
                  for f in fracs)
    rest = by.get((0.0, "obb"))
    out = ["*Against the paper.* The paper's Fig. 6 has culling with the update growing with the "
           "share of moving objects, AABBs faster and OBBs tighter."]
    out.append(("Both hold here at every share measured" if faster and tighter else
                "Here AABB updates are " + ("always" if faster else "not always") + " faster and "
                "OBBs " + ("always" if tighter else "not always") + " tighter")
               + f": from {100 * lo:g}% to {100 * hi:g}% moving, the OBB update takes "
               f"{C.ms(update_ms(by[(lo, 'obb')]))} to {C.ms(update_ms(by[(hi, 'obb')]))} ms "
               f"and the AABB one {C.ms(update_ms(by[(lo, 'aabb')]))} to "
               f"{C.ms(update_ms(by[(hi, 'aabb')]))} ms, while false positives go from "
               f"{C.pct(by[(lo, 'obb')]['accuracy']['rate'])} to "
               f"{C.pct(by[(hi, 'obb')]['accuracy']['rate'])} with OBBs and from "
               f"{C.pct(by[(lo, 'aabb')]['accuracy']['rate'])} to "
               f"{C.pct(by[(hi, 'aabb')]['accuracy']['rate'])} with AABBs.")
    if rest:
        a, b = by[(lo, "obb")], by[(hi, "obb")]
        out.append(
            f"Culling goes from {C.ms(rest['median_ms'])} ms at rest to {C.ms(b['median_ms'])} "
            f"ms with {100 * hi:g}% moving (OBB refit), with "
            f"{b['tests_per_frame'] / rest['tests_per_frame'] - 1:.0%} more box-plane tests: "
            "refit ancestors are looser than the preprocessed ones. Part of the rise is not "
            f"tests: at {100 * lo:g}% moving the tests barely change "
            f"({a['tests_per_frame']:,.0f} against "
            f"{rest['tests_per_frame']:,.0f}) yet culling takes {C.ms(a['median_ms'])} ms: "
            "the update has just swept the cache with its own temporaries, and the cull "
            "starts cold.")
    out.append(f"The update dominates from the smallest share: {C.ms(update_ms(by[(lo, 'obb')]))}"
               f" ms for {by[(lo, 'obb')]['moving']} moving leaves. A rigid motion moves an "
               "eigenvector OBB exactly, so no leaf is refit from its points (the paper "
               "recomputed eigenvectors); the cost is the ancestors' refit (Alg. 1 from the "
               "children's corners), done level by level in numpy, where per-call overhead "
               "dominates when few nodes move. The culling is compiled; the update is not.")
    return " ".join(out) + "\n"
