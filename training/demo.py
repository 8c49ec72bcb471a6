"""The training half of ``blendsr demo`` (torch): score the shipped pretrained models (``training/pretrained.py``)
and the baselines on the demo's held-out clip, optionally fine-tune one of them (or train it from scratch when no
weights are installed) on the demo's training clip, and write the speed-against-error table, the Pareto plot and a
side-by-side image.

``run_training_demo(train_clips, test_clips, out, steps)`` writes under ``out``:

    run_<model>/           the fine-tuning run (config, log, checkpoints) and demo_run.json (its starting weights'
                           sha256 and its step budget): an interrupted run resumes up to its budget, a finished
                           one is scored again as it is, and other starting weights or another budget start anew
    bench/                 bench_models.{json,csv,md} and pareto.png
    pareto.png             copy of bench/pareto.png
    side_by_side.png       LR (nearest), bicubic, demod-jbu, the best learned model, ground truth of a middle
                           test frame (tonemapped with the evaluation tonemap): whole frames with PSNR, the crop
                           where they differ most at full resolution, and why bicubic rings

and returns a JSON-ready summary.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

#: Configuration of the brief demo run: small crops, constant learning rate (the step budget sets the length: the
#: same number of steps on every machine, so the gain it reports does not depend on the machine's speed).
DEMO_OVERRIDES = ("data.crop=32", "data.batch_size=4", "optim.lr=5e-4", "optim.scheduler=\"constant\"",
                  "run.checkpoint_every=200", "run.log_every=5")
#: Fine-tuning a pretrained model: a smaller learning rate, the pretrained configuration otherwise.
FINETUNE_OVERRIDES = ("data.crop=32", "data.batch_size=4", "optim.lr=1e-4", "optim.scheduler=\"constant\"",
                      "optim.warmup_steps=0", "run.checkpoint_every=200", "run.log_every=5", "data.val_frames=0")


def run_training_demo(train_clips, test_clips, out, steps: int, model: str = "fusesr-l") -> dict:
    from training.bench_models import BenchOptions, benchmark, load_models
    from training.clip_sets import scale_of
    from training.config import config_from_checkpoint, load_config
    from training.pretrained import available
    from training.checkpoint import load_checkpoint
    from training.train import train

    out = Path(out)
    pretrained = available()
    models = [("bilinear", "bilinear"), ("bicubic", "bicubic"), ("demod-bilinear", "demod-bilinear"),
              ("demod-jbu", "demod-jbu"), *[(p, p) for p in pretrained]]
    summary = None
    if steps > 0:
        init = f"pretrained:{model}" if f"pretrained:{model}" in pretrained else ""
        run_dir = out / (f"run_{model.replace('-', '_')}" + ("_finetuned" if init else ""))
        resume = _prepare_run(run_dir, init, steps)
        if init:  # the pretrained configuration, fine-tuned
            cfg = config_from_checkpoint(load_checkpoint(init)["config"], source=init)
            over = load_config(None, [*FINETUNE_OVERRIDES, f"run.max_steps={int(steps)}"])
            cfg.data, cfg.optim, cfg.run = over.data, over.optim, over.run
            cfg.run.init_from = init
        else:
            cfg = load_config(None, [*DEMO_OVERRIDES, f"model.name=\"{model}\"", f"run.max_steps={int(steps)}"])
        cfg.data.clips = [str(c) for c in train_clips]  # a crop larger than the clips shrinks (training.run)
        if not (run_dir / "summary.json").is_file():
            train(cfg, run_dir, resume=resume)
        summary = json.loads((run_dir / "summary.json").read_text())
        label = f"{model} ({'fine-tuned ' if init else ''}{int(steps)} steps)"
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
        result["train"] = {k: summary[k] for k in ("model", "step", "stopped_by", "elapsed_s", "params", "device")
                           if k in summary}
    return result


def _prepare_run(run_dir: Path, init: str, steps: int) -> bool:
    """Whether the demo's run in ``run_dir`` resumes: ``steps`` on the same starting weights (``init``'s sha256, or
    none) in total over however many invocations. A run with other weights or another budget is removed (False);
    one with a checkpoint of the same weights and budget resumes up to the budget (True; a finished one, with its
    summary.json, is scored as it is)."""
    from training.checkpoint import file_sha256
    from training.pretrained import resolve
    want = {"init": init, "init_sha256": file_sha256(resolve(init)) if init else None, "steps": int(steps)}
    mark, last = run_dir / "demo_run.json", run_dir / "checkpoints" / "last.pt"
    try:
        same = json.loads(mark.read_text()) == want
    except (OSError, ValueError):
        same = False
    if not same or not last.is_file():
        shutil.rmtree(run_dir, ignore_errors=True)
        run_dir.mkdir(parents=True)
        mark.write_text(json.dumps(want))
        return False
    return True


def side_by_side(checkpoint: str, clip: str, path: Path, label: str | None = None) -> Path:
    """LR (nearest-neighbour), bicubic, demod-jbu, the model and the ground truth of the clip's middle frame: the
    whole frames, each under its name and PSNR, then the crop where they differ most at full resolution (each pixel
    drawn 2x2 for frames up to 960 wide), and a note on what the PSNR is and why bicubic rings
    (``gbuffer_export.preview.comparison_sheet``)."""
    import numpy as np

    from gbuffer_export.preview import comparison_sheet, save_png
    from training import metrics
    from training.inference import ClipFrames, load_model, upscale_frame

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
