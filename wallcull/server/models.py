"""The typed bodies of the HTTP API: validation happens here, at the boundary, and nowhere else.

The wall, the frame and the settings are the documents of :mod:`wallcull.documents`, the models
the command line reads them with. The schema says what the server accepts, as far as JSON
Schema can: ranges, lengths, patterns, and strict scalars (``true`` is not a number, ``"7"`` is
not a number, ``7.5`` is not an integer). What it cannot say is answered 422 with a detail:
that an orientation is a *unit* quaternion, that ``near < far`` and ``gap > -tile_size``, that
``cols x rows`` is at most 65,536 and ``history x tiles`` at most 2^20, that the eye is in front
of the wall, that a node name exists, that an update's matrix is invertible, that a spot
light has a direction and a mirror a non-zero normal and an outline in its plane.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Optional, Union

from fastapi import Path
from pydantic import (BaseModel, ConfigDict, Field, Strict, StringConstraints, TypeAdapter,
                      ValidationError)

from ..bounds import KINDS
from ..cull import METHODS
from ..documents import (Bool, Document, FrameSpec, Int, Length, NodeName, Num, SettingsSpec,
                         Quaternion, Vec3, Wall)
from ..errors import InputError
from ..lowilie import EFFORTS
from ..validate import MAX_FRAME, MAX_TILES

Tile = Int(ge=0, lt=MAX_TILES)
FrameNumber = Int(ge=0, le=MAX_FRAME)

#: What each pattern of a path, query or body string asks for, in words: a refusal names
#: that, and what was given, rather than the pattern (:func:`worded`).
PATTERN_WORDS: dict[str, str] = {}


def worded(pattern: str, words: str) -> str:
    """``pattern``, its refusals worded ``words``."""
    PATTERN_WORDS[pattern] = words
    return pattern


#: Scene names: plain file names, ASCII (what the scene folder can hold).
SCENE_NAME = worded(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$",
                    "a scene name is a plain file name of at most 128 letters, digits, '_', "
                    "'.' and '-', starting with a letter or digit")
SceneName = Annotated[str, Strict(), StringConstraints(pattern=SCENE_NAME)]
#: Wall ids, as the server makes them.
WALL_ID = worded(r"^[0-9a-f]{12}$", "a wall id is 12 hexadecimal digits (0-9, a-f)")
WallId = Annotated[str, Path(pattern=WALL_ID)]

Row = tuple[Num, Num, Num, Num]
Zero, One = Annotated[Num, Field(ge=0, le=0)], Annotated[Num, Field(ge=1, le=1)]

#: A request body: no key it does not list.
Body = Document


class NodeUpdate(Body):
    """A node's new local transform: ``matrix`` (4x4 affine, row by row), or position,
    orientation (unit quaternion w, x, y, z) and an optional scale."""

    matrix: Optional[tuple[Row, Row, Row, tuple[Zero, Zero, Zero, One]]] = None
    position: Optional[Vec3] = None
    orientation: Optional[Quaternion] = None
    scale: Optional[tuple[Length, Length, Length]] = None

    def value(self, name: str) -> Any:
        """The update of node ``name`` as :func:`wallcull.scene.node_matrix` takes it."""
        if self.matrix is not None:
            if (self.position, self.orientation, self.scale) != (None, None, None):
                raise InputError(f"update of {name!r} has a matrix and a position, orientation "
                                 "or scale: send one or the other")
            return self.matrix
        if self.position is None or self.orientation is None:
            raise InputError(f"update of {name!r} needs a matrix, or a position and an "
                             "orientation")
        out = {"position": self.position, "orientation": self.orientation}
        if self.scale is not None:
            out["scale"] = self.scale
        return out


#: Updates of one frame at most. A 1 MiB body holds 85,000 empty ones; counted before any is
#: validated, so that such a body costs one JSON parse (about 25 ms), not a validation that
#: would hold the GIL (and so the event loop) for a quarter of a second.
MAX_UPDATES = 10_000


class WallCreate(Body):
    wall: Wall
    scene: SceneName
    method: Literal[METHODS] = "adaptive"  # type: ignore[valid-type]
    bounds: Literal[KINDS] = "obb"  # type: ignore[valid-type]
    pseudo_groups: Bool = False
    history: Int(ge=2, le=4096) = 64
    depth: Literal["tight", "wall"] = "tight"
    reversed_z: Bool = False
    shadow_fit: Literal[EFFORTS] = "refined"  # type: ignore[valid-type]
    #: Drop what occluders hide: never, every frame, or when the camera is inside the scene.
    occlusion: Literal["off", "on", "auto"] = "off"
    #: Lights and mirrors for this wall instead of the scene's own.
    settings: Optional[SettingsSpec] = None
    #: Tiles grouped under one node credential each (a node driving several tiles); tiles
    #: no group names get a credential of their own.
    nodes: Optional[list[Annotated[list[Tile], Field(min_length=1, max_length=MAX_TILES)]]] = \
        Field(default=None, max_length=MAX_TILES)


class FramePost(Body):
    frame: FrameSpec
    updates: dict[NodeName, NodeUpdate] = Field(default_factory=dict, max_length=MAX_UPDATES)
    number: Optional[FrameNumber] = None
    refit: Optional[Literal["obb", "aabb"]] = None
    packets: Bool = False
    full: Bool = False

    @classmethod
    def from_body(cls, body: Any) -> "FramePost":
        """Validate, the updates in pieces: one pydantic call over 10,000 of them holds the
        GIL for 20-40 ms, which would stall the event loop even from a worker thread."""
        updates = body.get("updates") if isinstance(body, dict) else None
        if not isinstance(updates, dict) or len(updates) <= _PIECE:
            return cls.model_validate(body)
        if len(updates) > MAX_UPDATES:  # before validating any
            raise ValidationError.from_exception_data(cls.__name__, [{
                "type": "too_long", "loc": ("updates",),
                "input": f"{len(updates)} updates",
                "ctx": {"field_type": "Dictionary", "min_length": 0,
                        "max_length": MAX_UPDATES, "actual_length": len(updates)}}])
        out = cls.model_validate({**body, "updates": {}})
        items, checked = list(updates.items()), {}
        for k in range(0, len(items), _PIECE):
            try:
                checked.update(_UPDATES.validate_python(dict(items[k:k + _PIECE])))
            except ValidationError as exc:
                raise ValidationError.from_exception_data(cls.__name__, [
                    {**e, "loc": ("updates", *e["loc"])} for e in exc.errors()]) from None
        out.updates = checked
        return out


_PIECE = 2000
_UPDATES = TypeAdapter(dict[NodeName, NodeUpdate])


class Ack(Body):
    frame: FrameNumber


class NodeCredential(BaseModel):
    tiles: list[int]
    token: str


class Credentials(BaseModel):
    """Shown once, when the wall is created; the server keeps only their digests."""

    driver: str
    nodes: list[NodeCredential]


class WallInfo(BaseModel):
    id: str
    scene: str
    wall: dict
    tiles: int
    method: str
    bounds: str
    pseudo_groups: bool
    depth: str
    reversed_z: bool
    shadow_fit: str
    occlusion: str
    settings: Optional[dict] = None
    latest: int
    history: int
    subscribers: int
    #: the tiles of each node credential (a render node's tiles; its NATS subjects are named
    #: after the first)
    nodes: list[list[int]]


class WallCreated(WallInfo):
    credentials: Credentials


class WallList(BaseModel):
    walls: list[WallInfo]


class Barrier(BaseModel):
    frame: int
    acked: int
    tiles: int
    complete: bool


class TypedArray(BaseModel):
    """A little-endian typed array: its bytes, base64 in JSON, binary in msgpack."""

    dtype: Literal["<f4", "<u4"]
    shape: Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=2, max_length=2)]
    data: Annotated[str, Field(description="the array's bytes, row by row: base64 in JSON, "
                                           "binary (bin) in msgpack")]


class MeshAnswer(BaseModel):
    """A mesh as the mesh routes serve it, in its own local coordinates: float32 vertices
    ``(v, 3)``, uint32 faces ``(f, 3)``, each face's corners counter-clockwise seen from its
    front, and which faces a render node draws. Cached a year by its ETag, which covers the
    arrays and ``double_sided``."""

    mesh: Annotated[str, Field(description="the mesh's key (the node table's `mesh`)")]
    double_sided: Annotated[bool, Field(description=(
        "false for a glTF mesh whose material is not `doubleSided` (glTF's default, and a "
        "primitive of no material): a render node may cull its back faces, as glTF asks "
        "(front faces wind counter-clockwise; clockwise where the leaf's world transform "
        "mirrors, determinant < 0). True for every other mesh (OBJ and the other formats say "
        "nothing of sides): draw both faces. An answer without it (a server before it was "
        "served) means true"))]
    vertices: TypedArray
    faces: TypedArray


class Detail(BaseModel):
    """Every refusal: a status and one line saying what is wrong."""

    detail: str


_REFUSALS = {304: "Not modified: the ETag matches", 400: "Malformed msgpack body",
             401: "No token, or one this server does not hold",
             403: "The token does not hold this wall, role or tile",
             404: "No such scene, wall, tile, node or frame",
             408: "The body arrived too slowly", 409: "Conflicts with the server's state",
             410: "The frame left the history", 413: "Body too large",
             415: "Bodies are JSON or msgpack", 422: "Invalid input",
             507: "The state folder or the scene cache folder is full"}
#: What a 503 (for now: retry after ``Retry-After`` seconds) may say, by its cause: a route
#: names the causes it meets among its refusals' codes. ``UNWRITABLE`` is a 507 too.
WAITS = "the wall waits for its scene (a restart did not find it)"
UNWRITABLE = "the state folder or the scene cache folder cannot be written"
BUSY = "too many uploads at once"
CROWDED = ("the server is at its connection cap, and this long poll, the oldest, made room for "
           "a new connection")
RETRY_AFTER = {"Retry-After": {"description": "Seconds to wait before trying again",
                               "schema": {"type": "integer"}}}


def refusals(*codes: int | str) -> dict:
    """OpenAPI ``responses`` for the refusals a route may answer (all with a ``detail``):
    status codes, and the causes of a 503 (``WAITS``, ``UNWRITABLE``, ``BUSY``)."""
    causes = [c for c in codes if isinstance(c, str)]
    codes = [c for c in codes if isinstance(c, int)] + [507] * (UNWRITABLE in causes)
    out = {c: {"description": _REFUSALS[c]} if c == 304 else
           {"model": Detail, "description": _REFUSALS[c]} for c in (*codes, 422)}
    if 507 in out:
        out[507]["headers"] = RETRY_AFTER
    if causes:
        said = "; or ".join(causes)
        out[503] = {"model": Detail, "description": f"{said[0].upper()}{said[1:]}: retry",
                    "headers": RETRY_AFTER}
    return out
