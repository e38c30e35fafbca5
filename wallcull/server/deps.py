"""What the routes share, reached through the app's state: the scene store, the walls, the
metrics and the access check."""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from typing import Annotated, Optional

from fastapi import Depends, Header, Request

from ..service import SceneStore, Walls
from .http import Refused
from .metrics import Metrics


@dataclass
class ServerState:
    store: SceneStore
    walls: Walls
    metrics: Metrics
    token: str | None

    def authorized(self, value: str | None) -> bool:
        return self.token is None or (value is not None and secrets.compare_digest(
            value.encode(), self.token.encode()))


def server_state(request: Request) -> ServerState:
    return request.app.state.server


State = Annotated[ServerState, Depends(server_state)]


def require_token(state: State, authorization: Annotated[Optional[str], Header()] = None):
    # the scheme is case-insensitive (RFC 9110, 11.1); the token is not
    given = authorization[7:] if authorization and authorization[:7].lower() == "bearer " \
        else None
    if not state.authorized(given):
        raise Refused(401, "this request needs the server's token (Authorization: Bearer)")


#: ``dependencies=`` of every route that changes state.
TOKEN = [Depends(require_token)]
