"""The ranges float64 geometry stays meaningful in, which the documents users send are held to
(:mod:`wallcull.documents`), and tile lists in their short form (``0-3,8``)."""

from __future__ import annotations

from .errors import InputError

#: The largest wall accepted (tiles). 64 x 64 is the largest wall the project is built for;
#: the limit leaves room above it while refusing requests that could only exhaust memory.
MAX_TILES = 1 << 16

#: The largest frame number (2**53: the last integer every JSON client reads exactly).
MAX_FRAME = 1 << 53

#: Relative tolerance on the norm of a frame's quaternion (SPEC section 3).
QUATERNION_TOLERANCE = 1e-6

#: The ranges float64 geometry stays meaningful in (beyond them the matrices sent to clients
#: would overflow or lose every digit): lengths of the wall, m; and world coordinates.
MIN_LENGTH, MAX_LENGTH = 1e-9, 1e9
MAX_COORDINATE = 1e15

#: The deepest node tree a scene file may have (edges from a root to its deepest node). Real
#: scene graphs are tens deep; the hierarchy is built, and moved nodes refit, level by level,
#: so a chain of 200,000 nodes took minutes to load and a 20,000-deep one 0.2 s a frame to move.
MAX_DEPTH = 1000

#: Occlusion culling's dials (docs/occlusion.md): occluder triangles a frame, at most; the
#: buffer's texels across one tile (or screen), at least and at most.
MAX_OCCLUDER_TRIANGLES = 10_000_000
MIN_TEXELS, MAX_TEXELS = 2, 512

#: The least a tile may span of its distance from the eye. At 1e-10 its edges seen from the
#: eye are 450,000 ulps apart, and its corners land within about 2e-6 of NDC's (a 25th of a
#: pixel of a 16k tile); a tile a few ulps wide from there would be projected as noise, or
#: with a division by zero.
RESOLVABLE = 1e-10


def check_resolvable(eye, size: float, distance: float, which: str,
                     what: str) -> None:
    """InputError unless ``size`` (a tile's least side) spans at least :data:`RESOLVABLE` of
    ``distance`` (its farthest corner's from ``eye``)."""
    if not size >= RESOLVABLE * distance:
        raise InputError(f"{what} {[round(float(v), 9) for v in eye]} is {distance:.3g} m from "
                         f"{which} {size:.3g} m across: too far for float64 to tell its edges "
                         f"apart (a tile must span at least {RESOLVABLE:g} of its distance "
                         f"from the eye)")


def parse_tiles(spec: str, count: int | None = None) -> list[int]:
    """``"0-63"``, ``"0,2,5-7"`` or ``"all"`` (needs ``count``) to sorted tile ids, each below
    ``count`` (or ``MAX_TILES``)."""
    spec = spec.strip()
    limit = MAX_TILES if count is None else count
    if spec == "all":
        if count is None:
            raise InputError("'all' tiles needs the wall's tile count")
        return list(range(count))
    out: set[int] = set()
    for part in spec.split(","):
        lo, dash, hi = part.strip().partition("-")
        if not lo.isdigit() or (dash and not hi.isdigit()) or len(lo) > 6 or len(hi) > 6:
            raise InputError(f"bad tile range {part!r}: use N, N-M, or a comma list of them")
        first, last = int(lo), int(hi or lo)
        if first > last:
            raise InputError(f"tile range {part.strip()!r} runs backwards: write it "
                             f"{last}-{first}")
        if last >= limit:
            raise InputError(f"tiles {part.strip()!r} are not tiles of this wall "
                             f"(0-{limit - 1})")
        out.update(range(first, last + 1))
    if not out:
        raise InputError("no tiles given")
    return sorted(out)


def tiles_text(tiles) -> str:
    """Sorted tile ids in the short form :func:`parse_tiles` reads: ``[0, 1, 2, 5]`` ->
    ``"0-2,5"``."""
    tiles = [int(t) for t in tiles]
    parts, k = [], 0
    while k < len(tiles):
        j = k
        while j + 1 < len(tiles) and tiles[j + 1] == tiles[j] + 1:
            j += 1
        parts.append(str(tiles[k]) if j == k else f"{tiles[k]}-{tiles[j]}")
        k = j + 1
    return ",".join(parts)
