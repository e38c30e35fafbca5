"""A picture of a wall: every tile rendered from its own culled list and fitted frusta, by the
real OpenGL renderer, laid out with the wall's bezels. The README's picture comes from here:

    python -m wallcull_clients.picture powerplant --wall examples/wall-4x4.json --out docs/wall.png
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from wallcull.fit import FitOptions
from wallcull.paths import scene_path
from wallcull.pipeline import Session
from wallcull.scene import load
from wallcull.wall import Wall

from .render import TileRenderer


def wall_picture(scene_spec: str, wall: Wall, frame_index: int = 30, path: str = "orbit",
                 pixels: int = 240) -> np.ndarray:
    """``(H, W, 3)`` uint8: the wall's tiles, each ``pixels`` wide, bezels in dark grey."""
    scene = load(scene_spec)
    frame = scene_path(scene, wall, path, PATH_FRAMES)[frame_index]
    result = Session(scene, wall, fit=FitOptions()).frame(frame)
    w_px = pixels
    h_px = int(round(pixels * wall.tile_size[1] / wall.tile_size[0]))
    scale = w_px / wall.tile_size[0]  # pixels per metre, so that the bezels keep their size
    gx, gy = (max(0, int(round(g * scale))) for g in wall.gap)
    out = np.full((wall.rows * h_px + (wall.rows - 1) * gy,
                   wall.cols * w_px + (wall.cols - 1) * gx, 3), 12, dtype=np.uint8)
    renderer = TileRenderer(w_px, h_px)
    uploaded = set()
    for t in range(wall.tiles):
        draws = []
        ranges = dict(result.visibility.draw_ranges().tile(t))  # leaves shown in part
        for leaf in result.visibility.tile_leaves(t):
            key = scene.geometry[leaf]
            if key not in uploaded:
                renderer.upload(key, *scene.leaf_mesh(leaf),  # (glTF's sides, as a node)
                                single_sided=bool(scene.meshes.single_sided[scene.mesh_of[leaf]]))
                uploaded.add(key)
            draws.append((key, scene.world[leaf], int(leaf) + 1, ranges.get(int(leaf))))
        fit = result.fits[t]
        image = renderer.render(draws, np.asarray(fit["view"]), np.asarray(fit["projection"]))
        r, c = divmod(t, wall.cols)
        y, x = r * (h_px + gy), c * (w_px + gx)
        out[y:y + h_px, x:x + w_px] = image.color[:, :, :3]
    renderer.release()
    return out


#: Frames of the orbit path a picture is taken from.
PATH_FRAMES = 120


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m wallcull_clients.picture",
        description="A picture of a wall: every tile drawn by the OpenGL tile renderer from its "
                    "own culled list and fitted frusta, laid out with the wall's bezels.")
    p.add_argument("scene", nargs="?", default="powerplant")
    p.add_argument("--wall", default="examples/wall-4x4.json",
                   help="WALL.json, or the JSON inline: a grid of tiles")
    p.add_argument("--frame", type=int, default=30,
                   help=f"frame of the orbit path (0 to {PATH_FRAMES - 1})")
    p.add_argument("--pixels", type=int, default=240, help="width of one tile, pixels")
    p.add_argument("--out", default="wall.png")
    args = p.parse_args(argv)
    if not 0 <= args.frame < PATH_FRAMES or not 1 <= args.pixels <= 4096:
        p.error(f"--frame must be 0 to {PATH_FRAMES - 1} and --pixels 1 to 4096")
    from PIL import Image

    from wallcull.documents import read_json
    from wallcull.errors import InputError

    try:
        wall = Wall.from_dict(read_json(args.wall, "--wall"))
        if wall.kind != "grid":
            raise InputError("a picture lays out a grid of tiles; this wall is screens")
        if not os.path.isdir(os.path.dirname(os.path.abspath(args.out))):
            raise InputError(f"no folder for {args.out}")
        picture = wall_picture(args.scene, wall, args.frame, pixels=args.pixels)
        Image.fromarray(picture).save(args.out)
    except (InputError, OSError) as exc:
        print(f"picture: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
