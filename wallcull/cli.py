"""The command line (SPEC section 6). Exit status 0 on success, 2 on bad input, one line of error.

    wallcull cull SCENE --wall WALL.json --frame FRAME.json [--method M] [--bounds B] [--leaves] [--json]
    wallcull bench SCENE --wall WALL.json [--frames N] [--methods a,b] [--json]
    wallcull walk SCENE [--wall WALL.json]      # the README's main job: a walkthrough, per tile
    wallcull prepare SCENE [--force]            # a prepared file: the scene loads in seconds
    wallcull serve [--host 127.0.0.1] [--port 8000] [--scenes DIR] [--token T] [--state DIR]
                   [--wall-ttl SECONDS]
                   [--cors-origin ORIGIN ...] [--limit NAME=VALUE ...] [--nats URL]
    wallcull scenes
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from .errors import InputError
from .documents import read_json
from .workers import count as kernel_threads

#: The wall of SPEC section 2, used where no ``--wall`` is given.
DEFAULT_WALL = {"cols": 4, "rows": 4, "tile_size": [0.60, 0.34], "gap": [0.012, 0.012],
                "distance": 2.0, "near": 0.1, "far": 1000.0, "resolution": [1920, 1080]}


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, status 2 (argparse prints usage too by default)
        raise InputError(message)


def _wall(arg):
    from .wall import Wall

    return Wall.from_dict(read_json(arg, "--wall") if arg is not None else DEFAULT_WALL)


def _load(args):
    from .scene import load
    from .settings import read

    settings = read(args.settings) if getattr(args, "settings", None) else None
    return load(args.scene, hierarchy=args.hierarchy, branching=args.branching,
                settings=settings, clusters=args.clusters)


def _occlusion(args):
    """``--occlusion off|on|auto`` as the pipeline's options (None: off)."""
    from .occlude import OcclusionOptions

    return OcclusionOptions.parse(args.occlusion)


def _cluster_size(text: str):
    """``--clusters``: 'off' or a number of triangles (one-line error otherwise)."""
    from .clusters import parse_size

    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def cmd_cull(args) -> int:
    from .fit import FitOptions
    from .pipeline import Session, tile_records

    wall = _wall(args.wall)
    frame_spec = read_json(args.frame, "--frame")
    scene = _load(args)
    session = Session(scene, wall, args.method, args.bounds, args.pseudo_groups,
                      FitOptions(depth=args.depth, reversed_z=args.reversed_z,
                                 shadow_fit=args.shadow_fit), occlusion=_occlusion(args))
    session.frame(frame_spec)  # the first call compiles the kernels; time the second
    result = session.frame(frame_spec)
    tiles = tile_records(result, leaves=args.leaves)
    vis = result.visibility
    stats = {**vis.stats, **result.timings, "bounds": args.bounds, "scene": scene.name,
             "clusters": scene.cluster_size or "off", "triangles": int(vis.triangles().sum()),
             "draw_calls": int(vis.draw_calls().sum())}
    if args.json:
        print(json.dumps({"tiles": tiles, "stats": stats}))
        return 0
    s = scene.stats
    print(f"scene {scene.name}: {s['nodes']} nodes ({s['internal']} internal, {s['leaves']} "
          f"leaves), {describe_wall(wall)}, method {args.method}, bounds {args.bounds}")
    for tile in tiles:
        names = ", ".join(tile["visible"]) or "-"
        extras = "".join(f", {len(tile[k])} {k}" for k in ("shadows", "mirrors") if k in tile)
        where = f" (row {tile['row']}, col {tile['col']})" if "row" in tile else ""
        parts = f", {len(tile['ranges'])} in part" if tile["ranges"] else ""
        print(f"tile {tile['id']:>3}{where}: depth "
              f"{tile['near']:.4g}-{tile['far']:.4g}{extras}; {len(tile['visible'])} "
              f"{'leaves' if args.leaves else 'nodes'}{parts}: {names}")
    print(f"culled in {stats['cull_ms']:.3f} ms with {stats['primary_tests'] + stats['tests']} "
          f"box-plane tests; frusta fitted in {stats['fit_ms']:.3f} ms; the tiles draw "
          f"{stats['triangles']:,} triangles in {stats['draw_calls']:,} draw calls")
    return 0


def cmd_bench(args) -> int:
    from . import bench

    wall = _wall(args.wall)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bounds = [b.strip() for b in args.bounds.split(",") if b.strip()]
    from .fit import FitOptions
    from .lowilie import EFFORTS
    from .settings import read

    efforts = [e.strip() for e in args.shadow_fit.split(",") if e.strip()]
    if not efforts:
        raise InputError("--shadow-fit needs an effort: sphere, greedy or refined")
    for effort in efforts:
        if effort not in EFFORTS:
            raise InputError(f"unknown shadow fit {effort!r}; choose from {', '.join(EFFORTS)}")
    fit = FitOptions(reversed_z=args.reversed_z, shadow_fit=efforts[0]) if args.fit else None
    result = bench.run(args.scene, wall, frames=args.frames, methods=methods, bounds=bounds,
                       path=args.path, pseudo_groups=args.pseudo_groups,
                       accuracy_frames=args.accuracy, hierarchy=args.hierarchy,
                       branching=args.branching, clusters=args.clusters,
                       moving=args.moving, refit=args.refit,
                       fit=fit, settings=read(args.settings) if args.settings else None,
                       progress=not args.json,
                       shadow_fits=tuple(efforts) if len(efforts) > 1 else (),
                       stereo=args.stereo, occlusion=args.occlusion)
    if args.json:
        print(json.dumps(result))
        return 0
    _print_bench(result)
    return 0


def _print_bench(result: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    s, w = result["scene"], result["wall"]
    console = Console()
    console.print(f"[bold]{s['name']}[/]: {s['nodes']} nodes ({s['internal']} internal, "
                  f"{s['leaves']} leaves, branching {s['branching']:.2f}, depth {s['depth']}), "
                  f"{s['triangles']:,} triangles; loaded in {s['load_s']:.2f} s"
                  f"{' (prepared)' if s.get('prepared') else ''} + preprocessed "
                  f"in {s['preprocess_s']:.2f} s, peak {s['peak_rss_mb_after_load']:.0f} MB")
    moving = (f"; {result['moving']:.0%} of the leaves moving, refit "
              f"{result['refit'] or result['bounds']}" if result["moving"] else "")
    stereo = f", stereo (ipd {result['stereo']:g} m)" if result.get("stereo") else ""
    shape = (f"wall of {len(w['screens'])} screens" if "screens" in w
             else f"{w['cols']} x {w['rows']} wall")
    console.print(f"{shape}, {result['frames']} frames of the "
                  f"{result['path']} path{stereo}{moving}")
    for kind, methods in result.get("by_bounds", {result["bounds"]: result["methods"]}).items():
        table = Table(title=f"culling time per frame, bounds {kind}")
        refits = any("refit_median_ms" in m for m in methods.values())
        fits = any("fit_median_ms" in m for m in methods.values())
        for col in ("method", "median ms", "p99 ms", "mean ms", "tests/frame", "nodes/frame",
                    *(["refit median ms"] if refits else []),
                    *(["fit median ms", "fit p99 ms"] if fits else [])):
            table.add_column(col, justify="right")
        for name, m in methods.items():
            table.add_row(name, f"{m['median_ms']:.3f}", f"{m['p99_ms']:.3f}",
                          f"{m['mean_ms']:.3f}", f"{m['tests_per_frame']:.0f}",
                          f"{m['nodes_per_frame']:.0f}",
                          *([f"{m.get('refit_median_ms', 0):.3f}"] if refits else []),
                          *([f"{m['fit_median_ms']:.3f}", f"{m['fit_p99_ms']:.3f}"]
                            if fits else []))
        console.print(table)
    depth = next((m["depth_log2_far_over_near"] for m in result["methods"].values()
                  if "depth_log2_far_over_near" in m), None)
    if depth:
        console.print(f"depth range log2(far/near): wall {depth['wall']:.1f}, fitted "
                      f"{depth['fitted_mean']:.1f} on average: {depth['bits_gained']:.1f} bits "
                      f"of a 24-bit depth buffer gained")
    if result.get("occlusion", "off") != "off":
        main = result["stages"]
        console.print(f"occlusion {result['occlusion']} ({main['method']}): "
                      f"{main['occlude']['median_ms']:.3f} ms median, "
                      f"{main['occlude']['p99_ms']:.3f} ms p99 a frame; whole frame "
                      f"{main['total']['median_ms']:.3f} ms median; "
                      f"{result['methods'][main['method']]['triangles_per_frame']:,.0f} "
                      f"triangles drawn a frame")
        parts = result["methods"][main["method"]]["occlude_parts_median_ms"]
        if parts:
            console.print("  its parts, median ms: " + ", ".join(
                f"{name} {ms:.3f}" for name, ms in parts.items()))
    if "adaptive_speedup_vs_oh" in result:
        console.print(f"adaptive is {result['adaptive_speedup_vs_oh']:.1f}x faster than oh")
    if "accuracy" in result:
        acc = result["accuracy"]
        table = Table(title=f"false positives against the exact oracle, {acc['frames']} frames")
        table.add_column("bounds")
        for m in result["methods"]:
            table.add_column(m, justify="right")
        for kind, row in acc.items():
            if kind != "frames":
                table.add_row(kind, *(f"{v['rate']:.1%} of {v['reported']}" for v in row.values()))
        console.print(table)


def cmd_walk(args) -> int:
    from rich.console import Console
    from rich.progress import track
    from rich.table import Table

    from .paths import scene_path
    from .pipeline import Session

    wall = _wall(args.wall)
    scene = _load(args)
    session = Session(scene, wall, args.method, args.bounds, occlusion=_occlusion(args))
    frames = scene_path(scene, wall, args.path, args.frames)
    session.frame(frames[0])  # compile
    counts = np.zeros((len(frames), wall.tiles), dtype=np.int64)
    times = []
    for k, frame in enumerate(track(frames, description="culling", transient=True,
                                    console=Console(stderr=True))):
        result = session.frame(frame)
        times.append(result.timings["cull_ms"])
        vis = result.visibility
        counts[k] = [len(vis.tile_leaves(t)) for t in range(wall.tiles)]
    s = scene.stats
    console = Console()
    console.print(f"[bold]{scene.name}[/]: {s['leaves']} leaves, {s['triangles']:,} triangles; "
                  f"{describe_wall(wall)}; {len(frames)} frames of the {args.path} path; "
                  f"method {args.method}, bounds {args.bounds}")
    table = Table(title="leaves drawn per tile (mean, min-max over the walkthrough)")
    mean, lo, hi = counts.mean(0), counts.min(0), counts.max(0)
    cells = [f"{mean[t]:.0f} ({lo[t]}-{hi[t]})" for t in range(wall.tiles)]
    if wall.kind == "grid":
        table.add_column("row")
        for c in range(wall.cols):
            table.add_column(f"col {c}", justify="right")
        for r in range(wall.rows):
            table.add_row(str(r), *cells[r * wall.cols:(r + 1) * wall.cols])
    else:
        table.add_column("screen")
        table.add_column("leaves", justify="right")
        for t, cell in enumerate(cells):
            table.add_row(str(t), cell)
    console.print(table)
    t = np.asarray(times)
    console.print(f"culling time per frame: median {np.median(t):.3f} ms, p99 "
                  f"{np.percentile(t, 99):.3f} ms, max {t.max():.3f} ms")
    return 0


def describe_wall(wall) -> str:
    """``4 x 4 wall`` or ``wall of 5 screens``."""
    if wall.kind == "grid":
        return f"{wall.cols} x {wall.rows} wall"
    return f"wall of {wall.tiles} screens"


def cmd_serve(args) -> int:
    from .server import seconds_setting, serve, settings_from_env

    settings = settings_from_env()
    if not 0 <= args.port <= 65535:
        raise InputError(f"--port must be 0 to 65535, got {args.port}")
    if args.token is not None and not args.token.strip():
        raise InputError("--token must not be empty (leave it out for a server anyone may "
                         "use)")
    if args.scenes:
        settings["scene_folder"] = args.scenes
    if args.token:
        settings["token"] = args.token
    if args.state:
        settings["state"] = None if args.state.lower() == "none" else args.state
    if args.cors_origin:
        settings["origins"] = tuple(args.cors_origin)
    if args.nats:
        settings["nats"] = args.nats
    if args.nats_prefix:
        from .server.nats import check_prefix

        settings["nats_prefix"] = check_prefix(args.nats_prefix)
    if args.wall_ttl is not None:
        settings["wall_ttl"] = seconds_setting(args.wall_ttl, "--wall-ttl")
    for text in args.limit:
        settings["limits"] = settings["limits"].with_text(text)
    if settings.get("nats"):
        from .server.nats import check_broker

        check_broker(settings["nats"])
    serve(args.host, args.port, args.log_level, tls=_tls(args.tls_cert, args.tls_key),
          **settings)
    return 0


def _tls(cert: str | None, key: str | None) -> tuple[str, str | None] | None:
    """``(certificate, key)`` files for ``serve``, checked that they load (one line if not)."""
    if cert is None:
        if key is not None:
            raise InputError("--tls-key needs --tls-cert")
        return None
    import ssl

    try:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise InputError(f"cannot serve TLS with --tls-cert {cert}"
                         f"{f' --tls-key {key}' if key else ''}: "
                         f"{getattr(exc, 'strerror', None) or exc}") from None
    return cert, key


def cmd_prepare(args) -> int:
    import time

    from .scene import prepare

    from rich.console import Console

    t0 = time.perf_counter()
    # about 30 s and 3 GB a million nodes: a spinner on a terminal says it is at work
    with Console(stderr=True).status(f"preparing {args.scene}…"):
        path, scene = prepare(args.scene, hierarchy=args.hierarchy, branching=args.branching,
                              force=args.force, clusters=args.clusters)
    if scene is None:
        print(f"{args.scene}: {path} is current (--force writes it again)")
        return 0
    s = scene.stats
    print(f"{args.scene}: {s['nodes']:,} nodes, {s['leaves']:,} leaves, {s['clusters']:,} "
          f"clusters, {len(scene.meshes):,} meshes, prepared in {time.perf_counter() - t0:.1f} s: {path} "
          f"({path.stat().st_size / 1e6:,.0f} MB)")
    return 0


def cmd_overdraw(args) -> int:
    from rich.console import Console
    from rich.measure import Measurement
    from rich.progress import track
    from rich.table import Table

    from . import overdraw

    from .scene import parse_clusters

    sizes = [parse_clusters(k.strip()) for k in args.sizes.split(",") if k.strip()]
    wall = _wall(args.wall)
    if args.frames < 1:
        raise InputError(f"--frames must be at least 1, got {args.frames}")
    resolution = None
    if args.visible or args.visible_resolution:
        resolution = overdraw.default_resolution(wall)
        if args.visible_resolution:
            resolution[:] = _pixels(args.visible_resolution, "--visible-resolution")
    steps = iter(track(range(args.frames), description="overdraw", transient=True,
                       console=Console(stderr=True), disable=args.json))
    report = overdraw.run(args.scene, wall, args.path, args.frames, sizes, args.method,
                          args.bounds, args.hierarchy, args.branching,
                          progress=lambda: next(steps, None), occlusion=args.occlusion,
                          resolution=resolution).summary()
    if args.json:
        print(json.dumps(report))
        return 0
    console = Console()
    seen = "visible" in report
    console.print(f"[bold]{report['scene']}[/]: {report['triangles']:,} triangles; "
                  f"{describe_wall(wall)}; {args.frames} frames of the {args.path} path; method "
                  f"{args.method}, bounds {args.bounds}"
                  + (f"; id buffers of {report['visible_resolution']} pixels" if seen else ""))
    table = Table(title="triangles drawn per frame, summed over the tiles")
    occluded = any(e["occlusion"] for e in report["settings"])
    for col in ("lists", "triangles", "x floor", *(["x visible"] if seen else []),
                "draw calls", "cull ms", *(["occlude ms"] if occluded else [])):
        table.add_column(col, justify="right")

    def row(name, triangles, over_floor, over_visible, *times):
        table.add_row(name, f"{triangles:,.0f}", over_floor,
                      *([f"{over_visible:.2f}"] if seen else []),
                      *(times or [""] * (2 + occluded)))

    row("no culling", report["none"], f"{report['none_over_floor']:.1f}",
        report.get("none_over_visible"))
    for e in report["settings"]:
        name = "leaves" if e["clusters"] == "off" else f"clusters of {e['clusters']}"
        name += ", occlusion" if e["occlusion"] else ""
        row(name, e["triangles"], f"{e['over_floor']:.2f}", e.get("over_visible"),
            f"{e['draw_calls']:,.0f}", f"{e['cull_ms_median']:.3f}",
            *([f"{e['occlude_ms_median']:.3f}" if e["occlusion"] else ""] if occluded else []))
    row("floor", report["floor"], "1.00", report.get("floor_over_visible"))
    if seen:
        row("visible floor", report["visible"],
            f"{report['visible'] / report['floor']:.2f}" if report["floor"] else "nan", 1.0)
    if not console.is_terminal:  # a file or a pipe: whole rows, no number cut short
        console.width = max(console.width, Measurement.get(
            console, console.options.update_width(1000), table).maximum)
    console.print(table)
    return 0


def _pixels(text: str, option: str) -> tuple[int, int]:
    """``WxH`` (e.g. ``240x135``) as two integers from 1 to 16,384 (what GPUs render to), or
    a one-line error."""
    w, x, h = text.lower().partition("x")
    if x and w.strip().isdigit() and h.strip().isdigit() and 0 < int(w) <= 1 << 14 and \
            0 < int(h) <= 1 << 14:
        return int(w), int(h)
    raise InputError(f"{option} must be WIDTHxHEIGHT in pixels, each 1 to 16384, e.g. 240x135, "
                     f"got {text!r}")


def cmd_scenes(args) -> int:
    from wallcull import bundled

    for name, text in [*bundled.BUNDLED.items(), *bundled.TILED.items()]:
        print(f"{name}\t{text}")
    return 0


def parser() -> argparse.ArgumentParser:
    from .bounds import KINDS
    from .cull import METHODS
    from .lowilie import EFFORTS
    from .clusters import AUTO_SIZE, MAX_SIZE, MIN_SIZE
    from .occlude import SETTINGS
    from .overdraw import RESOLUTION_DIVISOR
    from .paths import PATHS
    from .scene import BRANCHING, CLUSTERS

    p = _Parser(prog="wallcull", description="Culling server for tiled display walls.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    def build_args(q, clusters=True):
        q.add_argument("scene", help="scene file, or a bundled scene name (wallcull scenes)")
        q.add_argument("--hierarchy", choices=("auto", "file"), default="auto",
                       help="auto: spatial groups under parents with very many children")
        q.add_argument("--branching", type=int, default=BRANCHING,
                       help="branching factor of the automatic hierarchy (and of cluster trees)")
        if clusters:
            q.add_argument("--clusters", type=_cluster_size, default=CLUSTERS,
                           metavar="auto|off|K",
                           help=f"cut leaves of more than K triangles into clusters of at most "
                                f"K ({MIN_SIZE}-{MAX_SIZE}), or not at all (off); auto, the "
                                f"default: {AUTO_SIZE}, coarser in scenes that would get more "
                                f"cluster nodes than twice their own")

    def occlusion_arg(q, default="off"):
        q.add_argument("--occlusion", choices=SETTINGS, default=default,
                       help="drop what occluders hide: never (off), every frame (on), or "
                            f"when the camera is inside the scene (auto); default {default}")

    def scene_args(q):
        build_args(q)
        q.add_argument("--settings", metavar="SETTINGS.json",
                       help="scene settings (lights, mirrors) instead of the scene's own")

    q = sub.add_parser("cull", help="cull one frame and print each tile's list")
    scene_args(q)
    q.add_argument("--wall", required=True, help="WALL.json, or the JSON inline")
    q.add_argument("--frame", required=True, help="FRAME.json, or the JSON inline")
    q.add_argument("--method", choices=METHODS, default="adaptive")
    q.add_argument("--bounds", choices=KINDS, default="obb")
    q.add_argument("--pseudo-groups", action="store_true", help="adaptive: regroup children")
    q.add_argument("--leaves", action="store_true", help="list leaf names only")
    q.add_argument("--depth", choices=("tight", "wall"), default="tight",
                   help="near/far per tile: fitted to what it shows, or the wall's")
    q.add_argument("--reversed-z", action="store_true",
                   help="projections with depth in [0, 1], near at 1 (glClipControl)")
    q.add_argument("--shadow-fit", choices=EFFORTS, default="refined",
                   help="shadow frusta: the bounding-sphere frustum, the paper's greedy quad, or "
                        "the refined quad (default)")
    occlusion_arg(q)
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_cull)

    q = sub.add_parser("bench", help="time the methods over a camera path")
    scene_args(q)
    q.add_argument("--wall", required=True, help="WALL.json, or the JSON inline")
    q.add_argument("--frames", type=int, default=200)
    q.add_argument("--methods", default=",".join(METHODS))
    q.add_argument("--bounds", default="obb", help="comma-separated bound types")
    q.add_argument("--path", choices=PATHS, default="orbit",
                   help="orbit: whole scene in view (the paper's worst case); fly: through it")
    q.add_argument("--pseudo-groups", action="store_true")
    q.add_argument("--stereo", type=float, metavar="IPD",
                   help="stereo frames with this interpupillary distance, m (e.g. 0.064)")
    q.add_argument("--accuracy", type=int, default=0, metavar="FRAMES",
                   help="count false positives against the exact oracle on this many frames")
    q.add_argument("--moving", type=float, default=0.0, metavar="FRACTION",
                   help="dynamic scene: this fraction of the leaves moves every frame")
    q.add_argument("--refit", choices=("obb", "aabb"),
                   help="how moved nodes and their ancestors are refit (default: as --bounds)")
    q.add_argument("--fit", action="store_true",
                   help="also time the fitted frusta (depth ranges, shadows, mirrors)")
    occlusion_arg(q)
    q.add_argument("--reversed-z", action="store_true", help="with --fit: reversed-Z projections")
    q.add_argument("--shadow-fit", default="refined", metavar="EFFORT[,EFFORT...]",
                   help="with --fit: shadow-frustum fitting, sphere|greedy|refined; several "
                        "compare their fit time and shadow-map coverage")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_bench)

    q = sub.add_parser("walk", help="cull a walkthrough and print per-tile results")
    scene_args(q)
    q.add_argument("--wall", help="WALL.json, or the JSON inline (default: SPEC's 4 x 4 wall)")
    q.add_argument("--frames", type=int, default=240)
    q.add_argument("--path", choices=PATHS, default="orbit")
    q.add_argument("--method", choices=METHODS, default="adaptive")
    q.add_argument("--bounds", choices=KINDS, default="obb")
    occlusion_arg(q)
    q.set_defaults(func=cmd_walk)

    q = sub.add_parser("prepare", help="write a scene's prepared file, so that it loads in "
                                       "seconds (in $WALLCULL_CACHE, else ~/.cache/wallcull)")
    build_args(q)
    q.add_argument("--force", action="store_true", help="write it even if a current one exists")
    q.set_defaults(func=cmd_prepare)

    q = sub.add_parser("overdraw", help="triangles the tiles draw over a camera path: with leaf "
                                        "lists, with clusters, the exact floor, no culling")
    build_args(q, clusters=False)
    q.add_argument("--wall", help="WALL.json, or the JSON inline (default: SPEC's 4 x 4 wall)")
    q.add_argument("--path", choices=PATHS, default="orbit")
    q.add_argument("--frames", type=int, default=60)
    q.add_argument("--sizes", default=f"{CLUSTERS}", metavar="K[,K...]",
                   help=f"cluster sizes (or auto) to compare with the leaf lists (default "
                        f"{CLUSTERS})")
    q.add_argument("--method", choices=METHODS, default="adaptive")
    q.add_argument("--bounds", choices=KINDS, default="obb")
    q.add_argument("--occlusion", action="store_true",
                   help="also each list setting (leaves, and the clusters') with occlusion "
                        "culling on (every frame)")
    q.add_argument("--visible", action="store_true",
                   help="also count the visible floor: the triangles with a pixel in the tile's "
                        "id buffer (each tile's list rasterized in software: slower)")
    q.add_argument("--visible-resolution", metavar="WxH",
                   help=f"pixels of each tile's id buffer (implies --visible; default: the "
                        f"tile's resolution / {RESOLUTION_DIVISOR}, 240x135 for 1920x1080 tiles)")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_overdraw)

    q = sub.add_parser("serve", help="run the culling server (HTTP + WebSocket)")
    q.add_argument("--host", default="127.0.0.1")
    q.add_argument("--port", type=int, default=8000)
    q.add_argument("--scenes", help="folder of scene files clients may name and upload to")
    q.add_argument("--token", help="the operator's token: scenes and walls need it, and "
                                   "frames, packets and acknowledgements need it or the wall's "
                                   "credentials (default: $WALLCULL_TOKEN; none: no access "
                                   "control at all)")
    q.add_argument("--state", metavar="DIR",
                   help="folder where walls survive restarts and uploads go without --scenes "
                        "(default: $WALLCULL_STATE, else ~/.local/state/wallcull; 'none': "
                        "walls in memory only)")
    q.add_argument("--cors-origin", action="append", default=[], metavar="ORIGIN",
                   help="a browser origin allowed to call the API and open streams, e.g. "
                        "https://wall.lab.example (repeatable; '*': any; default: "
                        "$WALLCULL_CORS_ORIGINS)")
    q.add_argument("--limit", action="append", default=[], metavar="NAME=VALUE",
                   help="change a limit, e.g. upload=16M or streams_per_tile=2 (repeatable; "
                        "see docs/deployment.md; default: $WALLCULL_LIMITS)")
    q.add_argument("--nats", metavar="URL",
                   help="also publish node messages on this NATS broker, e.g. "
                        "nats://127.0.0.1:4222, and take acknowledgements from it (default: "
                        "$WALLCULL_NATS)")
    q.add_argument("--nats-prefix", metavar="PREFIX",
                   help="first token of the NATS subjects (default: wallcull)")
    q.add_argument("--wall-ttl", metavar="SECONDS",
                   help="delete a wall once it has had no frame, acknowledgement or stream for "
                        "this long (default: $WALLCULL_WALL_TTL, else never; see "
                        "docs/hardening.md)")
    q.add_argument("--tls-cert", metavar="FILE",
                   help="serve HTTPS and WSS with this certificate chain (PEM; with its key "
                        "too, unless --tls-key names the key's own file)")
    q.add_argument("--tls-key", metavar="FILE", help="the private key of --tls-cert (PEM)")
    q.add_argument("--log-level", default="info",
                   choices=("critical", "error", "warning", "info", "debug", "trace"))
    q.set_defaults(func=cmd_serve)

    q = sub.add_parser("scenes", help="list the bundled scenes")
    q.set_defaults(func=cmd_scenes)
    from .experiments import register; register(sub)
    _register_plugins(sub)
    return p


#: Entry-point group through which other distributions add subcommands: the clients add
#: ``wallcull loadtest``. Each entry point names a ``register(subparsers)`` function.
PLUGINS = "wallcull.commands"


def _register_plugins(sub) -> None:
    from importlib.metadata import entry_points

    for ep in entry_points(group=PLUGINS):
        ep.load()(sub)


def main(argv=None) -> int:
    try:
        args = parser().parse_args(argv)
        kernel_threads()  # WALLCULL_THREADS, checked before any work
        return args.func(args)
    except InputError as exc:
        print(f"wallcull: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("wallcull: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except MemoryError as exc:
        print(f"wallcull: out of memory ({exc or 'MemoryError'}): the job needs more than this "
              "machine or its limit (ulimit -v) leaves; building a scene takes about 3 GB a "
              "million nodes, mapping a prepared one far less", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - never a traceback; WALLCULL_DEBUG=1 shows it
        if os.environ.get("WALLCULL_DEBUG"):
            raise
        print(f"wallcull: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
