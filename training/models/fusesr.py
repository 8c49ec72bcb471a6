"""``fusesr``: the H-Net of FuseSR (Zhong et al., SIGGRAPH Asia 2023), written from the paper and the layer sizes of
the authors' public code.

Per LR frame the encoder reads 7 channels [T(L_D) 3, depth 1, normal 3] (T = the HDR input transform, L_D the
demodulated irradiance; with ``demodulation = false`` T(radiance) instead). Encoder: 3x3 conv 7->64 + ReLU (the
shallow feature F_s, skip-connected to the head), then 64-64-32-24-24-32-32 3x3 convs with ReLU (F_f; BatchNorm too
with the option ``norm = "batch"``, the authors' choice; off by default, docs/training.md, "FuseSR").
History: F_f of the ``history`` previous frames is warped to the current frame with the LR motion vectors
(accumulated over frames), zeroed where the sample leaves the image and gated by a small attention net on
[motion / 16, warped history depth, current depth] (sigmoid). The current F_f is expanded to 64 channels.
HR branch: [F_beta_used 3, depth 1, normal 3, albedo 3] = 10 HR channels, pixel-unshuffled by the scale
(10 s^2 LR channels), 3x3 conv to 64 + ReLU. Fusion network F at LR: 3x3 conv to ``width`` (128) + ReLU and
``blocks`` (6) residual blocks. Head: concat [F output, F_s], 3x3 conv to 3 s^2, pixel shuffle to HR, 3x3 conv
3->3 + ReLU = T(L_D^HR). Output: SR = K * (T^-1(.) F_beta_used^HR + E^HR) with K the ground truth's pixel filter
(``model.remod_filter``, default Blackman-Harris 1.5 px as BlendSR renders it; not in the paper, whose G-buffers and
ground truth are both rasterised), or T^-1(.) without demodulation.

Options are the ``[model.fusesr]`` table (``training.models.options.FuseSROptions``; ``[model.fusesr-l]`` for
``fusesr-l``). Option (``hr_guide``, default off; not in the paper): the HR refinement reads the 10 HR G-buffer channels
beside the pixel-shuffled prediction (3x3 conv 13 -> 16 + ReLU, 3x3 conv 16 -> 3) instead of the 3x3 conv 3 -> 3,
a direct full-resolution path for the HR geometry (docs/results-history.md, "FuseSR Table 3 on the clean clips").

Deviation (``residual``, default on): the bilinear upsampling of the transformed LR input T(L_D^LR) is added
before the final ReLU, so the network learns a correction of the demod-bilinear baseline. Without it (the authors'
head, ``residual = false``) the final 3-channel ReLU went dead on about a third of the output pixels in our runs and
training stalled far below the non-learned baseline (docs/training.md, "FuseSR").

LR jitter (``model.jitter``, default on; not in the paper, whose data has none): the current frame's jitter enters
the fusion network as 2 constant channels, the residual upsampling samples at the jittered LR positions and history
warping adds the jitter difference to the motion (``base.history_offsets``).

Guided base (``guided_upsample``, default on; not in the paper): with the HR branch on, the residual base is
the joint bilateral upsampling of T(L_D^LR) guided by HR depth and normals (``guided.upsample_guided``, the
``demod-jbu`` baseline's upsampling) instead of the bilinear one, so the network corrects a base that already
respects the HR geometry. ``hr_gbuffer = false`` removes it with the branch (measured: docs/results-history.md).

Option (``zero_init_refine``, default off; not in the paper): the last 3x3 conv starts at zero, so a fresh
network outputs exactly its residual base (the guided or bilinear upsampling) and training moves away from it only
where the loss says so (docs/results-history.md, "FuseSR Table 3 on the clean clips", has the measurement).

Bounded correction (``residual_clamp``, default ``"none"``: the paper's network; not in the paper): with
``"lr-range"`` the network's demodulated HR output (after T^-1, before the remodulation) is clamped per channel to
the range [min, max] of the demodulated LR input over the 4 bilinear LR taps its residual base reads (at the
jittered LR position, borders clamped; only the taps of the pixel's demodulation class where the class-aware base
uses them: ``guided.tap_range``), widened by ``residual_clamp_margin`` (default 0) times the range's width. It is the
neighbourhood clamp of temporal anti-aliasing, applied in demodulated space, where the HR texture detail has been
divided out, so the LR range is a tight but honest bound on the irradiance; the guided base is a convex combination
of those taps and always lies inside it, so a network that outputs its base is unchanged. The clamp is piecewise
the identity (training passes the gradient where it does not bind). The fused HR stage runs it as its step 4b
(``kernels.hr_math.clamp_to_range``). A trained network can be run with it: ``pretrained:fusesr?residual_clamp=
lr-range`` (``inference.load_model``; docs/training.md, "FuseSR", has the measurement that chose the margin).
With ``"lr-guided"`` (needs the guided base) the range is over those of the taps that lie on the pixel's surface
only: whose joint bilateral range weight on the HR depth and normal guides is at least
``hr_math.CLAMP_SIMILARITY`` (0.5); where none does the output is not clamped. Where the 4 taps hold none of the
pixel's surface (a thin bright ledge, a silhouette narrower than an LR pixel) their range is no bound on its
irradiance, and "lr-range" darkened exactly those pixels (docs/training.md, "FuseSR").

Confidence gate (``confidence_gate``, default off; not in the paper; the "confidence-gated blend with demod-jbu" of
issue 40): the correction the network adds to its residual base (the refined output, before the base is added) is
multiplied by a per-HR-pixel confidence sigmoid(c), where c is a 1x1 convolution of the head's LR input features to
scale^2 logits, pixel-shuffled to HR. A confidence of 0 outputs the residual base (with ``guided_upsample``:
``demod-jbu``'s guided upsampling, done on T(L_D^LR) instead of L_D^LR); 1 is the ungated network. The convolution
starts at weight 0 and bias ``GATE_OPEN`` (sigmoid 0.982), so a network fine-tuned from ungated weights
(``run.init_from``, which starts the gate's parameters fresh: ``FuseSRFrame.FRESH_PARAMETERS``) starts within 2 % of
its correction. Trained with the baseline hinge (``loss.baseline_weight``), the gate is where the network learns to
fall back to the baseline on content it cannot correct: a saturated sigmoid gives exactly the base, which an
unbounded correction reaches only by cancelling to 0. It learns at ``optim.gate_lr_scale`` times the network's rate
(at 1 it barely moves from its start: docs/training.md, "FuseSR"). It costs C (the head's input channels)
multiply-accumulates per HR pixel, plus a sigmoid and a product: 64 for ``fusesr-fast`` (1.5 % of its 4.3 K), 128
for ``fusesr-l``, 192 for ``fusesr``. It runs before the fused HR stage, which is unchanged.

Transmission fallback (``transmission_fallback``, default off; not in the paper): the correction is 0 on the HR
pixels whose flags carry TRANSMISSION (docs/clip-format.md), so the output there is the residual base. At such a
pixel the HR depth, normals and albedo describe the transmissive surface, not the scene seen through it, so the
guidance the network corrects with is of another surface; the engines' upscalers take the same kind of mask
from the game for transparent surfaces (the reactive mask). The correction is dropped in L_D, before the
remodulation, which filters with the ground truth's pixel filter, so within a pixel or two of a glass edge the two
blend. Needs the HR ``flags`` buffer; costs a product per HR pixel. Its learned form, ``gate_transmission`` (with
``confidence_gate``): the gate's logit gains w * mask, w a parameter starting at 0 that learns with the gate, so
training decides how far the gate closes on glass. Measured on val before it was offered (docs/training.md,
"FuseSR"): the worst val clip of the FuseSR-fast weights shipped then (b50c607) lost 1.2 dB to ``demod-jbu`` on its
2.5 % of TRANSMISSION pixels and gained 0.4 dB on the rest.

Material inputs (``hr_material``, default off; not in the paper): the HR branch also reads the HR roughness and
metallic (``HR_MATERIAL_KEYS``, 2 channels after the 10, so 12 s^2 pixel-unshuffled LR channels; with ``hr_guide``
the refinement reads them too). The paper's G-buffers hold no material parameters beyond albedo, and F_beta folds
roughness and metallic into one pre-integrated term, so the network cannot tell a rough dielectric from a smooth
metal of the same F_beta. Their channels come last, so ``run.init_from`` weights trained without them load with
zero weights on them (``GROWN_INPUTS``): the fine-tune starts exactly at those weights' network.

Depth is normalised per frame by ``model.depth_norm`` (default d / (d + median LR depth of the current frame);
background 1). ``hr_gbuffer = false`` drops the HR branch (the HR F_beta is still used for remodulation when
``demodulation`` is on), reproducing the switches of the paper's Table 3.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from gbuffer_export.conventions import Flag
from training.kernels import hr_math
from training.models.base import (DWSConv, ResBlock, SRModel, backward_warp, conv, current, demodulated_mask,
                                  depth_features, frame, history_offsets)
from training.models.guided import tap_range
from training.transforms import forward_transform, inverse_transform

ENCODER_CHANNELS = (64, 64, 32, 24, 24, 32, 32)
#: the HR geometry FuseSR's HR branch reads (and ``fusesr-fast`` with ``hr_geometry``): normalised depth (1), normal
#: (3), albedo (3); ``FuseSRFrame.hr_geometry``
HR_GEOMETRY_KEYS = ("hr/depth", "hr/normal", "hr/albedo")
HR_GEOMETRY_CHANNELS = 7
HR_CHANNELS = 3 + HR_GEOMETRY_CHANNELS  # FuseSR's HR input: F_beta, then the geometry
#: the HR material parameters FuseSR's HR branch reads after them with ``hr_material``: roughness (1), metallic (1)
HR_MATERIAL_KEYS = ("hr/roughness", "hr/metallic")
GATE_OPEN = 4.0  # the confidence gate's initial logit: sigmoid(4) = 0.982, near the ungated network
#: the HR flags bit of ``transmission_fallback``, tested on the flags as float32 (every bit is below 2^24, so float32
#: holds them exactly, and floor and remainder export where bitwise operations on integers may not)
TRANSMISSION_BIT = float(Flag.TRANSMISSION)


class Encoder(nn.Module):
    """7 -> 64 (shallow, ReLU) then 64-64-32-24-24-32-32 with ReLU (and BatchNorm with ``norm = "batch"``).
    Returns (F_s, F_f)."""

    def __init__(self, cin: int = 7, norm: str = "none"):
        super().__init__()
        self.shallow = nn.Sequential(conv(cin, ENCODER_CHANNELS[0]), nn.ReLU(inplace=True))
        layers = []
        for a, b in zip(ENCODER_CHANNELS[:-1], ENCODER_CHANNELS[1:]):
            layers += [conv(a, b), nn.BatchNorm2d(b), nn.ReLU(inplace=True)] if norm == "batch" else \
                [conv(a, b), nn.ReLU(inplace=True)]
        self.main = nn.Sequential(*layers)

    def forward(self, x):
        s = self.shallow(x)
        return s, self.main(s)


class HistoryGate(nn.Module):
    """Per-pixel weight in (0, 1) for a warped history feature from [motion/16, warped depth, current depth]."""

    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(conv(4, 8), nn.ReLU(inplace=True), conv(8, 1))

    def forward(self, motion, depth_prev_warped, depth_cur):
        return torch.sigmoid(self.net(torch.cat([motion / 16.0, depth_prev_warped, depth_cur], dim=1)))


class FuseSRFrame(SRModel):
    """What ``fusesr`` (and ``fusesr-l``) and ``fusesr-fast`` share around their networks: the switches of
    ``FuseSRFastOptions`` (read here, once), the input colour key and the output (the residual base, the final
    ReLU, T^-1 and the remodulation)."""

    learned = True
    #: the confidence gate's parameters: they learn at ``optim.gate_lr_scale`` times the rate (``Trainer``)
    GATE_PARAMETERS = ("confidence.weight", "confidence.bias", "confidence_transmission")
    #: parameters a checkpoint made before an option existed may lack: ``run.init_from`` starts them fresh
    FRESH_PARAMETERS = GATE_PARAMETERS

    def __init__(self, scale: int, **keys):
        super().__init__(scale, **keys)
        opt = self.options  # training.models.options.FuseSRFastOptions or a subclass
        self.demod = bool(opt.demodulation)
        self.use_hr = bool(opt.hr_gbuffer)
        self.residual = bool(opt.residual)
        # the guided upsampling is the residual base: it needs the HR G-buffers and the residual head
        self.guided = bool(opt.guided_upsample) and self.use_hr and self.residual
        self.guide_sigmas = (opt.guide_sigma_depth, opt.guide_sigma_normal)
        # the bounded correction (module doc, "residual_clamp"): the margin, None when off
        self.clamp = float(opt.residual_clamp_margin) if opt.residual_clamp != "none" and self.residual else None
        self.clamp_guided = opt.residual_clamp == "lr-guided"  # over the taps of the pixel's surface only
        self.confidence = None  # the confidence gate's 1x1 conv (module doc, "Confidence gate"): confidence_head
        self.fallback = bool(opt.transmission_fallback) and self.residual  # module doc, "Transmission fallback"
        # gate_transmission (module doc, "Transmission fallback"): the gate logit's weight on the TRANSMISSION mask
        self.confidence_transmission = nn.Parameter(torch.zeros(1)) if opt.gate_transmission and \
            opt.confidence_gate and self.residual else None

    def confidence_head(self, cin: int) -> nn.Conv2d | None:
        """``confidence_gate`` (module doc): a 1x1 conv from the head's ``cin`` LR input channels to one logit per HR
        pixel (scale^2, pixel-shuffled), starting at weight 0 and bias ``GATE_OPEN``; None when the option is off."""
        if not (self.options.confidence_gate and self.residual):
            return None
        head = nn.Conv2d(cin, self.scale * self.scale, 1)
        nn.init.zeros_(head.weight)
        nn.init.constant_(head.bias, GATE_OPEN)
        return head

    def hr_geometry(self, batch: dict) -> torch.Tensor:
        """The current frame's HR geometry (B, ``HR_GEOMETRY_CHANNELS``, H, W): normalised depth, normal, albedo."""
        return torch.cat([depth_features(batch, "hr", 0, self.depth_norm), current(batch, "hr/normal"),
                          current(batch, "hr/albedo")], dim=1)

    def gated(self, y: torch.Tensor, head_in: torch.Tensor, batch: dict) -> torch.Tensor:
        """The correction ``y`` (B, 3, H, W) times the confidence in [0, 1] read from ``head_in`` (B, C, h, w), and
        0 on TRANSMISSION pixels with ``transmission_fallback``."""
        if self.confidence is not None:
            y = y * self.confidence_map(head_in, batch).to(y.dtype)
        if self.fallback:
            y = y * (1.0 - self.transmission_mask(batch)).to(y.dtype)
        return y

    def confidence_map(self, head_in: torch.Tensor, batch: dict) -> torch.Tensor:
        """(B, 1, H, W) the confidence gate as applied: sigmoid of the 1x1 conv of ``head_in``, pixel-shuffled, plus
        ``confidence_transmission`` times the TRANSMISSION mask with ``gate_transmission``."""
        logit = F.pixel_shuffle(self.confidence(head_in), self.scale)
        if self.confidence_transmission is not None:
            logit = logit + self.confidence_transmission * self.transmission_mask(batch).to(logit.dtype)
        return torch.sigmoid(logit)

    @staticmethod
    def transmission_mask(batch: dict) -> torch.Tensor:
        """(B, 1, H, W) 1 where the current frame's HR flags carry TRANSMISSION, else 0."""
        flags = current(batch, "hr/flags").to(torch.float32)
        return torch.remainder(torch.floor(flags / TRANSMISSION_BIT), 2.0)

    def fallback_keys(self) -> tuple[str, ...]:
        """The batch keys ``transmission_fallback`` and ``gate_transmission`` read."""
        return ("hr/flags",) if self.fallback or self.confidence_transmission is not None else ()

    @property
    def color_key(self) -> str:
        """The LR colour input: the demodulated irradiance, or the radiance with ``demodulation = false``."""
        return "lr/irradiance" if self.demod else "lr/radiance"

    def output(self, y: torch.Tensor, color: torch.Tensor, batch: dict, j_t) -> torch.Tensor:
        """SR from the refined network output ``y`` (B, 3, H, W) in the transformed space: plus the upsampled
        transformed LR colour ``color`` (B, 3, h, w) with ``residual``, ReLU, T^-1, and the remodulation with
        ``demodulation``; with ``hr_impl`` (the fused path) all of it in one fused pass (``training.kernels``)."""
        if self.residual and self.hr_impl:  # the fused HR stage (training.kernels.hr_stage)
            return self.fused_hr(batch, color, j_t, net=y, demodulated=self.demod, clamp=self.clamp,
                                 clamp_guided=self.clamp_guided)
        if self.residual:  # start from the upsampled (transformed) LR input; see the module doc
            y = y + self.upsample_input(color, batch, j_t, self.demod)
        out = inverse_transform(F.relu(y).float(), self.transform)
        if self.clamp is not None:
            out = self.clamp_to_lr_range(out, color, batch, j_t)
        return self.remodulate(out, batch) if self.demod else out

    def clamp_to_lr_range(self, out: torch.Tensor, color: torch.Tensor, batch: dict, j_t) -> torch.Tensor:
        """``residual_clamp = "lr-range"`` (module doc): ``out`` (B, 3, H, W, linear L_D) clamped per channel to
        the range of the LR input over the taps its residual base reads (``guided.tap_range``; ``color`` is the
        transformed LR input), inverse transformed, widened by ``residual_clamp_margin`` of its width
        (``hr_math.clamp_to_range``: the fused HR stage's step 4b). Piecewise the identity: the gradient reaches
        the network wherever the clamp does not bind."""
        classes = None
        if self.demod and self.by_class:
            classes = (demodulated_mask(current(batch, "lr/fbeta_used")),
                       demodulated_mask(current(batch, "hr/fbeta_used")))
        guides = self.guides(batch) if self.clamp_guided else None
        lo, hi = tap_range(color.float(), int(self.scale), j_t, classes, guides)
        if self.transform == "log1p":
            lo, hi = hr_math.inverse_log1p(lo), hr_math.inverse_log1p(hi)
        return hr_math.clamp_to_range(out, lo, hi, self.clamp)


class FuseSR(FuseSRFrame):
    NAME = "fusesr"
    default_history = 2
    hr_channels = 64
    separable = False
    #: first convs whose input channels ``hr_material`` appends to: ``run.init_from`` zero-pads weights without them
    GROWN_INPUTS = ("hr_branch.0.weight", "refine.0.weight")

    def __init__(self, scale: int, **keys):
        super().__init__(scale, **keys)  # keys: SRModel's; options: FuseSROptions (FuseSRLightOptions)
        self.history = self.default_history if self.config.history < 0 else self.config.history
        opt = self.options
        width, blocks = opt.width, opt.blocks
        s = self.scale
        self.encoder = Encoder(7, opt.norm)
        self.expand = nn.Sequential(conv(ENCODER_CHANNELS[-1], 64), nn.ReLU(inplace=True))
        self.gates = nn.ModuleList([HistoryGate() for _ in range(self.history)])
        cin = 64 + ENCODER_CHANNELS[-1] * self.history + (2 if self.use_jitter else 0)
        self.hr_material = bool(opt.hr_material) and self.use_hr
        hr_in = HR_CHANNELS + (len(HR_MATERIAL_KEYS) if self.hr_material else 0)
        if self.use_hr:
            self.hr_branch = nn.Sequential(conv(hr_in * s * s, self.hr_channels), nn.ReLU(inplace=True))
            cin += self.hr_channels
        make = DWSConv if self.separable else conv
        self.fuse_in = nn.Sequential(make(cin, width), nn.ReLU(inplace=True))
        self.blocks = nn.Sequential(*[ResBlock(width, self.separable) for _ in range(blocks)])
        self.head = conv(width + ENCODER_CHANNELS[0], 3 * s * s)
        self.confidence = self.confidence_head(width + ENCODER_CHANNELS[0])
        self.hr_guide = bool(opt.hr_guide) and self.use_hr
        # HR guidance (deviation, off by default): the refinement sees the 10 HR G-buffer channels at full resolution
        self.refine = nn.Sequential(conv(3 + hr_in, 16), nn.ReLU(inplace=True), conv(16, 3)) if self.hr_guide \
            else conv(3, 3)
        if opt.zero_init_refine and self.residual:  # start at the residual base (module doc)
            last = self.refine[-1] if self.hr_guide else self.refine
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    def needs(self):
        keys = [self.color_key, "lr/depth", "lr/normal", "depth_ref"]
        if self.history:
            keys.append("lr/motion")
        if self.use_hr:
            keys += ["hr/fbeta_used", *HR_GEOMETRY_KEYS, *(HR_MATERIAL_KEYS if self.hr_material else ())]
        if self.demod:
            keys += ["hr/fbeta_used", "hr/emission"]
        if self.residual:
            keys += self.upsample_keys(self.demod)
        return tuple(dict.fromkeys(keys + list(self.fallback_keys()))) + self.jitter_keys()

    def _lr_input(self, batch, back: int):
        color = forward_transform(frame(batch, self.color_key, back), self.transform)
        depth = depth_features(batch, "lr", back, self.depth_norm)
        return torch.cat([color, depth, frame(batch, "lr/normal", back)], dim=1), depth

    def forward(self, batch):
        x, depth_cur = self._lr_input(batch, 0)
        f_s, f_f = self.encoder(x)
        feats = [self.expand(f_f)]
        j_t = self.frame_jitter(batch)
        if j_t is not None:  # the current frame's sub-pixel sample offset, as two constant maps
            feats.append(j_t.to(f_f.dtype).view(-1, 2, 1, 1).expand(-1, -1, *f_f.shape[-2:]))
        if self.history:
            for k, motion in enumerate(history_offsets(batch, self.history, self.use_jitter), start=1):
                xk, dk = self._lr_input(batch, k)
                _, fk = self.encoder(xk)
                warped, valid = backward_warp(torch.cat([fk, dk], dim=1), motion)
                gate = self.gates[k - 1](motion, warped[:, -1:], depth_cur) * valid
                feats.append(warped[:, :-1] * gate)
        if self.use_hr:
            hr = torch.cat([current(batch, "hr/fbeta_used"), self.hr_geometry(batch),
                            *[current(batch, k) for k in (HR_MATERIAL_KEYS if self.hr_material else ())]], dim=1)
            feats.append(self.hr_branch(F.pixel_unshuffle(hr, self.scale)))
        y = self.blocks(self.fuse_in(torch.cat(feats, dim=1)))
        head_in = torch.cat([y, f_s], dim=1)
        y = F.pixel_shuffle(self.head(head_in), self.scale)
        y = self.refine(torch.cat([y, hr.to(y.dtype)], dim=1) if self.hr_guide else y)
        return self.output(self.gated(y, head_in, batch), x[:, :3], batch, j_t)
