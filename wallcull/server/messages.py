"""The messages of the streams (WebSocket and NATS) and of the packet routes, as pydantic models:
the AsyncAPI document's schemas are theirs (:mod:`.asyncapi`), and so are the OpenAPI
document's packets and frame answers. Strict: no key a message does not list, and a key that
may be left out is absent, never null. :mod:`wallcull.protocol` writes them; the tests validate
what the server sends, on every channel, against these schemas.
"""

from __future__ import annotations

from typing import Annotated, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field
from pydantic.json_schema import GenerateJsonSchema

from ..errors import InputError
from ..validate import MAX_FRAME

Id = Annotated[int, Field(ge=0)]
Ids = Annotated[list[Id], Field(description="leaf ids (scene.leaves), sorted")]
Ranges = Annotated[
    list[Annotated[list[Id], Field(min_length=3)]],
    Field(description="leaves drawn in part: [leaf, first, count, first, count, ...] each, the "
                      "runs of the leaf mesh's triangles to draw, sorted and apart; in a delta, "
                      "those new or changed since the base")]
Whole = Annotated[list[Id], Field(description="deltas: leaves drawn in part in the base, still "
                                              "listed, and drawn whole now")]


def Numbers(n: int, description: str | None = None):
    """An array of ``n`` numbers."""
    return Annotated[list[float], Field(min_length=n, max_length=n, description=description)]


Matrix = Annotated[list[Numbers(4)], Field(min_length=4, max_length=4,
                                           description="a 4 x 4 matrix, row by row "
                                                       "(SPEC section 1)")]


class Message(BaseModel):
    model_config = ConfigDict(extra="forbid")


class MessageSchema(GenerateJsonSchema):
    """JSON Schema of the messages: a key that may be left out is optional, not nullable (its
    default, None, means absent: it is not written), and properties carry no generated titles."""

    def default_schema(self, schema):
        if schema.get("default", ...) is None:
            return self.generate_inner(schema["schema"])
        return super().default_schema(schema)

    def field_title_should_be_set(self, schema) -> bool:
        return False


class Transforms(Message):
    """World transforms of moved leaves the node may lack (row by row)."""

    ids: Ids
    matrices: list[Numbers(16)]


class Shadow(Message):
    """A light's shadow frustum for the tile (Low-Ilie), or a cube map."""

    light: str
    view: Matrix = None
    cube: Literal[True] = None
    views: Annotated[list[Matrix], Field(min_length=6, max_length=6)] = None
    projection: Matrix
    near: float
    far: float
    coverage: float = None
    casters: Ids


class Mirror(Message):
    """A mirror the tile shows: reflected view, oblique near plane."""

    mirror: str
    view: Matrix
    projection: Matrix
    front_face: Literal["cw"]
    visible: Ids


class EyeMirror(Message):
    """A mirror seen by one eye of a stereo frame."""

    mirror: str
    view: Matrix
    projection: Matrix


class Rigid(Message):
    """A view: the rotation of the unit quaternion [w, x, y, z], then the translation."""

    rotation: Numbers(4)
    translation: Numbers(3)


class Eye(Message):
    """One eye of a stereo frame."""

    view: Matrix
    projection: Matrix
    near: float
    far: float
    mirrors: list[EyeMirror] = None


class Packet(Message):
    """One tile's frame (wallcull.protocol): its full list when base is null, else the delta
    against frame base."""

    frame: Id
    tile: Id
    time: float
    base: Optional[int]
    visible: Ids = None
    added: Ids = None
    removed: Ids = None
    count: Id
    ranges: Ranges = None
    whole: Whole = None
    transforms: Transforms = None
    view: Matrix
    projection: Matrix
    near: float
    far: float
    shadows: list[Shadow] = None
    mirrors: list[Mirror] = None
    left: Eye = None
    right: Eye = None


Extent = Numbers(4, "the frustum's extent [l/n, r/n, b/n, t/n]")
Depth = Numbers(2, "the depth range [n, f]")


class TileEye(Message):
    """One eye of a tile; extent and depth as the tile's."""

    view: Rigid = None
    extent: Extent = None
    depth: Depth = None
    mirrors: list[EyeMirror] = None


class TileEntry(Message):
    """One tile of a node message: its list (visible), or the delta's non-empty parts; its
    frustum's extent and depth when they changed since the base (a node keeps them by frame);
    its own view on a wall of screens."""

    tile: Id
    visible: Ids = None
    added: Ids = None
    removed: Ids = None
    count: Id
    ranges: Ranges = None
    whole: Whole = None
    view: Rigid = None
    extent: Extent = None
    depth: Depth = None
    shadows: list[Shadow] = None
    mirrors: list[Mirror] = None
    left: TileEye = None
    right: TileEye = None


class EyeView(Message):
    """The view of one eye of a stereo frame, shared by the node's tiles."""

    view: Rigid


class NodeMessage(Message):
    """One frame for a render node of several tiles (wallcull.protocol; the matrices:
    wallcull_clients.frusta)."""

    frame: Id
    time: float
    base: Optional[int]
    reversed_z: Literal[True] = None
    view: Rigid = None
    left: EyeView = None
    right: EyeView = None
    transforms: Transforms = None
    tiles: Annotated[list[TileEntry], Field(
        description="every tile of the node in a message with full lists; in a delta only "
                    "the tiles with something new: one left out keeps its list, extent and "
                    "depth of the base frame")]


class Control(Message):
    """From a node: it has drawn frame ack; full: send full lists next; node (NATS: in its
    acknowledgements and full requests): its name, when several nodes may take the same
    subject."""

    model_config = ConfigDict(json_schema_extra={"minProperties": 1})
    ack: Annotated[int, Field(ge=0, le=MAX_FRAME)] = None
    full: bool = None
    node: Annotated[str, Field(max_length=64)] = None


def control(value) -> tuple[int | None, bool, str | None]:
    """A node's control message held to :class:`Control` (by hand: a model's check costs more
    than the rest of an acknowledgement): its ``ack`` (None: none), whether it asks for full
    lists, its ``node`` name (None: none). :class:`InputError` names what is wrong."""
    if not isinstance(value, dict) or not value:
        raise InputError('a message must be an object of "ack", "full" or "node"')
    unknown = value.keys() - Control.model_fields.keys()
    if unknown:
        raise InputError(f"unknown key {sorted(map(str, unknown))[0]!r} in a message: "
                         '"ack", "full" and "node" are known')
    ack = value.get("ack")
    if "ack" in value and (not isinstance(ack, int) or isinstance(ack, bool) or
                           not 0 <= ack <= MAX_FRAME):
        raise InputError(f"ack must be a frame number, 0 to {MAX_FRAME}")
    full = value.get("full", False)
    if not isinstance(full, bool):
        raise InputError("full must be true or false")
    node = value.get("node")
    if "node" in value and not (isinstance(node, str) and len(node) <= 64):
        raise InputError("node must be a name of at most 64 characters")
    return ack, full, node


class StreamError(Message):
    """A message the server could not take, and why."""

    error: str


class FrameAnswer(Message):
    """A posted frame's number, its timings (ms by stage) and, if asked, every tile's packet."""

    frame: Id
    timings: dict[str, float]
    packets: list[Packet] = None


class FrameRefused(Message):
    """Why a frame posted on the frame stream was refused, with the status HTTP would give."""

    error: str
    status: Id


_COLUMN = "per tile, in tile order: "


class ConsoleStatus(Message):
    """A wall's state for the operator console (JSON), whenever it changes; frame: the newest
    held (-1: none yet, or none since a restart), newest: the newest handed out (before a
    restart too, as ``GET /walls/{wid}``'s ``latest``), posted: its server time, time: now (s
    since the epoch)."""

    wall: str
    frame: Annotated[int, Field(ge=-1)]
    newest: Annotated[int, Field(ge=-1)]
    time: float
    posted: Optional[float]
    count: Annotated[list[Id], Field(description=_COLUMN + "list size")]
    ack: Annotated[list[Annotated[int, Field(ge=-1)]],
                   Field(description=_COLUMN + "the newest frame acknowledged (-1: none)")]
    latency_ms: Annotated[list[Optional[float]],
                          Field(description=_COLUMN + "from that frame's post to its ack, ms")]
    streams: Annotated[list[Id], Field(description=_COLUMN + "streams open")]
    state: Annotated[list[Literal["offline", "waiting", "drawing", "acked", "lagging"]],
                     Field(description=_COLUMN + "offline, waiting (no frame yet), drawing, "
                                                 "acked (has drawn the newest frame) or lagging")]
