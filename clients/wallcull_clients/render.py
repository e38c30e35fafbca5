"""A headless OpenGL tile renderer: the tool that checks fitted frusta, later the render client.

Conventions (SPEC section 1): right-handed, the camera looks down its local ``-z``, column vectors,
``p_clip = projection @ view @ model @ p``, clip-space depth in ``[-1, 1]`` (``[0, 1]`` with
``reversed_z``). Matrices are numpy ``(4, 4)`` arrays indexed ``m[row][col]``, as on the wire.

One standalone EGL context (Mesa llvmpipe on a CPU) is created on first use and shared by every
:class:`TileRenderer` in the process; each renderer owns its framebuffer and its mesh cache. The
context belongs to the thread that created it: use the renderers from that thread only.

Framebuffer of a renderer (``width x height``):

* attachment 0: ``RGBA8`` color, Lambert shading with a headlight at the eye times a flat colour
  per ``draw_id`` (back faces darker), background ``BACKGROUND``;
* attachment 1: ``R32UI`` ids, the ``draw_id`` of the nearest surface, ``0`` for background
  (with ``triangle_ids``: ``draw_id`` plus the index of the nearest triangle in its mesh);
* depth: ``DEPTH_COMPONENT24`` (a depth texture, so it can be read back).

With ``samples > 0`` drawing goes to multisampled renderbuffers of the same formats, resolved into
the above after each frame (integer ids and depth resolve to one sample, not an average).
"""

from __future__ import annotations

import colorsys
import ctypes
from dataclasses import dataclass
from pathlib import Path
from typing import Hashable, Iterable

import numpy as np

try:
    import moderngl
except ImportError:  # pragma: no cover - reported when a renderer is created
    moderngl = None

#: Background colour of the color image, RGBA8 (opaque dark grey, so saved PNGs read well).
BACKGROUND = (0.1, 0.1, 0.1, 1.0)

# GL enums that moderngl does not name.
_GL_CLIP_DISTANCE0 = 0x3000
_GL_LOWER_LEFT = 0x8CA1
_GL_NEGATIVE_ONE_TO_ONE = 0x935E
_GL_ZERO_TO_ONE = 0x935F

_VERTEX_SHADER = """
#version 330
uniform mat4 mvp;    // projection @ view @ model, product taken in float64 on the CPU
uniform mat4 mv;     // view @ model, for shading only
uniform mat4 world;  // model, or model relative to the eye (camera_relative), for clip planes
uniform vec4 plane;  // world-space clip plane (a, b, c, d), in the same space as `world`
in vec3 in_pos;
out vec3 v_eye;
void main() {
    vec4 p = vec4(in_pos, 1.0);
    gl_Position = mvp * p;
    v_eye = (mv * p).xyz;
    gl_ClipDistance[0] = dot(plane, world * p);  // ignored unless GL_CLIP_DISTANCE0 is enabled
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform vec3 color;
uniform uint draw_id;
uniform bool triangle_ids;  // ids per triangle: draw_id + the triangle's index in its mesh
uniform uint first;         // the index of the draw's first triangle in its mesh
in vec3 v_eye;
layout(location = 0) out vec4 f_color;
layout(location = 1) out uint f_id;
void main() {
    // Flat triangle normal from screen-space derivatives: no normals need uploading.
    vec3 n = normalize(cross(dFdx(v_eye), dFdy(v_eye)));
    float shade = 0.25 + 0.75 * abs(dot(n, normalize(-v_eye)));
    if (!gl_FrontFacing) shade *= 0.5;  // makes wrong winding (e.g. mirrors) visible
    f_color = vec4(color * shade, 1.0);
    f_id = triangle_ids ? draw_id + first + uint(gl_PrimitiveID) : draw_id;
}
"""


class _Shared:
    """The process-wide context, program and glClipControl entry point (created lazily)."""

    ctx = None
    program = None
    clip_control = None  # ctypes function, or None when neither GL 4.5 nor ARB_clip_control


def _shared() -> type[_Shared]:
    if _Shared.ctx is None:
        if moderngl is None:
            raise RuntimeError("clients.render needs moderngl (pip install moderngl)")
        ctx = moderngl.create_standalone_context(backend="egl", require=330)
        with ctx:
            _Shared.program = ctx.program(vertex_shader=_VERTEX_SHADER,
                                          fragment_shader=_FRAGMENT_SHADER)
            # moderngl has no glClipControl; load it through the context's own EGL loader.
            if ctx.version_code >= 450 or "GL_ARB_clip_control" in ctx.extensions:
                address = ctx.mglo._context.load("glClipControl")
                if address:
                    _Shared.clip_control = ctypes.CFUNCTYPE(None, ctypes.c_uint, ctypes.c_uint)(address)
        _Shared.ctx = ctx
    return _Shared


def reversed_z_available() -> bool:
    """Whether ``render(..., reversed_z=True)`` works here (glClipControl reachable)."""
    return _shared().clip_control is not None


def draw_color(draw_id: int) -> tuple[float, float, float]:
    """The flat RGB colour (floats in [0, 1]) of ``draw_id``: hues spaced by the golden ratio."""
    return colorsys.hsv_to_rgb((draw_id * 0.618033988749895) % 1.0, 0.55, 0.95)


def _translation(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def _matrix(m, what: str) -> np.ndarray:
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"{what} must be a finite 4x4 matrix, got shape {m.shape}")
    return m


def _gl(m: np.ndarray) -> bytes:
    """A float64 row-major matrix as the column-major float32 bytes GLSL expects."""
    return np.asarray(m, dtype=np.float32).tobytes(order="F")


@dataclass
class Image:
    """One rendered frame; row 0 is the TOP row of the image (OpenGL's rows are flipped).

    ``color``: ``(h, w, 4)`` uint8 RGBA. ``ids``: ``(h, w)`` uint32 draw ids, 0 = background.
    ``depth``: ``(h, w)`` float32 window depth in ``[0, 1]`` (1 = far plane and background;
    with ``reversed_z`` 1 is the near plane and 0 the far plane and background).
    """

    color: np.ndarray
    ids: np.ndarray
    depth: np.ndarray

    def save_png(self, path) -> None:
        """Write the color image as an RGBA PNG."""
        from PIL import Image as PILImage

        PILImage.fromarray(self.color, "RGBA").save(Path(path))


@dataclass
class _Mesh:
    vao: object  # None, with vbo and ibo, for a mesh of no triangles: it draws nothing
    vbo: object
    ibo: object
    center: np.ndarray  # float64 local origin subtracted before the float32 conversion
    triangles: int
    single_sided: bool = False  # its back faces culled when drawn


def _ranges(rest: list) -> np.ndarray | None:
    """A draw's optional fourth item: ``(k, 2)`` int ranges, or None for the whole mesh."""
    if not rest or rest[0] is None:
        return None
    ranges = np.asarray(rest[0], dtype=np.int64).reshape(-1, 2)
    if (ranges[:, 1] < 0).any():
        raise ValueError("a draw range has a negative count")
    return ranges


class TileRenderer:
    """Offscreen renderer of cached meshes into a ``width x height`` tile (see module doc).

    GL objects are not freed by garbage collection: call :meth:`release` when done.
    """

    def __init__(self, width: int, height: int, *, samples: int = 0):
        if width < 1 or height < 1 or samples < 0:
            raise ValueError(f"bad renderer size {width}x{height} or samples {samples}")
        shared = _shared()
        self._ctx, self._program = shared.ctx, shared.program
        self.width, self.height, self.samples = int(width), int(height), int(samples)
        self._meshes: dict[Hashable, _Mesh] = {}
        size = (self.width, self.height)
        with self._ctx as ctx:
            self._color = ctx.texture(size, 4)
            self._ids = ctx.texture(size, 1, dtype="u4")
            self._depth = ctx.depth_texture(size)
            self._fbo = ctx.framebuffer([self._color, self._ids], self._depth)
            if samples:
                color = ctx.renderbuffer(size, 4, samples=samples)
                ids = ctx.renderbuffer(size, 1, samples=samples, dtype="u4")
                depth = ctx.depth_renderbuffer(size, samples=samples)
                self._draw_fbo = ctx.framebuffer([color, ids], depth)
            else:
                color, ids, depth = self._color, self._ids, self._depth
                self._draw_fbo = self._fbo
            # moderngl clears every color attachment with one float colour, whose bits land in the
            # integer id buffer: clear all to 0.0 (bits of uint 0), then the color alone.
            self._clear_color = ctx.framebuffer([color])
        self._gl_objects = [self._fbo, self._draw_fbo, self._clear_color, self._color, self._ids,
                            self._depth, color, ids, depth]

    @property
    def cached_bytes(self) -> int:
        """GPU bytes of the cached meshes (float32 vertices + uint32 indices)."""
        return sum(m.vbo.size + m.ibo.size for m in self._meshes.values() if m.vao is not None)

    def upload(self, key: Hashable, vertices: np.ndarray, faces: np.ndarray, *,
               single_sided: bool = False) -> None:
        """Cache a mesh under ``key``, replacing any mesh cached under it.

        ``vertices``: ``(n, 3)`` float, object space. ``faces``: ``(m, 3)`` int indices into them;
        a mesh of no faces (a glTF primitive of points) is cached and draws nothing.
        The vertices are stored as float32 relative to their bounding-box centre (subtracted in
        float64; the draw's model matrix gets it back), so a mesh baked far from the origin keeps
        its float32 precision. ``single_sided``: its back faces are culled when it is drawn, as
        glTF asks of a material that is not ``doubleSided`` (front faces wind counter-clockwise,
        clockwise under a model matrix of negative determinant); other meshes show both faces.
        """
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
            raise ValueError(f"vertices must be finite (n, 3), got shape {vertices.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
            raise ValueError(f"faces must be (m, 3) integers, got {faces.shape} {faces.dtype}")
        if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
            raise ValueError("faces index outside the vertices")
        center = (vertices.min(0) + vertices.max(0)) / 2 if len(vertices) else np.zeros(3)
        self.evict(key)
        if not len(faces):  # (a GL buffer cannot be empty)
            self._meshes[key] = _Mesh(None, None, None, center, 0, bool(single_sided))
            return
        with self._ctx as ctx:
            vbo = ctx.buffer((vertices - center).astype(np.float32).tobytes())
            ibo = ctx.buffer(faces.astype(np.uint32).tobytes())
            vao = ctx.vertex_array(self._program, [(vbo, "3f", "in_pos")],
                                   index_buffer=ibo, index_element_size=4)
        self._meshes[key] = _Mesh(vao, vbo, ibo, center, len(faces), bool(single_sided))

    def evict(self, key: Hashable) -> None:
        """Free the mesh cached under ``key`` (no-op if none)."""
        mesh = self._meshes.pop(key, None)
        if mesh is not None and mesh.vao is not None:
            with self._ctx:
                for obj in (mesh.vao, mesh.vbo, mesh.ibo):
                    obj.release()

    def render(self, draws: Iterable[tuple], view: np.ndarray,
               projection: np.ndarray, *, clip_plane=None, reversed_z: bool = False,
               front_face_cw: bool = False, camera_relative: bool = False,
               triangle_ids: bool = False) -> Image:
        """Draw ``(key, model (4, 4), draw_id >= 1)`` triples and read the frame back. A fourth
        item, ``ranges (k, 2)`` of ``(first triangle, triangles)``, draws only those triangles
        of the mesh (a leaf a tile shows in part: its clusters' draw ranges); None draws all.

        Each draw uploads ``projection @ view @ model`` multiplied in float64 and converted to
        float32 once: with world offsets of 1e7 (float32 ulp = 1) separate float32 matrices
        multiplied on the GPU would lose the whole object, while the product's translation is the
        small eye-relative offset. ``camera_relative=True`` also moves the world-space quantities
        the GPU still sees (the clip distance) to eye-relative space: ``view`` becomes its
        rotation-only part ``view @ T(eye)``, each model ``T(-eye) @ model`` and the clip plane is
        shifted to match, all in float64; the image is mathematically unchanged.

        Depth is cleared to 1 and tested LESS (of coincident surfaces the first drawn stays).
        ``reversed_z``: clip depth in ``[0, 1]`` via glClipControl, depth cleared to 0 and tested
        GREATER; pass a reversed projection (near -> 1, far -> 0).
        ``clip_plane``: world-space ``(a, b, c, d)``; points with ``a x + b y + c z + d < 0`` are
        clipped (``gl_ClipDistance[0]``), the inward-normal convention of ``wallcull.wall``.
        ``front_face_cw``: clockwise front faces, for mirrored views; only the back faces of
        meshes uploaded ``single_sided`` are culled, other meshes' front faces are only shaded
        brighter than their back faces.
        ``triangle_ids``: each pixel's id is its triangle's, ``draw_id`` plus the triangle's
        index in its mesh (``gl_PrimitiveID``, counted from the range's first triangle), so a
        draw of ``k`` triangles uses the ids ``draw_id`` to ``draw_id + k - 1``.
        Raises KeyError for a key not uploaded, ValueError for a bad matrix or draw_id.
        """
        view = _matrix(view, "view")
        projection = _matrix(projection, "projection")
        draws = [(key, _matrix(model, "model"), int(draw_id), _ranges(rest))
                 for key, model, draw_id, *rest in draws]
        for key, _, draw_id, ranges in draws:
            if key not in self._meshes:
                raise KeyError(f"no mesh uploaded under {key!r}")
            top = draw_id + (max(self._meshes[key].triangles - 1, 0) if triangle_ids else 0)
            if not 1 <= draw_id <= top < 2**32:
                raise ValueError(f"draw_id must be in [1, 2**32), got {draw_id}"
                                 + (" (and its mesh's triangles after it)" if triangle_ids else ""))
            if ranges is not None and len(ranges) and (
                    ranges.min() < 0 or (ranges.sum(axis=1) > self._meshes[key].triangles).any()):
                raise ValueError(f"ranges outside the {self._meshes[key].triangles} triangles "
                                 f"of {key!r}")
        shared = _shared()
        if reversed_z and shared.clip_control is None:
            raise NotImplementedError("reversed_z needs glClipControl (GL 4.5 or ARB_clip_control), "
                                      "which this OpenGL context lacks")
        to_world = np.eye(4)  # world space -> the space of the `world` uniform and the clip plane
        if camera_relative:  # view @ model == (view @ T(eye)) @ (T(-eye) @ model)
            eye = np.linalg.inv(view)[:3, 3]
            view, to_world = view @ _translation(eye), _translation(-eye)
        plane = np.zeros(4)
        if clip_plane is not None:
            plane = np.asarray(clip_plane, dtype=np.float64).reshape(4)
            plane = plane @ np.linalg.inv(to_world)  # planes transform by the inverse transpose

        program = self._program
        with self._ctx as ctx:
            # The context is shared between renderers: set every piece of state each frame.
            self._draw_fbo.use()
            ctx.enable_only(moderngl.DEPTH_TEST)
            ctx.front_face = "cw" if front_face_cw else "ccw"
            # Without a plane the shader gets (0, 0, 0, 0), distance 0 = kept: harmless also on
            # drivers that apply written clip distances regardless of the enable (llvmpipe does).
            (ctx.enable_direct if clip_plane is not None else ctx.disable_direct)(_GL_CLIP_DISTANCE0)
            if shared.clip_control is not None:
                shared.clip_control(_GL_LOWER_LEFT,
                                    _GL_ZERO_TO_ONE if reversed_z else _GL_NEGATIVE_ONE_TO_ONE)
            ctx.depth_func = ">" if reversed_z else "<"
            self._draw_fbo.clear(0.0, 0.0, 0.0, 0.0, depth=0.0 if reversed_z else 1.0)
            self._clear_color.clear(*BACKGROUND)
            self._draw_fbo.use()
            program["plane"].value = tuple(plane)
            program["triangle_ids"].value = triangle_ids
            for key, model, draw_id, ranges in draws:
                mesh = self._meshes[key]
                if mesh.vao is None:
                    continue  # no triangles
                if mesh.single_sided:  # its front winds the other way under a mirroring model
                    ctx.enable(moderngl.CULL_FACE)
                    ctx.cull_face = "back"
                    mirrored = np.linalg.det(model[:3, :3]) < 0
                    ctx.front_face = "cw" if front_face_cw != mirrored else "ccw"
                else:
                    ctx.disable(moderngl.CULL_FACE)
                    ctx.front_face = "cw" if front_face_cw else "ccw"
                world = to_world @ model @ _translation(mesh.center)
                modelview = view @ world
                program["mvp"].write(_gl(projection @ modelview))
                program["mv"].write(_gl(modelview))
                program["world"].write(_gl(world))
                program["color"].value = draw_color(draw_id)
                program["draw_id"].value = draw_id
                if ranges is None:
                    program["first"].value = 0
                    mesh.vao.render(moderngl.TRIANGLES)
                else:  # one draw call per range, counted in indices
                    for first, count in ranges.tolist():
                        program["first"].value = first
                        mesh.vao.render(moderngl.TRIANGLES, vertices=3 * count, first=3 * first)
            if self.samples:
                ctx.copy_framebuffer(self._fbo, self._draw_fbo)
            h, w = self.height, self.width
            color = np.frombuffer(self._color.read(), np.uint8).reshape(h, w, 4)
            ids = np.frombuffer(self._ids.read(), np.uint32).reshape(h, w)
            depth = np.frombuffer(self._depth.read(), np.float32).reshape(h, w)
        # OpenGL rows run bottom-up; flip so that row 0 is the top of the image.
        return Image(color[::-1].copy(), ids[::-1].copy(), depth[::-1].copy())

    def release(self) -> None:
        """Free the framebuffers and every cached mesh (the shared context stays)."""
        for key in list(self._meshes):
            self.evict(key)
        with self._ctx:
            for obj in {id(o): o for o in self._gl_objects}.values():
                obj.release()
        self._gl_objects = []
