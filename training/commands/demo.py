"""The training half of ``blendsr demo`` (torch): score the shipped pretrained models (``training/pretrained.py``)
and the baselines on the demo's held-out clip, optionally fine-tune one of them (or train it from scratch when no
weights are installed) on the demo's training clip, and write the speed-against-error table, the Pareto plot and a
side-by-side image.

``run_training_demo(train_clips, test_clips, out, steps, threads=0)`` writes under ``out``:

    run_<model>/           the fine-tuning run (config, log, checkpoints, summary.json with the steps it ran and
                           why it stopped) and demo_run.json (its starting weights and their sha256): a rerun on
                           the same weights continues it from its checkpoint up to the budget (a larger budget
                           continues too), one that has run its budget is scored again as it is; other weights, or
                           a budget below the steps already run, start anew
    bench/                 bench_models.{json,csv,md} and pareto.png
    pareto.png             copy of bench/pareto.png
    side_by_side.png       LR (nearest), bicubic, demod-jbu, the best learned model, ground truth of a middle
                           test frame (tonemapped with the evaluation tonemap): whole frames with PSNR, the crop
                           where they differ most at full resolution, and why bicubic rings

and returns a JSON-ready summary. The fine-tune is scored only after it has run its whole budget: stopped before
(SIGTERM during a step: ``training.train`` stops after it and records the steps run), the training half raises
``FineTuneStopped`` (a KeyboardInterrupt: the demo stops; the same command continues it). Every row, the plot and
the summary name the steps the run made (from its summary.json), never the budget asked for.
"""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

from gbuffer_export.clip import write_json_atomic

logger = logging.getLogger(__name__)

#: Configuration of the brief demo run: small crops, constant learning rate (the step budget sets the length: the
#: same number of steps on every machine, so the gain it reports does not depend on the machine's speed).
DEMO_OVERRIDES = ("data.crop=32", "data.batch_size=4", "optim.lr=5e-4", "optim.scheduler=\"constant\"",
                  "run.checkpoint_every=200", "run.log_every=5")
#: Fine-tuning a pretrained model: a smaller learning rate, the pretrained configuration otherwise.
FINETUNE_OVERRIDES = ("data.crop=32", "data.batch_size=4", "optim.lr=1e-4", "optim.scheduler=\"constant\"",
                      "optim.warmup_steps=0", "run.checkpoint_every=200", "run.log_every=5", "data.val_frames=0")


class FineTuneStopped(KeyboardInterrupt):
    """The fine-tune stopped before its budget (a signal): the demo stops instead of scoring it."""


def run_training_demo(train_clips, test_clips, out, steps: int, model: str = "fusesr-l", threads: int = 0) -> dict:
    from training.bench import BenchOptions, benchmark, load_models
    from training.clip_sets import scale_of
    from training.device import set_threads
    from training.pretrained import available

    out = Path(out)
    set_threads(threads)  # the scoring's threads; the fine-tune sets run.threads the same way
    pretrained = available()
    models = [("bilinear", "bilinear"), ("bicubic", "bicubic"), ("demod-bilinear", "demod-bilinear"),
              ("demod-jbu", "demod-jbu"), *[(p, p) for p in pretrained]]
    summary = None
    if steps > 0:
        init = f"pretrained:{model}" if f"pretrained:{model}" in pretrained else ""
        run_dir = out / (f"run_{model.replace('-', '_')}" + ("_finetuned" if init else ""))
        summary = fine_tune(run_dir, model, init, train_clips, steps, threads)
        label = f"{model} ({'fine-tuned ' if init else ''}{int(summary['step'])} steps)"
        models.append((label, str(run_dir / "checkpoints" / "last.pt")))
    clips = [str(c) for c in test_clips]
    bench = benchmark(load_models(models, scale_of(clips)), clips, out / "bench", BenchOptions(flip=False))
    shutil.copyfile(out / "bench" / "pareto.png", out / "pareto.png")
    learned = [r for r in bench["rows"] if r["model"] not in dict(models[:4])]
    best = max(learned, key=lambda r: r["psnr"])["model"] if learned else None
    side = side_by_side(dict(models)[best], str(test_clips[0]), out / "side_by_side.png", best) if best else None
    result = {"bench": bench["rows"], "device": bench["device"], "pretrained": pretrained,
              "side_by_side": str(side) if side else None, "pareto": str(out / "pareto.png")}
    if summary is not None:
        result["train"] = {k: summary[k] for k in ("model", "step", "max_steps", "stopped_by", "elapsed_s", "params",
                                                   "device", "threads") if k in summary}
    return result


def fine_tune(run_dir: Path, model: str, init: str, train_clips, steps: int, threads: int = 0) -> dict:
    """The demo's fine-tune (or training from scratch, ``init`` empty) in ``run_dir``, run or continued up to
    ``steps``; returns its summary.json, which records the steps run. FineTuneStopped when it stopped before."""
    from training.checkpoint import load_checkpoint
    from training.config import config_from_checkpoint, load_config
    from training.train import train
    done = _finished(run_dir, steps)
    if done is not None:
        return done
    resume = _prepare_run(run_dir, init, steps)
    over = [f"run.max_steps={int(steps)}", f"run.threads={int(threads)}"]
    if init:  # the pretrained configuration, fine-tuned
        cfg = config_from_checkpoint(load_checkpoint(init)["config"], source=init)
        sections = load_config(None, [*FINETUNE_OVERRIDES, *over])
        cfg.data, cfg.optim, cfg.run = sections.data, sections.optim, sections.run
        cfg.run.init_from = init
    else:
        cfg = load_config(None, [*DEMO_OVERRIDES, f"model.name=\"{model}\"", *over])
    cfg.data.clips = [str(c) for c in train_clips]  # a crop larger than the clips shrinks (training.run)
    summary = train(cfg, run_dir, resume=resume)
    if int(summary["step"]) < int(steps):
        logger.warning(f"the fine-tune stopped at step {summary['step']} of {steps} ({summary.get('stopped_by')}): "
                       "not scored; the same command continues it from its checkpoint")
        raise FineTuneStopped(f"the fine-tune stopped at step {summary['step']} of {steps} "
                              f"({summary.get('stopped_by')}); the same command continues it")
    return summary


def _finished(run_dir: Path, steps: int) -> dict | None:
    """The run's summary.json when it has run exactly ``steps`` steps (and its marker is there), else None."""
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    ok = (run_dir / "demo_run.json").is_file() and (run_dir / "checkpoints" / "last.pt").is_file()
    return summary if ok and int(summary.get("step", -1)) == int(steps) else None


def _prepare_run(run_dir: Path, init: str, steps: int) -> bool:
    """Whether the demo's run in ``run_dir`` continues (True) or starts anew (False, the folder emptied). It
    continues from its checkpoint when it started from the same weights (``init`` and their sha256, or none) and
    has not run more than ``steps`` steps: an interrupted run, or a finished one given a larger budget. Its summary
    is removed first: a run is recorded as done only when it writes one again."""
    from training.checkpoint import file_sha256, load_checkpoint
    from training.pretrained import resolve
    want = {"init": init, "init_sha256": file_sha256(resolve(init)) if init else None}
    mark, last = run_dir / "demo_run.json", run_dir / "checkpoints" / "last.pt"
    try:
        same = json.loads(mark.read_text()) == want and int(load_checkpoint(last)["step"]) <= int(steps)
    except (OSError, ValueError, KeyError):
        same = False
    if not same:
        shutil.rmtree(run_dir, ignore_errors=True)
        run_dir.mkdir(parents=True)
        write_json_atomic(mark, want)
        return False
    (run_dir / "summary.json").unlink(missing_ok=True)
    return True


def side_by_side(checkpoint: str, clip: str, path: Path, label: str | None = None) -> Path:
    """LR (nearest-neighbour), bicubic, demod-jbu, the model and the ground truth of the clip's middle frame: the
    whole frames, each under its name and PSNR, then the crop where they differ most at full resolution (each pixel
    drawn 2x2 for frames up to 960 wide), and a note on what the PSNR is and why bicubic rings
    (``gbuffer_export.preview.comparison_sheet``)."""
    import numpy as np

    from gbuffer_export.preview import comparison_sheet, save_png
    from training import metrics
    from training.inference.loading import ClipFrames, load_model, upscale_frame

    src = ClipFrames(clip)
    frame = src.frames[len(src.frames) // 2]
    panels = []
    lr = src.read(frame, "lr/radiance")
    panels.append(("LR (nearest)", np.repeat(np.repeat(lr, src.scale, 0), src.scale, 1)))
    ref = None
    for name, spec in (("bicubic", "bicubic"), ("demod-jbu", "demod-jbu"), ("model", checkpoint)):
        r = upscale_frame(load_model(spec, src.scale), src, frame)
        panels.append((name if spec != checkpoint else (label or Path(checkpoint).parents[1].name), r["sr"]))
        ref = r.get("reference")
    if ref is not None:
        panels.append(("ground truth", ref))
    shown, psnr = [], {}
    for name, img in panels:
        lines = [name]
        if ref is not None and name != "ground truth" and img.shape == ref.shape:
            psnr[name] = float(metrics.psnr_tm(img, ref))
            lines.append(f"PSNR {psnr[name]:.2f} dB")
        elif name == "ground truth":
            lines.append(f"frame {frame}")
        shown.append((lines, metrics.tonemapped(img)[0].permute(1, 2, 0).numpy()))
    below = psnr.get("bicubic", 0.0) < psnr.get("LR (nearest)", 0.0)
    notes = [f"{Path(clip).name}, frame {frame}, x{src.scale}. PSNR on the tonemapped frame (Reinhard, sRGB) "
             "against the ground truth, this frame only.",
             "bicubic rings, as it must on HDR radiance: its kernel has negative lobes, so next to an emitter "
             "(radiance far above its surroundings) it undershoots below 0 and is clamped to 0, a black halo"
             + (" - which is why it scores below nearest neighbour here." if below else ".")
             + " demod-jbu and the learned models upsample demodulated irradiance (emission subtracted first) "
               "and do not ring there."]
    w = shown[0][1].shape[1]
    save_png(path, comparison_sheet(shown, zoom=2 if w <= 960 else 1, notes=notes))
    return path
