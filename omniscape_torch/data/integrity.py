"""Whether a dataset's files are whole: a cheap look at each file's structure, for ``generate``
to render a damaged frame again on resume and for ``stats`` to leave it out and name it.

A file written by ``generate`` is whole (written atomically), but a copy, a sync or a disk can
cut one short later. `file_damage` reads only the structure that a cut breaks, without
decoding the pixels:

* PNG: the signature, then the chain of chunks (each one's length and type, 8 bytes read per
  chunk), which must reach ``IEND`` within the file;
* OpenEXR (single-part scanline files, as ``io.write_exr`` writes them): the header, the
  offset table, and every chunk it points to starting inside the file, the last one ending
  there; other OpenEXR files are decoded whole;
* JSON: parsed whole (the objects files are small);

so that a file cut anywhere is found, and a resume of a finished dataset stays quick: measured
on the default 8-frame dataset (4 cameras at 256 x 256, 224 files), 5-6 ms for all its files,
against 175 ms to decode them (Pillow's ``verify`` and a full OpenEXR read) and 0.3 s for
the rest of the resume. A bit flipped inside a file's compressed data is not found here (the
readers' decoding finds it: ``stats`` names such a file too).
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

__all__ = ["damaged_files", "file_damage"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_EXR_MAGIC = b"\x76\x2f\x31\x01"
#: Scanlines per chunk of each OpenEXR compression (NONE, RLE, ZIPS, ZIP, PIZ, PXR24, B44,
#: B44A, DWAA, DWAB).
_EXR_LINES = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256}
#: OpenEXR version flags: tiled, deep data, multi-part (read by a full decode instead).
_EXR_OTHER = 0x200 | 0x800 | 0x1000


def _png_damage(f, size: int) -> str | None:
    if f.read(8) != _PNG_SIGNATURE:
        return "not a PNG"
    pos = 8
    while True:
        head = f.read(8)
        if len(head) < 8:
            return "cut short (no IEND chunk)"
        length, kind = struct.unpack(">I4s", head)
        end = pos + 12 + length
        if end > size:
            return f"cut short (its {kind.decode('latin-1')} chunk ends past the file)"
        if kind == b"IEND":
            return None
        pos = end
        f.seek(pos)


def _exr_full_read(path: Path) -> str | None:
    from ..io import read_exr

    try:
        read_exr(path)
    except (ValueError, TypeError, OSError) as err:
        return f"not a readable OpenEXR file ({err})"
    return None


def _exr_damage(f, size: int, path: Path) -> str | None:
    head = f.read(8)
    if head[:4] != _EXR_MAGIC:
        return "not an OpenEXR file"
    if len(head) < 8:
        return "cut short (in its header)"
    if struct.unpack("<I", head[4:])[0] & _EXR_OTHER:
        return _exr_full_read(path)
    window = compression = None
    data = f.read(min(size, 1 << 16) - 8)
    pos = 0
    while True:   # attributes: name\0 type\0 size value, then an empty name
        if pos >= len(data):
            return "cut short (in its header)"
        if data[pos] == 0:
            pos += 1
            break
        name_end = data.find(b"\0", pos)
        type_end = data.find(b"\0", name_end + 1)
        if name_end < 0 or type_end < 0 or type_end + 5 > len(data):
            return "cut short (in its header)"
        name = data[pos:name_end]
        (length,) = struct.unpack_from("<i", data, type_end + 1)
        value = data[type_end + 5:type_end + 5 + length]
        if len(value) < length or length < 0:
            return "cut short (in its header)"
        if name == b"dataWindow" and length == 16:
            window = struct.unpack("<4i", value)
        elif name == b"compression" and length == 1:
            compression = value[0]
        pos = type_end + 5 + length
    if window is None or compression not in _EXR_LINES:
        return _exr_full_read(path)
    rows = window[3] - window[1] + 1
    chunks = -(-rows // _EXR_LINES[compression])
    table = data[pos:pos + 8 * chunks]
    if len(table) < 8 * chunks:
        f.seek(8 + pos)
        table = f.read(8 * chunks)
        if len(table) < 8 * chunks:
            return "cut short (in its offset table)"
    offsets = struct.unpack(f"<{chunks}Q", table)
    first = 8 + pos + 8 * chunks
    if any(not first <= o <= size - 8 for o in offsets):
        return "cut short (a chunk starts past the file)"
    last = max(offsets)
    f.seek(last)
    (length,) = struct.unpack("<i", f.read(8)[4:])
    if last + 8 + length > size:
        return "cut short (its last chunk ends past the file)"
    return None


def file_damage(path: str | os.PathLike) -> str | None:
    """What is wrong with the file at ``path`` (``"cut short (no IEND chunk)"``, ``"not a
    PNG"``, ...), or None when its structure is whole (module docstring: what is checked, by
    suffix; files of other suffixes are not looked into). A missing file is ``"missing"``."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            suffix = path.suffix.lower()
            if size == 0 and suffix in (".png", ".exr", ".json"):
                return "empty"   # other files may be (WoodScape's box files with no box)
            if suffix == ".png":
                return _png_damage(f, size)
            if suffix == ".exr":
                return _exr_damage(f, size, path)
            if suffix == ".json":
                try:
                    json.loads(f.read())
                except ValueError as err:
                    return f"not JSON ({err})"
    except FileNotFoundError:
        return "missing"
    except (IsADirectoryError, NotADirectoryError):
        return "not a file"
    return None


def damaged_files(root: str | os.PathLike, files) -> dict[str, str]:
    """``{relative path: what is wrong}`` of the ``files`` (paths relative to ``root``) that
    `file_damage` finds damaged; ``{}`` when all are whole."""
    root = Path(root)
    out = {}
    for file in files:
        why = file_damage(root / file)
        if why is not None:
            out[file] = why
    return out
