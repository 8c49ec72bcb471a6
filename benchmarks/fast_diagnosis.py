"""Two diagnoses of a FuseSR-family network on a dataset split (docs/results-history.md, "The confidence gate and HR
geometry"); one-off measurements, not scores.

    .venv/bin/python benchmarks/fast_diagnosis.py DATASET --split val --model SPEC gate
        per clip: the confidence gate's mean, 1st / 10th percentile, minimum and share below 0.5 over every HR pixel
        of every frame (the model needs ``confidence_gate``)
    .venv/bin/python benchmarks/fast_diagnosis.py DATASET --split val --model SPEC --clip NAME --every 3 bins
        one clip: the share of pixels whose HR F_beta (used) is 1, and the PSNR of the model and of demod-jbu per bin
        of the ground truth's tonemapped brightness (the mean of its channels), on every EVERY-th frame
    .venv/bin/python benchmarks/fast_diagnosis.py DATASET --split val --model SPEC --every 2 transmission
        per clip with HR TRANSMISSION pixels (the flag, docs/clip-format.md): their share, and the PSNR of the model
        and of demod-jbu on them and on the other pixels, on every EVERY-th frame
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BINS = (0.0, 0.2, 0.4, 0.7, 1.01)


def gate_stats(spec: str, clips: list[Path]) -> None:
    from training.evaluate import EvalOptions, evaluate_model
    from training.inference.loading import load_model
    model = load_model(spec, 4)
    module = model.module
    if getattr(module, "confidence", None) is None:
        raise SystemExit(f"{spec}: no confidence gate (model.<M>.confidence_gate)")
    seen = []
    applied = module.confidence_map  # the gate as ``gated`` applies it (with gate_transmission's term)

    def record(head_in, batch):
        out = applied(head_in, batch)
        seen.append(out.detach().float().flatten().numpy())
        return out
    module.confidence_map = record
    for clip in clips:
        seen.clear()
        evaluate_model(model, [str(clip)], EvalOptions(flip=False, scale=4, baseline=None))
        a = np.concatenate(seen)
        print(f"{clip.name}: mean {a.mean():.3f} p1 {np.percentile(a, 1):.3f} p10 {np.percentile(a, 10):.3f} "
              f"min {a.min():.3f} below 0.5 {(a < 0.5).mean():.4f}")


def squared_errors(models: dict, clip: Path, every: int, keep=None) -> dict[str, np.ndarray]:
    """Per model (name -> ``load_model``), the squared errors of every pixel of every EVERY-th frame of ``clip``,
    flattened; ``keep(inputs)`` is called on the first model's inputs of each frame."""
    from gbuffer_export.clip import open_clip
    from training import metrics
    from training.inference.loading import ClipFrames, run_frame
    base, sq = open_clip(clip), {}
    for k, (name, model) in enumerate(models.items()):
        source = ClipFrames(base.at_scale(4), eps=model.demod_eps)
        model.module.follow_reference_filter(source.clip.manifest)
        errors = []
        for f in list(source.frames)[::every]:
            sr, _, inputs = run_frame(model, source, f, str(clip), None)
            errors.append(metrics.squared_error(sr, inputs["hr/radiance"][0, -1].transpose(1, 2, 0)).ravel())
            if k == 0 and keep is not None:
                keep(inputs)
        sq[name] = np.concatenate(errors)
    return sq


def brightness_bins(spec: str, clip: Path, every: int) -> None:
    from training import metrics
    from training.inference.loading import load_model
    lum, unit = [], []

    def keep(inputs):
        lum.append(metrics.tonemapped(inputs["hr/radiance"][0, -1].transpose(1, 2, 0)).mean(dim=1)[0].numpy().ravel())
        unit.append((inputs["hr/fbeta_used"][0, -1] == 1).all(axis=0).ravel())
    sq = squared_errors({n: load_model(n, 4) for n in (spec, "demod-jbu")}, clip, every, keep)
    lum = np.concatenate(lum)
    print(f"{clip.name}: HR F_beta (used) is 1 on {np.concatenate(unit).mean():.3f} of pixels")
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        k = (lum >= lo) & (lum < hi)
        if k.any():
            cells = " ".join(f"{n} {metrics.psnr_from_mse(float(e[k].mean())):.2f}" for n, e in sq.items())
            print(f"brightness [{lo}, {hi}): {k.mean():.3f} of pixels: {cells}")


def transmission(spec: str, clips: list[Path], every: int) -> None:
    from gbuffer_export.conventions import Flag
    from training import metrics
    from training.inference.loading import load_model
    models = {name: load_model(name, 4) for name in (spec, "demod-jbu")}
    for clip in clips:
        mask = []  # read from the flags with numpy's bit operations, apart from the model's arithmetic test
        sq = squared_errors(models, clip, every, lambda inputs: mask.append(
            (inputs["hr/flags"][0, -1, 0].astype(np.int64) & int(Flag.TRANSMISSION)).ravel() > 0))
        t = np.concatenate(mask)
        if not t.any():
            continue
        cells = " | ".join(f"{n}: T {metrics.psnr_from_mse(float(e[t].mean())):.2f} rest "
                           f"{metrics.psnr_from_mse(float(e[~t].mean())):.2f} all {metrics.psnr_from_mse(float(e.mean())):.2f}"
                           for n, e in sq.items())
        print(f"{clip.name}: TRANSMISSION on {t.mean():.3f} of pixels: {cells}", flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("what", choices=("gate", "bins", "transmission"))
    p.add_argument("--split", default="val")
    p.add_argument("--model", required=True, help="pretrained:NAME or a checkpoint")
    p.add_argument("--clip", help="bins: the clip folder's name")
    p.add_argument("--every", type=int, default=3, help="bins, transmission: every EVERY-th frame")
    a = p.parse_args(argv)
    from gbuffer_export.dataset.build import split_clips
    clips = split_clips(a.dataset, a.split)
    if a.what == "gate":
        gate_stats(a.model, clips)
        return 0
    if a.what == "transmission":
        transmission(a.model, clips, a.every)
        return 0
    pick = [c for c in clips if c.name == a.clip]
    if not pick:
        p.error(f"--clip {a.clip!r} is not in the {a.split} split of {a.dataset}")
    brightness_bins(a.model, pick[0], a.every)
    return 0


if __name__ == "__main__":
    sys.exit(main())
