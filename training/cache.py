"""Training cache of a clip: every buffer decoded once into a memory-mapped ``.npy`` array, so that no EXR is
decoded inside a training step (pure numpy; no torch).

Layout::

    CACHE/index.json                 identity, frames, sizes, arrays, per-frame depth reference, sanitising log
    CACHE/<level>__<buffer>.npy      (N, H, W, C) for the N finished frames in ascending order (level: the clip's
                                     directory name, 'lr_x2.5' for an extra LR level)

``CACHE`` is ``CLIP/.blendsr_cache`` (ClipWriter ignores dot-names), or ``DIR/<clip-name>-<path-hash>`` when a cache
directory is given or the clip is not writable. The cache identity hashes the bytes of ``manifest.json``, the
clip's content (``validate.verdict.clip_content_digest``: the BLAKE2b hash of every file, so an EXR rewritten with
its file times kept, or replaced by a link, rebuilds the cache), the cache format version, the demodulation eps and the non-finite policy: when any of them changes the cache is wiped
and rebuilt. Arrays are added lazily (``ensure``), each under a file lock, written to a temporary name and renamed.

Colour buffers (radiance, emission, albedo, fbeta) are stored in ``colour_spaces.TRAINING_SPACE`` (Linear Rec.709):
a clip rendered in another working space (the manifest's ``scene_linear``) is converted when cached, after the
non-finite check and before demodulation.

Stored dtypes: radiance, irradiance, emission, fbeta_used, depth, motion and motion_next as float32 (float16
overflows above 65504 and loses motion precision); flags uint32; the other G-buffers float16. Derived buffers:
``irradiance`` and ``fbeta_used`` = ``gbuffer_export.demod.demodulate(radiance, emission, fbeta, flags, eps)``.
"""
from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import warnings
from contextlib import contextmanager
from pathlib import Path

import filelock
import numpy as np

from gbuffer_export.clip import (Clip, ClipError, UnsafePathError, open_clip, open_nofollow, split_key,
                                 write_json_atomic)
from gbuffer_export.colour_spaces import TRAINING_SPACE, convert_buffer
from gbuffer_export.conventions import BUFFERS, LEVELS
from gbuffer_export.demod import RADIANCE_CAP, demodulate
from gbuffer_export.validate.verdict import clip_content_digest

CACHE_VERSION = 5  # 2: radiance/emission beyond RADIANCE_CAP fall under data.nonfinite; 3: training space;
#                  4: radiance checked by validate's rule (non-finite, negative on surfaces); 5: keyed by content
#: The findings of ``blendsr validate`` the cache checks itself as it reads each frame, in validate's words, and
#: refuses or sanitises under ``data.nonfinite``: a clip failing only these is not refused before the cache.
CACHE_CHECKED = ("non-finite", "negative-radiance")
CACHE_DIRNAME = ".blendsr_cache"
DERIVED = ("irradiance", "fbeta_used")
#: The clip buffers the derived ones are computed from (``demodulate``; emission and flags are optional).
DERIVED_FROM = ("radiance", "fbeta")
FLOAT32_BUFFERS = ("radiance", "irradiance", "emission", "fbeta_used", "fbeta", "depth", "motion",
                   "motion_next")


class NonFiniteError(ClipError):
    """A buffer holds NaN/Inf where it must not (message names the file and frame)."""


class CacheSpaceError(ClipError):
    """The cache's filesystem has no room for an array or its index (the message names the file)."""


#: errno values that mean "the filesystem is full" (disk or quota)
NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


def space_error(path: Path, detail: str) -> CacheSpaceError:
    """The one-line error for a full cache filesystem, naming the file that could not be written."""
    return CacheSpaceError(f"{path}: no space left for the training cache ({detail}); free space on that "
                           "filesystem or set data.cache_dir to a folder with room")


def reserve(fd: int, size: int, what: Path) -> None:
    """Allocate ``size`` bytes of the open file ``fd`` now, so that writing into its memory map can never hit a full
    filesystem (SIGBUS, which kills the process with no message): ``os.posix_fallocate`` where the platform has it
    (Linux), else the file is filled with zeros (macOS, Windows: every block written once). CacheSpaceError naming
    ``what`` when the filesystem cannot hold it; filesystems without fallocate support get the zeros too."""
    try:
        try:
            os.posix_fallocate(fd, 0, size)
            return
        except AttributeError:  # not on this platform
            pass
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
                raise
        zeros = bytes(min(size, 1 << 22))
        os.lseek(fd, 0, os.SEEK_SET)
        left = size
        while left > 0:
            left -= os.write(fd, zeros[:min(left, len(zeros))])
        os.fsync(fd)
    except OSError as exc:
        if exc.errno in NO_SPACE:
            raise space_error(what, f"{size / 1e6:.1f} MB needed") from None
        raise


def storage_dtype(name: str) -> np.dtype:
    if name == "flags":
        return np.dtype(np.uint32)
    return np.dtype(np.float32 if name in FLOAT32_BUFFERS else np.float16)


def channels_of(name: str) -> int:
    if name in DERIVED:
        return 3
    return len(BUFFERS[name].channels)


def manifest_sha256(clip_path: Path) -> str:
    return hashlib.sha256((Path(clip_path) / "manifest.json").read_bytes()).hexdigest()


def default_cache_path(clip_path: Path, cache_dir: str | os.PathLike | None = None) -> Path:
    """Where the cache of ``clip_path`` lives (see module doc)."""
    clip_path = Path(clip_path).resolve()
    tag = f"{clip_path.name}-{hashlib.sha256(str(clip_path).encode()).hexdigest()[:10]}"
    if cache_dir:
        return Path(cache_dir) / tag
    if os.access(clip_path, os.W_OK):
        if (clip_path / CACHE_DIRNAME).is_symlink():  # never written through a link out of the clip
            raise UnsafePathError(f"{clip_path / CACHE_DIRNAME}: is a symbolic link; the cache is never written "
                                  "through a link (remove it; set data.cache_dir to keep the cache elsewhere)")
        return clip_path / CACHE_DIRNAME
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "blendsr"
    return base / tag


def check_finite(a: np.ndarray, name: str, where: str, policy: str, log: list) -> np.ndarray:
    """Apply the non-finite policy to buffer ``name``. Depth may be +inf (background); nothing else may be
    non-finite, and radiance/emission beyond +-RADIANCE_CAP (values no scene produces) count as non-finite.
    'error' raises NonFiniteError naming ``where``; 'sanitize' warns, records and repairs:
    radiance/emission by the demodulation rule (NaN -> 0, +-Inf -> +-cap), depth NaN/-Inf -> +inf (background),
    other buffers NaN/Inf -> 0."""
    if a.dtype.kind != "f":
        return a
    if name == "depth":
        bad = np.isnan(a) | np.isneginf(a)
    else:
        bad = ~np.isfinite(a)
    what = "NaN/Inf"
    if name in ("radiance", "emission"):  # beyond RADIANCE_CAP no scene produces: treated like Inf
        huge = np.abs(a) > RADIANCE_CAP
        if huge.any():
            bad |= huge
            what = f"NaN/Inf or implausible (|x| > {RADIANCE_CAP:.0e})"
    n = int(bad.sum())
    if n == 0:
        return a
    if policy == "error":
        raise NonFiniteError(f"{where}: {n} {what} value(s) in buffer {name!r}; fix the render or set "
                             "data.nonfinite = \"sanitize\"")
    warnings.warn(f"{where}: sanitised {n} {what} value(s) in buffer {name!r}", RuntimeWarning, stacklevel=3)
    log.append({"where": where, "buffer": name, "count": n})
    if name in ("radiance", "emission"):
        return np.clip(np.nan_to_num(a, nan=0.0, posinf=RADIANCE_CAP, neginf=-RADIANCE_CAP),
                       -RADIANCE_CAP, RADIANCE_CAP).astype(a.dtype)
    if name == "depth":
        return np.where(bad, np.inf, a).astype(a.dtype)
    return np.where(bad, 0.0, a).astype(a.dtype)


class ClipCache:
    """The cache of one clip. ``array(key)`` gives the (N, H, W, C) memmap of 'lr/irradiance' etc.;
    ``index_of[frame]`` its row; ``depth_ref[frame]`` the median finite LR depth of a frame (scene units).
    ``scale``: the LR level that 'lr/...' keys read (``Clip.at_scale``); None: the clip's level 'lr'. Caches of
    several levels of one clip share its cache directory."""

    def __init__(self, clip_path: str | os.PathLike, *, eps: float = 0.01, nonfinite: str = "error",
                 cache_dir: str | os.PathLike | None = None, scale: float | None = None):
        base = open_clip(clip_path)
        self.clip: Clip = base.at_scale(scale) if scale is not None else base
        self.colour_matrix = self.clip.colour_matrix(TRAINING_SPACE)  # None: the clip is in the training space
        self._base_sizes = base.sizes
        self._lr_dir = self.clip.level_dirs.get("lr", "lr")
        self._depth_ref_key = "depth_ref" if self._lr_dir == "lr" else f"depth_ref:{self._lr_dir}"
        self.clip_path = Path(clip_path)
        self.eps = float(eps)
        self.nonfinite = nonfinite
        self.path = default_cache_path(self.clip_path, cache_dir)
        self.manifest_sha256 = manifest_sha256(self.clip_path)
        self.content = clip_content_digest(self.clip_path)  # every file's hash, not its time: new bytes rebuild
        self.identity = hashlib.sha256(json.dumps(
            [CACHE_VERSION, self.manifest_sha256, self.content, self.eps, nonfinite,
             TRAINING_SPACE]).encode()).hexdigest()[:16]
        self.frames = list(self.clip.frames)
        if not self.frames:
            raise ClipError(f"{self.clip_path}: clip has no finished frame")
        self.index_of = {f: i for i, f in enumerate(self.frames)}
        self.scale = self.clip.scale
        self.sizes = self.clip.sizes
        self._arrays: dict[str, np.ndarray] = {}
        self._tmp: set[Path] = set()
        self._writing: Path = self.path / "index.json"  # the file a full filesystem error names
        self.index = self._load_or_reset()

    # -------------------------------------------------------------------------------------------- index
    @contextmanager
    def _lock(self):
        """The cache's lock (``CACHE/.lock``, filelock: flock or LockFileEx), blocking: one builder at a time."""
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            self._raise_if_full(exc, self.path)
            raise
        path = self.path / ".lock"
        if path.is_symlink():
            raise UnsafePathError(f"{path}: is a symbolic link; refused")
        lock = filelock.FileLock(path, thread_local=False, is_singleton=False)
        try:
            lock.acquire()
        except OSError as exc:
            self._raise_if_full(exc, path)
            raise
        try:
            yield
        finally:
            lock.release(force=True)

    def _read_index(self) -> dict | None:
        p = self.path / "index.json"
        if not p.is_file():
            return None
        try:
            return json.loads(p.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            return None

    def _load_or_reset(self) -> dict:
        with self._lock():
            idx = self._read_index()
            if idx is None or idx.get("identity") != self.identity:
                self.rebuilt = idx is not None
                for p in self.path.iterdir():
                    if p.name != ".lock":
                        shutil.rmtree(p) if p.is_dir() else p.unlink()
                idx = {"version": CACHE_VERSION, "identity": self.identity, "clip": str(self.clip_path.resolve()),
                       "manifest_sha256": self.manifest_sha256, "content": self.content, "frames": self.frames, "scale": self.scale,
                       "sizes": self._base_sizes, "eps": self.eps, "nonfinite": self.nonfinite, "arrays": {},
                       "depth_ref": {}, "sanitized": []}
                try:
                    write_json_atomic(self.path / "index.json", idx)
                except OSError as exc:
                    self._raise_if_full(exc, self.path / "index.json")
                    raise
            else:
                self.rebuilt = False
            return idx

    @property
    def keys(self) -> list[str]:
        """Keys available in the clip (derived ones included), cached or not."""
        out = []
        for lvl in LEVELS:
            out += [f"{lvl}/{b}" for b in self.clip.buffers]
            if {"radiance", "fbeta"} <= set(self.clip.buffers):
                out += [f"{lvl}/{d}" for d in DERIVED]
        return out

    def has(self, key: str) -> bool:
        return key in self.keys

    # -------------------------------------------------------------------------------------------- build
    def ensure(self, keys) -> "ClipCache":
        """Build the arrays of ``keys`` that are not cached yet (and the depth reference with 'lr/depth')."""
        keys = list(dict.fromkeys(keys))
        missing = [k for k in keys if self._real(k) not in self.index["arrays"]]
        if "lr/depth" in keys and not self.index.get(self._depth_ref_key):
            missing.append("lr/depth")
        if not missing:
            return self
        for k in missing:
            if not self.has(k):
                lvl, _, name = k.partition("/")
                lacking = [f"{lvl}/{b}" for b in DERIVED_FROM if b not in self.clip.buffers] \
                    if name in DERIVED else []
                what = (f"{' and '.join(map(repr, lacking))} (from which {k!r} is computed)" if lacking
                        else repr(k))
                raise ClipError(f"{self.clip_path}: clip has no buffer {what} (has {', '.join(self.clip.buffers)})")
        with self._lock():
            idx = self._read_index()
            if idx is None or idx.get("identity") != self.identity:
                raise ClipError(f"{self.path}: cache changed while building; rerun")
            self.index = idx
            self._writing = self.path / "index.json"
            try:
                for k in dict.fromkeys(missing):
                    if self._real(k) in self.index["arrays"] and not (k == "lr/depth"
                                                                       and not self.index.get(self._depth_ref_key)):
                        continue
                    lvl, name = k.split("/")
                    if name in DERIVED:
                        self._build_derived(lvl)
                    else:
                        self._build(lvl, name)
                    self._writing = self.path / "index.json"
                    write_json_atomic(self._writing, self.index)
            except OSError as exc:
                self._raise_if_full(exc, self._writing)
                raise
            finally:
                self._discard_tmp()
        return self

    def _raise_if_full(self, exc: OSError, path: Path) -> None:
        """CacheSpaceError (one line naming ``path``, the file being written) when ``exc`` says the cache's
        filesystem is full."""
        if exc.errno in NO_SPACE:
            raise space_error(path, exc.strerror or "filesystem full") from None

    def _real(self, key: str) -> str:
        """'lr/radiance' -> 'lr_x2.5/radiance' in a cache of the level at 2.5: the key under which it is stored."""
        level, _, name = key.partition("/")
        return f"{self._lr_dir}/{name}" if level == "lr" else key

    def _read_checked(self, frame: int, key: str) -> np.ndarray:
        a = self.clip.read(frame, key, exposed=True)  # radiance and emission times the clip's exposure
        where = f"{self.clip.path_of(frame, key)} (frame {frame})"
        name = split_key(key)[1]
        if name == "radiance" and self.nonfinite == "error":
            self._check_radiance(frame, key, a)  # validate's rule and words first
        a = check_finite(a, name, where, self.nonfinite, self.index["sanitized"])
        if name == "radiance" and self.nonfinite == "sanitize":
            a = self._sanitize_negative(frame, key, a)
        return convert_buffer(name, a, self.colour_matrix)

    def _radiance_problem(self, frame: int, key: str, a: np.ndarray) -> str | None:
        """``validate``'s radiance rule (gbuffer_export.validate.values.radiance_problem) on one frame."""
        from gbuffer_export.validate.values import radiance_problem
        lvl = split_key(key)[0]
        extra = {b: self.clip.read(frame, f"{lvl}/{b}") for b in ("flags", "depth") if b in self.clip.buffers}
        return radiance_problem(frame, self._real(key).split("/")[0], a, extra.get("flags"), extra.get("depth"))

    def _check_radiance(self, frame: int, key: str, a: np.ndarray) -> None:
        problem = self._radiance_problem(frame, key, a)
        if problem:
            raise NonFiniteError(f"{self.clip.path_of(frame, key)}: {problem}; fix the render ('blendsr validate' "
                                 "reports the same) or set data.nonfinite = \"sanitize\"")

    def _sanitize_negative(self, frame: int, key: str, a: np.ndarray) -> np.ndarray:
        """data.nonfinite = "sanitize": radiance that validate refuses as negative is clamped to 0 (warned, logged)."""
        problem = self._radiance_problem(frame, key, a)
        if not problem:
            return a
        where = f"{self.clip.path_of(frame, key)} (frame {frame})"
        n = int((a < 0).sum())
        warnings.warn(f"{where}: sanitised {n} negative value(s) in buffer 'radiance' ({problem})", RuntimeWarning,
                      stacklevel=3)
        self.index["sanitized"].append({"where": where, "buffer": "radiance", "count": n, "negative": True})
        return np.maximum(a, 0).astype(a.dtype)

    def _new_array(self, key: str) -> tuple[np.ndarray, Path, Path]:
        lvl, name = key.split("/")
        w, h = self.sizes[lvl]
        real = self._real(key).replace("/", "__")
        final = self.path / f"{real}.npy"
        tmp = self.path / f".{real}.npy.tmp{os.getpid()}"
        self._writing = final
        dtype, shape = storage_dtype(name), (len(self.frames), h, w, channels_of(name))
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)  # a leftover (or a planted link) is never written through
        fd = open_nofollow(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL)
        try:
            with open(fd, "r+b", closefd=False) as fh:
                np.lib.format.write_array_header_1_0(fh, {"descr": np.lib.format.dtype_to_descr(dtype),
                                                          "fortran_order": False, "shape": shape})
                offset = fh.tell()
            reserve(fd, offset + int(np.prod(shape)) * dtype.itemsize, final)  # before a byte is mapped
            arr = np.memmap(tmp, dtype=dtype, mode="r+", offset=offset, shape=shape)
        except BaseException:
            os.close(fd)
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
        os.close(fd)
        self._tmp.add(tmp)
        return arr, tmp, final

    def _discard_tmp(self) -> None:
        """Remove the temporary arrays of a build that failed (no stray files)."""
        for t in self._tmp:
            with contextlib.suppress(OSError):
                t.unlink()
        self._tmp.clear()

    def _commit(self, key: str, arr: np.ndarray, tmp: Path, final: Path) -> None:
        arr.flush()
        del arr
        os.replace(tmp, final)
        self._tmp.discard(tmp)
        self.index["arrays"][self._real(key)] = {"file": final.name, "dtype": storage_dtype(key.split("/")[1]).name}
        self._arrays.pop(key, None)

    def _build(self, lvl: str, name: str) -> None:
        key = f"{lvl}/{name}"
        arr, tmp, final = self._new_array(key)
        refs = {}
        for i, f in enumerate(self.frames):
            a = self._read_checked(f, key)
            if name == "flags":
                arr[i] = a.astype(np.uint32)
            else:
                arr[i] = a
            if key == "lr/depth":
                d = a[..., 0]
                fin = d[np.isfinite(d) & (d > 0)]
                refs[str(f)] = float(np.median(fin)) if fin.size else 1.0
        self._commit(key, arr, tmp, final)
        if key == "lr/depth":
            self.index[self._depth_ref_key] = refs

    def _build_derived(self, lvl: str) -> None:
        have_e = "emission" in self.clip.buffers
        have_f = "flags" in self.clip.buffers
        irr, tmp_i, fin_i = self._new_array(f"{lvl}/irradiance")
        fbu, tmp_f, fin_f = self._new_array(f"{lvl}/fbeta_used")
        for i, f in enumerate(self.frames):
            rad = self._read_checked(f, f"{lvl}/radiance")
            em = self._read_checked(f, f"{lvl}/emission") if have_e else None
            fb = self._read_checked(f, f"{lvl}/fbeta")
            fl = self.clip.read(f, f"{lvl}/flags") if have_f else None
            irr[i], fbu[i] = demodulate(rad, em, fb, fl, self.eps)
        self._commit(f"{lvl}/irradiance", irr, tmp_i, fin_i)
        self._commit(f"{lvl}/fbeta_used", fbu, tmp_f, fin_f)

    # -------------------------------------------------------------------------------------------- read
    def array(self, key: str) -> np.ndarray:
        """Memory-mapped (N, H, W, C) array of a cached key (call ``ensure`` first)."""
        a = self._arrays.get(key)
        if a is None:
            if self._real(key) not in self.index["arrays"]:
                raise ClipError(f"{self.path}: {key!r} is not cached; call ensure([{key!r}])")
            f = self.path / str(self.index["arrays"][self._real(key)]["file"])
            if f.parent != self.path or f.is_symlink():
                raise UnsafePathError(f"{self.path / 'index.json'}: array {f.name!r} is not a plain file of the "
                                      "cache; delete the cache folder")
            a = np.load(f, mmap_mode="r")
            self._arrays[key] = a
        return a

    def depth_ref(self, frame: int) -> float:
        return float(self.index.get(self._depth_ref_key, {}).get(str(frame), 1.0))

    def jitter(self, frame: int) -> np.ndarray:
        """The LR jitter (dx, dy) of a frame, LR pixels (float32 (2,)); see docs/clip-format.md."""
        return lr_jitter(self.clip, frame)

    def read(self, frame: int, key: str) -> np.ndarray:
        """One frame of a cached key as float32 H x W x C (flags uint32)."""
        a = self.array(key)[self.index_of[frame]]
        return np.asarray(a, dtype=np.uint32 if a.dtype == np.uint32 else np.float32)


def lr_jitter(clip: Clip, frame: int) -> np.ndarray:
    """(dx, dy) float32: the sample of LR pixel centre p was taken at p + (dx, dy) (LR pixels, x right, y down)."""
    return np.asarray(clip.camera(frame, "lr")["jitter"], dtype=np.float32)


__all__ = ["DERIVED_FROM", "ClipCache", "lr_jitter", "NonFiniteError", "CacheSpaceError", "default_cache_path",
           "check_finite", "CACHE_VERSION"]
