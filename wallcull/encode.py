"""Packets as bytes: the ``encode`` arrow of DESIGN.md, compiled.

A tile's packet (:mod:`wallcull.protocol`) is a msgpack map; building it as a Python dict and
packing it costs about 10 us a tile, 40 ms for a 64 x 64 wall. Here a frame is encoded in two
compiled passes over its arrays, with no Python object per tile:

* :func:`fit_segments`, once per frame: every tile's fitted frusta (``view``, ``projection``,
  ``near``, ``far``, any ``shadows`` and ``mirrors``) as msgpack key/value pairs. They do not
  depend on what a packet's delta is against, so every packet of the frame copies them.
* :func:`packets`: the packets of any tiles, each its header (frame, tile, time, base), its
  list (full, or a delta against the base) and its tile's segment.

The bytes decode to exactly the dict :func:`wallcull.protocol.packet` builds (a test holds
this); floats are float64, integers the shortest msgpack form, as ``msgpack.packb`` writes
them. JSON, and the rare packet that carries moved transforms, still go through the dict.
"""

from __future__ import annotations

from collections.abc import Sequence

import msgpack
import numpy as np
from numba import njit

from .fit import CUBE, FRUSTUM, Fits

_KEYS = ("frame", "tile", "time", "base", "visible", "added", "removed", "count", "view",
         "projection", "near", "far", "shadows", "mirrors", "light", "cube", "views", "coverage",
         "casters", "mirror", "front_face", "cw", "left", "right")
(K_FRAME, K_TILE, K_TIME, K_BASE, K_VISIBLE, K_ADDED, K_REMOVED, K_COUNT, K_VIEW,
 K_PROJECTION, K_NEAR, K_FAR, K_SHADOWS, K_MIRRORS, K_LIGHT, K_CUBE, K_VIEWS, K_COVERAGE,
 K_CASTERS, K_MIRROR, K_FRONT_FACE, V_CW, K_LEFT, K_RIGHT) = range(len(_KEYS))


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


@njit(cache=True)
def _int(buf, p, v):
    """A msgpack integer, in the shortest form (as msgpack.packb writes it)."""
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


@njit(cache=True)
def _ints(buf, p, values, a, b):
    p = _array(buf, p, b - a)
    for i in range(a, b):
        p = _int(buf, p, values[i])
    return p


@njit(cache=True)
def _mat4(buf, p, m, bits):
    buf[p] = 0x94
    p += 1
    for i in range(4):
        buf[p] = 0x94
        p += 1
        for j in range(4):
            p = _float(buf, p, m[i, j], bits)
    return p


# --------------------------------------------------------------------------- fits


@njit(cache=True, inline="always")
def _view(out, p, views, shared, t, bits):
    """A tile's view: the frame's shared one, pre-encoded (``views`` has one row), or its own."""
    if views.shape[0] == 1:
        return _copy(out, p, shared, 0, shared.shape[0])
    return _mat4(out, p, views[t], bits)


@njit(cache=True)
def _fit_segments(views, view_bytes, projection, near, far, s_kind, s_view, s_projection,
                  s_near, s_far, s_coverage, s_start, s_casters, s_names, s_name_off, s_cube,
                  s_cube_off, m_shown, m_views, m_view_bytes, m_view_off, m_projection,
                  m_start, m_visible, m_names, m_name_off, e_views, e_view_bytes, e_view_off,
                  e_projection, e_near, e_far, e_m_views, e_m_projection, e_m_shown, out,
                  out_start, out_pairs):
    """Every tile's fitted frusta as msgpack key/value pairs into ``out`` (see
    :func:`fit_segments` for the arguments)."""
    bits = np.empty(1)
    tiles = projection.shape[0]
    p = 0
    for t in range(tiles):
        out_start[t] = p
        pairs = 4
        p = _key(out, p, K_VIEW)
        p = _view(out, p, views, view_bytes, t, bits)
        p = _key(out, p, K_PROJECTION)
        p = _mat4(out, p, projection[t], bits)
        p = _key(out, p, K_NEAR)
        p = _float(out, p, near[t], bits)
        p = _key(out, p, K_FAR)
        p = _float(out, p, far[t], bits)
        shadows = 0
        for q in range(s_kind.shape[0]):
            shadows += s_kind[q, t] != 0
        if shadows:
            pairs += 1
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
        mirrors = 0
        for q in range(m_shown.shape[0]):
            mirrors += m_shown[q, t]
        if mirrors:
            pairs += 1
            p = _key(out, p, K_MIRRORS)
            p = _array(out, p, mirrors)
            for q in range(m_shown.shape[0]):
                if not m_shown[q, t]:
                    continue
                p = _map(out, p, 5)
                p = _key(out, p, K_MIRROR)
                p = _copy(out, p, m_names, m_name_off[q], m_name_off[q + 1])
                p = _key(out, p, K_VIEW)
                p = _view(out, p, m_views[q], m_view_bytes[m_view_off[q]:m_view_off[q + 1]], t,
                          bits)
                p = _key(out, p, K_PROJECTION)
                p = _mat4(out, p, m_projection[q, t], bits)
                p = _key(out, p, K_FRONT_FACE)
                p = _key(out, p, V_CW)
                p = _key(out, p, K_VISIBLE)
                p = _ints(out, p, m_visible, m_start[q, t], m_start[q, t + 1])
        for e in range(e_views.shape[0]):  # a stereo frame: "left", "right"
            pairs += 1
            p = _key(out, p, K_LEFT + e)
            seen = 0
            for q in range(m_shown.shape[0]):
                seen += m_shown[q, t] and e_m_shown[e, q, t]
            p = _map(out, p, 4 + (seen > 0))
            p = _key(out, p, K_VIEW)
            p = _view(out, p, e_views[e], e_view_bytes[e_view_off[e]:e_view_off[e + 1]], t,
                      bits)
            p = _key(out, p, K_PROJECTION)
            p = _mat4(out, p, e_projection[e, t], bits)
            p = _key(out, p, K_NEAR)
            p = _float(out, p, e_near[e, t], bits)
            p = _key(out, p, K_FAR)
            p = _float(out, p, e_far[e, t], bits)
            if seen:
                p = _key(out, p, K_MIRRORS)
                p = _array(out, p, seen)
                for q in range(m_shown.shape[0]):
                    if not (m_shown[q, t] and e_m_shown[e, q, t]):
                        continue
                    p = _map(out, p, 3)
                    p = _key(out, p, K_MIRROR)
                    p = _copy(out, p, m_names, m_name_off[q], m_name_off[q + 1])
                    p = _key(out, p, K_VIEW)
                    p = _mat4(out, p, e_m_views[e, q, 0 if e_m_views.shape[2] == 1 else t],
                              bits)
                    p = _key(out, p, K_PROJECTION)
                    p = _mat4(out, p, e_m_projection[e, q, t], bits)
        out_pairs[t] = pairs
    out_start[tiles] = p


def _views(view: np.ndarray) -> np.ndarray:
    """A view as ``(V, 4, 4)``: one shared row (grid), or one per tile (screens)."""
    return view[None] if view.ndim == 2 else view


def fit_segments(fits: Fits) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every tile's fitted frusta as msgpack key/value pairs: ``(data (uint8), start (T + 1,),
    pairs (T,))``; tile ``t``'s ``pairs[t]`` pairs are ``data[start[t]:start[t + 1]]``."""
    tiles = len(fits)
    shadows, mirrors, eyes = fits.shadows, fits.mirrors, fits.eyes
    shared = fits.view.ndim == 2
    vshape = (1 if shared else tiles, 4, 4)
    # one light's arrays per row; casters offset into one concatenated array
    s_kind = np.array([s.kind for s in shadows], np.int64).reshape(len(shadows), tiles)
    s_view = np.array([s.view for s in shadows]).reshape(len(shadows), tiles, 4, 4)
    s_projection = np.array([s.projection for s in shadows]).reshape(len(shadows), tiles, 4, 4)
    s_near, s_far, s_coverage = (np.array([getattr(s, k) for s in shadows]).reshape(
        len(shadows), tiles) for k in ("near", "far", "coverage"))
    offsets = np.cumsum([0] + [len(s.casters) for s in shadows])
    s_start = np.array([s.casters_start + o for s, o in zip(shadows, offsets)],
                       np.int64).reshape(len(shadows), tiles + 1)
    s_casters = np.concatenate([s.casters for s in shadows] or [np.zeros(0, np.int64)])
    s_names, s_name_off = _pack_each([s.light.name for s in shadows])
    s_cube, s_cube_off = _pack_each([s.cube_views.tolist() if s.cube_views is not None else []
                                     for s in shadows])
    m_shown = np.array([m.shown for m in mirrors], np.bool_).reshape(len(mirrors), tiles)
    m_views = np.array([_views(m.view) for m in mirrors]).reshape(len(mirrors), *vshape)
    m_view_bytes, m_view_off = _pack_each([m.view.tolist() if shared else [] for m in mirrors])
    m_projection = np.array([m.projection for m in mirrors]).reshape(len(mirrors), tiles, 4, 4)
    offsets = np.cumsum([0] + [len(m.visible) for m in mirrors])
    m_start = np.array([m.visible_start + o for m, o in zip(mirrors, offsets)],
                       np.int64).reshape(len(mirrors), tiles + 1)
    m_visible = np.concatenate([m.visible for m in mirrors] or [np.zeros(0, np.int64)])
    m_names, m_name_off = _pack_each([m.mirror.name for m in mirrors])
    e_views = np.array([_views(e.view) for e in eyes]).reshape(len(eyes), *vshape)
    e_view_bytes, e_view_off = _pack_each([e.view.tolist() if shared else [] for e in eyes])
    e_projection = np.array([e.projection for e in eyes]).reshape(len(eyes), tiles, 4, 4)
    e_near = np.array([e.near for e in eyes]).reshape(len(eyes), tiles)
    e_far = np.array([e.far for e in eyes]).reshape(len(eyes), tiles)
    e_m_views = np.array([[_views(v) for v, _, _ in e.mirrors] for e in eyes]).reshape(
        len(eyes), len(mirrors), *vshape)
    e_m_projection = np.array([[pr for _, pr, _ in e.mirrors] for e in eyes]).reshape(
        len(eyes), len(mirrors), tiles, 4, 4)
    e_m_shown = np.array([[ok for _, _, ok in e.mirrors] for e in eyes], np.bool_).reshape(
        len(eyes), len(mirrors), tiles)
    view_bytes = np.frombuffer(msgpack.packb(fits.view.tolist()) if shared else b"", np.uint8)
    # an upper bound: every matrix, number, key and name a tile may carry
    entries = 1 + len(shadows) + len(mirrors) * (1 + len(eyes)) + len(eyes)
    size = tiles * (entries * (2 * MAT4 + 4 * NUMBER + 256)) + int(s_cube_off[-1]) * tiles \
        + NUMBER * (len(s_casters) + len(m_visible)) \
        + (int(s_name_off[-1]) + int(m_name_off[-1]) * (1 + len(eyes))) * tiles
    out = np.empty(size, np.uint8)
    start = np.empty(tiles + 1, np.int64)
    pairs = np.empty(tiles, np.int64)
    _fit_segments(_views(fits.view), view_bytes, fits.projection, fits.near, fits.far, s_kind,
                  s_view, s_projection, s_near, s_far, s_coverage, s_start, s_casters, s_names,
                  s_name_off, s_cube, s_cube_off, m_shown, m_views, m_view_bytes, m_view_off,
                  m_projection, m_start, m_visible, m_names, m_name_off, e_views, e_view_bytes,
                  e_view_off, e_projection, e_near, e_far, e_m_views, e_m_projection, e_m_shown,
                  out, start, pairs)
    return out[:start[-1]], start, pairs


# --------------------------------------------------------------------------- packets


@njit(cache=True)
def _packets(tiles, frame, time, base, leaves, leaf_start, added, added_start, removed,
             removed_start, segments, segment_start, segment_pairs, extra, extra_start,
             extra_pairs, out, out_start):
    """The packets of ``tiles`` into ``out`` (see :func:`packets`)."""
    bits = np.empty(1)
    p = 0
    for k in range(tiles.shape[0]):
        t = tiles[k]
        out_start[k] = p
        delta = base >= 0
        pairs = 4 + (2 if delta else 1) + 1 + segment_pairs[t] + extra_pairs[k]
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


def packets(record, tiles: np.ndarray, base: int | None = None,
            delta: tuple | None = None, extras: dict | None = None) -> Encoded:
    """The msgpack packets of ``tiles`` for one frame: full lists when ``base`` is None, else
    deltas against frame ``base`` (``delta``: :func:`wallcull.protocol.tile_deltas` of the
    two). ``extras`` maps a tile to pre-encoded key/value pairs ``(bytes, count)`` it carries
    besides (moved transforms). ``record`` is a :class:`wallcull.protocol.FrameRecord`; its
    fits' segments are encoded once and kept on it."""
    segments = record.__dict__.get("_segments")
    if segments is None:
        segments = record.__dict__["_segments"] = fit_segments(record.fits)
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
    size = int(NUMBER * (lists + 8 * len(tiles)) + 96 * len(tiles) + len(extra)
               + np.diff(seg_start)[tiles].sum())
    out = np.empty(size, np.uint8)
    out_start = np.empty(len(tiles) + 1, np.int64)
    _packets(tiles, record.number, float(record.time), -1 if base is None else int(base),
             record.leaves, record.start, added, added_start, removed, removed_start, data,
             seg_start, seg_pairs, extra, extra_start, extra_pairs, out, out_start)
    return Encoded(out[:out_start[-1]].tobytes(), out_start)


def frame_packets(history, number: int, tiles, base: int | None = None) -> Encoded:
    """Frame ``number``'s msgpack packets for ``tiles``, as :func:`wallcull.protocol.packet`
    would build and pack them: deltas against frame ``base`` when it is given and still held,
    else full lists."""
    from . import protocol

    record = history.frames[number]
    tiles = np.asarray(tiles, np.int64)
    prior = history.get(base) if base is not None and base < number else None
    delta = protocol.tile_deltas(record, prior) if prior is not None else None
    extras = None
    if len(record.posed):  # a dynamic scene: the moved leaves' transforms, tile by tile
        extras = {}
        for t in tiles.tolist():
            added = delta[0][delta[1][t]:delta[1][t + 1]] if delta is not None else None
            moved = protocol.transforms(history, record, t, None if prior is None else base,
                                        added)
            if moved is not None:
                extras[t] = (msgpack.packb("transforms") + msgpack.packb(moved), 1)
    return packets(record, tiles, None if prior is None else base, delta, extras)
