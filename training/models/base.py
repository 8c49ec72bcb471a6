"""Base class and building blocks shared by the models (torch).

Tensors are channel-first. ``batch`` values are (B, T, C, H, W); ``current(batch, key)`` is the last frame.
Motion is in pixels of its level, image coordinates (x right, y down), backward: p_prev = p + motion.
``batch['lr_jitter']`` (B, T, 2) is each LR frame's jitter: the sample of LR pixel centre p was taken at p + jitter
(LR pixels). Models with ``use_jitter`` (``model.jitter``, default on) read it: upsampling samples the LR image at
u - jitter for an HR pixel centre u, and history warping adds jitter_t - jitter_(t-k) to the motion.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from gbuffer_export.errors import BlendSRError
from training.models import OPTIONAL_KEYS
from training.models.guided import GUIDE_KEYS, guide_features, upsample_guided
from training.models.resample import upsample  # noqa: F401  (re-exported: models import it from here)
from training.transforms import forward_transform, normalize_depth


def batch_factor(scale: torch.Tensor) -> float:
    """The one upscaling factor of a batch's ``scale`` ((B,), equal within a batch: the samplers draw one per batch),
    read on the host; ValueError (one line) for several."""
    factors = set(scale.reshape(-1).tolist())
    if len(factors) != 1:
        raise ValueError(f"batch['scale'] holds {sorted(factors)}: one factor per batch")
    return float(factors.pop())


class SRModel(nn.Module):
    """A super-resolution model. Subclasses set ``learned``, ``history`` and implement ``needs`` and ``forward``.

    ``SCALES``: the integer upscaling factors the model supports, or None for any scale >= 1 (integer or not); such a
    model reads the factor of each batch from ``batch_scale(batch)`` (``batch['scale']``, (B,) float, all equal)."""

    learned = False
    #: Whether the model predicts the demodulated irradiance and remodulates it (``remodulate``).
    demod = False
    #: A model that carries a state from frame to frame (``training.recurrent``; ``step(batch, state)``).
    recurrent = False
    #: This class's row in ``training.models.MODELS``: its options are ``MODELS[NAME].options``.
    NAME = ""
    SCALES: tuple[int, ...] | None = (2, 4, 8)
    #: The inference fast path (``training.models.fast_ops``; ``training.inference.fastpath.prepare_inference`` sets it):
    #: the same outputs as the reference implementations within float rounding, fewer and cheaper kernels.
    fast_ops = False
    #: The fused HR stage (``training.kernels.hr_stage``; ``prepare_inference(..., hr_stage="fused")`` sets it): None
    #: for the reference/fast-ops path, else the implementation (``hr_stage.IMPLS``) that ``fused_hr`` runs.
    hr_impl: str | None = None

    def __init__(self, scale: float, **keys):
        """A model upscaling by ``scale``. ``keys``: the shared ``[model]`` keys (``training.config.ModelConfig``:
        ``history``, ``jitter``, ``input_transform``, ``depth_norm``, ``upsample_by_class``, ``remod_filter``,
        ``remod_filter_px``) and the model's own options (its ``[model.<NAME>]`` table, ``training.models.options``)
        by keyword, e.g. ``FuseSR(4, width=64, jitter=False)``; a key left out takes the configuration's default
        (one place for every default). ``self.config`` holds the resulting validated ``ModelConfig``. ConfigError
        (one line) for a key the model does not have or a value out of range."""
        super().__init__()
        if not self.supports_scale(scale):
            raise BlendSRError(f"scale {scale:g}: model {self.NAME or type(self).__name__} supports "
                               f"{self.scales_text()}")
        from training.models.config import ModelConfig  # torch-free; its tables hold the defaults
        self.config = cfg = ModelConfig.of(self.NAME, **keys)
        self.scale = int(scale) if float(scale).is_integer() else float(scale)
        self.history = 0
        self.transform = cfg.input_transform
        self.depth_norm = cfg.depth_norm
        self.use_jitter = bool(cfg.jitter)
        self.by_class = bool(cfg.upsample_by_class)
        self.guided = False  # subclasses that may read the HR geometry set it and ``guide_sigmas`` from their options
        self.guide_sigmas: tuple[float, float] | None = None  # (depth, normal) tolerances of the guided upsampling
        self._set_remod_weights(remod_weights(cfg.remod_filter, cfg.remod_filter_px))

    @property
    def options(self):
        """The model's own options (the dataclass of its ``[model.<NAME>]`` table)."""
        return self.config.options

    def _set_remod_weights(self, w1) -> None:
        device = self.remod_kernel.device if getattr(self, "remod_kernel", None) is not None else None
        kernel = None if w1 is None else torch.tensor(w1, dtype=torch.float32, device=device)
        if "remod_kernel" in self._buffers:
            self.remod_kernel = kernel
        else:
            self.register_buffer("remod_kernel", kernel, persistent=False)
        self.remod_taps = None if w1 is None else tuple(float(v) for v in w1)  # the same weights, for fast_ops

    @classmethod
    def supports_scale(cls, scale) -> bool:
        """Whether the model can upscale by ``scale`` (a number)."""
        if isinstance(scale, bool) or not isinstance(scale, (int, float)):
            return False
        if cls.SCALES is None:
            return scale >= 1
        return float(scale).is_integer() and int(scale) in cls.SCALES

    @classmethod
    def scales_text(cls) -> str:
        """'2, 4 and 8' or 'any scale >= 1', for messages."""
        if cls.SCALES is None:
            return "any scale >= 1"
        s = [str(v) for v in cls.SCALES]
        return ", ".join(s[:-1]) + f" and {s[-1]}" if len(s) > 1 else s[0]

    def batch_scale(self, batch: dict) -> float:
        """The upscaling factor of ``batch``: ``batch['scale'][0]`` when the batch carries it, else ``self.scale``."""
        s = batch.get("scale")
        return batch_factor(s) if s is not None else self.scale

    def follow_reference_filter(self, manifest: dict) -> None:
        """With ``model.remod_filter = "REFERENCE"`` (non-learned models; training resolves it into the checkpoint),
        remodulate through the pixel filter of this clip's ground truth (manifest ``render.hr``)."""
        if self.config.remod_filter == "REFERENCE":
            from gbuffer_export.pixel_filter import reference_filter
            self._set_remod_weights(remod_weights("REFERENCE", self.config.remod_filter_px,
                                                  reference_filter(manifest)))

    def remod_filter_mismatch(self, manifest: dict, clip_path) -> str | None:
        """A one-line reason when this model remodulates with a pixel filter other than the one the clip's ground
        truth was rendered with (manifest ``render.hr``), else None."""
        if not self.demod or self.config.remod_filter in ("NONE", "REFERENCE"):
            return None
        from gbuffer_export.pixel_filter import reference_filter
        kind, width = reference_filter(manifest)
        mine = (self.config.remod_filter, float(self.config.remod_filter_px))
        if (kind, width) == mine:
            return None
        return (f"{clip_path}: the ground truth was rendered with the {kind} {width:g} px pixel filter but the model "
                f"remodulates through {mine[0]} {mine[1]:g} px (model.remod_filter, model.remod_filter_px)")

    def remodulate(self, irradiance: torch.Tensor, batch: dict) -> torch.Tensor:
        """HR radiance (B, 3, H, W) from a predicted HR irradiance: the point samples L_D * F_used^HR + E^HR (the
        G-buffers are point-sampled), seen through the ground truth's pixel filter (``model.remod_filter``;
        ``gbuffer_export.pixel_filter``) like the reference render, which averages its samples with that filter."""
        if self.fast_ops:
            from training.models import fast_ops
            return fast_ops.remodulate(irradiance, current(batch, "hr/fbeta_used"), current(batch, "hr/emission"),
                                       self.remod_taps)
        out = irradiance * current(batch, "hr/fbeta_used").to(irradiance.dtype) + \
            current(batch, "hr/emission").to(irradiance.dtype)
        return out if self.remod_kernel is None else separable_filter(out, self.remod_kernel)

    def upsample_input(self, x: torch.Tensor, batch: dict, jitter: torch.Tensor | None,
                       demodulated: bool = True, scale: float | None = None) -> torch.Tensor:
        """Upsampling of an LR input image (B, C, h, w) to HR by ``scale`` (default ``self.scale``), the base the
        models start from: bilinear, by class (``upsample_by_class``) for a ``demodulated`` L_D with
        ``model.upsample_by_class``, and with ``self.guided`` (the option ``guided_upsample`` of models that read
        the HR G-buffers) joint bilateral upsampling guided by HR depth and normals (``guided.upsample_guided``,
        tolerances ``guide_sigmas``) over that. Reads ``upsample_keys(demodulated)``."""
        scale = self.scale if scale is None else scale
        if self.fast_ops:
            from training.models import fast_ops
            by_class, bilinear, guided = fast_ops.upsample_by_class, fast_ops.upsample_bilinear, \
                fast_ops.upsample_guided
        else:
            by_class, bilinear, guided = upsample_by_class, \
                (lambda y, s, j: upsample(y, s, "bilinear", j)), upsample_guided
        classes = None
        if demodulated and self.by_class:
            classes = (demodulated_mask(current(batch, "lr/fbeta_used")),
                       demodulated_mask(current(batch, "hr/fbeta_used")))
            base = by_class(x, *classes, scale, jitter)
        else:
            base = bilinear(x, scale, jitter)
        if not self.guided:
            return base
        return guided(x, *self.guides(batch), scale, base, jitter, classes)

    def guides(self, batch: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """(LR, HR) scaled guides of the current frame (``guided.guide_features`` with ``guide_sigmas``): what the
        guided upsampling and the FuseSR family's ``"lr-guided"`` clamp weigh the taps by."""
        return tuple(guide_features(current(batch, f"{lv}/depth"), current(batch, f"{lv}/normal"), *self.guide_sigmas)
                     for lv in ("lr", "hr"))

    def fused_hr(self, batch: dict, lr: torch.Tensor, jitter: torch.Tensor | None, net: torch.Tensor | None = None,
                 demodulated: bool = True, clamp: float | None = None, clamp_guided: bool = False) -> torch.Tensor:
        """The HR stage in one fused pass (``training.kernels.hr_stage``, implementation ``self.hr_impl``): the
        output ``upsample_input(lr, ...)`` (with ``net``: ReLU(net + it), inverse-transformed, and with ``clamp``
        clamped to the taps' LR range widened by that margin, with ``clamp_guided`` the range of the pixel's surface's
        taps: the FuseSR family's ``residual_clamp``) followed, for
        a ``demodulated`` model, by ``remodulate`` would give, within float rounding."""
        from training.kernels.hr_stage import HRInputs, HRStage, run
        remod = bool(demodulated)
        spec = HRStage(scale=int(self.scale), by_class=bool(demodulated and self.by_class), guided=bool(self.guided),
                       sigmas=tuple(float(v) for v in self.guide_sigmas) if self.guided else None,
                       head=net is not None, log1p=net is not None and getattr(self, "transform", "") == "log1p",
                       remod=remod, taps=self.remod_taps if remod else None,
                       clamp=clamp if net is not None else None, clamp_guided=bool(clamp_guided))
        get = (lambda k: current(batch, k) if k in batch else None)
        t = HRInputs(lr, jitter, get("lr/fbeta_used"), get("hr/fbeta_used"), get("lr/depth"), get("lr/normal"),
                     get("hr/depth"), get("hr/normal"), get("hr/emission") if remod else None, net)
        if remod and t.hr_emission is None:
            t = t._replace(hr_emission=current(batch, "hr/emission"))  # the optional key's zeros
        return run(spec, t, self.hr_impl)

    def demod_base(self, batch: dict, jitter: torch.Tensor | None, scale: float | None = None) -> torch.Tensor:
        """The residual base of the option ``residual`` (``options.ResidualOptions``; not in the papers): T(L_D^LR
        upsampled as ``demod-bilinear`` does) (B, 3, H, W), T = ``self.transform``; the network's output T(L_D^HR)
        is added to it before T^-1 and the remodulation, so a network whose last conv is zero (``zero_init_head``)
        outputs exactly ``demod-bilinear``. Reads ``lr/irradiance`` and ``upsample_keys()``; ``scale`` as
        ``upsample_input``'s."""
        base = self.upsample_input(current(batch, "lr/irradiance"), batch, jitter, scale=scale)
        return forward_transform(base, self.transform)

    def base_keys(self) -> tuple[str, ...]:
        """Batch keys ``demod_base`` reads."""
        return ("lr/irradiance",) + self.upsample_keys()

    def upsample_keys(self, demodulated: bool = True) -> tuple[str, ...]:
        """Batch keys ``upsample_input`` reads."""
        keys = ("lr/fbeta_used", "hr/fbeta_used") if demodulated and self.by_class else ()
        return keys + (GUIDE_KEYS if self.guided else ())

    def jitter_keys(self) -> tuple[str, ...]:
        return ("lr_jitter",) if self.use_jitter else ()

    def frame_jitter(self, batch: dict, back: int = 0) -> torch.Tensor | None:
        """(B, 2) LR jitter of a frame when the model uses it (``model.jitter``) and the batch has it, else None."""
        return jitter(batch, back) if self.use_jitter else None

    def needs(self) -> tuple[str, ...]:
        """Batch keys the forward pass reads ('lr/...', 'hr/...', 'depth_ref')."""
        raise NotImplementedError

    @property
    def window(self) -> int:
        """LR frames per input window: the current one and ``history`` previous ones."""
        return self.history + 1


def remod_weights(kind: str, px: float, reference: tuple[str, float] | None = None):
    """1-D weights of the remodulation filter ``kind`` (``model.remod_filter``) of width ``px`` pixels
    (``model.remod_filter_px``); None for NONE or a point-sampling filter. REFERENCE uses ``reference`` (type,
    width px), by default BlendSR's own HR filter until a clip's manifest says otherwise."""
    if kind == "NONE":
        return None
    from gbuffer_export.pixel_filter import HR_REFERENCE_FILTER, weights_1d
    w1 = weights_1d(*(reference or HR_REFERENCE_FILTER)) if kind == "REFERENCE" else weights_1d(kind, px)
    return None if len(w1) == 1 else w1


def separable_filter(x: torch.Tensor, w1: torch.Tensor) -> torch.Tensor:
    """Convolve (B, C, H, W) with the separable kernel w1 x w1 (odd length), edges replicated."""
    k = w1.numel() // 2
    b, c, h, w = x.shape
    wt = w1.to(device=x.device, dtype=x.dtype)
    # every channel as its own image: the kernel's shape stays static (ONNX export traces the channel count)
    y = F.pad(x.reshape(b * c, 1, h, w), (k, k, k, k), mode="replicate")
    y = F.conv2d(F.conv2d(y, wt.view(1, 1, -1, 1)), wt.view(1, 1, 1, -1))
    return y.reshape(b, c, h, w)


def current(batch: dict, key: str) -> torch.Tensor:
    """(B, C, H, W) current frame of ``key`` (zeros of the radiance's shape for a missing optional key)."""
    x = batch.get(key)
    if x is None:
        if key in OPTIONAL_KEYS:
            level = key.split("/")[0]
            ref = next(v for k, v in batch.items() if k.startswith(level + "/"))
            return torch.zeros_like(ref[:, -1, :1]).expand(-1, 3, -1, -1)
        raise KeyError(f"batch lacks {key!r}")
    return x[:, -1]


def frame(batch: dict, key: str, back: int) -> torch.Tensor:
    """(B, C, H, W) frame ``back`` steps before the current one (clamped to the oldest frame in the batch)."""
    x = batch[key]
    t = x.shape[1]
    return x[:, max(t - 1 - back, 0)]


def jitter(batch: dict, back: int = 0) -> torch.Tensor | None:
    """(B, 2) LR jitter of a frame ``back`` steps before the current one (LR pixels), None when the batch has none."""
    j = batch.get("lr_jitter")
    if j is None:
        return None
    return j[:, max(j.shape[1] - 1 - back, 0)]


def depth_features(batch: dict, level: str, back: int, kind: str) -> torch.Tensor:
    """Normalised depth (B, 1, H, W) of a frame, with the current frame's reference depth."""
    ref = batch["depth_ref"][:, -1].reshape(-1, 1, 1, 1).to(batch[f"{level}/depth"].dtype)
    return normalize_depth(frame(batch, f"{level}/depth", back), ref, kind)


def backward_warp(x: torch.Tensor, motion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp ``x`` (B, C, H, W) of frame t-1 to frame t with the backward motion of frame t (B, 2, H, W, pixels):
    bilinear sampling at p + motion, clamped at the border, 0 where the sample leaves the image.
    Returns (warped, valid (B, 1, H, W) float). Matches ``gbuffer_export.conventions.backward_warp``."""
    b, _, h, w = x.shape
    ys = torch.arange(h, device=x.device, dtype=motion.dtype) + 0.5
    xs = torch.arange(w, device=x.device, dtype=motion.dtype) + 0.5
    sx = xs.view(1, 1, w) + motion[:, 0]
    sy = ys.view(1, h, 1) + motion[:, 1]
    valid = (sx >= 0) & (sx <= w) & (sy >= 0) & (sy <= h) & torch.isfinite(sx) & torch.isfinite(sy)
    sx = torch.nan_to_num(sx, nan=0.0, posinf=0.0, neginf=0.0)
    sy = torch.nan_to_num(sy, nan=0.0, posinf=0.0, neginf=0.0)
    grid = torch.stack([2.0 * sx / w - 1.0, 2.0 * sy / h - 1.0], dim=-1)
    out = F.grid_sample(x, grid.to(x.dtype), mode="bilinear", padding_mode="border", align_corners=False)
    valid = valid.unsqueeze(1).to(x.dtype)
    return out * valid, valid


def conv(cin: int, cout: int, k: int = 3) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, k, padding=k // 2)


def zero_init(layer: nn.Conv2d) -> None:
    """Weights and bias of ``layer`` to 0 (``zero_init_head``: a fresh network outputs its residual base)."""
    nn.init.zeros_(layer.weight)
    if layer.bias is not None:
        nn.init.zeros_(layer.bias)


class DWSConv(nn.Module):
    """Depthwise-separable 3x3 convolution: depthwise 3x3 then pointwise 1x1."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.depthwise = nn.Conv2d(cin, cin, 3, padding=1, groups=cin)
        self.pointwise = nn.Conv2d(cin, cout, 1)

    def forward(self, x):
        return self.pointwise(self.depthwise(x))


class ResBlock(nn.Module):
    """x + conv(relu(conv(x))) with plain or depthwise-separable 3x3 convolutions."""

    def __init__(self, channels: int, separable: bool = False):
        super().__init__()
        make = DWSConv if separable else conv
        self.conv1 = make(channels, channels)
        self.conv2 = make(channels, channels)

    def forward(self, x):
        return x + self.conv2(F.relu(self.conv1(x)))


def demodulated_mask(fbeta_used: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) 1 where a pixel was divided by its F_beta, 0 where F_used = 1 (background, UNTRUSTED flags: there
    L_D holds radiance minus emission, a quantity of another scale). The torch twin of
    ``gbuffer_export.demod.undivided_mask`` (its complement)."""
    return (fbeta_used != 1.0).any(dim=1, keepdim=True).to(fbeta_used.dtype)


def upsample_by_class(x: torch.Tensor, lr_mask: torch.Tensor, hr_mask: torch.Tensor, scale: int,
                      jitter: torch.Tensor | None = None) -> torch.Tensor:
    """Bilinear upsampling of the demodulated L_D (B, C, h, w) that never mixes the two kinds of pixel: an HR pixel
    of class c (``hr_mask`` (B, 1, H, W), 1 = demodulated) interpolates only the LR samples of class c (``lr_mask``
    (B, 1, h, w)) with renormalised bilinear weights, and takes the plain bilinear value where none of its 4 LR
    neighbours has its class. Without it an irradiance (radiance / F_beta, up to 1 / eps times larger) bleeds into
    neighbouring background or untrusted HR pixels and the reverse, as bright or dark seams along silhouettes."""
    plain = upsample(x, scale, "bilinear", jitter)
    out = plain
    for m_lr, m_hr in ((lr_mask, hr_mask), (1.0 - lr_mask, 1.0 - hr_mask)):
        num = upsample(x * m_lr, scale, "bilinear", jitter)
        den = upsample(m_lr, scale, "bilinear", jitter)
        ok = (den > 1e-6) & (m_hr > 0.5)
        out = torch.where(ok, num / den.clamp(min=1e-6), out)
    return out


def history_offsets(batch: dict, history: int, use_jitter: bool) -> list[torch.Tensor]:
    """Sampling offsets (B, 2, h, w, LR pixels) that bring frames t-1 .. t-history to frame t with
    ``backward_warp``. The surface seen at p + j_t was at p + j_t + m in frame t-1's un-jittered image, where
    frame t-1's pixel q holds its sample at q + j_(t-1): offset = m + j_t - j_(t-1). Further back the motion of
    frame t-k+1 is read at the previous offset and accumulated, then the jitter difference to frame t-k added."""
    raw = current(batch, "lr/motion")
    j_t = jitter(batch, 0) if use_jitter else None

    def with_jitter(m: torch.Tensor, k: int) -> torch.Tensor:
        if j_t is None:
            return m
        return m + (j_t - jitter(batch, k)).to(m.dtype).view(-1, 2, 1, 1)

    offsets = [with_jitter(raw, 1)]
    for k in range(2, history + 1):
        warped, _ = backward_warp(frame(batch, "lr/motion", k - 1), offsets[-1])
        raw = raw + warped
        offsets.append(with_jitter(raw, k))
    return offsets
