"""The training half of ``blendsr demo`` (torch): score the shipped pretrained models (``training/pretrained.py``)
and the baselines on the demo's held-out clip, optionally fine-tune one of them (or train it from scratch when no
weights are installed) on the demo's training clip, and write the speed-against-error table, the Pareto plot and a
side-by-side image.

``run_training_demo(train_clips, test_clips, out, minutes)`` writes under ``out``:

    run_<model>/           the fine-tuning run (config, log, checkpoints; resumed when the demo runs again)
    bench/                 bench_models.{json,csv,md} and pareto.png
    pareto.png             copy of bench/pareto.png
    side_by_side.png       LR (nearest), bicubic, demod-bilinear, the best learned model, ground truth of a middle
                           test frame (tonemapped with the evaluation tonemap)

and returns a JSON-ready summary.
"""
from __future__ import annotations

import shutil
from pathlib import Path

#: Configuration of the brief demo run: small crops, constant learning rate (the time budget sets the length).
DEMO_OVERRIDES = ("data.crop=32", "data.batch_size=4", "optim.lr=5e-4", "optim.scheduler=\"constant\"",
                  "run.checkpoint_every=200", "run.log_every=5")
#: Fine-tuning a pretrained model: a smaller learning rate, the pretrained configuration otherwise.
FINETUNE_OVERRIDES = ("data.crop=32", "data.batch_size=4", "optim.lr=1e-4", "optim.scheduler=\"constant\"",
                      "optim.warmup_steps=0", "run.checkpoint_every=200", "run.log_every=5", "data.val_frames=0")


def run_training_demo(train_clips, test_clips, out, minutes: float, model: str = "fusesr-l") -> dict:
    from training.bench_models import benchmark
    from training.config import config_from_checkpoint, load_config
    from training.pretrained import available
    from training.checkpoint import load_checkpoint
    from training.train import train

    out = Path(out)
    pretrained = available()
    models = [("bilinear", "bilinear"), ("bicubic", "bicubic"), ("demod-bilinear", "demod-bilinear"),
              ("demod-jbu", "demod-jbu"), *[(p, p) for p in pretrained]]
    summary = None
    if minutes > 0:
        init = f"pretrained:{model}" if f"pretrained:{model}" in pretrained else ""
        run_dir = out / (f"run_{model.replace('-', '_')}" + ("_finetuned" if init else ""))
        resume = (run_dir / "checkpoints" / "last.pt").is_file()
        if init:  # the pretrained configuration, fine-tuned
            cfg = config_from_checkpoint(load_checkpoint(init)["config"], source=init)
            over = load_config(None, [*FINETUNE_OVERRIDES, "run.max_steps=1000000"])
            cfg.data, cfg.optim, cfg.run = over.data, over.optim, over.run
            cfg.run.init_from = init
        else:
            cfg = load_config(None, [*DEMO_OVERRIDES, f"model.name=\"{model}\"", "run.max_steps=1000000"])
        cfg.data.clips = [str(c) for c in train_clips]
        from gbuffer_export.clip import open_clip
        w, h = open_clip(train_clips[0]).sizes["lr"]
        cfg.data.crop = min(cfg.data.crop, w, h)
        summary = train(cfg, run_dir, resume=resume, run_overrides={"minutes": float(minutes)})
        label = f"{model} ({'fine-tuned ' if init else ''}{minutes:g} min)"
        models.append((label, str(run_dir / "checkpoints" / "last.pt")))
    bench = benchmark(models, [str(c) for c in test_clips], out / "bench", flip=False)
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


def side_by_side(checkpoint: str, clip: str, path: Path, label: str | None = None) -> Path:
    """LR (nearest-neighbour), bicubic, demod-bilinear, the model and the ground truth of the clip's middle frame."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

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
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 2.2), dpi=120)
    for ax, (label, img) in zip(axes, panels):
        tm = metrics.tonemapped(img)[0].permute(1, 2, 0).numpy()
        title = label
        if ref is not None and label != "ground truth" and img.shape == ref.shape:
            title += f"\n{metrics.psnr_tm(img, ref):.2f} dB"
        ax.imshow(np.clip(tm, 0, 1))
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
