"""What of glTF wallcull reads: a document using a feature that trimesh's reader gets wrong is
either made plain before trimesh reads it (:func:`plain`) or refused in one line, naming it,
before any reader sees the file (an upload, a file on the command line, one in the server's
scene folder or in a zip).

Made plain (trimesh alone dropped, left out or misplaced them):

* a triangle fan (dropped, with every node below it), as triangles;
* ``EXT_mesh_gpu_instancing`` (only the node itself was drawn), as a child node per instance;
* normalized integer positions (``KHR_mesh_quantization``: read 32767 times too large) and
  sparse positions or indices (their values never applied), as plain arrays;
* Draco-compressed primitives (``KHR_draco_mesh_compression``: read as zeros), decoded by
  DracoPy (the ``formats`` extra), positions and triangles alone;
* a material that transmits light (``KHR_materials_transmission`` or
  ``KHR_materials_diffuse_transmission`` with a factor above 0: glass as Blender writes it,
  its ``alphaMode`` left opaque; trimesh drops the extension), as ``alphaMode`` ``BLEND``:
  what shows through it is never occlusion-culled.

Refused, each having lost or misplaced what a tile shows:

* any extension the file *requires* (meshopt: not decoded at all), but
  those made plain (:data:`MADE_PLAIN`) and those that change no geometry
  (:data:`GEOMETRY_FREE`: materials, texture transforms, lights);
* a mesh without primitives (dropped, with every node below it);
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

import numpy as np

from .errors import InputError

TRIANGLE_FAN = 6
INSTANCING = "EXT_mesh_gpu_instancing"
DRACO = "KHR_draco_mesh_compression"

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
                if not str(e).startswith(GEOMETRY_FREE) and e not in MADE_PLAIN]
    if required:
        hint = "; write it without compression (gltfpack: leave out -c)" if any(
            "meshopt" in str(e) for e in required) else ""
        raise InputError(f"cannot use {what}: it requires extensions {required!r}, which "
                         f"wallcull does not read{hint}")
    meshes = doc.get("meshes") or []
    morphed = set()
    for k, mesh in enumerate(meshes):
        prims = mesh.get("primitives")
        if isinstance(prims, list) and not prims:
            raise InputError(f"cannot use {what}: mesh {k} has no primitives (its node and "
                             "every node below it would be dropped)")
        if any(p.get("targets") for p in prims or []) and \
                any(w != 0 for w in mesh.get("weights") or []):
            morphed.add(k)
    for i, node in enumerate(doc.get("nodes") or []):
        if "camera" in node and ("mesh" in node or node.get("children")):
            raise InputError(f"cannot use {what}: node {i} carries a camera and a mesh or "
                             "children, which the reader drops with everything below it "
                             "(give the camera a node of its own)")
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


# --------------------------------------------------------------------------- made plain

#: Required extensions whose files are read once made plain (:func:`plain`): instances
#: expanded into nodes, quantized positions dequantized (its other integer attributes are read
#: as they are: trimesh reads integers, and a node's scale dequantizes positions), Draco
#: decoded.
MADE_PLAIN = (INSTANCING, "KHR_mesh_quantization", DRACO)
#: Material extensions that let light through, and their factor (0 by default: opaque).
TRANSMISSION = {"KHR_materials_transmission": "transmissionFactor",
                "KHR_materials_diffuse_transmission": "diffuseTransmissionFactor"}

_DTYPES = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
#: What a normalized integer's largest value stands for (1.0); signed ones are clamped to -1.
_UNIT = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
#: Bounds on what making a file plain may allocate: an accessor without a buffer view (given
#: by a sparse part alone) declares its count freely.
MAX_DENSE_BYTES = 1 << 30
MAX_INSTANCES = 4_000_000


def needs_plain(doc: dict) -> bool:
    """Whether ``doc`` uses something :func:`plain` rewrites (trimesh would read it as other
    geometry: fans dropped, instances left out, quantized positions 32767 times too large,
    sparse values never applied, Draco as zeros)."""
    try:
        accessors = doc.get("accessors") or []

        def odd(i) -> bool:
            a = accessors[i] if isinstance(i, int) and 0 <= i < len(accessors) else {}
            return bool(a.get("normalized")) or "sparse" in a

        for mesh in doc.get("meshes") or []:
            for p in mesh.get("primitives") or []:
                if p.get("mode") == TRIANGLE_FAN or odd((p.get("attributes") or {}).get(
                        "POSITION")) or odd(p.get("indices")) or \
                        DRACO in (p.get("extensions") or {}):
                    return True
        return any(INSTANCING in (n.get("extensions") or {}) for n in doc.get("nodes") or []) \
            or any(map(_transmits, doc.get("materials") or []))
    except (TypeError, AttributeError):
        return False  # malformed: the reader says what is wrong


def _transmits(material: dict) -> bool:
    """Whether a glTF material, blended by no ``alphaMode``, lets light through by an
    extension of :data:`TRANSMISSION` (a factor that is not a number counts as above 0)."""
    if str(material.get("alphaMode", "OPAQUE")).upper() in ("BLEND", "MASK"):
        return False
    for name, factor in TRANSMISSION.items():
        ext = (material.get("extensions") or {}).get(name)
        if isinstance(ext, dict):
            value = ext.get(factor, 0.0)
            if not (isinstance(value, (int, float)) and value <= 0):
                return True
    return False


def plain(doc: dict, buffers: list[bytes], what: str) -> bytes:
    """A GLB of ``doc`` (whose buffers' bytes are ``buffers``, in order) that trimesh reads as
    the file means: each triangle fan as triangles, normalized or sparse positions, sparse
    indices and Draco-compressed primitives as plain arrays, each node of
    ``EXT_mesh_gpu_instancing`` as a node with a child per instance (the instance's transform within the node's: glTF's order). Every buffer
    becomes the GLB's one binary chunk; images named by URI stay named (culling decodes
    none)."""
    doc = json.loads(json.dumps(doc))  # a copy to edit
    out = _Buffers(doc, buffers, what)
    dense: dict[int, int] = {}

    def densified(i: int, kind: str) -> int:
        if i not in dense:
            if kind == "POSITION":
                values = out.read(i).astype("<f4")
                dense[i] = out.add(values, "VEC3", 5126, bounds=True)
            else:
                dense[i] = out.add(out.read(i).astype("<u4"), "SCALAR", 5125)
        return dense[i]

    for mesh in doc.get("meshes") or []:
        for p in mesh.get("primitives") or []:
            if DRACO in (p.get("extensions") or {}):
                _draco(p, out)
            attributes = p.get("attributes") or {}
            position = attributes.get("POSITION")
            if position is not None and out.odd(position):
                attributes["POSITION"] = densified(position, "POSITION")
            if p.get("indices") is not None and out.odd(p["indices"]):
                p["indices"] = densified(p["indices"], "indices")
            if p.get("mode") == TRIANGLE_FAN:
                _fan(p, out)
    _instances(doc, out, what)
    for material in doc.get("materials") or []:
        if _transmits(material):  # (trimesh drops the extension: see the module docstring)
            material["alphaMode"] = "BLEND"
    for key in ("extensionsRequired", "extensionsUsed"):
        if key in doc:
            doc[key] = [e for e in doc[key] if e not in (INSTANCING, DRACO)]
            if not doc[key]:
                del doc[key]
    return out.glb()


def _fan(p: dict, out: "_Buffers") -> None:
    """Primitive ``p``, a triangle fan, as triangles (``v0 vi vi+1``: the fan's winding)."""
    if p.get("indices") is not None:
        fan = out.read(p["indices"])[:, 0].astype("<u4")
    else:
        fan = np.arange(out.count(p["attributes"]["POSITION"]), dtype="<u4")
    if len(fan) < 3:
        p["mode"] = 0  # points: no triangle, as trimesh reads them
        return
    triangles = np.empty((len(fan) - 2, 3), "<u4")
    triangles[:, 0], triangles[:, 1], triangles[:, 2] = fan[0], fan[1:-1], fan[2:]
    p["indices"] = out.add(triangles.reshape(-1, 1), "SCALAR", 5125)
    p["mode"] = 4


def _draco(p: dict, out: "_Buffers") -> None:
    """Primitive ``p``, compressed by Draco, as its decoded positions and triangles (its other
    attributes left out: culling needs none, and their accessors hold no data)."""
    try:
        import DracoPy
    except ImportError:
        raise InputError(f"cannot use {out.what}: it is compressed by Draco, which needs "
                         "DracoPy: pip install 'wallcull[formats]'") from None
    ext = p["extensions"].pop(DRACO)
    if not p["extensions"]:
        del p["extensions"]
    try:
        mesh = DracoPy.decode(out.view_bytes(ext["bufferView"]))
    except Exception as exc:  # noqa: BLE001 - the decoder's own errors: bad input
        raise InputError(f"cannot use {out.what}: its Draco data cannot be decoded "
                         f"({exc})") from None
    points = np.asarray(mesh.points, "<f4").reshape(-1, 3)
    faces = getattr(mesh, "faces", None)  # none: a point cloud
    faces = np.asarray(np.zeros((0, 3)) if faces is None else faces, "<u4").reshape(-1, 3)
    attributes = p.get("attributes") or {}
    declared = out.count(attributes["POSITION"]) if "POSITION" in attributes else None
    indices = out.count(p["indices"]) if p.get("indices") is not None else None
    if declared != len(points) or (indices is not None and indices != faces.size):
        raise InputError(f"cannot use {out.what}: its Draco data decodes to {len(points):,} "
                         f"vertices and {len(faces):,} triangles, not what its accessors "
                         "declare")
    p["attributes"] = {"POSITION": out.add(points, "VEC3", 5126, bounds=True)}
    if len(faces):
        p["indices"] = out.add(faces.reshape(-1, 1), "SCALAR", 5125)
        p["mode"] = 4
    else:
        p.pop("indices", None)
        p["mode"] = 0


def _instances(doc: dict, out: "_Buffers", what: str) -> None:
    """Each node with ``EXT_mesh_gpu_instancing`` loses its mesh and gains a child per
    instance, named ``<node> #<k>``, drawing the mesh at the instance's transform."""
    nodes = doc.get("nodes") or []
    made = 0
    for i in range(len(nodes)):
        node = nodes[i]
        ext = (node.get("extensions") or {}).pop(INSTANCING, None)
        if ext is None or "mesh" not in node:
            continue
        attributes = ext.get("attributes") or {}
        parts = {k: out.read(attributes[k]).astype(float)
                 for k in ("TRANSLATION", "ROTATION", "SCALE") if k in attributes}
        counts = {len(v) for v in parts.values()}
        if len(counts) != 1:
            raise InputError(f"cannot use {what}: node {i} places its instances by "
                             "attributes that differ in count" if counts else
                             f"cannot use {what}: node {i} uses {INSTANCING} without "
                             "attributes")
        count = counts.pop()
        made += count
        if made > MAX_INSTANCES:
            raise InputError(f"cannot use {what}: its instances make over {MAX_INSTANCES:,} "
                             "nodes")
        if "ROTATION" in parts:
            r = parts["ROTATION"]
            norm = np.linalg.norm(r, axis=1, keepdims=True)
            if not (np.isfinite(norm).all() and (norm > 0).all()):
                raise InputError(f"cannot use {what}: node {i} has an instance whose rotation "
                                 "is no quaternion")
            parts["ROTATION"] = r / norm
        name, mesh = node.get("name") or f"node {i}", node.pop("mesh")
        first = len(nodes)
        for k in range(count):
            child = {"name": f"{name} #{k}", "mesh": mesh}
            for key, field in (("TRANSLATION", "translation"), ("ROTATION", "rotation"),
                               ("SCALE", "scale")):
                if key in parts:
                    child[field] = parts[key][k].tolist()
            nodes.append(child)
        node["children"] = list(node.get("children") or []) + list(range(first, len(nodes)))
        if not node["extensions"]:
            del node["extensions"]


class _Buffers:
    """A document's buffers read by accessor, and the arrays :func:`plain` adds to them."""

    def __init__(self, doc: dict, buffers: list[bytes], what: str):
        self.doc, self.buffers, self.what = doc, buffers, what
        self.added: list[bytes] = []
        self.views = len(doc.get("bufferViews") or [])  # the file's own
        self.size = sum(len(b) + (-len(b) % 4) for b in buffers)

    def odd(self, i: int) -> bool:
        a = self.doc["accessors"][i]
        return bool(a.get("normalized")) or "sparse" in a

    def count(self, i: int) -> int:
        return int(self.doc["accessors"][i]["count"])

    def _array(self, view: int, offset: int, count: int, dtype: str, width: int,
               stride: int | None = None) -> np.ndarray:
        v = self.doc["bufferViews"][view]
        data = self.buffers[v["buffer"]]
        itemsize = np.dtype(dtype).itemsize
        start = int(v.get("byteOffset", 0)) + offset
        stride = stride or int(v.get("byteStride") or itemsize * width)
        end = start + stride * (count - 1) + itemsize * width if count else start
        if count and (start < 0 or end > len(data)):
            raise InputError(f"cannot use {self.what}: bufferView {view} reads past its buffer")
        return np.ndarray((count, width), dtype, data, start, (stride, itemsize)).copy()

    def view_bytes(self, view: int) -> bytes:
        v = self.doc["bufferViews"][view]
        start = int(v.get("byteOffset", 0))
        return self.buffers[v["buffer"]][start:start + int(v["byteLength"])]

    def read(self, i: int) -> np.ndarray:
        """Accessor ``i``'s elements as rows: sparse values applied, normalized integers as
        the numbers they stand for."""
        a = self.doc["accessors"][i]
        kind, width, count = a["componentType"], _WIDTH[a["type"]], int(a["count"])
        dtype = _DTYPES[kind]
        if count * width * max(np.dtype(dtype).itemsize, 4) > MAX_DENSE_BYTES:
            raise InputError(f"cannot use {self.what}: accessor {i} declares {count:,} "
                             "elements, over what wallcull reads")
        if "bufferView" in a:
            values = self._array(a["bufferView"], int(a.get("byteOffset", 0)), count, dtype,
                                 width)
        else:
            values = np.zeros((count, width), dtype)
        sparse = a.get("sparse")
        if sparse:
            n, ix, vx = int(sparse["count"]), sparse["indices"], sparse["values"]
            at = self._array(ix["bufferView"], int(ix.get("byteOffset", 0)), n,
                             _DTYPES[ix["componentType"]], 1)[:, 0]
            if len(at) and at.max() >= count:
                raise InputError(f"cannot use {self.what}: accessor {i}'s sparse indices "
                                 f"pass its {count} elements")
            values[at] = self._array(vx["bufferView"], int(vx.get("byteOffset", 0)), n, dtype,
                                     width, np.dtype(dtype).itemsize * width)
        if a.get("normalized") and kind in _UNIT:
            values = np.maximum(values / _UNIT[kind], -1.0)
        return values

    def add(self, values: np.ndarray, type_: str, kind: int, bounds: bool = False) -> int:
        """A new accessor of ``values`` (rows), in a buffer view of its own; its index."""
        data = np.ascontiguousarray(values, _DTYPES[kind]).tobytes()
        offset = self.size + sum(len(b) for b in self.added)
        self.added.append(data + b"\0" * (-len(data) % 4))
        views = self.doc.setdefault("bufferViews", [])
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data)})
        accessor = {"bufferView": len(views) - 1, "componentType": kind, "type": type_,
                    "count": len(values)}
        if bounds and len(values):
            accessor["min"] = values.min(axis=0).tolist()
            accessor["max"] = values.max(axis=0).tolist()
        accessors = self.doc.setdefault("accessors", [])
        accessors.append(accessor)
        return len(accessors) - 1

    def glb(self) -> bytes:
        """The document and every buffer (the originals, then what was added) as one GLB."""
        starts, at = [], 0
        for b in self.buffers:
            starts.append(at)
            at += len(b) + (-len(b) % 4)
        for view in (self.doc.get("bufferViews") or [])[:self.views]:
            view["byteOffset"] = starts[view["buffer"]] + int(view.get("byteOffset", 0))
            view["buffer"] = 0
        binary = b"".join(b + b"\0" * (-len(b) % 4) for b in self.buffers) + \
            b"".join(self.added)
        self.doc["buffers"] = [{"byteLength": len(binary)}]
        text = json.dumps(self.doc, separators=(",", ":")).encode()
        text += b" " * (-len(text) % 4)
        chunks = struct.pack("<II", len(text), 0x4E4F534A) + text
        chunks += struct.pack("<II", len(binary), 0x004E4942) + binary
        return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def _buffer_bytes(doc: dict, binary: bytes | None, fetch, what: str) -> list[bytes]:
    """The bytes of ``doc``'s buffers: a GLB's binary chunk where one has no URI, a data URI
    decoded, any other URI through ``fetch``."""
    import base64
    from urllib.parse import unquote_to_bytes

    out = []
    for k, b in enumerate(doc.get("buffers") or []):
        uri = b.get("uri")
        if uri is None:
            if binary is None or k:
                raise InputError(f"cannot use {what}: buffer {k} names no file")
            out.append(binary)
        elif uri.startswith("data:"):
            head, _, body = uri.partition(",")
            out.append(base64.b64decode(body) if head.endswith(";base64")
                       else unquote_to_bytes(body))
        else:
            try:
                out.append(fetch(uri))
            except (OSError, KeyError) as exc:
                raise InputError(f"cannot use {what}: its buffer {uri!r} cannot be read "
                                 f"({exc})") from None
    return out


def _split_glb(data: bytes) -> tuple[dict | None, bytes | None]:
    """A GLB's document and binary chunk (None, None where it is no GLB)."""
    doc = document(data, ".glb")
    if doc is None:
        return None, None
    offset = 20 + struct.unpack_from("<I", data, 12)[0]
    binary = None
    while offset + 8 <= len(data):
        size, kind = struct.unpack_from("<II", data, offset)
        if kind == 0x004E4942:
            binary = data[offset + 8:offset + 8 + size]
            break
        offset += 8 + size
    return doc, binary


def plain_bytes(data: bytes, suffix: str, fetch, what: str) -> bytes | None:
    """:func:`plain` of a ``.gltf`` or ``.glb`` file's bytes (``fetch(uri)``: the bytes of a
    file it names), or None when the file needs nothing made plain."""
    if suffix.lower() == ".glb":
        doc, binary = _split_glb(data)
    else:
        doc, binary = document(data, suffix), None
    if doc is None or not needs_plain(doc):
        return None
    try:
        return plain(doc, _buffer_bytes(doc, binary, fetch, what), what)
    except InputError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
        raise InputError(f"cannot use {what}: {exc!r} while reading it") from None


def plain_file(path: Path) -> bytes | None:
    """:func:`plain_bytes` of a scene file: a ``.gltf`` or ``.glb`` made plain as a GLB, a zip
    with its members made plain (as ``.glb`` members in their place), or None."""
    import io
    import posixpath
    import zipfile
    from urllib.parse import unquote

    suffix = path.suffix.lower()
    if suffix in (".gltf", ".glb"):
        return plain_bytes(path.read_bytes(), suffix, lambda uri: beside(path, uri).read_bytes(),
                           f"scene {path.name}")
    if suffix != ".zip" or not zipfile.is_zipfile(path):
        return None
    with zipfile.ZipFile(path) as z:
        names = set(z.namelist())
        made = {}
        for m in names:
            if Path(m).suffix.lower() not in (".gltf", ".glb"):
                continue

            def fetch(uri, folder=posixpath.dirname(m)):
                for name in (posixpath.join(folder, uri), posixpath.join(folder, unquote(uri))):
                    if posixpath.normpath(name) in names:
                        return z.read(posixpath.normpath(name))
                raise KeyError(uri)

            data = plain_bytes(z.read(m), Path(m).suffix, fetch, f"scene {path.name}:{m}")
            if data is not None:
                made[m] = data
        if not made:
            return None
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w") as out:
            for m in z.namelist():
                if m in made:
                    glb = str(Path(m).with_suffix(".glb"))
                    out.writestr(glb if glb not in names else m + ".glb", made[m])
                else:
                    out.writestr(z.getinfo(m), z.read(m))
    return buffer.getvalue()
