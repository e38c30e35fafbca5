"""Packets and node messages as bytes: the ``encode`` arrow of DESIGN.md, compiled.

A tile's packet (:mod:`wallcull.protocol`) is a msgpack map; building it as a Python dict and
packing it costs about 10 us a tile, 40 ms for a 64 x 64 wall. Here a frame is encoded in
compiled passes over its arrays, with no Python object per tile:

* the fits' segments, once per frame (:func:`_fit_segments`): every tile's fitted frusta
  (``view``, ``projection``, ``near``, ``far``, any ``shadows`` and ``mirrors``, ``left`` and
  ``right``) as msgpack key/value pairs. They do not depend on what a packet's delta is
  against, so every packet of the frame copies them;
* :func:`packets`: the packets of any tiles, each its header (frame, tile, time, base), its
  list (full, or a delta against the base) and its tile's segment;
* node messages (several tiles of one render node in one message): every tile's entry against
  a base once per frame (:func:`node_entries`: its list, its compact frusta), then a node's
  message is the frame's shared head and its tiles' entries, one slice when its tiles are
  consecutive (:func:`node_message`).

The bytes decode to exactly the dicts :func:`wallcull.protocol.packet` and
:func:`wallcull.protocol.node_message` build (a test holds this). In packets floats are
float64 and integers take the shortest msgpack form, as ``msgpack.packb`` writes them; in node
messages a depth that float32 holds exactly goes as float32. JSON, and the moved transforms of
a dynamic scene, still go through dicts.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import msgpack
import numpy as np
from numba import njit

from . import protocol
from .fit import CUBE, FRUSTUM, Fits

_KEYS = ("frame", "tile", "time", "base", "visible", "added", "removed", "count", "view",
         "projection", "near", "far", "shadows", "mirrors", "light", "cube", "views", "coverage",
         "casters", "mirror", "front_face", "cw", "left", "right", "rotation", "translation",
         "extent", "depth", "ranges", "whole")
(K_FRAME, K_TILE, K_TIME, K_BASE, K_VISIBLE, K_ADDED, K_REMOVED, K_COUNT, K_VIEW,
 K_PROJECTION, K_NEAR, K_FAR, K_SHADOWS, K_MIRRORS, K_LIGHT, K_CUBE, K_VIEWS, K_COVERAGE,
 K_CASTERS, K_MIRROR, K_FRONT_FACE, V_CW, K_LEFT, K_RIGHT, K_ROTATION, K_TRANSLATION, K_EXTENT,
 K_DEPTH, K_RANGES, K_WHOLE) = range(len(_KEYS))


def _pack_each(items) -> tuple[np.ndarray, np.ndarray]:
    """Objects packed with msgpack one by one, concatenated: ``(bytes (uint8), offsets
    (n + 1,))``."""
    parts = [msgpack.packb(s, use_bin_type=True) for s in items]
    offsets = np.zeros(len(parts) + 1, np.int64)
    np.cumsum([len(p) for p in parts], out=offsets[1:])
    return np.frombuffer(b"".join(parts), np.uint8).copy(), offsets


_KEY_BYTES, _KEY_OFFSETS = _pack_each(_KEYS)

MAT4 = 1 + 4 * (1 + 4 * 9)  # bytes of a 4x4 float64 matrix: array of 4 arrays of 4 floats
NUMBER = 9  # the most bytes a msgpack number takes


# --------------------------------------------------------------------------- writing


@njit(cache=True, inline="always")
def _copy(buf, p, src, a, b):
    buf[p:p + b - a] = src[a:b]
    return p + b - a


@njit(cache=True, inline="always")
def _key(buf, p, k):
    return _copy(buf, p, _KEY_BYTES, _KEY_OFFSETS[k], _KEY_OFFSETS[k + 1])


@njit(cache=True, inline="always")
def _be(buf, p, value, width):
    for i in range(width - 1, -1, -1):
        buf[p + i] = value & 0xFF
        value >>= 8
    return p + width


@njit(cache=True, _nrt=False)
def _int(buf, p, v):
    """A msgpack integer, in the shortest form (as msgpack.packb writes it). (Compiled without
    reference counts: it allocates nothing and its callers hold the buffer; inlined where it
    is called, as the small helpers are, it took a quarter more time to compile.)"""
    if v >= 0:
        if v < 128:
            buf[p] = v
            return p + 1
        if v < 256:
            buf[p] = 0xCC
            return _be(buf, p + 1, v, 1)
        if v < 65536:
            buf[p] = 0xCD
            return _be(buf, p + 1, v, 2)
        if v < 4294967296:
            buf[p] = 0xCE
            return _be(buf, p + 1, v, 4)
        buf[p] = 0xCF
        return _be(buf, p + 1, v, 8)
    if v >= -32:
        buf[p] = v & 0xFF
        return p + 1
    if v >= -128:
        buf[p] = 0xD0
        return _be(buf, p + 1, v & 0xFF, 1)
    if v >= -32768:
        buf[p] = 0xD1
        return _be(buf, p + 1, v & 0xFFFF, 2)
    if v >= -2147483648:
        buf[p] = 0xD2
        return _be(buf, p + 1, v & 0xFFFFFFFF, 4)
    buf[p] = 0xD3
    return _be(buf, p + 1, v, 8)


@njit(cache=True, inline="always")
def _float(buf, p, v, bits):
    """A msgpack float64 (``bits``: a one-element float64 scratch array)."""
    bits[0] = v
    u = bits.view(np.uint64)[0]
    buf[p] = 0xCB
    buf[p + 1] = (u >> 56) & 0xFF
    buf[p + 2] = (u >> 48) & 0xFF
    buf[p + 3] = (u >> 40) & 0xFF
    buf[p + 4] = (u >> 32) & 0xFF
    buf[p + 5] = (u >> 24) & 0xFF
    buf[p + 6] = (u >> 16) & 0xFF
    buf[p + 7] = (u >> 8) & 0xFF
    buf[p + 8] = u & 0xFF
    return p + 9


@njit(cache=True, inline="always")
def _header(buf, p, n, small, tag16, tag32):
    """A map or array header: ``small | n`` up to 15 items, else 16- or 32-bit lengths."""
    if n < 16:
        buf[p] = small | n
        return p + 1
    if n < 65536:
        buf[p] = tag16
        return _be(buf, p + 1, n, 2)
    buf[p] = tag32
    return _be(buf, p + 1, n, 4)


@njit(cache=True, inline="always")
def _map(buf, p, n):
    return _header(buf, p, n, 0x80, 0xDE, 0xDF)


@njit(cache=True, inline="always")
def _array(buf, p, n):
    return _header(buf, p, n, 0x90, 0xDC, 0xDD)


@njit(cache=True, inline="always")
def _ints(buf, p, values, a, b):
    p = _array(buf, p, b - a)
    for i in range(a, b):
        v = values[i]
        if 0 <= v < 128:  # the common forms here, as _int writes them, without a call
            buf[p] = v
            p += 1
        elif 256 <= v < 65536:
            buf[p] = 0xCD
            buf[p + 1] = v >> 8
            buf[p + 2] = v & 0xFF
            p += 3
        else:
            p = _int(buf, p, v)
    return p


@njit(cache=True)
def _parts(buf, p, which, a, b, part_leaf, range_start, ranges):
    """The draw ranges of parts ``which[a:b]`` (:class:`wallcull.protocol.FrameRecord`'s
    ``parts``), keyed: ``"ranges": [[leaf, first, count, ...], ...]``."""
    p = _key(buf, p, K_RANGES)
    p = _array(buf, p, b - a)
    for k in range(a, b):
        q = which[k]
        r0, r1 = range_start[q], range_start[q + 1]
        p = _array(buf, p, 1 + 2 * (r1 - r0))
        p = _int(buf, p, part_leaf[q])
        for r in range(r0, r1):
            p = _int(buf, p, ranges[r, 0])
            p = _int(buf, p, ranges[r, 1])
    return p


@njit(cache=True, inline="always")
def _mat4(buf, p, m, bits):
    buf[p] = 0x94
    p += 1
    for i in range(4):
        buf[p] = 0x94
        p += 1
        for j in range(4):
            p = _float(buf, p, m[i, j], bits)
    return p


@njit(cache=True, inline="always")
def _short_float(buf, p, v, bits, bits32):
    """A float as msgpack float32 when that is exact, else float64: the same value either way."""
    bits32[0] = v
    if np.float64(bits32[0]) != v:
        return _float(buf, p, v, bits)
    u = bits32.view(np.uint32)[0]
    buf[p] = 0xCA
    buf[p + 1] = (u >> 24) & 0xFF
    buf[p + 2] = (u >> 16) & 0xFF
    buf[p + 3] = (u >> 8) & 0xFF
    buf[p + 4] = u & 0xFF
    return p + 5


@njit(cache=True)
def _floats(buf, p, values, bits):
    p = _array(buf, p, values.shape[0])
    for i in range(values.shape[0]):
        p = _float(buf, p, values[i], bits)
    return p


@njit(cache=True)
def _rigid(buf, p, q, t, bits):
    """A rigid view: ``{"rotation": [w, x, y, z], "translation": [x, y, z]}``."""
    p = _map(buf, p, 2)
    p = _key(buf, p, K_ROTATION)
    p = _floats(buf, p, q, bits)
    p = _key(buf, p, K_TRANSLATION)
    return _floats(buf, p, t, bits)


# --------------------------------------------------------------------------- fits
#
# A frame's fits travel to the kernels as tuples of arrays (see _FitArrays): F the main
# view and projection, S the shadows (one light per row), M the mirrors, E the eyes of a
# stereo frame, C the compact forms of the node messages.


@njit(cache=True, inline="always")
def _view(out, p, views, shared, t, bits):
    """A tile's view: the frame's shared one, pre-encoded (``views`` has one row), or its own."""
    if views.shape[0] == 1:
        return _copy(out, p, shared, 0, shared.shape[0])
    return _mat4(out, p, views[t], bits)


@njit(cache=True)
def _shadows(out, p, t, S, bits):
    """Tile ``t``'s ``shadows`` pair, if it has any shadow frustum: ``(p, pairs written)``."""
    (s_kind, s_view, s_projection, s_near, s_far, s_coverage, s_start, s_casters, s_names,
     s_name_off, s_cube, s_cube_off) = S
    shadows = 0
    for q in range(s_kind.shape[0]):
        shadows += s_kind[q, t] != 0
    if not shadows:
        return p, 0
    p = _key(out, p, K_SHADOWS)
    p = _array(out, p, shadows)
    for q in range(s_kind.shape[0]):
        kind = s_kind[q, t]
        if kind == 0:
            continue
        p = _map(out, p, 7)
        p = _key(out, p, K_LIGHT)
        p = _copy(out, p, s_names, s_name_off[q], s_name_off[q + 1])
        if kind == CUBE:
            p = _key(out, p, K_CUBE)
            out[p] = 0xC3  # true
            p += 1
            p = _key(out, p, K_VIEWS)
            p = _copy(out, p, s_cube, s_cube_off[q], s_cube_off[q + 1])
        else:
            p = _key(out, p, K_VIEW)
            p = _mat4(out, p, s_view[q, t], bits)
        p = _key(out, p, K_PROJECTION)
        p = _mat4(out, p, s_projection[q, t], bits)
        p = _key(out, p, K_NEAR)
        p = _float(out, p, s_near[q, t], bits)
        p = _key(out, p, K_FAR)
        p = _float(out, p, s_far[q, t], bits)
        if kind == FRUSTUM:  # (a cube map has "cube" and "views" instead)
            p = _key(out, p, K_COVERAGE)
            p = _float(out, p, s_coverage[q, t], bits)
        p = _key(out, p, K_CASTERS)
        p = _ints(out, p, s_casters, s_start[q, t], s_start[q, t + 1])
    return p, 1


@njit(cache=True)
def _mirrors(out, p, t, M, bits):
    """Tile ``t``'s ``mirrors`` pair, if it sees any mirror: ``(p, pairs written)``."""
    (m_shown, m_views, m_view_bytes, m_view_off, m_projection, m_start, m_visible, m_names,
     m_name_off) = M
    mirrors = 0
    for q in range(m_shown.shape[0]):
        mirrors += m_shown[q, t]
    if not mirrors:
        return p, 0
    p = _key(out, p, K_MIRRORS)
    p = _array(out, p, mirrors)
    for q in range(m_shown.shape[0]):
        if not m_shown[q, t]:
            continue
        p = _map(out, p, 5)
        p = _key(out, p, K_MIRROR)
        p = _copy(out, p, m_names, m_name_off[q], m_name_off[q + 1])
        p = _key(out, p, K_VIEW)
        p = _view(out, p, m_views[q], m_view_bytes[m_view_off[q]:m_view_off[q + 1]], t, bits)
        p = _key(out, p, K_PROJECTION)
        p = _mat4(out, p, m_projection[q, t], bits)
        p = _key(out, p, K_FRONT_FACE)
        p = _key(out, p, V_CW)
        p = _key(out, p, K_VISIBLE)
        p = _ints(out, p, m_visible, m_start[q, t], m_start[q, t + 1])
    return p, 1


@njit(cache=True, inline="always")
def _eye_sees(M, E, e, t):
    """How many mirrors eye ``e`` of tile ``t`` sees."""
    seen = 0
    for q in range(M[0].shape[0]):
        seen += M[0][q, t] and E[8][e, q, t]
    return seen


@njit(cache=True)
def _eye_mirrors(out, p, e, t, M, E, bits):
    """Eye ``e``'s ``mirrors`` pair of tile ``t``, if it sees any."""
    m_shown, m_names, m_name_off = M[0], M[7], M[8]
    e_m_views, e_m_projection, e_m_shown = E[6], E[7], E[8]
    seen = _eye_sees(M, E, e, t)
    if not seen:
        return p
    p = _key(out, p, K_MIRRORS)
    p = _array(out, p, seen)
    for q in range(m_shown.shape[0]):
        if not (m_shown[q, t] and e_m_shown[e, q, t]):
            continue
        p = _map(out, p, 3)
        p = _key(out, p, K_MIRROR)
        p = _copy(out, p, m_names, m_name_off[q], m_name_off[q + 1])
        p = _key(out, p, K_VIEW)
        p = _mat4(out, p, e_m_views[e, q, 0 if e_m_views.shape[2] == 1 else t], bits)
        p = _key(out, p, K_PROJECTION)
        p = _mat4(out, p, e_m_projection[e, q, t], bits)
    return p


@njit(cache=True, nogil=True)
def _fit_segments(F, S, M, E, out, out_start, out_pairs):
    """Every tile's fitted frusta, as a packet carries them, as msgpack key/value pairs into
    ``out``: ``out_start`` (T + 1) offsets, ``out_pairs`` (T) pairs per tile."""
    views, view_bytes, projection, near, far = F
    e_views, e_view_bytes, e_view_off, e_projection, e_near, e_far = E[:6]
    bits = np.empty(1)
    tiles = projection.shape[0]
    p = 0
    for t in range(tiles):
        out_start[t] = p
        p = _key(out, p, K_VIEW)
        p = _view(out, p, views, view_bytes, t, bits)
        p = _key(out, p, K_PROJECTION)
        p = _mat4(out, p, projection[t], bits)
        p = _key(out, p, K_NEAR)
        p = _float(out, p, near[t], bits)
        p = _key(out, p, K_FAR)
        p = _float(out, p, far[t], bits)
        has_shadows = has_mirrors = 0
        if S[0].shape[0]:  # lights declared (a call passes its arrays' references)
            p, has_shadows = _shadows(out, p, t, S, bits)
        if M[0].shape[0]:
            p, has_mirrors = _mirrors(out, p, t, M, bits)
        for e in range(e_views.shape[0]):  # a stereo frame: "left", "right"
            p = _key(out, p, K_LEFT + e)
            p = _map(out, p, 4 + (_eye_sees(M, E, e, t) > 0))
            p = _key(out, p, K_VIEW)
            p = _view(out, p, e_views[e], e_view_bytes[e_view_off[e]:e_view_off[e + 1]], t,
                      bits)
            p = _key(out, p, K_PROJECTION)
            p = _mat4(out, p, e_projection[e, t], bits)
            p = _key(out, p, K_NEAR)
            p = _float(out, p, e_near[e, t], bits)
            p = _key(out, p, K_FAR)
            p = _float(out, p, e_far[e, t], bits)
            p = _eye_mirrors(out, p, e, t, M, E, bits)
        out_pairs[t] = 4 + has_shadows + has_mirrors + e_views.shape[0]
    out_start[tiles] = p


def _views(view: np.ndarray) -> np.ndarray:
    """A view as ``(V, 4, 4)``: one shared row (grid), or one per tile (screens)."""
    return view[None] if view.ndim == 2 else view


class _FitArrays:
    """A frame's :class:`~wallcull.fit.Fits` as the kernels' tuples of arrays, built once per
    frame (kept on its record) for its packets and node messages alike."""

    def __init__(self, fits: Fits):
        tiles = len(fits)
        shared = fits.view.ndim == 2
        if fits.shadows or fits.mirrors or fits.eyes:
            self.S, self.M, self.E = self._parts(fits, tiles, shared)
        else:  # the common case: nothing but each tile's view and projection
            self.S, self.M, self.E = _no_parts(tiles, shared)
        L, Q, E = self.S[0].shape[0], self.M[0].shape[0], self.E[0].shape[0]
        views = _views(fits.view)
        self.F = (views, np.frombuffer(msgpack.packb(fits.view.tolist()) if shared else b"",
                                       np.uint8), fits.projection, fits.near, fits.far)
        self.C = tuple(fits.compact)  # node messages: rigid views, extents
        self.tiles = tiles
        entries = 1 + L + Q * (1 + E) + E
        names = len(self.S[8]) + len(self.M[7]) * (1 + E)
        #: an upper bound on a frame's fits in bytes: every matrix, number, key and name
        self.bound = tiles * (entries * (2 * MAT4 + 4 * NUMBER + 256) + names
                              + len(self.S[10])) + NUMBER * (len(self.S[7]) + len(self.M[6]))

    @staticmethod
    def _parts(fits: Fits, tiles: int, shared: bool) -> tuple[tuple, tuple, tuple]:
        """The shadows (S), mirrors (M) and eyes (E) of a frame, as the kernels take them."""
        shadows, mirrors, eyes = fits.shadows, fits.mirrors, fits.eyes
        vshape = (1 if shared else tiles, 4, 4)
        L, Q = len(shadows), len(mirrors)
        offsets = np.cumsum([0] + [len(s.casters) for s in shadows])
        S = (
            np.array([s.kind for s in shadows], np.int64).reshape(L, tiles),
            _stacked([s.view for s in shadows], (L, tiles, 4, 4)),
            _stacked([s.projection for s in shadows], (L, tiles, 4, 4)),
            *(np.array([getattr(s, k) for s in shadows]).reshape(L, tiles)
              for k in ("near", "far", "coverage")),
            np.array([s.casters_start + o for s, o in zip(shadows, offsets)],
                     np.int64).reshape(L, tiles + 1),
            _joined([s.casters for s in shadows]),
            *_pack_each([s.light.name for s in shadows]),
            *_pack_each([s.cube_views.tolist() if s.cube_views is not None else []
                         for s in shadows]))
        offsets = np.cumsum([0] + [len(m.visible) for m in mirrors])
        M = (
            np.array([m.shown for m in mirrors], np.bool_).reshape(Q, tiles),
            _stacked([_views(m.view) for m in mirrors], (Q, *vshape)),
            *_pack_each([m.view.tolist() if shared else [] for m in mirrors]),
            _stacked([m.projection for m in mirrors], (Q, tiles, 4, 4)),
            np.array([m.visible_start + o for m, o in zip(mirrors, offsets)],
                     np.int64).reshape(Q, tiles + 1),
            _joined([m.visible for m in mirrors]),
            *_pack_each([m.mirror.name for m in mirrors]))
        E = len(eyes)
        e_views = np.array([_views(e.view) for e in eyes]).reshape(E, *vshape)
        e_projection = np.array([e.projection for e in eyes]).reshape(E, tiles, 4, 4)
        e_near = np.array([e.near for e in eyes]).reshape(E, tiles)
        e_far = np.array([e.far for e in eyes]).reshape(E, tiles)
        E = (
            e_views, *_pack_each([e.view.tolist() if shared else [] for e in eyes]),
            e_projection, e_near, e_far,
            np.array([[_views(v) for v, _, _ in e.mirrors] for e in eyes]).reshape(E, Q, *vshape),
            np.array([[pr for _, pr, _ in e.mirrors] for e in eyes]).reshape(E, Q, tiles, 4, 4),
            np.array([[ok for _, _, ok in e.mirrors] for e in eyes], np.bool_).reshape(E, Q, tiles))
        return S, M, E


@lru_cache(maxsize=16)
def _no_parts(tiles: int, shared: bool) -> tuple[tuple, tuple, tuple]:
    """The empty shadows, mirrors and eyes of a wall's frames (built once: 40 us a frame)."""
    class Nothing:
        shadows, mirrors, eyes = [], [], []

    parts = _FitArrays._parts(Nothing, tiles, shared)
    for part in parts:
        for a in part:
            a.flags.writeable = False
    return parts


def _stacked(arrays: list, shape: tuple) -> np.ndarray:
    """``arrays`` (float64, of one shape) as one array of ``shape``; with one, that array
    itself, not a copy (a 256 x 256 wall's per-tile matrices are 8 MB an array, a frame)."""
    if len(arrays) == 1 and arrays[0].flags.c_contiguous and arrays[0].dtype == np.float64:
        return arrays[0].reshape(shape)
    return np.array(arrays, np.float64).reshape(shape)


def _joined(lists: list) -> np.ndarray:
    """Id lists (int64) end to end; one list itself, not a copy."""
    if len(lists) == 1 and lists[0].dtype == np.int64:
        return lists[0]
    return np.concatenate(lists or [np.zeros(0, np.int64)])


def fit_arrays(record) -> _FitArrays:
    """The record's fits as the kernels take them (built once, kept on the record)."""
    found = record.__dict__.get("_fit_arrays")
    if found is None:
        found = record.__dict__["_fit_arrays"] = _FitArrays(record.fits)
    return found


# --------------------------------------------------------------------------- packets


@njit(cache=True, nogil=True)
def _packets(tiles, frame, time, base, leaves, leaf_start, added, added_start, removed,
             removed_start, parts, segments, segment_start, segment_pairs, extra, extra_start,
             extra_pairs, out, out_start):
    """The packets of ``tiles`` into ``out`` (see :func:`packets`); ``parts``: the draw ranges
    to send (:func:`_part_changes`)."""
    which, which_start, whole, whole_start, part_leaf, range_start, ranges = parts
    bits = np.empty(1)
    p = 0
    for k in range(tiles.shape[0]):
        t = tiles[k]
        out_start[k] = p
        delta = base >= 0
        n_parts = which_start[t + 1] - which_start[t]
        n_whole = whole_start[t + 1] - whole_start[t]
        pairs = 4 + (2 if delta else 1) + 1 + (n_parts > 0) + (n_whole > 0) + segment_pairs[t] \
            + extra_pairs[k]
        p = _map(out, p, pairs)
        p = _key(out, p, K_FRAME)
        p = _int(out, p, frame)
        p = _key(out, p, K_TILE)
        p = _int(out, p, t)
        p = _key(out, p, K_TIME)
        p = _float(out, p, time, bits)
        p = _key(out, p, K_BASE)
        if delta:
            p = _int(out, p, base)
            p = _key(out, p, K_ADDED)
            p = _ints(out, p, added, added_start[t], added_start[t + 1])
            p = _key(out, p, K_REMOVED)
            p = _ints(out, p, removed, removed_start[t], removed_start[t + 1])
        else:
            out[p] = 0xC0  # nil
            p += 1
            p = _key(out, p, K_VISIBLE)
            p = _ints(out, p, leaves, leaf_start[t], leaf_start[t + 1])
        p = _key(out, p, K_COUNT)
        p = _int(out, p, leaf_start[t + 1] - leaf_start[t])
        if n_parts:
            p = _parts(out, p, which, which_start[t], which_start[t + 1], part_leaf,
                       range_start, ranges)
        if n_whole:
            p = _key(out, p, K_WHOLE)
            p = _ints(out, p, whole, whole_start[t], whole_start[t + 1])
        p = _copy(out, p, extra, extra_start[k], extra_start[k + 1])
        p = _copy(out, p, segments, segment_start[t], segment_start[t + 1])
    out_start[tiles.shape[0]] = p


class Encoded(Sequence):
    """Packets encoded into one buffer: ``packets[k]`` is packet ``k``'s bytes, a zero-copy
    ``memoryview`` (bytes-like: sockets, ``msgpack.unpackb`` and ``bytes()`` take it)."""

    def __init__(self, data: bytes, offsets: np.ndarray):
        self.data = data
        self.offsets = offsets.tolist()
        self._view = memoryview(data)

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, k: int) -> memoryview:
        if not 0 <= k < len(self):
            raise IndexError(k)
        return self._view[self.offsets[k]:self.offsets[k + 1]]

    @property
    def nbytes(self) -> int:
        return len(self.data)


def _part_changes(record, prior=None) -> tuple:
    """The draw ranges a frame sends against ``prior`` (None: all of them), for the compiled
    writers: ``(which, which_start, whole, whole_start, part_leaf, range_start, ranges)``,
    ``which`` indexing the record's parts (:func:`wallcull.protocol.part_deltas`)."""
    part_start, part_leaf, range_start, ranges = record.parts
    if prior is None:
        none = np.zeros(len(part_start), np.int64)
        return (np.arange(len(part_leaf)), part_start, none[:0], none, part_leaf, range_start,
                ranges)
    return (*protocol.part_deltas(record, prior), part_leaf, range_start, ranges)


def _parts_bound(parts: tuple) -> int:
    """Bytes the draw ranges of ``parts`` take at most (per tile, its keys included)."""
    which, _, whole, _, _, range_start, _ = parts
    ranges = int((range_start[which + 1] - range_start[which]).sum()) if len(which) else 0
    tiles = len(parts[1])
    return NUMBER * (2 * ranges + 2 * len(which) + len(whole)) + 16 * tiles


def packets(record, tiles: np.ndarray, base: int | None = None,
            delta: tuple | None = None, extras: dict | None = None,
            prior=None) -> Encoded:
    """The msgpack packets of ``tiles`` for one frame: full lists when ``base`` is None, else
    deltas against frame ``base`` (``delta``: :func:`wallcull.protocol.tile_deltas` of the
    two; ``prior``: its record, whose draw ranges the delta's are against). ``extras`` maps a
    tile to pre-encoded key/value pairs ``(bytes, count)`` it carries besides (moved
    transforms). ``record`` is a :class:`wallcull.protocol.FrameRecord`; its fits' segments
    are encoded once and kept on it."""
    segments = record.__dict__.get("_segments")
    if segments is None:
        arrays = fit_arrays(record)
        data = np.empty(arrays.bound, np.uint8)
        seg_start = np.empty(arrays.tiles + 1, np.int64)
        seg_pairs = np.empty(arrays.tiles, np.int64)
        _fit_segments(arrays.F, arrays.S, arrays.M, arrays.E, data, seg_start, seg_pairs)
        segments = record.__dict__["_segments"] = (data[:seg_start[-1]], seg_start, seg_pairs)
    data, seg_start, seg_pairs = segments
    tiles = np.asarray(tiles, np.int64)
    zero = np.zeros(1, np.int64)
    added, added_start, removed, removed_start = delta if delta is not None else \
        (zero, zero, zero, zero)
    if extras:
        parts = [extras.get(int(t), (b"", 0)) for t in tiles]
        extra = np.frombuffer(b"".join(b for b, _ in parts), np.uint8)
        extra_start = np.zeros(len(tiles) + 1, np.int64)
        np.cumsum([len(b) for b, _ in parts], out=extra_start[1:])
        extra_pairs = np.array([n for _, n in parts], np.int64)
    else:
        extra = np.zeros(0, np.uint8)
        extra_start = np.zeros(len(tiles) + 1, np.int64)
        extra_pairs = np.zeros(len(tiles), np.int64)
    lists = np.diff(record.start)[tiles].sum() if base is None else \
        (np.diff(added_start)[tiles].sum() + np.diff(removed_start)[tiles].sum())
    parts = _part_changes(record, None if base is None else prior)
    size = int(NUMBER * (lists + 8 * len(tiles)) + 96 * len(tiles) + len(extra)
               + np.diff(seg_start)[tiles].sum() + _parts_bound(parts))
    out = np.empty(size, np.uint8)
    out_start = np.empty(len(tiles) + 1, np.int64)
    _packets(tiles, record.number, float(record.time), -1 if base is None else int(base),
             record.leaves, record.start, added, added_start, removed, removed_start, parts,
             data, seg_start, seg_pairs, extra, extra_start, extra_pairs, out, out_start)
    return Encoded(out[:out_start[-1]].tobytes(), out_start)


def frame_packets(history, number: int, tiles, base: int | None = None) -> Encoded:
    """Frame ``number``'s msgpack packets for ``tiles``, as :func:`wallcull.protocol.packet`
    would build and pack them: deltas against frame ``base`` when it is given and still held,
    else full lists."""
    record = history.frames[number]
    tiles = np.asarray(tiles, np.int64)
    prior = history.get(base) if base is not None and base < number else None
    delta = protocol.tile_deltas(record, prior) if prior is not None else None
    extras = None
    if history.dynamic(record):  # a dynamic scene: the moved leaves' transforms, tile by tile
        extras = {}
        for t in tiles.tolist():
            added = delta[0][delta[1][t]:delta[1][t + 1]] if delta is not None else None
            moved = protocol.transforms(history, record, t, None if prior is None else base,
                                        added)
            if moved is not None:
                extras[t] = (msgpack.packb("transforms") + msgpack.packb(moved), 1)
    return packets(record, tiles, None if prior is None else base, delta, extras, prior)


# --------------------------------------------------------------------------- node messages


@njit(cache=True)
def _compact_eye(out, p, t, e, own_view, sends, C, E, M, bits, bits32):
    """Eye ``e``'s record of tile ``t`` in a node message (``sends``: its extent, its depth)."""
    e_q, e_t, e_tangents, e_depth = C[4], C[5], C[6], C[7]
    p = _key(out, p, K_LEFT + e)
    p = _map(out, p, own_view + sends[0] + sends[1] + (_eye_sees(M, E, e, t) > 0))
    if own_view:
        p = _key(out, p, K_VIEW)
        p = _rigid(out, p, e_q[e, t], e_t[e, t], bits)
    p = _extent_depth(out, p, sends[0], sends[1], e_tangents[e], e_depth[e], t, bits, bits32)
    return _eye_mirrors(out, p, e, t, M, E, bits)


@njit(cache=True, inline="always")
def _extent_depth(out, p, extent, depth_range, tangents, depth, t, bits, bits32):
    """Tile ``t``'s extent (``tangents[t]``) and depth range (``depth[t]``) where asked. (Rows
    are read by index, never as views: each view's reference count is an atomic operation,
    and the calls for every tile of a 64 x 64 wall took half of its entries' time.)"""
    if extent:
        p = _key(out, p, K_EXTENT)
        p = _array(out, p, 4)
        for k in range(4):
            p = _float(out, p, tangents[t, k], bits)
    if depth_range:
        p = _key(out, p, K_DEPTH)
        out[p] = 0x92
        p = _short_float(out, p + 1, depth[t, 0], bits, bits32)
        p = _short_float(out, p, depth[t, 1], bits, bits32)
    return p


@njit(cache=True, nogil=True)
def _entries(delta, leaves, leaf_start, added, added_start, removed, removed_start, parts,
             sends, C, S, M, E, out, out_start):
    """Every tile's node-message entry into ``out``: its id, its list (full, or the delta's
    non-empty parts when they are shorter than the list), its count, its view where it has
    its own, its extent and depth range where ``sends`` (T, 2) says, its shadows, mirrors and
    eyes. In a delta, a tile with nothing new (the same list, extent and depth, nothing of its
    own) has no entry: ``out_start[t] == out_start[t + 1]``."""
    q, tr, tangents, depth = C[0], C[1], C[2], C[3]
    which, which_start, back, back_start, part_leaf, range_start, ranges = parts
    tiles = leaf_start.shape[0] - 1
    own_view = q.shape[0] > 1
    eyes = E[0].shape[0]
    bits = np.empty(1)
    bits32 = np.empty(1, np.float32)
    p = 0
    for t in range(tiles):
        out_start[t] = p
        n_added = added_start[t + 1] - added_start[t] if delta else 0
        n_removed = removed_start[t + 1] - removed_start[t] if delta else 0
        changes = n_added + n_removed
        whole = not delta or (changes > 0 and changes >= leaf_start[t + 1] - leaf_start[t])
        if whole:  # a delta no shorter than the list: the list
            n_added = n_removed = 0
        shadows = 0
        for k in range(S[0].shape[0]):
            shadows += S[0][k, t] != 0
        mirrors = 0
        for k in range(M[0].shape[0]):
            mirrors += M[0][k, t]
        n_parts = which_start[t + 1] - which_start[t]
        n_back = back_start[t + 1] - back_start[t]
        if delta and changes == 0 and not (own_view or sends[t, 0] or sends[t, 1] or shadows
                                           or mirrors or eyes or n_parts or n_back):
            continue  # nothing new: the node keeps the base's
        p = _map(out, p, 2 + whole + (n_added > 0) + (n_removed > 0) + (n_parts > 0)
                 + (n_back > 0) + own_view + sends[t, 0] + sends[t, 1] + (shadows > 0)
                 + (mirrors > 0) + eyes)
        p = _key(out, p, K_TILE)
        p = _int(out, p, t)
        if whole:
            p = _key(out, p, K_VISIBLE)
            p = _ints(out, p, leaves, leaf_start[t], leaf_start[t + 1])
        if n_added:
            p = _key(out, p, K_ADDED)
            p = _ints(out, p, added, added_start[t], added_start[t + 1])
        if n_removed:
            p = _key(out, p, K_REMOVED)
            p = _ints(out, p, removed, removed_start[t], removed_start[t + 1])
        p = _key(out, p, K_COUNT)
        p = _int(out, p, leaf_start[t + 1] - leaf_start[t])
        if n_parts:
            p = _parts(out, p, which, which_start[t], which_start[t + 1], part_leaf,
                       range_start, ranges)
        if n_back:  # leaves drawn in part in the base, whole now
            p = _key(out, p, K_WHOLE)
            p = _ints(out, p, back, back_start[t], back_start[t + 1])
        if own_view:
            p = _key(out, p, K_VIEW)
            p = _rigid(out, p, q[t], tr[t], bits)
        p = _extent_depth(out, p, sends[t, 0], sends[t, 1], tangents, depth, t, bits, bits32)
        if shadows:  # (a call passes its arrays' references: not for every tile)
            p, _ = _shadows(out, p, t, S, bits)
        if mirrors:
            p, _ = _mirrors(out, p, t, M, bits)
        for e in range(eyes):
            p = _compact_eye(out, p, t, e, own_view, sends[t], C, E, M, bits, bits32)
    out_start[tiles] = p


class NodeEntries:
    """One frame's node-message parts against one base: every tile's entry (``data``,
    ``start``; none for a tile a delta leaves out), how many entries tiles ``[0, t)`` have
    (``counted``), and what every message of the frame shares (``head``: its key/value pairs,
    ``head_pairs`` of them)."""

    def __init__(self, data: bytes, start: np.ndarray, head: bytes, head_pairs: int):
        # offsets read one by one as Python ints, as fast as from lists, at 8 bytes each
        # rather than 36 (a 256 x 256 wall's as lists took 5 MB a frame)
        self.data, self.start, self.head, self.head_pairs = data, _offsets(start), head, head_pairs
        self.counted = _offsets(np.concatenate([[0], np.cumsum(np.diff(start) > 0)]))
        self._view = memoryview(data)

    def body(self, tiles: np.ndarray) -> tuple[int, bytes | memoryview]:
        """How many entries ``tiles`` (sorted) have, and those entries concatenated: one slice
        when the tiles are consecutive."""
        first, last = int(tiles[0]), int(tiles[-1])
        if last - first + 1 == len(tiles):
            return (self.counted[last + 1] - self.counted[first],
                    self._view[self.start[first]:self.start[last + 1]])
        parts = [self._view[self.start[t]:self.start[t + 1]] for t in tiles.tolist()]
        return sum(len(part) > 0 for part in parts), b"".join(parts)


def _offsets(values: np.ndarray) -> memoryview:
    return memoryview(np.ascontiguousarray(values, np.int64))


def node_entries(history, number: int, base: int | None) -> NodeEntries:
    """Frame ``number``'s :class:`NodeEntries` against ``base`` (held, and older; None: full
    lists), kept on its record: every node of the wall takes its message from these."""
    return entries(history.frames[number], None if base is None else history.frames[base])


def entries(record, prior=None) -> NodeEntries:
    """:func:`node_entries` of a frame record against the record ``prior`` (None: full
    lists). The server calls it in the thread that computed the frame, against the frame
    before it (what most nodes have acknowledged by the time it is sent), so that its event
    loop only slices; the kernels run without the GIL."""
    base = None if prior is None else prior.number
    cache = record.__dict__.setdefault("_entries", {})
    found = cache.get(base)
    if found is not None:
        return found
    arrays = fit_arrays(record)
    tiles = arrays.tiles
    zero = np.zeros(1, np.int64)
    if base is None:
        delta, lists = (zero, zero, zero, zero), len(record.leaves)
        sends = np.ones((tiles, 2), np.bool_)
    else:
        delta = protocol.tile_deltas(record, prior)
        lists = len(delta[0]) + len(delta[2])
        sends = record.fits.compact.changed(prior.fits.compact)
    parts = _part_changes(record, prior)
    out = np.empty(NUMBER * (lists + 2 * tiles) + 64 * tiles + arrays.bound + _parts_bound(parts),
                   np.uint8)
    out_start = np.empty(tiles + 1, np.int64)
    _entries(base is not None, record.leaves, record.start, *delta, parts, sends, arrays.C,
             arrays.S, arrays.M, arrays.E, out, out_start)
    head = protocol.node_head(record.number, record.time, record.fits, base)
    packed = b"".join(msgpack.packb(k) + msgpack.packb(v) for k, v in head.items())
    found = cache[base] = NodeEntries(out[:out_start[-1]].tobytes(), out_start, packed,
                                      len(head))
    while len(cache) > 4:
        cache.pop(next(iter(cache)))
    return found


def node_message(history, number: int, tiles, base: int | None = None) -> bytes:
    """Frame ``number``'s node message for ``tiles`` (sorted) as msgpack, equal to
    :func:`wallcull.protocol.node_message` packed: deltas against frame ``base`` when it is
    given and still held, else full lists. Kept on the frame's record: every stream of the
    same tiles against the same base sends the same bytes."""
    record = history.frames[number]
    prior = history.get(base) if base is not None and base < number else None
    base = None if prior is None else base
    tiles = np.asarray(tiles, np.int64)
    made = record.__dict__.setdefault("_messages", {})
    key = (tiles.tobytes(), base)
    found = made.get(key)
    if found is None:
        if len(made) >= MESSAGES_KEPT:  # streams on many bases: start over
            made.clear()
        found = made[key] = _node_message(history, record, prior, tiles)
    return found


#: Node messages a frame's record keeps (by tiles and base) for the streams still to send it.
MESSAGES_KEPT = 4096


def _node_message(history, record, prior, tiles: np.ndarray) -> bytes:
    base = None if prior is None else prior.number
    parts = entries(record, prior)
    pairs, moved = parts.head_pairs + 1, b""
    if history.dynamic(record):  # a dynamic scene: the moved leaves any of the tiles may lack
        added = None
        if base is not None:
            d = protocol.tile_deltas(record, prior)
            added = np.unique(np.concatenate([d[0][d[1][t]:d[1][t + 1]] for t in tiles]))
        found = protocol.transforms(history, record, tiles, base, added)
        if found is not None:
            moved, pairs = _TRANSFORMS_KEY + msgpack.packb(found), pairs + 1
    count, body = parts.body(tiles)
    return b"".join((_map_header(pairs), parts.head, moved, _TILES_KEY, _array_header(count),
                     body))


_TRANSFORMS_KEY, _TILES_KEY = msgpack.packb("transforms"), msgpack.packb("tiles")


def _map_header(n: int) -> bytes:
    return bytes([0x80 | n]) if n < 16 else b"\xde" + n.to_bytes(2, "big")


def _array_header(n: int) -> bytes:
    return bytes([0x90 | n]) if n < 16 else b"\xdc" + n.to_bytes(2, "big") if n < 65536 \
        else b"\xdd" + n.to_bytes(4, "big")
