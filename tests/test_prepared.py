"""Prepared scenes: a mapped load is the fresh load array for array, reads no triangle, and a
stale or corrupt file is never trusted: it is refused, reported in one line, and rebuilt."""

import asyncio
import logging
from pathlib import Path

import numpy as np
import pytest

from wallcull import instances, prepared
from wallcull import scene as S
from wallcull.cli import main
from wallcull.pipeline import Session
from wallcull.scene import load, prepare
from wallcull.wall import Wall

from .randscene import random_scene

ARRAYS = ("parent", "child_start", "child_count", "children", "is_leaf", "synthetic", "local",
          "world", "mesh_of", "box")


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    """Each test its own cache folder."""
    folder = tmp_path / "cache"
    monkeypatch.setenv("WALLCULL_CACHE", str(folder))
    return folder


@pytest.fixture
def glb(tmp_path):
    path = tmp_path / "random.glb"
    path.write_bytes(random_scene(3, leaves=40).export(file_type="glb"))
    return path


def assert_same_scene(a, b):
    assert list(a.names) == list(b.names) and a.name == b.name
    for key in ARRAYS:
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    assert a.geometry == b.geometry and a.stats == b.stats and a.settings == b.settings
    assert list(a.meshes) == list(b.meshes)
    for key in a.meshes:
        for x, y in zip(a.meshes[key], b.meshes[key]):
            assert x.dtype == y.dtype
            np.testing.assert_array_equal(x, y)
    for kind in ("obb", "aabb"):
        for field in ("center", "axes", "half", "radius"):
            np.testing.assert_array_equal(getattr(a.bounds(kind), field),
                                          getattr(b.bounds(kind), field), err_msg=kind)


@pytest.mark.parametrize("spec", ["powerplant", "fatehpur*2", "glb"])
def test_a_prepared_load_is_the_fresh_load(spec, glb, cache):
    spec = str(glb) if spec == "glb" else spec
    fresh = load(spec, cache="off")
    path, built = prepare(spec)
    assert path.parent == cache and path.is_file() and built is not None
    mapped = load(spec)
    assert mapped.prepared == path and fresh.prepared is None
    assert isinstance(mapped.names, prepared.StringTable)
    assert_same_scene(mapped, fresh)
    assert prepare(spec) == (path, None)  # current: not written again


def test_a_prepared_load_reads_no_triangles(monkeypatch):
    """Culling and fitting a frame of a mapped scene needs its bounds, never its meshes."""
    prepare("powerplant")

    def refuse(*args, **kwargs):
        raise AssertionError("a mesh was read")

    monkeypatch.setattr(instances.MeshTable, "mesh", refuse)
    monkeypatch.setattr(S, "instance_points", refuse)
    monkeypatch.setattr(S, "instance_extremes", refuse)
    scene = load("powerplant")
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [0.6, 0.34], "distance": 2.0})
    from wallcull.fit import FitOptions
    from wallcull.paths import scene_path

    session = Session(scene, wall, fit=FitOptions())
    result = session.frame(scene_path(scene, wall, "orbit", 4)[1])
    assert sum(len(result.visibility.names(t)) for t in range(wall.tiles)) > 0
    assert scene.stats["triangles"] > 900_000


def test_a_stale_prepared_file_is_rebuilt(glb, caplog):
    path, _ = prepare(str(glb))
    glb.write_bytes(random_scene(4, leaves=12).export(file_type="glb"))  # the source changes
    with caplog.at_level(logging.WARNING, logger="wallcull"):
        scene = load(str(glb))
    assert [r.getMessage() for r in caplog.records] == [
        f"wallcull: prepared scene {path} is stale (its source or wallcull changed): "
        "rebuilding it"]
    assert scene.prepared is None
    assert_same_scene(scene, load(str(glb), cache="off"))
    assert load(str(glb)).prepared == path  # rewritten: current again


def test_a_prepared_file_of_other_code_is_stale(monkeypatch, caplog):
    prepare("fatehpur")
    monkeypatch.setattr(S, "_code_version", lambda: "some other wallcull")
    with caplog.at_level(logging.WARNING, logger="wallcull"):
        assert load("fatehpur").prepared is None
    assert "is stale" in caplog.text


def test_the_code_version_follows_the_file_readers(monkeypatch):
    """A prepared file holds what trimesh (and DracoPy) read and what ``gltf.py`` made of it:
    another version of either, or of the module, makes it stale (the readers were left out,
    and a fix there kept serving the old geometry)."""
    from importlib import metadata

    assert {"gltf.py", "validate.py"} <= set(S._BUILDERS)
    S._code_version.cache_clear()
    before = S._code_version()
    real = metadata.version
    monkeypatch.setattr(metadata, "version",
                        lambda name: "0.0.1" if name == "trimesh" else real(name))
    S._code_version.cache_clear()
    try:
        assert S._code_version() != before
    finally:
        monkeypatch.undo()
        S._code_version.cache_clear()
    assert S._code_version() == before


def flip_a_data_byte(path):
    data = bytearray(path.read_bytes())
    data[-100] ^= 0x10
    path.write_bytes(bytes(data))


def truncate(path):
    path.write_bytes(path.read_bytes()[:-64])


def extend(path):
    path.write_bytes(path.read_bytes() + b"\0" * 64)


def garbage(path):
    path.write_bytes(b"not a prepared scene at all")


def bad_header(path):
    data = bytearray(path.read_bytes())
    data[28:32] = b"{{{{"
    path.write_bytes(bytes(data))


def rewrite_header(path, change, checksum=True):
    """The header, parsed, changed by ``change`` and written back in the same length, its
    CRC-32 made to match (as a faulty writer would), or left as it was (damage)."""
    import json
    import zlib

    data = path.read_bytes()
    length, crc = (int(v) for v in np.frombuffer(data[8:24], "<u8"))
    header = json.loads(data[24:24 + length])
    change(header)
    text = json.dumps(header).encode().ljust(length)[:length]
    crc = zlib.crc32(text) if checksum else crc
    path.write_bytes(data[:8] + np.array([length, crc], "<u8").tobytes() + text
                     + data[24 + length:])


def bad_table(path):
    """A header that parses, but whose array table points outside the data."""
    rewrite_header(path, lambda h: h["arrays"]["parent"].__setitem__(2, 10**12))


def arrays_a_list(path):
    """A header of the wrong shape: its table of arrays a list."""
    rewrite_header(path, lambda h: h.__setitem__("arrays", []))


def meta_a_list(path):
    rewrite_header(path, lambda h: h.__setitem__("meta", [["key", 1]]))


def _moved(h):
    """The last array's offset 64 bytes back, still within the data: read from the wrong
    bytes, its table entry alone looks sound."""
    entry = max(h["arrays"].values(), key=lambda e: e[2])
    entry[2] -= 64


def an_offset_moved(path):
    """One digit of the header changed (the scene culled with bounds read from the wrong
    bytes, its shape checks passed): the header's checksum refuses it."""
    rewrite_header(path, _moved, checksum=False)


def arrays_overlap(path):
    """The same move by a writer that checksummed its header: the arrays overlap."""
    rewrite_header(path, _moved)


def an_older_format(path):
    data = bytearray(path.read_bytes())
    data[:8] = b"WCPREP01"
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", [flip_a_data_byte, truncate, extend, garbage, bad_header,
                                    bad_table, arrays_a_list, meta_a_list, an_offset_moved,
                                    arrays_overlap, an_older_format])
def test_a_corrupt_prepared_file_is_refused_and_rebuilt(damage, caplog):
    path, _ = prepare("fatehpur")
    damage(path)
    with pytest.raises(prepared.Corrupt):
        prepared.read(path)
    with caplog.at_level(logging.WARNING, logger="wallcull"):
        scene = load("fatehpur")
    assert len(caplog.records) == 1 and "is corrupt (" in caplog.text
    assert "\n" not in caplog.records[0].getMessage()
    assert scene.prepared is None
    assert_same_scene(scene, load("fatehpur", cache="off"))
    prepared.read(path)  # rebuilt: sound again


def test_cache_modes(cache):
    assert load("fatehpur").prepared is None and not cache.exists()  # read: nothing written
    assert load("fatehpur", cache="write").prepared is None  # built, and written
    assert load("fatehpur").prepared is not None
    path = next(cache.iterdir())
    garbage(path)
    assert load("fatehpur", cache="off").prepared is None  # off: not even looked at
    assert path.read_bytes() == b"not a prepared scene at all"
    with pytest.raises(ValueError):
        load("fatehpur", cache="sometimes")


def test_options_have_their_own_prepared_files():
    a, _ = prepare("fatehpur")
    b, _ = prepare("fatehpur", hierarchy="file")
    c, _ = prepare("fatehpur", branching=4)
    assert len({a, b, c}) == 3
    assert load("fatehpur", hierarchy="file").hierarchy == "file"


def test_the_format_round_trips_any_array(tmp_path):
    rng = np.random.default_rng(0)
    arrays = {"f64": rng.normal(size=(5, 4, 4)), "f32": rng.normal(size=(7, 3)).astype("f4"),
              "i32": np.arange(-3, 9, dtype="<i4").reshape(4, 3), "bool": rng.random(9) > 0.5,
              "empty": np.zeros((0, 3)), "big_endian": np.arange(5, dtype=">i8"),
              "u8": np.frombuffer(b"abc", dtype=np.uint8)}
    path = tmp_path / "x.wcprep"
    size = prepared.write(path, arrays, {"hello": [1, "two"]})
    assert path.stat().st_size == size and size % 64 == 0
    back, meta = prepared.read(path)
    assert meta == {"hello": [1, "two"]} and prepared.read_meta(path) == meta
    assert set(back) == set(arrays)
    for k, a in arrays.items():
        np.testing.assert_array_equal(back[k], a)
        assert back[k].shape == a.shape
    back["f64"][0, 0, 0] = 42.0  # copy-on-write: writable, and the file is untouched
    assert prepared.read(path)[0]["f64"][0, 0, 0] == arrays["f64"][0, 0, 0]
    assert not list(tmp_path.glob(".*.tmp"))


def test_string_tables_hold_any_names():
    names = ["world", "", "ünïcödé/名前", "a:b#g0", "x" * 300]
    table = prepared.StringTable(*prepared.encode_strings(names))
    assert len(table) == 5 and list(table) == names and table == names
    assert table[2] == names[2] and table[-1] == names[-1] and table[1:3] == names[1:3]
    with pytest.raises(IndexError):
        table[5]


def test_prepare_on_the_command_line(capsys, cache):
    assert main(["prepare", "fatehpur*2"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("fatehpur*2: 1,582 nodes") and str(cache) in out and out.count("\n") == 1
    assert main(["prepare", "fatehpur*2"]) == 0
    assert "is current" in capsys.readouterr().out
    assert main(["prepare", "fatehpur*2", "--force"]) == 0
    assert "prepared in" in capsys.readouterr().out
    for bad in (["prepare", "nowhere"], ["prepare", "powerplant*999"],
                ["prepare", "fatehpur", "--branching", "1"]):
        assert main(bad) == 2
        err = capsys.readouterr().err
        assert err.startswith("wallcull: error: ") and err.count("\n") == 1


def test_an_unwritable_cache_is_a_clear_error(tmp_path, monkeypatch, capsys, caplog):
    blocker = tmp_path / "file"
    blocker.write_text("in the way")
    monkeypatch.setenv("WALLCULL_CACHE", str(blocker / "cache"))
    assert main(["prepare", "fatehpur"]) == 2
    assert capsys.readouterr().err.startswith("wallcull: error: cannot write")
    with caplog.at_level(logging.WARNING, logger="wallcull"):
        assert load("fatehpur", cache="write").prepared is None  # the scene still loads
    assert "cannot write prepared scene" in caplog.text


def test_the_server_prepares_and_maps_its_scenes(cache, monkeypatch, tmp_path):
    """The server has a child process prepare a scene it has not seen, in its own cache folder
    (whatever the folder was when the children's forkserver started), and maps the file; a
    restarted server (a new store) maps the same file; its meshes have the same ETags."""
    from wallcull import sandbox
    from wallcull.service import SceneStore, mesh_blob

    monkeypatch.setenv("WALLCULL_CACHE", str(tmp_path / "elsewhere"))
    sandbox.run(len, ((),), seconds=60, memory=1 << 30, what="a first child")  # its forkserver
    monkeypatch.setenv("WALLCULL_CACHE", str(cache))
    first = asyncio.run(SceneStore().get("fatehpur*2"))
    assert first.prepared is not None and Path(first.prepared).parent == cache
    again = asyncio.run(SceneStore().get("fatehpur*2"))
    assert again.prepared == first.prepared and again.name == "fatehpur*2"
    for key in list(first.meshes)[:5]:
        assert mesh_blob(first, key).etag == mesh_blob(again, key).etag


def test_mesh_blobs_are_kept_within_a_budget(monkeypatch):
    from wallcull import service

    scene = load("fatehpur")
    keys = list(scene.meshes)
    sizes = {k: service.mesh_blob(scene, k) for k in keys}  # every mesh once
    etags = {k: b.etag for k, b in sizes.items()}
    monkeypatch.setattr(service, "MESH_CACHE_BYTES", 200_000)
    scene.__dict__.pop("_mesh_cache")
    for k in keys:
        assert service.mesh_blob(scene, k).etag == etags[k]
        cache = scene.__dict__["_mesh_cache"]
        total = sum(len(b.body["vertices"]["data"]) + len(b.body["faces"]["data"])
                    for b in cache.blobs.values())
        assert total == cache.held
        assert total <= 200_000 or len(cache.blobs) == 1
    assert len(scene.__dict__["_mesh_cache"].blobs) < len(keys)


def test_a_new_wall_warms_its_scene_meshes_within_the_budget(monkeypatch):
    """Encoded ahead of the nodes' first requests, in a thread, up to the budget."""
    from wallcull import service

    scene = load("fatehpur")
    scene.__dict__.pop("_mesh_cache", None)
    assert service.warm_meshes(scene) == len(scene.meshes)
    assert len(scene.__dict__["_mesh_cache"].blobs) == len(scene.meshes)
    monkeypatch.setattr(service, "MESH_CACHE_BYTES", 100_000)
    scene.__dict__.pop("_mesh_cache")
    warmed = service.warm_meshes(scene)
    assert 0 < warmed < len(scene.meshes)
    assert scene.__dict__["_mesh_cache"].held <= 100_000 + max(
        len(b.body["vertices"]["data"]) + len(b.body["faces"]["data"])
        for b in scene.__dict__["_mesh_cache"].blobs.values())