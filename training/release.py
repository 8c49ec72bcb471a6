"""Writing shipped weights (torch layer): the float16 weights as a safetensors file and its metadata JSON
(``training/pretrained.py`` describes the files; ``training.checkpoint.load_weights_file`` reads them)."""
from __future__ import annotations

import json
import os
from pathlib import Path

from gbuffer_export.errors import BlendSRError
from training.pretrained import MAX_BYTES


def write_weights_file(out: Path, ck: dict) -> None:
    """Write the model weights of the checkpoint dict ``ck`` (its moving average when it has one) in float16 to
    ``out`` as safetensors, with the format, configuration, scale and step as its JSON header; atomic; BlendSRError
    when the file would exceed 10 MB."""
    from safetensors.torch import save_file

    from training.checkpoint import WEIGHTS_FORMAT, WEIGHTS_HEADER, inference_weights
    header = {"format": WEIGHTS_FORMAT, "version": 1, "model_name": ck.get("model_name"), "config": ck["config"],
              "scale": ck["scale"], "step": ck.get("step"), "weights_dtype": "float16"}
    tensors = {k: (v.half() if v.is_floating_point() else v).detach().clone().contiguous()
               for k, v in inference_weights(ck).items()}  # clone: safetensors refuses shared storage
    tmp = out.with_name(f".{out.name}.tmp{os.getpid()}")
    try:
        save_file(tensors, tmp, metadata={WEIGHTS_HEADER: json.dumps(header)})
        size = tmp.stat().st_size
        if size > MAX_BYTES:
            raise BlendSRError(f"{out}: {size} bytes exceeds the 10 MB limit for shipped weights")
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)


def release(checkpoint: str | Path | dict, out: str | Path, meta: dict) -> dict:
    """Write the float16 weights of ``checkpoint`` (a checkpoint of ``blendsr train``, or earlier shipped weights, or
    such a checkpoint already loaded by ``load_checkpoint``)
    to ``out`` (a .safetensors file) and ``meta`` plus its size, sha256, step, parameter count and parameter digest
    to ``out`` with suffix .json; returns that metadata. BlendSRError for another suffix or a file over 10 MB."""
    from gbuffer_export.clip import write_json_atomic
    from training.checkpoint import file_sha256, load_checkpoint
    from training.inference.loading import load_model
    from training.trainer import param_digest
    out = Path(out)
    if out.suffix != ".safetensors":
        raise BlendSRError(f"{out}: shipped weights are written as .safetensors (a file that cannot run code)")
    ck = checkpoint if isinstance(checkpoint, dict) else load_checkpoint(checkpoint)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_weights_file(out, ck)
    meta = {**meta, "file": out.name, "bytes": out.stat().st_size, "sha256": file_sha256(out),
            "step": ck.get("step")}
    write_json_atomic(out.with_suffix(".json"), meta)  # the loader checks the sha256 recorded here
    model = load_model(str(out), int(ck["scale"]))
    meta = {**meta, "params": model.n_params, "param_digest": param_digest(model.module)}
    write_json_atomic(out.with_suffix(".json"), meta)
    return meta
