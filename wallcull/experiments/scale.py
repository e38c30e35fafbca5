"""Cost against scene size: preparing, loading and culling powerplant, ``powerplant*10``,
``*40`` and ``*200`` (about 5k, 50k, 200k and 1M nodes).

Each step runs in a fresh process, as a user runs it, so that its time and its peak memory are
its own: ``prepare`` (``wallcull prepare``, from nothing, into an empty cache), then a prepared
load (``wallcull.scene.load`` mapping that file) followed by the culling time per frame of
``adaptive`` over the orbit path on the 8 x 8 and 64 x 64 walls of ``examples/`` (the walls of
``wallcull bench``), timed by :func:`wallcull.bench.time_method`.

    python -m wallcull.experiments.scale prepare SCENE            # one step, JSON on stdout
    python -m wallcull.experiments.scale load SCENE FRAMES
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

from . import common as C
from .context import ROOT

SCENES = ("powerplant", "powerplant*10", "powerplant*40", "powerplant*200")
QUICK_SCENES = ("powerplant", "powerplant*2")
WALLS = ("wall-8x8.json", "wall-64x64.json")


def run(ctx: C.Context) -> tuple[dict, str]:
    scenes = ctx.size(SCENES, QUICK_SCENES)
    frames_n = ctx.size(100, 3)
    task = ctx.task("scale", 2 * len(scenes))
    cache = tempfile.mkdtemp(prefix="wallcull-scale-")
    rows = []
    try:
        for spec in scenes:
            row = {"scene": spec, **_child(cache, "prepare", spec)}
            task.advance()
            row.update(_child(cache, "load", spec, str(frames_n)))
            task.advance()
            rows.append(row)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    task.done()
    data = {"frames": frames_n, "path": "orbit", "method": "adaptive", "bounds": "obb",
            "walls": list(WALLS), "scenes": rows}
    return data, report(ctx, data)


def _child(cache: str, *args: str) -> dict:
    """One step in a fresh interpreter (its own peak memory); its JSON line."""
    env = {**os.environ, "WALLCULL_CACHE": cache}
    done = subprocess.run([sys.executable, "-m", __name__, *args], env=env, capture_output=True,
                          text=True, check=False)
    if done.returncode:
        raise RuntimeError(f"scale {' '.join(args)} failed: {done.stderr.strip()[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def measure_prepare(spec: str) -> dict:
    from ..bench import peak_rss_mb
    from ..scene import prepare

    t0 = time.perf_counter()
    path, scene = prepare(spec, force=True)
    seconds = time.perf_counter() - t0
    return {"nodes": scene.stats["nodes"], "leaves": scene.stats["leaves"],
            "triangles": scene.stats["triangles"], "prepare_s": seconds,
            "prepare_peak_mb": peak_rss_mb(), "file_mb": path.stat().st_size / 1e6}


def measure_load(spec: str, frames: int) -> dict:
    import psutil

    from ..bench import peak_rss_mb, time_method
    from ..paths import scene_path
    from ..scene import load
    from ..wall import Wall

    process = psutil.Process()
    t0 = time.perf_counter()
    scene = load(spec)
    seconds = time.perf_counter() - t0
    if scene.prepared is None:
        raise RuntimeError(f"{spec} did not load from its prepared file")
    out = {"load_s": seconds, "load_rss_mb": process.memory_info().rss / 1e6,
           "load_peak_mb": peak_rss_mb(), "cull": {}}
    for name in WALLS:
        wall = Wall.from_dict(json.loads((ROOT / "examples" / name).read_text()))
        path = scene_path(scene, wall, "orbit", frames)
        out["cull"][name] = time_method(scene, wall, path, "adaptive", "obb")
    out["rss_after_culling_mb"] = process.memory_info().rss / 1e6
    return out


def report(ctx: C.Context, data: dict) -> str:
    plt = C.pyplot()
    rows = data["scenes"]
    nodes = [r["nodes"] for r in rows]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    series = [
        (axes[0], "seconds", [("prepare (from the generator)", "prepare_s", "tab:red"),
                              ("prepared load", "load_s", "tab:green")]),
        (axes[1], "MB", [("prepare, peak RSS", "prepare_peak_mb", "tab:red"),
                         ("prepared load, resident", "load_rss_mb", "tab:green"),
                         ("resident after culling", "rss_after_culling_mb", "tab:olive"),
                         ("prepared file", "file_mb", "tab:gray")]),
    ]
    for ax, ylabel, lines in series:
        for label, key, color in lines:
            ax.plot(nodes, [r[key] for r in rows], "o-", color=color, label=label)
        ax.set_ylabel(ylabel)
    for wall, color in zip(data["walls"], ("tab:blue", "tab:purple")):
        axes[2].plot(nodes, [r["cull"][wall]["median_ms"] for r in rows], "o-", color=color,
                     label=f"adaptive, {wall[5:-5]} (median)")
    axes[2].set_ylabel("culling time per frame (ms)")
    for ax, title in zip(axes, ("(a) time", "(b) memory", "(c) culling")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("scene nodes")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    md = ["## Scale: cost against scene size\n",
          f"`powerplant*K` is K power plants side by side (the tree of one, tiled). Each step "
          f"runs in a fresh process: `wallcull prepare SCENE` into an empty cache (build the "
          f"hierarchy, fit the bounds, write the prepared file), then a prepared load "
          f"(`wallcull.scene.load` maps that file) and {data['frames']} frames of the "
          f"`{data['path']}` path culled by `{data['method']}` with `{data['bounds']}` bounds on "
          f"`examples/wall-8x8.json` and `examples/wall-64x64.json`, as `wallcull bench` "
          f"times them. Resident memory is read after the load, and again after culling "
          f"(the pages of the bounds and the tree the culler touched are then resident).\n",
          ctx.savefig(fig, "scale.png", "Cost against scene size") + "\n"]
    table = []
    for r in rows:
        cull = [r["cull"][w] for w in data["walls"]]
        table.append([f"`{r['scene']}`", f"{r['nodes']:,}", f"{r['triangles'] / 1e6:,.1f} M",
                      f"{r['prepare_s']:.1f}", f"{r['prepare_peak_mb']:,.0f}",
                      f"{r['file_mb']:,.0f}", f"{r['load_s']:.2f}",
                      f"{r['load_rss_mb']:,.0f} / {r['rss_after_culling_mb']:,.0f}",
                      *(f"{C.ms(c['median_ms'])} / {C.ms(c['p99_ms'])}" for c in cull)])
    md.append(C.table(["scene", "nodes", "triangles", "prepare s", "prepare peak MB",
                       "file MB", "prepared load s", "resident MB, loaded / culled",
                       "adaptive 8x8 ms",
                       "adaptive 64x64 ms"], table) + "\n")
    md.append("Culling times are median / p99 per frame. A prepared load maps the file and "
              "reads no triangle: names, hierarchy and bounds are paged in as the culler "
              "touches them, and meshes are read one at a time when a render node or the "
              "oracle asks for one.\n")
    return "\n".join(md)


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args[:1] == ["prepare"] and len(args) == 2:
        print(json.dumps(measure_prepare(args[1])))
    elif args[:1] == ["load"] and len(args) == 3:
        print(json.dumps(measure_load(args[1], int(args[2]))))
    else:
        print(__doc__.strip().splitlines()[-2:], file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
