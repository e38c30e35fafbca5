"""Prepared files: named arrays in one file that loads by memory-mapping, checked before use.

A scene's hierarchy, names, bounds and meshes take seconds to build from its source and under
a second to map from here (:mod:`wallcull.scene` decides what goes in; this module only stores
it). The layout, little-endian::

    magic   8 bytes   b"WCPREP02"
    length  8 bytes   uint64, bytes of the header
    crc     8 bytes   uint64, the CRC-32 of the header's bytes
    header  JSON      {"meta": {...}, "arrays": {name: [dtype, shape, offset, bytes]},
                       "data_bytes": D, "data_crc32": C}
    data    D bytes   from the first multiple of 64 after the header; each array starts on a
                      multiple of 64 (offsets relative to the data), after the one before

:func:`read` refuses (:class:`Corrupt`) a file whose magic, header (its CRC-32), length, array
table or CRC-32 of the data does not hold, so a truncated or damaged file is never used (a
header checked by its shape alone took an offset changed by 64 for a good one, and the scene
culled with bounds read from the wrong bytes). The data are checked by
reading them through once (about 0.1 s per 500 MB from the page cache) before they are mapped
copy-on-write: the arrays are ordinary, writable numpy arrays whose pages are read on first use
and never written back.
"""

from __future__ import annotations

import hashlib
import json
import mmap
import os
import re
import secrets
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

MAGIC = b"WCPREP02"
_PREAMBLE = 24  # the magic, the header's length and its CRC-32
SUFFIX = ".wcprep"
_ALIGN = 64
_READ = 16 << 20  # bytes per read while checking the CRC


class Corrupt(ValueError):
    """A prepared file that cannot be trusted: damaged, truncated, or not one at all."""


def cache_dir() -> Path:
    """Where prepared files go: ``$WALLCULL_CACHE``, else ``~/.cache/wallcull``."""
    folder = os.environ.get("WALLCULL_CACHE")
    return Path(folder) if folder else Path.home() / ".cache" / "wallcull"


def cache_path(label: str, identity: str) -> Path:
    """The prepared file of a source: ``<label>-<16 hex of identity's hash>.wcprep`` in
    :func:`cache_dir`. ``identity`` names the source and the options it is built with (not its
    content: a changed source finds its old file, and the file's key says it is stale)."""
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", label)[:64] or "scene"
    digest = hashlib.sha256(identity.encode()).hexdigest()[:16]
    return cache_dir() / f"{safe}-{digest}{SUFFIX}"


def write(path: str | os.PathLike, arrays: dict[str, np.ndarray], meta: dict) -> int:
    """Write ``arrays`` and JSON-able ``meta`` to ``path`` atomically (a temporary file beside
    it, then a rename); returns the file's size in bytes."""
    path = Path(path)
    table, offset = {}, 0
    for name, a in arrays.items():
        a = np.asarray(a)
        table[name] = [a.dtype.newbyteorder("<").str, list(a.shape), offset, int(a.nbytes)]
        offset = _aligned(offset + a.nbytes)
    crc = 0
    for name, a in arrays.items():
        crc = zlib.crc32(_bytes(a), crc)
        crc = zlib.crc32(bytes(_aligned(a.nbytes) - a.nbytes), crc)
    header = json.dumps({"meta": meta, "arrays": table, "data_bytes": offset,
                         "data_crc32": crc}).encode()
    start = _aligned(_PREAMBLE + len(header))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(MAGIC + np.array([len(header), zlib.crc32(header)], "<u8").tobytes()
                    + header)
            f.write(bytes(start - _PREAMBLE - len(header)))
            for a in arrays.values():
                f.write(_bytes(a))
                f.write(bytes(_aligned(a.nbytes) - a.nbytes))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return start + offset


def read_meta(path: str | os.PathLike) -> dict:
    """The header's ``meta`` alone, without checking the data (:class:`Corrupt` if unreadable)."""
    with open(path, "rb") as f:
        return _header(f, os.fstat(f.fileno()).st_size)[0]["meta"]


def read(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict]:
    """``(arrays, meta)`` of a prepared file, the arrays memory-mapped copy-on-write, once the
    file's length and the CRC-32 of its data are checked. :class:`Corrupt` otherwise."""
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        header, start = _header(f, size)
        crc, left = 0, header["data_bytes"]
        f.seek(start)
        buffer = bytearray(min(_READ, max(left, 1)))
        view = memoryview(buffer)
        while left:
            got = f.readinto(view[:min(left, len(buffer))])
            if not got:
                raise Corrupt("truncated")
            crc = zlib.crc32(view[:got], crc)
            left -= got
        if crc != header["data_crc32"]:
            raise Corrupt("its data do not match their checksum")
        mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_COPY)
    arrays = {}
    for name, (dtype, shape, offset, nbytes) in header["arrays"].items():
        count = int(np.prod(shape, dtype=np.int64))
        arrays[name] = np.frombuffer(mapped, dtype=np.dtype(dtype), count=count,
                                     offset=start + offset).reshape(shape) if count else \
            np.zeros(shape, dtype=np.dtype(dtype))
    return arrays, header["meta"]


def _header(f, size: int) -> tuple[dict, int]:
    head = f.read(_PREAMBLE)
    if head[:7] == MAGIC[:7] and head[:8] != MAGIC:
        raise Corrupt("written by another version of wallcull")
    if len(head) < _PREAMBLE or head[:8] != MAGIC:
        raise Corrupt("not a prepared scene (bad magic)")
    length, crc = (int(v) for v in np.frombuffer(head[8:], dtype="<u8"))
    if length > size - _PREAMBLE:
        raise Corrupt("truncated header")
    text = f.read(length)
    if zlib.crc32(text) != crc:
        raise Corrupt("its header does not match its checksum")
    try:
        header = json.loads(text)
        if not (isinstance(header, dict) and isinstance(header.get("arrays"), dict)
                and isinstance(header.get("meta"), dict)):
            raise Corrupt("a header of the wrong shape")
        start = _aligned(_PREAMBLE + length)
        end, after = start + int(header["data_bytes"]), 0
        for name, (dtype, shape, offset, nbytes) in header["arrays"].items():
            dt = np.dtype(dtype)
            if (dt.hasobject or int(np.prod(shape, dtype=np.int64)) * dt.itemsize != nbytes
                    or offset % _ALIGN or offset < after or start + offset + nbytes > end):
                raise Corrupt(f"array {name!r} does not fit its table entry")
            after = offset + nbytes
        int(header["data_crc32"])
    except Corrupt:
        raise
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise Corrupt(f"unreadable header ({type(exc).__name__})") from None
    if end != size:
        raise Corrupt(f"{size} bytes where the header says {end}")
    return header, start


def _aligned(n: int) -> int:
    return -(-n // _ALIGN) * _ALIGN


def _bytes(a: np.ndarray) -> memoryview:
    a = np.ascontiguousarray(a)
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    return memoryview(a.reshape(-1).view(np.uint8))


# --------------------------------------------------------------------------- strings


def encode_strings(strings: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """``(blob (B,) uint8, offsets (k + 1,) int64)``: the UTF-8 bytes of ``strings`` back to
    back; string ``i`` is ``blob[offsets[i]:offsets[i + 1]]``."""
    encoded = [s.encode() for s in strings]
    offsets = np.zeros(len(encoded) + 1, dtype=np.int64)
    np.cumsum([len(e) for e in encoded], out=offsets[1:])
    return np.frombuffer(b"".join(encoded), dtype=np.uint8), offsets


class StringTable(Sequence):
    """Strings stored as :func:`encode_strings` stores them, decoded one at a time on access:
    a million names cost their bytes, not a million Python objects."""

    def __init__(self, blob: np.ndarray, offsets: np.ndarray):
        self.blob, self.offsets = blob, offsets

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(i)
        return self.blob[self.offsets[i]:self.offsets[i + 1]].tobytes().decode()

    def __iter__(self):
        data, o = self.blob.tobytes(), self.offsets.tolist()
        return (data[a:b].decode() for a, b in zip(o[:-1], o[1:]))

    def __eq__(self, other) -> bool:
        return isinstance(other, Sequence) and len(other) == len(self) and list(self) == list(other)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"StringTable({len(self)} strings)"
