"""The verdict of a clip's last validation, recorded in the clip, and the one gate every consumer opens clips through.

``validate_clip`` writes ``CLIP/validation.json`` (atomically, ``write_json_atomic``; best effort: a clip on a
read-only disk is validated all the same): pass/fail, the error findings, the manifest's ``identity`` and, per file
of the clip (``manifest.json``, each finished frame's record and every buffer EXR of every level), its content hash
(``HASH_ALGORITHM``: BLAKE2b with a 16-byte digest, stdlib ``hashlib``, about 1 GB/s on one core) with the file's
size, mtime, ctime and inode. ``digest`` hashes the list of (file, hash): the clip's content in one key (the
training cache's key, ``training.cache``).

``gate.open_valid_clip`` is how ``train``, ``evaluate``, ``upscale``, ``preview`` and ``export-dataset`` open a clip: the
clip is read only if its last verdict passed and nothing changed since (the same identity, the same files, each
file's hash; a file whose size, times and inode are those recorded is not read again: ``utime`` cannot set the
ctime, so new bytes under kept file times still read as changed and are hashed). Otherwise the consumer validates
the clip itself (``validate_clip(quick=True)``, which records its verdict) and refuses a failing clip in one line
naming the clip and the failed check. Pure numpy + json: no bpy, no torch."""
from __future__ import annotations

import hashlib
import json
import logging
import os
import stat
import time
from pathlib import Path
from typing import Iterable

from ..clip import (FRAMES_DIR, MANIFEST, ClipError, UnsafePathError, check_no_links, frame_name, open_nofollow,
                    write_json_atomic)
from .report import ValidationReport

log = logging.getLogger(__name__)

VERDICT = "validation.json"
VERDICT_SCHEMA = "blendsr.validation"
VERDICT_VERSION = 1
HASH_ALGORITHM = "blake2b-128"
_CHUNK = 1 << 22
_MAX_LINES = 20


def file_hash(path: Path) -> str:
    """BLAKE2b-128 (hex) of the bytes of ``path``, read without following a link (UnsafePathError on a link)."""
    h = hashlib.blake2b(digest_size=16)
    with os.fdopen(open_nofollow(path, os.O_RDONLY), "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def clip_files(manifest: dict) -> list[str]:
    """Every file the clip's manifest vouches for, relative to the clip: the manifest, each finished frame's record
    and every buffer EXR of every level ([] parts for a manifest of the wrong shape: validation says why)."""
    files = [MANIFEST]
    try:
        frames = sorted(int(k) for k in manifest["frame_data"])
        levels, buffers = [str(x) for x in manifest["levels"]], [str(x) for x in manifest["buffers"]]
    except (KeyError, TypeError, ValueError, AttributeError):
        return files
    for f in frames:
        files.append(f"{FRAMES_DIR}/{frame_name(f)}.json")
        files += [f"{lvl}/{b}/{frame_name(f)}.exr" for lvl in levels for b in buffers]
    return files


def _stat_key(st: os.stat_result) -> list[int]:
    return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]


def file_state(root: Path, rel: str, previous: dict | None = None) -> dict | None:
    """{hash, stat} of ``root/rel``; None when it is missing, a link (or under one), or not a regular file. The
    hash of ``previous`` is reused when the stat (size, mtime, ctime, inode) is the one it was taken with."""
    path = root / rel
    try:
        check_no_links(root, path)
        st = os.stat(path, follow_symlinks=False)
    except (OSError, UnsafePathError):
        return None
    if not stat.S_ISREG(st.st_mode):
        return None
    key = _stat_key(st)
    if previous and previous.get("stat") == key and isinstance(previous.get("hash"), str):
        return previous
    try:
        return {"hash": file_hash(path), "stat": key}
    except (OSError, UnsafePathError):
        return None


def snapshot(root: Path, files: Iterable[str], previous: dict | None = None) -> dict[str, dict | None]:
    """{file: file_state} of ``files`` (``previous``: an earlier snapshot whose unchanged files are not read)."""
    previous = previous if isinstance(previous, dict) else {}
    return {rel: file_state(root, rel, previous.get(rel) if isinstance(previous.get(rel), dict) else None)
            for rel in files}


def content_digest(snap: dict[str, dict | None]) -> str:
    """One key for the clip's content: BLAKE2b-128 of the sorted (file, hash) list."""
    items = sorted((rel, s["hash"] if s else None) for rel, s in snap.items())
    return hashlib.blake2b(json.dumps(items).encode(), digest_size=16).hexdigest()


def _read_json(path: Path) -> dict | None:
    try:
        check_no_links(path.parent, path)
        with os.fdopen(open_nofollow(path, os.O_RDONLY), "r", encoding="utf-8") as f:
            data = json.load(f)
    except (OSError, ValueError, UnsafePathError):
        return None
    return data if isinstance(data, dict) else None


def read_verdict(root: str | os.PathLike) -> dict | None:
    """The recorded verdict of the clip at ``root`` (None when there is none, or it is not one)."""
    rec = _read_json(Path(root) / VERDICT)
    if rec is None or rec.get("schema") != VERDICT_SCHEMA or rec.get("hash") != HASH_ALGORITHM \
            or not isinstance(rec.get("files"), dict) or not isinstance(rec.get("ok"), bool):
        return None
    return rec


def before_validation(root: Path) -> dict[str, dict | None] | None:
    """The clip's files as they are before a validation reads them (None without a readable manifest)."""
    manifest = _read_json(root / MANIFEST)
    if manifest is None:
        return None
    old = read_verdict(root)
    return snapshot(root, clip_files(manifest), old["files"] if old else None)


def record_verdict(root: Path, report: ValidationReport, before: dict | None, *, quick: bool) -> dict | None:
    """Write the verdict of ``report`` into ``root/VERDICT`` when the files are still those ``before`` (taken
    before the checks read them); the record (also when it could not be written), or None when the clip changed
    during the validation or has no readable manifest."""
    manifest = _read_json(root / MANIFEST)
    if before is None or manifest is None:
        return None
    after = snapshot(root, clip_files(manifest), before)
    if after != before:
        log.warning(f"{root}: files changed while being validated; no verdict recorded")
        return None
    errors = report.errors
    rec = {"schema": VERDICT_SCHEMA, "version": VERDICT_VERSION, "ok": report.ok, "quick": bool(quick),
           "validated": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "identity": manifest.get("identity"),
           "errors": [{"code": f.code, "line": f.line()} for f in errors[:_MAX_LINES]],
           "error_count": len(errors), "hash": HASH_ALGORITHM, "digest": content_digest(after), "files": after}
    try:
        write_json_atomic(root / VERDICT, rec)
    except (OSError, ClipError) as exc:  # a read-only or full disk: the verdict holds for this process only
        log.debug(f"{root / VERDICT}: not written ({exc})")
    return rec


def current_verdict(root: str | os.PathLike) -> tuple[dict | None, str]:
    """(the recorded verdict, '') when it still describes the clip, else (None, why not)."""
    root = Path(root)
    rec = read_verdict(root)
    if rec is None:
        return None, "no recorded validation"
    manifest = _read_json(root / MANIFEST)
    if manifest is None or manifest.get("identity") != rec.get("identity"):
        return None, "its manifest's identity changed since its last validation"
    files = clip_files(manifest)
    if sorted(files) != sorted(rec["files"]):
        return None, "its frames changed since its last validation"
    now = snapshot(root, files, rec["files"])
    for rel in files:
        if now[rel] is None or rec["files"][rel] is None or now[rel]["hash"] != rec["files"][rel].get("hash"):
            return None, f"{rel} changed since its last validation"
    return rec, ""


def clip_content_digest(root: str | os.PathLike) -> str:
    """The content key of the clip at ``root`` (``content_digest`` of its files), hashing only the files whose stat
    differs from its recorded verdict's."""
    root = Path(root)
    manifest = _read_json(root / MANIFEST) or {}
    old = read_verdict(root)
    return content_digest(snapshot(root, clip_files(manifest), old["files"] if old else None))


__all__ = ["VERDICT", "HASH_ALGORITHM", "clip_files", "file_hash", "snapshot", "content_digest", "read_verdict",
           "record_verdict", "current_verdict", "clip_content_digest"]
