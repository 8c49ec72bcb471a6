"""Writing shipped weights (torch layer): the slim float16 checkpoint and its metadata (``training/pretrained.py``
describes the files)."""
from __future__ import annotations

from pathlib import Path

from gbuffer_export.errors import BlendSRError
from training.pretrained import MAX_BYTES


def release(checkpoint: str | Path, out: str | Path, meta: dict) -> dict:
    """Write the slim float16 checkpoint of ``checkpoint`` to ``out`` and ``meta`` (plus sizes and the parameter
    digest) to ``out`` with suffix .json; ValueError when the file would exceed 10 MB."""
    import torch

    from training.checkpoint import inference_weights, load_checkpoint
    from training.trainer import param_digest
    ck = load_checkpoint(checkpoint)
    slim = {"format": ck["format"], "version": ck.get("version", 1), "model_name": ck.get("model_name"),
            "config": ck["config"], "scale": ck["scale"], "step": ck.get("step"),
            "model": {k: (v.half() if v.is_floating_point() else v) for k, v in inference_weights(ck).items()},
            "weights_dtype": "float16"}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    torch.save(slim, tmp)
    size = tmp.stat().st_size
    if size > MAX_BYTES:
        tmp.unlink()
        raise BlendSRError(f"{out}: {size} bytes exceeds the 10 MB limit for shipped weights")
    tmp.replace(out)
    from training.inference import load_model
    model = load_model(str(out), int(ck["scale"]))
    meta = {**meta, "file": out.name, "bytes": size, "step": ck.get("step"),
            "params": sum(p.numel() for p in model.parameters()), "param_digest": param_digest(model)}
    from gbuffer_export.clip import write_json_atomic
    write_json_atomic(out.with_suffix(".json"), meta)
    return meta
