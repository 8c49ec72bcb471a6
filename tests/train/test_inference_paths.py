"""Issue 58: the inference path of the commands and the add-on (``--path``, default ``auto``:
``training.inference.fastpath.AutoPath``), the record of the path that ran, one CUDA graph per frame
(``training.inference.frame_graph.FrameGraph``; CUDA only, its CPU pass-through here) and the replay timer with a fake clock."""
from __future__ import annotations

import json
import logging

import pytest

torch = pytest.importorskip("torch")

from gbuffer_export.errors import BlendSRError  # noqa: E402
from training.inference import fastpath  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.inference.export import example_inputs  # noqa: E402
from training.inference.frame_graph import FrameGraph, time_replays  # noqa: E402
from training.inference.loading import InferenceModel  # noqa: E402
from training.models import build_model  # noqa: E402

from tests.conftest import run_cli  # noqa: E402


def _model(name: str = "demod-bilinear", seed: int = 0) -> tuple[InferenceModel, dict]:
    torch.manual_seed(seed)
    m = InferenceModel(build_model(ModelConfig(name=name, scale=4), 4).eval(), name)
    batch = {k: torch.from_numpy(v) for k, v in example_inputs(m, None, (32, 16)).items()}
    return m, batch


def _reference(name: str, batch: dict) -> torch.Tensor:
    m, _ = _model(name)
    with torch.inference_mode():
        return m.forward(batch)


class FakeClock:
    """start()/stop() -> ms over a counter that ``tick`` advances: each replay costs ``costs[i]`` ms in round i."""

    def __init__(self, costs):
        self.costs, self.round, self.now = list(costs), -1, 0.0

    def tick(self):
        self.now += self.costs[max(self.round, 0)]

    def start(self):
        self.round += 1
        self.t0 = self.now

    def stop(self):
        return self.now - self.t0


def test_time_replays_median_and_spread_of_the_rounds():
    clock = FakeClock([0.5, 0.3, 0.4, 0.4, 0.6])
    r = time_replays(clock.tick, n=100, rounds=5, clock=clock, warmup=0)
    assert r["rounds"] == pytest.approx([0.5, 0.3, 0.4, 0.4, 0.6])
    assert r["ms"] == pytest.approx(0.4) and r["ms_min"] == pytest.approx(0.3) and r["ms_max"] == pytest.approx(0.6)
    assert r["spread"] == pytest.approx(0.3 / 0.4) and r["n"] == 100
    with pytest.raises(ValueError, match="at least 100"):
        time_replays(clock.tick, n=10, clock=clock)


def test_frame_graph_calls_the_function_without_cuda():
    calls = []
    g = FrameGraph(lambda b, s: calls.append(1) or (b["x"] * 2, s))
    out, state = g({"x": torch.ones(2)}, None)
    assert calls == [1] and torch.equal(out, torch.full((2,), 2.0)) and state is None and len(g) == 0


def test_frame_graph_keys_host_values_by_value():
    """A CPU tensor among a graph's inputs (``batch['scale']``, read on the host) is part of its structure by value:
    scale 2 and scale 4 of the same LR size are two graphs; a large CPU tensor is refused."""
    from training.inference.frame_graph import _signature
    from training.inference.model import _device, host_scale
    x = torch.ones(1, 3, 4, 4)
    a, b = _signature([x, torch.tensor([2.0])]), _signature([x, torch.tensor([4.0])])
    assert a != b and a == _signature([x, torch.tensor([2.0])])
    with pytest.raises(ValueError, match="65 elements"):
        _signature([torch.ones(65)])
    batch = {"lr/radiance": x, "scale": torch.tensor([4.0])}
    assert host_scale(batch) is batch  # on the CPU nothing moves
    assert _device({"state": None, "x": x}) == torch.device("cpu") and _device({}) == torch.device("cpu")


def test_run_and_step_keep_the_scale_on_the_host(monkeypatch):
    """``InferenceModel.run`` and ``.step`` put every input on the device but ``scale``, which models read on the host
    (so the graph path needs no copy back, which would wait for the queued work). The device here is ``meta``."""
    import numpy as np
    m, batch = _model("bilinear")
    with monkeypatch.context() as mp:
        mp.setattr(InferenceModel, "device", property(lambda self: torch.device("meta")))
        moved = m._on_device({"scale": np.ones(1, np.float32), "lr/radiance": np.ones((1, 1, 3, 4, 4), np.float32)})
    assert moved["scale"].device.type == "cpu" and moved["lr/radiance"].device.type == "meta"
    sr, _ = m.run({k: v.numpy() for k, v in batch.items()})  # bilinear reads the host scale
    assert sr.shape[:2] == tuple(4 * n for n in batch["lr/radiance"].shape[-2:])


def test_frame_graph_keys_what_a_capture_bakes_in_and_bounds_the_graphs(monkeypatch):
    """The pixel filter a model follows per clip (``follow_reference_filter``) is baked into a capture: it is part of
    the key (``baked``), so a later clip with another filter captures its own graph; more structures than
    ``max_graphs`` is refused. The capture itself is replaced here (no CUDA)."""
    state = {"taps": (0.25, 0.5, 0.25)}
    g = FrameGraph(lambda x: x * 2, baked=lambda: state["taps"], max_graphs=2)
    captured = []

    def fake_capture(flat, spec):
        captured.append(flat[0].shape)
        return _Replay(), [flat[0]], [flat[0] * 2], tree_spec
    from torch.utils._pytree import tree_flatten
    tree_spec = tree_flatten(torch.ones(1))[1]
    monkeypatch.setattr(g, "_capture", fake_capture)
    x = torch.Tensor._make_subclass(_CudaLike, torch.ones(2))
    g(x)
    g(x)
    assert len(g) == 1
    state["taps"] = (1.0,)
    g(x)
    assert len(g) == 2 and len(captured) == 2
    state["taps"] = (0.5, 0.5)
    with pytest.raises(RuntimeError, match="more than 2 input structures"):
        g(x)


class _Replay:
    def replay(self):
        pass


class _CudaLike(torch.Tensor):
    """A CPU tensor that says it is on CUDA, so that FrameGraph takes its capture path (replaced in the test)."""

    @property
    def is_cuda(self):
        return True


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
@pytest.mark.parametrize("name", ["bilinear", "fourier-sr"])
def test_cuda_graph_path_reads_the_scale_on_the_host(name):
    """The graph path of a model that reads ``batch['scale']`` (``ModelBase.batch_scale``: a host read, not allowed
    while a graph is captured; found by the first H200 run of CHECK=graph) matches its eager output on two different
    frames (a stale replay would repeat the first), and bilinear at scales 2 and 4 (two graphs)."""
    import copy
    ref, _ = _model(name)
    eager = fastpath.prepare_inference(copy.deepcopy(ref), "cuda", path="fast")
    graph = fastpath.prepare_inference(ref, "cuda", path="graph")
    scales = (2.0, 4.0) if name == "bilinear" else (4.0,)
    for seed, scale in [(s, sc) for sc in scales for s in (0, 1)]:
        cpu_batch = {k: torch.from_numpy(v) for k, v in example_inputs(ref, None, (32, 16), seed=seed).items()}
        batch = {k: v.cuda() for k, v in cpu_batch.items()}
        batch["scale"] = torch.full_like(batch["scale"], scale)
        with torch.inference_mode():
            want = fastpath.forward(eager, batch)
            got = fastpath.forward(graph, batch)
        assert got.shape[-1] == int(cpu_batch["lr/radiance"].shape[-1] * scale)
        assert torch.allclose(got.float(), want.float(), atol=1e-4, rtol=1e-3), (seed, scale)
    assert len(graph.settings["graphs"]["forward"]) == len(scales)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
def test_cuda_frame_graph_replays_a_recurrent_step():
    w = torch.randn(3, 3, device="cuda")

    def step(x, state):
        new = x @ w if state is None else x @ w + state
        return new.sum(), new
    g = FrameGraph(step)
    xs = [torch.randn(4, 3, device="cuda") for _ in range(4)]
    state, want = None, None
    for x in xs:
        got, state = g(x, state)
        want_state = x @ w if want is None else x @ w + want
        want = want_state
        assert torch.allclose(state, want, atol=1e-5)
    assert len(g) == 2  # the first frame (no state) and the following ones


RECURRENT = ("rdg", "rdg-s", "nsrd", "nsrr-fec", "fourier-sr")


def test_recurrent_list_is_every_recurrent_model():
    """The CUDA test below covers every model with a state (``recurrent``), by the classes themselves."""
    import importlib
    from training.models import MODELS
    got = {n for n, info in MODELS.items() if getattr(getattr(importlib.import_module(info.module), info.cls),
                                                       "recurrent", False)}
    assert got == set(RECURRENT)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
@pytest.mark.parametrize("name", RECURRENT)
def test_cuda_graph_path_steps_a_recurrent_model(name, monkeypatch):
    """``InferenceModel.step`` on the graph path (one capture for a clip's first frame, one for the frames with a
    state) matches the same prepared model run eagerly (``frame_graph`` off: only the capture differs) over four
    frames with different content, output and carried state alike; a new clip starts from no state. TF32 is off
    so that the two agree to float rounding."""
    import copy
    from torch.utils._pytree import tree_flatten
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_tf32", False)
    ref, _ = _model(name)
    eager = fastpath.prepare_inference(copy.deepcopy(ref), "cuda", path="graph")
    eager.settings["frame_graph"] = False
    graph = fastpath.prepare_inference(ref, "cuda", path="graph")
    assert graph.settings["frame_graph"]
    for seed, at in enumerate([("a", 0), ("a", 1), ("a", 2), ("b", 0)]):
        inputs = example_inputs(ref, None, (32, 16), seed=seed)
        with torch.inference_mode():
            want, _ = eager.step(inputs, at=at)
            got, _ = graph.step(inputs, at=at)
        tol = 1e-4 * max(float(abs(want).max()), 1e-6)
        assert got.shape == want.shape and abs(got - want).max() <= tol, (name, at)
        states = [tree_flatten(m.state.state)[0] for m in (eager, graph)]
        assert len(states[0]) == len(states[1]) > 0
        for a, b in zip(*states):
            if torch.is_tensor(a):
                assert torch.allclose(b.float(), a.float(), rtol=1e-4, atol=1e-4 * float(a.abs().max()) + 1e-7), at
    assert len(graph.settings["graphs"]["step"]) == 2


def test_path_choices_and_default(monkeypatch):
    monkeypatch.delenv(fastpath.PATH_ENV, raising=False)
    assert fastpath.default_path() == "auto"
    monkeypatch.setenv(fastpath.PATH_ENV, "fused")
    assert fastpath.default_path() == "fused"
    monkeypatch.setenv(fastpath.PATH_ENV, "fastest")
    with pytest.raises(BlendSRError, match="BLENDSR_INFERENCE_PATH='fastest'"):
        fastpath.default_path()
    with pytest.raises(BlendSRError, match="inference path 'quick'"):
        fastpath.prepare_inference(_model()[0], path="quick")


def test_reference_path_leaves_the_model_as_built():
    m, batch = _model("demod-jbu")
    fastpath.prepare_inference(m, "cpu", path="reference")
    assert fastpath.path_record(m)["path"] == "reference" and not m.module.fast_ops and m.module.hr_impl is None
    with torch.inference_mode():
        assert torch.equal(m.forward(batch), _reference("demod-jbu", batch))


def _break_graph(monkeypatch, how: str):
    """The graph path's compiled module replaced: 'raise' (a CPU without a C++ compiler) or 'wrong' output."""
    def fake(model, dev, compile, path):
        if path != "graph":
            return None
        if how == "raise":
            def fail(batch):
                raise RuntimeError("no C++ compiler found\nmore lines")
            return fail
        return lambda batch: model(batch) * 1.01
    monkeypatch.setattr(fastpath, "_compiled", fake)


@pytest.mark.heavy
@pytest.mark.parametrize("how", ["raise", "wrong"])
def test_auto_falls_back_to_the_next_path_that_passes(monkeypatch, caplog, how):
    _break_graph(monkeypatch, how)
    m, batch = _model("demod-jbu")
    fastpath.prepare_inference(m, "cpu", path="auto")
    assert m.settings["path"] == "graph"  # prepared for the first candidate, not yet checked
    with caplog.at_level(logging.INFO, logger="training.inference.fastpath"), torch.inference_mode():
        out = m.forward(batch)
        again = m.forward(batch)  # the chosen path, no further check
    rec = fastpath.path_record(m)
    assert rec["path"] == "fused" and rec["auto"]["checked"] and rec["auto"]["max_rel_err"] <= 2e-5
    why = "failed (RuntimeError: no C++ compiler found)" if how == "raise" else "error 1.00e-02 > 2e-05"
    assert rec["auto"]["rejected"] == [f"graph: {why}"]
    assert "inference path graph" in caplog.text and "inference path: fused (auto" in caplog.text
    want = _reference("demod-jbu", batch)
    for o in (out, again):
        assert float((o - want).abs().max() / want.abs().max()) <= 2e-5


def test_auto_ends_on_the_reference_path(monkeypatch):
    monkeypatch.setattr(fastpath, "AUTO_ORDER", ("graph",))
    _break_graph(monkeypatch, "wrong")
    m, batch = _model("demod-jbu")
    fastpath.prepare_inference(m, "cpu", path="auto")
    with torch.inference_mode():
        out = m.forward(batch)
    rec = fastpath.path_record(m)
    assert rec["path"] == "reference" and rec["auto"]["rejected"][-1] == "reference: the last resort"
    assert torch.equal(out, _reference("demod-jbu", batch)) and not m.module.fast_ops


def test_auto_checks_a_recurrent_model_on_its_first_step(monkeypatch):
    _break_graph(monkeypatch, "raise")  # the recurrent step does not run the compiled module: graph passes
    m, _ = _model("nsrd")
    inputs = example_inputs(m, None, (32, 16))
    fastpath.prepare_inference(m, "cpu", path="auto")
    sr, _ = m.step(inputs, ("clip", 1))
    rec = fastpath.path_record(m)
    assert rec["path"] == "graph" and rec["auto"]["checked"] and rec["auto"]["max_rel_err"] <= 2e-5
    ref, _ = _model("nsrd")
    want, _ = ref.step(inputs, None)
    assert abs(sr - want).max() <= 2e-5 * abs(want).max()


def test_auto_picks_the_compiled_graph_on_the_cpu():
    """The product's CPU default, unpatched: the whole model compiled with freezing, within fp32's tolerance."""
    m, batch = _model("demod-bilinear")
    fastpath.prepare_inference(m, "cpu", path="auto")
    with torch.inference_mode():
        out = m.forward(batch)
    rec = fastpath.path_record(m)
    assert rec["path"] == "graph" and rec["compiled"] and rec["auto"]["rejected"] == []
    want = _reference("demod-bilinear", batch)
    assert float((out - want).abs().max() / want.abs().max()) <= fastpath.TOLERANCE["fp32"]


def test_upscale_records_the_path_and_takes_the_default_from_the_environment(tmp_path, monkeypatch):
    from gbuffer_export.synthetic import make_synthetic_clip
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 3), hr_size=(32, 16), scale=4)
    run_cli("upscale", "--model", "demod-jbu", "--clip", clip, "-o", tmp_path / "a", "--path", "reference",
            "--no-progress", check=True)
    assert json.loads((tmp_path / "a" / "upscale.json").read_text())["inference"]["path"] == "reference"
    run_cli("upscale", "--model", "demod-jbu", "--clip", clip, "-o", tmp_path / "b", "--no-progress", check=True)
    assert json.loads((tmp_path / "b" / "upscale.json").read_text())["inference"]["path"] == "fast"  # the suite's
    bad = run_cli("upscale", "--model", "demod-jbu", "--clip", clip, "-o", tmp_path / "c", "--path", "quick")
    assert bad.returncode == 2 and "--path: invalid choice: 'quick'" in bad.stderr


def test_speed_files_keep_the_graph_rows_timing(tmp_path):
    """bench_speed.csv takes a graph variant's row (its replay spread, replays and timing): the first H200 run of
    CHECK=graph timed every model and then failed writing the CSV ('dict contains fields not in fieldnames')."""
    import csv

    from training.bench import _speed_record, _write_speed
    pk = {"tflops": 100.0, "gbs": 1000.0}
    base = {"model": "bilinear", "params": 0, "macs": 0.0, "bytes": 2e6, "times": [0.3, 0.2]}
    rows = [_speed_record({**base, "variant": "bf16"}, pk, 100, lambda m: None),
            _speed_record({**base, "variant": "bf16 graph", "graph_timing": {"spread": 0.01, "n": 200}}, pk, 100,
                          lambda m: None)]
    meta = {"device": "cpu", "size": (16, 8), "scale": 4, "timing": "t", "repeats": 2, "warmup": 0,
            "peaks": {"bf16": {"tflops": 100.0, "gbs": 1000.0, "source": "given"}}}
    _write_speed(tmp_path, meta, rows, "table")
    got = list(csv.DictReader(open(tmp_path / "bench_speed.csv")))
    assert [r["variant"] for r in got] == ["bf16", "bf16 graph"]
    assert got[0]["spread"] == "" and float(got[1]["spread"]) == 0.01 and got[1]["replays"] == "200"


def test_a_batch_has_one_scale_factor():
    """``batch['scale']`` is (B,) with one factor per batch (the samplers draw one): ``batch_factor`` reads it on the
    host for every model and refuses a batch with several."""
    from training.models.base import batch_factor
    m, batch = _model("bilinear")
    assert batch_factor(torch.tensor([2.5, 2.5])) == 2.5
    assert m.module.batch_scale({"scale": torch.tensor([3.0])}) == 3.0
    with pytest.raises(ValueError, match=r"holds \[2.0, 4.0\]: one factor per batch"):
        m.module.batch_scale({"scale": torch.tensor([2.0, 4.0])})
