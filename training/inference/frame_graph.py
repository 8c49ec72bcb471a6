"""One CUDA graph per frame (torch): ``FrameGraph`` replays a model's whole frame, HR stage included, as one CUDA
graph; ``time_replays`` times N replays between two CUDA events (``training.inference.fastpath`` path ``graph``;
``blendsr bench models --path graph``; ``benchmarks/gpu/check.sh`` with ``CHECK=graph``).

``FrameGraph(fn)`` is called like ``fn`` (tensors, or lists/tuples/dicts of them, and None). The first call with a
new input structure (shapes, dtypes, strides, which values are None) copies the inputs into static buffers, runs
``fn`` twice on a side stream (cuDNN's algorithm search, Triton's autotuning and inductor's compilation happen
there, outside the capture), then captures one call into a ``torch.cuda.CUDAGraph``; every later call copies its
inputs into those buffers, replays the graph and returns a copy of its outputs (so a recurrent model's state, a
graph output, can be the next frame's input: it is copied into the input buffers before the replay). A recurrent
model's first frame (state None) and its later frames (state given) are two structures, hence two graphs.
A CPU tensor among the inputs is a host value the function reads on the host (``batch["scale"]``, which
``ModelBase.batch_scale`` turns into a float: a device read is not allowed while a graph is captured): it is part of
the structure by value (at most 64 elements), passed as it is, and baked into the graph.
Without CUDA (on the CPU) it calls ``fn``: the code paths stay testable there.
"""
from __future__ import annotations

import statistics
from collections.abc import Callable

import torch
from torch.utils._pytree import tree_flatten, tree_unflatten


HOST_VALUES_MAX = 64  # elements of a CPU tensor input, keyed by value (a host value, module doc)


def _leaf_key(t) -> tuple:
    if not torch.is_tensor(t):
        return (type(t), t)
    if t.is_cuda:
        return (tuple(t.shape), t.dtype, t.stride(), t.device)
    if t.numel() > HOST_VALUES_MAX:
        raise ValueError(f"FrameGraph: a CPU tensor input of {t.numel()} elements: only host values of at most "
                         f"{HOST_VALUES_MAX} (such as batch['scale']) may stay on the CPU; move the rest to CUDA")
    return (tuple(t.shape), t.dtype, "host", tuple(t.reshape(-1).tolist()))


def _signature(flat: list) -> tuple:
    return tuple(_leaf_key(t) for t in flat)


class FrameGraph:
    """``fn`` replayed as one CUDA graph per input structure (module doc). ``baked``: a function of no argument whose
    value is part of every graph's key, for what ``fn`` reads besides its inputs and a capture bakes in (a model's
    pixel filter, which ``follow_reference_filter`` sets per clip). More than ``max_graphs`` structures is refused:
    a host value that changes every frame would otherwise capture a graph per frame."""

    def __init__(self, fn: Callable, warmup: int = 2, baked: Callable[[], object] = lambda: None,
                 max_graphs: int = 32):
        self.fn, self.warmup, self.baked, self.max_graphs = fn, warmup, baked, max_graphs
        self.graphs: dict = {}  # key -> (graph, static inputs (flat), static outputs, output spec)

    def __call__(self, *args):
        flat, spec = tree_flatten(args)
        cuda = [t for t in flat if torch.is_tensor(t) and t.is_cuda]
        if not cuda:
            return self.fn(*args)
        key = (spec, _signature(flat), self.baked())
        if key not in self.graphs:
            if len(self.graphs) >= self.max_graphs:
                raise RuntimeError(f"FrameGraph: more than {self.max_graphs} input structures (shapes, host values, "
                                   f"baked state) captured; a host value that changes every frame? Keep it on CUDA")
            self.graphs[key] = self._capture(flat, spec)
        g, static, out, out_spec = self.graphs[key]
        for s, t in zip(static, flat):
            if torch.is_tensor(s) and s.is_cuda:
                s.copy_(t)
        g.replay()
        return tree_unflatten([o.clone() if torch.is_tensor(o) else o for o in out], out_spec)

    def _capture(self, flat: list, spec):
        static = [t.clone() if torch.is_tensor(t) else t for t in flat]
        args = tree_unflatten(static, spec)
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(self.warmup):
                self.fn(*args)
        torch.cuda.current_stream().wait_stream(side)
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g):
            result = self.fn(*args)
        out, out_spec = tree_flatten(result)
        return g, static, out, out_spec

    def replay_last(self) -> Callable[[], None]:
        """The replay of the most recently captured graph, alone (no input copies): what ``time_replays`` times."""
        if not self.graphs:
            raise RuntimeError("FrameGraph: nothing captured yet (call it once on CUDA tensors)")
        return next(reversed(self.graphs.values()))[0].replay

    def __len__(self) -> int:
        return len(self.graphs)


class CudaClock:
    """``start()`` then ``stop() -> ms``: two CUDA events on the current stream, the elapsed time between them after
    the second completes (the kernels' time on the device, not the host's)."""

    def start(self) -> None:
        self.a, self.b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        self.a.record()

    def stop(self) -> float:
        self.b.record()
        self.b.synchronize()
        return float(self.a.elapsed_time(self.b))


def time_replays(replay: Callable[[], None], n: int = 100, rounds: int = 5, clock=None, warmup: int = 3) -> dict:
    """Time ``n`` back-to-back calls of ``replay`` between the two marks of ``clock`` (``CudaClock``; a fake one in
    tests), ``rounds`` times. Returns {ms (the median over the rounds of the per-frame time), ms_min, ms_max,
    spread ((max - min) / median), rounds (the per-frame time of each), n}. ``n`` below 100 is refused: with fewer
    replays the events' resolution (about 0.5 us) and launch of the first replay weigh on a 0.05 ms frame."""
    if n < 100 or rounds < 1:
        raise ValueError(f"time_replays: n={n}, rounds={rounds}: at least 100 replays and 1 round")
    clock = clock or CudaClock()
    for _ in range(warmup):
        replay()
    per_frame = []
    for _ in range(rounds):
        clock.start()
        for _ in range(n):
            replay()
        per_frame.append(clock.stop() / n)
    med = statistics.median(per_frame)
    return {"ms": med, "ms_min": min(per_frame), "ms_max": max(per_frame),
            "spread": (max(per_frame) - min(per_frame)) / med if med > 0 else 0.0, "rounds": per_frame, "n": n}


__all__ = ["FrameGraph", "CudaClock", "time_replays"]
