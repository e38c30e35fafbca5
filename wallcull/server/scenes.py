"""Routes of the scenes: list, upload, describe, and their meshes."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from ..service import NotFound, describe, mesh_blob
from .deps import TOKEN, State
from .http import mesh_reply, reply
from .models import refusals

router = APIRouter(tags=["scenes"])


@router.get("/scenes")
async def list_scenes(request: Request, state: State):
    return reply(request, {"scenes": state.store.names()})


@router.post("/scenes", dependencies=TOKEN, status_code=201,
             responses=refusals(401, 409, 413), openapi_extra={
                 "requestBody": {"required": True, "content": {
                     "model/gltf-binary": {"schema": {"type": "string", "format": "binary"}}}}})
async def upload_scene(request: Request, state: State,
                       name: Annotated[str, Query(min_length=1, max_length=128)],
                       replace: bool = False):
    """Upload a GLB into the scene folder (or memory, without one)."""
    scene = await state.store.upload(name, await request.body(), replace)
    return reply(request, describe(scene, nodes=False), 201)


@router.get("/scenes/{name}", responses=refusals(404))
async def scene_info(request: Request, state: State, name: str, nodes: bool = False):
    """A scene's stats, bounds and settings; ``nodes=true`` adds every node: name, parent,
    leaf flag, mesh key and rest world transform (row by row, flattened)."""
    return reply(request, describe(await state.store.get(name), nodes))


@router.get("/scenes/{name}/meshes/{key}", responses=refusals(304, 404))
async def mesh(request: Request, state: State, name: str, key: str):
    """A mesh as typed arrays (little-endian float32 vertices, uint32 faces); cache it by
    its ETag."""
    return mesh_reply(request, mesh_blob(await state.store.get(name), key))


@router.get("/scenes/{name}/nodes/{node}/mesh", responses=refusals(304, 404))
async def node_mesh(request: Request, state: State, name: str, node: int):
    """The mesh of a leaf node, in the node's local coordinates (see ``nodes=true``)."""
    scene = await state.store.get(name)
    if not 0 <= node < len(scene) or scene.geometry[node] is None:
        raise NotFound(f"node {node} of scene {name!r} carries no mesh")
    return mesh_reply(request, mesh_blob(scene, scene.geometry[node]))
