"""Checks of the numbers in what users send (walls, screens, frames, settings): one-line
errors that name the value, and the ranges float64 geometry stays meaningful in."""

from __future__ import annotations

import math
from typing import Any

from .errors import InputError

#: The largest wall accepted (tiles). 64 x 64 is the largest wall the project is built for;
#: the limit leaves room above it while refusing requests that could only exhaust memory.
MAX_TILES = 1 << 16

#: Relative tolerance on the norm of a frame's quaternion (SPEC section 3).
QUATERNION_TOLERANCE = 1e-6

#: The ranges float64 geometry stays meaningful in (beyond them the matrices sent to clients
#: would overflow or lose every digit): lengths of the wall, m; and world coordinates.
MIN_LENGTH, MAX_LENGTH = 1e-9, 1e9
MAX_COORDINATE = 1e15

WALL_DEFAULTS = {"gap": (0.0, 0.0), "near": 0.1, "far": 1000.0, "resolution": (1920, 1080)}
WALL_KEYS = {"cols", "rows", "tile_size", "gap", "distance", "near", "far", "resolution"}


def as_number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{what} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise InputError(f"{what} must be finite, got {value!r}")
    return value


def as_vector(value: Any, n: int, what: str) -> tuple[float, ...]:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise InputError(f"{what} must be a list of {n} numbers, got {value!r}")
    return tuple(as_number(v, f"{what}[{i}]") for i, v in enumerate(value))


def as_count(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            raise InputError(f"{what} must be a whole number, got {value!r}")
    if value < 1:
        raise InputError(f"{what} must be at least 1, got {value}")
    return value


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
        if last >= limit or first > last:
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
