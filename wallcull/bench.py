"""``wallcull bench``: culling time per method over a camera path, and what it costs in accuracy.

Times are for the culling step alone (the frame's frusta, the first-level cull and the
traversal, down to per-tile lists), measured in this process with ``perf_counter`` over every
frame of the path, after a few warm-up frames that compile the kernels.
"""

from __future__ import annotations

import platform
import resource
import time
from contextlib import nullcontext
from dataclasses import replace

import numpy as np

from . import oracle, workers
from .cull import METHODS
from .documents import MAX_IPD
from .errors import InputError
from .encode import frame_packets, node_entries
from .fit import FRUSTUM, FitOptions
from .occlude import PARTS, OcclusionOptions
from .paths import scene_path
from .pipeline import Session
from .protocol import FrameRecord, History
from .scene import BRANCHING, CLUSTERS, Scene
from .wall import Frame, Wall

WARMUP_FRAMES = 3


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB: Linux's ``VmHWM``, which is this
    program's own (``ru_maxrss`` keeps the peak of the process that started it, across fork
    and exec, so a step started by a big parent reported the parent's peak)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux


def machine() -> dict:
    import os

    return {"python": platform.python_version(), "numpy": np.__version__,
            "cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "system": platform.system()}


def summarize(times_ms: list[float]) -> dict:
    t = np.asarray(times_ms)
    return {"median_ms": float(np.median(t)), "p99_ms": float(np.percentile(t, 99)),
            "mean_ms": float(t.mean()), "min_ms": float(t.min())}


class Motion:
    """A dynamic scene (paper Fig. 6): a fixed, seeded ``fraction`` of the leaves sway about
    their rest pose, each frame a different rigid offset (a turn of up to ~11 degrees about a
    random axis, a shift of up to 2% of the scene's size)."""

    def __init__(self, scene: Scene, fraction: float, seed: int = 0):
        if not 0 <= fraction <= 1:
            raise InputError(f"moving fraction must be in [0, 1], got {fraction}")
        rng = np.random.default_rng(seed)
        count = int(round(fraction * len(scene.leaves)))
        self.nodes = np.sort(rng.choice(scene.leaves, count, replace=False))
        self.base = scene.local[self.nodes]
        axis = rng.normal(size=(count, 3))
        self.axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
        self.shift = rng.normal(size=(count, 3)) * 0.02 * float(np.ptp(scene.box, axis=0).max())
        self.phase = rng.uniform(0, 2 * np.pi, count)

    def at(self, k: int) -> np.ndarray:
        """``(count, 4, 4)`` local transforms at frame ``k``: each part turned about its own
        origin and shifted, in its parent's frame (so the motion is rigid in the world even
        when the part's own transform scales)."""
        wave = np.sin(2 * np.pi * k / 60 + self.phase)
        angle = 0.2 * wave
        x, y, z = self.axis.T
        K = np.zeros((len(angle), 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -z, y, -x
        K -= np.swapaxes(K, 1, 2)
        s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
        turn = np.eye(3) + s * K + (1 - c) * K @ K  # Rodrigues
        out = self.base.copy()
        out[:, :3, :3] = turn @ self.base[:, :3, :3]
        out[:, :3, 3] += self.shift * wave[:, None]
        return out


#: The stages of a frame ``bench --json`` reports: ``occlude`` is the occlusion cull (0 on
#: frames it skips, and without ``--occlusion``); ``encode`` is every tile's entry of the
#: frame's node messages, encoded once in one compiled pass as the node streams and NATS send
#: them (a node's message is then a slice of it behind a shared head); ``encode_packets``, not
#: in ``total``, is every tile's packet as the per-tile streams and ``GET .../packets`` send it.
STAGES = ("cull", "occlude", "leaves", "fit", "encode", "total")


#: Frames each method culls in its turn when several are timed: each sees the machine's load
#: of the same minute, so their ratios hold on a shared machine (as the experiments do).
TURN = 40


def time_method(*args, **kwargs) -> dict:
    """:func:`timing` run to its end: one method alone."""
    return _drain(timing(*args, **kwargs))


def in_turns(timings: dict, frames: int) -> dict:
    """Run the generators of :func:`timing` (name -> generator, the same ``frames`` frames each)
    :data:`TURN` frames at a time in turn; name -> summary."""
    for a in range(0, frames, TURN):
        for timed in timings.values():
            for _ in range(min(TURN, frames - a)):
                next(timed)
    return {name: _drain(timed) for name, timed in timings.items()}


def _drain(timed) -> dict:
    while True:
        try:
            next(timed)
        except StopIteration as done:
            return done.value


def timing(scene: Scene, wall: Wall, frames, method: str, bounds: str,
           pseudo_groups: bool = False, progress=None, motion: Motion | None = None,
           refit: str | None = None, fit: FitOptions | None = None,
           stages: bool = False, occlusion: OcclusionOptions | None = None):
    """Cull every frame with one method; per-frame times and counters: a generator that
    yields after each frame timed and returns the summary (:func:`time_method`,
    :func:`in_turns`). With ``motion``, the
    moving nodes are updated and refit before each frame, and that time is reported apart;
    with ``fit``, the fitted frusta are timed too, and the depth precision they buy. With
    ``stages``, the whole frame as the server makes it (the fitted frusta with ``fit`` or the
    server's defaults): ``cull``, ``leaves`` (the per-tile leaf lists), ``fit``, ``encode``
    (every tile's entry of the node messages, a delta against the previous frame as a
    streaming node gets it) and their ``total``, and ``encode_packets`` (every tile's packet,
    as a per-tile stream gets it; see :data:`STAGES`). ``occlusion``: the occlusion setting,
    timed as the ``occlude`` stage, part by part (``occlude_parts_median_ms``, see
    :data:`~wallcull.occlude.PARTS`), and apart on the frames where it hid nothing
    (``nothing_hidden``). Also the triangles the tiles draw, a frame on average."""
    session = Session(scene, wall, method, bounds, pseudo_groups,
                      fit or (FitOptions() if stages else None), occlusion=occlusion)
    history, tiles, packet_bytes = History(4), np.arange(wall.tiles), []
    none = np.zeros(0, np.int64)
    for k, frame in enumerate(frames[:WARMUP_FRAMES]):  # every stage once: compiled, cached
        result = session.frame(frame)
        if stages:
            history.add(FrameRecord(k, 0.0, *result.leaves, result.fits, none,
                                    np.zeros((0, 4, 4)), result.parts))
            frame_packets(history, k, tiles, k - 1 if k else None)
            node_entries(history, k, k - 1 if k else None)
    history = History(4)
    times, refits, tests, pairs, fits, ratios, coverages = [], [], [], [], [], [], []
    stage_ms = {name: [] for name in (*STAGES, "encode_packets")}
    entry_bytes, triangles, idle, parts = [], [], [], []
    task = progress.add_task(f"{method:>8} {bounds}", total=len(frames)) if progress else None
    for k, frame in enumerate(frames):
        if motion is not None and len(motion.nodes):
            local = motion.at(k)
            t0 = time.perf_counter()
            session.state.move_nodes(motion.nodes, local, refit)
            refits.append((time.perf_counter() - t0) * 1e3)
        result = session.frame(frame)
        times.append(result.timings["cull_ms"])
        if fit is not None:
            fits.append(result.timings["fit_ms"])
            shown = np.diff(result.visibility.start) > 0
            ratios.extend(np.log2(result.fits.far[shown] / result.fits.near[shown]))
            fitted = [s.coverage[s.kind == FRUSTUM] for s in result.fits.shadows]
            coverages.extend(np.concatenate(fitted).tolist() if fitted else [])
        if stages:
            history.add(FrameRecord(k, time.time(), *result.leaves, result.fits, none,
                                    np.zeros((0, 4, 4)), result.parts))
            t0 = time.perf_counter()
            entries = node_entries(history, k, k - 1 if k else None)
            t1 = time.perf_counter()
            sent = frame_packets(history, k, tiles, k - 1 if k else None)
            t2 = time.perf_counter()
            packet_bytes.append(sent.nbytes)
            entry_bytes.append(len(entries.data))
            timings = {"occlude_ms": 0.0, **result.timings, "encode_ms": (t1 - t0) * 1e3}
            for name in STAGES[:-1]:
                stage_ms[name].append(timings[f"{name}_ms"])
            stage_ms["total"].append(sum(timings[f"{name}_ms"] for name in STAGES[:-1]))
            stage_ms["encode_packets"].append((t2 - t1) * 1e3)
        stats = result.visibility.stats
        tests.append(stats["tests"] + stats["primary_tests"])
        pairs.append(stats["pairs"])
        triangles.append(int(result.visibility.triangles().sum()))
        if "occlude_parts_ms" in stats:  # occlusion ran: where its time went
            parts.append(stats["occlude_parts_ms"])
        if stats.get("occluded") == 0:  # ... and hid nothing: what it cost then
            idle.append(result.timings["occlude_ms"])
        if progress:
            progress.advance(task)
        yield
    # leaves reported per frame, from the last frame (the lists, not their timing)
    out = {**summarize(times), "tests_per_frame": float(np.mean(tests)),
           "nodes_per_frame": float(np.mean(pairs)),
           "leaf_pairs_last_frame": int(len(result.leaves[1])),
           "triangles_per_frame": float(np.mean(triangles))}
    if occlusion is not None:
        out["nothing_hidden"] = {"frames": len(idle), **(
            {"occlude_median_ms": float(np.median(idle))} if idle else {})}
        out["occlude_parts_median_ms"] = {name: float(np.median([p[name] for p in parts]))
                                          for name in PARTS} if parts else {}
    if refits:
        out["refit_median_ms"] = float(np.median(refits))
        out["refit_p99_ms"] = float(np.percentile(refits, 99))
    if fits:
        wall_bits = float(np.log2(wall.far / wall.near))
        tight_bits = float(np.mean(ratios)) if ratios else wall_bits
        out.update({"fit_median_ms": float(np.median(fits)),
                    "fit_p99_ms": float(np.percentile(fits, 99)),
                    "depth_log2_far_over_near": {"wall": wall_bits, "fitted_mean": tight_bits,
                                                 "bits_gained": wall_bits - tight_bits}})
        if coverages:
            out["shadow_coverage_mean"] = float(np.mean(coverages))
    if stages:
        out["stages"] = {name: {"median_ms": float(np.median(v)),
                                "p99_ms": float(np.percentile(v, 99))}
                         for name, v in stage_ms.items()}
        out["stages"]["packet_bytes_per_frame"] = float(np.median(packet_bytes))
        out["stages"]["node_entry_bytes_per_frame"] = float(np.median(entry_bytes))
    return out


def accuracy(scene: Scene, wall: Wall, frames, methods, bounds_kinds, progress=None,
             motion: Motion | None = None, refit: str | None = None) -> dict:
    """False positives against the exact oracle: reported (leaf, tile) pairs that the tile's
    frustum does not meet, per bound type and method, summed over ``frames``."""
    out: dict = {}
    task = (progress.add_task("accuracy", total=len(frames) * len(bounds_kinds) * len(methods))
            if progress else None)
    for kind in bounds_kinds:
        out[kind] = {}
        for method in methods:
            session = Session(scene, wall, method, kind)
            false = total = 0
            extent = float(np.ptp(scene.box, axis=0).max())
            for k, frame in enumerate(frames):
                if motion is not None and len(motion.nodes):
                    session.state.move_nodes(motion.nodes, motion.at(k), refit)
                vis = session.frame(frame).visibility
                reported = [vis.tile_leaves(t).tolist() for t in range(wall.tiles)]
                tol = 1e-7 * max(extent, float(np.linalg.norm(frame.position)))
                f, n = oracle.false_positives(scene, wall.to_dict(), frame.to_dict(), reported,
                                              tol, world=session.state.world)
                false, total = false + f, total + n
                if progress:
                    progress.advance(task)
            out[kind][method] = {"false_positives": false, "reported": total,
                                 "rate": false / total if total else 0.0}
    return out


def run(scene_spec: str, wall: Wall, frames: int = 200, methods=METHODS, bounds=("obb",),
        path: str = "orbit", pseudo_groups: bool = False, accuracy_frames: int = 0,
        hierarchy: str = "auto", branching: int = BRANCHING,
        clusters: int | None = CLUSTERS, moving: float = 0.0,
        refit: str | None = None,
        fit: FitOptions | None = None, settings: dict | None = None,
        progress: bool = True, shadow_fits: tuple = (), stereo: float | None = None,
        occlusion: str = "off") -> dict:
    """The whole benchmark; returns the ``bench --json`` document. ``branching``: of the
    automatic hierarchy. ``shadow_fits``: fitting
    efforts (:data:`wallcull.lowilie.EFFORTS`) to compare, fit time against shadow-map
    coverage, with the main method. ``stereo``: the path's frames are stereo frames with this
    interpupillary distance (m), the head level with the display (SPEC section 3).
    ``occlusion``: ``off``, ``on`` or ``auto`` (:mod:`wallcull.occlude`), every method with
    it."""
    from . import scene as scene_mod

    if not methods or not bounds:
        raise InputError(f"name at least one {'method' if not methods else 'bound type'}")
    for m in methods:
        if m not in METHODS:
            raise InputError(f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    if frames < 1:
        raise InputError(f"--frames must be at least 1, got {frames}")
    if not 0 <= accuracy_frames <= frames:
        raise InputError(f"the oracle can check 0 to {frames} frames (the frames timed), "
                         f"not {accuracy_frames}")
    if stereo is not None and not 0 < stereo <= MAX_IPD:
        raise InputError(f"stereo needs an interpupillary distance over 0 and at most "
                         f"{MAX_IPD:g} m, got {stereo:g}")
    if accuracy_frames:
        oracle.rotations()  # refused before any work when this install has no oracle
    t0 = time.perf_counter()
    scene = scene_mod.load(scene_spec, hierarchy=hierarchy, branching=branching,
                           settings=settings, clusters=clusters)
    t1 = time.perf_counter()
    for kind in bounds:
        scene.bounds(kind)
    t2 = time.perf_counter()
    rss = peak_rss_mb()
    path_frames = scene_path(scene, wall, path, frames)
    if stereo is not None:
        path_frames = [Frame.make(f.position, f.orientation, f.eye, wall,
                                  (stereo, (1.0, 0.0, 0.0, 0.0))) for f in path_frames]
    motion = Motion(scene, moving) if moving else None
    by_bounds: dict = {}
    bar = _progress() if progress else nullcontext()
    with bar as p:
        for kind in bounds:  # the methods in turns: their ratios are of the same minutes
            by_bounds[kind] = in_turns(
                {m: timing(scene, wall, path_frames, m, kind, pseudo_groups, p, motion, refit,
                           fit, stages=True, occlusion=OcclusionOptions.parse(occlusion))
                 for m in methods}, len(path_frames))
        acc = (accuracy(scene, wall, path_frames[:accuracy_frames], methods, bounds, p, motion,
                        refit) if accuracy_frames else None)
        main = "adaptive" if "adaptive" in methods else methods[0]
        efforts = {}
        for effort in shadow_fits:
            options = replace(fit or FitOptions(), shadow_fit=effort)
            timed = time_method(scene, wall, path_frames, main, bounds[0], pseudo_groups, p,
                                motion, refit, options)
            efforts[effort] = {"fit_median_ms": timed["fit_median_ms"],
                               "fit_p99_ms": timed["fit_p99_ms"],
                               "coverage_mean": timed.get("shadow_coverage_mean")}
    result = {
        "scene": {"name": scene.name, **scene.stats, "prepared": scene.prepared is not None,
                  "load_s": t1 - t0,
                  "preprocess_s": t2 - t1, "peak_rss_mb_after_load": rss},
        "wall": wall.to_dict(), "frames": frames, "path": path, "stereo": stereo,
        "bounds": bounds[0],
        "pseudo_groups": pseudo_groups, "methods": by_bounds[bounds[0]],
        "moving": moving, "refit": refit, "fit": fit is not None, "occlusion": occlusion,
        "settings": {"lights": len(scene.settings.get("lights", [])),
                     "mirrors": len(scene.settings.get("mirrors", []))},
        "machine": machine(), "threads": workers.count(), "peak_rss_mb": peak_rss_mb(),
    }
    if efforts:
        result["shadow_fit"] = efforts
    if len(bounds) > 1:
        result["by_bounds"] = by_bounds
    result["stages"] = {"method": main, **result["methods"][main]["stages"]}
    if "adaptive" in methods and "oh" in methods:
        result["adaptive_speedup_vs_oh"] = (result["methods"]["oh"]["median_ms"]
                                            / result["methods"]["adaptive"]["median_ms"])
    if acc is not None:
        result["accuracy"] = {"frames": accuracy_frames, **acc}
    return result


def _progress():
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), console=Console(stderr=True), transient=True)
