"""Where the fused path's error comes from on a GPU: each guided model's fused path with the HR stage forced to
``compiled`` and to ``triton`` (fp32 and bf16, eager), against the CPU fp32 eager reference; max relative error.
Usage (repository root, on the device): python3 benchmarks/gpu/diag_fused.py"""
import copy
import sys
from pathlib import Path

sys.path[0] = str(Path(__file__).resolve().parents[2])  # not this folder: its profile.py would shadow the stdlib's
import torch  # noqa: E402

from tests.train.hr_stage_cases import _batch, _rel  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.inference.fastpath import forward, prepare_inference  # noqa: E402
from training.models import build_model  # noqa: E402

dev = torch.device("cuda")
for name, opts in (("demod-jbu", {}), ("fusesr-fast", {}), ("fusesr-l", {}),
                   ("fusesr-l", {"residual_clamp": "lr-range"})):
    ref = build_model(ModelConfig.of(name, **opts), 4).eval()
    name = name + ("+clamp" if opts else "")
    cpu_batch = _batch(ref, size=(128, 64))
    with torch.inference_mode():
        want = ref(cpu_batch)
    batch = {k: v.to(dev) for k, v in cpu_batch.items()}
    for precision in ("none", "bf16"):
        plain = prepare_inference(copy.deepcopy(ref), dev, precision, compile=False, path="fast")
        with torch.inference_mode():
            print(name, precision, "fast", f"{_rel(forward(plain, batch).cpu(), want):.2e}", flush=True)
        for impl in ("compiled", "triton"):
            m = prepare_inference(copy.deepcopy(ref), dev, precision, compile=False, path="fused")
            m.module.hr_impl = impl
            try:
                with torch.inference_mode():
                    got = forward(m, batch).cpu()
                print(name, precision, impl, f"{_rel(got, want):.2e}", flush=True)
            except Exception as exc:  # noqa: BLE001
                print(name, precision, impl, "failed:", type(exc).__name__, str(exc)[:200], flush=True)
