"""Who may call a route: each route declares a role (:func:`needs`), and the gate
(:mod:`.gate`) checks the caller's token against it before anything else happens, before the
body is read.

* ``OPEN``: anyone (scenes, meshes, wall listings, the barrier, health, metrics);
* ``OPERATOR``: the server's token (uploads, creating and deleting walls);
* ``DRIVER``: the operator, or the wall's driver credential (posting frames);
* ``NODE``: the operator, or a node credential of the wall that holds the tile in the path,
  or the tiles a node's stream asks for (packets, which carry the tracked head's pose;
  acknowledgements; streams).

A server without a token (``wallcull serve`` with no ``--token``) lets every request through:
the choice of a lab that wants no access control, on a network it trusts.
"""

from __future__ import annotations

from typing import Callable, Mapping

from ..credentials import DRIVER, NODE, OPERATOR
from ..errors import InputError
from ..validate import MAX_TILES, parse_tiles
from .deps import ServerState
from .http import Refused

OPEN = "open"


def needs(role: str) -> Callable:
    """Declare the role a route needs (put it below the route's decorator)."""
    def mark(endpoint):
        endpoint.wallcull_role = role
        return endpoint
    return mark


def role_of(endpoint) -> str:
    return getattr(endpoint, "wallcull_role", OPEN)


def leaf_routes(routes) -> list:
    """Every route an app dispatches to, routers included (FastAPI keeps an included router
    as one entry; wallcull includes them without a prefix, so their routes match as they are)."""
    out = []
    for route in routes:
        inner = getattr(route, "original_router", None)
        out += leaf_routes(inner.routes) if inner is not None else [route]
    return out


def query_names(route) -> frozenset[str]:
    """The query parameters a route declares (and ``token``, a stream's credential), kept on
    the route once found."""
    known = getattr(route, "wallcull_query", None)
    if known is None:
        names, stack = set(), [route.dependant] if hasattr(route, "dependant") else []
        while stack:
            dependant = stack.pop()
            names |= {q.alias for q in dependant.query_params}
            stack += dependant.dependencies
        if not hasattr(route, "methods"):  # a WebSocket route
            names.add("token")
        known = route.wallcull_query = frozenset(names)
    return known


def bearer(authorization: str | None) -> str | None:
    """The token of an ``Authorization: Bearer`` header (the scheme is case-insensitive,
    RFC 9110 11.1; the token is not)."""
    if authorization and authorization[:7].lower() == "bearer " and authorization[7:]:
        return authorization[7:]
    return None


def check(state: ServerState, role: str, token: str | None, params: Mapping[str, str]) -> None:
    """Refuse (401: no or unknown token; 403: a token that does not hold this) unless
    ``token`` may call a route needing ``role`` with these path parameters. The token is
    checked first: a deleted wall's credentials are forgotten with it (401), and its driver
    and nodes then ask ``GET /walls/{wid}`` (open to anyone) whether the wall is gone."""
    if state.open or role == OPEN:
        return
    if token is None:
        raise Refused(401, "this request needs a token (Authorization: Bearer ...): the "
                           "operator's, or a credential issued with its wall")
    if state.is_operator(token):
        return
    grant = state.walls.grant(token)
    if grant is None:
        raise Refused(401, "the token is not one this server holds")
    if role == OPERATOR:
        raise Refused(403, "this request needs the operator's token")
    if grant.wall != params.get("wid"):
        raise Refused(403, f"this credential is for wall {grant.wall}")
    if role == DRIVER and grant.role != DRIVER:
        raise Refused(403, "posting frames needs the wall's driver credential")
    if role == NODE:
        if grant.role != NODE:
            raise Refused(403, "this needs a node credential of the wall")
        if "tile" in params:
            tile = params["tile"]
            # str.isdigit is true of "²" and "٣", which int() refuses or reads as another
            # number: a tile is written in ASCII digits
            if not (tile.isascii() and tile.isdigit()):
                raise Refused(422, f"tile must be a whole number in ASCII digits, got {tile!r}")
            wanted = [int(tile)]
        else:  # a node's stream: the tiles it asks for, or by default all its credential holds
            try:
                wanted = parse_tiles(params["tiles"], MAX_TILES) if params.get("tiles") else []
            except InputError as exc:
                raise Refused(422, str(exc)) from None
        if not grant.tiles.issuperset(wanted):
            raise Refused(403, f"this node credential holds tiles {sorted(grant.tiles)}, "
                               f"not tiles {params.get('tile') or params.get('tiles')}")
