"""The typed bodies of the HTTP API: validation happens here, at the boundary, and nowhere else."""

from __future__ import annotations

from typing import Annotated, Any, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat

from ..bounds import KINDS
from ..cull import METHODS
from ..errors import InputError
from ..lowilie import EFFORTS
from ..wall import MAX_TILES

Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]


class WallSpec(BaseModel):
    """A wall (SPEC section 2)."""

    model_config = ConfigDict(extra="forbid")
    cols: int = Field(ge=1, le=MAX_TILES)
    rows: int = Field(ge=1, le=MAX_TILES)
    tile_size: tuple[FiniteFloat, FiniteFloat]
    gap: tuple[FiniteFloat, FiniteFloat] = (0.0, 0.0)
    distance: FiniteFloat
    near: FiniteFloat = 0.1
    far: FiniteFloat = 1000.0
    resolution: tuple[Annotated[int, Field(ge=1, le=1 << 16)],
                      Annotated[int, Field(ge=1, le=1 << 16)]] = (1920, 1080)


class FrameSpec(BaseModel):
    """A frame (SPEC section 3)."""

    model_config = ConfigDict(extra="forbid")
    position: Vec3
    orientation: tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat]
    eye: Vec3 = (0.0, 0.0, 0.0)


class NodeUpdate(BaseModel):
    """A node's new local transform: ``matrix`` (4x4, row by row), or position, orientation
    (unit quaternion w, x, y, z) and an optional scale."""

    model_config = ConfigDict(extra="forbid")
    matrix: Optional[list[list[FiniteFloat]]] = None
    position: Optional[Vec3] = None
    orientation: Optional[tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat]] = None
    scale: Optional[Vec3] = None

    def value(self) -> Any:
        if self.matrix is not None:
            return self.matrix
        if self.position is None or self.orientation is None:
            raise InputError("a node update needs a matrix, or a position and an orientation")
        out = {"position": self.position, "orientation": self.orientation}
        if self.scale is not None:
            out["scale"] = self.scale
        return out


class WallCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    wall: WallSpec
    scene: str = Field(min_length=1, max_length=128)
    method: Literal[METHODS] = "adaptive"  # type: ignore[valid-type]
    bounds: Literal[KINDS] = "obb"  # type: ignore[valid-type]
    pseudo_groups: bool = False
    history: int = Field(default=64, ge=2, le=4096)
    depth: Literal["tight", "wall"] = "tight"
    reversed_z: bool = False
    shadow_fit: Literal[EFFORTS] = "refined"  # type: ignore[valid-type]
    settings: Optional[dict[str, Any]] = Field(
        default=None, description="Scene settings (lights, mirrors; see the README) for this "
                                  "wall instead of the scene's own")


class FramePost(BaseModel):
    model_config = ConfigDict(extra="forbid")
    frame: FrameSpec
    updates: dict[str, NodeUpdate] = Field(default_factory=dict, max_length=100_000)
    number: Optional[int] = Field(default=None, ge=0, le=2**53)
    refit: Optional[Literal["obb", "aabb"]] = None
    packets: bool = False
    full: bool = False


class Ack(BaseModel):
    model_config = ConfigDict(extra="forbid")
    frame: int = Field(ge=0, le=2**53)


class FrameAnswer(BaseModel):
    frame: int
    timings: dict[str, float]
    packets: Optional[list[dict]] = None


class Packet(BaseModel):
    """See :mod:`wallcull.protocol`."""

    model_config = ConfigDict(extra="allow")
    frame: int
    tile: int
    time: float
    base: Optional[int]
    count: int
    visible: Optional[list[int]] = None
    added: Optional[list[int]] = None
    removed: Optional[list[int]] = None
    view: list[list[float]]
    projection: list[list[float]]


class Barrier(BaseModel):
    frame: int
    acked: int
    tiles: int
    complete: bool


class Detail(BaseModel):
    """Every refusal: a status and one line saying what is wrong."""

    detail: str


_REFUSALS = {304: "Not modified: the ETag matches", 400: "Malformed msgpack body",
             401: "Missing or wrong token", 404: "No such scene, wall, tile, node or frame",
             409: "Conflicts with the server's state", 410: "The frame left the history",
             413: "Body too large", 422: "Invalid input"}


def refusals(*codes: int) -> dict:
    """OpenAPI ``responses`` for the refusals a route may answer (all with a ``detail``)."""
    return {c: {"description": _REFUSALS[c]} if c == 304 else
            {"model": Detail, "description": _REFUSALS[c]} for c in (*codes, 422)}
