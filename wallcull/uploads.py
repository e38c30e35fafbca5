"""Uploaded scenes, taken apart safely: a GLB is checked against the bytes it holds and against
what a scene may declare, then parsed in a child process with a memory limit.

A GLB is a JSON document plus a binary chunk, and the JSON can declare far more than the file
holds: an accessor with no buffer view and a ``count`` of 10^8 is 1 kB of JSON that a reader
turns into gigabytes of zeros (and trimesh into more). So before any reader sees the file,
:func:`check_glb` walks the document:

* every buffer is the GLB's own binary chunk (no ``uri``: no files, no URLs, no data URIs), and
  no longer than the bytes present;
* every buffer view lies inside its buffer, with a legal ``byteStride``;
* every accessor (and the index and value parts of a sparse one) lies inside its buffer view,
  with a known component type and element type; a primitive's positions are float triples
  and its indices unsigned integers;
* nodes form a forest (no node with two parents, no cycle, no index out of range);
* it uses no glTF feature that the reader would read as other geometry (:mod:`wallcull.gltf`);
* the totals stay within :class:`wallcull.limits.Limits`: nodes (each primitive of a mesh of
  several becomes one), vertices and triangles (a strip of n indices draws n - 2,
  points and lines none) counted once per node that draws them, and the bytes every
  accessor declares.

Whatever a check misses, the parse itself (trimesh, then :meth:`Scene.from_trimesh` and the
bounds) runs in a child process with a memory limit and a deadline (:mod:`wallcull.sandbox`):
a file that makes the parser allocate too much, loop, or crash costs a 422 and a dead child,
never the server. The scene comes back pickled. Materials and textures are never decoded
(``skip_materials``): culling needs none.
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

from . import gltf
from .errors import InputError
from .limits import Limits
from .validate import MAX_DEPTH

GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = b"glTF", 0x4E4F534A, 0x004E4942
COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
ELEMENT_SIZE = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
INDEX_TYPES = (5121, 5123, 5125)
FLOAT = 5126
#: A primitive's mode: 4 triangles (the default), 5 a strip, 6 a fan; 0 to 3 points and lines.
TRIANGLES = 4
#: glTF counts and offsets are unsigned 32-bit at most in practice; anything larger is a lie.
MAX_INT = 1 << 32


# --------------------------------------------------------------------------- the checks


def _without_images(doc: dict, binary: bytes) -> bytes:
    """A GLB of the checked document ``doc`` and its binary chunk, with no image, texture or
    sampler, nor any material's reference to a texture: its materials keep their factors,
    ``alphaMode`` (a see-through one never occludes) and ``doubleSided`` (a single-sided one
    occludes with its front faces alone), and no image is ever decoded."""
    doc = {k: v for k, v in doc.items() if k not in ("images", "textures", "samplers")}

    def plain(value):
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()
                    if not (k.endswith("Texture") and isinstance(v, dict))}
        return [plain(v) for v in value] if isinstance(value, list) else value

    if "materials" in doc:
        doc["materials"] = plain(doc["materials"])
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), JSON_CHUNK) + text
    if binary:
        binary += b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(binary), BIN_CHUNK) + binary
    return struct.pack("<4sII", GLB_MAGIC, 2, 12 + len(chunks)) + chunks


def glb_chunks(data: bytes) -> tuple[bytes, bytes]:
    """The JSON and binary chunks of a GLB, after checking its header and chunk lengths."""
    if data[:4] != GLB_MAGIC:
        raise InputError("an upload must be a binary glTF (.glb) file")
    if len(data) < 20:
        raise InputError("cannot read the uploaded GLB: it ends inside its header")
    _, version, length = struct.unpack_from("<4sII", data)
    if version != 2:
        raise InputError(f"cannot read the uploaded GLB: glTF version {version}; only 2 is read")
    if length > len(data):
        raise InputError(f"cannot read the uploaded GLB: its header declares {length} bytes, "
                         f"{len(data)} arrived")
    chunks, offset = [], 12
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<II", data, offset)
        if offset + 8 + size > length:
            raise InputError(f"cannot read the uploaded GLB: a chunk of {size} bytes runs past "
                             "the end of the file")
        chunks.append((kind, data[offset + 8:offset + 8 + size]))
        offset += 8 + size
    if not chunks or chunks[0][0] != JSON_CHUNK:
        raise InputError("cannot read the uploaded GLB: its first chunk is not JSON")
    binary = next((c for k, c in chunks[1:] if k == BIN_CHUNK), b"")
    return chunks[0][1], binary


def _int(value, what: str, low: int = 0, high: int = MAX_INT) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise InputError(f"the uploaded GLB's {what} must be a whole number in [{low}, {high}], "
                         f"got {value!r}")
    return value


def _list(doc: dict, key: str) -> list:
    value = doc.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise InputError(f"the uploaded GLB's {key} must be a list of objects")
    return value


def _index(value, items: list, what: str) -> int:
    if not items:
        raise InputError(f"the uploaded GLB's {what} points at nothing")
    return _int(value, what, 0, len(items) - 1)


def _span(view: dict, offset: int, count: int, element: int, stride: int, what: str) -> None:
    """Refuse ``count`` elements of ``element`` bytes, ``stride`` apart from ``offset``, that
    do not fit in the buffer view."""
    end = offset + stride * (count - 1) + element
    if end > view["byteLength"]:
        raise InputError(f"the uploaded GLB's {what} reads {end} bytes of a buffer view of "
                         f"{view['byteLength']}")


def check_glb(data: bytes, limits: Limits) -> tuple[dict, bytes]:
    """Check an uploaded GLB (see the module docstring); returns its JSON document and its
    binary chunk."""
    text, binary = glb_chunks(data)
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise InputError(f"cannot read the uploaded GLB: its JSON is malformed: {exc}") from None
    if not isinstance(doc, dict):
        raise InputError("cannot read the uploaded GLB: its JSON is not an object")
    buffers, views = _list(doc, "buffers"), _list(doc, "bufferViews")
    accessors, meshes, nodes = _list(doc, "accessors"), _list(doc, "meshes"), _list(doc, "nodes")
    sizes = []
    for i, buf in enumerate(buffers):
        if "uri" in buf:
            raise InputError(f"cannot use buffer {i} of the uploaded GLB: it names a uri; an "
                             "upload carries its data in the GLB's binary chunk")
        if i > 0:
            raise InputError("cannot use the uploaded GLB: only its binary chunk can be a buffer")
        sizes.append(_int(buf.get("byteLength"), f"buffer {i} byteLength"))
        if sizes[-1] > len(binary):
            raise InputError(f"cannot use the uploaded GLB: buffer {i} declares {sizes[-1]} "
                             f"bytes; its binary chunk holds {len(binary)}")
    for i, view in enumerate(views):
        what = f"bufferView {i}"
        b = _index(view.get("buffer"), buffers, f"{what} buffer")
        offset = _int(view.get("byteOffset", 0), f"{what} byteOffset")
        length = _int(view.get("byteLength"), f"{what} byteLength", 1)
        if offset + length > sizes[b]:
            raise InputError(f"the uploaded GLB's {what} ends at byte {offset + length} of a "
                             f"buffer of {sizes[b]}")
        if "byteStride" in view:
            stride = _int(view["byteStride"], f"{what} byteStride", 4, 252)
            if stride % 4:
                raise InputError(f"the uploaded GLB's {what} byteStride must be a multiple of 4")
    declared = 0
    for i, acc in enumerate(accessors):
        what = f"accessor {i}"
        kind = acc.get("componentType")
        if kind not in COMPONENT_BYTES:
            raise InputError(f"the uploaded GLB's {what} componentType {kind!r} is unknown")
        if acc.get("type") not in ELEMENT_SIZE:
            raise InputError(f"the uploaded GLB's {what} type {acc.get('type')!r} is unknown")
        element = COMPONENT_BYTES[kind] * ELEMENT_SIZE[acc["type"]]
        count = _int(acc.get("count"), f"{what} count", 1)
        declared += count * element
        if "bufferView" in acc:
            view = views[_index(acc["bufferView"], views, f"{what} bufferView")]
            offset = _int(acc.get("byteOffset", 0), f"{what} byteOffset")
            _span(view, offset, count, element, view.get("byteStride", element), what)
            if view.get("byteStride", element) < element:
                raise InputError(f"the uploaded GLB's {what} elements overlap (stride "
                                 f"{view['byteStride']} < {element} bytes)")
        sparse = acc.get("sparse")
        if sparse is not None:
            if not isinstance(sparse, dict) or not isinstance(sparse.get("indices"), dict) \
                    or not isinstance(sparse.get("values"), dict):
                raise InputError(f"the uploaded GLB's {what} sparse part is malformed")
            n = _int(sparse.get("count"), f"{what} sparse count", 1, count)
            indices, values = sparse["indices"], sparse["values"]
            if indices.get("componentType") not in INDEX_TYPES:
                raise InputError(f"the uploaded GLB's {what} sparse indices have an unknown "
                                 "componentType")
            for part, size in ((indices, COMPONENT_BYTES[indices["componentType"]]),
                               (values, element)):
                view = views[_index(part.get("bufferView"), views, f"{what} sparse bufferView")]
                offset = _int(part.get("byteOffset", 0), f"{what} sparse byteOffset")
                _span(view, offset, n, size, size, f"{what} sparse part")
    if declared > limits.scene_bytes:
        raise InputError(f"the uploaded GLB declares {declared:,} bytes of data; a scene may "
                         f"declare at most {limits.scene_bytes:,}")
    per_mesh = [_mesh_size(m, k, accessors) for k, m in enumerate(meshes)]
    if len(nodes) > limits.nodes:
        raise InputError(f"the uploaded GLB has {len(nodes):,} nodes; a scene may have at most "
                         f"{limits.nodes:,}")
    parents = [-1] * len(nodes)
    vertices = faces = 0
    built = len(nodes)  # and a node for each primitive of a mesh of several
    for i, node in enumerate(nodes):
        children = node.get("children", [])
        if not isinstance(children, list):
            raise InputError(f"the uploaded GLB's node {i} children must be a list")
        for child in children:
            c = _index(child, nodes, f"node {i} child")
            if parents[c] != -1 or c == i:
                raise InputError(f"the uploaded GLB's node {c} has two parents or is its own: "
                                 "glTF nodes form a tree")
            parents[c] = i
        if "mesh" in node:
            v, f, p = per_mesh[_index(node["mesh"], meshes, f"node {i} mesh")]
            n, own = _copies(node, accessors, i)  # a node of instances: a child each
            vertices, faces = vertices + v * n, faces + f * n
            built += ((p if p > 1 else 0) + own) * n
    if built > limits.nodes:
        raise InputError(f"the uploaded GLB makes {built:,} nodes (each primitive of a mesh of "
                         f"several is one); a scene may have at most {limits.nodes:,}")
    _rooted(parents)
    for k, scene in enumerate(_list(doc, "scenes")):
        roots = scene.get("nodes", [])
        if not isinstance(roots, list):
            raise InputError(f"the uploaded GLB's scene {k} nodes must be a list")
        for root in roots:
            _index(root, nodes, f"scene {k} node")
    if vertices > limits.vertices or faces > limits.faces:
        raise InputError(f"the uploaded GLB draws {vertices:,} vertices and {faces:,} triangles "
                         f"(once per node); a scene may draw at most {limits.vertices:,} and "
                         f"{limits.faces:,}")
    gltf.check(doc, "the uploaded GLB")
    return doc, binary


def _mesh_size(mesh: dict, k: int, accessors: list) -> tuple[int, int, int]:
    """Vertices, triangles and primitives one instance of mesh ``k`` declares."""
    vertices = faces = 0
    prims = mesh.get("primitives", [])
    if not isinstance(prims, list) or not all(isinstance(p, dict) for p in prims):
        raise InputError(f"the uploaded GLB's mesh {k} primitives are malformed")
    for j, p in enumerate(prims):
        what = f"mesh {k} primitive {j}"
        attributes = p.get("attributes", {})
        if not isinstance(attributes, dict):
            raise InputError(f"the uploaded GLB's mesh {k} attributes are malformed")
        for name, a in attributes.items():
            _index(a, accessors, f"mesh {k} attribute {name}")
        n = 0
        if "POSITION" in attributes:
            position = accessors[attributes["POSITION"]]
            if position["componentType"] != FLOAT or position["type"] != "VEC3":
                raise InputError(f"the uploaded GLB's {what} POSITION must be float VEC3 "
                                 f"(componentType {FLOAT}), got {position['type']} of "
                                 f"{position['componentType']}")
            n = position["count"]
        vertices += n
        if "indices" in p:
            indices = accessors[_index(p["indices"], accessors, f"{what} indices")]
            if indices["componentType"] not in INDEX_TYPES or indices["type"] != "SCALAR":
                raise InputError(f"the uploaded GLB's {what} indices must be unsigned integer "
                                 f"SCALARs (componentType {', '.join(map(str, INDEX_TYPES))}), "
                                 f"got {indices['type']} of {indices['componentType']}")
            n = indices["count"]
        mode = _int(p.get("mode", TRIANGLES), f"{what} mode", 0, 6)
        faces += n // 3 if mode == TRIANGLES else max(n - 2, 0) if mode > TRIANGLES else 0
    return vertices, faces, len(prims)


def _copies(node: dict, accessors: list, i: int) -> tuple[int, int]:
    """How many times node ``i`` draws its mesh, and whether each is a node of its own
    (``EXT_mesh_gpu_instancing``: its instances, each made a child)."""
    ext = (node.get("extensions") or {}).get(gltf.INSTANCING)
    if ext is None:
        return 1, 0
    attributes = ext.get("attributes") if isinstance(ext, dict) else None
    if not isinstance(attributes, dict) or not attributes:
        raise InputError(f"the uploaded GLB's node {i} {gltf.INSTANCING} has no attributes")
    return max(accessors[_index(a, accessors, f"node {i} instances' {name}")]["count"]
               for name, a in attributes.items()), 1


def _rooted(parents: list[int]) -> None:
    """Every node's chain of parents reaches a root (each node has one parent at most, so a
    chain that comes back to itself is the only way not to), in at most ``MAX_DEPTH`` steps."""
    depth = [-1] * len(parents)  # -1: not seen, -2: on the chain being walked
    for i in range(len(parents)):
        chain, j = [], i
        while j != -1 and depth[j] == -1:
            depth[j] = -2
            chain.append(j)
            j = parents[j]
        if j != -1 and depth[j] == -2:
            raise InputError("the uploaded GLB's nodes form a cycle")
        d = -1 if j == -1 else depth[j]
        for k in reversed(chain):
            d += 1
            depth[k] = d
        if d > MAX_DEPTH:
            raise InputError(f"the uploaded GLB's nodes are over {MAX_DEPTH:,} deep; a "
                             f"scene's may be at most {MAX_DEPTH:,}")


# --------------------------------------------------------------------------- the parse


def parse_glb(path: str, name: str, limits: Limits):
    """Check and parse a GLB file into a usable :class:`~wallcull.scene.Scene` (in this process:
    call :func:`parse_sandboxed` for untrusted files)."""
    import numpy as np
    import trimesh

    from .scene import Scene, read_glb, usable

    data = Path(path).read_bytes()
    doc, binary = check_glb(data, limits)
    try:  # its materials without their images: what occludes needs their alphaMode and sides
        loaded = read_glb(_without_images(doc, binary))
    except MemoryError:
        raise
    except Exception as exc:  # noqa: BLE001 - a parser failure is bad input
        raise InputError(f"cannot read the uploaded GLB: {exc}") from None
    del data
    if not isinstance(loaded, trimesh.Scene):
        loaded = trimesh.Scene(loaded)
    if not loaded.geometry:
        raise InputError("the uploaded GLB has no geometry")
    try:
        with np.errstate(all="ignore"):  # odd files overflow on their way to being refused
            return usable(Scene.from_trimesh(loaded, name=name))
    except (InputError, MemoryError):
        raise
    except Exception as exc:  # noqa: BLE001 - whatever an odd file trips is bad input
        raise InputError(f"cannot use the uploaded GLB: {type(exc).__name__}: {exc}") from None


def parse_sandboxed(path: str | os.PathLike, name: str, limits: Limits):
    """:func:`parse_glb` in a child process (:mod:`wallcull.sandbox`) with
    ``limits.parse_memory`` bytes of address space and ``limits.parse_seconds`` of time.
    Blocking: call it from a worker thread. Whatever goes wrong in the child is an
    :class:`InputError`."""
    from . import sandbox

    return sandbox.run(parse_glb, (str(path), name, limits), seconds=limits.parse_seconds,
                       memory=limits.parse_memory, what="parsing the uploaded GLB")
