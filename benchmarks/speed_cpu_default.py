"""Issue 58, the CPU half: a model's 1080p 4x frame on the CPU on today's default path (``fast``), the ``fused``
path and the new default (``graph``, what ``auto`` picks on the CPU), in one process, frames interleaved
(old, fused, new, old, ...), each output checked against the fp32 reference (max |out - ref| / max |ref| within
``fastpath.TOLERANCE``). The machine is shared and busy: each frame is timed by wall clock and by the CPU time of
the process (``time.process_time``: with ``OMP_NUM_THREADS=1`` the frame's own work, whatever else runs), and
the record gives medians and the ratios old / new of both.

Usage: OMP_NUM_THREADS=1 python benchmarks/speed_cpu_default.py [--model fusesr-l] [--size 1920x1080]
       [--frames 5] [-o docs/bench/speed-cpu-default/fusesr-l.json]
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import time

import torch

from training.config import ModelConfig
from training.inference.export import example_inputs
from training.inference.fastpath import TOLERANCE, forward, prepare_inference, prepared_batch
from training.inference.loading import InferenceModel
from training.models import build_model

PATHS = ("fast", "fused", "graph")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--model", default="fusesr-l")
    p.add_argument("--size", default="1920x1080")
    p.add_argument("--frames", type=int, default=5)
    p.add_argument("-o", dest="out")
    a = p.parse_args()
    size = tuple(int(v) for v in a.size.split("x"))
    torch.manual_seed(0)
    base = InferenceModel(build_model(ModelConfig(name=a.model, scale=4), 4).eval(), a.model)
    batch = {k: torch.from_numpy(v) for k, v in example_inputs(base, None, size).items()}
    rows = {}
    with torch.inference_mode():
        want = base.forward(batch).float()
        for path in PATHS:
            m = copy.deepcopy(base)
            t0, c0 = time.perf_counter(), time.process_time()
            prepare_inference(m, "cpu", "none", path=path)
            b = prepared_batch(m, batch)
            got = forward(m, b).float()
            err = float((got - want).abs().max()) / float(want.abs().max())
            rows[path] = {"model": m, "batch": b, "wall": [], "cpu": [], "max_rel_err": err,
                          "tolerance": TOLERANCE["fp32"], "first_call_s": time.perf_counter() - t0,
                          "first_call_cpu_s": time.process_time() - c0}
            print(f"{path}: first call {rows[path]['first_call_s']:.1f} s, error {err:.2e}", flush=True)
        for _ in range(a.frames):
            for path, r in rows.items():
                t0, c0 = time.perf_counter(), time.process_time()
                forward(r["model"], r["batch"])
                r["wall"].append(1000 * (time.perf_counter() - t0))
                r["cpu"].append(1000 * (time.process_time() - c0))
    out = {"model": a.model, "size": list(size), "scale": 4, "batch": 1, "precision": "fp32 (the CPU has no bf16: "
           f"torch.ops.mkldnn._is_mkldnn_bf16_supported() = {torch.ops.mkldnn._is_mkldnn_bf16_supported()})",
           "threads": torch.get_num_threads(), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"),
           "cpu": platform.processor() or platform.machine(), "cpu_capability": torch.backends.cpu.get_cpu_capability(),
           "torch": torch.__version__, "frames": a.frames, "order": "interleaved: " + ", ".join(PATHS) + ", ...",
           "paths": {}}
    for path, r in rows.items():
        out["paths"][path] = {k: r[k] for k in ("wall", "cpu", "max_rel_err", "tolerance", "first_call_s",
                                                "first_call_cpu_s")}
        out["paths"][path].update(wall_median_ms=statistics.median(r["wall"]),
                                  cpu_median_ms=statistics.median(r["cpu"]), ok=r["max_rel_err"] <= r["tolerance"])
    old, new = out["paths"]["fast"], out["paths"]["graph"]
    out["ratio_fast_over_graph"] = {"wall": old["wall_median_ms"] / new["wall_median_ms"],
                                    "cpu": old["cpu_median_ms"] / new["cpu_median_ms"]}
    fused = out["paths"]["fused"]
    out["ratio_fused_over_graph"] = {"wall": fused["wall_median_ms"] / new["wall_median_ms"],
                                     "cpu": fused["cpu_median_ms"] / new["cpu_median_ms"]}
    text = json.dumps(out, indent=1)
    print(text)
    if a.out:
        with open(a.out + ".tmp", "w") as f:
            f.write(text + "\n")
        os.replace(a.out + ".tmp", a.out)


if __name__ == "__main__":
    main()
