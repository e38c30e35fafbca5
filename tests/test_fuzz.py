"""The HTTP API fuzzed from its own OpenAPI schema (schemathesis), in process over ASGI.

Bounded (25 examples per operation and phase, seeded), with the server's token sent most of the
time so that state-changing routes run, and with path parameters pointing at a real wall,
real scenes, tiles, frames, nodes and meshes some of the time. No request may get a 5xx, and
every response must conform to the schema where the schema declares it.
"""

from __future__ import annotations

import trimesh
import numpy as np
import schemathesis
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from schemathesis.checks import not_a_server_error
from schemathesis.python import asgi
from schemathesis.specs.openapi.checks import (content_type_conformance,
                                               response_schema_conformance,
                                               status_code_conformance)

from wallcull.server import create_app

TOKEN = "fuzz-t0ken"
BEARER = f"Bearer {TOKEN}"
WALL = {"cols": 2, "rows": 2, "tile_size": [0.6, 0.34], "distance": 2.0}
FRAME = {"position": [0.0, 20.0, 300.0], "orientation": [1.0, 0.0, 0.0, 0.0]}


def _tiny_glb() -> bytes:
    s = trimesh.Scene()
    for name, x in (("left", -3.0), ("right", 3.0)):
        m = np.eye(4)
        m[:3, 3] = [x, 0, -10]
        s.add_geometry(trimesh.creation.box(), node_name=name, geom_name=name, transform=m)
    return s.export(file_type="glb")


TINY = _tiny_glb()
APP = create_app(None, token=TOKEN, max_walls=6, max_body=64 << 10, max_upload=64 << 10)
schema = schemathesis.openapi.from_asgi("/openapi.json", APP)
schema.config.generation.update(max_examples=25, deterministic=True)


def _setup() -> dict:
    """A scene, a wall with frames and acknowledgements, in the app's own event loop (the one
    schemathesis drives it with)."""
    auth = {"Authorization": BEARER}
    with asgi.get_client(APP) as c:
        assert c.post(f"http://{asgi.HOST}/scenes?name=tiny", data=TINY,
                      headers=auth).status_code == 201
        r = c.post(f"http://{asgi.HOST}/walls", json={"wall": WALL, "scene": "tiny.glb"},
                   headers=auth)
        assert r.status_code == 201, r.text
        wid = r.json()["id"]
        for _ in range(3):
            assert c.post(f"http://{asgi.HOST}/walls/{wid}/frames", json={"frame": FRAME},
                          headers=auth).status_code == 200
        assert c.post(f"http://{asgi.HOST}/walls/{wid}/tiles/0/ack", json={"frame": 1},
                      headers=auth).status_code == 204
        nodes = c.get(f"http://{asgi.HOST}/scenes/tiny.glb?nodes=true").json()["nodes"]
    leaves = [i for i, leaf in enumerate(nodes["leaf"]) if leaf]
    return {"wid": wid, "leaves": leaves, "meshes": [nodes["mesh"][i] for i in leaves]}


REAL = _setup()
WID = REAL["wid"]


def _real_values(path: str) -> dict[str, st.SearchStrategy]:
    """Values of path parameters that name things the server holds."""
    return {
        "wid": st.just(WID),
        "name": st.sampled_from(["tiny.glb", "fatehpur"]) if "meshes" not in path
        and "nodes" not in path else st.just("tiny.glb"),
        "tile": st.sampled_from([0, 1, 3]),
        "frame": st.sampled_from(["latest", "0", "1", "2"]) if "packets" in path
        else st.sampled_from([0, 1, 2]),
        "node": st.sampled_from(REAL["leaves"] + [0]),
        "key": st.sampled_from(REAL["meshes"]),
    }


@schema.hook("flatmap_path_parameters")
def real_objects(context, path_parameters):
    """Two times in three, point the path at things that exist."""
    if not path_parameters:
        return st.just(path_parameters)
    real = _real_values(context.operation.path)
    mapped = st.fixed_dictionaries(
        {k: real[k] if k in real else st.just(v) for k, v in path_parameters.items()})
    return st.one_of(st.just(path_parameters), mapped, mapped)


@schema.hook("flatmap_headers")
def mostly_authorized(context, headers):
    """The token three times in four; otherwise whatever was generated (mostly refused)."""
    headers = dict(headers or {})
    authorized = {**{k: v for k, v in headers.items() if k.lower() != "authorization"},
                  "authorization": BEARER}
    return st.sampled_from([authorized, authorized, authorized, headers])


MOVE = {"left": {"position": [1.0, 0.0, -10.0], "orientation": [0.0, 0.0, 1.0, 0.0]}}
VALID_BODIES = {  # bodies that get past validation, so that the work behind it runs too
    ("POST", "/scenes"): [TINY],
    ("POST", "/walls"): [{"wall": WALL, "scene": "tiny.glb"},
                         {"wall": {**WALL, "gap": [-0.1, 0.05]}, "scene": "fatehpur",
                          "method": "oh", "bounds": "aabb", "history": 2}],
    ("POST", "/walls/{wid}/frames"): [
        {"frame": FRAME}, {"frame": FRAME, "packets": True, "full": True},
        {"frame": {**FRAME, "eye": [0.1, -0.2, 0.5]}, "updates": MOVE, "packets": True,
         "refit": "aabb"}],
    ("POST", "/walls/{wid}/tiles/{tile}/ack"): [{"frame": 0}, {"frame": 2}],
}


@schema.hook("flatmap_body")
def sometimes_a_valid_body(context, body):
    """Often a body that passes validation, besides whatever was generated."""
    valid = VALID_BODIES.get((context.operation.method.upper(), context.operation.path), [])
    return st.sampled_from([body, *valid, *valid])


@schema.hook("map_query")
def short_waits(context, query):
    """Waits for frames and the barrier shortened (still valid), so that the run stays short;
    uploads get a usable name half the time."""
    query = dict(query or {})
    for key in ("wait", "timeout"):
        value = query.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and 0.05 < value <= 10:
            query[key] = 0.05
    return query


@schema.hook("flatmap_query")
def upload_names(context, query):
    if context.operation.path == "/scenes" and context.operation.method.upper() == "POST":
        return st.sampled_from([query, {**(query or {}), "name": "fuzzed"}])
    return st.just(query)


@schemathesis.serializer("model/gltf-binary")
def _glb(ctx, value):
    if isinstance(value, (bytes, bytearray)):
        return bytes(value)
    return str(value).encode()


def _tidy() -> None:
    """Keep the state bounded between cases: only the prepared wall survives, with its
    history intact, and fuzzed uploads are forgotten."""
    walls = APP.state.server.walls
    for wid in [w for w in walls.sessions if w != WID]:
        walls.get(wid).close()
        walls.delete(wid)
    store = APP.state.server.store
    for name in [n for n in store.uploaded if n != "tiny.glb"]:
        store.uploaded.pop(name)
        store.cache.pop(name, None)


DELETES = [0]


@schema.parametrize()
@settings(deadline=None, derandomize=True, max_examples=25,
          suppress_health_check=list(HealthCheck))
def test_api_never_fails_and_keeps_its_schema(case):
    DELETES[0] += case.method.upper() == "DELETE"
    if case.method.upper() == "DELETE" and (case.path_parameters.get("wid") == WID
                                            or DELETES[0] % 2):
        # every other deletion, and any of the prepared wall, deletes a wall of its own
        with asgi.get_client(APP) as c:
            r = c.post(f"http://{asgi.HOST}/walls", json={"wall": WALL, "scene": "tiny.glb"},
                       headers={"Authorization": BEARER})
        if r.status_code == 201:
            case.path_parameters["wid"] = r.json()["id"]
    try:
        case.call_and_validate(checks=[not_a_server_error, status_code_conformance,
                                       content_type_conformance, response_schema_conformance])
    finally:
        _tidy()
    assert WID in APP.state.server.walls.sessions


def test_the_prepared_objects_survived_the_fuzzing():
    """The wall every case pointed at still serves, and the server is healthy."""
    with asgi.get_client(APP) as c:
        assert c.get(f"http://{asgi.HOST}/health").json()["status"] == "ok"
        r = c.get(f"http://{asgi.HOST}/walls/{WID}/tiles/0/packets/latest",
                  headers={"Authorization": BEARER})
        assert r.status_code == 200 and r.json()["tile"] == 0
