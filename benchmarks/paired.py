"""Two versions of the code on the same frames in one process, frame by frame in turn: a
stage's time under the working tree against under a git revision, paired so that both see the
same load (this 2-core machine is shared: medians of separate runs move by a fifth from one
minute to the next, a ratio of paired frames by a few hundredths).

    python benchmarks/paired.py REV [--settings SETTINGS.json] [--path orbit|fly]
        [--frames 200] [--stage fit|cull|occlude|total] [--occlusion on|auto]
        [--wall WALL.json] [--scene powerplant] [--stereo IPD]

``REV``'s ``wallcull`` package is extracted once (``git archive``) as ``wallcull_base`` into
``$WALLCULL_CACHE/paired/`` (default ``~/.cache/wallcull``), where its compiled kernels are
kept for the next run. Prints both medians, the median of the paired ratios and the ratio of
the means (each working tree over ``REV``); below 1 is faster, over the frames where the stage ran on both
sides (``frames_paired``). ``total`` is the session's stages (cull, occlusion, leaf lists,
fits), not the encoding. Both sides must make the same frames of the path. With ``--stereo``
the path's frames are stereo frames of that interpupillary distance. The fit stage also
reports the leaves the tiles' mirror passes list a frame, ``REV``'s then the working tree's.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tarfile
from io import BytesIO
from pathlib import Path

import numpy as np
from _cli import count  # beside this file
from wallcull_clients.driver import ipd

ROOT = Path(__file__).resolve().parent.parent


def base_package(rev: str) -> Path:
    """A folder holding ``REV``'s ``wallcull`` as the package ``wallcull_base``."""
    found = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"],
                           cwd=ROOT, capture_output=True, text=True)
    if found.returncode:
        raise ValueError(f"unknown revision {rev!r} (no commit of this checkout)")
    sha = found.stdout.strip()
    cache = Path(os.environ.get("WALLCULL_CACHE", Path.home() / ".cache" / "wallcull"))
    folder = cache / "paired" / sha
    if not (folder / "wallcull_base").is_dir():
        archive = subprocess.run(["git", "archive", sha, "wallcull"], cwd=ROOT, check=True,
                                 capture_output=True).stdout
        tmp = folder.with_suffix(".part")
        shutil.rmtree(tmp, ignore_errors=True)
        with tarfile.open(fileobj=BytesIO(archive)) as tar:
            tar.extractall(tmp, filter="data")
        (tmp / "wallcull").rename(tmp / "wallcull_base")
        tmp.rename(folder)
    return folder


def session(package: str, args, settings):
    """A session of ``package`` (``wallcull`` or ``wallcull_base``) and its frames."""
    import importlib

    def mod(name):
        return importlib.import_module(f"{package}.{name}")

    with open(args.wall) as f:
        wall = mod("wall").Wall.from_dict(json.load(f))
    scene = mod("scene").load(args.scene, settings=settings)
    frames = mod("paths").scene_path(scene, wall, args.path, args.frames)
    if args.stereo:
        Frame = mod("wall").Frame
        frames = [Frame.from_dict({**f.to_dict(), "stereo": {"ipd": args.stereo}}, wall)
                  for f in frames]
    occlusion = mod("occlude").OcclusionOptions.parse(args.occlusion) if args.occlusion \
        else None
    s = mod("pipeline").Session(scene, wall, "adaptive", "obb", False,
                                mod("fit").FitOptions(), occlusion=occlusion)
    for frame in frames[:5]:  # compiled, caches warm
        s.frame(frame)
    return s, frames


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("rev")
    p.add_argument("--settings")
    p.add_argument("--path", choices=("orbit", "fly"), default="orbit")
    p.add_argument("--frames", type=count(1), default=200)
    p.add_argument("--stage", choices=("fit", "cull", "occlude", "total"), default="fit")
    p.add_argument("--occlusion", choices=("on", "auto"))
    p.add_argument("--wall", default=str(ROOT / "examples" / "wall-8x8.json"))
    p.add_argument("--scene", default="powerplant")
    p.add_argument("--stereo", type=ipd, help="interpupillary distance, m: stereo frames")
    args = p.parse_args()
    if args.stage == "occlude" and not args.occlusion:
        p.error("--stage occlude needs --occlusion on or auto (without it nothing is timed)")
    settings = None
    if args.settings:
        with open(args.settings) as f:
            settings = json.load(f)
    try:
        sys.path.insert(0, str(base_package(args.rev)))
    except ValueError as exc:
        p.error(str(exc))
    pairs = [session("wallcull_base", args, settings), session("wallcull", args, settings)]
    poses = [np.array([np.r_[f.position, f.orientation] for f in frames[:args.frames]])
             for _, frames in pairs]
    if poses[0].shape != poses[1].shape or not np.array_equal(*poses):
        sys.exit(f"paired.py: {args.rev} makes other frames of the {args.path} path than the "
                 "working tree (its paths or scene loading differ): no pairs to compare")
    key = f"{args.stage}_ms"
    times, mirrored = [[], []], [0, 0]
    for k in range(args.frames):
        for which in ((0, 1) if k % 2 else (1, 0)):  # who goes first alternates
            s, frames = pairs[which]
            result = s.frame(frames[k])
            timings = result.timings
            times[which].append(sum(v for n, v in timings.items() if n.endswith("_ms"))
                                if args.stage == "total" else timings.get(key, 0.0))
            if args.stage == "fit":
                mirrored[which] += sum(len(m.visible) for m in result.fits.mirrors)
    base, new = np.array(times[0]), np.array(times[1])
    ran = (base > 0) & (new > 0)  # a stage skipped on a frame (occlusion's auto) is no pair
    if not ran.any():
        sys.exit(f"paired.py: the {args.stage} stage ran on none of the {args.frames} frames "
                 "on both sides")
    base, new = base[ran], new[ran]
    ratio = new / base
    print(json.dumps({"rev": args.rev, "stage": args.stage, "frames": args.frames,
                      "frames_paired": int(ran.sum()),
                      "base_median_ms": round(float(np.median(base)), 3),
                      "new_median_ms": round(float(np.median(new)), 3),
                      "paired_ratio_median": round(float(np.median(ratio)), 3),
                      "ratio_of_means": round(float(new.mean() / base.mean()), 3),
                      **({"mirror_leaves_per_frame": [round(m / args.frames, 1)
                                                      for m in mirrored]}
                         if args.stage == "fit" else {})},
                     allow_nan=False))


if __name__ == "__main__":
    main()
