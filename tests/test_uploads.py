"""Uploaded GLBs (wallcull.uploads): every declaration checked against the bytes present and
against the limits before a parser sees the file, and the parse itself in a child process
whose memory and time are limited."""

from __future__ import annotations

import json
import re
import os

import numpy as np
import pytest
import trimesh

from wallcull_clients.hostile import glb, many_nodes, vertex_bomb
from wallcull.errors import InputError
from wallcull import sandbox
from wallcull.limits import Limits
from wallcull.uploads import check_glb, glb_chunks, parse_sandboxed

BOX_V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], "<f4")
BOX_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5]], "<u4")


def box_doc(**change) -> tuple[dict, bytes]:
    """A one-node GLB document (positions and indices in one buffer) and its binary chunk."""
    v, f = BOX_V.tobytes(), BOX_F.tobytes()
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"name": "box", "mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
           "buffers": [{"byteLength": len(v) + len(f)}],
           "bufferViews": [{"buffer": 0, "byteLength": len(v)},
                           {"buffer": 0, "byteOffset": len(v), "byteLength": len(f)}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "type": "VEC3", "count": 8,
                          "min": [0, 0, 0], "max": [1, 1, 1]},
                         {"bufferView": 1, "componentType": 5125, "type": "SCALAR",
                          "count": 12}]}
    doc.update(change)
    return doc, v + f


def changed(path: str, value) -> bytes:
    """The box GLB with one value of its JSON replaced (``path``: keys and indices by dots)."""
    doc, binary = box_doc()
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]
    target = doc
    for k in keys[:-1]:
        target = target[k]
    if value is DELETE:
        del target[keys[-1]]
    else:
        target[keys[-1]] = value
    return glb(doc, binary)


DELETE = object()
SPARSE = {"count": 2, "indices": {"bufferView": 1, "componentType": 5125},
          "values": {"bufferView": 0}}

REFUSED = [  # (id, GLB, detail)
    ("buffer-uri", changed("buffers.0.uri", "/etc/passwd"), "uri"),
    ("data-uri", changed("buffers.0.uri", "data:application/octet-stream;base64,AAAA"), "uri"),
    ("buffer-longer-than-chunk", changed("buffers.0.byteLength", 10_000), "binary chunk holds"),
    ("view-past-buffer", changed("bufferViews.1.byteOffset", 100), "ends at byte"),
    ("view-negative-offset", changed("bufferViews.0.byteOffset", -4), "byteOffset"),
    ("view-bad-buffer", changed("bufferViews.0.buffer", 3), "buffer"),
    ("stride-too-small", changed("bufferViews.0.byteStride", 2), "byteStride"),
    ("stride-not-aligned", changed("bufferViews.0.byteStride", 14), "multiple of 4"),
    ("stride-overlaps", changed("bufferViews.0.byteStride", 8), "overlap"),
    ("stride-runs-past", changed("bufferViews.0.byteStride", 16), "reads"),
    ("count-past-view", changed("accessors.0.count", 9), "reads"),
    ("offset-past-view", changed("accessors.1.byteOffset", 8), "reads"),
    ("count-zero", changed("accessors.0.count", 0), "count"),
    ("count-float", changed("accessors.0.count", 8.0), "count"),
    ("count-bool", changed("accessors.0.count", True), "count"),
    ("component-type", changed("accessors.0.componentType", 5130), "componentType"),
    ("element-type", changed("accessors.0.type", "VEC7"), "type"),
    ("view-index", changed("accessors.0.bufferView", 7), "bufferView"),
    ("sparse-indices-past", changed("accessors.0.sparse", {**SPARSE, "count": 4,
                                                           "indices": {"bufferView": 1,
                                                                       "byteOffset": 40,
                                                                       "componentType": 5125}}),
     "sparse"),
    ("sparse-more-than-count", changed("accessors.0.sparse", {**SPARSE, "count": 9}), "sparse"),
    ("sparse-index-type", changed("accessors.0.sparse", {
        **SPARSE, "indices": {"bufferView": 1, "componentType": 5126}}), "sparse"),
    ("sparse-malformed", changed("accessors.0.sparse", [1, 2]), "sparse"),
    ("mesh-index", changed("nodes.0.mesh", 4), "mesh"),
    ("attribute-index", changed("meshes.0.primitives.0.attributes.POSITION", 9), "POSITION"),
    ("child-index", changed("nodes.0.children", [5]), "child"),
    ("own-child", changed("nodes.0.children", [0]), "tree"),
    ("scene-root", changed("scenes.0.nodes", [3]), "scene 0 node"),
    ("required-extension", changed("extensionsRequired", ["EXT_meshopt_compression"]),
     "extensions"),
    ("children-not-a-list", changed("nodes.0.children", 5), "node 0 children must be a list"),
    ("roots-not-a-list", changed("scenes.0.nodes", 0), "scene 0 nodes must be a list"),
    ("float-indices", changed("accessors.1.componentType", 5126),
     "indices must be unsigned integer SCALARs"),
    ("positions-not-floats", changed("meshes.0.primitives.0.attributes.POSITION", 1),
     "POSITION must be float VEC3"),
    ("mode", changed("meshes.0.primitives.0.mode", 9), "mode"),
    ("vertex-bomb", vertex_bomb(10 ** 8), "declares"),
    ("issue-10-file", vertex_bomb(9_999_999), "draws 9,999,999 vertices"),
]


@pytest.mark.parametrize("data,detail", [r[1:] for r in REFUSED], ids=[r[0] for r in REFUSED])
def test_declarations_are_checked_against_the_bytes_and_limits(data, detail):
    with pytest.raises(InputError, match=detail):
        check_glb(data, Limits())


def test_a_good_box_and_a_good_sparse_accessor_pass():
    check_glb(glb(*box_doc()), Limits())
    doc, binary = box_doc()
    doc["accessors"].append({"componentType": 5126, "type": "VEC3", "count": 8,
                             "sparse": {"count": 2, "indices": {"bufferView": 1,
                                                                "componentType": 5125},
                                        "values": {"bufferView": 0}}})
    check_glb(glb(doc, binary), Limits())


def test_two_parents_and_cycles_are_refused():
    doc, binary = box_doc(nodes=[{"name": "a", "children": [2]}, {"name": "b", "children": [2]},
                                 {"name": "c", "mesh": 0}], scenes=[{"nodes": [0, 1]}])
    with pytest.raises(InputError, match="two parents"):
        check_glb(glb(doc, binary), Limits())
    doc, binary = box_doc(nodes=[{"name": "a", "children": [1], "mesh": 0},
                                 {"name": "b", "children": [2]}, {"name": "c", "children": [0]}])
    with pytest.raises(InputError, match="cycle"):
        check_glb(glb(doc, binary), Limits())


def test_what_the_file_builds_counts_against_the_limits():
    """Limits hold on what a file makes, not on its declarations: each primitive of a mesh of
    several is a node, and a strip of n indices draws n - 2 triangles (not n / 3)."""
    doc, binary = box_doc()
    doc["meshes"][0]["primitives"] *= 300
    data = glb(doc, binary)
    check_glb(data, Limits(nodes=301))
    with pytest.raises(InputError, match="makes 301 nodes"):
        check_glb(data, Limits(nodes=300))
    doc, binary = box_doc()
    doc["meshes"][0]["primitives"][0]["mode"] = 5  # a strip of 12 indices: 10 triangles
    check_glb(glb(doc, binary), Limits(faces=10))
    with pytest.raises(InputError, match="10 triangles"):
        check_glb(glb(doc, binary), Limits(faces=9))
    doc["meshes"][0]["primitives"][0]["mode"] = 1  # lines: none
    check_glb(glb(doc, binary), Limits(faces=0))


def test_instances_count_against_the_limits():
    """A mesh drawn by many nodes counts once per node: 1,000 nodes of one 8-vertex box."""
    data = many_nodes(1000, per=50)
    check_glb(data, Limits())
    with pytest.raises(InputError, match="8,000 vertices"):
        check_glb(data, Limits(vertices=7999))
    with pytest.raises(InputError, match="12,000 triangles"):
        check_glb(data, Limits(faces=11_999))
    with pytest.raises(InputError, match="1,021 nodes"):
        check_glb(data, Limits(nodes=1000))
    with pytest.raises(InputError, match="declares 240 bytes"):
        check_glb(data, Limits(scene_bytes=239))


@pytest.mark.parametrize("data", [b"", b"glTF", b"glTF" + bytes(8), b"glTF\x01\x00\x00\x00" +
                                  bytes(12), glb(*box_doc())[:40]])
def test_truncated_headers_and_chunks_are_refused(data):
    with pytest.raises(InputError):
        glb_chunks(data)


def test_the_parse_runs_in_a_child_with_a_memory_limit(tmp_path):
    """A file within every declared limit whose parse needs more memory than the child may
    have: the child runs out and the upload is refused; this process is untouched."""
    import resource

    doc, binary = box_doc()
    doc["accessors"][0] = {"componentType": 5126, "type": "VEC3", "count": 3_000_000,
                           "min": [0, 0, 0], "max": [1, 1, 1]}  # zeros, no buffer view
    doc["meshes"][0]["primitives"][0].pop("indices")
    path = tmp_path / "big.glb"
    path.write_bytes(glb(doc, binary))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(InputError, match="memory|died"):
        parse_sandboxed(path, "big.glb", Limits(parse_memory=64 << 20))
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 20_000  # KiB


def test_the_child_gives_back_a_usable_scene_and_dies_on_a_deadline(tmp_path):
    s = trimesh.Scene()
    for k in range(3):
        m = np.eye(4)
        m[:3, 3] = [3 * k, 0, -10]
        s.add_geometry(trimesh.creation.box(), node_name=f"b{k}", geom_name=f"b{k}",
                       transform=m)
    path = tmp_path / "three.glb"
    path.write_bytes(s.export(file_type="glb"))
    scene = parse_sandboxed(path, "three.glb", Limits())
    assert scene.name == "three.glb" and scene.stats["leaves"] == 3
    assert np.isfinite(scene.bounds("obb").half).all()
    with pytest.raises(InputError, match="took over"):
        parse_sandboxed(path, "three.glb", Limits(parse_seconds=1e-4))


def test_an_upload_keeps_which_materials_are_see_through_and_decodes_no_image(tmp_path):
    """A glass (BLEND) and an alpha-tested (MASK) mesh are known as see-through (they never
    occlude), a textured opaque one is not; its texture, a PNG that is no picture, is never
    decoded. Which are single-sided (their material not ``doubleSided``: they occlude with
    their front faces alone) is known too."""
    from PIL import Image

    s = trimesh.Scene()
    for k, mode in enumerate(("OPAQUE", "BLEND", "MASK")):
        box = trimesh.creation.box()
        image = Image.new("RGBA", (4, 4), (255, 0, 0, 128))
        box.visual = trimesh.visual.TextureVisuals(
            uv=np.zeros((len(box.vertices), 2)),
            material=trimesh.visual.material.PBRMaterial(baseColorTexture=image,
                                                         alphaMode=mode,
                                                         doubleSided=mode == "MASK"))
        m = np.eye(4)
        m[:3, 3] = [3 * k, 0, -10]
        s.add_geometry(box, node_name=mode.lower(), geom_name=mode.lower(), transform=m)
    data = s.export(file_type="glb")
    doc = json.loads(glb_chunks(data)[0])
    assert doc["images"] and doc["textures"]
    start = data.index(b"\x89PNG")  # the image's bytes, spoiled: decoding them would fail
    path = tmp_path / "materials.glb"
    path.write_bytes(data[:start] + b"\0" * 8 + data[start + 8:])
    scene = parse_sandboxed(path, "materials.glb", Limits())
    assert dict(zip(scene.meshes, scene.meshes.see_through.tolist())) == {
        "opaque": False, "blend": True, "mask": True}
    assert dict(zip(scene.meshes, scene.meshes.single_sided.tolist())) == {
        "opaque": True, "blend": True, "mask": False}


def test_the_json_chunk_is_parsed_in_the_child_too():
    """A JSON chunk that is not an object, or nests too deep for the parser."""
    for text in (b"[1, 2]", b"[" * 100_000):
        data = b"glTF" + (2).to_bytes(4, "little") + (20 + len(text)).to_bytes(4, "little") + \
            len(text).to_bytes(4, "little") + (0x4E4F534A).to_bytes(4, "little") + text
        with pytest.raises(InputError, match="JSON"):
            check_glb(data, Limits())
    assert json.loads(glb_chunks(glb(*box_doc()))[0])["asset"]["version"] == "2.0"


def test_a_child_takes_the_settings_its_parent_has_when_it_starts(monkeypatch):
    """Children fork from a server process started once; they still see the parent's
    ``WALLCULL_*`` variables as they are now (the prepared scenes' folder, ...)."""
    def probe():
        return sandbox.run(os.getenv, ("WALLCULL_PROBE",), seconds=60, memory=1 << 30,
                           what="a probe")

    monkeypatch.setenv("WALLCULL_PROBE", "before")
    assert probe() == "before"
    monkeypatch.setenv("WALLCULL_PROBE", "after")
    assert probe() == "after"
    monkeypatch.delenv("WALLCULL_PROBE")
    assert probe() is None


def box_glb(vertices=BOX_V, faces=BOX_F, **change) -> bytes:
    """The box GLB with other vertex and face bytes (the same counts)."""
    doc, _ = box_doc(**change)
    return glb(doc, np.asarray(vertices, "<f4").tobytes() + np.asarray(faces, "<u4").tobytes())


def _with(array, at, value):
    out = np.array(array)
    out[at] = value
    return out


@pytest.mark.parametrize("data, detail", [
    (box_glb(faces=_with(BOX_F, (3, 2), 99)), "mesh .* has a face naming vertex 99, outside "
                                              "its 8 vertices"),
    (box_glb(vertices=_with(BOX_V, (2, 1), np.nan)), r"has a vertex that is not finite \(vertex 2"),
    (box_glb(vertices=_with(BOX_V, (5, 0), np.inf)), r"has a vertex that is not finite \(vertex 5"),
    (box_glb(nodes=[{"name": "x\ud800y", "mesh": 0}]), "node name 'x\\\\ud800y' is not valid "
                                                        "Unicode"),
], ids=["index", "nan", "inf", "surrogate"])
def test_a_mesh_or_name_that_cannot_be_drawn_is_refused_on_every_path(tmp_path, data, detail):
    """Refused in one line, naming the mesh or node, whether uploaded or read by a command:
    a face past its vertices used to be stored, served to the nodes and then fail the
    occlusion (a 500) or use another mesh's vertex; a vertex not finite dropped its mesh in
    silence; a name with half a surrogate pair was stored, then could not be prepared."""
    from wallcull.scene import load
    from wallcull.uploads import parse_glb

    path = tmp_path / "bad.glb"
    path.write_bytes(data)
    with pytest.raises(InputError, match=detail):
        parse_glb(str(path), "bad.glb", Limits())
    with pytest.raises(InputError, match=detail):
        load(str(path), cache="off")


def test_every_primitive_of_a_mesh_is_loaded_however_the_random_names_fall(monkeypatch):
    """trimesh names a mesh's extra primitives with 6 random hex digits, and two alike drop
    one: with the random source stuck (every draw alike), all 40 are still there, named by
    their geometry, the same on every load."""
    import random

    from wallcull.scene import Scene, read_glb

    doc, binary = box_doc()
    doc["meshes"][0]["primitives"] *= 40
    data = glb(doc, binary)
    monkeypatch.setattr(random, "getrandbits", lambda bits: 12345)
    scenes = [Scene.from_trimesh(read_glb(data)) for _ in range(2)]
    assert scenes[0].stats["leaves"] == 40
    assert scenes[0].names == scenes[1].names


@pytest.mark.parametrize("change, detail", [
    ({"nodes": [{"name": "box", "mesh": 0, "scale": [1e300, 1, 1]}]}, "cannot be bounded|not "
                                                                      "finite|too large"),
    ({"nodes": [{"name": "a", "children": [1]}, {"name": "b", "children": [0], "mesh": 0}]},
     "hang from no root of the scene as read"),
], ids=["huge-scale", "cycle"])
def test_a_command_refuses_a_file_an_upload_refuses(tmp_path, capsys, change, detail):
    """The command line reads files through the same checks as uploads: one line, status 2
    (it was an internal error, status 1)."""
    from wallcull import cli

    path = tmp_path / "odd.glb"
    path.write_bytes(box_glb(**change))
    assert cli.main(["walk", str(path), "--frames", "1"]) == 2
    err = capsys.readouterr().err
    assert re.search(detail, err) and len(err.strip().splitlines()) == 1, err


def test_a_node_tree_deeper_than_a_thousand_is_refused(tmp_path):
    """The hierarchy is built, and moved nodes refit, level by level: a chain of 200,000
    nodes took minutes to load, and a 20,000-deep one 0.2 s a frame to move. Refused on
    upload before the parse, and by every command."""
    from wallcull.scene import load
    from wallcull.validate import MAX_DEPTH

    def chain(depth):
        nodes = [{"name": f"n{i}", "children": [i + 1]} for i in range(depth)]
        return box_glb(nodes=nodes + [{"name": "box", "mesh": 0}])

    check_glb(chain(MAX_DEPTH), Limits())
    path = tmp_path / "chain.glb"
    path.write_bytes(chain(MAX_DEPTH))
    assert load(str(path), cache="off").stats["leaves"] == 1
    path.write_bytes(chain(MAX_DEPTH + 1))
    with pytest.raises(InputError, match="over 1,000 deep"):
        check_glb(path.read_bytes(), Limits())
    with pytest.raises(InputError, match="over 1,000 deep"):
        load(str(path), cache="off")


def _doc_with(edit) -> bytes:
    doc, binary = box_doc()
    edit(doc)
    return glb(doc, binary)


CAMERA = [{"type": "perspective", "perspective": {"yfov": 1.0, "znear": 0.1}}]
FEATURES = [  # (id, GLB, detail): what trimesh's reader would read as other geometry
    ("camera-parent", _doc_with(lambda d: d.update(
        nodes=[{"name": "rig", "camera": 0, "children": [1]}, {"name": "box", "mesh": 0}],
        cameras=CAMERA)), "node 0 carries a camera and a mesh or children"),
    ("camera-mesh", _doc_with(lambda d: d.update(
        nodes=[{"name": "box", "mesh": 0, "camera": 0}], cameras=CAMERA)), "carries a camera"),
    ("no-primitives", _doc_with(lambda d: d["meshes"].append({"primitives": []})),
     "mesh 1 has no primitives"),
    ("skin", _doc_with(lambda d: d.update(nodes=[{"name": "box", "mesh": 0, "skin": 0}],
                                           skins=[{"joints": [0]}])), "node 0 is skinned"),
    ("morph", _doc_with(lambda d: (d["meshes"][0].update(weights=[1.0]),
                                   d["meshes"][0]["primitives"][0].update(
                                       targets=[{"POSITION": 0}]))), "morph targets"),
    ("meshopt", _doc_with(lambda d: d.update(extensionsUsed=["EXT_meshopt_compression"],
                                             extensionsRequired=["EXT_meshopt_compression"])),
     "requires extensions .* leave out -c"),
]


@pytest.mark.parametrize("data,detail", [f[1:] for f in FEATURES], ids=[f[0] for f in FEATURES])
def test_glTF_read_as_other_geometry_is_refused_on_every_path(tmp_path, data, detail):
    """A glTF feature trimesh's reader gets wrong and wallcull does not make plain (it dropped
    nodes and whole subtrees, placed skins by their node, left meshopt's data undecoded) is refused
    in one line on upload, by a command and in a zip, where the command line and the scene
    folder loaded the file as other geometry, exit 0 (what is made plain: test_gltf.py)."""
    import zipfile

    from wallcull.scene import load

    with pytest.raises(InputError, match=detail):
        check_glb(data, Limits())
    path = tmp_path / "odd.glb"
    path.write_bytes(data)
    with pytest.raises(InputError, match=detail):
        load(str(path), cache="off")
    with zipfile.ZipFile(tmp_path / "odd.zip", "w") as z:
        z.writestr("inside/odd.glb", data)
    with pytest.raises(InputError, match=detail):
        load(str(tmp_path / "odd.zip"), cache="off")


def test_what_glTF_wallcull_reads_as_it_is_still_loads(tmp_path):
    """A camera on a node of its own, morph targets weighted zero, a sparse accessor that is
    no position, required extensions that change no geometry (materials, texture transforms):
    loaded, every triangle there, on upload and by a command."""
    from wallcull.scene import load

    def edit(d):
        d["nodes"] = [{"name": "box", "mesh": 0}, {"name": "eye", "camera": 0}]
        d["scenes"] = [{"nodes": [0, 1]}]
        d["cameras"] = CAMERA
        d["meshes"][0]["weights"] = [0.0]
        d["meshes"][0]["primitives"][0]["targets"] = [{"POSITION": 0}]
        d["accessors"].append({"componentType": 5126, "type": "VEC3", "count": 8,
                               "sparse": SPARSE})
        d["extensionsUsed"] = d["extensionsRequired"] = ["KHR_materials_unlit",
                                                         "KHR_texture_transform"]
        d["materials"] = [{"extensions": {"KHR_materials_unlit": {}}}]
        d["meshes"][0]["primitives"][0]["material"] = 0
    path = tmp_path / "fine.glb"
    path.write_bytes(_doc_with(edit))
    check_glb(path.read_bytes(), Limits())
    assert load(str(path), cache="off").stats["triangles"] == 4


def test_geometry_a_reader_leaves_hanging_is_refused():
    """Nodes whose parent a reader dropped hang from no root: refused, never lost in
    silence (the last guard behind the glTF checks)."""
    from wallcull.scene import Scene

    s = trimesh.Scene()
    s.add_geometry(trimesh.creation.box(), node_name="kept", geom_name="kept")
    s.graph.update(frame_from="dropped", frame_to="orphan", geometry="lost",
                   matrix=np.eye(4))
    s.geometry["lost"] = trimesh.creation.box()
    with pytest.raises(InputError, match="1 node.* with geometry .*'orphan'.* hang from no root"):
        Scene.from_trimesh(s, hierarchy="file")


def test_a_prepared_key_follows_the_files_a_scene_names(tmp_path):
    """A GLB's external buffer and an OBJ's material library are in the prepared file's key:
    changed, the scene is read again (the old geometry, and an old opaque material that now
    is glass, were served from the prepared file)."""
    from wallcull.scene import _file_hash

    doc, binary = box_doc()
    doc["buffers"][0]["uri"] = "data.bin"
    (tmp_path / "data.bin").write_bytes(binary)
    path = tmp_path / "ext.glb"
    path.write_bytes(glb(doc, b""))
    before = _file_hash(path)
    (tmp_path / "data.bin").write_bytes(binary[:-4] + b"\1\0\0\0")
    assert _file_hash(path) != before
    obj = tmp_path / "room.obj"
    obj.write_text("mtllib room.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl glass\nf 1 2 3\n")
    (tmp_path / "room.mtl").write_text("newmtl glass\nd 1.0\n")
    before = _file_hash(obj)
    (tmp_path / "room.mtl").write_text("newmtl glass\nd 0.3\n")
    assert _file_hash(obj) != before


def test_a_gltf_naming_its_buffer_percent_encoded_loads(tmp_path):
    """glTF URIs are percent-encoded: a buffer ``my%20data.bin`` is the file ``my data.bin``
    (a Blender export of a model with a space in its name). trimesh looked for the name as
    written and the scene was refused; the prepared key follows the file too."""
    from wallcull.scene import _file_hash, load

    doc, binary = box_doc()
    doc["buffers"][0]["uri"] = "my%20data.bin"
    (tmp_path / "my data.bin").write_bytes(binary)
    path = tmp_path / "spaced.gltf"
    path.write_text(json.dumps(doc))
    assert load(str(path), cache="off").stats["triangles"] == 4
    before = _file_hash(path)
    (tmp_path / "my data.bin").write_bytes(binary[:-4] + b"\1\0\0\0")
    assert _file_hash(path) != before
