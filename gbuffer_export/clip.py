"""The clip on disk: reading (``open_clip``) and atomic, resumable writing (``ClipWriter``).

Layout (see ``docs/clip-format.md``)::

    CLIP/manifest.json                    clip header + one record per finished frame
    CLIP/frames/000012.json               the record of frame 12, written last (the frame's commit marker)
    CLIP/<level>/<buffer>/000012.exr      one EXR per level, buffer and frame, channels from ``BUFFERS``

Levels: 'hr', 'lr' (the primary scale) and, in clips rendered with several scales, 'lr_x<s>' (e.g. 'lr_x2.5').

One writer per clip: ``ClipWriter`` holds ``CLIP/.lock`` (flock) for its lifetime: exclusively, or shared by the
processes of one ``--shard K/N`` split (each also holding ``CLIP/.lock.shard-KofN`` exclusively); the header is
claimed and ``manifest.json`` merged under ``CLIP/.lock.manifest``. Nothing is read or written through a symbolic
link inside a clip (``check_no_links``); dataset indexes resolve their paths with ``resolve_inside``.

Pure numpy + json + OpenEXR: no bpy, no torch.
"""
from __future__ import annotations

import contextlib
import copy
import errno
import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from .errors import BlendSRError, first_line, with_path
from .colour_spaces import DEFAULT_WORKING_SPACE, conversion_matrix, convert_buffer
from .conventions import (BUFFERS, LEVELS, METERED_KEYS, SCHEMA, SCHEMA_VERSION, buffer_spec, check_level_sizes,
                          expose, exposure_of, is_level_name, level_name, luminance_stats, metered_exposure)
from .exr import read_exr, write_exr

try:
    import fcntl
except ImportError:  # not POSIX: no locking (BlendSR renders on Linux)
    fcntl = None

MANIFEST = "manifest.json"
FRAMES_DIR = "frames"
LOCK = ".lock"                      # held by every writer of the clip for its whole run
MANIFEST_LOCK = ".lock.manifest"    # held while the header is claimed or the manifest merged
#: Header keys that may differ between the processes rendering one clip (shards) or between reruns.
VOLATILE_KEYS = ("shard", "created", "frame_data", "identity", "command")


class ClipError(BlendSRError):
    """A clip that cannot be opened or written as asked. The message is one line naming the path."""


class ClipBusyError(ClipError):
    """Another process is writing the clip (one writer per clip)."""


class UnsafePathError(ClipError):
    """A path from an index or manifest that leaves its folder, or a symbolic link inside a clip."""


def check_no_links(root: str | os.PathLike, path: str | os.PathLike) -> Path:
    """``path`` when no existing component of it below ``root`` is a symbolic link (``root`` itself may be one:
    the user chose it); UnsafePathError naming the link otherwise. Nothing inside a clip is read or written through
    a link, so a clip (or a resumed render) never reaches outside its folder."""
    root, path = Path(root), Path(path)
    try:
        rel = path.relative_to(root)
    except ValueError:
        raise UnsafePathError(f"{path}: is outside {root}") from None
    p = root
    for part in rel.parts:
        p = p / part
        if p.is_symlink():
            raise UnsafePathError(f"{p}: is a symbolic link; BlendSR reads and writes nothing through links inside "
                                  f"{root} (replace it with the file or folder itself)")
    return path


def resolve_inside(root: str | os.PathLike, rel, *, source: str | os.PathLike, entry: str) -> Path:
    """The one rule for every path an index or manifest names (a dataset.json clip ``path``, ...): ``rel`` must be a
    relative path that, with symbolic links resolved, stays inside ``root``. Returns ``root / rel``; UnsafePathError
    naming ``source`` (the file that holds the path) and ``entry`` (which of its entries) otherwise. A file from
    someone else can therefore never make BlendSR read or write outside the folder that holds it."""
    where = f"{source}: {entry}"
    if not isinstance(rel, str) or not rel.strip():
        raise UnsafePathError(f"{where}: path {rel!r} is not a non-empty relative path")
    if "\x00" in rel or os.path.isabs(rel) or Path(rel).is_absolute():
        raise UnsafePathError(f"{where}: path {rel!r} is absolute; paths in an index are relative to its folder")
    root = Path(root)
    base = root.resolve()
    target = (root / rel).resolve()
    if target != base and base not in target.parents:
        raise UnsafePathError(f"{where}: path {rel!r} leads outside {root} (to {target}); refused")
    if target == base:
        raise UnsafePathError(f"{where}: path {rel!r} is the folder itself, not an entry inside it")
    return root / rel


def open_nofollow(path: Path, flags: int) -> int:
    """``os.open`` (mode 0o644) that refuses a symbolic link at ``path`` (UnsafePathError, one line)."""
    try:
        return os.open(path, flags | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0), 0o644)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise UnsafePathError(f"{path}: is a symbolic link; refused") from None
        raise


def write_json_atomic(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as JSON to ``path`` through a temporary file and a rename (a link at ``path`` is replaced,
    never written through)."""
    text = json.dumps(obj, indent=1, sort_keys=False, default=_json_default, allow_nan=False) + "\n"
    write_bytes_atomic(path, text.encode())


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file ``.NAME.tmpPID`` and a rename (a link at ``path`` is
    replaced, never written through); a filesystem fault (a full disk) names ``path``, and no temporary stays."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with contextlib.suppress(FileNotFoundError):
        os.unlink(tmp)  # a leftover (or a planted link) of the same name
    try:
        with os.fdopen(open_nofollow(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL), "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:  # a full disk, Ctrl-C: no temporary left behind; the error names the file
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename is None and exc.errno is not None:
            raise with_path(exc, path) from exc
        raise


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def header_identity(header: dict) -> str:
    """Hash of the clip header without its volatile keys: two processes may write one clip only when equal."""
    stable = {k: v for k, v in header.items() if k not in VOLATILE_KEYS}
    if isinstance(stable.get("exposure"), dict) and stable["exposure"].get("mode") == "auto":  # the request only
        stable["exposure"] = {k: v for k, v in stable["exposure"].items() if k not in METERED_KEYS}
    return hashlib.sha256(json.dumps(stable, sort_keys=True, default=_json_default).encode()).hexdigest()[:16]


def frame_name(frame: int) -> str:
    return f"{frame:06d}"


def buffer_path(root: Path, frame: int, level: str, name: str) -> Path:
    return root / level / name / f"{frame_name(frame)}.exr"


def split_key(key: str) -> tuple[str, str]:
    """'hr/fbeta' -> ('hr', 'fbeta'), 'lr_x2.5/depth' -> ('lr_x2.5', 'depth'), with a clear error for anything
    else."""
    level, sep, name = key.partition("/")
    if not sep or not is_level_name(level):
        raise ClipError(f"buffer key {key!r} must be '<level>/<buffer>' with level hr, lr or lr_x<scale>")
    buffer_spec(name)
    return level, name


def level_scales(manifest: dict) -> dict[str, float]:
    """Scale of every level of a manifest (hr: 1.0). Version 1 manifests have no per-level scale: their 'lr' level
    is at the top-level ``scale``."""
    out = {}
    for lvl, v in manifest["levels"].items():
        if lvl == "hr":
            out[lvl] = 1.0
        elif isinstance(v, dict) and "scale" in v:
            out[lvl] = float(v["scale"])
        elif lvl == "lr":
            out[lvl] = float(manifest["scale"])
    return out


def levels_header(hr_size: tuple[int, int], scales) -> dict:
    """The manifest's ``levels``: 'hr' and one LR level per scale ('lr' for the first, 'lr_x<s>' for the others),
    each with width, height (pixels) and scale (float; hr 1.0). ValueError when a scale does not divide the size."""
    sizes = check_level_sizes(hr_size, scales)
    out = {"hr": {"width": int(hr_size[0]), "height": int(hr_size[1]), "scale": 1.0}}
    for s, (w, h) in sizes.items():
        out[level_name(s, scales[0])] = {"width": w, "height": h, "scale": float(s)}
    return out


def scale_value(s: float) -> int | float:
    """An integral scale as int (what version 1 readers see), any other as float."""
    return int(s) if float(s).is_integer() else float(s)


class Clip:
    """A rendered clip opened for reading. ``frames`` lists the finished frames in ascending order.

    ``scale`` is the scale of the level 'lr' (int when integral), ``scales`` every LR level's scale (sorted floats),
    ``levels`` every level's directory name, ``sizes`` (W, H) per level. ``at_scale(s)`` gives a view whose 'lr'
    is the level at scale s."""

    def __init__(self, path: Path, manifest: dict, level_dirs: dict[str, str] | None = None):
        self.path = path
        self.manifest = manifest
        #: level name seen by the caller -> directory on disk ('lr' -> 'lr_x4' in a view of an extra level)
        self.level_dirs: dict[str, str] = dict(level_dirs or {})
        self.frame_data: dict[str, dict] = manifest.get("frame_data", {})
        self.frames: list[int] = sorted(int(f) for f in self.frame_data)
        self.planned_frames: list[int] = list(manifest.get("frames", []))
        self.scale: int | float = scale_value(float(manifest["scale"]))
        self.buffers: tuple[str, ...] = tuple(manifest["buffers"])
        self.sizes: dict[str, tuple[int, int]] = {
            lvl: (int(v["width"]), int(v["height"])) for lvl, v in manifest["levels"].items()}
        #: working colour space of the colour buffers (the manifest's ``scene_linear``; Blender's default if absent)
        self.scene_linear: str = str(manifest.get("scene_linear", DEFAULT_WORKING_SPACE))
        self.levels: tuple[str, ...] = tuple(manifest["levels"])
        self.level_scale: dict[str, float] = level_scales(manifest)
        self.scales: list[float] = sorted(s for lvl, s in self.level_scale.items() if lvl != "hr")
        #: the multiplier of radiance and emission that every reader applies (``read(..., exposed=True)``; 1 for
        #: clips without ``exposure``: docs/clip-format.md, "Exposure")
        try:
            self.exposure: float = exposure_of(manifest)
        except BlendSRError as exc:
            raise ClipError(f"{path / MANIFEST}: {exc}") from None
        #: the content key of a clip opened through ``validate.verdict.open_valid_clip`` (None otherwise)
        self.digest: str | None = None

    def __repr__(self) -> str:
        return f"Clip({str(self.path)!r}, frames={len(self.frames)}, scale={self.scale})"

    @property
    def complete(self) -> bool:
        return set(self.planned_frames) <= set(self.frames)

    def level_at(self, scale: float) -> str:
        """The level whose scale is ``scale``; ClipError naming the clip's scales otherwise."""
        for lvl, s in self.level_scale.items():
            if lvl != "hr" and abs(s - float(scale)) < 1e-9:
                return lvl
        raise ClipError(f"{self.path}: clip has no LR level at scale {scale:g} (has "
                        f"{', '.join(f'{s:g}' for s in self.scales)})")

    def at_scale(self, scale: float) -> "Clip":
        """A view of this clip whose 'lr' level is the level at ``scale`` (its size, intrinsics, jitter, records);
        'hr' is unchanged and the other LR levels are hidden. The view reads the same files."""
        lvl = self.level_at(scale)
        real = self.level_dirs.get(lvl, lvl)
        if lvl == "lr" and len(self.scales) == 1:
            return self
        m = dict(self.manifest)
        m["scale"] = scale_value(self.level_scale[lvl])
        m["levels"] = {"hr": self.manifest["levels"]["hr"],
                       "lr": {**self.manifest["levels"][lvl], "scale": self.level_scale[lvl]}}
        m["frame_data"] = {f: {**{k: v for k, v in rec.items() if not k.startswith("lr")}, "lr": rec[lvl]}
                           for f, rec in self.frame_data.items() if lvl in rec}
        view = Clip(self.path, m, {**self.level_dirs, "lr": real})
        view.digest = self.digest
        return view

    def path_of(self, frame: int, key: str) -> Path:
        level, name = split_key(key)
        return buffer_path(self.path, frame, self.level_dirs.get(level, level), name)

    def read(self, frame: int, key: str, *, space: str | None = None, exposed: bool = False) -> np.ndarray:
        """Buffer ``key`` ('hr/fbeta', 'lr/radiance', 'lr_x2.5/depth', ...) of ``frame`` as H x W x C float32
        (the ``flags`` buffer as uint32). ``space``: a working space (e.g. ``colour_spaces.TRAINING_SPACE``) to
        convert the colour buffers (radiance, emission, albedo, fbeta) into; None gives them as stored.
        ``exposed``: radiance and emission multiplied by the clip's exposure (``conventions.expose``), as every
        consumer of the data reads them; False gives the physical values stored."""
        level, name = split_key(key)
        if level not in self.sizes:
            raise ClipError(f"{self.path}: clip has no level {level!r} (has {', '.join(self.levels)})")
        if name not in self.buffers:
            raise ClipError(f"{self.path}: clip has no buffer {name!r} (has {', '.join(self.buffers)})")
        if frame not in self.frame_data and str(frame) not in self.frame_data:
            raise ClipError(f"{self.path}: frame {frame} is not a finished frame of this clip")
        a = read_exr(check_no_links(self.path, self.path_of(frame, key)), buffer_spec(name).channels)
        if exposed:
            a = expose(name, a, self.exposure)
        return a if space is None else convert_buffer(name, a, self.colour_matrix(space))

    def colour_matrix(self, space: str) -> np.ndarray | None:
        """3x3 matrix from the clip's working space to ``space`` (``rgb_space = M @ rgb_clip``), None when they
        are the same. ClipError naming the manifest when ``scene_linear`` is a space blendsr cannot convert."""
        try:
            return conversion_matrix(self.scene_linear, space)
        except ValueError as exc:
            raise ClipError(f"{self.path / MANIFEST}: scene_linear: {exc}") from None

    def camera(self, frame: int, level: str) -> dict[str, np.ndarray]:
        """``world_from_camera`` (4x4), ``intrinsics`` (fx, fy, cx, cy) and ``jitter`` (dx, dy) of a frame and
        level, plus ``prev_world_from_camera`` and ``prev_intrinsics`` (the camera of frame - 1) and, in clips with
        ``motion_next``, ``next_world_from_camera`` and ``next_intrinsics`` (the camera of frame + 1)."""
        try:
            rec = self.frame_data[str(frame)][level]
        except KeyError:
            raise ClipError(f"{self.path}: no camera for frame {frame}, level {level!r}") from None
        names = ("world_from_camera", "intrinsics", "jitter", "prev_world_from_camera", "prev_intrinsics")
        out = {n: np.asarray(rec[n], dtype=np.float64) for n in names}
        out.update({n: np.asarray(rec[n], dtype=np.float64) for n in ("next_world_from_camera", "next_intrinsics")
                    if n in rec})
        return out

    def record(self, frame: int) -> dict:
        """The manifest's whole record of a frame (per level: cameras, spp, seeds, timings)."""
        return self.frame_data[str(frame)]


def load_manifest(path: str | os.PathLike) -> dict:
    """Read and minimally check ``CLIP/manifest.json``; ClipError with a one-line reason otherwise."""
    root = Path(path)
    mpath = root / MANIFEST if root.is_dir() or not root.suffix else root
    if mpath.is_symlink():
        check_no_links(mpath.parent, mpath)
    if not mpath.is_file():
        raise ClipError(f"{mpath}: no manifest (not a BlendSR clip, or nothing finished yet)")
    try:
        manifest = json.loads(mpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ClipError(f"{mpath}: manifest is not valid JSON ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("schema") != SCHEMA:
        raise ClipError(f"{mpath}: not a BlendSR clip manifest (schema is not {SCHEMA!r})")
    version = manifest.get("schema_version")
    if not isinstance(version, int) or version > SCHEMA_VERSION:
        raise ClipError(f"{mpath}: schema_version {version!r} is newer than this blendsr reads ({SCHEMA_VERSION}); "
                        "upgrade blendsr")
    for key in ("scale", "levels", "buffers", "frames", "frame_data"):
        if key not in manifest:
            raise ClipError(f"{mpath}: manifest lacks {key!r}")
    fd = manifest["frame_data"]
    if not isinstance(fd, dict):
        raise ClipError(f"{mpath}: frame_data is not an object of frame number -> record")
    for k, rec in fd.items():
        if not str(k).lstrip("-").isdigit() or not isinstance(rec, dict):
            raise ClipError(f"{mpath}: frame_data key {k!r} is not a frame number with a record (an object)")
    return manifest


def open_clip(path: str | os.PathLike) -> Clip:
    """Open a clip directory for reading."""
    root = Path(path)
    if not root.is_dir():
        raise ClipError(f"{root}: not a directory")
    check_no_links(root, root / FRAMES_DIR)  # a clip with links inside is refused as a whole
    manifest = load_manifest(root)
    try:
        return Clip(root, manifest)
    except BlendSRError:
        raise
    except (ValueError, TypeError, KeyError, AttributeError) as exc:  # a hand-edited manifest of the wrong shape
        raise ClipError(f"{root / MANIFEST}: malformed manifest ({type(exc).__name__}: {first_line(exc)})") from None


class ClipWriter:
    """Writes a clip atomically and resumably. Each buffer file is renamed into place when complete; a frame
    counts as finished only once its record ``frames/NNNNNN.json`` exists, and that is written last.

    One writer per clip: the writer holds ``CLIP/.lock`` until ``close()`` (or the end of a ``with`` block):
    exclusively, or, for a shard of ``header['shard'] = [K, N]`` with N > 1, shared with the other shards of the
    same N while holding its own ``.lock.shard-KofN`` exclusively. A second writer is refused (ClipBusyError) before
    it writes anything. The header is claimed under ``.lock.manifest``: the first writer writes ``manifest.json``
    at once, so a writer with other settings then finds it and is refused ("holds a different clip"): a clip never
    mixes frames of two renders. Nothing is written through a symbolic link inside the clip."""

    def __init__(self, path: str | os.PathLike, header: dict):
        self.path = Path(path)
        self.header = copy.deepcopy(header)
        self.header.setdefault("schema", SCHEMA)
        self.header.setdefault("schema_version", SCHEMA_VERSION)
        self.header["identity"] = header_identity(self.header)
        self._fds: list[int] = []
        #: frame -> metering of its HR radiance, for an auto exposure (added to the frame's record on commit)
        self._metering: dict[int, dict] = {}
        self._check_existing()
        self.path.mkdir(parents=True, exist_ok=True)
        try:
            self._lock_writer()
            with self._manifest_lock():
                self._check_existing()  # again, now that no other writer can claim the folder
                if not (self.path / MANIFEST).is_file():
                    self._merge()  # the claim: the header is on disk before any frame
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------------------------------ locking
    def _flock(self, name: str, mode: int) -> int | None:
        """Open ``CLIP/name`` (never through a link) and flock it with ``mode`` (non-blocking unless ``mode``
        lacks LOCK_NB); the open descriptor, or None when the lock is held elsewhere."""
        for _ in range(100):
            try:
                fd = open_nofollow(self.path / name, os.O_RDWR | os.O_CREAT)
            except OSError as exc:  # read-only, not ours, or full: the clip cannot be written at all
                raise ClipError(f"{self.path}: cannot write this clip ({exc.strerror or exc}: {name})") from None
            try:
                fcntl.flock(fd, mode)
            except BlockingIOError:
                os.close(fd)
                return None
            except BaseException:
                os.close(fd)
                raise
            if self._still_linked(fd, name):
                return fd
            os.close(fd)  # the last writer of a finished clip removed this file meanwhile: lock the new one
        raise ClipError(f"{self.path}: its lock file {name} keeps being replaced; is another program deleting it?")

    def _still_linked(self, fd: int, name: str) -> bool:
        """True when ``CLIP/name`` is still the file ``fd`` locked (not removed by a finishing writer)."""
        try:
            now = os.stat(self.path / name, follow_symlinks=False)
        except FileNotFoundError:
            return False
        mine = os.fstat(fd)
        return (now.st_dev, now.st_ino) == (mine.st_dev, mine.st_ino)

    def _remove_lock_files_if_finished(self) -> None:
        """The last writer of a finished clip (every planned frame has its record) removes the clip's lock files:
        it upgrades its hold on ``.lock`` to exclusive (refused while another shard still writes), then deletes
        ``.lock``, ``.lock.manifest`` and every ``.lock.shard-*`` before releasing it. A writer that opened a lock
        file just before it was deleted finds it unlinked after locking and locks the new one (``_flock``)."""
        if fcntl is None or not self._fds:
            return
        try:
            done = {int(k) for k in json.loads((self.path / MANIFEST).read_text()).get("frame_data", {})}
        except (OSError, ValueError, AttributeError):
            return
        planned = {int(f) for f in self.header.get("frames", [])}
        if not planned or not planned <= done:
            return
        try:
            fcntl.flock(self._fds[0], fcntl.LOCK_EX | fcntl.LOCK_NB)  # _fds[0] is .lock (shared for a shard)
        except OSError:
            return  # another shard of this clip still writes: it removes them when it finishes
        with self._manifest_lock():
            for p in [self.path / LOCK, *sorted(self.path.glob(f"{LOCK}.shard-*of*")), self.path / MANIFEST_LOCK]:
                with contextlib.suppress(OSError):
                    p.unlink()

    def _lock_writer(self) -> None:
        if fcntl is None:
            return
        k, n = (self.header.get("shard") or [1, 1])[:2]
        busy = (f"{self.path}: another 'blendsr render' is writing this clip; wait for it to finish or choose "
                "another output directory")
        if n <= 1:
            fd = self._flock(LOCK, fcntl.LOCK_EX | fcntl.LOCK_NB)
            if fd is None:
                raise ClipBusyError(busy)
            self._fds.append(fd)
            return
        fd = self._flock(LOCK, fcntl.LOCK_SH | fcntl.LOCK_NB)
        if fd is None:  # an unsharded writer holds it
            raise ClipBusyError(busy)
        self._fds.append(fd)
        fd = self._flock(f"{LOCK}.shard-{k}of{n}", fcntl.LOCK_EX | fcntl.LOCK_NB)
        if fd is None:
            raise ClipBusyError(f"{self.path}: another 'blendsr render --shard {k}/{n}' is writing this clip; wait "
                                "for it to finish")
        self._fds.append(fd)
        for other in sorted(self.path.glob(f"{LOCK}.shard-*of*")):
            if other.name.rpartition("of")[2] == str(n) or other.is_symlink():
                continue
            probe = self._flock(other.name, fcntl.LOCK_EX | fcntl.LOCK_NB)
            if probe is None:
                m = other.name.rpartition("of")[2]
                raise ClipBusyError(f"{self.path}: shards of another split (--shard K/{m}) are writing this clip; "
                                    f"every shard of one clip must use the same N (this is {k}/{n})")
            os.close(probe)

    @contextlib.contextmanager
    def _manifest_lock(self):
        if fcntl is None:
            yield
            return
        fd = self._flock(MANIFEST_LOCK, fcntl.LOCK_EX)
        try:
            yield
        finally:
            os.close(fd)

    def close(self) -> None:
        """Release the clip (its locks) for the next writer; idempotent. The last writer of a finished clip leaves
        no lock file behind."""
        if getattr(self, "_fds", None):
            with contextlib.suppress(Exception):
                self._remove_lock_files_if_finished()
        fds, self._fds = getattr(self, "_fds", []), []
        for fd in fds:
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> "ClipWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        self.close()

    def _check_existing(self) -> None:
        if not self.path.exists():
            return
        if not self.path.is_dir():
            raise ClipError(f"{self.path}: exists and is not a directory")
        mpath = self.path / MANIFEST
        if mpath.is_file() or mpath.is_symlink():
            old = load_manifest(self.path)
            if old.get("identity") != self.header["identity"]:
                raise ClipError(f"{self.path}: holds a different clip (other scene or settings); "
                                "choose another output directory or delete it")
        elif any(p.name not in (FRAMES_DIR, *LEVELS, *self.header["levels"]) and not p.name.startswith(".")
                 for p in self.path.iterdir()):
            raise ClipError(f"{self.path}: directory is not empty and holds no BlendSR clip")

    def _target(self, path: Path) -> Path:
        """``path`` inside the clip, checked: no folder on the way is a link (the file itself, if a link, is
        replaced by the atomic rename, never written through)."""
        check_no_links(self.path, path.parent)
        return path

    def record_path(self, frame: int) -> Path:
        return self.path / FRAMES_DIR / f"{frame_name(frame)}.json"

    def is_frame_done(self, frame: int) -> bool:
        """True when the frame's record and every buffer file it lists exist."""
        rp = self.record_path(frame)
        if not rp.is_file() or rp.is_symlink():
            return False
        try:
            json.loads(rp.read_text())
        except json.JSONDecodeError:
            return False
        paths = [buffer_path(self.path, frame, lvl, b) for lvl in self.header["levels"] for b in self.header["buffers"]]
        return all(p.is_file() and not p.is_symlink() for p in paths)

    def write_buffer(self, frame: int, level: str, name: str, data: np.ndarray) -> None:
        """Write buffer ``name`` (H x W x C in the channel order of ``BUFFERS``) of a frame and level."""
        spec = buffer_spec(name)
        if level not in self.header["levels"]:
            raise ClipError(f"{self.path}: clip has no level {level!r} (has {', '.join(self.header['levels'])})")
        w, h = self.header["levels"][level]["width"], self.header["levels"][level]["height"]
        data = np.asarray(data)
        if data.ndim == 2:
            data = data[..., None]
        if data.shape != (h, w, len(spec.channels)):
            raise ClipError(f"{self.path}: {level}/{name} has shape {data.shape}, expected {(h, w, len(spec.channels))}")
        if spec.dtype == "uint32":
            data = data.astype(np.uint32)
        else:
            data = data.astype(np.float32)
        write_exr(self._target(buffer_path(self.path, frame, level, name)),
                  {c: data[..., i] for i, c in enumerate(spec.channels)})
        if level == "hr" and name == "radiance" and (self.header.get("exposure") or {}).get("mode") == "auto":
            self._metering[frame] = luminance_stats(data, self.header.get("scene_linear", DEFAULT_WORKING_SPACE))

    def commit_frame(self, frame: int, record: dict) -> None:
        """Mark ``frame`` finished with its record (per level: cameras, jitter, spp, seed, seconds) and merge. A clip
        with an auto exposure adds the metering of the frame's HR radiance (``hr.luminance``) to the record."""
        for lvl in self.header["levels"]:
            for b in self.header["buffers"]:
                if not buffer_path(self.path, frame, lvl, b).is_file():
                    raise ClipError(f"{self.path}: cannot commit frame {frame}: {lvl}/{b} was not written")
        if frame in self._metering and isinstance(record.get("hr"), dict):
            record = {**record, "hr": {**record["hr"], "luminance": self._metering.pop(frame)}}
        write_json_atomic(self._target(self.record_path(frame)), record)
        self.merge()

    def discard_frame(self, frame: int) -> None:
        """Remove the buffer files of an unfinished ``frame`` (an interrupted render's partial frame); a finished
        frame (its record exists) is left alone."""
        if self.record_path(frame).is_file():
            return
        for lvl in self.header["levels"]:
            for b in self.header["buffers"]:
                p = buffer_path(self.path, frame, lvl, b)
                with contextlib.suppress(OSError, ClipError):
                    self._target(p).unlink()

    def merge(self) -> dict:
        """Rewrite ``manifest.json`` from the header and every frame record present (shards merge here, one at a
        time)."""
        with self._manifest_lock():
            return self._merge()

    def _merge(self) -> dict:
        data = {}
        rdir = check_no_links(self.path, self.path / FRAMES_DIR)
        if rdir.is_dir():
            for rp in sorted(rdir.glob("*.json")):
                if rp.is_symlink():
                    continue  # never read through a link; the frame is rendered again
                try:
                    data[str(int(rp.stem))] = json.loads(rp.read_text())
                except (ValueError, json.JSONDecodeError):
                    continue  # a torn record is not a finished frame
        manifest = dict(self.header)
        manifest["frame_data"] = {k: data[k] for k in sorted(data, key=int)}
        if isinstance(manifest.get("exposure"), dict):  # an auto exposure metered over the finished frames
            manifest["exposure"] = metered_exposure(manifest["exposure"], manifest["frame_data"])
        write_json_atomic(self.path / MANIFEST, manifest)
        return manifest


__all__ = ["levels_header", "level_scales", "scale_value", "check_no_links", "resolve_inside", "open_nofollow",
           "Clip", "ClipError", "ClipBusyError", "UnsafePathError", "ClipWriter", "open_clip", "load_manifest",
           "write_json_atomic", "BUFFERS"]
