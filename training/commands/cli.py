"""``blendsr train | evaluate | upscale | export``: argument parsing only; torch is imported inside the functions."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from gbuffer_export.errors import BlendSRError

from gbuffer_export.extras import HelpFormatter, require
from training.clip_sets import dataset_clips as _dataset_clips
from training.clip_sets import scale_of as _scale_of

FMT = HelpFormatter


def add_model_source(p: argparse.ArgumentParser) -> None:
    """--checkpoint CK | --model NAME, exactly one: the model that evaluate, upscale and export run."""
    from training.pretrained import PREFIX, PRETRAINED  # torch-free
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--checkpoint", metavar="CK",
                   help="checkpoint file of 'blendsr train', or pretrained:NAME for the shipped weights "
                        f"({', '.join(PREFIX + n for n in PRETRAINED)}; training/pretrained.py)")
    g.add_argument("--model", metavar="NAME", help="non-learned model: bilinear, bicubic, demod-bilinear, demod-jbu")


def register(subparsers) -> None:
    """The train, evaluate, upscale and export commands."""
    for add in (_register_train, _register_evaluate, _register_upscale, _register_export):
        add(subparsers)


def _register_train(subparsers) -> None:
    p = subparsers.add_parser(
        "train", formatter_class=FMT, help="train a model on exported clips",
        description="Train a super-resolution model on BlendSR clips. Configuration: defaults < --config TOML < "
                    "--set overrides < --max-steps/--minutes. The run directory receives config.toml, log.csv, "
                    "checkpoints/ and summary.json; see docs/training.md.")
    p.add_argument("--model", help="model name (see 'blendsr train --list-models'); overrides model.name")
    p.add_argument("--data", nargs="+", metavar="CLIP", default=[],
                   help="training clip directories, or dataset folders (their train split; their val split "
                        "becomes data.val_clips unless set)")
    p.add_argument("-o", "--output", metavar="RUN_DIR", help="run directory (created)")
    p.add_argument("--config", metavar="FILE", help="TOML configuration ([data] [model] [loss] [optim] [run])")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one configuration value (TOML literal), repeatable, e.g. --set data.crop=48")
    p.add_argument("--max-steps", type=int, metavar="N",
                   help="train until step N (run.max_steps, also the length of the cosine schedule); alone it "
                        "clears run.minutes, with --minutes the run stops at whichever comes first")
    p.add_argument("--minutes", type=float, metavar="M",
                   help="stop after M minutes of this invocation (run.minutes; run.max_steps stays a cap and the "
                        "schedule's length: give --max-steps too so that the learning rate decays in time)")
    p.add_argument("--resume", action="store_true", help="continue RUN_DIR/checkpoints/last.pt")
    p.add_argument("--list-models", action="store_true", help="print the model table and exit")
    p.set_defaults(func=cmd_train)


def _register_evaluate(subparsers) -> None:
    p = subparsers.add_parser(
        "evaluate", formatter_class=FMT, help="score a model against the HR ground truth",
        description="Evaluate a checkpoint or a non-learned model on clips: PSNR/SSIM on the declared tonemap, "
                    "PSNR on linear HDR (peak 1), HDR-FLIP, temporal PSNR, warping error, ms per frame. "
                    "Writes JSON (docs/evaluation.md describes every key).")
    add_model_source(p)
    p.add_argument("--data", nargs="+", required=True, metavar="CLIP",
                   help="clip directories, or dataset folders (their --split)")
    p.add_argument("--split", default="test", choices=("train", "val", "test"),
                   help="split of dataset folders given to --data")
    p.add_argument("--json", required=True, metavar="OUT", help="output JSON file")
    p.add_argument("--save-images", metavar="DIR", help="also write SR EXR + tonemapped PNG per frame")
    p.add_argument("--frames", metavar="A:B", help="inclusive frame range (default: all finished frames)")
    p.add_argument("--no-flip", action="store_true", help="skip HDR-FLIP (about 4 s per 1080p frame on a CPU)")
    p.add_argument("--cvvdp", action="store_true",
                   help="also ColorVideoVDP per clip (JOD; flicker and shimmer over the frames, on the display model "
                        "'standard_fhd'; docs/evaluation.md): the [video] extra")
    p.add_argument("--delta-e-itp", action="store_true",
                   help="also score Delta E ITP (HDR colour difference, radiance 1 shown at 203 cd/m^2)")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"), help="where the model runs")
    p.add_argument("--amp", default="none", choices=("none", "bf16", "fp16", "auto"),
                   help="autocast precision of the model")
    p.add_argument("--warmup", type=int, default=2, help="untimed runs before timing")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: the cores this process may use)")
    p.add_argument("--compile", action="store_true",
                   help="torch.compile the inference fast path (CUDA graphs on a GPU; compiling takes a while)")
    add_path_flag(p)
    p.add_argument("--set", action="append", default=[], metavar="model.KEY=VALUE",
                   help="configuration of a non-learned --model (TOML value), e.g. "
                        "model.demod-jbu.guide_sigma_depth=0.05; of a --checkpoint only its inference options, "
                        "e.g. model.fusesr.residual_clamp=lr-range (also written CK?residual_clamp=lr-range)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (one per clip)")
    p.set_defaults(func=cmd_evaluate)


def _register_upscale(subparsers) -> None:
    p = subparsers.add_parser(
        "upscale", formatter_class=FMT, help="write the super-resolved EXR sequence of a clip",
        description="Upscale every frame of a clip; writes OUT_DIR/NNNNNN.exr (linear Rec.709 RGB float32) and "
                    "OUT_DIR/upscale.json (model, ms per frame).")
    add_model_source(p)
    p.add_argument("--clip", required=True, help="clip directory")
    p.add_argument("-o", "--output", required=True, metavar="OUT_DIR", help="output directory")
    p.add_argument("--frames", metavar="A:B", help="inclusive frame range (default: all)")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"), help="where the model runs")
    p.add_argument("--amp", default="none", choices=("none", "bf16", "fp16", "auto"),
                   help="autocast precision of the model")
    p.add_argument("--compile", action="store_true", help="torch.compile the inference fast path")
    add_path_flag(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=cmd_upscale)


def _register_export(subparsers) -> None:
    p = subparsers.add_parser(
        "export", formatter_class=FMT, help="export a model to ONNX and check it against torch",
        description="Export to ONNX (opset 17, dynamic batch/height/width), run it with onnxruntime on the same "
                    "inputs and compare with torch. Inputs: the model's keys in order, each (B, T, C, H, W), plus "
                    "depth_ref (B, T); see OUT.onnx.json.")
    add_model_source(p)
    p.add_argument("--onnx", required=True, metavar="OUT.onnx", help="output ONNX file")
    p.add_argument("--clip", help="take the example input from this clip (default: random inputs)")
    p.add_argument("--scale", type=int, default=4, help="scale of a non-learned model (checkpoints know theirs)")
    p.add_argument("--hr-size", default="128x72", metavar="WxH", help="HR size of random example inputs")
    p.add_argument("--opset", type=int, default=17, help="ONNX opset")
    p.set_defaults(func=cmd_export)


#: ``--path``'s choices (``training.inference.fastpath.PATH_CHOICES``; written here: the CLI imports no torch to register)
PATH_CHOICES = ("auto", "reference", "fast", "fused", "graph")


def add_path_flag(p) -> None:
    p.add_argument("--path", default=None, choices=PATH_CHOICES,
                   help="inference path (default: $BLENDSR_INFERENCE_PATH, else auto): auto (the fastest that "
                        "passes the fp32 reference check on the first frame: graph, else fused, else fast; logged and recorded in the output), reference (fp32 "
                        "eager, the model as built), fast (fast ops, autocast), fused (fused HR stage, weights held "
                        "in the precision), graph (fused as one compiled graph on the CPU, one CUDA graph per "
                        "frame on a GPU); docs/evaluation.md, 'Inference paths'")


def refuse_dataset(path, option: str) -> None:
    """A dataset folder given where one clip is expected (``option``: the flag) is one line naming what to pass:
    ``--clip DATASET: this is a dataset ...: pass DATASET/clips/ID``, with a clip of its index as the example."""
    from gbuffer_export.dataset.build import DatasetError, INDEX, clip_dir, is_dataset, read_index
    root = Path(path)
    if not is_dataset(root):
        return
    example = ""
    try:
        entries = read_index(root)["clips"]
        if entries:
            example = f" (e.g. {clip_dir(root, entries[0])})"
    except (BlendSRError, OSError):
        pass
    raise DatasetError(f"{option} {root}: this is a dataset (it holds {INDEX}), not a clip: pass "
                       f"{root / 'clips' / 'ID'}, one of its clips{example}")


def _frames(text: str | None):
    from gbuffer_export.config import parse_frames
    rng = parse_frames(text)
    return None if rng is None else list(range(rng[0], rng[1] + 1))


def cmd_train(args) -> int:
    require("blendsr train", "train")
    from training.config import load_config
    from training.models import MODELS
    if args.list_models:
        for name, info in MODELS.items():
            print(f"{name:16s} {'learned' if info.learned else 'fixed  '}  {info.description}")
        return 0
    if not args.output:
        raise BlendSRError("train: -o RUN_DIR is required")
    overrides = list(args.set)
    if args.model:
        overrides.append(f'model.name="{args.model}"')
    run_overrides = {}
    if args.max_steps is not None:  # alone, a step budget replaces a time budget (also one saved in a checkpoint)
        run_overrides["max_steps"] = args.max_steps
        run_overrides["minutes"] = 0.0
    if args.minutes is not None:
        run_overrides["minutes"] = args.minutes
    data, val = _dataset_clips(args.data, "train"), _dataset_clips(args.data, "val", missing_ok=True)
    if args.resume and not (args.config or overrides):
        cfg = None  # the checkpoint's configuration; clips repeated alone must be its own (training.run.resume_run)
    else:
        cfg = load_config(args.config, overrides)
        for note in cfg.notes:
            print(f"note: {note}", file=sys.stderr)
        if data:
            cfg.data.clips = [str(c) for c in data]
            if val and not cfg.data.val_clips:
                cfg.data.val_clips = [str(c) for c in val]
        if not args.resume and not args.model and not args.config:
            raise BlendSRError("train: --model NAME is required (or model.name in --config)")
    from training.train import train
    from training.trainer import TrainingError
    try:
        train(cfg, args.output, resume=args.resume, run_overrides=run_overrides,
              data=[str(c) for c in data] if cfg is None else None)
    except TrainingError as exc:
        print(f"blendsr: error: {exc}", file=sys.stderr)
        return 1
    return 0


def _check_radiance(clips, frames) -> None:
    """Refuse radiance that 'blendsr validate' refuses (non-finite, negative on surfaces), in its words, before
    anything is scored (gbuffer_export.validate.values.check_clip_radiance)."""
    from gbuffer_export.clip import open_clip
    from gbuffer_export.validate.values import check_clip_radiance
    for c in clips:
        clip = open_clip(c)
        check_clip_radiance(clip, [f for f in frames if f in clip.frames] if frames else None)


def cmd_evaluate(args) -> int:
    require("blendsr evaluate", "train")
    from gbuffer_export.clip import write_json_atomic
    from training.evaluate import evaluate_model
    from training.inference.loading import load_model
    from training.device import resolve_device, set_threads
    set_threads(args.threads)
    args.data = [str(c) for c in _dataset_clips(args.data, args.split)]
    _check_radiance(args.data, _frames(args.frames))
    scale = _scale_of(args.data)
    spec = args.checkpoint or args.model
    from training.inference.fastpath import default_path, path_record, prepare_inference
    model = load_model(spec, scale, args.set, fast=False)
    prepare_inference(model, resolve_device(args.device), args.amp, compile=args.compile,
                      path=args.path or default_path())
    frames = _frames(args.frames)
    from training.evaluate import EvalOptions
    result = evaluate_model(model, args.data, EvalOptions(
        frames={str(c): frames for c in args.data} if frames else None, amp=None,
        flip=not args.no_flip, delta_e_itp=args.delta_e_itp, save_images=args.save_images, warmup=args.warmup,
        progress=not args.no_progress, cvvdp=args.cvvdp))
    result["amp"] = args.amp  # the precision asked; result["inference"] names the one that ran
    result["inference"] = path_record(model)
    write_json_atomic(args.json, result)
    from training.evaluate import worst_case_line
    m = result["mean"]
    print(f"{result['model']}: PSNR {m['psnr']:.2f} dB  SSIM {m['ssim']:.4f}  PSNR-HDR {m['psnr_hdr']:.2f} dB  "
          f"FLIP {m['flip'] if m['flip'] is None else round(m['flip'], 4)}  {m['ms_per_frame']:.2f} ms/frame  "
          f"({m['frames']} frames, {result['device']}) -> {args.json}")
    for key, what in (("regions", "region"), ("materials", "material")):
        if m.get(key):
            print(f"  error by {what} (pixels, share of the squared error, PSNR): " + "; ".join(
                f"{name} {v['fraction']:.1%}, {v['err_share']:.0%}, {v['psnr']:.2f} dB"
                for name, v in m[key].items() if v["psnr"] is not None and v["err_share"] is not None))
    if result["cvvdp"] is not None:
        print(f"  ColorVideoVDP {m['cvvdp']:.3f} JOD (mean of {len(result['per_clip'])} clip(s): " + ", ".join(
            f"{Path(c['clip']).name} {c['cvvdp']:.3f}" for c in result["per_clip"])
            + f"; display {result['cvvdp']['display']})")
    print(worst_case_line(result))
    return 0


def cmd_upscale(args) -> int:
    require("blendsr upscale", "train")
    from gbuffer_export.clip import write_json_atomic
    from gbuffer_export.exr import write_exr
    from gbuffer_export.validate.gate import open_valid_clip
    from training.inference.loading import ClipFrames, load_model, upscale_frame
    from training.device import resolve_device
    refuse_dataset(args.clip, "--clip")
    clip = open_valid_clip(args.clip, tolerate=("non-finite",))  # non-finite input: warned, output made finite
    from training.inference.fastpath import prepare_inference
    from training.inference.fastpath import default_path, path_record
    model = load_model(args.checkpoint or args.model, clip.scale, fast=False)
    prepare_inference(model, resolve_device(args.device), args.amp, compile=args.compile,
                      path=args.path or default_path())
    source = ClipFrames(clip, eps=model.demod_eps)
    frames = _frames(args.frames) or clip.frames
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    times, nonfinite = {}, {}
    from training.evaluate import sanitize_output
    iterator = frames
    if not args.no_progress:
        from tqdm import tqdm
        iterator = tqdm(frames, desc=f"upscale {Path(args.clip).name}", unit="frame", file=sys.stderr,
                        dynamic_ncols=True)
    for f in iterator:
        r = upscale_frame(model, source, f)
        sr, bad = sanitize_output(r["sr"])  # never an EXR with NaN pixels: 0 there, a warning, upscale.json says so
        if bad:
            nonfinite[str(f)] = bad
            print(f"warning: {out / f'{f:06d}.exr'}: the model output {bad} non-finite value(s) (NaN/Inf), written "
                  "as 0", file=sys.stderr)
        write_exr(out / f"{f:06d}.exr", {c: sr[..., i] for i, c in enumerate("RGB")})
        times[str(f)] = r["ms"]
    write_json_atomic(out / "upscale.json", {"model": model.spec, "clip": str(args.clip), "scale": clip.scale,
                                            "exposure": clip.exposure,  # the EXRs hold exposed radiance
                                            "frames": [int(f) for f in frames], "ms": times,
                                            "nonfinite_values": nonfinite, "inference": path_record(model)})
    print(f"wrote {len(frames)} frames to {out}"
          + (f" ({len(nonfinite)} with non-finite model output set to 0)" if nonfinite else ""))
    return 0


def cmd_export(args) -> int:
    require("blendsr export", "train", "export")
    from training.inference.export import export_onnx
    from training.inference.loading import load_model, split_spec
    from gbuffer_export.config import parse_size
    if args.checkpoint:  # CK or CK?KEY=VALUE (the inference options, e.g. residual_clamp)
        from training.checkpoint import load_checkpoint
        scale = int(load_checkpoint(split_spec(args.checkpoint)[0])["scale"])
    else:
        scale = args.scale
    model = load_model(args.checkpoint or args.model, scale)
    report = export_onnx(model, args.onnx, clip=args.clip, hr_size=parse_size(args.hr_size), opset=args.opset)
    print(json.dumps(report, indent=1))
    return 0 if report["match"] else 1
