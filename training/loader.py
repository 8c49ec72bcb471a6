"""Multi-process batch loading for training (torch): ``WorkerLoader``, the ``data.workers > 0`` replacement of
``data.Prefetcher``.

Batch k is ``TrainSampler.batch(k)``, a pure function of (seed, rank, k), so N worker processes can prepare steps
k, k+1, ... in parallel and ``torch.utils.data.DataLoader`` hands them back in order: a run with workers gives the
same batches as one without. Workers are forked: the clip caches' memory maps are shared with the parent (the page
cache holds one copy), nothing is pickled per batch but the result. With ``pin`` (``data.pin_memory``, CUDA only)
batches arrive in page-locked memory, so the copy to the GPU is asynchronous (``non_blocking``).

Workers end with their trainer: a killed trainer (kill -9) leaves no orphan holding the clip caches or ``RUN/.lock``
(``gbuffer_export.locks.die_with_parent``: the kernel's parent-death signal on Linux, a watch thread elsewhere).
"""
from __future__ import annotations

import functools
import multiprocessing
import os

import torch
from torch.utils.data import DataLoader, Dataset

from gbuffer_export.locks import die_with_parent


class _Steps(Dataset):
    def __init__(self, sampler, start: int, stop: int):
        self.sampler = sampler
        self.start = int(start)
        self.stop = int(stop)

    def __len__(self) -> int:
        return max(self.stop - self.start, 0)

    def __getitem__(self, i: int):
        step = self.start + int(i)
        batch, samples = self.sampler.batch(step)
        return step, {k: torch.from_numpy(v) for k, v in batch.items()}, samples


def _no_collate(item):
    return item


def _init_worker(parent: int, worker_id: int) -> None:
    die_with_parent(parent)


class WorkerLoader:
    """``get(step)`` -> (batch of CPU tensors, samples) for consecutive steps from ``start_step`` to ``stop_step``,
    prepared by ``workers`` processes, ``prefetch`` batches ahead each; ``close()`` stops them."""

    def __init__(self, sampler, start_step: int, stop_step: int, workers: int, prefetch: int = 2,
                 pin: bool = False):
        if workers < 1:
            raise ValueError("WorkerLoader needs workers >= 1 (use data.Prefetcher otherwise)")
        ctx = multiprocessing.get_context("fork") if "fork" in multiprocessing.get_all_start_methods() else None
        self.next_step = int(start_step)
        self.loader = DataLoader(_Steps(sampler, start_step, stop_step), batch_size=None, shuffle=False,
                                 num_workers=workers, collate_fn=_no_collate, pin_memory=bool(pin),
                                 prefetch_factor=max(prefetch, 1), persistent_workers=False,
                                 multiprocessing_context=ctx,
                                 worker_init_fn=functools.partial(_init_worker, os.getpid()))
        self.it = iter(self.loader)

    def get(self, step: int):
        got, batch, samples = next(self.it)
        if got != step:
            raise RuntimeError(f"worker loader out of order ({got} != {step})")
        return batch, samples

    def close(self) -> None:
        it, self.it = self.it, None
        if it is not None and hasattr(it, "_shutdown_workers"):
            it._shutdown_workers()


__all__ = ["WorkerLoader"]
