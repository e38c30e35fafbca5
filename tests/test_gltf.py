"""glTF that trimesh alone reads as other geometry, made plain before it reads it
(:func:`wallcull.gltf.plain`): every triangle where the file puts it, on every path (a command's
``.glb``, a ``.gltf`` with its buffer beside it, a zip, an upload).

The expected triangles are worked out here from how each file was built (glTF's own rules:
a fan's ``v0 vi vi+1``, an instance's transform within its node's, ``q / 32767`` for a
normalized short; Draco's encoder given the mesh), never by the code under test."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from wallcull_clients.hostile import glb
from wallcull.errors import InputError
from wallcull.limits import Limits
from wallcull.scene import load, prepare
from wallcull.uploads import check_glb, parse_glb

BOX_V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], "<f4")
BOX_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5]], "<u4")


class Doc:
    """A one-mesh glTF document built accessor by accessor, with its binary buffer."""

    def __init__(self):
        self.doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
                    "nodes": [], "meshes": [], "buffers": [], "bufferViews": [],
                    "accessors": []}
        self.data = b""

    def view(self, array: np.ndarray) -> int:
        raw = np.ascontiguousarray(array).tobytes()
        self.data += b"\0" * (-len(self.data) % 4)
        self.doc["bufferViews"].append({"buffer": 0, "byteOffset": len(self.data),
                                        "byteLength": len(raw)})
        self.data += raw
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, array, kind: int, type_: str, **extra) -> int:
        acc = {"componentType": kind, "type": type_, "count": len(array), **extra}
        if array is not None and "bufferView" not in extra:
            acc["bufferView"] = self.view(array)
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def mesh(self, position: int, indices: int | None = None, mode: int | None = None) -> int:
        prim = {"attributes": {"POSITION": position}}
        if indices is not None:
            prim["indices"] = indices
        if mode is not None:
            prim["mode"] = mode
        self.doc["meshes"].append({"primitives": [prim]})
        return len(self.doc["meshes"]) - 1

    def glb(self) -> bytes:
        self.doc["buffers"] = [{"byteLength": len(self.data)}]
        return glb(self.doc, self.data)


def positions(d: Doc, v=BOX_V) -> int:
    return d.accessor(v, 5126, "VEC3", min=v.min(0).tolist(), max=v.max(0).tolist())


def quaternion_matrix(q) -> np.ndarray:
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def fan_indexed():
    d = Doc()
    fan = np.array([0, 1, 3, 2, 6, 4], "<u2")
    d.doc["nodes"] = [{"name": "fan", "mesh": d.mesh(positions(d), d.accessor(fan, 5123,
                                                                              "SCALAR"), 6)}]
    expected = [BOX_V[[fan[0], fan[i], fan[i + 1]]] for i in range(1, len(fan) - 1)]
    return d, np.array(expected)


def fan_plain():
    d = Doc()
    d.doc["nodes"] = [{"name": "fan", "mesh": d.mesh(positions(d), None, 6)}]
    return d, np.array([BOX_V[[0, i, i + 1]] for i in range(1, 7)])


def instanced():
    d = Doc()
    mesh = d.mesh(positions(d), d.accessor(BOX_F.ravel(), 5125, "SCALAR"))
    t = np.array([[0, 0, 0], [10, 0, 0], [0, 20, -3]], "<f4")
    r = np.array([[0, 0, 0, 1], [0, 0, 0.7071068, 0.7071068], [0.5, 0.5, 0.5, 0.5]], "<f4")
    s = np.array([[1, 1, 1], [2, 2, 2], [1, 3, 0.5]], "<f4")
    ext = {"attributes": {"TRANSLATION": d.accessor(t, 5126, "VEC3"),
                          "ROTATION": d.accessor(r, 5126, "VEC4"),
                          "SCALE": d.accessor(s, 5126, "VEC3")}}
    d.doc["nodes"] = [{"name": "trees", "mesh": mesh, "translation": [100, 0, 0],
                       "rotation": [0, 0.3826834, 0, 0.9238795], "children": [1],
                       "extensions": {"EXT_mesh_gpu_instancing": ext}},
                      {"name": "sign", "mesh": mesh, "translation": [0, 5, 0]}]
    d.doc["extensionsUsed"] = d.doc["extensionsRequired"] = ["EXT_mesh_gpu_instancing"]
    node_r = quaternion_matrix([0, 0.3826834, 0, 0.9238795])
    box = BOX_V[BOX_F].astype(float)
    expected = []
    for k in range(3):
        local = box * s[k] @ quaternion_matrix(r[k]).T + t[k]
        expected.append(local @ node_r.T + [100, 0, 0])
    expected.append((box + [0, 5, 0]) @ node_r.T + [100, 0, 0])  # its child: no instance
    return d, np.concatenate(expected)


def quantized():
    d = Doc()
    q = np.array([[0, 0, 0], [32767, 0, 0], [0, -32767, 0], [0, 0, -32768]], "<i2")
    d.doc["nodes"] = [{"name": "q", "mesh": d.mesh(d.accessor(
        q, 5122, "VEC3", normalized=True, min=q.min(0).tolist(), max=q.max(0).tolist()),
        d.accessor(np.array([0, 1, 2, 0, 2, 3], "<u2"), 5123, "SCALAR"))}]
    d.doc["extensionsUsed"] = d.doc["extensionsRequired"] = ["KHR_mesh_quantization"]
    v = np.maximum(q / 32767.0, -1.0)
    return d, np.array([v[[0, 1, 2]], v[[0, 2, 3]]])


def sparse():
    d = Doc()
    moved = np.array([[5, 5, 5], [6, 5, 5]], "<f4")
    base = positions(d)
    d.doc["accessors"][base].update(max=[6, 5, 5], sparse={
        "count": 2, "indices": {"bufferView": d.view(np.array([2, 7], "<u4")),
                                "componentType": 5125},
        "values": {"bufferView": d.view(moved)}})
    faces = d.accessor(np.array([0, 1, 2, 0, 0, 0], "<u4"), 5125, "SCALAR")
    d.doc["accessors"][faces]["sparse"] = {
        "count": 3, "indices": {"bufferView": d.view(np.array([3, 4, 5], "<u1")),
                                "componentType": 5121},
        "values": {"bufferView": d.view(np.array([7, 6, 4], "<u4"))}}
    d.doc["nodes"] = [{"name": "s", "mesh": d.mesh(base, faces)}]
    v = BOX_V.copy()
    v[[2, 7]] = moved
    return d, np.array([v[[0, 1, 2]], v[[7, 6, 4]]])


def draco():
    DracoPy = pytest.importorskip("DracoPy", reason="Draco needs the formats extra")
    d = Doc()
    v = BOX_V * [1, 2, 3]
    encoded = DracoPy.encode(v, BOX_F, quantization_bits=16)
    decoded = len(np.asarray(DracoPy.decode(encoded).points).reshape(-1, 3))
    d.doc["accessors"] += [{"componentType": 5126, "type": "VEC3", "count": decoded,
                            "min": [0, 0, 0], "max": [1, 2, 3]},
                           {"componentType": 5125, "type": "SCALAR", "count": BOX_F.size}]
    view = d.view(np.frombuffer(encoded, "u1"))
    d.doc["meshes"] = [{"primitives": [{
        "attributes": {"POSITION": 0}, "indices": 1,
        "extensions": {"KHR_draco_mesh_compression": {"bufferView": view,
                                                      "attributes": {"POSITION": 0}}}}]}]
    d.doc["nodes"] = [{"name": "d", "mesh": 0, "translation": [0, 0, -4]}]
    d.doc["extensionsUsed"] = d.doc["extensionsRequired"] = ["KHR_draco_mesh_compression"]
    return d, v[BOX_F] + [0, 0, -4]


CASES = {"fan": fan_indexed, "fan-without-indices": fan_plain, "instancing": instanced,
         "quantized": quantized, "sparse": sparse, "draco": draco}


def canonical(triangles: np.ndarray) -> np.ndarray:
    """Triangles as rows, each turned to start at its least vertex (winding kept), sorted."""
    t = np.round(np.asarray(triangles, float).reshape(-1, 3, 3), 3)
    first = np.array([min(range(3), key=lambda k: tuple(tri[k])) for tri in t], int)
    t = np.stack([np.roll(tri, -k, axis=0) for tri, k in zip(t, first)]).reshape(-1, 9)
    return t[np.lexsort(t.T[::-1])]


def triangles(scene) -> np.ndarray:
    return np.concatenate([scene.leaf_triangles(int(leaf)) for leaf in scene.leaves])


@pytest.mark.parametrize("case", sorted(CASES))
def test_what_trimesh_misreads_is_made_plain_on_every_path(tmp_path, case):
    """Fans were dropped with their nodes, instances left out, normalized positions read
    32767 times too large, sparse values never applied: each was refused since, and is now
    read, every triangle where the file puts it."""
    d, expected = CASES[case]()
    data = d.glb()
    want = canonical(expected)
    (tmp_path / "a.glb").write_bytes(data)
    gltf_doc = json.loads(json.dumps(d.doc))
    gltf_doc["buffers"][0]["uri"] = "a%20b.bin"  # beside it, percent-encoded
    (tmp_path / "a b.bin").write_bytes(d.data)
    (tmp_path / "a.gltf").write_text(json.dumps(gltf_doc))
    with zipfile.ZipFile(tmp_path / "a.zip", "w") as z:
        z.writestr("in/a.gltf", json.dumps(gltf_doc))
        z.writestr("in/a b.bin", d.data)
    for name in ("a.glb", "a.gltf", "a.zip"):
        got = canonical(triangles(load(str(tmp_path / name), cache="off")))
        assert got.shape == want.shape, name
        np.testing.assert_allclose(got, want, atol=2e-4, err_msg=name)
    if case != "quantized":  # an upload's positions must be floats
        check_glb(data, Limits())
        got = canonical(triangles(parse_glb(str(tmp_path / "a.glb"), "a", Limits())))
        np.testing.assert_allclose(got, want, atol=2e-4)


def test_instances_count_against_an_uploads_limits(tmp_path):
    """Each instance is a node drawing its mesh: an upload's limits count them all."""
    d, _ = instanced()
    data = d.glb()
    check_glb(data, Limits(nodes=5))  # two nodes, three instances
    with pytest.raises(InputError, match="makes 5 nodes"):
        check_glb(data, Limits(nodes=4))
    with pytest.raises(InputError, match="16 triangles"):
        check_glb(data, Limits(faces=15))


def zero_rotation(d: Doc) -> None:
    ext = d.doc["nodes"][0]["extensions"]["EXT_mesh_gpu_instancing"]
    ext["attributes"]["ROTATION"] = d.accessor(np.zeros((3, 4), "<f4"), 5126, "VEC4")


def counts_differ(d: Doc) -> None:
    ext = d.doc["nodes"][0]["extensions"]["EXT_mesh_gpu_instancing"]
    ext["attributes"]["SCALE"] = d.accessor(np.ones((2, 3), "<f4"), 5126, "VEC3")


@pytest.mark.parametrize("edit,detail", [(zero_rotation, "rotation is no quaternion"),
                                         (counts_differ, "differ in count")])
def test_instances_that_cannot_be_placed_are_refused(tmp_path, edit, detail):
    """One line naming the node, where the file cannot say where its instances are."""
    d, _ = instanced()
    edit(d)
    (tmp_path / "bad.glb").write_bytes(d.glb())
    with pytest.raises(InputError, match="node 0 .*" + detail):
        load(str(tmp_path / "bad.glb"), cache="off")


def test_draco_that_cannot_be_decoded_is_refused_in_one_line(tmp_path, monkeypatch):
    """Draco data that does not decode, or decodes to other than its accessors declare (an
    upload's limits count the declared), and Draco without DracoPy: one line each."""
    d, _ = draco()
    path = tmp_path / "d.glb"
    view = d.doc["meshes"][0]["primitives"][0]["extensions"][
        "KHR_draco_mesh_compression"]["bufferView"]
    good = d.data
    start = d.doc["bufferViews"][view]["byteOffset"]
    d.data = good[:start] + b"\x07" * (len(good) - start)
    path.write_bytes(d.glb())
    with pytest.raises(InputError, match="Draco data cannot be decoded"):
        load(str(path), cache="off")
    d.data = good
    d.doc["accessors"][0]["count"] = 3
    path.write_bytes(d.glb())
    with pytest.raises(InputError, match="decodes to 8 vertices and 4 triangles"):
        load(str(path), cache="off")
    d.doc["accessors"][0]["count"] = 8
    path.write_bytes(d.glb())
    monkeypatch.setitem(__import__("sys").modules, "DracoPy", None)
    with pytest.raises(InputError, match=r"needs DracoPy: pip install 'wallcull\[formats\]'"):
        load(str(path), cache="off")


@pytest.mark.parametrize("plain", [False, True])
def test_which_meshes_are_single_sided_is_read_on_every_path(tmp_path, monkeypatch, plain):
    """A glTF material's ``doubleSided`` (false by default, and for a primitive of no
    material: glTF's default material) is kept per mesh on every path, with the file made
    plain first or not (``plain``: a fan in it), and in its prepared file: a single-sided mesh
    occludes with its front faces alone. An OBJ says nothing of sides: double-sided."""
    d = Doc()
    d.doc["materials"] = [{"doubleSided": True}, {"doubleSided": False}, {}]
    triangles_ = d.accessor(BOX_F.ravel(), 5125, "SCALAR")
    for k, material in enumerate([0, 1, 2, None]):
        prim = {"attributes": {"POSITION": positions(d, BOX_V + [2 * k, 0, 0])},
                "indices": triangles_}
        if material is not None:
            prim["material"] = material
        if plain and k == 3:
            prim["mode"], prim["indices"] = 6, d.accessor(np.arange(6, dtype="<u2"), 5123,
                                                          "SCALAR")
        d.doc["meshes"].append({"name": f"m{k}", "primitives": [prim]})
        d.doc["nodes"].append({"name": f"n{k}", "mesh": k})
    d.doc["scenes"] = [{"nodes": [0, 1, 2, 3]}]
    data = d.glb()
    (tmp_path / "a.glb").write_bytes(data)
    gltf_doc = json.loads(json.dumps(d.doc))
    gltf_doc["buffers"][0]["uri"] = "a.bin"
    (tmp_path / "a.bin").write_bytes(d.data)
    (tmp_path / "a.gltf").write_text(json.dumps(gltf_doc))
    with zipfile.ZipFile(tmp_path / "a.zip", "w") as z:  # (at its root: trimesh finds no
        z.writestr("a.gltf", json.dumps(gltf_doc))  # buffer under a folder, unless plain)
        z.writestr("a.bin", d.data)
    monkeypatch.setenv("WALLCULL_CACHE", str(tmp_path / "cache"))
    want = {"m0": False, "m1": True, "m2": True, "m3": True}
    scenes = []
    for name in ("a.glb", "a.gltf", "a.zip"):
        scenes.append(load(str(tmp_path / name), cache="off"))
        prepare(str(tmp_path / name))
        scenes.append(load(str(tmp_path / name)))
        assert scenes[-1].prepared is not None
    check_glb(data, Limits())
    scenes.append(parse_glb(str(tmp_path / "a.glb"), "a", Limits()))
    for scene in scenes:
        assert dict(zip(scene.meshes, scene.meshes.single_sided.tolist())) == want
    (tmp_path / "a.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\no t\nf 1 2 3\n")
    assert not load(str(tmp_path / "a.obj"), cache="off").meshes.single_sided.any()
