"""What every experiment shares: walls, scenes, the measuring loop, the oracle bookkeeping,
tables and plots.

Every number here comes from the product's own pieces: a :class:`~wallcull.pipeline.Session`
culls each frame and its ``timings["cull_ms"]`` is the time reported; false positives are
decided by :mod:`wallcull.oracle` with the tolerance :func:`wallcull.bench.accuracy` uses.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from .. import oracle
from ..bench import WARMUP_FRAMES, Motion
from ..errors import optional
from ..paths import scene_path as path_frames  # noqa: F401 - the experiments call it C.path_frames
from ..pipeline import Session
from ..scene import Scene, load
from ..wall import Wall
from .context import Context, Task  # noqa: F401 - experiments name them through this module

#: The wall of SPEC section 2 (tiles 0.60 x 0.34 m, 12 mm bezels, 2 m away), any size.
SPEC_TILE = (0.60, 0.34)
SPEC_GAP = (0.012, 0.012)
#: The physical size of the fixed-size wall of fig5: that of a 4 x 4 SPEC wall, rounded.
FIXED_SIZE = (2.4, 1.36)
#: Gap between tiles of the fixed-size wall, as a fraction of the tile pitch.
FIXED_GAP = 0.02

#: Bytes of one leaf id in a per-tile packet, and of one triangle and one vertex of geometry.
ID_BYTES = 4
VERTEX_BYTES = 12  # 3 x float32
TRIANGLE_BYTES = 12  # 3 x uint32


def spec_wall(cols: int, rows: int) -> Wall:
    """A wall of SPEC tiles: it grows with the tile count (the field of view widens)."""
    return Wall.from_dict({"cols": cols, "rows": rows, "tile_size": list(SPEC_TILE),
                           "gap": list(SPEC_GAP), "distance": 2.0, "near": 0.1, "far": 1000.0})


def fixed_wall(cols: int, rows: int) -> Wall:
    """A wall of fixed physical size ``FIXED_SIZE`` cut into ``cols x rows`` tiles with gaps of
    ``FIXED_GAP`` of the pitch: the field of view stays, the tiles shrink."""
    (W, H), g = FIXED_SIZE, FIXED_GAP
    gx, gy = g * W / cols, g * H / rows
    return Wall.from_dict({"cols": cols, "rows": rows,
                           "tile_size": [(W - (cols - 1) * gx) / cols, (H - (rows - 1) * gy) / rows],
                           "gap": [gx, gy], "distance": 2.0, "near": 0.1, "far": 1000.0})


def spaced(count: int, total: int, seed: int) -> list[int]:
    """``count`` frame indices spread evenly over ``[0, total)``, shifted by a seeded offset."""
    count = max(1, min(count, total))
    step = total / count
    offset = np.random.default_rng(seed).uniform(0, step)
    return sorted({int(offset + i * step) % total for i in range(count)})


# --------------------------------------------------------------------------- scenes


class Pristine:
    """A scene loaded once with :func:`wallcull.scene.load` and never preprocessed; each
    :meth:`fresh` copy is a scene as ``load`` returns it, so the first ``bounds(kind)`` on it
    is the whole preprocessing cost, without paying the file's parse again. Built from its
    source, never mapped from a prepared file (whose bounds are already fitted). ``kwargs``:
    :func:`~wallcull.scene.load`'s others (``clusters``)."""

    def __init__(self, spec: str, hierarchy: str = "auto", branching: int | None = None,
                 **kwargs):
        if branching is not None:
            kwargs["branching"] = branching
        t0 = time.perf_counter()
        self.scene = load(spec, hierarchy=hierarchy, cache="off", **kwargs)
        self.load_s = time.perf_counter() - t0

    def fresh(self) -> Scene:
        return copy.deepcopy(self.scene)


def preprocess(pristine: Pristine, kind: str) -> tuple[Scene, dict]:
    """A fresh scene with bounds ``kind`` computed, and the seconds spent fitting them (paper
    Alg. 1, leaves from their mesh templates)."""
    scene = pristine.fresh()
    t0 = time.perf_counter()
    scene.bounds(kind)
    return scene, {"bounds_s": time.perf_counter() - t0}


def scene_stats(scene: Scene) -> dict:
    return {"name": scene.name, **scene.stats}


# --------------------------------------------------------------------------- measuring


#: Runs timed together are interleaved in chunks of this many frames.
CHUNK = 40


@dataclass
class Run:
    """One configuration to time: a method and bound type culling a scene to a wall over
    ``frames``; with ``motion``, a share of the leaves moves before each frame."""

    scene: Scene
    wall: Wall
    frames: list
    method: str
    bounds: str = "obb"
    pseudo_groups: bool = False
    motion: Motion | None = None
    refit: str | None = None


def walk_all(runs: list[Run], task: Task | None = None, chunk: int = CHUNK) -> list[dict]:
    """Cull every run's frames, as :func:`wallcull.bench.time_method` does (same warm-up, same
    timer), keeping the per-frame series: ``cull_ms``, box-plane ``tests``, listed ``pairs``.

    The runs take turns, ``chunk`` frames at a time, each in its own session: on a machine
    shared with other work, a slow spell then falls on every run alike instead of on whichever
    ran during it.

    With ``motion``, the moving leaves are put at frame ``k``'s pose before frame ``k`` and the
    update (:meth:`SceneState.move_nodes`: the rigid move and the ancestors' refit) is timed
    apart, as ``refit_ms``. Updates chain frame after frame, as in the product.
    """
    walkers = [_Walker(run) for run in runs]
    for w in walkers:
        w.warm_up()
    longest = max(len(run.frames) for run in runs)
    for start in range(0, longest, chunk):
        for w in walkers:
            for k in range(start, min(start + chunk, len(w.run.frames))):
                w.step(k)
                if task:
                    task.advance()
    return [w.series() for w in walkers]


class _Walker:
    def __init__(self, run: Run):
        self.run = run
        self.session = Session(run.scene, run.wall, run.method, run.bounds, run.pseudo_groups)
        self.moving = run.motion is not None and len(run.motion.nodes) > 0
        n = len(run.frames)
        self.cull, self.refit_ms = np.zeros(n), np.zeros(n)
        self.tests, self.pairs = np.zeros(n, np.int64), np.zeros(n, np.int64)

    def _move(self, k: int) -> float:
        run = self.run
        local = run.motion.at(k)
        t0 = time.perf_counter()
        self.session.state.move_nodes(run.motion.nodes, local, run.refit)
        return (time.perf_counter() - t0) * 1e3

    def warm_up(self) -> None:
        for k, frame in enumerate(self.run.frames[:WARMUP_FRAMES]):
            if self.moving:
                self._move(k)
            self.session.frame(frame)

    def step(self, k: int) -> None:
        if self.moving:
            self.refit_ms[k] = self._move(k)
        result = self.session.frame(self.run.frames[k])
        self.cull[k] = result.timings["cull_ms"]
        stats = result.visibility.stats
        self.tests[k] = stats["tests"] + stats["primary_tests"]
        self.pairs[k] = stats["pairs"]

    def series(self) -> dict:
        out = {"cull_ms": self.cull, "tests": self.tests, "pairs": self.pairs}
        if self.moving:
            out["refit_ms"] = self.refit_ms
        return out


def summary(times) -> dict:
    t = np.asarray(times, dtype=float)
    return {"median_ms": float(np.median(t)), "mean_ms": float(t.mean()),
            "p99_ms": float(np.percentile(t, 99)), "min_ms": float(t.min()),
            "max_ms": float(t.max())}


def walk_summary(series: dict) -> dict:
    out = {**summary(series["cull_ms"]), "frames": len(series["cull_ms"]),
           "tests_per_frame": float(np.mean(series["tests"])),
           "nodes_per_frame": float(np.mean(series["pairs"]))}
    if "refit_ms" in series:
        out["update"] = summary(series["refit_ms"])  # move_nodes: the move and the refit
    return out


def leaf_pairs(session: Session, frame) -> list[np.ndarray]:
    """Per tile, the sorted leaf ids one frame's culling sends to it."""
    vis = session.frame(frame).visibility
    return [vis.tile_leaves(t) for t in range(session.wall.tiles)]


class Oracle:
    """The exact oracle's verdicts, memoized per (pose, tile, leaf) and shared by every bound
    type and method culled in that pose: a (leaf, tile) pair is a false positive when the
    leaf's triangles do not meet the tile frustum grown by the contract's tolerance, exactly as
    :func:`wallcull.oracle.false_positives` decides it."""

    def __init__(self, scene: Scene, wall: Wall):
        self.scene, self.wall, self.wall_dict = scene, wall, wall.to_dict()
        self.extent = float(np.ptp(scene.box, axis=0).max())
        self._meets: dict = {}
        self._tris: dict = {}
        self._planes: dict = {}
        m = scene.meshes
        self.leaf_bytes = np.zeros(len(scene), dtype=np.int64)
        used = scene.mesh_of[scene.leaves]
        self.leaf_bytes[scene.leaves] = (m.vertex_count[used] * VERTEX_BYTES
                                         + m.face_count[used] * TRIANGLE_BYTES)

    def false_pairs(self, key, frame, reported: list[np.ndarray], world=None) -> dict:
        """Count the false positives among ``reported[t]`` (leaf ids of tile ``t``) for one
        frame. ``key`` names the frame and the scene's pose (``world`` transforms, the rest
        pose if ``None``): verdicts are reused across calls with the same key."""
        fd = frame.to_dict()
        tol = 1e-7 * max(self.extent, float(np.linalg.norm(frame.position)))
        false = total = geometry = 0
        for t, leaves in enumerate(reported):
            pk = (key, t)
            if pk not in self._planes:
                self._planes[pk] = oracle.tile_frusta(self.wall_dict, fd, t, -tol)
            planes = self._planes[pk]
            for leaf in leaves.tolist():
                k = (key, t, leaf)
                meets = self._meets.get(k)
                if meets is None:
                    tk = (key, leaf)
                    if tk not in self._tris:
                        self._tris[tk] = oracle.leaf_triangles_display(self.scene, fd, leaf, world)
                    meets = self._meets[k] = oracle.meets(self._tris[tk], planes)
                total += 1
                if not meets:
                    false += 1
                    geometry += int(self.leaf_bytes[leaf])
        return {"false_positives": false, "reported": total, "geometry_bytes": geometry}


def accuracy_sum(parts: Iterable[dict], frames: int) -> dict:
    """Sum :meth:`Oracle.false_pairs` over frames: rate, and bytes per frame."""
    parts = list(parts)
    false = sum(p["false_positives"] for p in parts)
    total = sum(p["reported"] for p in parts)
    geometry = sum(p["geometry_bytes"] for p in parts)
    return {"false_positives": false, "reported": total, "frames": frames,
            "rate": false / total if total else 0.0,
            "packet_bytes_per_frame": false * ID_BYTES / frames,
            "reported_packet_bytes_per_frame": total * ID_BYTES / frames,
            "geometry_bytes_per_frame": geometry / frames}


# --------------------------------------------------------------------------- output


def rounded(series, digits: int = 4) -> list:
    return [round(float(x), digits) for x in series]


def table(header: list[str], rows: list[list], align: str | None = None) -> str:
    """A markdown table; ``align`` is one character per column, ``l`` or ``r``."""
    align = align or "l" + "r" * (len(header) - 1)
    marks = ["---" if a == "l" else "---:" for a in align]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(marks) + " |"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def ms(x: float) -> str:
    """Milliseconds to three significant digits or so."""
    return f"{x:.3f}" if x < 1 else f"{x:.2f}" if x < 10 else f"{x:.1f}"


def pct(x: float) -> str:
    return f"{100 * x:.2f}%"


def nbytes(x: float) -> str:
    for unit, size in (("MB", 1e6), ("kB", 1e3)):
        if x >= size:
            return f"{x / size:.1f} {unit}"
    return f"{x:.0f} B"


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only, no display)."""
    matplotlib = optional("matplotlib", "experiments", "wallcull experiment")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: One colour and marker per method, the same in every plot.
METHOD_STYLE = {"naive": ("tab:gray", "x"), "oh": ("tab:blue", "s"), "fh": ("tab:orange", "^"),
                "adaptive": ("tab:green", "o")}
METHOD_LABEL = {"naive": "naive", "oh": "OH without FH (oh)", "fh": "FH without OH (fh)",
                "adaptive": "adaptive OH+FH"}


