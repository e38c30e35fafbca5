"""The documents users write: a wall (SPEC section 2, or 2b's screens), a frame (section 3) and
a scene's settings (lights, mirrors), as pydantic models. One validator for every door: the
command line reads them here (:func:`parse`, one line of error), the server validates its
bodies with the same models, and its OpenAPI and AsyncAPI schemas are theirs.

The schema says what it can: types (strict: ``true`` is not a number, ``"7"`` is not a number,
``7.5`` is not an integer), ranges, lengths, no unknown keys. The models' validators add what
JSON Schema cannot say: that an orientation is a *unit* quaternion, ``near < far``, ``gap >
-tile_size``, screens that are rectangles, a spot light's direction, a
mirror's outline in its plane. What needs the wall too (an eye in front of every screen) is
checked where frame meets wall, :meth:`wallcull.wall.Frame.make`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Union

import numpy as np
from pydantic import (AllowInfNan, BaseModel, BeforeValidator, ConfigDict, Discriminator, Field,
                      Strict, Tag, TypeAdapter, ValidationError, field_validator,
                      model_validator)
from pydantic_core import PydanticCustomError

from .errors import InputError
from .validate import (MAX_COORDINATE, MAX_LENGTH, MAX_OCCLUDER_TRIANGLES, MAX_TEXELS,
                       MAX_TILES, MIN_LENGTH, MIN_TEXELS, QUATERNION_TOLERANCE)


def _whole(value):
    """JSON Schema's integers: ``7`` and ``7.0`` (a number with no fraction), never ``true``."""
    if isinstance(value, float) and value.is_integer() and abs(value) < 2.0 ** 63:
        return int(value)
    return value


def Int(**bounds) -> Any:
    """An integer within ``bounds`` (``ge``, ``le``, ``lt``); never a bool or a string. (The
    bounds go inside, next to the type, so that the schema states them as minimum/maximum.)"""
    return Annotated[int, Strict(), Field(**bounds), BeforeValidator(_whole)]


def Vector(n: int, item: Any) -> Any:
    """A list of exactly ``n`` items, as a tuple (its schema: an array of ``n`` items, in the
    words of every JSON Schema draft)."""
    def length(value):
        if not isinstance(value, (list, tuple)) or len(value) != n:
            raise PydanticCustomError("vector", "must be a list of {n} numbers, got {value}",
                                      {"n": n, "value": _short(value)})
        return value
    return Annotated[tuple[item, ...], Field(min_length=n, max_length=n),
                     BeforeValidator(length)]


#: A number: an integer or a float, finite; never a bool or a string.
Num = Annotated[float, Strict(), AllowInfNan(False)]
Bool = Annotated[bool, Strict()]
Coordinate = Annotated[Num, Field(ge=-MAX_COORDINATE, le=MAX_COORDINATE)]
Length = Annotated[Num, Field(ge=MIN_LENGTH, le=MAX_LENGTH)]
Offset = Annotated[Num, Field(ge=-MAX_LENGTH, le=MAX_LENGTH)]
#: A quaternion's component: a unit quaternion's, within the norm's tolerance
Unit = Annotated[Num, Field(ge=-1 - QUATERNION_TOLERANCE, le=1 + QUATERNION_TOLERANCE)]
Vec3 = Vector(3, Coordinate)
Point = Vector(3, Offset)  # display space, meters
Quaternion = Vector(4, Unit)
Pixels = Int(ge=1, le=1 << 16)
Resolution = Vector(2, Pixels)
#: Each of cols and rows: their product is at most 65,536 (``MAX_TILES``).
Count = Int(ge=1, le=256)
#: at most 10^6 m: the eye must be farther than ``near - distance`` in front of the wall, and
#: an eye is at most 10^9 m from the display's origin
Near = Annotated[Num, Field(gt=0, le=1e6)]
Far = Annotated[Num, Field(gt=0, le=MAX_COORDINATE)]
NodeName = Annotated[str, Strict(), Field(min_length=1, max_length=1024)]


class Document(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _refuse(kind: str, text: str) -> PydanticCustomError:
    """Our validators' errors, their text complete (``kind`` names them in the schema's
    vocabulary of error types)."""
    return PydanticCustomError(kind, text.replace("{", "(").replace("}", ")"))


def _depth_range(near: float, far: float) -> None:
    if not near < far:
        raise _refuse("near_far", f"needs 0 < near < far, got near={near}, far={far}")


class WallSpec(Document):
    """A wall (SPEC section 2): ``cols x rows`` tiles (at most 256 x 256) of ``tile_size``
    meters, ``gap`` apart (negative: projectors that overlap, by less than a tile), in the plane
    ``z = -distance``."""

    cols: Count
    rows: Count
    tile_size: Vector(2, Length)
    gap: Vector(2, Offset) = (0.0, 0.0)
    distance: Length
    near: Near = 0.1
    far: Far = 1000.0
    resolution: Resolution = (1920, 1080)

    @model_validator(mode="after")
    def _consistent(self):
        (w, h), (gx, gy) = self.tile_size, self.gap
        if gx <= -w or gy <= -h:
            raise _refuse("gap", f"gap {[gx, gy]} overlaps a whole tile; it must exceed "
                          "-tile_size")
        _depth_range(self.near, self.far)
        return self


#: Screens whose edges meet at a right angle within this (relative) are rectangles.
RIGHT_ANGLE = 1e-6


class ScreenSpec(Document):
    """One screen of a wall given screen by screen (SPEC section 2b): three corners in display
    space (the edges perpendicular, within 1e-6 relative), seen from the side its normal
    ``(bottom_right - bottom_left) x (top_left - bottom_left)`` points to."""

    bottom_left: Point
    bottom_right: Point
    top_left: Point
    resolution: Resolution = (1920, 1080)

    @model_validator(mode="after")
    def _rectangle(self):
        bl, br, tl = (np.array(c) for c in (self.bottom_left, self.bottom_right, self.top_left))
        u, v = br - bl, tl - bl
        width, height = np.linalg.norm(u), np.linalg.norm(v)
        scale = max(width, height, np.abs(bl).max(), 1e-300)
        if not (width > 1e-9 * scale and height > 1e-9 * scale):
            raise _refuse("degenerate", "is degenerate: each edge must be longer than 1e-9 of "
                          f"the largest of its edges and its corner's coordinates ({scale:g} m), "
                          f"got {width:g} x {height:g} m")
        if abs(u @ v) > RIGHT_ANGLE * width * height:
            angle = math.degrees(math.acos(np.clip(u @ v / width / height, -1, 1)))
            raise _refuse("rectangle", "is not a rectangle: its bottom and left edges meet at "
                          f"{angle:.6g} degrees, not 90")
        return self


class ScreensSpec(Document):
    """A wall given screen by screen (SPEC section 2b): CAVEs, cylinders, angled walls. Tile
    ids are indices in ``screens``."""

    screens: list[ScreenSpec] = Field(min_length=1, max_length=MAX_TILES)
    near: Near = 0.1
    far: Far = 1000.0

    @model_validator(mode="after")
    def _consistent(self):
        _depth_range(self.near, self.far)
        return self


def _wall_kind(value) -> str:
    return "screens" if isinstance(value, dict) and "screens" in value else "grid"


#: A wall in either form: a grid (section 2), or screens (section 2b) when it lists ``screens``.
Wall = Annotated[Union[Annotated[WallSpec, Tag("grid")], Annotated[ScreensSpec, Tag("screens")]],
                 Discriminator(_wall_kind)]


def _unit_quaternion(cls, value):
    norm = math.sqrt(sum(c * c for c in value))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise _refuse("quaternion", f"{list(value)} is not a unit quaternion (norm {norm:.9g})")
    return value


#: The farthest apart two eyes may be (m): an interpupillary distance is over 0 and at most
#: this, wherever one is given (a frame, ``bench --stereo``, the driver's ``--stereo``).
MAX_IPD = 1.0


class StereoSpec(Document):
    """Two eyes ``ipd`` apart across the tracked head (SPEC section 3): ``head`` is a unit
    quaternion."""

    ipd: Annotated[Num, Field(gt=0, le=MAX_IPD)]
    head: Quaternion = (1.0, 0.0, 0.0, 0.0)

    _unit = field_validator("head")(_unit_quaternion)


class FrameSpec(Document):
    """A frame (SPEC section 3): display space placed in the world, and the tracked eye.
    ``orientation`` must be a unit quaternion (within 1e-6 relative), and the eye in front of
    the wall (``eye[2] > near - distance``; of every screen, every eye)."""

    position: Vec3
    orientation: Quaternion
    eye: Point = (0.0, 0.0, 0.0)
    stereo: Optional[StereoSpec] = None

    _unit = field_validator("orientation")(_unit_quaternion)


def _nonzero(value, what: str):
    if not any(value):
        raise _refuse("zero", f"{what} must not be zero")


def unit(v) -> np.ndarray:
    """A vector that is not zero, scaled to length 1 (first by its largest component, so that
    a tiny vector's length cannot underflow to zero)."""
    v = np.array(v, dtype=np.float64)
    v = v / np.abs(v).max()
    return v / np.linalg.norm(v)


def _convex(polygon: np.ndarray, normal: np.ndarray) -> bool:
    """Whether ``polygon`` (in the plane of ``normal``, a unit vector) is a convex outline:
    every corner turns the same way, or goes straight on (never back), and the turns make one
    round."""
    edges = np.roll(polygon, -1, axis=0) - polygon
    lengths = np.linalg.norm(edges, axis=1)
    if (lengths == 0).any():
        return False
    edges = edges / lengths[:, None]
    after = np.roll(edges, -1, axis=0)
    turns = np.cross(edges, after) @ normal  # the sine of each corner's turn
    cosines = np.einsum("ij,ij->i", edges, after)
    if (turns < -1e-9).any() and (turns > 1e-9).any() or \
            ((np.abs(turns) <= 1e-9) & (cosines < 0)).any():
        return False
    return bool(abs(abs(np.arctan2(turns, cosines).sum()) - 2 * math.pi) < 1e-6)


class LightSpec(Document):
    """A light casting shadows: a point light, or a spot light with a ``direction`` and a
    half-angle ``angle`` (degrees). ``resolution``: its shadow map's pixels. A light whose
    ``shadows`` is false needs no frustum and is left out."""

    name: Optional[NodeName] = None
    type: Literal["point", "spot"] = "point"
    position: Vec3
    direction: Optional[Vec3] = None
    angle: Annotated[Num, Field(gt=0, lt=90)] = 45.0
    resolution: Vector(2, Int(ge=1, le=1 << 15)) = (2048, 2048)
    shadows: Bool = True

    @model_validator(mode="after")
    def _aimed(self):
        if self.type == "spot":
            if self.direction is None:
                raise _refuse("direction", "is a spot light without a direction")
            _nonzero(self.direction, "direction")
        return self


class MirrorSpec(Document):
    """A planar mirror: a point on it, its normal (toward the reflective side, not zero) and
    an optional convex ``polygon`` in its plane that bounds it."""

    name: Optional[NodeName] = None
    point: Vec3
    normal: Vec3
    polygon: Optional[list[Vec3]] = Field(default=None, min_length=3, max_length=1024)

    @model_validator(mode="after")
    def _planar(self):
        _nonzero(self.normal, "normal")
        if self.polygon is not None:
            normal = unit(self.normal)
            polygon = np.array(self.polygon)
            size = np.ptp(polygon, axis=0).max()
            if np.abs((polygon - self.point) @ normal).max() > 1e-6 * max(size, 1.0):
                raise _refuse("polygon", "polygon must lie in the mirror's plane")
            if not _convex(polygon, normal):
                raise _refuse("polygon", "polygon must be a convex outline, its corners in "
                                         "order around it")
        return self


class OcclusionSpec(Document):
    """What occludes in a scene, and what its occlusion culling may spend, when a wall turns
    it on: ``exclude``, nodes whose subtrees never occlude (besides the meshes whose
    materials are transparent or alpha-tested, which never do); ``budget``, occluder
    triangles a frame; ``texels``, the buffer's texels across a tile (see docs/occlusion.md)."""

    exclude: list[NodeName] = Field(default_factory=list, max_length=1 << 16)
    budget: Optional[Int(ge=0, le=MAX_OCCLUDER_TRIANGLES)] = None
    texels: Optional[Int(ge=MIN_TEXELS, le=MAX_TEXELS)] = None


class SettingsSpec(Document):
    """A scene's settings: ``up`` (for camera paths; default +y), lights that cast shadows,
    planar mirrors and what occludes (see docs/settings.md)."""

    up: Optional[Vec3] = None
    lights: list[LightSpec] = Field(default_factory=list, max_length=64)
    mirrors: list[MirrorSpec] = Field(default_factory=list, max_length=64)
    occlusion: OcclusionSpec = Field(default_factory=OcclusionSpec)

    @model_validator(mode="after")
    def _up_and_names(self):
        if self.up is not None:
            _nonzero(self.up, "up")
        for kind, items in (("light", self.lights), ("mirror", self.mirrors)):
            names = [item.name or f"{kind}{k}" for k, item in enumerate(items)]
            twice = next((n for k, n in enumerate(names) if n in names[:k]), None)
            if twice is not None:
                raise _refuse(f"{kind}s", f"has two {kind}s named {twice!r}: name them apart")
        return self


# --------------------------------------------------------------------------- reading them

_WALL = TypeAdapter(Wall)


def parse(kind: Any, value: Any, what: str):
    """``value`` validated as ``kind`` (a model, or :data:`Wall`); a model instance (a body the
    server has validated) passes as it is. Refused with one line naming ``what`` and the
    place: :class:`InputError`."""
    if isinstance(value, (WallSpec, ScreensSpec) if kind is Wall else kind):
        return value
    try:
        return _WALL.validate_python(value) if kind is Wall else kind.model_validate(value)
    except ValidationError as exc:
        raise InputError(one_line(exc, what, tagged=kind is Wall)) from None


def one_line(exc: ValidationError, what: str, tagged: bool = False) -> str:
    """A validation error as one line: the first problem, where it is (``tagged``: the first
    step is a union's tag, left out), and how many more."""
    errors = problems(exc.errors(include_url=False))
    # an unknown key first: a misspelt key explains the missing one
    e = min(errors, key=lambda e: e["type"] != "extra_forbidden")
    loc = list(e["loc"][1:] if tagged else e["loc"])
    parent, key = loc[:-1], loc[-1] if loc else None
    kind, ctx, given = e["type"], e.get("ctx", {}), _short(e.get("input"))
    if kind == "missing":
        text = f"{_where(what, parent)} is missing {key!r}"
    elif kind == "extra_forbidden":
        text = f"unknown {_where(what, parent)} key {key!r}"
    else:
        text = f"{_where(what, loc)} {_message(kind, ctx, e['msg'], given)}"
    more = len(errors) - 1
    return text + (f" (and {more} more problem{'s' * (more > 1)})" if more else "")


def problems(errors: list) -> list:
    """Validation errors without the follow-ons pydantic adds: an array whose element was
    refused is then also "too short" (``[1e300, 0, 0]`` is one problem, not two)."""
    locs = [tuple(e["loc"]) for e in errors]

    def follow_on(e) -> bool:
        at = tuple(e["loc"])
        return e["type"] == "too_short" and any(len(loc) > len(at) and loc[:len(at)] == at
                                                 for loc in locs)

    return [e for e in errors if not follow_on(e)]


def _where(what: str, loc) -> str:
    out = what
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else f" {part}" if out == what else f".{part}"
    return out


def _message(kind: str, ctx: dict, msg: str, given: str) -> str:
    bound = {"greater_than_equal": ("must be at least", "ge"),
             "less_than_equal": ("must be at most", "le"),
             "greater_than": ("must be greater than", "gt"),
             "less_than": ("must be less than", "lt")}.get(kind)
    if bound is not None:
        if kind == "greater_than" and ctx["gt"] == 0:
            return f"must be positive, got {given}"
        return f"{bound[0]} {ctx[bound[1]]:g}, got {given}" if isinstance(
            ctx[bound[1]], float) else f"{bound[0]} {ctx[bound[1]]}, got {given}"
    if kind in ("int_type", "int_from_float", "int_parsing"):
        return f"must be a whole number, got {given}"
    if kind in ("float_type", "float_parsing", "bool_type", "string_type"):
        return f"must be a {'number' if kind.startswith('float') else kind[:-5]}, got {given}"
    if kind == "finite_number":
        return f"must be finite, got {given}"
    if kind in ("model_type", "dict_type", "model_attributes_type"):
        return f"must be an object, got {given}"
    if kind == "too_short" and ctx.get("min_length") == 1:
        return "must be a non-empty list"
    text = msg.removeprefix("Value error, ").replace("Input should be", "must be")
    return text if kind in _OURS else f"{text}, got {given}"


#: Our validators' errors: their text says everything.
_OURS = {"vector", "near_far", "gap", "degenerate", "rectangle", "quaternion", "zero",
         "direction", "polygon"}


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def read_text(path: str | Path, what: str) -> str:
    """The text of the JSON file ``path`` (``what`` names it), or a one-line error."""
    try:
        return Path(path).read_text()
    except FileNotFoundError:
        raise InputError(f"{what} file not found: {path}") from None
    except UnicodeDecodeError:
        raise InputError(f"malformed JSON in {what}: {path} is not text") from None
    except OSError as exc:  # a folder, no permission
        raise InputError(f"cannot read {what} file {path}: {exc.strerror}") from None


def read_json(text: str, what: str):
    """A JSON document given inline (starting with ``{`` or ``[``) or as a file path."""
    text = text.strip()
    if not text:
        raise InputError(f"{what} is empty: give a file or inline JSON")
    if not text.startswith(("{", "[")):
        text = read_text(text, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"malformed JSON in {what}: {exc}") from None
