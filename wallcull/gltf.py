"""What of glTF wallcull reads: a document using a feature that trimesh's reader gets wrong is
refused in one line, naming it, before any reader sees the file (an upload, a file on the
command line, one in the server's scene folder or in a zip).

Read as other geometry than the file means, each of these lost or misplaced what a tile shows:

* any extension the file *requires* (Draco, meshopt, quantized positions: decoded as zeros,
  32767 times too large, or not at all), but those that change no geometry
  (:data:`GEOMETRY_FREE`: materials, texture transforms, lights);
* ``EXT_mesh_gpu_instancing`` (only the node itself was drawn, not its instances);
* a sparse accessor for positions or indices (its values were never applied);
* normalized integer positions (read without the normalization);
* a triangle fan, or a mesh without primitives (dropped, with every node below it);
* a node that carries a camera and a mesh or children (dropped, with everything below it);
* a skin (placed by its node's own transform, which glTF says to ignore) and morph targets
  with weights other than zero (the base shape, not the one shown).

A camera on a node of its own, points and lines (no triangles), integer positions that a
node's scale dequantizes, strips, and extensions a file uses but does not require (materials'
and lights') are read as they are.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

from .errors import InputError

TRIANGLE_FAN = 6
INSTANCING = "EXT_mesh_gpu_instancing"

#: Required extensions that change no geometry (materials, texture coordinates, lights): a
#: file requiring them is culled as it is drawn. Culling decodes no texture.
GEOMETRY_FREE = ("KHR_materials_", "KHR_texture_transform", "KHR_lights_punctual")


def check(doc: dict, what: str) -> None:
    """Refuse the glTF document ``doc`` (of ``what``: "the uploaded GLB", "scene x.glb") when
    it uses a feature of the module docstring's list. A malformed document is left to the
    checks and readers after this one."""
    try:
        _check(doc, what)
    except (TypeError, AttributeError, KeyError, IndexError):
        pass  # malformed: said by the upload's checks or by the reader


def _check(doc: dict, what: str) -> None:
    required = [e for e in doc.get("extensionsRequired") or []
                if not str(e).startswith(GEOMETRY_FREE)]
    if required:
        raise InputError(f"cannot use {what}: it requires extensions {required!r}, which "
                         "wallcull does not read")
    accessors = doc.get("accessors") or []

    def accessor(i) -> dict:
        return accessors[i] if isinstance(i, int) and 0 <= i < len(accessors) else {}

    meshes = doc.get("meshes") or []
    morphed = set()
    for k, mesh in enumerate(meshes):
        prims = mesh.get("primitives")
        if isinstance(prims, list) and not prims:
            raise InputError(f"cannot use {what}: mesh {k} has no primitives (its node and "
                             "every node below it would be dropped)")
        for j, p in enumerate(prims or []):
            where = f"mesh {k} primitive {j}"
            if p.get("mode") == TRIANGLE_FAN:
                raise InputError(f"cannot use {what}: {where} is a triangle fan, which wallcull "
                                 "does not read (export triangles or strips)")
            position = accessor((p.get("attributes") or {}).get("POSITION"))
            if position.get("normalized"):
                raise InputError(f"cannot use {what}: {where} has normalized integer positions "
                                 "(quantized), which wallcull does not read")
            for name, a in (("positions", position), ("indices", accessor(p.get("indices")))):
                if "sparse" in a:
                    raise InputError(f"cannot use {what}: {where} has sparse {name}, which "
                                     "wallcull does not read")
            if p.get("targets") and any(w != 0 for w in mesh.get("weights") or []):
                morphed.add(k)
    for i, node in enumerate(doc.get("nodes") or []):
        if "camera" in node and ("mesh" in node or node.get("children")):
            raise InputError(f"cannot use {what}: node {i} carries a camera and a mesh or "
                             "children, which the reader drops with everything below it "
                             "(give the camera a node of its own)")
        if INSTANCING in (node.get("extensions") or {}):
            raise InputError(f"cannot use {what}: node {i} uses {INSTANCING}, whose instances "
                             "wallcull does not read")
        if "skin" in node:
            raise InputError(f"cannot use {what}: node {i} is skinned, and wallcull culls "
                             "static meshes only (it would place the skin where its node is, "
                             "not where its joints put it)")
        mesh = node.get("mesh")
        weighted = node.get("weights") is not None and any(w != 0 for w in node["weights"])
        if isinstance(mesh, int) and 0 <= mesh < len(meshes) and (
                mesh in morphed or weighted and any(
                    p.get("targets") for p in meshes[mesh].get("primitives") or [])):
            raise InputError(f"cannot use {what}: node {i} shows mesh {mesh} with morph "
                             "targets weighted, and wallcull culls the base shape only")


def document(data: bytes, suffix: str) -> dict | None:
    """The JSON document of a ``.gltf`` or ``.glb`` file's bytes, or None where they cannot
    be read as one (the reader then says what is wrong)."""
    try:
        if suffix.lower() == ".gltf":
            doc = json.loads(data)
        else:
            magic, _, _, size, kind = struct.unpack_from("<4sIIII", data)
            if magic != b"glTF" or kind != 0x4E4F534A:
                return None
            doc = json.loads(data[20:20 + size])
    except (ValueError, struct.error, RecursionError):
        return None
    return doc if isinstance(doc, dict) else None


def beside(path: Path, uri: str) -> Path:
    """The file a glTF at ``path`` names by ``uri``: URIs are percent-encoded (a Blender export
    of "my model" names ``my%20model.bin``), but a file named as written is taken first."""
    from urllib.parse import unquote

    plain = path.parent / uri
    return plain if plain.exists() else path.parent / unquote(uri)


def resolver(path: Path):
    """trimesh's resolver of the files beside ``path``, decoding percent-encoded names
    (:func:`beside`): trimesh reads them as written, and refused such a file."""
    from trimesh.resolvers import FilePathResolver

    class Decoding(FilePathResolver):
        def get(self, name):
            return super().get(str(beside(path, name).relative_to(path.parent)))

    return Decoding(str(path))


def read_document(path: Path) -> dict | None:
    """:func:`document` of a file, reading a ``.glb``'s JSON chunk alone."""
    try:
        with open(path, "rb") as f:
            if path.suffix.lower() == ".gltf":
                return document(f.read(), ".gltf")
            head = f.read(20)
            size = struct.unpack_from("<I", head, 12)[0] if len(head) == 20 else 0
            return document(head + f.read(size), ".glb")
    except (OSError, struct.error):
        return None


def check_file(path: Path) -> None:
    """:func:`check` every glTF document of a scene file: the file itself, or the ``.gltf``
    and ``.glb`` members of a zip."""
    import zipfile

    suffix = path.suffix.lower()
    try:
        if suffix in (".gltf", ".glb"):
            docs = [(path.name, read_document(path))]
        elif suffix == ".zip" and zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as z:
                docs = [(f"{path.name}:{m}", document(z.read(m), Path(m).suffix))
                        for m in z.namelist() if Path(m).suffix.lower() in (".gltf", ".glb")]
        else:
            return
    except (OSError, zipfile.BadZipFile, RuntimeError):
        return  # the reader says what is wrong
    for name, doc in docs:
        if doc is not None:
            check(doc, f"scene {name}")
