"""The fused HR stage (training/kernels) against the fp32 eager reference of every guided model (CPU), the weights
held in bf16 without autocast, and the Triton kernels under TRITON_INTERPRET=1 against the torch path."""
import copy
import os
import warnings

import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.errors import BlendSRError  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.inference.export import example_inputs  # noqa: E402
from training.inference.fastpath import forward, hold_weights, prepare_inference  # noqa: E402
from training.kernels import hr_stage  # noqa: E402
from training.kernels.hr_stage import HRInputs, HRStage  # noqa: E402
from training.models import MODELS, build_model  # noqa: E402


@pytest.fixture(autouse=True)
def _fresh_dynamo():
    """Each test compiles from a fresh torch._dynamo state (a worker may have compiled other models before)."""
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()

#: max |fused - reference| / max |reference|: fp32 reorders sums and (compiled) uses SLEEF's exp/log (measured
#: 7.5e-6 at 1080p); bf16 weights and activations as test_fastpath's autocast tolerance.
TOL = {"none": 2e-5, "bf16": 2e-2}

#: The guided models and option sets whose HR stage is fused (every switch the stage reads).
CASES = [("demod-bilinear", {}), ("demod-bilinear", {"upsample_by_class": False, "jitter": False}),
         ("demod-jbu", {}), ("demod-jbu", {"upsample_by_class": False}), ("demod-jbu", {"remod_filter": "NONE"}),
         ("fusesr-fast", {}), ("fusesr-fast", {"guided_upsample": False, "input_transform": "none"}),
         ("fusesr-l", {}), ("fusesr", {"history": 1}), ("fusesr", {"history": 0, "demodulation": False}),
         ("fusesr-fast", {"residual_clamp": "lr-range"}),
         ("fusesr-l", {"residual_clamp": "lr-range", "residual_clamp_margin": 0.25, "jitter": False}),
         ("fusesr-fast", {"residual_clamp": "lr-guided"}),
         ("fusesr-l", {"residual_clamp": "lr-guided", "upsample_by_class": False, "guide_sigma_depth": 2.0,
                       "guide_sigma_normal": 1.0})]


def _batch(model, size=(48, 32), seed=3):
    """Random inputs with F_used = 1 bands at both levels (background/untrusted pixels: the class rule) and a
    background band of +inf depth (example_inputs)."""
    batch = {k: torch.from_numpy(v) for k, v in example_inputs(model, None, size, seed=seed).items()}
    for key, cut in (("hr/fbeta_used", size[0] // 3), ("lr/fbeta_used", size[0] // 12)):
        if key in batch:
            batch[key][..., :cut] = 1.0
    return batch


def _rel(got, want):
    return float((got - want).abs().max()) / float(want.abs().max())


#: Over a minute each on 2 busy cores (torch.compile, the Triton interpreter, shipped networks at size): run by
#: ``make test-heavy``, which CI runs after ``make test``.
heavy = pytest.mark.heavy


@pytest.mark.parametrize("name,opts", CASES)
def test_fused_hr_stage_matches_the_fp32_eager_reference(name, opts):
    _fused_matches(name, opts, ("torch",))


@heavy
@pytest.mark.parametrize("name", ["demod-jbu", "fusesr-fast"])
def test_compiled_fused_hr_stage_matches_the_fp32_eager_reference(name):
    _fused_matches(name, {}, ("compiled",))


@heavy
def test_cpu_graph_path_traces_the_stage_into_the_model_graph():
    """The CPU graph path compiles the whole model; the HR stage inside it is traced into that graph
    (``hr_stage.run`` calls ``hr_stage_torch`` while compiling), not through ``_compiled``'s lru_cache, which dynamo
    warned of on every first frame ("Silent incorrectness is only a potential risk"). Same output as the reference."""
    import torch._dynamo.utils as dynamo_utils
    dynamo_utils.warn_once_cache.clear()  # dynamo warns once per process
    torch.manual_seed(0)
    ref = build_model(ModelConfig.of("demod-jbu"), 4).eval()
    batch = _batch(ref)
    with torch.inference_mode():
        want = ref(batch)
        graph = prepare_inference(copy.deepcopy(ref), path="graph")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            got = forward(graph, batch)
    assert graph.settings["path"] == "graph" and graph.settings["compiled"] is not None
    assert graph.module.hr_impl == "compiled"  # the stage the switch is about ran inside the graph
    assert _rel(got, want) <= TOL["none"]
    assert [str(w.message)[:80] for w in caught if "lru_cache" in str(w.message)] == []


def _fused_matches(name, opts, impls):
    torch.manual_seed(0)
    ref = build_model(ModelConfig.of(name, **opts), 4).eval()
    batch = _batch(ref)
    with torch.inference_mode():
        want = ref(batch)
        for impl in impls:
            fused = prepare_inference(copy.deepcopy(ref), path="fused")
            fused.module.hr_impl = impl
            got = forward(fused, batch)
            assert got.dtype == torch.float32 and got.shape == want.shape
            assert _rel(got, want) <= TOL["none"], (impl, _rel(got, want))
    assert fused.settings["path"] == "fused"


def test_the_fused_stage_is_what_runs():
    """The fused path really replaces the upsampling and remodulation: a wrong sigma in its spec changes the
    output (the reference code is not silently run instead)."""
    ref = build_model(ModelConfig.of("demod-jbu"), 4).eval()
    batch = _batch(ref)
    fused = prepare_inference(copy.deepcopy(ref), path="fused")
    fused.module.hr_impl = "torch"
    calls = []
    real = hr_stage.hr_stage_torch
    try:
        hr_stage.hr_stage_torch = lambda spec, t: calls.append(spec) or real(spec, t)
        with torch.inference_mode():
            forward(fused, batch)
    finally:
        hr_stage.hr_stage_torch = real
    assert len(calls) == 1 and calls[0].guided and calls[0].by_class and calls[0].remod and not calls[0].head


#: The networks whose bf16 case runs the HR stage as compiled on the CPU (inductor's C++, a minute and more each
#: on 2 busy cores: ``make test-heavy``); the others run it eagerly (``hr_impl = "torch"``), which the weights
#: held in bf16 do not depend on.
BF16_COMPILED = ("fusesr", "fusesr-l")


@pytest.mark.parametrize("name", [pytest.param(n, marks=heavy) if n in BF16_COMPILED else n
                                  for n in MODELS if MODELS[n].learned])
def test_bf16_weights_held_without_autocast_match_the_fp32_reference(name):
    torch.manual_seed(0)
    ref = build_model(ModelConfig.of(name), 4).eval()
    batch = _batch(ref, size=(32, 32))
    with torch.inference_mode():
        want = ref(batch)
        fused = prepare_inference(copy.deepcopy(ref), precision="bf16", path="fused")
        if name not in BF16_COMPILED:
            fused.module.hr_impl = "torch"
        assert fused.settings["dtype"] is None and fused.settings["weights"] == "bf16"
        convs = [m for m in fused.module.modules() if isinstance(m, torch.nn.Conv2d)]
        assert convs and all(m.weight.dtype == torch.bfloat16 for m in convs)
        got = forward(fused, batch)
    assert got.dtype == torch.float32
    err = _rel(got, want)
    assert 1e-6 < err <= TOL["bf16"], err  # low precision really ran, within its tolerance


def _casts(model, batch) -> int:
    """dtype conversions (aten::_to_copy, autocast's included) in one forward pass."""
    from torch.profiler import ProfilerActivity, profile
    with torch.inference_mode(), profile(activities=[ProfilerActivity.CPU]) as prof:
        forward(model, batch)
    return sum(e.count for e in prof.key_averages() if e.key == "aten::_to_copy")


@heavy
def test_held_weights_cast_only_where_fp32_enters_the_network():
    """Heavy: the saving needs the HR stage compiled (inductor's C++ on the CPU, about a minute on 2 busy cores; run
    eagerly it casts 92 times against autocast's 137). That the weights are held in bf16 is checked in the suite
    by ``test_bf16_weights_held_without_autocast_match_the_fp32_reference``."""
    ref = build_model(ModelConfig.of("fusesr-l"), 4).eval()
    batch = _batch(ref, size=(32, 32))
    auto = _casts(prepare_inference(copy.deepcopy(ref), precision="bf16"), batch)
    held = _casts(prepare_inference(copy.deepcopy(ref), precision="bf16", path="fused"), batch)
    assert held < auto / 2, (held, auto)


def test_hold_weights_converts_convolutions_and_keeps_norms_in_fp32():
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.LayerNorm(4), torch.nn.Linear(4, 2))
    assert hold_weights(net, torch.bfloat16) == 2
    assert net[0].weight.dtype == net[2].weight.dtype == torch.bfloat16 and net[1].weight.dtype == torch.float32
    with torch.inference_mode():
        out = net(torch.rand(1, 3, 6, 6).permute(0, 2, 3, 1).permute(0, 3, 1, 2))
    assert out.dtype == torch.bfloat16


def test_unknown_path_is_refused():
    ref = build_model(ModelConfig.of("demod-jbu"), 4).eval()
    with pytest.raises(BlendSRError, match="inference path 'turbo'"):
        prepare_inference(ref, path="turbo")
    with pytest.raises(ValueError, match="implementation 'x'"):
        hr_stage.run(HRStage(4, False, False, None, False, False, False, None), HRInputs(torch.zeros(1, 3, 2, 2)),
                     "x")


# ------------------------------------------------------------------ Triton kernels under the CPU interpreter
def _inputs(b, h, w, s, channels_last, jitter, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *sh: torch.rand(*sh, generator=g)  # noqa: E731
    fl, fh = r(b, 3, h, w), r(b, 3, h * s, w * s)
    fl[..., :2], fh[..., : 2 * s] = 1.0, 1.0
    hd = 1 + 9 * r(b, 1, h * s, w * s)
    hd[..., :3, :] = float("inf")
    t = HRInputs(r(b, 3, h, w), r(b, 2) - 0.5 if jitter else None, fl, fh, 1 + 9 * r(b, 1, h, w),
                 r(b, 3, h, w) - 0.5, hd, r(b, 3, h * s, w * s) - 0.5, r(b, 3, h * s, w * s),
                 r(b, 3, h * s, w * s) - 0.3)
    if channels_last:
        t = HRInputs(*[v.contiguous(memory_format=torch.channels_last) if v is not None and v.dim() == 4 else v
                       for v in t])
    return t


BH = (0.11859148, 0.76281703, 0.11859148)
SPECS = [HRStage(4, True, True, (0.1, 0.2), False, False, True, BH),                       # demod-jbu
         HRStage(4, True, False, None, False, False, True, BH),                             # demod-bilinear
         HRStage(4, True, True, (0.1, 0.2), True, True, True, BH),                         # fusesr family
         HRStage(2, False, True, (0.1, 0.2), True, False, False, None),                     # no demodulation
         HRStage(4, False, False, None, False, False, True, (0.05, 0.2, 0.5, 0.2, 0.05)),   # 5 taps
         HRStage(4, True, False, None, False, False, True, (0.1,) * 7),                     # 7 taps: torch filter
         HRStage(4, True, True, (0.1, 0.2), True, True, True, BH, clamp=0.0),              # residual_clamp
         HRStage(2, False, True, (0.1, 0.2), True, False, False, None, clamp=0.5),         # clamp, no classes
         # "lr-guided" (wide sigmas: the random guides give similar and dissimilar taps, both)
         HRStage(4, True, True, (2.0, 1.0), True, True, True, BH, clamp=0.0, clamp_guided=True),
         HRStage(2, False, True, (2.0, 1.0), True, False, False, None, clamp=0.25, clamp_guided=True)]


def interpreter_errors(ks=None, quick=False) -> list:
    """Per spec of SPECS (those numbered ``ks``; None: all), the largest relative difference of
    ``hr_triton.hr_stage_triton`` to ``hr_stage_torch`` over batch 1 NCHW with jitter and batch 2 channels-last at
    3 x 5 LR pixels (run by ``interpreted`` under TRITON_INTERPRET=1); ``quick``: batch 1 NCHW with jitter only, at
    2 x 3 LR pixels (one program of BLOCK pixels per kernel)."""
    from training.kernels.hr_triton import hr_stage_triton
    out = []
    for k in range(len(SPECS)) if ks is None else ks:
        spec, err = SPECS[k], 0.0
        for b, cl, jit in ((1, False, True),) if quick else ((1, False, True), (2, True, k % 2 == 0)):
            t = _inputs(b, 2, 3, spec.scale, cl, jit, seed=k) if quick else _inputs(b, 3, 5, spec.scale, cl, jit,
                                                                                      seed=k)
            want, got = hr_stage.hr_stage_torch(spec, t), hr_stage_triton(spec, t)
            assert got.shape == want.shape and got.dtype == torch.float32
            err = max(err, _rel(got, want))
        out.append(err)
    return out


COMPILED = ("demod-jbu", "fusesr-l")


def interpreter_model_errors() -> list:
    """Per model of COMPILED, the fused path with the Triton implementation (the custom operator
    blendsr::hr_stage) under torch.compile, against the fp32 reference: relative error."""
    out = []
    for name in COMPILED:
        ref = build_model(ModelConfig.of(name), 4).eval()
        batch = _batch(ref, size=(32, 16))
        with torch.inference_mode():
            want = ref(batch)
            fused = prepare_inference(copy.deepcopy(ref), compile=True, path="fused")
            fused.module.hr_impl = "triton"
            out.append(_rel(forward(fused, batch), want))
    return out


def _interpret(calls: str):
    """``calls`` (an expression over ``t``, this module) evaluated in a fresh interpreter with TRITON_INTERPRET=1
    (triton reads it when first imported, and torch may have imported triton already here): its JSON value."""
    pytest.importorskip("triton", reason="triton is not installed (Linux x86-64 wheels; the dev extra has it)")
    import json
    import subprocess
    import sys
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    code = f"import json, tests.train.hr_stage_cases as t; print(json.dumps({calls}))"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=1200)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def interpreted():
    """``interpreter_errors`` of every spec and ``interpreter_model_errors``, interpreted (``_interpret``)."""
    return _interpret("[t.interpreter_errors(), t.interpreter_model_errors()]")


#: The spec the suite interprets (``test_a_triton_kernel_matches_the_torch_path_under_the_interpreter``): guided,
#: head and the "lr-guided" clamp at scale 2 (the Triton interpreter takes 5-15 s a launch at scale 4 on 2 busy
#: cores; every spec, the pixel filter's kernel with them, is interpreted by the heavy cases below).
QUICK_SPEC = len(SPECS) - 1


def test_a_triton_kernel_matches_the_torch_path_under_the_interpreter():
    """The suite's representative of the interpreter cases: one spec, one small launch (batch 1, jittered)."""
    err = _interpret(f"t.interpreter_errors([{QUICK_SPEC}], quick=True)")
    assert len(err) == 1 and err[0] <= 1e-6, (SPECS[QUICK_SPEC], err)


@heavy
@pytest.mark.parametrize("k", range(len(SPECS)))
def test_triton_kernels_match_the_torch_path_under_the_interpreter(interpreted, k):
    assert interpreted[0][k] <= 1e-6, (SPECS[k], interpreted[0][k])


@heavy
@pytest.mark.parametrize("k", range(len(COMPILED)))
def test_triton_stage_runs_inside_torch_compile_as_one_operator(interpreted, k):
    assert interpreted[1][k] <= TOL["none"], (COMPILED[k], interpreted[1][k])


# ------------------------------------------------------------------------------------------------ on a GPU
cuda = pytest.mark.skipif(not (torch.cuda.is_available() and hr_stage.triton_available()),
                          reason="needs a CUDA device and triton")
GUIDED = ["demod-bilinear", "demod-jbu", "fusesr-fast", "fusesr-l", "fusesr"]


@cuda
@pytest.mark.parametrize("k", range(len(SPECS)))
def test_cuda_triton_kernels_match_the_torch_path(k):
    from training.kernels.hr_triton import hr_stage_triton
    spec = SPECS[k]
    for b, cl, jit in ((1, False, True), (2, True, k % 2 == 0)):
        t = HRInputs(*[v.cuda() if v is not None else None for v in _inputs(b, 40, 72, spec.scale, cl, jit, k)])
        want = hr_stage.hr_stage_torch(spec, t)
        got = hr_stage_triton(spec, t)
        assert _rel(got, want) <= 1e-5, (b, cl, _rel(got, want))


@cuda
def test_cuda_fused_hr_stage_launches_two_kernels():
    from torch.profiler import ProfilerActivity, profile
    spec = SPECS[0]
    t = HRInputs(*[v.cuda() if v is not None else None for v in _inputs(1, 64, 96, 4, False, True)])
    hr_stage.run(spec, t, "triton")
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        hr_stage.run(spec, t, "triton")
        torch.cuda.synchronize()
    names = [e.name for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    names = sorted(names)
    assert len(names) == 2 and names[0].startswith("hr_pixels_kernel") and \
        names[1].startswith("pixel_filter_kernel"), names


@cuda
@pytest.mark.parametrize("name", GUIDED)
def test_cuda_fused_path_matches_the_cpu_fp32_reference(name):
    """On a GPU: the fused path (Triton HR stage), bf16 weights held, eager and torch.compile (reduce-overhead: CUDA
    graphs), against the fp32 eager reference computed on the CPU."""
    ref = build_model(ModelConfig.of(name), 4).eval()
    cpu_batch = _batch(ref, size=(128, 64))
    with torch.inference_mode():
        want = ref(cpu_batch)
    dev = torch.device("cuda")
    batch = {k: v.to(dev) for k, v in cpu_batch.items()}
    tol_fp32 = 1e-3 if MODELS[name].learned else TOL["none"]  # TF32 convolutions on CUDA
    for precision, comp, tol in (("none", False, tol_fp32), ("bf16", False, TOL["bf16"]),
                                 ("bf16", True, TOL["bf16"])):
        fused = prepare_inference(copy.deepcopy(ref), dev, precision, compile=comp, path="fused")
        assert fused.module.hr_impl == "triton"
        with torch.inference_mode():
            for _ in range(3):  # CUDA-graph warm-up and replay
                got = forward(fused, batch).cpu()
        assert _rel(got, want) <= tol, (precision, comp, _rel(got, want))


@heavy
@pytest.mark.parametrize("name", ["fusesr-l", "fusesr-fast", "fusesr"])
def test_shipped_weights_score_as_before_on_the_fused_path(name, tmp_path):
    """A shipped network on a rendered-like synthetic clip frame: the fused path's output (fp32) is the reference
    path's within the fp32 tolerance, so its scores are unchanged."""
    from gbuffer_export.synthetic import make_synthetic_clip
    from training import pretrained
    from training.inference.loading import ClipFrames, load_model, model_inputs
    if not (pretrained.WEIGHTS_DIR / pretrained.PRETRAINED[name]).is_file():
        pytest.skip(f"{name} not shipped")
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4, jitter=True)
    ref = load_model(f"pretrained:{name}", 4, fast=False)
    src = ClipFrames(clip, eps=ref.demod_eps)
    inputs = model_inputs(ref, src, src.frames[-1])
    batch = {k: torch.from_numpy(v) for k, v in inputs.items() if k in set(ref.module.needs())}
    with torch.inference_mode():
        want = ref.forward(batch)
        fused = prepare_inference(load_model(f"pretrained:{name}", 4, fast=False), path="fused")
        got = forward(fused, batch)
    assert _rel(got, want) <= TOL["none"], _rel(got, want)
    hr = torch.from_numpy(inputs["hr/radiance"][:, -1])
    psnr = [float(-10 * torch.log10(((x - hr) ** 2).mean())) for x in (want, got)]
    assert abs(psnr[0] - psnr[1]) < 1e-3, psnr


@heavy
def test_bench_models_paths_side_by_side_with_kernels_and_the_reference_check(tmp_path, monkeypatch, capsys):
    import json

    from gbuffer_export.cli import main
    from training.inference import fastpath
    args = ["bench", "models", "--device", "cpu", "--size", "64x32", "--models", "demod-jbu,fusesr-l",
            "--path", "reference,fast,fused", "--precision", "none,bf16", "--repeats", "1", "--warmup", "1",
            "--threads", "1", "--no-progress", "-o", str(tmp_path / "b")]
    assert main(args) == 0
    rows = json.loads((tmp_path / "b" / "bench_speed.json").read_text())["rows"]
    got = {(r["model"], r["variant"]): r for r in rows}
    assert set(got) == {(m, v) for m in ("demod-jbu", "fusesr-l") for v in (
        "fp32 eager reference", "fp32", "bf16", "fp32 fused", "bf16 fused")}
    for r in rows:
        assert r["kernels"] > 0 and r["max_rel_err"] <= r["tolerance"] and r["ms"] > 0
    assert got[("demod-jbu", "fp32 eager reference")]["max_rel_err"] == 0.0
    assert got[("demod-jbu", "fp32 fused")]["kernels"] < got[("demod-jbu", "fp32")]["kernels"] / 10
    assert got[("fusesr-l", "bf16 fused")]["tolerance"] == fastpath.TOLERANCE["bf16"]
    assert "max rel. error" in (tmp_path / "b" / "bench_speed.md").read_text()
    capsys.readouterr()
    monkeypatch.setitem(fastpath.TOLERANCE, "fp32", 0.0)  # any rounding is now out of tolerance
    assert main(["bench", "models", "--device", "cpu", "--size", "64x32", "--models", "demod-jbu", "--path", "fused",
                 "--repeats", "1", "--warmup", "1", "--threads", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "demod-jbu fp32 fused differs from the fp32 reference" in err[0]


def test_a_failing_triton_falls_back_to_the_compiled_path(monkeypatch, caplog):
    """Where the Triton kernels fail (simulated: the launch raises a compiler error),
    the self-check says so in one warning and the fused path uses inductor."""
    hr_stage.triton_works.cache_clear()

    def boom(spec, t, impl="compiled"):
        raise RuntimeError("PassManager::run failed\nmore")
    monkeypatch.setattr(hr_stage, "run", boom)
    with caplog.at_level("WARNING"):
        assert hr_stage.triton_works(torch.device("cpu")) is False
    assert "Triton kernels fail here (RuntimeError: PassManager::run failed)" in caplog.text
    hr_stage.triton_works.cache_clear()


def test_triton_kernels_compile_to_a_hopper_cubin_without_a_gpu(tmp_path, monkeypatch):
    """The Triton compiler (front end, PTX, the wheel's ptxas) takes both kernels for sm_90 with every switch
    combination the models use: what the interpreter cannot check (types, tuples, constexpr folding)."""
    pytest.importorskip("triton", reason="triton is not installed (Linux x86-64 wheels; the dev extra has it)")
    if os.environ.get("TRITON_INTERPRET"):
        pytest.skip("TRITON_INTERPRET is set: the kernels are interpreted, not compiled")
    monkeypatch.setenv("TRITON_CACHE_DIR", str(tmp_path / "triton"))  # the compiled kernels land there
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource
    from triton.compiler import compile as tcompile

    from training.kernels import hr_triton as k
    s4 = ("i32",) * 4
    target = GPUTarget("cuda", 90, 32)
    for flags in (127, k.F_GUIDED | k.F_HEAD):  # every switch; guided without classes or remodulation
        sig = {"lrs": ("*fp32",) * 4, "s_lrs": (s4,) * 4, "hrs": ("*fp32",) * 4 + ("*bf16", "*fp32"),
               "s_hrs": (s4,) * 6, "jit": "*fp32", "scalars": ("i32",) * 5 + ("fp32",) * 5, "FLAGS": "constexpr",
               "BLOCK": "constexpr"}
        assert "cubin" in tcompile(ASTSource(k.hr_pixels_kernel, sig, {"FLAGS": flags, "BLOCK": k.BLOCK}),
                                   target=target).asm
    sig = {"src": "*fp32", "dst": "*fp32", "strides": (s4, s4), "dims": ("i32", "i32"), "taps": ("fp32",) * 5,
           "NT": "constexpr", "BLOCK": "constexpr"}
    assert "cubin" in tcompile(ASTSource(k.pixel_filter_kernel, sig, {"NT": 3, "BLOCK": k.BLOCK}), target=target).asm


def test_triton_kernel_arguments_do_not_shadow_the_launch_binder_names():
    """Triton's launcher binds a kernel's arguments in a generated function whose own locals are ``params``,
    ``specialization`` and ``options`` (triton/runtime/jit.py, create_function_from_signature): an argument of that
    name is overwritten before it is specialised ("failed to specialize argument of type: dict", seen on an H200
    on 2026-11-27). Compiling without a GPU does not reach the binder, so the names are checked here."""
    import inspect
    pytest.importorskip("triton")
    from training.kernels import hr_triton as k
    for kernel in (k.hr_pixels_kernel, k.pixel_filter_kernel):
        names = set(inspect.signature(kernel.fn).parameters)
        assert not names & {"params", "specialization", "options", "backend", "specialize_impl", "JITCallable"}
