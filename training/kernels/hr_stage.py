"""The HR stage of the guided models, fused: everything that runs at HR around the network of ``demod-bilinear``,
``demod-jbu`` and the FuseSR family (``fusesr``, ``fusesr-l``, ``fusesr-fast``), in one pass over the HR pixels
and one pass of the pixel filter.

Per HR pixel (one definition of the math: ``hr_math``; every step reproduces a reference in ``models/``):

1. the 4 bilinear LR taps of its centre with the frame's jitter (``resample.upsample``), borders clamped;
2. the plain bilinear value and, with ``by_class``, the class-restricted one: only the taps whose demodulation
   class (F_used != 1) is the HR pixel's, renormalised (``base.upsample_by_class``);
3. with ``guided``, the joint bilateral value: taps weighted by exp(-|g_HR - g_LR|^2 / 2) on the scaled guides
   [log depth / sigma_d, normal / sigma_n] and by the class match, falling back to step 2's value where the
   weights sum below ``floor`` (``guided.upsample_guided``);
4. with ``head`` (FuseSR family), ReLU(network output + that base), then the inverse log1p transform with
   ``log1p``;
4b. with ``clamp`` (the FuseSR option ``residual_clamp = "lr-range"``), that value clamped per channel to the range
   of the LR image over the 4 taps of step 1 (only those of the pixel's class where step 2 uses them), inverse
   transformed with ``log1p``, widened by ``clamp`` times its width (``guided.tap_range``); with ``clamp_guided``
   (``"lr-guided"``) over the taps of the pixel's class whose step-3 range weight passes ``hr_math.similar``, and
   no clamp where none does;
5. with ``remod``, the point sample L_D F_used + E (``SRModel.remodulate``);

then the separable pixel filter ``taps`` x ``taps`` (edges replicated) over the result.

Implementations (``run``): ``triton`` on CUDA (``hr_triton``: one kernel for steps 1-5, one for the filter; LR
guides and classes computed per tap from the raw LR buffers, so nothing else is launched; called as the custom
operator ``blendsr::hr_stage``, which torch.compile keeps whole inside its graphs and CUDA graphs), and ``torch``
(``hr_stage_torch``: the same helpers on tensors: the two column taps of every HR column gathered at LR height,
then every HR row reading whole rows of them). On the CPU the fused path runs ``compiled``: ``hr_stage_torch``
under ``torch.compile``, whose C++ backend (inductor) turns it into two vectorised kernels (``_compiled``);
Triton's CPU interpreter is for tests only.
Demodulation itself (the eps rule) runs where the inputs are read (``training.inference.loading``, ``training.cache``:
``gbuffer_export.demod``) and is not repeated here: the models receive L_D and F_used.
"""
from __future__ import annotations

import functools
import logging

import torch
import torch.nn.functional as F

from training.kernels import hr_math as m
from training.kernels.spec import HRInputs, HRStage

log = logging.getLogger(__name__)

IMPLS = ("torch", "compiled", "triton")


def tap_axes(n_lr: int, scale: int, jit: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """[(index (B, n) long, weight (B, n))] of the 2 taps along one axis of n = n_lr * scale HR pixels; ``jit``
    (B, 1) the jitter along the axis."""
    i = torch.arange(n_lr * scale, device=jit.device, dtype=torch.float32).view(1, -1)
    u = m.tap_position(i, float(scale), jit)
    f = torch.floor(u)
    return [(m.tap_index(f + d, n_lr).long(), m.tap_weight(u, f + d)) for d in (0.0, 1.0)]


def _lr_planes(spec: HRStage, t: HRInputs) -> torch.Tensor:
    """(B, K, h, w) float32: the image (3), the scaled guide (4, ``guided``) and the class (1, ``by_class``)."""
    planes = [t.lr.float()]
    if spec.guided:
        planes += [m.guide_depth(t.lr_depth[:, :1].float(), spec.sigmas[0]),
                   m.guide_normal(t.lr_normal.float(), spec.sigmas[1])]
    if spec.by_class:
        f = t.lr_fbeta.float()
        planes.append(m.demodulated(f[:, 0:1], f[:, 1:2], f[:, 2:3]))
    return torch.cat(planes, dim=1)


def lr_columns(spec: HRStage, t: HRInputs) -> list[torch.Tensor]:
    """The two column taps of every HR column at LR height: [(B, K, h, W)] (``_lr_planes`` gathered along x)."""
    lr_all = _lr_planes(spec, t)
    b, k, h, w = lr_all.shape
    jit = _jitter(t)
    return [torch.gather(lr_all, 3, ix.view(b, 1, 1, -1).expand(b, k, h, -1))
            for ix, _ in tap_axes(w, spec.scale, jit[:, :1])]


def _jitter(t: HRInputs) -> torch.Tensor:
    b = t.lr.shape[0]
    return torch.zeros(b, 2, device=t.lr.device) if t.jitter is None else t.jitter.float()


class TapRange:
    """The per-channel range of the LR taps an HR pixel's base reads (``hr_math.range_add``, ``range_pick``): over
    all taps and, with ``by_class``, over those of the pixel's class; with ``guided`` (``residual_clamp =
    "lr-guided"``) over the taps of the pixel's class that ``hr_math.similar`` passes only, open where there are none
    (``hr_math.open_if_empty``). Off (``on`` false): does nothing."""

    def __init__(self, on: bool, by_class: bool, guided: bool = False):
        self.on, self.by_class, self.guided = on, by_class, guided
        self.plain = self.cls = None

    def add(self, v: list[torch.Tensor], use: torch.Tensor | None) -> None:
        """Widen by the tap values ``v`` (per channel); ``use``: where the tap counts for the class (or guided)
        range, None without one."""
        if not self.on:
            return
        if self.cls is None and self.plain is None:
            if not self.guided:  # "lr-guided" reads its own range only
                self.plain = [(x, x) for x in v]
            if use is not None:
                self.cls = [(torch.where(use, x, m.F32_MAX), torch.where(use, x, -m.F32_MAX)) for x in v]
            return
        if not self.guided:
            self.plain = [(torch.minimum(lo, x), torch.maximum(hi, x)) for (lo, hi), x in zip(self.plain, v)]
        if use is not None:
            self.cls = [m.range_add(lo, hi, x, use) for (lo, hi), x in zip(self.cls, v)]

    def bounds(self, cden, log1p: bool) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """([lo] * 3, [hi] * 3) of the taps the base read (class taps where ``cden`` > CLASS_EPS; with ``guided``
        the similar taps'), inverse transformed with ``log1p``."""
        if self.guided:
            pairs = [m.open_if_empty(lo, hi) for lo, hi in self.cls]
        elif self.by_class:
            pairs = [(m.range_pick(cden, cl, pl), m.range_pick(cden, ch, ph))
                     for (cl, ch), (pl, ph) in zip(self.cls, self.plain)]
        else:
            pairs = self.plain
        if log1p:
            pairs = [(m.inverse_log1p(lo), m.inverse_log1p(hi)) for lo, hi in pairs]
        return [p[0] for p in pairs], [p[1] for p in pairs]


def _range_use(spec: HRStage, same: torch.Tensor | None, sim: torch.Tensor | None) -> torch.Tensor | None:
    """Where a tap counts for ``TapRange``'s class range: its class matches (``by_class``), and with
    ``clamp_guided`` its range weight ``sim`` passes ``hr_math.similar``; None where there is no such range."""
    if not spec.clamp_guided:
        return same
    near = m.similar(sim)
    return near if same is None else same & near


def hr_pixels(spec: HRStage, t: HRInputs, cols: list[torch.Tensor]) -> torch.Tensor:
    """Steps 1-5 of the module doc from the column taps ``cols`` (``lr_columns``): each HR row reads whole rows of
    them (an index per row, contiguous along x): (B, 3, H, W) float32. Written per channel ((B, 1, H, W) tensors,
    joined at the end) so that inductor computes the weights once per pixel in one loop for all three channels
    instead of realising them in HR buffers for a loop over channels."""
    b, k, h, ww = cols[0].shape
    s = spec.scale
    hh = h * s
    jit = _jitter(t)
    wxs = [wx.view(b, 1, 1, ww) for _, wx in tap_axes(ww // s, s, jit[:, :1])]
    if spec.by_class:
        f = t.hr_fbeta.float()
        cls = m.demodulated(f[:, 0:1], f[:, 1:2], f[:, 2:3])
    if spec.guided:
        n_hr = t.hr_normal.float()
        g_hr = [m.guide_depth(t.hr_depth[:, :1].float(), spec.sigmas[0])] + \
            [m.guide_normal(n_hr[:, i:i + 1], spec.sigmas[1]) for i in range(3)]
    plain, cnum, gnum = [0.0] * 3, [0.0] * 3, [0.0] * 3
    cden = gden = 0.0
    rng = TapRange(spec.clamp is not None, spec.by_class, spec.clamp_guided)
    for iy, wy in tap_axes(h, s, jit[:, 1:2]):
        wy = wy.view(b, 1, hh, 1)
        for col, wx in zip(cols, wxs):
            v = [torch.gather(col[:, i:i + 1], 2, iy.view(b, 1, hh, 1).expand(b, 1, hh, ww)) for i in range(k)]
            wb = wy * wx
            plain = [p + wb * v[i] for i, p in enumerate(plain)]
            same = v[k - 1] == cls if spec.by_class else None
            if spec.by_class:
                wc = torch.where(same, wb, 0.0)
                cnum, cden = [c + wc * v[i] for i, c in enumerate(cnum)], cden + wc
            if spec.guided:
                sim = m.similarity(sum((v[3 + i] - g).square() for i, g in enumerate(g_hr)))
                wg = wb * sim
                if spec.by_class:
                    wg = torch.where(same, wg, 0.0)
                gnum, gden = [g + wg * v[i] for i, g in enumerate(gnum)], gden + wg
            rng.add(v[:3], _range_use(spec, same, sim if spec.guided else None))
    out = [m.class_or_plain(cnum[i], cden, plain[i]) for i in range(3)] if spec.by_class else plain
    if spec.guided:
        out = [m.guided_or_fallback(gnum[i], gden, out[i], spec.floor) for i in range(3)]
    if spec.head:
        net = t.net.float()
        out = [m.head(net[:, i:i + 1], o) for i, o in enumerate(out)]
        if spec.log1p:
            out = [m.inverse_log1p(o) for o in out]
        if spec.clamp is not None:
            lo, hi = rng.bounds(cden, spec.log1p)
            out = [m.clamp_to_range(o, lo[i], hi[i], spec.clamp) for i, o in enumerate(out)]
    if spec.remod:
        fb, em = t.hr_fbeta.float(), t.hr_emission.float()
        out = [m.remodulate(o, fb[:, i:i + 1], em[:, i:i + 1]) for i, o in enumerate(out)]
    return torch.cat(out, dim=1)


def pixel_filter(spec: HRStage, x: torch.Tensor) -> torch.Tensor:
    """The separable pixel filter ``spec.taps`` x ``spec.taps`` (edges replicated) as its 2-D stencil over the
    replicate-padded image (the Triton kernel's formulation; compiled, one padded buffer and one pass), or ``x``
    without a filter."""
    if spec.taps is None:
        return x
    k = len(spec.taps) // 2
    hh, ww = x.shape[-2:]
    p = F.pad(x, (k, k, k, k), mode="replicate")
    return sum(ti * tj * p[..., i:i + hh, j:j + ww] for i, ti in enumerate(spec.taps)
               for j, tj in enumerate(spec.taps))


def hr_stage_torch(spec: HRStage, t: HRInputs) -> torch.Tensor:
    """The HR stage (module doc) on tensors: (B, 3, H, W) float32."""
    return pixel_filter(spec, hr_pixels(spec, t, lr_columns(spec, t)))


@functools.lru_cache(maxsize=None)
def _compiled(spec: HRStage):
    """``hr_stage_torch`` as two compiled graphs: the column taps at LR height are materialised (compiled in one
    graph, inductor would inline their gathers into the HR loop, a scattered load per tap and channel), then the
    HR loop reads whole rows of them, contiguous along x (vectorised loads), and writes the padded image the
    filter's stencil reads in the same graph. Measured at 1080p on one CPU thread: 94 -> 27 ms for the HR loop
    with per-channel tensors, 10 ms for the columns, 29 ms for the HR loop with the filter."""
    cols = torch.compile(functools.partial(lr_columns, spec), dynamic=False)
    pixels = torch.compile(lambda t, c: pixel_filter(spec, hr_pixels(spec, t, c)), dynamic=False)
    return lambda t: pixels(t, cols(t))


def triton_available() -> bool:
    """Whether the Triton kernels can run here: triton importable and a CUDA device."""
    if not torch.cuda.is_available():
        return False
    try:
        import triton  # noqa: F401
    except ImportError:
        return False
    return True


def default_impl(device: torch.device) -> str:
    """The fused implementation for ``device``: triton on CUDA when available and its self-check passes
    (``triton_works``), else compiled (module doc)."""
    return "triton" if device.type == "cuda" and triton_available() and triton_works(device) else "compiled"


@functools.lru_cache(maxsize=None)
def triton_works(device: torch.device) -> bool:
    """Whether the Triton kernels compile and run on ``device`` and agree with the torch path (1e-5 of the peak)
    on a small random frame with every switch on; when not, the reason is logged (a warning) and the fused path
    runs ``compiled`` there (inductor), so a Triton version the kernels do not support costs speed, not a run."""
    g = torch.Generator().manual_seed(0)
    r = (lambda *sh: torch.rand(*sh, generator=g).to(device))
    b, h, w, s = 1, 8, 12, 4
    t = HRInputs(r(b, 3, h, w), r(b, 2) - 0.5, r(b, 3, h, w), r(b, 3, h * s, w * s), 1 + r(b, 1, h, w),
                 r(b, 3, h, w), 1 + r(b, 1, h * s, w * s), r(b, 3, h * s, w * s), r(b, 3, h * s, w * s),
                 r(b, 3, h * s, w * s))
    spec = HRStage(s, True, True, (0.1, 0.2), True, True, True, (0.1186, 0.7628, 0.1186), clamp=0.25)
    try:
        got, want = run(spec, t, "triton"), hr_stage_torch(spec, t)
        err = float((got - want).abs().max() / want.abs().max())
    except Exception as exc:  # noqa: BLE001 - any failure of the optional kernels means: use inductor
        log.warning("fused HR stage: the Triton kernels fail here (%s: %s); using torch.compile instead",
                    type(exc).__name__, str(exc).splitlines()[0] if str(exc) else "")
        return False
    if not err <= 1e-5:
        log.warning("fused HR stage: the Triton kernels differ from the torch path by %.2e here; using "
                    "torch.compile instead", err)
        return False
    return True


def run(spec: HRStage, t: HRInputs, impl: str = "compiled") -> torch.Tensor:
    """The HR stage with implementation ``impl`` (``IMPLS``): (B, 3, H, W) float32. ``compiled`` inside an enclosing
    ``torch.compile`` (the CPU graph path compiles the whole model: ``training.inference.fastpath``) traces
    ``hr_stage_torch`` into that graph rather than through ``_compiled``'s cache, which dynamo warned of
    (``tests/train/hr_stage_cases.py``: no warning, the reference's output)."""
    if impl == "triton":  # as the custom operator blendsr::hr_stage (opaque to torch.compile)
        from training.kernels.hr_triton import _spec_params, hr_stage_op
        return hr_stage_op(list(t), _spec_params(spec))
    if impl == "compiled":  # inside an enclosing torch.compile (the CPU graph path) the stage joins that graph
        return hr_stage_torch(spec, t) if torch.compiler.is_compiling() else _compiled(spec)(t)
    if impl == "torch":
        return hr_stage_torch(spec, t)
    raise ValueError(f"HR stage implementation {impl!r}: choose one of {', '.join(IMPLS)}")


__all__ = ["HRStage", "HRInputs", "IMPLS", "run", "hr_stage_torch", "default_impl", "triton_available"]
