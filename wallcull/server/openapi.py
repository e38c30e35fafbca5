"""The OpenAPI document, completed with what FastAPI cannot see: the bodies routes validate
themselves (:func:`.http.body_of`), JSON or msgpack, the answers in msgpack of the routes
that negotiate (:func:`.http.reply`), the 422 of an unknown query parameter on every route
(the gate's), who may call what (bearer security on every route that needs a token, when
the server has one), and the links from a wall to its frames, packets, acknowledgements and
barrier, so that a client (or a stateful fuzzer) can follow them.
"""

from __future__ import annotations

import re

from fastapi.openapi.utils import get_openapi
from fastapi.routing import APIRoute
from pydantic.json_schema import models_json_schema

from .access import OPEN, leaf_routes, role_of
from .models import Detail

REF = "#/components/schemas/{model}"
MSGPACK = "application/msgpack"
#: The tags whose routes answer through :func:`.http.reply`: JSON, or msgpack by ``Accept``.
NEGOTIATED = {"scenes", "walls"}

#: Links of a created wall (201 of ``POST /walls``): its id feeds every route of the wall.
#: (Constants are strings, as the OpenAPI schema asks of a link's parameters: ``"0"`` is
#: tile 0 in a path.)
WALL_LINKS = {
    "GetWall": {"operationId": "getWall", "parameters": {"wid": "$response.body#/id"}},
    "PostFrame": {"operationId": "postFrame", "parameters": {"wid": "$response.body#/id"}},
    "GetLatestPacket": {"operationId": "getPacket",
                        "parameters": {"wid": "$response.body#/id", "tile": "0",
                                       "frame": "latest"}},
    "Acknowledge": {"operationId": "acknowledge",
                    "parameters": {"wid": "$response.body#/id", "tile": "0"}},
    "Barrier": {"operationId": "barrier",
                "parameters": {"wid": "$response.body#/id", "frame": "0"}},
    "DeleteWall": {"operationId": "deleteWall", "parameters": {"wid": "$response.body#/id"}},
}
#: Links of a posted frame (200 of ``POST /walls/{wid}/frames``): its number.
FRAME_LINKS = {
    "GetPacket": {"operationId": "getPacket",
                  "parameters": {"wid": "$request.path.wid", "tile": "0",
                                 "frame": "$response.body#/frame"}},
    "Acknowledge": {"operationId": "acknowledge",
                    "parameters": {"wid": "$request.path.wid", "tile": "0"},
                    "requestBody": {"frame": "$response.body#/frame"}},
    "Barrier": {"operationId": "barrier",
                "parameters": {"wid": "$request.path.wid", "frame": "$response.body#/frame"}},
}


def document(app, secured: bool) -> dict:
    """The app's OpenAPI document (see the module docstring); ``secured``: the server has a
    token, so routes other than the open ones declare bearer security."""
    doc = get_openapi(title=app.title, version=app.version, description=app.description,
                      routes=app.routes)
    models = {}
    for route in leaf_routes(app.router.routes):
        if not isinstance(route, APIRoute) or not route.include_in_schema:
            continue
        for method in route.methods:
            op = doc["paths"][route.path_format][method.lower()]
            for dep in route.dependant.dependencies:
                model = getattr(dep.call, "body_model", None)
                if model is not None:
                    models[model.__name__] = model
                    body = {"schema": {"$ref": REF.format(model=model.__name__)}}
                    op["requestBody"] = {"required": True, "content": {
                        "application/json": body, MSGPACK: body}}
            if NEGOTIATED & set(op.get("tags", ())):
                for status, response in op["responses"].items():
                    content = response.get("content", {})
                    if status.startswith("2") and "application/json" in content:
                        content[MSGPACK] = content["application/json"]
            if "422" not in op["responses"]:  # the gate's: an unknown query parameter
                op["responses"]["422"] = {"description": "Invalid input", "content": {
                    "application/json": {"schema": {"$ref": REF.format(model="Detail")}}}}
                models.setdefault("Detail", Detail)
            if secured and role_of(route.endpoint) != OPEN:
                op["security"] = [{"bearer": []}]
    components = doc.setdefault("components", {})
    if models:
        _, defs = models_json_schema([(m, "validation") for m in models.values()],
                                     ref_template=REF)
        components.setdefault("schemas", {}).update(defs.get("$defs", {}))
    if secured:
        components["securitySchemes"] = {"bearer": {
            "type": "http", "scheme": "bearer",
            "description": "The operator's token, or a credential issued with a wall "
                           "(its driver's, or a node's)"}}
    return markdown(doc)


_ROLE = re.compile(r":[a-z]+:`~?\.*([^`]+)`")
_LITERAL = re.compile(r"``([^`]+)``")


def markdown(doc):
    """Every ``description`` of a document in Markdown, as OpenAPI and AsyncAPI read them: the
    docstrings' reStructuredText roles and literals (``:mod:`x``` and double backquotes)
    become code spans."""
    if isinstance(doc, dict):
        return {k: _LITERAL.sub(r"`\1`", _ROLE.sub(r"`\1`", v))
                if k == "description" and isinstance(v, str) else markdown(v)
                for k, v in doc.items()}
    if isinstance(doc, list):
        return [markdown(v) for v in doc]
    return doc
