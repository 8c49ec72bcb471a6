"""Triton kernels of the fused HR stage (``hr_stage``; CUDA): two launches per frame.

``hr_pixels_kernel``: steps 1-5 of ``hr_stage``'s module doc for a block of HR pixels of one row, reading the raw
LR buffers at the 4 bilinear taps (LR guides and classes computed per tap: no LR pre-pass) and the HR buffers once;
``pixel_filter_kernel``: the separable pixel filter as its full 2-D stencil (taps x taps loads, L1-resident). Every
tensor is addressed through its strides, so NCHW and channels-last inputs run without a layout copy. The per-pixel
math is ``hr_math``'s helpers, jitted with ``ops`` = ``triton.language`` (``hr_math.jit_for_triton``): the same
code the CPU path runs. Tests run both kernels under ``TRITON_INTERPRET=1`` on the CPU against the torch path
and compile them to an sm_90 cubin (tests/train/hr_stage_cases.py). Arguments are packed in tuples (Triton >= 3.3)
and the switches in one ``FLAGS`` constexpr.
"""
from __future__ import annotations

import torch
import triton
import triton.language as tl

from training.kernels import hr_math
from training.kernels.spec import HRInputs, HRStage

_h = hr_math.jit_for_triton()
tap_position, tap_weight, tap_index = _h["tap_position"], _h["tap_weight"], _h["tap_index"]
demodulated, guide_depth, guide_normal = _h["demodulated"], _h["guide_depth"], _h["guide_normal"]
similarity, class_or_plain, guided_or_fallback = _h["similarity"], _h["class_or_plain"], _h["guided_or_fallback"]
head, inverse_log1p, remodulate = _h["head"], _h["inverse_log1p"], _h["remodulate"]
range_add, range_pick, clamp_to_range = _h["range_add"], _h["range_pick"], _h["clamp_to_range"]
similar, open_if_empty = _h["similar"], _h["open_if_empty"]

BLOCK = 128
#: The empty tap range's bound (step 4b), a constexpr for the kernel.
BIG = tl.constexpr(hr_math.F32_MAX)


@triton.jit
def _ld(ptr, b, c, y, x, s, mask):
    """float32 value of ptr[b, c, y, x] with strides s = (sb, sc, sy, sx)."""
    return tl.load(ptr + b * s[0] + c * s[1] + y * s[2] + x * s[3], mask=mask, other=0.0).to(tl.float32)


#: Bits of the hr_pixels_kernel's FLAGS (the switches of ``HRStage``, and whether a jitter is given).
F_BY_CLASS, F_GUIDED, F_HEAD, F_LOG1P, F_REMOD, F_JITTER, F_CLAMP, F_CLAMP_GUIDED = 1, 2, 4, 8, 16, 32, 64, 128


@triton.jit
def hr_pixels_kernel(lrs, s_lrs, hrs, s_hrs, jit, scalars, FLAGS: tl.constexpr, BLOCK: tl.constexpr):
    """Steps 1-2 (the taps' sums and ranges) for BLOCK pixels of HR row program_id(1) of image program_id(2), then
    ``_finish`` (steps 3-5 and 4b). ``lrs`` = (LR image, F_used,
    depth, normal), ``hrs`` = (HR F_used, depth, normal, emission, network output, out), ``s_lrs`` / ``s_hrs``
    their strides (b, c, y, x); ``jit`` (B, 2); ``scalars`` = (h, w, W, jitter's 2 strides, scale, sigma_depth,
    sigma_normal, floor, clamp margin); ``FLAGS``: the F_* bits above."""
    BY_CLASS: tl.constexpr = (FLAGS & 1) != 0
    GUIDED: tl.constexpr = (FLAGS & 2) != 0
    HAS_JITTER: tl.constexpr = (FLAGS & 32) != 0
    CLAMP: tl.constexpr = (FLAGS & 64) != 0
    CLAMP_GUIDED: tl.constexpr = (FLAGS & 128) != 0
    CLASS_RANGE: tl.constexpr = (FLAGS & (1 | 64 | 128)) == (1 | 64)  # the class's range of "lr-range"
    lr, lr_fb, lr_d, lr_n = lrs[0], lrs[1], lrs[2], lrs[3]
    s_lr, s_lfb, s_ld, s_ln = s_lrs[0], s_lrs[1], s_lrs[2], s_lrs[3]
    hr_fb, hr_d, hr_n = hrs[0], hrs[1], hrs[2]
    s_hfb, s_hd, s_hn = s_hrs[0], s_hrs[1], s_hrs[2]
    h, w, ww, sj0, sj1 = scalars[0], scalars[1], scalars[2], scalars[3], scalars[4]
    scale, sd, sn, floor, margin = scalars[5], scalars[6], scalars[7], scalars[8], scalars[9]
    xb = tl.program_id(0)
    y = tl.program_id(1)
    b = tl.program_id(2)
    x = xb * BLOCK + tl.arange(0, BLOCK)
    mask = x < ww
    if HAS_JITTER:
        jx = tl.load(jit + b * sj0).to(tl.float32)
        jy = tl.load(jit + b * sj0 + sj1).to(tl.float32)
    else:
        jx = 0.0
        jy = 0.0
    ux = tap_position(x.to(tl.float32), scale, jx)
    uy = tap_position(y.to(tl.float32), scale, jy)
    fx = tl.floor(ux)
    fy = tl.floor(uy)
    if BY_CLASS:
        cls = demodulated(_ld(hr_fb, b, 0, y, x, s_hfb, mask), _ld(hr_fb, b, 1, y, x, s_hfb, mask),
                          _ld(hr_fb, b, 2, y, x, s_hfb, mask))
    if GUIDED:
        gh0 = guide_depth(_ld(hr_d, b, 0, y, x, s_hd, mask), sd)
        gh1 = guide_normal(_ld(hr_n, b, 0, y, x, s_hn, mask), sn)
        gh2 = guide_normal(_ld(hr_n, b, 1, y, x, s_hn, mask), sn)
        gh3 = guide_normal(_ld(hr_n, b, 2, y, x, s_hn, mask), sn)
    zero = tl.zeros([BLOCK], dtype=tl.float32)
    p0, p1, p2 = zero, zero, zero
    c0, c1, c2, cden = zero, zero, zero, zero
    g0, g1, g2, gden = zero, zero, zero, zero
    big = zero + BIG  # the tap ranges of step 4b: all taps (p) and the pixel's class (c; "lr-guided": its surface)
    plo0, plo1, plo2, phi0, phi1, phi2 = big, big, big, -big, -big, -big
    clo0, clo1, clo2, chi0, chi1, chi2 = big, big, big, -big, -big, -big
    for dy in tl.static_range(2):
        fyd = fy + dy
        wy = tap_weight(uy, fyd)
        iy = tap_index(fyd, h).to(tl.int32)
        for dx in tl.static_range(2):
            fxd = fx + dx
            wb = wy * tap_weight(ux, fxd)
            ix = tap_index(fxd, w).to(tl.int32)
            v0 = _ld(lr, b, 0, iy, ix, s_lr, mask)
            v1 = _ld(lr, b, 1, iy, ix, s_lr, mask)
            v2 = _ld(lr, b, 2, iy, ix, s_lr, mask)
            p0, p1, p2 = p0 + wb * v0, p1 + wb * v1, p2 + wb * v2
            if CLAMP:
                plo0, plo1, plo2 = tl.minimum(plo0, v0), tl.minimum(plo1, v1), tl.minimum(plo2, v2)
                phi0, phi1, phi2 = tl.maximum(phi0, v0), tl.maximum(phi1, v1), tl.maximum(phi2, v2)
            if BY_CLASS:
                same = demodulated(_ld(lr_fb, b, 0, iy, ix, s_lfb, mask), _ld(lr_fb, b, 1, iy, ix, s_lfb, mask),
                                   _ld(lr_fb, b, 2, iy, ix, s_lfb, mask)) == cls
                wc = tl.where(same, wb, 0.0)
                c0, c1, c2, cden = c0 + wc * v0, c1 + wc * v1, c2 + wc * v2, cden + wc
                if CLASS_RANGE:
                    clo0, chi0 = range_add(clo0, chi0, v0, same)
                    clo1, chi1 = range_add(clo1, chi1, v1, same)
                    clo2, chi2 = range_add(clo2, chi2, v2, same)
            if GUIDED:
                e0 = guide_depth(_ld(lr_d, b, 0, iy, ix, s_ld, mask), sd) - gh0
                e1 = guide_normal(_ld(lr_n, b, 0, iy, ix, s_ln, mask), sn) - gh1
                e2 = guide_normal(_ld(lr_n, b, 1, iy, ix, s_ln, mask), sn) - gh2
                e3 = guide_normal(_ld(lr_n, b, 2, iy, ix, s_ln, mask), sn) - gh3
                sim = similarity(e0 * e0 + e1 * e1 + e2 * e2 + e3 * e3)
                wg = wb * sim
                if BY_CLASS:
                    wg = tl.where(same, wg, 0.0)
                g0, g1, g2, gden = g0 + wg * v0, g1 + wg * v1, g2 + wg * v2, gden + wg
                if CLAMP_GUIDED:  # "lr-guided": the range of the taps of the pixel's surface (and class)
                    use = similar(sim)
                    if BY_CLASS:
                        use = use & same
                    clo0, chi0 = range_add(clo0, chi0, v0, use)
                    clo1, chi1 = range_add(clo1, chi1, v1, use)
                    clo2, chi2 = range_add(clo2, chi2, v2, use)
    _finish(hrs, s_hrs, (b, y, x, mask), ((p0, p1, p2), (c0, c1, c2, cden), (g0, g1, g2, gden)),
            ((plo0, plo1, plo2, phi0, phi1, phi2), (clo0, clo1, clo2, chi0, chi1, chi2)), (floor, margin), FLAGS)


@triton.jit
def _finish(hrs, s_hrs, at, sums, ranges, consts, FLAGS: tl.constexpr):
    """Steps 3-5 (and 4b) of one block from the tap sums of ``hr_pixels_kernel``, per channel k, and the store:
    ``at`` = (b, y, x, mask); ``sums`` = (p, c, g): the bilinear sums, the class and guided sums with their weight
    totals last; ``ranges`` = (all taps', the class's) tap ranges, 3 minima then 3 maxima; ``consts`` = (floor,
    clamp margin)."""
    BY_CLASS: tl.constexpr = (FLAGS & 1) != 0
    GUIDED: tl.constexpr = (FLAGS & 2) != 0
    HEAD: tl.constexpr = (FLAGS & 4) != 0
    LOG1P: tl.constexpr = (FLAGS & 8) != 0
    REMOD: tl.constexpr = (FLAGS & 16) != 0
    CLAMP: tl.constexpr = (FLAGS & 64) != 0
    CLAMP_GUIDED: tl.constexpr = (FLAGS & 128) != 0
    CLASS_PICK: tl.constexpr = (FLAGS & (1 | 128)) == 1  # "lr-range" by class
    hr_fb, hr_e, net, out = hrs[0], hrs[3], hrs[4], hrs[5]
    s_hfb, s_he, s_net, s_out = s_hrs[0], s_hrs[3], s_hrs[4], s_hrs[5]
    b, y, x, mask = at[0], at[1], at[2], at[3]
    p, c, g, prange, crange = sums[0], sums[1], sums[2], ranges[0], ranges[1]
    floor, margin = consts[0], consts[1]
    base = out + b * s_out[0] + y * s_out[2] + x * s_out[3]
    for k in tl.static_range(3):
        o = p[k]
        if BY_CLASS:
            o = class_or_plain(c[k], c[3], o)
        if GUIDED:
            o = guided_or_fallback(g[k], g[3], o, floor)
        if HEAD:
            o = head(_ld(net, b, k, y, x, s_net, mask), o)
            if LOG1P:
                o = inverse_log1p(o)
            if CLAMP:
                lo, hi = prange[k], prange[k + 3]
                if CLASS_PICK:
                    lo, hi = range_pick(c[3], crange[k], lo), range_pick(c[3], crange[k + 3], hi)
                if CLAMP_GUIDED:
                    lo, hi = open_if_empty(crange[k], crange[k + 3])
                if LOG1P:
                    lo, hi = inverse_log1p(lo), inverse_log1p(hi)
                o = clamp_to_range(o, lo, hi, margin)
        if REMOD:
            o = remodulate(o, _ld(hr_fb, b, k, y, x, s_hfb, mask), _ld(hr_e, b, k, y, x, s_he, mask))
        tl.store(base + k * s_out[1], o, mask=mask)


#: Longest pixel filter the kernel takes; longer ones run ``filters.shift_filter``.
MAX_TAPS = 5


@triton.jit
def pixel_filter_kernel(src, dst, strides, dims, taps, NT: tl.constexpr, BLOCK: tl.constexpr):
    """dst[b, c, y, x] = sum_ij taps_i taps_j src[b, c, clamp(y + i - k), clamp(x + j - k)], k = NT // 2;
    ``strides`` = (src's, dst's), ``dims`` = (H, W), ``taps`` MAX_TAPS floats of which the first NT are used."""
    s_src, s_dst = strides[0], strides[1]
    hh, ww = dims[0], dims[1]
    xb = tl.program_id(0)
    y = tl.program_id(1)
    bc = tl.program_id(2)
    b = bc // 3
    c = bc % 3
    x = xb * BLOCK + tl.arange(0, BLOCK)
    mask = x < ww
    acc = tl.zeros([BLOCK], dtype=tl.float32)
    for i in tl.static_range(NT):
        yy = tl.minimum(tl.maximum(y + i - NT // 2, 0), hh - 1)
        ti = taps[i]
        row = tl.zeros([BLOCK], dtype=tl.float32)
        for j in tl.static_range(NT):
            tj = taps[j]
            xx = tl.minimum(tl.maximum(x + j - NT // 2, 0), ww - 1)
            row += tj * _ld(src, b, c, yy, xx, s_src, mask)
        acc += ti * row
    tl.store(dst + b * s_dst[0] + c * s_dst[1] + y * s_dst[2] + x * s_dst[3], acc, mask=mask)


def _strides(t: torch.Tensor | None) -> tuple[int, int, int, int]:
    return tuple(t.stride()) if t is not None else (0, 0, 0, 0)


def hr_stage_triton(spec, t) -> torch.Tensor:
    """``hr_stage.hr_stage_torch``'s result with the two kernels: (B, 3, H, W) float32 (channels-last when the
    network output or the HR F_used is)."""
    b, _, h, w = t.lr.shape
    s = spec.scale
    hh, ww = h * s, w * s
    out = torch.empty(b, 3, hh, ww, device=t.lr.device, dtype=torch.float32, memory_format=_out_format(list(t)))
    dummy = t.lr
    pick = (lambda v: v if v is not None else dummy)
    jit = t.jitter if t.jitter is not None else torch.zeros(b, 2, device=t.lr.device)
    sig = spec.sigmas or (1.0, 1.0)
    flags = (F_BY_CLASS * spec.by_class | F_GUIDED * spec.guided | F_HEAD * spec.head | F_LOG1P * spec.log1p |
             F_REMOD * spec.remod | F_JITTER * (t.jitter is not None) | F_CLAMP * (spec.clamp is not None) |
             F_CLAMP_GUIDED * (spec.clamp is not None and spec.clamp_guided))
    lrs = (t.lr, pick(t.lr_fbeta), pick(t.lr_depth), pick(t.lr_normal))
    hrs = (pick(t.hr_fbeta), pick(t.hr_depth), pick(t.hr_normal), pick(t.hr_emission), pick(t.net), out)
    scalars = (h, w, ww, jit.stride(0), jit.stride(1), float(s), float(sig[0]), float(sig[1]), float(spec.floor),
               float(spec.clamp or 0.0))
    hr_pixels_kernel[(triton.cdiv(ww, BLOCK), hh, b)](
        lrs, (t.lr.stride(),) + tuple(_strides(v) for v in (t.lr_fbeta, t.lr_depth, t.lr_normal)),
        hrs, tuple(_strides(v) for v in (t.hr_fbeta, t.hr_depth, t.hr_normal, t.hr_emission, t.net)) + (out.stride(),),
        jit, scalars, FLAGS=int(flags), BLOCK=BLOCK)
    if spec.taps is None:
        return out
    if len(spec.taps) > MAX_TAPS:
        from training.kernels.filters import shift_filter
        return shift_filter(out, spec.taps)
    dst = torch.empty_like(out)
    taps = tuple(float(v) for v in spec.taps) + (0.0,) * (MAX_TAPS - len(spec.taps))
    pixel_filter_kernel[(triton.cdiv(ww, BLOCK), hh, b * 3)](out, dst, (out.stride(), dst.stride()), (hh, ww), taps,
                                                             NT=len(spec.taps), BLOCK=BLOCK)
    return dst


def _spec_params(spec) -> list[float]:
    """``HRStage`` as the flat float list the custom op takes (``_spec_of`` inverts it)."""
    sig = spec.sigmas or (1.0, 1.0)
    return [float(spec.scale), float(spec.by_class), float(spec.guided), float(sig[0]), float(sig[1]),
            float(spec.head), float(spec.log1p), float(spec.remod), float(spec.floor),
            float(0 if spec.clamp is None else 1 + spec.clamp_guided),
            float(spec.clamp or 0.0), *map(float, spec.taps or ())]


def _spec_of(params: list[float]):
    p = list(params)
    return HRStage(scale=int(p[0]), by_class=bool(p[1]), guided=bool(p[2]),
                   sigmas=(p[3], p[4]) if p[2] else None, head=bool(p[5]), log1p=bool(p[6]), remod=bool(p[7]),
                   taps=tuple(p[11:]) or None, floor=p[8], clamp=p[10] if p[9] else None,
                   clamp_guided=p[9] == 2)


def _out_format(tensors: list) -> torch.memory_format:
    """The output's layout: channels-last when the network output (or else the HR F_used) is."""
    net, hr_fbeta = tensors[9], tensors[3]
    like = net if net is not None else (hr_fbeta if hr_fbeta is not None else tensors[0])
    cl = like.dim() == 4 and like.shape[1] > 1 and like.is_contiguous(memory_format=torch.channels_last)
    return torch.channels_last if cl else torch.contiguous_format


@torch.library.custom_op("blendsr::hr_stage", mutates_args=())
def hr_stage_op(tensors: list[torch.Tensor | None], params: list[float]) -> torch.Tensor:
    """The fused HR stage as one opaque operator (``hr_stage.HRInputs`` as a list, the ``HRStage`` as
    ``_spec_params``): torch.compile keeps it as an external call inside its graph (and its CUDA graphs) instead of
    tracing into the launches."""
    return hr_stage_triton(_spec_of(params), HRInputs(*tensors))


@hr_stage_op.register_fake
def _(tensors, params):
    lr = tensors[0]
    s = int(params[0])
    return torch.empty(lr.shape[0], 3, lr.shape[2] * s, lr.shape[3] * s, device=lr.device, dtype=torch.float32,
                       memory_format=_out_format(tensors))
