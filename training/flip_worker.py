"""HDR-FLIP in a separate process (numpy + flip-evaluator only, no torch).

NVIDIA's flip-evaluator calls exit() on some inputs (an all-black HDR reference: its exposure range collapses),
which would end the whole evaluation. ``FlipRunner`` computes FLIP in a worker process; a frame whose worker died
gets ``None`` and a fresh worker takes the next frame. An all-black reference is answered without calling FLIP.
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp

import numpy as np


def _flip(reference: np.ndarray, test: np.ndarray) -> float:
    import flip_evaluator
    _, mean, _ = flip_evaluator.evaluate(reference, test, "HDR", applyMagma=False)
    return float(mean)


class FlipRunner:
    """``runner(reference, test)`` -> mean HDR-FLIP (float) or None when FLIP could not be computed.
    Inputs: H x W x 3 linear radiance (negative values are clamped to 0, as FLIP requires)."""

    def __init__(self):
        self._pool = None
        self.failures: list[str] = []

    def _executor(self):
        if self._pool is None:
            self._pool = cf.ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn"))
        return self._pool

    def __call__(self, reference: np.ndarray, test: np.ndarray) -> float | None:
        ref = np.ascontiguousarray(np.clip(np.nan_to_num(reference, nan=0.0, posinf=0.0), 0, None), np.float32)
        tst = np.ascontiguousarray(np.clip(np.nan_to_num(test, nan=0.0, posinf=0.0), 0, None), np.float32)
        if ref.ndim != 3 or ref.shape[2] != 3:
            raise ValueError(f"FLIP needs H x W x 3 images, got {ref.shape}")
        if not np.any(ref > 0):
            self.failures.append("all-black reference")
            return None
        try:
            return self._executor().submit(_flip, ref, tst).result()
        except cf.process.BrokenProcessPool:
            self.failures.append("flip-evaluator exited")
            self._pool = None
            return None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
