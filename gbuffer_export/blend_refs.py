"""The external files a .blend names, read without Blender (core: standard library, ``zstandard`` for Blender's
compressed files).

A .blend is a header and a sequence of blocks; the last but one (``DNA1``) describes every struct's fields. This
reader keeps the ID blocks that name a file (libraries, images, sounds, fonts, movie clips, volumes, Alembic/USD
cache files), then reads each one's ``filepath`` by the file's own struct description, skipping packed data (it is
inside the .blend). Used by ``scene_refs`` before Blender opens the file; both block header layouts are read (the
one of Blender 5.0's ``BLENDER17-01`` header and the older 12-byte one).
"""
from __future__ import annotations

import gzip
import re
import struct
from dataclasses import dataclass

from .errors import BlendSRError

#: Struct name -> ID kind as messages say it. Each holds ``filepath`` (``name`` for libraries before Blender 2.93).
FILE_IDS = {"Library": "library", "Image": "image", "bSound": "sound", "VFont": "font", "MovieClip": "movie clip",
            "Volume": "volume", "CacheFile": "cache file"}
#: Fields that point at packed data: a non-null one means Blender reads the data from the .blend, not the path.
PACKED_FIELDS = ("packedfile", "packedfiles")
#: Bytes of an ID block kept for reading (every file-naming struct is smaller).
KEEP_BYTES = 1 << 16


class BlendReadError(BlendSRError):
    """A .blend this reader cannot parse (the message names the file)."""


@dataclass(frozen=True)
class BlendRef:
    kind: str       # "library", "image", ...
    name: str       # the ID's name without its two-letter code
    path: str       # as stored: '//' relative to the .blend's folder, or absolute


def _open(path) -> object:
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic[:2] == b"\x1f\x8b":
        return gzip.open(path, "rb")
    if magic == b"\x28\xb5\x2f\xfd":
        try:
            import zstandard
        except ImportError:
            raise BlendReadError(f"{path}: a zstd-compressed .blend needs the Python package zstandard") from None
        return zstandard.ZstdDecompressor().stream_reader(open(path, "rb"), closefd=True)
    return open(path, "rb")


def _read_exact(f, n: int, path) -> bytes:
    out = bytearray()
    while len(out) < n:
        chunk = f.read(n - len(out))
        if not chunk:
            raise BlendReadError(f"{path}: truncated .blend (a block ends early)")
        out += chunk
    return bytes(out)


def _skip(f, n: int, path) -> None:
    while n > 0:
        chunk = f.read(min(n, 1 << 20))
        if not chunk:
            raise BlendReadError(f"{path}: truncated .blend (a block ends early)")
        n -= len(chunk)


def _header(f, path):
    """(pointer size, endian prefix, block header struct and its field order)."""
    head = f.read(12)
    if not head.startswith(b"BLENDER"):
        raise BlendReadError(f"{path}: not a .blend file (bad header)")
    m = re.match(rb"BLENDER(\d\d)-(\d\d)([vV])", head + f.read(5)) if head[7:9].isdigit() else None
    if m:  # Blender 5.0: 'BLENDER17-01v0500', 64-bit block headers
        e = "<" if m.group(3) == b"v" else ">"
        return 8, e, struct.Struct(e + "4siQqq"), ("code", "sdna", "old", "len", "nr")
    psize = 8 if head[7:8] == b"-" else 4
    e = "<" if head[8:9] == b"v" else ">"
    fmt = e + ("4siQii" if psize == 8 else "4siIii")
    return psize, e, struct.Struct(fmt), ("code", "len", "old", "sdna", "nr")


def _cstrings(data: bytes, pos: int, n: int) -> tuple[list[str], int]:
    out = []
    for _ in range(n):
        end = data.index(b"\0", pos)
        out.append(data[pos:end].decode("latin-1"))
        pos = end + 1
    return out, (pos + 3) & ~3


def _sdna(data: bytes, e: str, psize: int, path) -> dict:
    """Struct name -> {field name: (offset, size, base name)} of the top-level fields."""
    try:
        pos = 8  # 'SDNA' 'NAME'
        (n,) = struct.unpack_from(e + "i", data, pos)
        names, pos = _cstrings(data, pos + 4, n)
        (n,) = struct.unpack_from(e + "i", data, pos + 4)  # 'TYPE'
        types, pos = _cstrings(data, pos + 8, n)
        lens = struct.unpack_from(e + f"{n}h", data, pos + 4)  # 'TLEN'
        pos = (pos + 4 + 2 * n + 3) & ~3
        (ns,) = struct.unpack_from(e + "i", data, pos + 4)  # 'STRC'
        pos += 8
        out = {}
        for _ in range(ns):
            t, nf = struct.unpack_from(e + "hh", data, pos)
            pos += 4
            fields, off = {}, 0
            for _ in range(nf):
                ft, fn = struct.unpack_from(e + "hh", data, pos)
                pos += 4
                name = names[fn]
                dims = 1
                for d in re.findall(r"\[(\d+)\]", name):
                    dims *= int(d)
                size = (psize if name.startswith(("*", "(")) else lens[ft]) * dims
                base = re.sub(r"[\[*()].*|^[*(]+", "", name.lstrip("*(")).split("[")[0]
                fields[base] = (off, size, types[ft], name)
                off += size
            out[types[t]] = fields
        return out
    except (struct.error, ValueError, IndexError) as exc:
        raise BlendReadError(f"{path}: unreadable .blend struct description ({exc})") from None


def blend_references(path) -> list[BlendRef]:
    """Every external file the .blend at ``path`` names (libraries, images, ...), packed ones left out.
    BlendReadError when it is not a readable .blend."""
    kept, dna = [], None
    with _open(path) as f:
        psize, e, bhead, order = _header(f, path)
        while True:
            raw = f.read(bhead.size)
            if len(raw) < bhead.size:
                raise BlendReadError(f"{path}: truncated .blend (no end block)")
            h = dict(zip(order, bhead.unpack(raw)))
            code, size = h["code"], h["len"]
            if size < 0:
                raise BlendReadError(f"{path}: corrupt .blend (a block of negative size)")
            if code == b"ENDB":
                break
            if code == b"DNA1":
                dna = _read_exact(f, size, path)
            elif code[2:] == b"\0\0" and code[:2].isalpha():  # an ID block: kept for its struct
                keep = min(size, KEEP_BYTES)
                kept.append((h["sdna"], _read_exact(f, keep, path)))
                _skip(f, size - keep, path)
            else:
                _skip(f, size, path)
    if dna is None:
        raise BlendReadError(f"{path}: corrupt .blend (no struct description)")
    structs = _sdna(dna, e, psize, path)
    names = list(structs)
    refs = []
    for sdna_nr, data in kept:
        sname = names[sdna_nr] if 0 <= sdna_nr < len(names) else None
        if sname not in FILE_IDS:
            continue
        ref = _file_of(structs[sname], data, sname, e, psize, structs.get("ID", {}))
        if ref is not None:
            refs.append(ref)
    return refs


def _text(data: bytes, off: int, size: int) -> str:
    return data[off:off + size].split(b"\0", 1)[0].decode("utf-8", "replace")


def _file_of(fields: dict, data: bytes, sname: str, e: str, psize: int, id_fields: dict) -> BlendRef | None:
    pfmt = e + ("Q" if psize == 8 else "I")
    for packed in PACKED_FIELDS:
        if packed in fields:
            off = fields[packed][0]
            if off + psize <= len(data) and struct.unpack_from(pfmt, data, off)[0]:
                return None  # packed: Blender reads the data inside the .blend
    # the file's path: 'filepath', or 'name' (Image's DNA name, and Library's before Blender 2.93)
    key = next((k for k in ("filepath", "name") if k in fields and fields[k][2] == "char" and fields[k][1] >= 256),
               None)
    if key is None:
        return None
    off, size = fields[key][:2]
    path = _text(data, off, size)
    name = (_text(data, fields["id"][0] + id_fields["name"][0] + 2, id_fields["name"][1] - 2)
            if "id" in fields and "name" in id_fields else "")
    if not path or (sname == "VFont" and path == "<builtin>"):
        return None
    return BlendRef(FILE_IDS[sname], name, path)


__all__ = ["BlendRef", "BlendReadError", "blend_references"]
