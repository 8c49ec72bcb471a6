"""Checkpoint files: atomic writing, and loading that never runs code from the file.

A checkpoint is a ``torch.save`` zip of one dict (see docs/training.md, "Checkpoint format"). ``torch.load`` is a
pickle reader; with ``weights_only=False`` a crafted file runs arbitrary code as it is opened. ``load_checkpoint``
always reads with ``weights_only=True``: torch's restricted unpickler rebuilds only tensors, dicts, lists, tuples,
strings, numbers, booleans and None, plus the few numpy types in ``ALLOWED_GLOBALS`` (the numpy RNG state that
checkpoints of format version 1 hold). Anything else (``os.system``, ``builtins.eval``, a class from some module)
is refused with one line naming the file and the global it asked for, before any of it is called.

Version 2 checkpoints hold only plain types (the numpy RNG state as a dict of lists, ``numpy_rng_state``); version 1
checkpoints (numpy arrays in the RNG state) still load through the allow-list.

Shipped weights (``training/weights/*.safetensors``, written by ``training.release``) are no pickle at all: a
safetensors file holds only tensors and a JSON header, so reading one cannot execute code by construction.
``load_weights_file`` checks its sha256 against the ``sha256`` of the JSON beside it before reading it.
"""
from __future__ import annotations

import hashlib
import json
import os
import pickle
import zipfile
from pathlib import Path

import numpy as np
import torch

from gbuffer_export.errors import BlendSRError

CHECKPOINT_FORMAT = "blendsr.checkpoint"
CHECKPOINT_VERSION = 2
WEIGHTS_FORMAT = "blendsr.weights"   # the header of a shipped .safetensors file (key ``WEIGHTS_HEADER``)
WEIGHTS_HEADER = "blendsr"


def _numpy_globals() -> list:
    """The numpy callables a version-1 checkpoint's RNG state needs (an ndarray of uint32 and its dtype)."""
    try:
        from numpy.core.multiarray import _reconstruct
    except ImportError:  # numpy >= 2 moved it
        from numpy._core.multiarray import _reconstruct
    out = [_reconstruct, np.ndarray, np.dtype]
    dtypes = getattr(np, "dtypes", None)
    if dtypes is not None:
        out += [getattr(dtypes, n) for n in ("UInt32DType", "Float64DType", "Int64DType") if hasattr(dtypes, n)]
    return out


#: Everything beyond torch's own weights-only types that a BlendSR checkpoint may contain.
ALLOWED_GLOBALS = _numpy_globals()


class CheckpointError(BlendSRError):
    """A file is not a loadable BlendSR checkpoint (the message names it and says why, on one line)."""


def numpy_rng_state() -> dict:
    """The global numpy RNG state as plain types (no numpy objects in the checkpoint)."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    return {"bit_generator": str(name), "keys": [int(k) for k in keys], "pos": int(pos),
            "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}


def restore_numpy_rng(state) -> None:
    """Inverse of ``numpy_rng_state``; also takes the tuple ``np.random.get_state()`` (version-1 checkpoints)."""
    if isinstance(state, dict):
        state = (state["bit_generator"], np.asarray(state["keys"], dtype=np.uint32), state["pos"],
                 state["has_gauss"], state["cached_gaussian"])
    np.random.set_state(state)


def inference_weights(ck: dict) -> dict:
    """The weights a checkpoint is used with: its moving average (``ema_model``, written when the run had
    ``optim.ema_decay`` > 0) when it holds one, else the trained weights (``model``)."""
    return ck.get("ema_model") or ck["model"]


def save_checkpoint(path: Path, state: dict) -> None:
    """Write ``state`` to ``path`` atomically (temporary file in the same folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        try:
            torch.save(state, tmp)
        except RuntimeError as exc:  # torch reports a failed write as "unexpected pos", not as the OSError it was
            full = _write_fault(tmp, path)
            if full is not None:
                raise full from exc
            raise
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    remove_stale_temporaries(path.parent)


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Remove ``.NAME.pt.tmpPID`` files of processes that are gone (a run killed while saving); returns them."""
    gone = []
    for f in Path(folder).glob(".*.tmp*"):
        pid = f.name.rsplit(".tmp", 1)[-1]
        if not pid.isdigit() or int(pid) == os.getpid() or not f.is_file():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            f.unlink(missing_ok=True)
            gone.append(f)
        except PermissionError:
            pass
    return gone


def _write_fault(tmp: Path, path: Path) -> OSError | None:
    """The filesystem fault behind a failed torch.save into ``tmp``, naming the checkpoint ``path`` being written:
    ENOSPC when the folder's disk is (nearly) full, EROFS/EACCES when it cannot be written; None when neither
    explains it."""
    import errno
    import shutil
    folder = tmp.parent
    try:
        written = tmp.stat().st_size if tmp.exists() else 0
        free = shutil.disk_usage(folder).free
    except OSError as exc:
        return exc
    if free < max(1 << 20, written // 8):
        return OSError(errno.ENOSPC, f"No space left on device ({free} bytes free)", str(path))
    if not os.access(folder, os.W_OK):
        return OSError(errno.EACCES, "Permission denied", str(path))
    return None


def _unsafe_globals(path: Path) -> list[str]:
    try:
        return list(torch.serialization.get_unsafe_globals_in_checkpoint(str(path)))
    except Exception:
        return []


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Read a BlendSR checkpoint (a path, or ``pretrained:NAME`` for shipped weights) without executing anything
    from it; CheckpointError (one line) otherwise."""
    from training.pretrained import resolve
    path = Path(resolve(path))
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    if path.suffix == ".safetensors":
        return load_weights_file(path)
    if not zipfile.is_zipfile(path):
        raise CheckpointError(f"{path}: not a BlendSR checkpoint (not a torch.save zip archive)")
    try:
        with torch.serialization.safe_globals(ALLOWED_GLOBALS):
            ck = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        bad = [g for g in _unsafe_globals(path)
               if g not in {f"{f.__module__}.{f.__qualname__}" for f in ALLOWED_GLOBALS}]
        what = ", ".join(bad[:3]) if bad else "an object outside the allowed types"
        raise CheckpointError(f"{path}: refused: the file asks to build {what}, which a BlendSR checkpoint never "
                              "holds (it may run code; checkpoints load with torch weights_only=True)") from None
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path}: not a readable checkpoint ({first})") from None
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: not a BlendSR checkpoint (no format = {CHECKPOINT_FORMAT!r})")
    return ck


def file_sha256(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def recorded_sha256(path: Path) -> str:
    """The ``sha256`` that the JSON beside the weights file ``path`` records; CheckpointError (one line) without."""
    meta_path = path.with_suffix(".json")
    try:
        meta = json.loads(meta_path.read_text())
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no {meta_path.name} beside it to check it against (training.release writes "
                              "the weights and their JSON together)") from None
    except (OSError, ValueError) as exc:
        raise CheckpointError(f"{meta_path}: unreadable JSON ({exc})") from None
    sha = meta.get("sha256") if isinstance(meta, dict) else None
    if not isinstance(sha, str) or len(sha) != 64:
        raise CheckpointError(f"{meta_path}: no 'sha256' of {path.name} (64 hex digits)")
    return sha


def load_weights_file(path: str | os.PathLike, sha256: str | None = None) -> dict:
    """Read shipped weights (a .safetensors file of ``training.release``) into the dict ``load_checkpoint`` returns
    (``format``, ``version``, ``model_name``, ``config``, ``scale``, ``step``, ``weights_dtype`` and ``model``: name ->
    tensor). The file's sha256 must equal ``sha256`` (default: the one its JSON records); CheckpointError otherwise."""
    from safetensors import safe_open
    path = Path(path)
    want = sha256 or recorded_sha256(path)
    got = file_sha256(path)
    if got != want:
        raise CheckpointError(f"{path}: sha256 {got[:16]}... differs from the recorded {want[:16]}... (the file "
                              "was altered or truncated; reinstall BlendSR or rerun the release)")
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            header = (f.metadata() or {}).get(WEIGHTS_HEADER)
            tensors = {k: f.get_tensor(k) for k in f.keys()}
        header = json.loads(header) if header else None
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path}: not a readable safetensors file ({first})") from None
    if not isinstance(header, dict) or header.get("format") != WEIGHTS_FORMAT:
        raise CheckpointError(f"{path}: not BlendSR weights (no {WEIGHTS_HEADER!r} header with format = "
                              f"{WEIGHTS_FORMAT!r})")
    missing = [k for k in ("model_name", "config", "scale") if k not in header]
    if missing:
        raise CheckpointError(f"{path}: its header lacks {', '.join(missing)}")
    return {**header, "format": CHECKPOINT_FORMAT, "model": tensors}


def check_weights_fit(path, model: torch.nn.Module, weights: dict, name: str) -> None:
    """CheckpointError (one line naming ``path``) unless ``weights`` has exactly the names and shapes of ``model``'s
    state dict (``name``: the model's, for the message): nothing missing, nothing unexpected."""
    own = model.state_dict()
    missing = [k for k in own if k not in weights]
    unexpected = [k for k in weights if k not in own]
    shapes = [k for k in own if k in weights and tuple(own[k].shape) != tuple(weights[k].shape)]
    for what, keys in (("missing", missing), ("unexpected", unexpected), ("wrongly shaped", shapes)):
        if keys:
            more = f" and {len(keys) - 3} more" if len(keys) > 3 else ""
            raise CheckpointError(f"{path}: weights do not fit model {name}: {what} {', '.join(keys[:3])}{more}")
