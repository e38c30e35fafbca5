"""What the routes share, reached through the app's state: the scene store, the walls, the
metrics, the limits and who may do what."""

from __future__ import annotations

import asyncio
from dataclasses import InitVar, dataclass, field
from typing import Annotated, Any

from fastapi import Depends, Request

from ..credentials import digest, same_digest
from ..limits import Limits
from ..service import SceneStore, Walls
from .metrics import Metrics


#: Node tables (``GET /scenes/{name}?nodes=true``) encoded at once, each in a thread of the
#: background pool (of 4) for up to 13 s and its body's size in memory at a million nodes:
#: the pool's other threads stay free for wall creations, scene loads and other answers,
#: however many pages ask at once.
NODE_ENCODES = 1


@dataclass
class ServerState:
    store: SceneStore
    walls: Walls
    metrics: Metrics
    token: InitVar[str | None]  # the operator's token: only its digest is kept
    limits: Limits = field(default_factory=Limits)
    #: browser origins allowed (CORS and WebSocket ``Origin``); "*" allows any
    origins: tuple[str, ...] = ()
    bridge: Any = None  # the NATS bridge (wallcull.server.nats), when there is a broker
    streams: int = 0  # WebSocket streams open, on every wall
    uploads: int = 0  # uploads being received or parsed
    #: console streams open (wallcull.server.pages): [without, with] a credential of their wall
    consoles: list = field(default_factory=lambda: [0, 0])
    warming: set = field(default_factory=set)  # meshes being encoded for new walls
    #: bytes a second sent to consoles opened without a credential, all together
    open_budget: Any = None
    kernels_ready: bool = False  # every numba kernel loaded (wallcull.warm)
    #: node tables being encoded (wallcull.server.scenes.NODE_ENCODES at once)
    node_encodes: Any = None
    operator: str | None = field(init=False, default=None)

    def __post_init__(self, token):
        from .http import Budget

        self.operator = None if token is None else digest(token)
        self.open_budget = Budget(self.limits.open_bytes)
        if self.node_encodes is None:
            self.node_encodes = asyncio.Semaphore(NODE_ENCODES)

    @property
    def open(self) -> bool:
        """No token configured: a lab that wants no access control (every request allowed)."""
        return self.operator is None

    def is_operator(self, token: str) -> bool:
        return self.operator is not None and same_digest(digest(token), self.operator)


def server_state(request: Request) -> ServerState:
    return request.app.state.server


State = Annotated[ServerState, Depends(server_state)]
