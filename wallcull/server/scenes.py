"""Routes of the scenes: list, upload, describe, and their meshes."""

from __future__ import annotations

import errno
import hashlib
import os
from pathlib import Path as FilePath
from typing import Annotated

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import Response

from .. import protocol
from ..credentials import OPERATOR
from ..errors import InputError
from ..persist import StateWriteFailed
from ..workers import background
from ..service import NotFound, describe, mesh_blob
from .access import needs
from .deps import State
from .http import Refused, encode_in_pieces, holds, mesh_reply, reply
from .models import BUSY, SCENE_NAME, UNWRITABLE, MeshAnswer, refusals, worded

router = APIRouter(tags=["scenes"])

SceneName = Annotated[str, Path(pattern=SCENE_NAME)]
#: An upload's name; ``.glb`` is added when it does not end so.
UploadName = Annotated[str, Query(pattern=worded(
    r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,123}$", "an upload's name is a plain file name of at most "
    "124 letters, digits, '_', '.' and '-', starting with a letter or digit"))]


def upload(endpoint):
    """Mark a route whose body is an upload (its own size limit and concurrency cap)."""
    endpoint.wallcull_upload = True
    return endpoint


@router.get("/scenes", operation_id="listScenes")
async def list_scenes(request: Request, state: State):
    return reply(request, {"scenes": state.store.names()})


@router.post("/scenes", status_code=201, operation_id="uploadScene",
             responses=refusals(401, 403, 408, 409, 413, BUSY, UNWRITABLE), openapi_extra={
                 "requestBody": {"required": True, "content": {
                     "model/gltf-binary": {"schema": {"type": "string", "format": "binary"}}}}})
@needs(OPERATOR)
@upload
async def upload_scene(request: Request, state: State, name: UploadName, replace: bool = False):
    """Upload a GLB into the scene folder (or memory, without one). Its body is spooled to a
    file as it arrives, checked and parsed in a child process with a memory limit
    (:mod:`wallcull.uploads`), then moved into the folder atomically."""
    name = state.store.upload_name(name, replace)  # 409 first: the name is taken
    try:
        limit = state.limits.uploads
        if state.uploads >= limit:
            raise Refused(503, f"{limit} uploads are in progress; retry", {"Retry-After": "2"})
        state.uploads += 1
        try:
            scene = await _receive(request, state, name)
        except OSError as exc:  # the scene folder: a full disk (507), read-only (503)
            full = exc.errno in (errno.ENOSPC, errno.EDQUOT)
            raise StateWriteFailed(507 if full else 503, f"cannot store the upload in "
                                   f"{state.store.folder}: {exc.strerror}") from None
        finally:
            state.uploads -= 1
    finally:
        state.store.release(name)
    if any(row.spec.get("scene") == name for row, _ in state.walls.unavailable.values()):
        await state.walls.retry(state.store)  # the walls that waited for it come back now
    return reply(request, describe(scene, nodes=False), 201)


async def _receive(request: Request, state, name: str):
    """An upload's body, spooled, checked, parsed and stored as scene ``name``."""
    spool = state.store.spool()
    path = FilePath(spool.name)
    try:
        with spool:
            async for chunk in request.stream():
                spool.write(chunk)
        with open(path, "rb") as f:
            if f.read(4) != b"glTF":
                raise InputError("an upload must be a binary glTF (.glb) file")
        return await state.store.upload(name, path)
    finally:
        if path.exists():
            os.unlink(path)


@router.get("/scenes/{name}", operation_id="getScene",
            responses=refusals(304, 404, UNWRITABLE))
async def scene_info(request: Request, state: State, name: SceneName, nodes: bool = False):
    """A scene's stats, bounds and settings; ``nodes=true`` adds its node table (every node
    but the clusters): id, name, parent, leaf flag, mesh key and rest world transform (row by
    row, flattened). The table is encoded once per scene and format and kept with the scene;
    send its ETag back in ``If-None-Match`` to get a 304 while the scene is unchanged."""
    scene = await state.store.get(name)
    if not nodes:
        return reply(request, describe(scene, False))
    binary = protocol.wants_msgpack(request.headers.get("accept"))
    body, etag = await _node_table(state, scene, binary)
    headers = {"ETag": etag, "Cache-Control": "no-cache", "Vary": "Accept"}
    if holds(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    return Response(body, headers=headers,
                    media_type=protocol.MSGPACK if binary else protocol.JSON)


async def _node_table(state, scene, binary: bool) -> tuple[bytes, str]:
    """A scene's description with its node table, encoded (JSON or msgpack) and its ETag:
    once per scene and format (the bytes stay with the scene, counted in its cache budget,
    and go with it), one scene's at a time per format, ``deps.NODE_ENCODES`` at once."""
    held = scene.__dict__.setdefault("_node_tables", {})
    if binary in held:
        return held[binary]
    async with state.store.lock(f"{scene.name}\0nodes\0{binary}"):
        if binary not in held:
            async with state.node_encodes:
                held[binary] = await background(_encode_table, scene, binary)
    return held[binary]


def _encode_table(scene, binary: bool) -> tuple[bytes, str]:
    body = encode_in_pieces(describe(scene, True, arrays=True), binary)
    return body, '"' + hashlib.blake2b(body, digest_size=16).hexdigest() + '"'


@router.get("/scenes/{name}/meshes/{key}", operation_id="getMesh", response_model=MeshAnswer,
            responses=refusals(304, 404, UNWRITABLE))
async def mesh(request: Request, state: State, name: SceneName,
               key: Annotated[str, Path(max_length=1024)]):
    """A mesh as typed arrays (little-endian float32 vertices, uint32 faces) and whether a
    render node draws both its faces (``double_sided``: false for a single-sided glTF mesh,
    whose back faces it may cull); cache it by its ETag, which covers both."""
    return mesh_reply(request, mesh_blob(await state.store.get(name), key))


@router.get("/scenes/{name}/nodes/{node}/mesh", operation_id="getNodeMesh",
            response_model=MeshAnswer, responses=refusals(304, 404, UNWRITABLE))
async def node_mesh(request: Request, state: State, name: SceneName,
                    node: Annotated[int, Path(ge=0, le=2**31)]):
    """The mesh of a leaf node, in the node's local coordinates (see ``nodes=true``)."""
    scene = await state.store.get(name)
    if not 0 <= node < len(scene) or scene.geometry[node] is None:
        raise NotFound(f"node {node} of scene {name!r} carries no mesh")
    return mesh_reply(request, mesh_blob(scene, scene.geometry[node]))
