"""``wallcull experiment NAME``: reproduce the paper's figures and measure the speed-for-accuracy
trade, with the product's own pieces (scene loading, sessions, camera paths, the oracle).

Each experiment is a function ``run(ctx) -> (data, markdown)`` in the :data:`REGISTRY`; the
runner writes ``NAME.json`` (``data`` plus how it ran), the PNGs the experiment saved through
``ctx.savefig``, and ``NAME.md`` (the markdown, the plots linked, and how to reproduce it).
``all`` runs every registered experiment in order and assembles ``BENCHMARKS.md`` from the
fragments.

To add an experiment, write a module here with ``run(ctx: Context) -> tuple[dict, str]`` and add
one line to :data:`REGISTRY`; ``all`` and the command line pick it up.
"""

from __future__ import annotations

import importlib
import os
import re
import time
from contextlib import nullcontext
from pathlib import Path

from ..errors import InputError, optional
from .context import ROOT, Context, Experiment, loadavg, machine, progress_bar, write_json


def _module(name: str) -> Experiment:
    """``wallcull.experiments.<name>.run``, imported when it runs (the parser stays light)."""
    def run(ctx: Context) -> tuple[dict, str]:
        return importlib.import_module(f"{__name__}.{name}").run(ctx)

    run.__name__ = name
    return run


#: name -> experiment, in the order ``all`` runs them: the extension point. An experiment is any
#: ``run(ctx: Context) -> (data, markdown)``.
REGISTRY: dict[str, Experiment] = {
    "fig4": _module("fig4"),
    "fig5": _module("fig5"),
    "fig6": _module("fig6"),
    "bounds": _module("bounds"),
    "real": _module("real"),
    "frusta": _module("frusta"),
    "frame": _module("frame"),
    "walls": _module("walls"),
    "clusters": _module("clusters"),
    "occluders": _module("occluders"),
    "scale": _module("scale"),
}

DEFAULT_OUT = "docs/experiments"
REPORT = "BENCHMARKS.md"

INTRO = """\
# Benchmarks

Every table and plot on this page is produced by `wallcull experiment all`, which runs the
experiments below and writes this page from their fragments (`docs/experiments/NAME.md`, with the
raw numbers in `NAME.json` beside them). Nothing here is edited by hand: to change the text, change
`wallcull/experiments/`, then run the command again. A single `wallcull experiment NAME`
rewrites its own files in `docs/experiments/`, not this page: until `all` runs again, the page
shows that experiment's new plots beside its old tables.

The experiments follow section 5 of Nirnimesh, Harish and Narayanan, *Culling an Object Hierarchy
to a Frustum Hierarchy* (2006): its Figs. 4, 5 and 6, then what the paper does not measure, the
accuracy each bound type buys (false positives against the exact oracle of `wallcull/oracle.py`)
and the third-party scenes of `scenes/`. Every number is the product's: scenes come from
`wallcull.scene.load`, frames from `wallcull.paths.camera_path`, and each frame is culled by a
`wallcull.pipeline.Session`, whose `timings["cull_ms"]` is the time reported (the frame's planes,
the first-level cull and the traversal, down to per-tile lists), after three warm-up frames.
Configurations compared with each other (the four methods on one wall, say) are timed in turns,
40 frames at a time, so that a slow spell of the shared machine falls on all of them alike.

**How these numbers differ from the paper's, and why.** The paper ran C++ over an OpenSceneGraph
scene graph on 2006 hardware; this is Python with the traversals compiled by numba over flat
arrays, on a 2-core virtual machine shared with other work, so absolute times are an order of
magnitude or more below the paper's and carry some noise (the load average is recorded with each
run). The scenes are seeded look-alikes of the paper's models with the same node counts and
branching (see `scenes/`), not the models themselves. And our `oh` is the strong form of the
common approach: it starts from the first-level cull's roots and masks planes (Assarsson and
Moller), so the gap between `oh` and adaptive on small walls is smaller than the paper's 14 ms
against 5 ms; it opens up as the wall grows, as the paper's Fig. 5 says. Each section ends with
its own comparison.
"""


def register(subparsers) -> None:
    """Add the ``experiment`` subcommand to the ``wallcull`` parser."""
    q = subparsers.add_parser("experiment", help="run an experiment of docs/BENCHMARKS.md")
    q.add_argument("name", choices=[*REGISTRY, "all"], metavar="NAME",
                   help=f"one of {', '.join(REGISTRY)}, or all (then {REPORT} is written)")
    q.add_argument("--out", default=None,
                   help=f"output folder for JSON, PNG and markdown (default: the project's "
                        f"{DEFAULT_OUT}/)")
    q.add_argument("--quick", action="store_true",
                   help="a tiny version, for the test suite (needs --out)")
    q.add_argument("--seed", type=int, default=0, help="seed of every random choice")
    q.add_argument("--scenes", default=None,
                   help="folder of the third-party scenes (default: the project's scenes/)")
    q.add_argument("--report", default=None,
                   help=f"where `all` writes {REPORT} (default: the project's docs/{REPORT} "
                        f"with the default --out, else inside --out)")
    q.set_defaults(func=cmd_experiment)


def cmd_experiment(args) -> int:
    for module in ("matplotlib", "scipy", "psutil"):  # refused before any work, not midway
        optional(module, "experiments", "wallcull experiment")
    if not (ROOT / "examples").is_dir():
        raise InputError("wallcull experiment runs in a checkout of the repository (it reads "
                         "its examples/ and scenes/): run it from one, or install one with "
                         "pip install -e")
    if args.seed < 0:
        raise InputError(f"--seed must be 0 or more, got {args.seed}")
    if args.quick and not args.out:
        raise InputError(f"--quick needs --out DIR: a quick run would replace the published "
                         f"{DEFAULT_OUT}/ pages with its tiny numbers")
    if args.report and args.name != "all":
        raise InputError(f"--report is where `all` writes {REPORT}: one experiment writes its "
                         f"fragment, {args.name}.md, into --out")
    out = Path(args.out) if args.out else ROOT / DEFAULT_OUT
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file, not a folder")
    try:  # refused before any work, not after it
        out.mkdir(parents=True, exist_ok=True)
        if not os.access(out, os.W_OK):
            raise PermissionError(13, "Permission denied")
    except OSError as exc:
        raise InputError(f"cannot write into --out {out}: {exc.strerror or exc}") from None
    scenes = Path(args.scenes) if args.scenes else None
    if args.name == "all":
        report = Path(args.report) if args.report else (
            ROOT / "docs" / REPORT if args.out is None else out / REPORT)
        run_all(out, quick=args.quick, seed=args.seed, scenes_dir=scenes, report=report)
    else:
        run(args.name, out, quick=args.quick, seed=args.seed, scenes_dir=scenes)
    return 0


def command(name: str, quick: bool, seed: int, out: Path | None = None,
            scenes: Path | None = None) -> str:
    """The command line that runs it again: with ``--out`` and ``--scenes`` when they were
    not the project's (a quick run needs its ``--out``)."""
    mine = out is not None and Path(out).resolve() != (ROOT / DEFAULT_OUT).resolve()
    return ("wallcull experiment " + name + (" --quick" if quick else "")
            + (f" --seed {seed}" if seed else "") + (f" --out {out}" if mine else "")
            + (f" --scenes {scenes}" if scenes is not None else ""))


def run(name: str, out: Path, quick: bool = False, seed: int = 0, scenes_dir: Path | None = None,
        progress: bool = True) -> dict:
    """Run one experiment into ``out``; returns what ``NAME.json`` holds."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ctx = Context(name, out, quick=quick, seed=seed)
    if scenes_dir is not None:
        ctx.scenes_dir = Path(scenes_dir)
    load_before = loadavg()
    t0 = time.perf_counter()
    with (progress_bar() if progress else nullcontext()) as bar:
        ctx.progress = bar
        data, md = REGISTRY[name](ctx)
    seconds = time.perf_counter() - t0
    meta = {"experiment": name, "seed": seed, "quick": quick, "wall_clock_s": seconds,
            "command": command(name, quick, seed, out, scenes_dir), "machine": machine(),
            "loadavg_before": load_before, "loadavg_after": loadavg(), "plots": ctx.plots}
    result = {**meta, "results": data}
    write_json(out / f"{name}.json", result)
    missing = [p for p in ctx.plots if f"({p})" not in md]
    for p in missing:  # every plot is shown, even if the experiment's text forgot one
        md += f"\n![{p}]({p})\n"
    md = (md.rstrip() + f"\n\nReproduce: `{meta['command']}` (ran in {seconds:.0f} s; raw "
          f"numbers in [`{name}.json`]({name}.json)).\n")
    (out / f"{name}.md").write_text(md)
    return result


def run_all(out: Path, quick: bool = False, seed: int = 0, scenes_dir: Path | None = None,
            report: Path | None = None, progress: bool = True) -> dict:
    """Every registered experiment, then ``BENCHMARKS.md`` assembled from their fragments."""
    out = Path(out)
    report = Path(report) if report else out / REPORT
    t0 = time.perf_counter()
    results = {name: run(name, out, quick, seed, scenes_dir, progress) for name in REGISTRY}
    total = time.perf_counter() - t0
    summary = {"seed": seed, "quick": quick, "total_s": total, "machine": machine(),
               "experiments": {n: r["wall_clock_s"] for n, r in results.items()}}
    write_json(out / "all.json", summary)
    report.parent.mkdir(parents=True, exist_ok=True)
    report.write_text(assemble(out, report, results, summary))
    return summary


def assemble(out: Path, report: Path, results: dict, summary: dict) -> str:
    """The report: intro, machine, how to reproduce, then each fragment with its links made
    relative to the report."""
    import os

    rel = Path(os.path.relpath(out.resolve(), report.parent.resolve())).as_posix()
    prefix = "" if rel == "." else rel + "/"
    m = summary["machine"]
    loads = [r["loadavg_before"] for r in results.values() if r.get("loadavg_before")]
    fragments = {name: (out / f"{name}.md").read_text() for name in results}
    parts = [INTRO]
    parts.append(
        "## Machine and how to reproduce\n\n"
        f"{m['cores']} cores ({m['cpu']}), {m['system']}; Python {m['python']}, numpy "
        f"{m['numpy']}, numba {m['numba']}, scipy {m['scipy']}, trimesh {m['trimesh']}."
        + (f" Load average (1 min) before each experiment: "
           f"{', '.join(str(x[0]) for x in loads)}." if loads else "") + "\n\n"
        "From the root of a checkout installed as the README says (`pip install -e "
        "'.[test]'` in its virtual environment, which brings matplotlib):\n\n"
        "    " + command("all", summary["quick"], summary["seed"], out)
        + f"      # everything, {summary['total_s'] / 60:.1f} min here\n\n"
        + "\n".join(f"    {r['command']}" for r in results.values()) + "\n\n"
        + "| experiment | wall-clock |\n| --- | ---: |\n"
        + "".join(f"| [{n}](#{_anchor(fragments[n], n)}) | {s:.0f} s |\n"
                  for n, s in summary["experiments"].items())
        + f"| **total** | **{summary['total_s']:.0f} s** |\n")
    for text in fragments.values():
        text = re.sub(r"\]\((?!https?:|#|/)([^)]+)\)", lambda mt: f"]({prefix}{mt.group(1)})", text)
        parts.append(text)
    return "\n".join(p.rstrip() + "\n" for p in parts)


def _anchor(markdown: str, default: str) -> str:
    """GitHub's anchor of a fragment's first ``##`` heading."""
    for line in markdown.splitlines():
        if line.startswith("## "):
            text = re.sub(r"[^\w\- ]", "", line[3:].strip().lower())
            return text.replace(" ", "-")
    return default
