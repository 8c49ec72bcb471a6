"""``blendsr demo``: the whole story on this machine, small enough to run in minutes.

1. render two small clips of one scene of the built-in generator that no shipped weights were trained on, along
its camera path: the frames to score, and the frames right after them (the same scene and camera moving on),
2. validate them, 3. write a PNG contact sheet, then, when the training extras are installed, 4. fine-tune the
shipped pretrained FuseSR-l briefly on the later frames, as a user fine-tunes on their own scene (or train it from
scratch when no weights are installed), 5. evaluate the pretrained models, the fine-tuned one and the baselines on
the frames the fine-tune never saw,
6. write the speed-against-error table, the Pareto plot and a side-by-side image (LR, bicubic, demod-jbu, the best
learned model, ground truth).

SIGINT (Ctrl-C) and SIGTERM stop it within seconds wherever it is: a render stops after its pass in progress, the
fine-tune after its step (its checkpoint kept; the steps it ran recorded, not its budget), the scoring at once; the
same command then continues where it stopped. The fine-tune is scored only once it has run its whole budget, and
every table, plot and summary names the steps it ran."""
from __future__ import annotations

import argparse
import contextlib
import importlib.util
import signal
import subprocess
import sys
import time
from pathlib import Path

from ..extras import HelpFormatter


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", type=Path, default=Path("demo_out"), help="output folder")
    p.add_argument("--hr-size", default="256x144", help="HR resolution WxH in pixels")
    p.add_argument("--frames", default="1:12",
                   help="frames A:B of the clip to score; the fine-tuning clip is as many frames right after them")
    p.add_argument("--hr-spp", type=int, default=32, help="ground-truth samples per pixel")
    p.add_argument("--hr-denoise", action=argparse.BooleanOptionalAction, default=True,
                   help="denoise the ground truth with OpenImageDenoise")
    p.add_argument("--lr-spp", type=int, default=64,
                   help="LR samples per pixel (point-sampled: many samples give a clean, aliased LR frame like a "
                        "rasteriser's, for about 1/16 of the HR cost per sample at 4x)")
    p.add_argument("--train-steps", type=int, default=2000,
                   help="fine-tuning (or, without shipped weights, training) budget in optimiser steps (batch 4, LR "
                        "crop 32), in total over reruns into the same folder on the same shipped weights; the time it "
                        "took is printed and written to demo_summary.json (0: only evaluate)")
    p.add_argument("--test-seed", type=int, default=90,
                   help="built-in scene seed of the demo's scene (the shipped weights saw seeds 0-41, "
                        "dataset_large.toml adds 42-71)")
    p.add_argument("--threads", type=int, default=0,
                   help="CPU threads of the renders, the fine-tune and the scoring (0: the cores idle when it "
                        "starts: those this process may use (CPU affinity, cgroup CPU quota) less those other work "
                        "keeps busy; with two busy processes on 2 cores, 1 thread fine-tuned 8x faster than 2; "
                        "make demo THREADS=N)")
    p.add_argument("--render-only", action="store_true", help="stop after the contact sheet")


def _step(msg: str) -> float:
    print(f"\n== {msg}", flush=True)
    return time.perf_counter()


#: Seconds a render step is given to stop after its pass in progress once the demo is interrupted, then killed (its
#: clip then stays as consistent as after kill -9, and resumes: docs/clip-format.md).
STOP_GRACE_S = 5.0


def _cli(*args) -> None:
    cmd = [sys.executable, "-m", "gbuffer_export.cli", *map(str, args)]
    print("$ blendsr " + " ".join(map(str, args)), flush=True)
    proc = subprocess.Popen(cmd)
    try:
        code = proc.wait()
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM (stop_on_signals): the step stops too, within seconds
        with contextlib.suppress(ValueError, OSError):
            proc.send_signal(signal.SIGINT if sys.platform != "win32" else signal.SIGTERM)
        try:
            proc.wait(STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        raise
    if code != 0:
        raise SystemExit(f"blendsr: error: demo step failed (exit {code}): blendsr {' '.join(map(str, args))}")


@contextlib.contextmanager
def stop_on_signals():
    """Within the block SIGTERM is KeyboardInterrupt as SIGINT is: the demo stops where it is, and the CLI prints its
    resume line (exit 130). The fine-tune's loop turns SIGTERM into a stop after its step while it runs
    (training.train), and the training half then stops the demo."""
    try:
        previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    except ValueError:  # not the main thread: nothing to replace
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def run(args) -> int:
    with stop_on_signals():
        return _run(args)


def _run(args) -> int:
    from ..clip import open_clip, write_json_atomic
    from ..preview import contact_sheet
    from ..validate import validate_clip

    from ..extras import require
    require("blendsr demo", "render")  # renders first; the training half runs only with [train] (see above)
    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    from ..config import parse_frames
    from . import flags_named
    seed = args.test_seed
    with flags_named(args):
        a, b = parse_frames(args.frames)
    later = f"{b + 1}:{2 * b - a + 1}"
    threads = _threads(args.threads)  # the renders' too (Cycles' AUTO threads do not read the cgroup quota)
    clips = {"test": (out / "clips" / f"test_seed{seed}", args.frames),
             "finetune": (out / "clips" / f"finetune_seed{seed}_frames{later.replace(':', '-')}", later)}
    t = _step(f"render built-in scene {seed}: frames {args.frames} (to score) and {later} (to fine-tune on)")
    for _, (path, frames) in clips.items():
        _cli("render", "-o", path, "--seed", seed, "--hr-size", args.hr_size, "--frames", frames,
             "--hr-spp", args.hr_spp, "--lr-spp", args.lr_spp, "--device", "cpu", "--buffers", "all",
             "--hr-denoise" if args.hr_denoise else "--no-hr-denoise",  # all: every shipped network is scored
             "--threads", threads)
    print(f"   {time.perf_counter() - t:.0f} s")
    _step("validate")
    for name, (path, _) in clips.items():
        rep = validate_clip(path)
        print(f"   {name}: {rep.summary_line()}")
        if not rep.ok:
            for f in rep.errors:
                print("   " + f.line())
            return 1
    sheet = contact_sheet(open_clip(clips["test"][0]), out / "contact_sheet.png")
    print(f"   contact sheet: {sheet}")
    if args.render_only:
        return 0
    run_training_demo = _training_half()
    if run_training_demo is None:
        print("   torch or the training package is not installed: skipping training (pip install 'blendsr[train]')")
        return 0
    (out / "demo_summary.json").unlink(missing_ok=True)  # written again only once this run has scored
    summary = run_training_demo(train_clips=[clips["finetune"][0]], test_clips=[clips["test"][0]], out=out,
                                steps=args.train_steps, threads=threads)
    if "train" in summary:
        t = summary["train"]
        print(f"   fine-tune: {t.get('step')} steps run in {float(t.get('elapsed_s', 0.0)):.0f} s on {t.get('device')}"
              f" ({t.get('threads')} threads)")
    write_json_atomic(out / "demo_summary.json", summary)
    print(f"\nDone. Look at {out}/contact_sheet.png, {out}/side_by_side.png and {out}/pareto.png")
    return 0


def _threads(asked: int) -> int:
    """The demo's threads: ``asked``, or with 0 the cores idle now (``resources.idle_cores``), said in one line."""
    if asked:
        return int(asked)
    from ..resources import idle_cores, usable_cores
    threads, busy = idle_cores()
    print(f"   threads: {threads} ({usable_cores()} usable core(s), {busy:.1f} kept busy by other work; "
          "--threads or make demo THREADS= sets it)")
    return threads


def _training_half():
    """The function of the entry point ``blendsr.demo`` 'training' (the torch layer's), or None without torch."""
    from importlib import metadata
    if importlib.util.find_spec("torch") is None:
        return None
    for ep in metadata.entry_points(group="blendsr.demo"):
        if ep.name == "training":
            return ep.load()
    return None


def register(sub) -> None:
    p = sub.add_parser("demo", help="render, validate, train briefly and evaluate on the built-in scene",
                       description=__doc__, formatter_class=HelpFormatter)
    add_arguments(p)
    p.set_defaults(func=run)
