"""What a scene file may read: the one resolver of its external references (core: standard library only).

A scene file is read only inside its own folder and the folders the user allows (``allow_read``: ``blendsr render
--allow-read DIR``, a dataset spec's ``render.allow_read``). Before Blender sees the file, ``check_scene_refs``
resolves every file it names (links followed, ``..`` and absolute paths included):

- glTF (.gltf, .glb): buffer and image URIs (``data:`` URIs are inside the file); each accessor's count must fit its
  buffer view (a count of 10^9 in a small file is refused, not allocated);
- OBJ: every ``mtllib``, and every ``map_*``/``bump``/``disp``/``decal``/``refl``/``norm`` file of those MTL files;
- .blend: every library, image, sound, font, movie clip, volume and cache file it names (``blend_refs``), and those of
  its libraries in turn.

A reference that resolves outside the allowed folders, through a link that leaves them, or to something that is not
a regular file (``/dev/zero``, a FIFO, a folder) raises ``SceneRefError``, one line naming the scene file and the
reference; one inside an allowed folder that is not the scene's is returned, for the manifest. A missing file inside
is left to the importer (a missing texture renders neutral grey). The importers then run in a child process with
memory and time limits (``import_sandbox``).
"""
from __future__ import annotations

import json
import os
import re
import stat
import struct
from pathlib import Path
from urllib.parse import unquote

from .errors import BlendSRError

#: An accessor without a buffer view is zeros Blender allocates: at most this many elements.
MAX_ZERO_ACCESSOR = 1 << 26
COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
TYPE_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
#: MTL keywords that name a file besides ``map_*``.
MTL_FILE_KEYS = ("bump", "disp", "decal", "refl", "norm")
#: MTL texture options and how many values each takes at most (numbers, or one word).
MTL_OPTIONS = {"-blendu": 1, "-blendv": 1, "-boost": 1, "-cc": 1, "-clamp": 1, "-imfchan": 1, "-mm": 2, "-o": 3,
               "-s": 3, "-t": 3, "-texres": 1, "-type": 1, "-bm": 1, "-colorspace": 1}
#: Libraries of libraries are followed this deep.
MAX_LIBRARY_DEPTH = 8


class SceneRefError(BlendSRError):
    """A scene file that names a file it may not read, or a corrupt reference (one line naming both)."""


def read_roots(scene: Path, allow_read=()) -> tuple[Path, ...]:
    """The folders ``scene`` may read: its own folder first, then ``allow_read`` (links resolved)."""
    roots = [Path(os.path.realpath(Path(scene).parent))]
    for d in allow_read or ():
        p = Path(os.path.realpath(d))
        if not p.is_dir():
            raise SceneRefError(f"allow_read {d}: not a folder")
        roots.append(p)
    return tuple(roots)


def check_scene_file(path: Path) -> None:
    """SceneRefError unless ``path`` is a regular file (a folder named ``s.glb`` says it is a folder)."""
    path = Path(path)
    if path.is_dir():
        raise SceneRefError(f"{path}: is a folder, not a scene file")
    if not path.exists():
        raise SceneRefError(f"{path}: scene file not found")
    if not stat.S_ISREG(os.stat(path).st_mode):
        raise SceneRefError(f"{path}: not a regular file (a device, a FIFO or a socket)")


def _inside(real: Path, root: Path) -> bool:
    return real == root or root in real.parents


def resolve_ref(scene: Path, ref: str, base: Path, roots: tuple[Path, ...], what: str,
                shown: str | None = None, missing_ok: bool = False) -> Path | None:
    """``ref`` (as the file names it, relative to ``base`` or absolute) resolved with its links; SceneRefError
    when it leaves ``roots`` or is not a regular file. Returns the real path when it lies in an allowed folder other
    than the scene's (listed in the manifest), None otherwise. ``shown``: the reference as the file writes it.
    ``missing_ok`` (textures): a reference outside that names nothing at all reads nothing, and is left to the
    importer, which finds it missing and renders it neutral grey (an author's absolute texture path in a downloaded
    scene), as before the resolver."""
    shown = ref if shown is None else shown
    try:
        return _resolve(scene, ref, base, roots, what, shown, missing_ok)
    except SceneRefError:
        raise
    except (ValueError, OSError) as exc:  # a NUL or an unencodable character, a name too long for the system
        raise SceneRefError(f"{scene}: {what} {shown!r} is not a file name this system can open "
                            f"({type(exc).__name__})") from None


def _resolve(scene: Path, ref: str, base: Path, roots: tuple[Path, ...], what: str, shown: str,
             missing_ok: bool) -> Path | None:
    target = Path(ref) if os.path.isabs(ref) else Path(base) / ref
    real = Path(os.path.realpath(target))
    # an importer may apply '..' as text before following links (os.path.abspath), or follow links first
    # (realpath): the reference is read only when both readings stay inside an allowed folder
    textual = Path(os.path.realpath(os.path.normpath(os.path.abspath(target))))
    inside = next((r for r in roots if _inside(real, r)), None)
    if inside is None or not any(_inside(textual, r) for r in roots):
        if missing_ok and not any(os.path.lexists(p) for p in (target, real, textual)):
            return None  # nothing there to read (an author's absolute texture path): the importer finds it missing
        real = real if inside is None else textual
        via = f" (a link to {real})" if str(real) != os.path.normpath(os.path.abspath(target)) else ""
        raise SceneRefError(f"{scene}: {what} {shown!r} is outside the scene's folder{via}; it is not read (allow its "
                            "folder with --allow-read DIR, or render.allow_read in a spec)")
    if real.exists() and not stat.S_ISREG(os.stat(real).st_mode):
        raise SceneRefError(f"{scene}: {what} {shown!r} is not a regular file (a folder, device or FIFO); refused")
    return real if inside != roots[0] else None


# ---------------------------------------------------------------------------------------------------- glTF
def gltf_json(path: Path) -> dict:
    """The JSON of a .gltf or of a .glb's first chunk; SceneRefError (one line naming the file) if it is not glTF."""
    data = path.read_bytes() if path.suffix.lower() == ".gltf" else None
    if data is None:
        with open(path, "rb") as f:
            head = f.read(20)
            if len(head) < 20 or head[:4] != b"glTF":
                raise SceneRefError(f"{path}: not a glTF binary file (bad .glb header)")
            length, kind = struct.unpack_from("<I4s", head, 12)
            if kind != b"JSON":
                raise SceneRefError(f"{path}: not a glTF binary file (its first chunk is not JSON)")
            data = f.read(length)
            if len(data) < length:
                raise SceneRefError(f"{path}: truncated glTF binary (its JSON chunk ends early)")
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise SceneRefError(f"{path}: not a valid glTF file (JSON: {str(exc).splitlines()[0]})") from None
    except RecursionError:
        raise SceneRefError(f"{path}: not a valid glTF file (its JSON is nested too deeply to read)") from None
    if not isinstance(doc, dict):
        raise SceneRefError(f"{path}: not a valid glTF file (its JSON is not an object)")
    return doc


def gltf_items(doc: dict, key: str, path: Path) -> list:
    """``doc[key]`` as a list of objects (empty when absent); SceneRefError naming the file otherwise."""
    items = doc.get(key, [])
    if not isinstance(items, list) or not all(isinstance(x, dict) for x in items):
        raise SceneRefError(f"{path}: not a valid glTF file ({key} is not a list of objects)")
    return items


def uri_path(uri: str) -> str:
    """A glTF URI as the relative file path Blender's importer reads (``io_scene_gltf2``'s ``uri_to_path``):
    backslashes are separators, then percent-decoding. Every reader of a glTF URI here uses it, so what is checked
    is what the importer opens (``..\\x.bin`` is ``../x.bin``)."""
    return unquote(uri.replace("\\", "/"))


def _uri_refs(path: Path, doc: dict, roots, outside: list) -> None:
    for key in ("buffers", "images"):
        for i, item in enumerate(gltf_items(doc, key, path)):
            uri = item.get("uri")
            if uri is None:
                continue
            if not isinstance(uri, str):
                raise SceneRefError(f"{path}: glTF {key}[{i}].uri is not a string")
            if uri.startswith("data:"):
                continue
            if re.match(r"^[A-Za-z][A-Za-z0-9+.-]+:", uri):
                raise SceneRefError(f"{path}: glTF {key}[{i}].uri {uri!r} is not a file in the scene's folder "
                                    "(a URL); it is not read")
            real = resolve_ref(path, uri_path(uri), path.parent, roots, f"glTF {key}[{i}].uri", uri,
                               missing_ok=key == "images")
            if real is not None:
                outside.append(str(real))


def _element_bytes(acc: dict) -> int:
    comp, kind = COMPONENT_BYTES[acc["componentType"]], acc["type"]
    if kind.startswith("MAT") and comp < 4:  # matrix columns start on 4-byte boundaries
        n = int(kind[3])
        return n * ((n * comp + 3) & ~3)
    return TYPE_COMPONENTS[kind] * comp


def _int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _check_accessors(path: Path, doc: dict) -> None:
    """Each accessor's count fits its buffer view (or the zeros cap); its view fits its buffer."""
    views = gltf_items(doc, "bufferViews", path)
    buffers = gltf_items(doc, "buffers", path)
    for i, v in enumerate(views):
        b, off, n = v.get("buffer"), v.get("byteOffset", 0), v.get("byteLength")
        if not (_int(b) and _int(off) and _int(n)) or b >= len(buffers):
            raise SceneRefError(f"{path}: glTF bufferViews[{i}] is malformed (buffer, byteOffset, byteLength)")
        blen = buffers[b].get("byteLength")
        if not _int(blen) or off + n > blen:
            raise SceneRefError(f"{path}: glTF bufferViews[{i}] (bytes {off}..{off + n}) lies outside buffers[{b}] "
                                f"({blen} bytes): a corrupt glTF file")
    for i, acc in enumerate(gltf_items(doc, "accessors", path)):
        count = acc.get("count")
        if not _int(count) or acc.get("componentType") not in COMPONENT_BYTES or acc.get("type") not in \
                TYPE_COMPONENTS:
            raise SceneRefError(f"{path}: glTF accessors[{i}] is malformed (count, componentType or type)")
        size = _element_bytes(acc)
        bv = acc.get("bufferView")
        if bv is None:
            if count > MAX_ZERO_ACCESSOR:
                raise SceneRefError(f"{path}: glTF accessors[{i}] count {count} has no buffer view and exceeds "
                                    f"{MAX_ZERO_ACCESSOR} elements: a corrupt glTF file")
            continue
        if not _int(bv) or bv >= len(views):
            raise SceneRefError(f"{path}: glTF accessors[{i}].bufferView {bv!r} does not exist")
        view = views[bv]
        stride, offset, length = view.get("byteStride") or size, acc.get("byteOffset", 0), view.get("byteLength")
        if not (_int(stride) and _int(offset) and _int(length)):
            raise SceneRefError(f"{path}: glTF accessors[{i}] or bufferViews[{bv}]: byteOffset, byteStride and "
                                "byteLength must be non-negative integers: a corrupt glTF file")
        need = offset + (stride * (count - 1) + size if count else 0)
        if need > length:
            raise SceneRefError(f"{path}: glTF accessors[{i}] count {count} needs {need} bytes but its bufferView "
                                f"{bv} holds {length}: a corrupt glTF file")


def _gltf_refs(path: Path, roots, outside: list) -> None:
    doc = gltf_json(path)
    _uri_refs(path, doc, roots, outside)
    _check_accessors(path, doc)


# ---------------------------------------------------------------------------------------------------- OBJ
def _lines_with(path: Path, keys: tuple[str, ...]):
    """(keyword, rest of line) of each line of ``path`` starting with one of ``keys`` (case-insensitive), read
    in chunks (an OBJ may be gigabytes)."""
    pat = re.compile(rb"(?im)^[ \t]*((?:" + b"|".join(k.encode() for k in keys) + rb")[A-Za-z_]*)[ \t]+([^\r\n]*)")
    tail = b""
    with open(path, "rb") as f:
        while True:
            chunk = f.read(1 << 24)
            data = tail + chunk
            cut = data.rfind(b"\n") + 1 if chunk else len(data)
            for m in pat.finditer(data, 0, cut):
                yield m.group(1).decode("latin-1"), m.group(2).decode("utf-8", "replace").strip()
            tail = data[cut:]
            if not chunk:
                return


def _mtl_path(rest: str) -> list[str]:
    """The file of an MTL texture line (options skipped), and its last word (the importers' fallback)."""
    words = rest.split()
    i = 0
    while i < len(words) and words[i].lower() in MTL_OPTIONS:
        n = MTL_OPTIONS[words[i].lower()]
        i += 1
        for _ in range(n):
            if i < len(words) - 1 and (re.fullmatch(r"[-+]?[0-9.eE+-]+", words[i]) or n == 1):
                i += 1
    name = " ".join(words[i:])
    return sorted({c for c in (name, name.strip('"'), words[-1] if words else "") if c})


def _obj_refs(path: Path, roots, outside: list) -> None:
    for _, rest in _lines_with(path, ("mtllib",)):
        names = {rest, *rest.split(), rest.strip('"'), *(w.strip('"') for w in rest.split())}
        for name in sorted(n for n in names if n):
            real = resolve_ref(path, name, path.parent, roots, "mtllib")
            if real is not None:
                outside.append(str(real))
            mtl = Path(os.path.realpath(path.parent / name))
            if not mtl.is_file():
                continue
            for key, line in _lines_with(mtl, ("map_", *MTL_FILE_KEYS)):
                if not (key.lower().startswith("map_") or key.lower() in MTL_FILE_KEYS):
                    continue
                for ref in _mtl_path(line):
                    for base in {mtl.parent, path.parent}:  # the MTL's folder; the OBJ's (the importer's cwd)
                        real = resolve_ref(path, ref, base, roots, f"{mtl.name}: {key}", missing_ok=True)
                        if real is not None:
                            outside.append(str(real))


# ---------------------------------------------------------------------------------------------------- .blend
def _blend_refs(path: Path, roots, outside: list, depth: int = 0, seen=None) -> None:
    from .blend_refs import BlendReadError, blend_references
    seen = set() if seen is None else seen
    real_self = os.path.realpath(path)
    if real_self in seen or depth > MAX_LIBRARY_DEPTH:
        return
    seen.add(real_self)
    try:
        refs = blend_references(path)
    except BlendReadError as exc:
        raise SceneRefError(str(exc)) from None
    for ref in refs:
        rel = ref.path[2:] if ref.path.startswith("//") else ref.path
        base = Path(path).parent
        real = resolve_ref(path, rel, base, roots, f"{ref.kind} {ref.name!r} file",
                           missing_ok=ref.kind != "library")
        if real is not None:
            outside.append(str(real))
        if ref.kind == "library":
            lib = Path(os.path.realpath(base / rel))
            if lib.is_file():
                _blend_refs(lib, roots, outside, depth + 1, seen)


_READERS = {".gltf": _gltf_refs, ".glb": _gltf_refs, ".obj": _obj_refs, ".blend": _blend_refs}


def check_scene_refs(scene: Path, allow_read=()) -> list[str]:
    """Check every file ``scene`` names (module doc); returns those read from allowed folders outside its own
    (real paths, sorted) for the manifest. SceneRefError (one line) on a refusal."""
    scene = Path(scene)
    check_scene_file(scene)
    roots = read_roots(scene, allow_read)
    reader = _READERS.get(scene.suffix.lower())
    outside: list[str] = []
    if reader is not None:
        reader(scene, roots, outside)
    return sorted(set(outside))


__all__ = ["SceneRefError", "check_scene_file", "check_scene_refs", "gltf_items", "gltf_json", "read_roots",
           "resolve_ref", "uri_path"]
