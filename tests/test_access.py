"""Who may do what (wallcull.server.access, .gate): the operator's token, a wall's driver and
node credentials, each held to its wall, role and tiles; a server without a token lets all
through; browsers only from allowed origins; OPTIONS, 405 and strict types at the boundary."""

from __future__ import annotations

import html
import json
import re

import msgpack
import pytest
from hypothesis import given, settings, strategies as st
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketDenialResponse
from starlette.websockets import WebSocketDisconnect

from wallcull.server import create_app

TOKEN = "operator-t0ken"
OPERATOR = {"Authorization": f"Bearer {TOKEN}"}
WALL = {"cols": 2, "rows": 2, "tile_size": [0.6, 0.34], "distance": 2.0}
FRAME = {"position": [0.0, 20.0, 300.0], "orientation": [1.0, 0.0, 0.0, 0.0]}
ORIGIN = "https://wall.lab.example"


def bearer(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(None, token=TOKEN, origins=(ORIGIN,))) as c:
        yield c


@pytest.fixture
def wall(client):
    """A wall whose tiles 2 and 3 share one node credential; its answer, with credentials."""
    r = client.post("/walls", json={"wall": WALL, "scene": "fatehpur", "nodes": [[2, 3]]},
                    headers=OPERATOR)
    assert r.status_code == 201, r.text
    info = r.json()
    assert client.post(f"/walls/{info['id']}/frames", json={"frame": FRAME},
                       headers=OPERATOR).status_code == 200
    yield info
    client.delete(f"/walls/{info['id']}", headers=OPERATOR)


def node(info, tile: int) -> dict:
    return bearer(next(n["token"] for n in info["credentials"]["nodes"] if tile in n["tiles"]))


def test_credentials_are_issued_with_the_wall(wall):
    creds = wall["credentials"]
    assert sorted(map(tuple, (n["tiles"] for n in creds["nodes"]))) == [(0,), (1,), (2, 3)]
    tokens = [creds["driver"], *(n["token"] for n in creds["nodes"])]
    assert len(set(tokens)) == 4 and all(len(t) > 30 for t in tokens)


def test_each_credential_holds_its_role_wall_and_tiles(client, wall):
    wid, creds = wall["id"], wall["credentials"]
    driver = bearer(creds["driver"])
    other = client.post("/walls", json={"wall": WALL, "scene": "fatehpur"},
                        headers=OPERATOR).json()
    try:
        client.post(f"/walls/{other['id']}/frames", json={"frame": FRAME}, headers=OPERATOR)
        cases = [  # (method, path, body, headers, status)
            ("POST", f"/walls/{wid}/frames", {"frame": FRAME}, driver, 200),
            ("POST", f"/walls/{wid}/frames", {"frame": FRAME}, node(wall, 0), 403),
            ("POST", f"/walls/{other['id']}/frames", {"frame": FRAME}, driver, 403),
            ("POST", "/walls", {"wall": WALL, "scene": "fatehpur"}, driver, 403),
            ("DELETE", f"/walls/{wid}", None, node(wall, 0), 403),
            ("GET", f"/walls/{wid}/tiles/0/packets/0", None, node(wall, 0), 200),
            ("GET", f"/walls/{wid}/tiles/1/packets/0", None, node(wall, 0), 403),
            ("GET", f"/walls/{wid}/tiles/3/packets/0", None, node(wall, 2), 200),
            ("GET", f"/walls/{wid}/tiles/0/packets/0", None, driver, 403),
            ("GET", f"/walls/{other['id']}/tiles/0/packets/0", None, node(wall, 0), 403),
            ("GET", f"/walls/{other['id']}/tiles/0/packets/0", None, node(other, 0), 200),
            ("POST", f"/walls/{wid}/tiles/1/ack", {"frame": 0}, node(wall, 0), 403),
            ("POST", f"/walls/{wid}/tiles/1/ack", {"frame": 0}, driver, 403),
            ("POST", f"/walls/{wid}/tiles/0/ack", {"frame": 0}, node(wall, 0), 204),
            ("POST", f"/walls/{wid}/tiles/2/ack", {"frame": 0}, node(wall, 3), 204),
            ("POST", f"/walls/{wid}/tiles/1/ack", {"frame": 0}, bearer("wcn_forged"), 401),
            ("POST", f"/walls/{wid}/tiles/1/ack", {"frame": 0}, {}, 401),
        ]
        for method, path, body, headers, status in cases:
            r = client.request(method, path, json=body, headers=headers)
            assert r.status_code == status, (method, path, r.text)
            if status in (401, 403):
                assert r.json()["detail"]
        # only tiles 0 and 2 were acknowledged, by their nodes: no rogue completed the barrier
        assert client.get(f"/walls/{wid}/barrier/0?timeout=0").json()["acked"] == 2
    finally:
        client.delete(f"/walls/{other['id']}", headers=OPERATOR)


def test_a_deleted_walls_credentials_die_with_it(client, wall):
    """... checked first (401, as any token the server does not hold: the API's rule, which
    its fuzzer checks); the operator is told the wall is gone (404), and so is anyone who
    asks ``GET /walls/{wid}``, which needs no token: the driver and the nodes ask it when
    refused, and say that the wall was deleted."""
    info = client.post("/walls", json={"wall": WALL, "scene": "fatehpur"},
                       headers=OPERATOR).json()
    wid, driver = info["id"], bearer(info["credentials"]["driver"])
    assert client.post(f"/walls/{wid}/frames", json={"frame": FRAME},
                       headers=driver).status_code == 200
    assert client.delete(f"/walls/{wid}", headers=OPERATOR).status_code == 204
    for headers in (driver, node(info, 0), bearer("wcn_never-issued")):
        r = client.post(f"/walls/{wid}/frames", json={"frame": FRAME}, headers=headers)
        assert r.status_code == 401, headers
        r = client.get(f"/walls/{wid}/tiles/0/packets/0", headers=headers)
        assert r.status_code == 401, headers
    for path, token in ((f"/walls/{wid}/frames/stream", info["credentials"]["driver"]),
                        (f"/walls/{wid}/tiles/0/stream", node(info, 0)["Authorization"][7:]),
                        (f"/walls/{wid}/nodes/stream", node(info, 0)["Authorization"][7:])):
        with pytest.raises(WebSocketDenialResponse) as denied:
            with client.websocket_connect(f"{path}?token={token}"):
                pass
        assert denied.value.status_code == 401, path
    gone = (404, f"no wall {wid!r}")
    r = client.post(f"/walls/{wid}/frames", json={"frame": FRAME}, headers=OPERATOR)
    assert (r.status_code, r.json()["detail"]) == gone
    r = client.get(f"/walls/{wid}")  # no token
    assert (r.status_code, r.json()["detail"]) == gone
    # nowhere else do they hold anything; no token is still a 401
    r = client.post(f"/walls/{wall['id']}/frames", json={"frame": FRAME}, headers=driver)
    assert r.status_code == 401
    assert client.post(f"/walls/{wid}/frames", json={"frame": FRAME}).status_code == 401


def test_credentials_are_checked_before_the_body_is_read(client, wall):
    """A refused request's body is never read: a declared 1 GB body gets its 401 or 403 at
    once, not a 413, and a malformed one not a 422."""
    for headers, status in (({}, 401), (node(wall, 0), 403)):
        r = client.post(f"/walls/{wall['id']}/frames", content=b"{not json",
                        headers={**headers, "Content-Type": "application/json"})
        assert r.status_code == status
        r = client.post("/scenes?name=big", content=b"glTF",
                        headers={**headers, "Content-Length": str(1 << 30)})
        assert r.status_code == (401 if not headers else 403)


def test_streams_need_the_tiles_node_credential(client, wall):
    wid = wall["id"]
    for token, status in ((None, 401), ("nope", 401), (wall["credentials"]["driver"], 403),
                          (node(wall, 1)["Authorization"][7:], 403)):
        query = f"?token={token}" if token else ""
        with pytest.raises(WebSocketDenialResponse) as denied:
            with client.websocket_connect(f"/walls/{wid}/tiles/0/stream{query}"):
                pass
        assert denied.value.status_code == status
    with client.websocket_connect(f"/walls/{wid}/tiles/0/stream",
                                  headers=node(wall, 0)) as ws:  # the header works too
        assert msgpack.unpackb(ws.receive_bytes())["frame"] == 0


def test_a_server_without_a_token_lets_everyone_through():
    with TestClient(create_app(None)) as c:
        info = c.post("/walls", json={"wall": WALL, "scene": "fatehpur"}).json()
        assert "credentials" in info  # issued all the same, for clients written for both
        wid = info["id"]
        assert c.post(f"/walls/{wid}/frames", json={"frame": FRAME}).status_code == 200
        assert c.get(f"/walls/{wid}/tiles/1/packets/0").status_code == 200
        assert c.post(f"/walls/{wid}/tiles/1/ack", json={"frame": 0}).status_code == 204
        with c.websocket_connect(f"/walls/{wid}/tiles/0/stream") as ws:
            assert msgpack.unpackb(ws.receive_bytes())["frame"] == 0
        assert "bearer" not in c.get("/openapi.json").text.lower()


def test_options_and_methods_a_path_does_not_take(client, wall):
    r = client.options(f"/walls/{wall['id']}")
    assert r.status_code == 204 and r.headers["allow"] == "DELETE, GET, HEAD, OPTIONS"
    r = client.options("/walls")
    assert r.headers["allow"] == "GET, HEAD, OPTIONS, POST"
    assert client.options("/nowhere").status_code == 404
    r = client.patch(f"/walls/{wall['id']}", headers=OPERATOR)
    assert r.status_code == 405 and r.headers["allow"] == "DELETE, GET, HEAD, OPTIONS"
    r = client.head(f"/walls/{wall['id']}/frames")
    assert r.status_code == 405 and r.headers["allow"] == "OPTIONS, POST"


def test_head_is_a_get_without_its_body(client, wall):
    for path in (f"/walls/{wall['id']}", "/walls", "/openapi.json", "/", f"/walls/{wall['id']}/view", "/docs"):
        got, head = client.get(path, headers=OPERATOR), client.head(path, headers=OPERATOR)
        assert head.status_code == got.status_code == 200, path
        assert head.content == b"" and got.content, path
        assert head.headers["content-length"] == str(len(got.content)), path
        assert head.headers["content-type"] == got.headers["content-type"], path
    for path in ("/walls/0123456789ab", "/walls/nowhere", "/nowhere"):  # refusals too
        got, head = client.get(path, headers=OPERATOR), client.head(path, headers=OPERATOR)
        assert head.status_code == got.status_code >= 400 and head.content == b"", path


def test_cors_answers_allowed_origins_only(client):
    preflight = {"Origin": ORIGIN, "Access-Control-Request-Method": "POST",
                 "Access-Control-Request-Headers": "authorization, content-type"}
    r = client.options("/walls", headers=preflight)
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == ORIGIN
    assert "authorization" in r.headers["access-control-allow-headers"].lower()
    r = client.options("/walls", headers={**preflight, "Origin": "https://evil.example"})
    assert r.status_code == 400 and "access-control-allow-origin" not in r.headers
    r = client.get("/walls", headers={"Origin": ORIGIN})
    assert r.headers["access-control-allow-origin"] == ORIGIN
    assert "access-control-allow-origin" not in client.get(
        "/walls", headers={"Origin": "https://evil.example"}).headers


def test_websocket_origins_are_checked(client, wall):
    path = f"/walls/{wall['id']}/tiles/0/stream?token={TOKEN}"
    with pytest.raises(WebSocketDenialResponse) as denied:
        with client.websocket_connect(path, headers={"Origin": "https://evil.example"}):
            pass
    assert denied.value.status_code == 403 and "origin" in denied.value.json()["detail"]
    for origin in (ORIGIN, "http://testserver"):  # allowed, and the server's own pages
        with client.websocket_connect(path, headers={"Origin": origin}) as ws:
            assert msgpack.unpackb(ws.receive_bytes())["frame"] == 0


@pytest.mark.parametrize("body,where", [
    ({"frame": False}, "body.frame"), ({"frame": "7"}, "body.frame"),
    ({"frame": 1.5}, "body.frame")])
def test_numbers_are_numbers(client, wall, body, where):
    r = client.post(f"/walls/{wall['id']}/tiles/0/ack", json=body, headers=OPERATOR)
    assert r.status_code == 422 and where in r.json()["detail"]


@pytest.mark.parametrize("frame", [
    {**FRAME, "position": [True, 0, 0]}, {**FRAME, "position": ["1", 0, 0]},
    {**FRAME, "orientation": [1, 0, 0, 2]}])
def test_frames_are_held_to_their_schema(client, wall, frame):
    r = client.post(f"/walls/{wall['id']}/frames", json={"frame": frame, "number": 7},
                    headers=OPERATOR)
    assert r.status_code == 422
    r = client.post(f"/walls/{wall['id']}/frames", json={"frame": FRAME, "number": "7"},
                    headers=OPERATOR)
    assert r.status_code == 422 and "number" in r.json()["detail"]


def test_msgpack_nested_1000_deep_is_a_400(client, wall):
    deep: dict = {"frame": FRAME}
    inner = deep
    for _ in range(1000):
        inner["x"] = {}
        inner = inner["x"]
    for body in (msgpack.packb(deep), b"\x91" * 1000 + b"\xc0"):
        r = client.post(f"/walls/{wall['id']}/frames", content=body,
                        headers={**OPERATOR, "Content-Type": "application/msgpack"})
        assert r.status_code == 400 and "deeper" in r.json()["detail"], r.text
    r = client.post(f"/walls/{wall['id']}/frames", content=b"{}",
                    headers={**OPERATOR, "Content-Type": "text/plain"})
    assert r.status_code == 415


def test_the_schema_declares_security_links_and_bodies(client):
    doc = client.get("/openapi.json").json()
    assert doc["components"]["securitySchemes"]["bearer"]["scheme"] == "bearer"
    paths = doc["paths"]
    assert paths["/walls"]["post"]["security"] == [{"bearer": []}]
    assert "security" not in paths["/walls"]["get"]
    assert paths["/walls/{wid}/tiles/{tile}/packets/{frame}"]["get"]["security"]
    links = paths["/walls"]["post"]["responses"]["201"]["links"]
    assert {ln["operationId"] for ln in links.values()} >= {
        "getWall", "postFrame", "getPacket", "acknowledge", "barrier", "deleteWall"}
    assert paths["/walls/{wid}/frames"]["post"]["responses"]["200"]["links"]
    body = paths["/walls/{wid}/frames"]["post"]["requestBody"]["content"]["application/json"]
    assert body["schema"]["$ref"] == "#/components/schemas/FramePost"
    spec = doc["components"]["schemas"]["WallSpec"]["properties"]
    assert spec["tile_size"]["items"]["minimum"] > 0 and spec["tile_size"]["minItems"] == 2
    assert doc["components"]["schemas"]["WallCreate"]["properties"]["scene"]["pattern"]


def test_every_pattern_is_refused_in_words(client, wall):
    """A string that does not match its pattern is refused saying what it must be, and what
    was given, never the regular expression itself."""
    from wallcull.server.models import PATTERN_WORDS

    doc = json.dumps(client.get("/openapi.json").json())
    declared = set(re.findall(r'"pattern": "((?:[^"\\]|\\.)*)"', doc))
    assert {json.loads(f'"{p}"') for p in declared} <= set(PATTERN_WORDS)
    wid = wall["id"]
    for method, path, words in [
            ("get", "/walls/nowhere", "a wall id is 12 hexadecimal digits"),
            ("get", "/walls/nowhere/view", "a wall id is 12 hexadecimal digits"),
            ("get", f"/walls/{wid}/tiles/0/packets/next", "a frame is 'latest' or a frame number"),
            ("get", f"/walls/{wid}/view?tiles=zz", "tiles are 'all' or tile numbers"),
            ("get", f"/walls/{wid}/view?size=1x", "a size is WIDTHxHEIGHT"),
            ("get", "/scenes/.hidden", "a scene name is a plain file name"),
            ("post", "/scenes?name=.hidden", "an upload's name is a plain file name")]:
        r = getattr(client, method)(path, headers=OPERATOR)
        assert r.status_code == 422 and words in html.unescape(r.text), (path, r.text)
        assert "should match" not in r.text and "^" not in html.unescape(r.text), path
    r = client.post("/walls", json={"wall": WALL, "scene": "../x"}, headers=OPERATOR)
    assert r.json()["detail"] == ("body.scene: a scene name is a plain file name of at most 128 "
                                  "letters, digits, '_', '.' and '-', starting with a letter or "
                                  "digit, got '../x'")


@pytest.mark.parametrize("tile", ["%C2%B2", "%D9%A3", "%EF%BC%91", "1%C2%B2", "-1", "0x1"])
def test_tile_numbers_in_other_digits_are_422_never_500(client, wall, tile):
    """``"²".isdigit()`` is true and ``int("²")`` fails; ``"٣"`` reads as 3: a tile is written
    in ASCII digits, on every route and stream, with every credential."""
    wid = wall["id"]
    for headers in (node(wall, 0), OPERATOR, {}):
        r = client.get(f"/walls/{wid}/tiles/{tile}/packets/latest", headers=headers)
        assert r.status_code in (401, 404, 422), (headers, r.status_code, r.text)
        r = client.post(f"/walls/{wid}/tiles/{tile}/ack", json={"frame": 0}, headers=headers)
        assert r.status_code in (401, 404, 422), (headers, r.status_code, r.text)
    token = node(wall, 0)["Authorization"][7:]
    for query in (f"?token={token}", f"?token={TOKEN}"):
        with pytest.raises((WebSocketDenialResponse, WebSocketDisconnect)) as denied:
            with client.websocket_connect(f"/walls/{wid}/tiles/{tile}/stream{query}") as ws:
                ws.receive_bytes()
        exc = denied.value
        assert getattr(exc, "status_code", None) in (404, 422) or \
            getattr(exc, "code", None) == 1008, exc


@pytest.mark.parametrize("headers, query", [
    ({"Authorization": "Bearer garbage"}, "good"),
    ({"Authorization": "garbage"}, "good"),
    ({"Authorization": "Basic Zm9vOmJhcg=="}, "good"),
    ({"Authorization": "Bearer good"}, "other"),
    ({}, "good&token=other"),
])
def test_a_stream_whose_credentials_disagree_is_refused(client, wall, headers, query):
    """One request, one credential: a valid ``?token=`` beside a garbage or different
    ``Authorization`` is a 401, whichever a check would have read."""
    good = node(wall, 0)["Authorization"][7:]
    other = node(wall, 1)["Authorization"][7:]
    fill = lambda text: text.replace("good", good).replace("other", other)  # noqa: E731
    headers = {k: fill(v) for k, v in headers.items()}
    for path in (f"/walls/{wall['id']}/tiles/0/stream", f"/walls/{wall['id']}/nodes/stream",
                 f"/walls/{wall['id']}/console/stream"):
        with pytest.raises(WebSocketDenialResponse) as denied:
            with client.websocket_connect(f"{path}?token={fill(query)}", headers=headers):
                pass
        assert denied.value.status_code == 401, (path, denied.value.json())
    # the same credential twice, or once, is fine
    with client.websocket_connect(f"/walls/{wall['id']}/tiles/0/stream?token={good}",
                                  headers={"Authorization": f"Bearer {good}"}) as ws:
        assert msgpack.unpackb(ws.receive_bytes())["frame"] == 0


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 300), st.lists(st.lists(st.integers(0, 299), max_size=5), max_size=6),
       st.integers(0, 3))
def test_a_walls_credentials_kept_compactly_grant_what_they_were_issued_for(tiles, nodes, pad):
    """``credentials.Issued`` (one array of digests, one of tiles) answers for every issued
    token exactly what a dict of digests to grants did, nothing for any other token (one
    that shares a digest's first 8 bytes too), and writes the same rows."""
    import json

    from wallcull import credentials as cr

    groups = [g for g in nodes if all(0 <= t < tiles for t in g)]
    taken: set[int] = set()
    groups = [g for g in groups if not taken.intersection(g) and not taken.update(g)]
    shown, issued = cr.issue("w1", tiles, groups)
    want = {cr.digest(shown["driver"]): cr.Grant("w1", cr.DRIVER)}
    want.update({cr.digest(n["token"]): cr.Grant("w1", cr.NODE, frozenset(n["tiles"]))
                 for n in shown["nodes"]})
    assert len(issued) == len(want) == len(cr.node_groups(tiles, groups)[0])
    for token in [shown["driver"], *(n["token"] for n in shown["nodes"])]:
        assert issued.find(cr.raw_digest(token)) == want[cr.digest(token)]
    assert issued.find(cr.raw_digest("wcn_not-issued")) is None
    near = cr.raw_digest(shown["driver"])[:8] + bytes([pad]) * 24  # same prefix, not it
    assert issued.find(near) is None
    assert issued.nodes() == sorted(sorted(g.tiles) for g in want.values() if g.role == cr.NODE)
    rows = {d: (role, json.loads(t)) for d, role, t in issued.rows()}
    assert rows == {d: (g.role, sorted(g.tiles)) for d, g in want.items()}
    again = cr.Issued("w1", [bytes.fromhex(d) for d in rows],
                      [None if role == cr.DRIVER else t for role, t in rows.values()])
    assert list(again.rows()) == list(issued.rows())


@pytest.mark.parametrize("accept", ["application/json", "application/msgpack"])
def test_a_big_walls_credentials_are_shown_whole_and_each_holds_its_tiles(client, accept):
    """More node credentials than the answer encodes in one piece (they are made as it is
    encoded): every tile once, every token its own, in JSON and msgpack, and a token far
    down the list reads its own tile's packet and no other's."""
    from wallcull.server.http import PIECE

    big = {**WALL, "cols": 80, "rows": 60, "tile_size": [0.06, 0.03]}
    assert 80 * 60 > PIECE + 2
    r = client.post("/walls", json={"wall": big, "scene": "fatehpur", "nodes": [[5, 7, 6]]},
                    headers={**OPERATOR, "Accept": accept})
    assert r.status_code == 201, r.text
    info = msgpack.unpackb(r.content) if "msgpack" in accept else r.json()
    wid, nodes = info["id"], info["credentials"]["nodes"]
    try:
        assert len(nodes) == 80 * 60 - 2 and nodes[0]["tiles"] == [5, 6, 7]
        assert sorted(t for n in nodes for t in n["tiles"]) == list(range(80 * 60))
        assert len({n["token"] for n in nodes}) == len(nodes)
        client.post(f"/walls/{wid}/frames", json={"frame": FRAME}, headers=OPERATOR)
        late = nodes[PIECE + 1]
        tile = late["tiles"][0]
        for t, status in ((tile, 200), ((tile + 1) % (80 * 60), 403)):
            assert client.get(f"/walls/{wid}/tiles/{t}/packets/0",
                              headers=bearer(late["token"])).status_code == status
    finally:
        client.delete(f"/walls/{wid}", headers=OPERATOR)


def test_a_query_parameter_given_twice_is_refused(client, wall):
    """Each parameter takes one value: given twice, one of them was used in silence (the
    last ``name`` of an upload, the first ``tiles`` of a page)."""
    wid = wall["id"]
    for path in (f"/walls/{wid}/view?tiles=0&tiles=1", "/scenes?name=a&name=b",
                 f"/walls/{wid}/tiles/0/packets/latest?wait=0&wait=0"):
        r = client.request("POST" if path.startswith("/scenes") else "GET", path,
                           headers=OPERATOR)
        assert r.status_code == 422 and "more than once" in html.unescape(r.text), (path, r.text)
