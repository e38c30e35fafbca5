"""One contract, one validator: the wall, frame and settings documents are the models of
``wallcull.documents`` at every door. The command line and the server refuse the same documents
(one line, exit 2; a 422 with a detail) and accept the same; the OpenAPI document passes the
OpenAPI validator and the AsyncAPI document the official AsyncAPI 3.0 JSON Schema (vendored in
tests/schemas with its licence), and both carry Markdown, not reStructuredText."""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from fastapi.testclient import TestClient
from openapi_spec_validator import OpenAPIV31SpecValidator

from wallcull import cli, documents
from wallcull.server import create_app
from wallcull.server.asyncapi import document as asyncapi_document

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "contract-t0ken"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
WALL = {"cols": 2, "rows": 2, "tile_size": [0.6, 0.34], "distance": 2.0}
FRAME = {"position": [0.0, 20.0, 300.0], "orientation": [1.0, 0.0, 0.0, 0.0]}
SCREENS = json.loads((ROOT / "examples" / "wall-cave.json").read_text())
LIGHTS = json.loads((ROOT / "scenes" / "powerplant-lights3.json").read_text())


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(None, token=TOKEN, state=None)) as c:
        yield c


def _patched(doc, path, value):
    out = copy.deepcopy(doc)
    *parents, key = path
    node = out
    for p in parents:
        node = node[p]
    if value is KeyError:
        del node[key]
    else:
        node[key] = value
    return out


BAD_WALLS = [
    ({"cols": 0}, "cols"), ({"cols": 3.5}, "cols"), ({"cols": True}, "cols"),
    ({"tile_size": [0.6]}, "tile_size"), ({"tile_size": [0.6, "0.3"]}, "tile_size"),
    ({"gap": [-0.7, 0]}, "overlaps a whole tile"), ({"near": 3, "far": 2}, "near < far"),
    ({"cols": 257, "tile_size": [1e-3, 1e-3]}, "cols"),
    ({"distance": -1}, "distance"), ({"colour": "red"}, "colour"),
    ({"resolution": [1920, 0]}, "resolution"),
]
BAD_SCREENS = [
    (("screens", 0, "top_left"), [0.1, 1.5, -1.5], "not a rectangle"),
    (("screens", 0, "bottom_right"), [-1.5, -1.5, -1.5], "degenerate"),
    (("screens", 0, "top_left"), KeyError, "top_left"),
    (("screens",), [], "screens"),
    (("far",), 0.01, "near < far"),
]
BAD_FRAMES = [
    ({"orientation": [1, 0, 0, 0.5]}, "unit quaternion"),
    ({"orientation": [1, 0, 0]}, "orientation"),
    ({"position": [0, 0, float("inf")]}, "position"),
    ({"eye": [0, 0, -1.95]}, "in front"),
    ({"stereo": {"ipd": 0.06, "head": [1, 1, 0, 0]}}, "unit quaternion"),
    ({"stereo": {"ipd": 0}}, "ipd"),
    ({"stereo": {"ipd": 0.06, "tilt": 1}}, "tilt"),
    ({"where": 1}, "where"),
]
BAD_SETTINGS = [
    (("lights", 0, "type"), "area", "type"),
    (("lights", 1, "direction"), KeyError, "direction"),
    (("lights", 1, "angle"), 90, "angle"),
    (("mirrors", 0, "normal"), [0, 0, 0], "normal"),
    (("mirrors", 1, "polygon", 0), [0, 99, 0], "polygon"),
    (("mirrors", 1, "polygon", 3), [0.0, 5.0, -44.0], "convex"),  # a corner turned in
    (("mirrors", 1, "polygon", 2), [30.0, 0.0, -44.0], "convex"),  # a corner twice
    (("mirrors", 1, "polygon"), [[-30.0, 0.0, -44.0], [30.0, 0.0, -44.0], [-30.0, 25.0, -44.0],
                                 [30.0, 25.0, -44.0]], "convex"),  # crossing itself
    (("mirrors", 1, "polygon"), [[-30.0, 0.0, -44.0], [30.0, 0.0, -44.0], [0.0, 0.0, -44.0]],
     "convex"),  # no area: back along its first edge
    (("mirrors", 1, "name"), "floor", "two mirrors named 'floor'"),
    (("lights", 0, "name"), "flood", "two lights named 'flood'"),
    (("up",), [0, 0, 0], "up"),
    (("shadows",), True, "shadows"),
]


def cli_refusal(capsys, *argv) -> str:
    assert cli.main(list(argv)) == 2
    err = capsys.readouterr().err
    assert err.startswith("wallcull: error: ") and err.count("\n") == 1, err
    return err


def server_refusal(client, body) -> str:
    r = client.post("/walls", json=body, headers=AUTH)
    assert r.status_code == 422, r.text
    return r.json()["detail"]


def _spot_light_settings():
    """The example settings, with the spot light second (as BAD_SETTINGS patches them)."""
    spot = next(light for light in LIGHTS["lights"] if light.get("type") == "spot")
    assert LIGHTS["lights"][1] is spot and len(LIGHTS["mirrors"]) >= 2
    assert LIGHTS["mirrors"][1].get("polygon"), "the second mirror is bounded by a polygon"
    return LIGHTS


@pytest.mark.parametrize("patch, what", BAD_WALLS)
def test_a_bad_grid_is_refused_alike_by_the_command_line_and_the_server(capsys, client, patch,
                                                                         what):
    wall = {**WALL, **patch}
    err = cli_refusal(capsys, "cull", "powerplant", "--wall", json.dumps(wall),
                      "--frame", json.dumps(FRAME))
    detail = server_refusal(client, {"wall": wall, "scene": "powerplant"})
    assert what in err and what in detail, (err, detail)


@pytest.mark.parametrize("path, value, what", BAD_SCREENS)
def test_bad_screens_are_refused_alike(capsys, client, path, value, what):
    wall = _patched(SCREENS, path, value)
    err = cli_refusal(capsys, "cull", "powerplant", "--wall", json.dumps(wall),
                      "--frame", json.dumps(FRAME))
    detail = server_refusal(client, {"wall": wall, "scene": "powerplant"})
    assert what in err and what in detail, (err, detail)


@pytest.mark.parametrize("patch, what", BAD_FRAMES)
def test_a_bad_frame_is_refused_alike(capsys, client, patch, what):
    frame = {**FRAME, **patch}
    err = cli_refusal(capsys, "cull", "powerplant", "--wall", json.dumps(WALL),
                      "--frame", json.dumps(frame))
    r = client.post("/walls", json={"wall": WALL, "scene": "powerplant"}, headers=AUTH)
    wid = r.json()["id"]
    try:
        r = client.post(f"/walls/{wid}/frames", content=json.dumps({"frame": frame}),
                        headers={**AUTH, "Content-Type": "application/json"})  # inf as JSON5
        assert r.status_code == 422, r.text
        assert what in err and what in r.json()["detail"], (err, r.text)
    finally:
        client.delete(f"/walls/{wid}", headers=AUTH)


@pytest.mark.parametrize("path, value, what", BAD_SETTINGS)
def test_bad_settings_are_refused_alike(capsys, client, tmp_path, path, value, what):
    settings = _patched(_spot_light_settings(), path, value)
    (tmp_path / "s.json").write_text(json.dumps(settings))
    err = cli_refusal(capsys, "cull", "powerplant", "--wall", json.dumps(WALL), "--frame",
                      json.dumps(FRAME), "--settings", str(tmp_path / "s.json"))
    detail = server_refusal(client, {"wall": WALL, "scene": "powerplant", "settings": settings})
    assert what in err and what in detail, (err, detail)


def test_good_documents_pass_both(capsys, client, tmp_path):
    (tmp_path / "s.json").write_text(json.dumps(_spot_light_settings()))
    for wall in (WALL, SCREENS):
        frame = {**FRAME, "stereo": {"ipd": 0.064}}
        assert cli.main(["cull", "powerplant", "--wall", json.dumps(wall), "--frame",
                         json.dumps(frame), "--settings", str(tmp_path / "s.json"),
                         "--json"]) == 0
        tiles = json.loads(capsys.readouterr().out)["tiles"]
        r = client.post("/walls", json={"wall": wall, "scene": "powerplant",
                                        "settings": LIGHTS}, headers=AUTH)
        assert r.status_code == 201, r.text
        wid = r.json()["id"]
        r = client.post(f"/walls/{wid}/frames", json={"frame": frame, "packets": True},
                        headers=AUTH)
        assert r.status_code == 200, r.text
        assert len(r.json()["packets"]) == len(tiles)
        client.delete(f"/walls/{wid}", headers=AUTH)


def test_one_line_names_the_place_and_counts_the_rest():
    with pytest.raises(documents.InputError) as exc:
        documents.parse(documents.Wall, {"cols": 0, "rows": -1, "tile_size": [1, 1],
                                         "distance": 1, "colour": 1}, "wall")
    assert str(exc.value) == "unknown wall key 'colour' (and 2 more problems)"
    with pytest.raises(documents.InputError, match=r"^wall screens\[0\] is missing 'top_left'$"):
        documents.parse(documents.Wall, _patched(SCREENS, ("screens", 0, "top_left"), KeyError),
                        "wall")
    with pytest.raises(documents.InputError,
                       match=r"^frame orientation must be a list of 4 numbers, got \[1, 0\]$"):
        documents.parse(documents.FrameSpec, {**FRAME, "orientation": [1, 0]}, "frame")


# ------------------------------------------------------------------ the two documents


def test_openapi_passes_the_openapi_validator(client):
    for app in (client.app, create_app(None, state=None)):  # with and without a token
        doc = app.openapi()
        errors = [f"{list(e.absolute_path)}: {e.message}"
                  for e in OpenAPIV31SpecValidator(doc).iter_errors()]
        assert not errors, errors[:5]
    broken = copy.deepcopy(client.app.openapi())
    broken["paths"]["/walls"]["post"]["responses"]["201"]["links"]["Barrier"]["parameters"][
        "frame"] = 0  # the kind of error it used to have
    assert list(OpenAPIV31SpecValidator(broken).iter_errors())


@pytest.fixture(scope="module")
def asyncapi_schema():
    return jsonschema.Draft7Validator(
        json.loads((ROOT / "tests" / "schemas" / "asyncapi-3.0.0.json").read_text()))


def test_asyncapi_passes_the_official_schema(client, asyncapi_schema):
    doc = client.get("/asyncapi.json").json()
    assert doc == json.loads(json.dumps(asyncapi_document(client.app.version)))
    errors = [f"{list(e.absolute_path)}: {e.message}" for e in asyncapi_schema.iter_errors(doc)]
    assert not errors, errors[:5]
    for path, value in ((("operations", "tileControl", "action"), "publish"),  # AsyncAPI 2's
                        (("channels", "tileStream", "address"), 7),
                        (("components", "messages", "packet", "payload"), "Packet")):
        assert list(asyncapi_schema.iter_errors(_patched(doc, path, value))), path


def test_both_documents_have_the_same_models(client):
    """The AsyncAPI payloads are the pydantic models' (strict: a key a model lacks is
    refused), and the documents both hold share one schema: the frame's, the packet's."""
    from wallcull.server.asyncapi import schema
    from wallcull.server.messages import Packet

    packet = schema("Packet")
    assert set(packet["properties"]) == set(Packet.model_fields)
    assert packet["additionalProperties"] is False
    openapi = client.app.openapi()["components"]["schemas"]
    asyncapi = client.get("/asyncapi.json").json()["components"]["schemas"]
    for name in ("FrameSpec", "StereoSpec", "Packet", "Shadow"):
        assert set(asyncapi[name]["properties"]) == set(openapi[name]["properties"]), name
        for key, value in asyncapi[name]["properties"].items():
            for bound in ("minimum", "maximum", "minItems", "maxItems"):
                assert value.get(bound) == openapi[name]["properties"][key].get(bound), key


def test_descriptions_are_markdown(client):
    text = json.dumps(client.app.openapi()) + json.dumps(client.get("/asyncapi.json").json())
    assert not re.findall(r":[a-z]+:`", text), "reStructuredText roles"
    assert "``" not in text, "reStructuredText literals"
    assert "`wallcull.uploads`" in text and "`ids=true`" in text


def test_a_tiny_vector_is_a_direction_not_a_nan():
    """A spot light's direction, a mirror's normal and ``up`` are directions: one whose
    length underflows (1e-300 squared is 0) points the same way as any other."""
    from wallcull import settings

    def parsed(scale):
        return settings.parse({
            "up": [0, scale, 0],
            "lights": [{"type": "spot", "position": [0, 8, 0], "direction": [0, -scale, scale]}],
            "mirrors": [{"point": [0, 0, 0.2], "normal": [0, 0, scale]}]})

    tiny, plain = parsed(1e-300), parsed(1.0)
    np.testing.assert_allclose(tiny.lights[0].direction, plain.lights[0].direction, rtol=1e-15)
    np.testing.assert_allclose(tiny.mirrors[0].plane, plain.mirrors[0].plane, rtol=1e-15)
    np.testing.assert_allclose(tiny.up, plain.up, rtol=1e-15)
    assert np.isfinite(tiny.lights[0].direction).all()


def test_one_problem_is_told_once(client):
    """An array whose element is refused is not also "too short" (pydantic adds that)."""
    with pytest.raises(documents.InputError) as exc:
        documents.parse(documents.FrameSpec, {"position": [1e300, 0, 10],
                                              "orientation": [1, 0, 0, 0]}, "frame")
    assert "more problem" not in str(exc.value), exc.value
    r = client.post("/walls", json={"wall": WALL, "scene": "powerplant"}, headers=AUTH)
    wid = r.json()["id"]
    try:
        r = client.post(f"/walls/{wid}/frames", headers={**AUTH, "Content-Type":
                                                         "application/json"},
                        content=b'{"frame": {"position": [NaN, 0, 0], "orientation": [1, 0, 0, 0]}}')
        assert r.status_code == 422 and r.json()["detail"] == \
            "body.frame.position.0: Input should be a finite number", r.text
    finally:
        client.delete(f"/walls/{wid}", headers=AUTH)
