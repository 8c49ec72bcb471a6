"""Recurrent models (torch): running a model that carries a state from frame to frame.

A recurrent model (class attribute ``recurrent = True``, e.g. ``rdg``) has ``step(batch, state, reset=None) ->
(SR, state)`` for the last frame of ``batch``; ``state`` is a list of tensors (``model.state_shapes``), None at a
clip's first frame. Training feeds windows of ``data.window`` consecutive frames with a target for every frame
(``window_losses``): the state is carried across the window and detached every ``data.detach_every`` frames
(truncated back-propagation: each chunk is back-propagated as soon as it is complete, so only one chunk's graph is
held). Evaluation, ``upscale``, the add-on preview and ``bench models`` run a clip's frames in order with the state
reset at its first frame: ``training.inference.model.InferenceModel.step`` holds the state, ``lead_in`` says which
frames lead to a frame asked out of order.
"""
from __future__ import annotations

import torch

from training.models.window import frame_slice, window_length


def is_recurrent(model) -> bool:
    return bool(getattr(model, "recurrent", False))


def detach_state(state):
    return None if state is None else [s.detach() for s in state]


def window_losses(net, criterion, batch: dict, detach_every: int, backward, temporal: bool,
                  autocast_ctx, baseline=None) -> tuple[torch.Tensor, dict, torch.Tensor]:
    """Run ``net`` (``net(batch, state) -> (SR, state)``, a ``StepWrapper``) over the T frames of a window batch,
    the loss averaged over frames (``baseline(frame batch)``: the baseline's SR of that frame, or None). Every
    ``detach_every`` frames the summed loss of the chunk (divided by T) is
    back-propagated by ``backward(loss)`` and the state detached. Returns (total loss, {term: mean over frames}, SR of the last frame) with the loss detached. The
    temporal term is averaged over the T - 1 consecutive pairs, the others over the T frames."""
    t_len = window_length(batch)
    state = None
    total = 0.0
    sums: dict[str, float] = {}
    chunk = None
    sr_prev = None
    sr = None
    for t in range(t_len):
        sub = frame_slice(batch, t)
        with autocast_ctx():
            sr, state = net(sub, state)
            sr = sr.float()
        gt = batch["hr/radiance"][:, t]
        use_temporal = temporal and t > 0
        loss, terms = criterion(sr, gt, sr_prev if use_temporal else None,
                                batch["hr/radiance"][:, t - 1] if use_temporal else None,
                                batch["hr/motion"][:, t] if use_temporal and "hr/motion" in batch else None,
                                baseline(sub) if baseline is not None else None)
        for k, v in terms.items():
            sums[k] = sums.get(k, 0.0) + float(v.detach())
        if "temporal" in terms:  # the mean over the T - 1 frame pairs, so that loss = sum of weight x term
            w = criterion.cfg.temporal_weight * terms["temporal"]
            loss = (loss - w) / t_len + w / (t_len - 1)
        else:
            loss = loss / t_len
        chunk = loss if chunk is None else chunk + loss
        total += float(loss.detach())
        if not bool(torch.isfinite(loss.detach())):
            return torch.tensor(float("nan")), {k: torch.tensor(v / (t + 1)) for k, v in sums.items()}, sr.detach()
        sr_prev = sr
        if (t + 1) % detach_every == 0 or t == t_len - 1:
            backward(chunk)
            chunk = None
            state = detach_state(state)
            sr_prev = sr_prev.detach()
    # terms: the temporal term exists for T - 1 frames
    counts = {k: (t_len - 1 if k == "temporal" else t_len) for k in sums}
    return torch.tensor(total), {k: torch.tensor(v / counts[k]) for k, v in sums.items()}, sr.detach()


class StepWrapper(torch.nn.Module):
    """``forward(batch, state)`` = ``model.step(batch, state)``, so DDP / torch.compile see the step."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, batch, state=None):
        return self.model.step(batch, state)


