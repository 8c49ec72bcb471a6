"""The training half of ``blendsr demo`` (torch): train FuseSR briefly, evaluate it against the baselines on held-out
clips, write the speed-against-error table, the Pareto plot and a side-by-side image.

``run_training_demo(train_clips, test_clips, out, minutes)`` writes under ``out``:

    run_fusesr/            the training run (config, log, checkpoints; resumed when the demo runs again)
    bench/                 bench_models.{json,csv,md} and pareto.png
    pareto.png             copy of bench/pareto.png
    side_by_side.png       LR (nearest), bicubic, demod-bilinear, FuseSR, ground truth of a middle test frame
                           (tonemapped with the evaluation tonemap)

and returns a JSON-ready summary.
"""
from __future__ import annotations

import shutil
from pathlib import Path

#: Configuration of the brief demo run: small crops, constant learning rate (the time budget sets the length).
DEMO_OVERRIDES = ("data.crop=32", "data.batch_size=4", "optim.lr=5e-4", "optim.scheduler=\"constant\"",
                  "run.checkpoint_every=200", "run.log_every=5")


def run_training_demo(train_clips, test_clips, out, minutes: float, model: str = "fusesr") -> dict:
    from training.bench_models import benchmark
    from training.config import load_config
    from training.train import train

    out = Path(out)
    run_dir = out / f"run_{model.replace('-', '_')}"
    resume = (run_dir / "checkpoints" / "last.pt").is_file()
    cfg = load_config(None, [*DEMO_OVERRIDES, f"model.name=\"{model}\"", "run.max_steps=1000000"])
    cfg.data.clips = [str(c) for c in train_clips]
    from gbuffer_export.clip import open_clip
    w, h = open_clip(train_clips[0]).sizes["lr"]
    cfg.data.crop = min(cfg.data.crop, w, h)
    summary = train(cfg, run_dir, resume=resume, run_overrides={"minutes": float(minutes)})
    ck = run_dir / "checkpoints" / "last.pt"
    models = [("bilinear", "bilinear"), ("bicubic", "bicubic"), ("demod-bilinear", "demod-bilinear"),
              ("demod-jbu", "demod-jbu"), (model, str(ck))]
    bench = benchmark(models, [str(c) for c in test_clips], out / "bench", flip=False)
    shutil.copyfile(out / "bench" / "pareto.png", out / "pareto.png")
    side = side_by_side(str(ck), str(test_clips[0]), out / "side_by_side.png")
    return {"train": {k: summary[k] for k in ("model", "step", "stopped_by", "elapsed_s", "params", "device")
                      if k in summary},
            "bench": bench["rows"], "device": bench["device"], "side_by_side": str(side),
            "pareto": str(out / "pareto.png")}


def side_by_side(checkpoint: str, clip: str, path: Path) -> Path:
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
    for label, spec in (("bicubic", "bicubic"), ("demod-bilinear", "demod-bilinear"), ("model", checkpoint)):
        r = upscale_frame(load_model(spec, src.scale), src, frame)
        panels.append((label if spec != checkpoint else f"{Path(checkpoint).parents[1].name}", r["sr"]))
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
